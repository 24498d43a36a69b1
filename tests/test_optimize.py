"""Batched Powell and CMA-ES (common.optimize): never worse than the start, inside the bounds,
within the evaluation budget; Powell finds the minimum of convex quadratics, CMA-ES that of a
valley along no parameter."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.optimize import BRACKET, CMA_POPULATION, cma_es, line_search, powell, _Counter

PROPERTY = settings(max_examples=60, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])


ULP_SLACK = 1e-12  # rounding of x + t d at the box's faces


class Recorder:
    """Wraps f(X (N, n)) -> (N,) and keeps every point it was asked about."""

    def __init__(self, f):
        self.f, self.points = f, []

    def __call__(self, X):
        X = np.array(X, dtype=np.float64)
        assert X.ndim == 2
        self.points.append(X.copy())
        return self.f(X)

    @property
    def all_points(self) -> np.ndarray:
        return np.concatenate(self.points)


@st.composite
def problems(draw):
    """A random box, start inside it, and a piecewise-constant objective: an integer-rounded
    quadratic plus random half-space steps (what an XOR pixel count looks like)."""
    seed = draw(st.integers(0, 2**31 - 1))
    n = draw(st.integers(1, 6))
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-2.0, 0.0, n)
    hi = lo + rng.uniform(0.05, 3.0, n)
    x0 = rng.uniform(lo, hi)
    centre = rng.uniform(lo - 0.5, hi + 0.5)
    weights = rng.uniform(0.1, 10.0, n)
    scale = draw(st.sampled_from([1.0, 10.0, 1000.0]))
    k = draw(st.integers(0, 8))
    normals = rng.normal(size=(k, n))
    offsets = rng.normal(size=k)
    heights = rng.integers(-20, 21, size=k)

    def f(X):
        quad = np.floor(scale * np.sum(weights * (X - centre) ** 2, axis=1))
        steps = ((X @ normals.T) > offsets) @ heights if k else 0
        return quad + steps

    steps = rng.uniform(0.01, 1.0, n) * (hi - lo)
    max_evals = draw(st.integers(1, 400))
    return f, x0, lo, hi, steps, max_evals


@PROPERTY
@given(problems())
def test_powell_never_worse_than_start_and_inside_bounds(problem):
    f, x0, lo, hi, steps, max_evals = problem
    rec = Recorder(f)
    res = powell(rec, x0, lo, hi, steps, max_evals=max_evals)
    f0 = float(f(x0[None])[0])
    assert res.fun <= f0
    assert float(f(res.x[None])[0]) == res.fun  # the value reported is the value at x
    assert np.all(res.x >= lo) and np.all(res.x <= hi)
    pts = rec.all_points
    assert np.all(pts >= lo - ULP_SLACK) and np.all(pts <= hi + ULP_SLACK), "evaluated outside the bounds"
    assert res.nfev == len(pts)
    # the budget: checked before every batch, so at most one batch (<= len(BRACKET) points) over
    assert res.nfev <= max_evals + len(BRACKET) - 1
    assert res.status in (0, 1)


@PROPERTY
@given(problems())
def test_line_search_never_increases(problem):
    f, x0, lo, hi, steps, _ = problem
    counter = _Counter(f, 10_000)
    fx = float(counter(x0[None])[0])
    d = steps * np.sign(np.random.default_rng(len(x0)).normal(size=len(x0)))
    t, ft = line_search(counter, x0, fx, d, lo, hi, tol=0.01)
    assert ft <= fx
    if ft == fx:
        assert t == 0.0  # ties keep the start: no drift on plateaus
    assert float(f((x0 + t * d)[None])[0]) == ft


@pytest.mark.parametrize("n", [2, 4, 6, 9])
def test_powell_finds_the_minimum_of_a_convex_quadratic(n):
    rng = np.random.default_rng(n)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    H = Q @ np.diag(np.geomspace(1.0, 10.0, n)) @ Q.T  # rotated: the axes are not the eigenvectors
    c = rng.uniform(-0.5, 0.5, n)

    def f(X):
        D = X - c
        return np.einsum("bi,ij,bj->b", D, H, D)

    x0 = rng.uniform(-1.0, 1.0, n)
    res = powell(f, x0, np.full(n, -2.0), np.full(n, 2.0), np.full(n, 0.3), xtol=1e-3, ftol=1e-10,
                 max_evals=5000, max_iter=50)
    # measured: max |x - c| 3e-6 .. 3e-4 for n = 2..9 in 111..3400 evaluations
    assert np.abs(res.x - c).max() < 2e-3, res
    assert res.fun < 1e-5
    assert res.status == 0


def test_powell_stops_at_the_bounds_of_a_quadratic_outside_the_box():
    d = np.array([1.0, 3.0, 5.0, 10.0])
    c = np.array([3.0, -3.0, 0.2, -0.1])
    res = powell(lambda X: np.sum(d * (X - c) ** 2, axis=1), np.zeros(4), -np.ones(4), np.ones(4),
                 np.full(4, 0.3), xtol=1e-3, ftol=1e-10, max_evals=3000)
    np.testing.assert_allclose(res.x, np.clip(c, -1, 1), atol=1e-3)


def test_powell_with_default_tolerances_is_close_on_a_separable_quadratic():
    c = np.array([0.3, -0.4, 0.1])
    res = powell(lambda X: np.sum((X - c) ** 2, axis=1), np.zeros(3), -np.ones(3), np.ones(3), np.full(3, 0.2))
    assert np.abs(res.x - c).max() < 0.02  # xtol 0.02 of a 0.2 step
    assert res.nfev <= 400


def test_powell_stays_put_on_a_plateau():
    res = powell(lambda X: np.zeros(len(X)), np.array([0.3, -0.2]), -np.ones(2), np.ones(2), np.full(2, 0.5))
    np.testing.assert_array_equal(res.x, [0.3, -0.2])
    assert res.fun == 0.0


def test_powell_clips_a_start_outside_the_box():
    rec = Recorder(lambda X: np.sum(X ** 2, axis=1))
    res = powell(rec, np.array([5.0, -5.0]), np.array([1.0, -3.0]), np.array([2.0, -2.0]), np.full(2, 0.3))
    np.testing.assert_allclose(res.x, [1.0, -2.0], atol=0.02)
    assert np.all(rec.all_points[:, 0] >= 1.0) and np.all(rec.all_points[:, 1] <= -2.0)


def test_powell_is_deterministic():
    rng = np.random.default_rng(3)
    W = rng.normal(size=(5, 5))

    def f(X):
        return np.floor(100 * np.sum((X @ W) ** 2, axis=1)) + np.floor(10 * np.sin(5 * X).sum(axis=1))

    a = powell(f, np.full(5, 0.4), -np.ones(5), np.ones(5), np.full(5, 0.2))
    b = powell(f, np.full(5, 0.4), -np.ones(5), np.ones(5), np.full(5, 0.2))
    np.testing.assert_array_equal(a.x, b.x)
    assert (a.fun, a.nfev, a.nit) == (b.fun, b.nfev, b.nit)


def test_powell_evaluates_only_inside_the_bounds():
    rng = np.random.default_rng(1)
    outside = 0
    for _ in range(60):
        n = int(rng.integers(1, 6))
        lo = rng.uniform(-2.0, 0.0, n)
        hi = lo + rng.uniform(0.05, 3.0, n)
        c = rng.uniform(lo - 1.0, hi + 1.0)
        rec = Recorder(lambda X: np.floor(100 * np.sum((X - c) ** 2, axis=1)))
        powell(rec, rng.uniform(lo, hi), lo, hi, rng.uniform(0.01, 1.0, n) * (hi - lo))
        pts = rec.all_points
        outside += int(np.any(pts < lo) or np.any(pts > hi))
    assert outside == 0


@pytest.mark.parametrize("xtol", [0.0, -0.01, float("nan")])
def test_powell_refuses_a_line_search_resolution_that_is_not_positive(xtol):
    """The line searches refine until their spacing is below xtol: 0 or less would never stop
    refining short of the budget (and the compiled twin sizes its probes' arrays by it)."""
    with pytest.raises(ValueError, match="xtol must be positive"):
        powell(lambda X: np.sum(X ** 2, axis=1), np.ones(2), -np.ones(2), np.ones(2), np.full(2, 0.1), xtol=xtol)


def valley(X: np.ndarray) -> np.ndarray:
    """A narrow valley along no parameter, in whole units as pixel counts are: x0 and x1 must
    move together (their sum is cheap, their difference dear), the other parameters to 0."""
    X = np.atleast_2d(X)
    along, across = (X[:, 0] + X[:, 1]) / np.sqrt(2.0), (X[:, 0] - X[:, 1]) / np.sqrt(2.0)
    return np.floor(100.0 * ((along - 1.0) ** 2 + 400.0 * across ** 2 + np.sum(X[:, 2:] ** 2, axis=1)))


@pytest.mark.timeout(60)
def test_cma_es_goes_down_a_valley_that_runs_across_the_parameters():
    """From a point where moving any one parameter gains almost nothing (the valley's floor
    runs diagonally), the strategy learns the diagonal and reaches the minimum at x0 = x1 = 0.71."""
    n = 8
    lo, hi = np.full(n, -3.0), np.full(n, 3.0)
    start = np.zeros(n)
    res = cma_es(valley, start, np.full(n, 0.05), lo, hi, 6000, np.random.default_rng(0))
    assert valley(start)[0] == 100.0 and res.fun <= 2.0
    np.testing.assert_allclose(res.x[:2], np.sqrt(0.5), atol=0.05)
    assert res.nfev <= 6000 and res.status == 1 and res.nit == (res.nfev - 1) // CMA_POPULATION


def test_cma_es_is_seeded_keeps_the_box_and_never_returns_worse_than_its_start():
    n = 5
    lo, hi = np.full(n, -0.2), np.full(n, 0.5)
    start = np.full(n, 0.1)
    recorder = Recorder(valley)
    one = cma_es(recorder, start, np.full(n, 0.3), lo, hi, 800, np.random.default_rng(7))
    again = cma_es(valley, start, np.full(n, 0.3), lo, hi, 800, np.random.default_rng(7))
    other = cma_es(valley, start, np.full(n, 0.3), lo, hi, 800, np.random.default_rng(8))
    assert np.array_equal(one.x, again.x) and one.fun == again.fun and not np.array_equal(one.x, other.x)
    points = recorder.all_points
    assert len(points) == one.nfev <= 800 and np.all(points >= lo) and np.all(points <= hi)
    assert one.fun == valley(one.x)[0] == points_min(valley, points) <= valley(start)[0]
    # a start at the minimum is returned as it is
    floor = np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0])
    at_floor = cma_es(valley, floor, np.full(3, 0.3), np.full(3, -1.0), np.full(3, 1.0), 400,
                      np.random.default_rng(0))
    assert np.array_equal(at_floor.x, floor) and at_floor.fun == 0.0


def points_min(f, points: np.ndarray) -> float:
    return float(f(points).min())


@pytest.mark.timeout(60)
def test_cma_es_settles_on_a_minimum_beyond_the_box():
    """The valley's floor lies past the box's upper faces, so the best samples are moved onto
    them generation after generation: the step-size path follows the mean's clipped steps, not
    the draws' (which kept pointing out of the box and grew the spread without bound: 10 where
    8 is reached on the faces, a spread of 1e42)."""
    n = 5
    for seed in (0, 7):
        res = cma_es(valley, np.full(n, 0.1), np.full(n, 0.3), np.full(n, -0.2), np.full(n, 0.5), 6000,
                     np.random.default_rng(seed))
        assert res.fun == 8.0 and np.all(res.x[:2] > 0.49)
