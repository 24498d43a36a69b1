"""The whole chain from camera videos: synth --images -> video files -> import-video -> segment -> fit.

Fitting the segmented silhouettes must be about as accurate as fitting the true ones.
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from common.sequence import read_image
from server.cli import main as mocap

imageio = pytest.importorskip("imageio.v3")
pytest.importorskip("imageio_ffmpeg")

FRAMES = 4
SIZE = "320x240"
CAMERAS = 6
EXTRA_ERROR_MM = 8.0  # segmented silhouettes may cost this much mean accuracy over the true ones


def _encode(folder, path, fps=30):
    frames = [imageio.imread(p) for p in sorted(folder.glob("*.png"))]
    # near-lossless H.264 so that the test measures segmentation, not compression
    imageio.imwrite(path, np.stack(frames), fps=fps, codec="libx264", quality=10, macro_block_size=8)


@pytest.mark.slow  # whole first-frame searches: make test-slow
@pytest.mark.timeout(600)
def test_videos_to_poses(tmp_path):
    seq = tmp_path / "studio"
    assert mocap(["synth", "--out", str(seq), "--frames", str(FRAMES), "--images", "--cameras", str(CAMERAS),
                  "--size", SIZE, "--quiet"]) == 0
    cams = json.loads((seq / "sequence.json").read_text())["cameras"]
    videos, backgrounds = [], []
    for cam in cams:
        _encode(seq / "images" / cam, tmp_path / f"{cam}.mp4")
        _encode(seq / "background" / cam, tmp_path / f"{cam}_bg.mp4")
        videos.append(f"{cam}={tmp_path / f'{cam}.mp4'}")
        backgrounds.append(f"{cam}={tmp_path / f'{cam}_bg.mp4'}")
    imported = tmp_path / "imported"
    assert mocap(["import-video", "--calibration", str(seq / "calibration.json"), "--video", *videos,
                  "--background", *backgrounds, "--out", str(imported)]) == 0
    assert mocap(["segment", str(imported), "--method", "cheung"]) == 0
    shutil.copy(seq / "truth.jsonl", imported / "truth.jsonl")

    # segmentation quality against the exact masks
    for cam in cams[:2]:
        for f in range(FRAMES):
            truth = read_image(seq / "silhouettes_true" / cam / f"{f:06d}.png", "L") > 127
            seg = read_image(imported / "silhouettes" / cam / f"{f:06d}.png", "L") > 127
            eta = np.count_nonzero(truth & ~seg) / truth.sum()
            xi = np.count_nonzero(seg & ~truth) / (~truth).sum()
            assert eta < 0.08 and xi < 0.02, (cam, f, eta, xi)

    assert mocap(["fit", str(imported), "--out", str(tmp_path / "from_video"), "--quiet"]) == 0
    assert mocap(["fit", str(seq), "--out", str(tmp_path / "from_truth"), "--quiet"]) == 0
    video = json.loads((tmp_path / "from_video" / "summary.json").read_text())
    exact = json.loads((tmp_path / "from_truth" / "summary.json").read_text())
    assert video["frames"] == exact["frames"] == FRAMES
    assert video["mean_joint_error_mm"] < exact["mean_joint_error_mm"] + EXTRA_ERROR_MM, (video, exact)
