"""Settling a take: each frame's pose chosen among its neighbours' fits where the masks did not move.

A still actor's masks change by a few per cent of their area from frame to frame (segmentation
noise), and the energy has several minima within a fraction of a per cent of each other; each
frame's fit takes whichever its own noise favours, so a still body jumps by centimetres from
frame to frame. A moving actor's masks change by a third of their area at 30 fps. So a step
between frames costs in proportion to how little the masks changed: a joint moved by d mm
between frames t and t+1 costs ``weight * area_t / change_t * d^2`` pixels of energy, where
``area_t`` is the frames' mean silhouette area in pixels (an energy in pixels scales with it) and
``change_t`` the share of it that changed between the two frames' masks. Each frame chooses
among the fits of the frames within ``reach`` of it (its own included) the one that makes the
sum of energies and step costs least over the whole take (dynamic programming, exact).
"""
from __future__ import annotations

import numpy as np

SETTLE_REACH = 30           # frames either side whose fits a frame may take (a second at 30 fps)
# the share of the silhouette area a step costs per mm^2 of the joints' mean move, squared, per
# unit of change: a walk at 30 fps (8 cameras of 320x240, 15-23k silhouette pixels, 28-37% of
# them changed per frame) pays about 0.15 pixels per mm^2; the seated take (52k pixels, 1-5%
# changed between frames a third of a second apart) 2.6-13
SETTLE_WEIGHT_PER_MM2 = 2.5e-6
MIN_CHANGE = 1e-3           # a share of changed silhouette below this counts as this (identical masks)


def mask_step(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """(K, h, w) bool, (K, h, w) bool -> (the share of the silhouette that differs, the two
    frames' mean silhouette area in pixels)."""
    area = (int(np.count_nonzero(before)) + int(np.count_nonzero(after))) / 2.0
    return np.count_nonzero(before ^ after) / max(area, 1.0), area


def candidate_frames(count: int, reach: int = SETTLE_REACH) -> np.ndarray:
    """(count, 2 reach + 1) int: frame t's candidates are the fits of frames t - reach .. t +
    reach (index ``reach`` is its own); -1 where that frame does not exist."""
    t = np.arange(count)[:, None] + np.arange(-reach, reach + 1)[None, :]
    return np.where((t >= 0) & (t < count), t, -1)


def settle_choice(energies: np.ndarray, joints: np.ndarray, candidates: np.ndarray, change: np.ndarray,
                  area: np.ndarray, weight: float = SETTLE_WEIGHT_PER_MM2) -> np.ndarray:
    """Per frame the candidate on the path of least total energy plus step cost (Viterbi).

    energies (T, C): frame t's energy at candidate c's pose (inf where ``candidates`` is -1);
    joints (T, J, 3), metres: each frame's own fit; candidates (T, C) as ``candidate_frames``;
    change, area (T-1,): ``mask_step`` between frames t and t+1 -> (T,) int candidate indices.
    A step from pose a to pose b costs weight * area / change * (mean joint distance in mm)^2."""
    T, C = energies.shape
    scale = weight * np.asarray(area, dtype=np.float64) / np.maximum(np.asarray(change, dtype=np.float64), MIN_CHANGE)
    total = energies[0].astype(np.float64)
    back = np.zeros((T, C), dtype=np.int64)
    for t in range(1, T):
        # a missing candidate (-1) stands in as frame 0: its energy is inf, so never chosen
        a = joints[np.maximum(candidates[t - 1], 0)]                       # (C, J, 3)
        b = joints[np.maximum(candidates[t], 0)]
        step_mm = 1000.0 * np.linalg.norm(a[:, None] - b[None], axis=-1).mean(axis=-1)   # (C from, C to)
        through = total[:, None] + scale[t - 1] * step_mm ** 2
        back[t] = np.argmin(through, axis=0)
        total = through[back[t], np.arange(C)] + energies[t]
    path = np.empty(T, dtype=np.int64)
    path[-1] = int(np.argmin(total))
    for t in range(T - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path
