"""The server's frame loop: fit every frame of a sequence, write results frame by frame.

Each frame is fitted by ``common.search``'s schedules: tracked from the previous frame's fit; a
frame whose energy jumps above the recent frames' is a loss (a limb: every limb re-detected; the
whole body: searched again from its voxels, as a first frame is), the better fit kept. After
tracking, ``options.refine_passes`` passes fit every frame again from its neighbour's fit,
backwards then forwards alternately (``refine_pass``), the frames around poor fits and those
that stand out of their neighbours are refined once more, and each frame then takes whichever of
its neighbours' fits makes the take's energy and steps least where the masks did not move
(``settle_records``: a still actor holds still); with no pass, a run that starts from a search
(no truth) still refines its first frames backwards once tracking has settled. Jobs (limb chains,
hops, whole fits) go to a ``Solver``: this process, or a cluster of clients; ``mocap fit`` is this
loop with the local solver: single-process mode is the server with zero clients.

One module of about 910 lines: the frame loop, the actor-size search and the refinement passes
share the solver, the records and the result folder, and are read together.

Result folder (``server.results``):
    poses.jsonl   one line per frame: frame, params, joints, energy, seconds, ... (appended
                  per frame, so an interrupted run keeps what it had and --resume continues
                  after the last complete line; replaced whole after each refinement pass,
                  a replaced frame keeping its tracking fit under "first_pass")
    summary.json  run summary, accuracy against truth.jsonl when the sequence has one
    run.json      the settings, which --resume must match
"""
from __future__ import annotations

import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from common import voxels
from common.body import P, BodyModel, forward_kinematics, joints_dict, load_body_model, rest_params
from common.energy import whole_energy
from common.errors import InputFileError, UserError, print_warning
from common.consistency import UNEXPLAINED_FRAMES_SHARE, unexplained_foreground
from common.fitting import HOP_JOBS, ChainResult, FitOptions, FrameData, FrameResult, fit_rounds, full_energy
from common.frame import recorded_pixels
from common.helping_pool import HelpingPool
from common.proposals import voxel_starts
from common.retarget import nearest_turn
from common.scoring import accuracy, frame_quality, quality_summary, size_score
from common.settle import candidate_frames, mask_step, settle_choice
from common.search import (FIT_JOBS, SCHEDULES, VARIANTS, Context, Schedules, descend_outward, finish_frame,
                           fit_frame, is_chain_solve, lowest, refine_frame, run_schedule, search_frame,
                           solve_locally, poor_windows, standing_out, tracking_lost)
from common.schedule_tables import schedules_table
from common.sequence import Sequence
from server.output import counted, write_text
from server.threads import backend_threads
from server.results import (POSES_FILE, SUMMARY_FILE, prepare_result_folder, read_done_frames,
                            rewrite_complete, write_foreground_left_out)

# fewer views leave depth and the limbs' sides unresolved (tools/camera_count_accuracy.py,
# docs/accuracy.md "Fewer cameras": a walk fits 95/908 mm mean/worst with 1 camera, 63/858 with 2,
# 7/21 with 3)
MIN_GOOD_CAMERAS = 3


class Solver(Protocol):
    """Who solves the jobs (limb chains, hops, whole fits): this process, or clients over the network."""

    mode: str
    clients: int

    def begin_frame(self, frame: int, data: FrameData, start: np.ndarray, options: FitOptions) -> None:
        """A new frame: its silhouettes, start pose and the options its jobs are solved with
        unless a round gives its own."""

    def solve(self, jobs: list, params, iteration: int, options=None) -> Callable[[], list]:
        """Start ``jobs`` (``common.search.solve_job``) from ``params`` (one (35,) start, or one
        per job) under ``options`` (None: the frame's; one FitOptions; or one per job); the
        returned function waits for the results."""

    def workers(self) -> int:
        """How many jobs it solves at once (clients, and the server beside them)."""

    def timing(self) -> dict: ...

    def close(self) -> None: ...


class LocalSolver:
    """Single-process mode: the same jobs, run here, ``threads`` at once (the same poses for
    any number: ``common.search.solve_locally``)."""

    mode = "single"
    clients = 0

    def __init__(self, model: BodyModel, options: FitOptions, threads: int = 1):
        self.model, self.options = model, options
        self.data: FrameData | None = None
        self.compute_seconds = 0.0
        self.threads = backend_threads(threads, options)
        self._pool = HelpingPool(self.threads, "fit") if self.threads > 1 else None

    def begin_frame(self, frame: int, data: FrameData, start: np.ndarray, options: FitOptions) -> None:
        self.data, self.frame = data, int(frame)
        self._dispatch = solve_locally(self.model, data, options, int(frame), self._pool)

    def map(self, function: Callable, items) -> list:
        """[function(item) for item in items], side by side on the threads; in order."""
        if self._pool is None:
            return [function(item) for item in items]
        return list(self._pool.map(function, items))

    def solve(self, jobs: list, params, iteration: int, options=None) -> Callable[[], list]:
        collect = self._dispatch(jobs, params, iteration, options)

        def timed() -> list:
            t0 = time.perf_counter()
            out = collect()
            self.compute_seconds += time.perf_counter() - t0
            return out

        return timed

    def workers(self) -> int:
        return self.threads

    def timing(self) -> dict:
        return {"processes": []}

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)


@dataclass
class RunStats:
    seconds: list = field(default_factory=list)
    evaluations: list = field(default_factory=list)
    chain_cpu: dict = field(default_factory=dict)        # chain -> total CPU seconds
    chain_wall: dict = field(default_factory=dict)       # chain -> total wall seconds
    chain_evaluations: dict = field(default_factory=dict)
    server_compute: float = 0.0                          # torso + head + energy checks, seconds
    hops_run: int = 0                                    # hops of the refinement, dropped ones too (hop_fit)
    hop_seconds: float = 0.0                             # wall seconds in hop_fit

    def add_chains(self, chains: list[ChainResult]) -> None:
        for c in chains:
            self.chain_cpu[c.chain] = self.chain_cpu.get(c.chain, 0.0) + c.cpu_seconds
            self.chain_wall[c.chain] = self.chain_wall.get(c.chain, 0.0) + c.wall_seconds
            self.chain_evaluations[c.chain] = self.chain_evaluations.get(c.chain, 0) + c.evaluations
SOLVES_PER_ITERATION = ("torso", "left_arm", "right_arm", "left_leg", "right_leg", "head")


def chain_totals(chains: list[ChainResult]) -> dict:
    """Per chain over a frame's solves: evaluations, seconds and the energies before and after
    each solve summed. A solve's two energies are of its own window (a re-detection's, of the
    whole images), so only the pair of sums compares: their difference is what the chain's
    solves gained."""
    out: dict = {}
    for c in chains:
        t = out.setdefault(c.chain, {"evaluations": 0, "energy_before": 0, "energy": 0,
                                     "cpu_seconds": 0.0, "wall_seconds": 0.0})
        t["evaluations"] += c.evaluations
        t["cpu_seconds"] += c.cpu_seconds
        t["wall_seconds"] += c.wall_seconds
        t["energy_before"] += c.energy_before
        t["energy"] += c.energy
    return out


def silhouette_centre(data: FrameData) -> np.ndarray:
    """(3,) where the rays through the silhouettes' centroids meet (the actor, roughly)."""
    centre = voxels.silhouette_centre(data.studio, data.masks)
    if centre is None:
        raise UserError("cannot locate the actor: fewer than two cameras see a silhouette in the first frame")
    return centre


def usable_cameras(seq: Sequence, frames) -> Sequence:
    """``seq`` without the cameras whose mask is all on or all off in every one of ``frames``,
    each named in a warning: such a camera tells nothing of the actor (all on: any body fits;
    all off where the actor is in view: none does, and the hull and the size search carve
    everything away). Refused when that would leave no camera. Every mask of ``frames`` is
    checked first (``Sequence.check_files``, which reads a sequence's masks once)."""
    frames = list(frames)
    seq.check_files(frames)
    constant = seq.constant_cameras(frames)
    if not constant:
        return seq
    where = seq.mask_folder
    if len(constant) == len(seq.studio):
        raise InputFileError(where, f"every camera's mask is all on or all off in every frame ({len(frames)} "
                                    "frames); check the masks or the mask threshold")
    for name, state in constant.items():
        print_warning(f"{where / name}: camera {name}'s mask is all {state} in every frame ({len(frames)} "
                      "frames): left out; check the masks or the mask threshold")
    return seq.without_cameras(constant)


def truth_start(seq: Sequence) -> np.ndarray:
    """(35,) the truth's pose of the sequence's first frame; UserError where there is none."""
    truth = seq.truth()
    if truth is None or seq.frames[0] not in truth:
        raise UserError(f"{seq.path}: --init truth needs truth.jsonl with frame {seq.frames[0]}")
    return truth[seq.frames[0]].params.copy()


def initial_starts(model: BodyModel, seq: Sequence, data: FrameData, init: str) -> list[np.ndarray]:
    """The first frame's start poses: 'truth' (the sequence's truth), 'auto' (automatic
    initialisation from the frame's voxels, several starts) or 'standing' at the silhouettes."""
    if init == "truth":
        return [truth_start(seq)]
    if init == "standing":
        centre = silhouette_centre(data)
        return [rest_params(model, position=(centre[0], centre[1], model.joint_rest[0, 2]))]
    if init == "auto":
        return voxel_starts(model, data)
    raise UserError(f"unknown --init {init!r}")

# Actor sizes the first frame is tried at when the actor's height is not given, over the body
# model's own (1.67 m): adults of about 1.5 to 2.3 m in the calibration's units. A rig calibrated
# with a mis-measured board scales everyone: the seated take's sitter is fitted best at 1.4 (hips bent
# 74-76 degrees, `make real-test`); at 1.3, the largest size tried before 2026-12-02, 42-51.
ACTOR_SCALES = (0.9, 1.0, 1.1, 1.2, 1.3, 1.4)
# Another size is taken only where its fit scores this much less than the model's own size:
# the same pose fitted again at a nearby size moves the score by a few per cent either way
# (a crouch with Cheung noise, 1.0 truth: 1.7% less at 0.9), a body really too small by much
# more (the seated take: 28% less at 1.4).
ACTOR_SCALE_MIN_GAIN = 0.05


def context(model: BodyModel, data: FrameData, frame: int, options: FitOptions, solver: Solver,
            **kw) -> Context:
    """A search context for ``frame`` whose jobs go to ``solver`` (told of the frame here)."""
    solver.begin_frame(frame, data, kw.get("start", rest_params(model)), options)
    return Context(model, data, options, solver.solve, int(frame), side_by_side=solver.workers(), **kw)


@dataclass(frozen=True)
class ActorSize:
    """What the actor-size search found: the actor's ``scale`` over the body model's, and, for
    the first frame's search at the model's own size, the ``frame``, its voxel ``starts`` and the
    fits already made (``memo``, as ``common.search.run_schedule``'s), so the search does not
    fit them again; ``seconds`` it took."""

    scale: float
    frame: int
    starts: tuple
    memo: dict
    seconds: float


def choose_actor_scale(model: BodyModel, seq: Sequence, options: FitOptions, threads: int = 1,
                       schedules: Schedules = SCHEDULES) -> ActorSize:
    """The actor's size over ``model``'s, chosen by the silhouettes of the first frame: the
    first frame searched once at the model's size (the wide schedule, WIDE: every start, one way of
    re-detecting limbs), then its best pose fitted again at ACTOR_SCALES outward from the
    model's size while the score keeps falling (the pelvis height scaled along;
    ``descend_outward``), and the size whose fit explains the masks best (lowest
    ``size_score`` over the model's own size's on that side: a larger size's counts the model
    outside the silhouettes twice, a smaller one's does not) kept if it beats the model's own
    size by ACTOR_SCALE_MIN_GAIN. The score
    falls steadily towards the actor's size (the seated take: 37.6k at 1.0 down to 27.0k at
    1.4), so stopping where it rises fits two sizes for an actor of the model's size, not five.
    Why: real subjects are not the body model's size, and a body too small for its silhouettes
    folds into them wrongly (the seated take, fitted at 1.67 m, stood). ``threads``: the
    starts and the sizes are fitted that many at once."""
    t0 = time.perf_counter()
    frame = seq.frames[0]
    data = frame_data(model, seq, frame)
    solver = LocalSolver(model, options, threads)
    try:
        starts, memo = tuple(voxel_starts(model, data)), {}
        found = run_schedule(context(model, data, frame, options, solver, starts=starts), schedules.wide, memo=memo)
        own = {larger: max(size_score(data, found, larger), 1.0) for larger in (False, True)}

        def relative_score(scale: float) -> float:
            larger = scale > 1.0
            return size_score(*fit_at_scale(model, seq, frame, found.params, scale, options)[1:], larger) / own[larger]

        scores = descend_outward(ACTOR_SCALES, 1.0, 1.0, lambda scales: solver.map(relative_score, scales))
    finally:
        solver.close()
    lowest_scale = min(sorted(scores), key=scores.get)  # on a tie, the smaller size
    clear_gain = scores[lowest_scale] < 1.0 - ACTOR_SCALE_MIN_GAIN
    return ActorSize(lowest_scale if clear_gain else 1.0, frame, starts, memo, time.perf_counter() - t0)


def fit_at_scale(model: BodyModel, seq: Sequence, frame: int, params: np.ndarray, scale: float,
                 options: FitOptions) -> tuple[BodyModel, FrameData, FrameResult]:
    """(the actor, its frame data, the fit): ``params`` (35,), a fit of ``frame`` at ``model``'s
    size, fitted again with the body scaled by ``scale`` (the pelvis height scaled along)."""
    actor = model.scaled(scale)
    start = np.array(params, dtype=np.float64)
    start[P["root_z"]] *= scale
    data = frame_data(actor, seq, frame)
    wide = VARIANTS["wide-round"](options)
    return actor, data, fit_rounds(actor, data, start, wide, solve_locally(actor, data, wide, frame))


def recovery_starts(model: BodyModel, data: FrameData) -> list[np.ndarray]:
    """Start poses from the frame's voxels, or none where they give none (no actor in view)."""
    try:
        return voxel_starts(model, data)
    except UserError:
        return []


def track(model: BodyModel, data: FrameData, frame: int, start: np.ndarray, before: np.ndarray | None,
          energies: list, options: FitOptions, solver: Solver, progress=None, note=None,
          schedules: Schedules = SCHEDULES) -> tuple[FrameResult, bool, bool]:
    """One frame tracked from ``start`` (the previous frame's fit; ``before``, the one before),
    with ``energies`` the frames' so far: (fit, limbs re-detected, recovered from voxels)."""
    ctx = context(model, data, frame, options, solver, start=np.asarray(start, dtype=np.float64), before=before)
    result = fit_frame(model, data, ctx.start, options, ctx.dispatch, before=before, frame_number=frame,
                       schedules=schedules)
    limbs_redetected = recovered = False
    if tracking_lost(energies, result.energy, schedules.limb_loss_ratio):  # a limb lost: every limb searched
        again = run_schedule(Context(model, data, options, ctx.dispatch, frame, start=result.params),
                             schedules.limbs_lost, initial=result)
        limbs_redetected = again.energy < result.energy
        result = again
    starts = recovery_starts(model, data) if tracking_lost(energies, result.energy, schedules.loss_ratio) else []
    if starts:  # the whole body lost: start again from the voxels, as on a first frame
        if note:
            note(f"frame {frame}: tracking lost, searching from voxels")
        again = search_frame(model, data, starts, options, ctx.dispatch, frame, solver.workers(), schedules=schedules)
        # the voxels' headings are those of one turn: the fit's kept within a half turn of the
        # track's, so that the frames' headings run on
        heading = again.params.copy()
        heading[P["root_heading"]] = nearest_turn(heading[P["root_heading"]], ctx.start[P["root_heading"]])
        again = replace(again, params=heading)
        recovered = again.energy < result.energy
        result = lowest([result, again])
    return result, limbs_redetected, recovered



def run_settings(model: BodyModel, seq: Sequence, options: FitOptions, init: str,
                 schedules: Schedules = SCHEDULES) -> dict:
    """What decides a run's poses: written to run.json, and what ``--resume`` must match (the
    cameras left out, and the schedules not the defaults, named only where there are some, so
    that older runs resume)."""
    left_out = {"cameras_left_out": list(seq.left_out)} if seq.left_out else {}
    table, defaults = schedules_table(schedules), schedules_table(SCHEDULES)
    changed = {name: value for name, value in table.items() if value != defaults[name]}
    own = {"schedules": changed} if changed else {}
    return {"sequence": str(seq.path.resolve()), **sequence_calibration(seq), **left_out, "init": init,
            "world_up": seq.world.up,
            "masks_cleaned": seq.clean_masks, "mask_threshold": seq.mask_threshold,
            "actor_scale": model_scale(model), "options": options.to_wire(), **own}


def sequence_calibration(seq: Sequence) -> dict:
    """{"calibration": path} where the sequence was read with a calibration not its own (what
    the result's readers must read it with again), else {}."""
    return {"calibration": str(seq.calibration.resolve())} if seq.calibration is not None else {}


def frame_data(model: BodyModel, seq: Sequence, frame: int) -> FrameData:
    """One frame's FrameData: the sequence's silhouettes in its fit-frame studio."""
    return FrameData(model, seq.studio, seq.silhouettes(frame))


def user_joints(model: BodyModel, seq: Sequence, params: np.ndarray) -> dict:
    """{joint: [x, y, z]} of ``params`` (fit frame), in the user's world frame (``seq.world``)."""
    return joints_dict(seq.world.points_to_user(forward_kinematics(model, params).joints[0]))


def model_scale(model: BodyModel) -> float:
    """The actor's size over the body model's own: the factor it was scaled by, exactly, so that
    a resumed run rebuilds the same model from run.json (its height over the default body's
    differs in the last digits, and a body 1e-7 larger fits another pose in the end)."""
    return float(model.scale / load_body_model().scale)


SETTLE_FRAMES = 10  # frames tracked after a first-frame search before it is refined backwards (online runs)


def refine_chunks(order: list[int], chunk_frames: int) -> list[list[int]]:
    """A refinement pass's frame indices, in its order, cut into chunks of about
    ``chunk_frames`` (0: one chunk) in that order."""
    count = len(order)
    chunks = max(1, -(-count // chunk_frames)) if chunk_frames > 0 else 1
    bounds = [round(j * count / chunks) for j in range(chunks + 1)]
    return [order[bounds[j]:bounds[j + 1]] for j in range(chunks) if bounds[j + 1] > bounds[j]]


def refine_pass(model: BodyModel, seq: Sequence, records: list[dict], options: FitOptions, solver: Solver,
                stats: RunStats, backward: bool = True, progress=None, search: bool = False,
                hops: int = 0, anchor: np.ndarray | None = None, start_hops: int | None = None,
                schedules: Schedules = SCHEDULES) -> tuple[list[dict], int]:
    """Fitted frames fitted again in one direction, each by ``common.search.refine_frame`` from
    its neighbour's fit: going backwards each frame starts from the (already refined) fit of the
    frame after it, forwards from the frame before; each keeps the lowest energy. The pass's
    first frame, which has no neighbour, is fitted by ``start_hops`` hops (None: the pass's own
    ``hops``, else the schedules' ``pass_start_hops``) and from its limbs' other basins, unless
    ``anchor`` (35,) is the fit of the frame beyond it, which the pass then starts from (a run
    without refinement carrying its settled tracking back over the frames after a first-frame
    search). With ``search``, each frame is also fitted from each limb's other basins (tracking and
    its neighbours can share a torso and limb that are off together: basketball frame 84, the left
    ankle 74 mm off, an alternative leg 1.8% lower in energy). With ``hops`` > 0, every frame also
    gets that many hops, seeded by its frame number; a cluster's clients run them side by side.

    ``options.refine_chunk_frames`` > 0 cuts the take into chunks of about that many frames
    (``refine_chunks``) refined side by side on a single process's threads (one after another
    on a cluster, whose clients take each frame's jobs). A chunk starts from the fit its
    neighbour had before the pass; where chunks meet, the chunk's first frame is fitted again
    from its neighbour's refined fit once every chunk is done. The chunks depend on the take and
    the setting alone, so the poses are the same for any number of threads or clients.

    A replaced record keeps its tracking fit under "first_pass" (params, joints, energy); the
    pass's time and evaluations add to "refine_seconds" and "refine_evaluations" ("seconds" and
    "evaluations" stay tracking's); hops counted (dropped ones too) and their compute seconds go
    to ``stats``. Returns the records, changed, and how many were replaced."""
    out = [dict(r) for r in records]
    before = [np.asarray(r["params"], dtype=np.float64) for r in records]  # the fits before this pass
    step = -1 if backward else 1
    order = list(range(len(out)))[::step]
    done, replaced, lock = [0], set(), threading.Lock()

    def refine_one(i: int, neighbour, beyond, frame_hops: int, own_thread: bool = False, basins: bool = search):
        """Frame i again from ``neighbour``; its record changed here; the search's result.
        ``own_thread``: a chunk's frame, its jobs one after another in the chunk's thread;
        ``basins``: also from its limbs' other basins (REFINE_SEARCH)."""
        r = out[i]
        t0 = time.perf_counter()
        ahead = i + step  # the neighbour on the other side, not yet refined in a pass without chunks
        other = before[ahead] if 0 <= ahead < len(out) else None
        data = frame_data(model, seq, r["frame"])
        tracked = record_fit(r)
        if own_thread:
            dispatch, at_once = solve_locally(model, data, options, int(r["frame"])), 1
        else:
            ctx = context(model, data, r["frame"], options, solver)
            dispatch, at_once = ctx.dispatch, ctx.side_by_side
        again = refine_frame(model, data, tracked, options, dispatch, neighbour, beyond, other, frame_hops,
                             basins, r["frame"], at_once, schedules=schedules)
        if keep_refit(model, seq, r, again, time.perf_counter() - t0):
            with lock:
                replaced.add(i)
        with lock:
            done[0] += 1
            if progress:
                progress(min(done[0], len(out)), len(out), f"refining {'backwards' if backward else 'forwards'}")
        return again

    searched = []
    neighbour = None if anchor is None else np.asarray(anchor, dtype=np.float64)
    if neighbour is None and order:  # the pass's first frame, by hops on every thread
        first_hops = start_hops if start_hops is not None else hops or schedules.pass_start_hops
        searched.append(refine_one(order[0], None, None, first_hops, basins=True))
        neighbour, order = np.asarray(out[order[0]]["params"], dtype=np.float64), order[1:]
    chunks = refine_chunks(order, options.refine_chunk_frames)
    side_by_side = isinstance(solver, LocalSolver) and solver.threads > 1 and len(chunks) > 1

    def refine_chunk(c: int) -> list:
        near = neighbour if c == 0 else before[chunks[c][0] - step]
        far, results = None, []
        for i in chunks[c]:
            results.append(refine_one(i, near, far, hops, side_by_side))
            far, near = near, np.asarray(out[i]["params"], dtype=np.float64)
        return results

    indices = range(len(chunks))
    searched += [a for part in (solver.map(refine_chunk, indices) if side_by_side else map(refine_chunk, indices))
                 for a in part]
    # where chunks meet: each later chunk's first frame from its neighbour's refined fit
    for chunk in chunks[1:]:
        i = chunk[0]
        far = np.asarray(out[i - 2 * step]["params"], dtype=np.float64) if 0 <= i - 2 * step < len(out) else None
        searched.append(refine_one(i, np.asarray(out[i - step]["params"], dtype=np.float64), far, hops))
    for again in searched:
        stats.add_chains([c for c in again.chains if is_chain_solve(c)])
        hopped = [c for c in again.chains if c.chain in HOP_JOBS]
        stats.hops_run += len(hopped)
        stats.hop_seconds += sum(c.wall_seconds for c in hopped)
    return out, len(replaced)


def tracking_fit(r: dict) -> dict:
    """A record's fit as tracking left it, for its "first_pass" when a later step replaces it:
    params, joints and tracking's energy (its "tracked_energy" where its energy was taken again
    against cleared masks, ``leave_out_unexplained``)."""
    return {"params": r["params"], "joints": r["joints"], "energy": r.get("tracked_energy", r["energy"])}


def record_fit(r: dict) -> FrameResult:
    """A record's pose and energy as the fit a refinement starts from (nothing spent on it here)."""
    return FrameResult(np.asarray(r["params"], dtype=np.float64), int(r["energy"]), 0, 0)


def keep_refit(model: BodyModel, seq: Sequence, r: dict, again: FrameResult, seconds: float) -> bool:
    """Record ``r`` refitted (``again``, in ``seconds``): its time and evaluations added, its fit
    replaced where ``again`` is lower (the tracking fit kept under "first_pass"); whether it was."""
    r["refine_seconds"] = r.get("refine_seconds", 0.0) + seconds
    r["refine_evaluations"] = r.get("refine_evaluations", 0) + again.evaluations
    if not again.energy < r["energy"]:
        return False
    r.setdefault("first_pass", tracking_fit(r))
    r["params"] = [float(v) for v in again.params]
    r["joints"] = user_joints(model, seq, again.params)
    r["energy"] = int(again.energy)
    return True


def refine_poor_windows(model: BodyModel, seq: Sequence, records: list[dict], options: FitOptions, solver: Solver,
                        stats: RunStats, progress=None, schedules: Schedules = SCHEDULES) -> tuple[list[dict], int]:
    """After the passes: the frames around each run of poor fits (``common.search.poor_windows``:
    the XOR share of the silhouette well above the take's median) refined once more, forwards
    from the fit before the window, then backwards from the fit after it (``refine_pass``, each
    frame also by the schedules' ``poor_window_hops`` hops; a window at the take's end starts from
    hops). A run the passes left in a valley of its own (the cartwheel rolling onto its side, where
    each frame fitted from a neighbour that is off stays off) is refined from both sides again, as
    further passes would, and searched more widely, at a few frames' cost. The volume energy is no
    XOR (metres squared): its fits are not judged so. A window's end frames are not also started
    from halfway to the frame beyond it. Returns the records, changed, and how many frames ended
    with a lower energy."""
    if options.energy == "volume":
        return records, 0
    shares = [r["energy"] / max(int(np.count_nonzero(seq.silhouettes(r["frame"]))), 1) for r in records]
    out = [dict(r) for r in records]
    for first, last in poor_windows(shares, schedules.poor_share_ratio):
        for backward in (False, True):
            beyond = last + 1 if backward else first - 1
            anchor = np.asarray(out[beyond]["params"], dtype=np.float64) if 0 <= beyond < len(out) else None
            out[first:last + 1], _ = refine_pass(model, seq, out[first:last + 1], options, solver, stats, backward,
                                                 progress, hops=schedules.poor_window_hops, anchor=anchor,
                                                 start_hops=schedules.pass_start_hops, schedules=schedules)
    return out, sum(1 for r, before in zip(out, records) if r["energy"] < before["energy"])


def refit_standing_out(model: BodyModel, seq: Sequence, records: list[dict], options: FitOptions, solver: Solver,
                       stats: RunStats, schedules: Schedules = SCHEDULES) -> tuple[list[dict], int]:
    """After the passes: each frame whose energy stands STANDING_OUT_RATIO above both neighbours'
    (``standing_out``) refined again from its neighbour before it, with the one after as the
    other side, both as the passes left them. A backward pass refines a frame from halfway to a
    neighbour that still has tracking's fit, and a frame tracking left far off between two good
    ones can keep its own (05_17 from source frame 401 with other noise, frame 80: the right
    forearm folded the wrong way, 428.8 mm; fitted again so, 39.7). Returns the records,
    changed, and how many were replaced."""
    out = [dict(r) for r in records]
    replaced = 0
    for i in standing_out([r["energy"] for r in records], schedules.standing_out_ratio):
        r = out[i]
        t0 = time.perf_counter()
        data = frame_data(model, seq, r["frame"])
        ctx = context(model, data, r["frame"], options, solver)
        tracked = record_fit(r)
        again = refine_frame(model, data, tracked, options, ctx.dispatch, np.asarray(records[i - 1]["params"]),
                             None, np.asarray(records[i + 1]["params"]), frame_number=r["frame"],
                             side_by_side=ctx.side_by_side, schedules=schedules)
        stats.add_chains([c for c in again.chains if is_chain_solve(c)])
        replaced += keep_refit(model, seq, r, again, time.perf_counter() - t0)
    return out, replaced


def finish_frames(model: BodyModel, seq: Sequence, records: list[dict], options: FitOptions, solver: Solver,
                  stats: RunStats, progress=None, schedules: Schedules = SCHEDULES) -> tuple[list[dict], int]:
    """After the refinement: every frame fitted once more on its own (``common.search.finish_frame``:
    evolutions over all 35 parameters from its fit, the lowest polished), each keeping the lowest
    energy. The volume energy is no XOR: its fits are left as they are. Returns the records,
    changed, and how many were replaced."""
    if options.energy == "volume" or schedules.finish_evolutions < 1:
        return records, 0
    out = [dict(r) for r in records]
    replaced = 0
    for n, r in enumerate(out):
        t0 = time.perf_counter()
        data = frame_data(model, seq, r["frame"])
        ctx = context(model, data, r["frame"], options, solver)
        again = finish_frame(model, data, record_fit(r), options, ctx.dispatch, r["frame"], schedules)
        stats.add_chains([c for c in again.chains if is_chain_solve(c)])
        replaced += keep_refit(model, seq, r, again, time.perf_counter() - t0)
        if progress:
            progress(n + 1, len(out), "finishing")
    return out, replaced


UNEXPLAINED_ROUNDS = 3  # the foreground found again from the fits it gave, while it grows


def unexplained_pixels(model: BodyModel, seq: Sequence, records: list[dict]) -> tuple[np.ndarray | None, float]:
    """(the pixels (K, H, W) bool of the fit's ideal images that the fitted bodies of ``records``
    miss in most frames (``common.consistency.unexplained_foreground``) or None, the mean
    silhouette pixels per frame), against ``seq``'s masks."""
    missed, area = None, 0
    for r in records:
        data = frame_data(model, seq, r["frame"])
        body = data.whole_image_energy().render(np.asarray(r["params"], dtype=np.float64))
        miss = (data.masks & ~body).astype(np.int32)
        missed = miss if missed is None else missed + miss
        area += int(np.count_nonzero(data.masks))
    mean_area = area / len(records)
    return unexplained_foreground(missed, len(records), mean_area), mean_area


def leave_out_unexplained(model: BodyModel, seq: Sequence, records: list[dict], options: FitOptions,
                          solver: Solver, stats: RunStats, progress=None,
                          schedules: Schedules = SCHEDULES) -> tuple[Sequence, list[dict], dict]:
    """After the passes: the foreground that the fitted bodies miss in most of the take's frames
    (``unexplained_pixels``: a chair the actor sits on, which is one 3D component with the actor
    and so no static prop) cleared from every frame's masks (``Sequence.without_foreground``),
    and the take refined again against them, backwards then forwards, each frame keeping the
    lowest energy against the cleared masks: a limb laid along the chair's back, which the
    masks paid for, has to be where the actor is. Where the new fits miss more (the chair's
    back, once fewer frames' arms lie on it), again, up to UNEXPLAINED_ROUNDS times. A record's
    "energy" is then against the cleared masks, and one that no pass replaced keeps tracking's
    under "tracked_energy" (``tracked_record``). Returns the sequence (cleared, or ``seq``
    itself where nothing is), the records and, where pixels were cleared, {"share": their number
    over the mean silhouette area, "frames_replaced": how many frames changed pose, "rounds":
    the rounds of passes, "round_shares": the share each round added} (else {})."""
    out, flags, cleared, added = records, None, seq, []
    while len(added) < UNEXPLAINED_ROUNDS:
        found, mean_area = unexplained_pixels(model, seq, out)
        new = found if found is None or flags is None else found & ~flags
        if new is None or not new.any():
            break
        added.append(round(float(new.sum() / mean_area), 4))
        flags = new if flags is None else flags | new
        cleared = seq.without_foreground(recorded_pixels(seq.studio, flags))
        out = [dict(r) for r in out]
        for r in out:  # the energies the passes compare against, at the cleared masks
            if "first_pass" not in r:
                r.setdefault("tracked_energy", r["energy"])
            r["energy"] = full_energy(model, frame_data(model, cleared, r["frame"]), np.asarray(r["params"]))
        for backward in (True, False):
            out, _ = refine_pass(model, cleared, out, options, solver, stats, backward, progress,
                                 start_hops=schedules.unexplained_start_hops, schedules=schedules)
    if flags is None:
        return seq, records, {}
    return cleared, out, {"share": round(float(flags.sum() / mean_area), 4), "rounds": len(added),
                          "round_shares": added,
                          "frames_replaced": sum(a["params"] != b["params"] for a, b in zip(records, out))}


def settle_records(model: BodyModel, seq: Sequence, records: list[dict]) -> tuple[list[dict], int, list[dict]]:
    """The refined records with each frame's pose chosen among its neighbours' fits by
    ``common.settle.settle_choice`` (a still actor's frames take one pose where the masks did
    not move). A frame that takes another frame's fit keeps its own under "first_pass" where it
    has none there yet, and names the frame under "settled_from". Returns the records, changed,
    how many took another frame's fit, and each frame's ``frame_quality`` at its pose (from the
    same pass over the masks, since loading and cleaning them costs as much as the settling;
    a frame that took another's pose has its masks read once more for its new quality)."""
    out = [dict(r) for r in records]
    params = np.array([r["params"] for r in records], dtype=np.float64)
    joints = forward_kinematics(model, params).joints                   # (T, J, 3) fit frame, m
    candidates = candidate_frames(len(records))
    energies = np.full(candidates.shape, np.inf)
    steps, quality, masks_before = [], [], None
    for t, r in enumerate(records):
        data = frame_data(model, seq, r["frame"])
        there = candidates[t] >= 0
        energies[t, there] = data.whole_image_energy()(params[candidates[t, there]])
        quality.append(frame_quality(data, params[t]))
        if masks_before is not None:
            steps.append(mask_step(masks_before, data.masks))
        masks_before = data.masks
    change, area = np.array(steps, dtype=np.float64).reshape(-1, 2).T
    index = settle_choice(energies, joints, candidates, change, area)
    moved = 0
    for t, c in enumerate(index):
        s = candidates[t, c]
        if records[s]["params"] == records[t]["params"]:  # its own fit, or the same pose held
            continue
        moved += 1
        r = out[t]
        r.setdefault("first_pass", tracking_fit(r))
        r["params"] = records[s]["params"]
        r["joints"] = records[s]["joints"]
        r["energy"] = whole_energy(energies[t, c])
        r["settled_from"] = int(records[s]["frame"])
        quality[t] = frame_quality(frame_data(model, seq, r["frame"]), params[s])
    return out, moved, quality


def run_fit(model: BodyModel, seq: Sequence, out_dir: Path, options: FitOptions, solver: Solver,
            init: str | None = None, resume: bool = False, max_frames: int | None = None, progress=None,
            overwrite: bool = False, actor_size: ActorSize | None = None, schedules: Schedules = SCHEDULES) -> dict:
    """Fit the sequence's frames in order; returns the summary (also written to summary.json).

    ``resume``: continue the frames of an earlier run there (same settings); ``overwrite``:
    replace an earlier result; with neither, an earlier result is refused before any work.
    ``actor_size``: the actor-size search that chose ``model`` (its time is counted in the wall
    time; at the model's own size its first-frame fits are reused by the first frame's search).
    ``schedules``: how each frame is searched (``common.search.Schedules``; a Config.toml's
    ``[fit.schedules]``).
    """
    frames = seq.frames[:max_frames] if max_frames else list(seq.frames)
    seq = usable_cameras(seq, frames)  # every mask there and readable before anything is written
    if len(seq.studio) < MIN_GOOD_CAMERAS:
        print_warning(f"{len(seq.studio)} camera(s): fewer than {MIN_GOOD_CAMERAS} views leave depth and the "
                      "limbs' sides unresolved; expect joint errors of several centimetres and frames off by up "
                      "to a metre (a walk in the virtual studio, 2 cameras: 63 mm mean, 858 mm worst; 3 "
                      "cameras: 7 mm, 21 mm)")
    truth = seq.truth()
    if init is None:  # the truth's first pose where there is one, else automatic initialisation
        init = "truth" if truth else "auto"
    if init == "truth":
        truth_start(seq)  # refused before the result folder is touched
    done = prepare_result_folder(out_dir, run_settings(model, seq, options, init, schedules), resume, overwrite)
    if done and [d["frame"] for d in done] != frames[:len(done)]:
        raise InputFileError(out_dir / POSES_FILE, f"does not hold the first frames of {seq.path}; cannot --resume")
    if done and len(done) == len(frames) and (finished := finished_summary(out_dir, len(frames))):
        return finished  # resumed after its end: refining it again would change the poses exports were made of
    poses_path = out_dir / POSES_FILE
    stats = RunStats()
    wall0 = time.perf_counter()
    # tracking goes on from tracking's fits, as the run would have (settling after a search
    # replaces the first frames' records, not the poses tracking goes on from), and from the
    # energies as written (settled ones too, as the run's)
    tracked = [tracked_record(d) for d in done]
    x = np.asarray(tracked[-1]["params"], dtype=np.float64) if done else None
    x_before = np.asarray(tracked[-2]["params"], dtype=np.float64) if len(done) > 1 else None
    energies = [int(d["energy"]) for d in done]
    # a run that starts from a search goes back over its first frames once tracking has settled;
    # the refinement passes after tracking do that and more
    settle_index = min(SETTLE_FRAMES, len(frames) - 1) if init != "truth" and not options.refine_passes else -1
    # the next frame's masks cleaned (seq.cleaned, 0.07 s for 8 cameras of 320x240) on a thread of
    # their own while this frame is fitted: a single process has a core to spare during the
    # torso's solves. Not on a cluster's server: the cleaning holds the interpreter's lock for
    # milliseconds at a time (scipy.ndimage), which its broker thread would wait through
    ahead = ThreadPoolExecutor(1, thread_name_prefix="masks") if seq.clean_masks and solver.mode == "single" else None
    for n, frame in enumerate(frames[len(done):], start=len(done)):
        t0 = time.perf_counter()
        data = frame_data(model, seq, frame)
        if ahead is not None and n + 1 < len(frames):
            ahead.submit(seq.cleaned, frames[n + 1])
        if x is None and init == "truth":
            x = initial_starts(model, seq, data, init)[0]
        if x is None:
            if progress:
                progress(n, len(frames), f"frame {frame}: first-frame search ({init} start)")
            ctx = context(model, data, frame, options, solver)
            # the actor-size search fitted this frame's voxel starts at this model's size already
            # (fits of the same starts under the same first stage: a start is keyed by its variant alone)
            known = actor_size if (init == "auto" and actor_size and actor_size.scale == 1.0
                                   and actor_size.frame == frame
                                   and schedules.wide.stages[0] == schedules.search.stages[0]) else None
            result = search_frame(model, data, known.starts if known else initial_starts(model, seq, data, init),
                                  options, ctx.dispatch, frame, ctx.side_by_side, memo=known.memo if known else None,
                                  schedules=schedules)
            recovered = limbs_redetected = False
        else:
            result, limbs_redetected, recovered = track(
                model, data, frame, x, x_before, energies, options, solver,
                note=(lambda text: progress(n, len(frames), text)) if progress else None, schedules=schedules)
        energies.append(result.energy)
        x_before, x = x, result.params
        seconds = time.perf_counter() - t0
        chains = [c for c in result.chains if is_chain_solve(c)]  # not hops or whole fits
        record = {
            "frame": int(frame), "params": [float(v) for v in x], "joints": user_joints(model, seq, x),
            "actor_scale": model_scale(model), "world_up": seq.world.up,
            "energy": int(result.energy), "seconds": seconds, "iterations": result.iterations,
            "evaluations": result.evaluations, "recovered": recovered,
            "limbs_redetected": limbs_redetected,
            "chains": chain_totals(chains),
            # jobs beside the chain solves: whole fits of a round's starts, hops (dropped ones too)
            "whole_fits": sum(c.chain in FIT_JOBS for c in result.chains),
            "hops": sum(c.chain in HOP_JOBS for c in result.chains),
            "solves": [{"chain": c.chain, "iteration": i // len(SOLVES_PER_ITERATION), "evaluations": c.evaluations,
                        "energy_before": c.energy_before, "energy": c.energy, "cpu_seconds": c.cpu_seconds,
                        "wall_seconds": c.wall_seconds} for i, c in enumerate(chains)],
        }
        with open(poses_path, "a") as fh:  # reopened per frame: a refinement pass replaces the file
            fh.write(json.dumps(record) + "\n")
        stats.seconds.append(seconds)
        stats.evaluations.append(result.evaluations)
        stats.add_chains(chains)
        if n == settle_index > 0:
            if progress:
                progress(n + 1, len(frames), f"refining frames {frames[0]}-{frames[n - 1]} backwards")
            *before, last = read_done_frames(poses_path)
            refined, _ = refine_pass(model, seq, before, options, solver, stats, anchor=np.asarray(last["params"]),
                                     schedules=schedules)
            settled = refined + [last]
            rewrite_complete(poses_path, settled)
            energies = [int(r["energy"]) for r in settled]
        if progress:
            progress(n + 1, len(frames), f"E={result.energy}")
    if ahead is not None:
        ahead.shutdown(wait=True)
    records = read_done_frames(poses_path)
    if options.refine_passes:  # a resumed run's refinement starts again from tracking's fits, as the run's did
        records = [tracked_record(r) for r in records]
    passes = []
    for k in range(options.refine_passes if len(records) > 1 else 0):
        t0, hops_before, hop_seconds_before = time.perf_counter(), stats.hops_run, stats.hop_seconds
        backward = k % 2 == 0
        search = options.refine_search and k == 0
        hops = options.refine_hops if k == 0 else 0
        records, replaced = refine_pass(model, seq, records, options, solver, stats, backward, progress, search,
                                        hops, schedules=schedules)
        rewrite_complete(poses_path, records)  # each pass kept whole: an interrupted run keeps the last
        passes.append({"direction": "backward" if backward else "forward", "search": search, "hops": hops,
                       # more than hops x frames where hops ran side by side and some were dropped
                       "hops_run": stats.hops_run - hops_before,
                       "hop_seconds": stats.hop_seconds - hop_seconds_before,
                       "frames_replaced": replaced, "seconds": time.perf_counter() - t0})
    standing_out_refitted = poor_refined = finished = 0
    finish_seconds = 0.0
    left_out = {}
    if passes:
        records, poor_refined = refine_poor_windows(model, seq, records, options, solver, stats, progress, schedules)
        records, standing_out_refitted = refit_standing_out(model, seq, records, options, solver, stats, schedules)
        uncleared = seq
        seq, records, left_out = leave_out_unexplained(model, seq, records, options, solver, stats, progress,
                                                       schedules)
        t0 = time.perf_counter()
        records, finished = finish_frames(model, seq, records, options, solver, stats, progress, schedules)
        finish_seconds = time.perf_counter() - t0
        rewrite_complete(poses_path, records)
    write_foreground_left_out(out_dir, seq.foreground_left_out)
    settled, refined = 0, sum(1 for r in records if "first_pass" in r)
    if passes:  # offline runs only: a frame's pose may come from a later frame's fit
        records, settled, quality = settle_records(model, seq, records)
    else:
        quality = [frame_quality(frame_data(model, seq, r["frame"]), r["params"]) for r in records]
    records = [r | {"fit_quality": q} for r, q in zip(records, quality)]
    rewrite_complete(poses_path, records)
    if left_out:  # the fit against the masks before the clearing too: clearing must not hide a wrong pose
        # (one more pass over every frame's masks, only where something was cleared)
        before = [{"frame": r["frame"], "fit_quality": frame_quality(frame_data(model, uncleared, r["frame"]),
                                                                    r["params"])} for r in records]
        shares = quality_summary(before, seq.studio.names)
        left_out = left_out | {"fit_quality_before_clearing": {
            k: shares[k] for k in ("mean_xor_share", "max_xor_share", "per_camera_mean_xor_share")}}
    wall = time.perf_counter() - wall0 + (actor_size.seconds if actor_size else 0.0)
    summary = {
        "sequence": str(seq.path.resolve()), **sequence_calibration(seq),
        "cameras": list(seq.studio.names), "cameras_left_out": list(seq.left_out),
        "world_up": seq.world.up,
        "masks_cleaned": seq.clean_masks,
        # the volume of the static props removed from the masks (common.consistency), m^3; 0 without
        "static_props_m3": round(props.volume_m3, 4) if seq.clean_masks and (props := seq.static_props) else 0.0,
        "actor_scale": model_scale(model),
        "frames": len(records),
        "frames_fitted_this_run": len(stats.seconds),
        "mode": solver.mode,
        "clients": solver.clients,
        "threads": solver.workers() if solver.mode == "single" else 1,
        "energy_backend": options.energy,
        "init": init,
        # tracking, the paper's measure; the refinement passes are timed apart
        "seconds_per_frame": float(np.median(stats.seconds)) if stats.seconds else None,
        "mean_seconds_per_frame": float(np.mean(stats.seconds)) if stats.seconds else None,
        "refine_seconds_per_frame": sum(p["seconds"] for p in passes) / len(records) if passes else 0.0,
        "refinement_passes": passes,
        "finish_seconds_per_frame": finish_seconds / len(records),
        # with the actor-size search, which a user waits for too
        "wall_seconds": wall,
        "actor_size_seconds": actor_size.seconds if actor_size else 0.0,
        # this run's wall time and, after a --resume, the tracking time the earlier runs spent on
        # the frames they left (refinement runs again over every frame; their actor-size search
        # is not counted)
        "take_seconds": wall + sum(float(d.get("seconds") or 0.0) for d in done),
        "evaluations_per_frame": float(np.mean(stats.evaluations)) if stats.evaluations else None,
        "frames_recovered": sum(1 for r in records if r.get("recovered")),
        "frames_limbs_redetected": sum(1 for r in records if r.get("limbs_redetected")),
        "frames_refined": refined,
        "frames_poor_refined": poor_refined,
        "frames_standing_out_refitted": standing_out_refitted,
        "frames_finished": finished,  # lowered by the finish's evolutions (finish_frames)
        # foreground no fitted pose explains, cleared from the masks (leave_out_unexplained)
        "foreground_left_out": left_out,
        "frames_settled": settled,
        "chain_cpu_seconds_per_frame": {c: v / max(len(stats.seconds), 1) for c, v in stats.chain_cpu.items()},
        "chain_wall_seconds_per_frame": {c: v / max(len(stats.seconds), 1) for c, v in stats.chain_wall.items()},
        "chain_evaluations_per_frame": {c: v / max(len(stats.seconds), 1) for c, v in stats.chain_evaluations.items()},
        "options": options.to_wire(),
        "timing": solver.timing(),
        "fit_quality": quality_summary(records, seq.studio.names),
        **accuracy(records, truth),
        # the same before refinement: each frame as tracking left it
        **{f"tracking_{k}": v for k, v in accuracy([r.get("first_pass", r) | {"frame": r["frame"]} for r in records],
                                                   truth).items() if k != "per_joint_error_mm"},
    }
    write_text(out_dir / SUMMARY_FILE, json.dumps(summary, indent=1))
    return summary


# what refinement and settling add to a record (``refine_pass``, ``settle_records``), and the
# quality measured at the end
AFTER_TRACKING_FIELDS = ("first_pass", "refine_seconds", "refine_evaluations", "settled_from", "fit_quality",
                         "tracked_energy")


def tracked_record(record: dict) -> dict:
    """``record`` as tracking wrote it: a pose that refinement or settling replaced put back
    (its "first_pass"), their fields dropped. A run stopped after a refinement pass was written
    (each pass rewrites poses.jsonl whole) is refined again from tracking's fits when resumed,
    so it ends as the run would have; the same record where tracking's fit was kept."""
    out = {k: v for k, v in record.items() if k not in AFTER_TRACKING_FIELDS}
    if "tracked_energy" in record:
        out["energy"] = record["tracked_energy"]
    return out | record.get("first_pass", {})


def finished_summary(out_dir: Path, frames: int) -> dict | None:
    """The summary of a run in ``out_dir`` that finished with ``frames`` frames (written last,
    after its refinement), marked ``"already_complete"``; None where that run has not finished."""
    try:
        summary = json.loads((out_dir / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return None
    return summary | {"already_complete": True} if isinstance(summary, dict) and summary.get("frames") == frames else None


def refinement_note(summary: dict) -> str:
    """'(N passes[, the first searching[ and hopping]], K frames improved[, S settled on another
    frame's pose])' for a summary whose run refined (``mocap fit``'s table, the report)."""
    passes = summary["refinement_passes"]
    n = len(passes)
    extra = " and ".join(word for word, on in (("searching", passes[0].get("search")),
                                               ("hopping", passes[0].get("hops"))) if on)
    extra = f", {'the first ' if n > 1 else ''}{extra}" if extra else ""
    settled = summary.get("frames_settled", 0)
    settled = f", {settled} settled on another frame's pose" if settled else ""
    return f"({n} pass{'es' if n > 1 else ''}{extra}, {counted(summary.get('frames_refined', 0), 'frame')} improved{settled})"


def tracking_error_note(summary: dict) -> str:
    """'MEAN / MAX mm': a refined run's joint error as tracking left its frames."""
    return f"{summary['tracking_mean_joint_error_mm']:.1f} / {summary['tracking_max_joint_error_mm']:.1f} mm"


# the XOR's missed side this many times its outside side: the masks hold more than the body
MOSTLY_MISSED = 3.0
# ... and over this share of the masks: the body is not where the masks are (a calibration in
# metres read as millimetres put the body 234 m from the seated take's actor: 100% missed)
LOST_MISSED = 0.8


def masks_cleared_note(left_out: dict) -> str:
    """What ``leave_out_unexplained`` cleared (summary.json's "foreground_left_out"), as the fit's
    table and the report say it."""
    before = left_out.get("fit_quality_before_clearing", {})
    return (f"{left_out['share']:.0%} of the silhouette area that no fitted pose explains in "
            f"{UNEXPLAINED_FRAMES_SHARE:.0%} of the frames (a prop the actor touches), cleared from the masks; "
            f"{counted(left_out['frames_replaced'], 'frame')} changed pose"
            + (f"; XOR {before['mean_xor_share']:.0%} of the masks before the clearing" if before else ""))


def xor_sides(quality: dict) -> str:
    """The fit quality's XOR split into its two sides, as the report says it: the body outside
    the masks (a pose wrong where it shows), the masks the body misses (a limb not found, or
    foreground no body explains: props sat on, shadows, a larger actor)."""
    outside, missed = quality["mean_outside_share"], quality["mean_missed_share"]
    text = f"body outside the masks {outside:.0%}, masks the body misses {missed:.0%}"
    if missed > LOST_MISSED:  # no pose misses this much of an actor that is where the masks are
        text += (" (the body is mostly not where the masks are: check the calibration's units and up axis, "
                 "and the overlays)")
    elif missed > MOSTLY_MISSED * outside:
        text += " (mostly foreground no body part covers: a prop, shadows, loose clothes; see the overlays)"
    return text
