"""Multi-view consistency of silhouettes: drop foreground that the other cameras do not support.

Masks from real footage hold blobs that are not the person: flickering lights, floor seams, a
moved board. A blob seen by one camera only has no 3D object behind it: the visual hull of all
views (the voxels inside every camera's mask that sees them) does not project onto it. Each
connected blob of a camera's mask is kept when enough of it is covered by the hull's projection
into that camera, and dropped otherwise. Objects really in the scene (a chair the person sits
on) are in every view and stay: the fit's energy has to live with them.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from common.camera import Studio

HULL_GRID = 32               # voxels per side of the carved box (about 10 cm; blobs are judged whole, so
                             # 64 removed the same pixels to 0.2% on the seated take and a walk, at 7x the time)
HULL_EXTENT_M = 3.0          # metres: side of the box around the actor (its height too)
HULL_MIN_VIEWS = 2           # a voxel must project inside at least this many images
HULL_MISSES = 1              # ... and may fall outside this many of the masks that see it, where 3 or more do
                             # (a hole in one mask, segmentation noise, must not carve the actor away)
SPLAT_RADIUS_PX = 4          # the hull's projection is dilated by this much (voxels are coarse)
MIN_SUPPORTED_FRACTION = 0.3  # a blob is kept when at least this share of its pixels is supported,
MIN_SUPPORT_OF_BEST = 0.5     # or when it is supported at least half as much as the camera's best-supported
                              # blob (noise speckles that touch the actor join its blob and dilute its share)


def hull_points(studio: Studio, masks: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(n, 3) centres of the voxels inside the visual hull, in a HULL_EXTENT_M box on the floor
    around ``centre`` (3,). masks (K, H, W) bool in the studio's (distorted) images, padded
    beyond each camera's own size. A voxel outside a camera's image is not carved by it, and one
    outside HULL_MISSES of the masks that see it is still kept where at least three see it."""
    half = HULL_EXTENT_M / 2
    axes = [np.linspace(centre[0] - half, centre[0] + half, HULL_GRID),
            np.linspace(centre[1] - half, centre[1] + half, HULL_GRID),
            np.linspace(0.0, HULL_EXTENT_M, HULL_GRID)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    misses = np.zeros(len(points), dtype=np.int64)
    views = np.zeros(len(points), dtype=np.int64)
    for cam, mask in zip(studio, masks):
        uv = np.rint(cam.project(points)).astype(np.int64)
        seen = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        seen &= cam.depth(points) > 0
        on = np.zeros(len(points), dtype=bool)
        on[seen] = mask[uv[seen, 1], uv[seen, 0]]
        misses += seen & ~on
        views += seen
    allowed = np.where(views >= 3, HULL_MISSES, 0)
    return points[(misses <= allowed) & (views >= HULL_MIN_VIEWS)]


def supported_masks(studio: Studio, masks: np.ndarray, centre: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """masks (K, H, W) bool -> (the masks with unsupported blobs removed, (K,) pixels removed).

    ``centre`` (3,) is where the actor is (``common.voxels.silhouette_centre``); None leaves
    the masks as they are (nothing to carve around)."""
    masks = np.asarray(masks, dtype=bool)
    removed = np.zeros(len(studio), dtype=np.int64)
    if centre is None:
        return masks, removed
    points = hull_points(studio, masks, centre)
    if len(points) == 0:
        return masks, removed
    out = masks.copy()
    disk = ndimage.generate_binary_structure(2, 1)
    for k, (cam, mask) in enumerate(zip(studio, masks)):
        uv = np.rint(cam.project(points)).astype(np.int64)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        support = np.zeros(mask.shape, dtype=bool)
        support[uv[ok, 1], uv[ok, 0]] = True
        support = ndimage.binary_dilation(support, disk, iterations=SPLAT_RADIUS_PX)
        labels, count = ndimage.label(mask)
        if count == 0:
            continue
        sizes = np.bincount(labels.ravel(), minlength=count + 1)
        covered = np.bincount(labels.ravel(), weights=(support & mask).ravel(), minlength=count + 1)
        covered[0] = 0.0
        keep = (covered >= MIN_SUPPORTED_FRACTION * np.maximum(sizes, 1)) | (covered >= MIN_SUPPORT_OF_BEST * covered.max())
        keep &= covered > 0
        keep[0] = False
        out[k] = keep[labels]
        removed[k] = int(mask.sum() - out[k].sum())
    return out, removed
