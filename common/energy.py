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
    # two matrix products: numpy's three-operand einsum is several times slower here
    PQ = P[None, :, None] @ Qs[:, None]                               # (B, K, S, 3, 4)
    Cs = PQ @ np.swapaxes(P, -1, -2)[None, :, None]                   # dual conics (B, K, S, 3, 3)
    # adjugate of the (symmetric) dual conic = conic up to a scale whose sign we fix below
    d00, d01, d02 = Cs[..., 0, 0], Cs[..., 0, 1], Cs[..., 0, 2]
    d11, d12, d22 = Cs[..., 1, 1], Cs[..., 1, 2], Cs[..., 2, 2]
    adj = np.empty_like(Cs)
    adj[..., 0, 0] = d11 * d22 - d12 * d12
    adj[..., 1, 1] = d00 * d22 - d02 * d02
    adj[..., 2, 2] = d00 * d11 - d01 * d01
    adj[..., 0, 1] = adj[..., 1, 0] = d02 * d12 - d01 * d22
    adj[..., 0, 2] = adj[..., 2, 0] = d01 * d12 - d02 * d11
    adj[..., 1, 2] = adj[..., 2, 1] = d01 * d02 - d00 * d12
    x = np.einsum("kij,bsj->bksi", P[:, :, :3], centres) + P[None, :, None, :, 3]  # projected centres
    depth = x[..., 2]
    inside_val = np.einsum("bksi,bksij,bksj->bks", x, adj, x)
    sign = np.where(inside_val > 0, -1.0, 1.0)
    return adj * sign[..., None, None], depth > MIN_DEPTH_M


def conic_row_spans(C: np.ndarray, drawable: np.ndarray, y0: np.ndarray, x0: np.ndarray,
                    rows: int, width: int) -> tuple:
    """Covered pixel spans of image conics, only on the rows each conic covers.

    C (B, K, S, 3, 3) conics (negative inside); drawable (B, K, S); y0, x0 (K,) window corners;
    rows, width: window size. Pixel centres at integer coordinates are inside when the conic
    is negative there. Returns flat arrays over the non-empty spans:
    batch (N,), row_id (N,) = camera * rows + window row, start (N,), end (N,) (exclusive).
    """
    B, K, S = C.shape[:3]
    c00, c01, c02 = C[..., 0, 0], C[..., 0, 1], C[..., 0, 2]
    c11, c12, c22 = C[..., 1, 1], C[..., 1, 2], C[..., 2, 2]
    # y-extent: where the quadratic in x has a double root
    qa = c01 * c01 - c00 * c11
    qb = 2.0 * (c01 * c02 - c00 * c12)
    qc = c02 * c02 - c00 * c22
    disc_y = qb * qb - 4.0 * qa * qc
    ellipse = drawable & (qa < 0) & (c00 > 0) & (disc_y > 0)
    sq = np.sqrt(np.where(ellipse, disc_y, 0.0))
    qa_safe = np.where(ellipse, qa, -1.0)
    y_lo = (-qb + sq) / (2.0 * qa_safe)  # qa < 0: this is the smaller root
    y_hi = (-qb - sq) / (2.0 * qa_safe)
    wy0 = y0[None, :, None]
    first = np.clip(np.ceil(y_lo - wy0), 0, rows).astype(np.int64)
    last = np.clip(np.floor(y_hi - wy0) + 1, 0, rows).astype(np.int64)
    # one entry per covered row of each conic (no padding to the tallest conic)
    count = np.where(ellipse, last - first, 0).reshape(-1)
    total = int(count.sum())
    if total <= 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty, empty
    conic = np.repeat(np.arange(count.size), count)  # (T,) flat (b, k, s) index of each row
    ends = np.cumsum(count)
    row = first.reshape(-1)[conic] + (np.arange(total) - (ends - count)[conic])  # window rows
    cam = (conic // S) % K
    y = (row + y0[cam]).astype(np.float64)           # image rows
    a = c00.reshape(-1)[conic]
    b = 2.0 * (c01.reshape(-1)[conic] * y + c02.reshape(-1)[conic])
    c = (c11.reshape(-1)[conic] * y + 2.0 * c12.reshape(-1)[conic]) * y + c22.reshape(-1)[conic]
    root = np.sqrt(np.maximum(b * b - 4.0 * a * c, 0.0))
    inv2a = 0.5 / a
    wx0 = x0[cam]
    start = np.clip(np.ceil((-b - root) * inv2a - wx0), 0, width).astype(np.int64)
    end = np.clip(np.floor((-b + root) * inv2a - wx0) + 1, 0, width).astype(np.int64)
    keep = end > start
    return (conic // (K * S))[keep], (cam * rows + row)[keep], start[keep], end[keep]


def union_span_sums(batch, row_id, start, end, prefix: np.ndarray, batch_size: int) -> np.ndarray:
    """Sum of per-pixel values over the union of the spans of each row, per batch entry.

    prefix (K, rows, width + 1) per-row prefix sums; returns (batch_size,) totals.
    """
    if batch.size == 0:
        return np.zeros(batch_size, dtype=np.int64)
    K, R, Wp = prefix.shape
    group = batch * (K * R) + row_id
    order = np.argsort(group * Wp + start, kind="stable")
    group, start, end, batch, row_id = group[order], start[order], end[order], batch[order], row_id[order]
    # offset each row group past the previous one so one running maximum sweeps all groups
    offset = group * Wp
    reach = np.maximum.accumulate(end + offset)
    covered_from = np.empty_like(reach)
    covered_from[0] = -1
    covered_from[1:] = reach[:-1]
    s = np.maximum(start + offset, covered_from) - offset
    e = np.maximum(end, s)
    flat = prefix.reshape(-1)
    base = row_id * Wp
    vals = flat[base + e] - flat[base + s]
    return np.bincount(batch, weights=vals, minlength=batch_size).astype(np.int64)


def render_row_spans(row_id, start, end, cameras: int, rows: int, width: int) -> np.ndarray:
    """Flat spans of one pose -> (K, rows, width) bool coverage (pre-rendered static parts)."""
    # +1 where a span starts, -1 where it ends; bincount is many times faster than np.add.at
    size = cameras * rows * (width + 1)
    base = row_id * (width + 1)
    diff = (np.bincount(base + start, minlength=size) - np.bincount(base + end, minlength=size))
    diff = diff.reshape(cameras * rows, width + 1)
    return (np.cumsum(diff, axis=1)[:, :width] > 0).reshape(cameras, rows, width)


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
    volume_points: np.ndarray | None = None  # (n, 3) surface voxel centres, for the volume energy


def surface_distances(points: np.ndarray, centres: np.ndarray, axes: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Distance from each point to each ellipsoid's surface, to first order.

    points (n, 3); centres (..., 3), axes (..., 3, 3) columns, radii (..., 3) -> (..., n), metres.
    With u the point in the ellipsoid's frame over its radii and rho = |u| (1 on the surface),
    the distance is |rho - 1| / |grad rho|. Against the exact closest-point distance
    (``ellipsoid_fit.shell_distances``, Newton's iterations) on a walk frame's surface voxels:
    median 0.1 mm and 90th percentile 1.6 mm within 3 cm of a segment, the same closest
    segment for 98% of the voxels, at a fraction of the cost.
    """
    offsets = points - centres[..., None, :]                          # (..., n, 3)
    u = (offsets @ axes) / radii[..., None, :]
    rho = np.linalg.norm(u, axis=-1)
    grad = np.linalg.norm(u / radii[..., None, :], axis=-1)           # |grad rho| * rho
    return np.abs(rho - 1.0) * rho / np.maximum(grad, 1e-12)


class VolumeEnergy:
    """Bottino's volume energy: weighted squared distances from the surface voxels to the
    closest segment ellipsoid, metres^2 (the ``volume`` backend; windows do not apply, but the
    segments that do not move are measured once, like the XOR energy's pre-rendered masks)."""

    backend = "volume"

    def __init__(self, model: BodyModel, setup: EnergySetup):
        from common.ellipsoid_fit import segment_weights

        if setup.volume_points is None or len(setup.volume_points) == 0:
            raise ValueError("the volume energy needs surface voxels (EnergySetup.volume_points)")
        self.model, self.setup = model, setup
        self.points = np.asarray(setup.volume_points, dtype=np.float64)
        self.weights = segment_weights(model)
        self.evaluations = 0
        self.moving = tuple(setup.moving) if setup.prerender else tuple(range(16))
        static = [s for s in range(16) if s not in self.moving]
        # per point: the closest static segment's distance and weight (inf: none)
        self.static_distance = np.full(len(self.points), np.inf)
        self.static_weight = np.zeros(len(self.points))
        if static:
            d = self._distances(np.atleast_2d(setup.static_params), static)[0]  # (S, n)
            j = np.argmin(d, axis=0)
            self.static_distance = d[j, np.arange(len(self.points))]
            self.static_weight = self.weights[np.asarray(static)[j]]

    def _distances(self, params: np.ndarray, segments) -> np.ndarray:
        """(B, 35) -> (B, S, n) distances from the points to ``segments``."""
        seg = list(segments)
        pose = forward_kinematics(self.model, params, tuple(seg))
        m = self.model
        R = pose.rotations[:, seg]
        centres = pose.origins[:, seg] + np.einsum("bsij,sj->bsi", R, m.ellipsoid_centres[seg])
        return surface_distances(self.points, centres, R @ m.ellipsoid_axes[seg], m.ellipsoid_radii[seg])

    def __call__(self, params: np.ndarray) -> np.ndarray:
        """(B, 35) or (35,) -> (B,) energies."""
        p = np.atleast_2d(params)
        self.evaluations += len(p)
        d = self._distances(p, self.moving)                            # (B, M, n)
        j = np.argmin(d, axis=1)                                        # (B, n) the closest moving segment
        closest = np.take_along_axis(d, j[:, None], axis=1)[:, 0]
        moving_wins = closest < self.static_distance
        weight = np.where(moving_wins, self.weights[np.asarray(self.moving)][j], self.static_weight)
        distance = np.where(moving_wins, closest, self.static_distance)
        return np.sum(weight * distance ** 2, axis=1)


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
        self.width, self.rows = w, h
        self.P = np.stack([c.projection_matrix for c in studio])
        self.y0 = np.array([win.y0 for win in windows], dtype=np.float64)
        self.x0 = np.array([win.x0 for win in windows], dtype=np.float64)
        self.moving = tuple(setup.moving) if setup.prerender else tuple(range(16))
        static = tuple(s for s in range(16) if s not in self.moving)
        I = setup.inputs.astype(np.int32)
        if static:
            M = self._render(setup.static_params, static)
        else:
            M = np.zeros((K, h, w), dtype=bool)
        self.static_mask = M
        v = np.where(M, 0, 1 - 2 * I)
        self.prefix = np.concatenate([np.zeros((K, h, 1), np.int32), np.cumsum(v, axis=2, dtype=np.int32)], axis=2)
        self.base = int(np.count_nonzero(M ^ setup.inputs))

    def _spans(self, params: np.ndarray, segments) -> tuple:
        pose = forward_kinematics(self.model, params, tuple(segments))
        centres, A = ellipsoid_world(self.model, pose.rotations, pose.origins, segments)
        C, drawable = image_conics(self.P, centres, A)
        return conic_row_spans(C, drawable, self.y0, self.x0, self.rows, self.width)

    def _render(self, params: np.ndarray, segments) -> np.ndarray:
        _, row_id, start, end = self._spans(np.atleast_2d(params)[:1], segments)
        return render_row_spans(row_id, start, end, len(self.setup.studio), self.rows, self.width)

    def __call__(self, params: np.ndarray) -> np.ndarray:
        """(B, 35) or (35,) -> (B,) int64 energies (pixels)."""
        p = np.atleast_2d(params)
        batch, row_id, start, end = self._spans(p, self.moving)
        self.evaluations += len(p)
        return self.base + union_span_sums(batch, row_id, start, end, self.prefix, len(p))

    def render(self, params: np.ndarray) -> np.ndarray:
        """(35,) -> (K, h, w) bool: the model's silhouette windows (moving and static parts)."""
        return self._render(params, self.moving) | self.static_mask


ENERGY_BACKENDS = {"cpu": CpuEnergy, "volume": VolumeEnergy}


def make_energy(backend: str, model: BodyModel, setup: EnergySetup):
    if backend == "gl":
        from common.energy_gl import GlEnergy

        return GlEnergy(model, setup)
    try:
        return ENERGY_BACKENDS[backend](model, setup)
    except KeyError:
        raise ValueError(f"unknown energy backend {backend!r}; expected cpu, gl or volume") from None
