"""Hierarchical pose fitting (Theobalt et al. 2003, section 3), shared by server and clients.

One fit (``fit_rounds``) from a start pose:
 1. torso (root + spine) by Powell's method on the half-resolution energy;
 2. the four limbs, each by a grid search then Powell in 128x128 windows, followed by its
    hand or foot in 64x64 windows; and the head in 64x64 windows. Every limb and the head
    start from the same pose (Jacobi), so they are independent: a client can solve any of
    them and the result does not depend on who solved it or in which order;
 3. repeat until the full energy stops improving or an iteration cap.

A chain's solve (``solve_chain``), a limb's search over its whole range (``search_limb``), a
hop of basin hopping (``hop``) and an evolution strategy's run (``evolve``) are the units of
work below a fit; which starts are fitted, and
in what order, is ``common.search``.

One module of about 610 lines: the fit's chain solves, limb searches, hops and evolutions share
the optimizers and options above.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from itertools import product
from typing import Callable

import numpy as np

from common.body import (
    CHAINS, LIMB_CHAINS, LIMB_PARTS, P, PARAM_LIMITS, BodyModel, clip_to_limits, forward_kinematics,
    hold_limbs_in_world,
)
from common import optimize
from common.energy import ARM_WINDOW, MIN_DEPTH_M, SMALL_WINDOW, CpuEnergy, whole_energy
from common.frame import HALF, FrameData
from common.objective import HeldLimbs, SpinePrior, with_spine_prior
from common.powell_cpu import powell_cpu

ENERGY_BACKENDS = ("cpu", "gl", "coarse-to-fine", "volume")


# FitOptions fields that shape the search's schedules and the run (which starts, how many passes),
# never a single job: the server reads them, a SOLVE does not carry them
RUN_SETTINGS = ("turn_hypotheses", "turn_step_rad", "track_moved_on", "polish_iterations", "refine_passes",
                "refine_search", "refine_hops", "refine_chunk_frames")


@dataclass(frozen=True)
class FitOptions:
    """Fitting settings; every field is a plain scalar so it can travel in a SOLVE message."""

    energy: str = "cpu"              # cpu | gl | coarse-to-fine
    max_iterations: int = 2          # torso -> limbs -> extremities rounds per frame
    min_improvement: float = 0.002   # stop when the full energy improves by less (fraction)
    grid_steps: int = 3              # grid points per limb parameter (odd)
    grid_range_rad: float = 0.25     # +- half-width of the limb grid, radians
    torso_step_m: float = 0.03       # Powell's initial step, root translation
    torso_step_rad: float = 0.08     # Powell's initial step, rotations
    limb_step_rad: float = 0.15
    extremity_step_rad: float = 0.2
    xtol: float = 0.03               # line-search resolution, in units of a direction's step
    ftol: float = 1e-4               # Powell's relative energy tolerance
    max_evals_torso: int = 400
    max_evals_limb: int = 250
    max_evals_extremity: int = 60
    prerender: bool = True
    torso_half_resolution: bool = True  # the paper's 160x120 torso energy
    spine_twist_prior: float = 1500.0   # full-resolution pixels per rad^2 of spine twist
    limb_window_px: int = ARM_WINDOW    # the paper's 128x128 limb windows
    hinge_grid_full_range: bool = False  # grid elbows/knees over their whole range (rough starts)
    torso_grid_steps: int = 1           # >1: grid over pelvis heading x spine twist before Powell (off: measured worse on the walk)
    torso_grid_range_rad: float = 0.2
    redetect_limbs: bool = True         # search limbs over their whole range (lost limbs)
    redetect_turn: str = "final"        # which limbs when: see REDETECT_TURNS
    turn_hypotheses: int = 2            # also fit from the start turned by -+1..n turn steps about the vertical
    turn_step_rad: float = 0.15
    track_moved_on: bool = False        # tracking also fits from the previous pose moved on as it moved (fast preset)
    polish_iterations: int = 2          # further rounds for the best hypothesis, while the energy still falls
    refine_passes: int = 1              # after tracking, passes over all frames (backward, forward, ...): see server.session
    refine_search: bool = False         # the first pass also refits each frame from each limb's other basins (slow)
    refine_hops: int = 0                # the first pass also refits each frame from this many random chain moves (slow)
    refine_chunk_frames: int = 0        # >0: a pass refines chunks of about this many frames side by side (server.session)

    def __post_init__(self):
        if self.energy not in ENERGY_BACKENDS:
            raise ValueError(f"energy must be one of {ENERGY_BACKENDS}, got {self.energy!r}")
        if self.grid_steps < 1 or self.grid_steps % 2 == 0:
            raise ValueError("grid_steps must be odd and >= 1")
        if self.redetect_turn not in REDETECT_TURNS:
            raise ValueError(f"redetect_turn must be one of {REDETECT_TURNS}, got {self.redetect_turn!r}")
        if not 1 <= self.max_iterations < REDETECT_ROUND:
            raise ValueError(f"max_iterations must be 1..{REDETECT_ROUND - 1}, got {self.max_iterations}")
        if self.polish_iterations < 0:
            raise ValueError(f"polish_iterations must be >= 0, got {self.polish_iterations}")
        if self.refine_passes < 0:
            raise ValueError(f"refine_passes must be >= 0, got {self.refine_passes}")
        if self.refine_search and not self.refine_passes:
            raise ValueError("refine_search needs refine_passes >= 1: the search runs in the first pass")
        if self.refine_hops < 0:
            raise ValueError(f"refine_hops must be >= 0, got {self.refine_hops}")
        if self.refine_chunk_frames < 0:
            raise ValueError(f"refine_chunk_frames must be >= 0, got {self.refine_chunk_frames}")
        if self.refine_hops and not self.refine_passes:
            raise ValueError("refine_hops needs refine_passes >= 1: the hops run in the first pass")
        if not self.spine_twist_prior >= 0:  # NaN too
            raise ValueError(f"spine_twist_prior must be >= 0, got {self.spine_twist_prior}")
        if self.turn_hypotheses < 0:
            raise ValueError(f"turn_hypotheses must be >= 0, got {self.turn_hypotheses}")
        if not 0.0 < self.turn_step_rad * max(self.turn_hypotheses, 1) < np.pi:
            raise ValueError(f"turn_step_rad must be > 0 and turn_hypotheses * turn_step_rad < pi, "
                             f"got {self.turn_step_rad}")

    def to_wire(self) -> dict:
        """Every setting (run.json, summary.json)."""
        return dict(self.__dict__)

    def solve_settings(self) -> dict:
        """The settings a job is solved with, what a SOLVE carries: all but the schedule's
        (RUN_SETTINGS), which only the server's search reads."""
        return {k: v for k, v in self.__dict__.items() if k not in RUN_SETTINGS}

    @classmethod
    def from_wire(cls, options: dict) -> "FitOptions":
        unknown = set(options) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown fit options: {sorted(unknown)}")
        return cls(**options)


@dataclass(frozen=True)
class ChainResult:
    """What solving one chain gives back (the RESULT message carries the same fields)."""

    chain: str
    params: np.ndarray        # (35,) the full pose with this chain's parameters updated
    energy_before: int
    energy: int
    evaluations: int
    iterations: int
    wall_seconds: float
    cpu_seconds: float


@dataclass(frozen=True)
class FrameResult:
    """A fit of one frame: its pose, full-resolution XOR energy, and what it cost."""

    params: np.ndarray        # (35,)
    energy: int
    iterations: int
    evaluations: int          # of every solve spent on it, dropped fits too
    chains: tuple = ()        # ChainResult of every solve this process saw, in order
    variant: str = "track"    # the fit options it was fitted with (``common.search.VARIANTS``)
    start: np.ndarray | None = field(default=None, compare=False)  # (35,) the pose it was fitted from, where known


def _limb_centre_segments(chain: str) -> tuple:
    segs = CHAINS[chain].segments
    return segs[:2]  # upper arm + forearm, thigh + shin


# -------------------------------------------------------------------------- optimizers

def powell(energy, x0: np.ndarray, indices, steps: np.ndarray, options: FitOptions, max_evals: int,
           complete: "HeldLimbs | None" = None):
    """Powell's direction set over ``indices`` of the 35 parameters, others held at x0.

    complete: optional ``HeldLimbs`` applied to every candidate (the torso). On the ``cpu``
    energy (with or without the spine prior) the compiled twin ``powell_cpu`` runs, the same
    steps at a fraction of the overhead; on the others, ``optimize.powell``.
    Returns (params (35,), energy, evaluations, iterations).
    """
    idx = np.asarray(indices)
    base = np.array(x0, dtype=np.float64)

    def candidates(Z: np.ndarray) -> np.ndarray:
        cand = np.repeat(base[None], len(Z), axis=0)
        cand[:, idx] = Z
        return complete(cand) if complete else cand

    inner, prior = (energy.energy, energy.weight) if isinstance(energy, SpinePrior) else (energy, 0.0)
    if isinstance(inner, CpuEnergy):
        x, fun, nfev, nit = powell_cpu(inner, base, idx, steps, options.xtol, options.ftol, max_evals,
                                       hold_rotations=complete.reference_rotations if complete else None,
                                       prior_weight=prior, prior_index=P["spine_z"])
        return candidates(x[None])[0], fun, nfev, nit
    res = optimize.powell(lambda Z: energy(candidates(Z)), base[idx], PARAM_LIMITS[idx, 0], PARAM_LIMITS[idx, 1],
                          steps, xtol=options.xtol, ftol=options.ftol, max_evals=max_evals)
    return candidates(res.x[None])[0], res.fun, res.nfev, res.nit


def grid_search(energy, x0: np.ndarray, indices, steps: int, half_range: float, complete=None,
                absolute=()):
    """Batched grid of ``steps`` points per parameter over +-half_range around x0 (the paper's
    limb grid search); parameters in ``absolute`` span their whole joint range instead.
    Returns (best params (35,), its energy, evaluations)."""
    idx = np.asarray(indices)
    x0 = np.asarray(x0, dtype=np.float64)
    axes = [np.linspace(*PARAM_LIMITS[i], steps) if i in absolute else x0[i] + np.linspace(-half_range, half_range, steps)
            for i in idx]
    cand = np.repeat(x0[None], steps ** len(idx), axis=0)
    cand[:, idx] = np.clip(np.array(list(product(*axes))), PARAM_LIMITS[idx, 0], PARAM_LIMITS[idx, 1])
    if complete:
        cand = complete(cand)
    energies = energy(cand)
    best = int(np.argmin(energies))  # ties -> the first, which is deterministic
    return cand[best], float(energies[best]), len(cand)


# ------------------------------------------------------------------------ chain solves

def _clock():
    """(wall, CPU) seconds; the CPU time is this thread's, so jobs run side by side on threads
    each count their own."""
    return time.perf_counter(), time.thread_time()


def _stage_backends(options: FitOptions) -> tuple:
    return ("cpu", "gl") if options.energy == "coarse-to-fine" else (options.energy,)


def solve_chain(model: BodyModel, frame: FrameData, chain: str, params: np.ndarray,
                options: FitOptions, iteration: int = 0) -> ChainResult:
    """Optimize one chain's parameters with every other parameter held at ``params``."""
    wall0, cpu0 = _clock()
    x = np.array(params, dtype=np.float64)
    evals = iters = 0
    before = None
    energy_value = None
    for backend in _stage_backends(options):
        if chain == "torso":
            whole = (frame.whole_image_energy(options.torso_half_resolution) if backend == "cpu"
                     else frame.energy(backend, frame.full_setup(x, half=options.torso_half_resolution)))
            # the prior is in full-resolution pixels: a half-resolution energy counts a quarter as many
            scale = HALF ** 2 if options.torso_half_resolution else 1.0
            energy = with_spine_prior(whole, scale * options.spine_twist_prior if backend != "volume" else 0.0)
            before = before if before is not None else energy(x)[0]
            idx = CHAINS["torso"].params
            steps = np.array([options.torso_step_m] * 3 + [options.torso_step_rad] * 6)
            hold = HeldLimbs(model, forward_kinematics(model, x).rotations[0])
            n = 0
            if options.torso_grid_steps > 1:
                # the pelvis heading against the spine twist is the torso's flattest valley:
                # search it on a grid first, as the paper does for the limbs
                x, _, n = grid_search(energy, x, (P["root_heading"], P["spine_z"]), options.torso_grid_steps,
                                      options.torso_grid_range_rad, complete=hold)
            x, energy_value, n2, it = powell(energy, x, idx, steps, options, options.max_evals_torso, complete=hold)
            n += n2
        elif chain == "head":
            setup = frame.window_setup(x, CHAINS["head"].segments, SMALL_WINDOW, options.prerender)
            energy = frame.energy(backend, setup)
            before = before if before is not None else energy(x)[0]
            steps = np.full(2, options.extremity_step_rad)
            x, energy_value, n, it = powell(energy, x, CHAINS["head"].params, steps, options,
                                            options.max_evals_extremity)
        elif chain in LIMB_CHAINS and iteration == REDETECT_ROUND:
            x, before, energy_value, n = redetect_limb(model, frame, chain, x, options)
            it = 0
        elif chain in LIMB_CHAINS:
            proximal, distal, extremity = LIMB_PARTS[chain]
            setup = frame.window_setup(x, _limb_centre_segments(chain), options.limb_window_px, options.prerender)
            setup = replace(setup, moving=CHAINS[chain].segments)
            energy = frame.energy(backend, setup)
            before = before if before is not None else energy(x)[0]
            n = 0
            if backend == _stage_backends(options)[0] and options.grid_steps > 1:
                hinge = (proximal[3],) if options.hinge_grid_full_range else ()
                x, _, n = grid_search(energy, x, proximal, options.grid_steps, options.grid_range_rad, absolute=hinge)
            steps = np.full(len(proximal), options.limb_step_rad)
            x, _, n2, it = powell(energy, x, proximal, steps, options, options.max_evals_limb)
            n += n2
            ext_setup = frame.window_setup(x, extremity, SMALL_WINDOW, options.prerender)
            ext_energy = frame.energy(backend, ext_setup)
            x, _, n3, it3 = powell(ext_energy, x, distal, np.full(len(distal), options.extremity_step_rad),
                                   options, options.max_evals_extremity)
            n += n3
            it += it3
            energy_value = float(energy(x)[0])
            n += 1
            if (options.redetect_limbs and backend == _stage_backends(options)[0]
                    and redetects(options.redetect_turn, chain, iteration)):
                x, _, _, n4 = redetect_limb(model, frame, chain, x, options)
                n += n4
                energy_value = float(energy(x)[0])
        else:
            raise ValueError(f"unknown chain {chain!r}")
        evals += n + 1
        iters += it
    wall1, cpu1 = _clock()
    return ChainResult(chain, x, whole_energy(before), whole_energy(energy_value), evals, iters, wall1 - wall0,
                       cpu1 - cpu0)


# Which limbs are re-detected when (FitOptions.redetect_turn):
#  "final": tracking: once the frame's hypotheses are fitted, every limb against the best of
#           them (round REDETECT_ROUND, on the clients); where one is found that clearly lowers
#           the energy, the frame is fitted again from there;
#  "every": every limb in the first round, against a tracked pose: a frame whose energy jumped
#           (a limb lost in a fast move), searched again;
#  "round": one per round (round mod 4), at least 4 rounds: a first frame, one limb at a time;
#  "all":   every limb in the first round: a first frame, each limb against the others' start.
# Limbs solved side by side (Jacobi) against each other's old pose can all be re-detected into
# the same unexplained pixels ("all" loses both arms that way now and then); one at a time
# ("round") cannot, but finds less; a first frame tries both and keeps the lower energy.
# Against a tracked pose ("final", "every") a re-detected limb must clearly lower the energy
# and is refined from fewer grid points; a first frame has no tracked limb to protect.
REDETECT_TURNS = ("final", "every", "round", "all")
TRACKING_TURNS = ("final", "every")
REDETECT_ROUND = 1000  # the round number of the "final" re-detection: past any fitting round


def redetects(turn: str, chain: str, iteration: int) -> bool:
    """Whether ``chain`` is re-detected within fitting round ``iteration`` ("final" re-detects
    in its own round, after the fit)."""
    if turn == "final":
        return False
    if turn == "round":
        return iteration % len(LIMB_CHAINS) == LIMB_CHAINS.index(chain)
    return iteration == 0


# The re-detection grid: its points per shoulder/hip parameter and per elbow/knee. An
# evaluation of one limb over the whole images costs microseconds, so the grid is dense: a
# 5x5x5x3 grid missed a forearm lying in front of the trunk (its cells are 1.3 rad wide).
REDETECT_STEPS = 9
REDETECT_HINGE_STEPS = 4
REDETECT_MARGIN = 0.15    # the grid keeps this fraction of each joint range away from its limits
REDETECT_STARTS = 2       # grid points refined by Powell, one per basin (see distinct_rows)
# ... on a first frame's wide fits, where no limb is tracked yet: one per basin, 3 basins. The best
# 8 grid points crowd one or two basins; with 3 basins the 34 first frames of `mocap bench init
# --first-frame-only` took fewer evaluations, all within 50 mm (docs/accuracy.md)
REDETECT_STARTS_FIRST_FRAME = 3
BASIN_STARTS = 8          # grid points (one per basin) a limb's search for its other basins refines
REDETECT_STEP_RAD = 0.3   # Powell's first step from a grid point, rad
REDETECT_GAIN = 0.01      # the alternative must lower the whole-image energy by this fraction
BASIN_SEPARATION_M = 0.15  # limb poses whose elbow/knee or wrist/ankle lie this far apart: two basins
BASIN_SCAN_ROWS = 64       # grid points, lowest energy first, searched for basins before all of them


def redetect_limb(model: BodyModel, frame: FrameData, chain: str, x: np.ndarray, options: FitOptions):
    """Search one limb over its whole range on the whole images, and keep what explains the
    images better than the tracked limb. A limb that moved faster than the local search, or
    flipped into the mirror pose of an elbow or knee, is lost for good otherwise.
    Returns (params (35,), whole-image energy at x, at the result, evaluations)."""
    tracking = options.redetect_turn in TRACKING_TURNS
    found, current, n = search_limb(model, frame, chain, x, options,
                                    REDETECT_STARTS if tracking else REDETECT_STARTS_FIRST_FRAME)
    # a clear gain only: an alternative a few pixels better is as often a mirror pose of the limb
    # (on a first frame the tracked limb is no better than any other: no threshold)
    best_x, best_e = x, current
    threshold = current * (1.0 - (REDETECT_GAIN if tracking else 0.0))
    for e, y in found:
        if e < min(best_e, threshold):
            best_x, best_e = y, e
    return best_x, current, best_e, n


# A forearm's width in the half-resolution images (the median camera's), pixels, from which a
# limb's search ranks its grid there: the 320x240 studio's walk has 2.2 (1.6-4.3), the real
# seated take's 644x484 cameras 3.5-5.3, a 160x120 studio 1.2, where the half images lose the
# forearm the grid is ranked by (a folded forearm's true basin 99 mm off instead of found)
HALF_RESOLUTION_MIN_FOREARM_PX = 1.5


def half_resolution_resolves_limbs(model: BodyModel, frame: FrameData, x: np.ndarray) -> bool:
    """Whether a forearm at the pelvis of x (35,) is HALF_RESOLUTION_MIN_FOREARM_PX wide or more
    in the median camera's half-resolution image."""
    width_m = 2.0 * float(model.ellipsoid_radii[CHAINS["left_arm"].segments[1]].min())
    widths = [HALF * cam.K[0, 0] * width_m / max(float(cam.depth(x[:3])), MIN_DEPTH_M) for cam in frame.studio]
    return float(np.median(widths)) >= HALF_RESOLUTION_MIN_FOREARM_PX


def search_limb(model: BodyModel, frame: FrameData, chain: str, x: np.ndarray, options: FitOptions,
                starts: int):
    """One limb's whole range on the whole images, the other parts held at x: a grid, then
    Powell from the best point of each of the ``starts`` best basins (a basin's points crowd
    the top of the grid otherwise).
    Returns ([(energy, params (35,)) per start, in grid order], the energy at x, evaluations)."""
    proximal, distal, _ = LIMB_PARTS[chain]
    backend = "cpu" if options.energy == "coarse-to-fine" else options.energy
    energy = frame.energy(backend, replace(frame.full_setup(x), moving=CHAINS[chain].segments, prerender=True))
    # the grid only ranks starting points for Powell: at half resolution, where a forearm is still
    # wide enough there to be seen, it ranks them as well for a fraction of the cost (the grid
    # was a fifth of a fit's time; docs/accuracy.md)
    coarse = (frame.energy(backend, replace(frame.full_setup(x, half=True), moving=CHAINS[chain].segments,
                                            prerender=True))
              if half_resolution_resolves_limbs(model, frame, x) else energy)
    lo, hi = PARAM_LIMITS[list(proximal)].T
    pad = REDETECT_MARGIN * (hi - lo)
    axes = [np.linspace(lo[i] + pad[i], hi[i] - pad[i], REDETECT_STEPS if i < 3 else REDETECT_HINGE_STEPS)
            for i in range(4)]
    cand = np.repeat(x[None], np.prod([len(a) for a in axes]), axis=0)
    cand[:, list(proximal)] = np.array(list(product(*axes)))
    order = np.argsort(coarse(cand), kind="stable")
    # the basins' best points are almost always near the top: joints of the best few first
    kept = distinct_rows(limb_joints(model, chain, cand[order[:BASIN_SCAN_ROWS]]), starts)
    if len(kept) < starts:
        kept = distinct_rows(limb_joints(model, chain, cand[order]), starts)
    order = order[kept]
    n = len(cand) + 1
    found = []
    for k in order[:starts]:
        y, _, n2, _ = powell(energy, cand[k], proximal, np.full(len(proximal), REDETECT_STEP_RAD), options,
                             options.max_evals_limb)
        y, e, n3, _ = powell(energy, y, distal, np.full(len(distal), options.extremity_step_rad), options,
                             options.max_evals_extremity)
        n += n2 + n3
        found.append((e, y))
    return found, float(energy(x)[0]), n


def limb_joints(model: BodyModel, chain: str, params: np.ndarray) -> np.ndarray:
    """(B, 2, 3) the limb's middle and end joints (elbow and wrist, knee and ankle) for (B, 35) params."""
    return forward_kinematics(model, np.atleast_2d(params)).joints[:, list(CHAINS[chain].segments[1:])]


def distinct_rows(joints: np.ndarray, count: int, taken: np.ndarray | None = None) -> list[int]:
    """Indices of up to ``count`` rows of ``joints`` (B, 2, 3), in order, each with a joint
    BASIN_SEPARATION_M or more from the same joint of every row kept before it and of every
    row of ``taken`` (T, 2, 3)."""
    kept = list(taken) if taken is not None else []
    out = []
    for i, j in enumerate(joints):
        if all(np.linalg.norm(j - k, axis=1).max() >= BASIN_SEPARATION_M for k in kept):
            kept.append(j)
            out.append(i)
            if len(out) == count:
                break
    return out



def full_energy(model: BodyModel, frame: FrameData, params: np.ndarray) -> int:
    """Whole-body XOR energy at full resolution (the convergence test and the reported energy)."""
    return whole_energy(frame.whole_image_energy()(params)[0])


# dispatch(jobs, params, iteration, options=None) starts ``jobs`` (limb chains, hops or whole
# fits, ``common.search.solve_job``) and returns a function that waits for and returns their
# ChainResults in the order of ``jobs``. ``params`` is one (35,) start for all jobs or one per
# job; ``options`` the FitOptions for all jobs, one per job, or None for the frame's own. The
# server solves the head in between, so a cluster's clients and the server work at once.
Dispatch = Callable[..., Callable[[], list]]



# Basin hopping (``hop_fit``): each hop moves one chain by a random step, then fits the body.
HOP_CHAINS = ("torso", *LIMB_CHAINS)
HOP_SIGMA_RAD = 0.2     # standard deviation of a moved chain's angles, rad
HOP_SIGMA_M = 0.04      # ... of the root position, m
HOP_STEP_RAD = 0.1      # Powell's first steps over all 35 parameters: angles, rad
HOP_STEP_M = 0.03       # ... root position, m
HOP_MAX_EVALS = 3000    # per hop: a few sweeps over 35 directions
# The jobs of one round of hops, run side by side (the protocol's HOP_JOB_NAMES): job k is the
# round's k-th hop. More would mostly be hops dropped after a lower one beside them.
HOP_JOBS = ("hop0", "hop1", "hop2", "hop3")


def whole_body_objective(frame: FrameData, options: FitOptions):
    """The hops' and evolutions' objective: the whole-image ``cpu`` energy plus the spine prior
    (the server's check of their results scores the same)."""
    return with_spine_prior(frame.whole_image_energy(), options.spine_twist_prior)


def hop(model: BodyModel, frame: FrameData, params: np.ndarray, options: FitOptions, index: int,
        seed: int, job: str) -> ChainResult:
    """Hop number ``index`` from ``params`` (35,): chain HOP_CHAINS[index % 5] is moved by a
    random step drawn from (``seed``, ``index``) alone (the torso with the limbs held in their
    world orientation), and the whole body is fitted from there by Powell over all 35
    parameters at once, on the hops' objective: the whole-image ``cpu`` energy plus the spine
    prior. Returns it as ``job``'s ChainResult whose energies (before, after) are that
    objective, rounded here to whole pixels so that a cluster compares the same numbers."""
    wall0, cpu0 = _clock()
    objective = whole_body_objective(frame, options)
    every = np.arange(len(params))
    steps = np.where(every < 3, HOP_STEP_M, HOP_STEP_RAD)
    rng = np.random.default_rng((seed, index))
    chain = HOP_CHAINS[index % len(HOP_CHAINS)]
    idx = np.array(CHAINS[chain].params)
    start = np.array(params, dtype=np.float64)
    start[idx] += rng.normal(0.0, 1.0, len(idx)) * np.where(idx < 3, HOP_SIGMA_M, HOP_SIGMA_RAD)
    if chain == "torso":  # the limbs keep their world orientation, as in the torso's solves
        start = hold_limbs_in_world(model, start, params)[0]
    x, _, n, _ = powell(objective, clip_to_limits(start), every, steps, options, HOP_MAX_EVALS)
    before, after = (whole_energy(objective(p[None])[0]) for p in (np.asarray(params, dtype=np.float64), x))
    wall1, cpu1 = _clock()
    return ChainResult(job, x, before, after, n + 2, 1, wall1 - wall0, cpu1 - cpu0)


# An evolution (``evolve``): the whole body moved by an evolution strategy over all 35
# parameters at once, from a fit. The first samples' spread: angles, rad; the root position, m
EVOLVE_SIGMA_RAD = 0.05
EVOLVE_SIGMA_M = 0.02
# evaluations per evolution. The walk's 100 refined frames finished (`python tools/finish_budget.py
# R SEQ --evolutions 1,2 --evaluations 4000,6000`, from 7.12 mm mean error): one evolution of
# 4,000 came to 6.87 mm, of 6,000 to 6.64; two of 4,000 to 6.74, of 6,000 to 6.43: the
# covariance needs a few hundred generations to learn the body's valleys
EVOLVE_EVALS = 6000
# The jobs of one frame's evolutions, run side by side (the protocol's EVOLVE_JOB_NAMES): job k is
# evolution number ``iteration`` + k, seeded by the frame number and k
EVOLVE_JOBS = ("evolve0", "evolve1", "evolve2", "evolve3")


def evolve(model: BodyModel, frame: FrameData, params: np.ndarray, options: FitOptions, index: int,
           seed: int, job: str, evaluations: int = EVOLVE_EVALS) -> ChainResult:
    """Evolution number ``index`` from ``params`` (35,): ``optimize.cma_es`` over all 35
    parameters (``evaluations``, first spread EVOLVE_SIGMA_RAD / EVOLVE_SIGMA_M, the
    samples drawn from (``seed``, ``index``) alone) on the hops' objective, the whole-image
    ``cpu`` energy plus the spine prior. Returns it as ``job``'s ChainResult whose energies
    (before, after) are that objective rounded to whole pixels, as a hop's are.

    Why: a fit that the chains' solves and Powell left can still sit where the energy falls
    along a direction that moves many parameters together (the walk's refined fits: two
    evolutions a frame and a polish lowered the energy of 53 of 100 frames, and the mean error
    from 7.12 to 6.43 mm); an evolution strategy learns such directions from its samples."""
    wall0, cpu0 = _clock()
    objective = whole_body_objective(frame, options)
    start = np.asarray(params, dtype=np.float64)
    sigmas = np.where(np.arange(len(start)) < 3, EVOLVE_SIGMA_M, EVOLVE_SIGMA_RAD)
    res = optimize.cma_es(objective, start, sigmas, PARAM_LIMITS[:, 0], PARAM_LIMITS[:, 1], evaluations,
                          np.random.default_rng((seed, index)))
    before, after = (whole_energy(objective(p[None])[0]) for p in (start, res.x))
    wall1, cpu1 = _clock()
    return ChainResult(job, res.x, before, after, res.nfev + 2, res.nit, wall1 - wall0, cpu1 - cpu0)


def hop_fit(params: np.ndarray, hops: int, options: FitOptions, dispatch: Dispatch,
            side_by_side: int = 1) -> FrameResult:
    """Basin hopping from ``params`` (35,): ``hops`` hops (``hop``), one after
    another, each from the best pose so far; a hop with a lower objective (XOR energy plus the
    spine prior, what each hop's Powell minimises) becomes the best.
    ``dispatch`` runs the hops with ``options``, ``side_by_side`` (1..len(HOP_JOBS)) at once,
    all from the same best: hops k..k+n-1 as jobs HOP_JOBS[:n] with iteration k. Where one of
    them is lower, the next round starts after it and the hops beyond it are dropped: they
    started from a pose that is no longer the best. So the result is that of the hops one
    after another, however many run side by side; a cluster gains where hops fail, as most
    do once the first few have found the valley. Returns the best (``params``
    where no hop was lower) with its objective as ``energy`` (callers that compare it with other
    fits take its ``full_energy``); its ``evaluations`` are those of the hops one after
    another, its ``chains`` every hop's ChainResult, dropped ones too.

    Why: the hierarchy moves one chain at a time, and a frame whose torso and a limb are off
    together sits in a valley that no single chain can go down. Basketball frame 85 (the clip's
    last, its left ankle 70 mm off): the energy falls all along the straight line from the fit
    to the truth, yet neither a chain's own search nor Powell over all 35 parameters from the
    fit moves down it; a hop from a moved leg does. A whole-image evaluation costs tens of
    microseconds, so a hop of a few thousand evaluations costs about 0.1 s."""
    if hops < 1:
        raise ValueError(f"hop_fit needs hops >= 1, got {hops}")
    if not 1 <= side_by_side <= len(HOP_JOBS):
        raise ValueError(f"side_by_side must be 1..{len(HOP_JOBS)}, got {side_by_side}")
    best, best_energy = np.array(params, dtype=np.float64), None
    tried, evaluations, done = [], 0, 0
    while done < hops:
        results = dispatch(list(HOP_JOBS[:min(side_by_side, hops - done)]), best, done, options)()
        tried += results
        if best_energy is None:
            best_energy = results[0].energy_before
        lower = next((k for k, r in enumerate(results) if r.energy < best_energy), None)
        if lower is not None:
            best, best_energy = results[lower].params, results[lower].energy
        kept = results if lower is None else results[:lower + 1]
        evaluations += sum(r.evaluations for r in kept)
        done += len(kept)
    return FrameResult(best, whole_energy(best_energy), hops, evaluations, tuple(tried))


def merge_chains(params: np.ndarray, results: list) -> np.ndarray:
    """Take each result's own chain parameters (results of independent Jacobi solves)."""
    out = np.array(params, dtype=np.float64)
    for r in sorted(results, key=lambda r: r.chain):
        idx = list(CHAINS[r.chain].params)
        out[idx] = r.params[idx]
    return out


def fit_converged(improved: float, energy: float, rounds: int, options: FitOptions) -> bool:
    """Whether a fit stops after ``rounds`` rounds, the last of which lowered the full energy by
    ``improved`` to ``energy``: it gained less than ``options.min_improvement`` (a fraction),
    and re-detecting one limb per round (``redetect_turn`` "round") gave every limb its round."""
    rounds_needed = len(LIMB_CHAINS) if options.redetect_limbs and options.redetect_turn == "round" else 1
    return improved < options.min_improvement * max(energy, 1) and rounds >= rounds_needed


def fit_rounds(model: BodyModel, frame: FrameData, start: np.ndarray, options: FitOptions,
               dispatch: Dispatch, first_round: int = 0) -> FrameResult:
    """One hierarchical fit from ``start`` (35,): rounds of torso, then the four limbs side by
    side (``dispatch``, against the torso's result: Jacobi) and the head, until
    ``fit_converged`` or ``options.max_iterations`` rounds. A round whose energy is higher is
    not taken. ``first_round``: the fit goes on from a fit stopped after that many rounds
    (``start`` its result), as that fit would have gone on; its ``iterations`` count them all."""
    x = np.array(start, dtype=np.float64)
    best = full_energy(model, frame, x)
    chains, evaluations, rounds = [], 0, first_round
    for it in range(first_round, options.max_iterations):
        torso = solve_chain(model, frame, "torso", x, options)
        # the limbs go out first so that clients work while the server fits the head
        collect_limbs = dispatch(list(LIMB_CHAINS), torso.params, it, options)
        head = solve_chain(model, frame, "head", torso.params, options)
        limbs = collect_limbs()
        x_new = merge_chains(torso.params, [*limbs, head])
        e_new = full_energy(model, frame, x_new)
        chains += [torso, *limbs, head]
        evaluations += torso.evaluations + head.evaluations + sum(r.evaluations for r in limbs)
        rounds = it + 1
        improved = best - e_new
        if e_new <= best:
            x, best = x_new, e_new
        if fit_converged(improved, best, rounds, options):
            break
    return FrameResult(x, best, rounds, evaluations, tuple(chains))
