"""report.html: self-contained, correct data, and in headless Chromium: no console errors, the
player draws frames and plays (screenshots checked in the player's region).

Chromium is Debian's ``chromium`` package. When it is missing, the ``chromium`` fixture installs
it with apt-get if it may (root, apt-get present, and CI=true or MOCAP_INSTALL_CHROMIUM=1);
otherwise the browser tests skip and say how to get it.
"""
from __future__ import annotations

import argparse
import base64
import io
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from common.body import JOINT_NAMES
from common.errors import UserError
from common.export import FORMATS
from server.cli import main as cli_main
from server.commands import report as report_command
from server.pictures import load_result
from server.report import STRIP_HEIGHT, write_report

FRAMES = 3
CHROMIUM_NAMES = ("chromium", "chromium-browser")
CHROMIUM_TIMEOUT = 90          # seconds per browser run
INSTALL_TIMEOUT = 600          # seconds for apt-get
WINDOW = (1400, 1800)          # CSS pixels: the player, the summary and the first plots
FITTED_RGB = ((0xE4, 0x57, 0x2E), (0xF3, 0x9C, 0x4A), (0xB5, 0x30, 0x1A))  # the player's fitted skeleton
TRUTH_RGB = ((0x2E, 0x86, 0xAB), (0x5F, 0xB8, 0xDD), (0x1B, 0x5A, 0x78))   # and the truth's


def mocap_report(argv: list[str]) -> int:
    """Runs ``mocap report`` through its own parser (the command module's register())."""
    parser = argparse.ArgumentParser(prog="mocap")
    report_command.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["report", *argv])
    return args.func(args)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory) -> tuple[Path, Path]:
    """A real (tiny) fit: mocap synth, then mocap fit. Returns (sequence, result)."""
    root = tmp_path_factory.mktemp("report")
    seq, res = root / "seq", root / "res"
    assert cli_main(["synth", "--out", str(seq), "--frames", str(FRAMES), "--size", "160x120", "--cameras", "5",
                     "--quiet"]) == 0
    assert cli_main(["fit", str(seq), "--out", str(res), "--quiet"]) == 0
    return seq, res


@pytest.fixture(scope="module")
def report(fitted) -> Path:
    seq, res = fitted
    return write_report(res)


def test_mocap_report_writes_page_and_pictures(fitted, capsys):
    seq, res = fitted
    assert mocap_report([str(res), "--json", "--frames", "0,2", "--cameras", "cam1,cam3"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["report"] == str(res / "report.html") and Path(doc["report"]).stat().st_size > 10_000
    names = {Path(p).name for p in doc["pictures"]}
    assert {"overlay_000000.png", "overlay_000002.png", "model_000002.png", "sequence.gif", "sequence.mp4",
            "joint_error.png"} <= names
    # the take's video, made with the pictures, is in the page; the exports say how to open them
    text = Path(doc["report"]).read_text()
    video = re.search(r'<video[^>]+src="data:video/mp4;base64,([^"]+)"', text)
    assert video and base64.b64decode(video.group(1)) == (res / "pictures" / "sequence.mp4").read_bytes()
    for fmt in FORMATS:
        assert f"--format {fmt}</code>" in text
    assert "Forward -Z, Up Y" in text and "HALPE_26" in text and "body25" in text
    assert mocap_report([str(res), "--quiet", "--no-pictures", "--out", str(res / "r2.html")]) == 0
    assert capsys.readouterr().out == "" and (res / "r2.html").exists()
    assert mocap_report([str(res), "--no-gif", "--no-pictures", "--overwrite"]) == 0
    assert "report.html" in capsys.readouterr().out
    # pictures again, to a new page: refused for the pictures RESULT/pictures/ holds, where no
    # option would write them elsewhere
    with pytest.raises(UserError, match="holds an earlier set of pictures") as refused:
        mocap_report([str(res), "--no-gif", "--out", str(res / "r3.html")])
    assert "--overwrite" in str(refused.value) and "another folder" not in str(refused.value)
    assert str(refused.value).endswith("or --no-pictures to write the page alone")


def test_summary_shows_refinement_beside_tracking(fitted):
    from server.pictures import load_result
    from server.report import summary_rows

    seq, res = fitted
    summary = json.loads((res / "summary.json").read_text())
    rows = dict(summary_rows(load_result(res, seq)))
    assert rows["refinement seconds per frame"] == (f"{summary['refine_seconds_per_frame']:.3f} s (1 pass, "
                                                    f"{summary['frames_refined']} frames improved)")
    assert rows["tracking alone, mean / max joint error"] == (f"{summary['tracking_mean_joint_error_mm']:.1f} / "
                                                              f"{summary['tracking_max_joint_error_mm']:.1f} mm")
    take = "take time, with earlier runs' tracking"
    assert take not in rows  # fitted in one run: its wall time is the take's
    from dataclasses import replace

    resumed = replace(load_result(res, seq), summary=summary | {"frames_fitted_this_run": 1, "take_seconds": 12.34})
    assert dict(summary_rows(resumed))[take] == "12.3 s"


def test_page_is_self_contained(report):
    text = report.read_text()
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", text)
    assert "url(" not in text and "@import" not in text and "<link" not in text
    assert not re.search(r"<script[^>]+src=", text)
    images = re.findall(r'<img[^>]+src="([^"]+)"', text)
    assert len(images) >= 5  # plots, overlay strips, model views
    sizes = []
    for src in images:
        assert src.startswith("data:image/png;base64,")
        Image.open(io.BytesIO(base64.b64decode(src.split(",", 1)[1]))).verify()
        sizes.append(Image.open(io.BytesIO(base64.b64decode(src.split(",", 1)[1]))).size)
    # overlay strips: 4 of the 5 cameras, each tile 4:3 as the cameras' 160x120 images
    assert (4 * round(STRIP_HEIGHT * 4 / 3) + 3 * 4, STRIP_HEIGHT + 16) in sizes


def test_player_data_is_the_fit(report, fitted):
    seq, res = fitted
    text = report.read_text()
    raw = re.search(r'<script type="application/json" id="player-data">(.*?)</script>', text, re.S).group(1)
    data = json.loads(raw)
    poses = [json.loads(line) for line in (res / "poses.jsonl").read_text().splitlines()]
    assert data["frames"] == [p["frame"] for p in poses]
    assert data["joints"] == list(JOINT_NAMES) and len(data["bones"]) == 16
    fitted_mm = np.array([[p["joints"][n] for n in JOINT_NAMES] for p in poses]) * 1000.0
    assert np.abs(np.array(data["fitted"]).reshape(-1, 17, 3) - fitted_mm).max() <= 0.5
    assert data["truth"] is not None and len(data["truth"]) == FRAMES
    summary = json.loads((res / "summary.json").read_text())
    assert np.mean(data["error"]) == pytest.approx(summary["mean_joint_error_mm"], abs=0.2)


def test_report_without_the_sequence(fitted, tmp_path, capsys):
    seq, res = fitted
    moved = tmp_path / "res"
    shutil.copytree(res, moved)
    (moved / "summary.json").write_text(json.dumps({**json.loads((res / "summary.json").read_text()),
                                                    "sequence": str(tmp_path / "gone")}))
    with pytest.raises(UserError, match="--fps"):
        mocap_report([str(moved), "--quiet", "--overwrite"])
    shutil.rmtree(moved / "pictures", ignore_errors=True)
    assert mocap_report([str(moved), "--json", "--fps", "30", "--no-gif", "--overwrite"]) == 0
    pictures = {Path(p).name for p in json.loads(capsys.readouterr().out)["pictures"]}
    assert "energy.png" in pictures and "model_000000.png" in pictures
    assert not any(p.startswith("overlay") for p in pictures) and "joint_error.png" not in pictures
    text = (moved / "report.html").read_text()
    assert "no overlays" in text and "no truth.jsonl" in text and "No overlay video" in text
    assert '"truth":null' in text


# ---------------------------------------------------------------------------------- Chromium

def _find_chromium() -> str | None:
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


@pytest.fixture(scope="session")
def chromium() -> str:
    path = _find_chromium()
    allowed = os.environ.get("CI", "").lower() in ("1", "true") or os.environ.get("MOCAP_INSTALL_CHROMIUM") == "1"
    if path is None and allowed and shutil.which("apt-get") and os.geteuid() == 0:
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        subprocess.run(["apt-get", "update", "-q"], env=env, timeout=INSTALL_TIMEOUT, capture_output=True)
        subprocess.run(["apt-get", "install", "-y", "-q", "--no-install-recommends", "chromium"], env=env,
                       timeout=INSTALL_TIMEOUT, capture_output=True)
        path = _find_chromium()
    if path is None:
        pytest.skip("Debian's chromium is not installed: `apt-get install chromium` (as root), or run the tests "
                    "with MOCAP_INSTALL_CHROMIUM=1 (CI=true does it) to let this fixture install it")
    return path


def run_chromium(chromium: str, url: str, tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    profile = tmp_path / f"profile{len(list(tmp_path.glob('profile*')))}"
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
           "--hide-scrollbars", "--force-device-scale-factor=1", f"--window-size={WINDOW[0]},{WINDOW[1]}",
           f"--user-data-dir={profile}", "--enable-logging=stderr", "--v=0", *args, url]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT)


def dump_dom(chromium: str, page: Path, tmp_path: Path, fragment: str = "", budget_ms: int = 500):
    """(<html> attributes, <body> attributes, console lines) after ``budget_ms`` of virtual time."""
    proc = run_chromium(chromium, page.as_uri() + fragment, tmp_path, f"--virtual-time-budget={budget_ms}",
                        "--dump-dom")
    html_tag = re.search(r"<html[^>]*>", proc.stdout)
    body_tag = re.search(r"<body[^>]*>", proc.stdout)
    assert html_tag and body_tag, proc.stderr[-2000:]
    attrs = [dict(re.findall(r'([\w-]+)="([^"]*)"', t.group(0))) for t in (html_tag, body_tag)]
    console = [line for line in proc.stderr.splitlines() if ":CONSOLE" in line]
    return attrs[0], attrs[1], console


def screenshot(chromium: str, page: Path, tmp_path: Path, fragment: str, name: str) -> np.ndarray:
    out = tmp_path / name
    proc = run_chromium(chromium, page.as_uri() + fragment, tmp_path, "--virtual-time-budget=500",
                        f"--screenshot={out}")
    assert out.exists(), proc.stderr[-2000:]
    return np.asarray(Image.open(out).convert("RGB"))


def colour_pixels(img: np.ndarray, colours, tolerance: int = 12) -> int:
    return sum(int(np.count_nonzero(np.all(np.abs(img.astype(int) - c) <= tolerance, axis=-1))) for c in colours)


@pytest.mark.timeout(INSTALL_TIMEOUT + 300)
def test_page_loads_without_console_errors_and_plays(chromium, report, tmp_path):
    html_attrs, body, console = dump_dom(chromium, report, tmp_path, "#frame=1")
    assert "data-errors" not in html_attrs, html_attrs.get("data-error-messages")
    assert console == []  # the page logs nothing: no uncaught errors, no warnings
    assert int(body["data-frames-drawn"]) >= 1 and body["data-frame"] == "1"
    # playing: a second of (virtual) time draws about fps frames
    html_attrs, body, console = dump_dom(chromium, report, tmp_path, "#play", budget_ms=1000)
    assert "data-errors" not in html_attrs and console == []
    assert int(body["data-frames-drawn"]) >= 10


@pytest.mark.timeout(INSTALL_TIMEOUT + 300)
def test_take_video_decodes_in_chromium(chromium, fitted, tmp_path):
    """The embedded MP4 (every frame at the take's rate) is one the browser reads."""
    _, res = fitted
    if not (res / "pictures" / "sequence.mp4").exists():  # the pictures test made it, unless run alone
        assert mocap_report([str(res), "--quiet", "--overwrite"]) == 0
    page = tmp_path / "report.html"
    write_report(res, out=page)
    html_attrs, body, console = dump_dom(chromium, page, tmp_path, "#frame=0", budget_ms=3000)
    assert "data-errors" not in html_attrs and console == []
    fps = load_result(res).motion.fps
    assert float(body["data-video-duration"]) == pytest.approx(FRAMES / fps, abs=1.5 / fps)


@pytest.mark.timeout(INSTALL_TIMEOUT + 300)
def test_error_hook_catches_a_broken_page(chromium, report, tmp_path):
    """The no-error check above can fail: a page with a script error is caught."""
    broken = tmp_path / "broken.html"
    broken.write_text(report.read_text().replace("</body>", "<script>undefinedFunction();</script></body>"))
    html_attrs, _, console = dump_dom(chromium, broken, tmp_path)
    assert html_attrs.get("data-errors") == "1" and "undefinedFunction" in html_attrs["data-error-messages"]
    assert any("undefinedFunction" in line for line in console)


@pytest.mark.timeout(INSTALL_TIMEOUT + 300)
def test_screenshot_shows_skeletons_and_plots(chromium, report, tmp_path):
    _, body, _ = dump_dom(chromium, report, tmp_path, "#frame=0")
    x, y, w, h = (int(v) for v in body["data-canvas-rect"].split(","))
    assert x + w <= WINDOW[0] and y + h <= WINDOW[1]
    first = screenshot(chromium, report, tmp_path, "#frame=0", "frame0.png")
    region = first[y:y + h, x:x + w]
    # non-empty: the fitted skeleton and the truth are drawn (reference: an empty canvas has neither)
    assert colour_pixels(region, FITTED_RGB) > 300
    assert colour_pixels(region, TRUTH_RGB) > 300
    assert colour_pixels(first[:y], FITTED_RGB) == 0  # nothing of the player outside its canvas
    # another frame and another viewpoint draw a different picture
    turned = screenshot(chromium, report, tmp_path, "#frame=2&yaw=20&pitch=40", "frame2.png")
    changed = np.count_nonzero(np.any(turned[y:y + h, x:x + w] != region, axis=-1))
    assert changed > 500
    # the plots under the player: a white plot area with dark axes and coloured curves
    below = first[y + h + 40:]
    assert colour_pixels(below, ((0xE4, 0x57, 0x2E),), tolerance=30) > 200  # joint error curve
    assert np.count_nonzero(np.all(below < 60, axis=-1)) > 2000              # axes and labels


def test_pictures_made_again_replace_the_earlier_set_whole(fitted, tmp_path, capsys):
    """--overwrite swaps in a new pictures folder: an earlier run's overlays of other frames go."""
    _, res = fitted
    again = tmp_path / "res"
    shutil.copytree(res, again)
    assert mocap_report([str(again), "--quiet", "--no-gif", "--overwrite", "--frames", "0"]) == 0
    assert mocap_report([str(again), "--quiet", "--no-gif", "--overwrite", "--frames", "1"]) == 0
    names = {p.name for p in (again / "pictures").iterdir()}
    assert "overlay_000001.png" in names and "overlay_000000.png" not in names and "sequence.gif" not in names
    with pytest.raises(UserError, match="--cameras: cam1 given more than once"):
        mocap_report([str(again), "--no-pictures", "--overwrite", "--cameras", "cam1,cam2,cam1"])
