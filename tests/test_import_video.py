"""``mocap import-video`` with videos as users have them: lengths that differ by a frame or two,
cameras that started late, unreadable, truncated and damaged files (frames lost in the middle),
image folders that lack a frame. Frames are matched by content: each synthetic frame is one grey
level that encodes its frame number."""
from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from common.calibration import load_calibration, save_calibration, studio_to_json
from common.camera import Studio, circle_studio
from common.sequence import load_sequence
from server.cli import main
from server import frame_sources
from server.commands import import_video

imageio = pytest.importorskip("imageio.v2")
pytest.importorskip("imageio_ffmpeg")

pytestmark = pytest.mark.timeout(120)

W, H = 64, 48
LEVEL0, LEVEL_STEP = 20, 10  # grey level of frame i: LEVEL0 + LEVEL_STEP * i
BEFORE = 250  # grey level of frames before the synchronous start
REAL_TAKE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "uu_seated_4cam"


def _write_video(path: Path, numbers, codec="mpeg4", noise_rows: int = 0) -> Path:
    """A video whose frame j shows frame number numbers[j] (None: a frame from before the start);
    ``noise_rows`` rows of noise at the top make its packets large enough to damage one by one."""
    rng = np.random.default_rng(0)
    with imageio.get_writer(path, "ffmpeg", fps=25, codec=codec, quality=8, macro_block_size=16) as w:
        for n in numbers:
            frame = np.full((H, W, 3), BEFORE if n is None else LEVEL0 + LEVEL_STEP * n, np.uint8)
            frame[:noise_rows] = rng.integers(0, 256, (noise_rows, W, 3))
            w.append_data(frame)
    return path


def _write_folder(folder: Path, frames, shift: int = 0) -> Path:
    """A folder of images named by number: ``img<n + shift>.png`` shows frame n."""
    folder.mkdir(parents=True)
    for n in frames:
        Image.fromarray(np.full((H, W, 3), LEVEL0 + LEVEL_STEP * n, np.uint8)).save(folder / f"img{n + shift:04d}.png")
    return folder


def _damage(path: Path, at: float, size: int) -> Path:
    """The file with ``size`` bytes from the fraction ``at`` of its length overwritten by 0xFF."""
    data = bytearray(path.read_bytes())
    start = int(len(data) * at)
    data[start:start + size] = b"\xff" * size
    path.write_bytes(bytes(data))
    return path


def _lose_frames(path: Path, frames, headers: bool) -> Path:
    """The AVI with the chunks of its video frames ``frames`` overwritten by 0xFF: whole (read in
    file order, they are lost without a gap in the count) or their data only (the decoder fails
    on them)."""
    data = bytearray(path.read_bytes())
    at, chunks = data.index(b"movi") + 4, []
    while data[at:at + 4] == b"00dc":  # the video frames' chunks, up to the index
        size = int.from_bytes(data[at + 4:at + 8], "little")
        chunks.append((at, size))
        at += 8 + size + size % 2
    for k in frames:
        at, size = chunks[k]
        start = at if headers else at + 8
        data[start:at + 8 + size] = b"\xff" * (at + 8 + size - start)
    path.write_bytes(bytes(data))
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


def test_sizes_the_calibration_lacks_come_from_the_videos_without_a_guess_warning(tmp_path, capsys):
    """EasyMocap's intri.yml as write_intri writes it (no H_/W_): the videos give the sizes, and
    no line says they were guessed."""
    folder = tmp_path / "calib"
    save_calibration(circle_studio(3, W, H, overhead=False), folder, fmt="easymocap")
    intri = folder / "intri.yml"
    intri.write_text("".join(line for line in intri.read_text().splitlines(keepends=True)
                             if not line.startswith(("H_", "W_"))))
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(4)) for c in ("cam1", "cam2", "cam3")}
    rc, _, err = _run(capsys, folder, videos, "--out", tmp_path / "seq")
    assert rc == 0 and err == "", err
    assert all((c.width, c.height) == (W, H) and not c.size_guessed for c in load_sequence(tmp_path / "seq").studio)


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


def test_an_offset_past_the_trim_limit_is_no_length_difference(tmp_path, calib, capsys):
    """Recordings of one length, one camera 12 frames late (more than the 10 frames two lengths
    may differ by): the others' last 12 frames go with the offset, with a warning, no error."""
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(22)) for c in ("cam1", "cam2", "cam3")}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out, "--offset", "cam2=12", "--step", "3")
    assert rc == 0, err
    assert _one_line(err) == ("warning: with the offsets (cam1 22, cam2 22 (offset +12), cam3 22 frames) the frames "
                              "all cameras have are 0..9")
    seq = load_sequence(out)
    assert seq.frames == [0, 3, 6, 9]
    for f in seq.frames:
        assert [_number(im) for im in seq.images(f)] == [f, f + 12, f]
    rc, _, err = _run(capsys, calib, videos, "--out", tmp_path / "late", "--offset", "cam2=-12", "--step", "3")
    assert rc == 0 and "the frames all cameras have are 12..21" in _one_line(err)
    # image folders numbered from 1000: the same
    folders = {c: _write_folder(tmp_path / "numbered" / c, range(22), shift=1000) for c in ("cam1", "cam2", "cam3")}
    rc, _, err = _run(capsys, calib, folders, "--out", tmp_path / "numbered_seq", "--offset", "cam2=12", "--step", "3")
    assert rc == 0 and "the frames all cameras have are 1000..1009" in err, err  # (and the frame rate's warning)


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
    for extra in ((), ("--missing-frames", "skip")):  # where its frames were lost cannot be told
        rc, _, err = _run(capsys, calib, {**good, "cam2": cut}, "--out", out, *extra)
        line = _one_line(err)
        assert rc == 2 and f"{cut}: --video cam2: only" in line and "truncated" in line, line
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


def test_folders_are_matched_by_the_numbers_in_their_names(tmp_path, calib, capsys):
    """A folder that lacks a frame inside the range is an error naming the file, not a camera whose
    later frames shift by one; --missing-frames skip leaves that frame out of every camera."""
    folders = {c: _write_folder(tmp_path / c, [f for f in range(12) if c != "cam3" or f != 5])
               for c in ("cam1", "cam2", "cam3")}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, folders, "--out", out)
    line = _one_line(err)
    assert rc == 2 and f"{folders['cam3'] / 'img0005.png'}: --video cam3: frame 5 is missing" in line, line
    assert "cam1, cam2" in line and "--missing-frames skip" in line and not out.exists()
    rc, stdout, err = _run(capsys, calib, folders, "--out", out, "--missing-frames", "skip", "--fps", "30")
    line = _one_line(err)
    assert rc == 0 and "warning" in line and "frame numbers 5 (cam3 lacks 5)" in line, line
    seq = load_sequence(out)
    assert seq.frames == [f for f in range(12) if f != 5] and "imported 11 frames" in stdout
    for f in seq.frames:
        assert [_number(im) for im in seq.images(f)] == [f, f, f]
    rc, _, err = _run(capsys, calib, folders, "--out", out, "--missing-frames", "sometimes")
    assert rc == 2 and "--missing-frames: invalid choice" in _one_line(err)


def test_a_folder_that_starts_late_is_trimmed(tmp_path, calib, capsys):
    # cam2's first image is frame 1 (within 5 %): the others' frame 0 is cut, with a warning.
    folders = {"cam1": _write_folder(tmp_path / "cam1", range(24)),
               "cam2": _write_folder(tmp_path / "cam2", range(1, 24)),
               "cam3": _write_folder(tmp_path / "cam3", range(24))}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, folders, "--out", out, "--step", "2", "--fps", "30")
    line = _one_line(err)
    assert rc == 0 and "cam2 23 numbered 1..23" in line and "all cameras have the frames 1..23" in line, line
    seq = load_sequence(out)
    assert seq.frames == list(range(2, 24, 2))  # on the --start 0 + k --step 2 grid
    for f in seq.frames:
        assert [_number(im) for im in seq.images(f)] == [f, f, f]
    # A short take whose cameras stopped two frames apart (17% of 12): trimmed all the same
    short = {c: _write_folder(tmp_path / "short" / c, range(12 - 2 * (c == "cam3"))) for c in ("cam1", "cam2", "cam3")}
    rc, _, err = _run(capsys, calib, short, "--out", tmp_path / "short_seq", "--fps", "30")
    assert rc == 0 and "all cameras have the frames 0..9, the rest is left out" in _one_line(err), err
    assert load_sequence(tmp_path / "short_seq").frames == list(range(10))
    # Folders numbered in steps of 3 (all alike) lack no frame.
    stepped = {c: _write_folder(tmp_path / "stepped" / c, range(0, 12, 3)) for c in ("cam1", "cam2", "cam3")}
    rc, _, err = _run(capsys, calib, stepped, "--out", tmp_path / "stepped_seq", "--fps", "30")
    assert rc == 0 and err == "", err
    assert load_sequence(tmp_path / "stepped_seq").frames == [0, 3, 6, 9]


def test_offsets_shift_a_folders_numbers(tmp_path, calib, capsys):
    # cam3's counter ran 100 ahead: its img0105.png is the others' frame 5.
    folders = {"cam1": _write_folder(tmp_path / "cam1", range(12)),
               "cam2": _write_folder(tmp_path / "cam2", range(12)),
               "cam3": _write_folder(tmp_path / "cam3", [f for f in range(12) if f != 7], shift=100)}
    rc, _, err = _run(capsys, calib, folders, "--out", tmp_path / "plain")
    assert rc == 2 and "no frames in common" in _one_line(err) and "cam3 11 numbered 100..111" in err
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, folders, "--out", out, "--offset", "cam3=100")
    line = _one_line(err)
    assert rc == 2 and f"{folders['cam3'] / 'img0107.png'}: --video cam3: frame 7 is missing" in line, line
    rc, _, err = _run(capsys, calib, folders, "--out", out, "--offset", "cam3=100", "--missing-frames", "skip",
                      "--step", "2", "--fps", "30")
    assert rc == 0 and err == "", err  # frame 7 is not on the --step 2 grid: nothing is missing
    seq = load_sequence(out)
    assert seq.frames == [0, 2, 4, 6, 8, 10] and seq.meta["offsets"]["cam3"] == 100
    for f in seq.frames:
        assert [_number(im) for im in seq.images(f)] == [f, f, f]


@pytest.mark.parametrize("headers", [True, False], ids=["chunks", "data"])
def test_frames_a_damaged_video_lost_are_missing_frame_numbers(tmp_path, calib, capsys, headers):
    """A damaged stretch of an AVI loses frames: read in file order, its chunks are lost without a
    gap in the count (chunks), or the decoder fails on them and the constant-rate output repeats
    the frame before them and puts the one after them a frame early (data). Each frame the decoder
    returns keeps its own number; the lost numbers are an error naming the video, or with
    --missing-frames skip are left out of every camera, as a folder's missing images are."""
    cams = ("cam1", "cam2", "cam3")
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(24), "mjpeg", noise_rows=8) for c in cams}
    undamaged = {c: [np.asarray(f) for f in imageio.get_reader(p, "ffmpeg")] for c, p in videos.items()}
    videos["cam2"] = _lose_frames(shutil.copy(videos["cam2"], tmp_path / "damaged.avi"), range(6, 10), headers)
    decoded = [_number(np.asarray(f)[8:]) for f in imageio.get_reader(videos["cam2"], "ffmpeg")]
    # the premise: decoded frame by frame, the frames after the stretch are out of place
    assert (len(decoded), decoded[6]) == (20, 10) if headers else (len(decoded), decoded[9]) == (24, 10), decoded
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out)
    line = _one_line(err)
    assert rc == 2 and f"{videos['cam2']}: --video cam2: 4 frames 6, 7, 8, 9 are lost" in line, line
    assert "but not in cam1, cam3" in line and "--missing-frames skip" in line and not out.exists()
    rc, stdout, err = _run(capsys, calib, videos, "--out", out, "--missing-frames", "skip")
    line = _one_line(err)
    assert rc == 0 and "warning" in line and "frame numbers 6, 7, 8, 9 (cam2 lacks 6, 7, 8, 9)" in line, line
    seq = load_sequence(out)
    assert seq.frames == [f for f in range(24) if not 6 <= f <= 9] and "imported 20 frames" in stdout
    # the undamaged cameras' frames are those decoded frame by frame; cam2's, its undamaged copy's
    for f in seq.frames:
        for image, c in zip(seq.images(f), cams):
            assert np.array_equal(image, undamaged[c][f]), (c, f)


def test_a_gap_in_a_videos_timestamps_is_lost_frames(tmp_path, calib, capsys):
    """An MP4 whose timestamps skip frames 5..8 (a camera that dropped them): decoded frame by frame
    at the constant rate, ffmpeg repeats the frames beside the gap and stays off after it. Each
    frame keeps the number its time gives; the gap's numbers are lost (and any the constant-rate
    output dropped to catch up)."""
    import imageio_ffmpeg

    videos = {c: _write_video(tmp_path / f"{c}.mp4", range(24), "libx264", noise_rows=8) for c in ("cam1", "cam3")}
    videos["cam2"] = tmp_path / "cam2.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(videos["cam1"]), "-vf",
                    "select='not(between(n,5,8))'", "-fps_mode", "passthrough", "-c:v", "libx264", str(videos["cam2"])],
                   check=True)
    decoded = [_number(np.asarray(f)[8:]) for f in imageio.get_reader(videos["cam2"], "ffmpeg")]
    assert decoded[15:] != list(range(15, len(decoded)))  # the premise: out of step after the gap
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out, "--missing-frames", "skip")
    line = _one_line(err)
    assert rc == 0 and "frame numbers 5, 6, 7, 8" in line, line
    seq = load_sequence(out)
    assert not {5, 6, 7, 8} & set(seq.frames) and seq.frames[-1] == 23 and len(seq.frames) >= 16
    for f in seq.frames:
        assert [_number(im[8:]) for im in seq.images(f)] == [f, f, f]


def test_a_damaged_video_stays_in_step_with_offset_and_step(tmp_path, calib, capsys, monkeypatch):
    monkeypatch.setattr(import_video, "HOLD_BYTES", 5 * W * H * 3)  # most frames are decoded again, by the index
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(24), "mjpeg", noise_rows=8) for c in ("cam1", "cam3")}
    # cam2 started 2 frames early: its frames 8..11, lost, are the others' 6..9
    videos["cam2"] = _lose_frames(_write_video(tmp_path / "cam2.avi", [None, None, *range(24)], "mjpeg", noise_rows=8),
                                  range(8, 12), headers=True)
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out, "--offset", "cam2=2", "--start", "1", "--step", "2",
                      "--stop", "21", "--missing-frames", "skip")
    line = _one_line(err)
    assert rc == 0 and "frame numbers 7, 9 (cam2 lacks 7, 9)" in line, line  # 6 and 8 are not on the grid
    seq = load_sequence(out)
    assert seq.frames == [1, 3, 5, 11, 13, 15, 17, 19]
    for f in seq.frames:
        assert [_number(im[8:]) for im in seq.images(f)] == [f, f, f]


def test_a_video_that_lost_its_first_frame_is_refused(tmp_path, calib, capsys):
    """Frames lost before the first one decoded leave no gap: every later frame would stand in
    for an earlier one, whatever --missing-frames says."""
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(24), "mjpeg", noise_rows=8) for c in ("cam1", "cam2", "cam3")}
    _lose_frames(videos["cam2"], [0, 10, 11], headers=False)
    first = next(iter(imageio.get_reader(videos["cam2"], "ffmpeg")))
    assert _number(np.asarray(first)[8:]) == 1  # the premise: decoded, frame 1 comes first
    rc, _, err = _run(capsys, calib, videos, "--out", tmp_path / "seq", "--missing-frames", "skip")
    line = _one_line(err)
    assert rc == 2 and f"{videos['cam2']}: --video cam2: its first frames are lost (about 1;" in line, line
    assert not (tmp_path / "seq").exists()


def test_an_ffmpeg_that_cannot_say_which_frames_are_lost(tmp_path, calib, capsys, monkeypatch):
    """Before 6.1 ffmpeg cannot say which decoded frame each output frame shows: a video that
    decodes shorter than its file declares is refused, as the place of its lost frames cannot be
    told, whatever --missing-frames says."""
    monkeypatch.setattr(frame_sources, "_reports_frames", lambda: False)
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(24), "mjpeg", noise_rows=8) for c in ("cam1", "cam2", "cam3")}
    _lose_frames(videos["cam2"], range(6, 10), headers=True)
    out = tmp_path / "seq"
    for extra in ((), ("--missing-frames", "skip")):
        rc, _, err = _run(capsys, calib, videos, "--out", out, *extra)
        line = _one_line(err)
        assert rc == 2 and f"{videos['cam2']}: --video cam2: only 0.80 s of the 0.96 s" in line, line
        assert "about 4 frames are lost" in line and "cannot leave them out" in line and not out.exists()


def test_one_file_for_two_cameras_is_refused(tmp_path, calib, capsys):
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(6)) for c in ("cam1", "cam2", "cam3")}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, {**videos, "cam3": videos["cam1"]}, "--out", out)
    line = _one_line(err)
    assert rc == 2 and f"{videos['cam1']}: given for both --video cam1 and --video cam3" in line, line
    link = tmp_path / "link.avi"
    link.symlink_to(videos["cam2"])
    rc, _, err = _run(capsys, calib, {**videos, "cam3": link}, "--out", out)
    assert rc == 2 and "given for both --video cam2 and --video cam3" in _one_line(err)
    folders = {c: _write_folder(tmp_path / c, range(6)) for c in ("cam1", "cam2")}
    rc, _, err = _run(capsys, calib, {**folders, "cam3": folders["cam2"]}, "--out", out)
    assert rc == 2 and "two cameras cannot record the same folder" in _one_line(err)
    rc, _, err = _run(capsys, calib, videos, "--out", out, "--background", f"cam1={videos['cam1']}",
                      f"cam2={videos['cam1']}", f"cam3={videos['cam3']}")
    assert rc == 2 and "given for both --video cam1 and --background cam2" in _one_line(err)
    assert not out.exists()


def test_units_of_a_calibration_that_does_not_say(tmp_path, capsys):
    studio = circle_studio(3, W, H, overhead=False)
    doc = studio_to_json(studio)
    del doc["units"]
    for cam in doc["cameras"]:
        cam["t"] = [1000 * v for v in cam["t"]]
    calib = tmp_path / "calib_mm.json"
    calib.write_text(json.dumps(doc))
    videos = {c: _write_video(tmp_path / f"{c}.avi", range(4)) for c in ("cam1", "cam2", "cam3")}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, calib, videos, "--out", out)
    assert rc == 2 and "--units mm" in _one_line(err) and not out.exists()
    rc, _, err = _run(capsys, calib, videos, "--out", out, "--units", "mm")
    assert rc == 0, err
    imported = load_calibration(out / "calibration.json")
    assert np.allclose([c.t for c in imported], [c.t for c in studio])


@pytest.fixture
def real_calib(tmp_path) -> Path:
    xml = tmp_path / "xml"
    xml.mkdir()
    for k in range(1, 5):
        shutil.copy(REAL_TAKE / f"cam{k}" / "config.xml", xml / f"cam{k}.xml")
    calib = tmp_path / "calibration.json"
    save_calibration(load_calibration(xml, units="mm", size=(644, 486)), calib)
    return calib


@pytest.mark.skipif(not REAL_TAKE.is_dir(), reason="the real 4-camera take is not in ../shared")
def test_real_take_with_a_damaged_stretch(tmp_path, real_calib, capsys):
    """The take's Xvid AVIs have two packets per frame (50 per second, at 25 fps); a damaged
    stretch of cam3 loses 9 frames (90..98), read in file order without a gap in their count. Read
    by the index, each frame keeps its number: those before the stretch and after the next key
    frame are the undamaged file's, those between (decoded from a damaged reference) nearest to it
    at their own number; the lost ones are said, or left out with --missing-frames skip."""
    damaged = tmp_path / "cam3.avi"
    shutil.copy(REAL_TAKE / "cam3" / "video.avi", damaged)
    damaged.chmod(0o644)
    data = bytearray(damaged.read_bytes())
    data[300_000:320_000] = b"\xff" * 20_000  # the decoder drops about 9 frames here
    damaged.write_bytes(bytes(data))
    videos = {f"cam{k}": REAL_TAKE / f"cam{k}" / "video.avi" for k in range(1, 5)}
    out = tmp_path / "seq"
    rc, _, err = _run(capsys, real_calib, {**videos, "cam3": damaged}, "--out", out, "--step", "10")
    line = _one_line(err)
    assert rc == 2 and f"{damaged}: --video cam3: frame 90 is lost" in line, line  # 90..98: 91..98 are off --step
    rc, _, err = _run(capsys, real_calib, {**videos, "cam3": damaged}, "--out", out, "--step", "10",
                      "--missing-frames", "skip")
    assert rc == 0 and "frame numbers 90 (cam3 lacks 90)" in err, err
    seq = load_sequence(out)
    assert seq.frames == [f for f in range(0, 211, 10) if f != 90]
    near = {g for f in seq.frames for g in (f - 1, f, f + 1)}
    undamaged = {k: {i: np.asarray(im) for i, im in enumerate(imageio.get_reader(videos[f"cam{k}"], "ffmpeg"))
                     if i in near} for k in (1, 3)}
    for f in seq.frames:
        images = seq.images(f)
        assert np.array_equal(images[0], undamaged[1][f]), f  # an undamaged camera: as decoded frame by frame
        if f < 89 or f > 150:
            assert np.array_equal(images[2], undamaged[3][f]), f
        else:
            error = {d: np.abs(images[2].astype(int) - undamaged[3][f + d]).mean() for d in (-1, 0, 1)}
            assert min(error, key=error.get) == 0, (f, error)


@pytest.mark.skipif(not REAL_TAKE.is_dir(), reason="the real 4-camera take is not in ../shared")
def test_real_take_counts_frames_by_decoding(tmp_path, real_calib, capsys):
    """imageio's count_frames() says 426 for these AVIs; decoding gives 214 (cam4: 215)."""
    videos = {f"cam{k}": REAL_TAKE / f"cam{k}" / "video.avi" for k in range(1, 5)}
    out = tmp_path / "seq"
    rc, stdout, err = _run(capsys, real_calib, videos, "--out", out, "--step", "10")
    assert rc == 0, err
    assert "cam4 215" in _one_line(err)
    meta = json.loads((out / "sequence.json").read_text())
    assert meta["frames"] == list(range(0, 211, 10)) and meta["fps"] == pytest.approx(50.0)
    assert len(list((out / "images" / "cam4").iterdir())) == 22
    # Sequential decoding: no grey, half-decoded frames (a seek gives a flat grey picture).
    images = load_sequence(out).images(210)
    assert images.shape == (4, 486, 644, 3) and all(im.std() > 10 for im in images)


def test_folders_say_the_frame_rate_they_take_and_out_stays_outside_them(tmp_path, calib, capsys):
    """Image folders carry no frame rate: the one taken is said (exports play at it), and --fps
    sets it; an --out inside a source folder is refused (--overwrite would replace its frames)."""
    folders = {c: _write_folder(tmp_path / c, range(4)) for c in ("cam1", "cam2", "cam3")}
    rc, _, err = _run(capsys, calib, folders, "--out", tmp_path / "seq")
    assert rc == 0 and "30 fps taken (--fps sets it" in _one_line(err)
    assert load_sequence(tmp_path / "seq").fps == pytest.approx(30.0)
    rc, _, err = _run(capsys, calib, folders, "--out", tmp_path / "seq2", "--fps", "50")
    assert rc == 0 and err == "" and load_sequence(tmp_path / "seq2").fps == pytest.approx(50.0)
    before = sorted(p.name for p in folders["cam2"].iterdir())
    rc, _, err = _run(capsys, calib, folders, "--out", folders["cam2"] / "seq")
    assert rc == 2 and "inside --video cam2's folder" in _one_line(err)
    assert sorted(p.name for p in folders["cam2"].iterdir()) == before
