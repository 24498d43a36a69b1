"""Powell's direction set (``common.optimize.powell``) compiled around the ``cpu`` energy.

Why a compiled twin: a chain's solve makes thousands of line-search probes of a handful of
poses each, and with the energy's own kernel taking about 10 microseconds a pose, numpy's and
Python's per-probe overhead (building candidates, clipping, bookkeeping) cost as much as the
energy. Here the whole solve is one compiled call. It takes the same steps as
``common.optimize.powell`` on the same objective (tests/test_energy.py holds the two equal
pose for pose), so which one runs changes the time, not the result. (Clipping by min/max keeps
a -0.0 that np.clip would make +0.0 at a bound of exactly 0; no joint limit is 0.)

The objective of a solve: the candidate's chain parameters put into the full pose; for the
torso, the limbs held in their world orientation (``body.hold_limbs_in_world``) and the pose
clipped into the joint limits; the ``cpu`` energy (``energy.pose_energies``); plus, for the
torso, the spine twist prior (``common.objective.SpinePrior``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from common.body import _LIMB_ROOTS, PARAM_COUNT, PARAM_LIMITS, _hold_limbs
from common.energy import CpuEnergy, pose_energies
from common.optimize import BRACKET, EXPAND, MAX_EXPANSIONS, MAX_ITERATIONS, REFINE

_NO_HOLD = np.zeros((16, 3, 3))  # the reference rotations' place when no limbs are held (one compiled signature)
_LIMITS_LOW = np.ascontiguousarray(PARAM_LIMITS[:, 0])
_LIMITS_HIGH = np.ascontiguousarray(PARAM_LIMITS[:, 1])
PROBES_AT_ONCE = max(len(BRACKET), 2, len(REFINE))  # the most offsets one _probe call evaluates


@njit(cache=True, nogil=True)
def _objective(Z, full, idx, hold, reference_rotations, limb_roots, limits_low, limits_high, prior_weight,
               prior_index, energy_base, kernel):
    """Z (m, n) chain parameters -> (m,) objective values, float64 (see the module's docstring)."""
    m = Z.shape[0]
    cand = np.empty((m, full.shape[0]))
    for r in range(m):
        cand[r] = full
        for j in range(idx.shape[0]):
            cand[r, idx[j]] = Z[r, j]
    if hold:
        _hold_limbs(cand, reference_rotations, limb_roots)
        for r in range(m):
            for i in range(full.shape[0]):
                cand[r, i] = min(max(cand[r, i], limits_low[i]), limits_high[i])
    sums = pose_energies(cand, *kernel)
    out = np.empty(m)
    for r in range(m):
        out[r] = float(energy_base + sums[r])
        if prior_weight > 0:
            twist = cand[r, prior_index]
            out[r] += prior_weight * (twist * twist)
    return out


@njit(cache=True, nogil=True, inline="always")
def _clipped_step(x, t, d, lo, hi, out) -> None:
    """out (n,) = x + t d clipped into the box [lo, hi] (``np.clip``; out may be x)."""
    for i in range(x.shape[0]):
        out[i] = min(max(x[i] + t * d[i], lo[i]), hi[i])


@njit(cache=True, nogil=True, inline="always")
def _line_range(x, d, lo, hi) -> tuple:
    """``optimize._line_range``: the interval of t keeping x + t d inside the box [lo, hi]."""
    tmin, tmax = -np.inf, np.inf
    for i in range(x.shape[0]):
        if d[i] != 0.0:
            t1, t2 = (lo[i] - x[i]) / d[i], (hi[i] - x[i]) / d[i]
            tmin, tmax = max(tmin, min(t1, t2)), min(tmax, max(t1, t2))
    return tmin, tmax


@njit(cache=True, nogil=True)
def _probe(offsets, x, d, lo, hi, tmin, tmax, line, nfev, max_evals, problem, scratch) -> None:
    """Evaluate the line at the new (clipped, not yet probed) ``offsets``, in increasing order;
    they join ``line``'s probes. line: (ts, fs, count) with count (1,) the probes so far;
    scratch: (X (PROBES_AT_ONCE, n) candidate rows, keep (PROBES_AT_ONCE,)), reused where a
    probe made a list, a sorted array and its candidates' array each time (together about 6%
    of a limb's solve)."""
    ts, fs, count = line
    X, keep = scratch
    n = 0
    for t in offsets:  # clipped, sorted by insertion, without repeats or earlier probes
        t = min(max(t, tmin), tmax)
        if _holds(ts, count[0], t) or _holds(keep, n, t):
            continue
        j = n
        while j > 0 and keep[j - 1] > t:
            keep[j] = keep[j - 1]
            j -= 1
        keep[j] = t
        n += 1
    if n == 0 or nfev[0] >= max_evals:
        return
    for r in range(n):
        _clipped_step(x, keep[r], d, lo, hi, X[r])
    values = _objective(X[:n], *problem)
    nfev[0] += n
    for r in range(n):
        ts[count[0]] = keep[r]
        fs[count[0]] = values[r]
        count[0] += 1


@njit(cache=True, nogil=True, inline="always")
def _holds(values, count, t) -> bool:
    """Whether t is among the first ``count`` values."""
    for i in range(count):
        if values[i] == t:
            return True
    return False


@njit(cache=True, nogil=True)
def _lowest(fs, count) -> int:
    """The index of the probe of lowest value among the first ``count``, the first of equals
    (t = 0 wins ties: no drift)."""
    best = 0
    for i in range(1, count):
        if fs[i] < fs[best]:
            best = i
    return best


@njit(cache=True, nogil=True)
def _line_search(x, fx, d, lo, hi, tol, nfev, max_evals, problem, line, scratch):
    """``optimize.line_search``: (t, f) with f <= fx (t = 0 if nothing better); ``line``'s
    arrays hold its probes (``_line_capacity``)."""
    ts, fs, count = line
    tmin, tmax = _line_range(x, d, lo, hi)
    ts[0], fs[0], count[0] = 0.0, fx, 1
    _probe(BRACKET, x, d, lo, hi, tmin, tmax, line, nfev, max_evals, problem, scratch)
    span = 1.0
    for _ in range(MAX_EXPANSIONS):
        best = ts[_lowest(fs, count[0])]
        if abs(best) < span * 0.99 or nfev[0] >= max_evals:
            break
        _probe(best * np.array([1.5, EXPAND]), x, d, lo, hi, tmin, tmax, line, nfev, max_evals, problem, scratch)
        span *= EXPAND
    spacing = 0.25 * span
    while spacing > tol and nfev[0] < max_evals:
        _probe(ts[_lowest(fs, count[0])] + spacing * REFINE, x, d, lo, hi, tmin, tmax, line, nfev, max_evals,
               problem, scratch)
        spacing *= 0.25
    best = _lowest(fs, count[0])
    return ts[best], fs[best]


@njit(cache=True, nogil=True)
def _line_capacity(tol: float) -> int:
    """The most probes one line search makes (``_line_search``): the start, the bracket, the
    expansions, and the refinements down to ``tol`` from the widest span."""
    span = 1.0
    for _ in range(MAX_EXPANSIONS):  # the widest span, grown as _line_search grows it
        span *= EXPAND
    refinements, spacing = 0, 0.25 * span
    while spacing > tol:
        refinements += 1
        spacing *= 0.25
    return 1 + len(BRACKET) + 2 * MAX_EXPANSIONS + len(REFINE) * refinements


@njit(cache=True, nogil=True)
def _powell(x0, lo, hi, steps, xtol, ftol, max_evals, max_iter, problem):
    """``optimize.powell`` -> (x (n,), f, evaluations, iterations)."""
    nfev = np.zeros(1, np.int64)
    n = x0.shape[0]
    capacity = _line_capacity(xtol)
    line = (np.empty(capacity), np.empty(capacity), np.zeros(1, np.int64))
    scratch = (np.empty((PROBES_AT_ONCE, n)), np.empty(PROBES_AT_ONCE))
    x = np.empty(n)
    for i in range(n):
        x[i] = min(max(x0[i], lo[i]), hi[i])
    fx = _objective(x.reshape(1, n), *problem)[0]
    nfev[0] += 1
    dirs = np.diag(steps)
    nit = 0
    while nit < max_iter:
        nit += 1
        f_start, x_start = fx, x.copy()
        biggest, biggest_i = 0.0, 0
        for i in range(dirs.shape[0]):
            d = dirs[i]
            t, ft = _line_search(x, fx, d, lo, hi, xtol, nfev, max_evals, problem, line, scratch)
            if fx - ft > biggest:
                biggest, biggest_i = fx - ft, i
            if ft < fx:
                _clipped_step(x, t, d, lo, hi, x)
                fx = ft
        if nfev[0] >= max_evals:
            break
        if 2.0 * (f_start - fx) <= ftol * (abs(f_start) + abs(fx)) + 1e-12:
            break
        delta = x - x_start
        if np.any(delta != 0):
            t, ft = _line_search(x, fx, delta, lo, hi, xtol, nfev, max_evals, problem, line, scratch)
            if ft < fx:
                _clipped_step(x, t, delta, lo, hi, x)
                fx = ft
            kept = np.empty_like(dirs)
            row = 0
            for i in range(dirs.shape[0]):
                if i != biggest_i:
                    kept[row] = dirs[i]
                    row += 1
            kept[row] = delta
            dirs = kept
    return x, fx, nfev[0], nit


def powell_cpu(energy: CpuEnergy, x0: np.ndarray, indices, steps: np.ndarray, xtol: float, ftol: float,
               max_evals: int, hold_rotations: np.ndarray | None = None, prior_weight: float = 0.0,
               prior_index: int = 0, max_iter: int = MAX_ITERATIONS) -> tuple:
    """Powell over ``indices`` of the 35 parameters of x0 (35,), the others held, on ``energy``.

    hold_rotations: (16, 3, 3) the reference pose's segment rotations: hold the limbs in their
    world orientation and clip into the joint limits (the torso); prior_weight: the spine twist
    prior's weight on parameter ``prior_index`` (0: none).
    Returns (chain parameters (n,), objective, evaluations, iterations); ``energy`` counts them.
    """
    idx = np.asarray(indices, dtype=np.int64)
    full = np.ascontiguousarray(x0, dtype=np.float64)
    steps = np.asarray(steps, dtype=np.float64)
    hold = hold_rotations is not None
    # the compiled loops index without bounds checks: refuse what would read past an array
    if full.shape != (PARAM_COUNT,):
        raise ValueError(f"expected {PARAM_COUNT} parameters, got shape {full.shape}")
    if idx.ndim != 1 or steps.shape != idx.shape or np.any((idx < 0) | (idx >= PARAM_COUNT)):
        raise ValueError(f"indices {idx.tolist()} and steps of shape {steps.shape} do not match 35 parameters")
    if not xtol > 0:
        raise ValueError(f"xtol must be positive, got {xtol}")
    if hold and np.shape(hold_rotations) != (16, 3, 3):
        raise ValueError(f"hold_rotations must be (16, 3, 3), got {np.shape(hold_rotations)}")
    problem = (full, idx, hold, np.ascontiguousarray(hold_rotations if hold else _NO_HOLD, dtype=np.float64),
               _LIMB_ROOTS, _LIMITS_LOW, _LIMITS_HIGH, float(prior_weight), int(prior_index),
               np.float64(energy.base), energy.kernel_tables)
    x, fun, nfev, nit = _powell(full[idx], np.ascontiguousarray(PARAM_LIMITS[idx, 0]),
                                np.ascontiguousarray(PARAM_LIMITS[idx, 1]), steps,
                                float(xtol), float(ftol), int(max_evals), int(max_iter), problem)
    energy.evaluations += int(nfev)
    return x, float(fun), int(nfev), int(nit)
