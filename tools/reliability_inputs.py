"""Bad inputs through the real ``mocap`` command line, each judged handled or not.

``run_bad_inputs(work_dir)`` makes a tiny sequence (``mocap synth``, 2 frames, 3 cameras of
64x48) and a result of it (``mocap fit``), then some 200 cases, each a copy with one thing
wrong: every file kind the project reads (sequence.json, truth.jsonl, calibrations in every
format, silhouettes, images, BVH, TOML, CURVE keys), the numeric options of the commands with
negative, zero, nan, inf and text values as they apply, and results in the way of a new run.
Each runs as a subprocess; it is handled when it exits 2 with exactly one non-empty line on
stderr that starts with "mocap" and names the file or option, no traceback anywhere, and
(where the case has files in place) those files unchanged, byte for byte.

    .venv/bin/python tools/reliability_inputs.py [--work DIR] [--json FILE]

prints a table and the totals (about 2.5 minutes on two idle cores).

One module of about 560 lines: the cases are a flat list, one short builder each, read as the
list of what is refused; split by file kind they would each need the same fixtures and runner.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zmq.auth

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common.calibration import load_calibration, save_calibration  # noqa: E402

CLI = [sys.executable, "-m", "server.cli"]
CASE_TIMEOUT_S = 60.0  # a case whose bad input is taken starts real work: a 1-frame fit here takes ~3 s
WAITING_TIMEOUT_S = 20.0  # server / client cases that, when a bad value is taken, wait for peers
WORKERS = 2  # cases are independent processes; two at a time on two cores
SEQUENCE_OPTIONS = ["--frames", "2", "--cameras", "3", "--size", "64x48"]  # the tiny sequence
OUTCOME_CHARS = 220  # of the outcome line kept per case
DATA = REPO / "tests" / "data"
CLIP = REPO / "common" / "data" / "clips" / "cmu_12_01_walk.bvh"
READ_ONLY_FOR_ROOT = Path("/proc/mocap-read-only")  # root writes through chmod 555; nobody writes in /proc


@dataclass
class Case:
    """One bad input: the command line, what its error line must name, files that must not change."""

    name: str
    argv: list[str]
    names: str
    keep: list[Path] = field(default_factory=list)
    timeout_s: float = CASE_TIMEOUT_S


# --------------------------------------------------------------------------- running and judging
def _snapshot(paths: list[Path]) -> dict[str, bytes]:
    """Every file under ``paths`` -> its bytes (a folder's files, recursively)."""
    out = {}
    for path in paths:
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            out[str(f)] = f.read_bytes() if f.exists() else b""
    return out


def _judge(case: Case, rc: int | None, stdout: str, stderr: str, before: dict, after: dict) -> tuple[bool, str]:
    lines = [line for line in stderr.splitlines() if line.strip()]
    if "Traceback" in stderr or "Traceback" in stdout:
        return False, "traceback: " + (lines[-1] if lines else "")
    if rc is None:
        return False, f"still running after {case.timeout_s:g} s (the bad input was taken)"
    if rc != 2:
        return False, f"exit {rc}" + (f": {lines[-1]}" if lines else " (accepted)")
    if len(lines) != 1:
        return False, f"{len(lines)} lines on stderr: " + " | ".join(lines[:3])
    line = lines[0]
    if not line.startswith("mocap"):
        return False, f"does not start with 'mocap': {line}"
    if case.names not in line:
        return False, f"does not name {case.names}: {line}"
    if before != after:
        changed = sorted(set(before) ^ set(after) | {k for k in before if after.get(k) != before[k]})
        return False, f"changed {changed[0]}: {line}"
    return True, line


def _run_case(case: Case) -> dict:
    before = _snapshot(case.keep)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(CLI + case.argv, cwd=REPO, capture_output=True, text=True, timeout=case.timeout_s,
                              stdin=subprocess.DEVNULL)
        rc, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    except subprocess.TimeoutExpired as exc:
        rc, stdout, stderr = None, _text(exc.stdout), _text(exc.stderr)
    seconds = time.perf_counter() - t0
    handled, outcome = _judge(case, rc, stdout, stderr, before, _snapshot(case.keep))
    return {"name": case.name, "handled": handled, "outcome": outcome[:OUTCOME_CHARS], "seconds": round(seconds, 2)}


def _text(data) -> str:
    return data.decode(errors="replace") if isinstance(data, bytes) else (data or "")


def _mocap(*argv) -> None:
    """Run a command that must succeed (making the valid inputs)."""
    proc = subprocess.run(CLI + [str(a) for a in argv], cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"mocap {' '.join(map(str, argv))}: {proc.stderr.strip()}")


# --------------------------------------------------------------------------- valid inputs
@dataclass
class Base:
    sequence: Path
    result: Path
    calibrations: dict  # format -> (path to load, file inside to spoil)
    video: dict  # camera -> folder of its frames
    work: Path

    def case_dir(self, name: str) -> Path:
        path = self.work / "cases" / name
        path.mkdir(parents=True)
        return path

    def spoiled_sequence(self, name: str, relpath: str, data: bytes | None) -> Path:
        """A copy of the sequence with ``relpath`` holding ``data`` (None: a folder in its place)."""
        root = self.case_dir(name) / "seq"
        shutil.copytree(self.sequence, root)
        target = root / relpath
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
        if data is None:
            target.mkdir(parents=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        return root

    def spoiled_file(self, name: str, file_name: str, data: bytes | None) -> Path:
        path = self.case_dir(name) / file_name
        path.mkdir() if data is None else path.write_bytes(data)
        return path


def _make_base(work: Path) -> Base:
    base = work / "base"
    seq, res = base / "seq", base / "res"
    _mocap("synth", "--out", seq, *SEQUENCE_OPTIONS, "--quiet")
    _mocap("fit", seq, "--out", res, "--frames", "1", "--quiet")
    studio = load_calibration(seq / "calibration.json")
    cals = {}
    for fmt, name, inner in (("easymocap", "easymocap", "intri.yml"), ("pose2sim", "Calib.toml", ""),
                             ("anipose", "calibration.toml", ""), ("opencv-xml", "xml", "cam1.xml")):
        save_calibration(studio, base / name, fmt)
        cals[fmt] = (base / name, inner)
    shutil.copy(DATA / "calibration" / "projection" / "cam0.txt", base / "cam0.txt")
    shutil.copy(DATA / "calibration" / "qualisys" / "Calib.qca.txt", base / "Calib.qca.txt")
    cals["projection"] = (base / "cam0.txt", "")
    cals["qualisys"] = (base / "Calib.qca.txt", "")
    from PIL import Image

    rng = np.random.default_rng(0)
    video = {}
    for cam in studio:
        folder = base / "video" / cam.name
        folder.mkdir(parents=True)
        for i in range(2):
            pixels = rng.integers(0, 256, (cam.height, cam.width, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(folder / f"{i:06d}.png")
        video[cam.name] = folder
    return Base(seq, res, cals, video, work)


# --------------------------------------------------------------------------- bad files
def png_declaring(width: int, height: int) -> bytes:
    """A PNG whose header declares width x height 8-bit grey pixels (its data holds one row)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * (width + 1))) + chunk(b"IEND", b""))


def _json_edit(data: bytes, edit) -> bytes:
    doc = json.loads(data)
    edit(doc)
    return json.dumps(doc).encode()


def set_field(*keys_value):
    *keys, value = keys_value

    def edit(doc):
        node = doc
        for key in keys[:-1]:
            node = node[key]
        node[keys[-1]] = value
    return edit


def _fit(seq: Path, out: Path, *extra) -> list[str]:
    return ["fit", str(seq), "--out", str(out), "--quiet", "--frames", "1", *map(str, extra)]


def _sequence_cases(b: Base) -> list[Case]:
    meta = (b.sequence / "sequence.json").read_bytes()
    truth = (b.sequence / "truth.jsonl").read_bytes()
    cal = (b.sequence / "calibration.json").read_bytes()
    mask = (b.sequence / "silhouettes" / "cam2" / "000000.png").read_bytes()
    first_truth = truth.split(b"\n")[0]
    deep = b"[" * 100000

    def truth_line(edit) -> bytes:
        return first_truth + b"\n" + _json_edit(first_truth, edit) + b"\n"

    def no_key(key):
        return lambda doc: doc.pop(key)

    files = {
        "sequence.json": {
            "a list": b"[0, 1]", "fps text": _json_edit(meta, set_field("fps", "fast")),
            "fps 0": _json_edit(meta, set_field("fps", 0)),
            "fps negative": _json_edit(meta, set_field("fps", -30)), "fps NaN": _json_edit(meta, set_field("fps", float("nan"))),
            "fps true": _json_edit(meta, set_field("fps", True)), "frames text": _json_edit(meta, set_field("frames", "0,1")),
            "frame 1.5": _json_edit(meta, set_field("frames", [0, 1.5])), "frame -1": _json_edit(meta, set_field("frames", [-1])),
            "frame twice": _json_edit(meta, set_field("frames", [0, 0])),
            "frames empty": _json_edit(meta, set_field("frames", [])),
            "camera a number": _json_edit(meta, set_field("cameras", [1, 2, 3])), "not JSON": meta[:-3],
            "not UTF-8": meta.replace(b"fps", b"f\xffs"), "empty": b"", "a folder": None, "nested deep": deep,
        },
        "truth.jsonl": {
            "not UTF-8": truth.replace(b'"frame"', b'"fr\xe9me"'), "not JSON": first_truth + b"\n{\"frame\": 1,\n",
            "record a list": first_truth + b"\n[1, 2]\n", "frame missing": truth_line(no_key("frame")),
            "frame 1.5": truth_line(set_field("frame", 1.5)), "frame text": truth_line(set_field("frame", "1")),
            "params short": truth_line(set_field("params", [0.0, 1.0])),
            "params NaN": truth_line(lambda d: d["params"].__setitem__(0, float("nan"))),
            "joints a list": truth_line(lambda d: d.__setitem__("joints", list(d["joints"].values()))),
            "joint missing": truth_line(lambda d: d["joints"].pop(next(iter(d["joints"])))),
            "joint of 2": truth_line(lambda d: d["joints"].__setitem__(next(iter(d["joints"])), [0.0, 1.0])),
            "a folder": None,
        },
        "calibration.json": {
            "version 99": _json_edit(cal, set_field("version", 99)), "version text": _json_edit(cal, set_field("version", "1")),
            "width 64.5": _json_edit(cal, set_field("cameras", 0, "width", 64.5)),
            "width 0": _json_edit(cal, set_field("cameras", 0, "width", 0)),
            "width true": _json_edit(cal, set_field("cameras", 0, "width", True)),
            "huge size": _json_edit(cal, lambda d: d["cameras"][0].update(width=10 ** 6, height=10 ** 6)),
            "name a number": _json_edit(cal, set_field("cameras", 0, "name", 5)),
            "K NaN": _json_edit(cal, lambda d: d["cameras"][0]["K"][0].__setitem__(0, float("nan"))),
            "K 2x2": _json_edit(cal, set_field("cameras", 0, "K", [[1, 0], [0, 1]])),
            "dist text": _json_edit(cal, set_field("cameras", 0, "dist", ["a"] * 5)),
            "R not a rotation": _json_edit(cal, set_field("cameras", 0, "R", [[2, 0, 0], [0, 1, 0], [0, 0, 1]])),
            "t null": _json_edit(cal, set_field("cameras", 0, "t", None)),
            "no cameras": _json_edit(cal, set_field("cameras", [])),
            "units furlong": _json_edit(cal, set_field("units", "furlong")),
            "format other": _json_edit(cal, set_field("format", "x")),
            "not JSON": cal[:len(cal) // 2], "not UTF-8": cal.replace(b'"cam1"', b'"cam\xff"', 1), "empty": b"",
            "a folder": None, "a list": b"[]",
        },
        "silhouettes/cam2/000000.png": {
            "declares 40000x40000": png_declaring(40000, 40000), "truncated": mask[:len(mask) // 2], "empty": b"",
            "text": b"not an image\n", "a folder": None, "wrong size": png_declaring(10, 10),
        },
    }
    cases = []
    for relpath, spoils in files.items():
        for what, data in spoils.items():
            name = f"{relpath.split('/')[0]} {what}"
            seq = b.spoiled_sequence(name, relpath, data)
            cases.append(Case(name, _fit(seq, seq.parent / "res"), str(seq / relpath)))
    seq = b.spoiled_sequence("sequence.json unknown frame", "sequence.json", _json_edit(meta, set_field("frames", [0, 99])))
    cases.append(Case("sequence.json unknown frame", _fit(seq, seq.parent / "res", "--frames", "2"), "000099.png"))
    seq = b.spoiled_sequence("silhouettes missing file", "silhouettes/cam3/000000.png", b"")
    (seq / "silhouettes" / "cam3" / "000000.png").unlink()
    cases.append(Case("silhouettes missing file", _fit(seq, seq.parent / "res"), "cam3/000000.png"))
    return cases


SPOILS = {"not UTF-8": lambda d: d[:len(d) // 2] + b"\xff\xfe" + d[len(d) // 2:],
          "truncated": lambda d: d[:len(d) // 2], "empty": lambda d: b""}
FIELD_SPOILS = {  # format -> (old, new): one field made wrong
    "easymocap": (b"names:", b"cameras:"), "pose2sim": (b"matrix = [", b'matrix = ["a", '),
    "anipose": (b"size = [", b"size = [ 0, 0], old = ["), "opencv-xml": (b"<rows>3</rows>", b"<rows>2</rows>"),
    "projection": (b" -2.6928117659925137", b""), "qualisys": (b'viewrotation="90"', b'viewrotation="45"'),
}


def _calibration_cases(b: Base) -> list[Case]:
    cases = []
    for fmt, (path, inner) in b.calibrations.items():
        valid = (path / inner if inner else path).read_bytes()
        spoils = {what: spoil(valid) for what, spoil in SPOILS.items()}
        old, new = FIELD_SPOILS[fmt]
        assert old in valid, (fmt, old)
        spoils["a field"] = valid.replace(old, new, 1)
        for what, data in spoils.items():
            name = f"calibration {fmt} {what}"
            folder = b.case_dir(name)
            target = folder / path.name
            shutil.copytree(path, target) if path.is_dir() else shutil.copy(path, target)
            (target / inner if inner else target).write_bytes(data)
            units = ["--units", "mm"] if fmt in ("projection", "qualisys") else []
            cases.append(Case(name, ["calib", "show", str(target), "--from", fmt, *units], str(target)))
    return cases


def _bvh_and_toml_cases(b: Base) -> list[Case]:
    clip = CLIP.read_bytes()
    lines = clip.split(b"\n")
    motion = lines.index(next(line for line in lines if line.strip() == b"MOTION"))

    def with_line(i: int, line: bytes) -> bytes:
        return b"\n".join(lines[:i] + [line] + lines[i + 1:])

    deep = ("HIERARCHY\nROOT j0\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n"
            + "".join(f"JOINT j{i}\n{{\nOFFSET 0 0 1\n" for i in range(1, 2000)) + "}\n" * 2000
            + "MOTION\nFrames: 1\nFrame Time: 0.1\n0\n").encode()
    bvh = {
        "not UTF-8": with_line(3, lines[3] + b" \xe9"), "truncated": clip[:len(clip) // 3],
        "motion not numeric": with_line(motion + 3, lines[motion + 3].replace(b" ", b" x", 1)),
        "short motion line": with_line(motion + 3, lines[motion + 3].rsplit(b" ", 1)[0]),
        "channel count": clip.replace(b"CHANNELS 6", b"CHANNELS 7", 1),
        "channel count superscript": clip.replace(b"CHANNELS 6", "CHANNELS \u00b3".encode(), 1),
        "nested deep": deep, "no MOTION": b"\n".join(lines[:motion]), "empty": b"", "a folder": None,
    }
    cases = []
    for what, data in bvh.items():
        name = f"bvh {what}"
        path = b.spoiled_file(name, "clip.bvh", data)
        cases.append(Case(name, ["synth", "--clip", str(path), "--out", str(path.parent / "seq"), *SEQUENCE_OPTIONS,
                                 "--quiet"], str(path)))
    tomls = {
        "segment params not TOML": ("segment", b"regions = \n"),
        "segment params unknown key": ("segment", b"nope = 1\n"),
        "segment params nan": ("segment", b"shadow_depth = nan\n"),
        "segment params text": ("segment", b"regions = 'two'\n"),
        "segment params not UTF-8": ("segment", b"# caf\xe9\nregions = 2\n"),
        "joint map not TOML": ("synth", b"[joints\n"),
        "joint map unknown role": ("synth", b"[joints]\ntail = 'Hips'\n"),
        "joint map not a name": ("synth", b"[joints]\npelvis = 3\n"),
    }
    for name, (command, data) in tomls.items():
        path = b.spoiled_file(name, "file.toml", data)
        argv = (["segment", str(b.sequence), "--params", str(path)] if command == "segment" else
                ["synth", "--joint-map", str(path), "--out", str(path.parent / "seq"), *SEQUENCE_OPTIONS, "--quiet"])
        cases.append(Case(name, argv, str(path)))
    for what, files in {"keys empty folder": {}, "keys garbage secret": {"server.key_secret": b"\x00garbage"},
                        "keys no clients": None}.items():
        folder = b.case_dir(what) / "keys"
        folder.mkdir()
        if files is None:  # a real server pair, no allowed clients
            zmq.auth.create_certificates(folder, "server")
        for file_name, data in (files or {}).items():
            (folder / file_name).write_bytes(data)
        argv = ["server", str(b.sequence), "--out", str(folder.parent / "res"), "--quiet", "--frames", "1",
                "--curve-keys", str(folder), "--bind", f"ipc://{folder.parent / 'sock'}"]
        cases.append(Case(what, argv, str(folder), timeout_s=WAITING_TIMEOUT_S))
    name = "import-video image declares 40000x40000"
    folder = b.case_dir(name)
    videos = []
    for cam, frames in b.video.items():
        shutil.copytree(frames, folder / cam)
        videos.append(f"{cam}={folder / cam}")
    bomb = folder / "cam1" / "000001.png"
    bomb.write_bytes(png_declaring(40000, 40000))
    cases.append(Case(name, ["import-video", "--calibration", str(b.sequence / "calibration.json"), "--video", *videos,
                             "--out", str(folder / "imported")], str(bomb)))
    return cases


# --------------------------------------------------------------------------- bad options
# option -> the bad values it is tried with (a value that means something, such as 0 for "off",
# is left out).
FIT_OPTIONS = {
    "--frames": ["-1", "0", "nan", "abc", "1.5"], "--iterations": ["-1", "0", "abc"],
    "--set": ["fit.grid_steps=0", "fit.grid_range=nan", "fit.turn_step=0", "fit.spine_twist_prior=-1",
              "fit.redetect=maybe", "fit.nothing=1", "grid_steps", "fit.grid_steps=[1, 2]",
              "fit.schedules=3", 'fit.schedules={tracking={stages=[{proposers=["nope"]}]}}',
              'fit.schedules={search={budget=-1, stages=[{proposers=["starts"]}]}}', "fit.schedules={search_hops=true}"],
    "--turn-hypotheses": ["-1"], "--polish-iterations": ["-1"],
    "--refine-passes": ["-1"], "--refine-hops": ["-1"], "--mask-threshold": ["-1", "70000", "abc"],
    "--actor-height": ["0", "-1", "nan", "abc"], "--clients": ["-1", "abc"], "--client-timeout": ["0", "-1", "nan"],
    "--heartbeat": ["0", "-1", "nan", "inf"],
}
SYNTH_OPTIONS = {
    "--frames": ["-1", "0", "abc"], "--start": ["-1"], "--step": ["0", "-1"], "--cameras": ["0", "-1", "abc"],
    "--size": ["0x0", "-5x10", "abc", "100000x100000"], "--sizes": ["abc", "0x0"], "--radius": ["0", "-1", "nan"],
    "--height": ["nan", "inf"], "--fov": ["0", "180", "-5", "nan"], "--distortion": ["nan", "inf"],
    "--position": ["nan,0", "abc"], "--seed": ["-1", "abc"],
}
VOXELS_OPTIONS = {
    "--grid": ["0", "-1", "abc"], "--q": ["0", "-1"], "--epsilon": ["-1", "nan"], "--frames": ["-1", "0"],
    "--pictures": ["-1"], "--mask-threshold": ["-1", "70000"],
}
EXPORT_OPTIONS = {"--fps": ["0", "-1", "nan", "inf", "abc"]}
REPORT_OPTIONS = {"--fps": ["0", "-1", "nan", "inf"], "--frames": ["abc", "-1", "99"], "--cameras": ["nosuch"]}
CALIB_OPTIONS = {"--size": ["0x0", "abc", "-1x5", "nanxnan"], "--units": ["furlong"]}
IMPORT_OPTIONS = {"--start": ["-1"], "--stop": ["-1"], "--step": ["0", "-1"], "--fps": ["0", "nan"],
                  "--offset": ["cam1=abc"]}


def _option_cases(b: Base) -> list[Case]:
    cases = []

    def add(command: str, option: str, values: list[str], argv_for, names: str | None = None, **kw):
        for value in values:
            name = f"{command} {option} {value}"
            folder = b.case_dir(name)
            cases.append(Case(name, argv_for(folder, [f"{option}={value}"]), names or option, **kw))

    for option, values in FIT_OPTIONS.items():
        frames = [] if option == "--frames" else ["--frames", "1"]
        add("fit", option, values,
            lambda d, o: ["fit", str(b.sequence), "--out", str(d / "res"), "--quiet", *frames, *o])
    for option, values in SYNTH_OPTIONS.items():
        base = [a for a in SEQUENCE_OPTIONS if option not in ("--size", "--sizes") or a not in ("--size", "64x48")]
        add("synth", option, values, lambda d, o, base=base: ["synth", "--out", str(d / "seq"), *base, "--quiet", *o])
    for option, values in VOXELS_OPTIONS.items():
        frames = [] if option == "--frames" else ["--frames", "1"]
        add("voxels", option, values, lambda d, o, frames=frames: ["voxels", str(b.sequence), "--out", str(d / "vox"),
                                                                   "--pictures", "0", "--quiet", *frames, *o])
    add("voxels", "--bounds", ["nan"], lambda d, o: ["voxels", str(b.sequence), "--out", str(d / "vox"), "--quiet",
                                                     "--frames", "1", "--bounds", "nan", "0", "0", "1", "1", "1"])
    add("voxels", "--bounds", ["reversed"], lambda d, o: ["voxels", str(b.sequence), "--out", str(d / "vox"), "--quiet",
                                                          "--frames", "1", "--bounds", "1", "1", "1", "0", "0", "0"])
    for option, values in EXPORT_OPTIONS.items():
        add("export", option, values,
            lambda d, o: ["export", str(b.result), "--format", "bvh", "--out", str(d / "m.bvh"), "--quiet", *o])
    for option, values in REPORT_OPTIONS.items():
        add("report", option, values, lambda d, o: ["report", str(b.result), "--out", str(d / "r.html"),
                                                    "--no-pictures", "--no-gif", "--quiet", *o])
    for option, values in CALIB_OPTIONS.items():
        add("calib", option, values, lambda d, o: ["calib", "convert", str(b.sequence / "calibration.json"),
                                                   str(d / "out.json"), *o])
    videos = [f"{cam}={folder}" for cam, folder in b.video.items()]
    for option, values in IMPORT_OPTIONS.items():
        add("import-video", option, values,
            lambda d, o: ["import-video", "--calibration", str(b.sequence / "calibration.json"), "--video", *videos,
                          "--out", str(d / "imported"), *o])
    add("server", "--min-clients", ["-1"], lambda d, o: ["server", str(b.sequence), "--out", str(d / "res"), "--quiet",
                                                         "--frames", "1", "--bind", f"ipc://{d / 'sock'}", *o],
        timeout_s=WAITING_TIMEOUT_S)
    add("client", "--reconnect-min", ["-1"], lambda d, o: ["client", "--connect", f"ipc://{d / 'sock'}", "--quiet", *o],
        timeout_s=WAITING_TIMEOUT_S)
    return cases


# --------------------------------------------------------------------------- results in the way
def _result_cases(b: Base) -> list[Case]:
    cases = []

    def copy_result(name: str) -> Path:
        res = b.case_dir(name) / "res"
        shutil.copytree(b.result, res)
        return res

    res = copy_result("result exists: fit again")
    cases.append(Case("result exists: fit again", _fit(b.sequence, res), str(res), keep=[res]))
    name = "result exists: fit a sequence missing a frame"
    res = copy_result(name)
    seq = res.parent / "seq"
    shutil.copytree(b.sequence, seq)
    (seq / "silhouettes" / "cam3" / "000001.png").unlink()
    cases.append(Case(name, ["fit", str(seq), "--out", str(res), "--quiet"], str(res), keep=[res]))
    name = "--out names a file"
    out = b.case_dir(name) / "a-file"
    out.write_text("keep me\n")
    cases.append(Case(name, _fit(b.sequence, out), str(out), keep=[out]))
    name = "--out in a read-only folder"
    folder = b.case_dir(name) / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    out = (READ_ONLY_FOR_ROOT if os.geteuid() == 0 else folder) / "res"
    cases.append(Case(name, _fit(b.sequence, out), str(out)))
    name = "sequence exists: synth again"
    seq = b.case_dir(name) / "seq"
    shutil.copytree(b.sequence, seq)
    cases.append(Case(name, ["synth", "--out", str(seq), *SEQUENCE_OPTIONS, "--seed", "1", "--quiet"], str(seq),
                      keep=[seq]))
    name = "result exists: voxels again"
    vox = b.case_dir(name) / "vox"
    vox.mkdir()
    (vox / "voxels.json").write_text('{"frames": []}\n')  # the summary an earlier mocap voxels wrote
    cases.append(Case(name, ["voxels", str(b.sequence), "--out", str(vox), "--frames", "1", "--pictures", "0",
                             "--quiet"], str(vox), keep=[vox]))
    name = "export over an existing file"
    out = b.case_dir(name) / "motion.bvh"
    out.write_text("an earlier export\n")
    cases.append(Case(name, ["export", str(b.result), "--format", "bvh", "--out", str(out), "--quiet"], str(out),
                      keep=[out]))
    name = "report over an existing file"
    out = b.case_dir(name) / "report.html"
    out.write_text("an earlier report\n")
    cases.append(Case(name, ["report", str(b.result), "--out", str(out), "--no-pictures", "--no-gif", "--quiet"],
                      str(out), keep=[out]))
    return cases


# --------------------------------------------------------------------------- entry points
def run_bad_inputs(work_dir: Path) -> list[dict]:
    """Make the inputs in ``work_dir`` (emptied first), run every case, return one dict per case:
    name, handled (bool), outcome (the error line, or what went wrong), seconds."""
    work = Path(work_dir)
    if (work / "cases").exists() or (work / "base").exists():
        _make_writable(work)
        shutil.rmtree(work / "cases", ignore_errors=True)
        shutil.rmtree(work / "base", ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    base = _make_base(work)
    cases = _sequence_cases(base) + _calibration_cases(base) + _bvh_and_toml_cases(base) + _option_cases(base)
    cases += _result_cases(base)
    with ThreadPoolExecutor(WORKERS) as pool:
        return list(pool.map(_run_case, cases))


def _make_writable(work: Path) -> None:
    for path in work.rglob("*"):
        if path.is_dir() and not path.is_symlink():
            path.chmod(0o755)


def print_table(results: list[dict], out=sys.stdout) -> None:
    width = max(len(r["name"]) for r in results)
    for r in results:
        print(f"{'ok ' if r['handled'] else 'BAD'}  {r['name'].ljust(width)}  {r['seconds']:6.2f} s  {r['outcome']}",
              file=out)
    handled = sum(r["handled"] for r in results)
    print(f"bad inputs tried {len(results)}, handled {handled}, not handled {len(results) - handled}", file=out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=None, help="folder for the inputs (default: a temporary one)")
    parser.add_argument("--json", type=Path, default=None, help="also write the cases and totals as JSON")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bad_inputs_") as tmp:
        t0 = time.perf_counter()
        results = run_bad_inputs(args.work or Path(tmp))
        print_table(results)
        print(f"{time.perf_counter() - t0:.0f} s")
        if args.work is None:
            _make_writable(Path(tmp))
    if args.json:
        handled = sum(r["handled"] for r in results)
        args.json.write_text(json.dumps({"bad_inputs_tried": len(results), "bad_inputs_handled": handled,
                                         "cases": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
