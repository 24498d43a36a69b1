"""Calibration files: read and write studios in the formats users already have.

Our own JSON format (``calibration.json``; ``version`` other than ``JSON_VERSION`` is refused,
and so is a key it does not have, with the closest known one suggested)::

    {"format": "silhouette-mocap-calibration", "version": 1, "units": "m",
     "cameras": [{"name": str, "K": 3x3, "dist": [k1, k2, p1, p2, k3], "R": 3x3,
                  "t": [3], "width": int, "height": int, "size_guessed": bool (optional)}, ...]}

Other formats (``FORMATS``; ``WRITE_FORMATS`` are also written), the way their tools lay them out:

- ``easymocap``: a folder with OpenCV FileStorage YAML ``intri.yml`` (``names``, ``K_<cam>``,
  ``dist_<cam>``, optional ``H_<cam>``/``W_<cam>``: EasyMocap's ``write_intri`` writes none) and
  ``extri.yml`` (``R_<cam>`` Rodrigues, ``Rot_<cam>`` 3x3, ``T_<cam>``).
- ``pose2sim``: ``Calib.toml``, ``[cam_01]`` sections with name, size, matrix, 4 distortions
  (k1 k2 p1 p2; a 5th, k3, is written only when non-zero), Rodrigues rotation, translation,
  ``fisheye = false``; ``[metadata]``.
- ``anipose``: ``calibration.toml`` as aniposelib's ``CameraGroup.dump`` writes it
  (``[cam_0]`` ... with 5 distortions; ``[metadata]``).
- ``opencv-xml``: OpenCV FileStorage XML, one file per camera, tag names matched
  case-insensitively from common spellings (``XML_TAGS``).
- ``projection``: one 3x4 projection matrix P = K [R | t] per camera: a ``.txt`` of 12 numbers
  (``#`` comment lines and a PMVS ``CONTOUR`` header allowed) or an OpenCV XML file with a
  ``P``/``ProjectionMatrix`` node. P is split into K, R, t by an RQ decomposition (fx, fy > 0,
  det R = +1, K[2, 2] = 1); no distortion. A skew |K[0, 1]| above ``SKEW_WARNING`` * fx is kept
  (our cameras model skew) and reported in a warning line, since it usually means a poor P.
- ``qualisys``: a QTM ``.qca.txt`` (XML ``<calibration><cameras><camera serial=...>``), read as
  Pose2Sim's ``calib_qca_fun``: ``intrinsic`` values (focal lengths, centre point, distortions)
  in 1/64 pixel, principal point shifted by ``fov_video`` left/top, image size from
  ``fov_video``, ``transform`` the camera's position (mm) and rotation (r11..r33 column-major,
  as Pose2Sim reads them) in a camera frame with y up and z backwards, turned by pi about x into
  OpenCV's. ``viewrotation`` (0/90/180/270, taken as clockwise) turns the image: K, R, the
  tangential distortion and the size follow. Cameras whose ``model`` is marker-only are skipped.

The other formats' files may hold other tools' fields (OpenCV's calibration sample, EasyVolcap,
FreeMocap add theirs), which are passed over; but a name we do not read that is close to a field
the camera lacks (``DistortionCoeffz``, ``dsit_01``, ``viewRotation``: difflib, case ignored,
``MISSPELT_MATCH``) is refused as misspelt, since the camera would silently go without it.

A folder of per-camera files (``opencv-xml`` and ``projection``) is either ``<cam>.xml`` /
``<cam>.txt`` files at the top, or ``<cam>/`` sub-folders each holding one file with a camera
(K, R and t, or P). Files holding no camera (a board description, an intrinsics-only estimate
next to the full camera) are skipped and named in one warning line; two files with a camera in
one sub-folder are an error. A ``.txt`` made only of numbers is a projection file (12 numbers).
A folder may also hold a single-file calibration (our ``calibration.json``, a Pose2Sim or
Anipose ``.toml``, a ``.qca.txt``), which is then read; a folder holding two calibrations of any
kinds (``calibration.json`` beside the camera files it was converted from, EasyMocap's files
beside camera files, camera files both at the top and in sub-folders) is refused, naming them
(``folder_calibrations``), since the one last edited may not be the one that would be read.

Image sizes are optional in every format (and at most ``MAX_IMAGE_PIXELS``, as every image read
is): without one in the file or ``size``, a camera's size
is twice its principal point, rounded (as Pose2Sim's converters do), one warning line names the
cameras, and ``Camera.size_guessed`` is set (kept in our JSON as ``"size_guessed": true``) so
that ``with_image_sizes`` can later put in the images' real size. EasyMocap and OpenCV XML are
written without a guessed size; Pose2Sim and Anipose, whose files always hold one, are not
written with a guess (``check_sizes_writable``).

Camera sections in TOML files and files in folders are taken in natural order (``cam_2`` before
``cam_10``). Translations are metres inside; files other than our JSON and Qualisys (mm) do
not say their units, so ``units`` scales them (a file that says its units is read in them, and
a ``units`` that disagrees is named in a warning), and without ``units`` a rig whose cameras
stand more than ``MAX_CAMERA_DISTANCE`` from the origin is refused as probably millimetres.
Whoever gave the units, a rig whose farthest two cameras stand outside ``STUDIO_CAMERA_SPAN``
gets a warning line. Numbers are written with full double precision (EasyMocap itself writes 6
decimals), so every written format round-trips exactly.

One module of about 1,450 lines: the seven formats share the field checks, units, image sizes
and camera building of its first half; each later section is one format's reader and writer.
"""
from __future__ import annotations

import difflib
import json
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from common.camera import Camera, CalibrationError, Studio, make_camera
from common.errors import FieldChecks, print_warning

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

JSON_FORMAT_NAME = "silhouette-mocap-calibration"
JSON_VERSION = 1  # the only version there is; a file of another was written by a newer release
JSON_FIELDS = ("format", "version", "units", "cameras")
JSON_CAMERA_FIELDS = ("name", "K", "dist", "R", "t", "width", "height", "size_guessed")
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # metres per unit
WRITE_FORMATS = ("json", "easymocap", "pose2sim", "anipose", "opencv-xml")
FORMATS = WRITE_FORMATS + ("projection", "qualisys")
ROUNDING_TOLERANCE = 1e-5  # |R^T R - I| of a rotation matrix written with 6 decimals; snapped
MAX_CAMERA_DISTANCE = 50.0  # metres; a camera centre farther from the origin means "not metres"
# metres: the farthest two cameras of a capture room (or a stereo pair) stand at least and at
# most this far apart; outside it, the units the file was read in are likely wrong (a millimetre
# file read as cm: tens of metres; metres in a file that says mm: millimetres apart). Between
# cameras, not from the origin: a stereo file has one camera there
STUDIO_CAMERA_SPAN = (0.02, 30.0)
UNIT_ORIGINS = {  # where the units of a studio outside that span came from -> (how it was read, what to check)
    "given": ("with --units {units}", "check --units"),
    "declared": ("in {units}, as the file says,", "are the file's units right?"),
    "assumed": ("in metres (the file does not say)", "pass --units if they are not metres"),
}
# Pixels (width x height) a camera's image, and so any image file read, may have: three times
# 8K video (7680 x 4320, 33 Mpx), ten times a 10 Mpx machine-vision camera; 300 MB as RGB.
MAX_IMAGE_PIXELS = 100_000_000
EASYMOCAP_FILES = ("intri.yml", "extri.yml")
SINGLE_FILE_NAMES = ("calibration.json", "calibration.toml", "calib.toml")  # lower-cased; ours, Anipose's, Pose2Sim's
MAX_SINGLE_FILE_BYTES = 16 * 2**20  # bytes; a larger .json/.toml in a calibration folder is not looked into
TOML_NON_CAMERA_SECTIONS = ("metadata", "capture_volume", "charuco", "checkerboard")  # FreeMocap adds the last three
TOML_CAMERA_FIELDS = ("name", "size", "matrix", "distortions", "rotation", "translation", "fisheye")
# EasyMocap keys <prefix>_<camera> per file; a group's prefixes are spellings of one field
EASYMOCAP_FIELDS = {"intri.yml": (("K",), ("dist", "D"), ("H",), ("W",)), "extri.yml": (("R", "Rot"), ("T",))}
# what QTM writes on a <camera>, its children and its <intrinsic> (Pose2Sim's spelling "tangential" too)
QUALISYS_CAMERA_ATTRIBUTES = ("active", "avg-residual", "model", "point-count", "serial", "viewrotation")
QUALISYS_CAMERA_CHILDREN = ("fov_marker", "fov_marker_max", "fov_video", "fov_video_max", "transform", "intrinsic")
QUALISYS_INTRINSIC_ATTRIBUTES = (
    "focallength", "sensorMinU", "sensorMaxU", "sensorMinV", "sensorMaxV", "focalLengthU", "focalLengthV",
    "pixelAspectRatio", "centerPointU", "centerPointV", "skew", "radialDistortion1", "radialDistortion2",
    "radialDistortion3", "tangentalDistortion1", "tangentalDistortion2", "tangentialDistortion1",
    "tangentialDistortion2")
# difflib ratio from which a name we do not read is taken for a misspelling of a field the camera
# lacks (DistortionCoeffz 0.94, dsit_01 0.86), not for another tool's node (image_points vs
# image_size 0.6); and the lower one from which our JSON's error suggests a field
MISSPELT_MATCH = 0.8
SUGGEST_MATCH = 0.6
YAML_KEY_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")  # what OpenCV FileStorage accepts in K_<cam> keys
FILE_NAME = re.compile(r"^(?!\.\.?$)[^/\\\x00-\x1f]+$")  # a camera name usable as <cam>.xml
SKEW_WARNING = 0.01  # |K[0, 1]| / fx of a decomposed P above which a warning names the camera
SINGULAR_P = 1e-12  # |det M| / |M|^3 (M = P[:, :3]) below which a projection matrix is singular
QUALISYS_SUBPIXELS = 64.0  # Qualisys writes intrinsics and distortions in 1/64 pixel
QUALISYS_SUFFIX = ".qca.txt"
QUALISYS_VIEW_ROTATIONS = (0, 90, 180, 270)  # degrees, clockwise
CONTOUR_HEADER = "CONTOUR"  # first line of PMVS / VisualSFM projection files
FULL_KINDS = ("camera", "projection")  # file kinds holding a whole camera
TOP_CAMERA_KINDS = FULL_KINDS + ("broken", "foreign")  # read (and refused if bad) when files are at the top
QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])  # Qualisys camera frame (y up, z backwards) -> OpenCV's
TURN_CLOCKWISE = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera frame of a turned image

# OpenCV XML node names per field, compared after lower-casing and dropping underscores.
XML_TAGS = {
    "K": ("CameraMatrix", "camera_matrix", "K", "Intrinsics", "intrinsic", "intrinsic_matrix"),
    "dist": ("DistortionCoeffs", "distortion_coefficients", "dist_coeffs", "D", "Distortion", "dist"),
    "R": ("Rotation", "R", "rotation_matrix", "rvec"),
    "t": ("Translation", "T", "tvec"),
    "width": ("image_width", "width"),
    "height": ("image_height", "height"),
    "size": ("ImageSize", "image_size", "size"),
    "P": ("ProjectionMatrix", "P", "projection_matrix"),
}
CAMERA_FIELDS = ("K", "R", "t")  # an XML file with all three (or a P) holds a camera
# An XML file of another kind is a damaged camera file, refused when read, where it names tags
# of two camera fields or more (one alone may be a notes file's <p>); one that does not parse,
# where it is empty, has an <opencv_storage> root or names one camera field (a file cut short);
# otherwise it is notes, passed over
CAMERA_FIELD_TAGS = {field: frozenset(tag.lower().replace("_", "") for tag in XML_TAGS[field])
                     for field in (*CAMERA_FIELDS, "P")}
CAMERA_TAG_TEXT = re.compile(r"<\s*([A-Za-z_]+)\b")


def _names_camera_fields(tags, at_least: int = 2) -> bool:
    """Whether ``tags`` (any spelling) name ``at_least`` of the camera fields K, R, t, P."""
    keys = {_tag_key(tag) for tag in tags}
    return sum(1 for field_tags in CAMERA_FIELD_TAGS.values() if keys & field_tags) >= at_least


Warn = Callable[[str], None]  # receives one line to show the user


# ----------------------------------------------------------------------------- our JSON

def studio_to_json(studio: Studio) -> dict:
    return {
        "format": JSON_FORMAT_NAME,
        "version": JSON_VERSION,
        "units": "m",
        "cameras": [
            {"name": c.name, "K": c.K.tolist(), "dist": c.dist.tolist(), "R": c.R.tolist(),
             "t": c.t.tolist(), "width": c.width, "height": c.height,
             **({"size_guessed": True} if c.size_guessed else {})}
            for c in studio
        ],
    }


def _checks(source) -> FieldChecks:
    """Field checks whose failures are CalibrationError (no field for the whole file)."""
    return FieldChecks(source, error=lambda path, where, problem: CalibrationError(path, where, problem))


def studio_from_json(doc, source: str, units: str | None = None) -> Studio:
    """A studio from our JSON document; ``units`` scales files that do not say theirs.

    The format is ours, so a key it does not have is refused (a misspelt "dist" would otherwise
    leave the camera without distortion).
    """
    checks = _checks(source)
    if not isinstance(doc, dict):
        raise CalibrationError(source, "<root>", "expected a JSON object")
    _refuse_unknown_keys(doc, JSON_FIELDS, source, "")
    if doc.get("format", JSON_FORMAT_NAME) != JSON_FORMAT_NAME:
        raise CalibrationError(source, "format", f"expected {JSON_FORMAT_NAME!r}, got {doc.get('format')!r}")
    if doc.get("version", JSON_VERSION) != JSON_VERSION or isinstance(doc.get("version"), bool):
        raise CalibrationError(source, "version", f"version {doc.get('version')!r} is not supported (this release "
                               f"reads version {JSON_VERSION}); convert the file with the release that wrote it")
    file_units = doc.get("units", units or "m")
    if not isinstance(file_units, str) or file_units not in UNIT_SCALE:
        raise CalibrationError(source, "units", f"expected one of {sorted(UNIT_SCALE)}, got {file_units!r}")
    scale = UNIT_SCALE[file_units]
    cams = doc.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise CalibrationError(source, "cameras", "missing or empty list")
    out = []
    for i, c in enumerate(cams):
        if not isinstance(c, dict):
            raise CalibrationError(source, f"cameras[{i}]", "expected an object")
        named = isinstance(c.get("name"), str) and c["name"]
        _refuse_unknown_keys(c, JSON_CAMERA_FIELDS, source, f"{c['name'] if named else f'cameras[{i}]'}.")
        for key in ("name", "K", "R", "t", "width", "height"):
            if key not in c:
                raise CalibrationError(source, f"cameras[{i}].{key}", "missing")
        name = checks.text(c["name"], f"cameras[{i}].name")
        width, height = (checks.whole(c[key], f"{name}.{key}", minimum=1) for key in ("width", "height"))
        guessed = checks.flag(c.get("size_guessed", False), f"cameras[{i}].size_guessed")
        K, R, t = (_numbers(c[key], source, f"{name}.{key}") for key in ("K", "R", "t"))
        dist = None if c.get("dist") is None else _numbers(c["dist"], source, f"{name}.dist")
        cam = make_camera(name, K, dist, R, t * scale, width, height, source)
        out.append(replace(cam, size_guessed=guessed))
    return Studio(tuple(out), source)


def _refuse_unknown_keys(doc: dict, known: tuple, source: str, where: str) -> None:
    """Refuse the first key of ``doc`` not in ``known``, suggesting the closest known one."""
    for key in doc:
        if key not in known:
            close = _closest(key, known, SUGGEST_MATCH)
            hint = f"did you mean {close}?" if close else "the fields are " + ", ".join(known)
            raise CalibrationError(source, f"{where}{key}", f"not a field we know; {hint}")


def _closest(name: str, spellings, cutoff: float, key: Callable[[str], str] = str.lower) -> str | None:
    """The one of ``spellings`` closest to ``name`` when compared by ``key`` (difflib ratio >= cutoff), else None."""
    by_key = {key(s): s for s in spellings}
    match = difflib.get_close_matches(key(name), list(by_key), n=1, cutoff=cutoff)
    return by_key[match[0]] if match else None


def _refuse_misspelt(names, known, lacking, source: str, where: str = "",
                     read_as: Callable[[str], str] = str) -> None:
    """Refuse the first of ``names`` (keys, nodes, attributes of a file that may hold other tools'
    too) that is not one of ``known`` but close to one of ``lacking``, the spellings of fields
    the camera does not have: a misspelt field, which would otherwise be passed over.

    read_as: how the reader matches a name (exactly, or XML tags without case and underscores);
    closeness ignores case either way (viewRotation is a misspelt viewrotation).
    """
    known_keys = {read_as(k) for k in known}
    for name in names:
        if read_as(name) not in known_keys:
            close = _closest(name, lacking, MISSPELT_MATCH, lambda n: read_as(n).lower())
            if close:
                raise CalibrationError(source, f"{where}{name}", f"not a field we know; did you mean {close}?")


# ----------------------------------------------------------------------------- public API

def load_calibration(path, units: str | None = None, fmt: str | None = None,
                     size: tuple[int, int] | None = None, warn: Warn = print_warning,
                     image_sizes: dict[str, tuple[int, int]] | None = None, images: str = "images") -> Studio:
    """Read a studio from ``path`` in any of ``FORMATS`` (detected when ``fmt`` is None).

    units: "m", "cm" or "mm" for files that do not say (None: metres, checked for plausibility);
    a file that says its units (our JSON, Qualisys) is read in them, and a ``units`` that
    disagrees is named in a warning line.
    size: (width, height) pixels for cameras whose file gives no image size; without it their
    size is guessed (``Camera.size_guessed``) and one line passed to ``warn`` names them.
    image_sizes: camera -> (width, height) of its images, named ``images`` in messages: put in
    for guessed sizes, checked against the file's (``with_image_sizes``).
    warn: receives each warning line (guessed sizes, skipped files, skewed projection matrices,
    doubtful units).
    """
    path = Path(path)
    source = str(path)
    if units is not None and units not in UNIT_SCALE:
        raise CalibrationError(source, "units", f"expected one of {sorted(UNIT_SCALE)}, got {units!r}")
    if not path.exists():
        raise CalibrationError(source, "", "does not exist")
    if fmt is None:
        fmt, path = _locate(path)
        source = str(path)
    lines: list[str] = []  # warnings wait for success: a failed read says one thing, its error
    if fmt == "json":
        if path.is_dir():
            raise CalibrationError(source, "", "is a folder, expected a calibration JSON file")
        doc = _read_json(path)
        studio = studio_from_json(doc, source, units)
        declared = doc.get("units")
    else:
        studio = _read_format(path, fmt, units, size, lines.append)
        declared = "mm" if fmt == "qualisys" else None
    _check_image_sizes(studio, source)
    if image_sizes:
        studio = with_image_sizes(studio, image_sizes, images)
    guessed = [c.name for c in studio if c.size_guessed]
    if guessed and fmt != "json":  # our JSON marks its guesses, and says so when shown
        lines.append(f"{path}: no image size for {', '.join(guessed)}; guessed as twice the principal point "
                     "(pass --size WxH or --size-from CAMERA=PATH; import-video takes it from the videos)")
    lines += _units_lines(studio, source, units, declared)
    for line in lines:
        warn(line)
    return studio


def _units_lines(studio: Studio, source: str, units: str | None, declared: str | None) -> list[str]:
    """Warning lines on the units a studio was read in (the file's ``declared`` ones, else ``units``,
    else metres); refuses, as ``check_units``, a studio that cannot be in metres."""
    if declared is not None:
        ignored = [] if units in (None, declared) else [
            f"{source}: units: the file says {declared}; --units {units} is for files that do not say, and is not used"]
        return ignored + units_doubt(studio, declared, source, "declared")
    if units is None:
        check_units(studio, source)
        return units_doubt(studio, "m", source, "assumed")
    return units_doubt(studio, units, source)


def _check_image_sizes(studio: Studio, source: str) -> None:
    """Refuse a camera whose image would be larger than any image may be (MAX_IMAGE_PIXELS)."""
    for cam in studio:
        if cam.width * cam.height > MAX_IMAGE_PIXELS:
            raise CalibrationError(source, f"{cam.name}.size", f"{cam.width}x{cam.height} pixels, more than the "
                                   f"{MAX_IMAGE_PIXELS / 1e6:g} Mpx an image may have")


def _read_format(path: Path, fmt: str, units: str | None, size, warn: Warn) -> Studio:
    """A studio from a file or folder in ``fmt`` (not json)."""
    scale = UNIT_SCALE[units or "m"]
    if fmt == "easymocap":
        return _read_easymocap(path.parent if path.is_file() else path, scale, size)
    if fmt in ("pose2sim", "anipose"):
        return _read_toml(path, scale, size)
    if fmt in ("opencv-xml", "projection"):
        return _read_camera_files(path, scale, size, warn)
    if fmt == "qualisys":
        return _read_qualisys(_qualisys_file(path), size, warn)
    raise CalibrationError(str(path), "format", f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")


def with_image_sizes(studio: Studio, sizes: dict[str, tuple[int, int]], source: str) -> Studio:
    """``studio`` with each camera named in ``sizes`` at its images' (width, height) pixels.

    A guessed size (``Camera.size_guessed``) is replaced; a size from the calibration file that
    differs from the images' raises CalibrationError (saying so when it is twice the principal
    point: maybe a guess that a file unable to mark one passed on). ``source`` names the images
    (for messages).
    """
    unknown = [name for name in sizes if name not in studio.names]
    if unknown:
        raise CalibrationError(studio.source, "cameras", f"no camera {unknown[0]!r} for the images of {source} "
                               f"(cameras: {', '.join(studio.names)})")
    cams = []
    for cam in studio:
        if cam.name not in sizes:
            cams.append(cam)
            continue
        width, height = (int(v) for v in sizes[cam.name])
        if width <= 0 or height <= 0:
            raise CalibrationError(source, f"{cam.name}.size", f"must be positive, got {width}x{height}")
        if cam.size_guessed:
            cam = replace(cam, width=width, height=height, size_guessed=False)
        elif (cam.width, cam.height) != (width, height):
            hint = ("" if (cam.width, cam.height) != _twice_principal_point(cam.K) else
                    f"; {cam.width}x{cam.height} is twice the principal point, the size a converter guesses for a "
                    "camera without one: if it was guessed, put the images' size in the calibration")
            raise CalibrationError(studio.source, f"{cam.name}.size", f"the calibration says {cam.width}x{cam.height} "
                                   f"but the images ({source}) are {width}x{height}{hint}")
        cams.append(cam)
    return Studio(tuple(cams), studio.source)


def save_calibration(studio: Studio, path, fmt: str | None = None) -> None:
    """Write ``studio`` to ``path`` as ``fmt`` (one of ``WRITE_FORMATS``; default: from the name, see
    ``output_format``).

    easymocap and opencv-xml write into a folder ``path`` (opencv-xml writes one file when
    ``path`` ends in .xml and the studio has one camera); they leave out guessed sizes, as the
    files they read came without. pose2sim and anipose refuse guessed sizes (``check_sizes_writable``).
    """
    path = Path(path)
    fmt = output_format(path, fmt)
    if fmt in ("json", "pose2sim", "anipose") and path.is_dir():
        raise CalibrationError(str(path), "", f"is a folder; {fmt} calibration is a single file")
    check_sizes_writable(studio, path, fmt)
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
                raise CalibrationError(str(path), "", f"one .xml file holds one camera, the studio has "
                                       f"{len(studio)}; give a folder to write one file per camera")
            _write(path, _xml_text(studio[0]))
        else:
            for cam in studio:
                _write(path / f"{cam.name}.xml", _xml_text(cam))


def check_sizes_writable(studio: Studio, path, fmt: str) -> None:
    """Refuse to write guessed image sizes to ``path`` in ``fmt`` when the format cannot mark them.

    pose2sim and anipose files always hold a size, which their readers (ours too) take for the
    images': a guess written there would pass for a measured size.
    """
    guessed = [c.name for c in studio if c.size_guessed]
    if fmt in ("pose2sim", "anipose") and guessed:
        raise CalibrationError(str(path), "size", f"no image size for {', '.join(guessed)} (guessed as twice the "
                               f"principal point), and a {fmt} file cannot mark a size as guessed: give the images' "
                               "size (--size WxH, --size-from CAMERA=VIDEO), or write .json, which keeps it marked")


def detect_format(path) -> str:
    """The format of an existing calibration file or folder (one of ``FORMATS``)."""
    return _locate(Path(path))[0]


def _locate(path: Path) -> tuple[str, Path]:
    """(format, what to read) of a calibration file or folder: a folder holding one single-file
    calibration (our JSON, a TOML, a .qca.txt) reads that file; one holding two calibrations
    of any kinds is refused (``folder_calibrations``)."""
    if path.is_dir():
        found = folder_calibrations(path)
        _refuse_several(path, found)
        if found and found[0][0] != "camera":
            fmt, inner, _ = found[0]
            return (fmt if fmt != "toml" else detect_format(inner)), inner
        entries = _camera_files(path)  # also the broken ones, reported when read
        if entries:
            fmt = "projection" if any(kind == "projection" for _, _, kind in entries) else "opencv-xml"
            return fmt, path
        raise CalibrationError(str(path), "<folder>", "no calibration found: expected intri.yml + extri.yml "
                               "(EasyMocap), calibration.json, a .toml (Pose2Sim, Anipose), one .qca.txt "
                               "(Qualisys), or camera files (.xml with K, R, t or P; .txt with a 3x4 P), one per "
                               "camera or one per sub-folder")
    name = path.name.lower()
    suffix = path.suffix.lower()
    if suffix == ".toml":
        doc = _read_toml_doc(path)
        sections = _toml_camera_sections(doc)
        if sections and all(isinstance(doc[s], dict) and "fisheye" in doc[s] for s in sections):
            return "pose2sim", path
        return "anipose", path
    if name.endswith(QUALISYS_SUFFIX):
        return "qualisys", path
    if suffix in (".xml", ".txt"):
        kind = _file_kind(path)
        if kind in ("qualisys", "projection"):
            return kind, path
        return ("projection" if suffix == ".txt" else "opencv-xml"), path
    if suffix in (".yml", ".yaml"):
        return "easymocap", path
    return "json", path


def folder_calibrations(folder) -> list[tuple[str, Path, str]]:
    """(kind, path, description) of each whole calibration in ``folder``, in the order read.

    kind: "easymocap" (intri.yml + extri.yml), "json" (``calibration.json``, or any .json saying
    ``JSON_FORMAT_NAME``), "toml" (``SINGLE_FILE_NAMES``, or any .toml with a camera's
    ``matrix``), "qualisys" (each .qca.txt), "camera" (the files holding a whole camera at the
    top, and those in sub-folders: two sets when both are there). Files holding no camera (a
    board, an intrinsics-only estimate) are no calibration. More than one means the folder does
    not say which it is: a user who converted a lab's files to calibration.json beside them and
    then edited one of the two would otherwise get the other without a word.
    """
    folder = Path(folder)
    found: list[tuple[str, Path, str]] = []
    if all((folder / name).is_file() for name in EASYMOCAP_FILES):
        found.append(("easymocap", folder, " + ".join(EASYMOCAP_FILES)))
    for p in sorted((p for p in folder.iterdir() if p.is_file()), key=lambda p: natural_key(p.name)):
        low = p.name.lower()
        if low.endswith(QUALISYS_SUFFIX):
            found.append(("qualisys", p, p.name))
        elif p.suffix.lower() == ".json" and _is_calibration_json(p):
            found.append(("json", p, p.name))
        elif p.suffix.lower() == ".toml" and _is_calibration_toml(p):
            found.append(("toml", p, p.name))
    for files in _full_camera_files(folder):
        if files:
            found.append(("camera", folder, camera_files_named(folder, files)))
    return found


def camera_files_named(folder: Path, files: list[Path]) -> str:
    """``files`` (camera files in ``folder`` or its sub-folders) in a few words: "4 camera files
    (cam1/config.xml, ..., cam4/config.xml)"."""
    names = [f.relative_to(folder).as_posix() for f in files]
    shown = ", ".join(names) if len(names) <= 3 else f"{names[0]}, ..., {names[-1]}"
    return f"{len(names)} camera file{'s' * (len(names) > 1)} ({shown})"


def _refuse_several(folder: Path, found: list[tuple[str, Path, str]]) -> None:
    if len(found) > 1:
        easymocap = " (intri.yml for EasyMocap)" if any(kind == "easymocap" for kind, _, _ in found) else ""
        refuse_calibrations(folder, [what for _, _, what in found],
                            f"give the file to use{easymocap}, or move the others out of the folder")


def refuse_calibrations(folder: Path, calibrations: list[str], advice: str) -> None:
    """Raise CalibrationError: ``folder`` holds these (two or more) calibrations, and which was
    meant (or last edited) is not ours to guess; ``advice`` says what to do."""
    raise CalibrationError(str(folder), "<folder>", f"holds {len(calibrations)} calibrations: "
                           f"{_and(calibrations)}; {advice}")


def _and(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _small_text(path: Path) -> str | None:
    """A file's text, or None when it cannot be a calibration (unreadable, not UTF-8, too large)."""
    try:
        if path.stat().st_size > MAX_SINGLE_FILE_BYTES:
            return None
        return path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None


def _is_calibration_json(path: Path) -> bool:
    """Ours by name (even when broken: it is read, and refused, if it is the only one), or by its ``format``."""
    if path.name.lower() in SINGLE_FILE_NAMES:
        return True
    text = _small_text(path)
    try:
        doc = json.loads(text) if text is not None else None
    except ValueError:
        return False
    return isinstance(doc, dict) and doc.get("format") == JSON_FORMAT_NAME


def _is_calibration_toml(path: Path) -> bool:
    """Pose2Sim's and Anipose's names, or a section with a camera ``matrix`` (not a Config.toml)."""
    if path.name.lower() in SINGLE_FILE_NAMES:
        return True
    text = _small_text(path)
    try:
        doc = tomllib.loads(text) if text is not None else {}
    except tomllib.TOMLDecodeError:
        return False
    return any(isinstance(doc[s], dict) and "matrix" in doc[s] for s in _toml_camera_sections(doc))


def output_format(path, fmt: str | None = None) -> str:
    """The format to write ``path`` in: ``fmt`` if given, else from the name.

    .json -> json, .toml -> pose2sim (Pose2Sim's Calib.toml is in metres like us; pass
    ``anipose`` for aniposelib), .xml -> opencv-xml (one camera). A folder needs ``fmt``.
    """
    path = Path(path)
    if fmt is not None:
        if fmt not in WRITE_FORMATS:
            raise CalibrationError(str(path), "format", f"cannot write format {fmt!r}; expected one of "
                                   + ", ".join(WRITE_FORMATS))
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


def units_doubt(studio: Studio, units: str, source: str, origin: str = "given") -> list[str]:
    """A warning line where the farthest two cameras read in ``units`` stand nearer or farther
    apart than a capture room's (``STUDIO_CAMERA_SPAN``); else none. ``origin`` says where the
    units came from (``UNIT_ORIGINS``: given by the user, declared by the file, assumed)."""
    centres = np.array([c.center for c in studio])
    span = float(np.linalg.norm(centres[:, None] - centres[None], axis=-1).max())
    low, high = STUDIO_CAMERA_SPAN
    if len(studio) < 2 or low <= span <= high:
        return []
    read, advice = UNIT_ORIGINS[origin]
    apart = f"{span * 1000:.0f} mm" if span < 1.0 else f"{span:.1f} m"
    return [f"{source}: {read.format(units=units)} the farthest two cameras stand {apart} apart, where a capture "
            f"room's stand {low:g}-{high:g} m: {advice}"]


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
    checks = _checks(path)
    return checks.decode(checks.read())


def _read_json(path: Path):
    checks = _checks(path)
    return checks.parse_json(checks.read())


def _write(path: Path, text: str, newline: str | None = None) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w", encoding="utf-8", newline=newline) as f:
            f.write(text)
    except OSError as exc:
        raise CalibrationError(str(path), "", f"cannot write ({exc})") from None


def _numbers(value, source: str, field: str) -> np.ndarray:
    """Numbers (nested lists, an OpenCV matrix node, or text) -> float64 array."""
    if isinstance(value, _CvMat):
        return _cvmat(value, source, field)
    if isinstance(value, str):
        value = value.split()
    if isinstance(value, np.ndarray):
        value = value.tolist()

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


def _build(name: str, K, dist, R, t, width, height, scale: float, fields: dict, size=None) -> Camera:
    """Parse and validate one camera; ``fields`` maps K/dist/R/t/size -> (source, field in the file).

    R may be a Rodrigues vector or a 3x3 matrix; t is scaled to metres. Without width and
    height the size is ``size``, else guessed from the principal point (``size_guessed``).
    """
    K = _numbers(K, *fields["K"])
    dist = _numbers(dist, *fields["dist"]) if dist is not None else None
    R = _rotation(R, *fields["R"])
    t = _numbers(t, *fields["t"])
    guessed = width is None or height is None
    if not guessed:
        width, height = _pixels(width, *fields["size"]), _pixels(height, *fields["size"])
    elif size is not None:
        (width, height), guessed = size, False
    else:
        width, height = _guessed_size(K, *fields["size"])
    try:
        cam = make_camera(name, K, dist, R, t * scale, width, height, fields["K"][0])
    except CalibrationError as exc:  # name the field as the file spells it
        key = exc.field_name.rsplit(".", 1)[-1]
        source, field = fields.get(key, (exc.source, exc.field_name))
        raise CalibrationError(source, field, exc.problem) from None
    return replace(cam, size_guessed=True) if guessed else cam


def _twice_principal_point(K: np.ndarray) -> tuple[int, int]:
    """(width, height) guessed from a (3, 3) K: twice the principal point, rounded (as Pose2Sim's converters)."""
    width, height = (int(np.floor(2.0 * c + 0.5)) for c in K.reshape(3, 3)[:2, 2])
    return width, height


def _guessed_size(K: np.ndarray, source: str, field: str) -> tuple:
    """(width, height) as twice the principal point, rounded; (None, None) for a K make_camera refuses."""
    if K.size != 9:
        return None, None
    width, height = _twice_principal_point(K)
    if width <= 0 or height <= 0:
        raise CalibrationError(source, field, f"missing, and the principal point ({K.reshape(3, 3)[0, 2]:g}, "
                               f"{K.reshape(3, 3)[1, 2]:g}) gives no size to guess; pass --size WxH")
    return width, height


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
        raise CalibrationError(str(path), "", f"not valid OpenCV YAML ({problem})") from None
    if not isinstance(doc, dict):
        raise CalibrationError(str(path), "<root>", "expected a mapping of named nodes")
    return doc


def _read_easymocap(folder: Path, scale: float, size) -> Studio:
    intri_path, extri_path = folder / EASYMOCAP_FILES[0], folder / EASYMOCAP_FILES[1]
    for p in (intri_path, extri_path):
        if not p.is_file():
            raise CalibrationError(str(p), "", "does not exist (EasyMocap needs intri.yml and extri.yml)")
    intri, extri = _read_opencv_yaml(intri_path), _read_opencv_yaml(extri_path)
    si, se = str(intri_path), str(extri_path)
    names = intri.get("names")
    if not isinstance(names, list) or not names:
        raise CalibrationError(si, "names", "missing or empty list of camera names")
    for i, raw in enumerate(names):
        if isinstance(raw, bool) or not isinstance(raw, (str, int)) or raw == "":
            raise CalibrationError(si, f"names[{i}]", f"expected a camera name, got {raw!r}")
    names = [str(raw) for raw in names]
    for doc, file_path in ((intri, intri_path), (extri, extri_path)):
        _refuse_easymocap_misspelt(doc, names, file_path)
    cams = []
    for name in names:
        K, k_key = _yaml_node(intri, si, f"K_{name}")
        dist, d_key = _yaml_node(intri, si, f"dist_{name}", f"D_{name}")
        R, r_key = _yaml_node(extri, se, f"R_{name}", f"Rot_{name}")  # EasyMocap itself uses the Rodrigues R_
        t, t_key = _yaml_node(extri, se, f"T_{name}")
        height, width = intri.get(f"H_{name}"), intri.get(f"W_{name}")
        fields = {"K": (si, k_key), "dist": (si, d_key), "R": (se, r_key), "t": (se, t_key),
                  "size": (si, f"H_{name}/W_{name}")}
        cams.append(_build(name, K, dist, R, t, width, height, scale, fields, size))
    return Studio(tuple(cams), str(folder))


def _refuse_easymocap_misspelt(doc: dict, names: list[str], path: Path) -> None:
    """Refuse a key close to one a camera lacks (dsit_01, dist_1 for camera 01): other tools
    (EasyVolcap) add keys of their own, so keys we do not read are otherwise passed over."""
    groups = EASYMOCAP_FIELDS[path.name]
    known = ["names"] + [f"{prefix}_{name}" for name in names for group in groups for prefix in group]
    lacking = [f"{prefix}_{name}" for name in names for group in groups
               if all(doc.get(f"{p}_{name}") is None for p in group) for prefix in group]
    _refuse_misspelt([str(key) for key in doc], known, lacking, str(path))


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
        if not c.size_guessed:
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
        raise CalibrationError(str(path), "", f"not valid TOML ({exc})") from None


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
        # Pose2Sim and aniposelib write these keys, FreeMocap more: only a misspelling is refused
        _refuse_misspelt(list(c), TOML_CAMERA_FIELDS, [k for k in TOML_CAMERA_FIELDS if k not in c], source, f"{sec}.")
        for key in ("matrix", "distortions", "rotation", "translation"):
            if key not in c:
                raise CalibrationError(source, f"{sec}.{key}", "missing")
        if _checks(source).flag(c.get("fisheye", False), f"{sec}.fisheye"):
            raise CalibrationError(source, f"{sec}.fisheye", "fisheye cameras are not supported "
                                   "(pinhole with k1 k2 p1 p2 k3 only)")
        dims = c.get("size", [None, None])
        if not isinstance(dims, list) or len(dims) != 2:
            raise CalibrationError(source, f"{sec}.size", f"expected [width, height], got {dims!r}")
        fields = {"K": (source, f"{sec}.matrix"), "dist": (source, f"{sec}.distortions"),
                  "R": (source, f"{sec}.rotation"), "t": (source, f"{sec}.translation"),
                  "size": (source, f"{sec}.size")}
        name = _checks(source).text(c.get("name", sec), f"{sec}.name")
        cams.append(_build(name, c["matrix"], c["distortions"], c["rotation"], c["translation"],
                           *dims, scale, fields, size))
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


# ----------------------------------------------------------------------------- camera files: OpenCV XML, P

def _camera_candidates(folder: Path) -> list[Path]:
    """The .xml and .txt files (not .qca.txt) directly in ``folder``, in natural order."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in (".xml", ".txt")
                   and not p.name.lower().endswith(QUALISYS_SUFFIX)), key=lambda p: natural_key(p.name))


def _camera_files(folder: Path, warn: Warn | None = None) -> list[tuple[str, Path, str]]:
    """(camera name, file, kind) for a folder of per-camera files, in natural order of names.

    Files at the top are the cameras when one of them holds a whole camera; otherwise each
    sub-folder's one camera file. Files passed over are named in one line to ``warn``.
    """
    top = [(p.stem, p, _file_kind(p)) for p in _camera_candidates(folder)]
    entries, skipped = [], []
    if not any(kind in FULL_KINDS for _, _, kind in top):
        entries, skipped = _sub_folder_cameras(folder)
    if entries:
        skipped = [p for _, p, _ in top] + skipped
    else:  # cameras at the top; a broken one among them is reported when read
        entries = [e for e in top if e[2] in TOP_CAMERA_KINDS]
        skipped = [p for _, p, kind in top if kind not in TOP_CAMERA_KINDS]
    if warn is not None and entries and skipped:
        warn(f"{folder}: skipped (no camera fields): " + ", ".join(p.relative_to(folder).as_posix() for p in skipped))
    return sorted(entries, key=lambda e: natural_key(e[0]))


def _full_camera_files(folder: Path) -> tuple[list[Path], list[Path]]:
    """The files holding a whole camera at the top of ``folder``, and in its sub-folders (all of
    them, even two in one sub-folder: that is refused when read)."""
    return (camera_files_in(folder),
            [p for sub in sorted(d for d in folder.iterdir() if d.is_dir()) for p in camera_files_in(sub)])


def calibration_files(path) -> list[Path]:
    """The files a read of the calibration at ``path`` uses, whose changes change what is read:
    a file itself; EasyMocap's two files; a folder's single-file calibrations and its camera
    files (at the top and one sub-folder down), never the folder, which may hold what a run
    writes beside them (a take read as its own calibration)."""
    path = Path(path)
    if not path.is_dir():
        return [path]
    if all((path / name).is_file() for name in EASYMOCAP_FILES):
        return [path / name for name in EASYMOCAP_FILES]
    single = [inner for kind, inner, _ in folder_calibrations(path) if kind not in ("camera", "easymocap")]
    top, subs = _full_camera_files(path)
    return single + top + subs


def camera_files_in(folder: Path) -> list[Path]:
    """The files directly in ``folder`` that hold a whole camera (K, R, t or P), in natural order."""
    return [p for p in _camera_candidates(folder) if _file_kind(p) in FULL_KINDS]


def _sub_folder_cameras(folder: Path) -> tuple[list[tuple[str, Path, str]], list[Path]]:
    """(camera name = sub-folder, file, kind) for each sub-folder with a camera file, and the files skipped."""
    entries, skipped = [], []
    for sub in sorted(d for d in folder.iterdir() if d.is_dir()):
        files = [(p, _file_kind(p)) for p in _camera_candidates(sub)]
        full = [p for p, kind in files if kind in FULL_KINDS]
        if len(full) > 1:
            raise CalibrationError(str(sub), "<folder>", "more than one file holds a camera (K, R, t or P): "
                                   + ", ".join(p.name for p in full) + "; keep one")
        chosen = full or [p for p, kind in files if kind == "broken"][:1]  # reported when read
        entries += [(sub.name, p, kind) for p, kind in files if p in chosen]
        skipped += [p for p, _ in files if p not in chosen]
    return entries, skipped


def _file_kind(path: Path) -> str:
    """What a calibration file holds, read leniently (errors come when it is read as a camera).

    "camera": OpenCV XML with K, R and t; "projection": OpenCV XML with P, or a .txt of 12 numbers
    (a .txt of 9, a 3x3 K beside it, holds no camera; of another count it is "broken");
    "qualisys": a Qualisys <calibration>; "broken": OpenCV XML with some of K, R, t, or not
    valid XML, empty or naming camera fields; "foreign": XML of another kind that names camera
    fields; "none": no camera fields at all (a board, notes, another tool's project file).
    """
    if _is_projection_text(path):
        try:
            values = _numbers(_projection_text(path), str(path), "P")
        except CalibrationError:
            return "none"
        if values.size in (0, 9):  # empty, or a 3x3 intrinsic matrix: no camera here
            return "none"
        return "projection" if values.size == 12 else "broken"
    try:
        root = _parse_xml(path)
    except CalibrationError:  # a damaged camera file is refused when read; damaged notes are passed over
        try:
            text = _read_text(path)
        except CalibrationError:  # not text either: reported when read
            return "broken"
        # a camera file cut short may name one field or none whole: its root says what it was
        tags = CAMERA_TAG_TEXT.findall(text)
        damaged = not text.strip() or "opencv_storage" in tags or _names_camera_fields(tags, at_least=1)
        return "broken" if damaged else "none"
    if root.tag != "opencv_storage":
        if root.tag == "calibration":
            return "qualisys"
        # another tool's XML (a project file, a board description): a camera only where it names camera fields
        return "foreign" if _names_camera_fields(elem.tag for elem in root.iter()) else "none"
    nodes = _xml_nodes(path, root)
    present = [field for field in CAMERA_FIELDS if _xml_find(nodes, field)[0] is not None]
    if len(present) == len(CAMERA_FIELDS):
        return "camera"
    if _xml_find(nodes, "P")[0] is not None:
        return "projection"
    return "broken" if present else "none"


def _read_camera_files(path: Path, scale: float, size, warn: Warn) -> Studio:
    if path.is_dir():  # --from says the kind, not which of two sets of camera files
        _refuse_several(path, [c for c in folder_calibrations(path) if c[0] == "camera"])
        entries = _camera_files(path, warn)
        if not entries:
            raise CalibrationError(str(path), "<folder>", "no camera files (.xml with K, R, t or P; .txt with a 3x4 P)")
    else:
        entries = [(path.stem, path, "")]
    read = [_read_camera_entry(name, p, kind, scale, size) for name, p, kind in entries]
    skewed = [cam.name for cam, from_p in read if from_p and abs(cam.K[0, 1]) > SKEW_WARNING * cam.K[0, 0]]
    if skewed:
        warn(f"{path}: the projection matrices of {', '.join(skewed)} decompose with a skew above "
             f"{SKEW_WARNING:.0%} of fx (kept as it is; a poor or mis-assembled P?)")
    return Studio(tuple(cam for cam, _ in read), str(path))


def _read_camera_entry(name: str, path: Path, kind: str, scale: float, size) -> tuple[Camera, bool]:
    """``_read_camera_file``; where a camera's folder holds no whole camera and the file read in
    its place is refused (an intrinsics-only file beside a missing config.xml), the error says
    that no other file there would do."""
    try:
        return _read_camera_file(name, path, scale, size)
    except CalibrationError as exc:
        if kind != "broken" or path.parent.name != name:
            raise
        raise CalibrationError(exc.source, exc.field_name, f"{exc.problem}; no other file in {name}/ holds a "
                               "whole camera (K, R, t or P)") from None


def _read_camera_file(name: str, path: Path, scale: float, size) -> tuple[Camera, bool]:
    """One camera from an OpenCV XML or projection .txt file -> (camera, whether it came from a P)."""
    source = str(path)
    if _is_projection_text(path):
        P = _projection_matrix(_projection_text(path), source, "P")
        return _projection_camera(name, P, None, None, scale, (source, "P"), (source, "<size>"), size), True
    nodes = _xml_nodes(path, _parse_xml(path))
    _refuse_misspelt([elem.tag for elem in nodes.values()], [tag for tags in XML_TAGS.values() for tag in tags],
                     _xml_lacking(nodes), source, read_as=_tag_key)
    width, height, size_field = _xml_size(nodes, source)
    p_tag, P = _xml_find(nodes, "P")
    if P is not None and any(_xml_find(nodes, field)[0] is None for field in CAMERA_FIELDS):
        P = _projection_matrix(P, source, p_tag)
        return _projection_camera(name, P, width, height, scale, (source, p_tag), (source, size_field), size), True
    k_tag, K = _xml_required(nodes, "K", source)
    d_tag, dist = _xml_find(nodes, "dist")
    r_tag, R = _xml_required(nodes, "R", source)
    t_tag, t = _xml_required(nodes, "t", source)
    fields = {"K": (source, k_tag), "dist": (source, d_tag or XML_TAGS["dist"][0]), "R": (source, r_tag),
              "t": (source, t_tag), "size": (source, size_field)}
    return _build(name, K, dist, R, t, width, height, scale, fields, size), False


def _parse_xml(path: Path) -> ET.Element:
    data = _checks(path).read()
    try:
        return ET.fromstring(data)
    except ET.ParseError as exc:
        raise CalibrationError(str(path), "", f"not valid XML ({exc})") from None


def _xml_nodes(path: Path, root: ET.Element) -> dict:
    """An OpenCV FileStorage XML root's nodes by tag, lower-cased and without underscores."""
    if root.tag != "opencv_storage":
        raise CalibrationError(str(path), "<root>", f"expected <opencv_storage>, got <{root.tag}>")
    nodes = {}
    for child in root:
        nodes.setdefault(_tag_key(child.tag), child)
    return nodes


def _tag_key(tag: str) -> str:
    return tag.lower().replace("_", "")


def _xml_find(nodes: dict, field: str):
    """(tag as the file spells it, value) of the first of ``XML_TAGS[field]`` present, else (None, None)."""
    for tag in XML_TAGS[field]:
        elem = nodes.get(_tag_key(tag))
        if elem is not None:
            return elem.tag, _xml_value(elem)
    return None, None


def _xml_lacking(nodes: dict) -> list[str]:
    """The spellings (``XML_TAGS``) of the fields a camera file lacks: the image size unless it has
    one (width and height, or size), P unless it has K, R and t, and K, R, t unless it has either."""
    have = {field for field in XML_TAGS if _xml_find(nodes, field)[0] is not None}
    if {"width", "height"} <= have or "size" in have:
        have |= {"width", "height", "size"}
    if set(CAMERA_FIELDS) <= have or "P" in have:
        have |= {*CAMERA_FIELDS, "P"}
    return [tag for field, tags in XML_TAGS.items() if field not in have for tag in tags]


def _xml_required(nodes: dict, field: str, source: str):
    tag, value = _xml_find(nodes, field)
    if tag is None:
        raise CalibrationError(source, XML_TAGS[field][0],
                               "missing (also accepted: " + ", ".join(XML_TAGS[field][1:]) + ")")
    return tag, value


def _xml_size(nodes: dict, source: str):
    """(width, height, field) from image_width/image_height or ImageSize; None, None when absent."""
    w_tag, width = _xml_find(nodes, "width")
    h_tag, height = _xml_find(nodes, "height")
    if width is not None and height is not None:
        return width, height, f"{w_tag}/{h_tag}"
    s_tag, dims = _xml_find(nodes, "size")
    if dims is None:
        return None, None, "image_width/image_height"
    arr = _numbers(dims, source, s_tag).reshape(-1)
    if arr.size != 2:
        raise CalibrationError(source, s_tag, f"expected 2 values (width height), got {arr.size}")
    return arr[0], arr[1], s_tag


def _xml_value(elem: ET.Element):
    """An OpenCV FileStorage XML node -> _CvMat, or its text (numbers separated by spaces)."""
    if elem.get("type_id") == "opencv-matrix":
        parts = {child.tag.lower(): (child.text or "") for child in elem}
        return _CvMat(parts.get("rows", "").strip(), parts.get("cols", "").strip(), parts.get("data", ""))
    return (elem.text or "").strip()


PROJECTION_SEPARATORS = str.maketrans(",;[]", "    ")


def _is_projection_text(path: Path) -> bool:
    """A .txt that is not XML (a Qualisys file is XML whatever its name)."""
    if path.suffix.lower() != ".txt":
        return False
    try:
        return not _read_text(path).lstrip().startswith("<")
    except CalibrationError:
        return True  # reported when read


def _projection_text(path: Path) -> str:
    """A projection .txt's numbers: without '#' comment lines and a PMVS ``CONTOUR`` header;
    commas and semicolons (CSV rows, a matrix copied from MATLAB or numpy) separate numbers as
    spaces do, and brackets around them are dropped."""
    lines = [line for line in _read_text(path).splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if lines and lines[0].strip() == CONTOUR_HEADER:
        lines = lines[1:]
    return " ".join(lines).translate(PROJECTION_SEPARATORS)


def _projection_matrix(value, source: str, field: str) -> np.ndarray:
    arr = _numbers(value, source, field)
    if arr.size != 12 or (arr.ndim == 2 and arr.shape != (3, 4)):
        raise CalibrationError(source, field, "expected a 3x4 projection matrix (12 numbers), got "
                               + (f"shape {arr.shape}" if arr.size == 12 else f"{arr.size} numbers"))
    return arr.reshape(3, 4)


def _projection_camera(name: str, P: np.ndarray, width, height, scale: float, where: tuple, size_where: tuple,
                       size) -> Camera:
    K, R, t = decompose_projection(P, *where)
    fields = {"K": where, "dist": where, "R": where, "t": where, "size": size_where}
    return _build(name, K, None, R, t, width, height, scale, fields, size)


def decompose_projection(P, source: str = "<memory>", field: str = "P"):
    """(3, 4) projection matrix -> K (3, 3), R (3, 3), t (3,) with P = s K [R | t] for some s != 0.

    RQ decomposition of P[:, :3] with signs fixed so that K's diagonal is positive and det R = +1
    (P and -P are the same camera), and K scaled to K[2, 2] = 1. A singular P[:, :3] raises
    CalibrationError naming ``source`` and ``field``.
    """
    P = np.asarray(P, dtype=np.float64).reshape(3, 4)
    det = np.linalg.det(P[:, :3])
    if not abs(det) > SINGULAR_P * np.linalg.norm(P[:, :3]) ** 3:
        raise CalibrationError(source, field, "singular: its left 3x3 block has rank < 3 (not a pinhole camera)")
    if det < 0:
        P = -P
    flip = np.eye(3)[::-1]  # reverses rows: turns numpy's QR into an RQ decomposition
    Q, U = np.linalg.qr((flip @ P[:, :3]).T)
    K, R = flip @ U.T @ flip, flip @ Q.T
    signs = np.sign(np.diag(K))
    K, R = K * signs, signs[:, None] * R  # K D and D R with D = diag(signs), D D = I
    t = np.linalg.solve(K, P[:, 3])
    return np.triu(K / K[2, 2]), R, t


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
            + ("" if cam.size_guessed else
               f"<image_width>{cam.width}</image_width>\n<image_height>{cam.height}</image_height>\n")
            + "</opencv_storage>\n")


# ----------------------------------------------------------------------------- Qualisys .qca.txt

def _qualisys_file(path: Path) -> Path:
    if not path.is_dir():
        return path
    files = sorted(path.glob("*" + QUALISYS_SUFFIX))
    if len(files) != 1:
        raise CalibrationError(str(path), "<folder>", f"expected one {QUALISYS_SUFFIX} file, found {len(files)}")
    return files[0]


def _read_qualisys(path: Path, size, warn: Warn) -> Studio:
    source = str(path)
    root = _parse_xml(path)
    if root.tag != "calibration":
        raise CalibrationError(source, "<root>", f"expected <calibration> (Qualisys), got <{root.tag}>")
    elems = root.findall("cameras/camera")
    if not elems:
        raise CalibrationError(source, "cameras", "no <camera> elements in <cameras>")
    for i, elem in enumerate(elems):
        if not elem.get("serial"):
            raise CalibrationError(source, f"cameras.camera[{i}].serial", "missing")
    marker_only = [e.get("serial") for e in elems if not _qualisys_video(e)]
    if len(marker_only) == len(elems):
        raise CalibrationError(source, "cameras", "only marker cameras (model without 'video'): no images")
    if marker_only:
        warn(f"{source}: skipped marker cameras (no video): {', '.join(marker_only)}")
    cams = [_qualisys_camera(e, source, size) for e in elems if _qualisys_video(e)]
    return Studio(tuple(sorted(cams, key=lambda c: natural_key(c.name))), source)


def _qualisys_video(elem: ET.Element) -> bool:
    """Pose2Sim's test: a camera films when its model says "video" or "none" (here also: no model)."""
    model = elem.get("model")
    return model is None or any(word in model.lower() for word in ("video", "none"))


def _qualisys_camera(elem: ET.Element, source: str, size) -> Camera:
    name = elem.get("serial")
    _refuse_qualisys_misspelt(elem, name, source)
    fov = elem.find("fov_video")
    sides = ("left", "top", "right", "bottom")
    box = None if fov is None else [_attr_number(fov, f"{name}.fov_video", source, side) for side in sides]
    width, height = (box[2] - box[0] + 1, box[3] - box[1] + 1) if box else (None, None)
    K, dist = _qualisys_intrinsics(_qualisys_child(elem, "intrinsic", name, source), name, source,
                                   box[:2] if box else (0.0, 0.0))
    R, t = _qualisys_pose(_qualisys_child(elem, "transform", name, source), name, source)
    for _ in range(_qualisys_turns(elem, name, source, fov)):
        K, dist, R, t, width, height = _turn_clockwise(K, dist, R, t, width, height)
    where_k, where_rt = (source, f"{name}.intrinsic"), (source, f"{name}.transform")
    fields = {"K": where_k, "dist": where_k, "R": where_rt, "t": where_rt, "size": (source, f"{name}.fov_video")}
    return _build(name, K, dist, R, t, width, height, UNIT_SCALE["mm"], fields, size)


def _refuse_qualisys_misspelt(elem: ET.Element, name: str, source: str) -> None:
    """Refuse an attribute or child of a <camera> (or attribute of its <intrinsic>) close to one
    it lacks: the optional ones (viewrotation, fov_video, skew, radialDistortion3) would
    otherwise silently take their defaults."""
    def check(names, known, where):
        _refuse_misspelt(names, known, [k for k in known if k not in names], source, where)

    check(list(elem.attrib), QUALISYS_CAMERA_ATTRIBUTES, f"{name}.")
    check([child.tag for child in elem], QUALISYS_CAMERA_CHILDREN, f"{name}.")
    intrinsic = elem.find("intrinsic")
    if intrinsic is not None:
        check(list(intrinsic.attrib), QUALISYS_INTRINSIC_ATTRIBUTES, f"{name}.intrinsic.")


def _qualisys_intrinsics(intr: ET.Element, name: str, source: str, corner) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3) in pixels of the video's field of view (top-left ``corner`` on the sensor), dist (5,)."""
    def num(*attrs, default=None):
        return _attr_number(intr, f"{name}.intrinsic", source, *attrs, default=default) / QUALISYS_SUBPIXELS

    fu = num("focalLengthU")
    if intr.get("focalLengthV") is None and intr.get("pixelAspectRatio") is not None:
        fv = fu / _attr_number(intr, f"{name}.intrinsic", source, "pixelAspectRatio")
    else:
        fv = num("focalLengthV")
    K = np.array([[fu, num("skew", default=0.0), num("centerPointU") - corner[0]],
                  [0.0, fv, num("centerPointV") - corner[1]], [0.0, 0.0, 1.0]])
    dist = np.array([num("radialDistortion1"), num("radialDistortion2"),
                     num("tangentalDistortion1", "tangentialDistortion1"),  # QTM spells it "tangental"
                     num("tangentalDistortion2", "tangentialDistortion2"), num("radialDistortion3", default=0.0)])
    return K, dist


def _qualisys_pose(tr: ET.Element, name: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera R (3, 3), t (3,) in mm, OpenCV axes."""
    def num(attr):
        return _attr_number(tr, f"{name}.transform", source, attr)

    # r11 r12 r13 is the first column of the camera's orientation in the world (Pose2Sim reads it so)
    R = QUALISYS_TO_OPENCV @ np.array([[num(f"r{i}{j}") for j in (1, 2, 3)] for i in (1, 2, 3)])
    return R, -R @ np.array([num(axis) for axis in "xyz"])


def _qualisys_child(elem: ET.Element, tag: str, name: str, source: str) -> ET.Element:
    child = elem.find(tag)
    if child is None:
        raise CalibrationError(source, f"{name}.{tag}", "missing")
    return child


def _attr_number(elem: ET.Element, where: str, source: str, *attrs: str, default=None) -> float:
    """The first of ``attrs`` present on ``elem`` as a number; ``default`` (or an error) when none is."""
    for attr in attrs:
        if elem.get(attr) is not None:
            arr = _numbers(elem.get(attr), source, f"{where}.{attr}").reshape(-1)
            if arr.size != 1:
                raise CalibrationError(source, f"{where}.{attr}", f"expected one number, got {elem.get(attr)!r}")
            return float(arr[0])
    if default is None:
        raise CalibrationError(source, f"{where}.{attrs[0]}", "missing")
    return default


def _qualisys_turns(elem: ET.Element, name: str, source: str, fov) -> int:
    """Quarter turns clockwise of the camera's image (its ``viewrotation``)."""
    text = elem.get("viewrotation", "0")
    try:
        degrees = int(float(text))
    except ValueError:
        degrees = None
    if degrees not in QUALISYS_VIEW_ROTATIONS:
        raise CalibrationError(source, f"{name}.viewrotation",
                               f"expected one of {QUALISYS_VIEW_ROTATIONS}, got {text!r}")
    if degrees and fov is None:
        raise CalibrationError(source, f"{name}.fov_video", "missing (the image size is needed to turn the image "
                               f"by viewrotation {degrees})")
    return degrees // 90


def _turn_clockwise(K, dist, R, t, width, height):
    """The same camera with its image turned 90 degrees clockwise: pixel (u, v) -> (height - 1 - v, u).

    The camera frame turns with it (x' = -y, y' = x), so K' = T K Z^T, R' = Z R, t' = Z t, the
    tangential distortion (p1, p2) -> (p2, -p1), and width and height swap.
    """
    T = np.array([[0.0, -1.0, height - 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Z = TURN_CLOCKWISE
    dist = np.array([dist[0], dist[1], dist[3], -dist[2], dist[4]])
    return T @ K @ Z.T, dist, Z @ R, Z @ t, height, width
