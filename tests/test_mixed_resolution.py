"""Cameras of different image sizes in one studio: the padded (K, H, W) silhouette stack
(camera k's pixels at [:h_k, :w_k], False beyond) through packing and the wire, FrameData,
the cpu and gl energies (whole images, half resolution, windows), undistortion, SPOT voxels,
overlays and `mocap synth --sizes`. A camera counts the same in a mixed studio as alone."""
from __future__ import annotations

from dataclasses import replace

import msgpack
import numpy as np
import pytest
from PIL import Image

from common.body import CHAINS, JOINT_NAMES, forward_kinematics
from common.camera import Studio
from common.energy import ARM_WINDOW, SMALL_WINDOW, CpuEnergy, EnergySetup, Window
from common.errors import UserError
from common.export import FittedMotion
from common.fitting import FitOptions, FrameData
from common.search import fit_frame
from common.motion_import import import_bvh
from common.packing import (clear_padding, downsample_masks, inside_images, pack_planes, packbits_masks, pad_stack,
                            padded_shape, unpack_planes, unpackbits_masks)
from common.protocol import CameraSpec, Frame, ProtocolError, decode, encode
from common.synth import synth_studio
from common.voxels import SpotGrid, actor_bounds, silhouette_centre
from server.cli import main

from conftest import WALK_CLIP

SIZES = ((320, 240), (400, 300), (480, 360))  # width, height per camera
PADDED = (360, 480)                           # the stack's (H, W)
WALK_FRAME = 41                               # a mid-stride source frame of the bundled walk
# Measured (3 cameras, ellipsoid silhouettes, the start 74 mm off): mean joint error 11.8 mm
# all at 320x240, 10.1 mm mixed, 11.3 mm all at 480x360.
FIT_SLACK = 1.2, 2.0                          # mixed error <= 1.2 x same-size error + 2 mm


@pytest.fixture(scope="module")
def studio() -> Studio:
    return synth_studio(3, SIZES)


@pytest.fixture(scope="module")
def pose(model) -> np.ndarray:
    p = import_bvh(model, WALK_CLIP, [WALK_FRAME]).params[0].copy()
    p[:2] = 0.0  # the studio looks at the origin
    return p


def own_images(model, studio, params) -> list[np.ndarray]:
    """Per camera (h_k, w_k) bool ellipsoid silhouettes, each camera rendered alone."""
    out = []
    for cam in studio:
        setup = whole_setup(Studio((cam,)), np.zeros((1, cam.height, cam.width), bool), params)
        out.append(CpuEnergy(model, setup).render(params)[0])
    return out


def whole_setup(studio, masks, params) -> EnergySetup:
    windows = tuple(Window(0, 0, c.width, c.height) for c in studio)
    return EnergySetup(studio, windows, masks, tuple(range(16)), np.asarray(params), prerender=False)


def with_garbage_padding(masks: np.ndarray, sizes) -> np.ndarray:
    """The stack with every pixel beyond each camera's image set: nothing may count them."""
    return masks | ~inside_images(sizes, masks.shape[1:])


def single(studio, k: int) -> Studio:
    return Studio((studio[k],))


def shifted(params: np.ndarray, dx: float, dy: float) -> np.ndarray:
    p = params.copy()
    p[0] += dx
    p[1] += dy
    return p


@pytest.fixture(scope="module")
def masks(model, studio, pose) -> np.ndarray:
    return pad_stack(own_images(model, studio, pose))


@pytest.fixture(scope="module")
def candidates(model, studio, pose) -> np.ndarray:
    """(B, 35) poses, some of them across camera 1's image edges, into the stack's padding."""
    cands = np.array([pose, shifted(pose, 0.1, -0.05)] + [shifted(pose, 0.0, dy) for dy in (1.2, 1.6, 2.0)]
                     + [shifted(pose, dx, 0.0) for dx in (-1.4, 1.3)])
    cam = studio[0]
    big = Window(0, 0, PADDED[1], PADDED[0])  # camera 1 with an image as large as the stack
    seen_in_padding = 0
    for p in cands:
        setup = EnergySetup(single(studio, 0), (big,), np.zeros((1,) + PADDED, bool), tuple(range(16)), p, False)
        r = CpuEnergy(model, setup).render(p)[0]
        seen_in_padding += r[cam.height:].any() or r[:, cam.width:].any()
    assert seen_in_padding >= 2  # the test does exercise the padding
    return cands


# --------------------------------------------------------------------------- packing and wire

def test_padded_stack_helpers(studio):
    assert studio.sizes == list(SIZES) and studio.padded_shape == PADDED
    a, b = np.ones((2, 3), bool), np.ones((4, 1), bool)
    stack = pad_stack([a, b])
    assert stack.shape == (2, 4, 3) and padded_shape([(3, 2), (1, 4)]) == (4, 3)
    np.testing.assert_array_equal(stack, inside_images([(3, 2), (1, 4)], (4, 3)))
    assert stack.sum() == 6 + 4
    np.testing.assert_array_equal(pad_stack([a, a]), np.ones((2, 2, 3), bool))  # one size: the plain stack
    with pytest.raises(ValueError):
        pad_stack([np.ones(3, bool)])
    # images keep their channels; zeros beyond
    images = pad_stack([np.full((2, 3, 3), 7, np.uint8), np.full((4, 1, 3), 9, np.uint8)], dtype=np.uint8)
    assert images.shape == (2, 4, 3, 3) and images.dtype == np.uint8
    assert (images[0, :2] == 7).all() and (images[1, :, :1] == 9).all() and images.sum() == 7 * 18 + 9 * 12
    with pytest.raises(ValueError):
        pad_stack([np.ones((2, 3, 3)), np.ones((2, 3))])
    # clear_padding clears beyond each camera; one size: the input itself
    full = np.ones((2, 4, 3), bool)
    np.testing.assert_array_equal(clear_padding(full, [(3, 2), (1, 4)]), stack)
    assert clear_padding(full, [(3, 4), (3, 4)]) is full


def test_packing_round_trips_the_padded_stack(masks):
    K, H, W = masks.shape
    np.testing.assert_array_equal(unpackbits_masks(packbits_masks(masks), K, H, W), masks)
    np.testing.assert_array_equal(unpack_planes(pack_planes(masks), K), masks)
    # camera k's half-resolution pixels are those of its own image downsampled
    half = downsample_masks(masks)
    for k, (w, h) in enumerate(SIZES):
        np.testing.assert_array_equal(half[k, :h // 2, :w // 2], downsample_masks(masks[k, :h, :w]))


def test_frame_message_of_a_mixed_studio(studio, masks):
    cams = tuple(CameraSpec.from_camera(c) for c in studio)
    garbage = with_garbage_padding(masks, SIZES)
    msg = Frame(session="s1", frame=3, cameras=cams, silhouettes=packbits_masks(garbage),
                previous_params=[0.0] * 35, body_scale=1.0, body_fingerprint="0123456789abcdef")
    assert (msg.H, msg.W) == PADDED and msg.sizes == SIZES
    back = decode(encode(msg))
    np.testing.assert_array_equal(back.masks(), masks)  # the padding's bits are cleared
    assert [(c.width, c.height) for c in back.studio()] == list(SIZES)
    header = msgpack.unpackb(encode(msg)[0])
    for H, W in ((240, 480), (360, 400)):  # not the cameras' largest height and width
        header.update(H=H, W=W)
        with pytest.raises(ProtocolError) as err:
            decode([msgpack.packb(header), packbits_masks(np.zeros((3, H, W), bool))])
        assert err.value.reason == "bad_field"


# ------------------------------------------------------------------------------- frame data

def test_frame_data_takes_the_padded_stack_and_clears_the_padding(model, studio, masks):
    frame = FrameData(model, studio, with_garbage_padding(masks, SIZES))
    np.testing.assert_array_equal(frame.masks, masks)
    assert frame.half_masks.shape == (3, 180, 240)
    for k, (w, h) in enumerate(SIZES):
        alone = FrameData(model, single(studio, k), masks[k:k + 1, :h, :w])
        np.testing.assert_array_equal(frame.half_masks[k, :h // 2, :w // 2], alone.half_masks[0])
        assert not frame.half_masks[k, h // 2:].any() and not frame.half_masks[k, :, w // 2:].any()
    with pytest.raises(ValueError, match="480x360"):
        FrameData(model, studio, masks[:, :300, :400])
    same = synth_studio(3, SIZES[:1])
    plain = masks[:, :240, :320]
    assert FrameData(model, same, plain).masks.shape == (3, 240, 320)


def test_undistortion_is_per_camera(model, studio, masks):
    cams = list(studio)
    cams[1] = replace(cams[1], dist=np.array([0.08, -0.02, 0.001, 0.0, 0.0]))
    distorted = Studio(tuple(cams))
    frame = FrameData(model, distorted, masks)
    assert not any(c.has_distortion for c in frame.studio)
    for k, (w, h) in enumerate(SIZES):
        alone = FrameData(model, single(distorted, k), masks[k:k + 1, :h, :w])
        np.testing.assert_array_equal(frame.masks[k, :h, :w], alone.masks[0])
        assert not frame.masks[k, h:].any() and not frame.masks[k, :, w:].any()
    assert np.count_nonzero(frame.masks[1] ^ masks[1]) > 0  # it did resample camera 2


# ----------------------------------------------------------------------------------- energies

@pytest.mark.parametrize("half", [False, True])
def test_whole_image_energy_is_the_sum_of_the_cameras_alone(model, studio, masks, candidates, half):
    frame = FrameData(model, studio, with_garbage_padding(masks, SIZES))
    mixed = frame.whole_image_energy(half)(candidates)
    weights = frame.camera_weights  # (energy.camera_weights: 480x360 is not sharp enough to count less)
    alone = sum(weights[k] * FrameData(model, single(studio, k), masks[k:k + 1, :h, :w])
                .whole_image_energy(half)(candidates) for k, (w, h) in enumerate(SIZES))
    np.testing.assert_array_equal(mixed, alone)
    if not half:
        assert mixed[0] == 0  # the pose that drew the silhouettes
    rendered = frame.whole_image_energy(half).render(candidates[2])
    sizes = (frame.half_studio if half else frame.studio).sizes
    assert not (rendered & ~inside_images(sizes, rendered.shape[1:])).any()


@pytest.mark.parametrize("chain, size, prerender", [
    ("left_arm", ARM_WINDOW, True), ("right_leg", ARM_WINDOW, False), ("head", SMALL_WINDOW, True)])
def test_window_energies_are_the_sum_of_the_cameras_alone(model, studio, masks, candidates, chain, size,
                                                          prerender):
    frame = FrameData(model, studio, with_garbage_padding(masks, SIZES))
    segments = CHAINS[chain].segments
    for start in candidates[[1, 3, 5]]:
        mixed = CpuEnergy(model, frame.window_setup(start, segments, size, prerender))
        parts = [CpuEnergy(model, FrameData(model, single(studio, k), masks[k:k + 1, :h, :w])
                           .window_setup(start, segments, size, prerender)) for k, (w, h) in enumerate(SIZES)]
        batch = candidates + np.linspace(-0.05, 0.05, len(candidates))[:, None] * (np.arange(35) >= 3)
        np.testing.assert_array_equal(mixed(batch), sum(w * e(batch) for w, e in zip(frame.camera_weights, parts)))


def test_energy_refuses_input_windows_that_do_not_fit(model, studio, pose):
    windows = tuple(Window(0, 0, c.width, c.height) for c in studio)
    with pytest.raises(ValueError, match="largest"):
        CpuEnergy(model, EnergySetup(studio, windows, np.zeros((3, 240, 320), bool), (4,), pose))
    with pytest.raises(ValueError, match="windows"):
        CpuEnergy(model, EnergySetup(studio, windows[:2], np.zeros((3,) + PADDED, bool), (4,), pose))


def test_gl_energy_counts_each_camera_as_alone(model, studio, masks, candidates):
    from common.energy_gl import GlEnergy
    from common.render_gl import gl_context

    try:
        ctx = gl_context()
    except UserError as exc:
        pytest.skip(f"no headless OpenGL: {exc}")
    garbage = with_garbage_padding(masks, SIZES)
    weights = np.array([1.0, 0.75, 0.5])  # each camera's pixels' worth, as the cpu energy weighs them
    setup = replace(whole_setup(studio, garbage, candidates[0]), weights=weights)
    mixed = GlEnergy(model, setup, surface="ellipsoid")
    parts = [GlEnergy(model, whole_setup(single(studio, k), masks[k:k + 1, :h, :w], candidates[0]),
                      surface="ellipsoid") for k, (w, h) in enumerate(SIZES)]
    e_mixed, e_alone = mixed(candidates), sum(w * e(candidates) for w, e in zip(weights, parts))
    silhouette = masks.sum()
    assert np.max(np.abs(e_mixed - e_alone)) <= 0.002 * silhouette, (e_mixed, e_alone)
    cpu = CpuEnergy(model, setup)(candidates)
    assert np.max(np.abs(e_mixed - cpu)) <= 0.01 * silhouette, (e_mixed, cpu)
    rendered = mixed.render(candidates[2])
    assert not (rendered & ~inside_images(SIZES, PADDED)).any()
    assert ctx.error == "GL_NO_ERROR"
    for e in [mixed, *parts]:
        e.release()


def test_a_short_fit_recovers_the_pose_as_a_same_size_studio_does(model, pose):
    rng = np.random.default_rng(0)
    start = shifted(pose, 0.04, -0.03)
    start[3:] += rng.normal(0.0, 0.08, len(start) - 3)
    options = FitOptions(turn_hypotheses=0, redetect_limbs=False)
    truth = forward_kinematics(model, pose).joints[0]
    errors = {}
    for name, sizes in (("same", SIZES[:1]), ("mixed", SIZES)):
        studio = synth_studio(3, sizes)
        frame = FrameData(model, studio, pad_stack(own_images(model, studio, pose)))
        result = fit_frame(model, frame, start, options)
        errors[name] = np.linalg.norm(forward_kinematics(model, result.params).joints[0] - truth, axis=1).mean()
    start_error = np.linalg.norm(forward_kinematics(model, start).joints[0] - truth, axis=1).mean()
    assert errors["mixed"] < start_error / 3
    assert errors["mixed"] <= FIT_SLACK[0] * errors["same"] + FIT_SLACK[1] / 1000.0, errors


# ------------------------------------------------------------------------------------ voxels

def test_voxels_are_those_of_the_cameras_own_images(studio, masks):
    bounds = actor_bounds(studio, masks)
    grid = SpotGrid.build(studio, grid=32, bounds=bounds)
    assert grid.image_shape == PADDED
    garbage = with_garbage_padding(masks, SIZES)
    result = grid.reconstruct(garbage)
    counts = grid.sample_counts(garbage)
    np.testing.assert_array_equal(result.occupied, (counts >= grid.threshold).all(axis=0))
    np.testing.assert_array_equal(result.occupied, grid.reconstruct(masks).occupied)
    assert result.occupied.sum() > 100
    pixels = grid.sample_pixels()
    seen = (pixels >= 0).all(axis=(0, 1))  # every sample of the voxel inside every camera's image
    for k, (w, h) in enumerate(SIZES):
        alone = SpotGrid.build(single(studio, k), grid=32, bounds=bounds)
        mine = alone.sample_pixels()[0]
        y, x = np.divmod(pixels[k], PADDED[1])
        assert np.all((x[:, seen] < w) & (y[:, seen] < h))
        np.testing.assert_array_equal(y[:, seen] * w + x[:, seen], mine[:, seen])  # the same pixels
        np.testing.assert_array_equal(counts[k][seen], alone.sample_counts(masks[k:k + 1, :h, :w])[0][seen])


def test_actor_centre_ignores_the_padding(model, studio, masks, pose):
    centre = silhouette_centre(studio, masks)
    np.testing.assert_allclose(silhouette_centre(studio, with_garbage_padding(masks, SIZES)), centre)
    pelvis = forward_kinematics(model, pose).joints[0, JOINT_NAMES.index("pelvis")]
    assert np.linalg.norm(centre[:2] - pelvis[:2]) < 0.15
    np.testing.assert_array_equal(actor_bounds(studio, with_garbage_padding(masks, SIZES)),
                                  actor_bounds(studio, masks))


# ---------------------------------------------------------------------------------- pictures

def test_overlays_of_a_mixed_studio(tmp_path, model, studio, masks, pose):
    from server.pictures import ModelPainter, ResultData, overlay_strip

    class PaddedSequence:  # what common.sequence gives for a mixed studio: the padded stack
        def __init__(self):
            self.studio = studio

        def silhouettes(self, frame):
            return with_garbage_padding(masks, SIZES)

    joints = forward_kinematics(model, pose).joints
    motion = FittedMotion(np.array([0]), 30.0, pose[None], joints, model)
    result = ResultData(tmp_path, [], {}, motion, PaddedSequence(), None)
    painter = ModelPainter(model)
    painter.gl = False  # the ellipsoids: the very silhouettes of the masks
    strip, xor = overlay_strip(result, painter, 0, [0, 1, 2])
    assert xor == {c.name: 0 for c in studio}
    assert strip.shape[0] == 360 + 16 and strip.shape[1] == sum(w for w, _ in SIZES) + 2 * 4


# ------------------------------------------------------------------------------------- synth

def test_synth_writes_a_mixed_resolution_studio(tmp_path):
    from common.calibration import load_calibration

    out = tmp_path / "mixed"
    rc = main(["synth", "--clip", str(WALK_CLIP), "--out", str(out), "--quiet", "--frames", "1", "--cameras", "3",
               "--sizes", "96x72,120x90", "--radius", "4", "--height", "2"])
    assert rc == 0
    cams = load_calibration(out / "calibration.json")
    assert [(c.width, c.height) for c in cams] == [(96, 72), (120, 90), (96, 72)]  # cycled
    for cam in cams:
        with Image.open(out / "silhouettes" / cam.name / "000000.png") as im:
            assert im.size == (cam.width, cam.height)
            assert np.asarray(im.convert("L")).any()
        np.testing.assert_allclose(np.hypot(*cam.center[:2]), 4.0, atol=1e-9)
        np.testing.assert_allclose(cam.center[2], 2.0, atol=1e-9)
    same = synth_studio(3, [(96, 72)], 4.0, 2.0)
    for a, b in zip(cams, same):  # sizes do not move the cameras
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.center, b.center, atol=1e-9)


@pytest.mark.parametrize("args, needle", [
    (["--sizes", "96x72,abc"], "--sizes"),
    (["--sizes", "96x72,8x8"], "--sizes: 8x8"),
    (["--sizes", "96x72,96x72,96x72,96x72"], "--sizes: 4 sizes for 3 cameras"),
    (["--radius", "0"], "--radius"),
    (["--radius", "nan"], "--radius"),
    (["--height", "-1"], "--height"),
])
def test_synth_refuses_bad_studio_flags(tmp_path, capsys, args, needle):
    rc = main(["synth", "--clip", str(WALK_CLIP), "--out", str(tmp_path / "x"), "--quiet", "--frames", "1",
               "--cameras", "3", *args])
    assert rc == 2
    assert needle in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
