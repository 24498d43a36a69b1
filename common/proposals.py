"""Start poses for a search (``common.search``): every way the fit proposes where a frame might
be, each a pure function of poses and the frame's images.

- about the start: turned about the vertical (``turned``), tilted ahead (``tilted_ahead``),
  rotated about the pelvis's own axes (``rotated_about_pelvis``), halfway between neighbours
  (``midway``);
- one limb moved: into its other basins (``limb_alternatives``), an arm to its other twists
  (``arm_twists``, the solves' choice ``arm_twist_alternative``);
- no start at all: the frame's voxels and ellipsoids, standing, head-down and posture starts
  (``voxel_starts``);
- a search's choice among its fits also weighs how likely a body is upside down
  (``inversion_cost``).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from common import voxels
from common.body import (CHAINS, JOINT_NAMES, P, PARAM_LIMITS, BodyModel, clip_to_limits,
                         forward_kinematics, matrix_to_rotvec, rest_params, rotvec_to_matrix)
from common.errors import UserError
from common.fitting import BASIN_STARTS, FitOptions, distinct_rows, limb_joints, powell, search_limb
from common.frame import FrameData, spot_grid
from common.postures import SEARCH_POSTURES, posture_params
from common.retarget import heading_tilt, nearest_turn

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


def pelvis_twisted(model: BodyModel, params: np.ndarray, angle: float) -> np.ndarray:
    """(35,) the pose with the pelvis alone turned by ``angle`` (rad) about the vertical: the
    chest and the thighs keep their orientation in the world (the spine and the hips turn back
    by as much), so the shoulders and the legs stay where they were."""
    x = np.array(params, dtype=np.float64)
    R = forward_kinematics(model, x, segments=(0,)).rotations[0, 0]
    x[P["root_heading"]] += angle
    back = R.T @ rotvec_to_matrix(np.array([0.0, 0.0, -angle])) @ R  # the old pelvis in the new one's frame
    for name in ("spine", "l_hip", "r_hip"):
        idx = [P[f"{name}_x"], P[f"{name}_y"], P[f"{name}_z"]]
        x[idx] = matrix_to_rotvec(back @ rotvec_to_matrix(x[idx]))
    return clip_to_limits(x)


# The joints turned by rotation vectors: a vector v of angle |v| and the vector of angle
# |v| - 2 pi along it are the same rotation, and fits near half a turn land on either
BALL_JOINTS = tuple([P[f"{joint}_x"], P[f"{joint}_y"], P[f"{joint}_z"]]
                    for joint in ("spine", "l_shoulder", "r_shoulder", "l_hip", "r_hip"))
# ... the twin taken only within this of the reference's vector (rad): two rotations that near
# are one pose written two ways; farther apart (a spine bent forward against one bent back),
# the way between them through the joint's limits is the plain one
TWIN_NEAR_RAD = np.pi / 2


def same_pose_near(params: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(35,) ``params`` written as the same pose nearest the ``reference`` pose's (35,) numbers:
    its root heading moved by whole turns to within pi of the reference's, and each ball joint's
    rotation vector v replaced by v (1 - 2 pi / |v|), the same rotation the other way round,
    where that lies nearer the reference's and within TWIN_NEAR_RAD of it. The heading is
    unwrapped, and two fits of neighbouring frames can stand a whole turn apart in their numbers
    (a frame searched again from the voxels), or hold a shoulder turned nearly half a turn as
    vectors pointing opposite ways; a mean or a straight line between them must not spin the
    body or the limb round."""
    out = np.array(params, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    out[P["root_heading"]] = nearest_turn(out[P["root_heading"]], reference[P["root_heading"]])
    for idx in BALL_JOINTS:
        v = out[idx]
        angle = float(np.linalg.norm(v))
        if angle > 0.0:
            other = v * (1.0 - 2.0 * np.pi / angle)
            apart = np.linalg.norm(other - reference[idx])
            if apart < min(np.linalg.norm(v - reference[idx]), TWIN_NEAR_RAD):
                out[idx] = other
    return out


def midway(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """(35,) the pose halfway between two poses (35,) parameter by parameter, ``after`` written
    as the same pose nearest ``before`` (``same_pose_near``), within the joint limits: a frame's
    start between its neighbours' fits. Without it, 05_17 from source frame 401 started frame 15
    halfway between a fit at heading 3.58 and a recovered one at 9.75 (3.47 plus a turn): facing
    backwards; and 05_13's frame 13 there with the right shoulder turned half a turn from both
    neighbours', 0.43 rad apart but written as vectors near pi pointing opposite ways."""
    before = np.asarray(before, dtype=np.float64)
    return clip_to_limits((before + same_pose_near(after, before)) / 2.0)


def moved_on(params: np.ndarray, params_before: np.ndarray | None) -> tuple:
    """() or a 1-tuple of (35,): ``params`` moved on by as much as every parameter moved since
    ``params_before`` (the frame before), within the joint limits: where the actor is going at
    a constant speed. The previous frame's fit and its turns trail a body that keeps moving
    (the dance lost a limb in 36 of 100 frames tracked from them, 23 with this start too)."""
    if params_before is None:
        return ()
    x = np.asarray(params, dtype=np.float64)
    return (clip_to_limits(2.0 * x - same_pose_near(params_before, x)),)


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



LIMB_ALTERNATIVES = 2  # per limb: other basins refitted after a first frame's search


def limb_alternatives(model: BodyModel, frame: FrameData, chain: str, x: np.ndarray, options: FitOptions,
                      count: int = LIMB_ALTERNATIVES) -> tuple[list[np.ndarray], int]:
    """((35,) poses: x with one limb moved into up to ``count`` of its other basins, the lowest
    energy first; the evaluations the limb's search spent). Given a wrong torso the true limb can
    explain the images worse than a wrong one (a forearm folded into its upper arm's silhouette,
    when it lies in front of the trunk); fitted again as a whole, the true limb wins
    (``server.session.search_frame``)."""
    found, _, evaluations = search_limb(model, frame, chain, x, options, BASIN_STARTS)
    found.sort(key=lambda ey: ey[0])
    poses = np.array([y for _, y in found]).reshape(-1, len(x))
    keep = distinct_rows(limb_joints(model, chain, poses), count, taken=limb_joints(model, chain, x))
    return [poses[k] for k in keep], evaluations


# A nearly straight arm's twist about the upper arm hardly shows in silhouettes, and in the
# wrong twist the elbow cannot bend the way the forearm goes, so it stays straight: the arm sits
# in a basin of its own that neither its grid nor its other basins (``limb_alternatives``, which
# tell basins apart by the elbow and wrist) reach. The dance (05_10) frames 15-16: the right
# shoulder's twist 2 rad off, the elbow at its straight limit, the wrist 60 mm off.
# A forearm folded onto its upper arm (the elbow at its other limit) hides the twist as well, and
# unfolds only the wrong way: 05_17 with other noise (`--seed 1`), its last frame, the right
# forearm folded up to the shoulder, the wrist 464 mm off; turned and half unfolded, three of the
# seven twists fit into the truth's basin (9 mm, 9% less energy), folded as it was none does.
ARM_CHAINS = ("left_arm", "right_arm")
ARM_TWISTS = 7                  # turns about the upper arm tried, 360 / (ARM_TWISTS + 1) degrees apart
ARM_TWIST_MAX_ELBOW_RAD = 0.5   # arms bent less than this are tried ...
ARM_TWIST_FOLDED_RAD = 0.5      # ... and arms folded to within this of the elbow's limit
ARM_TWIST_ELBOW_RAD = 0.3       # each turned start bent at least this much
ARM_TWIST_UNFOLDED_RAD = 1.5    # ... and at most this much: a folded arm's turns start half unfolded


def arm_twists(model: BodyModel, chain: str, params: np.ndarray) -> np.ndarray:
    """(ARM_TWISTS, 35) ``params`` with ``chain``'s upper arm turned about its own axis by
    k * 2 pi / (ARM_TWISTS + 1), k = 1..ARM_TWISTS (the elbow stays where it is), and the elbow
    bent between ARM_TWIST_ELBOW_RAD and ARM_TWIST_UNFOLDED_RAD, within the joint limits."""
    shoulder, elbow = list(CHAINS[chain].params[:3]), CHAINS[chain].params[3]
    upper_arm, forearm = CHAINS[chain].segments[:2]  # a segment's joint is where it starts
    axis = model.joint_rest[forearm] - model.joint_rest[upper_arm]
    axis = axis / np.linalg.norm(axis)  # the rest pose's upper arm, in the shoulder's frame
    angles = np.arange(1, ARM_TWISTS + 1) * (2.0 * np.pi / (ARM_TWISTS + 1))
    turned = rotvec_to_matrix(np.asarray(params)[shoulder]) @ rotvec_to_matrix(angles[:, None] * axis)
    out = np.repeat(np.asarray(params, dtype=np.float64)[None], ARM_TWISTS, axis=0)
    out[:, shoulder] = matrix_to_rotvec(turned)
    out[:, elbow] = np.clip(out[:, elbow], ARM_TWIST_ELBOW_RAD, ARM_TWIST_UNFOLDED_RAD)
    return clip_to_limits(out)


def shoulder_turn_rad(params: np.ndarray, other: np.ndarray, chain: str) -> float:
    """The angle between the shoulder rotations of ``chain``'s arm in two poses (35,), radians."""
    shoulder = list(CHAINS[chain].params[:3])
    relative = rotvec_to_matrix(np.asarray(params)[shoulder]).T @ rotvec_to_matrix(np.asarray(other)[shoulder])
    return float(np.linalg.norm(matrix_to_rotvec(relative)))


def arm_twist_tried(chain: str, x: np.ndarray) -> bool:
    """Whether ``chain``'s arm in ``x`` (35,) is straight or folded enough for its twists to be
    tried: bent between ARM_TWIST_MAX_ELBOW_RAD and ARM_TWIST_FOLDED_RAD short of its limit,
    its twist shows."""
    elbow = CHAINS[chain].params[3]
    bend = x[elbow]
    return bool(bend < ARM_TWIST_MAX_ELBOW_RAD or bend > PARAM_LIMITS[elbow, 1] - ARM_TWIST_FOLDED_RAD)


def arm_twist_options(options: FitOptions) -> FitOptions:
    """The arm's solves from its twists and from ``x`` itself: without the grid (the turned
    starts are the grid; a 3^4 grid each costs 4 times as much)."""
    return replace(options, grid_steps=1)


def arm_twists_towards(chain: str, x: np.ndarray, twisted: list, neighbour: np.ndarray | None) -> list:
    """Of ``twisted`` (ChainResults: ``chain``'s arm solved from each of ``arm_twists``), the
    ones that count: given the ``neighbour`` frame's fit (35,), only those whose shoulder
    rotation is nearer the neighbour's than ``x``'s. An arm does not turn half a turn between
    frames, and a wrong twist can have less energy (walk frame 12: 15,404 against 15,473 for
    the arm as tracked, 62 mm off at the wrist against 26)."""
    if neighbour is None:
        return list(twisted)
    away = shoulder_turn_rad(x, neighbour, chain)
    return [r for r in twisted if shoulder_turn_rad(r.params, neighbour, chain) < away]


def arm_twist_alternative(turned: list, own) -> np.ndarray | None:
    """(35,) the lowest of ``turned`` (ChainResults, ``arm_twists_towards``) where it is below
    ``own`` (the arm solved the same way from ``x`` itself), else None."""
    lowest = min(turned, key=lambda r: r.energy)
    return lowest.params if lowest.energy < own.energy else None


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

