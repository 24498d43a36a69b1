"""Calibration formats: fixtures as each tool writes them, round trips, the CLI, bad input."""
from __future__ import annotations

import json
import re
import shutil
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from common.calibration import (
    EASYMOCAP_FILES, FORMATS, WRITE_FORMATS, decompose_projection, detect_format, folder_calibrations, load_calibration,
    matrix_to_rodrigues, natural_key, output_format, rodrigues_to_matrix, save_calibration, units_doubt,
    with_image_sizes,
)
from common.camera import Camera, CalibrationError, Studio, circle_studio, make_camera
from server.cli import main

DATA = Path(__file__).parent / "data" / "calib"
NEW = Path(__file__).parent / "data" / "calibration"  # layouts met in labs: guessed sizes, P, Qualisys
REAL_UU = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "uu_seated_4cam"  # not in the repo
TOL = 1e-9

# (fixture, detected format, load options, camera names in order)
FIXTURES = [
    ("easymocap", "easymocap", {}, ["01", "02", "03", "04"]),
    ("pose2sim/Calib.toml", "pose2sim", {}, ["cam_01", "cam_02", "cam_03", "cam_04"]),
    ("anipose/calibration.toml", "anipose", {"units": "mm"}, list("ABCDEFGHIJK")),
    ("opencv_xml", "opencv-xml", {}, ["cam1", "cam2", "cam10"]),
    ("opencv_xml_subfolders", "opencv-xml", {}, ["left", "right"]),
    ("json/calibration.json", "json", {}, ["cam1", "cam2", "cam3"]),
]
OUT_NAME = {"json": "out.json", "pose2sim": "Calib.toml", "anipose": "calibration.toml",
            "easymocap": "easymocap_out", "opencv-xml": "xml_out"}


def assert_same(a: Studio, b: Studio, tol: float = TOL) -> None:
    assert a.names == b.names
    for ca, cb in zip(a, b):
        assert (ca.width, ca.height) == (cb.width, cb.height), ca.name
        for field in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(getattr(ca, field), getattr(cb, field), rtol=0, atol=tol,
                                       err_msg=f"{ca.name}.{field}")


def random_studio(seed: int, count: int) -> Studio:
    """A ring rig with random intrinsics, skew and distortion (k3 zero on some cameras)."""
    rng = np.random.default_rng(seed)
    cams = []
    for i, c in enumerate(circle_studio(count, width=int(rng.integers(320, 2000)), height=int(rng.integers(240, 1200)),
                                        radius=float(rng.uniform(2.0, 6.0)))):
        K = c.K.copy()
        K[0, 0] *= rng.uniform(0.8, 1.2)
        K[1, 1] *= rng.uniform(0.8, 1.2)
        K[0, 1] = rng.normal(0.0, 0.5) if i % 3 == 0 else 0.0
        K[:2, 2] += rng.normal(0.0, 10.0, 2)
        dist = rng.normal(0.0, [0.2, 0.1, 1e-3, 1e-3, 0.05])
        if i % 2:
            dist[4] = 0.0
        t = c.t + rng.normal(0.0, 0.1, 3)
        cams.append(Camera(c.name, K, dist, c.R, t, c.width, c.height))
    return Studio(tuple(cams))


def cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def copy_fixture(tmp_path: Path, name: str) -> Path:
    src = DATA / name
    dst = tmp_path / Path(name).name
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy(src, dst)
    return dst


def edit(path: Path, old: str, new: str) -> None:
    """Replace every ``old`` in the file by ``new`` (bytes kept, CRLF included)."""
    data = path.read_bytes().decode()
    assert old in data, f"{old!r} not in {path}"
    path.write_bytes(data.replace(old, new).encode())


# ----------------------------------------------------------------------------- reading fixtures

@pytest.mark.parametrize("name, fmt, options, names", FIXTURES, ids=[f[0] for f in FIXTURES])
def test_fixture_loads(name, fmt, options, names):
    path = DATA / name
    assert detect_format(path) == fmt
    studio = load_calibration(path, **options)
    assert studio.names == names
    for cam in studio:
        assert 1.0 < np.linalg.norm(cam.center) < 10.0  # metres
        assert cam.depth(np.array([0.0, 0.0, 1.0])) > 0  # every rig looks at the actor


def test_easymocap_values():
    studio = load_calibration(DATA / "easymocap")
    cam = studio.camera("01")
    assert (cam.width, cam.height) == (1920, 1080)
    assert cam.K[0, 0] == pytest.approx(1158.047983, abs=1e-12)
    assert cam.dist[0] == pytest.approx(-0.172720, abs=1e-12)
    # R comes from the Rodrigues R_01 as in EasyMocap; the 6-decimal Rot_01 agrees with it
    text = (DATA / "easymocap" / "extri.yml").read_text()
    rot_line = text.split("Rot_01:")[1].split("data: [")[1].split("]")[0]
    rot = np.array([float(x) for x in rot_line.split(",")]).reshape(3, 3)
    np.testing.assert_allclose(cam.R, rot, atol=1e-6)


def test_easymocap_without_rodrigues_uses_rot(tmp_path):
    folder = copy_fixture(tmp_path, "easymocap")
    edit(folder / "extri.yml", "R_02:", "Rx_02:")
    studio = load_calibration(folder)  # 6-decimal Rot_02, snapped to the nearest rotation
    np.testing.assert_allclose(studio.camera("02").R, load_calibration(DATA / "easymocap").camera("02").R, atol=2e-6)
    rot = studio.camera("02").R
    assert np.abs(rot.T @ rot - np.eye(3)).max() < 1e-12
    edit(folder / "extri.yml", "Rot_02: !!opencv-matrix\r\n  rows: 3\r\n  cols: 3\r\n  dt: d\r\n  data: [-0.993781",
         "Rot_02: !!opencv-matrix\r\n  rows: 3\r\n  cols: 3\r\n  dt: d\r\n  data: [-0.983781")
    with pytest.raises(CalibrationError, match=r"extri\.yml: Rot_02: not a rotation"):
        load_calibration(folder)


def test_pose2sim_values():
    cam = load_calibration(DATA / "pose2sim" / "Calib.toml")[0]
    assert (cam.width, cam.height) == (1088, 1920)  # size = [w, h]
    assert cam.dist[4] == 0.0  # four distortions: k1 k2 p1 p2
    assert cam.t[2] == pytest.approx(3.6984292690485367, abs=1e-15)


def test_anipose_units_and_natural_sort(tmp_path):
    studio = load_calibration(DATA / "anipose" / "calibration.toml", units="mm")
    assert studio.camera("B").t[1] == pytest.approx(0.866422700524554, abs=1e-15)
    assert studio.camera("A").dist.size == 5
    # sections in lexicographic order in the file still come out cam_0, cam_1, cam_2 ... cam_10
    text = (DATA / "anipose" / "calibration.toml").read_text()
    blocks = text.split("\n\n")
    cams, rest = blocks[:11], blocks[11:]
    shuffled = sorted(cams, key=lambda b: b.split("]")[0]) + rest
    assert [b.split("]")[0] for b in shuffled[:4]] == ["[cam_0", "[cam_1", "[cam_10", "[cam_2"]
    (tmp_path / "calibration.toml").write_text("\n\n".join(shuffled))
    assert_same(load_calibration(tmp_path / "calibration.toml", units="mm"), studio, tol=0)
    cm = load_calibration(DATA / "anipose" / "calibration.toml", units="cm")
    np.testing.assert_allclose(cm[0].t, 10 * studio[0].t, atol=1e-12)


def test_units_given_that_put_the_cameras_out_of_a_room_are_doubted():
    """A millimetre file read with --units m puts cameras kilometres apart (with cm, tens of
    metres): read as the user said, with one warning line naming the file; the right units say
    nothing, and neither does a camera at the origin (a stereo file's first)."""
    path = DATA / "anipose" / "calibration.toml"
    warned = []
    load_calibration(path, units="mm", warn=warned.append)
    assert not any("check --units" in w for w in warned)
    load_calibration(path, units="m", warn=warned.append)
    doubt = [w for w in warned if "check --units" in w]
    assert len(doubt) == 1 and str(path) in doubt[0] and "--units m " in doubt[0]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    stereo = Studio(tuple(make_camera(n, K, None, np.eye(3), t, 640, 480)
                          for n, t in (("left", np.zeros(3)), ("right", np.array([-0.12, 0.0, 0.0])))))
    assert units_doubt(stereo, "mm", "stereo") == []  # 12 cm apart, one at the origin
    assert "check --units" in units_doubt(Studio(stereo.cameras[:1] + (make_camera(
        "far", K, None, np.eye(3), np.array([-120.0, 0, 0]), 640, 480),)), "cm", "x")[0]


def test_opencv_xml_tag_variants():
    studio = load_calibration(DATA / "opencv_xml")
    cam1, cam2, cam10 = studio
    assert all((c.width, c.height) == (1280, 720) for c in studio)  # image_width, ImageSize, width
    assert cam10.dist[4] == 0.0 and cam10.dist[0] != 0.0  # 4 coefficients in D
    # cam2 stores a Rodrigues vector under <R>
    text = (DATA / "opencv_xml" / "cam2.xml").read_text()
    rvec = np.array([float(x) for x in text.split("<R ")[1].split("<data>")[1].split("</data>")[0].split()])
    np.testing.assert_allclose(cam2.R, rodrigues_to_matrix(rvec), atol=1e-15)
    single = load_calibration(DATA / "opencv_xml" / "cam1.xml")
    assert single.names == ["cam1"]
    assert_same(single, Studio((cam1,)), tol=0)


# ----------------------------------------------------------------------------- round trips

ROUND_TRIP = [f for f in FIXTURES if f[1] != "json"]


@pytest.mark.parametrize("name, fmt, options, names", ROUND_TRIP, ids=[f[0] for f in ROUND_TRIP])
def test_fixture_round_trip_through_json(tmp_path, name, fmt, options, names):
    original = load_calibration(DATA / name, **options)
    save_calibration(original, tmp_path / "calibration.json")
    via_json = load_calibration(tmp_path / "calibration.json")
    assert_same(via_json, original, tol=0)
    out = tmp_path / OUT_NAME[fmt]
    save_calibration(via_json, out, fmt)
    assert detect_format(out) == fmt
    assert_same(load_calibration(out), original)  # written in metres: no --units needed


@pytest.mark.parametrize("fmt", WRITE_FORMATS)
@pytest.mark.parametrize("seed, count", [(1, 4), (2, 8), (3, 12)])
def test_random_rig_round_trip(tmp_path, fmt, seed, count):
    studio = random_studio(seed, count)
    out = tmp_path / OUT_NAME[fmt]
    save_calibration(studio, out, fmt)
    back = load_calibration(out, fmt=fmt)
    assert_same(back, studio)
    save_calibration(back, tmp_path / "again.json")
    assert_same(load_calibration(tmp_path / "again.json"), studio)


def test_written_files_look_like_the_tools(tmp_path):
    studio = random_studio(5, 3)
    save_calibration(studio, tmp_path / "em", "easymocap")
    intri = (tmp_path / "em" / "intri.yml").read_bytes()
    assert intri.startswith(b"%YAML:1.0\r\n---\r\nnames:\r\n  - \"cam1\"\r\n")
    assert b"K_cam1: !!opencv-matrix\r\n  rows: 3\r\n  cols: 3\r\n  dt: d\r\n  data: [" in intri
    assert b"dist_cam1: !!opencv-matrix\r\n  rows: 1\r\n  cols: 5\r\n" in intri
    extri = (tmp_path / "em" / "extri.yml").read_bytes()
    assert b"R_cam1: !!opencv-matrix\r\n  rows: 3\r\n  cols: 1\r\n" in extri and b"Rot_cam1:" in extri
    save_calibration(studio, tmp_path / "Calib.toml")  # .toml -> pose2sim
    p2s = (tmp_path / "Calib.toml").read_text()
    assert p2s.startswith('[cam_01]\nname = "cam1"\nsize = [ ')
    assert "fisheye = false\n\n[cam_02]" in p2s and p2s.endswith("[metadata]\nadjusted = false\nerror = 0.0\n")
    save_calibration(studio, tmp_path / "calibration.toml", "anipose")
    ani = (tmp_path / "calibration.toml").read_text()
    assert ani.startswith(f'[cam_0]\nname = "cam1"\nsize = [ {studio[0].width}, {studio[0].height},]\nmatrix = [ [ ')
    assert ani.endswith("\n\n[metadata]\n")
    save_calibration(studio, tmp_path / "xml", "opencv-xml")
    xml = (tmp_path / "xml" / "cam2.xml").read_text()
    assert xml.startswith('<?xml version="1.0"?>\n<opencv_storage>\n<CameraMatrix type_id="opencv-matrix">\n')
    assert sorted(p.name for p in (tmp_path / "xml").iterdir()) == ["cam1.xml", "cam2.xml", "cam3.xml"]


def test_rodrigues():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, 190), [0.0, 1e-12, 1e-6, np.pi - 1e-9, np.pi - 1e-4,
                                                          np.pi, 2.6, 2.7, 3.0, 3.1]])
    for axis, angle in zip(axes, angles):
        R = rodrigues_to_matrix(axis * angle)
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-14 and np.linalg.det(R) > 0
        np.testing.assert_allclose(rodrigues_to_matrix(matrix_to_rodrigues(R)), R, atol=1e-12)
        if angle < np.pi - 1e-6:  # at pi, +axis and -axis are the same rotation
            np.testing.assert_allclose(matrix_to_rodrigues(R), axis * angle, atol=1e-9)
    np.testing.assert_allclose(rodrigues_to_matrix([0, 0, np.pi / 2]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)


def test_natural_key():
    names = ["cam_10", "cam_2", "cam_1", "Cam_3", "cam_0"]
    assert sorted(names, key=natural_key) == ["cam_0", "cam_1", "cam_2", "Cam_3", "cam_10"]


def test_output_format(tmp_path):
    assert output_format(tmp_path / "a.json") == "json"
    assert output_format(tmp_path / "a.toml") == "pose2sim"
    assert output_format(tmp_path / "a.toml", "anipose") == "anipose"
    assert output_format(tmp_path / "one.xml") == "opencv-xml"
    for ambiguous in (tmp_path / "folder", tmp_path / "intri.yml", tmp_path):
        with pytest.raises(CalibrationError, match="--format"):
            output_format(ambiguous)
    with pytest.raises(CalibrationError, match="one .xml file holds one camera"):
        save_calibration(random_studio(1, 3), tmp_path / "one.xml")


def test_sizes_fall_back_to_size_option(tmp_path):
    folder = copy_fixture(tmp_path, "easymocap")
    text = (folder / "intri.yml").read_bytes().decode()
    lines = [line for line in text.split("\r\n") if not line.startswith(("H_", "W_"))]
    (folder / "intri.yml").write_bytes("\r\n".join(lines).encode())
    warnings = []
    studio = load_calibration(folder, warn=warnings.append)
    assert [(c.width, c.height) for c in studio][0] == (1916, 1070)  # 2 x (958.129311, 535.047041), rounded
    assert all(c.size_guessed for c in studio)
    assert len(warnings) == 1 and "no image size for 01, 02, 03, 04" in warnings[0]
    warnings.clear()
    studio = load_calibration(folder, size=(1280, 720), warn=warnings.append)
    assert all((c.width, c.height) == (1280, 720) and not c.size_guessed for c in studio)
    assert warnings == []


def test_json_units(tmp_path):
    doc = json.loads((DATA / "json" / "calibration.json").read_text())
    base = load_calibration(DATA / "json" / "calibration.json")
    for cam in doc["cameras"]:
        cam["t"] = (np.asarray(cam["t"]) * 1000).tolist()
    doc["units"] = "mm"
    (tmp_path / "mm.json").write_text(json.dumps(doc))
    assert_same(load_calibration(tmp_path / "mm.json"), base, tol=1e-12)
    del doc["units"]  # a JSON that does not say: checked like the other formats
    (tmp_path / "nounits.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="units: .*pass --units mm"):
        load_calibration(tmp_path / "nounits.json")
    assert_same(load_calibration(tmp_path / "nounits.json", units="mm"), base, tol=1e-12)


def test_declared_units_are_the_files(tmp_path, capsys):
    """A file that says its units is read in them; a --units that disagrees is named in one
    warning line, not refused: --units is for files that do not say, and a project passes its
    setting to every step, the fit of an imported sequence (calibration.json, metres) too."""
    path = DATA / "json" / "calibration.json"
    warned = []
    assert_same(load_calibration(path, units="mm", warn=warned.append), load_calibration(path), tol=0)
    assert warned == [f"{path}: units: the file says m; --units mm is for files that do not say, and is not used"]
    warned.clear()
    load_calibration(path, units="m", warn=warned.append)
    assert warned == []
    rc, _, err = cli(capsys, "calib", "convert", path, tmp_path / "out.json", "--units", "cm")
    assert rc == 0 and err == (f"warning: {path}: units: the file says m; --units cm is for files that do not "
                               "say, and is not used\n")
    assert_same(load_calibration(tmp_path / "out.json"), load_calibration(path), tol=0)


def test_a_rig_out_of_a_room_is_doubted_whoever_gave_the_units(tmp_path, capsys):
    """Metres in a file that says mm put the cameras millimetres apart: calib show and convert
    name it as they do units given with --units; so does a file without units read as metres."""
    doc = json.loads((DATA / "json" / "calibration.json").read_text())
    doc["units"] = "mm"
    path = tmp_path / "says_mm.json"
    path.write_text(json.dumps(doc))
    expected = (f"warning: {path}: in mm, as the file says, the farthest two cameras stand 5 mm apart, where a "
                "capture room's stand 0.02-30 m: are the file's units right?\n")
    for argv in (("show", path), ("convert", path, tmp_path / "out.json")):
        rc, _, err = cli(capsys, "calib", *argv)
        assert rc == 0 and err == expected
    save_calibration(circle_studio(4, radius=20.0), tmp_path / "em", "easymocap")  # 40 m across
    warned = []
    load_calibration(tmp_path / "em", warn=warned.append)
    assert warned == [f"{tmp_path / 'em'}: in metres (the file does not say) the farthest two cameras stand "
                      "40.0 m apart, where a capture room's stand 0.02-30 m: pass --units if they are not metres"]
    assert load_calibration(DATA / "json" / "calibration.json", warn=warned.append) and len(warned) == 1


# ----------------------------------------------------------------------------- CLI

@pytest.mark.parametrize("name, fmt, options, names", FIXTURES, ids=[f[0] for f in FIXTURES])
def test_cli_convert_to_json_and_show(tmp_path, capsys, name, fmt, options, names):
    extra = ["--units", options["units"]] if "units" in options else []
    out = tmp_path / "calibration.json"
    rc, stdout, err = cli(capsys, "calib", "convert", DATA / name, out, *extra)
    assert rc == 0, err
    assert f"wrote {len(names)} cameras" in stdout
    assert_same(load_calibration(out), load_calibration(DATA / name, **options), tol=0)
    rc, stdout, err = cli(capsys, "calib", "show", DATA / name, *extra)
    assert rc == 0, err
    lines = stdout.splitlines()
    assert f"{len(names)} cameras ({fmt};" in lines[0]
    assert lines[1].split()[:4] == ["camera", "size", "fx", "fy"]
    assert [line.split()[0] for line in lines[2:-1]] == names
    assert lines[-1].startswith("up axis: +z (found from the cameras)")


@pytest.mark.parametrize("fmt", [f for f in WRITE_FORMATS if f != "json"])
def test_cli_convert_from_json(tmp_path, capsys, fmt):
    out = tmp_path / OUT_NAME[fmt]
    rc, stdout, err = cli(capsys, "calib", "convert", DATA / "json" / "calibration.json", out, "--format", fmt)
    assert rc == 0, err
    assert out.exists()
    assert_same(load_calibration(out), load_calibration(DATA / "json" / "calibration.json"))


def test_cli_toml_defaults_to_pose2sim_and_size_option(tmp_path, capsys):
    rc, _, err = cli(capsys, "calib", "convert", DATA / "opencv_xml", tmp_path / "c.toml")
    assert rc == 0, err
    assert detect_format(tmp_path / "c.toml") == "pose2sim"
    folder = copy_fixture(tmp_path, "opencv_xml_subfolders")
    edit(folder / "left" / "calibration.xml", "<image_width>640</image_width>\n<image_height>480</image_height>\n", "")
    rc, stdout, err = cli(capsys, "calib", "show", folder)
    assert rc == 0, err
    assert err.count("\n") == 1 and "no image size for left;" in err and "--size" in err
    assert "left    627x488*" in stdout and "right   640x480 " in stdout  # 2 x (313.27, 243.81)
    assert stdout.splitlines()[-2].startswith("* size guessed as twice the principal point: left")
    rc, stdout, err = cli(capsys, "calib", "show", folder, "--size", "640x480")
    assert rc == 0 and err == "" and "*" not in stdout
    rc, _, err = cli(capsys, "calib", "show", folder, "--size", "640by480")
    assert rc == 2 and "--size: expected WIDTHxHEIGHT" in err


def test_cli_output_needs_format(tmp_path, capsys):
    rc, _, err = cli(capsys, "calib", "convert", DATA / "json" / "calibration.json", tmp_path / "out")
    assert rc == 2
    assert err.count("\n") == 1 and "pass --format" in err
    rc, _, err = cli(capsys, "calib", "convert", DATA / "anipose" / "calibration.toml", tmp_path / "a.json")
    assert rc == 2
    assert "calibration.toml: units:" in err and "pass --units mm" in err
    assert not (tmp_path / "a.json").exists()


# ----------------------------------------------------------------------------- bad input

BAD = [
    # (fixture, file to edit inside it or "", old text, new text, expected message parts)
    ("pose2sim/Calib.toml", "", 'matrix = [ [ 1895', 'matrices = [ [ 1895', ["Calib.toml: cam_02.matrix: missing"]),
    ("pose2sim/Calib.toml", "", "translation = [ 1.08", 'translation = [ "a", 1.08',
     ["Calib.toml: cam_01.translation: not numeric"]),
    ("pose2sim/Calib.toml", "", "size = [ 1088.0, 1920.0]", "size = [ 1088.5, 1920.0]",
     ["Calib.toml: cam_01.size: expected a whole number of pixels"]),
    ("pose2sim/Calib.toml", "", "fisheye = false", "fisheye = true", ["Calib.toml: cam_01.fisheye: fisheye"]),
    ("pose2sim/Calib.toml", "", "rotation = [ 1.27", "rotation = [ 0.0, 1.27",
     ["Calib.toml: cam_01.rotation: expected a Rodrigues"]),
    ("pose2sim/Calib.toml", "", "matrix = [ [ 2058", "matrix = [ [ -2058",
     ["Calib.toml: cam_01.matrix: expected [[fx"]),
    ("pose2sim/Calib.toml", "", "[cam_02]", "[cam_02", ["Calib.toml: not valid TOML"]),
    ("anipose/calibration.toml", "", "distortions = [ -0.18", "distortions = [ true, -0.18",
     ["calibration.toml: cam_0.distortions: not numeric"]),
    ("easymocap", "intri.yml", "rows: 3\r\n  cols: 3\r\n  dt: d\r\n  data: [1158.047983, 0.000000, 958.129311, ",
     "rows: 2\r\n  cols: 3\r\n  dt: d\r\n  data: [", ["intri.yml: K_01: expected shape (3, 3)"]),
    ("easymocap", "intri.yml", "data: [1158.047983, 0.000000, ", "data: [", ["intri.yml: K_01: data has 7 values"]),
    ("easymocap", "intri.yml", "dist_02:", "distortion_02:", ["intri.yml: dist_02: missing"]),
    ("easymocap", "intri.yml", "names:", "cameras:", ["intri.yml: names: missing"]),
    ("easymocap", "intri.yml", "data: [1158.047983", "data: [fx", ["intri.yml: K_01: not numeric"]),
    ("easymocap", "intri.yml", "names:\r\n", "names: [\r\n", ["intri.yml: not valid OpenCV YAML"]),
    ("easymocap", "extri.yml", "T_03:", "Tvec_03:", ["extri.yml: T_03: missing"]),
    ("opencv_xml", "cam1.xml", "Translation", "Position",
     ["cam1.xml: Translation: missing (also accepted: T, tvec)"]),
    ("opencv_xml", "cam10.xml", "<dt>d</dt>\n  <data>\n    8.", "<dt>d</dt>\n  <data>\n    9.",  # in rotation_matrix
     ["cam10.xml: rotation_matrix: not a rotation"]),
    ("opencv_xml", "cam2.xml", "<ImageSize>\n  1280 720", "<ImageSize>\n  1280",
     ["cam2.xml: ImageSize: expected 2 values"]),
    ("opencv_xml", "cam2.xml", "<data>\n    7.18", "<data>\n    seven", ["cam2.xml: camera_matrix: not numeric"]),
    ("opencv_xml", "cam1.xml", "</opencv_storage>", "", ["cam1.xml: not valid XML"]),
    ("opencv_xml", "cam1.xml", "opencv_storage>", "storage>", ["cam1.xml: <root>: expected <opencv_storage>"]),
    ("json/calibration.json", "", '"width": 320', '"width": "wide"',
     ["calibration.json: cam1.width: expected a whole number >= 1, got the text 'wide'"]),
    ("json/calibration.json", "", '"format"', '{"format"', ["calibration.json: not valid JSON"]),
    ("json/calibration.json", "", '"width": 320', '"size_guessed": "yes", "width": 320',
     ["calibration.json: cameras[0].size_guessed: expected true or false"]),
    ("../calibration/qualisys/Calib.qca.txt", "", "<intrinsic ", "<intrinsics ",
     ["Calib.qca.txt: 21876.intrinsics: not a field we know; did you mean intrinsic?"]),
    ("../calibration/qualisys/Calib.qca.txt", "", 'focalLengthU="1', 'focalLengthU="f1',
     ["Calib.qca.txt: 21876.intrinsic.focalLengthU: not numeric"]),
    ("../calibration/qualisys/Calib.qca.txt", "", 'centerPointV="', 'centerPointW="',
     ["Calib.qca.txt: 21876.intrinsic.centerPointW: not a field we know; did you mean centerPointV?"]),
    ("../calibration/qualisys/Calib.qca.txt", "", 'viewrotation="90"', 'viewrotation="45"',
     ["Calib.qca.txt: 21878.viewrotation: expected one of (0, 90, 180, 270), got '45'"]),
    ("../calibration/qualisys/Calib.qca.txt", "", ' r23="', ' r23x="',
     ["Calib.qca.txt: 21876.transform.r23: missing"]),
    ("../calibration/qualisys/Calib.qca.txt", "", 'model="Miqus Video"', 'model="Miqus M5"',
     ["Calib.qca.txt: cameras: only marker cameras"]),
    ("../calibration/projection", "cam0.txt", " -2.6928117659925137", "",
     ["cam0.txt: P: expected a 3x4 projection matrix (12 numbers), got 11 numbers"]),
    ("../calibration/projection", "cam2.xml", "<cols>4</cols>", "<cols>3</cols>",
     ["cam2.xml: P: data has 12 values, expected rows x cols = 3 x 3"]),
    ("../calibration/projection", "cam3.xml", "0.6021884868512882 -1.9467116692959197 0.382073167044072",
     "-984.6160922250725 -1668.6248083965163 244.33579032468407", ["cam3.xml: ProjectionMatrix: singular"]),
    ("../calibration/uu_layout", "cam2/config.xml", "Translation", "Position",
     ["cam2/config.xml: Translation: missing"]),
    ("../calibration/uu_layout", "cam1/config.xml", "<data>\n    4.", "<data>\n    -4.",
     ["cam1/config.xml: CameraMatrix: expected [[fx"]),
    # a misspelt field that the reader would pass over (the camera losing its distortion, its
    # size, its image's turn): our JSON knows every key, other files may hold other tools'
    ("json/calibration.json", "", '"dist"', '"dsit"',
     ["calibration.json: cam1.dsit: not a field we know; did you mean dist?"]),
    ("json/calibration.json", "", '"format"', '"fromat"', ["calibration.json: fromat: not a field we know; "
                                                          "did you mean format?"]),
    ("json/calibration.json", "", '"width": 320', '"foo": 1, "width": 320',
     ["calibration.json: cam1.foo: not a field we know; the fields are name, K, dist, R, t, width, height, "
      "size_guessed"]),
    ("../calibration/uu_layout", "cam2/config.xml", "DistortionCoeffs", "DistortionCoeffz",
     ["cam2/config.xml: DistortionCoeffz: not a field we know; did you mean DistortionCoeffs?"]),
    ("opencv_xml", "cam1.xml", "image_height>", "Image_Heigth>",
     ["cam1.xml: Image_Heigth: not a field we know; did you mean image_height?"]),
    ("opencv_xml", "cam1.xml", "Translation", "Translaton",
     ["cam1.xml: Translaton: not a field we know; did you mean Translation?"]),
    ("easymocap", "intri.yml", "dist_02:", "dsit_02:", ["intri.yml: dsit_02: not a field we know; "
                                                        "did you mean dist_02?"]),
    ("easymocap", "intri.yml", "H_03:", "H_3:", ["intri.yml: H_3: not a field we know; did you mean H_03?"]),
    ("pose2sim/Calib.toml", "", "distortions = [ -0.3200", "distortion = [ -0.3200",
     ["Calib.toml: cam_02.distortion: not a field we know; did you mean distortions?"]),
    ("anipose/calibration.toml", "", "size = [", "Size = [",
     ["calibration.toml: cam_0.Size: not a field we know; did you mean size?"]),
    ("../calibration/qualisys/Calib.qca.txt", "", 'viewrotation="90"', 'viewRotation="90"',
     ["Calib.qca.txt: 21878.viewRotation: not a field we know; did you mean viewrotation?"]),
    ("../calibration/qualisys/Calib.qca.txt", "", "<fov_video ", "<fov_vidoe ",
     ["Calib.qca.txt: 21876.fov_vidoe: not a field we know; did you mean fov_video?"]),
    ("../calibration/qualisys/Calib.qca.txt", "", 'radialDistortion3="-0.009895"', 'radialDistortoin3="-0.009895"',
     ["Calib.qca.txt: 21876.intrinsic.radialDistortoin3: not a field we know; did you mean radialDistortion3?"]),
]


@pytest.mark.parametrize("fixture, inner, old, new, expected", BAD,
                         ids=[f"{b[0]}:{b[4][0].split(': ')[1]}" for b in BAD])
def test_bad_input(tmp_path, capsys, fixture, inner, old, new, expected):
    path = copy_fixture(tmp_path, fixture)
    edit(path / inner if inner else path, old, new)
    with pytest.raises(CalibrationError) as info:
        load_calibration(path, units="mm" if "anipose" in fixture else None)
    for part in expected:
        assert part in str(info.value)
    rc, stdout, err = cli(capsys, "calib", "show", path, *(["--units", "mm"] if "anipose" in fixture else []))
    assert rc == 2
    assert stdout == "" and err.count("\n") == 1
    assert err.startswith("mocap calib show: error: " + str(path))
    for part in expected:
        assert part in err


def test_other_tools_fields_are_read_past(tmp_path):
    """Files that other tools wrote with fields of their own load as without them: OpenCV's
    calibration sample, EasyVolcap's EasyMocap files, FreeMocap's TOML."""
    folder = copy_fixture(tmp_path, "../calibration/uu_layout")
    edit(folder / "cam1" / "config.xml", "</opencv_storage>",
         "<calibration_time>Mon Mar 18</calibration_time>\n<nframes>25</nframes>\n<board_width>8</board_width>\n"
         "<square_size>115.</square_size>\n<avg_reprojection_error>0.31</avg_reprojection_error>\n"
         "<image_points>1 2</image_points>\n<P1>1 0 0</P1>\n<Q>1</Q>\n<distortion_model>plumb_bob"
         "</distortion_model>\n</opencv_storage>")
    assert_same(load_calibration(folder, units="mm", warn=lambda line: None),
                load_calibration(NEW / "uu_layout", units="mm", warn=lambda line: None), tol=0)
    folder = copy_fixture(tmp_path, "easymocap")
    edit(folder / "intri.yml", "H_01:", "ccm_01: 1\r\nH_01:")
    edit(folder / "extri.yml", "T_01:", "t_01: 0.5\r\nn_01: 0.1\r\nf_01: 9.0\r\nbounds_01: 2\r\nT_01:")
    assert_same(load_calibration(folder), load_calibration(DATA / "easymocap"), tol=0)
    path = copy_fixture(tmp_path, "anipose/calibration.toml")
    edit(path, "translation = [", "world_position = [ 1.0, 2.0, 3.0,]\nworld_orientation = [ 0.0,]\ntranslation = [")
    assert_same(load_calibration(path, units="mm"), load_calibration(DATA / "anipose" / "calibration.toml",
                                                                     units="mm"), tol=0)


def test_missing_and_empty_inputs(tmp_path, capsys):
    rc, _, err = cli(capsys, "calib", "show", tmp_path / "nothing.toml")
    assert rc == 2 and "nothing.toml: does not exist" in err
    rc, _, err = cli(capsys, "calib", "show", tmp_path)
    assert rc == 2 and f"{tmp_path}: <folder>: no calibration found" in err
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.xml").write_text("<opencv_storage/>")
    (tmp_path / "a" / "y.xml").write_text("<opencv_storage/>")
    rc, _, err = cli(capsys, "calib", "show", tmp_path)  # files without camera fields are no calibration
    assert rc == 2 and f"{tmp_path}: <folder>: no calibration found" in err
    shutil.copy(DATA / "opencv_xml" / "cam1.xml", tmp_path / "a" / "x.xml")
    shutil.copy(DATA / "opencv_xml" / "cam2.xml", tmp_path / "a" / "y.xml")
    rc, _, err = cli(capsys, "calib", "show", tmp_path)
    assert rc == 2 and err.count("\n") == 1
    assert "a: <folder>: more than one file holds a camera (K, R, t or P): x.xml, y.xml; keep one" in err
    shutil.rmtree(tmp_path / "a")
    folder = copy_fixture(tmp_path, "easymocap")
    (folder / "extri.yml").unlink()
    with pytest.raises(CalibrationError, match=r"extri\.yml: does not exist"):
        load_calibration(folder, fmt="easymocap")
    assert load_calibration(DATA / "easymocap" / "intri.yml").names == ["01", "02", "03", "04"]


def test_bad_camera_names_for_format(tmp_path):
    cam = random_studio(4, 1)[0]
    studio = Studio((Camera("left/front", cam.K, cam.dist, cam.R, cam.t, cam.width, cam.height),))
    with pytest.raises(CalibrationError, match=r"left/front\.name: cannot be written"):
        save_calibration(studio, tmp_path / "em", "easymocap")
    with pytest.raises(CalibrationError, match=r"left/front\.name: cannot be written"):
        save_calibration(studio, tmp_path / "xml", "opencv-xml")
    save_calibration(studio, tmp_path / "c.toml")  # TOML quotes any name
    assert load_calibration(tmp_path / "c.toml").names == ["left/front"]



# ----------------------------------------------------------------------------- image sizes: optional, guessed

def guess(cam: Camera) -> tuple[int, int]:
    """Twice the principal point, rounded half up: what a reader without a size puts in."""
    return int(np.floor(2 * cam.K[0, 2] + 0.5)), int(np.floor(2 * cam.K[1, 2] + 0.5))


def drop_lines(path: Path, pattern: str) -> None:
    """Remove every line matching ``pattern`` (line endings kept)."""
    text = path.read_bytes().decode()
    kept = "".join(line for line in text.splitlines(keepends=True) if not re.search(pattern, line))
    assert kept != text, f"{pattern!r} not in {path}"
    path.write_bytes(kept.encode())


SIZELESS = [
    # (fixture, file inside it or "", line pattern holding the size, load options)
    ("easymocap", "intri.yml", r"^[HW]_", {}),
    ("pose2sim/Calib.toml", "", r"^size = ", {}),
    ("anipose/calibration.toml", "", r"^size = ", {"units": "mm"}),
    ("opencv_xml", "cam1.xml", r"image_(width|height)", {}),
    ("../calibration/qualisys/Calib.qca.txt", "", r"<fov_video ", {}),
]


@pytest.mark.parametrize("fixture, inner, pattern, options", SIZELESS, ids=[f[0] for f in SIZELESS])
def test_size_optional_in_every_format(tmp_path, fixture, inner, pattern, options):
    path = copy_fixture(tmp_path, fixture)
    before = load_calibration(path, warn=lambda line: None, **options)
    drop_lines(path / inner if inner else path, pattern)
    if "qualisys" in fixture:  # turning an image needs its size
        edit(path, 'viewrotation="90"', 'viewrotation="0"')
    warnings = []
    studio = load_calibration(path, warn=warnings.append, **options)
    guessed = [c.name for c in studio if c.size_guessed]
    size_lines = [line for line in warnings if "no image size" in line]
    assert guessed and len(size_lines) == 1
    assert f"no image size for {', '.join(guessed)}; guessed as twice the principal point" in size_lines[0]
    for cam in studio:
        assert (cam.width, cam.height) == (guess(cam) if cam.size_guessed else (before.camera(cam.name).width,
                                                                                 before.camera(cam.name).height))
    if "qualisys" not in fixture:  # (the Qualisys principal point moves with fov_video's left/top)
        assert_same(Studio(tuple(Camera(c.name, c.K, c.dist, c.R, c.t, 1, 1) for c in studio)),
                    Studio(tuple(Camera(c.name, c.K, c.dist, c.R, c.t, 1, 1) for c in before)), tol=0)
    warnings.clear()
    sized = load_calibration(path, size=(1280, 720), warn=warnings.append, **options)
    assert not any(c.size_guessed for c in sized) and not any("no image size" in line for line in warnings)
    assert all((c.width, c.height) == (1280, 720) for c in sized if c.name in guessed)


def test_easymocap_as_write_intri_writes_it(tmp_path, capsys):
    folder = NEW / "easymocap_write_intri"
    intri = (folder / "intri.yml").read_bytes()
    assert intri.startswith(b'%YAML:1.0\r\n---\r\nnames:\r\n  - "1"\r\n') and b"H_" not in intri and b"W_" not in intri
    assert b"dist_1: !!opencv-matrix\r\n  rows: 1\r\n  cols: 5\r\n  dt: d\r\n  data: [-0.170000, " in intri
    warnings = []
    studio = load_calibration(folder, warn=warnings.append)
    assert studio.names == ["1", "2", "3"]
    assert [(c.width, c.height) for c in studio] == [(1921, 1083), (1929, 1077), (1937, 1071)]  # 2 x (960.3, 541.7) ...
    assert all(c.size_guessed for c in studio)
    assert warnings == [f"{folder}: no image size for 1, 2, 3; guessed as twice the principal point "
                        "(pass --size WxH or --size-from CAMERA=PATH; import-video takes it from the videos)"]
    rc, stdout, err = cli(capsys, "calib", "show", folder)
    assert rc == 0 and err.count("\n") == 1 and err.startswith("warning: ") and "1, 2, 3" in err
    assert "1921x1083*" in stdout and "* size guessed as twice the principal point: 1, 2, 3" in stdout
    rc, stdout, err = cli(capsys, "calib", "show", folder, "--size", "1920x1080")
    assert rc == 0 and err == "" and "1920x1080 " in stdout and "*" not in stdout
    # written back to EasyMocap without the guessed H_/W_, read back the same
    save_calibration(studio, tmp_path / "em", "easymocap")
    assert b"H_1" not in (tmp_path / "em" / "intri.yml").read_bytes()
    back = load_calibration(tmp_path / "em", warn=lambda line: None)
    assert_same(back, studio) and all(c.size_guessed for c in back)


def test_size_guessed_in_json_and_xml(tmp_path):
    studio = load_calibration(NEW / "uu_layout", units="mm", warn=lambda line: None)
    half = with_image_sizes(studio, {"cam2": (644, 486)}, "cam2/video.avi")
    save_calibration(half, tmp_path / "c.json")
    doc = json.loads((tmp_path / "c.json").read_text())
    assert [c.get("size_guessed") for c in doc["cameras"]] == [True, None, True]  # written only when true
    back = load_calibration(tmp_path / "c.json")
    assert [c.size_guessed for c in back] == [True, False, True]
    assert_same(back, half, tol=0)
    save_calibration(back, tmp_path / "xml", "opencv-xml")
    assert "image_width" not in (tmp_path / "xml" / "cam1.xml").read_text()
    assert "<image_width>644</image_width>" in (tmp_path / "xml" / "cam2.xml").read_text()
    again = load_calibration(tmp_path / "xml", warn=lambda line: None)
    assert [c.size_guessed for c in again] == [True, False, True]
    assert_same(again, half)
    assert back.scaled(0.5)[0].size_guessed and not back.scaled(0.5)[1].size_guessed


def test_with_image_sizes():
    studio = load_calibration(NEW / "uu_layout", units="mm", warn=lambda line: None)
    fixed = with_image_sizes(studio, {"cam1": (644, 486), "cam3": (644, 486)}, "videos")
    assert [(c.width, c.height, c.size_guessed) for c in fixed] == [(644, 486, False), (657, 453, True),
                                                                     (644, 486, False)]
    assert fixed.source == studio.source
    assert_same(Studio(tuple(Camera(c.name, c.K, c.dist, c.R, c.t, 1, 1) for c in fixed)),
                Studio(tuple(Camera(c.name, c.K, c.dist, c.R, c.t, 1, 1) for c in studio)), tol=0)
    assert with_image_sizes(fixed, {"cam1": (644, 486)}, "videos")[0].width == 644  # agrees: kept
    known = load_calibration(DATA / "opencv_xml")  # 1280x720 from the files
    with pytest.raises(CalibrationError) as info:
        with_image_sizes(known, {"cam1": (1280, 720), "cam2": (640, 360)}, "videos/cam2.mp4")
    assert str(info.value) == (f"{DATA / 'opencv_xml'}: cam2.size: the calibration says 1280x720 "
                               "but the images (videos/cam2.mp4) are 640x360")
    with pytest.raises(CalibrationError, match=r"cameras: no camera 'cam7' for the images of videos \(cameras: cam1"):
        with_image_sizes(known, {"cam7": (640, 360)}, "videos")


def test_guessed_sizes_are_not_written_as_measured(tmp_path, capsys):
    """Pose2Sim and Anipose files always hold a size, which every reader takes for the images':
    a guess is refused there (one line naming OUT and the cameras), written once given."""
    folder = NEW / "uu_layout"  # config.xml files without image sizes
    for name, fmt in (("c.toml", "pose2sim"), ("a.toml", "anipose")):
        out = tmp_path / name
        rc, stdout, err = cli(capsys, "calib", "convert", folder, out, "--units", "mm", "--format", fmt)
        assert rc == 2 and stdout == "" and err.count("\n") == 1 and not out.exists()
        assert err.startswith(f"mocap calib convert: error: {out}: size: no image size for cam1, cam2, cam3 (guessed "
                              f"as twice the principal point), and a {fmt} file cannot mark a size as guessed")
        assert "--size WxH" in err and "--size-from CAMERA=VIDEO" in err and ".json" in err
    with pytest.raises(CalibrationError, match=r"lib\.toml: size: no image size for cam1, cam2, cam3"):
        save_calibration(load_calibration(folder, units="mm", warn=lambda line: None), tmp_path / "lib.toml")
    rc, _, err = cli(capsys, "calib", "convert", folder, tmp_path / "c.toml", "--units", "mm", "--size", "644x486")
    assert rc == 0, err
    written = load_calibration(tmp_path / "c.toml")
    assert [(c.width, c.height, c.size_guessed) for c in written] == [(644, 486, False)] * 3


def test_size_from_the_images(tmp_path, capsys):
    """--size-from CAMERA=PATH (an image, a folder of frames, a video) puts in the images' size
    for a guessed one and must agree with a size the file gives."""
    for cam, size in (("cam1", (644, 486)), ("cam2", (640, 480))):
        Image.new("RGB", size).save(tmp_path / f"{cam}.png")
    (tmp_path / "cam3").mkdir()
    Image.new("RGB", (320, 240)).save(tmp_path / "cam3" / "000007.png")
    sources = [f"cam1={tmp_path / 'cam1.png'}", f"cam2={tmp_path / 'cam2.png'}", f"cam3={tmp_path / 'cam3'}"]
    out = tmp_path / "c.toml"
    rc, _, err = cli(capsys, "calib", "convert", NEW / "uu_layout", out, "--units", "mm", "--size-from", *sources)
    assert rc == 0, err
    assert err.count("\n") == 1 and "skipped (no camera fields)" in err  # no guessed size left to name
    assert [(c.width, c.height) for c in load_calibration(out)] == [(644, 486), (640, 480), (320, 240)]
    rc, stdout, err = cli(capsys, "calib", "show", NEW / "uu_layout", "--units", "mm", "--size-from", sources[0])
    assert rc == 0 and "no image size for cam2, cam3;" in err
    assert [line.split()[:2] for line in stdout.splitlines()[2:4]] == [["cam1", "644x486"], ["cam2", "657x453*"]]
    rc, _, err = cli(capsys, "calib", "show", DATA / "opencv_xml", "--size-from", sources[1])
    assert rc == 2 and err.count("\n") == 1
    assert "opencv_xml: cam2.size: the calibration says 1280x720 but the images (--size-from) are 640x480" in err
    for args, message in ((["cam1"], "--size-from: expected CAMERA=PATH, got 'cam1'"),
                          ([sources[0].replace("cam1=", "cam7=")], "cameras: no camera 'cam7' for the images of "
                                                                  "--size-from"),
                          ([f"cam1={tmp_path / 'none.png'}"], "none.png: --size-from cam1: does not exist"),
                          ([sources[0], sources[0]], "--size-from cam1: given twice")):
        rc, stdout, err = cli(capsys, "calib", "show", NEW / "uu_layout", "--units", "mm", "--size-from", *args)
        assert rc == 2 and stdout == "" and err.count("\n") == 1 and message in err, err


def test_a_guess_passed_off_as_measured_is_named_when_the_images_disagree(tmp_path, capsys):
    """A Calib.toml whose sizes are twice the principal point (what Pose2Sim's converters write
    without one): import-video's refusal says the size may have been a guess."""
    studio = load_calibration(NEW / "uu_layout", units="mm", warn=lambda line: None)
    calib = tmp_path / "Calib.toml"
    save_calibration(Studio(tuple(replace(c, size_guessed=False) for c in studio)), calib)
    for name in studio.names:  # a file each: two cameras given one file is refused first
        Image.new("RGB", (644, 486)).save(tmp_path / f"{name}.png")
    rc, _, err = cli(capsys, "import-video", "--calibration", calib, "--out", tmp_path / "seq",
                     "--video", *(f"{name}={tmp_path / f'{name}.png'}" for name in studio.names))
    assert rc == 2 and err.count("\n") == 1 and not (tmp_path / "seq").exists()
    assert err.endswith(f"{calib}: cam1.size: the calibration says 663x449 but the images (--video) are 644x486; "
                        "663x449 is twice the principal point, the size a converter guesses for a camera without "
                        "one: if it was guessed, put the images' size in the calibration\n")


# ----------------------------------------------------------------------------- folders with other files

def test_folder_skips_files_without_camera_fields(tmp_path, capsys):
    folder = NEW / "uu_layout"
    assert detect_format(folder) == "opencv-xml"
    warnings = []
    studio = load_calibration(folder, units="mm", warn=warnings.append)
    assert studio.names == ["cam1", "cam2", "cam3"]
    assert warnings[0] == (f"{folder}: skipped (no camera fields): checkerboard.xml, cam1/intrinsics.xml, "
                           "cam2/intrinsics.xml, cam3/intrinsics.xml")
    assert len(warnings) == 2 and "no image size for cam1, cam2, cam3" in warnings[1]
    cam1 = studio.camera("cam1")
    assert cam1.K[0, 0] == pytest.approx(491.7564, abs=1e-9)  # config.xml's, not intrinsics.xml's 393.4
    assert cam1.dist[0] == pytest.approx(-0.3587, abs=1e-12)
    assert (cam1.width, cam1.height) == (663, 449)  # 2 x (331.690674, 224.39888)
    np.testing.assert_allclose([c.center for c in studio], [[3.4, 4.4, -1.8], [0.3, 4.6, -1.7], [-3.5, 0.1, -2.1]],
                               atol=1e-9)  # millimetres, world z down as in the lab's files
    out = tmp_path / "out.json"
    rc, stdout, err = cli(capsys, "calib", "convert", folder, out, "--units", "mm")
    assert rc == 0, err
    assert err.count("\n") == 2 and "skipped (no camera fields): checkerboard.xml" in err
    assert_same(load_calibration(out), studio, tol=0)
    rc, _, err = cli(capsys, "calib", "convert", folder, tmp_path / "again.json")
    assert rc == 2 and err.count("\n") == 1 and "pass --units mm" in err


def test_folder_camera_choice(tmp_path):
    folder = copy_fixture(tmp_path, "../calibration/uu_layout")
    shutil.copy(folder / "cam2" / "config.xml", folder / "cam2" / "config_old.xml")
    with pytest.raises(CalibrationError) as info:
        load_calibration(folder, units="mm")
    assert str(info.value) == (f"{folder / 'cam2'}: <folder>: more than one file holds a camera (K, R, t or P): "
                               "config.xml, config_old.xml; keep one")
    (folder / "cam2" / "config_old.xml").unlink()
    for sub in ("cam1", "cam2", "cam3"):  # one camera per file at the top: the board is still skipped
        shutil.move(folder / sub / "config.xml", folder / f"{sub}.xml")
    warnings = []
    studio = load_calibration(folder, units="mm", warn=warnings.append)
    assert_same(studio, load_calibration(NEW / "uu_layout", units="mm", warn=lambda line: None), tol=0)
    assert warnings[0] == f"{folder}: skipped (no camera fields): checkerboard.xml"
    (folder / "cam4.xml").write_text((folder / "cam1" / "intrinsics.xml").read_text())  # at the top: a camera
    with pytest.raises(CalibrationError, match=r"cam4\.xml: Rotation: missing"):
        load_calibration(folder, units="mm")


def test_other_tools_xml_and_damaged_notes_in_a_folder_are_skipped(tmp_path, capsys):
    """Files that name no camera fields are passed over whatever they hold (another tool's
    project file, notes that do not parse); one that names them is a damaged camera, refused."""
    folder = copy_fixture(tmp_path, "../calibration/uu_layout")
    (folder / "project.xml").write_text("<project><name>lab</name><p>seated take</p></project>")
    (folder / "notes.xml").write_text("<notes>board moved after cam2 <b>was</notes>")
    warnings = []
    studio = load_calibration(folder, units="mm", warn=warnings.append)
    assert studio.names == ["cam1", "cam2", "cam3"]
    assert warnings[0] == (f"{folder}: skipped (no camera fields): checkerboard.xml, notes.xml, project.xml, "
                           "cam1/intrinsics.xml, cam2/intrinsics.xml, cam3/intrinsics.xml")
    rc, _, err = cli(capsys, "calib", "convert", folder, tmp_path / "out.json", "--units", "mm")
    assert rc == 0 and "skipped (no camera fields): checkerboard.xml, notes.xml, project.xml" in err
    (folder / "cam4.xml").write_text("<camera><Rotation>1 0 0</Rotation><Translation>0 0 0</Translation></camera>")
    for sub in ("cam1", "cam2", "cam3"):  # cameras at the top: the damaged one is read and refused
        shutil.move(folder / sub / "config.xml", folder / f"{sub}.xml")
    with pytest.raises(CalibrationError, match=r"cam4\.xml: <root>: expected <opencv_storage>, got <camera>"):
        load_calibration(folder, units="mm")
    (folder / "cam4.xml").write_text("<opencv_storage><Rotation>1 0 0</Rotation><Translation>0 0")
    with pytest.raises(CalibrationError, match=r"cam4\.xml: not valid XML"):
        load_calibration(folder, units="mm")
    whole = (folder / "cam1.xml").read_text()
    for cut in (whole.index("<Rotation") + 4, whole.index("<CameraMatrix") + 3):  # a file cut short
        (folder / "cam4.xml").write_text(whole[:cut])
        with pytest.raises(CalibrationError, match=r"cam4\.xml: not valid XML"):
            load_calibration(folder, units="mm")


@pytest.mark.skipif(not REAL_UU.is_dir(), reason="needs the shared real recordings")
def test_real_uu_folder(tmp_path, capsys):
    out = tmp_path / "calibration.json"
    rc, stdout, err = cli(capsys, "calib", "convert", REAL_UU, out, "--units", "mm")
    assert rc == 0, err
    assert err.count("\n") == 2
    assert "skipped (no camera fields): checkerboard.xml, cam1/intrinsics.xml, cam2/intrinsics.xml" in err
    assert "no image size for cam1, cam2, cam3, cam4" in err
    studio = load_calibration(out)
    assert studio.names == ["cam1", "cam2", "cam3", "cam4"]
    for cam in studio:
        assert cam.size_guessed and (cam.width, cam.height) == guess(cam)
        assert -2.2 < cam.center[2] < -1.6  # the board's world z points down
        assert cam.dist[0] < -0.3  # strong barrel distortion
    real = with_image_sizes(studio, {name: (644, 486) for name in studio.names}, str(REAL_UU / "*/video.avi"))
    assert all((c.width, c.height) == (644, 486) and not c.size_guessed for c in real)
    toml = tmp_path / "Calib.toml"  # Pose2Sim's file holds the videos' size, never a guess
    sources = [f"{name}={REAL_UU / name / 'video.avi'}" for name in studio.names]
    rc, _, err = cli(capsys, "calib", "convert", REAL_UU, toml, "--units", "mm", "--size-from", *sources)
    assert rc == 0 and err.count("\n") == 1 and "skipped (no camera fields)" in err
    assert_same(load_calibration(toml), real)


def one_line(err: str) -> str:
    """The one error line of a refused command (no traceback)."""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


@pytest.mark.timeout(60)
def test_a_folder_holding_two_calibrations_is_refused(tmp_path, capsys):
    """calibration.json converted from the lab's XML files into their folder, then edited: which of
    the two is meant is not known, so the folder is refused naming both, and each is read when given."""
    folder = copy_fixture(tmp_path, "../calibration/uu_layout")
    rc, _, err = cli(capsys, "calib", "convert", folder, folder / "calibration.json", "--units", "mm")
    assert rc == 0, err
    edit(folder / "calibration.json", '"name": "cam1"', '"name": "cam1_moved"')
    expected = (f"{folder}: <folder>: holds 2 calibrations: calibration.json and 3 camera files (cam1/config.xml, "
                "cam2/config.xml, cam3/config.xml); give the file to use, or move the others out of the folder")
    with pytest.raises(CalibrationError) as info:
        load_calibration(folder, units="mm")
    assert str(info.value) == expected
    with pytest.raises(CalibrationError, match="holds 2 calibrations"):
        detect_format(folder)
    for argv in (["calib", "show", folder, "--units", "mm"],
                 ["calib", "convert", folder, tmp_path / "out.json", "--units", "mm"],
                 ["import-video", "--calibration", folder, "--video", "cam1=cam1.avi", "--out", tmp_path / "seq",
                  "--units", "mm"]):
        rc, _, err = cli(capsys, *argv)
        assert rc == 2 and one_line(err).endswith(expected), argv
    assert not (tmp_path / "out.json").exists() and not (tmp_path / "seq").exists()
    edited = load_calibration(folder / "calibration.json")  # each is read when given by name
    assert edited.names == ["cam1_moved", "cam2", "cam3"]
    assert load_calibration(folder / "cam1" / "config.xml", units="mm", warn=lambda line: None).names == ["config"]

    # EasyMocap's files beside them make three; the intrinsics-only files and the board are none
    save_calibration(edited, folder, fmt="easymocap")
    rc, _, err = cli(capsys, "calib", "show", folder)
    assert rc == 2 and one_line(err).endswith(
        "holds 3 calibrations: intri.yml + extri.yml, calibration.json and 3 camera files (cam1/config.xml, "
        "cam2/config.xml, cam3/config.xml); give the file to use (intri.yml for EasyMocap), or move the others "
        "out of the folder")
    assert "intrinsics.xml" not in err and "checkerboard" not in err
    assert_same(load_calibration(folder / "intri.yml"), edited)

    # the camera files alone are read as before; a folder whose one calibration is a file reads it
    alone = tmp_path / "alone"
    alone.mkdir()
    (folder / "calibration.json").rename(alone / "calibration.json")
    for name in EASYMOCAP_FILES:
        (folder / name).unlink()
    assert_same(load_calibration(folder, units="mm", warn=lambda line: None),
                load_calibration(NEW / "uu_layout", units="mm", warn=lambda line: None), tol=0)
    (alone / "notes.json").write_text('{"lab": "uu"}')  # not a calibration
    assert detect_format(alone) == "json"
    assert_same(load_calibration(alone), edited, tol=0)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("beside", ["Calib.toml", "rig.json", "Calib.qca.txt", "top-level xml"])
def test_any_second_calibration_in_a_folder_is_named(tmp_path, beside):
    folder = copy_fixture(tmp_path, "opencv_xml")
    if beside in ("Calib.toml", "rig.json"):  # a .json is ours by its "format", whatever its name
        save_calibration(load_calibration(folder), folder / beside)
    elif beside == "Calib.qca.txt":
        shutil.copy(NEW / "qualisys" / beside, folder / beside)
    else:  # camera files at the top and in sub-folders: two sets
        shutil.copytree(DATA / "opencv_xml_subfolders", folder, dirs_exist_ok=True)
        beside = "2 camera files (left/calibration.xml, right/calibration.xml)"
    (folder / "Config.toml").write_text('[calibration]\nunits = "mm"\n')  # a project's settings: no calibration
    with pytest.raises(CalibrationError) as info:
        load_calibration(folder)
    assert str(info.value).startswith(f"{folder}: <folder>: holds 2 calibrations: ")
    assert beside in str(info.value) and "3 camera files (cam1.xml, cam2.xml, cam10.xml)" in str(info.value)
    if beside.startswith("2 camera files"):  # --from says the kind, not which of the two sets
        with pytest.raises(CalibrationError, match="holds 2 calibrations"):
            load_calibration(folder, fmt="opencv-xml")


@pytest.mark.timeout(60)
@pytest.mark.skipif(not REAL_UU.is_dir(), reason="needs the shared real recordings")
def test_real_uu_folder_is_one_calibration(capsys):
    """Per-camera folders with config.xml and intrinsics.xml, and a checkerboard.xml: one calibration."""
    assert [kind for kind, _, _ in folder_calibrations(REAL_UU)] == ["camera"]
    rc, out, err = cli(capsys, "calib", "show", REAL_UU, "--units", "mm")
    assert rc == 0, err
    assert out.startswith(f"{REAL_UU}: 4 cameras (opencv-xml")
    assert "skipped (no camera fields): checkerboard.xml, cam1/intrinsics.xml" in err


# ----------------------------------------------------------------------------- Qualisys

def qualisys_reference(path: Path) -> dict:
    """serial -> function projecting (N, 3) world points (m) to pixels, straight from the raw attributes."""
    out = {}
    for elem in ET.parse(path).getroot().iter("camera"):
        if "Video" in elem.get("model"):
            out[elem.get("serial")] = _qualisys_projector(elem)
    return out


def _qualisys_projector(elem):
    a = {k: float(v) for k, v in elem.find("intrinsic").attrib.items()}
    tr = {k: float(v) for k, v in elem.find("transform").attrib.items()}
    fov = {k: float(v) for k, v in elem.find("fov_video").attrib.items()}
    M = np.array([[tr[f"r{i}{j}"] for j in "123"] for i in "123"])  # Pose2Sim's reading of r11..r33
    pos = np.array([tr["x"], tr["y"], tr["z"]])

    def project(X):
        q = (X * 1000.0 - pos) @ M.T  # Qualisys camera frame: x right, y up, z backwards
        x, y = q[:, 0] / -q[:, 2], q[:, 1] / q[:, 2]
        k1, k2, k3 = a["radialDistortion1"] / 64, a["radialDistortion2"] / 64, a["radialDistortion3"] / 64
        p1, p2 = a["tangentalDistortion1"] / 64, a["tangentalDistortion2"] / 64
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        u = a["focalLengthU"] / 64 * xd + a["centerPointU"] / 64 - fov["left"]
        v = a["focalLengthV"] / 64 * yd + a["centerPointV"] / 64 - fov["top"]
        if elem.get("viewrotation") == "90":  # the image turned clockwise
            u, v = (fov["bottom"] - fov["top"]) - v, u
        return np.stack([u, v], axis=-1)
    return project


def test_qualisys_projects_as_the_raw_numbers(capsys):
    path = NEW / "qualisys" / "Calib.qca.txt"
    assert detect_format(path) == detect_format(path.parent) == "qualisys"
    warnings = []
    studio = load_calibration(path, warn=warnings.append)
    assert studio.names == ["21876", "21877", "21878"]  # 21880 is a marker camera (Miqus M3)
    assert warnings == [f"{path}: skipped marker cameras (no video): 21880"]
    assert [(c.width, c.height) for c in studio] == [(1920, 1088), (1280, 1024), (1088, 1920)]
    assert not any(c.size_guessed for c in studio)
    points = np.random.default_rng(3).uniform([-0.5, -0.5, 0.2], [0.5, 0.5, 1.8], (50, 3))
    for serial, project in qualisys_reference(path).items():
        cam = studio.camera(serial)
        assert np.all(cam.depth(points) > 0)
        np.testing.assert_allclose(cam.project(points), project(points), rtol=0, atol=1e-7, err_msg=serial)
        uv = cam.project(points)
        assert np.all((uv > 0) & (uv < [cam.width, cam.height]))  # the actor is in view
    np.testing.assert_allclose(studio.camera("21876").center, [3.1, -2.0, 1.9], atol=1e-12)
    assert studio.camera("21876").dist[2] == pytest.approx(0.000642 / 64, abs=1e-15)  # "tangental", 1/64
    rc, stdout, err = cli(capsys, "calib", "show", path)
    assert rc == 0 and err.count("\n") == 1 and "3 cameras (qualisys;" in stdout
    rc, stdout, err = cli(capsys, "calib", "show", path, "--units", "m")  # the file's mm are used
    assert rc == 0 and f"{path}: units: the file says mm; --units m is for files that do not say" in err
    assert stdout.splitlines()[2].split()[4:7] == ["3.100", "-2.000", "1.900"]


@pytest.mark.parametrize("degrees", [90, 180, 270])
def test_qualisys_viewrotation_turns_the_image(tmp_path, degrees):
    path = copy_fixture(tmp_path, "../calibration/qualisys/Calib.qca.txt")
    edit(path, 'viewrotation="90"', 'viewrotation="0"')
    upright = load_calibration(path, warn=lambda line: None).camera("21878")
    edit(path, 'serial="21878" viewrotation="0"', f'serial="21878" viewrotation="{degrees}"')
    turned = load_calibration(path, warn=lambda line: None).camera("21878")
    points = np.random.default_rng(4).uniform([-0.5, -0.5, 0.2], [0.5, 0.5, 1.8], (30, 3))
    u, v = upright.project(points).T
    w, h = upright.width, upright.height
    expected = {90: (h - 1 - v, u, h, w), 180: (w - 1 - u, h - 1 - v, w, h), 270: (v, w - 1 - u, h, w)}[degrees]
    np.testing.assert_allclose(turned.project(points), np.stack(expected[:2], axis=-1), rtol=0, atol=1e-8)
    assert (turned.width, turned.height) == expected[2:]
    np.testing.assert_allclose(turned.center, upright.center, atol=1e-12)


# ----------------------------------------------------------------------------- projection matrices

def random_camera_P(rng, skew: float = 0.0):
    K = np.array([[rng.uniform(300, 3000), 0.0, rng.uniform(200, 1000)], [0.0, 0.0, rng.uniform(200, 700)],
                  [0.0, 0.0, 1.0]])
    K[1, 1] = K[0, 0] * rng.uniform(0.9, 1.1)
    K[0, 1] = skew * K[0, 0]
    R = rodrigues_to_matrix(rng.normal(size=3))
    t = rng.normal(0.0, 3.0, 3)
    scale = rng.uniform(0.01, 100.0) * rng.choice([-1.0, 1.0])  # P is defined up to any non-zero factor
    return scale * K @ np.hstack([R, t[:, None]]), K, R, t


def relative_error(P, Q) -> float:
    """|P - s Q| / |P| for the best factor s."""
    s = np.sum(P * Q) / np.sum(Q * Q)
    return float(np.linalg.norm(P - s * Q) / np.linalg.norm(P))


def test_projection_round_trip(tmp_path):
    rng = np.random.default_rng(11)
    for i in range(200):
        P, K, R, t = random_camera_P(rng, skew=rng.normal(0.0, 0.002) if i % 2 else 0.0)
        K2, R2, t2 = decompose_projection(P)
        assert K2[0, 0] > 0 and K2[1, 1] > 0 and K2[2, 2] == 1.0 and np.all(K2[[1, 2, 2], [0, 0, 1]] == 0)
        assert np.linalg.det(R2) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(K2, K, rtol=1e-9, atol=1e-9 * K[0, 0])
        np.testing.assert_allclose(R2, R, rtol=0, atol=1e-9)
        np.testing.assert_allclose(t2, t, rtol=0, atol=1e-9 * max(1.0, np.abs(t).max()))
        assert relative_error(P, K2 @ np.hstack([R2, t2[:, None]])) < 1e-9
    # through a file: P -> K, R, t -> P
    P = random_camera_P(rng)[0]
    (tmp_path / "cam0.txt").write_text("\n".join(" ".join(repr(float(x)) for x in row) for row in P))
    assert detect_format(tmp_path / "cam0.txt") == "projection"
    cam = load_calibration(tmp_path / "cam0.txt", units="m", size=(1920, 1080))[0]
    assert cam.name == "cam0" and relative_error(P, cam.projection_matrix) < 1e-9


def test_projection_folder():
    folder = NEW / "projection"
    assert detect_format(folder) == "projection"
    assert detect_format(folder / "cam2.xml") == detect_format(folder / "cam1.txt") == "projection"
    warnings = []
    studio = load_calibration(folder, warn=warnings.append)
    assert studio.names == ["cam0", "cam1", "cam2", "cam3"]  # .txt, CONTOUR .txt, <P>, <ProjectionMatrix>
    assert warnings[0] == f"{folder}: skipped (no camera fields): README.txt"
    assert len(warnings) == 2 and "no image size for cam0, cam1, cam3;" in warnings[1]
    assert (studio.camera("cam2").width, studio.camera("cam2").height) == (1280, 720)
    for i, cam in enumerate(studio):
        a = 2 * np.pi * i / 4 + 0.3
        np.testing.assert_allclose(cam.center, [3.2 * np.cos(a), 3.2 * np.sin(a), 1.6], atol=1e-9)
        assert cam.depth(np.array([0.0, 0.0, 1.0])) > 0
        assert not cam.has_distortion and abs(cam.K[0, 1]) < 1e-9 * cam.K[0, 0]
        if i < 2:  # the .txt files: the matrix read back
            rows = [line for line in (folder / f"{cam.name}.txt").read_text().splitlines() if line[0] not in "#C"]
            P = np.array([[float(x) for x in row.split()] for row in rows])
            assert relative_error(P, cam.projection_matrix) < 1e-12


def test_projection_text_with_commas_and_brackets(tmp_path):
    """P as CSV rows, as one comma-separated line and as a matrix copied from numpy or MATLAB:
    each read as the space-separated text is."""
    rng = np.random.default_rng(7)
    layouts = {"a": lambda rows: "\n".join(" ".join(r) for r in rows),
               "b": lambda rows: "\n".join(",".join(r) for r in rows),
               "c": lambda rows: ", ".join(x for r in rows for x in r),
               "d": lambda rows: "[" + "; ".join(" ".join(r) for r in rows) + "]",
               "e": lambda rows: "[[" + "],\n [".join(", ".join(r) for r in rows) + "]]"}
    written = {}
    for name, layout in layouts.items():
        written[name] = random_camera_P(rng, 0.0)[0]
        (tmp_path / f"{name}.txt").write_text(layout([[repr(float(x)) for x in row] for row in written[name]]) + "\n")
    studio = load_calibration(tmp_path, size=(640, 480))
    assert studio.names == list(layouts)
    for cam in studio:
        assert relative_error(written[cam.name], cam.projection_matrix) < 1e-12
    (tmp_path / "f.txt").write_text("1, 2, 3, x, 5, 6, 7, 8, 9, 10, 11, 12\n")
    with pytest.raises(CalibrationError, match=r"f\.txt: P: not numeric"):
        load_calibration(tmp_path / "f.txt", size=(640, 480))


def test_projection_skew_warning(tmp_path):
    rng = np.random.default_rng(5)
    for name, skew in (("a", 0.0), ("b", 0.05), ("c", 0.005), ("d", -0.03)):
        P = random_camera_P(rng, skew)[0]
        (tmp_path / f"{name}.txt").write_text(" ".join(repr(float(x)) for x in P.reshape(-1)))
    warnings = []
    studio = load_calibration(tmp_path, size=(640, 480), warn=warnings.append)
    assert warnings == [f"{tmp_path}: the projection matrices of b, d decompose with a skew above 1% of fx "
                        "(kept as it is; a poor or mis-assembled P?)"]
    assert studio.camera("b").K[0, 1] == pytest.approx(0.05 * studio.camera("b").K[0, 0], rel=1e-9)


def test_projection_errors(tmp_path, capsys):
    cases = {
        "eleven.txt": ("1 0 0 0\n0 1 0 0\n0 0 1", "P: expected a 3x4 projection matrix (12 numbers), got 11 numbers"),
        "singular.txt": ("1 0 0 0\n0 1 0 0\n1 1 0 1\n", "P: singular: its left 3x3 block has rank < 3"),
        "zero.txt": ("0 0 0 0 0 0 0 0 0 0 0 0", "P: singular"),
        "words.txt": ("P = [1 0 0 0; 0 1 0 0; 0 0 1 0]", "P: not numeric"),
        "shape.xml": ('<opencv_storage><P type_id="opencv-matrix"><rows>4</rows><cols>3</cols><dt>d</dt>'
                      "<data>1 0 0 0 1 0 0 0 1 0 0 1</data></P></opencv_storage>",
                      "P: expected a 3x4 projection matrix (12 numbers), got shape (4, 3)"),
    }
    for name, (text, problem) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(CalibrationError, match=re.escape(f"{path}: {problem}")):
            load_calibration(path, size=(640, 480))
        rc, stdout, err = cli(capsys, "calib", "show", path, "--size", "640x480")
        assert rc == 2 and stdout == "" and err.count("\n") == 1
        assert err.startswith(f"mocap calib show: error: {path}: {problem}") and "Traceback" not in err


def test_cli_refuses_read_only_output_formats(tmp_path, capsys):
    for fmt in ("projection", "qualisys"):
        assert fmt in FORMATS and fmt not in WRITE_FORMATS
        with pytest.raises(CalibrationError, match=f"cannot write format '{fmt}'"):
            output_format(tmp_path / "out", fmt)
        assert main(["calib", "convert", str(NEW / "projection"), str(tmp_path / "out"), "--format", fmt]) == 2
    capsys.readouterr()
    rc, stdout, err = cli(capsys, "calib", "convert", NEW / "qualisys" / "Calib.qca.txt", tmp_path / "q.json")
    assert rc == 0, err
    assert_same(load_calibration(tmp_path / "q.json"), load_calibration(NEW / "qualisys", warn=lambda line: None),
                tol=0)


def test_a_3x3_intrinsics_text_beside_a_projection_is_skipped(tmp_path, capsys):
    """A camera folder holding P.txt and the K.txt it came from: K (9 numbers) is no camera."""
    for cam in ("a", "b"):
        (tmp_path / cam).mkdir()
        (tmp_path / cam / "P.txt").write_text((NEW / "projection" / "cam1.txt").read_text())
        (tmp_path / cam / "K.txt").write_text("800 0 320\n0 800 240\n0 0 1\n")
    studio = load_calibration(tmp_path)
    assert studio.names == ["a", "b"]
    assert "skipped (no camera fields): a/K.txt, b/K.txt" in capsys.readouterr().err


@pytest.mark.timeout(30)
def test_the_files_a_calibration_is_read_from(tmp_path):
    """What decides whether a calibration changed: its files, never a folder that may hold what a
    run writes beside them (a take read as its own calibration, EasyMocap's files in a take)."""
    from common.calibration import calibration_files, save_calibration

    studio = circle_studio(3)
    take = tmp_path / "take"
    save_calibration(studio, tmp_path / "xml", fmt="opencv-xml")
    for cam in studio.names:
        (take / cam).mkdir(parents=True)
        shutil.copy(tmp_path / "xml" / f"{cam}.xml", take / cam / "config.xml")
        (take / cam / "notes.txt").write_text("focus set by hand")
    (take / "sequence").mkdir()
    (take / "sequence" / "calibration.json").write_text("{}")  # what a run writes there
    assert calibration_files(take) == [take / cam / "config.xml" for cam in studio.names]
    save_calibration(studio, tmp_path / "easymocap", fmt="easymocap")
    assert calibration_files(tmp_path / "easymocap") == [tmp_path / "easymocap" / "intri.yml",
                                                         tmp_path / "easymocap" / "extri.yml"]
    save_calibration(studio, tmp_path / "calibration.json")
    assert calibration_files(tmp_path / "calibration.json") == [tmp_path / "calibration.json"]


@pytest.mark.timeout(30)
def test_a_camera_folder_without_its_camera_file_says_so(tmp_path, capsys):
    """The lab's layout with cam3's config.xml missing: its intrinsics-only file is the folder's
    one candidate, and the error says no other file there holds a camera."""
    from common.calibration import save_calibration

    studio = circle_studio(3)
    save_calibration(studio, tmp_path / "xml", fmt="opencv-xml")
    for cam in studio.names:
        (tmp_path / "lab" / cam).mkdir(parents=True)
        shutil.copy(tmp_path / "xml" / f"{cam}.xml", tmp_path / "lab" / cam / "config.xml")
        (tmp_path / "lab" / cam / "intrinsics.xml").write_text(
            '<?xml version="1.0"?>\n<opencv_storage><CameraMatrix type_id="opencv-matrix"><rows>3</rows>'
            '<cols>3</cols><dt>d</dt><data>300 0 160 0 300 120 0 0 1</data></CameraMatrix></opencv_storage>\n')
    (tmp_path / "lab" / "cam3" / "config.xml").unlink()
    rc, _, err = cli(capsys, "calib", "show", tmp_path / "lab")
    assert rc == 2 and err.strip().endswith("no other file in cam3/ holds a whole camera (K, R, t or P)"), err
    assert f"{tmp_path / 'lab' / 'cam3' / 'intrinsics.xml'}: " in err
