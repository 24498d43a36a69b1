"""Powell's direction-set method with batched line searches, and an evolution strategy over
many parameters at once (``cma_es``), for XOR energies (pixel counts, weighted per camera:
piecewise constant).

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
from numba import njit

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


# CMA-ES (Hansen's tutorial, "The CMA Evolution Strategy", 2016): the population's size is
# about its 4 + 3 ln(n) for the 35 pose parameters
CMA_POPULATION = 16


@njit(cache=True)
def _cholesky(C: np.ndarray) -> np.ndarray:
    """The lower factor L (n, n) of a covariance C = L L^T, in plain loops: LAPACK's
    decompositions start threads that, on a machine whose cores are already busy (a fit's own
    threads), made each decomposition of a 35x35 matrix take milliseconds instead of
    microseconds; and loops give the same bits on every machine, as a cluster's clients must."""
    n = C.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        d = C[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        L[j, j] = np.sqrt(max(d, 1e-300))
        for i in range(j + 1, n):
            v = C[i, j]
            for k in range(j):
                v -= L[i, k] * L[j, k]
            L[i, j] = v / L[j, j]
    return L


@njit(cache=True)
def _times_transposed(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A B^T for A (m, k) and B (n, k), in plain loops (as ``_cholesky``: no BLAS threads, the
    same bits everywhere)."""
    out = np.zeros((A.shape[0], B.shape[0]))
    for i in range(A.shape[0]):
        for j in range(B.shape[0]):
            v = 0.0
            for k in range(A.shape[1]):
                v += A[i, k] * B[j, k]
            out[i, j] = v
    return out


@njit(cache=True)
def _solve_lower(L: np.ndarray, v: np.ndarray) -> np.ndarray:
    """x with L x = v, L (n, n) lower triangular, by forward substitution (plain loops, as
    ``_cholesky``)."""
    n = L.shape[0]
    x = np.zeros(n)
    for i in range(n):
        s = v[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    return x


def _norm(v: np.ndarray) -> float:
    """The Euclidean norm by numpy's own summation (``np.linalg.norm`` calls BLAS, whose
    kernels differ between CPUs)."""
    return float(np.sqrt((v * v).sum()))


def cma_es(f, x0: np.ndarray, sigmas: np.ndarray, lower: np.ndarray, upper: np.ndarray, max_evals: int,
           rng: np.random.Generator, population: int = CMA_POPULATION) -> OptimizeResult:
    """Minimise f over the box [lower, upper] from x0 by a covariance matrix adaptation
    evolution strategy: each generation samples ``population`` points (N, n) around a mean, moves
    the mean to the weighted best half and learns from them the directions along which the
    energy falls, as a covariance (n, n), sampled through its Cholesky factor. Samples outside
    the box are moved onto it.

    Why beside Powell: a pose fitted chain by chain, or by Powell along the parameters, can sit
    where the energy falls only along a direction that moves many parameters at once (the torso
    turned with the limbs turned back); the learned covariance finds such a direction.

    f: (N, n) -> (N,); sigmas (n,): the first samples' standard deviations; ``rng`` draws every
    sample, so a seeded generator gives the same result. Returns the best point evaluated (x0
    where none is lower) as an OptimizeResult (nit: generations)."""
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    n = len(x0)
    mu = population // 2
    w = np.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    w /= w.sum()
    mueff = 1.0 / float(np.sum(w ** 2))
    cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
    cs = (mueff + 2) / (n + mueff + 5)
    c1 = 2 / ((n + 1.3) ** 2 + mueff)
    cmu = min(1 - c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
    damps = 1 + 2 * max(0.0, np.sqrt((mueff - 1) / (n + 1)) - 1) + cs
    chi_n = np.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
    counter = _Counter(f, max_evals)
    mean = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    best_x, best_f = mean.copy(), float(counter(mean[None])[0])
    sigma, cov = 1.0, np.diag(np.asarray(sigmas, dtype=np.float64) ** 2)
    pc, ps = np.zeros(n), np.zeros(n)
    generation = 0
    while counter.nfev + population <= max_evals:
        factor = _cholesky(cov)
        z = rng.standard_normal((population, n))
        X = np.clip(mean + sigma * _times_transposed(z, factor), lo, hi)
        y = (X - mean) / sigma
        F = counter(X)
        generation += 1
        order = np.argsort(F, kind="stable")[:mu]
        if F[order[0]] < best_f:
            best_f, best_x = float(F[order[0]]), X[order[0]].copy()
        step = (w[:, None] * y[order]).sum(axis=0)
        mean = mean + sigma * step
        # the path in the samples' standard units (L^-1 of the step: C^-1/2 up to a turn), of the
        # step the mean took: the samples' own draws z would go on lengthening it while the
        # samples are moved onto the box's faces, and the spread would grow without bound
        ps = (1 - cs) * ps + np.sqrt(cs * (2 - cs) * mueff) * _solve_lower(factor, step)
        norm = _norm(ps) / np.sqrt(1 - (1 - cs) ** (2 * generation)) / chi_n
        hsig = float(norm < 1.4 + 2 / (n + 1))
        pc = (1 - cc) * pc + hsig * np.sqrt(cc * (2 - cc) * mueff) * step
        chosen = y[order] * np.sqrt(w)[:, None]
        cov = ((1 - c1 - cmu) * cov + c1 * (np.outer(pc, pc) + (1 - hsig) * cc * (2 - cc) * cov)
               + cmu * _times_transposed(chosen.T, chosen.T))
        sigma *= np.exp((cs / damps) * (_norm(ps) / chi_n - 1))
    return OptimizeResult(best_x, best_f, counter.nfev, generation, 1, "evaluation budget spent")
