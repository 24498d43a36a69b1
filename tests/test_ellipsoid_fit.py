"""Ellipsoidal shells on surface voxels and the body's first-frame initialisation (common/ellipsoid_fit.py)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from common.body import JOINT_NAMES, P, forward_kinematics, load_body_model, rest_params, rot_z, rotvec_to_matrix
from common.camera import circle_studio
from common.ellipsoid_fit import (HEAD_DOWN_ROLLS, LIMB_GROUPS, SHELL_NAMES, EllipsoidFit, VolumeTarget, _limb_starts,
                                  activate, fit_ellipsoids, head_down_starts, hull_energy, initial_pose, moments, segment_ellipsoids,
                                  shell_distances, volume_energy)
from common.voxels import SpotGrid, person_ellipsoids, render_ellipsoids


def shell_points(centre, axes, radii, count, rng, noise=0.0):
    """Points uniformly (by area) on an ellipsoid's surface, with optional Gaussian noise."""
    s = rng.normal(size=(count * 6, 3))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    w = np.linalg.norm(s / radii, axis=1)  # area element of the map sphere -> ellipsoid
    keep = rng.random(len(s)) < w / w.max()
    p = (s[keep][:count] * radii) @ np.asarray(axes).T + centre
    return p + rng.normal(scale=noise, size=p.shape)


def random_rotation(rng) -> np.ndarray:
    return Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()


def test_shell_distance_is_the_closest_surface_point():
    rng = np.random.default_rng(0)
    centres = np.array([[0.1, 0.2, 0.3], [-0.4, 0.0, 1.0]])
    axes = np.stack([random_rotation(rng), random_rotation(rng)])
    radii = np.array([[0.4, 0.15, 0.08], [0.2, 0.2, 0.05]])
    points = rng.normal(scale=0.4, size=(400, 3)) + [0.0, 0.1, 0.6]
    d = shell_distances(points, centres, axes, radii)
    for e in range(2):
        dense = shell_points(centres[e], axes[e], radii[e], 400_000, rng)
        brute = cKDTree(dense).query(points)[0]
        assert np.abs(d[:, e] - brute).max() < 2e-3  # the dense sampling's spacing


def test_moments_recover_a_complete_shell():
    rng = np.random.default_rng(1)
    for radii in ([0.3, 0.3, 0.3], [0.45, 0.12, 0.07], [0.2, 0.15, 0.1]):
        R = random_rotation(rng)
        pts = shell_points([0.2, -0.1, 1.0], R, radii, 20_000, rng)
        centre, axes, r = moments(pts)
        np.testing.assert_allclose(centre, [0.2, -0.1, 1.0], atol=0.005)
        np.testing.assert_allclose(r, radii, rtol=0.03)
        if radii[0] > radii[1] > radii[2]:
            for k in range(3):
                assert abs(axes[:, k] @ R[:, k]) > 0.99
        np.testing.assert_allclose(axes.T @ axes, np.eye(3), atol=1e-9)
        assert np.linalg.det(axes) > 0 and axes[2, 0] >= 0


def _six_shells():
    centres = np.array([[0.0, 0.0, 1.1], [0.0, 0.0, 1.75], [0.6, 0.0, 1.3], [-0.6, 0.0, 1.3],
                        [0.15, 0.0, 0.4], [-0.15, 0.0, 0.4]])
    axes = np.stack([np.eye(3)[:, [2, 0, 1]]] * 6)  # long axis vertical
    axes[2] = axes[3] = np.eye(3)  # arms horizontal along x
    radii = np.array([[0.35, 0.18, 0.12], [0.12, 0.1, 0.09], [0.3, 0.05, 0.05], [0.3, 0.05, 0.05],
                      [0.38, 0.07, 0.07], [0.38, 0.07, 0.07]])
    return centres, axes, radii


def test_em_tracking_recovers_moved_shells():
    rng = np.random.default_rng(2)
    centres, axes, radii = _six_shells()
    pts = np.concatenate([shell_points(c, a, r, 700, rng, noise=0.005) for c, a, r in zip(centres, axes, radii)])
    # The previous frame: every shell a few centimetres off and a little turned.
    tilt = Rotation.from_rotvec([0.0, 0.12, 0.0]).as_matrix()
    previous = EllipsoidFit(centres + rng.normal(scale=0.03, size=(6, 3)), tilt @ axes, radii * 1.1,
                            np.ones(6, bool), np.zeros(0, int), 0.0, True)
    fit = fit_ellipsoids(pts, previous, iterations=6)
    assert fit.labelled and fit.active.all()
    np.testing.assert_allclose(fit.centres, centres, atol=0.02)
    for e in range(6):
        if radii[e, 0] > 1.5 * radii[e, 1]:
            assert abs(fit.axes[e][:, 0] @ axes[e][:, 0]) > 0.99
    assert np.mean(fit.assignment == np.repeat(np.arange(6), 700)) > 0.97
    assert fit.error < 0.015


@pytest.fixture(scope="module")
def person_voxels():
    studio = circle_studio(8, 320, 240)
    grid = SpotGrid.build(studio, grid=64)
    return grid.reconstruct(render_ellipsoids(studio, *person_ellipsoids(arm_raise=0.6)))


def test_activation_finds_and_names_six_shells(person_voxels):
    pts = person_voxels.surface_points()
    fit = activate(pts)
    assert fit.active.all() and fit.labelled
    assert fit.facing is not None and fit.facing @ [0.0, -1.0, 0.0] > 0.95  # the feet point at -y
    c = dict(zip(SHELL_NAMES, fit.centres))
    np.testing.assert_allclose(c["head"], [0.0, 0.0, 1.63], atol=0.05)
    assert c["left_arm"][0] > 0.3 and c["right_arm"][0] < -0.3  # facing -y, left is +x
    assert c["left_leg"][0] > 0.03 and c["right_leg"][0] < -0.03 and c["left_leg"][2] < 0.6
    for name, sign in (("left_arm", 1.0), ("right_arm", -1.0)):
        arm = np.array([sign * np.sin(0.6), 0.0, -np.cos(0.6)])  # the synthetic arm's direction
        assert abs(fit.axes[SHELL_NAMES.index(name)][:, 0] @ arm) > 0.95
    tracked = fit_ellipsoids(pts, fit)  # the next frame: tracking keeps the names
    np.testing.assert_allclose(tracked.centres[1:4], fit.centres[1:4], atol=0.03)  # head, arms
    assert tracked.centres[4][0] > 0.03 and tracked.centres[5][0] < -0.03  # legs grow, sides kept


def test_activation_stops_when_one_shell_fits():
    studio = circle_studio(8, 320, 240)
    grid = SpotGrid.build(studio, grid=48)
    ball = grid.reconstruct(render_ellipsoids(studio, [[0.0, 0.0, 1.0]], [np.eye(3)], [[0.35, 0.35, 0.35]]))
    fit = activate(ball.surface_points())
    assert fit.count == 1 and not fit.labelled
    np.testing.assert_allclose(fit.radii[0], 0.35, atol=0.04)
    with pytest.raises(ValueError):
        fit_ellipsoids(np.zeros((3, 3)))


def test_volume_energy_is_bottinos_distance():
    model = load_body_model()
    p = rest_params(model)
    c, a, r = segment_ellipsoids(model, p)
    rng = np.random.default_rng(3)
    on_surface = np.concatenate([shell_points(c[j], a[j], r[j], 30, rng) for j in (0, 2, 10)])
    assert volume_energy(model, p, on_surface) < 1e-12
    lifted = on_surface + [0.0, 0.0, 0.02]
    weights = np.ones(16)
    d = shell_distances(lifted, c, a, r).min(axis=1)
    assert volume_energy(model, p, lifted, weights) == pytest.approx(np.sum(d ** 2))
    moved = p.copy()
    moved[0] += 0.1
    assert volume_energy(model, moved, on_surface) > 10 * volume_energy(model, p, lifted)


@pytest.mark.parametrize("segments", [tuple(range(16)), (0, 1, 2, 3), (4, 5, 6), (13, 14, 15), (3,)])
def test_the_compiled_fit_objective_skips_only_shells_that_cannot_be_nearest(segments):
    """The voxel fit's objective solves a shell's distance only where its lower bound could be
    a point's lowest: its data term, the moving segments against the others held fixed, is the
    sum over points of the lowest weighted squared distance to any segment, however many shells
    it skipped (and the robust term, of the moving segments alone, the bounded loss of their
    full distances)."""
    from common.ellipsoid_fit import ROBUST_DISTANCE, _objective_problem, _solve_objective

    model = load_body_model()
    rng = np.random.default_rng(11)
    weights = rng.uniform(0.5, 2.0, 16)
    base = rest_params(model)
    c, a, r = segment_ellipsoids(model, base)
    points = np.concatenate([shell_points(c[j], a[j], r[j], 40, rng, noise=0.03) for j in range(16)])
    target = VolumeTarget(points, np.zeros((4, 4, 4), np.float32), np.zeros(3), np.full(3, 0.5))
    rest_depth = np.zeros((16, 24))
    for _ in range(5):
        p = base.copy()
        p[6:] += rng.normal(scale=0.4, size=29)
        cp, ap, rp = segment_ellipsoids(model, p)
        problem = _objective_problem(model, p, segments, target, weights, rest_depth, robust=False, hull_scale=0.0)
        every = (shell_distances(points, cp, ap, rp) ** 2 * weights).min(axis=1).sum()
        assert _solve_objective(p, *problem) == pytest.approx(every, rel=1e-12)
        robust = _objective_problem(model, p, segments, target, weights, rest_depth, robust=True, hull_scale=0.0)
        seg = list(segments)
        d2 = (shell_distances(points, cp[seg], ap[seg], rp[seg]) ** 2 * weights[seg]).min(axis=1)
        expected = np.sum(ROBUST_DISTANCE ** 2 * d2 / (d2 + ROBUST_DISTANCE ** 2))
        assert _solve_objective(p, *robust) == pytest.approx(expected, rel=1e-12)


def test_initial_pose_recovers_a_standing_actor():
    truth_model = load_body_model().scaled(1.05)
    p = rest_params(truth_model, position=(0.2, -0.1, truth_model.joint_rest[0, 2]), heading=0.8)
    p[P["l_shoulder_y"]], p[P["r_shoulder_y"]] = 0.5, -0.3  # arms raised sideways, unequally
    p[P["l_hip_y"]], p[P["r_hip_y"]] = 0.12, -0.12
    studio = circle_studio(8, 320, 240)
    voxels = SpotGrid.build(studio, grid=64).reconstruct(render_ellipsoids(studio, *segment_ellipsoids(truth_model, p)))
    init = initial_pose(voxels)
    assert init.scale == pytest.approx(1.05, abs=0.04)
    assert np.cos(init.heading - 0.8) > np.cos(0.25)
    truth = forward_kinematics(truth_model, p).joints[0]
    found = forward_kinematics(init.model, init.params).joints[0]
    error = np.linalg.norm(found - truth, axis=1)
    assert error.mean() < 0.06, dict(zip(JOINT_NAMES, error.round(3)))
    target = VolumeTarget.from_voxels(voxels)
    start = rest_params(init.model, init.params[:3], init.params[3])
    assert (volume_energy(init.model, init.params, target.points) + hull_energy(init.model, init.params, target)
            < volume_energy(init.model, start, target.points) + hull_energy(init.model, start, target))


def test_initial_pose_finds_arms_against_the_body():
    """The actor's own body (size kept), arms hanging against the trunk: the case that the
    limbs' shells and a one-pass limb search got wrong (an arm across the chest)."""
    model = load_body_model()
    p = rest_params(model, position=(-0.1, 0.15, model.joint_rest[0, 2]), heading=2.0)
    p[P["l_shoulder_y"]], p[P["r_shoulder_y"]] = 0.6, -0.6  # upper arms ~9 degrees from vertical
    p[P["l_hip_y"]], p[P["r_hip_y"]] = 0.1, -0.1
    studio = circle_studio(8, 320, 240)
    voxels = SpotGrid.build(studio, grid=64).reconstruct(render_ellipsoids(studio, *segment_ellipsoids(model, p)))
    init = initial_pose(voxels, model)
    assert init.scale == 1.0 and init.model is model
    truth = forward_kinematics(model, p).joints[0]
    error = np.linalg.norm(forward_kinematics(model, init.params).joints[0] - truth, axis=1)
    named = dict(zip(JOINT_NAMES, error.round(3)))
    assert error.mean() < 0.05, named
    for joint in ("l_elbow", "l_wrist", "r_elbow", "r_wrist"):
        assert named[joint] < 0.1, named
    # both front/back candidates come back, the chosen one first
    assert init.candidates.shape == (2, 35)
    np.testing.assert_array_equal(init.candidates[0], init.params)
    assert np.cos(init.candidates[1][3] - init.candidates[0][3]) < 0.0
    # a score (the silhouettes' XOR energy in a session) overrides the volume energy's choice
    seen = []

    def prefer_the_other(candidates):
        seen.append(candidates.shape)
        return [float(np.allclose(c, init.params)) for c in candidates]

    other = initial_pose(voxels, model, score=prefer_the_other)
    assert seen == [(2, 35)]
    np.testing.assert_allclose(other.params, init.candidates[1])
    np.testing.assert_allclose(other.candidates[1], init.params)


def test_limb_starts_take_the_nearest_shell_whatever_its_label(person_voxels):
    """Left and right come from the feet, which can be wrong; a start aimed at the other
    side's arm shell would put the arm through the chest."""
    fit = activate(person_voxels.surface_points())
    order = [0, 1, 3, 2, 4, 5]  # the arms' labels swapped
    swapped = EllipsoidFit(fit.centres[order], fit.axes[order], fit.radii[order], fit.active[order],
                           fit.assignment, fit.error, True)
    model = load_body_model()
    p = rest_params(model)  # faces -y like the synthetic person: left is +x
    for limb, side in (("left_arm", 1.0), ("right_arm", -1.0)):
        for start in _limb_starts(model, p, limb, swapped):
            q = p.copy()
            q[list(LIMB_GROUPS[limb][0])] = start
            elbow = forward_kinematics(model, q).joints[0][JOINT_NAMES.index(limb[0] + "_elbow")]
            assert side * elbow[0] > 0.1, (limb, start)


def _root_rotation(params) -> np.ndarray:
    """(3, 3) the pelvis's world rotation: heading about z, then the tilt."""
    return rot_z(np.array([params[P["root_heading"]]]))[0] @ rotvec_to_matrix(
        np.array([params[P["root_tilt_x"]], params[P["root_tilt_y"]], 0.0]))


def test_head_down_starts_lie_along_the_trunk_head_down():
    """A star-shaped cartwheel, head down and leaning: the shells' axes have no sign, and the
    starts put the head at the trunk's lower end, turned HEAD_DOWN_ROLLS ways; one of them is
    within the roll step (plus the shell's own tilt error) of the actor's orientation."""
    model = load_body_model()
    p = rest_params(model, position=(0.1, -0.2, 0.9), heading=0.7)
    p[P["root_tilt_x"]], p[P["root_tilt_y"]] = 2.4, 0.5
    p[P["l_shoulder_y"]], p[P["r_shoulder_y"]] = 1.9, -1.9
    p[P["l_hip_y"]], p[P["r_hip_y"]] = 0.6, -0.6
    studio = circle_studio(8, 320, 240)
    voxels = SpotGrid.build(studio, grid=64).reconstruct(render_ellipsoids(studio, *segment_ellipsoids(model, p)))
    starts = head_down_starts(model, activate(voxels.surface_points()))
    assert starts.shape == (HEAD_DOWN_ROLLS, 35)
    neck, pelvis = JOINT_NAMES.index("neck"), JOINT_NAMES.index("pelvis")
    truth = forward_kinematics(model, p).joints[0]
    joints = forward_kinematics(model, starts).joints
    assert np.all(joints[:, neck, 2] < joints[:, pelvis, 2] - 0.3)  # every start head down
    spine = truth[neck] - truth[pelvis]
    for j in joints:  # the spine along the trunk's axis, the trunk where the actor's is (the
        # trunk's shell takes in the tops of the thighs, so its centre sits towards the pelvis)
        along = j[neck] - j[pelvis]
        assert np.dot(along, spine) / np.linalg.norm(along) / np.linalg.norm(spine) > np.cos(0.25)
        assert np.linalg.norm((j[neck] + j[pelvis]) / 2 - (truth[neck] + truth[pelvis]) / 2) < 0.2
    turns = [np.arccos(np.clip((np.trace(_root_rotation(s).T @ _root_rotation(p)) - 1) / 2, -1, 1)) for s in starts]
    assert min(turns) < np.pi / HEAD_DOWN_ROLLS + 0.25, np.round(turns, 2)
