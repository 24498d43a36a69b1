"""Fitting: chain solves and frames lower the energy and track the truth; `mocap fit` writes
its result folder, resumes after a crash, and refuses bad input with one line and exit 2."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from common.body import CHAINS, JOINT_NAMES, LIMB_CHAINS, LIMB_ROOTS, P, PARAM_COUNT, PARAM_LIMITS, forward_kinematics
from common.energy import whole_energy
from common.fitting import HOP_JOBS, FitOptions, FrameData, full_energy, hop_fit, solve_chain
from common.search import (POLISHED, SCHEDULES, Context, Schedule, Stage, descend_outward, fit_frame, run_schedule,
                           solve_locally)
from server.cli import main
from server.output import counted

from conftest import SMALL_FRAMES

# Measured on the small sequence (4 cameras 160x120, bundled walk, no noise, skinned surface),
# fitting frames 0-2 from the truth of frame 0: per-frame mean joint error 7.6 / 13.1 / 16.0 mm,
# mean 12.2 mm, max 39.0 mm; holding the previous frame's truth instead: 25.6 / 25.0 mm.
MEAN_JOINT_ERROR_MM = 22.0
MAX_JOINT_ERROR_MM = 60.0
SUMMARY_KEYS = ("frames", "mode", "clients", "energy_backend", "seconds_per_frame", "wall_seconds",
                "evaluations_per_frame", "mean_joint_error_mm", "max_joint_error_mm", "per_joint_error_mm")
RECORD_KEYS = ("frame", "params", "joints", "energy", "seconds")


def one_stage(model, data, stages, fit=None, options=None, **context):
    """The lowest of ``fit`` and the fits of one schedule stage or a few (``common.search``)."""
    options = options or FitOptions()
    ctx = Context(model, data, options, solve_locally(model, data, options), **context)
    return run_schedule(ctx, Schedule(stages if isinstance(stages, tuple) else (stages,)), initial=fit)


def joint_errors_mm(model, params, truth_frame) -> np.ndarray:
    fitted = forward_kinematics(model, params).joints[0]
    true = np.array([truth_frame.joints[n] for n in JOINT_NAMES])
    return np.linalg.norm(fitted - true, axis=1) * 1000.0


@pytest.fixture(scope="module")
def frames(model, small_loaded):
    seq, truth = small_loaded
    return [FrameData(model, seq.studio, seq.silhouettes(f)) for f in seq.frames], truth


# --------------------------------------------------------------------------- library

def test_fit_three_frames_from_the_truth_start(model, frames):
    data, truth = frames
    assert len(data) == SMALL_FRAMES
    x = truth[0].params.copy()
    errors = []
    for f, frame in enumerate(data):
        start_energy = full_energy(model, frame, x)
        result = fit_frame(model, frame, x, FitOptions())
        assert result.energy <= start_energy, f
        assert result.energy == full_energy(model, frame, result.params)
        assert np.isfinite(result.params).all() and result.params.shape == (PARAM_COUNT,)
        assert result.evaluations > 0 and 1 <= result.iterations <= FitOptions().max_iterations
        errors.append(joint_errors_mm(model, result.params, truth[f]))
        x = result.params
    errors = np.array(errors)
    assert errors.mean() < MEAN_JOINT_ERROR_MM, errors.mean(axis=1)
    assert errors.max() < MAX_JOINT_ERROR_MM
    # fitting beats standing still: the previous frame's true pose is further from the truth
    stale = np.array([joint_errors_mm(model, truth[f - 1].params, truth[f]).mean() for f in range(1, len(data))])
    assert errors[1:].mean(axis=1).mean() < stale.mean()


@pytest.mark.parametrize("chain", list(CHAINS))
def test_solve_chain_lowers_its_energy_and_moves_only_its_parameters(model, frames, chain):
    data, truth = frames
    start = truth[0].params  # the pose of frame 0, fitted against frame 1's silhouettes
    r = solve_chain(model, data[1], chain, start, FitOptions())
    assert r.chain == chain
    assert r.energy <= r.energy_before
    assert r.evaluations > 0
    changed = set(np.nonzero(r.params != start)[0])
    own = set(CHAINS[chain].params)
    if chain == "torso":  # the torso also re-expresses the limb roots (hold_limbs_in_world)
        own |= {first + i for _, _, first in LIMB_ROOTS for i in range(3)}
    assert changed <= own, sorted(changed - own)


@pytest.mark.parametrize("half", [True, False])
def test_the_torsos_spine_prior_is_in_full_resolution_pixels(model, frames, half):
    """The prior's weight is per full-resolution pixel: on the half-resolution images, whose
    XOR counts a quarter as many pixels, the torso's objective carries a quarter of it."""
    data, truth = frames
    start = truth[0].params.copy()
    start[P["spine_z"]] = 0.3
    options = FitOptions(torso_half_resolution=half, spine_twist_prior=1000.0)
    r = solve_chain(model, data[1], "torso", start, options)
    xor = float(data[1].whole_image_energy(half)(start[None])[0])
    assert r.energy_before == whole_energy(xor + (0.25 if half else 1.0) * 1000.0 * 0.3 ** 2)


def test_solve_chain_is_deterministic(model, frames):
    data, truth = frames
    a = solve_chain(model, data[1], "left_leg", truth[0].params, FitOptions())
    b = solve_chain(model, data[1], "left_leg", truth[0].params, FitOptions())
    np.testing.assert_array_equal(a.params, b.params)
    assert (a.energy, a.evaluations) == (b.energy, b.evaluations)


def test_polishing_takes_the_best_hypothesis_further(model, five_frames):
    """From three frames back, two rounds per hypothesis stop short; the polishing rounds go on
    from the best of them and lower the energy and the error."""
    from common.sequence import load_sequence

    seq = load_sequence(five_frames)
    truth = seq.truth()
    start, frame = truth[seq.frames[1]].params, seq.frames[4]
    data = FrameData(model, seq.studio, seq.raw_silhouettes(frame))  # the masks as synthesised, noise and all
    options = FitOptions(turn_hypotheses=1, redetect_limbs=False)
    plain = fit_frame(model, data, start, replace(options, polish_iterations=0))
    polished = fit_frame(model, data, start, replace(options, polish_iterations=2))
    assert polished.energy < plain.energy
    assert polished.energy == full_energy(model, data, polished.params)
    assert len(polished.chains) > len(plain.chains) and polished.evaluations > plain.evaluations
    error = [joint_errors_mm(model, r.params, truth[frame]).mean() for r in (plain, polished)]
    assert error[1] < error[0], error


def test_turn_hypotheses_undo_a_start_turned_from_the_truth(model, frames):
    """A start turned 0.15 rad about the vertical from frame 2's true pose: the hierarchy alone
    stays turned (torso and limbs each fit well where they are); fitted again from the start
    turned back, the whole body lands on the truth, whose energy is lower."""
    from common.proposals import turned

    data, truth = frames
    start = turned(truth[2].params, 0.15)
    plain = fit_frame(model, data[2], start, FitOptions(turn_hypotheses=0, redetect_limbs=False))
    turns = fit_frame(model, data[2], start, FitOptions(turn_hypotheses=1, turn_step_rad=0.15, redetect_limbs=False))
    heading = P["root_heading"]
    assert abs(plain.params[heading] - truth[2].params[heading]) > 0.1
    assert abs(turns.params[heading] - truth[2].params[heading]) < 0.02
    assert turns.energy < plain.energy
    assert joint_errors_mm(model, turns.params, truth[2]).mean() < joint_errors_mm(model, plain.params, truth[2]).mean()
    assert turns.evaluations > 1.5 * plain.evaluations  # three fits, all counted (each its own cost)
    np.testing.assert_allclose(turned(start, -0.15), truth[2].params, atol=1e-12)


def test_midway_is_the_mean_pose_within_the_joint_limits():
    from common.proposals import midway

    rng = np.random.default_rng(5)
    a, b = rng.normal(0.0, 1.0, (2, PARAM_COUNT))
    a[P["l_elbow"]] = b[P["l_elbow"]] = PARAM_LIMITS[P["l_elbow"], 0] - 0.4  # both past the limit
    mid = midway(a, b)
    inside = np.arange(PARAM_COUNT) != P["l_elbow"]
    within = (PARAM_LIMITS[:, 0] <= (a + b) / 2) & ((a + b) / 2 <= PARAM_LIMITS[:, 1])
    np.testing.assert_allclose(mid[inside & within], ((a + b) / 2)[inside & within], atol=1e-15)
    assert mid[P["l_elbow"]] == PARAM_LIMITS[P["l_elbow"], 0]
    assert np.all((PARAM_LIMITS[:, 0] <= mid) & (mid <= PARAM_LIMITS[:, 1]))
    np.testing.assert_array_equal(midway(a, b), midway(b, a))


def test_the_same_pose_is_written_nearest_a_reference():
    """A heading a whole turn (or several) from another's is the same pose: moved by whole turns
    to within pi of the reference's. A ball joint's rotation vector near half a turn has a twin
    pointing the other way (angle |v| - 2 pi): taken where it is nearer the reference's. Nothing
    else changes, and a pose near the reference is left as it is."""
    from common.body import rotvec_to_matrix
    from common.proposals import BALL_JOINTS, same_pose_near

    truth = np.random.default_rng(2).normal(0.0, 0.5, PARAM_COUNT)
    fit = truth + 0.05
    fit[P["root_heading"]] += 2.0 * np.pi
    near = same_pose_near(truth, fit)
    assert near[P["root_heading"]] == pytest.approx(truth[P["root_heading"]] + 2.0 * np.pi)
    others = np.arange(PARAM_COUNT) != P["root_heading"]
    np.testing.assert_array_equal(near[others], truth[others])
    np.testing.assert_array_equal(same_pose_near(truth, truth), truth)
    turns = truth.copy()
    turns[P["root_heading"]] += 6.0 * np.pi
    assert same_pose_near(truth, turns)[P["root_heading"]] == pytest.approx(turns[P["root_heading"]])
    shoulder = [P["r_shoulder_x"], P["r_shoulder_y"], P["r_shoulder_z"]]
    assert shoulder in [list(idx) for idx in BALL_JOINTS]
    axis = np.array([0.6, 0.0, -0.8])
    a, b = truth.copy(), truth.copy()
    a[shoulder], b[shoulder] = 3.0 * axis, -3.1 * axis  # 0.18 rad apart, written opposite ways
    twin = same_pose_near(b, a)[shoulder]
    np.testing.assert_allclose(twin, (3.1 - 2.0 * np.pi) * -axis)
    np.testing.assert_allclose(rotvec_to_matrix(twin), rotvec_to_matrix(b[shoulder]), atol=1e-12)
    np.testing.assert_array_equal(np.delete(same_pose_near(b, a), shoulder), np.delete(b, shoulder))
    # far apart as rotations too (a spine bent forward, one bent back; a hip either way): as it is
    spine = [P["spine_x"], P["spine_y"], P["spine_z"]]
    hip = [P["l_hip_x"], P["l_hip_y"], P["l_hip_z"]]
    c, d = truth.copy(), truth.copy()
    c[spine], d[spine] = [1.5, 0.8, 1.0], [-0.7, -0.8, -1.0]
    c[hip], d[hip] = [1.3, 0.0, 0.0], [-2.0, 0.0, 0.0]
    np.testing.assert_array_equal(same_pose_near(c, d), c)


def test_midway_between_poses_written_apart_lies_between_them():
    """Neighbours' fits at headings 3.58 and 9.75 (3.47 and a turn) are poses 0.11 rad apart:
    halfway faces 3.525 (or that and a turn), never backwards (6.67, what a plain mean gives).
    Shoulders 0.18 rad apart written as vectors near pi pointing opposite ways: halfway is
    between them, not a shoulder turned half a turn (what a plain mean, near zero, gives)."""
    from common.body import matrix_to_rotvec, rotvec_to_matrix
    from common.proposals import midway
    from common.retarget import nearest_turn

    a, b = np.zeros(PARAM_COUNT), np.zeros(PARAM_COUNT)
    a[P["root_heading"]], b[P["root_heading"]] = 3.58, 3.47 + 2.0 * np.pi
    for mid in (midway(a, b), midway(b, a)):
        assert nearest_turn(mid[P["root_heading"]], 3.525) == pytest.approx(3.525)
    shoulder = [P["l_shoulder_x"], P["l_shoulder_y"], P["l_shoulder_z"]]
    axis = np.array([0.0, 0.6, 0.8])
    a[shoulder], b[shoulder] = 2.95 * axis, -3.05 * axis
    for mid in (midway(a, b), midway(b, a)):
        for end in (a, b):
            apart = matrix_to_rotvec(rotvec_to_matrix(mid[shoulder]).T @ rotvec_to_matrix(end[shoulder]))
            assert np.linalg.norm(apart) < 0.2


def test_moved_on_from_the_same_poses_written_apart_is_the_same():
    """The pose moved on as it moved since the frame before does not depend on how the frame
    before is written: its heading a turn on, or a shoulder near half a turn as its twin."""
    from common.proposals import moved_on

    rng = np.random.default_rng(7)
    x = rng.normal(0.0, 0.3, PARAM_COUNT)
    before = x - 0.02
    shoulder = [P["r_shoulder_x"], P["r_shoulder_y"], P["r_shoulder_z"]]
    axis = np.array([0.0, 0.6, -0.8])
    x[shoulder], before[shoulder] = 2.95 * axis, 2.85 * axis
    (plain,) = moved_on(x, before)
    written = before.copy()
    written[P["root_heading"]] += 2.0 * np.pi
    written[shoulder] = (2.85 - 2.0 * np.pi) * axis  # the same rotation, the other way round
    (again,) = moved_on(x, written)
    np.testing.assert_allclose(again, plain, atol=1e-12)
    np.testing.assert_allclose(plain[shoulder], 3.05 * axis)  # on along the axis, at the same speed


def test_tilted_ahead_follows_the_pelvis_tilt_only_while_it_moves(model, frames):
    from common.proposals import TILT_AHEAD_RAD, TILT_MOVING_RAD, tilted_ahead

    _, truth = frames
    x = truth[2].params
    tilt = [P["root_tilt_x"], P["root_tilt_y"]]
    assert tilted_ahead(x, None) == ()
    still = x.copy()
    still[tilt] -= 0.4 * TILT_MOVING_RAD
    assert tilted_ahead(x, still) == ()
    before = x.copy()
    before[tilt] -= (0.06, -0.08)  # the tilt moved by (0.06, -0.08) rad since the frame before
    (ahead,) = tilted_ahead(x, before)
    np.testing.assert_allclose(ahead[tilt] - x[tilt], TILT_AHEAD_RAD * np.array([0.6, -0.8]))
    others = np.ones(PARAM_COUNT, dtype=bool)
    others[tilt] = False
    np.testing.assert_array_equal(ahead[others], x[others])


def test_a_tilted_ahead_start_catches_a_pelvis_the_fit_trails(model, frames):
    """A start whose pelvis trails the truth's forward tilt by 0.25 rad, having moved that way
    since the frame before: the tilted-ahead start lands on the truth, and wins on energy."""
    from common.proposals import TILT_AHEAD_RAD

    data, truth = frames
    options = FitOptions(turn_hypotheses=0, redetect_limbs=False)
    lagging = truth[2].params.copy()
    lagging[P["root_tilt_x"]] -= TILT_AHEAD_RAD
    before = lagging.copy()
    before[P["root_tilt_x"]] -= 0.1
    plain = fit_frame(model, data[2], lagging, options)
    ahead = fit_frame(model, data[2], lagging, options, before=before)
    assert ahead.energy < plain.energy
    assert abs(ahead.params[P["root_tilt_x"]] - truth[2].params[P["root_tilt_x"]]) < 0.02
    assert joint_errors_mm(model, ahead.params, truth[2]).mean() < joint_errors_mm(model, plain.params, truth[2]).mean()


def test_moved_on_goes_on_as_the_pose_moved(model, frames):
    from common.body import PARAM_LIMITS
    from common.proposals import moved_on

    _, truth = frames
    x = truth[2].params
    assert moved_on(x, None) == ()
    before = x.copy()
    before[P["root_x"]] -= 0.05
    before[P["l_knee"]] -= 0.2
    (ahead,) = moved_on(x, before)
    np.testing.assert_allclose(ahead - x, x - before, atol=1e-12)
    far = x.copy()
    far[P["l_knee"]] = PARAM_LIMITS[P["l_knee"], 1] - 0.01
    before = far.copy()
    before[P["l_knee"]] -= 0.5
    assert moved_on(far, before)[0][P["l_knee"]] == PARAM_LIMITS[P["l_knee"], 1]  # within the limits


def test_a_start_moved_on_catches_a_body_the_fit_trails(model, frames):
    """The previous frame's fit trails the truth by as much as it moved since the frame before
    (the body, an arm and a leg moving at a constant speed): tracking's start moved on
    (``track_moved_on``, the fast preset's) lands on the truth, and wins on energy."""
    data, truth = frames
    options = FitOptions(turn_hypotheses=0, redetect_limbs=False, track_moved_on=True)
    step = np.zeros(PARAM_COUNT)
    step[[P["root_x"], P["root_y"]]] = 0.06, -0.04
    step[[P["r_shoulder_x"], P["r_elbow"], P["l_hip_x"], P["l_knee"]]] = 0.5, -0.5, 0.4, 0.5
    lagging = truth[2].params - step
    plain = fit_frame(model, data[2], lagging, options)
    ahead = fit_frame(model, data[2], lagging, options, before=lagging - step)
    off = fit_frame(model, data[2], lagging, replace(options, track_moved_on=False), before=lagging - step)
    assert off.energy == plain.energy  # the default's tracking does not move on
    assert ahead.energy < plain.energy
    assert joint_errors_mm(model, ahead.params, truth[2]).mean() < 0.5 * joint_errors_mm(model, plain.params, truth[2]).mean()


def test_redetection_finds_a_lost_arm(model, small_loaded):
    """An arm swung 1.5 rad away is beyond the local grid and Powell; the whole-range search
    (the re-detection round) brings it back. A fitting round does not re-detect."""
    from common.fitting import REDETECT_ROUND

    seq, truth = small_loaded
    f = seq.frames[1]
    true = truth[f].params
    lost = true.copy()
    lost[P["l_shoulder_x"]:P["l_shoulder_x"] + 3] += (1.5, 0.0, 0.0)
    data = FrameData(model, seq.studio, seq.silhouettes(f))
    tracked = solve_chain(model, data, "left_arm", lost, FitOptions())
    found = solve_chain(model, data, "left_arm", lost, FitOptions(), iteration=REDETECT_ROUND)
    elbow_wrist = [JOINT_NAMES.index("l_elbow"), JOINT_NAMES.index("l_wrist")]
    tracked_mm = joint_errors_mm(model, tracked.params, truth[f])[elbow_wrist]
    found_mm = joint_errors_mm(model, found.params, truth[f])[elbow_wrist]
    assert found.energy < 0.99 * found.energy_before  # its whole-image energy, clearly lower
    assert tracked_mm.max() > 100.0, tracked_mm  # lost without it
    assert found_mm.max() < 60.0, found_mm  # 160x120 images: the wrist within a hand's length
    others = np.ones(35, dtype=bool)
    others[list(CHAINS["left_arm"].params)] = False
    np.testing.assert_array_equal(found.params[others], lost[others])
    # a limb where it belongs stays: nothing clears the gain
    kept = solve_chain(model, data, "left_arm", true, FitOptions(), iteration=REDETECT_ROUND)
    np.testing.assert_array_equal(kept.params, true)
    assert kept.energy == kept.energy_before


def test_limb_alternatives_find_a_forearm_folded_away(model, small_loaded):
    """A forearm folded back along its upper arm, the elbow at its limit: among the arm's other
    basins is the true one, and refitting the frame from it lowers the energy."""
    from common.fitting import BASIN_SEPARATION_M, distinct_rows, limb_joints
    from common.proposals import limb_alternatives

    seq, truth = small_loaded
    f = seq.frames[1]
    true = truth[f].params
    folded = true.copy()
    folded[P["l_elbow"]] = PARAM_LIMITS[P["l_elbow"], 1]
    data = FrameData(model, seq.studio, seq.silhouettes(f))
    alternatives, evaluations = limb_alternatives(model, data, "left_arm", folded, FitOptions(), count=2)
    assert 1 <= len(alternatives) <= 2
    assert evaluations > 1000  # the whole range's grid and the Powell solves from its basins
    joints = limb_joints(model, "left_arm", np.array([folded, *alternatives]))
    assert len(distinct_rows(joints, 3)) == len(joints)  # basins apart from x and each other
    true_joints = limb_joints(model, "left_arm", true)[0]
    off_mm = [1000 * np.linalg.norm(j - true_joints, axis=1).max() for j in joints[1:]]
    assert min(off_mm) < 60.0, off_mm  # 160x120 images, as above
    assert 1000 * np.linalg.norm(joints[0] - true_joints, axis=1).max() > 1000 * BASIN_SEPARATION_M
    others = np.ones(35, dtype=bool)
    others[list(CHAINS["left_arm"].params)] = False
    for a in alternatives:
        np.testing.assert_array_equal(a[others], folded[others])
    options = FitOptions(turn_hypotheses=0, redetect_limbs=False)  # the refits alone
    best = alternatives[int(np.argmin(off_mm))]
    assert fit_frame(model, data, best, options).energy < fit_frame(model, data, folded, options).energy


def test_a_first_frames_limb_search_refines_one_grid_point_per_basin(model, small_loaded, monkeypatch):
    """A first frame's re-detection (no tracked limb) fits Powell from REDETECT_STARTS_FIRST_FRAME
    grid points, each in a basin of its own: the grid's best points crowd one basin."""
    import common.fitting as fitting

    seq, truth = small_loaded
    f = seq.frames[1]
    data = FrameData(model, seq.studio, seq.silhouettes(f))
    options = replace(FitOptions(), redetect_turn="round")  # a first frame's wide fits re-detect so
    proximal = list(fitting.LIMB_PARTS["left_arm"][0])
    starts = []
    powell = fitting.powell

    def recording(energy, x0, indices, *args, **kwargs):
        if list(indices) == proximal:
            starts.append(np.array(x0))
        return powell(energy, x0, indices, *args, **kwargs)

    monkeypatch.setattr(fitting, "powell", recording)
    fitting.redetect_limb(model, data, "left_arm", truth[f].params, options)
    assert len(starts) == fitting.REDETECT_STARTS_FIRST_FRAME
    joints = fitting.limb_joints(model, "left_arm", np.array(starts))
    assert fitting.distinct_rows(joints, len(starts)) == list(range(len(starts)))  # each in its own basin


@pytest.mark.parametrize("scores,expected", [
    ({0.9: 5.0, 1.1: 6.0, 1.2: 1.0}, {1.0: 4.0, 0.9: 5.0, 1.1: 6.0}),  # up on both sides: stop there
    ({0.9: 3.0, 0.8: 3.5, 1.1: 3.9, 1.2: 3.0, 1.3: 3.0}, {1.0: 4.0, 0.9: 3.0, 0.8: 3.5, 1.1: 3.9, 1.2: 3.0, 1.3: 3.0}),
])
def test_descend_outward_scores_each_side_while_it_falls(scores, expected):
    batches = []

    def score_many(values):
        batches.append(list(values))
        return [scores[v] for v in values]

    assert descend_outward((0.8, 0.9, 1.1, 1.2, 1.3), 1.0, 4.0, score_many) == expected
    assert all(len(b) <= 2 for b in batches)  # the nearest untried value of each side at once


def test_distinct_rows_keeps_one_row_per_basin():
    from common.fitting import BASIN_SEPARATION_M, distinct_rows

    d = BASIN_SEPARATION_M
    rows = np.zeros((5, 2, 3))
    rows[1, 1, 0] = 0.5 * d   # the same basin as row 0
    rows[2, 1, 0] = 1.5 * d   # another
    rows[3, 0, 2] = 1.2 * d   # another: its elbow moved
    rows[4, 1, 0] = 3.0 * d
    assert distinct_rows(rows, 10) == [0, 2, 3, 4]
    assert distinct_rows(rows, 2) == [0, 2]
    assert distinct_rows(rows, 10, taken=rows[4:]) == [0, 2, 3]


def test_frame_data_refuses_mismatched_silhouettes(model, small_loaded):
    seq, _ = small_loaded
    masks = seq.silhouettes(seq.frames[0])
    with pytest.raises(ValueError, match="cameras"):
        FrameData(model, seq.studio, masks[:-1])
    with pytest.raises(ValueError, match="largest camera"):
        FrameData(model, seq.studio, masks[:, :-2])


def test_fit_options_validate_and_travel():
    with pytest.raises(ValueError, match="energy"):
        FitOptions(energy="quantum")
    with pytest.raises(ValueError, match="grid_steps"):
        FitOptions(grid_steps=4)
    with pytest.raises(ValueError, match="turn_hypotheses"):
        FitOptions(turn_hypotheses=-1)
    with pytest.raises(ValueError, match="polish_iterations"):
        FitOptions(polish_iterations=-1)
    with pytest.raises(ValueError, match="turn_step_rad"):
        FitOptions(turn_hypotheses=8, turn_step_rad=0.5)
    with pytest.raises(ValueError, match="bogus"):
        FitOptions.from_wire({"bogus": 1})
    opts = FitOptions(max_iterations=3, prerender=False)
    assert FitOptions.from_wire(json.loads(json.dumps(opts.to_wire()))) == opts
    # a SOLVE carries what a job is solved with, not the schedule's settings
    from common.fitting import RUN_SETTINGS

    run = FitOptions(turn_hypotheses=1, polish_iterations=0, refine_passes=3, refine_hops=5)
    solve = run.solve_settings()
    assert not set(solve) & set(RUN_SETTINGS) and set(solve) | set(RUN_SETTINGS) == set(run.to_wire())
    assert FitOptions.from_wire(solve) == replace(FitOptions(), **{k: v for k, v in solve.items()})


# ------------------------------------------------------------------------ mocap fit

def fit(sequence: Path, out: Path, *args: str) -> int:
    return main(["fit", str(sequence), "--out", str(out), "--quiet", *args])


def read_lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def fresh_result(small_sequence, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "result"
    assert fit(small_sequence, out, "--frames", "2") == 0
    return out


def test_mocap_fit_writes_the_result_folder(fresh_result, small_loaded):
    from common.bvh import read_bvh

    _, truth = small_loaded
    records = read_lines(fresh_result / "poses.jsonl")
    assert [r["frame"] for r in records] == [0, 1]
    for r in records:
        assert set(RECORD_KEYS) <= set(r)
        assert len(r["params"]) == PARAM_COUNT and np.isfinite(r["params"]).all()
        assert sorted(r["joints"]) == sorted(JOINT_NAMES)
        assert isinstance(r["energy"], int) and r["energy"] >= 0
        assert r["seconds"] > 0
    summary = json.loads((fresh_result / "summary.json").read_text())
    assert set(SUMMARY_KEYS) <= set(summary), sorted(set(SUMMARY_KEYS) - set(summary))
    assert summary["frames"] == 2
    assert (summary["mode"], summary["clients"], summary["energy_backend"]) == ("single", 0, "cpu")
    assert summary["seconds_per_frame"] > 0 and summary["wall_seconds"] > 0
    assert summary["evaluations_per_frame"] > 0
    assert sorted(summary["per_joint_error_mm"]) == sorted(JOINT_NAMES)
    # the accuracy in the summary is the accuracy of the records against truth.jsonl
    errs = np.array([[np.linalg.norm(np.subtract(r["joints"][n], truth[r["frame"]].joints[n])) * 1000
                      for n in JOINT_NAMES] for r in records])
    assert summary["mean_joint_error_mm"] == pytest.approx(errs.mean(), rel=1e-9)
    assert summary["max_joint_error_mm"] == pytest.approx(errs.max(), rel=1e-9)
    assert summary["per_frame_max_error_mm"] == pytest.approx(errs.max(axis=1), rel=1e-9)
    assert summary["mean_joint_error_mm"] < MEAN_JOINT_ERROR_MM
    motion = read_bvh(fresh_result / "motion.bvh")
    assert motion.num_frames == 2


def test_the_summary_table_shows_refinement_beside_tracking(fresh_result):
    import io

    from server.commands.fit import print_summary

    summary = json.loads((fresh_result / "summary.json").read_text())
    out = io.StringIO()
    print_summary(summary, out)
    table = out.getvalue()
    assert f"{summary['refine_seconds_per_frame']:.3f} (1 pass, {counted(summary['frames_refined'], 'frame')} improved)" in table
    assert (f"{summary['mean_joint_error_mm']:.1f} / {summary['max_joint_error_mm']:.1f} mm (tracking alone "
            f"{summary['tracking_mean_joint_error_mm']:.1f} / "
            f"{summary['tracking_max_joint_error_mm']:.1f} mm)") in table
    out = io.StringIO()
    print_summary({**summary, "refinement_passes": []}, out)
    assert "refinement" not in out.getvalue() and "tracking alone" not in out.getvalue()


@pytest.mark.timeout(120)
def test_fit_names_the_report_command_and_the_next_steps(small_sequence, tmp_path, capsys):
    """mocap fit writes no report.html: its table and last line name the commands that follow,
    with the result folder as one word to copy; --quiet and --json print neither."""
    import shlex

    out = tmp_path / "my result"
    assert main(["fit", str(small_sequence), "--out", str(out), "--frames", "1", "--refine-passes", "0"]) == 0
    printed = capsys.readouterr().out
    result = shlex.quote(str(out))
    assert f"in a camera (mocap report {result} names them)" in printed and "report.html names" not in printed
    assert printed.splitlines()[-1].startswith(f"next: mocap report {result}; mocap export {result} --format ")
    assert main(["fit", str(small_sequence), "--out", str(out), "--frames", "1", "--refine-passes", "0",
                 "--resume", "--json"]) == 0
    json.loads(capsys.readouterr().out)  # the summary alone


def test_fit_refuses_negative_refine_passes(small_sequence, tmp_path, capsys):
    assert fit(small_sequence, tmp_path / "r", "--refine-passes", "-1") == 2
    assert "--refine-passes: expected an integer >= 0, got -1" in capsys.readouterr().err


def test_a_run_stopped_after_its_refinement_was_written_ends_as_it_would_have(fresh_result, small_sequence,
                                                                             tmp_path, monkeypatch):
    """Stopped after the refinement pass rewrote poses.jsonl, before the summary: --resume
    refines again from tracking's fits (each record's "first_pass"), not from the refined ones
    (refining a refined take again can move it), and ends with the uninterrupted run's poses."""
    import server.session as session

    fresh = read_lines(fresh_result / "poses.jsonl")
    assert any("first_pass" in r for r in fresh)  # the refinement replaced a frame
    refined_from = []
    real_pass = session.refine_pass

    def logged_pass(model, seq, records, *args, **kwargs):
        refined_from.append([r["params"] for r in records])
        assert not any(k in r for r in records for k in session.AFTER_TRACKING_FIELDS)
        return real_pass(model, seq, records, *args, **kwargs)

    monkeypatch.setattr(session, "refine_pass", logged_pass)
    out = tmp_path / "result"
    out.mkdir()
    shutil.copy(fresh_result / "poses.jsonl", out)
    shutil.copy(fresh_result / "run.json", out)
    assert fit(small_sequence, out, "--frames", "2", "--resume") == 0
    assert refined_from == [[r.get("first_pass", r)["params"] for r in fresh]]  # tracking's fits
    resumed = read_lines(out / "poses.jsonl")
    assert [r["params"] for r in resumed] == [r["params"] for r in fresh]
    assert [r.get("first_pass") for r in resumed] == [r.get("first_pass") for r in fresh]


def test_a_resume_keeps_the_size_the_run_chose(small_sequence, tmp_path):
    """A run stopped before its first frame was written left only run.json: --resume fits at
    the size that run chose (its run.json's), not the model's, and is not refused."""
    first = tmp_path / "first"
    assert fit(small_sequence, first, "--frames", "1", "--actor-height", "1.9") == 0
    scale = json.loads((first / "run.json").read_text())["actor_scale"]
    assert scale != 1.0
    out = tmp_path / "stopped"
    out.mkdir()
    shutil.copy(first / "run.json", out)
    assert fit(small_sequence, out, "--frames", "1", "--resume") == 0
    assert [r["actor_scale"] for r in read_lines(out / "poses.jsonl")] == [scale]
    assert read_lines(out / "poses.jsonl")[0]["params"] == read_lines(first / "poses.jsonl")[0]["params"]


def test_mocap_fit_resume_after_a_crash(fresh_result, small_sequence, tmp_path, capsys):
    fresh = (fresh_result / "poses.jsonl").read_text().splitlines(keepends=True)
    out = tmp_path / "result"
    out.mkdir()
    torn = fresh[1][: len(fresh[1]) // 3]  # a crash in the middle of writing frame 1
    (out / "poses.jsonl").write_text(fresh[0] + torn)
    shutil.copy(fresh_result / "run.json", out)  # the settings the crashed run was started with
    (out / "motion.trc").write_text("made from frame 0 alone")  # an export of the result before
    capsys.readouterr()
    assert fit(small_sequence, out, "--frames", "2", "--resume") == 0
    assert (f"{out}: motion.trc was made from the result before this run went on; make them again"
            in capsys.readouterr().err)
    assert (out / "motion.trc").read_text() == "made from frame 0 alone"  # kept: the user's to replace
    resumed = read_lines(out / "poses.jsonl")
    first, second = json.loads(fresh[0]), json.loads(fresh[1])
    assert [r["frame"] for r in resumed] == [0, 1]
    # kept as it was; the refinement pass then ran again over both frames
    assert {k: v for k, v in resumed[0].items() if not k.startswith("refine_")} == \
        {k: v for k, v in first.items() if not k.startswith("refine_")}
    assert resumed[1]["params"] == second["params"]  # the same pose as an uninterrupted run
    assert resumed[1]["energy"] == second["energy"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["frames_fitted_this_run"] == 1
    assert (out / "motion.bvh").is_file()


def test_mocap_fit_resume_of_a_finished_result_changes_nothing(fresh_result, small_sequence, tmp_path, capsys):
    """A finished run resumed with its own settings: nothing to do. Refining it again would
    change poses that its report and exports were made of."""
    out = tmp_path / "result"
    shutil.copytree(fresh_result, out)
    before = {name: (out / name).read_bytes() for name in ("poses.jsonl", "summary.json", "motion.bvh")}
    capsys.readouterr()
    assert fit(small_sequence, out, "--frames", "2", "--resume") == 0
    assert "already complete (2 frames); nothing to resume" in capsys.readouterr().err
    assert {name: (out / name).read_bytes() for name in before} == before
    (out / "motion.bvh").unlink()  # stopped after the summary, before the BVH: that is made again
    assert fit(small_sequence, out, "--frames", "2", "--resume") == 0
    assert (out / "motion.bvh").read_bytes() == before["motion.bvh"]


def test_export_all_after_fit_keeps_the_fits_own_bvh(fresh_result, tmp_path, capsys):
    """`mocap fit` writes RESULT/motion.bvh; `mocap export RESULT --format all` then writes the
    same bytes there, which loses nothing, so it is not refused; a BVH that differs (another
    rest pose) still is, without --overwrite."""
    from server.cli import main as cli_main

    out = tmp_path / "result"
    shutil.copytree(fresh_result, out)
    bvh = (out / "motion.bvh").read_bytes()
    assert cli_main(["export", str(out), "--format", "all", "--quiet"]) == 0
    assert (out / "motion.bvh").read_bytes() == bvh and (out / "motion.glb").is_file()
    assert cli_main(["export", str(out), "--format", "all", "--quiet"]) == 0  # again: every file the same
    capsys.readouterr()
    assert cli_main(["export", str(out), "--format", "bvh", "--rest", "tpose"]) == 2
    assert "motion.bvh: exists; pass --overwrite" in capsys.readouterr().err
    assert (out / "motion.bvh").read_bytes() == bvh


def test_mocap_fit_resume_refuses_a_foreign_result(fresh_result, small_sequence, tmp_path, capsys):
    out = tmp_path / "result"
    out.mkdir()
    (out / "poses.jsonl").write_text(json.dumps({"frame": 7, "params": [0.0] * 35}) + "\n")
    shutil.copy(fresh_result / "run.json", out)
    assert fit(small_sequence, out, "--frames", "2", "--resume") == 2
    err = capsys.readouterr().err
    assert "poses.jsonl" in err and "resume" in err


@pytest.fixture
def broken_copy(small_sequence, tmp_path) -> Path:
    seq = tmp_path / "seq"
    shutil.copytree(small_sequence, seq)
    return seq


def _expect_user_error(capsys, rc: int, *needles: str) -> str:
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    assert err.startswith("mocap fit: error:")
    for needle in needles:
        assert needle in err, err
    return err


def test_fit_missing_sequence_folder(tmp_path, capsys):
    rc = fit(tmp_path / "no_such_sequence", tmp_path / "out", "--frames", "2")
    _expect_user_error(capsys, rc, "no_such_sequence")


def test_fit_corrupt_calibration(broken_copy, tmp_path, capsys):
    (broken_copy / "calibration.json").write_text('{"cameras": [')
    rc = fit(broken_copy, tmp_path / "out", "--frames", "2")
    _expect_user_error(capsys, rc, str(broken_copy / "calibration.json"))


def test_fit_calibration_with_a_bad_rotation(broken_copy, tmp_path, capsys):
    path = broken_copy / "calibration.json"
    doc = json.loads(path.read_text())
    doc["cameras"][1]["R"] = (2.0 * np.array(doc["cameras"][1]["R"])).tolist()
    path.write_text(json.dumps(doc))
    rc = fit(broken_copy, tmp_path / "out", "--frames", "2")
    _expect_user_error(capsys, rc, "calibration.json", "cam2.R")


def test_fit_silhouette_of_the_wrong_size(broken_copy, tmp_path, capsys):
    from common.sequence import write_mask_png

    png = broken_copy / "silhouettes" / "cam2" / "000000.png"
    write_mask_png(png, np.zeros((60, 80), dtype=bool))
    rc = fit(broken_copy, tmp_path / "out", "--frames", "2")
    _expect_user_error(capsys, rc, str(png), "80x60")


def test_fit_truncated_png_is_refused_before_anything_is_written(broken_copy, tmp_path, capsys):
    png = broken_copy / "silhouettes" / "cam3" / "000001.png"
    png.write_bytes(png.read_bytes()[:60])
    out = tmp_path / "out"
    rc = fit(broken_copy, out, "--frames", "2")
    _expect_user_error(capsys, rc, str(png))
    # every frame's masks are read before the first is fitted: no result folder at all
    assert not out.exists()


def test_fit_into_the_sequence_folder_is_refused_and_too_many_frames_said(broken_copy, tmp_path, capsys):
    rc = fit(broken_copy, broken_copy, "--frames", "1")
    _expect_user_error(capsys, rc, f"--out {broken_copy}: the sequence folder itself")
    assert not (broken_copy / "poses.jsonl").exists()
    assert fit(broken_copy, tmp_path / "out", "--frames", "99", "--iterations", "1", "--refine-passes", "0") == 0
    assert f"--frames 99: {broken_copy} has 3 frames; fitting them all" in capsys.readouterr().err
    assert len(read_lines(tmp_path / "out" / "poses.jsonl")) == 3


@pytest.mark.timeout(300)
def test_a_camera_whose_masks_are_all_off_is_left_out_with_a_warning(broken_copy, tmp_path, capsys):
    """A dead camera (masks all off in every frame) would carve every hull and body away: the
    fit and the voxels go on without it, naming it; with every camera dead, one error line."""
    from common.sequence import write_mask_png

    frames = sorted((broken_copy / "silhouettes" / "cam2").iterdir())
    for png in frames:
        write_mask_png(png, np.zeros((120, 160), dtype=bool))
    out = tmp_path / "out"
    assert fit(broken_copy, out, "--frames", "2", "--init", "auto", "--preset", "fast") == 0
    err = capsys.readouterr().err
    assert err.count("camera cam2's mask is all off in every frame (2 frames): left out;") == 1
    records = read_lines(out / "poses.jsonl")
    assert len(records) == 2 and len(records[0]["fit_quality"]["xor_share"]) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["fit_quality"]["per_camera_mean_xor_share"]) == {"cam1", "cam3", "cam4"}
    # the result says which cameras it was fitted with, a resume must have the same, and its
    # pictures are drawn with them
    assert summary["cameras"] == ["cam1", "cam3", "cam4"] and summary["cameras_left_out"] == ["cam2"]
    assert json.loads((out / "run.json").read_text())["cameras_left_out"] == ["cam2"]
    from server.pictures import load_result
    assert load_result(out).sequence.studio.names == ["cam1", "cam3", "cam4"]
    assert main(["voxels", str(broken_copy), "--out", str(tmp_path / "vox"), "--grid", "16", "--quiet"]) == 0
    assert "cam2's mask is all off in every frame (3 frames): left out" in capsys.readouterr().err
    summary = json.loads((tmp_path / "vox" / "voxels.json").read_text())
    assert summary["cameras"] == 3 and min(f["occupied"] for f in summary["frames"]) > 0
    for camera in ("cam1", "cam3", "cam4"):
        for png in sorted((broken_copy / "silhouettes" / camera).iterdir()):
            write_mask_png(png, np.zeros((120, 160), dtype=bool))
    _expect_user_error(capsys, fit(broken_copy, tmp_path / "none", "--frames", "2"),
                       "every camera's mask is all on or all off in every frame (2 frames)")


# ------------------------------------------------------------------ loss of tracking

def test_tracking_lost_is_a_jump_over_the_recent_median():
    from common.search import tracking_lost

    assert not tracking_lost([1000, 1010], 5000)  # too little history to judge
    assert not tracking_lost([1000, 1010, 990, 1005], 1100)
    assert tracking_lost([1000, 1010, 990, 1005], 1400)
    assert not tracking_lost([5000] * 9 + [1000, 1000, 1000], 1400)  # the last ten frames count


def test_a_frame_stands_out_over_both_neighbours_mean():
    from common.search import STANDING_OUT_RATIO, standing_out

    assert standing_out([1000, 1000, 1200, 1000, 1000]) == [2]
    assert standing_out([1000, 1000, 1070, 1000, 1000]) == []  # the masks' noise
    assert standing_out([1300, 1000, 1000, 1300]) == []  # the first and the last have one neighbour
    assert standing_out([1000, 1100, 1200, 1300]) == []  # a rise, not a frame apart
    assert standing_out([1000, 1100, 1000], ratio=1.05) == [1] and STANDING_OUT_RATIO > 1.0


def test_runs_of_poor_frames_are_refined_with_a_margin():
    from common.search import POOR_SHARE_RATIO, poor_windows

    shares = [0.10] * 20
    assert poor_windows(shares) == []
    shares[8] = shares[9] = 0.13   # a run of two
    shares[19] = 0.125             # the last frame
    assert poor_windows(shares, margin=3) == [(5, 12), (16, 19)]
    assert poor_windows(shares, margin=5) == [(3, 19)]  # windows that meet are one
    shares[0] = 0.112              # noise
    assert poor_windows(shares, margin=0) == [(8, 9), (19, 19)] and POOR_SHARE_RATIO > 1.0
    assert poor_windows([]) == [] and poor_windows([0.0, 0.0, 0.01]) == []  # a median of nothing


@pytest.fixture(scope="module")
def five_frames(tmp_path_factory, model):
    from common.camera import circle_studio
    from common.synth import SynthOptions, synthesize
    from conftest import WALK_CLIP

    out = tmp_path_factory.mktemp("five") / "seq"
    synthesize(model, circle_studio(6, 240, 180), WALK_CLIP, out,
               SynthOptions(frames=5, start=1, step=4, noise="none", surface="skinned", seed=0))
    return out


@pytest.mark.timeout(300)
def test_a_lost_body_is_found_again_from_the_voxels(model, five_frames, tmp_path, monkeypatch):
    """Three frames fitted, then the last pose thrown 0.6 m aside (as if tracking had jumped
    off the actor): the next frame's energy jumps, the fit restarts from the frame's voxels and
    lands on the actor again. The voxel fit's own starts only (the search from all of them is
    the automatic start's test), and no refinement pass."""
    from common.sequence import load_sequence
    from server import session
    from server.session import LocalSolver, run_fit

    all_starts = session.voxel_starts
    monkeypatch.setattr(session, "voxel_starts", lambda model, data: all_starts(model, data)[:3])
    seq = load_sequence(five_frames)
    options = FitOptions(refine_passes=0)
    run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=3)
    lines = read_lines(tmp_path / "poses.jsonl")
    assert not any(r["recovered"] for r in lines)
    lines[-1]["params"][0] += 0.6
    lines[-1]["params"][P["root_heading"]] += 4.0 * np.pi  # the same pose, two turns on in its numbers
    (tmp_path / "poses.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    summary = run_fit(model, seq, tmp_path, options, LocalSolver(model, options), resume=True, max_frames=4)
    last = read_lines(tmp_path / "poses.jsonl")[-1]
    assert last["recovered"] and summary["frames_recovered"] == 1
    # the voxels' heading is taken to the turn the track is on, so the headings run on
    assert abs(last["params"][P["root_heading"]] - lines[-1]["params"][P["root_heading"]]) < np.pi
    truth = seq.truth()[last["frame"]]
    assert joint_errors_mm(model, np.array(last["params"]), truth).mean() < 50.0


@pytest.mark.timeout(300)
def test_the_loss_ratios_say_when_limbs_and_the_body_are_searched_again(model, five_frames, monkeypatch):
    """A start thrown 0.6 m off the actor: the frame's energy jumps over the recent ones', so
    tracking re-detects the limbs and searches from the voxels; with the schedules' ratios set
    above the jump it does neither."""
    from common.sequence import load_sequence
    from server import session
    from server.session import LocalSolver, frame_data, track

    all_starts = session.voxel_starts
    monkeypatch.setattr(session, "voxel_starts", lambda model, data: all_starts(model, data)[:3])
    seq = load_sequence(five_frames)
    truth = seq.truth()
    frame = seq.frames[1]
    start = truth[frame].params.copy()
    start[0] += 0.6
    data = frame_data(model, seq, frame)
    energies = [int(full_energy(model, data, truth[frame].params))] * 3
    options = FitOptions(refine_passes=0)
    patient = replace(SCHEDULES, limb_loss_ratio=9.0, loss_ratio=9.5)
    solver = LocalSolver(model, options)
    try:
        _, redetected, recovered = track(model, data, frame, start, None, energies, options, solver)
        assert redetected and recovered
        _, redetected, recovered = track(model, data, frame, start, None, energies, options, solver,
                                         schedules=patient)
        assert not redetected and not recovered
    finally:
        solver.close()


@pytest.mark.timeout(300)
def test_the_next_frames_masks_are_cleaned_while_a_frame_is_fitted(model, five_frames, tmp_path):
    """Tracking cleans the next frame's masks on a thread of its own; the poses are those of a
    run whose masks were all cleaned beforehand."""
    import threading

    from common.sequence import load_sequence
    from server.session import LocalSolver, run_fit

    options = FitOptions(refine_passes=0)
    seq = load_sequence(five_frames)
    calls, clean = [], seq.cleaned

    def watched(frame):
        calls.append((frame, threading.current_thread().name, frame in seq._cleaned))
        return clean(frame)

    seq.cleaned = watched
    run_fit(model, seq, tmp_path / "ahead", options, LocalSolver(model, options), max_frames=4)
    ahead = {frame for frame, thread, cached in calls if thread.startswith("masks") and not cached}
    assert ahead and ahead <= set(seq.frames[1:4])
    before = load_sequence(five_frames)
    for frame in before.frames[:4]:
        before.cleaned(frame)
    run_fit(model, before, tmp_path / "before", options, LocalSolver(model, options), max_frames=4)
    assert read_lines(tmp_path / "ahead" / "poses.jsonl") and (
        [r["params"] for r in read_lines(tmp_path / "ahead" / "poses.jsonl")]
        == [r["params"] for r in read_lines(tmp_path / "before" / "poses.jsonl")])


@pytest.mark.timeout(300)
@pytest.mark.parametrize("backward", [True, False])
def test_a_refinement_pass_refits_a_spoilt_frame_from_its_neighbour(model, five_frames, tmp_path, backward):
    """Three tracked frames, the one at the far end of the pass then spoilt (its left arm swung
    1.6 rad away, as a first frame's search or a lost limb can leave it): the pass refits it
    from its tracked neighbour, keeps the lower energy and the spoilt fit under "first_pass"."""
    from common.sequence import load_sequence
    from server.session import LocalSolver, RunStats, refine_pass, run_fit

    seq = load_sequence(five_frames)
    options = FitOptions(refine_passes=0)
    run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=3)
    records = read_lines(tmp_path / "poses.jsonl")
    spoilt_at, start_at = (0, -1) if backward else (-1, 0)
    spoilt = np.array(records[spoilt_at]["params"])
    spoilt[P["l_shoulder_x"]] += 1.6
    data = FrameData(model, seq.studio, seq.silhouettes(records[spoilt_at]["frame"]))
    records[spoilt_at].update(params=spoilt.tolist(), energy=full_energy(model, data, spoilt))
    refined, replaced = refine_pass(model, seq, records, options, LocalSolver(model, options), RunStats(), backward)
    assert [r["frame"] for r in refined] == [r["frame"] for r in records]
    assert refined[start_at]["energy"] <= records[start_at]["energy"]  # the pass starts from it, hopped
    assert refined[spoilt_at]["first_pass"] == {k: records[spoilt_at][k] for k in ("params", "joints", "energy")}
    assert refined[spoilt_at]["energy"] < records[spoilt_at]["energy"]
    assert replaced == sum("first_pass" in r for r in refined) >= 1
    assert all(r["energy"] <= r.get("first_pass", r)["energy"] for r in refined)
    truth = seq.truth()[refined[spoilt_at]["frame"]]
    arm = [JOINT_NAMES.index("l_elbow"), JOINT_NAMES.index("l_wrist")]
    assert joint_errors_mm(model, np.array(refined[spoilt_at]["params"]), truth)[arm].max() < 50.0
    assert np.allclose([refined[spoilt_at]["joints"][n] for n in JOINT_NAMES],
                       forward_kinematics(model, np.array(refined[spoilt_at]["params"])).joints[0])


def test_refinement_chunks_cover_the_pass_in_its_order():
    from server.session import refine_chunks

    backward = list(range(9, -1, -1))
    assert refine_chunks(backward, 0) == [backward]
    assert refine_chunks(backward, 20) == [backward]
    chunks = refine_chunks(backward, 4)  # 10 frames: three chunks of 3-4, in the pass's order
    assert [i for c in chunks for i in c] == backward and len(chunks) == 3
    assert all(3 <= len(c) <= 4 for c in chunks)
    assert refine_chunks(list(range(5)), 1) == [[0], [1], [2], [3], [4]]
    assert refine_chunks([], 4) == []


@pytest.mark.timeout(300)
def test_a_chunked_pass_meets_at_the_seams(model, five_frames, tmp_path, monkeypatch):
    """Chunks of one frame after the hopped first frame: the first chunk starts from that frame's
    refined fit, a later one from its neighbour's fit before the pass, and once every chunk is
    done its frame is fitted again from the neighbour's refined fit; every frame keeps the
    lowest energy."""
    from common.sequence import load_sequence
    from server import session
    from server.session import LocalSolver, RunStats, refine_pass, run_fit

    seq = load_sequence(five_frames)
    options = FitOptions(refine_passes=0, refine_chunk_frames=1)
    run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=3)
    records = read_lines(tmp_path / "poses.jsonl")
    starts = []
    real = session.refine_frame

    def spy(model_, data, tracked, options_, dispatch, neighbour, *rest, **named):
        starts.append((rest[-2], None if neighbour is None else np.array(neighbour)))
        return real(model_, data, tracked, options_, dispatch, neighbour, *rest, **named)

    monkeypatch.setattr(session, "refine_frame", spy)
    refined, _ = refine_pass(model, seq, records, options, LocalSolver(model, options), RunStats(), backward=True)
    frames = [r["frame"] for r in records]
    # the hopped last frame; chunk [1] from its refined fit, chunk [0] from the fit frame 1 had
    # before the pass; then where they meet, frame 0 again from frame 1's refined fit
    assert [f for f, _ in starts] == [frames[2], frames[1], frames[0], frames[0]]
    assert starts[0][1] is None
    np.testing.assert_array_equal(starts[1][1], refined[2]["params"])
    np.testing.assert_array_equal(starts[2][1], records[1]["params"])  # not yet refined
    np.testing.assert_array_equal(starts[3][1], refined[1]["params"])  # refined
    assert all(r["energy"] <= r.get("first_pass", r)["energy"] for r in refined)


@pytest.mark.timeout(300)
def test_a_pass_given_an_anchor_starts_from_it_without_hops(model, five_frames, tmp_path):
    """The settle pass of a run without refinement: the frames before the last tracked one are
    refitted backwards from that frame's fit (the anchor), which is neither refitted nor hopped;
    a pass without an anchor hops its first frame."""
    from common.sequence import load_sequence
    from common.search import PASS_START_HOPS
    from server.session import LocalSolver, RunStats, refine_pass, run_fit

    seq = load_sequence(five_frames)
    options = FitOptions(refine_passes=0)
    run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=3)
    records = read_lines(tmp_path / "poses.jsonl")
    anchored = RunStats()
    refined, _ = refine_pass(model, seq, records[:-1], options, LocalSolver(model, options), anchored,
                             anchor=np.array(records[-1]["params"]))
    assert [r["frame"] for r in refined] == [r["frame"] for r in records[:-1]]
    assert anchored.hops_run == 0
    assert all(r["energy"] <= r.get("first_pass", r)["energy"] for r in refined)
    hopped = RunStats()
    refine_pass(model, seq, records[-1:], options, LocalSolver(model, options), hopped)
    assert hopped.hops_run >= PASS_START_HOPS


@pytest.mark.timeout(300)
@pytest.mark.parametrize("backward", [True, False])
def test_a_refinement_pass_fits_each_inner_frame_from_halfway_between_its_neighbours(model, five_frames, tmp_path,
                                                                                     monkeypatch, backward):
    """Each frame with a neighbour on both sides is also fitted from the mean of the fit the
    pass just left behind it (refined) and the fit ahead of it (not yet refined); the end frames
    are not, and every frame keeps the lowest energy of its fits."""
    from common.proposals import midway
    from common.sequence import load_sequence
    from server import session
    from server.session import LocalSolver, RunStats, refine_pass, run_fit

    seq = load_sequence(five_frames)
    options = FitOptions(refine_passes=0)
    run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=4)
    records = read_lines(tmp_path / "poses.jsonl")
    from common import search

    starts = []
    fits = search.fit_starts

    def spy(ctx, jobs, *rest):
        starts.extend((ctx.frame_number, np.array(s)) for s, _ in jobs)
        return fits(ctx, jobs, *rest)

    monkeypatch.setattr(search, "fit_starts", spy)
    refined, _ = refine_pass(model, seq, records, options, LocalSolver(model, options), RunStats(), backward,
                             schedules=replace(SCHEDULES, pass_start_hops=0))
    step = -1 if backward else 1
    order = list(range(len(records)))[::step]
    for behind, i in zip(order, order[1:-1]):
        expected = midway(refined[behind]["params"], records[i + step]["params"])
        assert any(f == records[i]["frame"] and np.allclose(s, expected, atol=1e-12) for f, s in starts), i
    for end in (order[0], order[-1]):
        ends = [s for f, s in starts if f == records[end]["frame"]]
        assert not any(np.allclose(s, midway(a["params"], b["params"])) for s in ends
                       for a in (*records, *refined) for b in (*records, *refined)
                       if not np.allclose(a["params"], b["params"]))  # halfway between two fits
    assert all(r["energy"] <= b["energy"] for r, b in zip(refined, records))


@pytest.mark.timeout(300)
def test_a_pass_refits_its_first_frame_from_its_limbs_other_basins(model, five_frames, tmp_path, monkeypatch):
    """The pass's first frame, which has no neighbour to be refitted from, with its left forearm
    folded back along the upper arm: every pass refits it from the arm's other basins, a plain
    pass too; a searching pass refits every frame so, a plain one its first frame only. run_fit
    searches in its first pass only, and says so."""
    from common.sequence import load_sequence
    from server import session
    from server.session import LocalSolver, RunStats, refine_pass, refinement_note, run_fit

    searching = replace(SCHEDULES, pass_start_hops=0)  # the search alone, not the start's hops
    # the masks as rendered: the cleaning drops a few stray pixels of the hands (1-6 per camera),
    # and on them the arm's other basin lies 460 mm off with less energy
    seq = load_sequence(five_frames, clean_masks=False)
    options = FitOptions(refine_passes=2, refine_search=True)
    summary = run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=2,
                      schedules=searching)
    assert [(p["direction"], p["search"]) for p in summary["refinement_passes"]] == [("backward", True),
                                                                                     ("forward", False)]
    assert refinement_note(summary) == f"(2 passes, the first searching, {counted(summary['frames_refined'], 'frame')} improved)"
    records = read_lines(tmp_path / "poses.jsonl")
    spoilt = np.array(records[-1]["params"])
    spoilt[P["l_elbow"]] = PARAM_LIMITS[P["l_elbow"], 1]
    data = FrameData(model, seq.studio, seq.silhouettes(records[-1]["frame"]))
    records[-1].update(params=spoilt.tolist(), energy=full_energy(model, data, spoilt))
    arm = [JOINT_NAMES.index("l_elbow"), JOINT_NAMES.index("l_wrist")]
    truth = seq.truth()[records[-1]["frame"]]
    searched_frames = []
    real = session.refine_frame

    def spy(model_, data_, tracked, options_, dispatch, neighbour, beyond, other, hops, search, *rest, **named):
        searched_frames.append(search)
        return real(model_, data_, tracked, options_, dispatch, neighbour, beyond, other, hops, search, *rest,
                    **named)

    monkeypatch.setattr(session, "refine_frame", spy)
    for search in (False, True):
        searched_frames.clear()
        refined, replaced = refine_pass(model, seq, records, options, LocalSolver(model, options), RunStats(),
                                        search=search, schedules=searching)
        assert searched_frames == [True, search]  # the pass's first frame (the last), then the other
        assert replaced >= 1 and refined[-1]["energy"] < records[-1]["energy"]
        assert all(r["energy"] <= b["energy"] for r, b in zip(refined, records))
        assert joint_errors_mm(model, np.array(refined[-1]["params"]), truth)[arm].max() < 50.0


def test_arm_twists_turn_the_upper_arm_about_itself_and_bend_the_elbow(model):
    """Each turned start keeps the elbow where it is and moves the wrist round it, a different
    place per turn; the elbow is bent at least ARM_TWIST_ELBOW_RAD; nothing else changes."""
    from common.body import rest_params
    from common.proposals import ARM_TWIST_ELBOW_RAD, ARM_TWISTS, arm_twists

    rng = np.random.default_rng(3)
    params = rest_params(model)
    params[6:] += rng.normal(0.0, 0.3, PARAM_COUNT - 6)
    params[P["r_elbow"]] = 0.1
    turned = arm_twists(model, "right_arm", params)
    assert turned.shape == (ARM_TWISTS, PARAM_COUNT)
    arm = list(CHAINS["right_arm"].params[:4])
    others = np.setdiff1d(np.arange(PARAM_COUNT), arm)
    np.testing.assert_array_equal(turned[:, others], np.repeat(params[None, others], ARM_TWISTS, axis=0))
    assert np.all(turned[:, P["r_elbow"]] == ARM_TWIST_ELBOW_RAD)
    joints = forward_kinematics(model, np.vstack([params, turned])).joints
    elbow, wrist = JOINT_NAMES.index("r_elbow"), JOINT_NAMES.index("r_wrist")
    np.testing.assert_allclose(joints[1:, elbow], np.repeat(joints[:1, elbow], ARM_TWISTS, axis=0), atol=1e-9)
    wrists = joints[1:, wrist]
    assert min(np.linalg.norm(a - b) for i, a in enumerate(wrists) for b in wrists[i + 1:]) > 0.05


@pytest.mark.timeout(120)
def test_a_straight_arm_twisted_half_a_turn_is_turned_back(model, five_frames, monkeypatch):
    """The left arm of a walk frame's truth turned half a turn about itself and straightened, as
    the walk's first frame was found: the hierarchy's fit from there keeps it (the wrist over
    50 mm off, measured 72), the ``twists`` proposer turns it back (under 30 mm) at a lower
    energy; where the neighbour frame's arm is twisted as it is, only if the turn back is
    TWIST_AWAY_GAIN lower. A bent arm is not tried: its twist shows."""
    import common.search as search
    from common.fitting import solve_chain
    from common.proposals import ARM_TWIST_MAX_ELBOW_RAD, arm_twist_options, arm_twist_tried, arm_twists
    from common.sequence import load_sequence

    seq = load_sequence(five_frames)
    frame = seq.frames[0]
    truth = seq.truth()[frame]
    data = FrameData(model, seq.studio, seq.silhouettes(frame))
    options = FitOptions()
    start = arm_twists(model, "left_arm", truth.params)[3]  # 180 degrees
    start[P["l_elbow"]] = PARAM_LIMITS[P["l_elbow"], 0]
    twisted = fit_frame(model, data, start, options)
    assert joint_errors_mm(model, twisted.params, truth).max() > 50.0
    for neighbour in (None, truth.params):  # no neighbour (a first frame), or one with the true twist
        best = one_stage(model, data, Stage(("twists",)), twisted, start=neighbour)
        assert best.energy < twisted.energy
        assert joint_errors_mm(model, best.params, truth).max() < 30.0
    # a neighbour whose arm is twisted as this one is: no turn is towards it, but the turn back,
    # fitted, is clearly lower (TWIST_AWAY_GAIN), so it is taken all the same ...
    away = one_stage(model, data, Stage(("twists",)), twisted, start=twisted.params)
    assert away.energy <= (1.0 - search.TWIST_AWAY_GAIN) * twisted.energy
    assert joint_errors_mm(model, away.params, truth).max() < 30.0
    # ... and where the gain asked for is more than it gives, the fit stays as it was; the turned
    # arms' solves and the fit from the turn back were made (as jobs) and count
    monkeypatch.setattr(search, "TWIST_AWAY_GAIN", 1.0 - 0.5 * away.energy / twisted.energy)
    kept = one_stage(model, data, Stage(("twists",)), twisted, start=twisted.params)
    np.testing.assert_array_equal(kept.params, twisted.params)
    solves = [solve_chain(model, data, "left_arm", y, arm_twist_options(options), iteration=1)
              for y in arm_twists(model, "left_arm", twisted.params)]
    assert kept.evaluations - twisted.evaluations > sum(r.evaluations for r in solves)
    assert kept.evaluations == away.evaluations  # refused, the fit from the turn back cost as much
    bent = twisted.params.copy()
    bent[P["l_elbow"]] = ARM_TWIST_MAX_ELBOW_RAD
    assert arm_twist_tried("left_arm", twisted.params) and not arm_twist_tried("left_arm", bent)


def test_a_folded_arm_is_turned_and_half_unfolded(model):
    """A forearm folded onto its upper arm hides its twist as a straight one does: an elbow
    within ARM_TWIST_FOLDED_RAD of its limit is tried, and its turned starts are bent
    ARM_TWIST_UNFOLDED_RAD, so that Powell can unfold them either way; an arm bent halfway is not
    tried (its twist shows)."""
    from common.body import rest_params
    from common.proposals import (ARM_TWIST_FOLDED_RAD, ARM_TWIST_UNFOLDED_RAD, ARM_TWISTS, arm_twist_tried,
                                  arm_twists)

    params = rest_params(model)
    limit = PARAM_LIMITS[P["r_elbow"], 1]
    for bend, tried in ((limit, True), (limit - ARM_TWIST_FOLDED_RAD + 0.01, True),
                        (limit - ARM_TWIST_FOLDED_RAD - 0.01, False), (1.5, False), (0.2, True)):
        params[P["r_elbow"]] = bend
        assert arm_twist_tried("right_arm", params) == tried, bend
    params[P["r_elbow"]] = limit
    turned = arm_twists(model, "right_arm", params)
    assert turned.shape == (ARM_TWISTS, PARAM_COUNT) and np.all(turned[:, P["r_elbow"]] == ARM_TWIST_UNFOLDED_RAD)


# radians from the truth: the pelvis tilted and the spine bent back while the left leg swings
# forward, a valley the hierarchy alone does not leave (the hop and evolution tests below)
TORSO_AND_LEG_OFF = {"l_hip_x": -0.6, "l_hip_y": 0.4, "root_tilt_x": 0.2, "spine_x": -0.3}


def torso_and_leg_off(model, sequence) -> tuple:
    """(frame, its truth, its FrameData, FitOptions(), the hierarchy's fit from the truth with
    TORSO_AND_LEG_OFF) for the second frame of ``sequence``."""
    from common.body import clip_to_limits
    from common.sequence import load_sequence

    seq = load_sequence(sequence)
    frame = seq.frames[1]
    truth = seq.truth()[frame]
    data = FrameData(model, seq.studio, seq.silhouettes(frame))
    start = np.array(truth.params, dtype=np.float64)
    for name, change in TORSO_AND_LEG_OFF.items():
        start[P[name]] += change
    options = FitOptions()
    return frame, truth, data, options, fit_frame(model, data, clip_to_limits(start), options)


@pytest.mark.timeout(120)
def test_hops_take_a_torso_and_leg_off_together_towards_the_truth(model, five_frames):
    """Pelvis tilted and spine bent back while the left leg swings forward: the hierarchy's fit
    from there stays off (about 39 mm worst joint, 18 mm mean, measured), hops take the torso
    and the leg down the valley together. Seeded: the same hops give the same pose."""
    frame, truth, data, options, fitted = torso_and_leg_off(model, five_frames)
    hopped = hop_fit(fitted.params, 20, options, solve_locally(model, data, options, frame))
    assert full_energy(model, data, hopped.params) < fitted.energy
    assert hopped.energy < hopped.chains[0].energy_before  # the objective, spine prior included
    # measured: 18.4 -> 13.8 mm (half this start's offsets: 11.5 -> 10.7, the hierarchy gets
    # most of the way alone)
    assert joint_errors_mm(model, hopped.params, truth).mean() < joint_errors_mm(model, fitted.params, truth).mean() - 2.0
    assert len(hopped.chains) == 20 and hopped.energy == min(c.energy for c in hopped.chains)
    assert np.array_equal(hop_fit(fitted.params, 20, options, solve_locally(model, data, options, frame)).params,
                          hopped.params)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("side_by_side", [2, 4])
def test_hops_side_by_side_give_the_hops_one_after_another(model, five_frames, side_by_side):
    """Hops run side by side from the same best pose; those after a lower one are dropped and
    run again from it, so the pose is that of one hop after another, as a cluster's must be."""
    from common.sequence import load_sequence

    seq = load_sequence(five_frames)
    frame = seq.frames[2]
    data = FrameData(model, seq.studio, seq.silhouettes(frame))
    start = np.array(seq.truth()[frame].params, dtype=np.float64)
    start[P["spine_x"]] += 0.2
    start[P["r_shoulder_x"]] -= 0.4
    options = FitOptions()
    one = hop_fit(start, 9, options, solve_locally(model, data, options, frame))
    rounds = []

    def dispatch(jobs, params, iteration, job_options=None):
        rounds.append((len(jobs), iteration))
        return solve_locally(model, data, options, frame)(jobs, params, iteration, job_options)

    together = hop_fit(start, 9, options, dispatch, side_by_side)
    assert np.array_equal(together.params, one.params) and together.energy == one.energy < one.chains[0].energy_before
    assert together.evaluations == one.evaluations  # those of the hops one after another
    # more hops ran than were kept: some started from a pose a hop beside them had bettered
    assert len(together.chains) > len(one.chains) == 9
    assert rounds[0] == (side_by_side, 0) and all(n <= side_by_side for n, _ in rounds)
    assert sum(n for n, _ in rounds) == len(together.chains)


@pytest.mark.timeout(120)
def test_evolutions_take_a_torso_and_leg_off_together_towards_the_truth(model, five_frames):
    """The torso and a leg off together, as in the hops' test: an evolution from the
    hierarchy's fit moves them down the valley together, reports its energies as the server's
    check scores them (an honest client's result is accepted), and is a function of its seed
    and number alone. The finish (evolutions, the lowest polished) ends lower than the fit, and
    with no evolutions it is the fit."""
    from common.fitting import EVOLVE_JOBS, FrameResult, evolve
    from common.search import finish_frame
    from server.trust import check_result

    frame, truth, data, options, fitted = torso_and_leg_off(model, five_frames)
    moved = evolve(model, data, fitted.params, options, 0, frame, EVOLVE_JOBS[0])
    assert moved.energy < moved.energy_before and check_result(data, moved, fitted.params, options, 0) is None
    assert np.array_equal(evolve(model, data, fitted.params, options, 0, frame, EVOLVE_JOBS[1]).params, moved.params)
    assert not np.array_equal(evolve(model, data, fitted.params, options, 1, frame, EVOLVE_JOBS[0]).params,
                              moved.params)
    finished = finish_frame(model, data, fitted, options, solve_locally(model, data, options, frame), frame)
    assert finished.energy < fitted.energy and finished.energy == full_energy(model, data, finished.params)
    # measured: 18.4 mm mean joint error, 728 pixels -> 12.7 mm, 576 pixels after the finish
    assert joint_errors_mm(model, finished.params, truth).mean() < joint_errors_mm(model, fitted.params, truth).mean() - 2.0
    evolved = [c for c in finished.chains if c.chain in EVOLVE_JOBS]
    assert [c.chain for c in evolved] == list(EVOLVE_JOBS[:SCHEDULES.finish_evolutions])
    unchanged = finish_frame(model, data, fitted, options, solve_locally(model, data, options, frame), frame,
                             replace(SCHEDULES, finish_evolutions=0))
    assert isinstance(unchanged, FrameResult) and np.array_equal(unchanged.params, fitted.params)
    assert unchanged.energy == fitted.energy and unchanged.chains == fitted.chains


def test_hop_fit_refuses_no_hops_and_too_many_side_by_side(model, five_frames):
    from common.sequence import load_sequence

    seq = load_sequence(five_frames)
    data = FrameData(model, seq.studio, seq.silhouettes(seq.frames[0]))
    start = np.array(seq.truth()[seq.frames[0]].params)
    with pytest.raises(ValueError, match="hops >= 1"):
        hop_fit(start, 0, FitOptions(), solve_locally(model, data, FitOptions()))
    with pytest.raises(ValueError, match="side_by_side"):
        hop_fit(start, 1, FitOptions(), solve_locally(model, data, FitOptions()), len(HOP_JOBS) + 1)


def test_fit_refuses_a_search_without_refinement_passes(small_sequence, tmp_path, capsys):
    assert fit(small_sequence, tmp_path / "r", "--refine-search", "--refine-passes", "0") == 2
    assert "refine_search" in capsys.readouterr().err


@pytest.mark.timeout(300)
def test_a_hopping_pass_refits_a_frame_whose_torso_and_leg_are_off_together(model, five_frames, tmp_path):
    """The pass's first frame (which has no neighbour) spoilt as in the test above: the hops
    refit it closer to the truth, and so do a plain pass's PASS_START_HOPS. run_fit hops in its
    first pass only, and says so."""
    from common.body import clip_to_limits
    from common.sequence import load_sequence
    from common.search import PASS_START_HOPS
    from server.session import LocalSolver, RunStats, refine_pass, refinement_note, run_fit

    seq = load_sequence(five_frames)
    options = FitOptions(refine_passes=2, refine_hops=10)
    summary = run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=2)
    assert [(p["direction"], p["hops"]) for p in summary["refinement_passes"]] == [("backward", 10), ("forward", 0)]
    assert refinement_note(summary) == f"(2 passes, the first hopping, {counted(summary['frames_refined'], 'frame')} improved)"
    records = read_lines(tmp_path / "poses.jsonl")
    frame = records[-1]["frame"]
    data = FrameData(model, seq.studio, seq.silhouettes(frame))
    start = np.array(seq.truth()[frame].params, dtype=np.float64)
    for name, change in TORSO_AND_LEG_OFF.items():
        start[P[name]] += change
    spoilt = fit_frame(model, data, clip_to_limits(start), options)
    records[-1].update(params=spoilt.params.tolist(), energy=spoilt.energy)
    hopped, _ = refine_pass(model, seq, records, options, LocalSolver(model, options), RunStats(), hops=10)
    assert hopped[-1]["energy"] < records[-1]["energy"]
    truth = seq.truth()[frame]
    assert joint_errors_mm(model, np.array(hopped[-1]["params"]), truth).mean() < \
        joint_errors_mm(model, spoilt.params, truth).mean()
    # a plain pass, too, hops its first frame (PASS_START_HOPS), and that frame alone
    stats = RunStats()
    plain, _ = refine_pass(model, seq, records, options, LocalSolver(model, options), stats)
    assert stats.hops_run == PASS_START_HOPS
    assert plain[-1]["energy"] < records[-1]["energy"]
    assert joint_errors_mm(model, np.array(plain[-1]["params"]), truth).mean() < \
        joint_errors_mm(model, spoilt.params, truth).mean()


def test_refinement_note_names_what_the_first_pass_did():
    from server.session import refinement_note

    def note(passes, refined=3):
        return refinement_note({"refinement_passes": passes, "frames_refined": refined})

    plain = {"direction": "backward", "search": False, "hops": 0}
    assert note([plain]) == "(1 pass, 3 frames improved)"
    assert note([{**plain, "hops": 60}]) == "(1 pass, hopping, 3 frames improved)"
    assert note([{**plain, "search": True, "hops": 60}, plain]) == \
        "(2 passes, the first searching and hopping, 3 frames improved)"
    assert note([{**plain, "search": True}, plain]) == "(2 passes, the first searching, 3 frames improved)"
    assert refinement_note({"refinement_passes": [plain], "frames_refined": 3, "frames_settled": 2}) == \
        "(1 pass, 3 frames improved, 2 settled on another frame's pose)"


@pytest.mark.parametrize("args, field", [(("--refine-hops", "5", "--refine-passes", "0"), "refine_hops needs"),
                                         (("--refine-hops", "-1"), "--refine-hops: expected an integer >= 0"),
                                         (("--set", "fit.spine_twist_prior=-1"),
                                          "--set: [fit] spine_twist_prior: expected a number >= 0"),
                                         (("--set", "fit.spine_twist_prior=nan"),
                                          "--set: [fit] spine_twist_prior: expected a number >= 0")])
def test_fit_refuses_bad_refinement_and_prior_options(small_sequence, tmp_path, capsys, args, field):
    assert fit(small_sequence, tmp_path / "r", *args) == 2
    assert field in capsys.readouterr().err


def test_the_search_s_knobs_reach_the_fit_options_from_a_file_or_set(tmp_path):
    """The [fit] keys with no option of their own (server.config.SEARCH_KNOBS) reach FitOptions
    from a Config.toml (--config) and from --set, --set over the file, the file over the preset."""
    import argparse

    from server.commands.fit import add_fit_arguments, options_from_args
    from server.config import fit_option_defaults

    def options(*argv, config=None, preset=None):
        parser = argparse.ArgumentParser()
        add_fit_arguments(parser)
        args = parser.parse_args(["seq", "--out", "r", *argv])
        parser.set_defaults(**fit_option_defaults(preset, config, args.set))
        return options_from_args(parser.parse_args(["seq", "--out", "r", *argv]))

    assert options().spine_twist_prior == FitOptions().spine_twist_prior and options().redetect_limbs
    assert options("--set", "fit.spine_twist_prior=500").spine_twist_prior == 500.0
    file = tmp_path / "Config.toml"
    file.write_text("[fit]\ngrid_steps = 5\nredetect = false\nturn_step = 0.2\nprerender = false\n"
                    "grid_range = 0.5\n")
    chosen = options(config=file)
    assert (chosen.grid_steps, chosen.redetect_limbs, chosen.turn_step_rad, chosen.prerender,
            chosen.grid_range_rad) == (5, False, 0.2, False, 0.5)
    assert options("--set", "fit.grid_steps=9", config=file, preset="best").grid_steps == 9


def test_schedules_read_from_a_file_or_set_reach_the_fit(tmp_path):
    """[fit.schedules] from a Config.toml (--config) and --set: each schedule named replaces the
    default one whole, the rest stay; the defaults written as tables read back as themselves."""
    import argparse

    from common.schedule_tables import schedules_from_table, schedules_table
    from server.commands.fit import add_fit_arguments, schedules_from_args
    from server.config import fit_option_defaults

    def schedules(*argv, config=None):
        parser = argparse.ArgumentParser()
        add_fit_arguments(parser)
        args = parser.parse_args(["seq", "--out", "r", *argv])
        parser.set_defaults(**fit_option_defaults(None, config, args.set))
        return schedules_from_args(parser.parse_args(["seq", "--out", "r", *argv]), FitOptions())

    assert schedules() == SCHEDULES
    assert schedules_from_table(schedules_table(SCHEDULES)) == SCHEDULES
    file = tmp_path / "Config.toml"
    file.write_text('[fit.schedules]\nsearch_hops = 5\nloss_ratio = 1.5\n[fit.schedules.tracking]\n'
                    'stages = [{proposers = ["start", "start_turns"]}, {proposers = ["again"], variants = ["polish"]}]\n'
                    '[fit.schedules.search]\nbudget = 1000\nstages = [{proposers = ["starts"], variants = ["wide-round"], '
                    'drop = [2, 1.5]}, {proposers = ["again"], variants = "as-fitted", rounds = 2, min_gain = 0.01}]\n')
    chosen = schedules(config=file)
    assert chosen.tracking == Schedule((Stage(("start", "start_turns")), Stage(("again",), ("polish",))))
    assert chosen.search == Schedule((Stage(("starts",), ("wide-round",), drop=(2, 1.5)),
                                      Stage(("again",), None, rounds=2, min_gain=0.01)), budget=1000)
    assert (chosen.search_hops, chosen.loss_ratio, chosen.refine, chosen.wide) == (5, 1.5, SCHEDULES.refine,
                                                                                     SCHEDULES.wide)
    # --set replaces the schedules it names and keeps the file's others
    given = schedules("--set", 'fit.schedules={limbs_lost={stages=[{proposers=["start"]}]}}', config=file)
    assert given.limbs_lost == Schedule((Stage(("start",)),)) and given.tracking == chosen.tracking
    assert (given.search, given.search_hops) == (chosen.search, 5)


@pytest.mark.parametrize("table, message", [
    ('{tracking={stages=[{proposers=["start", "nope"]}]}}', "tracking: stage 1: unknown proposer 'nope' (known: start,"),
    ('{search={stages=[{proposers=["starts"], variants=["wide"]}]}}', "search: stage 1: unknown variant 'wide'"),
    ('{refine={stages=[{proposers=["start"]}, {proposers=["again"], rounds=0}]}}',
     "refine: stage 2: rounds: expected an integer >= 1, got 0"),
    ('{refine={stages=[{proposers=["start"], drop=[2]}]}}', "drop: expected [rounds >= 1, ratio >= 1]"),
    ('{refine={stages=[{proposer=["start"]}]}}', "stage 1: unknown key 'proposer'"),
    ('{refine={stages=[]}}', "refine: stages: expected a list of one or more stage tables"),
    ('{search={budget=-1, stages=[{proposers=["starts"]}]}}', "search: budget: expected an integer >= 0"),
    ('{tracking_stages={stages=[{proposers=["start"]}]}}', "unknown schedule 'tracking_stages' (did you mean 'tracking'?)"),
    ('{search_hops=-2}', "search_hops: expected an integer >= 0, got -2"),
    ('{pass_start_hops=1.5}', "pass_start_hops: expected an integer >= 0, got 1.5"),
    ('{loss_ratio=0.9}', "loss_ratio: expected a number between 1 and 10 (times), got 0.9"),
    ('{after_hops={budget=10, stages=[{proposers=["twists"]}]}}', "after_hops: budget: added to a refinement's"),
    ('{tracking={stages=[{proposers=["again"]}]}}', "tracking: stage 1 makes no start: its proposers need one of start,"),
    ('{search={stages=[{proposers=["starts"], variants="as-fitted"}]}}',
     "search: stage 1 makes no start: its variants fit nothing with these settings (as-fitted)"),
])
def test_fit_refuses_bad_schedules_naming_the_schedule_and_stage(small_sequence, tmp_path, capsys, table, message):
    assert fit(small_sequence, tmp_path / "r", "--set", f"fit.schedules={table}") == 2
    err = capsys.readouterr().err
    assert "[fit.schedules] " in err and message in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


@pytest.mark.timeout(300)
def test_a_run_keeps_its_own_schedules_and_resumes_only_with_them(small_sequence, tmp_path, capsys):
    """run.json holds the schedules that are not the defaults (a run with the defaults holds
    none, so that runs from before schedules were settings resume); --resume refuses others."""
    lean = 'fit.schedules={tracking={stages=[{proposers=["start"]}]}}'
    assert fit(small_sequence, tmp_path / "plain", "--frames", "1", "--refine-passes", "0") == 0
    assert "schedules" not in json.loads((tmp_path / "plain" / "run.json").read_text())
    assert fit(small_sequence, tmp_path / "r", "--frames", "1", "--refine-passes", "0", "--set", lean) == 0
    assert json.loads((tmp_path / "r" / "run.json").read_text())["schedules"] == {
        "tracking": {"stages": [{"proposers": ["start"]}], "budget": 0}}
    capsys.readouterr()
    assert fit(small_sequence, tmp_path / "r", "--frames", "2", "--refine-passes", "0", "--resume") == 2
    assert "--resume: the settings differ" in capsys.readouterr().err
    assert fit(small_sequence, tmp_path / "r", "--frames", "2", "--refine-passes", "0", "--resume", "--set", lean) == 0
    assert len(read_lines(tmp_path / "r" / "poses.jsonl")) == 2


def test_a_first_stage_that_fits_nothing_under_the_preset_is_refused(small_sequence, tmp_path, capsys):
    """Tracking polished only, under the fast preset (no polish rounds), would make no fit: refused
    before anything is fitted or written."""
    table = '{tracking={stages=[{proposers=["start"], variants=["polish"]}]}}'
    assert fit(small_sequence, tmp_path / "r", "--preset", "fast", "--set", f"fit.schedules={table}") == 2
    assert "tracking: stage 1 makes no start: its variants fit nothing with these settings (polish)" in \
        capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.timeout(300)
def test_a_leaner_tracking_schedule_is_what_tracks(model, frames):
    """A tracking schedule of the previous pose alone fits that one start: its evaluations are
    one fit's, a fraction of the default schedule's turns, polish and re-detection."""
    data, truth = frames
    lean = replace(SCHEDULES, tracking=Schedule((Stage(("start",)),)))
    alone = fit_frame(model, data[1], truth[0].params, FitOptions(), schedules=lean)
    plain = one_stage(model, data[1], Stage(("start",)), start=truth[0].params)
    default = fit_frame(model, data[1], truth[0].params, FitOptions())
    assert alone.energy == plain.energy and alone.evaluations == plain.evaluations
    assert 4 * alone.evaluations < default.evaluations


@pytest.mark.timeout(300)
def test_refinement_passes_alternate_and_keep_the_tracking_fit_and_its_accuracy(model, five_frames, tmp_path):
    """Two passes after tracking: backward then forward, poses.jsonl rewritten with the lower
    energies, and the summary scoring both the refined frames and the frames as tracked."""
    from common.sequence import load_sequence
    from common.scoring import accuracy
    from server.session import LocalSolver, run_fit

    seq = load_sequence(five_frames)
    tracked = run_fit(model, seq, tmp_path / "tracked", FitOptions(refine_passes=0),
                      LocalSolver(model, FitOptions(refine_passes=0)), max_frames=4)
    options = FitOptions(refine_passes=2)
    summary = run_fit(model, seq, tmp_path / "refined", options, LocalSolver(model, options), max_frames=4)
    assert [p["direction"] for p in summary["refinement_passes"]] == ["backward", "forward"]
    assert tracked["refinement_passes"] == [] and tracked["refine_seconds_per_frame"] == 0.0
    assert summary["refine_seconds_per_frame"] > 0.0
    lines = read_lines(tmp_path / "refined" / "poses.jsonl")
    before = read_lines(tmp_path / "tracked" / "poses.jsonl")
    assert [r["frame"] for r in lines] == [r["frame"] for r in before]
    # tracking is deterministic: each frame's tracking fit is the refinement-free run's
    for r, b in zip(lines, before):
        assert r.get("first_pass", r)["params"] == b["params"]
        assert r["energy"] <= b["energy"]
    assert summary["frames_refined"] == sum("first_pass" in r for r in lines)
    replaced = [p["frames_replaced"] for p in summary["refinement_passes"]]
    assert max(replaced) <= summary["frames_refined"] <= sum(replaced)  # a frame replaced twice counts once
    assert summary["tracking_mean_joint_error_mm"] == pytest.approx(tracked["mean_joint_error_mm"])
    assert summary["tracking_per_frame_error_mm"] == pytest.approx(tracked["per_frame_error_mm"])
    assert summary["mean_joint_error_mm"] == pytest.approx(accuracy(lines, seq.truth())["mean_joint_error_mm"])


@pytest.mark.timeout(300)
def test_a_limb_lost_between_frames_is_found_again(model, five_frames, tmp_path):
    """Three frames fitted, then the last pose's left arm swung 1.6 rad away (a fast move the
    local search cannot follow): the next frame's re-detection finds the arm again, without a
    restart from the voxels."""
    from common.sequence import load_sequence
    from server.session import LocalSolver, run_fit

    seq = load_sequence(five_frames)
    options = FitOptions()
    run_fit(model, seq, tmp_path, options, LocalSolver(model, options), max_frames=3)
    lines = read_lines(tmp_path / "poses.jsonl")
    lines[-1]["params"][P["l_shoulder_x"]] += 1.6
    (tmp_path / "poses.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    summary = run_fit(model, seq, tmp_path, options, LocalSolver(model, options), resume=True, max_frames=4)
    last = read_lines(tmp_path / "poses.jsonl")[-1]
    assert summary["frames_recovered"] == 0
    # the take's time: this run's and the first run's tracking of the three frames it kept
    from server.project import result_figures

    carried = sum(r["seconds"] for r in lines)
    assert summary["frames_fitted_this_run"] == 1 and carried > 0
    assert summary["take_seconds"] == pytest.approx(summary["wall_seconds"] + carried)
    assert result_figures(tmp_path)["seconds_per_frame"] == pytest.approx(summary["take_seconds"] / 4)
    arm = [JOINT_NAMES.index("l_elbow"), JOINT_NAMES.index("l_wrist")]
    errors = joint_errors_mm(model, np.array(last["params"]), seq.truth()[last["frame"]])[arm]
    assert errors.max() < 50.0, errors


@pytest.mark.slow  # whole first-frame searches: make test-slow
@pytest.mark.timeout(300)
def test_init_auto_ignores_the_truth_and_is_scored_by_it(five_frames, tmp_path):
    """--init auto starts from the voxels even though the sequence has truth, which then only
    scores; without --init the truth's first pose is the start."""
    assert fit(five_frames, tmp_path / "auto", "--frames", "2", "--init", "auto") == 0
    auto = json.loads((tmp_path / "auto" / "summary.json").read_text())
    assert auto["init"] == "auto"
    assert auto["per_frame_error_mm"][0] < 50.0, auto["per_frame_error_mm"]
    # the searched first frame was fitted again backwards from the second (itself fitted by the
    # pass's start hops): the lower energy kept
    lines = read_lines(tmp_path / "auto" / "poses.jsonl")
    from common.sequence import load_sequence
    assert [r["frame"] for r in lines] == load_sequence(five_frames).frames[:2]
    assert auto["frames_refined"] == sum("first_pass" in r for r in lines)
    assert all(r["energy"] < r["first_pass"]["energy"] for r in lines if "first_pass" in r)
    # the search ends with hops; they are no chain solves, and the per-chain figures leave them out
    assert not set(lines[0]["chains"]) & set(HOP_JOBS) and not set(auto["chain_evaluations_per_frame"]) & set(HOP_JOBS)
    assert fit(five_frames, tmp_path / "given", "--frames", "1") == 0
    assert json.loads((tmp_path / "given" / "summary.json").read_text())["init"] == "truth"


@pytest.mark.timeout(300)
def test_voxel_starts_cover_four_headings_upright_and_bent_and_head_down(model, five_frames):
    from common.body import P
    from common.ellipsoid_fit import HEAD_DOWN_ROLLS
    from common.sequence import load_sequence
    from common.proposals import POSTURE_STARTS_KEPT, STANDING_START_TILTS_RAD, STANDING_START_TURNS_RAD, voxel_starts

    seq = load_sequence(five_frames)
    frame = seq.frames[0]
    starts = voxel_starts(model, FrameData(model, seq.studio, seq.silhouettes(frame)))
    standing_count = 2 * len(STANDING_START_TURNS_RAD) * len(STANDING_START_TILTS_RAD)
    assert len(starts) == 2 + standing_count + HEAD_DOWN_ROLLS + POSTURE_STARTS_KEPT
    # the posture starts (seated, crouching, kneeling, lying) come last, knees bent or trunk not upright
    for start in starts[-POSTURE_STARTS_KEPT:]:
        assert start[P["l_knee"]] > 0.5 or abs(start[P["root_tilt_x"]]) > 1.0 or abs(start[P["root_tilt_y"]]) > 1.0
    front, back = starts[0], starts[1]
    assert np.isclose(abs(np.angle(np.exp(1j * (front[P["root_heading"]] - back[P["root_heading"]])))), np.pi,
                      atol=0.5)
    standing = np.array(starts[2:2 + standing_count])
    assert sorted(set(np.round(standing[:, P["root_tilt_x"]], 6))) == sorted(STANDING_START_TILTS_RAD)
    # at the voxel fit's front and back headings, and a quarter turn from each
    headings = standing[:, P["root_heading"]].reshape(2, len(STANDING_START_TURNS_RAD), -1)
    for candidate, per_turn in zip((front, back), headings):
        for turn, heading in zip(STANDING_START_TURNS_RAD, per_turn):
            assert np.allclose(heading, candidate[P["root_heading"]] + turn)
    head_down = forward_kinematics(model, np.array(starts[-HEAD_DOWN_ROLLS - POSTURE_STARTS_KEPT:-POSTURE_STARTS_KEPT])).joints
    assert np.all(head_down[:, JOINT_NAMES.index("neck"), 2] < head_down[:, 0, 2])
    truth = seq.truth()[frame].params
    # the actor is where one of the starts is, within a body width
    assert min(np.linalg.norm(s[:2] - truth[:2]) for s in starts) < 0.2


@pytest.mark.slow  # whole first-frame searches: make test-slow
@pytest.mark.timeout(300)
def test_a_head_down_actor_is_found_from_the_voxels(model):
    """A cartwheel's star, head down: the upright and bent-forward starts end about 0.9 m off
    (measured: 909 mm mean); with the head-down starts the search finds it within 50 mm
    (measured: 17 mm; 14 mm with the rotated fits)."""
    from common.body import rest_params, skinned_vertices
    from common.camera import circle_studio
    from common.render_gl import MeshRenderer
    from common.proposals import voxel_starts
    from common.search import SEARCH_HOPS, search_frame

    p = rest_params(model, position=(0.1, -0.2, 0.9), heading=0.7)
    p[P["root_tilt_x"]], p[P["root_tilt_y"]] = 2.4, 0.5  # head down, leaning
    p[P["l_shoulder_y"]], p[P["r_shoulder_y"]] = 1.9, -1.9  # arms spread overhead
    p[P["l_hip_y"]], p[P["r_hip_y"]] = 0.6, -0.6  # legs in a V
    p[P["l_knee"]] = 0.5
    studio = circle_studio(6, 240, 180)
    pose = forward_kinematics(model, p)
    labels = MeshRenderer(studio, model.triangles, model.triangle_segment).render_labels(skinned_vertices(model, pose))
    data = FrameData(model, studio, np.array([label >= 0 for label in labels]))
    options = FitOptions()
    found = search_frame(model, data, voxel_starts(model, data), options, solve_locally(model, data, options))
    error_mm = np.linalg.norm(forward_kinematics(model, found.params).joints[0] - pose.joints[0], axis=1) * 1000
    assert error_mm.mean() < 50.0, dict(zip(JOINT_NAMES, error_mm.round()))
    assert sum(c.chain in HOP_JOBS for c in found.chains) >= SEARCH_HOPS  # the search ends with hops


@pytest.mark.timeout(300)
def test_a_starts_stage_keeps_the_start_that_explains_the_images(model, five_frames):
    """One start 0.6 m beside the actor, one near the truth: the near one wins, and both
    starts' solves are counted."""
    from common.sequence import load_sequence

    seq = load_sequence(five_frames)
    frame = seq.frames[0]
    data = FrameData(model, seq.studio, seq.silhouettes(frame))
    truth = seq.truth()[frame]
    aside = truth.params.copy()
    aside[0] += 0.6
    near = truth.params.copy()
    near[0] += 0.03
    options = FitOptions(turn_hypotheses=0)
    alone = one_stage(model, data, Stage(("starts",)), starts=(near,), options=options)
    both = one_stage(model, data, Stage(("starts",)), starts=(aside, near), options=options)
    assert both.energy <= alone.energy
    assert joint_errors_mm(model, both.params, truth).mean() < 20.0
    assert both.evaluations > alone.evaluations


def test_the_search_loop_refits_the_lowest_few_and_stops_when_a_round_gains_too_little(monkeypatch):
    """The search loop with fits faked (a pose is one number; fitting b lands on FIT[b], the
    "every" variant 5 lower in energy): the beam proposes from its lowest fits, each under the
    variant it was fitted with; a stage stops after a round that gains less than ``min_gain``; a
    start fitted once under a variant is not fitted again; every fit is counted; the lowest is
    kept, the first on a tie."""
    from common import search
    from common.fitting import FrameResult

    FIT = {2: 12, 0: 10, 3: 13, 1: 11, 10: 20, 20: 20}
    ENERGY = {12: 120, 10: 100, 13: 130, 11: 110, 20: 90}
    fitted = []

    def fake_fit_starts(ctx, jobs, *_):
        fitted.extend((int(start[0]), variant) for start, variant in jobs)
        return [FrameResult(np.array([float(FIT[int(start[0])])]),
                            ENERGY[FIT[int(start[0])]] - 5 * (variant == "every"), 1, 1, variant=variant)
                for start, variant in jobs]

    monkeypatch.setattr(search, "fit_starts", fake_fit_starts)
    ctx = Context(None, None, FitOptions(), None, starts=tuple(np.array([b]) for b in (2, 0, 3, 1)))
    schedule = Schedule((Stage(("starts",), ("track", "every")),
                         Stage(("again",), None, rounds=3, min_gain=0.01, beam=2),
                         Stage(("starts",), ("track",))))  # fitted already: nothing to do
    found = run_schedule(ctx, schedule)
    assert fitted == [(b, v) for b in (2, 0, 3, 1) for v in ("track", "every")] + [
        (10, "every"), (10, "track"),  # round 1: the two lowest (10 every: 95, 10 track: 100), 95 -> 85
        (20, "every"), (20, "track")]  # round 2: 85 stays 85, so no round 3
    assert (found.params[0], found.energy, found.variant, found.evaluations) == (20, 85, "every", 12)
    # a budget spent: no further round starts (the starts' 8 evaluations spend a budget of 8)
    fitted.clear()
    found = run_schedule(ctx, Schedule(schedule.stages, budget=8))
    assert len(fitted) == 8 and found.evaluations == 8 and found.energy == 95


def test_which_limbs_are_redetected_when():
    from common.fitting import redetects

    def limbs(turn, iteration):
        return [c for c in LIMB_CHAINS if redetects(turn, c, iteration)]

    # tracking: in a round of its own after the fit, never within a fitting round
    assert [limbs("final", it) for it in range(3)] == [[], [], []]
    # first frames: one limb per round, or all of them in the first round
    assert [limbs("round", it) for it in range(5)] == [[c] for c in LIMB_CHAINS] + [[LIMB_CHAINS[0]]]
    assert limbs("all", 0) == list(LIMB_CHAINS) and limbs("all", 1) == []
    # a frame whose energy jumped while tracking: every limb, in the first round
    assert limbs("every", 0) == list(LIMB_CHAINS) and limbs("every", 1) == []
    with pytest.raises(ValueError, match="redetect_turn"):
        FitOptions(redetect_turn="sometimes")


@pytest.mark.timeout(120)
def test_a_frame_fitted_with_its_legs_swapped_is_put_right(model, five_frames):
    """A stride fitted from the truth with the legs swapped stays swapped (measured: 97 mm
    mean, 483 mm worst joint): neither leg alone can take the other's place. Fitted again
    from the legs swapped back, as a searched frame is, it is within 15 mm."""
    from common.body import swap_sides
    from common.sequence import load_sequence

    seq = load_sequence(five_frames)
    frame = seq.frames[2]
    truth = seq.truth()[frame]
    data = FrameData(model, seq.studio, seq.silhouettes(frame))
    options = FitOptions()
    swapped = fit_frame(model, data, swap_sides(truth.params, "leg"), options)
    assert joint_errors_mm(model, swapped.params, truth).max() > 200.0
    best = one_stage(model, data, Stage(("swaps",)), swapped)  # legs swapped, arms swapped
    assert best.energy < swapped.energy and joint_errors_mm(model, best.params, truth).mean() < 15.0


def test_rotated_about_pelvis_carries_the_whole_body_about_the_pelvis_axes(model, frames):
    from common.body import rotvec_to_matrix
    from common.proposals import rotated_about_pelvis, turned

    _, truth = frames
    x = truth[2].params.copy()
    x[P["root_heading"]] += 4.0 * np.pi  # a heading far from (-pi, pi] stays where it was
    x[P["root_tilt_x"]], x[P["root_tilt_y"]] = 0.4, -0.3
    before = forward_kinematics(model, x)
    for axis in range(3):
        y = rotated_about_pelvis(model, x, axis, 0.5)
        after = forward_kinematics(model, y)
        turn = before.rotations[0, 0] @ rotvec_to_matrix(0.5 * np.eye(3)[axis]) @ before.rotations[0, 0].T
        np.testing.assert_allclose(after.rotations[0], turn @ before.rotations[0], atol=1e-12)  # every segment
        np.testing.assert_allclose(after.joints[0, 0], before.joints[0, 0], atol=1e-12)  # about the root joint
        assert abs(y[P["root_heading"]] - x[P["root_heading"]]) < np.pi
        root_rotation = [P["root_heading"], P["root_tilt_x"], P["root_tilt_y"]]
        np.testing.assert_array_equal(np.delete(y, root_rotation), np.delete(x, root_rotation))
    upright = truth[2].params.copy()
    upright[P["root_tilt_x"]] = upright[P["root_tilt_y"]] = 0.0  # the spine vertical: a turn about it is a turn
    np.testing.assert_allclose(rotated_about_pelvis(model, upright, 2, 0.3), turned(upright, 0.3), atol=1e-12)


def test_a_pelvis_twisted_alone_leaves_the_chest_and_the_legs_as_they_were(model, frames):
    from common.body import rotvec_to_matrix
    from common.proposals import pelvis_twisted

    _, truth = frames
    x = truth[2].params.copy()
    x[P["root_tilt_x"]], x[P["root_tilt_y"]] = 0.2, -0.1
    before = forward_kinematics(model, x)
    y = pelvis_twisted(model, x, 0.2)
    after = forward_kinematics(model, y)
    assert y[P["root_heading"]] == pytest.approx(x[P["root_heading"]] + 0.2)
    np.testing.assert_allclose(after.rotations[0, 0], rotvec_to_matrix(np.array([0.0, 0.0, 0.2])) @ before.rotations[0, 0],
                               atol=1e-12)
    chest_and_beyond = [s for s in range(16) if s not in (0, 1)]  # all but the pelvis and the abdomen
    np.testing.assert_allclose(after.rotations[0, chest_and_beyond], before.rotations[0, chest_and_beyond], atol=1e-9)
    np.testing.assert_array_equal(y[P["root_x"]:P["root_z"] + 1], x[P["root_x"]:P["root_z"] + 1])
    assert not np.allclose(after.rotations[0, 0], before.rotations[0, 0])


@pytest.mark.timeout(300)
def test_a_hops_best_has_its_pelvis_turned_back(model, frames, monkeypatch):
    """Refinement with hops (a pass's first frame) ends by turning the hops' best and turning its
    pelvis alone (``AFTER_HOPS``), as the fits before the hops were: a fit with the pelvis
    turned 0.15 rad off, the hips turned back, comes back to the truth's heading."""
    from common import search
    from common.fitting import FrameResult
    from common.proposals import pelvis_twisted

    data, truth = frames
    x = truth[2].params
    twisted = pelvis_twisted(model, x, 0.15)
    hop = FrameResult(twisted, full_energy(model, data[2], twisted), 1, 0)
    again = one_stage(model, data[2], search.AFTER_HOPS.stages, fit=hop)
    assert again.energy < hop.energy
    assert abs(again.params[P["root_heading"]] - x[P["root_heading"]]) < 0.05

    schedules = []
    monkeypatch.setattr(search, "run_schedule", lambda ctx, schedule, initial: schedules.append(schedule) or initial)
    for hops in (0, 1):
        search.refine_frame(model, data[2], hop, FitOptions(), None, None, None, None, hops)
    after = len(search.AFTER_HOPS.stages)
    assert schedules[0].stages == search.REFINE.stages and schedules[1].stages[-after:] == search.AFTER_HOPS.stages


@pytest.mark.timeout(300)
def test_a_body_rotated_off_the_truth_is_rotated_back(model, five_frames):
    """Frame 2 fitted from its true pose leaned 0.6 rad forward about the pelvis, limbs carried
    along, stays leaned (measured: 27 mm mean): the torso alone and each limb alone fit
    well where they are. The rotated fits of a search take it back within 15 mm (measured: 10 mm)."""
    from common.proposals import rotated_about_pelvis
    from common.sequence import load_sequence

    seq = load_sequence(five_frames)
    frame = seq.frames[2]
    truth = seq.truth()[frame]
    data = FrameData(model, seq.studio, seq.silhouettes(frame))
    options = FitOptions()
    leaned = fit_frame(model, data, rotated_about_pelvis(model, truth.params, 0, 0.6), options)
    assert joint_errors_mm(model, leaned.params, truth).mean() > 20.0
    found = one_stage(model, data, (Stage(("rotations",), ("deep",), rounds=3), *POLISHED), leaned)
    assert joint_errors_mm(model, found.params, truth).mean() < 15.0
    assert found.energy < leaned.energy


def test_ctrl_c_inside_a_compiled_loop_says_interrupted(small_sequence, tmp_path, monkeypatch, capsys):
    """Ctrl-C while a numba loop runs reaches Python as a SystemError ("returned a result with
    an exception set") whose context is the KeyboardInterrupt: one line and exit 130, as any
    Ctrl-C; a SystemError of another cause is not hidden."""
    import server.commands.fit as fit_command

    def stopped(args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("CPUDispatcher(<function _powell>) returned a result with an exception set")

    monkeypatch.setattr(fit_command, "run", stopped)
    assert fit(small_sequence, tmp_path / "r") == 130
    assert capsys.readouterr().err.strip() == ("mocap fit: interrupted; stopped before its first frame was fitted; "
                                               f"nothing is in {tmp_path / 'r'}")
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "poses.jsonl").write_text('{"frame": 0}\n')  # a frame written before the stop
    assert fit(small_sequence, tmp_path / "r") == 130
    assert capsys.readouterr().err.strip() == (f"mocap fit: interrupted; the frames fitted are kept in {tmp_path / 'r'}, "
                                               "and the same command with --resume continues")

    def broken(args):
        raise SystemError("something else")

    monkeypatch.setattr(fit_command, "run", broken)
    with pytest.raises(SystemError, match="something else"):
        fit(small_sequence, tmp_path / "r")


@pytest.mark.parametrize("scale, edge", [(1.4, "largest"), (0.9, "smallest"), (1.2, None)])
def test_a_size_at_the_search_s_end_is_warned(model, small_loaded, tmp_path, monkeypatch, capsys, scale, edge):
    """The size search ends at its range's edges: a size chosen there may be cut short (the
    seated take's 1.4), and the user is told what can cause it and how to set the size."""
    import argparse

    import server.commands.fit as fit_command
    from server.session import ACTOR_SCALES, ActorSize

    assert (ACTOR_SCALES[0], ACTOR_SCALES[-1]) == (0.9, 1.4)
    monkeypatch.setattr(fit_command, "choose_actor_scale", lambda *a: ActorSize(scale, 0, (), {}, 0.0))
    args = argparse.Namespace(actor_height="auto", resume=False, threads=1, out=tmp_path / "r")
    actor, size = fit_command.actor_model(model, small_loaded, FitOptions(), args, "auto")
    assert size.scale == scale and actor.height == pytest.approx(model.height * scale)
    err = capsys.readouterr().err
    if edge is None:
        assert err == ""
    else:
        assert err.count("\n") == 1 and f"actor size {scale:.2f} is the {edge} the size search tries" in err
        assert "--actor-height" in err and "calib show" in err


@pytest.mark.parametrize("scale", [1.4, 0.9, 1.75 / 1.66])
def test_a_resumed_run_rebuilds_the_same_actor(model, tmp_path, scale):
    """run.json records the actor's size as the factor it was scaled by, so that --resume builds
    the very same model: its height over the model's differed in the 8th digit, and a resumed
    fit of the seated take (size 1.4) came out up to 26 mm from the same run left alone."""
    import argparse

    import server.commands.fit as fit_command
    from server.session import model_scale

    actor = model.scaled(scale)
    out = tmp_path / "r"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"actor_scale": model_scale(actor)}))
    args = argparse.Namespace(actor_height="auto", resume=True, threads=1, out=out)
    again, _ = fit_command.actor_model(model, None, FitOptions(), args, "auto")
    np.testing.assert_array_equal(again.ellipsoid_radii, actor.ellipsoid_radii)
    np.testing.assert_array_equal(again.joint_rest, actor.joint_rest)


def test_chain_totals_compare_each_solve_with_itself():
    """A chain's solves in a frame report energies of different windows (a limb's 128x128
    window, a re-detection's whole images): the record sums each side, so after never exceeds
    before where every solve gained (first-before against last-after read a window's 8,904
    against the whole images' 23,764)."""
    from common.fitting import ChainResult
    from server.session import chain_totals

    x = np.zeros(35)
    solves = [ChainResult("left_arm", x, 8904, 8800, 40, 2, 0.01, 0.01),      # its window
              ChainResult("left_arm", x, 8790, 8790, 30, 1, 0.01, 0.01),      # its window, moved on
              ChainResult("left_arm", x, 23790, 23764, 90, 0, 0.02, 0.02),    # re-detected: whole images
              ChainResult("right_leg", x, 5000, 4900, 10, 1, 0.005, 0.004)]
    totals = chain_totals(solves)
    assert totals["left_arm"]["energy_before"] == 8904 + 8790 + 23790
    assert totals["left_arm"]["energy"] == 8800 + 8790 + 23764
    assert totals["left_arm"]["evaluations"] == 160 and totals["right_leg"]["energy"] == 4900
    assert all(t["energy"] <= t["energy_before"] for t in totals.values())


@pytest.mark.timeout(30)
def test_a_record_put_back_as_tracked_has_trackings_energy():
    """A fit resumed after its refinement was written starts again from tracking's records: a
    record whose energy was taken again against cleared masks (``leave_out_unexplained``) gets
    tracking's back, and a fit that replaces it keeps tracking's energy as its first pass."""
    from server.session import tracked_record, tracking_fit

    x = [0.0] * PARAM_COUNT
    record = {"frame": 3, "params": x, "joints": {}, "energy": 900, "tracked_energy": 1200,
              "fit_quality": {"xor_share": [0.1]}}
    assert tracked_record(record) == {"frame": 3, "params": x, "joints": {}, "energy": 1200}
    assert tracking_fit(record)["energy"] == 1200
    replaced = record | {"params": [1.0] * PARAM_COUNT, "energy": 800, "first_pass": tracking_fit(record)}
    assert tracked_record(replaced) == {"frame": 3, "params": x, "joints": {}, "energy": 1200}
