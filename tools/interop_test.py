"""Our exports in the tools people open them in: Blender, OpenSim, the Khronos glTF validator,
three.js in headless Chromium (``make interop-test``; not part of the pytest suite).

    python tools/interop_test.py [--out DIR] [--frames N]

1. A fitted walk: ``mocap synth`` (the bundled CMU walk) and ``mocap fit``, then
   ``mocap export --format all`` and a T-pose BVH (``--rest tpose``).
2. Blender (Debian's ``blender``; installed with apt-get, as root, when missing, with
   ``python3-numpy``), headless: imports the A-pose BVH, the T-pose BVH and the GLB with the
   settings docs/exports.md gives (``tools/interop_blender.py``); every frame there, 17 bones, and
   every joint within 1 mm of poses.jsonl in Blender's world.
3. The GLB: pygltflib loads and validates it; the Khronos validator (npm ``gltf-validator``)
   finds no error and no warning.
4. OpenSim's own Python package (PyPI ``opensim``, in a virtual environment in DIR) reads the
   TRC and the MOT: marker names within Pose2Sim's HALPE_26, positions within 1 mm, the MOT's
   columns and degrees.
5. three.js (npm ``three``, installed into DIR, never into the project) loads the GLB in
   headless Chromium (Debian's ``chromium``): 17 bones whose world positions at the animation's
   keys are within 1 mm of poses.jsonl, an animation that plays on its own, and a screenshot with
   the body drawn (pixels that are not background).

Prints each check with its figures and a summary (also DIR/interop.json); exits 1 when a check
fails. DIR (default: a new temporary folder) keeps every file for a look afterwards.
"""
from __future__ import annotations

import argparse
import functools
import html
import http.server
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import ClassVar

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from common.export import (  # the project's modules, from this checkout
    BVH_JOINT_NAMES, HEAD_JOINT, MOT_COLUMNS, SEGMENT_BVH_NAMES, halpe26_markers, opensim_points,
)
from common.gltf import JOINT_NODE_NAMES, from_gltf, glb_joint_positions
from server.pictures import load_result

TOLERANCE_MM = 1.0           # the issue's bar for joints read back by another tool
FRAMES = 24                  # fitted walk frames
IMAGE_SIZE = "160x120"       # synthetic cameras: small, the fit is what matters, not its accuracy
CAMERAS = 4
THREE = "three@^0.187.0"     # npm: three.js, and the Khronos validator
VALIDATOR = "gltf-validator@2.0.0-dev.3.10"
OPENSIM = "opensim>=4.5,<5"  # PyPI: OpenSim's own bindings and file adapters
OPENSIM_VENV = ROOT / "build" / "interop-opensim-venv"
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars", "--force-device-scale-factor=1", "--window-size=640,640")
CANVAS = (640, 480)          # the three.js page's canvas, CSS pixels, at the page's top left
BODY_PIXELS_MIN = 0.01       # share of the canvas the drawn body covers at least (a 1.7 m actor at 3.6 m: ~6%)
PLAY_MS = 1500               # virtual milliseconds the page plays the animation
APT_TIMEOUT_S = 1200
STEP_TIMEOUT_S = 600
HALPE_26 = {"Hip", "RHip", "RKnee", "RAnkle", "RBigToe", "RSmallToe", "RHeel", "LHip", "LKnee", "LAnkle",
            "LBigToe", "LSmallToe", "LHeel", "Neck", "Head", "Nose", "RShoulder", "RElbow", "RWrist",
            "LShoulder", "LElbow", "LWrist"}  # Pose2Sim/skeletons.py


class Checks:
    """Collects named results: passed or not, with the figures that say why."""

    def __init__(self):
        self.results = []

    def add(self, name: str, ok: bool, **figures) -> bool:
        self.results.append({"check": name, "ok": bool(ok), **figures})
        shown = ", ".join(f"{k} {v}" for k, v in figures.items())
        print(f"{'PASS' if ok else 'FAIL'}  {name}" + (f"  ({shown})" if shown else ""), flush=True)
        return ok

    @property
    def ok(self) -> bool:
        return all(r["ok"] for r in self.results)


def run(cmd, timeout=STEP_TIMEOUT_S, **kwargs) -> subprocess.CompletedProcess:
    """A command that must succeed; its output is shown when it does not."""
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=timeout, check=False, **kwargs)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-4000:] + proc.stderr[-4000:])
        raise SystemExit(f"interop: {' '.join(map(str, cmd[:3]))} ... failed ({proc.returncode})")
    return proc


def ensure_debian_packages(programs: dict[str, tuple[str, ...]]) -> None:
    """{program: Debian packages}: installs the packages of the programs not on PATH (apt-get, root)."""
    missing = [pkg for prog, pkgs in programs.items() if shutil.which(prog) is None for pkg in pkgs]
    if not missing:
        return
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        raise SystemExit(f"interop: needs {', '.join(missing)}: run as root with apt-get, or install them")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    print(f"installing {' '.join(missing)} (apt-get)", flush=True)
    run(["apt-get", "update", "-q"], timeout=APT_TIMEOUT_S, env=env)
    run(["apt-get", "install", "-y", "-q", "--no-install-recommends", *missing], timeout=APT_TIMEOUT_S, env=env)


def mocap(*args) -> None:
    run([sys.executable, "-m", "server.cli", *args], cwd=ROOT)


def deviation_mm(got, expected) -> float:
    return float(np.abs(np.asarray(got, dtype=np.float64) - expected).max() * 1000.0)


# --------------------------------------------------------------------------------- Blender

def blender_import(work: Path, kind: str, path: Path, fps: float, frames: int, points) -> dict:
    job = {"kind": kind, "file": str(path), "fps": fps, "frames": frames, "points": points,
           "out": str(work / f"blender_{kind}_{path.stem}.json")}
    job_path = work / f"blender_{kind}_{path.stem}_job.json"
    job_path.write_text(json.dumps(job))
    run(["blender", "-b", "--factory-startup", "--python", ROOT / "tools" / "interop_blender.py", "--", job_path])
    return json.loads(Path(job["out"]).read_text())


def keyed_frames(got: dict) -> int:
    """Frames of the imported action. Blender keys a glTF time t at t x its scene's whole frame
    rate: at 30.0001 fps the last of 24 keys lands at 22.9999, hence the rounding."""
    first, last = got["action_range"]
    return round(last - first) + 1


def check_blender(checks: Checks, work: Path, exports: Path, motion) -> dict:
    F, expected = len(motion.frames), motion.fit_joints  # Blender's world is our z-up frame
    figures = {}
    bvh_points = [[n, "head"] for n in SEGMENT_BVH_NAMES] + [[HEAD_JOINT, "tail"]]  # head top: the End Site
    for label, path in (("BVH (A-pose rest)", exports / "motion.bvh"), ("BVH (T-pose rest)", exports / "motion_tpose.bvh")):
        got = blender_import(work, "bvh", path, motion.rate, F, bvh_points)
        err = deviation_mm(got["positions"], expected)
        frames = keyed_frames(got)
        checks.add(f"Blender {got['blender']} imports the {label}",
                   frames == F and set(got["keys"].values()) == {F} and sorted(got["bones"]) == sorted(BVH_JOINT_NAMES)
                   and err < TOLERANCE_MM, frames=f"{frames}/{F}", bones=len(got["bones"]),
                   scene_fps=got["scene_fps"], max_joint_deviation_mm=f"{err:.4f}")
        figures[label] = err
    got = blender_import(work, "glb", exports / "motion.glb", motion.rate, F, [[n, "head"] for n in JOINT_NODE_NAMES])
    err = deviation_mm(got["positions"], expected)
    keyed = keyed_frames(got)
    checks.add(f"Blender {got['blender']} imports the GLB",
               keyed == F and set(got["keys"].values()) == {F} and sorted(got["bones"]) == sorted(JOINT_NODE_NAMES)
               and got["meshes"] == ["Body"] and err < TOLERANCE_MM,
               frames=f"{keyed}/{F}", bones=len(got["bones"]), max_joint_deviation_mm=f"{err:.4f}")
    figures["GLB"] = err
    return figures


# ------------------------------------------------------------------------------------ glTF

def check_gltf(checks: Checks, npm: Path, glb: Path, motion) -> None:
    import warnings

    import pygltflib
    from pygltflib.validator import validate

    gltf = pygltflib.GLTF2.load(str(glb))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # pygltflib: "provisional function"
        validate(gltf)
    times, joints = glb_joint_positions(gltf)
    err = deviation_mm(joints, motion.fit_joints)
    checks.add("pygltflib loads and validates the GLB, its animation evaluated in Python",
               len(times) == len(motion.frames) and err < TOLERANCE_MM, bytes=glb.stat().st_size,
               max_joint_deviation_mm=f"{err:.4f}")
    shutil.copy(ROOT / "tools" / "interop_gltf_validate.mjs", npm / "validate.mjs")
    report = json.loads(run(["node", npm / "validate.mjs", glb]).stdout)
    issues = report["issues"]
    checks.add(f"Khronos glTF validator {report['validatorVersion']}",
               issues["numErrors"] == 0 and issues["numWarnings"] == 0, errors=issues["numErrors"],
               warnings=issues["numWarnings"], infos=issues["numInfos"],
               messages=[m["code"] for m in issues["messages"]][:5])


# --------------------------------------------------------------------------------- OpenSim

def check_opensim(checks: Checks, work: Path, exports: Path, motion) -> None:
    venv = OPENSIM_VENV  # kept between runs: OpenSim's wheels are some 400 MB
    if not (venv / "bin" / "python").exists():
        run([sys.executable, "-m", "venv", venv])
        run([venv / "bin" / "pip", "install", "--quiet", OPENSIM, "numpy"])
    got = json.loads(run([venv / "bin" / "python", ROOT / "tools" / "interop_opensim.py", exports / "motion.trc",
                          exports / "motion.mot"]).stdout)
    names, expected = halpe26_markers(opensim_points(motion))
    trc = got["trc"]
    err = deviation_mm(trc["markers"], expected)
    checks.add(f"OpenSim {got['opensim']} reads the TRC",
               set(trc["labels"]) <= HALPE_26 and trc["labels"] == list(names) and trc["units"] == "m"
               and len(trc["markers"]) == len(motion.frames) and abs(trc["rate"] - motion.rate) < 1e-6
               and err < TOLERANCE_MM, markers=len(trc["labels"]), units=trc["units"],
               max_marker_deviation_mm=f"{err:.4f}")
    mot = got["mot"]
    values = np.array(mot["values"])
    angle_err = float(np.abs(np.radians(values[:, 3:]) - motion.params[:, 3:]).max())
    checks.add(f"OpenSim {got['opensim']} reads the MOT",
               mot["labels"] == list(MOT_COLUMNS) and mot["in_degrees"] == "yes" and len(values) == len(motion.frames)
               and np.allclose(mot["times"], motion.times, atol=1e-6) and angle_err < 1e-6,
               columns=len(mot["labels"]), inDegrees=mot["in_degrees"], max_angle_error_rad=f"{angle_err:.1e}")


# -------------------------------------------------------------------------------- three.js

class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    # module scripts need a JavaScript type
    extensions_map: ClassVar[dict] = {**http.server.SimpleHTTPRequestHandler.extensions_map,
                                      ".js": "text/javascript", ".mjs": "text/javascript", ".glb": "model/gltf-binary"}

    def log_message(self, *args):
        pass


def serve(folder: Path) -> http.server.ThreadingHTTPServer:
    """A static file server for ``folder`` on a loopback port (module scripts and fetch() do not
    work from file:// pages)."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(folder)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def chromium(work: Path, url: str, *args: str) -> subprocess.CompletedProcess:
    profile = Path(tempfile.mkdtemp(prefix="profile-", dir=work))  # a fresh profile every run
    return run(["chromium", *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args, url], timeout=120)


def page_result(work: Path, url: str, budget_ms: int) -> dict:
    dom = chromium(work, url, f"--virtual-time-budget={budget_ms}", "--dump-dom").stdout
    found = re.search(r'<pre id="result">(.*?)</pre>', dom, re.DOTALL)
    doc = json.loads(html.unescape(found.group(1))) if found and found.group(1) != "pending" else {"error": "no result"}
    if "error" in doc:
        raise SystemExit(f"interop: the three.js page failed: {doc['error']}")
    return doc


def check_three(checks: Checks, work: Path, npm: Path, glb: Path, motion) -> None:
    from PIL import Image

    shutil.copy(ROOT / "tools" / "interop_three.html", work / "three.html")
    server = serve(work)
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}/three.html?glb={glb.relative_to(work)}"
        doc = page_result(work, base + "&mode=sample", 3000)
        expected = motion.fit_joints
        err = max(deviation_mm(from_gltf(s["joints"]), expected[s["key"]]) for s in doc["samples"])
        checks.add(f"three.js r{doc['three']} loads the GLB in Chromium",
                   doc["bones"] == list(JOINT_NODE_NAMES) and doc["keys"] == len(motion.frames) and err < TOLERANCE_MM,
                   bones=len(doc["bones"]), tracks=doc["tracks"], keys=doc["keys"], duration_s=f"{doc['duration']:.3f}",
                   max_joint_deviation_mm=f"{err:.4f}")
        play = page_result(work, base + "&mode=play", PLAY_MS)
        checks.add("three.js plays the animation", play["ticks"] > 10 and play["mixer_time"] > 0.5 and play["moved"] > 0.05,
                   ticks=play["ticks"], mixer_time_s=f"{play['mixer_time']:.2f}", hips_moved_m=f"{play['moved']:.3f}")
        shot = work / "three_screenshot.png"
        chromium(work, base + "&mode=shot", "--virtual-time-budget=3000", f"--screenshot={shot}")
        pixels = np.asarray(Image.open(shot).convert("RGB"))[:CANVAS[1], :CANVAS[0]].astype(int)
        body = float(np.mean(np.any(pixels < 235, axis=-1)))  # the page's background is white
        checks.add("three.js draws the body", body > BODY_PIXELS_MIN, body_pixels=f"{body:.1%}", screenshot=str(shot))
    finally:
        server.shutdown()


# ------------------------------------------------------------------------------------ main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="work folder (default: a new temporary one, kept)")
    ap.add_argument("--frames", type=int, default=FRAMES, help=f"frames of the fitted walk (default {FRAMES})")
    args = ap.parse_args(argv)
    started = time.monotonic()
    work = (args.out or Path(tempfile.mkdtemp(prefix="mocap-interop-"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    print(f"interop: work folder {work}", flush=True)
    ensure_debian_packages({"blender": ("blender", "python3-numpy"), "chromium": ("chromium",),
                            "npm": ("nodejs", "npm")})
    seq, res, exports = work / "seq", work / "res", work / "exports"
    if not (res / "poses.jsonl").exists():
        mocap("synth", "--out", seq, "--frames", args.frames, "--size", IMAGE_SIZE, "--cameras", CAMERAS, "--quiet",
              "--overwrite")
        mocap("fit", seq, "--out", res, "--quiet", "--overwrite")
    mocap("export", res, "--format", "all", "--out", exports, "--overwrite", "--quiet")
    mocap("export", res, "--format", "bvh", "--rest", "tpose", "--out", exports / "motion_tpose.bvh", "--overwrite",
          "--quiet")
    motion = load_result(res).motion
    print(f"interop: a fitted walk of {len(motion.frames)} frames at {motion.rate:g} fps "
          f"({time.monotonic() - started:.0f} s)", flush=True)
    npm = work / "npm"
    npm.mkdir(exist_ok=True)
    run(["npm", "install", "--prefix", npm, "--no-audit", "--no-fund", "--no-save", THREE, VALIDATOR])

    checks = Checks()
    blender = check_blender(checks, work, exports, motion)
    check_gltf(checks, npm, exports / "motion.glb", motion)
    check_opensim(checks, work, exports, motion)
    check_three(checks, work, npm, exports / "motion.glb", motion)
    seconds = time.monotonic() - started
    summary = {"ok": checks.ok, "seconds": round(seconds, 1), "frames": len(motion.frames), "fps": motion.rate,
               "glb_bytes": (exports / "motion.glb").stat().st_size,
               "blender_max_joint_deviation_mm": blender, "checks": checks.results}
    (work / "interop.json").write_text(json.dumps(summary, indent=1))
    passed = sum(r["ok"] for r in checks.results)
    print(f"interop: {passed} passed, {len(checks.results) - passed} failed in {seconds:.0f} s "
          f"(details: {work / 'interop.json'})")
    return 0 if checks.ok else 1


if __name__ == "__main__":
    sys.exit(main())
