"""Retargeting captured motion onto our 35 parameters.

Input per frame: world positions of canonical joint roles (pelvis, spine_upper, neck, head,
head_end, {l,r}_shoulder/elbow/wrist/hip/knee/ankle/toe ...) in our world (metres, z up,
the source's rest pose facing -y), and each role's world rotation relative to the source's
own rest pose. Rest poses differ between skeletons (T-pose, A-pose, bent elbows), so bone
*directions* come from positions (swing) and only what positions cannot tell, the twist of a
straight limb and the small joints (head, wrists, ankles), comes from rotation deltas.
"""
from __future__ import annotations

import numpy as np

from common.body import (
    FORWARD, P, PARAM_COUNT, BodyModel, clip_to_limits, joint_frames, matrix_to_rotvec, rot_z,
    rotvec_to_matrix,
)

STRAIGHT_LIMB_RAD = np.radians(25.0)  # below this bend the bend plane is unreliable for twist
EPS = 1e-9


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), EPS)


def frame_from(lateral: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(..., 3) lateral (towards +x at rest) and up -> (..., 3, 3) orthonormal frame [x, y, z]."""
    x = _unit(lateral)
    z = _unit(up - np.sum(up * x, -1, keepdims=True) * x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def frame_from_two(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """(..., 3, 3) frame whose first column is ``primary`` and second lies towards ``secondary``."""
    a = _unit(primary)
    b = _unit(secondary - np.sum(secondary * a, -1, keepdims=True) * a)
    return np.stack([a, b, np.cross(a, b)], axis=-1)


def nearest_turn(angle, reference):
    """``angle`` (rad, any shape) moved by whole turns to within pi of ``reference`` (the same
    shape or broadcast): the same rotation, numbered as the reference's neighbour."""
    return angle + 2.0 * np.pi * np.round((reference - angle) / (2.0 * np.pi))


def heading_tilt(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3, 3) root rotations -> heading (F,) unwrapped, tilt (F, 2) with R = Rz(h) exp(tilt)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()  # x y z w
    heading = np.unwrap(2.0 * np.arctan2(q[:, 2], q[:, 3]))
    swing = np.einsum("fji,fjk->fik", rot_z(heading), R)
    tilt = matrix_to_rotvec(swing)[:, :2]
    return heading, tilt


def _limb(model_axis, rest_upper, upper, lower, delta_upper):
    """Orientation of a limb's proximal bone from its direction and its bend plane.

    model_axis (3,): the hinge axis in the rest pose; rest_upper (3,): rest proximal direction;
    upper, lower (F, 3): target bone directions; delta_upper (F, 3, 3): source rotation of the
    proximal bone relative to its rest (used for the twist of a straight limb).
    Returns world rotation (F, 3, 3) of the proximal bone and the hinge flexion (F,).
    """
    bend = np.cross(upper, lower)
    bend_norm = np.linalg.norm(bend, axis=-1)
    hint = delta_upper @ model_axis
    hint = hint - np.sum(hint * upper, -1, keepdims=True) * upper
    axis_from_bend = bend / np.maximum(bend_norm, EPS)[:, None]
    # a bent limb defines its own axis; blend towards the rotation hint as it straightens
    w = np.clip(np.arcsin(np.clip(bend_norm, 0, 1)) / STRAIGHT_LIMB_RAD, 0.0, 1.0)[:, None]
    flip = np.sum(axis_from_bend * hint, -1, keepdims=True) < 0
    axis_from_bend = np.where(flip & (w < 1.0), -axis_from_bend, axis_from_bend)
    axis = _unit(w * axis_from_bend + (1.0 - w) * _unit(hint))
    target = frame_from_two(upper, axis)
    rest = frame_from_two(rest_upper[None], model_axis[None])
    R = target @ np.swapaxes(rest, -1, -2)
    cos = np.sum(upper * lower, -1)
    sin = np.sum(np.cross(upper, lower) * axis, -1)
    return R, np.arctan2(sin, cos)


def retarget(model: BodyModel, pos: dict, rot: dict) -> np.ndarray:
    """Role positions (F, 3) and rest-relative world rotations (F, 3, 3) -> params (F, 35).

    Required roles in ``pos``: pelvis, neck, head, l_/r_ shoulder, elbow, wrist, hip, knee,
    ankle. In ``rot``: pelvis, spine_upper, head, l_/r_ shoulder, elbow, wrist, hip, knee, ankle.
    Parameters are clipped into the joint limits.
    """
    J = {n: model.joint_rest[i] for i, n in enumerate(
        ("pelvis", "spine", "chest", "neck", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow",
         "r_wrist", "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle", "head_top"))}
    F = len(pos["pelvis"])
    out = np.zeros((F, PARAM_COUNT))
    frames = joint_frames(model)

    # root: hips give the lateral axis, pelvis->neck the up axis
    pelvis_rest = frame_from(J["l_hip"] - J["r_hip"], J["neck"] - J["pelvis"])
    pelvis_now = frame_from(pos["l_hip"] - pos["r_hip"], pos["neck"] - pos["pelvis"])
    R_root = pelvis_now @ pelvis_rest.T
    heading, tilt = heading_tilt(R_root)
    hip_mid_rest = 0.5 * (J["l_hip"] + J["r_hip"]) - J["pelvis"]
    hip_mid_now = 0.5 * (pos["l_hip"] + pos["r_hip"])
    out[:, 0:3] = hip_mid_now - R_root @ hip_mid_rest
    out[:, 3] = heading
    out[:, 4:6] = tilt

    # spine: shoulders give the chest's lateral axis, hips-centre -> neck its up axis
    chest_rest = frame_from(J["l_shoulder"] - J["r_shoulder"], J["neck"] - 0.5 * (J["l_hip"] + J["r_hip"]))
    chest_now = frame_from(pos["l_shoulder"] - pos["r_shoulder"], pos["neck"] - hip_mid_now)
    R_chest = chest_now @ chest_rest.T
    out[:, 6:9] = matrix_to_rotvec(np.swapaxes(R_root, -1, -2) @ R_chest)
    R_chest = R_root @ rotvec_to_matrix(out[:, 6:9])  # the chest our model will actually have

    # head: rotation delta relative to the chest
    head_local = np.swapaxes(rot["spine_upper"], -1, -2) @ rot["head"]
    rv = matrix_to_rotvec(head_local)
    out[:, P["neck_nod"]] = rv[:, 0]
    out[:, P["neck_turn"]] = rv[:, 2]

    for side, base, s, e, w in (("l", 11, "l_shoulder", "l_elbow", "l_wrist"),
                                ("r", 17, "r_shoulder", "r_elbow", "r_wrist")):
        f = frames[side]
        rest_up = _unit(J[e] - J[s])
        R_up, flex = _limb(f["elbow_axis"], rest_up, _unit(pos[e] - pos[s]), _unit(pos[w] - pos[e]), rot[s])
        out[:, base:base + 3] = matrix_to_rotvec(np.swapaxes(R_chest, -1, -2) @ R_up)
        out[:, base + 3] = flex
        hand_local = matrix_to_rotvec(np.swapaxes(rot[e], -1, -2) @ rot[w])
        out[:, base + 4] = hand_local @ f["elbow_axis"]
        out[:, base + 5] = hand_local @ f["wrist_dev_axis"]

    R_pelvis = R_root
    for side, base, h, k, a in (("l", 23, "l_hip", "l_knee", "l_ankle"), ("r", 29, "r_hip", "r_knee", "r_ankle")):
        f = frames[side]
        rest_thigh = _unit(J[k] - J[h])
        R_thigh, flex = _limb(f["knee_axis"], rest_thigh, _unit(pos[k] - pos[h]), _unit(pos[a] - pos[k]), rot[h])
        out[:, base:base + 3] = matrix_to_rotvec(np.swapaxes(R_pelvis, -1, -2) @ R_thigh)
        out[:, base + 3] = flex
        foot_local = matrix_to_rotvec(np.swapaxes(rot[k], -1, -2) @ rot[a])
        out[:, base + 4] = foot_local @ np.array([1.0, 0.0, 0.0])
        out[:, base + 5] = foot_local @ FORWARD
    return clip_to_limits(out)
