"""Calibration formats: fixtures as each tool writes them, round trips, the CLI, bad input."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from common.calibration import (
    FORMATS, detect_format, load_calibration, matrix_to_rodrigues, natural_key, output_format,
    rodrigues_to_matrix, save_calibration,
)
from common.camera import Camera, CalibrationError, Studio, circle_studio
from server.cli import main

DATA = Path(__file__).parent / "data" / "calib"
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


@pytest.mark.parametrize("fmt", FORMATS)
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
    with pytest.raises(CalibrationError, match=r"intri\.yml: H_01/W_01: missing .*--size WxH"):
        load_calibration(folder)
    studio = load_calibration(folder, size=(1280, 720))
    assert all((c.width, c.height) == (1280, 720) for c in studio)


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
    assert [line.split()[0] for line in lines[2:]] == names


@pytest.mark.parametrize("fmt", [f for f in FORMATS if f != "json"])
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
    rc, _, err = cli(capsys, "calib", "show", folder)
    assert rc == 2
    assert "left" in err and "calibration.xml: image_width/image_height: missing" in err and "--size" in err
    rc, stdout, err = cli(capsys, "calib", "show", folder, "--size", "640x480")
    assert rc == 0, err
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
    ("pose2sim/Calib.toml", "", "[cam_02]", "[cam_02", ["Calib.toml: <file>: not valid TOML"]),
    ("anipose/calibration.toml", "", "distortions = [ -0.18", "distortions = [ true, -0.18",
     ["calibration.toml: cam_0.distortions: not numeric"]),
    ("easymocap", "intri.yml", "rows: 3\r\n  cols: 3\r\n  dt: d\r\n  data: [1158.047983, 0.000000, 958.129311, ",
     "rows: 2\r\n  cols: 3\r\n  dt: d\r\n  data: [", ["intri.yml: K_01: expected shape (3, 3)"]),
    ("easymocap", "intri.yml", "data: [1158.047983, 0.000000, ", "data: [", ["intri.yml: K_01: data has 7 values"]),
    ("easymocap", "intri.yml", "dist_02:", "distortion_02:", ["intri.yml: dist_02: missing"]),
    ("easymocap", "intri.yml", "names:", "cameras:", ["intri.yml: names: missing"]),
    ("easymocap", "intri.yml", "data: [1158.047983", "data: [fx", ["intri.yml: K_01: not numeric"]),
    ("easymocap", "intri.yml", "names:\r\n", "names: [\r\n", ["intri.yml: <file>: not valid OpenCV YAML"]),
    ("easymocap", "extri.yml", "T_03:", "Tvec_03:", ["extri.yml: T_03: missing"]),
    ("opencv_xml", "cam1.xml", "Translation", "Position",
     ["cam1.xml: Translation: missing (also accepted: T, tvec)"]),
    ("opencv_xml", "cam10.xml", "<dt>d</dt>\n  <data>\n    8.", "<dt>d</dt>\n  <data>\n    9.",  # in rotation_matrix
     ["cam10.xml: rotation_matrix: not a rotation"]),
    ("opencv_xml", "cam2.xml", "<ImageSize>\n  1280 720", "<ImageSize>\n  1280",
     ["cam2.xml: ImageSize: expected 2 values"]),
    ("opencv_xml", "cam2.xml", "<data>\n    7.18", "<data>\n    seven", ["cam2.xml: camera_matrix: not numeric"]),
    ("opencv_xml", "cam1.xml", "</opencv_storage>", "", ["cam1.xml: <file>: not valid XML"]),
    ("opencv_xml", "cam1.xml", "opencv_storage>", "storage>", ["cam1.xml: <root>: expected <opencv_storage>"]),
    ("json/calibration.json", "", '"width": 320', '"width": "wide"',
     ["calibration.json: cam1.size: not integers"]),
    ("json/calibration.json", "", '"format"', '{"format"', ["calibration.json: <file>: not valid JSON"]),
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
    assert err.startswith("mocap calib: error: " + str(path))
    for part in expected:
        assert part in err


def test_missing_and_empty_inputs(tmp_path, capsys):
    rc, _, err = cli(capsys, "calib", "show", tmp_path / "nothing.toml")
    assert rc == 2 and "nothing.toml: <file>: does not exist" in err
    rc, _, err = cli(capsys, "calib", "show", tmp_path)
    assert rc == 2 and f"{tmp_path}: <folder>: no calibration found" in err
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.xml").write_text("<opencv_storage/>")
    (tmp_path / "a" / "y.xml").write_text("<opencv_storage/>")
    rc, _, err = cli(capsys, "calib", "show", tmp_path)
    assert rc == 2 and "a: <folder>: expected one .xml file per camera folder, found x.xml, y.xml" in err
    folder = copy_fixture(tmp_path, "easymocap")
    (folder / "extri.yml").unlink()
    with pytest.raises(CalibrationError, match=r"extri\.yml: <file>: does not exist"):
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
