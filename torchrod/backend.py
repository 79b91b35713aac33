"""Two array backends for one algorithm: NumPy (the CPU, small batches) and torch (any device, large batches).

The estimator's iteration and the forward-sensitivity march are written ONCE against :class:`Backend`, the few
array operations they need with one signature. :data:`NUMPY` runs them on NumPy arrays: on the CPU a NumPy
operation on a small array costs 1-2 us against torch's 5-20 us, which decides the time of a one-reading estimate
(a few hundred small operations). :func:`torch_backend` runs them on tensors of any device (CUDA, or the CPU for
large batches). The policy, constants and decisions live in the shared code, never in a backend; tests hold the
two backends to the same answers.

Arrays are batch first. Only what both libraries do identically is exposed; where they differ (sorting, Cholesky
failures, dtype names) the methods below say what they return.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

__all__ = ["NUMPY", "Backend", "NumpyBackend", "TorchBackend", "backend_for", "torch_backend"]


class Backend:
    """Array operations shared by the estimator's backends (see the module docstring). Float arrays are float64,
    complex arrays complex128, index arrays int64."""

    name = "abstract"
    lib: Any

    # -------------------------------------------------------------- creation and conversion
    def asarray(self, x: Any, dtype: str = "float") -> Any: ...
    def from_torch(self, t: torch.Tensor) -> Any: ...
    def to_torch(self, x: Any, device: torch.device) -> torch.Tensor: ...
    def zeros(self, shape: tuple[int, ...], dtype: str = "float") -> Any: ...
    def full(self, shape: tuple[int, ...], value: float, dtype: str = "float") -> Any: ...
    def ones(self, shape: tuple[int, ...], dtype: str = "float") -> Any:
        return self.full(shape, True if dtype == "bool" else 1, dtype)

    def arange(self, n: int) -> Any: ...
    def tolist(self, x: Any) -> Any:
        return x.tolist()

    # -------------------------------------------------------------- elementwise and reductions
    def where(self, c: Any, a: Any, b: Any) -> Any:
        return self.lib.where(c, a, b)

    def concat(self, xs: list[Any], axis: int = 0) -> Any: ...
    def stack(self, xs: list[Any], axis: int = 0) -> Any: ...
    def clip(self, x: Any, lo: Any = None, hi: Any = None) -> Any: ...
    def nonzero(self, mask: Any) -> Any: ...
    def argsort_desc(self, x: Any) -> Any:
        """Indices sorting each row of x (B, n) in descending order, stable (equal values keep their order)."""
        ...

    def take(self, x: Any, idx: Any, axis: int) -> Any:
        """take_along_axis: x and idx of the same number of dimensions."""
        ...

    def any(self, x: Any, axis: Any = None) -> Any: ...
    def all(self, x: Any, axis: Any = None) -> Any: ...
    def amax(self, x: Any, axis: Any) -> Any: ...
    def amin(self, x: Any, axis: Any) -> Any: ...
    def argmin(self, x: Any, axis: int) -> Any: ...
    def mT(self, x: Any) -> Any:
        """Swap the last two axes."""
        ...

    def complex(self, re: Any, im: Any) -> Any: ...
    def conj(self, z: Any) -> Any: ...
    def real_pairs(self, z: Any) -> Any:
        """(..., ) complex -> (..., 2) real (x, y)."""
        ...

    def copy(self, x: Any) -> Any: ...
    def expand(self, x: Any, shape: tuple[int, ...]) -> Any:
        """A broadcast view of x with ``shape`` (read only)."""
        ...

    def astype(self, x: Any, dtype: str) -> Any: ...
    def put(self, x: Any, idx: Any, values: Any) -> Any:
        """A copy of x with rows ``idx`` (1-D indices along axis 0) replaced by ``values``."""
        out = self.copy(x)
        out[idx] = values
        return out

    def einsum(self, spec: str, *xs: Any) -> Any:
        if spec == "rkp,rk->rp":  # J^T r, the commonest: a matrix product costs less than einsum's parsing
            J, r = xs
            return (r[:, None, :] @ J)[:, 0, :]
        if spec == "rkp,rp->rk":
            J, x = xs
            return (J @ x[:, :, None])[..., 0]
        return self.lib.einsum(spec, *xs)

    def isfinite(self, x: Any) -> Any:
        return self.lib.isfinite(x)

    def eye(self, n: int) -> Any:
        return self.asarray(np.eye(n))

    def add_at(self, x: Any, idx: Any, values: Any) -> Any:
        """A copy of x (n,) with ``values`` added at ``idx`` (repeated indices accumulate)."""
        out = self.copy(x)
        if self.name == "numpy":
            np.add.at(out, idx, values)
        else:
            out.index_add_(0, idx, values)
        return out

    def solve(self, A: Any, b: Any) -> tuple[Any, Any]:
        """Solve A x = b for (n, P, P) A and (n, P, k) b: x, and (n,) bool where A was finite and the solve
        finite (elsewhere x is zero)."""
        P = A.shape[-1]
        flat = A.reshape(-1, P, P)
        ok = self.all(self.isfinite(flat.reshape(flat.shape[0], -1)), 1)
        eye = self.eye(P)
        safe = self.where(ok[:, None, None], flat, self.expand(eye, flat.shape))
        rhs = b.reshape(flat.shape[0], P, -1)
        try:
            x = self.lib.linalg.solve(safe, rhs)
        except (np.linalg.LinAlgError, RuntimeError):  # singular somewhere: least squares row by row
            x = (
                self.lib.linalg.lstsq(safe, rhs)[0]
                if self.name == "torch"
                else np.stack([np.linalg.lstsq(safe[i], rhs[i], rcond=None)[0] for i in range(flat.shape[0])])
            )
        ok = ok & self.all(self.isfinite(x.reshape(x.shape[0], -1)), 1)
        x = self.where(ok[:, None, None], x, 0.0)
        return x.reshape(b.shape), ok.reshape(A.shape[:-2])

    def diagonal(self, A: Any) -> Any:
        """(..., P, P) -> (..., P) the diagonals."""
        return self.lib.diagonal(A, 0, -2, -1) if self.name == "numpy" else A.diagonal(dim1=-2, dim2=-1)

    # -------------------------------------------------------------- linear algebra
    def cholesky(self, A: Any) -> tuple[Any, Any]:
        """Batched Cholesky factors of symmetric A (n, P, P) and (n,) bool: True where A was positive definite
        and finite (the factor is then lower triangular; elsewhere it is the identity)."""
        ...

    def cho_solve(self, C: Any, b: Any) -> Any:
        """Solve (C C^T) x = b for x, C (n, P, P) lower triangular, b (n, P)."""
        ...

    def spd_solve(self, A: Any, b: Any) -> tuple[Any, Any]:
        """Solve A x = b for symmetric positive definite A (n, P, P), b (n, P) or (n, P, k): x (zero where the
        solve failed) and (n,) bool where A and x are finite and the solve succeeded."""
        ...

    def eigh(self, A: Any) -> tuple[Any, Any, Any]:
        """Eigenvalues (n, P) ascending, eigenvectors (n, P, P) of symmetric A, and (n,) bool: True where the
        decomposition succeeded (rows with non-finite entries, or where the solver fails, get NaN and False)."""
        ...


class NumpyBackend(Backend):
    """:class:`Backend` on NumPy arrays (CPU)."""

    name = "numpy"
    lib = np
    _dtypes = {"float": np.float64, "complex": np.complex128, "int": np.int64, "bool": np.bool_}

    def asarray(self, x: Any, dtype: str = "float") -> Any:
        if isinstance(x, torch.Tensor):
            x = x.detach().cpu().numpy()
        return np.asarray(x, dtype=self._dtypes[dtype])

    def from_torch(self, t: torch.Tensor) -> Any:
        return t.detach().cpu().numpy()

    def to_torch(self, x: Any, device: torch.device) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x)).to(device)

    def zeros(self, shape: tuple[int, ...], dtype: str = "float") -> Any:
        return np.zeros(shape, dtype=self._dtypes[dtype])

    def full(self, shape: tuple[int, ...], value: float, dtype: str = "float") -> Any:
        return np.full(shape, value, dtype=self._dtypes[dtype])

    def arange(self, n: int) -> Any:
        return np.arange(n)

    def concat(self, xs: list[Any], axis: int = 0) -> Any:
        return np.concatenate(xs, axis=axis)

    def stack(self, xs: list[Any], axis: int = 0) -> Any:
        return np.stack(xs, axis=axis)

    def clip(self, x: Any, lo: Any = None, hi: Any = None) -> Any:
        if lo is not None:
            x = np.maximum(x, lo)
        if hi is not None:
            x = np.minimum(x, hi)
        return x

    def nonzero(self, mask: Any) -> Any:
        return np.flatnonzero(mask)

    def argsort_desc(self, x: Any) -> Any:
        return np.argsort(-x, axis=-1, kind="stable")

    def take(self, x: Any, idx: Any, axis: int) -> Any:
        # Fancy indexing: take_along_axis costs ~5x more on small arrays.
        if x.ndim == 2 and axis == 1:
            return x[np.arange(x.shape[0])[:, None], idx]
        if x.ndim == 3 and axis == 1:
            return x[np.arange(x.shape[0])[:, None, None], idx, np.arange(x.shape[2])[None, None, :]]
        return np.take_along_axis(x, idx, axis=axis)

    def any(self, x: Any, axis: Any = None) -> Any:
        return x.any(axis)

    def all(self, x: Any, axis: Any = None) -> Any:
        return x.all(axis)

    def amax(self, x: Any, axis: Any) -> Any:
        return x.max(axis)

    def amin(self, x: Any, axis: Any) -> Any:
        return x.min(axis)

    def argmin(self, x: Any, axis: int) -> Any:
        return x.argmin(axis)

    def mT(self, x: Any) -> Any:
        return np.swapaxes(x, -1, -2)

    def complex(self, re: Any, im: Any) -> Any:
        return re + 1j * im

    def conj(self, z: Any) -> Any:
        return np.conj(z)

    def real_pairs(self, z: Any) -> Any:
        return np.stack((z.real, z.imag), axis=-1)

    def copy(self, x: Any) -> Any:
        return x.copy()

    def expand(self, x: Any, shape: tuple[int, ...]) -> Any:
        out = np.empty(shape, dtype=x.dtype)  # a copy: cheaper than broadcast_to on small arrays
        out[...] = x
        return out

    def astype(self, x: Any, dtype: str) -> Any:
        return x.astype(self._dtypes[dtype])

    def cholesky(self, A: Any) -> tuple[Any, Any]:
        n, P = A.shape[0], A.shape[-1]
        ok = np.isfinite(A).all(axis=(1, 2))
        safe = np.where(ok[:, None, None], A, np.eye(P))
        try:
            return np.linalg.cholesky(safe), ok
        except np.linalg.LinAlgError:  # some row is not positive definite: factor row by row
            C = np.empty_like(safe)
            for i in range(n):
                try:
                    C[i] = np.linalg.cholesky(safe[i])
                except np.linalg.LinAlgError:
                    C[i], ok[i] = np.eye(P), False
            return C, ok

    def cho_solve(self, C: Any, b: Any) -> Any:
        # Two triangular solves; NumPy has no batched triangular solver, and a general solve of these small
        # systems costs about the same.
        y = np.linalg.solve(C, b[..., None])
        return np.linalg.solve(np.swapaxes(C, -1, -2), y)[..., 0]

    @staticmethod
    def _solve_finite(A: Any, rhs: Any) -> Any:
        """``np.linalg.solve(A, rhs)`` where A, rhs and the solution are all finite and no system is singular (the
        common case, checked with whole-array reductions); None otherwise (the caller's per-row path then)."""
        if not (np.isfinite(A).all() and np.isfinite(rhs).all()):
            return None
        try:
            x = np.linalg.solve(A, rhs)
        except np.linalg.LinAlgError:
            return None
        return x if np.isfinite(x).all() else None

    def solve(self, A: Any, b: Any) -> tuple[Any, Any]:
        P = A.shape[-1]
        flat = A.reshape(-1, P, P)
        x = self._solve_finite(flat, b.reshape(flat.shape[0], P, -1))
        if x is not None:
            return x.reshape(b.shape), np.ones(A.shape[:-2], dtype=bool)
        return super().solve(A, b)

    def spd_solve(self, A: Any, b: Any) -> tuple[Any, Any]:
        n, P = A.shape[0], A.shape[-1]
        vector = b.ndim == 2
        rhs = b[..., None] if vector else b
        x = self._solve_finite(A, rhs)
        if x is not None:
            return (x[..., 0] if vector else x), np.ones((n,), dtype=bool)
        ok = np.isfinite(A.reshape(n, -1)).all(1) & np.isfinite(rhs.reshape(n, -1)).all(1)
        good = bool(ok.all())
        if not good:  # solve the others; the broken rows get the identity and a zero right-hand side
            A = np.where(ok[:, None, None], A, np.eye(P))
            rhs = np.where(ok[:, None, None], rhs, 0.0)
        try:
            x = np.linalg.solve(A, rhs)
        except np.linalg.LinAlgError:  # singular somewhere: row by row
            x = np.zeros_like(rhs)
            for i in range(n):
                try:
                    x[i] = np.linalg.solve(A[i], rhs[i])
                except np.linalg.LinAlgError:
                    ok[i] = False
            good = False
        finite = np.isfinite(x.reshape(n, -1)).all(1)
        if not (good and bool(finite.all())):
            ok = ok & finite
            x = np.where(ok[:, None, None], x, 0.0)
        return (x[..., 0] if vector else x), ok

    def eigh(self, A: Any) -> tuple[Any, Any, Any]:
        n, P = A.shape[0], A.shape[-1]
        ok = np.isfinite(A).all(axis=(1, 2))
        safe = np.where(ok[:, None, None], A, np.eye(P))
        try:
            w, v = np.linalg.eigh(safe)
        except np.linalg.LinAlgError:
            w, v = np.empty((n, P)), np.empty((n, P, P))
            for i in range(n):
                try:
                    w[i], v[i] = np.linalg.eigh(safe[i])
                except np.linalg.LinAlgError:
                    ok[i] = False
        w = np.where(ok[:, None], w, np.nan)
        v = np.where(ok[:, None, None], v, np.nan)
        return w, v, ok


class TorchBackend(Backend):
    """:class:`Backend` on torch tensors of one device."""

    name = "torch"
    lib = torch

    def __init__(self, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self._dtypes = {
            "float": torch.float64,
            "complex": torch.complex128,
            "int": torch.int64,
            "bool": torch.bool,
        }

    def asarray(self, x: Any, dtype: str = "float") -> Any:
        return torch.as_tensor(x, dtype=self._dtypes[dtype], device=self.device)

    def from_torch(self, t: torch.Tensor) -> Any:
        return t.detach().to(self.device)

    def to_torch(self, x: Any, device: torch.device) -> torch.Tensor:
        return x.to(device)

    def zeros(self, shape: tuple[int, ...], dtype: str = "float") -> Any:
        return torch.zeros(shape, dtype=self._dtypes[dtype], device=self.device)

    def full(self, shape: tuple[int, ...], value: float, dtype: str = "float") -> Any:
        return torch.full(shape, value, dtype=self._dtypes[dtype], device=self.device)

    def arange(self, n: int) -> Any:
        return torch.arange(n, device=self.device)

    def where(self, c: Any, a: Any, b: Any) -> Any:
        if not isinstance(a, torch.Tensor) and not isinstance(b, torch.Tensor):
            a = torch.as_tensor(a, dtype=torch.float64, device=self.device)
        return torch.where(c, a, b)

    def concat(self, xs: list[Any], axis: int = 0) -> Any:
        return torch.cat(xs, dim=axis)

    def stack(self, xs: list[Any], axis: int = 0) -> Any:
        return torch.stack(xs, dim=axis)

    def clip(self, x: Any, lo: Any = None, hi: Any = None) -> Any:
        if lo is not None:
            x = torch.maximum(x, lo) if isinstance(lo, torch.Tensor) else x.clamp(min=lo)
        if hi is not None:
            x = torch.minimum(x, hi) if isinstance(hi, torch.Tensor) else x.clamp(max=hi)
        return x

    def nonzero(self, mask: Any) -> Any:
        return mask.nonzero().squeeze(1)

    def argsort_desc(self, x: Any) -> Any:
        return x.sort(dim=-1, descending=True, stable=True).indices

    def take(self, x: Any, idx: Any, axis: int) -> Any:
        return x.gather(axis, idx)

    def any(self, x: Any, axis: Any = None) -> Any:
        return x.any() if axis is None else x.any(dim=axis)

    def all(self, x: Any, axis: Any = None) -> Any:
        return x.all() if axis is None else x.all(dim=axis)

    def amax(self, x: Any, axis: Any) -> Any:
        return x.amax(dim=axis)

    def amin(self, x: Any, axis: Any) -> Any:
        return x.amin(dim=axis)

    def argmin(self, x: Any, axis: int) -> Any:
        return x.argmin(dim=axis)

    def mT(self, x: Any) -> Any:
        return x.transpose(-1, -2)

    def complex(self, re: Any, im: Any) -> Any:
        return torch.complex(re, im)

    def conj(self, z: Any) -> Any:
        return torch.conj_physical(z)

    def real_pairs(self, z: Any) -> Any:
        return torch.view_as_real(z.contiguous())

    def copy(self, x: Any) -> Any:
        return x.clone()

    def expand(self, x: Any, shape: tuple[int, ...]) -> Any:
        return x.expand(*shape)

    def astype(self, x: Any, dtype: str) -> Any:
        return x.to(self._dtypes[dtype])

    def cholesky(self, A: Any) -> tuple[Any, Any]:
        P = A.shape[-1]
        ok = torch.isfinite(A).all(dim=2).all(dim=1)
        eye = torch.eye(P, dtype=A.dtype, device=A.device)
        safe = torch.where(ok.view(-1, 1, 1), A, eye)
        C, info = torch.linalg.cholesky_ex(safe)
        ok = ok & (info == 0)
        return torch.where(ok.view(-1, 1, 1), C, eye), ok

    def cho_solve(self, C: Any, b: Any) -> Any:
        return torch.cholesky_solve(b.unsqueeze(-1), C).squeeze(-1)

    def spd_solve(self, A: Any, b: Any) -> tuple[Any, Any]:
        P = A.shape[-1]
        vector = b.dim() == 2
        rhs = b.unsqueeze(-1) if vector else b
        ok = torch.isfinite(A).all(dim=2).all(dim=1) & torch.isfinite(rhs).all(dim=2).all(dim=1)
        eye = torch.eye(P, dtype=A.dtype, device=A.device)
        C, info = torch.linalg.cholesky_ex(torch.where(ok.view(-1, 1, 1), A, eye))
        ok = ok & (info == 0)
        x = torch.cholesky_solve(torch.where(ok.view(-1, 1, 1), rhs, 0.0), torch.where(ok.view(-1, 1, 1), C, eye))
        ok = ok & torch.isfinite(x).all(dim=2).all(dim=1)
        x = torch.where(ok.view(-1, 1, 1), x, 0.0)
        return (x.squeeze(-1) if vector else x), ok

    def eigh(self, A: Any) -> tuple[Any, Any, Any]:
        n, P = A.shape[0], A.shape[-1]
        ok = torch.isfinite(A).all(dim=2).all(dim=1)
        eye = torch.eye(P, dtype=A.dtype, device=A.device)
        safe = torch.where(ok.view(-1, 1, 1), A, eye)
        try:
            w, v = torch.linalg.eigh(safe)
        except RuntimeError:  # the solver did not converge on some row: one at a time
            w = torch.empty(n, P, dtype=A.dtype, device=A.device)
            v = torch.empty(n, P, P, dtype=A.dtype, device=A.device)
            ok = ok.clone()
            for i in range(n):
                try:
                    w[i], v[i] = torch.linalg.eigh(safe[i])
                except RuntimeError:
                    ok[i] = False
        nan = torch.full((), math.nan, dtype=A.dtype, device=A.device)
        return torch.where(ok.view(-1, 1), w, nan), torch.where(ok.view(-1, 1, 1), v, nan), ok


NUMPY = NumpyBackend()


def torch_backend(device: torch.device | str = "cpu") -> TorchBackend:
    """The torch backend on ``device``."""
    return TorchBackend(device)


def backend_for(name: str, device: torch.device) -> Backend:
    """``"numpy"`` (the CPU only) or ``"torch"`` on ``device``."""
    if name == "numpy":
        if device.type != "cpu":
            raise ValueError(f"the numpy backend runs on the CPU only, got device {device}")
        return NUMPY
    if name == "torch":
        return TorchBackend(device)
    raise ValueError(f"backend must be 'numpy' or 'torch', got {name!r}")
