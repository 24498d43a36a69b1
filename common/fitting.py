"""Hierarchical pose fitting (Theobalt et al. 2003, section 3), shared by server and clients.

Per frame, from the previous frame's pose:
 1. torso (root + spine) by Powell's method on the half-resolution energy;
 2. the four limbs, each by a grid search then Powell in 128x128 windows, followed by its
    hand or foot in 64x64 windows; and the head in 64x64 windows. Every limb and the head
    start from the same pose (Jacobi), so they are independent: a client can solve any of
    them and the result does not depend on who solved it or in which order;
 3. repeat until the full energy stops improving or an iteration cap.

``solve_job`` is the unit of work a client does (a chain's ``solve_chain``, or one hop of a
refinement's ``hop_fit``); ``fit_frame`` is the server's loop, with the limb solves handed to
a ``dispatch`` callable (local by default).
"""
from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from functools import cached_property
from itertools import product
from typing import Callable

import numpy as np

from common.body import (
    CHAINS, LIMB_CHAINS, LIMB_PARTS, P, PARAM_LIMITS, BodyModel, clip_to_limits, forward_kinematics,
    hold_limbs_in_world, matrix_to_rotvec, rest_params, rotvec_to_matrix,
)
from common import optimize
from common.camera import Camera, Studio, distort_normalized
from common.energy import (
    ARM_WINDOW, SMALL_WINDOW, CpuEnergy, EnergySetup, Window, centred_window, cut_window, make_energy,
)
from common.packing import clear_padding, downsample_masks, pad_stack
from common.powell_cpu import powell_cpu
from common.retarget import heading_tilt, nearest_turn

HALF = 0.5  # torso works at half resolution (paper: 160x120 of 320x240)
ENERGY_BACKENDS = ("cpu", "gl", "coarse-to-fine", "volume")
VOLUME_GRID = 64  # voxels per side for the volume energy's SPOT reconstruction


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
    spine_twist_prior: float = 1500.0   # energy units (pixels) per rad^2 of spine twist
    limb_window_px: int = ARM_WINDOW    # the paper's 128x128 limb windows
    hinge_grid_full_range: bool = False  # grid elbows/knees over their whole range (rough starts)
    torso_grid_steps: int = 1           # >1: grid over pelvis heading x spine twist before Powell (off: measured worse on the walk)
    torso_grid_range_rad: float = 0.2
    redetect_limbs: bool = True         # search limbs over their whole range (lost limbs)
    redetect_turn: str = "final"        # which limbs when: see REDETECT_TURNS
    hypotheses: int = 1                 # 2: fit each frame with both first-round torso schedules, keep the better
    turn_hypotheses: int = 2            # also fit from the start turned by -+1..n turn steps about the vertical
    turn_step_rad: float = 0.15
    polish_iterations: int = 2          # further rounds for the best hypothesis, while the energy still falls
    refine_passes: int = 1              # after tracking, passes over all frames (backward, forward, ...): see server.session
    refine_search: bool = False         # the first pass also refits each frame from each limb's other basins (slow)
    refine_hops: int = 0                # the first pass also refits each frame from this many random chain moves (slow)

    def __post_init__(self):
        if self.energy not in ENERGY_BACKENDS:
            raise ValueError(f"energy must be one of {ENERGY_BACKENDS}, got {self.energy!r}")
        if self.grid_steps < 1 or self.grid_steps % 2 == 0:
            raise ValueError("grid_steps must be odd and >= 1")
        if self.redetect_turn not in REDETECT_TURNS:
            raise ValueError(f"redetect_turn must be one of {REDETECT_TURNS}, got {self.redetect_turn!r}")
        if not 1 <= self.hypotheses <= len(SCHEDULES):
            raise ValueError(f"hypotheses must be 1..{len(SCHEDULES)}, got {self.hypotheses}")
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
        return dict(self.__dict__)

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


@dataclass
class FrameResult:
    params: np.ndarray
    energy: int
    iterations: int
    evaluations: int
    chains: list = field(default_factory=list)  # ChainResult of every solve, in order
    wall_seconds: float = 0.0


_UNDISTORT_MAPS: dict = {}
_SPOT_GRIDS: OrderedDict = OrderedDict()  # lookup tables per studio and box, the most recent kept
SPOT_GRIDS_KEPT = 4  # each about 20 MB (64^3, 8 cameras); an actor crossing the studio needs a few


def undistort_map(cam: Camera) -> np.ndarray:
    """(H, W) flat indices into the distorted image for each pixel of the ideal pinhole image."""
    key = (cam.K.tobytes(), cam.dist.tobytes(), cam.width, cam.height)
    if key not in _UNDISTORT_MAPS:
        v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
        fx, s_, cx, fy, cy = cam.K[0, 0], cam.K[0, 1], cam.K[0, 2], cam.K[1, 1], cam.K[1, 2]
        y = (v - cy) / fy
        x = (u - cx - s_ * y) / fx
        xd, yd = distort_normalized(x, y, cam.dist)
        ud = np.rint(fx * xd + s_ * yd + cx).astype(np.int64)
        vd = np.rint(fy * yd + cy).astype(np.int64)
        inside = (ud >= 0) & (ud < cam.width) & (vd >= 0) & (vd < cam.height)
        _UNDISTORT_MAPS[key] = np.where(inside, vd * cam.width + ud, -1)
    return _UNDISTORT_MAPS[key]


def undistort_masks(studio: Studio, masks: np.ndarray) -> tuple[Studio, np.ndarray]:
    """Silhouettes resampled into ideal pinhole images (same K, no distortion), and that studio.

    masks: (K, H, W) bool, the padded stack (``packing.pad_stack``) -> the same shape.
    Fitting works in undistorted images so that every energy backend projects with plain
    pinhole cameras and agrees; a mask is resampled once per frame (nearest pixel).
    """
    if not any(c.has_distortion for c in studio):
        return studio, masks
    cams, out = [], []
    for cam, mask in zip(studio, masks):
        mask = mask[:cam.height, :cam.width]
        if cam.has_distortion:
            idx = undistort_map(cam)
            mask = np.where(idx >= 0, mask.reshape(-1)[np.maximum(idx, 0)], False)
            cam = replace(cam, dist=np.zeros_like(cam.dist))
        cams.append(cam)
        out.append(mask)
    return Studio(tuple(cams), studio.source), pad_stack(out)


def spot_grid(studio: Studio, masks: np.ndarray, grid: int):
    """SPOT lookup tables for a box around the actor; built once per studio and box."""
    from common.voxels import SpotGrid, actor_bounds

    bounds = actor_bounds(studio, masks)
    key = (grid, bounds.tobytes(), tuple((c.name, c.K.tobytes(), c.R.tobytes(), c.t.tobytes()) for c in studio))
    if key not in _SPOT_GRIDS:
        _SPOT_GRIDS[key] = SpotGrid.build(studio, grid=grid, q=2, bounds=bounds)
        while len(_SPOT_GRIDS) > SPOT_GRIDS_KEPT:
            _SPOT_GRIDS.popitem(last=False)
    _SPOT_GRIDS.move_to_end(key)
    return _SPOT_GRIDS[key]


class FrameData:
    """One frame's input silhouettes (undistorted) at full and half resolution, and its studio.

    masks: (K, H, W) bool, camera k's silhouette at [:h_k, :w_k] with (w_k, h_k) its image
    size and H, W the largest (cameras of one size: the plain stack; of different sizes: the
    padded stack of ``packing.pad_stack``). Pixels beyond a camera's image are cleared here,
    once per frame, and no energy counts them.
    """

    def __init__(self, model: BodyModel, studio: Studio, masks: np.ndarray):
        self.model = model
        masks = np.asarray(masks, dtype=bool)
        if masks.ndim != 3 or masks.shape[0] != len(studio):
            raise ValueError(f"expected (K, H, W) silhouettes of {len(studio)} cameras, got shape {masks.shape}")
        H, W = studio.padded_shape
        if masks.shape[1:] != (H, W):
            raise ValueError(f"silhouettes are {masks.shape[2]}x{masks.shape[1]}, the calibration's largest "
                             f"camera width and height {W}x{H}")
        masks = clear_padding(masks, studio.sizes)
        self.original_studio = studio
        studio, masks = undistort_masks(studio, masks)
        self.studio = studio
        self.masks = masks
        self._whole_image_energies: dict = {}  # half -> energy (see whole_image_energy)

    @cached_property
    def half_studio(self) -> Studio:
        """The studio at half resolution (image sizes rounded down, as the masks are)."""
        return Studio(tuple(replace(c.scaled(HALF), width=c.width // 2, height=c.height // 2) for c in self.studio))

    @cached_property
    def half_masks(self) -> np.ndarray:
        """(K, H // 2, W // 2) bool, camera k's at [:h_k // 2, :w_k // 2] (cleared beyond)."""
        return clear_padding(downsample_masks(self.masks, 2), self.half_studio.sizes)

    @cached_property
    def surface_points(self) -> np.ndarray:
        """(n, 3) centres of the frame's SPOT surface voxels (for the volume energy)."""
        return spot_grid(self.studio, self.masks, VOLUME_GRID).reconstruct(self.masks).surface_points()

    def full_setup(self, params: np.ndarray, half: bool = False) -> EnergySetup:
        studio = self.half_studio if half else self.studio
        masks = self.half_masks if half else self.masks
        windows = tuple(Window(0, 0, c.width, c.height) for c in studio)
        return EnergySetup(studio, windows, masks, tuple(range(16)), np.asarray(params), prerender=False)

    def whole_image_energy(self, half: bool = False):
        """The ``cpu`` energy of the whole images with every segment moving. Nothing is
        pre-rendered, so it does not depend on a pose: built once per frame and resolution
        (its prefix sums over 8 full images cost more than a few evaluations)."""
        if half not in self._whole_image_energies:
            setup = self.full_setup(rest_params(self.model), half=half)
            self._whole_image_energies[half] = make_energy("cpu", self.model, setup)
        return self._whole_image_energies[half]

    def energy(self, backend: str, setup: EnergySetup):
        """The ``backend`` energy of ``setup`` for this frame (the volume energy is over its voxels)."""
        if backend == "volume":  # one energy over the whole body's voxels: no windows
            setup = replace(setup, volume_points=self.surface_points)
        return make_energy(backend, self.model, setup)

    def window_setup(self, params: np.ndarray, segments, size: int, prerender: bool) -> EnergySetup:
        """Windows of ``size`` centred on the projected centre of ``segments`` at ``params``."""
        pose = forward_kinematics(self.model, params)
        R, o = pose.rotations[0, list(segments)], pose.origins[0, list(segments)]
        # the mean of the parts' ellipsoid centres: the middle of the bones, not the joints
        centre = (np.einsum("sij,sj->si", R, self.model.ellipsoid_centres[list(segments)]) + o).mean(axis=0)
        windows, cuts = [], []
        for cam, mask in zip(self.studio, self.masks):
            w = centred_window(cam.project(centre), size)
            windows.append(w)
            cuts.append(cut_window(mask[:cam.height, :cam.width], w))
        return EnergySetup(self.studio, tuple(windows), np.stack(cuts), tuple(segments), np.asarray(params),
                           prerender=prerender)


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

@dataclass(frozen=True)
class SpinePrior:
    """The torso energy plus a soft prior against twisting the spine: ``weight`` silhouette
    pixels per rad^2 of the chest's twist against the pelvis.

    A round pelvis and abdomen make the twist between pelvis and chest almost invisible in
    silhouettes: without a prior the pelvis heading drifts, traded against spine twist and
    hip rotations. The prior keeps that trade-off where the anatomy puts it.
    """

    energy: Callable
    weight: float

    def __post_init__(self):
        if not self.weight > 0:  # the compiled Powell adds the prior only for a positive weight
            raise ValueError(f"the spine twist prior's weight must be positive, got {self.weight}")

    def __call__(self, params: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(params)
        return self.energy(p) + self.weight * p[:, P["spine_z"]] ** 2


def with_spine_prior(energy, weight: float):
    """``energy`` with the spine twist prior of ``weight`` (itself where the weight is 0)."""
    return SpinePrior(energy, weight) if weight > 0 else energy


@dataclass(frozen=True)
class HeldLimbs:
    """The torso's candidates completed: the limbs held in the world orientation they have at
    the reference pose (``hold_limbs_in_world``), then clipped into the joint limits."""

    model: BodyModel
    reference_rotations: np.ndarray  # (16, 3, 3) the reference pose's segment rotations

    def __call__(self, candidates: np.ndarray) -> np.ndarray:
        """(B, 35) -> (B, 35)"""
        return clip_to_limits(hold_limbs_in_world(self.model, candidates, None, self.reference_rotations))


def _clock():
    return time.perf_counter(), time.process_time()


def _stage_backends(options: FitOptions) -> tuple:
    return ("cpu", "gl") if options.energy == "coarse-to-fine" else (options.energy,)


def solve_chain(model: BodyModel, frame: FrameData, chain: str, params: np.ndarray,
                options: FitOptions, iteration: int = 0, position_only: bool = False) -> ChainResult:
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
            energy = with_spine_prior(whole, options.spine_twist_prior if backend != "volume" else 0.0)
            before = before if before is not None else int(energy(x)[0])
            idx = CHAINS["torso"].params
            steps = np.array([options.torso_step_m] * 3 + [options.torso_step_rad] * 6)
            hold = HeldLimbs(model, forward_kinematics(model, x).rotations[0])
            if position_only:
                idx, steps = idx[:3], steps[:3]
            n = 0
            if options.torso_grid_steps > 1 and not position_only:
                # the pelvis heading against the spine twist is the torso's flattest valley:
                # search it on a grid first, as the paper does for the limbs
                x, _, n = grid_search(energy, x, (P["root_heading"], P["spine_z"]), options.torso_grid_steps,
                                      options.torso_grid_range_rad, complete=hold)
            x, energy_value, n2, it = powell(energy, x, idx, steps, options, options.max_evals_torso, complete=hold)
            n += n2
        elif chain == "head":
            setup = frame.window_setup(x, CHAINS["head"].segments, SMALL_WINDOW, options.prerender)
            energy = frame.energy(backend, setup)
            before = before if before is not None else int(energy(x)[0])
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
            before = before if before is not None else int(energy(x)[0])
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
    return ChainResult(chain, x, int(before), int(round(energy_value)), evals, iters, wall1 - wall0, cpu1 - cpu0)


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
REDETECT_STARTS_FIRST_FRAME = 8  # ... on a first frame, the best 8, where no limb is tracked yet
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
                                    REDETECT_STARTS if tracking else REDETECT_STARTS_FIRST_FRAME,
                                    one_per_basin=tracking)
    # a clear gain only: an alternative a few pixels better is as often a mirror pose of the limb
    # (on a first frame the tracked limb is no better than any other: no threshold)
    best_x, best_e = x, current
    threshold = current * (1.0 - (REDETECT_GAIN if tracking else 0.0))
    for e, y in found:
        if e < min(best_e, threshold):
            best_x, best_e = y, e
    return best_x, current, best_e, n


def search_limb(model: BodyModel, frame: FrameData, chain: str, x: np.ndarray, options: FitOptions,
                starts: int, one_per_basin: bool):
    """One limb's whole range on the whole images, the other parts held at x: a grid, then
    Powell from its ``starts`` best points, or with ``one_per_basin`` from the best point of
    each of the ``starts`` best basins (a basin's points crowd the top of the grid otherwise).
    Returns ([(energy, params (35,)) per start, in grid order], the energy at x, evaluations)."""
    proximal, distal, _ = LIMB_PARTS[chain]
    setup = replace(frame.full_setup(x), moving=CHAINS[chain].segments, prerender=True)
    energy = frame.energy("cpu" if options.energy == "coarse-to-fine" else options.energy, setup)
    lo, hi = PARAM_LIMITS[list(proximal)].T
    pad = REDETECT_MARGIN * (hi - lo)
    axes = [np.linspace(lo[i] + pad[i], hi[i] - pad[i], REDETECT_STEPS if i < 3 else REDETECT_HINGE_STEPS)
            for i in range(4)]
    cand = np.repeat(x[None], np.prod([len(a) for a in axes]), axis=0)
    cand[:, list(proximal)] = np.array(list(product(*axes)))
    order = np.argsort(energy(cand), kind="stable")
    if one_per_basin:
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


LIMB_ALTERNATIVES = 2  # per limb: other basins refitted after a first frame's search


def limb_alternatives(model: BodyModel, frame: FrameData, chain: str, x: np.ndarray, options: FitOptions,
                      count: int = LIMB_ALTERNATIVES) -> list[np.ndarray]:
    """(35,) poses: x with one limb moved into up to ``count`` of its other basins, the lowest
    energy first. Given a wrong torso the true limb can explain the images worse than a wrong
    one (a forearm folded into its upper arm's silhouette, when it lies in front of the
    trunk); fitted again as a whole, the true limb wins (``server.session.search_frame``)."""
    found, _, _ = search_limb(model, frame, chain, x, options, REDETECT_STARTS_FIRST_FRAME, one_per_basin=True)
    found.sort(key=lambda ey: ey[0])
    poses = np.array([y for _, y in found]).reshape(-1, len(x))
    keep = distinct_rows(limb_joints(model, chain, poses), count, taken=limb_joints(model, chain, x))
    return [poses[k] for k in keep]


# A nearly straight arm's twist about the upper arm hardly shows in silhouettes, and in the
# wrong twist the elbow cannot bend the way the forearm goes, so it stays straight: the arm sits
# in a basin of its own that neither its grid nor its other basins (``limb_alternatives``, which
# tell basins apart by the elbow and wrist) reach. The dance (05_10) frames 15-16: the right
# shoulder's twist 2 rad off, the elbow at its straight limit, the wrist 60 mm off.
ARM_CHAINS = ("left_arm", "right_arm")
ARM_TWISTS = 7                  # turns about the upper arm tried, 360 / (ARM_TWISTS + 1) degrees apart
ARM_TWIST_MAX_ELBOW_RAD = 0.5   # arms bent less than this are tried
ARM_TWIST_ELBOW_RAD = 0.3       # each turned start bent at least this much


def arm_twists(model: BodyModel, chain: str, params: np.ndarray) -> np.ndarray:
    """(ARM_TWISTS, 35) ``params`` with ``chain``'s upper arm turned about its own axis by
    k * 2 pi / (ARM_TWISTS + 1), k = 1..ARM_TWISTS (the elbow stays where it is), and the elbow
    bent at least ARM_TWIST_ELBOW_RAD, within the joint limits."""
    shoulder, elbow = list(CHAINS[chain].params[:3]), CHAINS[chain].params[3]
    upper_arm, forearm = CHAINS[chain].segments[:2]  # a segment's joint is where it starts
    axis = model.joint_rest[forearm] - model.joint_rest[upper_arm]
    axis = axis / np.linalg.norm(axis)  # the rest pose's upper arm, in the shoulder's frame
    angles = np.arange(1, ARM_TWISTS + 1) * (2.0 * np.pi / (ARM_TWISTS + 1))
    turned = rotvec_to_matrix(np.asarray(params)[shoulder]) @ rotvec_to_matrix(angles[:, None] * axis)
    out = np.repeat(np.asarray(params, dtype=np.float64)[None], ARM_TWISTS, axis=0)
    out[:, shoulder] = matrix_to_rotvec(turned)
    out[:, elbow] = np.maximum(out[:, elbow], ARM_TWIST_ELBOW_RAD)
    return clip_to_limits(out)


def shoulder_turn_rad(params: np.ndarray, other: np.ndarray, chain: str) -> float:
    """The angle between the shoulder rotations of ``chain``'s arm in two poses (35,), radians."""
    shoulder = list(CHAINS[chain].params[:3])
    relative = rotvec_to_matrix(np.asarray(params)[shoulder]).T @ rotvec_to_matrix(np.asarray(other)[shoulder])
    return float(np.linalg.norm(matrix_to_rotvec(relative)))


def arm_twist_alternative(model: BodyModel, frame: FrameData, chain: str, x: np.ndarray, options: FitOptions,
                          neighbour: np.ndarray | None = None) -> np.ndarray | None:
    """(35,) ``x`` with ``chain``'s arm solved (``solve_chain`` without its grid) from each of
    its ``arm_twists``, the lowest, where that is below the arm solved from ``x`` itself; None
    where none is, or where the arm is bent ARM_TWIST_MAX_ELBOW_RAD or more (its twist shows).
    Given the ``neighbour`` frame's fit (35,), only the solved arms whose shoulder rotation is
    nearer the neighbour's than ``x``'s count: an arm does not turn half a turn between
    frames, and a wrong twist can have less energy (walk frame 12: 15,404 against 15,473 for
    the arm as tracked, 62 mm off at the wrist against 26)."""
    if x[CHAINS[chain].params[3]] >= ARM_TWIST_MAX_ELBOW_RAD:
        return None
    local = replace(options, grid_steps=1)  # the turned starts are the grid; a 3^4 grid each costs 4x
    turned = [solve_chain(model, frame, chain, y, local, iteration=1) for y in arm_twists(model, chain, x)]
    if neighbour is not None:
        away = shoulder_turn_rad(x, neighbour, chain)
        turned = [r for r in turned if shoulder_turn_rad(r.params, neighbour, chain) < away]
    if not turned:
        return None
    lowest = min(turned, key=lambda r: r.energy)
    own = solve_chain(model, frame, chain, x, local, iteration=1)
    return lowest.params if lowest.energy < own.energy else None


def full_energy(model: BodyModel, frame: FrameData, params: np.ndarray) -> int:
    """Whole-body XOR energy at full resolution (the convergence test and the reported energy)."""
    return int(frame.whole_image_energy()(params)[0])


# dispatch(jobs, params, iteration) starts the limb solves (or a refinement's hops, HOP_JOBS)
# and returns a function that waits for and returns their ChainResults (in the order
# of ``jobs``); the server solves the head in between, so a cluster's clients and the server
# work at the same time.
Dispatch = Callable[[list, np.ndarray, int], Callable[[], list]]


def solve_locally(model: BodyModel, frame: FrameData, options: FitOptions, frame_number: int = 0) -> Dispatch:
    """Dispatch in this process: each job by ``solve_job``, in order."""
    def dispatch(jobs: list, params: np.ndarray, iteration: int):
        return lambda: [solve_job(model, frame, j, params, options, iteration, frame_number) for j in jobs]

    return dispatch


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


def hop(model: BodyModel, frame: FrameData, params: np.ndarray, options: FitOptions, index: int,
        seed: int, job: str) -> ChainResult:
    """Hop number ``index`` from ``params`` (35,): chain HOP_CHAINS[index % 5] is moved by a
    random step drawn from (``seed``, ``index``) alone (the torso with the limbs held in their
    world orientation), and the whole body is fitted from there by Powell over all 35
    parameters at once, on the hops' objective: the whole-image ``cpu`` energy plus the spine
    prior. Returns it as ``job``'s ChainResult whose energies (before, after) are that
    objective, rounded here to whole pixels so that a cluster compares the same numbers."""
    wall0, cpu0 = _clock()
    objective = with_spine_prior(frame.whole_image_energy(), options.spine_twist_prior)
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
    before, after = (round(float(objective(p[None])[0])) for p in (np.asarray(params, dtype=np.float64), x))
    wall1, cpu1 = _clock()
    return ChainResult(job, x, before, after, n + 2, 1, wall1 - wall0, cpu1 - cpu0)


def hop_fit(params: np.ndarray, options: FitOptions, dispatch: Dispatch, side_by_side: int = 1) -> FrameResult:
    """Basin hopping from ``params`` (35,): ``options.refine_hops`` hops (``hop``), one after
    another, each from the best pose so far; a hop with a lower objective (XOR energy plus the
    spine prior, what each hop's Powell minimises) becomes the best.
    ``dispatch`` runs the hops with ``options``, ``side_by_side`` (1..len(HOP_JOBS)) at once,
    all from the same best: hops k..k+n-1 as jobs HOP_JOBS[:n] with iteration k. Where one of
    them is lower, the next round starts after it and the hops beyond it are dropped: they
    started from a pose that is no longer the best. So the result is that of the hops one
    after another, however many run side by side; a cluster gains where hops fail, as most
    do once the first few have found the valley. ``dispatch`` must run the hops with these
    ``options`` (``solve_job`` reads the hop count from them). Returns the best (``params``
    where no hop was lower) with its objective as ``energy`` (callers that compare it with other
    fits take its ``full_energy``); its ``evaluations`` are those of the hops one after
    another, its ``chains`` every hop's ChainResult, dropped ones too.

    Why: the hierarchy moves one chain at a time, and a frame whose torso and a limb are off
    together sits in a valley that no single chain can go down. Basketball frame 85 (the clip's
    last, its left ankle 70 mm off): the energy falls all along the straight line from the fit
    to the truth, yet neither a chain's own search nor Powell over all 35 parameters from the
    fit moves down it; a hop from a moved leg does. A whole-image evaluation costs tens of
    microseconds, so a hop of a few thousand evaluations costs about 0.1 s."""
    if options.refine_hops < 1:
        raise ValueError(f"hop_fit needs refine_hops >= 1, got {options.refine_hops}")
    if not 1 <= side_by_side <= len(HOP_JOBS):
        raise ValueError(f"side_by_side must be 1..{len(HOP_JOBS)}, got {side_by_side}")
    best, best_energy = np.array(params, dtype=np.float64), None
    hops, evaluations, done = [], 0, 0
    while done < options.refine_hops:
        results = dispatch(list(HOP_JOBS[:min(side_by_side, options.refine_hops - done)]), best, done)()
        hops += results
        if best_energy is None:
            best_energy = results[0].energy_before
        lower = next((k for k, r in enumerate(results) if r.energy < best_energy), None)
        if lower is not None:
            best, best_energy = results[lower].params, results[lower].energy
        kept = results if lower is None else results[:lower + 1]
        evaluations += sum(r.evaluations for r in kept)
        done += len(kept)
    return FrameResult(best, int(best_energy), options.refine_hops, evaluations, hops)


def solve_job(model: BodyModel, frame: FrameData, job: str, params: np.ndarray, options: FitOptions,
              iteration: int = 0, frame_number: int = 0) -> ChainResult:
    """A client's unit of work: a chain's solve (``solve_chain``), or a hop of ``hop_fit``: job
    HOP_JOBS[k] is hop number ``iteration`` + k, seeded by ``frame_number`` (so the same pose
    wherever it runs)."""
    if job not in HOP_JOBS:
        return solve_chain(model, frame, job, params, options, iteration=iteration)
    index = iteration + HOP_JOBS.index(job)
    if index >= options.refine_hops:
        raise ValueError(f"{job} of round {iteration} is hop {index}; refine_hops={options.refine_hops} has no such hop")
    return hop(model, frame, params, options, index, frame_number, job)


def merge_chains(params: np.ndarray, results: list) -> np.ndarray:
    """Take each result's own chain parameters (results of independent Jacobi solves)."""
    out = np.array(params, dtype=np.float64)
    for r in sorted(results, key=lambda r: r.chain):
        idx = list(CHAINS[r.chain].params)
        out[idx] = r.params[idx]
    return out


SCHEDULES = ("held", "position-first")  # the first round's torso: all 9 parameters, or the root position
# A hypothesis whose energy after a round is this fraction above the best so far is not fitted
# on: over walk, dance and basketball it saved 4% of the evaluations at the same accuracy; at
# 1% it saved 13%, but the dance lost an arm.
ABANDON_MARGIN = 0.03


def fit_frame(model: BodyModel, frame: FrameData, start: np.ndarray, options: FitOptions,
              dispatch: Dispatch | None = None, extra_starts: tuple = ()) -> FrameResult:
    """Fit one frame from ``start`` (the previous frame's pose). ``dispatch`` solves limb chains.

    The frame is fitted from several hypotheses and the one of lowest full energy is kept (the
    first on a tie):
    - the start, with the first round's torso fitted in all 9 parameters;
    - with ``options.hypotheses`` = 2, the start again, with only the root position fitted in
      the first round. The limbs start where they were in the previous frame, so in the first
      round they pull the torso towards last frame's pose: turning the pelvis to meet a swinging
      thigh is the walk's typical error; moving only the root first avoids it, but lags behind
      a turning dancer;
    - with ``options.turn_hypotheses`` = n > 0, the start turned about the vertical by -d, +d,
      -2d, +2d, ... up to n turn steps d = ``options.turn_step_rad``, the whole body with it.
      The pelvis heading is the torso's flattest valley: a tracked pose can sit turned from the
      truth with the hips twisted back to keep the legs in place, a coordinated minimum that the
      torso-then-limbs hierarchy cannot leave, since neither the torso nor a limb alone can undo
      it. Refitting from turned starts can.
    - each of ``extra_starts`` (35,), e.g. ``tilted_ahead``'s.
    Every hypothesis is fitted to the end unless its first round leaves it ABANDON_MARGIN above
    the best so far: choosing the best after the first round (to save time) lost an arm on the
    dance clip. The best then gets up to ``options.polish_iterations`` more rounds while its
    energy still falls: two rounds stop short of the minimum (a walk frame fitted again from
    its own result lost 0.4-1.1% of its energy and 1-4 mm of error). With
    ``options.redetect_turn`` "final", the limbs are then re-detected against the best
    (``_redetect_and_refit``).
    """
    wall0 = time.perf_counter()
    dispatch = dispatch or solve_locally(model, frame, options)
    hypotheses = [(start, schedule == "position-first") for schedule in SCHEDULES[:options.hypotheses]]
    hypotheses += [(turned(start, sign * step * options.turn_step_rad), False)
                   for step in range(1, options.turn_hypotheses + 1) for sign in (-1, 1)]
    hypotheses += [(np.asarray(x, dtype=np.float64), False) for x in extra_starts]
    results = []
    for x, position_first in hypotheses:
        # a hypothesis far above the best so far after its first round is not fitted on
        give_up = min(r.energy for r in results) * (1.0 + ABANDON_MARGIN) if results else None
        results.append(_fit_schedule(model, frame, x, options, dispatch, position_first, give_up_above=give_up))
    best = lowest_energy(results)
    if options.polish_iterations:
        polished = _fit_schedule(model, frame, best.params, options, dispatch, False, options.polish_iterations)
        best = lowest_energy([best, polished])
    if options.redetect_limbs and options.redetect_turn == "final":
        best = _redetect_and_refit(model, frame, best, options, dispatch)
    best.wall_seconds = time.perf_counter() - wall0
    return best


def _redetect_and_refit(model: BodyModel, frame: FrameData, best: FrameResult, options: FitOptions,
                        dispatch: Dispatch) -> FrameResult:
    """Every limb searched over its whole range against the fitted pose (side by side, on the
    clients); if any is found elsewhere, the frame fitted again from there, the lower energy
    kept. A limb that moved faster than the local search (a basketball player's forearm swing)
    is found in the frame it is lost."""
    found = dispatch(list(LIMB_CHAINS), best.params, REDETECT_ROUND)()
    moved = [r for r in found if r.energy < r.energy_before]
    refits = [_fit_schedule(model, frame, merge_chains(best.params, moved), options, dispatch, False)] if moved else []
    chains = [*best.chains, *found, *(c for r in refits for c in r.chains)]
    evaluations = best.evaluations + sum(r.evaluations for r in [*found, *refits])
    best = min([best, *refits], key=lambda r: r.energy)
    best.chains, best.evaluations = chains, evaluations
    return best


def turned(params: np.ndarray, angle: float) -> np.ndarray:
    """(35,) the same pose turned by ``angle`` (rad) about the vertical through the pelvis."""
    out = np.array(params, dtype=np.float64)
    out[P["root_heading"]] += angle
    return out


def rotated_about_pelvis(model: BodyModel, params: np.ndarray, axis: int, angle: float) -> np.ndarray:
    """(35,) the same pose with the whole body rotated by ``angle`` (rad) about the pelvis's own
    axis ``axis`` (0: towards its left, 1: its back, 2: up its spine) through the root joint,
    the limbs carried along; the heading kept within pi of the pose's own."""
    x = np.array(params, dtype=np.float64)
    R = forward_kinematics(model, x, segments=(0,)).rotations[0, 0]
    heading, tilt = heading_tilt((R @ rotvec_to_matrix(angle * np.eye(3)[axis]))[None])
    x[P["root_heading"]] = nearest_turn(heading[0], x[P["root_heading"]])
    x[[P["root_tilt_x"], P["root_tilt_y"]]] = tilt[0]
    return x


def midway(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """(35,) the pose halfway between two poses (35,) parameter by parameter, within the joint
    limits: a frame's start between its neighbours' fits."""
    return clip_to_limits((np.asarray(before, dtype=np.float64) + np.asarray(after, dtype=np.float64)) / 2.0)


TILT_MOVING_RAD = 0.03  # pelvis tilt change per frame above which a tilted-ahead start is tried
TILT_AHEAD_RAD = 0.25   # how far ahead of the last tilt that start is


def tilted_ahead(params: np.ndarray, params_before: np.ndarray | None) -> tuple:
    """() or a 1-tuple of (35,): ``params`` with the pelvis tilted TILT_AHEAD_RAD further along
    the way its tilt moved since ``params_before`` (the frame before), when it moved by at
    least TILT_MOVING_RAD. The turn hypotheses turn about the vertical only; a dancer bending
    the pelvis far forward or sideways (a penche) outruns the fit's tilt, which then trails
    further every frame."""
    if params_before is None:
        return ()
    tilt = [P["root_tilt_x"], P["root_tilt_y"]]
    moved = np.asarray(params, dtype=np.float64)[tilt] - np.asarray(params_before, dtype=np.float64)[tilt]
    size = float(np.linalg.norm(moved))
    if size < TILT_MOVING_RAD:
        return ()
    ahead = clip_to_limits(np.array(params, dtype=np.float64))
    ahead[tilt] = np.clip(ahead[tilt] + TILT_AHEAD_RAD * moved / size, PARAM_LIMITS[tilt, 0], PARAM_LIMITS[tilt, 1])
    return (ahead,)


def lowest_energy(results: list, score: Callable | None = None) -> FrameResult:
    """The FrameResult of lowest energy (or lowest ``score(result)``; the first on a tie), now
    carrying the chain solves and evaluations of every one of ``results``, in order: what was
    spent to choose it."""
    chains = [c for r in results for c in r.chains]
    evaluations = sum(r.evaluations for r in results)
    best = min(results, key=score or (lambda r: r.energy))
    best.chains, best.evaluations = chains, evaluations
    return best


def _fit_schedule(model: BodyModel, frame: FrameData, start: np.ndarray, options: FitOptions,
                  dispatch: Dispatch, position_first: bool, rounds: int | None = None,
                  give_up_above: float | None = None) -> FrameResult:
    x = np.array(start, dtype=np.float64)
    best = full_energy(model, frame, x)
    result = FrameResult(x, best, 0, 0)
    # re-detecting one limb per round: every limb gets its round before the fit may stop
    rounds_needed = len(LIMB_CHAINS) if options.redetect_limbs and options.redetect_turn == "round" else 1
    for it in range(rounds or options.max_iterations):
        torso = solve_chain(model, frame, "torso", x, options, position_only=position_first and it == 0)
        after_torso = torso.params
        # the limbs go out first so that clients work while the server fits the head
        collect_limbs = dispatch(list(LIMB_CHAINS), after_torso, it)
        head = solve_chain(model, frame, "head", after_torso, options)
        limb_results = collect_limbs()
        x_new = merge_chains(after_torso, [*limb_results, head])
        e_new = full_energy(model, frame, x_new)
        result.chains.extend([torso, *limb_results, head])
        result.evaluations += torso.evaluations + head.evaluations + sum(r.evaluations for r in limb_results)
        result.iterations = it + 1
        improved = best - e_new
        if e_new <= best:
            x, best = x_new, e_new
        if (improved < options.min_improvement * max(best, 1) and not (position_first and it == 0)
                and it + 1 >= rounds_needed):
            break
        if give_up_above is not None and best > give_up_above and not (position_first and it == 0):
            break
    result.params, result.energy = x, best
    return result
