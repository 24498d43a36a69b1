"""Body model: rest pose, forward kinematics geometry, joint limits, chains, limb holding."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.body import (
    CHAINS, FORWARD, JOINT_NAMES, LIMB_CHAINS, LIMB_PARTS, MIRROR_SIGNS, P, PARAM_COUNT, PARAM_LIMITS, PARAM_NAMES,
    SEGMENT_NAMES, SEGMENT_PARENTS, clip_to_limits, forward_kinematics, hold_limbs_in_world,
    joint_frames, rest_params, rigid_vertices, skinned_vertices, swap_sides,
)

J = {name: i for i, name in enumerate(JOINT_NAMES)}
S = {name: i for i, name in enumerate(SEGMENT_NAMES)}


def random_params(model, rng, n: int, spread: float = 0.5) -> np.ndarray:
    """(n, 35) poses: rest plus uniform noise on every angle, inside the joint limits."""
    base = rest_params(model)
    p = base + rng.uniform(-spread, spread, (n, PARAM_COUNT))
    p[:, 0:3] = base[0:3] + rng.uniform(-0.5, 0.5, (n, 3))
    p[:, 3] = rng.uniform(-np.pi, np.pi, n)
    return clip_to_limits(p)


def unit(v):
    return v / np.linalg.norm(v)


# ----------------------------------------------------------------------------- layout

def test_layout_sizes(model):
    assert len(PARAM_NAMES) == PARAM_COUNT == 35
    assert len(SEGMENT_NAMES) == len(SEGMENT_PARENTS) == 16
    assert len(JOINT_NAMES) == 17
    assert model.joint_rest.shape == (17, 3)
    assert PARAM_LIMITS.shape == (35, 2)
    assert np.all(PARAM_LIMITS[:, 0] < PARAM_LIMITS[:, 1])
    # parents come before children: forward kinematics can run in index order
    assert all(p < s for s, p in enumerate(SEGMENT_PARENTS))


# ------------------------------------------------------------------------- rest pose

def test_rest_params_reproduce_rest_joints(model):
    pose = forward_kinematics(model, rest_params(model))
    assert pose.joints.shape == (1, 17, 3)
    np.testing.assert_allclose(pose.joints[0], model.joint_rest, atol=1e-12)
    np.testing.assert_allclose(pose.rotations[0], np.broadcast_to(np.eye(3), (16, 3, 3)), atol=1e-12)


def test_rest_params_position_and_heading(model):
    pos, heading = np.array([0.3, -1.2, 0.95]), 1.1
    joints = forward_kinematics(model, rest_params(model, position=pos, heading=heading)).joints[0]
    expected = Rotation.from_euler("z", heading).apply(model.joint_rest - model.joint_rest[0]) + pos
    np.testing.assert_allclose(joints, expected, atol=1e-12)


def test_rest_surfaces_are_the_rest_mesh(model):
    pose = forward_kinematics(model, rest_params(model))
    np.testing.assert_allclose(rigid_vertices(model, pose), model.vertices, atol=1e-9)
    np.testing.assert_allclose(skinned_vertices(model, pose), model.vertices, atol=1e-6)


def test_skin_weights_sum_to_one(model):
    np.testing.assert_allclose(np.sum(model.skin_weights, axis=1, dtype=np.float64), 1.0, atol=1e-9)


def test_skinned_surface_moves_with_the_root(model):
    """Linear blend skinning with weights summing to 1 moves every vertex by the root's
    translation (regression: float16 weights summing to 1 +- 4e-4 put vertices 4 mm off at 10 m)."""
    p = rest_params(model)
    q = p.copy()
    q[0:3] += [10.0, 0.0, 0.0]
    a = skinned_vertices(model, forward_kinematics(model, p))
    b = skinned_vertices(model, forward_kinematics(model, q))
    np.testing.assert_allclose(b - a, np.broadcast_to([10.0, 0.0, 0.0], a.shape), atol=1e-4)


def test_scaled_model_scales_rest_joints(model):
    big = model.scaled(1.1)
    joints = forward_kinematics(big, rest_params(big)).joints[0]
    np.testing.assert_allclose(joints, 1.1 * model.joint_rest, atol=1e-12)


# ------------------------------------------------------------------------- geometry

@pytest.mark.parametrize("side", ["l", "r"])
def test_elbow_flexion_90_degrees_puts_wrist_in_front(model, side):
    """Geometry, independent of the FK code: with the upper arm at rest, a 90 deg flexion turns
    the forearm about the hinge axis (perpendicular to the upper arm and the actor's forward
    direction) until it is perpendicular to the upper arm, pointing forwards; its component
    along the hinge axis (the rest forearm's small out-of-plane part) and its length stay."""
    shoulder, elbow, wrist = (model.joint_rest[J[f"{side}_{n}"]] for n in ("shoulder", "elbow", "wrist"))
    upper = unit(elbow - shoulder)
    axis = unit(np.cross(upper, FORWARD))
    fore_rest = wrist - elbow
    length = np.linalg.norm(fore_rest)
    along_axis = fore_rest @ axis
    forward_in_plane = unit(FORWARD - (FORWARD @ upper) * upper)
    expected = elbow + along_axis * axis + np.sqrt(length ** 2 - along_axis ** 2) * forward_in_plane

    p = rest_params(model)
    p[P[f"{side}_elbow"]] = np.pi / 2
    joints = forward_kinematics(model, p).joints[0]
    np.testing.assert_allclose(joints[J[f"{side}_elbow"]], elbow, atol=1e-12)  # the elbow does not move
    np.testing.assert_allclose(joints[J[f"{side}_wrist"]], expected, atol=1e-9)
    fore = joints[J[f"{side}_wrist"]] - elbow
    assert abs(np.degrees(np.arccos(unit(fore) @ upper)) - 90.0) < 1e-6
    assert fore @ FORWARD > 0.9 * length  # the hand comes to the front, not behind the back


@pytest.mark.parametrize("side", ["l", "r"])
def test_knee_flexion_90_degrees_puts_ankle_behind(model, side):
    hip, knee, ankle = (model.joint_rest[J[f"{side}_{n}"]] for n in ("hip", "knee", "ankle"))
    thigh = unit(knee - hip)
    p = rest_params(model)
    p[P[f"{side}_knee"]] = np.pi / 2
    joints = forward_kinematics(model, p).joints[0]
    shin = joints[J[f"{side}_ankle"]] - joints[J[f"{side}_knee"]]
    np.testing.assert_allclose(np.linalg.norm(shin), np.linalg.norm(ankle - knee), rtol=1e-12)
    assert abs(np.degrees(np.arccos(unit(shin) @ thigh)) - 90.0) < 1e-6
    assert shin @ -FORWARD > 0.9 * np.linalg.norm(shin)  # heel to the back
    # straight knee: shin continues the thigh up to the hinge-axis component of the rest shin
    p[P[f"{side}_knee"]] = 0.0
    joints = forward_kinematics(model, p).joints[0]
    shin = unit(joints[J[f"{side}_ankle"]] - joints[J[f"{side}_knee"]])
    axis = joint_frames(model)[side]["knee_axis"]
    off_plane = unit(ankle - knee) @ axis
    np.testing.assert_allclose(shin @ thigh, np.sqrt(1 - off_plane ** 2), atol=1e-9)


def test_fk_preserves_bone_lengths_and_rotations_are_proper(model, rng):
    p = random_params(model, rng, 20)
    pose = forward_kinematics(model, p)
    R = pose.rotations
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-10)
    for s in range(1, 16):
        parent = SEGMENT_PARENTS[s]
        rest_len = np.linalg.norm(model.joint_rest[s] - model.joint_rest[parent])
        lengths = np.linalg.norm(pose.joints[:, s] - pose.joints[:, parent], axis=1)
        np.testing.assert_allclose(lengths, rest_len, rtol=1e-10)


def test_root_translation_moves_every_joint_rigidly(model, rng):
    p = random_params(model, rng, 1)[0]
    q = p.copy()
    q[0:3] += [0.4, -0.2, 0.1]
    np.testing.assert_allclose(forward_kinematics(model, q).joints - forward_kinematics(model, p).joints,
                               np.broadcast_to([0.4, -0.2, 0.1], (1, 17, 3)), atol=1e-12)


def test_heading_turns_about_vertical_through_pelvis(model, rng):
    p = random_params(model, rng, 1)[0]
    q = p.copy()
    q[P["root_heading"]] += 0.7
    a = forward_kinematics(model, p).joints[0]
    b = forward_kinematics(model, q).joints[0]
    np.testing.assert_allclose(b - p[0:3], Rotation.from_euler("z", 0.7).apply(a - p[0:3]), atol=1e-12)


def test_batch_fk_equals_per_row_fk(model, rng):
    p = random_params(model, rng, 9)
    batch = forward_kinematics(model, p)
    assert batch.joints.shape == (9, 17, 3)
    for i in range(len(p)):
        single = forward_kinematics(model, p[i])
        np.testing.assert_allclose(batch.joints[i], single.joints[0], atol=1e-12)
        np.testing.assert_allclose(batch.rotations[i], single.rotations[0], atol=1e-12)
        np.testing.assert_allclose(batch.origins[i], single.origins[0], atol=1e-12)


def test_compiled_fk_equals_the_kinematic_chain_written_with_scipy(model, rng):
    """The compiled forward kinematics against an independent composition: every segment's
    world rotation is its parent's times its local rotation, and its origin is the parent's
    origin plus the parent's rotation of the rest offset; a subset leaves the others NaN."""
    from common.body import local_rotations

    p = random_params(model, rng, 5, spread=1.0)
    pose = forward_kinematics(model, p)
    local = local_rotations(model, p)
    for b in range(len(p)):
        R = {0: Rotation.from_euler("z", p[b, 3]) * Rotation.from_rotvec([p[b, 4], p[b, 5], 0.0])}
        np.testing.assert_allclose(local[b, 0], R[0].as_matrix(), atol=1e-12)
        origin = {0: p[b, 0:3]}
        for s in range(1, 16):
            parent = SEGMENT_PARENTS[s]
            origin[s] = origin[parent] + R[parent].apply(np.array(model.offsets[s]))
            R[s] = R[parent] * Rotation.from_matrix(local[b, s])
            np.testing.assert_allclose(pose.rotations[b, s], R[s].as_matrix(), atol=1e-10)
            np.testing.assert_allclose(pose.origins[b, s], origin[s], atol=1e-10)
    left_arm = forward_kinematics(model, p, (S["l_forearm"],))
    computed = [S["pelvis"], S["abdomen"], S["chest"], S["l_upperarm"], S["l_forearm"]]
    np.testing.assert_allclose(left_arm.origins[:, computed], pose.origins[:, computed], atol=1e-12)
    others = [s for s in range(16) if s not in computed]
    assert np.isnan(left_arm.origins[:, others]).all() and np.isnan(left_arm.rotations[:, others]).all()


def test_fk_rejects_wrong_parameter_count(model):
    with pytest.raises(ValueError, match="35"):
        forward_kinematics(model, np.zeros(34))


# --------------------------------------------------------------------------- limits

def test_clip_to_limits_respects_every_limit(rng):
    p = rng.uniform(-10, 10, (50, 35))
    c = clip_to_limits(p)
    assert np.all(c >= PARAM_LIMITS[:, 0]) and np.all(c <= PARAM_LIMITS[:, 1])
    inside = (p >= PARAM_LIMITS[:, 0]) & (p <= PARAM_LIMITS[:, 1])
    np.testing.assert_array_equal(c[inside], p[inside])  # values inside are untouched
    low = p < PARAM_LIMITS[:, 0]
    np.testing.assert_array_equal(c[low], np.broadcast_to(PARAM_LIMITS[:, 0], p.shape)[low])
    np.testing.assert_array_equal(clip_to_limits(c), c)
    # any leading shape
    assert clip_to_limits(rng.uniform(-10, 10, (2, 3, 35))).shape == (2, 3, 35)


def test_limits_are_anatomical(model):
    for name in ("l_elbow", "r_elbow", "l_knee", "r_knee"):
        lo, hi = PARAM_LIMITS[P[name]]
        assert lo <= 0.0 < np.radians(120) < hi < np.pi  # hinge: straight is allowed, no hyperflexion
    for name in ("root_x", "root_y", "root_z", "root_heading"):
        assert np.isinf(PARAM_LIMITS[P[name]]).all()  # free root
    # the rest pose is inside the limits
    r = rest_params(model)
    np.testing.assert_array_equal(clip_to_limits(r), r)


# --------------------------------------------------------------------------- chains

def test_chains_partition_the_parameters():
    owned = [i for c in CHAINS.values() for i in c.params]
    assert sorted(owned) == list(range(PARAM_COUNT))  # every parameter once, none twice
    assert set(CHAINS) == {"torso", "head", *LIMB_CHAINS}
    for chain, (proximal, distal, extremity) in LIMB_PARTS.items():
        assert sorted(proximal + distal) == sorted(CHAINS[chain].params)
        assert set(extremity) <= set(CHAINS[chain].segments)


def test_chain_parameters_move_only_the_chain_segments(model, rng):
    base = random_params(model, rng, 1)[0]
    ref = forward_kinematics(model, base)
    for name, chain in CHAINS.items():
        if name == "torso":
            continue
        q = base.copy()
        q[list(chain.params)] += 0.2
        pose = forward_kinematics(model, q)
        moved = {s for s in range(16)
                 if not (np.allclose(pose.rotations[0, s], ref.rotations[0, s], atol=1e-12)
                         and np.allclose(pose.origins[0, s], ref.origins[0, s], atol=1e-12))}
        assert moved == set(chain.segments), name


# ---------------------------------------------------------------------- hold limbs

def test_hold_limbs_in_world_keeps_limb_root_orientations(model, rng):
    reference = random_params(model, rng, 1, spread=0.4)[0]
    cand = np.repeat(reference[None], 6, axis=0)
    cand[:, 0:3] += rng.uniform(-0.1, 0.1, (6, 3))
    cand[:, 3] += rng.uniform(-0.6, 0.6, 6)
    cand[:, 4:9] += rng.uniform(-0.3, 0.3, (6, 5))
    held = hold_limbs_in_world(model, cand, reference)
    assert held.shape == cand.shape
    limb_roots = [S["l_upperarm"], S["r_upperarm"], S["l_thigh"], S["r_thigh"]]
    ref_pose = forward_kinematics(model, reference)
    new_pose = forward_kinematics(model, held)
    for s in limb_roots:
        np.testing.assert_allclose(new_pose.rotations[:, s], np.broadcast_to(ref_pose.rotations[0, s], (6, 3, 3)),
                                   atol=1e-9)
    # the torso moved as asked; only shoulder and hip rotation vectors were changed
    limb_root_params = [i for base in (11, 17, 23, 29) for i in range(base, base + 3)]
    others = [i for i in range(PARAM_COUNT) if i not in limb_root_params]
    np.testing.assert_array_equal(held[:, others], cand[:, others])
    for s in (S["pelvis"], S["chest"]):
        assert not np.allclose(new_pose.rotations[:, s], ref_pose.rotations[0, s], atol=1e-3)
    # without holding, the same torso change swings the limbs
    swung = forward_kinematics(model, cand)
    assert not np.allclose(swung.rotations[:, S["l_thigh"]], ref_pose.rotations[0, S["l_thigh"]], atol=1e-3)


def test_hold_limbs_at_reference_is_identity_on_the_pose(model, rng):
    reference = random_params(model, rng, 1, spread=0.4)[0]
    held = hold_limbs_in_world(model, reference[None], reference)
    np.testing.assert_allclose(forward_kinematics(model, held).joints, forward_kinematics(model, reference).joints,
                               atol=1e-9)


@pytest.mark.parametrize("limb, segments", [("arm", ("upperarm", "forearm", "hand")), ("leg", ("thigh", "shin", "foot"))])
def test_swapped_sides_are_each_others_mirror_image(model, rng, limb, segments):
    """With the trunk at rest (symmetric), each limb swapped in takes the mirror image of the
    other's world rotations and joint positions; swapping twice gives the pose back."""
    x = rest_params(model)
    for side in "lr":
        for name in MIRROR_SIGNS[limb]:
            x[P[f"{side}_{name}"]] = rng.uniform(-0.6, 0.6) + (0.8 if name in ("elbow", "knee") else 0.0)
    y = swap_sides(x, limb)
    fx, fy = forward_kinematics(model, x), forward_kinematics(model, y)
    mirror = np.diag([-1.0, 1.0, 1.0])  # x lateral, the pelvis at x = 0
    for a, b in (("l", "r"), ("r", "l")):
        for seg in segments:
            i, j = SEGMENT_NAMES.index(f"{a}_{seg}"), SEGMENT_NAMES.index(f"{b}_{seg}")
            np.testing.assert_allclose(mirror @ fx.rotations[0, i] @ mirror, fy.rotations[0, j], atol=1e-9)
    joints = [n[2:] for n in JOINT_NAMES if n.startswith("l_")]
    moved = [j for j in joints if not np.allclose(fx.joints[0, JOINT_NAMES.index("l_" + j)],
                                                  fy.joints[0, JOINT_NAMES.index("l_" + j)])]
    assert moved  # the swap changed the limb
    for j in joints:
        np.testing.assert_allclose(mirror @ fx.joints[0, JOINT_NAMES.index("l_" + j)],
                                   fy.joints[0, JOINT_NAMES.index("r_" + j)], atol=1e-9)
    others = [k for k in range(len(x)) if not any(PARAM_NAMES[k] in (f"l_{n}", f"r_{n}") for n in MIRROR_SIGNS[limb])]
    np.testing.assert_array_equal(y[others], x[others])
    np.testing.assert_allclose(swap_sides(y, limb), x)
    with pytest.raises(ValueError, match="limb"):
        swap_sides(x, "tail")
