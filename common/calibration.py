"""Calibration files: read and write studios in the formats users already have.

Our own JSON format (``calibration.json``)::

    {"format": "silhouette-mocap-calibration", "version": 1, "units": "m",
     "cameras": [{"name": str, "K": 3x3, "dist": [k1, k2, p1, p2, k3], "R": 3x3,
                  "t": [3], "width": int, "height": int}, ...]}
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common.camera import Camera, CalibrationError, Studio, make_camera

JSON_FORMAT_NAME = "silhouette-mocap-calibration"
JSON_VERSION = 1
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # metres per unit


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
    return Studio(tuple(out), source)


def _numeric(value) -> bool:
    try:
        return np.asarray(value, dtype=np.float64).size > 0
    except (TypeError, ValueError):
        return False


def load_calibration(path, units: str | None = None) -> Studio:
    """Read a studio from ``path`` (our JSON; other formats by extension or folder layout)."""
    path = Path(path)
    if not path.exists():
        raise CalibrationError(str(path), "<file>", "does not exist")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationError(str(path), "<file>", f"not valid JSON ({exc})") from None
    return studio_from_json(doc, str(path), units)


def save_calibration(studio: Studio, path) -> None:
    Path(path).write_text(json.dumps(studio_to_json(studio), indent=1))
