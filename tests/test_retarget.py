"""Motion import: every real CMU clip retargets onto our 35 parameters, inside the joint limits,
with the source's bone directions."""
from __future__ import annotations

import numpy as np
import pytest

from common.body import (
    JOINT_NAMES, P, PARAM_COUNT, clip_to_limits, forward_kinematics, rest_params,
)
from common.bvh import read_bvh
from common.errors import UserError
from common.motion_import import import_bvh
from common.retarget import retarget
from common.skeleton_map import role_trajectories

from conftest import BUNDLED_CLIPS, SHARED_CLIPS, SHARED_MOCAP, WALK_CLIP

J = {name: i for i, name in enumerate(JOINT_NAMES)}
BONES = tuple((f"{s}_{a}", f"{s}_{b}") for s in "lr"
              for a, b in (("shoulder", "elbow"), ("elbow", "wrist"), ("hip", "knee"), ("knee", "ankle")))
FRAME_STRIDE = 3          # every 3rd source frame (120 fps clips): fast, still ~100-900 frames per clip
# Measured over the 17 shared clips + 3 bundled ones (every 3rd frame): mean angle per clip
# 0.46-0.72 deg, 2.17 deg for 05_06 (a dance whose leg raises reach the hip limits); the forearm
# and shin carry ~2 deg from our rest forearm/shin lying 2 deg off their hinge plane.
MEAN_ANGLE_DEG = 3.0
MEDIAN_ANGLE_DEG = 1.0
BONE_MEAN_ANGLE_DEG = 6.0  # worst bone of the worst clip: 4.05 (05_06, right shin)

ALL_CLIPS = [pytest.param(p, id=f"shared/{p.parent.name}/{p.name}") for p in SHARED_CLIPS] + \
            [pytest.param(p, id=f"bundled/{p.name}") for p in BUNDLED_CLIPS]


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors -> (3, 3) rotation R minimising |R src - dst|."""
    U, _, Vt = np.linalg.svd(src.T @ dst)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def bone_directions(model, clip, idx):
    """Source (role_trajectories, z up) and our (FK of the import) bone directions, (F, 8, 3) each."""
    motion = read_bvh(clip)
    params = import_bvh(model, clip, idx).params
    roles = role_trajectories(motion, frames=idx)
    joints = forward_kinematics(model, params).joints
    src = np.stack([unit(roles[b] - roles[a]) for a, b in BONES], axis=1)
    ours = np.stack([unit(joints[:, J[b]] - joints[:, J[a]]) for a, b in BONES], axis=1)
    return src, ours, params


def test_shared_clips_are_there():
    if not SHARED_MOCAP.is_dir():
        pytest.skip(f"{SHARED_MOCAP} absent")
    assert len(SHARED_CLIPS) >= 10
    assert len(BUNDLED_CLIPS) >= 1


@pytest.mark.parametrize("clip", ALL_CLIPS)
def test_clip_imports_inside_limits(model, clip):
    motion = read_bvh(clip)
    imported = import_bvh(model, clip)  # every frame
    p = imported.params
    assert p.shape == (motion.num_frames, PARAM_COUNT)
    assert np.isfinite(p).all()
    np.testing.assert_array_equal(clip_to_limits(p), p)
    assert imported.frame_time > 0
    # the floor: the lowest ankle over the clip is at our rest ankle height; the actor is upright
    joints = forward_kinematics(model, p).joints
    assert abs(joints[:, [J["l_ankle"], J["r_ankle"]], 2].min() - model.joint_rest[J["l_ankle"], 2]) < 1e-9
    head_above_pelvis = joints[:, J["head_top"], 2] - joints[:, J["pelvis"], 2]
    assert np.median(head_above_pelvis) > 0.6


@pytest.mark.parametrize("clip", ALL_CLIPS)
def test_bone_directions_match_the_source(model, clip):
    """Upper arm, forearm, thigh and shin point where the source's do, after one rotation for the
    whole clip (the axis change between the file's world and ours)."""
    idx = np.arange(1, read_bvh(clip).num_frames, FRAME_STRIDE)
    src, ours, _ = bone_directions(model, clip, idx)
    R = kabsch(src.reshape(-1, 3), ours.reshape(-1, 3))
    angles = np.degrees(np.arccos(np.clip(np.sum((src @ R.T) * ours, axis=-1), -1.0, 1.0)))  # (F, 8)
    assert angles.mean() < MEAN_ANGLE_DEG, angles.mean(axis=0)
    assert np.median(angles) < MEDIAN_ANGLE_DEG
    assert angles.mean(axis=0).max() < BONE_MEAN_ANGLE_DEG, dict(zip(BONES, angles.mean(axis=0).round(2)))


def test_bone_direction_check_detects_a_wrong_limb(model):
    """The comparison above is not vacuous: swapping left and right arms breaks it."""
    idx = np.arange(1, read_bvh(WALK_CLIP).num_frames, 8)
    src, ours, _ = bone_directions(model, WALK_CLIP, idx)
    swapped = ours[:, [4, 5, 6, 7, 0, 1, 2, 3]]
    R = kabsch(src.reshape(-1, 3), swapped.reshape(-1, 3))
    angles = np.degrees(np.arccos(np.clip(np.sum((src @ R.T) * swapped, axis=-1), -1.0, 1.0)))
    assert angles.mean() > MEAN_ANGLE_DEG


def test_frame_subset_equals_rows_of_full_import(model):
    full = import_bvh(model, WALK_CLIP).params
    idx = np.array([1, 40, 80, 200])
    part = import_bvh(model, WALK_CLIP, idx).params
    others = [i for i in range(PARAM_COUNT) if i != P["root_z"]]
    np.testing.assert_allclose(part[:, others], full[idx][:, others], atol=1e-9)
    # the floor is set per import (lowest ankle of the chosen frames): a constant height shift
    dz = part[:, P["root_z"]] - full[idx, P["root_z"]]
    np.testing.assert_allclose(dz, dz[0], atol=1e-9)


def test_frames_outside_the_clip_are_a_user_error(model):
    n = read_bvh(WALK_CLIP).num_frames
    with pytest.raises(UserError, match=str(n - 1)):
        import_bvh(model, WALK_CLIP, [0, n])


def test_unmappable_skeleton_is_a_user_error(model, tmp_path):
    bvh = tmp_path / "two_bones.bvh"
    bvh.write_text("HIERARCHY\nROOT A\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition Yposition Zposition "
                   "Zrotation Xrotation Yrotation\n  JOINT B\n  {\n    OFFSET 0 1 0\n    CHANNELS 3 "
                   "Zrotation Xrotation Yrotation\n    End Site\n    {\n      OFFSET 0 1 0\n    }\n  }\n}\n"
                   "MOTION\nFrames: 1\nFrame Time: 0.01\n0 0 0 0 0 0 0 0 0\n")
    with pytest.raises(UserError, match="two_bones.bvh"):
        import_bvh(model, bvh)


# ------------------------------------------------------------- regressions (fixed in 63a54ec)

def _own_rest_roles(model):
    """Role positions/rotations of our own model in its rest pose, as retarget() takes them."""
    pose = forward_kinematics(model, rest_params(model))
    pos = {n: pose.joints[:, i] for i, n in enumerate(JOINT_NAMES)}
    pos["head"] = pose.joints[:, J["neck"]]
    roles = ["pelvis", "spine_upper", "head"] + [f"{s}_{j}" for s in "lr"
                                                 for j in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")]
    rot = {r: np.eye(3)[None] for r in roles}
    return pos, rot


def test_retargeting_our_own_rest_pose_keeps_the_spine_straight(model):
    """Regression: the chest's rest frame took 'up' from neck - spine, the live frame from
    neck - hip midpoint, so an upright source got spine_x = -0.042 rad (head top 21 mm off)."""
    pos, rot = _own_rest_roles(model)
    q = retarget(model, pos, rot)[0]
    np.testing.assert_allclose(q[P["spine_x"]:P["spine_z"] + 1], 0.0, atol=1e-3)
    joints = forward_kinematics(model, q).joints[0]
    for name in ("neck", "head_top"):
        assert np.linalg.norm(joints[J[name]] - model.joint_rest[J[name]]) < 1e-3, name


TRAVELLING_CLIPS = [p for p in BUNDLED_CLIPS if p.stem in ("cmu_12_01_walk", "06_08")]


@pytest.mark.parametrize("clip", TRAVELLING_CLIPS, ids=lambda p: p.name)
def test_imported_floor_stays_level(model, clip):
    """The lowest ankle per frame follows the source's (scaled to our legs) within 3 cm.

    Measured: peak-to-peak 1.1-1.5 cm (the source's own steps). Regression: source_axes() took the
    vertical from the rest pose's neck - pelvis, tilting the world 2-4 deg; walks went downhill
    (17-26 cm over 3-4 m)."""
    motion = read_bvh(clip)
    idx = np.arange(1, motion.num_frames, 4)
    joints = forward_kinematics(model, import_bvh(model, clip, idx).params).joints
    roles = role_trajectories(motion, frames=idx)
    src_leg = (np.linalg.norm(roles["l_knee"] - roles["l_hip"], axis=1).mean()
               + np.linalg.norm(roles["l_ankle"] - roles["l_knee"], axis=1).mean())
    our_leg = (np.linalg.norm(model.joint_rest[J["l_knee"]] - model.joint_rest[J["l_hip"]])
               + np.linalg.norm(model.joint_rest[J["l_ankle"]] - model.joint_rest[J["l_knee"]]))
    ours = joints[:, [J["l_ankle"], J["r_ankle"]], 2].min(axis=1)
    src = np.minimum(roles["l_ankle"][:, 2], roles["r_ankle"][:, 2]) * our_leg / src_leg
    assert np.ptp(ours - src) < 0.03


@pytest.mark.parametrize("clip", BUNDLED_CLIPS, ids=lambda p: p.name)
def test_import_keeps_the_source_vertical(model, clip):
    """The rotation between the file's z-up world and ours is about z only (was 2.3-4.5 deg off)."""
    idx = np.arange(1, read_bvh(clip).num_frames, 6)
    src, ours, _ = bone_directions(model, clip, idx)
    R = kabsch(src.reshape(-1, 3), ours.reshape(-1, 3))
    assert np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))) < 1.0


def test_nearest_turn_moves_an_angle_by_whole_turns_to_within_pi_of_the_reference():
    from common.retarget import nearest_turn

    angles = np.array([0.3, 0.3 + 4.0 * np.pi, -2.0 * np.pi + 0.1, 3.0])
    reference = np.array([0.2, 0.0, 2.0 * np.pi, -3.0])
    moved = nearest_turn(angles, reference)
    assert np.all(np.abs(moved - reference) <= np.pi)
    turns = (moved - angles) / (2.0 * np.pi)
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-12)
    np.testing.assert_allclose(moved, [0.3, 0.3, 2.0 * np.pi + 0.1, 3.0 - 2.0 * np.pi], atol=1e-12)
