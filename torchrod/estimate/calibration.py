"""Calibration of a rod from readings with known forces: the location bias, then the bending stiffness.

The paper calibrates in two steps (its "Model Calibration"): first the location bias, then the stiffness. Both are
fitted here by nonlinear least squares on the curvatures themselves (not on re-estimated forces), with the forward
model :func:`torchrod.model.body_frame.grating_curvature` and its gradients by autograd:

1. Location bias b [m]. The gratings sit at the rod's ``gratings`` in the model's coordinate; the known forces are
   located in the true (fibre's) coordinate. With the sign of :class:`~torchrod.rod.Rod` (reported location =
   ``s_model + location_bias``) the model sees each force at ``s_model = s_true - b``. The force components are left
   free (two per force, per reading), so that an error in the stiffness or in the known components cannot leak into
   b: unknowns (b, f_x, f_y of every force), nominal EI.
   The curvature field depends on the loads only through the distances between gratings and forces (the rod is
   integrated from the free tip, where U = U' = 0 beyond the last force), so moving the forces by -b is exactly
   the same as moving the gratings by +b.
2. Bending stiffness EI [N m^2], with b fixed: the curvature depends on the forces only through f / EI (the
   body-frame equations scale exactly), so EI is the one scale between the known force magnitudes and the
   curvatures: unknown log(EI / EI_nominal). With ``directions="known"`` the known (f_x, f_y) are used as given;
   with ``directions="free"`` only their magnitudes are trusted and each force's direction is a free angle.

Solver: ``scipy.optimize.least_squares`` (trust-region reflective, bounds keep every ``s_true - b`` inside
[0, L]) with the exact Jacobian, which autograd assembles per reading (the unknowns of one reading touch only its
own residuals). Standard errors are the Gauss-Newton ones, ``sigma^2 (J^T J)^-1`` with ``sigma^2 = RSS / (n - p)``
estimated from the residuals (n observed curvature components, p unknowns). The stiffness step keeps b fixed but
its covariance includes b's column, so the stiffness's error carries the bias's uncertainty (with b held exactly,
it would come out about 25 % too small: the two are correlated through the forces' lever arms).

What it will not stand behind. A calibration is written into a rod that every later estimate trusts, so
:func:`calibrate` checks its own result and lists in :attr:`CalibrationResult.problems` what is wrong with it
(:meth:`CalibrationResult.apply` then refuses unless forced; ``torchrod calibrate`` exits with status 1 and writes
no rod unless ``--force``):

- readings inconsistent with the known forces: readings all but zero while the known forces bend the rod (a dead
  or disconnected sensor, :data:`DEAD_SIGNAL`); forces fitted freely to the readings that point against the known
  ones (a flipped sign or frame; with ``directions="known"``);
- a residual far beyond the noise (:data:`MAX_RESIDUAL_RATIO`): of the free fit (the readings do not fit this rod
  at all) against the given noise, or against half the readings' own size; of the known-force fit against the
  noise, which is the given sigma or, without one, what the free fit leaves;
- a stiffness outside physical bounds (:data:`STIFFNESS_RATIO_RANGE` of the nominal one; a Young's modulus outside
  :data:`torchrod.rod.YOUNGS_MODULUS_RANGE`), or not determined by the data (a relative standard error above
  :data:`MAX_RELATIVE_STD`, or none); a location bias not determined;
- a least-squares solve that stopped on its evaluation limit.

The readings and their known forces come as :class:`CalibrationData` (from a file: ``torchrod calibrate``, or
:func:`torchrod.io.known_loads.read_readings`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from ..errors import OptionsError, ReadingError, TorchrodTypeError
from ..loads import PointForces
from ..model.body_frame import grating_curvature
from ..rod import YOUNGS_MODULUS_RANGE, Rod

__all__ = [
    "DEAD_SIGNAL",
    "MAX_RELATIVE_STD",
    "MAX_RESIDUAL_RATIO",
    "STIFFNESS_RATIO_RANGE",
    "CalibrationData",
    "CalibrationResult",
    "calibrate",
    "summary",
]

Directions = Literal["known", "free"]

MAX_RESIDUAL_RATIO = 3.0
"""A fit's RMS residual beyond this many times the noise is far beyond it (module docstring)."""

STIFFNESS_RATIO_RANGE = (0.1, 10.0)
"""Fitted over nominal bending stiffness: outside this range the rod file, not the rod, is wrong (diameters enter
EI to the fourth power, and a material's modulus is known far better than tenfold)."""

MAX_RELATIVE_STD = 0.1
"""A fitted stiffness whose standard error is more than this fraction of it is not determined by the data; a
location bias whose standard error is more than this fraction of the length neither."""

DEAD_SIGNAL = 1e-3
"""Readings whose RMS is below this fraction of what the known forces give at the nominal stiffness are taken for
a dead or disconnected sensor."""


@dataclass(frozen=True)
class CalibrationData:
    """R readings with known forces.

    Attributes:
        curvature: (R, G, 2) measured (u_x, u_y) at the gratings [1/m]; 0 where missing.
        present: (R, G) bool, True where the grating has a reading.
        forces: R known force sets, ``s`` [m] in the true (fibre's) coordinate, ``f`` [N] body frame.
        ids: the readings' ids (None where absent).
    """

    curvature: torch.Tensor
    present: torch.Tensor
    forces: PointForces
    ids: tuple[Any, ...] = ()

    def __post_init__(self) -> None:
        c, p, f = self.curvature, self.present, self.forces
        if not isinstance(c, torch.Tensor) or c.dim() != 3 or c.shape[2] != 2:
            shape = tuple(c.shape) if isinstance(c, torch.Tensor) else type(c).__name__
            raise OptionsError(f"curvature must have shape (R, G, 2), got {shape}")
        if not isinstance(p, torch.Tensor) or p.shape != c.shape[:2]:
            shape = tuple(p.shape) if isinstance(p, torch.Tensor) else type(p).__name__
            raise OptionsError(f"present must have shape (R, G) = {tuple(c.shape[:2])}, got {shape}")
        if not isinstance(f, PointForces) or f.batch_size != c.shape[0]:
            raise OptionsError(f"forces must be PointForces for the {c.shape[0]} readings")
        object.__setattr__(self, "present", p.to(torch.bool))
        ids = tuple(self.ids) if self.ids else (None,) * c.shape[0]
        if len(ids) != c.shape[0]:
            raise OptionsError(f"ids must hold one id per reading ({c.shape[0]}), got {len(ids)}")
        object.__setattr__(self, "ids", ids)

    @property
    def num_readings(self) -> int:
        return self.curvature.shape[0]


@dataclass(frozen=True)
class CalibrationResult:
    """Fitted location bias and bending stiffness, with Gauss-Newton standard errors.

    Attributes:
        location_bias: b [m] (reported location = s_model + b).
        location_bias_std: its standard error [m].
        bending_stiffness: EI [N m^2].
        bending_stiffness_std: its standard error [N m^2] (b's uncertainty included).
        nominal_stiffness: the EI the calibration started from [N m^2].
        rms_location_step, rms_stiffness_step: RMS curvature residual of each step [1/m].
        fitted_forces: the step-1 free forces (model coordinate ``s_true - b``; components at the nominal EI, so
            they equal the true ones times nominal / true EI) [m, N].
        converged: both least-squares solves ended on a tolerance.
        observations: number of observed curvature components used.
        reading_rms: RMS of the observed curvature components [1/m].
        predicted_rms: RMS of what the known forces give at the nominal stiffness, at the same components [1/m].
        force_agreement: how the step-1 forces point along the known ones: sum f_fit . f_known / (|F_fit| |F_known|)
            over all forces, +1 when parallel, -1 when opposite (NaN without a fitted force).
        noise: the sensor's sigma the residuals were judged against [1/m], None when not given.
        problems: what is wrong with this calibration, one sentence each (module docstring); empty when nothing.
    """

    location_bias: float
    location_bias_std: float
    bending_stiffness: float
    bending_stiffness_std: float
    nominal_stiffness: float
    rms_location_step: float
    rms_stiffness_step: float
    fitted_forces: PointForces
    converged: bool
    observations: int
    reading_rms: float = math.nan
    predicted_rms: float = math.nan
    force_agreement: float = math.nan
    noise: float | None = None
    problems: tuple[str, ...] = ()

    @property
    def stiffness_ratio(self) -> float:
        """Fitted over nominal EI."""
        return self.bending_stiffness / self.nominal_stiffness

    def apply(self, rod: Rod, *, force: bool = False) -> Rod:
        """``rod`` with the fitted bias and stiffness. A rod described by its geometry keeps it and gets its
        Young's modulus scaled by the stiffness ratio (EI is proportional to E), as the paper calibrates E; a rod
        given by its EI gets the new EI.

        Raises :class:`~torchrod.errors.ReadingError` listing :attr:`problems` when there are any, unless
        ``force``: a calibration that cannot be stood behind is not applied by default."""
        if self.problems and not force:
            raise ReadingError(
                "the calibration is not applied: " + "; ".join(self.problems) + " (force=True applies it anyway)"
            )
        if rod.youngs_modulus is not None:
            return rod.with_(
                location_bias=self.location_bias,
                youngs_modulus=rod.youngs_modulus * self.bending_stiffness / rod.bending_stiffness,
                bending_stiffness=self.bending_stiffness,
            )
        return rod.with_(location_bias=self.location_bias, bending_stiffness=self.bending_stiffness)


# ---------------------------------------------------------------------------------------------- least squares
@dataclass(frozen=True)
class _Fit:
    x: np.ndarray  # global + local unknowns at the solution
    std: np.ndarray  # their standard errors (NaN if not determined)
    rms: float  # RMS residual [1/m]
    converged: bool


JACOBIAN_ROWS = 4096
"""The most simulated rows (copies of the readings) one reverse pass of the calibration's Jacobian takes: it bounds
the memory of the pass's record, which for every component at once would hold 2 G copies of every reading."""


class _Problem:
    """Curvature residuals of R readings as a function of n_g global unknowns and per-reading local ones.

    ``model(X)`` maps the per-reading parameter rows X (R, n_g + K) (globals repeated on every row, then the
    reading's K local slots) to the curvature (R, G, 2), and k copies of them stacked, (k R, n_g + K), to the k
    copies' curvature (k R, G, 2). ``local_used`` (R, K) marks the slots that are unknowns;
    the others keep ``local_fixed``'s values. The global unknown vector is [globals, used local slots in row-major
    order]; its Jacobian is assembled from reverse passes over copies of the rows, copy m giving the derivative of every
    reading's residual in one curvature component w.r.t. that reading's own row of X (readings are independent).
    """

    def __init__(
        self,
        model: Callable[[torch.Tensor], torch.Tensor],
        data: CalibrationData,
        n_global: int,
        local_used: torch.Tensor,
        local_fixed: torch.Tensor,
    ) -> None:
        self.model, self.data, self.n_global = model, data, n_global
        self.local_used, self.local_fixed = local_used, local_fixed
        self.obs = data.present.unsqueeze(-1).expand(-1, -1, 2)  # (R, G, 2)
        R, K = local_used.shape
        used = local_used.reshape(-1).cpu().numpy()
        self.col: np.ndarray = np.full(R * K, -1, dtype=np.int64)
        self.col[used] = n_global + np.arange(int(used.sum()))
        self.col = self.col.reshape(R, K)
        self.num_unknowns = n_global + int(used.sum())
        obs = self.obs.cpu().numpy()
        self.num_obs = int(obs.sum())
        self.obs_reading = np.broadcast_to(np.arange(R)[:, None, None], obs.shape)[obs]  # reading of each residual
        # The curvature components (grating, x or y) some reading observes: the Jacobian's, one copy each.
        present_any = data.present.any(0).tolist()
        self.components = [(g, c) for g, seen in enumerate(present_any) if seen for c in range(2)]
        self._cache: tuple[bytes, np.ndarray, np.ndarray] | None = None

    def rows(self, theta: np.ndarray) -> torch.Tensor:
        d = self.data.curvature
        t = torch.as_tensor(theta, dtype=d.dtype, device=d.device)
        R = self.local_used.shape[0]
        local = self.local_fixed.clone()
        local[self.local_used] = t[self.n_global :]
        return torch.cat((t[: self.n_global].expand(R, -1), local), dim=1)

    def residual(self, theta: np.ndarray) -> np.ndarray:
        """Observed residuals (n,) [1/m] at ``theta``."""
        with torch.no_grad():
            resid = self.model(self.rows(theta)) - self.data.curvature
        return resid[self.obs].cpu().numpy()

    def evaluate(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observed residuals (n,) and their Jacobian (n, p) w.r.t. all unknowns at ``theta`` (cached).

        The rows are simulated in k copies at once, copy m differentiated for its own curvature component: one
        reverse pass gives k components of every reading's Jacobian (class docstring), with at most
        :data:`JACOBIAN_ROWS` rows per pass."""
        key = np.asarray(theta, dtype=np.float64).tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        X = self.rows(theta)
        R, P = X.shape
        G = self.data.curvature.shape[1]
        components = self.components
        J = torch.zeros(R, G, 2, P, dtype=X.dtype, device=X.device)
        per = max(1, JACOBIAN_ROWS // R)
        curvature = None
        for first in range(0, len(components), per):
            chunk = components[first : first + per]
            k = len(chunk)
            copies = X.detach().repeat(k, 1).requires_grad_(True)
            pick = torch.zeros(k, 1, G, 2, dtype=X.dtype, device=X.device)
            for m, (g, c) in enumerate(chunk):
                pick[m, 0, g, c] = 1.0
            with torch.enable_grad():
                out = self.model(copies).view(k, R, G, 2)
                (grad,) = torch.autograd.grad((out * pick).sum(), copies)
            grad = grad.view(k, R, P)
            for m, (g, c) in enumerate(chunk):
                J[:, g, c] = grad[m]
            if curvature is None:
                curvature = out[0].detach()
        if curvature is None:  # no grating present in any reading (the data's checks refuse it before)
            with torch.no_grad():
                curvature = self.model(X)
        r = (curvature - self.data.curvature)[self.obs].cpu().numpy()
        Jo = J[self.obs].cpu().numpy()  # (n, n_global + K)
        full = np.zeros((self.num_obs, self.num_unknowns))
        full[:, : self.n_global] = Jo[:, : self.n_global]
        cols = self.col[self.obs_reading]  # (n, K)
        n_idx, k_idx = np.nonzero(cols >= 0)
        full[n_idx, cols[n_idx, k_idx]] = Jo[n_idx, self.n_global + k_idx]
        self._cache = (key, r, full)
        return r, full

    def solve(self, theta0: np.ndarray, lower: np.ndarray, upper: np.ndarray, free: np.ndarray | None = None) -> _Fit:
        """Least squares over the unknowns marked ``free`` (default all; the others stay at ``theta0``). The
        standard errors come from the Jacobian of ALL unknowns: a fixed one counts as estimated from the same data,
        so its uncertainty and correlations propagate into the others'."""
        from scipy.optimize import least_squares

        p, n = self.num_unknowns, self.num_obs
        if n <= p:
            raise OptionsError(f"{n} observed curvature components cannot determine {p} unknowns: add readings")
        free = np.ones(p, dtype=bool) if free is None else np.asarray(free, dtype=bool)
        base = np.array(theta0, dtype=np.float64)

        def full(sub: np.ndarray) -> np.ndarray:
            theta = base.copy()
            theta[free] = sub
            return theta

        sol = least_squares(
            lambda sub: self.residual(full(sub)),
            base[free],
            jac=lambda sub: self.evaluate(full(sub))[1][:, free],
            bounds=(lower[free], upper[free]),
            method="trf",
            x_scale="jac",
            ftol=1e-12,
            xtol=1e-12,
            gtol=1e-12,
            max_nfev=200,
        )
        theta = full(sol.x)
        r, J = self.evaluate(theta)
        rss = float(r @ r)
        sigma2 = rss / (n - p)
        std = _standard_errors(J, sigma2)
        return _Fit(x=theta, std=std, rms=math.sqrt(rss / n), converged=bool(sol.status > 0))


def _standard_errors(J: np.ndarray, sigma2: float) -> np.ndarray:
    """sqrt(diag(sigma^2 (J^T J)^-1)), taken in unit-diagonal form; NaN when J^T J is numerically singular."""
    A = J.T @ J
    d = np.sqrt(np.diag(A))
    if not np.all(d > 0):
        return np.full(J.shape[1], np.nan)
    C = A / np.outer(d, d)
    w = np.linalg.eigvalsh(C)
    if w[0] <= w[-1] * 1e-13:
        return np.full(J.shape[1], np.nan)
    cov = np.linalg.inv(C) / np.outer(d, d) * sigma2
    return np.sqrt(np.diag(cov))


# ---------------------------------------------------------------------------------------------- calibration
def calibrate(
    rod: Rod,
    data: CalibrationData,
    *,
    directions: Directions = "known",
    initial_bias: float = 0.0,
    noise: float | None = None,
) -> CalibrationResult:
    """Fit the location bias, then the bending stiffness, from readings with known forces (module docstring).

    Args:
        rod: the rod being calibrated: its gratings, length and nominal EI (its location_bias is not used).
        data: R readings with known forces (:func:`torchrod.io.known_loads.read_readings`), s in the true coordinate.
        directions: ``"known"``: step 2 uses the known (f_x, f_y); ``"free"``: only their magnitudes.
        initial_bias: starting value of b [m].
        noise: the sensor's sigma per curvature component [1/m], if known: the residuals are judged against it
            (else against what forces fitted freely leave).
    Returns:
        :class:`CalibrationResult` with its :attr:`~CalibrationResult.problems`; ``result.apply(rod)`` is the
        calibrated rod (refused while there are problems, unless forced).
    """
    if noise is not None and not (isinstance(noise, (int, float)) and 0.0 < noise < math.inf):
        raise OptionsError(f"noise must be a positive sigma [1/m] or None, got {noise!r}")
    if not isinstance(rod, Rod):
        raise TorchrodTypeError(f"rod must be a Rod, got {type(rod).__name__}")
    if not isinstance(data, CalibrationData):
        raise TorchrodTypeError(f"data must be CalibrationData, got {type(data).__name__}")
    if directions not in ("known", "free"):
        raise OptionsError(f"directions must be 'known' or 'free', got {directions!r}")
    R, G, _ = data.curvature.shape
    if G != rod.num_gratings:
        raise OptionsError(f"readings hold {G} gratings, the rod has {rod.num_gratings}")
    loads = data.forces
    if loads.dtype != data.curvature.dtype or loads.device != data.curvature.device:
        raise OptionsError("forces and curvature must share dtype and device")
    active = loads.active
    if not bool(active.any()):
        raise OptionsError("no known force in the readings: the bias and the stiffness cannot be fitted")
    s_true = loads.s
    s_real = s_true[active]
    if bool(((s_real < 0) | (s_real > rod.length)).any()):
        raise OptionsError(f"known force locations must lie in [0, L = {rod.length}] m, got {s_real.tolist()}")
    # s_true - b must stay in [0, L] for every real force
    lo_b, hi_b = float(s_real.max()) - rod.length, float(s_real.min())
    if not lo_b <= initial_bias <= hi_b:
        raise OptionsError(f"initial_bias {initial_bias} m would move a force off the rod; allowed [{lo_b}, {hi_b}] m")
    ei0 = rod.bending_stiffness
    h = loads.max_forces
    mask = loads.mask

    def each(t: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
        """``t`` (R, ...) of the readings, for rows X holding k copies of theirs (k R, ...) (:class:`_Problem`)."""
        k = X.shape[0] // R
        return t if k == 1 else t.repeat(k, *([1] * (t.dim() - 1)))

    def each_mask(X: torch.Tensor) -> torch.Tensor | None:
        return None if mask is None else each(mask, X)

    def shifted(X: torch.Tensor) -> torch.Tensor:
        """The model locations s_true - b of rows X (b in their first column), both steps' unknown or fixed bias."""
        s = each(s_true, X)
        return torch.where(each(active, X), s - X[:, :1], s)

    # ---- step 1: b with free force components, nominal EI
    def model_bias(X: torch.Tensor) -> torch.Tensor:
        forces = PointForces(shifted(X), X[:, 1:].reshape(-1, h, 2), each_mask(X))
        return grating_curvature(rod, forces, bending_stiffness=ei0)

    used = active.unsqueeze(-1).expand(-1, -1, 2).reshape(R, 2 * h)
    fixed = loads.masked_f().reshape(R, 2 * h).detach()
    step1 = _Problem(model_bias, data, 1, used, fixed)
    theta0 = np.concatenate(([initial_bias], fixed[used].cpu().numpy()))
    lower = np.full_like(theta0, -np.inf)
    upper = np.full_like(theta0, np.inf)
    lower[0], upper[0] = lo_b, hi_b
    fit1 = step1.solve(theta0, lower, upper)
    bias, bias_std = float(fit1.x[0]), float(fit1.std[0])
    fitted = step1.rows(fit1.x).detach()
    s_model = torch.where(active, s_true - bias, s_true)
    fitted_forces = PointForces(s_model, fitted[:, 1:].reshape(R, h, 2), mask)

    # ---- step 2: EI with b fixed: curvature(s, f, EI) = curvature(s, f * EI0 / EI, EI0). The unknowns are
    # (b, log(EI / EI0), [angles]); b stays at its step-1 value but is kept in the Jacobian so that its
    # uncertainty propagates into the stiffness's standard error.
    magnitude = loads.magnitude()  # (R, h)

    if directions == "known":
        f_known = loads.masked_f()

        def model_stiffness(X: torch.Tensor) -> torch.Tensor:
            scale = torch.exp(-X[:, 1:2]).unsqueeze(-1)
            forces = PointForces(shifted(X), each(f_known, X) * scale, each_mask(X))
            return grating_curvature(rod, forces, bending_stiffness=ei0)

        used2 = torch.zeros(R, 0, dtype=torch.bool, device=active.device)
        fixed2 = torch.zeros(R, 0, dtype=loads.dtype, device=loads.device)
        theta0 = np.array([bias, 0.0])
    else:
        # start each direction from the step-1 fit of that force
        angle0 = torch.atan2(fitted_forces.f[..., 1], fitted_forces.f[..., 0])

        def model_stiffness(X: torch.Tensor) -> torch.Tensor:
            scale = torch.exp(-X[:, 1:2])
            phi = X[:, 2:]
            f = torch.stack((torch.cos(phi), torch.sin(phi)), -1) * (each(magnitude, X) * scale).unsqueeze(-1)
            return grating_curvature(rod, PointForces(shifted(X), f, each_mask(X)), bending_stiffness=ei0)

        used2, fixed2 = active, angle0.detach()
        theta0 = np.concatenate(([bias, 0.0], angle0[active].cpu().numpy()))
    # a sensible start: the magnitude ratio of the step-1 fit (EI / EI0 = |f_known| / |f_fitted|)
    ratio = float((magnitude[active] ** 2).sum() / (magnitude[active] * fitted_forces.magnitude()[active]).sum())
    if math.isfinite(ratio) and ratio > 0:
        theta0[1] = math.log(ratio)
    step2 = _Problem(model_stiffness, data, 2, used2, fixed2)
    free = np.ones_like(theta0, dtype=bool)
    free[0] = False
    unbounded = np.full_like(theta0, np.inf)
    fit2 = step2.solve(theta0, -unbounded, unbounded, free)
    log_ratio = float(fit2.x[1])
    ei = ei0 * math.exp(min(log_ratio, 700.0)) if math.isfinite(log_ratio) else math.nan
    ei_std = ei * float(fit2.std[1])
    # The diagnostics the checks use: the readings' size, what the known forces give at the nominal stiffness, and
    # how the freely fitted forces point along the known ones.
    observed = data.present.unsqueeze(-1).expand(-1, -1, 2)
    with torch.no_grad():
        predicted = grating_curvature(rod, PointForces(s_true, loads.masked_f(), mask), bending_stiffness=ei0)
    reading_rms = float(data.curvature[observed].pow(2).mean().sqrt())
    predicted_rms = float(predicted[observed].pow(2).mean().sqrt())
    f_fit, f_known = fitted_forces.masked_f()[active], loads.masked_f()[active]
    norm = float(f_fit.norm() * f_known.norm())
    agreement = float((f_fit * f_known).sum()) / norm if norm > 0 else math.nan
    result = CalibrationResult(
        location_bias=bias,
        location_bias_std=bias_std,
        bending_stiffness=ei,
        bending_stiffness_std=ei_std,
        nominal_stiffness=ei0,
        rms_location_step=fit1.rms,
        rms_stiffness_step=fit2.rms,
        fitted_forces=fitted_forces,
        converged=fit1.converged and fit2.converged,
        observations=step1.num_obs,
        reading_rms=reading_rms,
        predicted_rms=predicted_rms,
        force_agreement=agreement,
        noise=noise,
    )
    return dataclasses.replace(result, problems=_problems(result, rod, directions))


def _problems(result: CalibrationResult, rod: Rod, directions: str) -> tuple[str, ...]:
    """What is wrong with ``result`` (module docstring: the checks), one sentence each."""
    out = []
    r = result
    ratio = MAX_RESIDUAL_RATIO
    if not r.reading_rms > DEAD_SIGNAL * r.predicted_rms:
        out.append(
            f"readings inconsistent with the known forces: the readings are all but zero (RMS {r.reading_rms:.3g} "
            f"1/m) while the known forces bend the rod to an RMS of {r.predicted_rms:.3g} 1/m at the nominal "
            "stiffness: a dead or disconnected sensor, or readings in other units than 1/m"
        )
    elif r.noise is not None and r.rms_location_step > ratio * r.noise:
        out.append(
            f"residual far beyond the noise: even forces fitted freely leave an RMS residual of "
            f"{r.rms_location_step:.3g} 1/m, {r.rms_location_step / r.noise:.3g} times the noise sigma "
            f"{r.noise:.3g} 1/m: the readings do not fit this rod (check the rod file and the readings' units)"
        )
    elif r.noise is None and r.rms_location_step > 0.5 * r.reading_rms:
        out.append(
            f"residual far beyond the noise: even forces fitted freely leave an RMS residual of "
            f"{r.rms_location_step:.3g} 1/m of readings of RMS {r.reading_rms:.3g} 1/m: the readings do not fit "
            "this rod (check the rod file and the readings' units)"
        )
    else:  # the readings fit the rod: do they fit the known forces?
        if directions == "known" and not r.force_agreement >= 0.5:
            way = "against" if r.force_agreement < -0.5 else "away from"
            out.append(
                f"readings inconsistent with the known forces: forces fitted freely to the readings point {way} the "
                f"known ones (agreement {r.force_agreement:+.2f}; +1 when parallel): is the sign of the curvature, "
                "or the frame of the known forces, flipped or turned? (--directions free trusts only their "
                "magnitudes)"
            )
        noise = r.noise if r.noise is not None else r.rms_location_step
        which = "the noise sigma" if r.noise is not None else "the residual of forces fitted freely"
        reference = max(noise, 1e-6 * r.reading_rms)
        if r.rms_stiffness_step > ratio * reference:
            out.append(
                f"residual far beyond the noise: the known forces leave an RMS residual of {r.rms_stiffness_step:.3g} "
                f"1/m, {r.rms_stiffness_step / reference:.3g} times {which} ({noise:.3g} 1/m): the readings are "
                "inconsistent with the known forces (their locations, magnitudes or directions)"
            )
    lo, hi = STIFFNESS_RATIO_RANGE
    e = rod.youngs_modulus * r.stiffness_ratio if rod.youngs_modulus is not None else None
    e_lo, e_hi = YOUNGS_MODULUS_RANGE
    if not (lo <= r.stiffness_ratio <= hi) or (e is not None and not e_lo <= e <= e_hi):
        modulus = f", a Young's modulus of {e:.3g} Pa" if e is not None else ""
        out.append(
            f"stiffness outside physical bounds: the fit gives EI = {r.bending_stiffness:.3g} N m^2{modulus}, "
            f"{r.stiffness_ratio:.3g} times the rod file's (allowed {lo:g} to {hi:g} times"
            + (f", and {e_lo:g} to {e_hi:g} Pa" if e is not None else "")
            + ")"
        )
    relative = r.bending_stiffness_std / r.bending_stiffness if r.bending_stiffness > 0 else math.nan
    if not relative <= MAX_RELATIVE_STD:
        out.append(
            f"stiffness not determined by the data: EI = {r.bending_stiffness:.3g} +/- {r.bending_stiffness_std:.3g} "
            f"N m^2 (more than {100 * MAX_RELATIVE_STD:g} %): add readings with larger known forces"
        )
    if not r.location_bias_std <= MAX_RELATIVE_STD * rod.length:
        out.append(
            f"location bias not determined by the data: {r.location_bias:.3g} +/- {r.location_bias_std:.3g} m: add "
            "readings with known forces at several places along the rod"
        )
    if not r.converged:
        out.append("a least-squares solve stopped on its evaluation limit: the fit may not be the best one")
    return tuple(out)


def summary(result: CalibrationResult, rod: Rod | None = None) -> Sequence[str]:
    """Human-readable lines: fitted values with standard errors, residuals, and the new Young's modulus."""
    change = (result.stiffness_ratio - 1) * 100
    lines = [
        f"location_bias     = {result.location_bias * 1e3:+.4f} +/- {result.location_bias_std * 1e3:.4f} mm",
        (
            f"bending_stiffness = {result.bending_stiffness:.6e} +/- {result.bending_stiffness_std:.2e} N m^2"
            f" ({change:+.3f} % from {result.nominal_stiffness:.6e})"
        ),
    ]
    if rod is not None and rod.youngs_modulus is not None:
        e = rod.youngs_modulus * result.bending_stiffness / rod.bending_stiffness
        e_std = e * result.bending_stiffness_std / result.bending_stiffness
        lines.append(f"youngs_modulus    = {e / 1e9:.4f} +/- {e_std / 1e9:.4f} GPa")
    lines.append(
        f"rms residual      = {result.rms_location_step:.4g} 1/m (bias step), {result.rms_stiffness_step:.4g} 1/m"
        f" (stiffness step), {result.observations} curvature components"
    )
    lines.extend(f"problem: {text}" for text in result.problems)
    return lines
