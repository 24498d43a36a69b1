"""Pictures of a result: overlays, 3D views, the GIF, plots; results opened with their sequence."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from common.body import P, forward_kinematics, joints_dict, load_body_model
from common.errors import UserError
from server.cli import main as cli_main
from server.pictures import (
    AGREE, BACKGROUND, EXTRA, MISSED, OUTLINE, TRUTH_COLOUR, ModelPainter, camera_indices, crop_box,
    default_cameras, default_frames, load_result, make_plots, make_result_pictures, orbit_camera,
    overlay_image, overlay_strip, worst_frame,
)

FRAMES = 4
BENT = 2           # the frame whose fitted left elbow is off by ELBOW_ERROR
ELBOW_ERROR = 0.9  # radians


def fake_result(folder: Path, sequence: Path, bent: int | None = BENT) -> Path:
    """A result folder whose 'fit' is the truth, except frame ``bent``'s left elbow."""
    model = load_body_model()
    folder.mkdir(parents=True, exist_ok=True)
    truth = [json.loads(line) for line in (sequence / "truth.jsonl").read_text().splitlines()]
    with open(folder / "poses.jsonl", "w") as fh:
        for i, t in enumerate(truth):
            params = np.array(t["params"])
            if i == bent:
                params[P["l_elbow"]] += ELBOW_ERROR
            joints = forward_kinematics(model, params).joints[0]
            chains = {c: {"evaluations": 100 + k, "energy_before": 900 - k, "energy": 800 - k, "cpu_seconds": 0.01 * k,
                          "wall_seconds": 0.01 * k} for k, c in enumerate(("torso", "left_arm", "right_arm", "head"))}
            fh.write(json.dumps({"frame": t["frame"], "params": params.tolist(), "joints": joints_dict(joints),
                                 "energy": 2000 + 100 * i, "seconds": 0.2, "iterations": 2, "evaluations": 400,
                                 "chains": chains}) + "\n")
    (folder / "summary.json").write_text(json.dumps({"sequence": str(sequence), "frames": len(truth), "mode": "single",
                                                     "clients": 0, "energy_backend": "cpu", "seconds_per_frame": 0.2}))
    return folder


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    seq = tmp_path_factory.mktemp("seq") / "walk"
    assert cli_main(["synth", "--out", str(seq), "--frames", str(FRAMES), "--size", "160x120", "--cameras", "5",
                     "--quiet"]) == 0
    return seq


@pytest.fixture(scope="module")
def result(tmp_path_factory, sequence):
    return load_result(fake_result(tmp_path_factory.mktemp("res") / "r", sequence))


def test_load_result_finds_sequence_truth_and_rate(result, sequence):
    assert result.sequence is not None and result.sequence.path == sequence
    assert result.motion.fps == pytest.approx(result.sequence.fps)
    err = result.joint_errors_mm()
    assert err.shape == (FRAMES, 17)
    assert np.abs(np.delete(err, BENT, axis=0)).max() < 1e-6  # the 'fit' is the truth there
    assert err[BENT].max() > 50.0                             # a wrist tens of cm off
    assert worst_frame(result) == BENT
    assert BENT in default_frames(result) and len(default_frames(result)) <= 4


def test_result_without_its_sequence_needs_a_rate(tmp_path, sequence):
    folder = fake_result(tmp_path / "r", sequence)
    (folder / "summary.json").write_text(json.dumps({"sequence": str(tmp_path / "moved")}))
    with pytest.raises(UserError, match="--fps"):
        load_result(folder)
    res = load_result(folder, fps=50.0)
    assert res.sequence is None and res.truth is None and res.motion.fps == 50.0
    assert load_result(folder, sequence_dir=sequence).truth is not None  # --sequence finds it again
    with pytest.raises(UserError, match="not a result folder"):
        load_result(tmp_path / "nothing", fps=30.0)


def test_overlay_colours():
    sil = np.zeros((20, 20), bool)
    sil[5:15, 5:15] = True
    model = np.zeros((20, 20), bool)
    model[5:15, 8:18] = True
    img = overlay_image(sil, model)
    assert tuple(img[0, 0]) == BACKGROUND
    assert tuple(img[10, 6]) == MISSED       # silhouette only
    assert tuple(img[10, 16]) == EXTRA       # model only
    assert tuple(img[10, 10]) == AGREE       # both
    assert tuple(img[5, 10]) == OUTLINE and tuple(img[10, 17]) == OUTLINE and tuple(img[10, 8]) == OUTLINE


def test_crop_box_keeps_the_actor_and_the_aspect():
    m = np.zeros((120, 160), bool)
    m[40:90, 70:85] = True
    x0, y0, x1, y1 = crop_box([m], 0.75)
    assert x0 <= 70 and x1 >= 85 and y0 <= 40 and y1 >= 90
    assert (x1 - x0) / (y1 - y0) == pytest.approx(0.75, abs=0.03)
    assert crop_box([np.zeros((120, 160), bool)], 0.75) == (0, 0, 160, 120)


def test_overlays_show_the_fit(result):
    painter = ModelPainter(result.motion.model)
    cams = camera_indices(result.sequence.studio, ["cam1", "cam3"])
    good_strip, good = overlay_strip(result, painter, 0, cams)
    bad_strip, bad = overlay_strip(result, painter, BENT, cams)
    assert good_strip.shape == (120 + 16, 2 * 160 + 4, 3)
    sil = result.sequence.silhouettes(0)
    for c, name in zip(cams, ("cam1", "cam3")):
        # the rigid mesh against the skinned surface's silhouette: close, not identical
        assert good[name] < 0.3 * sil[c].sum()
    assert sum(bad.values()) > sum(good.values()) + 50
    small, _ = overlay_strip(result, painter, 0, cams, height=60, crop=True)
    assert small.shape == (60 + 16, 2 * 80 + 4, 3)  # cropped tiles keep the cameras' 4:3


def test_cropped_tiles_are_shaped_like_their_camera():
    """A portrait camera's tile is portrait, a landscape one's landscape, the actor inside both."""
    for H, W in ((120, 160), (160, 90), (100, 100)):
        m = np.zeros((H, W), bool)
        m[H // 3:H // 3 + H // 3, W // 2 - 4:W // 2 + 4] = True  # a standing actor: tall and narrow
        x0, y0, x1, y1 = crop_box([m], W / H)
        assert (x1 - x0) / (y1 - y0) == pytest.approx(W / H, rel=0.05), (H, W)
        assert x0 <= W // 2 - 4 and x1 >= W // 2 + 4 and y0 <= H // 3 and y1 >= 2 * (H // 3)


def test_3d_view_from_any_side(result):
    painter = ModelPainter(result.motion.model)
    i = 1
    target = result.motion.joints[i, 0]
    for az, el in ((-90.0, 10.0), (90.0, 30.0), (-50.0, -5.0)):  # front, back, front-left from below
        cam = orbit_camera(target, az, el, size=(200, 160))
        img = painter.view(result.motion.params[i], cam, result.truth[i])
        assert img.shape == (160, 200, 3)
        r, g, b = (img[..., k].astype(int) for k in range(3))
        warm = np.count_nonzero(r > b + 60)   # left limbs
        cool = np.count_nonzero(b > r + 60)   # right limbs
        assert warm > 100 and cool > 100, (az, warm, cool)
        assert np.count_nonzero(np.all(img == TRUTH_COLOUR, axis=-1)) > 20  # the true skeleton
    front = orbit_camera(target, -90.0, 0.0)
    assert front.center[1] < target[1] - 3.0  # azimuth -90: in front of the actor (-y)


def test_ellipsoid_fallback_without_gl(result):
    mesh = ModelPainter(result.motion.model)
    ell = ModelPainter(result.motion.model)
    ell.gl = False  # as if no EGL context could be made
    cams = tuple(result.sequence.studio)[:2]
    for a, b in zip(mesh.silhouettes(result.motion.params[0], cams), ell.silhouettes(result.motion.params[0], cams)):
        iou = np.count_nonzero(a & b) / np.count_nonzero(a | b)
        assert iou > 0.6, iou
    img = ell.view(result.motion.params[0], orbit_camera(result.motion.joints[0, 0], -60.0, 10.0, (160, 160)))
    assert np.count_nonzero(np.any(img != BACKGROUND, axis=-1)) > 500


def test_plots(result, tmp_path, sequence):
    plots = make_plots(result)
    assert set(plots) == {"joint_error.png", "energy.png", "timing.png"}
    for name, png in plots.items():
        im = Image.open(__import__("io").BytesIO(png))
        assert im.format == "PNG" and im.size[0] >= 600 and im.size[1] >= 250
    folder = fake_result(tmp_path / "r", sequence)
    (folder / "summary.json").write_text("{}")
    assert set(make_plots(load_result(folder, fps=30.0))) == {"energy.png", "timing.png"}  # no truth


def test_make_result_pictures(result, sequence):
    paths = make_result_pictures(result.path, frames=[0, BENT], cameras=["cam2", "cam5"])
    names = {p.name for p in paths}
    assert {"joint_error.png", "energy.png", "timing.png", "overlay_000000.png", f"overlay_{BENT:06d}.png",
            "model_000000.png", f"model_{BENT:06d}.png", "sequence.gif", "sequence.mp4"} == names
    for p in paths:
        assert p.parent == result.path / "pictures" and p.stat().st_size > 0
    strip = Image.open(result.path / "pictures" / "overlay_000000.png")
    assert strip.size == (2 * 160 + 4, 120 + 16)
    gif = Image.open(result.path / "pictures" / "sequence.gif")
    assert gif.n_frames == FRAMES
    assert gif.info["duration"] == pytest.approx(1000.0 / result.motion.fps, abs=10)  # GIF: 10 ms steps
    # the video: every frame, at the take's rate, the GIF's pictures (H.264 pads to even sizes)
    import imageio.v2 as imageio

    with imageio.get_reader(result.path / "pictures" / "sequence.mp4", format="ffmpeg") as reader:
        assert reader.get_meta_data()["fps"] == pytest.approx(result.motion.rate, rel=1e-3)
        pictures = np.array([frame for frame in reader])
    assert len(pictures) == FRAMES
    gif.seek(0)
    first = np.asarray(gif.convert("RGB"))
    assert pictures.shape[1:] == (first.shape[0] + first.shape[0] % 2, first.shape[1] + first.shape[1] % 2, 3)
    assert np.abs(pictures[0, :first.shape[0], :first.shape[1]].astype(int) - first).mean() < 12  # lossy, alike


def test_bad_choices_are_user_errors(result):
    with pytest.raises(UserError, match="unknown camera"):
        camera_indices(result.sequence.studio, ["cam99"])
    with pytest.raises(UserError, match="was not fitted"):
        make_result_pictures(result.path, frames=[999], gif=False)
    assert default_cameras(result.sequence.studio) == ["cam1", "cam2", "cam4", "cam5"]
