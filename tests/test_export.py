"""Exports of fitted motion: BVH, C3D, TRC, JSON lines, CSV, read back to the same joints; mocap export."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from common.body import (
    JOINT_NAMES, P, PARAM_NAMES, SEGMENT_NAMES, clip_to_limits, forward_kinematics, joints_dict,
    load_body_model, rest_params,
)
from common.bvh import read_bvh
from common.errors import UserError
from common.export import (
    BVH_JOINT_NAMES, BVH_UNITS_PER_M, FORMATS, SUFFIXES, TO_BVH, TO_OPENSIM, FittedMotion,
    actor_from_joints, bvh_to_world_joints, export_motion, params_to_bvh,
)
from server.cli import main as cli_main

ROUND_TRIP_M = 1e-4  # the bar for BVH and C3D round trips
FPS = 25.0
FRAMES = 48


def motion_params(model, frames: int = FRAMES, seed: int = 0) -> np.ndarray:
    """(F, 35) smooth, demanding motion: a walk forward while spinning 1.5 turns, wide limb swings."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, frames)[:, None]
    base = rest_params(model)
    amp = rng.uniform(-1.0, 1.0, (1, 35)) * 1.2
    phase = rng.uniform(0, 2 * np.pi, (1, 35))
    p = base + amp * np.sin(2 * np.pi * t * 1.5 + phase)
    p[:, 0] = 0.8 * t[:, 0]
    p[:, 1] = -0.5 + 0.3 * np.sin(3 * t[:, 0])
    p[:, 2] = base[2] + 0.05 * np.sin(8 * t[:, 0])
    p[:, P["root_tilt_x"]:P["root_tilt_y"] + 1] *= 0.2  # leaning, not cartwheels
    p[:, P["root_heading"]] = 3.0 * np.pi * t[:, 0]      # 1.5 turns: Euler angles must not jump
    p[:, P["l_shoulder_x"]] = 2.4 * np.sin(2 * np.pi * t[:, 0])  # through large rotations
    return clip_to_limits(p)


def records_for(model, params: np.ndarray, first_frame: int = 10) -> list[dict]:
    joints = forward_kinematics(model, params).joints
    return [{"frame": first_frame + i, "params": [float(v) for v in params[i]], "joints": joints_dict(joints[i]),
             "energy": 1000 + i, "seconds": 0.1} for i in range(len(params))]


@pytest.fixture(scope="module")
def motion() -> FittedMotion:
    model = load_body_model()
    return FittedMotion.from_records(records_for(model, motion_params(model)), FPS)


@pytest.fixture(scope="module")
def result_dir(tmp_path_factory, motion) -> Path:
    """A result folder without a sequence (so the frame rate must be given)."""
    d = tmp_path_factory.mktemp("result")
    model = load_body_model()
    with open(d / "poses.jsonl", "w") as fh:
        for r in records_for(model, motion.params):
            fh.write(json.dumps(r) + "\n")
    (d / "summary.json").write_text(json.dumps({"sequence": str(d / "gone"), "frames": len(motion.frames)}))
    return d


# ------------------------------------------------------------------------------------- BVH

def test_bvh_round_trip_through_our_reader(tmp_path, motion):
    path = export_motion("bvh", tmp_path / "m.bvh", motion)
    bvh = read_bvh(path)
    assert bvh.names == BVH_JOINT_NAMES
    assert bvh.num_frames == FRAMES
    assert bvh.frame_time == pytest.approx(1.0 / FPS, abs=1e-12)
    assert bvh.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    assert len(bvh.end_site_parents) == 5  # head top, hands, feet
    err = np.abs(bvh_to_world_joints(bvh) - motion.joints).max()
    assert err < ROUND_TRIP_M, err


def test_bvh_round_trip_through_bvhio(tmp_path, motion):
    """An independent parser (bvhio, PyPI) reads the same joint positions, End Site included."""
    bvhio = pytest.importorskip("bvhio")
    path = export_motion("bvh", tmp_path / "m.bvh", motion)
    root = bvhio.readAsHierarchy(str(path))
    by_name = {j.Name: j for j, _, _ in root.layout()}
    assert set(by_name) == set(BVH_JOINT_NAMES)
    raw = bvhio.readAsBvh(str(path))
    head_end = next(j for j, _, _ in raw.Root.layout() if j.Name == "Head").EndSite  # BVH frame
    head = by_name["Head"]
    root.loadRestPose()
    # bvhio aligns its joint frames with the bones; the BVH frame is the world rotation
    # relative to the rest pose (where every BVH rotation is the identity)
    rest_inverse = head.RotationWorldInverse
    got = np.empty((FRAMES, 17, 3))
    names = BVH_JOINT_NAMES[:4] + BVH_JOINT_NAMES[5:]  # segment joints, in JOINT_NAMES order
    for f in range(FRAMES):
        root.loadPose(f)
        for j, n in enumerate(names):
            got[f, j] = np.array(by_name[n].PositionWorld)
        got[f, 16] = np.array(head.PositionWorld) + np.array(head.RotationWorld * rest_inverse * head_end)
    world = (got @ TO_BVH) / BVH_UNITS_PER_M
    err = np.abs(world - motion.joints).max()
    assert err < ROUND_TRIP_M, err


def test_bvh_axes_offsets_and_continuity(motion):
    """Y up, facing +Z, cm; offsets are the actor's segments; Euler curves without jumps."""
    model = motion.model
    bvh = params_to_bvh(model, motion.params, 1.0 / FPS)
    # rest skeleton: the head is above the hips (Y), the toes point forward (+Z), left is +X
    from common.bvh import rest_positions

    rest, ends = rest_positions(bvh)
    assert ends[0, 1] > rest[0, 1] + 50.0                      # head top about 60 cm above the hips
    assert rest[BVH_JOINT_NAMES.index("LeftUpLeg"), 0] > 0 > rest[BVH_JOINT_NAMES.index("RightUpLeg"), 0]
    foot_tip = ends[list(bvh.end_site_parents).index(BVH_JOINT_NAMES.index("LeftFoot"))]
    assert foot_tip[2] > rest[BVH_JOINT_NAMES.index("LeftFoot"), 2]
    # offsets = the actor's segment vectors, cm
    knee = BVH_JOINT_NAMES.index("LeftLeg")  # the shin's joint: offset = hip -> knee
    expected = TO_BVH @ model.offsets[SEGMENT_NAMES.index("l_shin")] * BVH_UNITS_PER_M
    np.testing.assert_allclose(bvh.offsets[knee], expected, atol=1e-9)
    # the root position channels are the pelvis in BVH axes
    np.testing.assert_allclose(bvh.values[:, :3], motion.joints[:, 0] @ TO_BVH.T * BVH_UNITS_PER_M, atol=1e-9)
    # spinning 1.5 turns and swinging wide: no rotation channel wraps by 360 degrees or flips to
    # the other Euler triple between frames (per-frame changes here are below 25 degrees, except
    # fast ones near gimbal lock)
    jumps = np.abs(np.diff(bvh.values[:, 3:], axis=0)).max()
    assert jumps < 120.0, jumps
    # the heading turns about BVH Y (the root's third rotation channel) through 540 degrees, unwrapped
    assert np.ptp(bvh.values[:, 5]) > 500.0


def test_bvh_roles_map_for_our_own_importer(tmp_path, motion):
    """Our BVH importer (which drives synthetic studios) recognises every role in the export."""
    from common.skeleton_map import joint_label, map_skeleton

    path = export_motion("bvh", tmp_path / "m.bvh", motion)
    bvh = read_bvh(path)
    labels = {r: joint_label(bvh, i) for r, i in map_skeleton(bvh).items()}
    assert labels["pelvis"] == "Hips" and labels["neck"] == "Neck" and labels["head"] == "Head"
    assert labels["l_wrist"] == "LeftHand" and labels["r_ankle"] == "RightFoot"
    assert labels["spine_upper"] == "Chest" and labels["head_end"] == "Head/end"


def test_actor_segment_lengths_come_from_the_result():
    """A bigger actor, and one with a longer left shin: offsets follow the recorded joints."""
    base = load_body_model()
    params = motion_params(base, frames=6)
    big = base.scaled(1.1)
    recs = records_for(big, params)
    m = FittedMotion.from_records(recs, FPS)
    assert m.model.height == pytest.approx(big.height, rel=1e-9)
    np.testing.assert_allclose(m.model.offsets, big.offsets, atol=1e-12)

    shin = SEGMENT_NAMES.index("l_shin")
    assert actor_from_joints(base, params, forward_kinematics(base, params).joints) is base
    jr = base.joint_rest.copy()
    jr[[12]] += 0.04 * (jr[12] - jr[11]) / np.linalg.norm(jr[12] - jr[11])  # ankle 4 cm lower
    from dataclasses import replace

    stretched = replace(base, joint_rest=jr)
    got = actor_from_joints(base, params, forward_kinematics(stretched, params).joints)
    assert np.linalg.norm(got.offsets[shin]) == pytest.approx(np.linalg.norm(stretched.offsets[shin]), abs=1e-9)
    bvh = params_to_bvh(got, params, 1.0 / FPS)
    np.testing.assert_allclose(bvh_to_world_joints(bvh), forward_kinematics(stretched, params).joints, atol=1e-6)


def test_joints_that_no_body_model_explains_are_refused():
    base = load_body_model()
    params = motion_params(base, frames=4)
    recs = records_for(base, params)
    recs[2]["joints"]["l_elbow"][0] += 0.01
    with pytest.raises(UserError, match="another body model"):
        FittedMotion.from_records(recs, FPS)
    with pytest.raises(UserError, match="no fitted frames"):
        FittedMotion.from_records([], FPS)
    with pytest.raises(UserError, match="frame rate"):
        FittedMotion.from_records(records_for(base, params), 0.0)


# ------------------------------------------------------------------------ joint positions

@pytest.mark.filterwarnings("ignore:No analog data")
def test_c3d_round_trip(tmp_path, motion):
    c3d = pytest.importorskip("c3d")
    path = export_motion("c3d", tmp_path / "m.c3d", motion)
    with open(path, "rb") as fh:
        reader = c3d.Reader(fh)
        assert reader.point_rate == pytest.approx(FPS)
        assert reader.get("POINT:UNITS").string_value.strip() == "mm"
        assert [label.strip() for label in reader.point_labels] == list(JOINT_NAMES)
        assert reader.get("POINT:Y_SCREEN").string_value.strip() == "+Z"
        frames = [points for _, points, _ in reader.read_frames()]
    pts = np.array(frames)
    assert pts.shape == (FRAMES, len(JOINT_NAMES), 5)
    assert np.all(pts[:, :, 3] >= 0)  # every point valid
    err = np.abs(pts[:, :, :3] / 1000.0 - motion.joints).max()
    assert err < ROUND_TRIP_M, err


def read_trc(path: Path) -> tuple[dict, list[str], np.ndarray, np.ndarray]:
    """A TRC file -> header {key: value}, marker names, times (F,), points (F, M, 3)."""
    lines = path.read_text().splitlines()
    header = dict(zip(lines[1].split("\t"), lines[2].split("\t")))
    names = [n for n in lines[3].split("\t")[2:] if n]
    rows = [line.split("\t") for line in lines[6:] if line.strip()]
    times = np.array([float(r[1]) for r in rows])
    pts = np.array([[float(v) for v in r[2:]] for r in rows]).reshape(len(rows), len(names), 3)
    return header, names, times, pts


def test_trc_for_opensim(tmp_path, motion):
    path = export_motion("trc", tmp_path / "m.trc", motion)
    header, names, times, pts = read_trc(path)
    assert header["DataRate"] == "25" and header["Units"] == "mm"
    assert int(header["NumFrames"]) == FRAMES and int(header["NumMarkers"]) == len(JOINT_NAMES)
    assert names == list(JOINT_NAMES)
    np.testing.assert_allclose(times, np.arange(FRAMES) / FPS, atol=1e-6)
    world = (pts / 1000.0) @ TO_OPENSIM  # inverse of a rotation: its transpose
    assert np.abs(world - motion.joints).max() < ROUND_TRIP_M
    head, pelvis = JOINT_NAMES.index("head_top"), JOINT_NAMES.index("pelvis")
    assert np.all(pts[:, head, 1] > pts[:, pelvis, 1])  # OpenSim: Y up


def test_json_lines_and_csv(tmp_path, motion):
    jl = export_motion("json", tmp_path / "m.jsonl", motion)
    docs = [json.loads(line) for line in jl.read_text().splitlines()]
    assert [d["frame"] for d in docs] == motion.frames.tolist()
    assert docs[1]["time"] == pytest.approx(1.0 / FPS)
    np.testing.assert_array_equal(np.array([d["params"] for d in docs]), motion.params)
    np.testing.assert_array_equal(np.array([[d["joints"][n] for n in JOINT_NAMES] for d in docs]), motion.joints)

    path = export_motion("csv", tmp_path / "m.csv", motion)
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head = rows[0]
    assert head[:4] == ["frame", "time_s", "pelvis_x_m", "pelvis_y_m"] and head[-35:] == list(PARAM_NAMES)
    data = np.array(rows[1:], dtype=np.float64)
    np.testing.assert_array_equal(data[:, 2:2 + 51].reshape(-1, 17, 3), motion.joints)
    np.testing.assert_array_equal(data[:, -35:], motion.params)


def test_unknown_format_is_a_user_error(tmp_path, motion):
    with pytest.raises(UserError, match="unknown export format"):
        export_motion("fbx", tmp_path / "m.fbx", motion)


# -------------------------------------------------------------------------------- mocap export

def test_mocap_export_all_formats_json(tmp_path, result_dir, capsys):
    out = tmp_path / "exports"
    assert cli_main(["export", str(result_dir), "--format", "all", "--out", str(out), "--fps", "25", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [d["format"] for d in doc] == list(FORMATS)
    for d in doc:
        assert Path(d["path"]) == out / f"motion{SUFFIXES[d['format']]}"
        assert Path(d["path"]).stat().st_size == d["bytes"] > 0
        assert d["frames"] == FRAMES and d["fps"] == 25.0


def test_mocap_export_one_format_quiet_and_default_path(result_dir, capsys):
    assert cli_main(["export", str(result_dir), "--format", "trc", "--fps", "30", "--quiet"]) == 0
    assert capsys.readouterr().out == ""
    header, *_ = read_trc(result_dir / "motion.trc")
    assert header["DataRate"] == "30"
    assert cli_main(["export", str(result_dir), "--format", "bvh", "--fps", "30"]) == 0
    assert "motion.bvh (bvh, 48 frames at 30 fps)" in capsys.readouterr().out


def test_mocap_export_errors(tmp_path, result_dir, capsys):
    # the sequence named in summary.json is gone: the frame rate must come from --fps
    assert cli_main(["export", str(result_dir), "--format", "bvh"]) == 2
    assert "--fps" in capsys.readouterr().err
    assert cli_main(["export", str(tmp_path / "nothing"), "--format", "bvh", "--fps", "30"]) == 2
    assert "not a result folder" in capsys.readouterr().err
    assert cli_main(["export", str(result_dir), "--format", "c3d", "--fps", "-1"]) == 2
    assert cli_main(["export", str(result_dir), "--format", "csv", "--fps", "30",
                     "--out", str(tmp_path / "no" / "such" / "m.csv")]) == 2
    assert "does not exist" in capsys.readouterr().err
