"""Fitted motion out: glTF (.glb), BVH, OpenSim TRC and MOT, EasyMocap keypoints3d, C3D, JSON lines, CSV.

Axis conventions of the files we write (docs/exports.md has the full table and the import
settings of Blender, OpenSim and three.js):
- GLB: metres, Y up, the actor facing +Z at rest (glTF's rules; ``common.gltf``). Blender's
  glTF importer turns it into its Z-up world, which is then our z-up fit frame.
- BVH: Y up, the actor facing +Z in the rest pose, centimetres. Blender's importer (default
  forward -Z, up Y) turns this into its Z-up world, which is then exactly our world: x to the
  actor's left at rest, the actor facing -y, z up. The rest pose is the body model's A-pose or
  a T-pose (``BVH_RESTS``); the motion is the same in both.
- TRC and MOT: OpenSim's convention, Y up, the actor's rest forward along +X, Z to its right,
  metres; TRC markers are named as Pose2Sim's HALPE_26 skeleton names them.
- keypoints3d: EasyMocap's per-frame JSON, body25 joint order, the user's world, metres.
- C3D: the user's world unchanged, millimetres; POINT:Y_SCREEN names its up axis (X_SCREEN +X,
  or +Y where x is up), so that viewers such as Mokka show the actor upright.
- CSV and JSON lines: the user's world, metres.

Upright formats (GLB, BVH, TRC, MOT) are written from the z-up fit frame, so that their up is
the actor's up whatever the user's world; keypoints3d, C3D, CSV and JSON lines keep the user's
world, the one poses.jsonl and the calibration are in (for a z-up world the two are the same).

Every writer takes a ``FittedMotion``: frame numbers, frame rate, per-frame parameters and joint
positions, and the body model (with the fitted actor's segment lengths) that turns one into the
other.

One module of about 520 lines: the eight writers share ``FittedMotion`` and the axis conversions,
each of them one short section.
"""
from __future__ import annotations

import csv
import json
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from common.body import (
    HEAD_TOP_SEGMENT, JOINT_NAMES, PARAM_COUNT, PARAM_NAMES, SEGMENT_PARENTS, BodyModel,
    forward_kinematics, joints_dict, load_body_model, local_rotations,
)
from common.bvh import BvhMotion, bvh_global_transforms, end_site_positions, write_bvh
from common.errors import UserError
from common.gltf import write_glb
from common.world import world_frame
from common.retarget import nearest_turn

FORMATS = ("glb", "mot", "trc", "keypoints3d", "bvh", "c3d", "json", "csv")
# keypoints3d is a folder (one JSON file per frame); the others are files
SUFFIXES = {"glb": ".glb", "mot": ".mot", "trc": ".trc", "keypoints3d": "_keypoints3d", "bvh": ".bvh", "c3d": ".c3d",
            "json": ".jsonl", "csv": ".csv"}
FOLDER_FORMATS = ("keypoints3d",)
ALL_FORMATS = "all"  # a name for every one of FORMATS
EXPORT_STEM = "motion"  # RESULT/motion.<suffix>: where mocap export writes by default


def named_formats(names) -> list[str]:
    """The formats ``names`` (FORMATS or ALL_FORMATS) stand for, in order, each once."""
    return list(dict.fromkeys(FORMATS if ALL_FORMATS in names else names))


def export_name(fmt: str) -> str:
    """The default file (or folder) name of a format's export in a result folder."""
    return f"{EXPORT_STEM}{SUFFIXES[fmt]}"
BVH_RESTS = ("apose", "tpose")
DEFAULT_BVH_REST = "apose"  # the body model's own rest, as BVH files of ours always had

BVH_UNITS_PER_M = 100.0  # centimetres
MM_PER_M = 1000.0
# our world (z up, facing -y) -> BVH world (y up, facing +z)
TO_BVH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
# our world -> OpenSim (y up, rest forward +x, z to the right)
TO_OPENSIM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
ROT_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")
# BVH joints per body segment (a joint sits at its segment's proximal end); the head segment
# is split into Neck (which carries its rotation) and Head (fixed, HEAD_JOINT_FRACTION of the
# way to the top of the head), the layout Blender rigs and BVH importers, ours included, expect.
SEGMENT_BVH_NAMES = (
    "Hips", "Spine", "Chest", "Neck",
    "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
    "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot",
)
HEAD_JOINT = "Head"
HEAD_JOINT_FRACTION = 0.35  # of neck -> head top: about the base of the skull
BVH_JOINT_NAMES = SEGMENT_BVH_NAMES[:4] + (HEAD_JOINT,) + SEGMENT_BVH_NAMES[4:]  # file (depth-first) order
EXTREMITY_END_SCALE = 2.0  # End Sites of hands and feet: twice the ellipsoid centre's offset
ACTOR_TOLERANCE_M = 1e-6   # recorded joints vs forward kinematics of the rebuilt actor
C3D_LABEL_LENGTH = 16      # characters per C3D point label


def frame_step(frames) -> int:
    """The common step of frame numbers (F,): their differences' greatest common divisor (1 for
    a single frame): 5 for a take imported with ``--step 5``, a missing frame or not."""
    steps = np.diff(np.unique(np.asarray(frames, dtype=np.int64)))
    return max(int(np.gcd.reduce(steps)) if len(steps) else 1, 1)


def frames_off_step(frames) -> list[int]:
    """The frame numbers between the first and the last of ``frames`` (F,) on their
    ``frame_step`` that ``frames`` lacks (a frame that failed to import or to fit)."""
    frames = np.unique(np.asarray(frames, dtype=np.int64))
    if len(frames) < 2:
        return []
    return sorted(set(range(int(frames[0]), int(frames[-1]) + 1, frame_step(frames))) - set(frames.tolist()))


def sample_rate(frames: np.ndarray, fps: float) -> float:
    """Samples per second of fits at ``frames`` (F,) (frame numbers of a recording at ``fps``):
    ``fps`` over their ``frame_step``, so that a take imported with ``--step 5`` from 50 fps
    plays at 10. Formats with one fixed rate (BVH, C3D, TRC) would otherwise play it five times
    too fast, while those that keep each frame's time (glTF, MOT, CSV, JSON) already have it
    right."""
    return float(fps) / frame_step(frames)


@dataclass(frozen=True)
class FittedMotion:
    """A fitted sequence ready to export.

    frames: (F,) int frame numbers; fps: frames per second; params: (F, 35);
    joints: (F, 17, 3) world joint positions, metres, in the user's frame (as recorded by the fit);
    model: the actor whose forward kinematics turns params into joints; up: the user's up axis
    (``common.world``): params and ``fit_joints`` are in the z-up fit frame.
    """

    frames: np.ndarray
    fps: float
    params: np.ndarray
    joints: np.ndarray
    model: BodyModel
    up: str = "+z"

    @property
    def world(self):
        return world_frame(self.up)

    @property
    def fit_joints(self) -> np.ndarray:
        """(F, 17, 3) the joints in the z-up fit frame (as params put them): for pictures."""
        return self.world.points_to_fit(self.joints)

    @property
    def times(self) -> np.ndarray:
        """(F,) seconds from the first frame (frame numbers may skip)."""
        return (self.frames - self.frames[0]) / self.fps

    @property
    def rate(self) -> float:
        """Fitted frames per second (``sample_rate``): what formats with one fixed rate write."""
        return sample_rate(self.frames, self.fps)

    @classmethod
    def from_records(cls, records: list[dict], fps: float, source: str = "poses.jsonl",
                     base: BodyModel | None = None) -> "FittedMotion":
        """poses.jsonl records (frame, params, joints {name: [x, y, z]}) -> FittedMotion."""
        if not records:
            raise UserError(f"{source}: no fitted frames to export")
        if not (np.isfinite(fps) and fps > 0):
            raise UserError(f"{source}: frame rate must be positive, got {fps!r}")
        for n, r in enumerate(records, start=1):
            missing = [k for k in ("frame", "params", "joints") if k not in r]
            missing += [f"joints.{j}" for j in JOINT_NAMES if "joints" in r and j not in r["joints"]]
            if missing:
                raise UserError(f"{source}: record {n} (frame {r.get('frame', '?')}): no {', '.join(missing)}")
        try:
            frames = np.array([int(r["frame"]) for r in records])
            params = np.array([r["params"] for r in records], dtype=np.float64)
            joints = np.array([[r["joints"][n] for n in JOINT_NAMES] for r in records], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise UserError(f"{source}: not a poses record ({exc})") from None
        if params.shape != (len(records), PARAM_COUNT) or joints.shape != (len(records), len(JOINT_NAMES), 3):
            raise UserError(f"{source}: expected {PARAM_COUNT} params and {len(JOINT_NAMES)} joints per frame")
        up = str(records[0].get("world_up", "+z"))
        # joints are in the user's world; the body's parameters in the z-up fit frame (common.world)
        model = actor_from_joints(base or load_body_model(), params, world_frame(up).points_to_fit(joints), source)
        return cls(frames, float(fps), params, joints, model, up)


def actor_from_joints(base: BodyModel, params: np.ndarray, joints: np.ndarray,
                      source: str = "poses.jsonl") -> BodyModel:
    """The actor whose segment lengths the recorded joints show: ``base`` rescaled per segment.

    params (F, 35), joints (F, 17, 3). A uniform size change scales the whole body (mesh and
    ellipsoids); what remains per segment stretches that segment along its rest direction,
    which leaves every hinge axis as it was. Raises UserError when the joints cannot come from
    the body model at all (a result made with another model).
    """
    parents = np.array(SEGMENT_PARENTS[1:] + (HEAD_TOP_SEGMENT,))
    children = np.arange(1, 17)
    rec = np.linalg.norm(joints[:, children] - joints[:, parents], axis=-1).mean(axis=0)  # (16,)
    rest = np.linalg.norm(base.joint_rest[children] - base.joint_rest[parents], axis=-1)
    ratio = rec / rest
    scale = float(np.median(ratio))
    model = base.scaled(scale) if abs(scale - 1.0) > 1e-12 else base
    stretch = ratio / scale
    if np.any(np.abs(stretch - 1.0) > 1e-12):
        jr = model.joint_rest.copy()
        offsets = model.joint_rest[children] - model.joint_rest[parents]
        for i, (c, p) in enumerate(zip(children, parents)):  # parents come first
            jr[c] = jr[p] + offsets[i] * stretch[i]
        seg = model.vertex_segment.astype(np.int64)
        vertices = model.vertices + (jr[seg] - model.joint_rest[seg])
        model = replace(model, joint_rest=jr, vertices=vertices)
    err = np.abs(forward_kinematics(model, params).joints - joints).max()
    if err > ACTOR_TOLERANCE_M:
        raise UserError(f"{source}: joints differ from the body model's forward kinematics of params by "
                        f"{err * 1000:.3f} mm; this result was fitted with another body model")
    return model


# ----------------------------------------------------------------------------------------- BVH

def continuous_euler_zxy(R: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations -> (F, 3) intrinsic Z-X-Y Euler angles, degrees, R = Rz Rx Ry.

    Of the two Euler triples of each rotation (and their 360 degree shifts) the one nearest to
    the previous frame's, so that curves in Blender's graph editor do not jump.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock: scipy still returns a valid triple
        e = Rotation.from_matrix(R).as_euler("ZXY")
    alt = np.stack([e[:, 0] + np.pi, np.pi - e[:, 1], e[:, 2] + np.pi], axis=1)
    out = np.empty_like(e)
    out[0] = e[0]
    for f in range(1, len(e)):
        best, best_d = None, np.inf
        for cand in (e[f], alt[f]):
            c = nearest_turn(cand, out[f - 1])
            d = np.abs(c - out[f - 1]).sum()
            if d < best_d:
                best, best_d = c, d
        out[f] = best
    return np.degrees(out)


def rest_rotations(model: BodyModel, rest: str = DEFAULT_BVH_REST) -> np.ndarray:
    """(16, 3, 3) world rotation of each segment from the body model's rest to the rest pose ``rest``.

    "apose": the body model's own rest (arms hanging at about 45 degrees, forearms a little
    forward): identities. "tpose": upper arms and forearms straight out sideways (the left
    along +x), thighs and shins straight down, each turned the shortest way; hands and feet
    turn with their forearm and shin, the torso and head stay.
    """
    if rest not in BVH_RESTS:
        raise UserError(f"unknown BVH rest pose {rest!r}; choose one of {', '.join(BVH_RESTS)}")
    T = np.tile(np.eye(3), (16, 1, 1))
    if rest == "apose":
        return T
    J = model.joint_rest
    lateral, down = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0])
    # (segment, its proximal and distal joints, target direction); the extremity follows
    for seg, a, b, target, extremity in ((4, 4, 5, lateral, None), (5, 5, 6, lateral, 6),
                                         (7, 7, 8, -lateral, None), (8, 8, 9, -lateral, 9),
                                         (10, 10, 11, down, None), (11, 11, 12, down, 12),
                                         (13, 13, 14, down, None), (14, 14, 15, down, 15)):
        T[seg] = _shortest_rotation(J[b] - J[a], target)
        if extremity is not None:
            T[extremity] = T[seg]
    return T


def _shortest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3,), (3,) -> (3, 3) the smallest rotation taking direction a to direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3)  # aligned already (a segment exactly opposite its target does not occur)
    return Rotation.from_rotvec(axis / s * np.arctan2(s, a @ b)).as_matrix()


def params_to_bvh(model: BodyModel, params: np.ndarray, frame_time: float, rest: str = DEFAULT_BVH_REST) -> BvhMotion:
    """(F, 35) fitted parameters -> a BvhMotion in BVH conventions (Y up, cm).

    One joint per segment at its proximal joint, plus the fixed Head joint; the head, hands and
    feet end in End Sites (the head's is the head_top joint). Offsets are the actor's rest
    segments, turned into the rest pose ``rest`` (``rest_rotations``: T_s per segment): a
    segment's offsets and End Sites turn with it, its local rotation becomes
    T_parent L T_s^-1, so that every joint's world position is unchanged. Joints are in
    depth-first order, as the file lists them.
    """
    p = np.atleast_2d(params)
    T = rest_rotations(model, rest)
    TP = np.stack([T[SEGMENT_PARENTS[s]] if s else np.eye(3) for s in range(16)])  # each segment's parent's
    local = TP[None] @ local_rotations(model, p) @ np.swapaxes(T, -1, -2)[None]
    C = TO_BVH
    seg_offsets = (np.einsum("sij,sj->si", TP, model.offsets) @ C.T) * BVH_UNITS_PER_M
    seg_offsets[0] = 0.0  # the root's position comes from its channels
    head_top = C @ T[HEAD_TOP_SEGMENT] @ model.head_top_offset * BVH_UNITS_PER_M
    seg_euler = [continuous_euler_zxy(C @ local[:, s] @ C.T) for s in range(16)]
    index = {s: (s if s <= HEAD_TOP_SEGMENT else s + 1) for s in range(16)}  # segment -> BVH joint
    head = HEAD_TOP_SEGMENT + 1
    parents = np.empty(17, dtype=np.int64)
    offsets = np.empty((17, 3))
    cols = [None] * 17
    for s in range(16):
        j = index[s]
        parents[j] = index[SEGMENT_PARENTS[s]] if SEGMENT_PARENTS[s] >= 0 else -1
        offsets[j] = seg_offsets[s]
        cols[j] = seg_euler[s]
    parents[head], offsets[head] = HEAD_TOP_SEGMENT, HEAD_JOINT_FRACTION * head_top
    cols[head] = np.zeros((len(p), 3))
    cols[0] = np.concatenate([(p[:, 0:3] @ C.T) * BVH_UNITS_PER_M, cols[0]], axis=1)
    channels = [("Xposition", "Yposition", "Zposition") + ROT_CHANNELS] + [ROT_CHANNELS] * 16
    end_parents = [head]
    end_offsets = [(1.0 - HEAD_JOINT_FRACTION) * head_top]
    for s in (6, 9, 12, 15):  # hands and feet
        end_parents.append(index[s])
        end_offsets.append(C @ T[s] @ model.ellipsoid_centres[s] * EXTREMITY_END_SCALE * BVH_UNITS_PER_M)
    return BvhMotion(BVH_JOINT_NAMES, parents, offsets, channels, np.array(end_parents), np.array(end_offsets),
                     frame_time, np.concatenate(cols, axis=1), "silhouette-mocap")


def bvh_to_world_joints(motion: BvhMotion) -> np.ndarray:
    """A BVH we wrote (possibly re-saved by another tool) -> (F, 17, 3) joints, our world, metres.

    Joints are found by name, so another tool's joint order does not matter.
    """
    pos, rot = bvh_global_transforms(motion)
    ends = end_site_positions(motion, transforms=(pos, rot))
    out = np.empty((motion.num_frames, len(JOINT_NAMES), 3))
    for s, name in enumerate(SEGMENT_BVH_NAMES):
        out[:, s] = pos[:, motion.joint_index(name)]
    head = motion.joint_index(HEAD_JOINT)
    out[:, 16] = ends[:, list(motion.end_site_parents).index(head)]
    return bvh_joint_positions_to_world(out)


def bvh_joint_positions_to_world(positions: np.ndarray) -> np.ndarray:
    """(..., 3) positions read from our BVH (Y up, cm) -> our world (Z up, metres)."""
    return (positions @ TO_BVH) / BVH_UNITS_PER_M


def write_motion_bvh(path, model: BodyModel, params: np.ndarray, fps: float, rest: str = DEFAULT_BVH_REST) -> None:
    write_bvh(path, params_to_bvh(model, params, 1.0 / fps, rest))


def write_bvh_export(path, motion: FittedMotion, rest: str = DEFAULT_BVH_REST) -> None:
    write_motion_bvh(path, motion.model, motion.params, motion.rate, rest)


def write_glb_export(path, motion: FittedMotion) -> None:
    """The skinned body, its skeleton and the motion as glTF 2.0 binary (``common.gltf``)."""
    write_glb(path, motion.model, motion.params, motion.times, motion.rate)


# ------------------------------------------------------------------------- joint positions

def _midpoint(a: str, b: str):
    ia, ib = JOINT_NAMES.index(a), JOINT_NAMES.index(b)
    return lambda joints: 0.5 * (joints[..., ia, :] + joints[..., ib, :])


def _joint(name: str):
    i = JOINT_NAMES.index(name)
    return lambda joints: joints[..., i, :]


# Pose2Sim's HALPE_26 markers (Pose2Sim/skeletons.py) that our skeleton has, in HALPE_26's tree
# order. Hip (HALPE's mid-hip) and Neck (the base of the neck, between the shoulders) are the
# midpoints of our two hip and two shoulder joints; Head is HALPE's head top. Nose, the toes and
# heels we do not fit, so they are left out rather than made up.
HALPE26_MARKERS = {
    "Hip": _midpoint("l_hip", "r_hip"),
    "RHip": _joint("r_hip"), "RKnee": _joint("r_knee"), "RAnkle": _joint("r_ankle"),
    "LHip": _joint("l_hip"), "LKnee": _joint("l_knee"), "LAnkle": _joint("l_ankle"),
    "Neck": _midpoint("l_shoulder", "r_shoulder"), "Head": _joint("head_top"),
    "RShoulder": _joint("r_shoulder"), "RElbow": _joint("r_elbow"), "RWrist": _joint("r_wrist"),
    "LShoulder": _joint("l_shoulder"), "LElbow": _joint("l_elbow"), "LWrist": _joint("l_wrist"),
}
# OpenPose BODY_25 order, as EasyMocap's CONFIG['body25'] lists it
BODY25_NAMES = (
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip",
    "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
    "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
)
BODY25_FROM_HALPE = {"MidHip": "Hip"}  # the same point under OpenPose's name; others share names
KEYPOINTS3D_FORMAT = "%06d.json"       # EasyMocap names each frame's file by its frame number
KEYPOINTS3D_PERSON = 0                 # EasyMocap's person id of our one actor


def halpe26_markers(joints: np.ndarray) -> tuple[tuple[str, ...], np.ndarray]:
    """(F, 17, 3) joints -> the HALPE_26 marker names we have and (F, M, 3) their positions."""
    return tuple(HALPE26_MARKERS), np.stack([f(joints) for f in HALPE26_MARKERS.values()], axis=-2)


def body25_keypoints(joints: np.ndarray) -> np.ndarray:
    """(F, 17, 3) joints -> (F, 25, 4) BODY_25 keypoints (x, y, z, confidence): confidence 1
    where our skeleton has the point, 0 (and the point at the origin) where it has not."""
    out = np.zeros(joints.shape[:-2] + (len(BODY25_NAMES), 4))
    for k, name in enumerate(BODY25_NAMES):
        halpe = BODY25_FROM_HALPE.get(name, name)
        if halpe in HALPE26_MARKERS:
            out[..., k, :3] = HALPE26_MARKERS[halpe](joints)
            out[..., k, 3] = 1.0
    return out


def opensim_points(motion: FittedMotion) -> np.ndarray:
    """(F, 17, 3) the joints in OpenSim's axes (Y up, X forward), metres, from the fit frame."""
    return motion.fit_joints @ TO_OPENSIM.T


def write_trc(path, motion: FittedMotion, title: str | None = None) -> None:
    """OpenSim TRC marker file (Pose2Sim's layout): HALPE_26 markers, metres, Y up. title: the
    file name the header gives (default: ``path``'s)."""
    names, pts = halpe26_markers(opensim_points(motion))
    F, M, _ = pts.shape
    rate, camera = f"{motion.rate:.10g}", f"{motion.fps:.10g}"  # the data's rate, the recording's
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{title or Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{camera}\t{F}\t{M}\tm\t{rate}\t1\t{F}",
        "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(M)),
        "",
    ]
    for i in range(F):
        vals = "\t".join(f"{v:.6f}" for v in pts[i].reshape(-1))
        lines.append(f"{i + 1}\t{motion.times[i]:.6f}\t{vals}")
    Path(path).write_text("\n".join(lines) + "\n")


# .mot columns: the pelvis position in OpenSim's axes (metres; OpenSim's pelvis_t* names), then
# our 32 angle parameters in degrees (rotation-vector components are axis x angle)
MOT_COLUMNS = ("pelvis_tx", "pelvis_ty", "pelvis_tz") + PARAM_NAMES[3:]


def mot_table(motion: FittedMotion) -> np.ndarray:
    """(F, 1 + 35) time (s), the pelvis in OpenSim's axes (m), the angle parameters (degrees)."""
    p = motion.params
    pelvis = p[:, 0:3] @ TO_OPENSIM.T
    return np.concatenate([motion.times[:, None], pelvis, np.degrees(p[:, 3:])], axis=1)


def write_mot(path, motion: FittedMotion, title: str | None = None) -> None:
    """OpenSim motion file (.mot, the STO text layout): our joint angles in degrees. title: the
    table's name in the header (default: ``path``'s stem)."""
    table = mot_table(motion)
    header = [
        title or Path(path).stem,
        "version=1",
        f"nRows={len(table)}",
        f"nColumns={table.shape[1]}",
        "inDegrees=yes",
        "",
        "Units are S.I. units (second, meters, Newtons, ...)",
        "Angles are in degrees: root_heading and the hinges, and rotation vectors (axis x angle) in the",
        "z-up body frame of silhouette-mocap (docs/exports.md); pelvis_t* are metres in OpenSim's axes.",
        "",
        "endheader",
        "\t".join(("time",) + MOT_COLUMNS),
    ]
    rows = ["\t".join(f"{v:.8g}" for v in row) for row in table]
    Path(path).write_text("\n".join(header + rows) + "\n")


def write_keypoints3d(folder, motion: FittedMotion) -> None:
    """EasyMocap keypoints3d: ``folder/<frame:06d>.json`` per frame, each
    ``[{"id": 0, "keypoints3d": [[x, y, z, confidence] x 25]}]`` in body25 order, metres, the
    user's world (the calibration's)."""
    folder = Path(folder)
    folder.mkdir(exist_ok=True)
    kp = body25_keypoints(motion.joints)
    for f, points in zip(motion.frames, kp):
        # laid out as EasyMocap's own writer does: one keypoint per line
        rows = ",\n".join("      [" + ", ".join(f"{v:.6f}" for v in p) + "]" for p in points)
        text = f'[\n  {{\n    "id": {KEYPOINTS3D_PERSON},\n    "keypoints3d": [\n{rows}\n    ]\n  }}\n]\n'
        (folder / (KEYPOINTS3D_FORMAT % int(f))).write_text(text)


def write_csv(path, motion: FittedMotion) -> None:
    """One row per frame: frame, time, joint positions (metres, the user's world), the 35 parameters."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "time_s"] + [f"{n}_{a}_m" for n in JOINT_NAMES for a in "xyz"] + list(PARAM_NAMES))
        for i, f in enumerate(motion.frames):
            w.writerow([int(f), f"{motion.times[i]:.6f}"] + [repr(float(v)) for v in motion.joints[i].reshape(-1)]
                       + [repr(float(v)) for v in motion.params[i]])


def write_jsonl(path, motion: FittedMotion) -> None:
    """One JSON object per line: frame, time, params (35, the fit frame's), joints {name: [x, y, z]}
    (metres, the user's world)."""
    with open(path, "w") as fh:
        for i, f in enumerate(motion.frames):
            fh.write(json.dumps({"frame": int(f), "time": float(motion.times[i]),
                                 "params": [float(v) for v in motion.params[i]],
                                 "joints": joints_dict(motion.joints[i])}) + "\n")


def write_c3d(path, motion: FittedMotion) -> None:
    """C3D point data of joint positions: millimetres, the user's world axes, float storage,
    POINT:RATE the fitted frames' rate."""
    import c3d

    writer = c3d.Writer(point_rate=float(motion.rate), analog_rate=0.0, point_scale=-1.0, point_units="mm  ")
    writer.set_point_labels([n[:C3D_LABEL_LENGTH].ljust(C3D_LABEL_LENGTH) for n in JOINT_NAMES])
    up = motion.up.upper()  # viewers: the world's up axis up on screen, x (or y) to the right
    writer.set_screen_axis(X="+Y" if up[1] == "X" else "+X", Y=up)
    no_analog = np.zeros((0, 0), dtype=np.float32)
    for frame in motion.joints * MM_PER_M:
        points = np.zeros((len(JOINT_NAMES), 5), dtype=np.float32)
        points[:, :3] = frame  # column 3: residual 0 = valid; column 4: camera mask
        writer.add_frames([(points, no_analog)])
    with open(path, "wb") as fh, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data", UserWarning)  # we write none, on purpose
        writer.write(fh)


WRITERS = {"glb": write_glb_export, "mot": write_mot, "trc": write_trc, "keypoints3d": write_keypoints3d,
           "bvh": write_bvh_export, "c3d": write_c3d, "json": write_jsonl, "csv": write_csv}


def export_motion(fmt: str, path, motion: FittedMotion, bvh_rest: str = DEFAULT_BVH_REST,
                  final_path=None) -> Path:
    """Write ``motion`` as ``fmt`` (one of FORMATS) to ``path`` (a folder for FOLDER_FORMATS).

    bvh_rest: the BVH's rest pose (``BVH_RESTS``); final_path: the name the file will have when
    ``path`` is a temporary one (TRC and MOT headers name it). Returns ``path``.
    """
    if fmt not in WRITERS:
        raise UserError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    path = Path(path)
    final = Path(final_path or path)
    options = {"bvh": {"rest": bvh_rest}, "trc": {"title": final.name}, "mot": {"title": final.stem}}
    WRITERS[fmt](path, motion, **options.get(fmt, {}))
    return path
