"""Exports of fitted motion: glTF, BVH, C3D, OpenSim TRC and MOT, EasyMocap keypoints3d, JSON lines,
CSV, read back to the same joints; mocap export. (Blender, OpenSim and three.js themselves:
tools/interop_test.py, behind ``make interop-test``.)"""
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
from common.bvh import read_bvh, rest_positions
from common.errors import UserError
from common.world import world_frame
from common.export import (
    BODY25_NAMES, BVH_JOINT_NAMES, BVH_UNITS_PER_M, FORMATS, MOT_COLUMNS, SUFFIXES, TO_BVH, TO_OPENSIM,
    FittedMotion, actor_from_joints, bvh_to_world_joints, export_motion, params_to_bvh, sample_rate,
)
from server.results import frames_text
from common.export import frames_off_step
from server.cli import main as cli_main

pytestmark = pytest.mark.timeout(120)
ROUND_TRIP_M = 1e-4  # the bar for BVH and C3D round trips
INTEROP_M = 1e-3     # the bar for what Blender and viewers read from our GLB
FPS = 25.0
FRAMES = 48
# Pose2Sim's HALPE_26 skeleton (Pose2Sim/skeletons.py, perfanalytics/pose2sim): every marker name
HALPE_26 = ("Hip", "RHip", "RKnee", "RAnkle", "RBigToe", "RSmallToe", "RHeel", "LHip", "LKnee", "LAnkle",
            "LBigToe", "LSmallToe", "LHeel", "Neck", "Head", "Nose", "RShoulder", "RElbow", "RWrist",
            "LShoulder", "LElbow", "LWrist")
# EasyMocap's CONFIG['body25']['joint_names'] (easymocap/dataset/config.py, zju3dv/EasyMocap)
EASYMOCAP_BODY25 = ("Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip",
                    "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
                    "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel")


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


def records_for(model, params: np.ndarray, first_frame: int = 10, step: int = 1) -> list[dict]:
    joints = forward_kinematics(model, params).joints
    return [{"frame": first_frame + step * i, "params": [float(v) for v in params[i]], "joints": joints_dict(joints[i]),
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


def test_bvh_tpose_rest_moves_the_same(tmp_path, motion):
    """--rest tpose: arms straight out and legs straight down at rest, the same world joints in
    every frame as the A-pose file."""
    a = read_bvh(export_motion("bvh", tmp_path / "a.bvh", motion, bvh_rest="apose"))
    t = read_bvh(export_motion("bvh", tmp_path / "t.bvh", motion, bvh_rest="tpose"))
    assert t.names == a.names and t.num_frames == a.num_frames
    err = np.abs(bvh_to_world_joints(t) - bvh_to_world_joints(a)).max()
    assert err < 1e-6, err
    assert np.abs(bvh_to_world_joints(t) - motion.joints).max() < ROUND_TRIP_M
    rest, _ = rest_positions(t)  # BVH axes: y up, x to the actor's left
    idx = {n: i for i, n in enumerate(t.names)}
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        arm = rest[idx[f"{side}Hand"]] - rest[idx[f"{side}Arm"]]
        leg = rest[idx[f"{side}Foot"]] - rest[idx[f"{side}UpLeg"]]
        np.testing.assert_allclose(arm / np.linalg.norm(arm), [sign, 0.0, 0.0], atol=1e-9)
        np.testing.assert_allclose(leg / np.linalg.norm(leg), [0.0, -1.0, 0.0], atol=1e-9)
    arest, _ = rest_positions(a)
    np.testing.assert_allclose(rest[idx["Neck"]], arest[idx["Neck"]], atol=1e-9)  # the torso as it was
    with pytest.raises(UserError, match="rest pose"):
        export_motion("bvh", tmp_path / "x.bvh", motion, bvh_rest="sitting")


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


def test_trc_for_opensim_with_pose2sim_markers(tmp_path, motion):
    path = export_motion("trc", tmp_path / "m.trc", motion)
    header, names, times, pts = read_trc(path)
    assert header["DataRate"] == "25" and header["Units"] == "m"
    assert path.read_text().splitlines()[0].endswith("\tm.trc")
    assert set(names) <= set(HALPE_26) and len(names) == len(set(names)) == 15
    assert {"Nose", "RBigToe", "LHeel"}.isdisjoint(names)  # not fitted: left out, not made up
    assert int(header["NumFrames"]) == FRAMES and int(header["NumMarkers"]) == len(names)
    np.testing.assert_allclose(times, np.arange(FRAMES) / FPS, atol=1e-6)
    world = pts @ TO_OPENSIM  # inverse of a rotation: its transpose
    J = {n: motion.joints[:, i] for i, n in enumerate(JOINT_NAMES)}
    expected = {"RKnee": J["r_knee"], "LWrist": J["l_wrist"], "Head": J["head_top"],
                "Hip": 0.5 * (J["l_hip"] + J["r_hip"]), "Neck": 0.5 * (J["l_shoulder"] + J["r_shoulder"])}
    for name, want in expected.items():
        assert np.abs(world[:, names.index(name)] - want).max() < ROUND_TRIP_M, name
    assert np.all(pts[:, names.index("Head"), 1] > pts[:, names.index("Hip"), 1])  # OpenSim: Y up


def read_mot(path: Path) -> tuple[dict, list[str], np.ndarray]:
    """An OpenSim .mot -> header {key: value}, column labels, (F, C) values."""
    lines = path.read_text().splitlines()
    end = lines.index("endheader")
    header = dict(line.split("=", 1) for line in lines[1:end] if "=" in line)
    labels = lines[end + 1].split("\t")
    return header, labels, np.array([[float(v) for v in line.split("\t")] for line in lines[end + 2:]])


def test_mot_of_joint_angles_in_degrees(tmp_path, motion):
    path = export_motion("mot", tmp_path / "m.mot", motion)
    header, labels, table = read_mot(path)
    assert path.read_text().splitlines()[0] == "m"  # OpenSim: the table's name comes first
    assert header["version"] == "1" and header["inDegrees"] == "yes"
    assert int(header["nRows"]) == FRAMES and int(header["nColumns"]) == len(labels) == 36
    assert labels == ["time", *MOT_COLUMNS] and labels[4:] == list(PARAM_NAMES[3:])
    np.testing.assert_allclose(table[:, 0], np.arange(FRAMES) / FPS, atol=1e-6)
    np.testing.assert_allclose(np.radians(table[:, 4:]), motion.params[:, 3:], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(table[:, 1:4] @ TO_OPENSIM, motion.params[:, 0:3], rtol=1e-7, atol=1e-9)
    assert np.ptp(table[:, labels.index("root_heading")]) > 500.0  # 1.5 turns: degrees, unwrapped


def test_keypoints3d_for_easymocap(tmp_path, motion):
    folder = export_motion("keypoints3d", tmp_path / "kp", motion)
    files = sorted(folder.iterdir())
    assert [f.name for f in files] == [f"{int(f):06d}.json" for f in motion.frames]  # EasyMocap: frame number
    assert BODY25_NAMES == EASYMOCAP_BODY25
    doc = json.loads(files[3].read_text())
    assert isinstance(doc, list) and len(doc) == 1 and set(doc[0]) == {"id", "keypoints3d"} and doc[0]["id"] == 0
    kp = np.array(doc[0]["keypoints3d"])
    assert kp.shape == (25, 4)
    have = {n for n, c in zip(BODY25_NAMES, kp[:, 3]) if c > 0}
    assert have == {"Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip", "RHip",
                    "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle"}
    assert np.all(kp[kp[:, 3] == 0, :3] == 0)  # what we lack: confidence 0
    J = {n: motion.joints[3, i] for i, n in enumerate(JOINT_NAMES)}
    np.testing.assert_allclose(kp[BODY25_NAMES.index("LKnee"), :3], J["l_knee"], atol=1e-6)
    np.testing.assert_allclose(kp[BODY25_NAMES.index("MidHip"), :3], 0.5 * (J["l_hip"] + J["r_hip"]), atol=1e-6)


# ------------------------------------------------------------------------------------- glTF

@pytest.fixture(scope="module")
def glb(tmp_path_factory, motion):
    import pygltflib

    path = export_motion("glb", tmp_path_factory.mktemp("glb") / "m.glb", motion)
    return path, pygltflib.GLTF2.load(str(path))


def test_glb_validates(glb):
    """pygltflib's checks, and the Khronos rules a validator applies that matter for our file."""
    import warnings

    from pygltflib.validator import validate

    from common.gltf import JOINT_NODE_NAMES, accessor_array

    path, g = glb
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "provisional function"
        validate(g)
    assert path.read_bytes()[:4] == b"glTF" and g.asset.version == "2.0"
    blob = g.binary_blob()
    assert g.buffers[0].byteLength == len(blob)
    for view in g.bufferViews:
        assert view.byteOffset % 4 == 0 and view.byteOffset + view.byteLength <= len(blob)
    prim = g.meshes[0].primitives[0]
    pos = accessor_array(g, prim.attributes.POSITION)
    acc = g.accessors[prim.attributes.POSITION]
    np.testing.assert_allclose(acc.min, pos.min(axis=0))
    np.testing.assert_allclose(acc.max, pos.max(axis=0))
    assert accessor_array(g, prim.indices).max() < len(pos)
    normals = accessor_array(g, prim.attributes.NORMAL)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    weights = accessor_array(g, prim.attributes.WEIGHTS_0)
    assert np.abs(weights.sum(axis=1, dtype=np.float32) - 1).max() < 2e-7 * 4  # glTF's tolerance
    joints = accessor_array(g, prim.attributes.JOINTS_0)
    assert np.all(joints[weights == 0] == 0) and joints.max() < len(g.skins[0].joints)
    assert [g.nodes[j].name for j in g.skins[0].joints] == list(JOINT_NODE_NAMES)
    times = accessor_array(g, g.animations[0].samplers[0].input)
    assert np.all(np.diff(times) > 0) and g.accessors[g.animations[0].samplers[0].input].min == [0.0]
    for ch in g.animations[0].channels:
        if ch.target.path == "rotation":
            q = accessor_array(g, g.animations[0].samplers[ch.sampler].output)
            np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
            assert np.all(np.einsum("fi,fi->f", q[1:], q[:-1]) > 0)  # no flips between keys


def test_glb_animation_reproduces_the_joints(glb, motion):
    """Evaluated as a glTF viewer does, the animation's joint nodes are the fitted joints; the
    skinned mesh is the body model's skinned surface; metres, y up, the frame rate kept."""
    from common.body import forward_kinematics, skinned_vertices
    from common.gltf import TO_GLTF, glb_joint_positions, glb_skinned_vertices

    _, g = glb
    times, joints = glb_joint_positions(g)
    np.testing.assert_allclose(times, np.arange(FRAMES) / FPS, atol=1e-6)
    assert g.animations[0].extras["fps"] == FPS
    err = np.abs(joints - motion.joints).max()
    assert err < INTEROP_M and err < 1e-6, err  # float32 in the file: micrometres
    head, pelvis = JOINT_NAMES.index("head_top"), JOINT_NAMES.index("pelvis")
    gl = joints @ TO_GLTF.T
    assert np.all(gl[:, head, 1] > gl[:, pelvis, 1] + 0.5)  # y up
    pose = forward_kinematics(motion.model, motion.params[[0, 30]])
    for k, frame in enumerate((0, 30)):
        mesh = glb_skinned_vertices(g, frame)
        # four influences instead of the model's up to five: a fraction of a millimetre
        assert np.abs(mesh - skinned_vertices(motion.model, pose, k)).max() < INTEROP_M


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
        path = Path(d["path"])
        assert path == out / f"motion{SUFFIXES[d['format']]}"
        size = sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() else path.stat().st_size
        assert size == d["bytes"] > 0
        assert d["frames"] == FRAMES and d["fps"] == 25.0
    assert len(list((out / "motion_keypoints3d").iterdir())) == FRAMES
    assert not list(out.glob(".*"))  # no partial files left
    # again: every target holds what would be written, which loses nothing, and is left as it
    # is, its modification time too (mocap run tells its own exports from edited ones by it); at
    # another frame rate the timed files would change, and every target is checked before the
    # first is written, so nothing is replaced without --overwrite
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    assert cli_main(["export", str(result_dir), "--format", "all", "--out", str(out), "--fps", "25", "--json"]) == 0
    assert all(d["unchanged"] for d in json.loads(capsys.readouterr().out))
    assert before == {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    assert cli_main(["export", str(result_dir), "--format", "csv", "--out", str(out / "motion.csv"), "--fps", "25"]) == 0
    assert "holds this export already" in capsys.readouterr().out
    assert cli_main(["export", str(result_dir), "--format", "all", "--out", str(out), "--fps", "30"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert before == {p.name: p.stat().st_mtime_ns for p in out.iterdir()}


def test_mocap_export_several_formats_and_rest(tmp_path, result_dir, capsys):
    out = tmp_path / "some"
    assert cli_main(["export", str(result_dir), "--format", "glb,trc", "--format", "bvh", "--rest", "tpose",
                     "--out", str(out), "--fps", "25", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [d["format"] for d in doc] == ["glb", "trc", "bvh"] and doc[2]["rest"] == "tpose"
    assert sorted(p.name for p in out.iterdir()) == ["motion.bvh", "motion.glb", "motion.trc"]
    bvh = read_bvh(out / "motion.bvh")
    rest, _ = rest_positions(bvh)
    arm = rest[bvh.names.index("LeftHand")] - rest[bvh.names.index("LeftArm")]
    assert abs(arm[1]) < 1e-6  # T-pose: the arm horizontal at rest
    # several formats into what names a file: refused, nothing made
    single = tmp_path / "single.glb"
    assert cli_main(["export", str(result_dir), "--format", "glb,trc", "--out", str(single), "--fps", "25"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "several formats are written into a folder" in err and not single.exists()
    # a folder format: refused when there, replaced whole with --overwrite
    kp = tmp_path / "kp"
    assert cli_main(["export", str(result_dir), "--format", "keypoints3d", "--out", str(kp), "--fps", "25",
                     "--quiet"]) == 0
    (kp / "000099.json").write_text("[]")  # a frame of a longer take's export
    assert cli_main(["export", str(result_dir), "--format", "keypoints3d", "--out", str(kp), "--fps", "25"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert cli_main(["export", str(result_dir), "--format", "keypoints3d", "--out", str(kp), "--fps", "25",
                     "--overwrite", "--quiet"]) == 0
    assert not (kp / "000099.json").exists() and len(list(kp.iterdir())) == FRAMES
    assert cli_main(["export", str(result_dir), "--format", "glb,fbx", "--fps", "25"]) == 2
    assert "unknown format fbx" in capsys.readouterr().err


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


# ------------------------------------------------------------------- a take fitted every 5th frame

def test_the_fitted_frames_rate_is_the_recordings_over_their_step():
    assert sample_rate(np.arange(0, 200, 5), 50.0) == 10.0
    assert sample_rate(np.array([3, 8, 18, 23]), 50.0) == 10.0  # a frame missing: still every 5th
    assert sample_rate(np.array([0, 2, 3]), 30.0) == 30.0
    assert sample_rate(np.array([7]), 25.0) == 25.0
    assert frames_text([0, 5, 10, 20]) == "0..20, one in 5, without 15" and frames_text([3, 4]) == "3..4"
    assert frames_text([0, 5, 10]) == "0..10, one in 5" and frames_text([]) == "none"
    assert frames_off_step([3, 8, 18, 23]) == [13] and frames_off_step([0, 2, 3]) == [1] and frames_off_step([7]) == []


def test_a_take_fitted_every_5th_frame_plays_in_real_time_in_every_format(tmp_path):
    """`import-video --step 5` of a 50 fps recording keeps frame numbers 0, 5, 10, ...: formats
    that keep each frame's time had them right; those with one rate (BVH, C3D, TRC) wrote 50
    fps and played the take five times too fast."""
    model = load_body_model()
    params = motion_params(model, frames=12)
    sub = FittedMotion.from_records(records_for(model, params, first_frame=0, step=5), 50.0)
    assert sub.rate == 10.0
    np.testing.assert_allclose(sub.times, np.arange(12) * 0.1)
    bvh = read_bvh(export_motion("bvh", tmp_path / "m.bvh", sub))
    assert bvh.frame_time == pytest.approx(0.1)
    header, _, times, _ = read_trc(export_motion("trc", tmp_path / "m.trc", sub))
    assert header["DataRate"] == "10" and header["OrigDataRate"] == "10" and header["CameraRate"] == "50"
    np.testing.assert_allclose(times, np.arange(12) * 0.1, atol=1e-6)
    assert float(read_mot(export_motion("mot", tmp_path / "m.mot", sub))[2][1, 0]) == pytest.approx(0.1)
    c3d = pytest.importorskip("c3d")
    with open(export_motion("c3d", tmp_path / "m.c3d", sub), "rb") as fh:
        assert c3d.Reader(fh).point_rate == pytest.approx(10.0)


def test_c3d_tells_viewers_the_calibrations_up_axis(tmp_path):
    """C3D keeps the user's world: a z-down calibration's actor stands upright in a viewer only
    if POINT:Y_SCREEN says -Z."""
    c3d = pytest.importorskip("c3d")
    model = load_body_model()
    params = motion_params(model, frames=3)
    joints = world_frame("-z").points_to_user(forward_kinematics(model, params).joints)  # as a fit records them
    records = [r | {"world_up": "-z", "joints": joints_dict(j)} for r, j in zip(records_for(model, params), joints)]
    with open(export_motion("c3d", tmp_path / "m.c3d", FittedMotion.from_records(records, FPS)), "rb") as fh:
        reader = c3d.Reader(fh)
        assert reader.get("POINT:Y_SCREEN").string_value.strip() == "-Z"
        assert reader.get("POINT:X_SCREEN").string_value.strip() == "+X"
