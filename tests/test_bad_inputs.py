"""Bad input files, each refused with one InputFileError / CalibrationError naming the file and
the field (and the line of line-based files), never a traceback: images (too large, truncated,
empty, a folder), sequence.json, truth.jsonl, calibrations of every format, BVH."""
from __future__ import annotations

import json
import re
import shutil
import struct
import sys
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from common.body import JOINT_NAMES, PARAM_NAMES
from common.bvh import read_bvh
from common.calibration import MAX_IMAGE_PIXELS, load_calibration, save_calibration
from common.camera import Studio, circle_studio
from common.errors import InputFileError, UserError
from common.sequence import image_size, load_sequence, read_image, read_mask, write_sequence_meta
from server.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from reliability_inputs import set_field  # noqa: E402  one JSON field set to a value, as the bad-input run sets it

DATA = Path(__file__).parent / "data"
W, H = 32, 24
CAMERAS = 2


def png_declaring(width: int, height: int) -> bytes:
    """A PNG whose header declares width x height 8-bit grey pixels (its data holds one row)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * (width + 1))) + chunk(b"IEND", b""))


def make_sequence(root: Path, frames=(0, 1)) -> tuple[Path, Studio]:
    """A sequence folder: 2 cameras of W x H, binary masks, sequence.json and truth.jsonl."""
    studio = circle_studio(CAMERAS, W, H, overhead=False)
    root.mkdir(parents=True)
    save_calibration(studio, root / "calibration.json")
    for cam in studio:
        for f in frames:
            mask = np.zeros((H, W), dtype=bool)
            mask[8:16, 10:20] = True
            path = root / "silhouettes" / cam.name / f"{f:06d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(mask).save(path)
    write_sequence_meta(root, frames, 30.0, studio.names)
    with open(root / "truth.jsonl", "w") as fh:
        for f in frames:
            fh.write(json.dumps(truth_record(f)) + "\n")
    return root, studio


def truth_record(frame: int) -> dict:
    return {"frame": frame, "params": [0.0] * len(PARAM_NAMES),
            "joints": {name: [0.0, 0.0, 1.0] for name in JOINT_NAMES}}


def refused(call, *parts: str, kind=UserError):
    """Run ``call``: it must raise ``kind`` whose one-line message holds every part."""
    with pytest.raises(kind) as info:
        call()
    message = str(info.value)
    assert "\n" not in message
    for part in parts:
        assert part in message, message
    return message


# --------------------------------------------------------------------------- images

READERS = {"mask": lambda p: read_mask(p), "image": lambda p: read_image(p, "RGB"), "size": image_size}


@pytest.mark.parametrize("reader", sorted(READERS))
def test_an_image_declaring_more_pixels_than_the_limit_is_refused(tmp_path, reader):
    """40000x40000 raised PIL's DecompressionBombError (a traceback) before there was a limit."""
    path = tmp_path / "000000.png"
    path.write_bytes(png_declaring(40000, 40000))
    refused(lambda: READERS[reader](path), str(path), "declares 40000x40000 pixels",
            f"{MAX_IMAGE_PIXELS / 1e6:g} Mpx", kind=InputFileError)


def test_an_image_within_the_limit_reads_without_pil_warnings(tmp_path):
    """90 Mpx is above PIL's own guard (89 Mpx: a warning line) but within ours: no warning."""
    path = tmp_path / "big.png"
    path.write_bytes(png_declaring(10000, 9000))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert image_size(path) == (10000, 9000)


@pytest.mark.parametrize("reader", sorted(READERS))
@pytest.mark.parametrize("case", ["truncated", "empty", "folder", "text", "bad_data"])
def test_broken_image_files_are_one_error(tmp_path, reader, case):
    path = tmp_path / "000000.png"
    good = tmp_path / "good.png"
    Image.fromarray(np.random.default_rng(0).random((64, 64)) > 0.5).save(good)  # noise: a long pixel stream
    data = good.read_bytes()
    if case == "folder":
        path.mkdir()
    else:
        path.write_bytes({"truncated": data[:40], "empty": b"", "text": b"not an image\n",
                          "bad_data": data[:len(data) // 2]}[case])
    if case == "bad_data" and reader == "size":  # the header is whole: only decoding fails
        assert image_size(path) == (64, 64)
        return
    expected = "a folder" if case == "folder" else "not a readable image"
    message = refused(lambda: READERS[reader](path), str(path), expected, kind=InputFileError)
    assert message.count(path.name) == 1  # PIL's reason names the file too: said once


def test_a_folder_in_place_of_a_frame_file_stops_check_files(tmp_path):
    root, studio = make_sequence(tmp_path / "seq")
    target = root / "silhouettes" / "cam2" / "000001.png"
    target.unlink()
    target.mkdir()
    seq = load_sequence(root)
    refused(lambda: seq.check_files(seq.frames), str(target), "a folder", kind=InputFileError)


# --------------------------------------------------------------------------- sequence.json

SEQUENCE_JSON = [
    # (text of sequence.json, message parts)
    ('[0, 1]', ["sequence.json: <root>: expected an object {...}, got a list of 2"]),
    ('{"frames": [0, 1], "fps": "fast"}', ["sequence.json: fps: expected a finite number > 0, got the text 'fast'"]),
    ('{"frames": [0, 1], "fps": 0}', ["fps: expected a finite number > 0, got the number 0"]),
    ('{"frames": [0, 1], "fps": -30}', ["fps: expected a finite number > 0"]),
    ('{"frames": [0, 1], "fps": NaN}', ["fps: expected a finite number > 0, got the number nan"]),
    ('{"frames": [0, 1], "fps": true}', ["fps: expected a finite number > 0, got true"]),
    ('{"frames": "0,1"}', ["frames: expected a list [...], got the text '0,1'"]),
    ('{"frames": [0, 1.5]}', ["frames[1]: expected a whole number >= 0, got the number 1.5"]),
    ('{"frames": [0, -1]}', ["frames[1]: expected a whole number >= 0, got the number -1"]),
    ('{"frames": [0, "1"]}', ["frames[1]: expected a whole number >= 0, got the text '1'"]),
    ('{"frames": [1, 0, 1]}', ["frames: frame 1 listed twice"]),
    ('{"frames": []}', ["frames: an empty list"]),
    ('{"frames": [0, 1], "cameras": ["cam1", 2]}', ["cameras[1]: expected a non-empty text in quotes"]),
    ('{"frames": [0, 1]', ["sequence.json: not valid JSON"]),
    ('{"frames": [0, 1], "fps": 30, "note": "caf\xe9"}', ["sequence.json: line 1: not UTF-8 text (byte 0xe9)"]),
    ('[' * 100000, ["sequence.json: not valid JSON (nested too deeply)"]),
]


@pytest.mark.parametrize("text, parts", SEQUENCE_JSON, ids=[p[0][:40] for p in SEQUENCE_JSON])
def test_bad_sequence_json(tmp_path, text, parts):
    root, _ = make_sequence(tmp_path / "seq")
    (root / "sequence.json").write_bytes(text.encode("latin-1"))
    refused(lambda: load_sequence(root), str(root / "sequence.json"), *parts, kind=InputFileError)


def test_sequence_json_that_is_a_folder(tmp_path):
    root, _ = make_sequence(tmp_path / "seq")
    (root / "sequence.json").unlink()
    (root / "sequence.json").mkdir()
    refused(lambda: load_sequence(root), "sequence.json: a folder, expected a file", kind=InputFileError)


def test_good_sequence_json_fields_are_read(tmp_path):
    root, _ = make_sequence(tmp_path / "seq", frames=(3, 5))
    (root / "sequence.json").write_text('{"frames": [5, 3.0], "fps": 25, "cameras": ["cam1", "cam2"], "x": {}}')
    seq = load_sequence(root)
    assert seq.frames == [5, 3] and seq.fps == 25.0 and isinstance(seq.frames[1], int)


# --------------------------------------------------------------------------- truth.jsonl

def _truth_line(**change) -> str:
    doc = truth_record(1)
    for key, value in change.items():
        if value is KeyError:
            del doc[key]
        else:
            doc[key] = value
    return json.dumps(doc)


JOINTS_AS_LIST = [[0.0, 0.0, 1.0]] * len(JOINT_NAMES)
SHORT_JOINT = {**{n: [0.0, 0.0, 1.0] for n in JOINT_NAMES}, JOINT_NAMES[3]: [0.0, 1.0]}
TRUTH = [
    # (second line of truth.jsonl as bytes, message parts)
    (b'{"frame": 1, "params": [\xff]}', ["truth.jsonl: line 2: not UTF-8 text (byte 0xff)"]),
    (b'{"frame": 1, "params": ', ["truth.jsonl: line 2: not valid JSON"]),
    (b'[1, 2, 3]', ["line 2: <record>: expected an object {...}, got a list of 3"]),
    (_truth_line(frame=KeyError).encode(), ["line 2: frame: missing"]),
    (_truth_line(frame=1.5).encode(), ["line 2: frame: expected a whole number >= 0, got the number 1.5"]),
    (_truth_line(frame=True).encode(), ["line 2: frame: expected a whole number >= 0, got true"]),
    (_truth_line(frame="1").encode(), ["line 2: frame: expected a whole number >= 0, got the text '1'"]),
    (_truth_line(params=[0.0] * 3).encode(), [f"line 2: params: expected a list of {len(PARAM_NAMES)} numbers"]),
    (_truth_line(params=[None] * len(PARAM_NAMES)).encode(), ["line 2: params[0]: expected a finite number, got null"]),
    (_truth_line(params=[float("nan")] * len(PARAM_NAMES)).encode(), ["line 2: params[0]: expected a finite number"]),
    (_truth_line(joints=JOINTS_AS_LIST).encode(), ["line 2: joints: expected an object {...}, got a list of 17"]),
    (_truth_line(joints={}).encode(), ["line 2: joints: no " + JOINT_NAMES[0]]),
    (_truth_line(joints=SHORT_JOINT).encode(), [f"line 2: joints.{JOINT_NAMES[3]}: expected a list of 3 numbers"]),
]


@pytest.mark.parametrize("line, parts", TRUTH, ids=[t[1][0].split(": ", 2)[-1][:40] for t in TRUTH])
def test_bad_truth_jsonl(tmp_path, line, parts):
    root, _ = make_sequence(tmp_path / "seq")
    (root / "truth.jsonl").write_bytes(json.dumps(truth_record(0)).encode() + b"\n" + line + b"\n")
    seq = load_sequence(root)
    refused(seq.truth, str(root / "truth.jsonl"), *parts, kind=InputFileError)


def test_truth_jsonl_reads_with_blank_lines(tmp_path):
    root, _ = make_sequence(tmp_path / "seq")
    text = (root / "truth.jsonl").read_text()
    (root / "truth.jsonl").write_text("\n" + text.replace("\n", "\n\n"))
    truth = load_sequence(root).truth()
    assert sorted(truth) == [0, 1] and truth[1].joints[JOINT_NAMES[0]].shape == (3,)


# --------------------------------------------------------------------------- calibration

def _json_calibration(tmp_path: Path, edit) -> Path:
    path = tmp_path / "calibration.json"
    save_calibration(circle_studio(CAMERAS, W, H, overhead=False), path)
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    return path




CALIBRATION_JSON = [
    (set_field("version", 99), ["calibration.json: version: version 99 is not supported"]),
    (set_field("version", "1"), ["version: version '1' is not supported"]),
    (set_field("cameras", 0, "width", 320.5), ["cam1.width: expected a whole number >= 1, got the number 320.5"]),
    (set_field("cameras", 0, "width", True), ["cam1.width: expected a whole number >= 1, got true"]),
    (set_field("cameras", 0, "height", 0), ["cam1.height: expected a whole number >= 1, got the number 0"]),
    (set_field("cameras", 0, "width", 10 ** 30), ["cam1.size: 1000000000000000000000000000000x24 pixels, more than"]),
    (set_field("cameras", 0, "name", 5), ["cameras[0].name: expected a non-empty text in quotes, got the number 5"]),
    (set_field("cameras", 0, "name", ""), ["cameras[0].name: expected a non-empty text in quotes"]),
    (set_field("cameras", 0, "K", 0, 0, float("nan")), ["cam1.K: contains NaN or infinity"]),
    (set_field("cameras", 0, "K", [[1, 0], [0, 1]]), ["cam1.K: expected shape (3, 3)"]),
    (set_field("cameras", 0, "dist", ["a"] * 5), ["cam1.dist: not numeric"]),
    (set_field("cameras", 0, "dist", [float("inf")] * 5), ["cam1.dist: contains NaN or infinity"]),
    (set_field("cameras", 0, "t", None), ["cam1.t: not numeric: None"]),
    (set_field("cameras", 0, "R", {"a": 1}), ["cam1.R: not numeric"]),
    (set_field("cameras", 0, "size_guessed", 1), ["cameras[0].size_guessed: expected true or false"]),
    (set_field("units", []), ["units: expected one of ['cm', 'm', 'mm'], got []"]),  # found by the fuzz suite
]


@pytest.mark.parametrize("edit, parts", CALIBRATION_JSON, ids=[c[1][0].split(": ")[-2][:40] for c in CALIBRATION_JSON])
def test_bad_calibration_json_fields(tmp_path, edit, parts):
    path = _json_calibration(tmp_path, edit)
    refused(lambda: load_calibration(path), str(path), *parts)


def _written(tmp_path: Path, fmt: str) -> tuple[Path, Path]:
    """(path to load, the file inside it to spoil) of a calibration in ``fmt``."""
    studio = circle_studio(CAMERAS, W, H, overhead=False)
    if fmt == "projection":  # one file: in a folder, a file holding no camera is skipped with a warning
        path = tmp_path / "cam0.txt"
        shutil.copy(DATA / "calibration" / "projection" / "cam0.txt", path)
        return path, path
    if fmt == "qualisys":
        path = tmp_path / "Calib.qca.txt"
        shutil.copy(DATA / "calibration" / "qualisys" / "Calib.qca.txt", path)
        return path, path
    name = {"json": "calibration.json", "pose2sim": "Calib.toml", "anipose": "calibration.toml",
            "easymocap": "easymocap", "opencv-xml": "xml"}[fmt]
    path = tmp_path / name
    save_calibration(studio, path, fmt)
    inner = {"easymocap": path / "intri.yml", "opencv-xml": path / "cam1.xml"}.get(fmt, path)
    return path, inner


FORMATS = ("json", "easymocap", "pose2sim", "anipose", "opencv-xml", "projection", "qualisys")
SPOILS = {
    "not_utf8": lambda data: data[:len(data) // 2] + b"\xff\xfe" + data[len(data) // 2:],
    "truncated": lambda data: data[:len(data) // 2],
    "empty": lambda data: b"",
    "binary": lambda data: bytes(range(256)) * 4,
}


@pytest.mark.parametrize("spoil", sorted(SPOILS))
@pytest.mark.parametrize("fmt", FORMATS)
def test_spoiled_calibration_files_are_one_error(tmp_path, capsys, fmt, spoil):
    path, inner = _written(tmp_path, fmt)
    inner.write_bytes(SPOILS[spoil](inner.read_bytes()))
    fmt_option = ["--from", fmt]  # a spoiled file may be detected as another format
    rc = main(["calib", "show", str(path), *fmt_option, *(["--units", "mm"] if fmt == "qualisys" else [])])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and err.startswith("mocap calib show: error: ") and str(path) in err, err


def test_easymocap_and_toml_camera_names(tmp_path):
    path, inner = _written(tmp_path, "easymocap")
    for yml in ("intri.yml", "extri.yml"):
        text = (path / yml).read_text()
        (path / yml).write_text(text.replace('  - "cam2"', "  - [cam2]"))
    refused(lambda: load_calibration(path), "intri.yml: names[1]: expected a camera name, got ['cam2']")
    path, _ = _written(tmp_path, "pose2sim")
    path.write_text(path.read_text().replace('name = "cam1"', "name = 7"))
    refused(lambda: load_calibration(path), "Calib.toml: cam_01.name: expected a non-empty text in quotes")
    path.write_text(path.read_text().replace("fisheye = false", 'fisheye = "no"', 1))
    refused(lambda: load_calibration(path), "Calib.toml: cam_01.fisheye: expected true or false")


# --------------------------------------------------------------------------- BVH

SIMPLE_BVH = (DATA / "bvh" / "simple.bvh").read_bytes()


def test_bvh_not_utf8_names_the_line(tmp_path):
    path = tmp_path / "clip.bvh"
    lines = SIMPLE_BVH.split(b"\n")
    lines[2] = lines[2] + b" \xe9"
    path.write_bytes(b"\n".join(lines))
    refused(lambda: read_bvh(path), str(path), "line 3: not UTF-8 text (byte 0xe9)", kind=InputFileError)


@pytest.mark.parametrize("pattern, new, expected", [
    (rb"CHANNELS 6", "CHANNELS \u00b3".encode(), "CHANNELS count must be a whole number, found '\u00b3'"),
    (rb"Frames: *\d+", "Frames: \u00b2".encode(), "Frames must be a whole number, found '\u00b2'"),
])
def test_bvh_counts_in_other_digits(tmp_path, pattern, new, expected):
    """str.isdigit takes superscripts, which int() refuses: a ValueError traceback before."""
    path = tmp_path / "clip.bvh"
    path.write_bytes(re.sub(pattern, new, SIMPLE_BVH, count=1))
    refused(lambda: read_bvh(path), str(path), expected, kind=InputFileError)


def test_bvh_nested_too_deep(tmp_path):
    """A RecursionError traceback before."""
    depth = 2000
    text = ("HIERARCHY\nROOT j0\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n"
            + "".join(f"JOINT j{i}\n{{\nOFFSET 0 0 1\n" for i in range(1, depth))
            + "}\n" * depth + "MOTION\nFrames: 1\nFrame Time: 0.1\n0\n")
    path = tmp_path / "deep.bvh"
    path.write_text(text)
    refused(lambda: read_bvh(path), str(path), "nested more than", kind=InputFileError)


# --------------------------------------------------------------------------- through the CLI

def test_fit_refuses_a_sequence_json_list_in_one_line(tmp_path, capsys):
    root, _ = make_sequence(tmp_path / "seq")
    (root / "sequence.json").write_text("[0, 1]")
    rc = main(["fit", str(root), "--out", str(tmp_path / "res"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("mocap fit: error: ") and "sequence.json: <root>: expected an object" in err
