"""The server's frame loop: fit every frame of a sequence, write results frame by frame.

The torso and head are solved here; limb chains go to a ``Solver`` (local, or a cluster of
clients). A frame whose energy jumps above the recent frames' is a loss of tracking: it is
fitted again from its voxels, as a first frame is, and the better fit kept. After tracking,
``options.refine_passes`` passes fit every frame again from its neighbour's fit, backwards then
forwards alternately (``refine_pass``); with none, a run that starts from a search (no truth)
still fits its first frames again backwards once tracking has settled. ``mocap fit`` is this
loop with the local solver: single-process mode is the server with zero clients.

Result folder:
    poses.jsonl   one line per frame: frame, params, joints, energy, seconds, ... (appended
                  per frame, so an interrupted run keeps what it had and --resume continues
                  after the last complete line; replaced whole after each refinement pass,
                  a replaced frame keeping its tracking fit under "first_pass")
    summary.json  run summary, accuracy against truth.jsonl when the sequence has one
    motion.bvh    the fitted motion
"""
from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from common import voxels
from common.body import (JOINT_NAMES, LIMB_CHAINS, MIRROR_SIGNS, P, BodyModel, forward_kinematics, joints_dict,
                         clip_to_limits, load_body_model, rest_params, swap_sides)
from common.errors import InputFileError, UserError, print_warning
from common.fitting import (ARM_CHAINS, HOP_JOBS, ChainResult, FitOptions, FrameData, FrameResult,
                            arm_twist_alternative, fit_frame, full_energy, hop_fit, limb_alternatives,
                            lowest_energy, midway, powell, rotated_about_pelvis, solve_job, spot_grid, tilted_ahead)
from common.postures import SEARCH_POSTURES, posture_params
from common.export import FORMATS, export_name
from common.sequence import Sequence
from server.output import check_folder_target, write_text

POSES_FILE = "poses.jsonl"
SUMMARY_FILE = "summary.json"
RUN_FILE = "run.json"  # the settings of the run that wrote poses.jsonl, which --resume must match
MOTION_FILE = "motion.bvh"
RESULT_FILES = (POSES_FILE, SUMMARY_FILE, RUN_FILE, MOTION_FILE)
# made from a result, so stale once it is replaced (mocap report, mocap export's default names)
DERIVED_FILES = ("report.html", "pictures") + tuple(export_name(f) for f in FORMATS if export_name(f) != MOTION_FILE)
# fewer views leave depth and the limbs' sides unresolved (tools/camera_count_accuracy.py,
# docs/accuracy.md "Fewer cameras": a walk fits 95/908 mm mean/worst with 1 camera, 63/858 with 2,
# 7/21 with 3)
MIN_GOOD_CAMERAS = 3
FIRST_FRAME_ITERATIONS = 6      # torso -> limbs rounds for a first frame started without truth
FIRST_FRAME_GRID_STEPS = 5      # limb grid points per parameter, first frame
FIRST_FRAME_GRID_RANGE = 1.0    # radians, +- limb grid half-width, first frame
FIRST_FRAME_LIMB_WINDOW = 400   # pixels: the limb may be far from where the start pose puts it
# both ways of re-detecting the limbs of a first frame (common.fitting.REDETECT_TURNS); on 7
# hard first frames neither wins everywhere, together all 7 are within 50 mm
FIRST_FRAME_REDETECT_TURNS = ("round", "all")


def first_frame_options(options: FitOptions, redetect_turn: str) -> FitOptions:
    """A start pose from voxels can have a limb far off: search limbs widely, in big windows,
    re-detect them ``redetect_turn`` (one of FIRST_FRAME_REDETECT_TURNS) and iterate the
    first frame to convergence. No turn hypotheses: the starts come at the headings the voxels
    give, and each is fitted again from its result; the tracking fit that ends the search
    (``search_frame``) has them. No polishing either: up to FIRST_FRAME_ITERATIONS rounds
    already run each fit to convergence, and polishing made the first frame 25% slower."""
    return replace(options, max_iterations=max(options.max_iterations, FIRST_FRAME_ITERATIONS),
                   grid_steps=FIRST_FRAME_GRID_STEPS, grid_range_rad=FIRST_FRAME_GRID_RANGE,
                   limb_window_px=FIRST_FRAME_LIMB_WINDOW, hinge_grid_full_range=True,
                   redetect_turn=redetect_turn, turn_hypotheses=0, polish_iterations=0)


class Solver(Protocol):
    """Who solves the limb chains and hops: this process, or clients over the network."""

    mode: str
    clients: int

    def begin_frame(self, frame: int, data: FrameData, start: np.ndarray, options: FitOptions) -> None:
        """A new frame: its silhouettes, start pose and the options its chains are solved with."""

    def solve(self, chains: list, params: np.ndarray, iteration: int) -> Callable[[], list]:
        """Start solving ``chains`` (or hops, ``common.fitting.solve_job``) from ``params``;
        the returned function waits for the results."""

    def workers(self) -> int:
        """How many jobs it solves at once (clients, and the server beside them)."""

    def timing(self) -> dict: ...

    def close(self) -> None: ...


class LocalSolver:
    """Single-process mode: the same chain solves, run here in a fixed order."""

    mode = "single"
    clients = 0

    def __init__(self, model: BodyModel, options: FitOptions):
        self.model, self.options = model, options
        self.data: FrameData | None = None
        self.compute_seconds = 0.0

    def begin_frame(self, frame: int, data: FrameData, start: np.ndarray, options: FitOptions) -> None:
        self.data, self.frame = data, int(frame)
        self.frame_options = options

    def solve(self, chains: list, params: np.ndarray, iteration: int) -> Callable[[], list]:
        data, options, frame = self.data, self.frame_options, self.frame

        def collect() -> list:
            t0 = time.perf_counter()
            out = [solve_job(self.model, data, c, params, options, iteration, frame) for c in chains]
            self.compute_seconds += time.perf_counter() - t0
            return out

        return collect

    def workers(self) -> int:
        return 1

    def timing(self) -> dict:
        return {"processes": []}

    def close(self) -> None:
        pass


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
    """Per chain over a frame's iterations: evaluations and seconds summed, energy first -> last."""
    out: dict = {}
    for c in chains:
        t = out.setdefault(c.chain, {"evaluations": 0, "energy_before": c.energy_before, "energy": c.energy,
                                     "cpu_seconds": 0.0, "wall_seconds": 0.0})
        t["evaluations"] += c.evaluations
        t["cpu_seconds"] += c.cpu_seconds
        t["wall_seconds"] += c.wall_seconds
        t["energy"] = c.energy
    return out


def silhouette_centre(data: FrameData) -> np.ndarray:
    """(3,) where the rays through the silhouettes' centroids meet (the actor, roughly)."""
    centre = voxels.silhouette_centre(data.studio, data.masks)
    if centre is None:
        raise UserError("cannot locate the actor: fewer than two cameras see a silhouette in the first frame")
    return centre


def initial_starts(model: BodyModel, seq: Sequence, data: FrameData, init: str) -> list[np.ndarray]:
    """The first frame's start poses: 'truth' (the sequence's truth), 'auto' (automatic
    initialisation from the frame's voxels, several starts) or 'standing' at the silhouettes."""
    if init == "truth":
        truth = seq.truth()
        if truth is None or seq.frames[0] not in truth:
            raise UserError(f"{seq.path}: --init truth needs truth.jsonl with frame {seq.frames[0]}")
        return [truth[seq.frames[0]].params.copy()]
    if init == "standing":
        centre = silhouette_centre(data)
        return [rest_params(model, position=(centre[0], centre[1], model.joint_rest[0, 2]))]
    if init == "auto":
        return voxel_starts(model, data)
    raise UserError(f"unknown --init {init!r}")


VOXEL_INIT_GRID = 64  # voxels per side for the first-frame initialisation
# Standing starts beside the voxel fit's poses, per heading: upright, and bent forward at the
# hips (a player dribbling): a crouch or a bent trunk misleads the voxel fit's pelvis (it
# settles 0.3 m low, legs folded), and the silhouette fit cannot climb out of that.
STANDING_START_TILTS_RAD = (0.0, 0.8)
# ... and per voxel-fit heading, also turned a quarter: the heading comes from the widest
# horizontal direction of the chest's voxels, which a hull carved by few views gets wrong (06_02
# from source frame 262, the actor in five of eight views: 0.9 rad off, the search 242 mm off;
# with the quarter turns 54 mm)
STANDING_START_TURNS_RAD = (0.0, np.pi / 2)


def voxel_starts(model: BodyModel, data: FrameData) -> list[np.ndarray]:
    """Start poses from the frame's SPOT voxels and ellipsoids (Cheung et al.; Bottino's volume
    fitting), for a sequence without truth or T-pose: the voxel fit's front and back
    candidates; then a standing pose at each one's position, at its heading and a quarter turn
    from it (STANDING_START_TURNS_RAD), per STANDING_START_TILTS_RAD; then rest poses head down
    along the trunk's shell (``head_down_starts``: a cartwheel, a handstand).
    ``fit_from_starts`` lets the silhouettes choose."""
    from common.ellipsoid_fit import head_down_starts, initial_pose as fit_to_voxels

    grid = spot_grid(data.studio, data.masks, VOXEL_INIT_GRID).reconstruct(data.masks)
    # front or back: the silhouettes tell them apart better than the voxels' volume energy
    silhouette_energy = data.whole_image_energy()
    try:
        init = fit_to_voxels(grid, model, score=silhouette_energy)
    except ValueError as exc:
        raise UserError(f"automatic initialisation failed on the first frame: {exc}") from None
    starts = [c.copy() for c in init.candidates]
    for c in init.candidates:
        for turn in STANDING_START_TURNS_RAD:
            for tilt in STANDING_START_TILTS_RAD:
                standing = rest_params(model, position=(c[0], c[1], model.joint_rest[0, 2]), heading=c[3] + turn)
                standing[P["root_tilt_x"]] = tilt
                starts.append(standing)
    postures = posture_starts(model, data, voxels.silhouette_centre(data.studio, data.masks), starts[0][3])
    return starts + list(head_down_starts(model, init.shells)) + postures


POSTURE_HEADINGS = 8        # headings (evenly spread) at which each of SEARCH_POSTURES is tried, its root fitted
POSTURE_STARTS_KEPT = 3     # the lowest this many of them start the search
POSTURE_ROOT_EVALS = 200    # evaluations of the root's Powell fit per posture and heading


def posture_starts(model: BodyModel, data: FrameData, centre: np.ndarray | None, heading: float) -> list:
    """Seated, crouching, kneeling and lying starts (``common.postures.SEARCH_POSTURES``) at the
    actor's place, screened cheaply on the half-resolution whole-image energy: every posture at
    POSTURE_HEADINGS headings from ``heading``, each with its root (position and heading) fitted
    by Powell, the POSTURE_STARTS_KEPT lowest kept.
    Why: every other start is upright or head down, and the search's local fits do not fold a
    standing body onto a chair (a seated take fitted from them ends standing, 71% XOR). Every
    heading gets its root fitted because a crouch or a seat as placed looks alike facing front
    and back, the silhouettes' centre ahead of the pelvis (ranked as placed, a crouch was kept
    facing back, 90 mm off)."""
    if centre is None:
        return []
    energy = data.whole_image_energy(half=True)
    headings = heading + np.arange(POSTURE_HEADINGS) * (2.0 * np.pi / POSTURE_HEADINGS)
    placed = np.array([posture_params(model, name, centre[0], centre[1], h)
                       for name in SEARCH_POSTURES for h in headings])
    root = [P["root_x"], P["root_y"], P["root_z"], P["root_heading"]]
    steps = np.array([0.1, 0.1, 0.05, 0.3])
    options = FitOptions()
    fitted = [powell(energy, start, root, steps, options, POSTURE_ROOT_EVALS)[:2] for start in placed]
    fitted.sort(key=lambda f: f[1])
    return [params for params, _ in fitted[:POSTURE_STARTS_KEPT]]


# Actor sizes the first frame is tried at when the actor's height is not given, over the body
# model's own (1.66 m): adults of about 1.5 to 2.15 m, in the calibration's units (a rig
# calibrated with a mis-measured board scales everyone).
ACTOR_SCALES = (0.9, 1.0, 1.1, 1.2, 1.3)
# Another size is taken only where its fit has this much less energy than the model's own size:
# the same pose fitted again at a nearby size moves the energy by a few per cent either way
# (a crouch, 1.0 truth: 2.4% less at 0.9), a body really too small by much more (the seated
# take: 28% less at 1.3).
ACTOR_SCALE_MIN_GAIN = 0.05


def choose_actor_scale(model: BodyModel, seq: Sequence, options: FitOptions) -> float:
    """The actor's size over ``model``'s, chosen by the silhouettes of the first frame: the
    first frame searched once at the model's size (every start, one way of re-detecting limbs),
    then its best pose fitted again at each of ACTOR_SCALES (the pelvis height scaled along),
    and the size whose fit explains the masks best (lowest XOR energy) kept if it beats the
    model's own size by ACTOR_SCALE_MIN_GAIN.
    Why: real subjects are not the body model's size, and a body too small for its silhouettes
    folds into them wrongly (the seated take, fitted at 1.66 m, stood)."""
    frame = seq.frames[0]
    data = frame_data(model, seq, frame)
    solver = LocalSolver(model, options)
    wide = first_frame_options(options, FIRST_FRAME_REDETECT_TURNS[0])
    found = fit_from_starts(model, data, frame, voxel_starts(model, data), [wide], solver)
    best_scale, best_energy = 1.0, found.energy * (1.0 - ACTOR_SCALE_MIN_GAIN)
    for scale in ACTOR_SCALES:
        if scale == 1.0:
            continue
        actor = model.scaled(scale)
        start = np.array(found.params)
        start[P["root_z"]] *= scale
        actor_data = frame_data(actor, seq, frame)
        actor_solver = LocalSolver(actor, options)
        actor_solver.begin_frame(frame, actor_data, start, wide)
        fit = fit_frame(actor, actor_data, start, wide, actor_solver.solve)
        if fit.energy < best_energy:
            best_scale, best_energy = scale, fit.energy
    return best_scale


REFIT_GAIN = 0.005   # a start's fit is fitted again from its result while the energy falls this much
MAX_REFITS = 3
REFITTED_STARTS = 3  # the fits (of all starts and ways of re-detecting limbs) fitted again, lowest first


def fit_from_starts(model: BodyModel, data: FrameData, frame: int, starts: list, options_list: list,
                    solver: Solver) -> FrameResult:
    """Fit one frame from every start under each of ``options_list``; then the REFITTED_STARTS
    lowest fits, each under its own options, are fitted again from their result while that
    still lowers the energy by REFIT_GAIN (each fit re-detects the limbs from a better torso),
    and the lowest of all is kept. The lowest fit is not always the one that refits lowest:
    06_08's first frame has a start a quarter turn off that fits to 17,513 and refits to
    17,484, 40 mm off, while the next start fits to 18,759 and refits to 16,877, 20 mm off."""
    def score(fit: FrameResult) -> float:
        return fit.energy + inversion_cost(model, data, fit.params)

    tries = []
    for options in options_list:
        solver.begin_frame(frame, data, starts[0], options)
        tries += [(fit_frame(model, data, s, options, solver.solve), options) for s in starts]
    ranked = sorted(tries, key=lambda t: score(t[0]))
    refitted = []
    for best, options in ranked[:REFITTED_STARTS]:
        solver.begin_frame(frame, data, best.params, options)
        for _ in range(MAX_REFITS):
            again = fit_frame(model, data, best.params, options, solver.solve)
            gained = again.energy <= best.energy * (1.0 - REFIT_GAIN)
            best = lowest_energy([best, again])
            if not gained:
                break
        refitted.append(best)
    return lowest_energy(refitted + [fit for fit, _ in ranked[REFITTED_STARTS:]], score)  # every fit's solves counted


# What a body upside down costs against an upright one when a search chooses among its fits, as a
# share of the frame's silhouette area (a lying body half of it): people are upright far more
# often, and where props or a mask add foreground the body cannot explain, an inverted body can
# reach into it better (the seated take: upside down, the legs up the chair's back, 5% less XOR
# than seated). A real handstand wins by far more (05_06's cartwheel: 32%).
INVERTED_COST_SHARE = 0.05


def inversion_cost(model: BodyModel, data: FrameData, params: np.ndarray) -> float:
    """INVERTED_COST_SHARE of the silhouette area times (1 - cos of the trunk's angle from
    the vertical) / 2: 0 upright, half lying, all of it upside down."""
    joints = forward_kinematics(model, params).joints[0]
    trunk = joints[JOINT_NAMES.index("neck")] - joints[0]
    up = float(trunk[2] / max(np.linalg.norm(trunk), 1e-9))
    return INVERTED_COST_SHARE * float(np.count_nonzero(data.masks)) * (1.0 - up) / 2.0


def search_frame(model: BodyModel, data: FrameData, frame: int, starts: list, options: FitOptions,
                 solver: "Solver") -> FrameResult:
    """A frame without a trusted start (a first frame, a recovery): the wide search of
    ``first_frame_options`` from every start, once per way of re-detecting the limbs
    (FIRST_FRAME_REDETECT_TURNS), the lowest fits fitted again (``fit_from_starts``); then one
    fit with the tracking ``options``, whose local grids and small windows refine what the wide
    search found; then the whole body rotated about the pelvis's axes (``rotated_body_fits``);
    then fits with the legs, and the arms, swapped (``swapped_side_fits``); then
    a fit from each limb's other basins (``limb_alternatives``) and from each nearly straight
    arm's lower twist (``arm_twist_fits``); then hops; each time the lowest energy kept."""
    wide = [first_frame_options(options, turn) for turn in FIRST_FRAME_REDETECT_TURNS]
    found = fit_from_starts(model, data, frame, starts, wide, solver)
    solver.begin_frame(frame, data, found.params, options)
    found = lowest_energy([found, fit_frame(model, data, found.params, options, solver.solve)])
    found = rotated_body_fits(model, data, frame, found, options, solver)
    found = lowest_energy([found, *swapped_side_fits(model, data, frame, found.params, options, solver)])
    found = lowest_energy([found, *limb_alternative_fits(model, data, frame, found.params, options, solver)])
    found = lowest_energy([found, *arm_twist_fits(model, data, frame, found.params, options, solver)])
    return lowest_energy([found, hopped_fit(model, data, frame, found.params, options, SEARCH_HOPS, solver)])


SEARCH_HOPS = 30  # hops of basin hopping that end a search (``hopped_fit``)


def hopped_fit(model: BodyModel, data: FrameData, frame: int, params: np.ndarray, options: FitOptions, hops: int,
               solver: Solver) -> FrameResult:
    """The frame fitted by ``hops`` hops of ``hop_fit`` from ``params`` (up to four side by side
    on a cluster's clients), its energy the whole-image XOR energy (``full_energy``) so that it
    compares with other fits. A search's torso and limbs can be off together where no chain
    alone goes down: 06_02 from source frame 262 (the actor in five of eight views) is found
    54 mm off, 6% above the truth's energy; 30 hops take it to 27 mm."""
    # the hop count travels in the options (``solve_job`` reads it), which allow hops only with passes
    hopping = replace(options, refine_hops=hops, refine_passes=max(options.refine_passes, 1))
    solver.begin_frame(frame, data, params, hopping)
    hopped = hop_fit(params, hopping, solver.solve, min(solver.workers(), len(HOP_JOBS)))
    return replace(hopped, energy=full_energy(model, data, hopped.params))


# The whole body rotated about the pelvis's three axes by these angles, each fitted again
# (``rotated_body_fits``), for up to BODY_ROTATION_ROUNDS rounds while a round lowers the energy.
BODY_ROTATIONS_RAD = (-0.6, -0.3, 0.3, 0.6)
BODY_ROTATION_ROUNDS = 3


def rotated_body_fits(model: BodyModel, data: FrameData, frame: int, found: FrameResult, options: FitOptions,
                      solver: Solver) -> FrameResult:
    """Rounds of whole-body fits from ``found`` rotated about each of the pelvis's own axes by
    each of BODY_ROTATIONS_RAD, limbs carried along (``rotated_about_pelvis``); each round
    starts from the lowest fit so far and the rounds stop when one finds nothing lower.
    Why: the searches' starts are a few orientations apart, and the tracking fit's turn
    hypotheses turn about the vertical only. A body upside down and sideways settles with the
    trunk tilted off and the limbs bent to make up for it, where no chain alone goes down: 05_06
    from source frame 150 (a cartwheel, hands on the floor) was found with the pelvis 36 degrees
    off, 64 mm and 13% above the truth's energy; a rotation about the pelvis's front-to-back axis
    brings it to 31 mm, the next rounds' to about 20 mm."""
    for _ in range(BODY_ROTATION_ROUNDS):
        starts = [clip_to_limits(rotated_about_pelvis(model, found.params, axis, angle))
                  for axis in range(3) for angle in BODY_ROTATIONS_RAD]
        before = found.energy
        found = lowest_energy([found, *whole_body_fits(model, data, frame, starts, options, solver)])
        if found.energy >= before:
            break
    return found


def swapped_side_fits(model: BodyModel, data: FrameData, frame: int, params: np.ndarray, options: FitOptions,
                      solver: Solver) -> list[FrameResult]:
    """The frame fitted again as a whole body from ``params`` with the legs swapped, and with
    the arms swapped (``swap_sides``). A stride with the left foot ahead and one with the right
    look alike from the side, and neither leg alone can move to the other's place: 05_01 from
    source frame 127 (the actor 1.5 m off the studio's centre, feet out of three views) was
    found with its legs swapped, the ankles 0.5 m off and 11% above the truth's energy; fitted
    from the legs swapped back it is 15 mm off."""
    return whole_body_fits(model, data, frame, [swap_sides(params, limb) for limb in MIRROR_SIGNS], options, solver)


def limb_alternative_fits(model: BodyModel, data: FrameData, frame: int, params: np.ndarray, options: FitOptions,
                          solver: Solver) -> list[FrameResult]:
    """The frame fitted again from each limb's other basins (``limb_alternatives`` of
    ``params``), each as a whole body: a limb found wrong holds the torso where it explains that
    limb, and neither can move alone."""
    alternatives = [a for chain in LIMB_CHAINS for a in limb_alternatives(model, data, chain, params, options)]
    return whole_body_fits(model, data, frame, alternatives, options, solver)


def arm_twist_fits(model: BodyModel, data: FrameData, frame: int, params: np.ndarray, options: FitOptions,
                   solver: Solver, neighbour: np.ndarray | None = None) -> list[FrameResult]:
    """The frame fitted again as a whole body from each nearly straight arm turned to a lower
    twist (``arm_twist_alternative``, solved here; with the ``neighbour`` frame's fit, only a
    turn towards that fit's twist). The dance's frames 15-16 (05_10) were tracked with the right
    arm straight and twisted 2 rad off, the wrist 60 mm off."""
    starts = [alt for chain in ARM_CHAINS
              if (alt := arm_twist_alternative(model, data, chain, params, options, neighbour)) is not None]
    return whole_body_fits(model, data, frame, starts, options, solver)


def whole_body_fits(model: BodyModel, data: FrameData, frame: int, starts: list, options: FitOptions,
                    solver: Solver) -> list[FrameResult]:
    """The frame fitted from each of ``starts`` (35,) in turn, each a separate tracking fit."""
    fits = []
    for start in starts:
        solver.begin_frame(frame, data, start, options)
        fits.append(fit_frame(model, data, start, options, solver.solve))
    return fits


LOSS_ENERGY_RATIO = 1.25  # a frame's energy this far above the recent median: tracking is lost
LIMB_LOSS_ENERGY_RATIO = 1.06  # ... this far: a limb may be lost, every limb is re-detected
LOSS_HISTORY = 10         # frames in that median
LOSS_MIN_HISTORY = 3


def tracking_lost(energies: list, energy: float, ratio: float = LOSS_ENERGY_RATIO) -> bool:
    """Whether ``energy`` jumps ``ratio`` times above the median of the last frames' energies
    (silhouette noise moves it by a few per cent; a limb lost in a fast move adds 5-15%, a body
    fitted beside the actor its whole area)."""
    recent = energies[-LOSS_HISTORY:]
    return len(recent) >= LOSS_MIN_HISTORY and energy > ratio * float(np.median(recent))


def recovery_starts(model: BodyModel, data: FrameData) -> list[np.ndarray]:
    """Start poses from the frame's voxels, or none where they give none (no actor in view)."""
    try:
        return voxel_starts(model, data)
    except UserError:
        return []


def read_done_frames(path: Path) -> list[dict]:
    """The records of an existing poses.jsonl.

    A torn last line (a crash while it was written: no newline at its end) is dropped; any
    other line that is not a record is an InputFileError naming it, because the frames after
    it would otherwise be lost or fitted again.
    """
    if not path.exists():
        return []
    lines = path.read_bytes().split(b"\n")
    done = []
    for n, raw in enumerate(lines[:-1], start=1):  # lines[-1]: b"" or the torn last line
        try:
            record = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError):
            record = None
        if not (isinstance(record, dict) and isinstance(record.get("frame"), int)
                and isinstance(record.get("params"), list)):
            raise InputFileError(path, f"line {n}: not a pose record (corrupt?); repair or remove the file, "
                                       "or fit again with --overwrite")
        done.append(record)
    return done


def run_settings(model: BodyModel, seq: Sequence, options: FitOptions, init: str) -> dict:
    """What decides a run's poses: written to run.json, and what ``--resume`` must match."""
    return {"sequence": str(seq.path.resolve()), "init": init, "world_up": seq.world.up,
            "masks_cleaned": seq.clean_masks, "mask_threshold": seq.mask_threshold,
            "actor_scale": model_scale(model), "options": options.to_wire()}


def settings_differences(before: dict, now: dict, prefix: str = "") -> list[str]:
    """'KEY NOW (was BEFORE)' for every setting that differs, nested keys joined by dots."""
    out = []
    for key in sorted(set(before) | set(now)):
        a, b = before.get(key), now.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += settings_differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key} {b!r} (was {a!r})")
    return out


def check_resume(out_dir: Path, settings: dict) -> None:
    """Refuse to continue a run with other settings than those it was started with."""
    path = out_dir / RUN_FILE
    if not path.exists():
        raise InputFileError(path, "missing: no record of the settings the earlier frames were fitted with; "
                                   "fit again with --overwrite")
    try:
        before = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise InputFileError(path, "not valid JSON (corrupt?); fit again with --overwrite") from None
    if not isinstance(before, dict):
        raise InputFileError(path, "expected a JSON object; fit again with --overwrite")
    differ = settings_differences(before, settings)
    if differ:
        raise UserError(f"--resume: the settings differ from the run being continued ({path}): "
                        + "; ".join(differ) + ". Pass the same options, or --overwrite to fit again")


def prepare_result_folder(out_dir: Path, settings: dict, resume: bool, overwrite: bool) -> list[dict]:
    """Check a result folder and make it ready for a run; returns the records being continued.

    An earlier result is refused unless ``resume`` (its settings must match, see
    ``check_resume``) or ``overwrite`` (its files, and those made from them, are removed).
    """
    earlier = check_folder_target(out_dir, RESULT_FILES, resume=resume, overwrite=overwrite)
    poses_path = out_dir / POSES_FILE
    if resume and earlier:
        check_resume(out_dir, settings)
        done = read_done_frames(poses_path)
        _rewrite_complete(poses_path, done)  # drop a torn last line before appending
        return done
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in (RESULT_FILES + DERIVED_FILES) if earlier else ():
        target = out_dir / name
        if target.is_dir():
            shutil.rmtree(target)
        else:
            target.unlink(missing_ok=True)
    write_text(out_dir / RUN_FILE, json.dumps(settings, indent=1))
    return []


def _rewrite_complete(path: Path, records: list[dict]) -> None:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w") as fh:
        for r in records:
            fh.write(json.dumps(r) + "\n")
    os.replace(tmp, path)


def frame_data(model: BodyModel, seq: Sequence, frame: int) -> FrameData:
    """One frame's FrameData: the sequence's silhouettes in its fit-frame studio."""
    return FrameData(model, seq.studio, seq.silhouettes(frame))


def user_joints(model: BodyModel, seq: Sequence, params: np.ndarray) -> dict:
    """{joint: [x, y, z]} of ``params`` (fit frame), in the user's world frame (``seq.world``)."""
    return joints_dict(seq.world.points_to_user(forward_kinematics(model, params).joints[0]))


def model_scale(model: BodyModel) -> float:
    """The actor's size over the body model's own (its height over the default body's)."""
    return float(model.height / load_body_model().height)


QUALITY_FLAG_SHARE = 0.3  # a frame whose XOR is above this share of a camera's silhouette is flagged


def frame_quality(model: BodyModel, seq: Sequence, record: dict) -> dict:
    """How well the fitted body explains one frame's masks, per camera: the XOR (model xor
    silhouette) as a share of the silhouette's area (undistorted images, the fit's own), the
    whole frame's share, and whether (and which cameras) it is above QUALITY_FLAG_SHARE."""
    data = frame_data(model, seq, record["frame"])
    rendered = data.whole_image_energy().render(np.asarray(record["params"]))
    sizes = [(c.height, c.width) for c in data.studio]
    xor = [int(np.count_nonzero(r[:h, :w] ^ m[:h, :w])) for r, m, (h, w) in zip(rendered, data.masks, sizes)]
    area = [int(np.count_nonzero(m[:h, :w])) for m, (h, w) in zip(data.masks, sizes)]
    share = [x / a if a else (0.0 if x == 0 else 1.0) for x, a in zip(xor, area)]
    flagged = [c.name for c, v in zip(data.studio, share) if v > QUALITY_FLAG_SHARE]
    return {"xor_share": [round(v, 4) for v in share], "xor_pixels": xor, "silhouette_pixels": area,
            "xor_share_total": round(sum(xor) / max(sum(area), 1), 4), "flagged_cameras": flagged}


def quality_summary(records: list[dict], cameras: list[str]) -> dict:
    """Fit quality over the records: the mean and worst XOR share, per camera too, and the
    frames flagged (``frame_quality``) with the cameras that disagree."""
    q = [r["fit_quality"] for r in records if "fit_quality" in r]
    if not q:
        return {}
    total = np.array([v["xor_share_total"] for v in q])
    per_camera = np.array([v["xor_share"] for v in q])
    return {"mean_xor_share": float(total.mean()), "max_xor_share": float(total.max()),
            "per_camera_mean_xor_share": {c: float(v) for c, v in zip(cameras, per_camera.mean(axis=0))},
            "flag_share": QUALITY_FLAG_SHARE,
            "frames_flagged": [{"frame": r["frame"], "cameras": r["fit_quality"]["flagged_cameras"]}
                               for r in records if r.get("fit_quality", {}).get("flagged_cameras")]}


def joint_errors_mm(joints: np.ndarray, truth_frame) -> np.ndarray:
    """(17,) distances of fitted joints (17, 3) metres, in JOINT_NAMES order, from a TruthFrame's, mm."""
    true = np.array([truth_frame.joints[n] for n in JOINT_NAMES])
    return np.linalg.norm(np.asarray(joints) - true, axis=1) * 1000.0


def accuracy(records: list[dict], truth: dict | None) -> dict:
    """Joint position errors against the truth, millimetres."""
    if not truth:
        return {}
    errs = [joint_errors_mm([r["joints"][n] for n in JOINT_NAMES], truth[r["frame"]])
            for r in records if r["frame"] in truth]
    if not errs:
        return {}
    E = np.array(errs)
    per_frame = E.mean(axis=1)
    return {
        "mean_joint_error_mm": float(E.mean()),
        "max_joint_error_mm": float(E.max()),
        "per_joint_error_mm": {n: float(v) for n, v in zip(JOINT_NAMES, E.mean(axis=0))},
        "per_frame_error_mm": [float(v) for v in per_frame],
        "per_frame_max_error_mm": [float(v) for v in E.max(axis=1)],
    }


SETTLE_FRAMES = 10  # frames tracked after a first-frame search before it is refined backwards (online runs)
# hops that refit a pass's first frame, which has no neighbour to be refitted from: the
# sequence's last frame on a backward pass is otherwise only ever tracking's fit (basketball's
# last frame: the left ankle 70 mm off, the clip's worst). One frame per pass, so it can have
# a deeper search than the rest: on the three accuracy clips' last frames, 120 hops lowered
# the energy of 30 hops' fit on all three, by 0.3-0.5% (basketball's left wrist 48 -> 33 mm),
# for about 13 s per pass.
PASS_START_HOPS = 120


def refine_pass(model: BodyModel, seq: Sequence, records: list[dict], options: FitOptions, solver: Solver,
                stats: RunStats, backward: bool = True, progress=None, search: bool = False,
                hops: int = 0) -> tuple[list[dict], int]:
    """Fitted frames fitted again in one direction, each from its neighbour's fit.

    Tracking leaves frames in basins that a later frame escaped (an arm whose twist showed once
    it bent; a first frame found by search, 10-20 mm off). Going backwards each frame starts from
    the (already refined) fit of the frame after it, forwards from the frame before; each keeps
    the lower energy of its fits. Each frame with neighbours on both sides is also fitted from
    halfway between their fits (``midway``): tracking can leave a frame with its torso and
    limbs off together, in a valley that neither neighbour's fit leads out of, while their
    mean lies in the truth's (the dance's frames 21 and 39: 54 and 50 mm off; fitted from
    halfway, 16 and 23 mm with 1.2 and 1.4% less energy). The pass's first frame, which has
    no neighbour, is fitted by PASS_START_HOPS hops (the pass's own ``hops`` where it has them;
    the search too, where asked). Every frame's nearly straight arms are also tried at their
    other twists (``arm_twist_fits``). A replaced record keeps its tracking fit under "first_pass" (params,
    joints, energy); the pass's time and evaluations add to "refine_seconds" and
    "refine_evaluations" ("seconds" and "evaluations" stay tracking's). Returns the records,
    changed, and how many were replaced.

    With ``search``, each frame is also fitted from each limb's other basins around the better
    of its fits (``limb_alternative_fits``, as a first frame is): tracking and its neighbours
    can share a torso and limb that are off together (basketball frame 84: the left ankle 74 mm
    off, an alternative leg 1.8% lower in energy). About nine times the cost of a plain pass.
    With ``hops`` > 0, each frame is also fitted by that many hops of ``hop_fit`` from the best
    of its fits, each seeded by the frame's number and its own; a cluster's clients run them
    side by side. Their time goes to the pass's "hop_seconds", their count, dropped ones too,
    to its "hops_run"; their chains stay out of the per-chain figures.
    """
    out = [dict(r) for r in records]
    order = range(len(out) - 1, -1, -1) if backward else range(len(out))
    neighbour = beyond = None
    replaced = 0
    for done, i in enumerate(order):
        r = out[i]
        frame_hops = hops or (PASS_START_HOPS if neighbour is None else 0)
        if neighbour is not None or search or frame_hops:
            t0 = time.perf_counter()
            ahead = i - 1 if backward else i + 1  # the neighbour on the other side, not yet refined
            other = np.asarray(out[ahead]["params"], dtype=np.float64) if 0 <= ahead < len(out) else None
            fits = _refits(model, seq, r, neighbour, beyond, other, options, solver, search, frame_hops, stats)
            r["refine_seconds"] = r.get("refine_seconds", 0.0) + time.perf_counter() - t0
            if fits:  # a pass's first frame may have no hops, no other basins and no twist to try
                again = lowest_energy(fits)
                stats.add_chains([c for c in again.chains if c.chain not in HOP_JOBS])
                r["refine_evaluations"] = r.get("refine_evaluations", 0) + again.evaluations
                if again.energy < r["energy"]:
                    r.setdefault("first_pass", {"params": r["params"], "joints": r["joints"], "energy": r["energy"]})
                    r["params"] = [float(v) for v in again.params]
                    r["joints"] = user_joints(model, seq, again.params)
                    r["energy"] = int(again.energy)
                    replaced += 1
        beyond, neighbour = neighbour, np.asarray(r["params"], dtype=np.float64)
        if progress:
            progress(done + 1, len(out), f"refining {'backwards' if backward else 'forwards'}")
    return out, replaced


def _refits(model: BodyModel, seq: Sequence, record: dict, neighbour: np.ndarray | None,
            beyond: np.ndarray | None, other: np.ndarray | None, options: FitOptions, solver: Solver,
            search: bool, hops: int, stats: RunStats) -> list[FrameResult]:
    """A refinement pass's fits of one frame: from its neighbour's fit (``neighbour``, the one
    beyond it ``beyond``) where it has one, and from halfway between that fit and the fit of its
    neighbour on the other side (``other``, not yet refined in this pass) where it has both;
    with ``search``, from each limb's other basins around the better of that fit and the
    record's; from each nearly straight arm's lower twist towards the neighbour's, around the
    best so far (``arm_twist_fits``); with ``hops``, basin hopping from the best of all these
    and the record (its time and hop count added to ``stats``)."""
    data = frame_data(model, seq, record["frame"])
    fits = []

    def best_so_far() -> np.ndarray:  # the record's pose on a tie
        return min([(record["energy"], np.asarray(record["params"])), *((f.energy, f.params) for f in fits)],
                   key=lambda fit: fit[0])[1]

    if neighbour is not None:
        solver.begin_frame(record["frame"], data, neighbour, options)
        fits.append(fit_frame(model, data, neighbour, options, solver.solve,
                              extra_starts=tilted_ahead(neighbour, beyond)))
        if other is not None:
            fits += whole_body_fits(model, data, record["frame"], [midway(neighbour, other)], options, solver)
    if search:
        fits += limb_alternative_fits(model, data, record["frame"], best_so_far(), options, solver)
    fits += arm_twist_fits(model, data, record["frame"], best_so_far(), options, solver, neighbour)
    if hops:
        t0 = time.perf_counter()
        fits.append(hopped_fit(model, data, record["frame"], best_so_far(), options, hops, solver))
        stats.hop_seconds += time.perf_counter() - t0
        stats.hops_run += len(fits[-1].chains)
    return fits


def run_fit(model: BodyModel, seq: Sequence, out_dir: Path, options: FitOptions, solver: Solver,
            init: str | None = None, resume: bool = False, max_frames: int | None = None, progress=None,
            overwrite: bool = False) -> dict:
    """Fit the sequence's frames in order; returns the summary (also written to summary.json).

    ``resume``: continue the frames of an earlier run there (same settings); ``overwrite``:
    replace an earlier result; with neither, an earlier result is refused before any work.
    """
    frames = seq.frames[:max_frames] if max_frames else list(seq.frames)
    seq.check_files(frames)  # every mask there and readable before anything is written
    for warning in seq.check_masks(frames):
        print_warning(warning)
    if len(seq.studio) < MIN_GOOD_CAMERAS:
        print_warning(f"{len(seq.studio)} camera(s): fewer than {MIN_GOOD_CAMERAS} views leave depth and the "
                      "limbs' sides unresolved; expect joint errors of several centimetres and frames off by up "
                      "to a metre (a walk in the virtual studio, 2 cameras: 63 mm mean, 858 mm worst; 3 "
                      "cameras: 7 mm, 21 mm)")
    truth = seq.truth()
    if init is None:  # the truth's first pose where there is one, else automatic initialisation
        init = "truth" if truth else "auto"
    done = prepare_result_folder(out_dir, run_settings(model, seq, options, init), resume, overwrite)
    if done and [d["frame"] for d in done] != frames[:len(done)]:
        raise InputFileError(out_dir / POSES_FILE, f"does not hold the first frames of {seq.path}; cannot --resume")
    poses_path = out_dir / POSES_FILE
    stats = RunStats()
    wall0 = time.perf_counter()
    x = np.asarray(done[-1]["params"], dtype=np.float64) if done else None
    x_before = np.asarray(done[-2]["params"], dtype=np.float64) if len(done) > 1 else None
    energies = [int(d["energy"]) for d in done]
    # a run that starts from a search goes back over its first frames once tracking has settled;
    # the refinement passes after tracking do that and more
    settle_index = min(SETTLE_FRAMES, len(frames) - 1) if init != "truth" and not options.refine_passes else -1
    for n, frame in enumerate(frames[len(done):], start=len(done)):
        t0 = time.perf_counter()
        data = frame_data(model, seq, frame)
        if x is None and init == "truth":
            x = initial_starts(model, seq, data, init)[0]
        if x is None:
            if progress:
                progress(n, len(frames), f"frame {frame}: first-frame search ({init} start)")
            result = search_frame(model, data, frame, initial_starts(model, seq, data, init), options, solver)
        else:
            solver.begin_frame(frame, data, x, options)
            result = fit_frame(model, data, x, options, solver.solve, extra_starts=tilted_ahead(x, x_before))
        recovered = limbs_redetected = False
        if tracking_lost(energies, result.energy, LIMB_LOSS_ENERGY_RATIO):
            # every limb searched over its whole range, from the fitted torso
            every = replace(options, redetect_turn="every")
            solver.begin_frame(frame, data, result.params, every)
            again = fit_frame(model, data, result.params, every, solver.solve)
            result = lowest_energy([result, again])
            limbs_redetected = result is again
        starts = recovery_starts(model, data) if tracking_lost(energies, result.energy) else []
        if starts:  # the whole body lost: start again from the voxels, as on a first frame
            if progress:
                progress(n, len(frames), f"frame {frame}: tracking lost, searching from voxels")
            again = search_frame(model, data, frame, starts, options, solver)
            result = lowest_energy([result, again])
            recovered = result is again
        energies.append(result.energy)
        x_before, x = x, result.params
        seconds = time.perf_counter() - t0
        chains = [c for c in result.chains if c.chain not in HOP_JOBS]  # a search's hops: not chain solves
        record = {
            "frame": int(frame), "params": [float(v) for v in x], "joints": user_joints(model, seq, x),
            "actor_scale": model_scale(model), "world_up": seq.world.up,
            "energy": int(result.energy), "seconds": seconds, "iterations": result.iterations,
            "evaluations": result.evaluations, "recovered": recovered,
            "limbs_redetected": limbs_redetected,
            "chains": chain_totals(chains),
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
            refined, _ = refine_pass(model, seq, read_done_frames(poses_path), options, solver, stats)
            _rewrite_complete(poses_path, refined)
            energies = [int(r["energy"]) for r in refined]
        if progress:
            progress(n + 1, len(frames), f"E={result.energy}")
    records = read_done_frames(poses_path)
    passes = []
    for k in range(options.refine_passes if len(records) > 1 else 0):
        t0, hops_before, hop_seconds_before = time.perf_counter(), stats.hops_run, stats.hop_seconds
        backward = k % 2 == 0
        search = options.refine_search and k == 0
        hops = options.refine_hops if k == 0 else 0
        records, replaced = refine_pass(model, seq, records, options, solver, stats, backward, progress, search,
                                        hops)
        _rewrite_complete(poses_path, records)  # each pass kept whole: an interrupted run keeps the last
        passes.append({"direction": "backward" if backward else "forward", "search": search, "hops": hops,
                       # more than hops x frames where hops ran side by side and some were dropped
                       "hops_run": stats.hops_run - hops_before,
                       "hop_seconds": stats.hop_seconds - hop_seconds_before,
                       "frames_replaced": replaced, "seconds": time.perf_counter() - t0})
    records = [r | {"fit_quality": frame_quality(model, seq, r)} for r in records]
    _rewrite_complete(poses_path, records)
    summary = {
        "sequence": str(seq.path.resolve()),
        "world_up": seq.world.up,
        "masks_cleaned": seq.clean_masks,
        "actor_scale": model_scale(model),
        "frames": len(records),
        "frames_fitted_this_run": len(stats.seconds),
        "mode": solver.mode,
        "clients": solver.clients,
        "energy_backend": options.energy,
        "init": init,
        # tracking, the paper's measure; the refinement passes are timed apart
        "seconds_per_frame": float(np.median(stats.seconds)) if stats.seconds else None,
        "mean_seconds_per_frame": float(np.mean(stats.seconds)) if stats.seconds else None,
        "refine_seconds_per_frame": sum(p["seconds"] for p in passes) / len(records) if passes else 0.0,
        "refinement_passes": passes,
        "wall_seconds": time.perf_counter() - wall0,
        "evaluations_per_frame": float(np.mean(stats.evaluations)) if stats.evaluations else None,
        "frames_recovered": sum(1 for r in records if r.get("recovered")),
        "frames_limbs_redetected": sum(1 for r in records if r.get("limbs_redetected")),
        "frames_refined": sum(1 for r in records if "first_pass" in r),
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


def refinement_note(summary: dict) -> str:
    """'(N passes[, the first searching[ and hopping]], K frames improved)' for a summary whose
    run refined (``mocap fit``'s table, the report)."""
    passes = summary["refinement_passes"]
    n = len(passes)
    extra = " and ".join(word for word, on in (("searching", passes[0].get("search")),
                                               ("hopping", passes[0].get("hops"))) if on)
    extra = f", {'the first ' if n > 1 else ''}{extra}" if extra else ""
    return f"({n} pass{'es' if n > 1 else ''}{extra}, {summary.get('frames_refined', 0)} frames improved)"


def tracking_error_note(summary: dict) -> str:
    """'MEAN / MAX mm': a refined run's joint error as tracking left its frames."""
    return f"{summary['tracking_mean_joint_error_mm']:.1f} / {summary['tracking_max_joint_error_mm']:.1f} mm"


def load_records(out_dir: Path) -> list[dict]:
    path = Path(out_dir) / POSES_FILE
    if not path.exists():
        raise InputFileError(path, "missing (not a result folder?)")
    return read_done_frames(path)
