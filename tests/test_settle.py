"""Settling a take (common.settle, server.session.settle_records): a still actor's frames take
one pose where the masks did not move; a moving actor's frames keep their own fits."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from common.body import JOINT_NAMES, P, forward_kinematics
from common.fitting import FrameData, full_energy
from common.scoring import frame_quality
from common.settle import MIN_CHANGE, candidate_frames, mask_step, settle_choice


def test_candidates_are_the_frames_within_reach():
    c = candidate_frames(4, reach=2)
    assert c.shape == (4, 5)
    assert c[0].tolist() == [-1, -1, 0, 1, 2]
    assert c[3].tolist() == [1, 2, 3, -1, -1]
    assert (c[:, 2] == np.arange(4)).all()  # the middle column: each frame's own fit


def test_mask_step_is_the_differing_share_of_the_silhouettes_and_their_mean_area():
    a = np.zeros((2, 4, 4), dtype=bool)
    a[:, :2] = True                      # 16 pixels
    b = a.copy()
    assert mask_step(a, b) == (0.0, 16.0)
    b[0, 0] = False                      # 4 pixels off
    assert mask_step(a, b) == (pytest.approx(4 / 14), 14.0)
    assert mask_step(a, ~a)[0] == pytest.approx(2.0)


AREA = 20_000.0   # silhouette pixels: 8 cameras of 320x240


def _two_poses_take(T: int, change: float, lower: np.ndarray):
    """Frames whose fits alternate between pose A (even frames) and pose B 20 mm away (odd);
    frame t's energy of A is 1,000 and of B 1,000 - lower[t]."""
    joints = np.zeros((T, 3, 3))
    joints[1::2, :, 0] = 0.020
    cand = candidate_frames(T, reach=3)
    is_b = (cand % 2 == 1)
    energies = np.where(cand >= 0, 1000.0 - np.where(is_b, lower[:, None], 0.0), np.inf)
    return energies, joints, cand, np.full(T - 1, change), np.full(T - 1, AREA)


def test_a_still_take_settles_on_the_pose_lowest_over_the_take():
    """The masks barely change (1%): frames keep jumping between two poses 20 mm apart, each
    taking the one its own noise favours; settled, every frame takes the one lowest over all."""
    rng = np.random.default_rng(0)
    lower = rng.normal(0.0, 2.0, 12) + 0.5   # B is lower on most frames, by a few pixels
    energies, joints, cand, change, area = _two_poses_take(12, 0.01, lower)
    chosen = cand[np.arange(12), settle_choice(energies, joints, cand, change, area)]
    assert (chosen % 2 == 1).all()          # B everywhere
    steps = np.linalg.norm(np.diff(joints[chosen], axis=0), axis=-1).mean(axis=-1)
    assert steps.max() == 0.0


def test_a_moving_take_keeps_each_frames_own_fit():
    """The masks change by a third between frames (an actor moving at 30 fps): a step of 20 mm
    costs 67 px here, less than the 300 px its masks hold against the other pose, so each frame keeps its own."""
    lower = np.where(np.arange(12) % 2 == 1, 300.0, -300.0)   # each frame's own pose lower by 300 px
    energies, joints, cand, change, area = _two_poses_take(12, 0.3, lower)
    chosen = cand[np.arange(12), settle_choice(energies, joints, cand, change, area)]
    assert ((chosen % 2) == np.arange(12) % 2).all()  # (frames 0 and 2 hold the same pose A: either)
    # the same take with still masks: one pose, since 20 mm now costs 2,000 px a step
    energies, joints, cand, change, area = _two_poses_take(12, 0.01, lower)
    chosen = cand[np.arange(12), settle_choice(energies, joints, cand, change, area)]
    assert len(set((chosen % 2).tolist())) == 1


def test_the_step_cost_scales_with_the_silhouette_area_as_the_energy_does():
    """The same take in images of a quarter of the pixels (energies and areas a quarter):
    the same choice. (A cost in pixels alone held a moving 160x120 take on one pose.)"""
    lower = np.where(np.arange(12) % 2 == 1, 300.0, -300.0)
    energies, joints, cand, change, area = _two_poses_take(12, 0.3, lower)
    full = settle_choice(energies, joints, cand, change, area)
    quarter = settle_choice(energies / 4.0, joints, cand, change, area / 4.0)
    assert (cand[np.arange(12), full] % 2 == np.arange(12) % 2).all()
    assert (cand[np.arange(12), quarter] % 2 == np.arange(12) % 2).all()


def test_identical_masks_count_as_a_small_change_not_a_division_by_zero():
    energies, joints, cand, change, area = _two_poses_take(6, 0.0, np.full(6, 1.0))
    chosen = cand[np.arange(6), settle_choice(energies, joints, cand, change, area)]
    assert (chosen % 2 == 1).all() and MIN_CHANGE > 0


def _records(model, seq, params_per_frame):
    from server.session import frame_data, user_joints

    return [{"frame": int(f), "params": [float(v) for v in p], "joints": user_joints(model, seq, p),
             "energy": full_energy(model, frame_data(model, seq, f), p)}
            for f, p in zip(seq.frames, params_per_frame)]


@pytest.mark.timeout(120)
def test_settle_records_gives_a_still_takes_worse_frame_its_neighbours_pose(model, small_sequence, tmp_path):
    """Three frames of one still pose (the first frame's masks copied to the others), the middle
    one fitted with its arm 0.1 rad off: it takes its neighbour's pose, names the frame, keeps
    its own fit under "first_pass" and has the new pose's energy."""
    from common.sequence import load_sequence
    from server.session import settle_records

    still = tmp_path / "still"
    shutil.copytree(small_sequence, still)
    for cam_dir in (still / "silhouettes").iterdir():
        files = sorted(cam_dir.iterdir())
        for f in files[1:]:
            shutil.copyfile(files[0], f)
    seq = load_sequence(still)
    truth = seq.truth()[seq.frames[0]].params
    off = truth.copy()
    off[P["l_shoulder_x"]] += 0.1
    records = _records(model, seq, [truth, off, truth])
    assert records[1]["energy"] > records[0]["energy"]
    settled, moved, quality = settle_records(model, seq, records)
    assert moved == 1
    assert settled[1]["params"] == records[0]["params"] and settled[1]["settled_from"] in (seq.frames[0], seq.frames[2])
    assert settled[1]["first_pass"] == {k: records[1][k] for k in ("params", "joints", "energy")}
    data = FrameData(model, seq.studio, seq.silhouettes(seq.frames[1]))
    assert settled[1]["energy"] == full_energy(model, data, truth)
    assert settled[0] == records[0] and settled[2] == records[2]
    assert quality[1] == frame_quality(data, truth) and quality[0] == quality[1]  # same masks, same pose
    assert np.allclose([settled[1]["joints"][n] for n in JOINT_NAMES], forward_kinematics(model, truth).joints[0])


@pytest.mark.timeout(120)
def test_settle_records_leaves_a_moving_takes_fits(model, small_loaded):
    """The walk's frames fitted at their truth: each truth explains its own masks best, and the
    masks moved, so no frame takes another's pose."""
    from server.session import settle_records

    seq, truth = small_loaded
    records = _records(model, seq, [truth[f].params for f in seq.frames])
    settled, moved, quality = settle_records(model, seq, records)
    assert moved == 0 and settled == records and len(quality) == len(records)
