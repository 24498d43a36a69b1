"""Fuzzing every reader and the CLI: a bad input is refused with UserError (the CLI: exit 2 and
one line), never any other exception.

Each reader gets garbage bytes, truncations, byte flips and insertions of a valid file, tokens
of its text replaced by awkward ones (nan, -1, 1e400, quotes, brackets) and, for JSON, random
JSON values in each field. Runs are deterministic (``derandomize``) and bounded:
a small multiple of ``FUZZ_EXAMPLES`` examples per test (default ``DEFAULT_EXAMPLES``;
``make reliability`` runs more).
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from common.bvh import read_bvh
from common.calibration import load_calibration, save_calibration, tomllib
from common.camera import circle_studio
from common.errors import UserError
from common.motion_import import import_bvh
from common.segmentation import CheungParams, load_params, params_dict
from common.sequence import image_size, load_sequence, read_image, read_mask
from server.cli import build_parser, main
from test_bad_inputs import make_sequence

DATA = Path(__file__).parent / "data"
DEFAULT_EXAMPLES = 100  # a unit of examples: the whole file in about 30 s on two busy cores
EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", DEFAULT_EXAMPLES))


def fuzz_settings(examples: int = EXAMPLES):
    return settings(max_examples=max(examples, 1), deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# --------------------------------------------------------------------------- mutations
AWKWARD_TOKENS = ("nan", "inf", "-inf", "1e400", "-1", "0", "-0", "1.5", "99", "abc", "", '"', "'", "[", "]",
                  "{", "}", ",", "=", ":", "true", "null", "\u00b2", "\x00", "\n", "<", ">", "&", "9" * 30)
TOKEN = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?|[A-Za-z_]+|\S")


def _flip(data: bytes, changes) -> bytes:
    out = bytearray(data)
    for at, value in changes:
        out[at % len(out)] = value
    return bytes(out)


def _replace_token(data: bytes, index: int, new: bytes) -> bytes:
    tokens = list(TOKEN.finditer(data))
    m = tokens[index % len(tokens)]
    return data[:m.start()] + new + data[m.end():]


def mutated(valid: bytes) -> st.SearchStrategy[bytes]:
    """Bytes near ``valid`` (a file that reads): garbage, cut, flipped, grown, a token swapped."""
    n = len(valid)
    return st.one_of(
        st.binary(max_size=2 * n),
        st.integers(0, n - 1).map(lambda k: valid[:k]),
        st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=8)
        .map(lambda changes: _flip(valid, changes)),
        st.tuples(st.integers(0, n), st.binary(min_size=1, max_size=16))
        .map(lambda c: valid[:c[0]] + c[1] + valid[c[0]:]),
        st.tuples(st.integers(0, n), st.integers(1, 64)).map(lambda c: valid[:c[0]] + valid[c[0] + c[1]:]),
        st.tuples(st.integers(0, 10 ** 6), st.sampled_from(AWKWARD_TOKENS) | st.text(max_size=6))
        .map(lambda c: _replace_token(valid, c[0], c[1].encode())),
    )


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70) | st.floats() | st.text(max_size=6)
    | st.sampled_from([0, -1, 1, 0.5, 1e308, 2 ** 64, "", "1", "nan"]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=8)


def _json_paths(doc, prefix=()) -> list[tuple]:
    """Every place in a JSON document: (key or index, ...) from the root."""
    places = [prefix]
    if isinstance(doc, dict):
        for key, value in doc.items():
            places += _json_paths(value, prefix + (key,))
    elif isinstance(doc, list):
        for i, value in enumerate(doc):
            places += _json_paths(value, prefix + (i,))
    return places


def _json_with(doc, place: tuple, value, delete: bool):
    doc = json.loads(json.dumps(doc))
    if not place:
        return value
    node = doc
    for key in place[:-1]:
        node = node[key]
    if delete:
        del node[place[-1]]
    else:
        node[place[-1]] = value
    return doc


def json_mutated(valid: bytes) -> st.SearchStrategy[bytes]:
    """A valid JSON file with one field (anywhere) deleted or replaced by a random JSON value."""
    doc = json.loads(valid)
    return st.tuples(st.sampled_from(_json_paths(doc)), JSON_VALUES, st.booleans()).map(
        lambda c: json.dumps(_json_with(doc, c[0], c[1], c[2] and bool(c[0]))).encode())


def toml_mutated(valid: bytes) -> st.SearchStrategy[bytes]:
    """A valid TOML file with one field deleted or replaced by a random value TOML can hold."""
    doc = tomllib.loads(valid.decode())

    def dumped(c):
        try:
            return tomli_w.dumps(_json_with(doc, c[0], c[1], c[2] and bool(c[0]))).encode()
        except (TypeError, ValueError, AttributeError):  # null, or a root that is not a table
            return None
    return (st.tuples(st.sampled_from(_json_paths(doc)), JSON_VALUES, st.booleans()).map(dumped)
            .filter(lambda b: b is not None))


def jsonl_mutated(valid: bytes) -> st.SearchStrategy[bytes]:
    """A JSON-lines file with one line's field mutated as ``json_mutated``."""
    lines = valid.splitlines()
    return st.integers(0, len(lines) - 1).flatmap(
        lambda i: json_mutated(lines[i]).map(lambda line: b"\n".join(lines[:i] + [line] + lines[i + 1:])))


def file_mutated(valid: bytes, kind: str) -> st.SearchStrategy[bytes]:
    """``mutated``, and for kind "json", "jsonl" or "toml" twice as often one field changed."""
    fields = {"json": json_mutated, "jsonl": jsonl_mutated, "toml": toml_mutated}.get(kind)
    return mutated(valid) if fields is None else st.one_of(mutated(valid), fields(valid), fields(valid))


def must_refuse_cleanly(call) -> None:
    """Run ``call``: success or UserError; any other exception fails the test (it is re-raised)."""
    try:
        call()
    except UserError as exc:
        assert "\n" not in str(exc), f"a message of more than one line: {exc}"


@contextlib.contextmanager
def scratch():
    """A temporary folder, also the working folder (a fuzzed relative --out lands there)."""
    here = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="fuzz_") as tmp:
        os.chdir(tmp)
        try:
            yield Path(tmp)
        finally:
            os.chdir(here)


# --------------------------------------------------------------------------- valid inputs
@pytest.fixture(scope="module")
def valid_sequence(tmp_path_factory) -> Path:
    return make_sequence(tmp_path_factory.mktemp("fuzz_sequence") / "seq")[0]


SEQUENCE_FILES = {  # file of the sequence -> how it is mutated
    "sequence.json": "json", "truth.jsonl": "jsonl", "calibration.json": "json",
    "silhouettes/cam1/000000.png": "bytes", "silhouettes/cam2/000001.png": "bytes",
}


def read_whole_sequence(root: Path) -> None:
    """What a fit reads before its first frame: the folder, truth, every mask, one frame's stack."""
    seq = load_sequence(root, clean_masks=False)
    seq.truth()
    seq.check_files(seq.frames)
    seq.constant_cameras(seq.frames)
    seq.silhouettes(seq.frames[0])


@fuzz_settings(EXAMPLES * 3)
@given(data=st.data())
def test_sequence_folder(valid_sequence, data):
    name = data.draw(st.sampled_from(sorted(SEQUENCE_FILES)), label="file")
    valid = (valid_sequence / name).read_bytes()
    spoiled = data.draw(file_mutated(valid, SEQUENCE_FILES[name]), label="bytes")
    with scratch() as tmp:
        root = tmp / "seq"
        shutil.copytree(valid_sequence, root)
        (root / name).write_bytes(spoiled)
        must_refuse_cleanly(lambda: read_whole_sequence(root))


# --------------------------------------------------------------------------- calibration
CALIBRATION_FILES = {  # format -> (name to load, files inside it to spoil, how)
    "json": ("calibration.json", ["."], "json"),
    "easymocap": ("easymocap", ["intri.yml", "extri.yml"], "bytes"),
    "pose2sim": ("Calib.toml", ["."], "toml"),
    "anipose": ("calibration.toml", ["."], "toml"),
    "opencv-xml": ("xml", ["cam1.xml", "cam2.xml"], "bytes"),
    "projection": ("projection", ["cam0.txt", "cam2.xml"], "bytes"),
    "qualisys": ("Calib.qca.txt", ["."], "bytes"),
}


@pytest.fixture(scope="module")
def valid_calibrations(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fuzz_calibrations")
    studio = circle_studio(3, 64, 48, overhead=False)
    for fmt in ("json", "easymocap", "pose2sim", "anipose", "opencv-xml"):
        save_calibration(studio, root / CALIBRATION_FILES[fmt][0], fmt)
    shutil.copytree(DATA / "calibration" / "projection", root / "projection")
    shutil.copy(DATA / "calibration" / "qualisys" / "Calib.qca.txt", root / "Calib.qca.txt")
    return root


@fuzz_settings(EXAMPLES * 3)
@given(data=st.data())
def test_calibration_formats(valid_calibrations, data):
    fmt = data.draw(st.sampled_from(sorted(CALIBRATION_FILES)), label="format")
    name, inner_files, kind = CALIBRATION_FILES[fmt]
    inner = data.draw(st.sampled_from(inner_files), label="file")
    valid = (valid_calibrations / name / inner).read_bytes()
    spoiled = data.draw(file_mutated(valid, kind), label="bytes")
    detect = data.draw(st.booleans(), label="detect format")
    units = "mm" if fmt in ("qualisys", "projection") else None  # the fixtures are in millimetres
    with scratch() as tmp:
        src = valid_calibrations / name
        path = tmp / name
        shutil.copytree(src, path) if src.is_dir() else shutil.copy(src, path)
        (path / inner).write_bytes(spoiled) if inner != "." else path.write_bytes(spoiled)
        must_refuse_cleanly(lambda: load_calibration(path, units, None if detect else fmt, warn=lambda line: None))


# --------------------------------------------------------------------------- images
def _encoded(array: np.ndarray, fmt: str, mode: str | None = None) -> bytes:
    buf = io.BytesIO()
    (Image.fromarray(array, mode) if mode else Image.fromarray(array)).save(buf, format=fmt)
    return buf.getvalue()


_rng = np.random.default_rng(0)
_MASK = _rng.random((12, 16)) > 0.5
_GREY = (_MASK * 255).astype(np.uint8)
_RGB = _rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
VALID_IMAGES = {
    "mask.png": _encoded(_MASK, "PNG"), "grey.png": _encoded(_GREY, "PNG"), "rgb.png": _encoded(_RGB, "PNG"),
    "grey16.png": _encoded(_GREY.astype(np.uint16) * 257, "PNG"), "rgb.jpg": _encoded(_RGB, "JPEG"),
    "grey.bmp": _encoded(_GREY, "BMP"), "rgb.tif": _encoded(_RGB, "TIFF"), "grey.pgm": _encoded(_GREY, "PPM"),
    "palette.gif": _encoded(_GREY, "GIF"),
}
IMAGE_READERS = {
    "mask": read_mask, "mask>128": lambda p: read_mask(p, 128), "rgb": lambda p: read_image(p, "RGB"),
    "grey": lambda p: read_image(p, "L"), "size": image_size,
}


@fuzz_settings(EXAMPLES * 2)
@given(data=st.data())
def test_image_files(data):
    name = data.draw(st.sampled_from(sorted(VALID_IMAGES)), label="image")
    spoiled = data.draw(mutated(VALID_IMAGES[name]), label="bytes")
    with scratch() as tmp:
        path = tmp / name
        path.write_bytes(spoiled)
        for reader in IMAGE_READERS.values():
            must_refuse_cleanly(lambda: reader(path))


# --------------------------------------------------------------------------- BVH, TOML parameters
@fuzz_settings(EXAMPLES * 2)
@given(spoiled=mutated((DATA / "bvh" / "simple.bvh").read_bytes()))
def test_bvh_files(spoiled):
    with scratch() as tmp:
        path = tmp / "clip.bvh"
        path.write_bytes(spoiled)
        must_refuse_cleanly(lambda: read_bvh(path))


@fuzz_settings(EXAMPLES)
@given(spoiled=mutated((DATA / "bvh" / "simple.bvh").read_bytes()))
def test_bvh_import(model, spoiled):
    """A clip that parses must import (retarget onto the body) or be refused: ``mocap synth --clip``."""
    with scratch() as tmp:
        path = tmp / "clip.bvh"
        path.write_bytes(spoiled)
        must_refuse_cleanly(lambda: import_bvh(model, path))


def _toml(doc: dict) -> bytes:
    def value(v):
        if isinstance(v, bool):
            return str(v).lower()
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)
    return "".join(f"{k} = {value(v)}\n" for k, v in doc.items()).encode()


@fuzz_settings(EXAMPLES)
@given(spoiled=mutated(_toml(params_dict(CheungParams(thresholds=((5.0, 30.0, 0.1), (5.0, 30.0, 0.1)))))))
def test_segmentation_parameters(spoiled):
    with scratch() as tmp:
        path = tmp / "params.toml"
        path.write_bytes(spoiled)
        must_refuse_cleanly(lambda: load_params("cheung", path))


# --------------------------------------------------------------------------- the CLI
# Commands fuzzed in-process with their inputs missing, so that a run stops at its first read
# (synth reads nothing: only its parsing is fuzzed). keys, server, live, bench and client start
# or write things and are left out.
RUN_COMMANDS = {
    "fit": ["{missing}", "--out", "{out}"], "voxels": ["{missing}", "--out", "{out}"], "segment": ["{missing}"],
    "export": ["{missing}", "--format", "bvh"], "report": ["{missing}", "--out", "{out}/r.html"],
    "import-video": ["--calibration", "{missing}/c.json", "--video", "cam1={missing}/v.mp4", "--out", "{out}"],
    "calib show": ["{missing}"], "calib convert": ["{missing}", "{out}/c.json"],
}
PARSE_ONLY = {"synth": ["--out", "{out}"]}
OPTION_TEXT = st.one_of(
    st.integers(-10 ** 6, 10 ** 6).map(str), st.floats().map(repr),
    st.sampled_from(["nan", "inf", "-inf", "1e309", "0", "-0", "-1", "", " ", "abc", "1,2", "0x10", "1_0", "3 ",
                     "64x48", "0x0", "-1x5", "cam1=x", "+z", "-h", "--"]),
    # no line breaks or other control characters: the CLI prints a path as it is given, so one
    # holding a line break would make a message of two lines
    st.text(st.characters(blacklist_categories=("Cc", "Zl", "Zp")), max_size=6))


def _subparser(command: str):
    parser = build_parser()
    for word in command.split():
        parser = next(a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict)).choices[word]
    return parser


def _value_options(command: str) -> list[tuple[str, int]]:
    """(option, number of values) of every option of ``command`` that takes values."""
    out = []
    for action in _subparser(command)._actions:
        if action.option_strings and action.nargs != 0 and "--help" not in action.option_strings:
            count = action.nargs if isinstance(action.nargs, int) else 1
            out.append((action.option_strings[-1], count))
    return out


def _option_words(option: str, values: list[str]) -> list[str]:
    """One value as ``--opt=VALUE`` (any text, "-1" or "-h" included); several as separate words."""
    return [f"{option}={values[0]}"] if len(values) == 1 else [option, *values]


def cli_argv(command: str) -> st.SearchStrategy[list[str]]:
    """One to three of ``command``'s options that take values, with random values."""
    options = _value_options(command)
    chosen = st.lists(st.sampled_from(options), min_size=1, max_size=3, unique=True)

    def words(opts):
        values = st.tuples(*[st.lists(OPTION_TEXT, min_size=n, max_size=n) for _, n in opts])
        return values.map(lambda vals: [w for (opt, _), v in zip(opts, vals) for w in _option_words(opt, v)])
    return chosen.flatmap(words)


def run_cli(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse
            rc = exc.code
    return rc, err.getvalue()


@fuzz_settings(EXAMPLES * 2)
@given(data=st.data())
def test_cli_options(data):
    command = data.draw(st.sampled_from(sorted(RUN_COMMANDS) + sorted(PARSE_ONLY)), label="command")
    template = RUN_COMMANDS.get(command) or PARSE_ONLY[command]
    options = data.draw(cli_argv(command), label="options")
    with scratch() as tmp:
        fixed = [a.format(missing=tmp / "missing", out=tmp / "out") for a in template]
        argv = command.split() + fixed + options
        if command in PARSE_ONLY:
            try:
                _subparser(command).parse_args(fixed + options)
            except SystemExit as exc:
                assert exc.code == 2
            return
        rc, err = run_cli(argv)
        assert rc == 2, (argv, rc, err)
        assert "Traceback" not in err and err.count("\n") == 1 and err.startswith("mocap"), (argv, err)
