"""The virtual studio, `mocap synth`: complete sequences, truth inside the silhouettes,
determinism, Cheung noise rates, bad input."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from common.body import JOINT_NAMES, PARAM_COUNT
from common.sequence import load_sequence
from common.synth import BLOB_RADIUS_PX, BLOBS_PER_IMAGE, CHEUNG_ETA, CHEUNG_XI, add_cheung_noise
from server.cli import main

from conftest import SHARED_MOCAP, WALK_CLIP

SHARED_120_FPS = SHARED_MOCAP / "cmu_jalderson" / "02_01.bvh"  # Frame Time: 0.008333 (120.0048 fps)

SYNTH_SECONDS_60 = 30.0   # the bound for 60 frames, 8 cameras, 320x240 (measured ~13 s here)
JOINT_DILATION_PX = 2
JOINTS_INSIDE = 0.95      # measured: 100% of joints inside on the walk, 8 cameras, 5 frames
ETA_TOL = 0.004           # ~5 sigma at ~80,000 foreground pixels
XI_TOL = 0.0015           # blobs add ~0.0009 of the background on top of xi


def synth(tmp_path: Path, name: str, *args: str) -> tuple[int, Path]:
    out = tmp_path / name
    rc = main(["synth", "--clip", str(WALK_CLIP), "--out", str(out), "--quiet", *args])
    return rc, out


def assert_complete(out: Path, frames: int, cameras: int, size: tuple[int, int]) -> None:
    from PIL import Image

    assert (out / "calibration.json").is_file()
    calib = load_sequence(out)
    assert len(calib.studio) == cameras
    assert calib.frames == list(range(frames))
    cam_dirs = sorted(p.name for p in (out / "silhouettes").iterdir())
    assert cam_dirs == sorted(calib.studio.names)
    for cam in calib.studio:
        pngs = sorted((out / "silhouettes" / cam.name).glob("*.png"))
        assert [p.name for p in pngs] == [f"{i:06d}.png" for i in range(frames)]
        with Image.open(pngs[0]) as im:
            assert im.size == size
        mask = np.asarray(Image.open(pngs[-1]).convert("L"))
        assert set(np.unique(mask)) <= {0, 255}
    lines = (out / "truth.jsonl").read_text().splitlines()
    assert len(lines) == frames
    for i, line in enumerate(lines):
        doc = json.loads(line)
        assert doc["frame"] == i
        assert len(doc["params"]) == PARAM_COUNT and np.isfinite(doc["params"]).all()
        assert sorted(doc["joints"]) == sorted(JOINT_NAMES)
        assert all(len(v) == 3 and np.isfinite(v).all() for v in doc["joints"].values())


@pytest.fixture(scope="module")
def walk8(tmp_path_factory):
    """mocap synth defaults (8 cameras, 320x240), 5 frames, clean and with Cheung noise (seed 7)."""
    base = tmp_path_factory.mktemp("walk8")
    rc_clean, clean = synth(base, "clean", "--frames", "5", "--step", "4", "--seed", "7")
    rc_noisy, noisy = synth(base, "noisy", "--frames", "5", "--step", "4", "--seed", "7", "--noise", "cheung")
    assert rc_clean == 0 and rc_noisy == 0
    return clean, noisy


def test_synth_writes_a_complete_sequence(walk8):
    clean, _ = walk8
    assert_complete(clean, frames=5, cameras=8, size=(320, 240))
    meta = json.loads((clean / "sequence.json").read_text())
    assert meta["source_frames"] == [1, 5, 9, 13, 17]  # --start 1 --step 4
    assert meta["fps"] == 30.0                        # 120 fps / 4 (Frame Time .0083333: 30.00012)


@pytest.mark.slow
def test_synth_60_frames_under_30_seconds(tmp_path):
    t0 = time.perf_counter()
    rc, out = synth(tmp_path, "seq", "--frames", "60", "--step", "4")
    seconds = time.perf_counter() - t0
    assert rc == 0
    assert_complete(out, frames=60, cameras=8, size=(320, 240))
    assert seconds < SYNTH_SECONDS_60, f"{seconds:.1f} s"


@pytest.mark.timeout(120)
@pytest.mark.skipif(not SHARED_120_FPS.is_file(), reason="needs the shared mocap clips")
def test_a_120_fps_clip_every_4th_frame_is_30_fps_exactly(tmp_path):
    """The file rounds 1/120 s to 0.008333; the sequence says the rate it was recorded at over 4."""
    assert "Frame Time: 0.008333\n" in SHARED_120_FPS.read_text()
    out = tmp_path / "seq"
    assert main(["synth", "--clip", str(SHARED_120_FPS), "--out", str(out), "--frames", "2", "--step", "4",
                 "--cameras", "2", "--size", "80x60", "--quiet"]) == 0
    assert json.loads((out / "sequence.json").read_text())["fps"] == 30.0
    assert load_sequence(out).fps == 30.0


@pytest.mark.timeout(120)
def test_synth_says_what_it_wrote_in_words_and_as_json_when_asked(tmp_path, capsys):
    out = tmp_path / "seq"
    argv = ["synth", "--clip", str(WALK_CLIP), "--out", str(out), "--frames", "2", "--cameras", "2",
            "--size", "80x60"]
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"wrote {out}: 2 frames at 30 fps from 2 cameras (skinned surface, no noise; truth.jsonl "
                     f"holds the true poses)", f"next: mocap fit {out} --out RESULT"]
    assert main([*argv, "--overwrite", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"out": str(out), "frames": 2, "fps": 30.0, "cameras": 2,
                                                   "noise": "none", "surface": "skinned"}


def test_truth_joints_fall_inside_the_silhouettes(walk8):
    clean, _ = walk8
    seq = load_sequence(clean)
    truth = seq.truth()

    def inside_fraction(offset) -> float:
        hits = []
        for f in seq.frames:
            masks = seq.silhouettes(f)
            joints = np.array([truth[f].joints[n] for n in JOINT_NAMES]) + offset
            for cam, mask in zip(seq.studio, masks):
                grown = binary_dilation(mask, iterations=JOINT_DILATION_PX)
                uv = np.round(cam.project(joints)).astype(int)
                ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
                hit = np.zeros(len(joints), dtype=bool)
                hit[ok] = grown[uv[ok, 1], uv[ok, 0]]
                hits.append(hit)
        return float(np.mean(hits))

    assert inside_fraction(np.zeros(3)) >= JOINTS_INSIDE
    # the check can fail: the same joints 40 cm to the side mostly miss the silhouettes
    assert inside_fraction(np.array([0.4, 0.0, 0.0])) < 0.5


def test_same_seed_gives_identical_files(tmp_path):
    args = ("--frames", "2", "--cameras", "3", "--size", "80x60", "--noise", "cheung", "--seed", "5")
    rc_a, a = synth(tmp_path, "a", *args)
    rc_b, b = synth(tmp_path, "b", *args)
    assert rc_a == rc_b == 0
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) == 2 + 3 * 2 + 1  # calibration, sequence, 6 PNGs, truth
    for rel in files_a:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


def test_different_seed_gives_different_noise(tmp_path):
    common = ("--frames", "2", "--cameras", "3", "--size", "80x60", "--noise", "cheung")
    _, a = synth(tmp_path, "a", *common, "--seed", "1")
    _, b = synth(tmp_path, "b", *common, "--seed", "2")
    sa, sb = load_sequence(a), load_sequence(b)
    for f in sa.frames:
        assert not np.array_equal(sa.silhouettes(f), sb.silhouettes(f))
    # the motion is the same; only the noise differs
    assert (a / "truth.jsonl").read_text() == (b / "truth.jsonl").read_text()


def written_masks(out: Path, frame: int) -> np.ndarray:
    """(K, H, W) bool: the mask files as synth wrote them (a loaded sequence cleans its masks)."""
    from PIL import Image

    cams = json.loads((out / "sequence.json").read_text())["cameras"]
    return np.stack([np.asarray(Image.open(out / "silhouettes" / c / f"{frame:06d}.png")) > 0 for c in cams])


def test_cheung_noise_rates_match_the_paper(walk8):
    clean, noisy = walk8
    missed = fg = false = bg = 0
    for f in load_sequence(clean).frames:
        c, n = written_masks(clean, f), written_masks(noisy, f)
        missed += np.count_nonzero(c & ~n)
        fg += np.count_nonzero(c)
        false += np.count_nonzero(~c & n)
        bg += np.count_nonzero(~c)
    eta, xi = missed / fg, false / bg
    assert fg > 50_000  # enough pixels for the tolerance
    assert abs(eta - CHEUNG_ETA) < ETA_TOL, eta
    blob_excess = BLOBS_PER_IMAGE * np.pi * BLOB_RADIUS_PX[1] ** 2 / (320 * 240)  # at most
    assert CHEUNG_XI - XI_TOL < xi < CHEUNG_XI + blob_excess + XI_TOL, xi


def test_add_cheung_noise_rates_on_a_plain_mask():
    rng = np.random.default_rng(0)
    mask = np.zeros((400, 400), dtype=bool)
    mask[100:300, 100:300] = True
    noisy = add_cheung_noise(mask, rng)
    eta = np.count_nonzero(mask & ~noisy) / mask.sum()
    xi = np.count_nonzero(~mask & noisy) / (~mask).sum()
    assert abs(eta - CHEUNG_ETA) < 0.003
    assert abs(xi - CHEUNG_XI) < 0.002
    np.testing.assert_array_equal(add_cheung_noise(mask, np.random.default_rng(3)),
                                  add_cheung_noise(mask, np.random.default_rng(3)))


# ------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("args, needle", [
    (["--clip", "{tmp}/no_such_clip.bvh"], "no_such_clip.bvh: missing"),
    (["--clip", "{tmp}/garbage.bvh"], "garbage.bvh"),
    (["--size", "abc"], "--size"),
    (["--size", "8x8"], "--size: 8x8"),
    (["--size", "320x240x3"], "--size"),
    (["--frames", "0"], "--frames"),
    (["--step", "0"], "--step"),
    (["--cameras", "0"], "--cameras"),
], ids=["missing-clip", "garbage-clip", "size-text", "size-small", "size-3d", "frames-0", "step-0", "cameras-0"])
def test_bad_input_exits_2_naming_the_problem(tmp_path, capsys, args, needle):
    (tmp_path / "garbage.bvh").write_text("this is not a BVH file\n")
    argv = ["synth", "--out", str(tmp_path / "out"), "--quiet"]
    if "--clip" not in args:
        argv += ["--clip", str(WALK_CLIP)]
    argv += [a.format(tmp=tmp_path) for a in args]
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1, err
    assert err.startswith("mocap synth: error:")
    assert needle in err, err
    assert not (tmp_path / "out" / "truth.jsonl").exists()
