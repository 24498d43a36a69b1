"""Fit quality without truth (common.scoring.frame_quality, quality_summary; the sides as
`mocap fit` and the report say them): the XOR and its two sides, on masks drawn from the body
itself, with foreground added that no body explains and with the pose moved."""
from __future__ import annotations

import numpy as np
import pytest

from common.body import P, rest_params
from common.frame import FrameData
from common.scoring import QUALITY_FLAG_SHARE, frame_quality, quality_summary
from server.session import xor_sides

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def drawn(model, small_studio):
    """(pose, masks drawn from the body at that pose with the fit's own renderer)."""
    pose = rest_params(model)  # standing in the middle of the studio
    blank = np.zeros((len(small_studio), small_studio[0].height, small_studio[0].width), bool)
    masks = FrameData(model, small_studio, blank).whole_image_energy().render(pose)
    return pose, masks


def test_the_pose_the_masks_were_drawn_from_explains_them(model, small_studio, drawn):
    pose, masks = drawn
    assert all(m.sum() > 300 for m in masks)  # every camera sees the body
    q = frame_quality(FrameData(model, small_studio, masks), pose)
    assert q["xor_pixels"] == [0] * len(small_studio) and q["xor_share_total"] == 0.0
    assert q["outside_pixels"] == q["missed_pixels"] == [0] * len(small_studio)
    assert q["silhouette_pixels"] == [int(m.sum()) for m in masks] and not q["flagged_cameras"]


def test_foreground_no_body_explains_is_missed_and_flags_its_camera(model, small_studio, drawn):
    pose, masks = drawn
    prop = masks.copy()
    h, w = prop.shape[1:]
    area = int(masks[1].sum())
    rows = int(np.ceil(area / w))  # a block at the top, over half the actor's area: past the flag
    prop[1, :rows, :] = True
    added = int(prop[1].sum() - masks[1].sum())
    q = frame_quality(FrameData(model, small_studio, prop), pose)
    assert q["missed_pixels"][1] == added and q["outside_pixels"] == [0] * len(small_studio)
    assert q["xor_pixels"][1] == added and q["xor_share"][1] == pytest.approx(added / prop[1].sum(), abs=1e-4)
    assert q["xor_share"][1] > QUALITY_FLAG_SHARE and q["flagged_cameras"] == [small_studio[1].name]
    summary = quality_summary([{"frame": 0, "fit_quality": q}], small_studio.names)
    assert summary["mean_outside_share"] == 0.0
    assert summary["mean_missed_share"] == pytest.approx(added / sum(q["silhouette_pixels"]))
    assert summary["frames_flagged"] == [{"frame": 0, "cameras": [small_studio[1].name]}]
    said = xor_sides(summary)
    assert "body outside the masks 0%" in said and "a prop" in said


def test_a_pose_off_the_masks_is_outside_and_missed_alike(model, small_studio, drawn):
    pose, masks = drawn
    moved = pose.copy()
    moved[P["root_x"]] += 0.3  # the whole body 30 cm aside
    q = frame_quality(FrameData(model, small_studio, masks), moved)
    assert all(o > 0 and m > 0 for o, m in zip(q["outside_pixels"], q["missed_pixels"]))
    assert q["xor_pixels"] == [o + m for o, m in zip(q["outside_pixels"], q["missed_pixels"])]
    summary = quality_summary([{"frame": 0, "fit_quality": q}], small_studio.names)
    assert "mostly" not in xor_sides(summary)  # a wrong pose shows on both sides
    lost = xor_sides({"mean_outside_share": 0.01, "mean_missed_share": 0.99})  # the body far from the masks
    assert "the body is mostly not where the masks are: check the calibration's units" in lost and "a prop" not in lost
    older = {k: v for k, v in q.items() if k not in ("outside_pixels", "missed_pixels")}  # written before the sides
    assert "mean_missed_share" not in quality_summary([{"frame": 0, "fit_quality": older}], small_studio.names)
