"""BVH reading, writing, forward kinematics, skeleton role mapping, units and axes."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.bvh import (
    BvhMotion, bvh_global_transforms, end_site_positions, format_bvh, parse_bvh, read_bvh, recorded_rate,
    rest_positions, write_bvh,
)
from common.errors import InputFileError, UserError
from common.skeleton_map import (
    KNOWN_UNITS, OPTIONAL_ROLES, REQUIRED_ROLES, guess_units, guess_up_axis, joint_label,
    load_joint_map, map_skeleton, name_parts, point_positions, role_rest_positions, role_rotations,
    role_trajectories, up_axis_rotation,
)

DATA = Path(__file__).parent / "data" / "bvh"
MOCAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"
CLIPS = sorted(MOCAP.glob("**/*.bvh")) if MOCAP.is_dir() else []
CMU_MAP = {
    "pelvis": "Hips", "spine_lower": "Spine", "spine_upper": "Spine1", "neck": "Neck", "head": "Head",
    "head_end": "Head/end", "l_clavicle": "LeftShoulder", "l_shoulder": "LeftArm", "l_elbow": "LeftForeArm",
    "l_wrist": "LeftHand", "l_hip": "LeftUpLeg", "l_knee": "LeftLeg", "l_ankle": "LeftFoot",
    "l_toe": "LeftToeBase", "r_clavicle": "RightShoulder", "r_shoulder": "RightArm",
    "r_elbow": "RightForeArm", "r_wrist": "RightHand", "r_hip": "RightUpLeg", "r_knee": "RightLeg",
    "r_ankle": "RightFoot", "r_toe": "RightToeBase",
}

TWO_BONE = """HIERARCHY
ROOT A
{
  OFFSET 0 0 0
  CHANNELS 3 Zrotation Yrotation Xrotation
  JOINT B
  {
    OFFSET 1 0 0
    CHANNELS 1 Zrotation
    End Site
    {
      OFFSET 1 0 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.1
0 0 0 0
90 0 0 0
90 0 0 90
"""


def labels(motion: BvhMotion, mapping: dict) -> dict:
    return {r: joint_label(motion, i) for r, i in mapping.items()}


# ------------------------------------------------------------------------------ real CMU clips

@pytest.mark.parametrize("clip", CLIPS or [None], ids=lambda c: c.name if c else "none")
def test_cmu_clip_reads_maps_and_scales(clip):
    if clip is None:
        pytest.skip(f"{MOCAP} is absent")
    m = read_bvh(clip)
    assert m.num_joints == 31 and m.num_channels == 96 and m.num_frames > 100
    assert m.frame_time == pytest.approx(1 / 120, rel=1e-3)
    assert m.fps == 120.0  # .0083333 and 0.008333 alike
    pos, rot = bvh_global_transforms(m)
    assert pos.shape == (m.num_frames, 31, 3) and rot.shape == (m.num_frames, 31, 3, 3)
    assert np.all(np.isfinite(pos))
    assert np.allclose(rot[-1] @ np.swapaxes(rot[-1], -1, -2), np.eye(3), atol=1e-9)

    mapping = map_skeleton(m)
    assert set(REQUIRED_ROLES) <= set(mapping)
    got = labels(m, mapping)
    assert {r: got[r] for r in CMU_MAP} == CMU_MAP
    assert guess_units(m) == pytest.approx(0.0254 / 0.45)
    assert guess_up_axis(m) == "+y"

    traj = role_trajectories(m, mapping, frames=0)
    t = {r: v[0] for r, v in traj.items()}
    hip_to_ankle = np.mean([t[f"{s}_hip"][2] - t[f"{s}_ankle"][2] for s in "lr"])
    assert 0.75 < hip_to_ankle < 0.95  # metres, an adult's legs
    height = t["head_end"][2] - min(t["l_toe"][2], t["r_toe"][2])
    assert 1.35 < height < 1.6  # toe to the head's End Site, which lies below the crown
    assert t["l_shoulder"][0] - t["r_shoulder"][0] > 0.25  # left is +x: file axes kept, y turned to z
    first = m.values[0, 6:]
    if np.all(first == np.round(first)):  # the cgspeed clips begin with an added T-pose
        for s in "lr":
            for j in ("elbow", "wrist"):
                assert abs(t[f"{s}_{j}"][2] - t[f"{s}_shoulder"][2]) < 0.1
            assert np.linalg.norm((t[f"{s}_ankle"] - t[f"{s}_hip"])[:2]) < 0.06


def test_cmu_read_and_fk_fast():
    clip = MOCAP / "cmu_jalderson" / "05_04.bvh"
    if not clip.is_file():
        pytest.skip(f"{clip} is absent")
    t0 = time.perf_counter()
    m = read_bvh(clip)
    pos, rot = bvh_global_transforms(m)
    end_site_positions(m, transforms=(pos, rot))
    elapsed = time.perf_counter() - t0
    assert m.num_frames == 1200
    assert elapsed < 1.0, f"read + FK of 1200 frames took {elapsed:.2f} s"


def test_cmu_round_trip(tmp_path):
    if not CLIPS:
        pytest.skip(f"{MOCAP} is absent")
    m = read_bvh(CLIPS[0])
    write_bvh(tmp_path / "out.bvh", m)
    back = read_bvh(tmp_path / "out.bvh")
    assert_same_motion(m, back)


# ------------------------------------------------------------------------------ frame rates

@pytest.mark.timeout(10)
@pytest.mark.parametrize("frame_time, fps", [
    (0.008333, 120.0), (0.0083333, 120.0), (1 / 120, 120.0), (0.004167, 240.0), (0.002083, 480.0),
    (0.041667, 24.0), (0.04, 25.0), (0.1, 10.0),
    (0.033367, 30000 / 1001), (0.016683, 60000 / 1001), (0.041708, 24000 / 1001),  # NTSC stays NTSC
    (0.0333, 1 / 0.0333), (0.0583333, 1 / 0.0583333),  # 30.03, 17.14: no rate near enough to snap to
    (0.0, 0.0),
])
def test_recorded_rate_undoes_the_rounded_frame_time(frame_time, fps):
    assert recorded_rate(frame_time) == fps


@pytest.mark.timeout(30)
def test_a_rounded_frame_time_is_kept_in_the_file_and_exports_write_the_rate(tmp_path, model):
    from common.export import write_motion_bvh

    motion = parse_bvh(TWO_BONE.replace("Frame Time: 0.1", "Frame Time: 0.008333"))
    assert motion.fps == 120.0 and motion.frame_time == 0.008333
    assert "Frame Time: 0.008333\n" in format_bvh(motion)  # as read: written back unchanged
    write_motion_bvh(tmp_path / "fit.bvh", model, np.zeros((2, 35)), 30.0)  # a synthesized sequence's fps
    again = read_bvh(tmp_path / "fit.bvh")
    assert again.frame_time == 1 / 30 and again.fps == 30.0


# ------------------------------------------------------------------------------ reading and writing

def assert_same_motion(a: BvhMotion, b: BvhMotion, tol=1e-6):
    assert a.names == b.names
    assert a.channels == b.channels
    assert np.array_equal(a.parents, b.parents)
    assert np.array_equal(a.end_site_parents, b.end_site_parents)
    assert np.allclose(a.offsets, b.offsets, atol=tol, rtol=0)
    assert np.allclose(a.end_site_offsets, b.end_site_offsets, atol=tol, rtol=0)
    assert np.allclose(a.values, b.values, atol=tol, rtol=0)
    assert a.frame_time == pytest.approx(b.frame_time, abs=1e-12)


@pytest.mark.parametrize("name", sorted(p.name for p in DATA.glob("*.bvh")))
def test_fixture_round_trip(tmp_path, name):
    m = read_bvh(DATA / name)
    write_bvh(tmp_path / name, m)
    back = read_bvh(tmp_path / name)
    assert_same_motion(m, back)
    assert format_bvh(back) == format_bvh(m)


def test_two_bone_fk_by_hand():
    m = parse_bvh(TWO_BONE, "two_bone")
    assert m.names == ("A", "B") and list(m.parents) == [-1, 0]
    assert m.channels == (("Zrotation", "Yrotation", "Xrotation"), ("Zrotation",))
    pos, rot = bvh_global_transforms(m)
    ends = end_site_positions(m)
    assert np.allclose(pos[:, 1], [[1, 0, 0], [0, 1, 0], [0, 1, 0]], atol=1e-12)
    assert np.allclose(ends[:, 0], [[2, 0, 0], [0, 2, 0], [-1, 1, 0]], atol=1e-12)
    assert np.allclose(rot[2, 1], [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], atol=1e-12)
    # frames: an int, indices, a slice
    p1, _ = bvh_global_transforms(m, frames=2)
    assert p1.shape == (1, 2, 3) and np.allclose(p1[0], pos[2])
    assert np.allclose(bvh_global_transforms(m, frames=[2, 0])[0], pos[[2, 0]])
    assert np.allclose(end_site_positions(m, frames=slice(1, 3)), ends[1:3])


@pytest.mark.parametrize("order", ["XYZ", "YXZ", "ZXY", "ZYX"])
def test_rotation_orders_match_intrinsic_euler(order):
    """Channels "Yrotation Xrotation Zrotation" mean R = Ry @ Rx @ Rz (intrinsic Euler YXZ)."""
    rng = np.random.default_rng(7)
    angles = rng.uniform(-170, 170, (5, 2, 3))
    chans = " ".join(f"{a}rotation" for a in order)
    rows = "\n".join(" ".join(f"{v:.6f}" for v in np.r_[[0.5, -1.0, 2.0], f[0], f[1]]) for f in angles)
    text = (f"HIERARCHY\nROOT R\n{{\nOFFSET 0 0 0\nCHANNELS 6 Xposition Yposition Zposition {chans}\n"
            f"JOINT C\n{{\nOFFSET 0 3 0\nCHANNELS 3 {chans}\nEnd Site\n{{\nOFFSET 0 0 2\n}}\n}}\n}}\n"
            f"MOTION\nFrames: 5\nFrame Time: 0.04\n{rows}\n")
    m = parse_bvh(text)
    pos, rot = bvh_global_transforms(m)
    r0 = Rotation.from_euler(order, angles[:, 0], degrees=True).as_matrix()
    r1 = Rotation.from_euler(order, angles[:, 1], degrees=True).as_matrix()
    assert np.allclose(rot[:, 0], r0, atol=1e-6)
    assert np.allclose(rot[:, 1], r0 @ r1, atol=1e-6)
    assert np.allclose(pos[:, 0], [0.5, -1.0, 2.0])
    assert np.allclose(pos[:, 1], pos[:, 0] + r0 @ [0, 3, 0], atol=1e-6)
    assert np.allclose(end_site_positions(m)[:, 0], pos[:, 1] + (r0 @ r1) @ [0, 0, 2], atol=1e-6)


def test_position_channels_on_every_joint():
    """Position channels give the joint's local translation (the OFFSET is its rest value)."""
    m = read_bvh(DATA / "mixamo_positions.bvh")
    assert all(c[:3] == ("Xposition", "Yposition", "Zposition") for c in m.channels)
    # the same motion without the (constant, = OFFSET) position channels of the non-root joints
    keep = np.concatenate([np.arange(s, s + len(c)) if j == 0 else np.arange(s + 3, s + len(c))
                           for j, (s, c) in enumerate(zip(m.channel_starts, m.channels))])
    rot_only = dataclasses.replace(
        m, channels=tuple(c if j == 0 else c[3:] for j, c in enumerate(m.channels)), values=m.values[:, keep])
    pos_a, rot_a = bvh_global_transforms(m)
    pos_b, rot_b = bvh_global_transforms(rot_only)
    assert np.allclose(pos_a, pos_b, atol=1e-9) and np.allclose(rot_a, rot_b, atol=1e-12)
    # the root sits where its channels say, not OFFSET + channels
    assert np.allclose(pos_a[:, 0], m.values[:, :3])
    # a stretched forearm: the channel value, not the OFFSET, sets the translation
    j = m.joint_index("mixamorig:LeftHand")
    values = m.values.copy()
    values[:, m.channel_starts[j]] *= 2.0
    pos_c, _ = bvh_global_transforms(dataclasses.replace(m, values=values))
    elbow = m.joint_index("mixamorig:LeftForeArm")
    bone = np.linalg.norm(pos_c[:, j] - pos_c[:, elbow], axis=1)
    assert np.allclose(bone, 2 * abs(m.offsets[j, 0]))


def test_whitespace_crlf_and_names_with_spaces():
    text = TWO_BONE.replace("ROOT A", "ROOT  Bip01   Pelvis").replace("\n", "\r\n").replace("  ", "\t")
    text = text.replace("OFFSET 1 0 0\n", "OFFSET\t1   0\t0 \n")
    m = parse_bvh("\ufeff" + text)
    assert m.names == ("Bip01 Pelvis", "B")
    assert m.num_frames == 3
    one_line = "HIERARCHY ROOT A { OFFSET 0 0 0 CHANNELS 1 Xrotation End Site { OFFSET 0 1 0 } }\nMOTION\nFrames: 1\nFrame Time: 1\n5\n"
    assert parse_bvh(one_line).values.tolist() == [[5.0]]


def test_rest_positions_and_zero_frames():
    m = parse_bvh(TWO_BONE.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.1\n")
    assert m.values.shape == (0, 4)
    joints, ends = rest_positions(m)
    assert np.allclose(joints, [[0, 0, 0], [1, 0, 0]]) and np.allclose(ends, [[2, 0, 0]])
    assert bvh_global_transforms(m)[0].shape == (0, 2, 3)


BAD = {
    "no_motion": (TWO_BONE.split("MOTION")[0], "no MOTION"),
    "short_frame": (TWO_BONE.replace("90 0 0 90", "90 0 90"), "line 21: 3 values, the hierarchy has 4 channels"),
    "long_frame": (TWO_BONE.replace("0 0 0 0\n", "0 0 0 0 0\n"), "line 19: 5 values"),
    "not_number": (TWO_BONE.replace("90 0 0 0", "90 0 abc 0"), "line 20: value 3 is not a finite number: 'abc'"),
    "nan": (TWO_BONE.replace("90 0 0 0", "90 0 nan 0"), "line 20: value 3"),
    "frames_count": (TWO_BONE.replace("Frames: 3", "Frames: 4"), "Frames: 4 (line 17) but 3 frame lines"),
    "frames_word": (TWO_BONE.replace("Frames: 3", "Frames: three"), "line 17: Frames must be a whole number"),
    "no_frame_time": (TWO_BONE.replace("Frame Time: 0.1", "Time 0.1"), "line 18: expected 'Frame Time: SECONDS'"),
    "bad_channel": (TWO_BONE.replace("CHANNELS 1 Zrotation", "CHANNELS 1 Wrotation"), "line 9: unknown channel 'Wrotation'"),
    "bad_offset": (TWO_BONE.replace("OFFSET 1 0 0\n    CHANNELS", "OFFSET 1 x 0\n    CHANNELS"), "line 8: OFFSET of 'B' must be a number"),
    "unclosed": (TWO_BONE.replace("  }\n}\nMOTION", "  }\nMOTION"), "line 14: file ends where '}' closing joint 'A'"),
    "no_hierarchy": (TWO_BONE.replace("HIERARCHY", "HIERARCH"), "line 1: file must start with HIERARCHY"),
    "stray_word": (TWO_BONE.replace("    OFFSET 1 0 0\n    CHANNELS", "    OFFSET 1 0 0\n    BONE\n    CHANNELS"), "line 9: unexpected 'BONE'"),
    "no_brace": (TWO_BONE.replace("JOINT B\n  {\n", "JOINT B\n"), "line 7: expected '{', found 'OFFSET'"),
    "duplicate": (TWO_BONE.replace("JOINT B", "JOINT A"), "line 6: duplicate joint name 'A'"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_files_name_the_line(tmp_path, case):
    text, expected = BAD[case]
    path = tmp_path / f"{case}.bvh"
    path.write_text(text)
    with pytest.raises(InputFileError) as err:
        read_bvh(path)
    assert str(path) in str(err.value)
    assert expected in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="cannot read"):
        read_bvh(tmp_path / "nope.bvh")


# ------------------------------------------------------------------------------ skeleton mapping

FIXTURE_MAPS = {
    "simple.bvh": {
        "pelvis": "Hips", "spine_lower": "Spine", "spine_upper": "Chest", "neck": "Neck", "head": "Head",
        "head_end": "Head/end", "l_shoulder": "LeftShoulder", "l_elbow": "LeftElbow", "l_wrist": "LeftWrist",
        "l_hand_end": "LeftWrist/end", "l_hip": "LeftHip", "l_knee": "LeftKnee", "l_ankle": "LeftAnkle",
        "r_shoulder": "RightShoulder", "r_wrist": "RightWrist", "r_ankle": "RightAnkle",
    },
    "mixamo_positions.bvh": {
        "pelvis": "mixamorig:Hips", "spine_lower": "mixamorig:Spine", "spine_upper": "mixamorig:Spine2",
        "neck": "mixamorig:Neck", "head": "mixamorig:Head", "head_end": "mixamorig:HeadTop_End",
        "l_clavicle": "mixamorig:LeftShoulder", "l_shoulder": "mixamorig:LeftArm",
        "l_elbow": "mixamorig:LeftForeArm", "l_wrist": "mixamorig:LeftHand",
        "l_hand_end": "mixamorig:LeftHandMiddle4/end", "l_hip": "mixamorig:LeftUpLeg",
        "l_knee": "mixamorig:LeftLeg", "l_ankle": "mixamorig:LeftFoot", "l_toe": "mixamorig:LeftToeBase",
        "r_clavicle": "mixamorig:RightShoulder", "r_shoulder": "mixamorig:RightArm",
    },
    "biped_zup_inches.bvh": {
        "pelvis": "Bip01 Pelvis", "spine_lower": "Bip01 Spine", "spine_upper": "Bip01 Spine1",
        "neck": "Bip01 Neck", "head": "Bip01 Head", "head_end": "Bip01 HeadNub",
        "l_clavicle": "Bip01 L Clavicle", "l_shoulder": "Bip01 L UpperArm", "l_elbow": "Bip01 L Forearm",
        "l_wrist": "Bip01 L Hand", "l_hand_end": "Bip01 L Finger2Nub", "l_hip": "Bip01 L Thigh",
        "l_knee": "Bip01 L Calf", "l_ankle": "Bip01 L Foot", "l_toe": "Bip01 L Toe0",
        "r_clavicle": "Bip01 R Clavicle", "r_elbow": "Bip01 R Forearm", "r_knee": "Bip01 R Calf",
    },
    "ue_suffix_lr_zup_cm.bvh": {  # _L/_R markers, twist joints inside the upper-arm chain
        "pelvis": "pelvis", "spine_lower": "spine_01", "spine_upper": "spine_03", "neck": "neck_01",
        "head": "head", "head_end": "head/end", "l_clavicle": "clavicle_L", "l_shoulder": "upperarm_L",
        "l_elbow": "lowerarm_L", "l_wrist": "hand_L", "l_hand_end": "middle_01_L/end", "l_hip": "thigh_L",
        "l_knee": "calf_L", "l_ankle": "foot_L", "l_toe": "ball_L", "r_shoulder": "upperarm_R",
        "r_elbow": "lowerarm_R", "r_wrist": "hand_R",
    },
}
FIXTURE_UNITS = {"simple.bvh": ("m", "+y"), "mixamo_positions.bvh": ("cm", "+y"),
                 "biped_zup_inches.bvh": ("inch", "+z"), "ue_suffix_lr_zup_cm.bvh": ("cm", "+z")}


@pytest.mark.parametrize("name", sorted(FIXTURE_MAPS))
def test_fixture_skeletons_map(name):
    m = read_bvh(DATA / name)
    mapping = map_skeleton(m)
    got = labels(m, mapping)
    assert {r: got.get(r) for r in FIXTURE_MAPS[name]} == FIXTURE_MAPS[name]
    assert set(REQUIRED_ROLES) <= set(mapping)
    if name == "simple.bvh":
        assert "l_clavicle" not in mapping and "r_clavicle" not in mapping
    unit, up = FIXTURE_UNITS[name]
    assert guess_units(m) == KNOWN_UNITS[unit]
    assert guess_up_axis(m) == up


def test_all_fixtures_share_one_world():
    """The fixtures are one body (1.73 m, T-pose, left +x) in different names, units and axes:
    in our world their rest poses agree once the pelvis is put at the origin."""
    rests = {}
    for name in FIXTURE_MAPS:
        m = read_bvh(DATA / name)
        r = role_rest_positions(m)
        rests[name] = {k: v - r["pelvis"] for k, v in r.items()}
    common = ("spine_upper", "neck", "head", "l_shoulder", "l_elbow", "l_wrist", "r_wrist",
              "l_hip", "l_knee", "l_ankle", "r_ankle")
    ref = rests["simple.bvh"]
    for name, r in rests.items():
        for role in common:
            if name == "biped_zup_inches.bvh" and role == "spine_upper":
                continue  # Biped's chest joint sits lower
            assert np.allclose(r[role], ref[role], atol=0.002), (name, role, r[role], ref[role])
    assert ref["l_wrist"][0] > 0.6 and ref["head"][2] > 0.6 and ref["l_ankle"][2] < -0.8


@pytest.mark.parametrize("name", sorted(FIXTURE_MAPS))
def test_role_trajectories_match_fk(name):
    m = read_bvh(DATA / name)
    mapping = map_skeleton(m)
    unit, up = FIXTURE_UNITS[name]
    traj = role_trajectories(m, mapping)
    rots = role_rotations(m, mapping)
    rest = role_rest_positions(m, mapping)
    W = up_axis_rotation(up)
    pts = point_positions(m)
    for role, i in mapping.items():
        assert traj[role].shape == (m.num_frames, 3) and rots[role].shape == (m.num_frames, 3, 3)
        assert np.allclose(traj[role], KNOWN_UNITS[unit] * pts[:, i] @ W.T)
    # rotations are relative to the rest pose, in the z-up world: rest bone vectors turn into
    # frame bone vectors (no position channels below the root in these bones' joints)
    for a, b in (("l_elbow", "l_wrist"), ("r_knee", "r_ankle"), ("head", "head_end")):
        if name == "mixamo_positions.bvh":
            continue  # position channels equal OFFSETs there, the identity holds as well
        bone_now = traj[b] - traj[a]
        bone_rest = rest[b] - rest[a]
        assert np.allclose(bone_now, rots[a] @ bone_rest, atol=1e-6)
    # frame 0 of the fixtures is the rest pose with the root moved
    assert np.allclose(traj["l_wrist"][0] - traj["pelvis"][0], rest["l_wrist"] - rest["pelvis"], atol=1e-6)
    assert np.allclose(rots["l_elbow"][0], np.eye(3), atol=1e-9)


SIDE_STYLES = {
    "_L": lambda s, b: f"{b}_{s[0]}",
    ".L": lambda s, b: f"{b}.{s[0]}",
    "left_": lambda s, b: f"{s.lower()}_{b.lower()}",
    "l_": lambda s, b: f"{s[0].lower()}_{b.lower()}",
    "L prefix": lambda s, b: f"{s[0]}{b}",
    "Bip L": lambda s, b: f"Bip01 {s[0]} {b}",
    "UPPER": lambda s, b: f"{s.upper()}_{b.upper()}",
    "lower": lambda s, b: f"{s.lower()}{b.lower()}",
    "suffix Left": lambda s, b: f"{b}Left" if s == "Left" else f"{b}Right",
}


@pytest.mark.parametrize("style", sorted(SIDE_STYLES))
def test_side_markers(style):
    m = read_bvh(DATA / "simple.bvh")
    rename = SIDE_STYLES[style]
    names = tuple(rename(n[:4], n[4:]) if n.startswith("Left") else rename(n[:5], n[5:]) if n.startswith("Right")
                  else n for n in m.names)
    renamed = dataclasses.replace(m, names=names)
    got = labels(renamed, map_skeleton(renamed))
    want = labels(m, map_skeleton(m))
    for role, joint in want.items():
        old = joint.split("/")[0]
        new = names[m.names.index(old)]
        assert got[role] == joint.replace(old, new), (style, role)


def test_acclaim_asf_names():
    """CMU's own ASF names as some BVH converters keep them: lhumerus, lradius, lwrist, lfemur ..."""
    m = read_bvh(DATA / "simple.bvh")
    asf = {"Hips": "root", "Spine": "lowerback", "Chest": "thorax", "Neck": "lowerneck", "Head": "head",
           "Shoulder": "humerus", "Elbow": "radius", "Wrist": "wrist", "Hip": "femur", "Knee": "tibia",
           "Ankle": "foot"}
    names = tuple(("l" + asf[n[4:]]) if n.startswith("Left") else ("r" + asf[n[5:]]) if n.startswith("Right")
                  else asf[n] for n in m.names)
    renamed = dataclasses.replace(m, names=names)
    got = labels(renamed, map_skeleton(renamed))
    assert got["pelvis"] == "root" and got["spine_lower"] == "lowerback" and got["spine_upper"] == "thorax"
    assert (got["l_shoulder"], got["l_elbow"], got["l_wrist"]) == ("lhumerus", "lradius", "lwrist")
    assert (got["r_hip"], got["r_knee"], got["r_ankle"]) == ("rfemur", "rtibia", "rfoot")


def test_name_parts():
    assert name_parts("mixamorig:LeftForeArm") == ("l", ("fore", "arm"))
    assert name_parts("Bip01 R Calf") == ("r", ("calf",))
    assert name_parts("upperarm_twist_01_l") == ("l", ("upperarm", "twist"))
    assert name_parts("LHipJoint") == ("l", ("hip", "joint"))
    assert name_parts("LowerBack") == (None, ("lower", "back"))
    assert name_parts("Spine1") == (None, ("spine",))
    assert name_parts("Hand.R") == ("r", ("hand",))
    assert name_parts("lhumerus") == ("l", ("humerus",))
    assert name_parts("lowerback") == (None, ("lowerback",))


def test_unmapped_roles_are_named_and_joint_map_fixes_them(tmp_path):
    m = read_bvh(DATA / "simple.bvh")
    names = tuple({"LeftKnee": "Bone7", "LeftAnkle": "Bone8"}.get(n, n) for n in m.names)
    odd = dataclasses.replace(m, names=names, source="odd.bvh")
    with pytest.raises(UserError) as err:
        map_skeleton(odd)
    msg = str(err.value)
    assert msg.startswith("odd.bvh: ") and "l_knee" in msg and "l_ankle" in msg and "Bone7" in msg
    assert "r_knee" not in msg.split("(joints")[0]
    toml = tmp_path / "map.toml"
    toml.write_text('[joints]\nl_knee = "Bone7"\nl_ankle = "bone8"\nhead_end = "Head/end"\nl_toe = "Bone8/end"\n')
    override = load_joint_map(toml)
    assert override == {"l_knee": "Bone7", "l_ankle": "bone8", "head_end": "Head/end", "l_toe": "Bone8/end"}
    got = labels(odd, map_skeleton(odd, override))
    assert got["l_knee"] == "Bone7" and got["l_ankle"] == "Bone8" and got["l_toe"] == "Bone8/end"
    assert got["l_hip"] == "LeftHip"  # the automatic map stays under the override


def test_joint_map_errors(tmp_path):
    m = read_bvh(DATA / "simple.bvh")
    bad = tmp_path / "bad.toml"
    for text, expected in (
        ("joints = 3\n", "needs a [joints] table"),
        ("[joints]\nelbow_l = \"LeftElbow\"\n", "joints.elbow_l: unknown role"),
        ("[joints]\nl_elbow = 3\n", "joints.l_elbow: must be a joint name"),
        ("[joints\n", "not valid TOML"),
    ):
        bad.write_text(text)
        with pytest.raises(InputFileError, match=expected.replace("[", r"\[")):
            load_joint_map(bad)
    with pytest.raises(UserError, match="role l_elbow names joint 'Nope'"):
        map_skeleton(m, {"l_elbow": "Nope"})
    with pytest.raises(UserError, match="has no End Site"):
        map_skeleton(m, {"l_elbow": "LeftElbow/end"})


def scaled(m: BvhMotion, k: float) -> BvhMotion:
    pos_cols = np.array([c.endswith("position") for chans in m.channels for c in chans])
    values = m.values.copy()
    values[:, pos_cols] *= k
    return dataclasses.replace(m, offsets=m.offsets * k, end_site_offsets=m.end_site_offsets * k, values=values)


@pytest.mark.parametrize("unit", sorted(KNOWN_UNITS))
def test_guess_units_snaps_to_known_units(unit):
    m = scaled(read_bvh(DATA / "simple.bvh"), 1.0 / KNOWN_UNITS[unit])
    assert guess_units(m) == KNOWN_UNITS[unit]
    legless = dataclasses.replace(m, names=tuple(n.replace("Ankle", "Bone") for n in m.names))
    with pytest.raises(UserError, match="l_hip, l_knee, l_ankle"):
        map_skeleton(legless)
    assert guess_units(legless) == KNOWN_UNITS[unit]  # from the rest pose's extent


def test_guess_units_odd_scale_is_not_snapped():
    m = scaled(read_bvh(DATA / "simple.bvh"), 10.0)  # decimetres: no known unit
    assert guess_units(m) == pytest.approx(0.1, rel=0.05)
    assert guess_units(m) not in KNOWN_UNITS.values()


def test_up_axis_rotations_are_proper():
    for up in ("+x", "-x", "+y", "-y", "+z", "-z"):
        W = up_axis_rotation(up)
        assert np.allclose(W @ W.T, np.eye(3)) and np.linalg.det(W) == pytest.approx(1.0)
        v = np.zeros(3)
        v["xyz".index(up[1])] = 1.0 if up[0] == "+" else -1.0
        assert np.allclose(W @ v, [0, 0, 1])
    assert np.allclose(up_axis_rotation("y") @ [0, 0, 1], [0, -1, 0])  # y-up facing +z -> facing -y
    with pytest.raises(UserError):
        up_axis_rotation("up")


def test_optional_roles_are_optional():
    assert not set(OPTIONAL_ROLES) & set(REQUIRED_ROLES)
    assert {"l_clavicle", "l_hand_end", "l_toe", "r_toe"} <= set(OPTIONAL_ROLES)
    assert {"pelvis", "spine_lower", "spine_upper", "neck", "head", "head_end", "l_shoulder",
            "r_ankle"} <= set(REQUIRED_ROLES)
