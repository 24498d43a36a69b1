"""One search: propose start poses, fit each the same way, keep the lowest.

Every fit of a frame is a *schedule* of a few *stages*, declared as data (``TRACKING``,
``LIMBS_LOST``, ``SEARCH``, ``REFINE``, ...: the defaults of ``Schedules``, which a Config.toml's
``[fit.schedules]`` replaces schedule by schedule, ``common.schedule_tables``). A stage asks its
proposers (``PROPOSERS``) for start poses from the best fit so far (or from its ``beam`` lowest
fits), fits every start by the same hierarchical fit (``common.fitting.fit_rounds``) under the
stage's fit options (``VARIANTS``), and keeps the lowest score. It repeats while a round lowers the best score by its
``min_gain``, up to ``rounds``; a schedule stops where its evaluation budget is spent. A start
already fitted under the same options is not fitted again. New kinds of start are one proposer
each (``common.proposals`` holds the pose making).

The starts of one round are independent fits, so they are jobs (``FIT_JOBS``), handed out as
the limb chains are: a cluster's clients fit them side by side, and with no clients the server
fits them itself with the same code (``solve_job``), so the poses do not depend on who fitted
what. A round of a single start is fitted here, its limbs dispatched.

Schedules:
- ``TRACKING``: the previous frame's pose, turned either way about the vertical, tilted ahead
  and (``track_moved_on``) moved on as it moved; the best polished by more rounds; its limbs
  re-detected over their whole range;
- ``LIMBS_LOST``: a frame whose energy jumped: fitted again with every limb re-detected;
- ``SEARCH``: a frame with no trusted start (a first frame, a recovery): wide fits from the
  voxels' starts (those far behind after two rounds stopped there; the lowest few also with
  their limbs re-detected the other way), the lowest refitted; the tracking fit; rotations
  about the pelvis; sides swapped, limbs' other basins, arms' other twists; basin hopping;
- ``REFINE`` (``REFINE_SEARCH``): a tracked frame again, from its neighbour's fit (turned,
  tilted ahead), then from halfway between its neighbours (turned), each polished and its limbs
  re-detected; its pelvis turned alone; its arms' other twists (and its limbs' other basins);
  hops where asked, their best turned and its pelvis turned alone;
- ``FINISH``: a refined frame once more, on its own: evolutions over all 35 parameters from its
  fit (``evolve``), the lowest polished.

One module of about 800 lines: the schedules, the loop that runs them, the jobs their fits go
out as and the proposers are read together (a stage names its proposers and variants, the
loop its jobs).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from common.body import CHAINS, LIMB_CHAINS, MIRROR_SIGNS, BodyModel, clip_to_limits, swap_sides
from common.fitting import (EVOLVE_JOBS, HOP_JOBS, REDETECT_ROUND, ChainResult, Dispatch, FitOptions, FrameResult,
                            evolve, fit_rounds, full_energy, hop, hop_fit, merge_chains, solve_chain)
from common.frame import FrameData
from common.helping_pool import HelpingPool
from common.proposals import (ARM_CHAINS, arm_twist_alternative, arm_twist_options, arm_twist_tried, arm_twists,
                              arm_twists_towards, inversion_cost, limb_alternatives, midway,
                              moved_on, pelvis_twisted, rotated_about_pelvis, tilted_ahead, turned)

# The jobs of one round of starts, fitted side by side (the protocol's FIT_JOB_NAMES): job k is
# the round's k-th start; a round with more starts goes out in several.
FIT_JOBS = tuple(f"fit{k}" for k in range(16))


# ------------------------------------------------------------------------------ jobs

def solve_job(model: BodyModel, frame: FrameData, job: str, params: np.ndarray, options: FitOptions,
              iteration: int = 0, frame_number: int = 0, pool: HelpingPool | None = None) -> ChainResult:
    """The unit of work anyone does, server or client: a chain's solve (``solve_chain``), a hop
    (HOP_JOBS[k] is hop number ``iteration`` + k, seeded by ``frame_number``), an evolution
    (EVOLVE_JOBS[k], number ``iteration`` + k, seeded the same way), or a whole fit
    from ``params`` (FIT_JOBS: ``fit_rounds``, its limbs solved here or on ``pool``, going on
    from round ``iteration``), whose energies are the full energy at the start and at the fit.
    A whole fit's seconds count the jobs its thread ran for others while it waited on ``pool``."""
    if job in FIT_JOBS:
        wall0, cpu0 = time.perf_counter(), time.thread_time()
        local = solve_locally(model, frame, options, frame_number, pool)
        fit = fit_rounds(model, frame, params, options, local, first_round=iteration)
        return ChainResult(job, fit.params, full_energy(model, frame, params), fit.energy, fit.evaluations,
                           fit.iterations, time.perf_counter() - wall0, time.thread_time() - cpu0)
    if job in HOP_JOBS:
        return hop(model, frame, params, options, iteration + HOP_JOBS.index(job), frame_number, job)
    if job in EVOLVE_JOBS:
        return evolve(model, frame, params, options, iteration + EVOLVE_JOBS.index(job), frame_number, job)
    return solve_chain(model, frame, job, params, options, iteration=iteration)


def per_job(value, count: int, single: Callable[[object], bool]) -> list:
    """``value`` for each of ``count`` jobs: repeated where ``single(value)``, else its items."""
    if single(value):
        return [value] * count
    items = list(value)
    if len(items) != count:
        raise ValueError(f"{len(items)} values for {count} jobs")
    return items


def job_starts(params, count: int) -> list[np.ndarray]:
    """One (35,) start per job from a (35,) start for all or a sequence of them."""
    return [np.asarray(p, dtype=np.float64) for p in per_job(params, count, lambda v: np.ndim(v) == 1)]


def job_options(options, frame_options: FitOptions, count: int) -> list[FitOptions]:
    """One FitOptions per job: ``frame_options`` where None, one for all, or one each."""
    return per_job(frame_options if options is None else options, count, lambda v: isinstance(v, FitOptions))


def solve_locally(model: BodyModel, frame: FrameData, options: FitOptions, frame_number: int = 0,
                  pool: HelpingPool | None = None) -> Dispatch:
    """Dispatch in this process: each job by ``solve_job``, in order, or side by side on
    ``pool``'s threads (the energy's compiled loops release the GIL). A whole fit's limbs go
    to the same pool, whose threads run queued jobs while they wait, so a round of three fits
    on two threads ends with both threads on the last fit's limbs. Every job is a pure
    function of its inputs and the results come back in the order of ``jobs``, so the poses do
    not depend on the pool."""
    def dispatch(jobs: list, params, iteration: int, options_given=None):
        starts, opts = job_starts(params, len(jobs)), job_options(options_given, options, len(jobs))
        if pool is None or len(jobs) < 2:
            return lambda: [solve_job(model, frame, j, s, o, iteration, frame_number, pool)
                            for j, s, o in zip(jobs, starts, opts)]
        futures = [pool.submit(solve_job, model, frame, j, s, o, iteration, frame_number, pool)
                   for j, s, o in zip(jobs, starts, opts)]
        return lambda: [f.result() for f in futures]

    return dispatch


def is_chain_solve(result: ChainResult) -> bool:
    """A chain's solve, not a hop or a whole fit (the per-chain figures count these)."""
    return result.chain in CHAINS


# -------------------------------------------------------------------- fit variants

FIRST_FRAME_ITERATIONS = 6      # torso -> limbs rounds for a first frame started without truth
FIRST_FRAME_GRID_STEPS = 5      # limb grid points per parameter, first frame
FIRST_FRAME_GRID_RANGE = 1.0    # radians, +- limb grid half-width, first frame
FIRST_FRAME_LIMB_WINDOW = 400   # pixels: the limb may be far from where the start pose puts it


def first_frame_options(options: FitOptions, redetect_turn: str) -> FitOptions:
    """A start pose from voxels can have a limb far off: search limbs widely, in big windows,
    re-detect them ``redetect_turn`` ("round" or "all", common.fitting.REDETECT_TURNS) and
    iterate the fit to convergence."""
    return replace(options, max_iterations=max(options.max_iterations, FIRST_FRAME_ITERATIONS),
                   grid_steps=FIRST_FRAME_GRID_STEPS, grid_range_rad=FIRST_FRAME_GRID_RANGE,
                   limb_window_px=FIRST_FRAME_LIMB_WINDOW, hinge_grid_full_range=True, redetect_turn=redetect_turn)


# name -> the fit options a start is fitted with, from the run's options (None: not fitted)
VARIANTS: dict[str, Callable[[FitOptions], FitOptions | None]] = {
    "track": lambda o: o,
    # more rounds for the best: two rounds stop short of the minimum (a walk frame fitted again
    # from its own result lost 0.4-1.1% of its energy and 1-4 mm of error)
    "polish": lambda o: replace(o, max_iterations=o.polish_iterations) if o.polish_iterations else None,
    # a whole body moved far (rotated, sides swapped) settles in more rounds than a tracked one
    "deep": lambda o: replace(o, max_iterations=o.max_iterations + o.polish_iterations),
    "every": lambda o: replace(o, redetect_turn="every"),  # every limb re-detected in the first round
    # both ways of re-detecting a first frame's limbs: on 7 hard first frames neither wins
    # everywhere, together all 7 are within 50 mm
    "wide-round": lambda o: first_frame_options(o, "round"),
    "wide-all": lambda o: first_frame_options(o, "all"),
}


# ---------------------------------------------------------------------- schedules

@dataclass(frozen=True)
class Stage:
    """Propose starts with ``proposers`` from each of the ``beam`` lowest fits so far (one with
    none), fit each under each of ``variants`` (None: the variant its fit was fitted with), keep
    the lowest; again while a round lowers the best score by ``min_gain`` (a fraction), up to
    ``rounds`` rounds. ``score``: "energy" (the XOR energy) or "upright" (plus
    ``inversion_cost``: where the body's posture is unknown, among a search's starts);
    ``choose``: the stage ends by keeping its lowest-scoring fit alone, so that later stages
    compare their fits with that one, by their own score; ``drop`` (rounds, ratio): the starts
    fitted together are fitted that many rounds, and only those scoring within ``ratio`` times
    the lowest go on to the end (the others keep what they reached)."""

    proposers: tuple[str, ...]
    variants: tuple[str, ...] | None = ("track",)
    rounds: int = 1
    min_gain: float = 0.0
    beam: int = 1
    score: str = "energy"
    choose: bool = False
    drop: tuple[int, float] | None = None


@dataclass(frozen=True)
class Schedule:
    """Stages in order; ``budget``: the evaluations after which no further round starts (None:
    no limit). The result is the lowest energy of the fits the last stage compared."""

    stages: tuple[Stage, ...]
    budget: int | None = None


POLISHED = (Stage(("again",), ("polish",)), Stage(("redetected",)))
TRACKING = Schedule((Stage(("start", "start_turns", "tilt_ahead", "moved_on")), *POLISHED))
LIMBS_LOST = Schedule((Stage(("start", "start_turns"), ("every",)), Stage(("again",), ("polish",))))
# The lowest wide fits fitted again from their result while that still lowers the energy (each
# fit re-detects the limbs from a better torso). The lowest fit is not always the one that refits
# lowest: 06_08's first frame has a start a quarter turn off that fits to 17,513 and refits to
# 17,484, 40 mm off, while the next start fits to 18,759 and refits to 16,877, 20 mm off.
REFITTED = Stage(("again",), None, rounds=3, min_gain=0.005, beam=3, score="upright", choose=True)
# Every start fitted two rounds, and on to the end where it scores within 1.75 times the lowest:
# a start from the wrong posture settles in its own valley and stays there. Logged on 12 first
# frames of `mocap bench init`, the start that ended lowest was within 1.35 times the lowest
# after two rounds; with the drop, all 34 first frames come out as before, for 14% fewer
# evaluations (docs/accuracy.md)
WIDE_STARTS = Stage(("starts",), ("wide-round",), score="upright", drop=(2, 1.75))
WIDE = Schedule((WIDE_STARTS, REFITTED))
BODY_ROTATION_ROUNDS = 3
# The starts fitted one way of re-detecting limbs, then the lowest WIDE_BOTH_STARTS of them the
# other way too: fitting every start both ways was 62% of a search's time (a walk's first frame)
WIDE_BOTH_STARTS = 4
SEARCH = Schedule((
    WIDE_STARTS,
    Stage(("origin",), ("wide-all",), beam=WIDE_BOTH_STARTS, score="upright"), REFITTED,
    Stage(("best", "turns")), *POLISHED,  # local grids and small windows refine what the wide fits found
    Stage(("rotations",), ("deep",), rounds=BODY_ROTATION_ROUNDS),
    Stage(("swaps", "basins", "twists"), ("deep",)), *POLISHED,
    Stage(("hops",)),
), budget=4_000_000)  # evaluations: about twice the most any of the 34 first frames of `mocap bench init` spent
# (1.97M before the limb basins' and arm twists' own solves were counted, which add 1-2%)
# The neighbour's fit, then the pose halfway, each turned either way as tracking turns its start,
# each group's best polished and its limbs re-detected, as tracking does. With one polish and one
# re-detection for both, the dance was 10.6 / 60.3 mm (3 frames over 40) instead of 10.4 / 45.9
# (2 frames), the same tracking refined; leaner still (no turns, no re-detection), a walk's pass
# took 0.39 s a frame instead of 0.62 but the error was worse on 15 of the 16 shared clips other
# than the cartwheel (by up to 1.3 mm; docs/accuracy.md).
# Then the best's pelvis turned alone (``pelvis_twisted``): the worst frames of 05_13, 05_17 and
# 06_15 (41-45 mm, the right hip the worst joint) had the pelvis turned 0.18-0.24 rad with the
# spine and hips turned back, which no chain alone undoes.
REFINE = Schedule((Stage(("start", "start_turns", "tilt_ahead")), *POLISHED, Stage(("midway", "midway_turns")),
                   *POLISHED, Stage(("pelvis_twists",)), Stage(("twists",), ("deep",)), Stage(("hops",))))
REFINE_SEARCH = Schedule((*REFINE.stages[:-2], Stage(("basins", "twists"), ("deep",)), REFINE.stages[-1]))
# A frame with hops (a pass's first frame; every frame with --refine-hops): the hops' best
# turned, its pelvis turned alone and its arms' other twists tried, as the fits before them
# were. 05_17's last frame kept a hop's fit 40.9 mm off (the right hip), its pelvis turned 0.2
# rad from the truth's with the hips turned back; its pelvis turned 0.15 rad and fitted again:
# 3% lower, 33 mm off. With other noise (`--seed 1`) the same frame kept a hop's fit with the
# right forearm folded up the wrong way (464 mm off): the tracked fit's twists, tried before
# the hops, had its torso off too; the hops' best, twisted, comes to 5% less energy, 30 mm off
AFTER_HOPS = Schedule((Stage(("pelvis_twists", "turns")), Stage(("twists",), ("deep",))))
# Every frame once more after the refinement, each frame on its own: evolutions over all 35
# parameters from its fit (``evolve``), the lowest polished. Each frame's fit already had its
# neighbours' poses as starts, so a frame finished apart from them gives up nothing; its
# evolutions are jobs side by side, on a cluster's clients too (docs/accuracy.md, "Evolved
# whole-body moves")
FINISH = Schedule((Stage(("evolved",)), Stage(("again",), ("polish",))))
# evolutions a frame in the finish: most frames are lowered by one evolution and not another
# (the walk's refined frames: one 6.64 mm, two 6.43, from 7.12; ``EVOLVE_EVALS``)
FINISH_EVOLUTIONS = 2
# hops that end a search: 06_02 from source frame 262 (five of eight views) 54 -> 27 mm. Logged
# hop by hop on the 34 first frames of `mocap bench init --first-frame-only`, the mean error
# after 0, 10, 20 and 30 hops was 14.6, 13.7, 13.1 and 12.7 mm, at about 0.1 s a hop; with 20,
# the cartwheel's (05_06) recoveries went wrong: 13.8 / 103 mm, 18 frames over 40 -> 14.0 / 150, 27
SEARCH_HOPS = 30
# hops that refit a pass's first frame, which has no neighbour to be refitted from: the
# sequence's last frame on a backward pass is otherwise only ever tracking's fit (basketball's
# last frame: the left ankle 70 mm off, the clip's worst). One frame per pass, so it can have
# a deeper search than the rest: on the three accuracy clips' last frames, 120 hops lowered
# the energy of 30 hops' fit on all three, by 0.3-0.5% (basketball's left wrist 48 -> 33 mm),
# for about 13 s per pass. It is also fitted from each limb's other basins (the first pass's
# ``search``, done for this frame in every pass): basketball's last frame kept a left elbow
# 89 mm off through the hops, and from the basins its energy fell from 3,272 to 3,188 pixels
# and its worst joint to 35 mm.
PASS_START_HOPS = 120
# Hops for every frame of a poor window's passes (``server.session.refine_poor_windows``). Each frame of the run
# the passes left in a valley of its own is fitted from its neighbour, which is off too; a hop
# moves one chain and fits all 35 parameters together, which goes down a valley that runs across
# the chains (docs/accuracy.md, "Hops in poor windows": the cartwheel's frames over 40 mm 11 -> 7
# with 20, 7 with 40 and 80)
POOR_WINDOW_HOPS = 20
# hops that refit each first frame of the passes after foreground no pose explains was cleared,
# from its own fit: with PASS_START_HOPS (120) the posture takes beside a prop came out no
# better, a third slower (docs/accuracy.md)
UNEXPLAINED_START_HOPS = 20

# a refined frame whose energy is this many times the mean of its neighbours' stands out (the
# masks' noise moves a frame's energy by a few per cent: 5 of the 17 shared clips' 1,686 refined
# frames stand out at 1.08)
STANDING_OUT_RATIO = 1.08
# A refined frame whose XOR share of its silhouette area is this many times the take's median
# share is poor, and the frames around it are refined once more (``poor_windows``): silhouette
# noise and the body's own shape move the share by about a tenth, a run left in a valley of its
# own (the cartwheel rolling onto its side) by up to a half. With the windows' hops a window
# costs a few frames' search and has lowered every clip's error it was tried on, so the line
# is at 1.15 (docs/accuracy.md, "Poor runs refined again", "Hops in poor windows")
POOR_SHARE_RATIO = 1.15
LOSS_ENERGY_RATIO = 1.25  # a frame's energy this far above the recent median: tracking is lost
LIMB_LOSS_ENERGY_RATIO = 1.06  # ... this far: a limb may be lost, every limb is re-detected


@dataclass(frozen=True)
class Schedules:
    """The schedules a run fits its frames by, and its hop budgets (a Config.toml's
    ``[fit.schedules]``, whose keys are these fields' names): ``after_hops`` is added to a
    refinement's stages where it hops; ``finish`` fits every frame once more after the
    refinement, with ``finish_evolutions`` evolutions (0: no finish); ``search_hops`` are the
    hops of the search's ``hops`` proposer, ``pass_start_hops`` those of a refinement pass's
    first frame (server.session), ``poor_window_hops`` every frame's in a poor window's passes,
    ``unexplained_start_hops`` a pass's first frame's after clearing foreground no pose
    explains; the ratios say when the
    limbs-lost and search schedules run in tracking (``tracking_lost``) and which refined frames
    are refined again (``poor_windows``, ``standing_out``)."""

    tracking: Schedule = TRACKING
    limbs_lost: Schedule = LIMBS_LOST
    wide: Schedule = WIDE
    search: Schedule = SEARCH
    refine: Schedule = REFINE
    refine_search: Schedule = REFINE_SEARCH
    after_hops: Schedule = AFTER_HOPS
    finish: Schedule = FINISH
    search_hops: int = SEARCH_HOPS
    pass_start_hops: int = PASS_START_HOPS
    poor_window_hops: int = POOR_WINDOW_HOPS
    unexplained_start_hops: int = UNEXPLAINED_START_HOPS
    finish_evolutions: int = FINISH_EVOLUTIONS
    limb_loss_ratio: float = LIMB_LOSS_ENERGY_RATIO
    loss_ratio: float = LOSS_ENERGY_RATIO
    poor_share_ratio: float = POOR_SHARE_RATIO
    standing_out_ratio: float = STANDING_OUT_RATIO


SCHEDULES = Schedules()


@dataclass(frozen=True)
class Context:
    """What a schedule's proposers and fits see of one frame.

    start: the pose the frame starts from (tracking: the previous frame's fit; refinement: the
    neighbour's), before: the one before it, other: refinement's neighbour on the other side;
    starts: a search's starts; hops: basin hops for the ``hops`` proposer, ``side_by_side`` at
    once; evolutions: the ``evolved`` proposer's, all at once."""

    model: BodyModel
    frame: FrameData
    options: FitOptions
    dispatch: Dispatch
    frame_number: int = 0
    start: np.ndarray | None = None
    before: np.ndarray | None = None
    other: np.ndarray | None = None
    starts: tuple = ()
    hops: int = 0
    side_by_side: int = 1
    evolutions: int = 0


@dataclass
class _Spent:
    """Solves spent by proposers (limb searches, hops' dropped rounds) beside the fits."""

    chains: list = field(default_factory=list)
    evaluations: int = 0

    def add(self, results: list[ChainResult]) -> None:
        self.chains += results
        self.evaluations += sum(r.evaluations for r in results)


def lowest(fits: list[FrameResult], score: Callable[[FrameResult], float] | None = None,
           made: list[FrameResult] | None = None, spent: _Spent | None = None) -> FrameResult:
    """The fit of lowest ``score`` (default its energy; the first on a tie) among ``fits``, as a
    new result carrying the solves and evaluations of every one of ``made`` (default ``fits``)
    and ``spent``: what was spent to choose it."""
    best = min(fits, key=score or (lambda f: f.energy))
    made = fits if made is None else made
    chains = tuple(c for f in made for c in f.chains) + tuple(spent.chains if spent else ())
    evaluations = sum(f.evaluations for f in made) + (spent.evaluations if spent else 0)
    return replace(best, chains=chains, evaluations=evaluations)


def descend_outward(values: tuple, centre: float, centre_score: float,
                    score_many: Callable[[list], list]) -> dict:
    """{value: score} of ``centre`` and of ``values`` scored outward from it, the nearest
    untried value on each side at once (``score_many``: [value] -> [score], side by side);
    a side stops at its first value that does not lower the score below the value before it.
    Which values are scored depends on the scores alone, never on how many score at once."""
    scores = {centre: centre_score}
    sides = [sorted((v for v in values if v > centre)), sorted((v for v in values if v < centre), reverse=True)]
    previous = [centre, centre]
    while True:
        step = [(k, side[0]) for k, side in enumerate(sides) if side]
        if not step:
            return scores
        for (k, value), score in zip(step, score_many([v for _, v in step])):
            scores[value] = score
            sides[k] = sides[k][1:] if score < scores[previous[k]] else []
            previous[k] = value


def run_schedule(ctx: Context, schedule: Schedule, initial: FrameResult | None = None,
                 memo: dict | None = None) -> FrameResult:
    """The lowest-energy of ``initial`` (a fit made elsewhere, never proposed from again by
    ``again``) and the fits the schedule's stages make; see the module docstring and ``Stage``.
    Its solves and evaluations are those of every fit made, chosen or not. ``memo``: {(variant,
    start bytes): fit} of fits already made of this frame by this model under ``ctx.options``
    (an earlier schedule's), used instead of fitting those starts again; the new fits are added."""
    memo = {} if memo is None else memo  # (variant, start bytes) -> fit, across schedules
    fits = [initial] if initial is not None else []  # the candidates
    made = list(fits)       # every fit, for what was spent
    own = set()             # ids of the fits made here
    fitted = set()          # (variant, start bytes) already fitted here
    # (proposer, source id, variants): a proposer asked again from the same fit makes the same
    # starts, fitted already, and a limb search's solves again: a refinement's second
    # re-detection often has the first one's fit as its source
    proposed = set()
    spent = _Spent()
    for stage in schedule.stages:
        score = _scorer(ctx, stage.score)
        for _ in range(stage.rounds):
            if schedule.budget is not None and sum(f.evaluations for f in made) + spent.evaluations >= schedule.budget:
                break
            best_before = score(min(fits, key=score)) if fits else np.inf
            sources = sorted(fits, key=score)[:stage.beam] if fits else [None]
            jobs, keys = [], []
            for source in sources:
                variants = stage.variants or ((source.variant,) if source is not None else ())
                for name in stage.proposers:
                    if (name, id(source), variants) in proposed:
                        continue
                    proposed.add((name, id(source), variants))
                    for start in PROPOSERS[name](ctx, source, spent, id(source) in own):
                        if isinstance(start, FrameResult):  # fitted by the proposer itself (hops)
                            fits.append(start)
                            made.append(start)
                            own.add(id(start))
                            continue
                        for variant in variants:
                            k = (variant, np.asarray(start, dtype=np.float64).tobytes())
                            if k not in fitted and VARIANTS[variant](ctx.options) is not None:
                                fitted.add(k)
                                jobs.append((start, variant))
                                keys.append(k)
            new = _fit_or_recall(ctx, jobs, keys, memo, stage.drop, score)
            fits += new
            made += new
            own.update(id(f) for f in new)
            if not fits or not score(min(fits, key=score)) < best_before * (1.0 - stage.min_gain):
                break
        if stage.choose and fits:
            fits = [min(fits, key=score)]
    return lowest(fits, made=made, spent=spent)


def _fit_or_recall(ctx: Context, jobs: list[tuple[np.ndarray, str]], keys: list, memo: dict,
                   drop: tuple[int, float] | None = None, score=None) -> list[FrameResult]:
    """The jobs' fits, in their order: ``memo``'s where it holds their key, else ``fit_starts``'
    (then kept in ``memo``)."""
    missing = [i for i, k in enumerate(keys) if k not in memo]
    for i, fit in zip(missing, fit_starts(ctx, [jobs[i] for i in missing], drop, score)):
        memo[keys[i]] = fit
    return [memo[k] for k in keys]


def _scorer(ctx: Context, name: str) -> Callable[[FrameResult], float]:
    if name == "energy":
        return lambda f: f.energy
    if name == "upright":  # people are upright far more often (``inversion_cost``)
        return lambda f: f.energy + inversion_cost(ctx.model, ctx.frame, f.params)
    raise ValueError(f"unknown score {name!r}")


def fit_starts(ctx: Context, jobs: list[tuple[np.ndarray, str]], drop: tuple[int, float] | None = None,
               score: Callable[[FrameResult], float] | None = None) -> list[FrameResult]:
    """Each (start (35,), variant) fitted by ``fit_rounds``: one here, its limbs dispatched;
    several as FIT_JOBS side by side. With ``drop`` (rounds, ratio), several are fitted that
    many rounds first, and those that ``score`` (default the energy) more than ``ratio`` times
    the lowest, stop there. Tracking fits every start to the end: dropping those more than 3%
    above the lowest after their first round saved a fifth of the walk's tracking time and cost
    1.8 mm of its mean error (8.7 -> 10.5 mm, 40 frames)."""
    if not jobs:
        return []
    if len(jobs) == 1:
        start, variant = jobs[0]
        fit = fit_rounds(ctx.model, ctx.frame, start, VARIANTS[variant](ctx.options), ctx.dispatch)
        return [replace(fit, variant=variant, start=start)]
    starts, options = [s for s, _ in jobs], [VARIANTS[v](ctx.options) for _, v in jobs]
    if drop is None:
        fits = _fit_jobs(ctx, starts, options)
    else:
        rounds, ratio = drop
        fits = _fit_jobs(ctx, starts, [replace(o, max_iterations=min(rounds, o.max_iterations)) for o in options])
        score = score or (lambda f: f.energy)
        bar = ratio * min(score(f) for f in fits)
        # a fit that stopped before its last round had converged; one whose options allow no
        # more rounds is done
        going = [i for i, f in enumerate(fits)
                 if f.iterations == rounds and rounds < options[i].max_iterations and score(f) <= bar]
        rest = _fit_jobs(ctx, [fits[i].params for i in going], [options[i] for i in going], rounds)
        for i, late in zip(going, rest):
            fits[i] = replace(late, evaluations=fits[i].evaluations + late.evaluations,
                              chains=fits[i].chains + late.chains)
    return [replace(f, variant=variant, start=start) for f, (start, variant) in zip(fits, jobs)]


def _fit_jobs(ctx: Context, starts: list, options: list[FitOptions], first_round: int = 0) -> list[FrameResult]:
    """Fits from ``starts`` under ``options`` (one each) as FIT_JOBS, len(FIT_JOBS) at a time,
    going on from round ``first_round``."""
    out = []
    for k in range(0, len(starts), len(FIT_JOBS)):
        n = len(starts[k:k + len(FIT_JOBS)])
        results = ctx.dispatch(list(FIT_JOBS[:n]), starts[k:k + n], first_round, options[k:k + n])()
        out += [FrameResult(r.params, r.energy, r.iterations, r.evaluations, (r,)) for r in results]
    return out


# ---------------------------------------------------------------------- proposers
# proposer(ctx, source fit or None, spent, made here) -> starts (35,) or fits made by the proposer

def _start(ctx, source, spent, own):
    return [] if ctx.start is None else [ctx.start]


def _turns(params: np.ndarray, options: FitOptions) -> list:
    # the pelvis heading is the torso's flattest valley: a tracked pose can sit turned from the
    # truth with the hips twisted back to keep the legs in place, which neither the torso nor a
    # limb alone can undo
    return [turned(params, sign * step * options.turn_step_rad)
            for step in range(1, options.turn_hypotheses + 1) for sign in (-1, 1)]


def _start_turns(ctx, source, spent, own):
    return [] if ctx.start is None else _turns(ctx.start, ctx.options)


def _best_turns(ctx, source, spent, own):
    return [] if source is None else _turns(source.params, ctx.options)


def _midway_turns(ctx, source, spent, own):
    return [] if ctx.start is None or ctx.other is None else _turns(midway(ctx.start, ctx.other), ctx.options)


PELVIS_TWISTS_RAD = (-0.15, 0.15)


def _pelvis_twists(ctx, source, spent, own):
    return [] if source is None else [pelvis_twisted(ctx.model, source.params, a) for a in PELVIS_TWISTS_RAD]


def _tilt_ahead(ctx, source, spent, own):
    return [] if ctx.start is None else list(tilted_ahead(ctx.start, ctx.before))


def _moved_on(ctx, source, spent, own):
    # the fast preset's (``track_moved_on``): with refinement after tracking (the default),
    # three of the 17 shared clips gained a frame over 40 mm, 05_17 one of 473 mm
    return [] if ctx.start is None or not ctx.options.track_moved_on else list(moved_on(ctx.start, ctx.before))


def _midway(ctx, source, spent, own):
    return [] if ctx.start is None or ctx.other is None else [midway(ctx.start, ctx.other)]


def _starts(ctx, source, spent, own):
    return list(ctx.starts)


def _best(ctx, source, spent, own):
    return [] if source is None else [source.params]


def _origin(ctx, source, spent, own):
    """The start the fit was fitted from: to fit it again another way."""
    return [] if source is None or source.start is None else [source.start]


def _again(ctx, source, spent, own):
    return [source.params] if source is not None and own else []


def _redetected(ctx, source, spent, own):
    """Every limb searched over its whole range against a fit made here (side by side); if any
    is found elsewhere, the fit with those limbs moved. A limb that moved faster than the local
    search (a basketball player's forearm swing) is found in the frame it is lost. Like
    ``again``, never from a fit made elsewhere: a refinement's tracked fit had its limbs searched
    when it was tracked, and searching them again cost a refinement a fifth of its evaluations
    for the same poses (the dance and 01_01, 40 frames each)."""
    options = ctx.options
    if source is None or not own or not (options.redetect_limbs and options.redetect_turn == "final"):
        return []
    found = ctx.dispatch(list(LIMB_CHAINS), source.params, REDETECT_ROUND, options)()
    spent.add(found)
    moved = [r for r in found if r.energy < r.energy_before]
    return [merge_chains(source.params, moved)] if moved else []


# The whole body rotated about the pelvis's three axes by these angles. A body upside down and
# sideways settles with the trunk tilted off and the limbs bent to make up for it, where no chain
# alone goes down: 05_06 from source frame 150 (a cartwheel) was found with the pelvis 36 degrees
# off, 64 mm; rotated about the front-to-back axis and fitted again, 31 mm, the next rounds ~20.
BODY_ROTATIONS_RAD = (-0.6, -0.3, 0.3, 0.6)


def _rotations(ctx, source, spent, own):
    if source is None:
        return []
    return [clip_to_limits(rotated_about_pelvis(ctx.model, source.params, axis, angle))
            for axis in range(3) for angle in BODY_ROTATIONS_RAD]


def _swaps(ctx, source, spent, own):
    """The legs swapped, the arms swapped: a stride with the left foot ahead and one with the right
    look alike from the side, and neither leg alone can move to the other's place (05_01 from
    source frame 127, feet out of three views: found with its legs swapped, the ankles 0.5 m off)."""
    return [] if source is None else [swap_sides(source.params, limb) for limb in MIRROR_SIGNS]


def _basins(ctx, source, spent, own):
    """Each limb moved into its other basins: a limb found wrong holds the torso where it
    explains that limb, and neither can move alone."""
    if source is None:
        return []
    starts = []
    for chain in LIMB_CHAINS:
        alternatives, evaluations = limb_alternatives(ctx.model, ctx.frame, chain, source.params, ctx.options)
        spent.evaluations += evaluations
        starts += alternatives
    return starts


# In a refinement, an arm's lowest twist turned away from the neighbour's is fitted too, and kept
# only where the fit is this much lower (a fraction of the source's energy). Where the frames
# around share a wrong twist, no twist turns towards them: 05_02 from source frame 401, frames
# 34-43, the right arm turned with its hand bent to its limits, the wrist up to 68 mm off; fitted
# from the arm's twists, frame 38 came 1.1% lower and 23 mm off. A wrong twist that wins by less
# stays out (walk frame 12: 0.45%, 62 mm off at the wrist against 26).
TWIST_AWAY_GAIN = 0.01


def _twists(ctx, source, spent, own):
    """Each nearly straight or fully folded arm at its lower twist (towards the neighbour's, in a
    refinement; one turned away, fitted here, where it is TWIST_AWAY_GAIN lower).
    The arms' solves are jobs, both arms' k-th twist in one round (then the arms solved as they
    are), so they run side by side."""
    if source is None:
        return []
    x = source.params
    arms = [chain for chain in ARM_CHAINS if arm_twist_tried(chain, x)]
    if not arms:
        return []
    options = arm_twist_options(ctx.options)
    starts = {chain: arm_twists(ctx.model, chain, x) for chain in arms}
    twisted = {chain: [] for chain in arms}
    for k in range(max(len(s) for s in starts.values())):
        round_arms = [chain for chain in arms if k < len(starts[chain])]
        found = ctx.dispatch(round_arms, [starts[chain][k] for chain in round_arms], 1, options)()
        spent.add(found)
        for chain, result in zip(round_arms, found):
            twisted[chain].append(result)
    turned = {chain: arm_twists_towards(chain, x, twisted[chain], ctx.start) for chain in arms}
    away = ctx.start is not None  # a refinement: a twist may turn away from the neighbour's
    compared = [chain for chain in arms if turned[chain] or away]
    if not compared:
        return []
    own_solves = ctx.dispatch(compared, x, 1, options)()
    spent.add(own_solves)
    alternatives, away_starts = [], []
    for chain, solved in zip(compared, own_solves):
        towards = arm_twist_alternative(turned[chain], solved) if turned[chain] else None
        if towards is not None:
            alternatives.append(towards)
        elif away and (y := arm_twist_alternative(twisted[chain], solved)) is not None:
            away_starts.append(y)
    # fitted here, to be kept only well below the source; what they cost counts either way
    fitted = fit_starts(ctx, [(y, "deep") for y in away_starts])
    spent.chains += [c for f in fitted for c in f.chains]
    spent.evaluations += sum(f.evaluations for f in fitted)
    bar = (1.0 - TWIST_AWAY_GAIN) * source.energy
    return alternatives + [replace(f, evaluations=0, chains=()) for f in fitted if f.energy <= bar]


def _hops(ctx, source, spent, own):
    """Basin hopping from the fit (``hop_fit``), as one fit whose energy is the full energy."""
    if source is None or ctx.hops < 1:
        return []
    hopped = hop_fit(source.params, ctx.hops, ctx.options, ctx.dispatch, min(max(ctx.side_by_side, 1), len(HOP_JOBS)))
    return [replace(hopped, energy=full_energy(ctx.model, ctx.frame, hopped.params))]


def _evolved(ctx, source, spent, own):
    """The fit moved by ``ctx.evolutions`` evolutions (``evolve``), side by side, each as one fit
    whose energy is the full energy."""
    if source is None or ctx.evolutions < 1:
        return []
    fits = []
    for k in range(0, ctx.evolutions, len(EVOLVE_JOBS)):
        jobs = list(EVOLVE_JOBS[:min(len(EVOLVE_JOBS), ctx.evolutions - k)])
        for r in ctx.dispatch(jobs, source.params, k, ctx.options)():
            fits.append(FrameResult(r.params, full_energy(ctx.model, ctx.frame, r.params), r.iterations,
                                    r.evaluations, (r,)))
    return fits


PROPOSERS = {
    "start": _start, "start_turns": _start_turns, "turns": _best_turns, "tilt_ahead": _tilt_ahead,
    "moved_on": _moved_on, "midway": _midway, "midway_turns": _midway_turns, "pelvis_twists": _pelvis_twists,
    "starts": _starts,
    "best": _best, "origin": _origin, "again": _again, "redetected": _redetected,
    "rotations": _rotations, "swaps": _swaps, "basins": _basins, "twists": _twists, "hops": _hops,
    "evolved": _evolved,
}


# ---------------------------------------------------------------------- entry points

def fit_frame(model: BodyModel, frame: FrameData, start: np.ndarray, options: FitOptions,
              dispatch: Dispatch | None = None, before: np.ndarray | None = None,
              frame_number: int = 0, schedules: Schedules = SCHEDULES) -> FrameResult:
    """Track one frame from ``start`` (35,), the previous frame's fit (``before``: the one
    before that), by the tracking schedule (TRACKING)."""
    dispatch = dispatch or solve_locally(model, frame, options, frame_number)
    ctx = Context(model, frame, options, dispatch, frame_number, start=np.asarray(start, dtype=np.float64),
                  before=before)
    return run_schedule(ctx, schedules.tracking)


def search_frame(model: BodyModel, frame: FrameData, starts: list, options: FitOptions, dispatch: Dispatch,
                 frame_number: int = 0, side_by_side: int = 1, memo: dict | None = None,
                 schedules: Schedules = SCHEDULES) -> FrameResult:
    """A frame without a trusted start (a first frame, a recovery), searched from ``starts`` by
    the search schedule (SEARCH); ``memo`` as ``run_schedule``'s (the actor-size search's fits
    of the same frame)."""
    ctx = Context(model, frame, options, dispatch, frame_number, starts=tuple(starts), hops=schedules.search_hops,
                  side_by_side=side_by_side)
    return run_schedule(ctx, schedules.search, memo=memo)


def refine_frame(model: BodyModel, frame: FrameData, fit: FrameResult, options: FitOptions, dispatch: Dispatch,
                 neighbour: np.ndarray | None, beyond: np.ndarray | None, other: np.ndarray | None,
                 hops: int = 0, search: bool = False, frame_number: int = 0, side_by_side: int = 1,
                 schedules: Schedules = SCHEDULES) -> FrameResult:
    """A tracked frame (``fit``) fitted again by the refine schedule (REFINE; refine_search,
    REFINE_SEARCH, with ``search``) from its
    ``neighbour``'s refined fit (``beyond``: the one beyond it; ``other``: the not yet refined
    neighbour on the other side) and with ``hops`` hops, whose best is then turned and its arms
    twisted (after_hops, ``AFTER_HOPS``); ``fit`` where nothing is lower.

    Tracking leaves frames in basins that a later frame escaped (an arm whose twist showed once
    it bent; a first frame found by search). Halfway between the neighbours' fits (``midway``):
    tracking can leave a frame with its torso and limbs off together, in a valley that neither
    neighbour's fit leads out of, while their mean lies in the truth's (the dance's frames 21 and
    39: 54 and 50 mm off; fitted from halfway, 16 and 23 mm)."""
    ctx = Context(model, frame, options, dispatch, frame_number, start=neighbour, before=beyond, other=other,
                  hops=hops, side_by_side=side_by_side)
    schedule = schedules.refine_search if search else schedules.refine
    if hops:
        schedule = Schedule((*schedule.stages, *schedules.after_hops.stages), schedule.budget)
    return run_schedule(ctx, schedule, initial=fit)


def finish_frame(model: BodyModel, frame: FrameData, fit: FrameResult, options: FitOptions, dispatch: Dispatch,
                 frame_number: int = 0, schedules: Schedules = SCHEDULES) -> FrameResult:
    """A refined frame (``fit``) fitted once more on its own by the finish schedule (FINISH), with
    the schedules' ``finish_evolutions`` evolutions; ``fit`` where nothing is lower."""
    ctx = Context(model, frame, options, dispatch, frame_number, evolutions=schedules.finish_evolutions)
    return run_schedule(ctx, schedules.finish, initial=fit)


def standing_out(energies: list, ratio: float = STANDING_OUT_RATIO) -> list[int]:
    """Indices of the frames (not the first or the last) whose energy is ``ratio`` times the
    mean of their two neighbours' or more."""
    e = np.asarray(energies, dtype=np.float64)
    return [i for i in range(1, len(e) - 1) if e[i] >= ratio * 0.5 * (e[i - 1] + e[i + 1])]


POOR_MARGIN_FRAMES = 3  # frames refined either side of a run of poor ones


def poor_windows(shares: list, ratio: float = POOR_SHARE_RATIO, margin: int = POOR_MARGIN_FRAMES) -> list[tuple[int, int]]:
    """[(first, last) index, inclusive]: each run of frames whose share (XOR over silhouette
    area) is ``ratio`` times the median of ``shares`` or more, ``margin`` frames added either
    side (within the take), runs that meet or overlap merged, in order."""
    s = np.asarray(shares, dtype=np.float64)
    if len(s) == 0 or not np.median(s) > 0.0:  # fits that explain their masks whole: none is poor
        return []
    poor = np.flatnonzero(s >= ratio * float(np.median(s)))
    windows: list[tuple[int, int]] = []
    for i in poor:
        first, last = max(int(i) - margin, 0), min(int(i) + margin, len(s) - 1)
        if windows and first <= windows[-1][1] + 1:
            windows[-1] = (windows[-1][0], last)
        else:
            windows.append((first, last))
    return windows


LOSS_HISTORY = 10         # frames in tracking_lost's median
LOSS_MIN_HISTORY = 3


def tracking_lost(energies: list, energy: float, ratio: float = LOSS_ENERGY_RATIO) -> bool:
    """Whether ``energy`` jumps ``ratio`` times above the median of the last frames' energies
    (silhouette noise moves it by a few per cent; a limb lost in a fast move adds 5-15%, a body
    fitted beside the actor its whole area)."""
    recent = energies[-LOSS_HISTORY:]
    return len(recent) >= LOSS_MIN_HISTORY and energy > ratio * float(np.median(recent))
