"""The XOR energy E(pose) = sum over cameras of |rendered XOR input| inside each camera's window.

One interface, two backends (this module: ``cpu``; ``common.energy_gl``: ``gl``):

- The studio's K input silhouettes are cut into per-camera windows (the paper's sub-windows:
  128x128 around an arm or leg, 64x64 around the head, a hand or a foot, the whole image at
  half resolution for the torso), centred on the part's projection at the start pose.
- Parts that do not move during a sub-optimization are pre-rendered into a static mask M.
  With the input I and the moving parts' render R, inside a window
      |(R or M) xor I| = |M xor I| + sum over R of v,   v = 0 where M, else 1 - 2 I,
  so each evaluation only needs the moving parts and per-row prefix sums of v.
- The cpu backend renders each segment's ellipsoid exactly as an image conic
  C = (P Q* P^T)^-1, takes one covered span per (camera, segment, row), merges spans per row
  and sums v over the merged spans with the prefix sums: no per-pixel work per evaluation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.body import BodyModel, forward_kinematics
from common.camera import Studio

ARM_WINDOW = 128   # pixels, windows for upper arm + forearm, thigh + shin
SMALL_WINDOW = 64  # pixels, windows for head, hands, feet
MIN_DEPTH_M = 0.1  # ellipsoids closer to a camera than this are not drawn


@dataclass(frozen=True)
class Window:
    """A rectangle of one camera's image, in that camera's pixel grid (may extend past edges)."""

    x0: int
    y0: int
    width: int
    height: int


def centred_window(centre_uv: np.ndarray, size: int) -> Window:
    x0 = int(np.floor(centre_uv[0] - size / 2 + 0.5))
    y0 = int(np.floor(centre_uv[1] - size / 2 + 0.5))
    return Window(x0, y0, size, size)


def cut_window(mask: np.ndarray, w: Window) -> np.ndarray:
    """(H, W) bool image -> (w.height, w.width) bool, zeros outside the image."""
    H, W = mask.shape
    out = np.zeros((w.height, w.width), dtype=bool)
    xs, ys = max(w.x0, 0), max(w.y0, 0)
    xe, ye = min(w.x0 + w.width, W), min(w.y0 + w.height, H)
    if xs < xe and ys < ye:
        out[ys - w.y0:ye - w.y0, xs - w.x0:xe - w.x0] = mask[ys:ye, xs:xe]
    return out


# --------------------------------------------------------------------------- geometry

def ellipsoid_world(model: BodyModel, rotations: np.ndarray, origins: np.ndarray, segments) -> tuple:
    """Posed ellipsoids of ``segments``.

    rotations (B, 16, 3, 3), origins (B, 16, 3) -> centres (B, S, 3), shape matrices A (B, S, 3, 3)
    with the ellipsoid = {c + A u : |u| <= 1}.
    """
    seg = np.asarray(segments)
    R = rotations[:, seg]
    centres = np.einsum("bsij,sj->bsi", R, model.ellipsoid_centres[seg]) + origins[:, seg]
    local_A = model.ellipsoid_axes[seg] * model.ellipsoid_radii[seg][:, None, :]  # (S, 3, 3)
    A = R @ local_A
    return centres, A


def image_conics(P: np.ndarray, centres: np.ndarray, A: np.ndarray) -> tuple:
    """Project ellipsoids to image conics.

    P (K, 3, 4) camera matrices, centres (B, S, 3), A (B, S, 3, 3) ->
    conic matrices C (B, K, S, 3, 3) scaled so that x^T C x < 0 inside, and a (B, K, S) bool
    of conics that are drawable (ellipsoid in front of the camera).
    """
    B, S = centres.shape[:2]
    # dual quadric Q* = T diag(1,1,1,-1) T^T with T = [[A, c], [0, 1]]
    Qs = np.empty((B, S, 4, 4))
    Qs[..., :3, :3] = A @ np.swapaxes(A, -1, -2) - centres[..., :, None] * centres[..., None, :]
    Qs[..., :3, 3] = -centres
    Qs[..., 3, :3] = -centres
    Qs[..., 3, 3] = -1.0
    Cs = np.einsum("kij,bsjl,kml->bksim", P, Qs, P)  # dual conics (B, K, S, 3, 3)
    # adjugate of the dual conic = conic up to a scale whose sign we fix below
    c0, c1, c2 = Cs[..., 0], Cs[..., 1], Cs[..., 2]
    adj = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=-2)
    ch = np.concatenate([centres, np.ones((B, S, 1))], axis=-1)
    x = np.einsum("kij,bsj->bksi", P, ch)  # projected centres (homogeneous)
    depth = x[..., 2]
    inside_val = np.einsum("bksi,bksij,bksj->bks", x, adj, x)
    sign = np.where(inside_val > 0, -1.0, 1.0)
    return adj * sign[..., None, None], depth > MIN_DEPTH_M


def conic_spans(C: np.ndarray, rows: np.ndarray, x0: np.ndarray, width: int) -> tuple:
    """Covered pixel spans of conics on image rows.

    C (..., K, S, 3, 3); rows (K, R) image row centres per camera; x0 (K,) window left edges.
    Returns start, end (..., K, S, R) int32 window columns, end exclusive, empty if start >= end.
    """
    a = C[..., 0, 0][..., None]
    y = rows[:, None, :]
    b = 2.0 * (C[..., 0, 1][..., None] * y + C[..., 0, 2][..., None])
    c = (C[..., 1, 1][..., None] * y + 2.0 * C[..., 1, 2][..., None]) * y + C[..., 2, 2][..., None]
    disc = b * b - 4.0 * a * c
    ok = (disc > 0) & (a > 0)
    root = np.sqrt(np.where(ok, disc, 0.0))
    inv2a = 0.5 / np.where(ok, a, 1.0)
    xs = (-b - root) * inv2a - x0[:, None, None]
    xe = (-b + root) * inv2a - x0[:, None, None]
    start = np.clip(np.ceil(xs), 0, width).astype(np.int32)
    end = np.clip(np.floor(xe) + 1, 0, width).astype(np.int32)
    end = np.where(ok, end, start)
    return start, end


def merged_span_sums(start: np.ndarray, end: np.ndarray, prefix: np.ndarray) -> np.ndarray:
    """Sum of per-pixel values over the union of spans in each row.

    start, end (B, K, S, R) int32 window columns; prefix (K, R, W+1) per-row prefix sums.
    Returns (B,) totals.
    """
    B, K, S, R = start.shape
    if S > 1:
        order = np.argsort(start, axis=2, kind="stable")
        start = np.take_along_axis(start, order, 2)
        end = np.take_along_axis(end, order, 2)
        reach = np.maximum.accumulate(end, axis=2)
        prev = np.concatenate([np.zeros_like(reach[:, :, :1]), reach[:, :, :-1]], axis=2)
        start = np.maximum(start, prev)
        end = np.maximum(end, start)
    Wp = prefix.shape[2]
    base = (np.arange(K)[:, None] * R + np.arange(R)[None, :]) * Wp  # (K, R)
    flat = prefix.reshape(-1)
    vals = flat[base[None, :, None, :] + end] - flat[base[None, :, None, :] + start]
    return vals.reshape(B, -1).sum(axis=1)


def render_spans_mask(start: np.ndarray, end: np.ndarray, width: int) -> np.ndarray:
    """start, end (K, S, R) -> (K, R, width) bool coverage (used to pre-render static parts)."""
    K, S, R = start.shape
    diff = np.zeros((K, R, width + 1), dtype=np.int32)
    k_idx = np.broadcast_to(np.arange(K)[:, None, None], start.shape)
    r_idx = np.broadcast_to(np.arange(R)[None, None, :], start.shape)
    nonempty = end > start
    np.add.at(diff, (k_idx[nonempty], r_idx[nonempty], start[nonempty]), 1)
    np.add.at(diff, (k_idx[nonempty], r_idx[nonempty], end[nonempty]), -1)
    return np.cumsum(diff, axis=2)[..., :width] > 0


# ------------------------------------------------------------------------ the energy

@dataclass(frozen=True)
class EnergySetup:
    """Everything that stays fixed during one sub-optimization.

    studio: cameras (already scaled for half-resolution work); windows: one per camera, all of
    the same size; inputs: (K, h, w) bool input silhouette windows; moving: segments that move;
    static_params: (35,) pose whose other segments are pre-rendered.
    """

    studio: Studio
    windows: tuple
    inputs: np.ndarray
    moving: tuple
    static_params: np.ndarray
    prerender: bool = True


class CpuEnergy:
    """The ``cpu`` backend: analytic ellipsoid silhouettes, spans and prefix sums."""

    backend = "cpu"

    def __init__(self, model: BodyModel, setup: EnergySetup):
        self.model = model
        self.setup = setup
        self.evaluations = 0
        studio, windows = setup.studio, setup.windows
        K = len(studio)
        h, w = setup.inputs.shape[1:]
        self.width = w
        self.P = np.stack([c.projection_matrix for c in studio])
        self.rows = np.stack([np.arange(h, dtype=np.float64) + win.y0 for win in windows])  # (K, h)
        self.x0 = np.array([win.x0 for win in windows], dtype=np.float64)
        self.moving = tuple(setup.moving) if setup.prerender else tuple(range(16))
        static = tuple(s for s in range(16) if s not in self.moving)
        I = setup.inputs.astype(np.int32)
        if static:
            M = self._render(setup.static_params[None], static)[0]
        else:
            M = np.zeros((K, h, w), dtype=bool)
        self.static_mask = M
        v = np.where(M, 0, 1 - 2 * I)
        self.prefix = np.concatenate([np.zeros((K, h, 1), np.int32), np.cumsum(v, axis=2, dtype=np.int32)], axis=2)
        self.base = int(np.count_nonzero(M ^ setup.inputs))

    def _spans(self, params: np.ndarray, segments) -> tuple:
        pose = forward_kinematics(self.model, params)
        centres, A = ellipsoid_world(self.model, pose.rotations, pose.origins, segments)
        C, ok = image_conics(self.P, centres, A)
        start, end = conic_spans(C, self.rows, self.x0, self.width)
        end = np.where(ok[..., None], end, start)
        return start, end

    def _render(self, params: np.ndarray, segments) -> np.ndarray:
        start, end = self._spans(params, segments)
        return np.stack([render_spans_mask(s, e, self.width) for s, e in zip(start, end)])

    def __call__(self, params: np.ndarray) -> np.ndarray:
        """(B, 35) or (35,) -> (B,) int64 energies (pixels)."""
        p = np.atleast_2d(params)
        start, end = self._spans(p, self.moving)
        self.evaluations += len(p)
        return self.base + merged_span_sums(start, end, self.prefix)

    def render(self, params: np.ndarray) -> np.ndarray:
        """(35,) -> (K, h, w) bool: the model's silhouette windows (moving or static parts)."""
        return self._render(np.atleast_2d(params), self.moving)[0] | self.static_mask


ENERGY_BACKENDS = {"cpu": CpuEnergy}


def make_energy(backend: str, model: BodyModel, setup: EnergySetup):
    if backend == "gl":
        from common.energy_gl import GlEnergy

        return GlEnergy(model, setup)
    try:
        return ENERGY_BACKENDS[backend](model, setup)
    except KeyError:
        raise ValueError(f"unknown energy backend {backend!r}; expected cpu or gl") from None
