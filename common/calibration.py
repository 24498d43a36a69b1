"""Calibration files: read and write studios in the formats users already have.

Our own JSON format (``calibration.json``)::

    {"format": "silhouette-mocap-calibration", "version": 1, "units": "m",
     "cameras": [{"name": str, "K": 3x3, "dist": [k1, k2, p1, p2, k3], "R": 3x3,
                  "t": [3], "width": int, "height": int}, ...]}

Other formats (``FORMATS``), read and written the way their tools do:

- ``easymocap``: a folder with OpenCV FileStorage YAML ``intri.yml`` (``names``, ``K_<cam>``,
  ``dist_<cam>``, optional ``H_<cam>``/``W_<cam>``) and ``extri.yml`` (``R_<cam>`` Rodrigues,
  ``Rot_<cam>`` 3x3, ``T_<cam>``), as EasyMocap's ``write_camera`` writes them.
- ``pose2sim``: ``Calib.toml``, ``[cam_01]`` sections with name, size, matrix, 4 distortions
  (k1 k2 p1 p2; a 5th, k3, is written only when non-zero), Rodrigues rotation, translation,
  ``fisheye = false``; ``[metadata]``.
- ``anipose``: ``calibration.toml`` as aniposelib's ``CameraGroup.dump`` writes it
  (``[cam_0]`` ... with 5 distortions; ``[metadata]``).
- ``opencv-xml``: OpenCV FileStorage XML, one file per camera (a folder of ``<cam>.xml``, or of
  ``<cam>/<any>.xml``), tag names matched case-insensitively from common spellings.

Camera sections in TOML files and XML files in folders are taken in natural order
(``cam_2`` before ``cam_10``). Translations are metres inside; files other than our JSON do
not say their units, so ``units`` scales them, and without ``units`` a rig whose cameras stand
more than ``MAX_CAMERA_DISTANCE`` from the origin is refused as probably millimetres.
Numbers are written with full double precision (EasyMocap itself writes 6 decimals), so every
format round-trips exactly.
"""
from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from common.camera import Camera, CalibrationError, Studio, make_camera

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

JSON_FORMAT_NAME = "silhouette-mocap-calibration"
JSON_VERSION = 1
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # metres per unit
FORMATS = ("json", "easymocap", "pose2sim", "anipose", "opencv-xml")
ROUNDING_TOLERANCE = 1e-5  # |R^T R - I| of a rotation matrix written with 6 decimals; snapped
MAX_CAMERA_DISTANCE = 50.0  # metres; a camera centre farther from the origin means "not metres"
EASYMOCAP_FILES = ("intri.yml", "extri.yml")
TOML_NON_CAMERA_SECTIONS = ("metadata", "capture_volume", "charuco", "checkerboard")  # FreeMocap adds the last three
YAML_KEY_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")  # what OpenCV FileStorage accepts in K_<cam> keys
FILE_NAME = re.compile(r"^(?!\.\.?$)[^/\\\x00-\x1f]+$")  # a camera name usable as <cam>.xml

# OpenCV XML node names per field, compared after lower-casing and dropping underscores.
XML_TAGS = {
    "K": ("CameraMatrix", "camera_matrix", "K", "Intrinsics", "intrinsic", "intrinsic_matrix"),
    "dist": ("DistortionCoeffs", "distortion_coefficients", "dist_coeffs", "D", "Distortion", "dist"),
    "R": ("Rotation", "R", "rotation_matrix", "rvec"),
    "t": ("Translation", "T", "tvec"),
    "width": ("image_width", "width"),
    "height": ("image_height", "height"),
    "size": ("ImageSize", "image_size", "size"),
}


# ----------------------------------------------------------------------------- our JSON

def studio_to_json(studio: Studio) -> dict:
    return {
        "format": JSON_FORMAT_NAME,
        "version": JSON_VERSION,
        "units": "m",
        "cameras": [
            {"name": c.name, "K": c.K.tolist(), "dist": c.dist.tolist(), "R": c.R.tolist(),
             "t": c.t.tolist(), "width": c.width, "height": c.height}
            for c in studio
        ],
    }


def studio_from_json(doc, source: str, units: str | None = None) -> Studio:
    if not isinstance(doc, dict):
        raise CalibrationError(source, "<root>", "expected a JSON object")
    if doc.get("format", JSON_FORMAT_NAME) != JSON_FORMAT_NAME:
        raise CalibrationError(source, "format", f"expected {JSON_FORMAT_NAME!r}, got {doc.get('format')!r}")
    file_units = doc.get("units", units or "m")
    if file_units not in UNIT_SCALE:
        raise CalibrationError(source, "units", f"expected one of {sorted(UNIT_SCALE)}, got {file_units!r}")
    scale = UNIT_SCALE[file_units]
    cams = doc.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise CalibrationError(source, "cameras", "missing or empty list")
    out = []
    for i, c in enumerate(cams):
        if not isinstance(c, dict):
            raise CalibrationError(source, f"cameras[{i}]", "expected an object")
        for key in ("name", "K", "R", "t", "width", "height"):
            if key not in c:
                raise CalibrationError(source, f"cameras[{i}].{key}", "missing")
        t = np.asarray(c["t"], dtype=np.float64) * scale if _numeric(c["t"]) else c["t"]
        out.append(make_camera(c["name"], c["K"], c.get("dist"), c["R"], t, c["width"], c["height"], source))
    studio = Studio(tuple(out), source)
    if "units" not in doc and units is None:
        check_units(studio, source)
    return studio


def _numeric(value) -> bool:
    try:
        return np.asarray(value, dtype=np.float64).size > 0
    except (TypeError, ValueError):
        return False


# ----------------------------------------------------------------------------- public API

def load_calibration(path, units: str | None = None, fmt: str | None = None,
                     size: tuple[int, int] | None = None) -> Studio:
    """Read a studio from ``path`` in any of ``FORMATS`` (detected when ``fmt`` is None).

    units: "m", "cm" or "mm" for files that do not say (None: metres, checked for plausibility).
    size: (width, height) pixels for cameras whose file gives no image size.
    """
    path = Path(path)
    if units is not None and units not in UNIT_SCALE:
        raise CalibrationError(str(path), "units", f"expected one of {sorted(UNIT_SCALE)}, got {units!r}")
    if not path.exists():
        raise CalibrationError(str(path), "<file>", "does not exist")
    fmt = fmt or detect_format(path)
    if fmt == "json":
        if path.is_dir():
            raise CalibrationError(str(path), "<file>", "is a folder, expected a calibration JSON file")
        return studio_from_json(_read_json(path), str(path), units)
    scale = UNIT_SCALE[units or "m"]
    if fmt == "easymocap":
        studio = _read_easymocap(path.parent if path.is_file() else path, scale, size)
    elif fmt in ("pose2sim", "anipose"):
        studio = _read_toml(path, scale, size)
    elif fmt == "opencv-xml":
        studio = _read_xml(path, scale, size)
    else:
        raise CalibrationError(str(path), "format", f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    if units is None:
        check_units(studio, str(path))
    return studio


def save_calibration(studio: Studio, path, fmt: str | None = None) -> None:
    """Write ``studio`` to ``path`` as ``fmt`` (default: from the name, see ``output_format``).

    easymocap and opencv-xml write into a folder ``path`` (opencv-xml writes one file when
    ``path`` ends in .xml and the studio has one camera).
    """
    path = Path(path)
    fmt = output_format(path, fmt)
    if fmt in ("json", "pose2sim", "anipose") and path.is_dir():
        raise CalibrationError(str(path), "<file>", f"is a folder; {fmt} calibration is a single file")
    if fmt == "json":
        text = json.dumps(studio_to_json(studio), indent=1)
        _write(path, text)
    elif fmt == "pose2sim":
        _write(path, _pose2sim_text(studio))
    elif fmt == "anipose":
        _write(path, _anipose_text(studio))
    elif fmt == "easymocap":
        _check_names(studio, str(path), YAML_KEY_NAME, "only letters, digits, '_' and '-'")
        intri, extri = _easymocap_texts(studio)
        _write(path / EASYMOCAP_FILES[0], intri, newline="")
        _write(path / EASYMOCAP_FILES[1], extri, newline="")
    elif fmt == "opencv-xml":
        _check_names(studio, str(path), FILE_NAME, "it must be usable as a file name")
        if path.suffix.lower() == ".xml":
            if len(studio) != 1:
                raise CalibrationError(str(path), "<file>", f"one .xml file holds one camera, the studio has "
                                       f"{len(studio)}; give a folder to write one file per camera")
            _write(path, _xml_text(studio[0]))
        else:
            for cam in studio:
                _write(path / f"{cam.name}.xml", _xml_text(cam))


def detect_format(path) -> str:
    """The format of an existing calibration file or folder (one of ``FORMATS``)."""
    path = Path(path)
    if path.is_dir():
        if all((path / name).is_file() for name in EASYMOCAP_FILES):
            return "easymocap"
        if _xml_camera_files(path):
            return "opencv-xml"
        raise CalibrationError(str(path), "<folder>", "no calibration found: expected intri.yml + extri.yml "
                               "(EasyMocap) or OpenCV .xml files (one per camera, or one per sub-folder)")
    suffix = path.suffix.lower()
    if suffix == ".toml":
        doc = _read_toml_doc(path)
        sections = _toml_camera_sections(doc)
        if sections and all(isinstance(doc[s], dict) and "fisheye" in doc[s] for s in sections):
            return "pose2sim"
        return "anipose"
    if suffix == ".xml":
        return "opencv-xml"
    if suffix in (".yml", ".yaml"):
        return "easymocap"
    return "json"


def output_format(path, fmt: str | None = None) -> str:
    """The format to write ``path`` in: ``fmt`` if given, else from the name.

    .json -> json, .toml -> pose2sim (Pose2Sim's Calib.toml is in metres like us; pass
    ``anipose`` for aniposelib), .xml -> opencv-xml (one camera). A folder needs ``fmt``.
    """
    path = Path(path)
    if fmt is not None:
        if fmt not in FORMATS:
            raise CalibrationError(str(path), "format", f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
        return fmt
    by_suffix = {".json": "json", ".toml": "pose2sim", ".xml": "opencv-xml"}
    suffix = path.suffix.lower()
    if suffix in by_suffix and not path.is_dir():
        return by_suffix[suffix]
    raise CalibrationError(str(path), "format", "cannot tell the output format from the name; pass "
                           "--format (easymocap and opencv-xml write a folder, json/pose2sim/anipose a file)")


def check_units(studio: Studio, source: str) -> None:
    """Refuse a studio whose translations look like millimetres or centimetres read as metres."""
    distances = [float(np.linalg.norm(c.center)) for c in studio]
    i = int(np.argmax(distances))
    if distances[i] > MAX_CAMERA_DISTANCE:
        raise CalibrationError(
            source, "units",
            f"camera {studio[i].name!r} stands {distances[i]:.1f} units from the origin, more than "
            f"{MAX_CAMERA_DISTANCE:.0f} m if they were metres; the file looks like millimetres or "
            "centimetres: pass --units mm (or cm; --units m if the studio really is that large)")


def natural_key(text: str) -> tuple:
    """Sort key putting "cam_2" before "cam_10"."""
    parts = re.split(r"(\d+)", text)
    return tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(parts))


def rodrigues_to_matrix(rvec) -> np.ndarray:
    """(3,) axis * angle (radians) -> (3, 3) rotation matrix, as cv2.Rodrigues."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta == 0.0:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * (kx @ kx)


def matrix_to_rodrigues(R) -> np.ndarray:
    """(3, 3) rotation matrix -> (3,) axis * angle, as cv2.Rodrigues (angle in [0, pi])."""
    R = np.asarray(R, dtype=np.float64)
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # sin(theta) * axis
    s = float(np.linalg.norm(v))
    c = 0.5 * (np.trace(R) - 1.0)
    theta = float(np.arctan2(s, c))
    if c > -0.9:  # away from pi the skew part gives the axis accurately
        return v * (theta / s) if s > 0.0 else np.zeros(3)
    # near pi: R + R^T = 2 cos I + 2 (1 - cos) k k^T; take the strongest column for the axis
    B = 0.5 * (R + R.T) - c * np.eye(3)
    j = int(np.argmax(np.diag(B)))
    k = B[:, j] / np.linalg.norm(B[:, j])
    if k @ v < 0.0:
        k = -k
    return k * theta


# ----------------------------------------------------------------------------- shared helpers

@dataclass(frozen=True)
class _CvMat:
    """An OpenCV matrix node as read (validated later, when the file and field are known)."""
    rows: object
    cols: object
    data: object


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(str(path), "<file>", f"cannot read ({exc})") from None


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationError(str(path), "<file>", f"not valid JSON ({exc})") from None


def _write(path: Path, text: str, newline: str | None = None) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w", encoding="utf-8", newline=newline) as f:
            f.write(text)
    except OSError as exc:
        raise CalibrationError(str(path), "<file>", f"cannot write ({exc})") from None


def _numbers(value, source: str, field: str) -> np.ndarray:
    """Numbers (nested lists, an OpenCV matrix node, or text) -> float64 array."""
    if isinstance(value, _CvMat):
        return _cvmat(value, source, field)
    if isinstance(value, str):
        value = value.split()

    def scalar(x):
        if isinstance(x, bool) or x is None:
            raise ValueError
        return float(x)

    def convert(x):
        return [convert(e) for e in x] if isinstance(x, (list, tuple)) else scalar(x)

    try:
        arr = np.asarray(convert(value), dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(source, field, f"not numeric: {value!r}") from None
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(source, field, "contains NaN or infinity")
    return arr


def _cvmat(mat: _CvMat, source: str, field: str) -> np.ndarray:
    try:
        rows, cols = int(mat.rows), int(mat.cols)
    except (TypeError, ValueError):
        raise CalibrationError(source, field, f"rows/cols not integers: {mat.rows!r} x {mat.cols!r}") from None
    data = _numbers(mat.data, source, field).reshape(-1)
    if data.size != rows * cols:
        raise CalibrationError(source, field, f"data has {data.size} values, expected rows x cols = {rows} x {cols}")
    return data.reshape(rows, cols)


def _rotation(value, source: str, field: str) -> np.ndarray:
    """A Rodrigues vector (3 values) or a 3x3 matrix -> (3, 3).

    A matrix that is a rotation to the decimals it was written with is snapped to the nearest
    rotation (a no-op for full-precision files); anything farther is left for make_camera to refuse.
    """
    arr = _numbers(value, source, field)
    if arr.size == 3:
        return rodrigues_to_matrix(arr)
    if arr.size == 9:
        R = arr.reshape(3, 3)
        err = np.abs(R.T @ R - np.eye(3)).max()
        if err <= ROUNDING_TOLERANCE and np.linalg.det(R) > 0:
            u, _, vt = np.linalg.svd(R)  # the nearest rotation: undo the file's rounding
            R = u @ vt
        return R
    raise CalibrationError(source, field, f"expected a Rodrigues vector (3 values) or a 3x3 matrix, "
                           f"got shape {arr.shape}")


def _pixels(value, source: str, field: str) -> int:
    arr = _numbers(value, source, field).reshape(-1)
    if arr.size != 1 or not float(arr[0]).is_integer():
        raise CalibrationError(source, field, f"expected a whole number of pixels, got {value!r}")
    return int(arr[0])


def _build(name: str, K, dist, R, t, width, height, scale: float, fields: dict) -> Camera:
    """Parse and validate one camera; ``fields`` maps K/dist/R/t/size -> (source, field in the file).

    R may be a Rodrigues vector or a 3x3 matrix; t is scaled to metres.
    """
    K = _numbers(K, *fields["K"])
    dist = _numbers(dist, *fields["dist"]) if dist is not None else None
    R = _rotation(R, *fields["R"])
    t = _numbers(t, *fields["t"])
    width = _pixels(width, *fields["size"])
    height = _pixels(height, *fields["size"])
    try:
        return make_camera(name, K, dist, R, t * scale, width, height, fields["K"][0])
    except CalibrationError as exc:  # name the field as the file spells it
        key = exc.field_name.rsplit(".", 1)[-1]
        source, field = fields.get(key, (exc.source, exc.field_name))
        raise CalibrationError(source, field, exc.problem) from None


def _size_or_fallback(width, height, size, source: str, field: str):
    if width is not None and height is not None:
        return width, height
    if size is not None:
        return size
    raise CalibrationError(source, field, "missing (the file gives no image size; pass --size WxH)")


def _check_names(studio: Studio, target: str, pattern: re.Pattern, allowed: str) -> None:
    for cam in studio:
        if not pattern.match(cam.name):
            raise CalibrationError(target, f"{cam.name}.name", f"cannot be written to this format: {allowed}")


def _num(x) -> str:
    """Shortest text that reads back as the same double, always with a '.' (YAML 1.1 floats need it)."""
    text = repr(float(x))
    if "." not in text and "e" in text:
        mantissa, exponent = text.split("e")
        text = f"{mantissa}.0e{exponent}"
    return text


# ----------------------------------------------------------------------------- EasyMocap YAML

class _OpenCVYamlLoader(yaml.SafeLoader):
    """PyYAML loader that understands OpenCV's ``!!opencv-matrix`` nodes."""


def _construct_cvmat(loader, node):
    m = loader.construct_mapping(node, deep=True)
    return _CvMat(m.get("rows"), m.get("cols"), m.get("data", []))


_OpenCVYamlLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _construct_cvmat)


def _read_opencv_yaml(path: Path) -> dict:
    text = _read_text(path)
    # PyYAML rejects OpenCV's "%YAML:1.0" directive; it carries no information, so drop it.
    text = re.sub(r"\A\s*%YAML[: ]?[0-9.]*[^\n]*\n", "", text)
    try:
        doc = yaml.load(text, Loader=_OpenCVYamlLoader)
    except yaml.YAMLError as exc:
        problem = " ".join(str(exc).split())
        raise CalibrationError(str(path), "<file>", f"not valid OpenCV YAML ({problem})") from None
    if not isinstance(doc, dict):
        raise CalibrationError(str(path), "<root>", "expected a mapping of named nodes")
    return doc


def _read_easymocap(folder: Path, scale: float, size) -> Studio:
    intri_path, extri_path = folder / EASYMOCAP_FILES[0], folder / EASYMOCAP_FILES[1]
    for p in (intri_path, extri_path):
        if not p.is_file():
            raise CalibrationError(str(p), "<file>", "does not exist (EasyMocap needs intri.yml and extri.yml)")
    intri, extri = _read_opencv_yaml(intri_path), _read_opencv_yaml(extri_path)
    si, se = str(intri_path), str(extri_path)
    names = intri.get("names")
    if not isinstance(names, list) or not names:
        raise CalibrationError(si, "names", "missing or empty list of camera names")
    cams = []
    for raw in names:
        name = str(raw)
        K, k_key = _yaml_node(intri, si, f"K_{name}")
        dist, d_key = _yaml_node(intri, si, f"dist_{name}", f"D_{name}")
        R, r_key = _yaml_node(extri, se, f"R_{name}", f"Rot_{name}")  # EasyMocap itself uses the Rodrigues R_
        t, t_key = _yaml_node(extri, se, f"T_{name}")
        height, width = intri.get(f"H_{name}"), intri.get(f"W_{name}")
        size_field = f"H_{name}/W_{name}"
        width, height = _size_or_fallback(width, height, size, si, size_field)
        fields = {"K": (si, k_key), "dist": (si, d_key), "R": (se, r_key), "t": (se, t_key),
                  "size": (si, size_field)}
        cams.append(_build(name, K, dist, R, t, width, height, scale, fields))
    return Studio(tuple(cams), str(folder))


def _yaml_node(doc: dict, source: str, *keys):
    """The first of ``keys`` present in ``doc`` -> (value, key); CalibrationError naming keys[0] if none."""
    for key in keys:
        if doc.get(key) is not None:
            return doc[key], key
    raise CalibrationError(source, keys[0], "missing")


def _yaml_matrix(key: str, value: np.ndarray) -> list[str]:
    """One ``!!opencv-matrix`` node as EasyMocap's FileStorage.write writes it."""
    value = np.atleast_2d(value)
    return [f"{key}: !!opencv-matrix", f"  rows: {value.shape[0]}", f"  cols: {value.shape[1]}", "  dt: d",
            "  data: [{}]".format(", ".join(_num(x) for x in value.reshape(-1)))]


def _easymocap_texts(studio: Studio) -> tuple[str, str]:
    head = ["%YAML:1.0", "---", "names:"] + [f'  - "{c.name}"' for c in studio]
    intri, extri = list(head), list(head)
    for c in studio:
        intri += _yaml_matrix(f"K_{c.name}", c.K) + _yaml_matrix(f"dist_{c.name}", c.dist[None])
        intri += [f"H_{c.name}: {c.height}", f"W_{c.name}: {c.width}"]
        extri += _yaml_matrix(f"R_{c.name}", matrix_to_rodrigues(c.R)[:, None])
        extri += _yaml_matrix(f"Rot_{c.name}", c.R) + _yaml_matrix(f"T_{c.name}", c.t[:, None])
    return "".join(line + "\r\n" for line in intri), "".join(line + "\r\n" for line in extri)


# ----------------------------------------------------------------------------- Pose2Sim / Anipose TOML

def _read_toml_doc(path: Path) -> dict:
    text = _read_text(path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(str(path), "<file>", f"not valid TOML ({exc})") from None


def _toml_camera_sections(doc: dict) -> list[str]:
    return sorted((k for k in doc if k not in TOML_NON_CAMERA_SECTIONS), key=natural_key)


def _read_toml(path: Path, scale: float, size) -> Studio:
    doc = _read_toml_doc(path)
    source = str(path)
    sections = _toml_camera_sections(doc)
    if not sections:
        raise CalibrationError(source, "<root>", "no camera sections (expected [cam_1] ... or [cam_0] ...)")
    cams = []
    for sec in sections:
        c = doc[sec]
        if not isinstance(c, dict):
            raise CalibrationError(source, sec, "expected a [section] describing a camera")
        for key in ("matrix", "distortions", "rotation", "translation"):
            if key not in c:
                raise CalibrationError(source, f"{sec}.{key}", "missing")
        if c.get("fisheye") is True:
            raise CalibrationError(source, f"{sec}.fisheye", "fisheye cameras are not supported "
                                   "(pinhole with k1 k2 p1 p2 k3 only)")
        if "size" in c:
            dims = c["size"]
            if not isinstance(dims, list) or len(dims) != 2:
                raise CalibrationError(source, f"{sec}.size", f"expected [width, height], got {dims!r}")
            width, height = dims
        else:
            width, height = _size_or_fallback(None, None, size, source, f"{sec}.size")
        fields = {"K": (source, f"{sec}.matrix"), "dist": (source, f"{sec}.distortions"),
                  "R": (source, f"{sec}.rotation"), "t": (source, f"{sec}.translation"),
                  "size": (source, f"{sec}.size")}
        name = c.get("name", sec)
        cams.append(_build(str(name), c["matrix"], c["distortions"], c["rotation"], c["translation"],
                           width, height, scale, fields))
    return Studio(tuple(cams), source)


def _toml_string(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)  # a JSON string is a valid TOML basic string


def _pose2sim_text(studio: Studio) -> str:
    """Calib.toml laid out as Pose2Sim's ``toml_write``."""
    out = []
    for i, c in enumerate(studio):
        K = c.K
        dist = c.dist if c.dist[4] != 0.0 else c.dist[:4]  # Pose2Sim writes k1 k2 p1 p2
        r, t = matrix_to_rodrigues(c.R), c.t
        out.append(
            f"[cam_{i + 1:02d}]\n"
            f"name = {_toml_string(c.name)}\n"
            f"size = [ {_num(c.width)}, {_num(c.height)}]\n"
            f"matrix = [ [ {_num(K[0, 0])}, {_num(K[0, 1])}, {_num(K[0, 2])}], "
            f"[ 0.0, {_num(K[1, 1])}, {_num(K[1, 2])}], [ 0.0, 0.0, 1.0]]\n"
            f"distortions = [ {', '.join(_num(d) for d in dist)}]\n"
            f"rotation = [ {_num(r[0])}, {_num(r[1])}, {_num(r[2])}]\n"
            f"translation = [ {_num(t[0])}, {_num(t[1])}, {_num(t[2])}]\n"
            "fisheye = false\n\n")
    out.append("[metadata]\nadjusted = false\nerror = 0.0\n")
    return "".join(out)


def _anipose_text(studio: Studio) -> str:
    """calibration.toml laid out as aniposelib's ``CameraGroup.dump`` (via the toml package)."""

    def arr(values) -> str:
        return "[" + "".join(f" {v}," for v in values) + "]"

    out = []
    for i, c in enumerate(studio):
        r = matrix_to_rodrigues(c.R)
        out.append(
            f"[cam_{i}]\n"
            f"name = {_toml_string(c.name)}\n"
            f"size = {arr([c.width, c.height])}\n"
            f"matrix = {arr(arr(_num(x) for x in row) for row in c.K)}\n"
            f"distortions = {arr(_num(d) for d in c.dist)}\n"
            f"rotation = {arr(_num(x) for x in r)}\n"
            f"translation = {arr(_num(x) for x in c.t)}\n\n")
    out.append("[metadata]\n")
    return "".join(out)


# ----------------------------------------------------------------------------- OpenCV XML

def _xml_camera_files(folder: Path) -> list[tuple[str, Path]]:
    """(camera name, file) for a folder of <cam>.xml, or of <cam>/ sub-folders holding one .xml."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() == ".xml"]
    if files:
        return sorted(((p.stem, p) for p in files), key=lambda e: natural_key(e[0]))
    found = []
    for sub in folder.iterdir():
        if not sub.is_dir():
            continue
        xmls = sorted(p for p in sub.iterdir() if p.is_file() and p.suffix.lower() == ".xml")
        if len(xmls) > 1:
            raise CalibrationError(str(sub), "<folder>", "expected one .xml file per camera folder, found "
                                   + ", ".join(p.name for p in xmls))
        if xmls:
            found.append((sub.name, xmls[0]))
    return sorted(found, key=lambda e: natural_key(e[0]))


def _read_xml(path: Path, scale: float, size) -> Studio:
    if path.is_dir():
        entries = _xml_camera_files(path)
        if not entries:
            raise CalibrationError(str(path), "<folder>", "no .xml camera files")
    else:
        entries = [(path.stem, path)]
    cams = tuple(_read_xml_camera(name, p, scale, size) for name, p in entries)
    return Studio(cams, str(path))


def _xml_value(elem: ET.Element):
    """An OpenCV FileStorage XML node -> _CvMat, or its text (numbers separated by spaces)."""
    if elem.get("type_id") == "opencv-matrix":
        parts = {child.tag.lower(): (child.text or "") for child in elem}
        return _CvMat(parts.get("rows", "").strip(), parts.get("cols", "").strip(), parts.get("data", ""))
    return (elem.text or "").strip()


def _read_xml_camera(name: str, path: Path, scale: float, size) -> Camera:
    source = str(path)
    try:
        root = ET.fromstring(path.read_bytes())
    except OSError as exc:
        raise CalibrationError(source, "<file>", f"cannot read ({exc})") from None
    except ET.ParseError as exc:
        raise CalibrationError(source, "<file>", f"not valid XML ({exc})") from None
    if root.tag != "opencv_storage":
        raise CalibrationError(source, "<root>", f"expected <opencv_storage>, got <{root.tag}>")
    nodes = {}
    for child in root:
        nodes.setdefault(child.tag.lower().replace("_", ""), child)

    def find(field):
        for tag in XML_TAGS[field]:
            elem = nodes.get(tag.lower().replace("_", ""))
            if elem is not None:
                return elem.tag, _xml_value(elem)
        return None, None

    def required(field):
        tag, value = find(field)
        if tag is None:
            raise CalibrationError(source, XML_TAGS[field][0], "missing (also accepted: "
                                   + ", ".join(XML_TAGS[field][1:]) + ")")
        return tag, value

    k_tag, K = required("K")
    d_tag, dist = find("dist")
    r_tag, R = required("R")
    t_tag, t = required("t")
    w_tag, width = find("width")
    h_tag, height = find("height")
    s_tag, dims = find("size")
    size_field = "image_width/image_height"
    if (width is None or height is None) and dims is not None:
        arr = _numbers(dims, source, s_tag).reshape(-1)
        if arr.size != 2:
            raise CalibrationError(source, s_tag, f"expected 2 values (width height), got {arr.size}")
        (width, height), size_field = arr.tolist(), s_tag
    elif width is not None and height is not None:
        size_field = f"{w_tag}/{h_tag}"
    width, height = _size_or_fallback(width, height, size, source, size_field)
    fields = {"K": (source, k_tag), "dist": (source, d_tag or XML_TAGS["dist"][0]), "R": (source, r_tag),
              "t": (source, t_tag), "size": (source, size_field)}
    return _build(name, K, dist, R, t, width, height, scale, fields)


def _xml_matrix(tag: str, value: np.ndarray) -> str:
    value = np.atleast_2d(value)
    return (f'<{tag} type_id="opencv-matrix">\n  <rows>{value.shape[0]}</rows>\n'
            f"  <cols>{value.shape[1]}</cols>\n  <dt>d</dt>\n  <data>\n"
            f"    {' '.join(_num(x) for x in value.reshape(-1))}</data></{tag}>\n")


def _xml_text(cam: Camera) -> str:
    """One camera as OpenCV FileStorage XML (translation in metres)."""
    return ('<?xml version="1.0"?>\n<opencv_storage>\n'
            + _xml_matrix("CameraMatrix", cam.K)
            + _xml_matrix("DistortionCoeffs", cam.dist[:, None])
            + _xml_matrix("Rotation", cam.R)
            + _xml_matrix("Translation", cam.t[:, None])
            + f"<image_width>{cam.width}</image_width>\n<image_height>{cam.height}</image_height>\n"
            + "</opencv_storage>\n")
