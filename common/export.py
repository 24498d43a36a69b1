"""Fitted motion out: BVH (Blender, MotionBuilder), C3D and TRC of joint positions, JSON lines, CSV.

Axis conventions of the files we write: BVH is Y-up, the actor facing +Z at rest, centimetres
(what Blender's importer and most tools expect; Blender turns it Z-up on import). C3D and TRC
keep our world: Z-up, millimetres, the same as most lab systems and OpenSim's defaults.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from common.body import (
    HEAD_TOP_SEGMENT, JOINT_NAMES, SEGMENT_PARENTS, BodyModel, forward_kinematics,
    local_rotations,
)
from common.bvh import BvhMotion, write_bvh

BVH_UNITS_PER_M = 100.0  # centimetres
# our world (z up, facing -y) -> BVH world (y up, facing +z)
TO_BVH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
ROT_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")
BVH_JOINT_NAMES = (
    "Hips", "Spine", "Chest", "Head",
    "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
    "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot",
)
EXTREMITY_END_SCALE = 2.0  # End Sites of hands and feet: twice the ellipsoid centre's offset


def params_to_bvh(model: BodyModel, params: np.ndarray, frame_time: float) -> BvhMotion:
    """(F, 35) fitted parameters -> a BvhMotion in BVH conventions (Y up, cm)."""
    p = np.atleast_2d(params)
    F = len(p)
    local = local_rotations(model, p)
    C = TO_BVH
    offsets = (model.offsets @ C.T) * BVH_UNITS_PER_M
    offsets[0] = 0.0
    cols = []
    root_pos = (p[:, 0:3] @ C.T) * BVH_UNITS_PER_M
    for s in range(16):
        R = C @ local[:, s] @ C.T
        euler = Rotation.from_matrix(R).as_euler("ZXY", degrees=True)  # intrinsic: Rz Rx Ry
        if s == 0:
            cols.append(root_pos)
        cols.append(euler)
    values = np.concatenate(cols, axis=1)
    channels = [("Xposition", "Yposition", "Zposition") + ROT_CHANNELS] + [ROT_CHANNELS] * 15
    end_parents, end_offsets = [], []
    children = {p_ for p_ in SEGMENT_PARENTS if p_ >= 0}
    for s in range(16):
        if s in children:
            continue
        if s == HEAD_TOP_SEGMENT:
            off = model.head_top_offset
        else:
            off = model.ellipsoid_centres[s] * EXTREMITY_END_SCALE
        end_parents.append(s)
        end_offsets.append(C @ off * BVH_UNITS_PER_M)
    return BvhMotion(BVH_JOINT_NAMES, np.array(SEGMENT_PARENTS), offsets, channels,
                     np.array(end_parents), np.array(end_offsets), frame_time, values, "silhouette-mocap")


def bvh_joint_positions_to_world(positions: np.ndarray) -> np.ndarray:
    """(..., 3) positions read from our BVH (Y up, cm) -> our world (Z up, metres)."""
    return (positions @ TO_BVH) / BVH_UNITS_PER_M


def write_motion_bvh(path, model: BodyModel, params: np.ndarray, fps: float) -> None:
    write_bvh(path, params_to_bvh(model, params, 1.0 / fps))


def joint_positions(model: BodyModel, params: np.ndarray) -> np.ndarray:
    """(F, 35) -> (F, 17, 3) world joint positions, metres."""
    return forward_kinematics(model, np.atleast_2d(params)).joints


def write_trc(path, joints: np.ndarray, fps: float, frames: list[int]) -> None:
    """OpenSim TRC marker file of joint positions in millimetres, Z up."""
    F, J, _ = joints.shape
    names = JOINT_NAMES
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{fps:g}\t{fps:g}\t{F}\t{J}\tmm\t{fps:g}\t1\t{F}",
        "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(J)),
        "",
    ]
    for i in range(F):
        vals = "\t".join(f"{v:.4f}" for v in (joints[i] * 1000.0).reshape(-1))
        lines.append(f"{i + 1}\t{i / fps:.6f}\t{vals}")
    Path(path).write_text("\n".join(lines) + "\n")


def write_csv(path, joints: np.ndarray, params: np.ndarray, frames: list[int], fps: float) -> None:
    from common.body import PARAM_NAMES

    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "time_s"] + [f"{n}_{a}_m" for n in JOINT_NAMES for a in "xyz"] + list(PARAM_NAMES))
        for i, f in enumerate(frames):
            w.writerow([f, f"{i / fps:.6f}"] + [f"{v:.6f}" for v in joints[i].reshape(-1)]
                       + [f"{v:.6f}" for v in params[i]])


def write_jsonl(path, joints: np.ndarray, params: np.ndarray, frames: list[int], fps: float) -> None:
    from common.body import joints_dict

    with open(path, "w") as fh:
        for i, f in enumerate(frames):
            fh.write(json.dumps({"frame": int(f), "time": i / fps, "params": [float(v) for v in params[i]],
                                 "joints": joints_dict(joints[i])}) + "\n")


def write_c3d(path, joints: np.ndarray, fps: float) -> None:
    """C3D point data of joint positions (millimetres, Z up) via the ``c3d`` package."""
    import c3d

    writer = c3d.Writer(point_rate=float(fps), point_units="mm")
    writer.set_point_labels([n.ljust(16)[:16] for n in JOINT_NAMES])
    for frame in joints * 1000.0:
        points = np.zeros((len(JOINT_NAMES), 5), dtype=np.float32)
        points[:, :3] = frame
        writer.add_frames([(points, np.zeros((0,), dtype=np.float32))])
    with open(path, "wb") as fh:
        writer.write(fh)

