"""``mocap import-video`` with videos as users have them: lengths that differ by a frame or two,
cameras that started late, unreadable and truncated files. Frames are matched by content: each
synthetic frame is one grey level that encodes its frame number."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from common.calibration import load_calibration, save_calibration
from common.camera import Studio, circle_studio
from common.sequence import load_sequence
from server.cli import main
from server.commands import import_video

imageio = pytest.importorskip("imageio.v2")
pytest.importorskip("imageio_ffmpeg")

W, H = 64, 48
LEVEL0, LEVEL_STEP = 20, 10  # grey level of frame i: LEVEL0 + LEVEL_STEP * i
BEFORE = 250  # grey level of frames before the synchronous start
REAL_TAKE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "uu_seated_4cam"


def _write_video(path: Path, numbers, codec="mpeg4") -> Path:
    """A video whose frame j shows frame number numbers[j] (None: a frame from before the start)."""
    with imageio.get_writer(path, "ffmpeg", fps=25, codec=codec, quality=8, macro_block_size=16) as w:
        for n in numbers:
            w.append_data(np.full((H, W, 3), BEFORE if n is None else LEVEL0 + LEVEL_STEP * n, np.uint8))
    return path


def _number(image: np.ndarray) -> int:
    return int(round((image.mean() - LEVEL0) / LEVEL_STEP))


@pytest.fixture
def calib(tmp_path) -> Path:
    path = tmp_path / "calib.json"
    save_calibration(circle_studio(3, W, H, overhead=False), path)
    return path


def _run(capsys, calib, videos: dict, *extra) -> tuple[int, str, str]:
    args = ["import-video", "--calibration", str(calib), "--video", *(f"{c}={p}" for c, p in videos.items()), *extra]
    rc = main([str(a) for a in args])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_lengths_differing_by_a_frame_are_trimmed(tmp_path, calib, capsys):
    videos = {"cam1": _write_video(tmp_path / "a.avi", range(20)),
              "cam2": _write_video(tmp_path / "b.avi", range(20)),
              "cam3": _write_video(tmp_path / "c.avi", range(21))}
    out = tmp_path / "seq"
    rc, stdout, err = _run(capsys, calib, videos, "--out", out, "--step", "3")
    assert rc == 0, err
    line = _one_line(err)
    assert "warning" in line and "cam1 20, cam2 20, cam3 21" in line and "0..19" in line
    assert "imported 7 frames (0..18)" in stdout
    seq = load_sequence(out)
    assert seq.frames == [0, 3, 6, 9, 12, 15, 18] and seq.fps == pytest.approx(25.0)
    for f in seq.frames:
        assert [_number(im) for im in seq.images(f)] == [f, f, f]
    assert sorted(p.name for p in (out / "images" / "cam3").iterdir()) == [f"{f:06d}.png" for f in seq.frames]


def test_offsets_match_frames_by_content(tmp_path, calib, capsys):
    # cam2 started 3 frames early (its frame j + 3 is frame j), cam3 2 frames late (its frame j - 2 is frame j).
    videos = {"cam1": _write_video(tmp_path / "a.mp4", range(20), "libx264"),
              "cam2": _write_video(tmp_path / "b.mp4", [None] * 3 + list(range(20)), "libx264"),
              "cam3": _write_video(tmp_path / "c.mp4", range(2, 20), "libx264")}
    out = tmp_path / "seq"
    rc, stdout, err = _run(capsys, calib, videos, "--out", out, "--offset", "cam2=3", "cam3=-2",
                           "--start", "1", "--step", "4")
    assert rc == 0 and err == "", err
    seq = load_sequence(out)
    assert seq.frames == [5, 9, 13, 17]  # on the 1 + 4k grid, from frame 2 (cam3's first)
    assert seq.meta["offsets"] == {"cam1": 0, "cam2": 3, "cam3": -2}
    for f in seq.frames:
        assert [_number(im) for im in seq.images(f)] == [f, f, f]
    # Without the offsets the videos differ by 5 frames of 23: more than 5 %, an error.
    rc, _, err = _run(capsys, calib, videos, "--out", tmp_path / "plain")
    assert rc == 2 and "frame counts differ" in _one_line(err) and not (tmp_path / "plain").exists()


def test_frames_beyond_the_memory_budget_are_decoded_again(tmp_path, calib, capsys, monkeypatch):
    monkeypatch.setattr(import_video, "HOLD_BYTES", 5 * W * H * 3)  # 5 frames of 3 cameras x 7 are held
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(20)) for c in ("cam1", "cam2", "cam3")}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out, "--step", "3", "--offset", "cam3=1")
    assert rc == 0, err
    seq = load_sequence(out)
    assert seq.frames == [0, 3, 6, 9, 12, 15, 18] and "0..18" in _one_line(err)  # cam3 has 19 after the offset
    for f in seq.frames:
        assert [_number(im) for im in seq.images(f)] == [f, f, f + 1]


def test_a_large_length_difference_is_an_error(tmp_path, calib, capsys):
    videos = {"cam1": _write_video(tmp_path / "a.avi", range(20)),
              "cam2": _write_video(tmp_path / "b.avi", range(20)),
              "cam3": _write_video(tmp_path / "c.avi", range(8))}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out)
    line = _one_line(err)
    assert rc == 2 and "frame counts differ between cameras: cam1 20, cam2 20, cam3 8" in line
    assert not out.exists()


@pytest.mark.parametrize("offsets,message", [
    (["cam9=1"], "--offset cam9: no camera of that name"),
    (["cam2=1.5"], "--offset cam2: expected a whole number of frames, got '1.5'"),
    (["cam2"], "--offset: expected CAMERA=FRAMES"),
    (["cam2=1", "cam2=2"], "--offset cam2: given twice"),
    (["cam2=40"], "no frames in common"),
    (["cam2=-25"], "no frames in common"),
])
def test_bad_offsets(tmp_path, calib, capsys, offsets, message):
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(12)) for c in ("cam1", "cam2", "cam3")}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out, "--offset", *offsets)
    assert rc == 2 and message in _one_line(err)
    assert not out.exists()


def test_unreadable_and_truncated_videos(tmp_path, calib, capsys):
    good = {c: _write_video(tmp_path / f"{c}.avi", range(20)) for c in ("cam1", "cam2", "cam3")}
    garbage = tmp_path / "garbage.avi"
    garbage.write_bytes(b"not a video at all" * 100)
    data = good["cam2"].read_bytes()
    header_only = tmp_path / "header_only.avi"
    header_only.write_bytes(data[:len(data) // 2])
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[:int(len(data) * 0.8)])
    out = tmp_path / "seq"
    for bad in (garbage, header_only):
        rc, _, err = _run(capsys, calib, {**good, "cam2": bad}, "--out", out)
        line = _one_line(err)
        assert rc == 2 and f"{bad}: --video cam2: not a readable video" in line, line
    rc, _, err = _run(capsys, calib, {**good, "cam2": cut}, "--out", out)
    line = _one_line(err)
    assert rc == 2 and "frame counts differ" in line and "truncated" in line
    # An unreadable background is found before anything is written too.
    rc, _, err = _run(capsys, calib, good, "--out", out, "--background",
                      *(f"{c}={garbage if c == 'cam3' else p}" for c, p in good.items()))
    assert rc == 2 and f"{garbage}: --background cam3: not a readable video" in _one_line(err)
    assert not out.exists()


def test_video_size_must_match_the_calibration(tmp_path, capsys):
    calib = tmp_path / "calib.json"
    save_calibration(circle_studio(3, 2 * W, H, overhead=False), calib)
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(5)) for c in ("cam1", "cam2", "cam3")}
    rc, _, err = _run(capsys, calib, videos, "--out", tmp_path / "seq")
    line = _one_line(err)
    assert rc == 2 and "128x48" in line and "64x48" in line and not (tmp_path / "seq").exists()


def test_a_guessed_calibration_size_takes_the_videos(tmp_path, capsys):
    calib = tmp_path / "calib.json"
    guessed = circle_studio(3, 2 * W, H, overhead=False)
    save_calibration(Studio(tuple(replace(c, size_guessed=True) for c in guessed)), calib)
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(5)) for c in ("cam1", "cam2", "cam3")}
    rc, _, err = _run(capsys, calib, videos, "--out", tmp_path / "seq")
    assert rc == 0, err
    studio = load_sequence(tmp_path / "seq").studio
    assert all((c.width, c.height, c.size_guessed) == (W, H, False) for c in studio)


@pytest.mark.skipif(not REAL_TAKE.is_dir(), reason="the real 4-camera take is not in ../shared")
def test_real_take_counts_frames_by_decoding(tmp_path, capsys):
    """imageio's count_frames() says 426 for these AVIs; decoding gives 214 (cam4: 215)."""
    xml = tmp_path / "xml"
    xml.mkdir()
    for k in range(1, 5):
        shutil.copy(REAL_TAKE / f"cam{k}" / "config.xml", xml / f"cam{k}.xml")
    calib = tmp_path / "calibration.json"
    save_calibration(load_calibration(xml, units="mm", size=(644, 486)), calib)
    videos = {f"cam{k}": REAL_TAKE / f"cam{k}" / "video.avi" for k in range(1, 5)}
    out = tmp_path / "seq"
    rc, stdout, err = _run(capsys, calib, videos, "--out", out, "--step", "10")
    assert rc == 0, err
    assert "cam4 215" in _one_line(err)
    meta = json.loads((out / "sequence.json").read_text())
    assert meta["frames"] == list(range(0, 211, 10)) and meta["fps"] == pytest.approx(50.0)
    assert len(list((out / "images" / "cam4").iterdir())) == 22
    # Sequential decoding: no grey, half-decoded frames (a seek gives a flat grey picture).
    images = load_sequence(out).images(210)
    assert images.shape == (4, 486, 644, 3) and all(im.std() > 10 for im in images)
