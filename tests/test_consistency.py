"""The multi-view cleaning's kernels against the plain rules they compute faster: the visual
hull's count (compiled) against ``Camera.project`` and ``Camera.depth``, and the dilation of a
box around the pixels against scipy's dilation of the whole image."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from common.camera import Studio
from common.consistency import HULL_MIN_VIEWS, HULL_MISSES, carved, dilated, footprint, image_points
from common.synth import synth_studio

pytestmark = pytest.mark.timeout(120)


def carved_by_projection(studio: Studio, masks: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``carved``'s rule written with the cameras' own projection."""
    misses = np.zeros(len(points), dtype=np.int64)
    views = np.zeros(len(points), dtype=np.int64)
    for cam, mask in zip(studio, masks):
        with np.errstate(invalid="ignore"):  # points behind a distorting camera project to nothing finite
            uv = np.rint(cam.project(points)).astype(np.int64)
        seen = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        seen &= cam.depth(points) > 0
        on = np.zeros(len(points), dtype=bool)
        on[seen] = mask[uv[seen, 1], uv[seen, 0]]
        misses += seen & ~on
        views += seen
    return (misses <= np.where(views >= 3, HULL_MISSES, 0)) & (views >= HULL_MIN_VIEWS)


@pytest.mark.parametrize("distortion", [0.0, -0.35])
def test_the_compiled_hull_count_is_the_cameras_projection(distortion):
    studio = synth_studio(6, [(320, 240), (400, 300), (160, 120)], distortion=distortion)
    rng = np.random.default_rng(7)
    H, W = studio.padded_shape
    masks = np.zeros((len(studio), H, W), dtype=bool)
    for k, cam in enumerate(studio):  # a blob around the studio's middle, with holes
        uv = np.rint(cam.project(rng.normal([0.0, 0.0, 1.0], [0.3, 0.3, 0.6], size=(4000, 3)))).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        masks[k, uv[ok, 1], uv[ok, 0]] = True
        masks[k] = ndimage.binary_dilation(masks[k], iterations=3) & (rng.random((H, W)) > 0.05)
    # points around the actor, some behind a camera and some outside its image
    points = rng.uniform([-4.0, -4.0, -0.5], [4.0, 4.0, 3.0], size=(20000, 3))
    inside = carved(studio, masks, points)
    assert inside.any() and not inside.all()
    np.testing.assert_array_equal(inside, carved_by_projection(studio, masks, points))
    # one camera turned away sees none of them: it neither carves nor counts as a view
    turned = Studio((replace(studio[0], R=-studio[0].R, t=-studio[0].t),) + studio.cameras[1:])
    np.testing.assert_array_equal(carved(turned, masks, points), carved_by_projection(turned, masks, points))


@pytest.mark.parametrize("square", [False, True])
@pytest.mark.parametrize("iterations", [0, 1, 4, 9])
def test_dilating_the_box_around_the_pixels_is_dilating_the_image(square, iterations):
    rng = np.random.default_rng(iterations)
    structure = ndimage.generate_binary_structure(2, 2 if square else 1)
    for mask in (rng.random((60, 80)) > 0.995,  # scattered, some near every edge
                 np.pad(rng.random((10, 12)) > 0.5, ((1, 49), (66, 2))),  # a blob by the top right corner
                 np.zeros((30, 40), dtype=bool)):
        expected = ndimage.binary_dilation(mask, structure, iterations=iterations) if iterations else mask
        np.testing.assert_array_equal(dilated(mask, iterations, square), expected)


def test_a_footprint_is_the_dilated_projection_of_the_points_in_view():
    cam = synth_studio(1, [(320, 240)], distortion=-0.2)[0]
    points = np.array([[0.0, 0.0, 1.0], [0.2, -0.1, 1.5], [40.0, 0.0, 1.0]])  # the last one outside the image
    pixels = image_points(cam, points)
    assert len(pixels) == 2
    single = np.zeros((240, 320), dtype=bool)
    single[pixels[:, 1], pixels[:, 0]] = True
    np.testing.assert_array_equal(footprint(pixels, (240, 320), 3), ndimage.binary_dilation(single, iterations=3))


def test_bench_cleaning_rows():
    from common.consistency import bench_cleaning

    rows = bench_cleaning(cameras=(4,), width=160, height=120)
    assert len(rows) == 1 and rows[0]["cameras"] == 4 and rows[0]["size"] == [160, 120]
    assert rows[0]["frames_per_second"] > 0 and rows[0]["milliseconds_per_frame"] == 1000 / rows[0]["frames_per_second"]
    assert rows[0]["pixels_removed"] > 0  # Cheung's noise speckles that no other camera supports


# ------------------------------------------------------------------ foreground no pose explains

@pytest.mark.timeout(30)
def test_foreground_missed_in_most_frames_is_unexplained_and_a_short_take_tells_none():
    from common.consistency import UNEXPLAINED_MIN_FRAMES, unexplained_foreground

    frames = 20
    missed = np.zeros((2, 40, 50), dtype=np.int32)
    missed[0, 5:15, 5:15] = 14   # 70% of the frames: a chair's back
    missed[1, 20:30, 20:30] = 13  # 65%: a limb the fit missed for a while
    missed[1, 0:2, 0:2] = frames
    flags = unexplained_foreground(missed, frames, mean_area=2000.0)
    assert flags is not None and flags.sum() == 100 + 4
    assert flags[0, 5:15, 5:15].all() and not flags[1, 20:30, 20:30].any()
    assert unexplained_foreground(missed, frames, mean_area=6000.0) is None  # under 2% of the silhouettes
    assert unexplained_foreground(missed, UNEXPLAINED_MIN_FRAMES - 1, mean_area=2000.0) is None


@pytest.mark.timeout(60)
def test_pixels_cleared_in_the_recorded_images_are_clear_where_the_fit_looks():
    """Flags found in the ideal pinhole images the fit works in (``undistort_masks``) are cleared
    in the images as recorded, so that the cleared masks, undistorted again, are clear there;
    a camera without distortion takes them as they are."""
    from common.camera import circle_studio
    from common.frame import recorded_pixels, undistort_masks

    cams = list(circle_studio(2, 160, 120))
    cams[0] = replace(cams[0], dist=np.array([-0.3, 0.05, 0.0, 0.0, 0.0]))
    studio = Studio(tuple(cams))
    masks = np.zeros((2, 120, 160), dtype=bool)
    masks[:, 20:100, 30:130] = True
    _, ideal = undistort_masks(studio, masks)
    flags = np.zeros_like(ideal)
    flags[:, 40:70, 60:90] = True
    flags &= ideal
    cleared = masks & ~recorded_pixels(studio, flags)
    _, again = undistort_masks(studio, cleared)
    assert not (again & flags).any()
    assert (again == (ideal & ~flags)).mean() > 0.99  # little else goes
    np.testing.assert_array_equal(recorded_pixels(studio, flags)[1], flags[1])
