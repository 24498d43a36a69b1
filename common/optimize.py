"""Powell's direction-set method with batched line searches, for XOR energies (pixel counts,
weighted per camera: piecewise constant).

Why not scipy's Powell: with bounds, scipy's line search (``fminbound``) never compares its
result with the starting point, so on a piecewise-constant energy it regularly returns a pose
worse than the one it started from; and Brent's method asks for one point at a time, while
our energies evaluate a batch of candidates for little more than the price of one. Here each
line search brackets with a batch of points along the direction and then narrows around the
best with further batches (a batched golden/parabolic search); the best point seen is always
kept, so the energy never goes up.

The objective is ``f(X (N, n)) -> (N,)``; the interface follows scipy's result object.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BRACKET = np.array([-1.0, -0.5, -0.25, 0.25, 0.5, 1.0])  # first probes, in units of the step
EXPAND = 2.0      # bracket growth when the best probe is at the end of the bracket
MAX_EXPANSIONS = 3
REFINE = np.array([-0.5, -0.25, 0.25, 0.5])  # refinement probes, in units of the spacing
MAX_ITERATIONS = 20  # Powell sweeps over the directions, at most


@dataclass(frozen=True)
class OptimizeResult:
    x: np.ndarray
    fun: float
    nfev: int
    nit: int
    status: int      # 0 converged, 1 evaluation budget spent
    message: str


def _line_range(x: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[float, float]:
    """The interval of t keeping x + t d inside the box [lo, hi]. (Python floats: for a few
    parameters, numpy's per-call overhead cost more than the arithmetic.)"""
    tmin, tmax = -np.inf, np.inf
    for xi, di, low, high in zip(x.tolist(), d.tolist(), lo.tolist(), hi.tolist()):
        if di != 0.0:
            t1, t2 = (low - xi) / di, (high - xi) / di
            tmin, tmax = max(tmin, min(t1, t2)), min(tmax, max(t1, t2))
    return tmin, tmax


class _Counter:
    def __init__(self, f, max_evals: int):
        self.f, self.max_evals, self.nfev = f, max_evals, 0

    @property
    def spent(self) -> bool:
        return self.nfev >= self.max_evals

    def __call__(self, X: np.ndarray) -> np.ndarray:
        self.nfev += len(X)
        return np.asarray(self.f(X), dtype=np.float64)


def line_search(f: _Counter, x: np.ndarray, fx: float, d: np.ndarray, lo, hi, tol: float):
    """Minimise f(x + t d) over t; returns (t, f) with f <= fx (t = 0 if nothing better)."""
    tmin, tmax = _line_range(x, d, lo, hi)
    ts, fs = [0.0], [fx]  # a handful of probes: plain lists cost less than numpy's set operations

    def probe(cands):
        cands = sorted({min(max(float(t), tmin), tmax) for t in cands}.difference(ts))
        if not cands or f.spent:
            return
        t = np.array(cands)
        # clip the points too: x + t d can land one rounding step outside the box
        vals = f(np.minimum(np.maximum(x[None] + t[:, None] * d[None], lo), hi))  # np.clip, at a third of its overhead
        ts.extend(cands)
        fs.extend(vals.tolist())

    def best_t() -> float:
        return ts[fs.index(min(fs))]  # the first of equals: t = 0 wins ties, no drift

    probe(BRACKET)
    span = 1.0
    for _ in range(MAX_EXPANSIONS):  # the minimum may lie beyond the first bracket
        best = best_t()
        if abs(best) < span * 0.99 or f.spent:
            break
        probe(best * np.array([1.5, EXPAND]))
        span *= EXPAND
    spacing = 0.25 * span  # distance from the best probe to its neighbours
    while spacing > tol and not f.spent:
        probe(best_t() + spacing * REFINE)
        spacing *= 0.25
    i = fs.index(min(fs))
    return float(ts[i]), float(fs[i])


def powell(f, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray, steps: np.ndarray,
           xtol: float = 0.02, ftol: float = 1e-4, max_evals: int = 400,
           max_iter: int = MAX_ITERATIONS) -> OptimizeResult:
    """Minimise f over the box [lower, upper] from x0 with Powell's direction set.

    f: (N, n) -> (N,); steps (n,): initial direction lengths (the first probes reach one step);
    xtol: line-search resolution in units of a direction's length; ftol: relative decrease
    per iteration below which the search stops.
    """
    if not xtol > 0:  # the line searches refine until their spacing is below it
        raise ValueError(f"xtol must be positive, got {xtol}")
    counter = _Counter(f, max_evals)
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    fx = float(counter(x[None])[0])
    dirs = np.diag(np.asarray(steps, dtype=np.float64))
    nit, status, message = 0, 0, "converged"
    while nit < max_iter:
        nit += 1
        f_start, x_start = fx, x.copy()
        biggest, biggest_i = 0.0, 0
        for i, d in enumerate(dirs):
            t, ft = line_search(counter, x, fx, d, lo, hi, xtol)
            if fx - ft > biggest:
                biggest, biggest_i = fx - ft, i
            if ft < fx:
                x, fx = np.clip(x + t * d, lo, hi), ft
        if counter.spent:
            status, message = 1, "evaluation budget spent"
            break
        if 2.0 * (f_start - fx) <= ftol * (abs(f_start) + abs(fx)) + 1e-12:
            break
        # Powell's update: the net move of this sweep replaces the direction of largest decrease
        delta = x - x_start
        if np.any(delta != 0):
            t, ft = line_search(counter, x, fx, delta, lo, hi, xtol)
            if ft < fx:
                x, fx = np.clip(x + t * delta, lo, hi), ft
            dirs = np.concatenate([np.delete(dirs, biggest_i, axis=0), delta[None]])
    return OptimizeResult(x, fx, counter.nfev, nit, status, message)
