"""Captured motion (BVH) -> our 35 parameters per frame, scaled to our actor.

The source skeleton's axes and facing come from its rest pose (hips give the left side, the
spine gives up), so y-up and z-up files, T- and A-poses import alike. Positions are scaled by
the ratio of our leg length to the source's, which keeps the feet on the floor for actors of
any size and makes the file's length unit irrelevant.
"""
from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from common.body import P, BodyModel, forward_kinematics, rot_z
from common.bvh import (
    BvhMotion, bvh_global_transforms, end_site_positions, read_bvh, recorded_rate, rest_positions,
)
from common.errors import UserError
from common.retarget import retarget
from common.skeleton_map import guess_up_axis, load_joint_map, map_skeleton, up_axis_rotation

REQUIRED_ROLES = (
    "pelvis", "spine_upper", "neck", "head",
    "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
    "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle",
)


@dataclass(frozen=True)
class ImportedMotion:
    """params: (F, 35) per source frame; frame_time: seconds between source frames."""

    params: np.ndarray
    frame_time: float
    source: str
    frames: np.ndarray  # (F,) source frame indices

    @property
    def fps(self) -> float:
        """The source's frame rate, as recorded (the file's Frame Time is rounded: ``recorded_rate``)."""
        return recorded_rate(self.frame_time)


def _roles(motion: BvhMotion, joint_map_path=None) -> dict:
    """Role -> point index: joint j < J, or J + e for End Site e (see common.skeleton_map)."""
    override = load_joint_map(joint_map_path) if joint_map_path else None
    mapping = map_skeleton(motion, override)
    missing = [r for r in REQUIRED_ROLES if r not in mapping]
    if missing:
        raise UserError(f"{motion.source}: cannot map joints for roles {missing}; pass --joint-map FILE.toml")
    return mapping


def _joint_of(motion: BvhMotion, point: int) -> int:
    """The joint whose rotation a point follows (an End Site follows its parent joint)."""
    J = motion.num_joints
    return point if point < J else int(motion.end_site_parents[point - J])


def source_axes(motion: BvhMotion, roles: dict) -> np.ndarray:
    """(3, 3) rotation taking the file's axes to ours: the file's up axis to +z (its floor stays
    level), then turned about z so that the rest pose's left hip lies towards +x."""
    up = up_axis_rotation(guess_up_axis(motion, roles))
    rest = np.concatenate(rest_positions(motion))
    left = up @ (rest[roles["l_hip"]] - rest[roles["r_hip"]])
    return rot_z(-np.arctan2(left[1], left[0])) @ up


def leg_length(points: dict) -> float:
    return float(np.linalg.norm(points["l_knee"] - points["l_hip"]) + np.linalg.norm(points["l_ankle"] - points["l_knee"]))


def import_bvh(model: BodyModel, path, frames=None, joint_map_path=None) -> ImportedMotion:
    """Read a BVH file and retarget the chosen source frames (default: all) onto ``model``."""
    motion = read_bvh(path)
    roles = _roles(motion, joint_map_path)
    idx = np.arange(motion.num_frames) if frames is None else np.asarray(frames, dtype=np.int64)
    if idx.size == 0 or idx.min() < 0 or idx.max() >= motion.num_frames:
        raise UserError(f"{path}: frames {idx.min() if idx.size else '-'}..{idx.max() if idx.size else '-'} "
                        f"outside the clip's 0..{motion.num_frames - 1}")
    A = source_axes(motion, roles)
    rest = np.concatenate(rest_positions(motion))
    src_rest = {r: rest[j] for r, j in roles.items()}
    ours = {"l_hip": model.joint_rest[10], "l_knee": model.joint_rest[11], "l_ankle": model.joint_rest[12]}
    scale = leg_length(ours) / leg_length(src_rest)
    pos_joints, rot_all = bvh_global_transforms(motion, idx)
    pos_all = np.concatenate([pos_joints, end_site_positions(motion, transforms=(pos_joints, rot_all))], axis=1)
    pos = {r: scale * pos_all[:, j] @ A.T for r, j in roles.items()}
    rot = {r: A @ rot_all[:, _joint_of(motion, j)] @ A.T for r, j in roles.items()}
    if "head_end" not in pos:
        pos["head_end"] = pos["head"]
    params = retarget(model, pos, rot)
    # the floor: the lowest ankle over the clip sits at our rest ankle height
    ankles = forward_kinematics(model, params).joints[:, [12, 15], 2]
    params[:, P["root_z"]] += model.joint_rest[12, 2] - ankles.min()
    return ImportedMotion(params, motion.frame_time, str(path), idx)
