"""Covariance matrix adaptation (CMA-ES, Hansen's (mu/mu_w, lambda) form) over all 35 pose
parameters at once, on the whole images.

Why: the hierarchical fit moves one chain at a time, and Powell over all 35 parameters searches
along one direction at a time. A body rolling over (the cartwheel, 05_06) settles where the
torso and every limb are off together: the energy falls along the straight line from the fit
to the truth, but moving the torso alone costs thousands of pixels (its limbs leave their
silhouettes), so no chain and no axis goes down. CMA-ES learns the correlated direction from
the samples that did better, which is that line's kind of move.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from common.body import clip_to_limits


@dataclass(frozen=True)
class CmaResult:
    """The lowest pose sampled (35,), its objective, and the evaluations spent."""

    params: np.ndarray
    energy: float
    evaluations: int


def cma_minimise(objective: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, scale: np.ndarray,
                 sigma: float, max_evaluations: int, rng: np.random.Generator,
                 min_sigma: float = 1e-3) -> CmaResult:
    """Minimise ``objective`` ((B, 35) -> (B,)) from ``x0`` (35,), each parameter's step in
    units of ``scale`` (35,) times ``sigma``, every sample clipped into the joint limits; stops
    after ``max_evaluations`` or when the step falls under ``min_sigma``. The mean starts at
    ``x0``; the lowest sample (or ``x0``) is returned."""
    x0 = np.asarray(x0, dtype=np.float64)
    n = len(x0)
    lam = 4 + int(3 * np.log(n))
    mu = lam // 2
    w = np.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    w /= w.sum()
    mueff = 1.0 / (w ** 2).sum()
    cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
    cs = (mueff + 2) / (n + mueff + 5)
    c1 = 2 / ((n + 1.3) ** 2 + mueff)
    cmu = min(1 - c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
    damps = 1 + 2 * max(0.0, np.sqrt((mueff - 1) / (n + 1)) - 1) + cs
    chi_n = np.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
    mean = np.zeros(n)
    C = np.eye(n)
    pc, ps = np.zeros(n), np.zeros(n)
    best_x, best_e = x0, float(objective(x0[None])[0])
    used, generation = 1, 0
    while used + lam <= max_evaluations and sigma > min_sigma:
        eigen, B = np.linalg.eigh(C)
        D = np.sqrt(np.maximum(eigen, 1e-20))
        y = (rng.standard_normal((lam, n)) * D) @ B.T
        X = clip_to_limits(x0 + (mean + sigma * y) * scale)
        e = np.asarray(objective(X), dtype=np.float64)
        used += lam
        generation += 1
        order = np.argsort(e, kind="stable")
        if e[order[0]] < best_e:
            best_x, best_e = X[order[0]], float(e[order[0]])
        chosen = y[order[:mu]]
        step = w @ chosen
        mean = mean + sigma * step
        ps = (1 - cs) * ps + np.sqrt(cs * (2 - cs) * mueff) * (B @ ((B.T @ step) / D))
        held = np.linalg.norm(ps) / np.sqrt(1 - (1 - cs) ** (2 * generation)) / chi_n < 1.4 + 2 / (n + 1)
        pc = (1 - cc) * pc + held * np.sqrt(cc * (2 - cc) * mueff) * step
        C = (1 - c1 - cmu) * C + c1 * np.outer(pc, pc) + cmu * (chosen.T * w) @ chosen
        sigma *= np.exp((cs / damps) * (np.linalg.norm(ps) / chi_n - 1))
    return CmaResult(np.array(best_x), best_e, used)
