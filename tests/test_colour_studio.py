"""The colour studio: room backgrounds, rasterising, cast shadows, compositing, palette."""
from __future__ import annotations

import numpy as np
import pytest

from common import colour_studio as cs
from common.body import SEGMENT_NAMES
from common.camera import circle_studio, look_at

W, H = 160, 120


@pytest.fixture(scope="module")
def studio():
    return circle_studio(5, W, H)


def _disc_triangles(centre, radius, camera, n=64):
    """A floor disc as a triangle fan, projected: (n, 3, 2) pixels."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = np.stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), np.zeros(n)], 1)
    pts = np.vstack([[centre[0], centre[1], 0.0], rim])
    faces = np.stack([np.zeros(n, int), 1 + np.arange(n), 1 + (np.arange(n) + 1) % n], 1)
    return camera.project(pts)[faces]


def test_rasterise_square_covers_its_pixel_centres():
    square = np.array([[[10.5, 20.5], [30.5, 20.5], [30.5, 40.5]],
                       [[10.5, 20.5], [30.5, 40.5], [10.5, 40.5]]])
    mask = cs.rasterise_mask(square, 64, 64)
    assert mask.sum() == 20 * 20
    assert mask[21:41, 11:31].all()
    # Winding does not matter; triangles off the image are clipped.
    assert cs.rasterise_mask(square[:, ::-1], 64, 64).sum() == 400
    assert not cs.rasterise_mask(square + 200.0, 64, 64).any()


def test_rasterise_labels_nearest_triangle_wins():
    tri = np.array([[[0, 0], [40, 0], [0, 40]], [[5, 5], [45, 5], [5, 45]]], dtype=float)
    labels = cs.rasterise_labels(tri, np.array([[2.0] * 3, [1.0] * 3]), np.array([7, 9]), 50, 50)
    assert labels[10, 10] == 9  # both cover it, the second is nearer
    assert labels[1, 1] == 7 and labels[40, 5] == 9 and labels[49, 49] == -1
    labels = cs.rasterise_labels(tri, np.array([[1.0] * 3, [2.0] * 3]), np.array([7, 9]), 50, 50)
    assert labels[10, 10] == 7


def test_background_floor_lines_up_in_every_view(studio):
    """Floor tiles differ in brightness; every camera sees the same tile brighter."""
    tile = cs.FLOOR_TILE
    i, j = np.meshgrid(np.arange(-4, 4), np.arange(-4, 4))
    a = np.c_[(i.ravel() + 0.5) * tile, (j.ravel() + 0.5) * tile, np.zeros(i.size)]
    b = a + [tile, 0.0, 0.0]
    contrast = cs._hash01(i.ravel() + 1, j.ravel()) - cs._hash01(i.ravel(), j.ravel())
    strong = np.abs(contrast) > 0.5  # tile brightness differs by more than 7 %
    a, b, sign = a[strong], b[strong], np.sign(contrast[strong])
    for k, cam in enumerate(studio):
        bg = cs.make_background(cam, np.random.default_rng(k)).astype(float).sum(-1)
        pa, pb = np.rint(cam.project(a)).astype(int), np.rint(cam.project(b)).astype(int)
        inside = ((pa >= 0) & (pa < [W, H])).all(1) & ((pb >= 0) & (pb < [W, H])).all(1)
        assert inside.sum() >= 5, cam.name
        seen = np.sign(bg[pb[inside, 1], pb[inside, 0]] - bg[pa[inside, 1], pa[inside, 0]])
        assert (seen == sign[inside]).mean() > 0.85, cam.name


def test_background_is_deterministic_and_has_floor_and_walls(studio):
    cam = studio[0]
    a = cs.make_background(cam, np.random.default_rng(3))
    b = cs.make_background(cam, np.random.default_rng(3))
    assert a.shape == (H, W, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    rays = cs.pixel_rays(cam)
    floor = rays[..., 2] < -0.05
    # Floor (grey) and walls (coloured) differ: the chroma spread is larger above the horizon.
    chroma = a.astype(float).std(-1)
    assert floor.any() and (~floor).any()
    assert chroma[~floor].mean() > chroma[floor].mean() + 5.0


def test_floor_shadow_of_a_sphere_under_vertical_light(studio):
    """Light straight down: the shadow of a sphere is the disc beneath it."""
    pts, faces = cs._ellipsoid_mesh((0.2, -0.1, 1.0), (0.3, 0.3, 0.3), (0, 0, 1), rings=16, sectors=32)
    for cam in studio:
        shadow = cs.floor_shadow_mask(cam, pts, (0.0, 0.0, -1.0), faces)
        disc = cs.rasterise_mask(_disc_triangles((0.2, -0.1), 0.3, cam), W, H)
        iou = (shadow & disc).sum() / (shadow | disc).sum()
        assert iou > 0.9, (cam.name, iou)
    with pytest.raises(ValueError, match="downwards"):
        cs.floor_shadow_mask(studio[0], pts, (0.0, 0.0, 1.0), faces)


def test_slanted_light_moves_the_shadow_away_from_the_light(studio):
    pts, faces = cs._ellipsoid_mesh((0.0, 0.0, 1.0), (0.2, 0.2, 0.2), (0, 0, 1))
    cam = studio[len(studio) - 1]  # overhead
    shadow = cs.floor_shadow_mask(cam, pts, (0.5, 0.0, -1.0), faces)
    disc = cs.rasterise_mask(_disc_triangles((0.5, 0.0), 0.2, cam), W, H)
    assert (shadow & disc).sum() / (shadow | disc).sum() > 0.7


def test_composite_shadow_keeps_colour_and_gain_and_noise(studio):
    cam = studio[0]
    rng = np.random.default_rng(0)
    bg = cs.make_background(cam, rng)
    mask = np.zeros((H, W), bool)
    mask[40:60, 70:80] = True
    shadow = np.zeros((H, W), bool)
    shadow[90:110, 40:100] = True
    colour = np.zeros((H, W, 3), np.uint8)
    colour[mask] = (10, 200, 30)
    img = cs.composite_frame(cam, mask, colour, shadow, bg, rng, 1.0, 0.0, shadow_darkening=0.5)
    core = np.zeros_like(shadow)
    core[92:108, 42:98] = True  # away from the soft edge
    ratio = img[core].astype(float) / np.maximum(bg[core].astype(float), 1.0)
    assert np.allclose(ratio, 0.5, atol=0.03)
    assert np.array_equal(img[mask], colour[mask])
    assert np.array_equal(img[:30], bg[:30])
    # Gain scales everything; noise has the requested spread.
    bright = cs.composite_frame(cam, mask, None, None, bg, rng, 1.1, 0.0)
    assert np.allclose(bright[~mask].astype(float), np.clip(np.rint(bg[~mask] * 1.1), 0, 255), atol=1.0)
    assert np.all(bright[mask] == np.clip(np.rint(np.array(cs.DEFAULT_BODY_COLOUR) * 1.1), 0, 255))
    noisy = cs.composite_frame(cam, mask, None, None, bg, rng, 1.0, 3.0)
    mid = (bg > 20) & (bg < 235) & ~mask[..., None]
    assert 2.7 < (noisy.astype(float) - bg)[mid].std() < 3.3
    with pytest.raises(ValueError, match="do not match"):
        cs.composite_frame(cam, mask[:10], None, None, bg, rng)


def test_clothing_colours_palette():
    ids = np.arange(-1, 17).reshape(1, -1)
    rgb = clothing = cs.clothing_colours(ids)
    assert rgb.shape == (1, 18, 3) and rgb.dtype == np.uint8
    assert np.all(clothing[0, 0] == 0) and np.all(clothing[0, -1] == 0)
    by_name = {name: tuple(clothing[0, 1 + i]) for i, name in enumerate(SEGMENT_NAMES)}
    assert by_name["chest"] == cs.CLOTHING["shirt"] and by_name["l_upperarm"] == cs.CLOTHING["shirt"]
    assert by_name["head"] == cs.CLOTHING["skin"] and by_name["r_hand"] == cs.CLOTHING["skin"]
    assert by_name["l_thigh"] == cs.CLOTHING["trousers"] and by_name["pelvis"] == cs.CLOTHING["trousers"]
    assert by_name["r_foot"] == cs.CLOTHING["shoes"]


def test_toy_body_renders_in_every_camera(studio):
    pts, faces, seg = cs.toy_body((0.3, -0.2), 0.7, 0.3)
    assert faces.min() >= 0 and faces.max() < len(pts)
    assert set(np.unique(seg)) == set(range(len(SEGMENT_NAMES)))
    assert pts[:, 2].min() > -0.01 and 1.6 < pts[:, 2].max() < 1.9
    for cam in studio:
        mask, colour = cs.render_body(cam, pts, faces, seg)
        assert 150 < mask.sum() < 0.3 * W * H
        assert np.all(colour[~mask] == 0) and colour[mask].max() > 100


def test_studio_scene_shapes_and_truth():
    scene = cs.studio_scene(W, H, cameras=2, frames=2, background_frames=3, seed=1)
    assert scene.backgrounds.shape == (2, 3, H, W, 3)
    assert scene.images.shape == (2, 2, H, W, 3) and scene.truth.shape == (2, 2, H, W)
    assert scene.truth.any(axis=(2, 3)).all() and scene.shadows.any(axis=(2, 3)).all()
    assert not (scene.truth & scene.shadows).any()
    again = cs.studio_scene(W, H, cameras=2, frames=2, background_frames=3, seed=1)
    assert np.array_equal(scene.images, again.images)


def test_distorted_camera_rays_round_trip():
    cam = look_at("c", (2.0, -2.0, 1.5), (0, 0, 0.8), W, H)
    cam = type(cam)(cam.name, cam.K, np.array([-0.2, 0.05, 0.001, -0.001, 0.0]), cam.R, cam.t, W, H)
    rays = cs.pixel_rays(cam)
    pix = cam.project(cam.center + 2.0 * rays[::20, ::20])
    v, u = np.mgrid[0:H:20, 0:W:20]
    assert np.allclose(pix, np.stack([u, v], -1), atol=1e-3)
