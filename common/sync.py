"""Frame offsets between cameras, estimated from the silhouettes: which frames were taken together.

Cameras without a shared clock start recording at different moments, and a video can lose a
frame at its start; camera c's frame i + d_c then shows the moment of the others' frame i (a
camera that started recording two frames before the others: d_c = 2; one whose first two
frames were lost: -2). The silhouettes say which d: the visual hull of the other cameras at a
moment projects onto a camera's silhouette of the same moment, and less well onto one taken a
frame earlier or later, by as much as the actor moved in between. For each camera and each
candidate offset d the agreement is measured over frames across the take:

- the hull of the other cameras (a ``SYNC_GRID``-cell lattice in the box around the actor,
  each point inside every other mask that sees it) is projected into the camera;
- precision: the share of those points that fall inside the camera's mask of frame f + d;
  recall: the share of that mask within a cell's radius of them; the agreement is their
  harmonic mean (an F1 score), so a larger mask at another frame is not preferred for its size.

Offsets move one camera at a time: every camera is judged against the others at their offsets
so far, and the one whose best offset beats its present one most clearly (``margin``: the mean
frame-by-frame gain over its standard error, above ``MOVE_Z``) takes it; then all are judged
again, until none moves. A camera off by a few frames makes the others' hull wrong too, so two
cameras off at once blur each other's peaks until the clearer one is put right. A camera's
offset is ``resolved`` where its best also beats both neighbouring offsets by ``PEAK_Z``: a view
along the actor's path (a walk towards the camera) changes too little from frame to frame to
tell, and says so. Offsets are then stated against the offset most cameras share (mostly 0),
in the convention of ``mocap import-video --offset``: camera c's frame i + offset_c was taken
with the others' frame i.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.camera import Studio
from common.consistency import HULL_EXTENT_M, carved, cell_radius_px, footprint, hull_lattice, image_points
from common.packing import pad_stack
from common.voxels import silhouette_centre

SYNC_GRID = 64         # lattice points per side of the 3 m box: 4.7 cm cells, under a forearm's width
SYNC_FRAMES = 24       # frames across the take the agreement is averaged over
MAX_OFFSET = 5         # frames either way tried by default
PEAK_Z = 3.0           # standard errors by which the best offset must beat each neighbour, frame by frame
MOVE_Z = 6.0           # ... and by which a camera's best must beat its present offset for it to move: at
                       # PEAK_Z a camera in step that leaned a frame one way was moved; at 6, none in the
                       # trials (tools/sync_trials.py, docs/accuracy.md)
TOLERANT_VIEWS = 4     # the others' hull lets a point miss one of their masks where this many see it


@dataclass(frozen=True)
class CameraSync:
    """One camera's estimate: ``offset`` (its frame i + offset was taken with the others' frame
    i); ``scores`` {offset: mean agreement 0..1} for every offset tried, against the others at
    their offsets; ``resolved``: whether ``offset`` is the best and beats both neighbouring
    offsets clearly, frame by frame (``peak``; where not, this view cannot tell the frames
    apart: the actor moves along its line of sight, or not at all)."""

    camera: str
    offset: int
    scores: dict
    resolved: bool
    judged: int = 0  # frames its agreement was measured in (those whose masks all exist)


@dataclass(frozen=True)
class SyncEstimate:
    """Every camera's ``CameraSync`` in calibration order; ``frames``: the frame indices tried
    (each camera's ``judged`` says how many of them had every mask needed)."""

    cameras: tuple
    frames: tuple

    @property
    def offsets(self) -> dict:
        """{camera: offset} for every camera."""
        return {c.camera: c.offset for c in self.cameras}

    @property
    def unresolved(self) -> list[str]:
        """The cameras whose offset could not be told."""
        return [c.camera for c in self.cameras if not c.resolved]


def margin(per_frame: dict, a: int, b: int) -> float:
    """How clearly offset ``a`` beats offset ``b``: the mean of their frame-by-frame difference in
    agreement over its standard error (``per_frame`` {offset: (F,) agreements}); inf where every
    frame gains the same, -inf where none is judged."""
    gain = np.asarray(per_frame[a]) - np.asarray(per_frame[b])
    if len(gain) < 2:
        return -np.inf
    error = gain.std(ddof=1) / np.sqrt(len(gain))
    return float(gain.mean() / error) if error > 0 else (np.inf if gain.mean() > 0 else -np.inf)


def peak(per_frame: dict) -> tuple[int, bool]:
    """(the offset of the highest mean agreement, whether it beats both neighbouring offsets by
    ``PEAK_Z`` standard errors, ``margin``); a tie goes to the offset nearer 0. A best offset at
    the end of those tried is never sharp: the agreement may rise further beyond it."""
    means = {d: float(np.mean(a)) if len(a) else 0.0 for d, a in per_frame.items()}
    best = max(means, key=lambda d: (means[d], -abs(d)))
    neighbours = (best - 1, best + 1)
    return best, all(d in per_frame and margin(per_frame, best, d) > PEAK_Z for d in neighbours)


def most_common(shifts: list[int]) -> int:
    """The shift most cameras have (a tie: 0 where it is among them, else the one nearest 0)."""
    counts = {s: shifts.count(s) for s in shifts}
    return max(counts, key=lambda s: (counts[s], s == 0, -abs(s)))


def others_hull(studio: Studio, masks: np.ndarray, camera: int, points: np.ndarray) -> np.ndarray:
    """(m, 3) the points (n, 3) inside the visual hull (``consistency.carved``) of the masks
    (K, H, W) bool of every camera but ``camera``, a miss allowed only where ``TOLERANT_VIEWS``
    or more of them see a point: one camera still off (a view that barely changes cannot be
    synchronised by its own agreement) must not carve the others' hull."""
    keep = [k for k in range(len(studio)) if k != camera]
    others = Studio(tuple(studio[k] for k in keep), studio.source)
    return points[carved(others, masks[keep], points, TOLERANT_VIEWS)]


def agreement(mask: np.ndarray, pixels: np.ndarray, splat: np.ndarray) -> float:
    """F1 of one camera's ``mask`` (H, W) bool against the hull's projected ``pixels`` (m, 2)
    (column, row) and their ``splat`` (H, W) bool: 0 where either is empty."""
    if len(pixels) == 0 or not mask.any():
        return 0.0
    precision = float(mask[pixels[:, 1], pixels[:, 0]].mean())
    recall = float((mask & splat).sum() / mask.sum())
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


def camera_scores(studio: Studio, mask_of, camera: int, frames: list, shifts: list, candidates: range,
                  grid: int = SYNC_GRID) -> dict:
    """{d: (F,) agreements} of camera ``camera`` at each offset d of ``candidates``: at each of
    ``frames`` (indices) f, the other cameras k at frame f + shifts[k] (their offsets so far)
    against this one at f + d. ``mask_of(k, i)`` -> camera k's (h_k, w_k) bool mask of frame
    index i, or None where it lacks that frame; a frame where a mask is missing, or the others'
    hull is not seen, is left out (for every d alike)."""
    cam = studio[camera]
    shape = (cam.height, cam.width)
    cell_m = HULL_EXTENT_M / (grid - 1)
    agreements = {d: [] for d in candidates}
    for f in frames:
        views = [mask_of(k, f + shifts[k]) for k in range(len(studio))]
        own = [mask_of(camera, f + d) for d in candidates]
        if any(v is None for v in views) or any(m is None for m in own):
            continue
        others = pad_stack(views)
        centre = silhouette_centre(studio, others)
        if centre is None:
            continue
        hull = others_hull(studio, others, camera, hull_lattice(centre, grid))
        pixels = image_points(cam, hull)
        if len(pixels) == 0:
            continue
        splat = footprint(pixels, shape, cell_radius_px(cam, hull, cell_m), square=True)
        for d, mask in zip(candidates, own):
            agreements[d].append(agreement(mask, pixels, splat))
    return {d: np.array(a) for d, a in agreements.items()}


def judged_frames(count: int, max_offset: int, frames: int) -> list[int]:
    """Up to ``frames`` indices evenly across 0..count-1 that stay inside the take whatever
    offsets within ``max_offset`` the cameras are given. ValueError when none do."""
    lo, hi = 2 * max_offset, count - 1 - 2 * max_offset  # a camera shifted and its candidate shifted
    if hi < lo:
        raise ValueError(f"{count} frames are too few to try offsets of up to {max_offset} frames: "
                         f"at least {4 * max_offset + 1} are needed")
    return sorted(set(np.linspace(lo, hi, min(frames, hi - lo + 1)).round().astype(int).tolist()))


def estimate_offsets(studio: Studio, mask_of, count: int, max_offset: int = MAX_OFFSET,
                     frames: int = SYNC_FRAMES, grid: int = SYNC_GRID) -> SyncEstimate:
    """Every camera's frame offset (see the module docstring).

    studio: the K cameras; mask_of(k, i) -> camera k's (h_k, w_k) bool mask of frame index i,
    or None where it lacks that frame (``camera_scores``); count: the frame indices 0..count-1
    there are; max_offset: the offsets tried either way; ``frames`` indices judged
    (``judged_frames``).
    """
    K = len(studio)
    judged = judged_frames(count, max_offset, frames)
    candidates = range(-max_offset, max_offset + 1)
    shifts = [0] * K
    moved = 0
    while True:
        per_frame = [camera_scores(studio, mask_of, k, judged, shifts, candidates, grid) for k in range(K)]
        peaks = [peak(p) for p in per_frame]
        # the camera whose best offset beats its present one most clearly moves, one a round: the
        # others' hull then holds one camera fewer out of step, and their peaks sharpen
        moves = [(margin(p, best, shifts[k]), k, best) for k, (p, (best, _)) in enumerate(zip(per_frame, peaks))
                 if best != shifts[k]]
        moves = [m for m in moves if m[0] > MOVE_Z]
        if not moves or moved > K:  # every camera once and one more: judged again after the last move
            break
        _, k, best = max(moves)
        shifts[k] = best
        moved += 1
    centre = most_common(shifts)  # the offsets stated against the cameras most of which agree
    cameras = tuple(CameraSync(cam.name, shifts[k] - centre,
                               {d - centre: float(np.mean(a)) if len(a) else 0.0 for d, a in per_frame[k].items()},
                               peaks[k][1] and peaks[k][0] == shifts[k], min(len(a) for a in per_frame[k].values()))
                    for k, cam in enumerate(studio))
    return SyncEstimate(cameras, tuple(judged))
