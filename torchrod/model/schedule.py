"""The event schedule of a march: which events, in which order, and how many steps between them. ONE definition.

Every march of the rod (the primal march and its discrete adjoint in :mod:`torchrod.model.body_frame`, the
forward-sensitivity march of :mod:`torchrod.model.sensitivity` on arrays and on Python numbers) integrates from
the free tip s = L towards the base through a sequence of events per sample: the query positions (gratings, sample
points) and the force locations. This module fixes, for all of them:

* the events and their order: sorted by position from the tip to the base; at equal positions a FORCE comes before
  a QUERY (the query reads the state after the jump: it sees the force with zero lever). The curvature is
  continuous at a force, so the order changes no value, only which one-sided derivative in s a tie yields: the
  distal one (a grating at a force sees it move: dU_k/ds_i = the slope jump). The estimator turns it into the
  proximal one where it needs that side (:mod:`torchrod.estimate.problem`);
* the segments: segment e runs from the previous event (or the tip) to event e;
* the step counts: ``ceil(rate x segment / step_angle)``, at least 1, at most ``max_steps``, where the rate is a
  bound on the solution's local rate max(|U|, sqrt|m|) [1/m] at the segment's proximal end (the RKN error per
  step is a function of rate x step). Two rules:

  - ``"bound"`` (rigorous, the simulator's): |m| is constant between forces and jumps by at most |f_i| / EI at a
    force, so |m| <= M = sum of the distal |f_i| / EI; |m|^2 = |U'|^2 + |U|^4 / 4 gives |U| <= sqrt(2 M), and
    linear growth from the tip gives |U| <= sum_i |f_i| (s_i - s)^+ / EI;
  - ``"estimate"`` (the estimator's): the same two terms with vector sums of the complex jumps
    J_i = i (f_x + i f_y) / EI instead of sums of magnitudes, |sum_i J_i (s_i - s)^+| and sqrt|sum_i J_i|: opposed
    forces cancel. It is the small-deflection solution's own rate, a quarter fewer steps for the same accuracy
    over the synthetic envelope.

* the unloaded events (:func:`skip_unloaded`): distal to the most distal force the state of a march that starts
  from the zero state at the tip is zero and stays zero. The estimator's marches (the sensitivity march, the exact
  model's ``march_curvature``) give those events no steps (the force's own segment keeps its steps). The
  propagator's seeds are carried from the tip: on the zero state their tangent map is exactly linear, dU += seg
  dW, which the one-row march applies once per skipped event and the array march by stepping those events (a step
  of the scheme is that map). The simulator's differentiable march steps them all (the zero steps change no
  value).

* the steps in sequence (:func:`sequence`): a batched march takes each row's steps one after the other, so a
  batch costs its largest row's count, not the sum over events of the largest counts; a row past its last step
  steps by zero, which leaves its state unchanged.

A non-finite rate gives 1 step (NaN) or ``max_steps`` (inf). Every sample gets its own counts: a sample's result
does not depend on the samples batched with it.

The functions run on NumPy arrays and torch tensors alike (:mod:`torchrod.backend`); on tensors, the sorted
positions and segments keep their autograd history (the step lengths are differentiable in s). :func:`row` is the
same schedule for one row on Python numbers, for the marches that run a row at a time (a few dozen NumPy operations
on arrays of one row cost more than the march itself); a test holds it to the array functions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from ..backend import Backend

__all__ = ["RULES", "events", "rates", "row", "sequence", "skip_unloaded", "step_counts"]

RULES = ("bound", "estimate")


def events(xp: Backend, query: Any, s: Any, length: float) -> tuple[Any, Any, Any]:
    """Events sorted from the tip to the base.

    Args:
        query: (Q,) positions [m], or per row (B, Q); s: (B, h) force locations [m]; length: L [m].
    Returns:
        pos (B, E) sorted positions [m], order (B, E) with order < h a force's index and order >= h the query
        ``order - h``, seg (B, E) segment lengths [m] (segment e ends at event e), E = h + Q.
    """
    B = s.shape[0]
    Q = query.shape[-1]
    pos = xp.concat([s, xp.expand(query, (B, Q)) if query.ndim == 1 else query], 1)
    order = xp.argsort_desc(pos)
    pos = xp.take(pos, order, 1)
    start = xp.concat([pos[:, :1] * 0.0 + float(length), pos[:, :-1]], 1)  # in pos's dtype
    seg = xp.clip(start - pos, lo=0.0)
    return pos, order, seg


def rates(xp: Backend, s: Any, jump: Any, pos: Any, rule: str) -> Any:
    """(B, E) bound on the local rate [1/m] at each event's position (the module docstring).

    Args:
        s: (B, h) force locations [m]; pos: (B, E) event positions [m].
        jump: ``"estimate"``: (B, h) complex slope jumps J_i = i (f_x + i f_y) / EI [1/m^2]; ``"bound"``: (B, h)
            their magnitudes |f_i| / EI.
    """
    lib = xp.lib
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
    # The sums over the forces, force by force in index order (an axis of length h would cost NumPy a loop per
    # element); "estimate" sums the real and imaginary parts of the jumps apart.
    parts = [jump] if rule == "bound" else [jump.real, jump.imag]
    levered = [0.0 * pos for _ in parts]  # sum_i J_i (s_i - s)^+
    distal = [0.0 * pos for _ in parts]  # sum_i J_i [s_i > s]
    for i in range(s.shape[1]):
        lever = xp.clip(s[:, i : i + 1] - pos, lo=0.0)  # (B, E) [m]
        beyond = xp.astype(lever > 0, "float")
        for k, part in enumerate(parts):
            j = part[:, i : i + 1]
            levered[k] = levered[k] + j * lever
            distal[k] = distal[k] + j * beyond
    if rule == "bound":
        m = distal[0]  # |m| <= M [1/m^2]
        u = lib.minimum(levered[0], lib.sqrt(2.0 * m))
        return lib.maximum(u, lib.sqrt(m))
    return lib.maximum(lib.hypot(*levered), lib.sqrt(lib.hypot(*distal)))


def step_counts(
    xp: Backend,
    s: Any,
    jump: Any,
    pos: Any,
    seg: Any,
    *,
    step_angle: float,
    max_steps: int,
    rule: str,
) -> Any:
    """(B, E) integer steps per segment: ``rate x seg / step_angle`` rounded up, in [1, max_steps]."""
    lib = xp.lib
    need = rates(xp, s, jump, pos, rule) * seg / step_angle
    need = xp.where(need != need, 1.0, xp.clip(need, hi=float(max_steps)))  # NaN -> 1, inf -> max_steps
    return xp.astype(xp.clip(lib.ceil(need), lo=1.0), "int")


def skip_unloaded(xp: Backend, order: Any, steps: Any, h: int) -> Any:
    """``steps`` (B, E) with zero steps for the events distal to every force (``order`` (B, E) from :func:`events`,
    h forces). The most distal force's own segment keeps its steps: a march that records each event in the slot
    after its steps then takes the force's jump after the records distal to it."""
    forces = xp.lib.cumsum(order < h, 1) if xp.name == "numpy" else (order < h).cumsum(1)
    return xp.where(forces > 0, steps, 0 * steps)


def sequence(xp: Backend, order: Any, seg: Any, steps: Any) -> tuple[Any, Any]:
    """Each row's steps one after the other (module docstring).

    Args:
        order, seg: (B, E) from :func:`events`; steps: (B, E) integer steps per segment (0 allowed).
    Returns:
        hstep (B, K) step lengths [m], K the largest row's count of steps, zero past a row's last step; and slot
        (B, E), the steps taken when each force's and each query's event is reached (0: none), forces first, then
        the queries, in their input order.
    """
    B = steps.shape[0]
    last = xp.lib.cumsum(steps, 1) if xp.name == "numpy" else steps.cumsum(1)  # (B, E)
    K = int(xp.amax(last[:, -1], 0)) if B else 0
    E = steps.shape[1]
    # (B, K) each step's event: how many events end at or before it.
    if xp.name == "numpy":
        # One search over all rows: row b's ends shifted by b (K + 1) keep the rows apart and in order.
        lib = xp.lib
        shift = (lib.arange(B) * (K + 1))[:, None]
        event = lib.searchsorted((last + shift).ravel(), (lib.arange(K)[None, :] + shift).ravel(), side="right")
        event = event.reshape(B, K) - lib.arange(B)[:, None] * E
    else:
        event = xp.lib.searchsorted(last, xp.expand(xp.arange(K)[None, :], (B, K)).contiguous(), right=True)
    h = xp.where(steps > 0, seg / xp.clip(steps, lo=1), 0.0 * seg)
    hstep = xp.take(xp.concat([h, 0.0 * seg[:, :1]], 1), event, 1)  # past the last event: zero (in seg's dtype)
    # Each force's and query's slot: ``last`` through the inverse of the event order.
    inverse = xp.zeros((B, E), "int")
    inverse[xp.arange(B)[:, None], order] = xp.expand(xp.arange(E)[None, :], (B, E))
    slot = xp.take(last, inverse, 1)
    return hstep, slot


def _nanmax(a: float, b: float) -> float:
    return a if a != a or a >= b else b  # NaN propagates, as NumPy's maximum


def _nanmin(a: float, b: float) -> float:
    return a if a != a or a <= b else b


def row(
    query: Sequence[float],
    s: Sequence[float],
    jump: Sequence[Any],
    length: float,
    *,
    step_angle: float,
    max_steps: int,
    rule: str,
    skip: bool,
) -> tuple[list[int], list[float], list[int]]:
    """:func:`events`, :func:`step_counts` and (``skip``) :func:`skip_unloaded` for one row, on Python numbers.

    Args:
        query: Q positions [m]; s: h force locations [m]; jump: h jumps as :func:`rates` takes them (complex for
            ``"estimate"``, magnitudes for ``"bound"``).
    Returns:
        order (E,), seg (E,) [m] and steps (E,), as the array functions' rows.
    """
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
    h = len(s)
    bound = rule == "bound"
    pos = list(s) + list(query)
    order = sorted(range(len(pos)), key=pos.__getitem__, reverse=True)  # stable: forces first at ties
    seg: list[float] = []
    steps: list[int] = []
    start = float(length)
    passed = [False] * h  # the forces reached so far: only they can be distal
    reached = False
    cap, top = float(max_steps), max(max_steps, 1)
    for idx in order:
        p = pos[idx]
        d = start - p
        d = d if d != d or d >= 0.0 else 0.0
        seg.append(d)
        start = p
        if not reached:  # no force distal: rate 0, one step (none for the unloaded events where they are skipped)
            if idx < h:
                reached = passed[idx] = True
            steps.append(1 if reached or not skip else 0)
            continue
        # The sums over the distal forces in index order (the other terms are exact zeros in the arrays' sums).
        a = m = 0.0 if bound else 0j
        for i in range(h):
            if passed[i]:
                x = s[i] - p
                if x > 0.0:
                    a += jump[i] * x
                    m += jump[i]
                elif x != x:
                    a = x
        if bound:
            rate = _nanmax(_nanmin(a, math.sqrt(2.0 * m)), math.sqrt(m))
        else:  # _nanmax(|a|, sqrt|m|), inline (the hot path of the one-row marches)
            ra, rm = abs(a), math.sqrt(abs(m))
            rate = ra if ra != ra or ra >= rm else rm
        need = rate * d / step_angle
        # max(ceil(min(need, max_steps)), 1), NaN: 1
        steps.append(1 if need != need else top if need >= cap else max(math.ceil(need), 1))
        if idx < h:
            passed[idx] = True
    return order, seg, steps
