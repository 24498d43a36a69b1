"""The XOR energy E(pose) = sum over cameras of w_k |rendered XOR input| inside each camera's window.

One interface, two backends (this module: ``cpu``; ``common.energy_gl``: ``gl``):

- The studio's K input silhouettes are cut into per-camera windows (the paper's sub-windows:
  128x128 around an arm or leg, 64x64 around the head, a hand or a foot, the whole image at
  half resolution for the torso), centred on the part's projection at the start pose.
- Parts that do not move during a sub-optimization are pre-rendered into a static mask M.
  With the input I and the moving parts' render R, inside a window
      |(R or M) xor I| = |M xor I| + sum over R of v,   v = 0 where M, else 1 - 2 I,
  so each evaluation only needs the moving parts and, per window row, two bit masks: the
  pixels where v = +1 and where v = -1.
- The cpu backend renders each segment's ellipsoid exactly as an image conic
  C = (P Q* P^T)^-1 and takes one covered span per (camera, segment, row); the spans are ORed
  into a bit mask per row, so spans that overlap count once, and the sum of v is two
  population counts per 64 pixels: no per-pixel work per evaluation. (Merging the spans in
  sorted order over prefix sums gives the same sums; it took a tenth longer on a 16-part torso
  and a sixth longer on a whole body, about the same on a limb: tools/energy_kernel_bench.py,
  docs/accuracy.md.) The conics and the sums of an evaluation are compiled loops (numba):
  numpy's per-call overhead, not arithmetic, was most of an evaluation's time.
- Each camera's count is weighted (``camera_weights``): a camera that sees the body more than
  1.5 times larger (linearly) than the studio's median camera counts as if it saw it at 1.5
  times the median's scale, so one near camera, whose misfit between body model and actor
  grows with the square of its scale, cannot outvote the others. Where the cameras see the
  body alike (the paper's studio) every weight is 1.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
from numba import njit

from common.body import _SEGMENT_PARENTS, PARAM_COUNT, BodyModel, _forward_kinematics, _segment_mask, forward_kinematics
from common.camera import Studio
from common.conic_bits import (_conic_row_form, _conic_rows, _or_span, _popcount, _row_span, conic_coverage,
                               cut_windows, window_value_bits, xor_bits)
from common.packing import inside_images, padded_shape

ARM_WINDOW = 128   # pixels, windows for upper arm + forearm, thigh + shin
SMALL_WINDOW = 64  # pixels, windows for head, hands, feet
MIN_DEPTH_M = 0.1  # ellipsoids closer to a camera than this are not drawn
POSE_CHUNK = 32    # poses whose conics one compiled evaluation makes at once (pose_energies)


class Window(NamedTuple):
    """A rectangle of one camera's image, in that camera's pixel grid (may extend past edges).
    (A named tuple: a fit makes some 3,000 of them a frame, a frozen dataclass's init took 3 us.)"""

    x0: int
    y0: int
    width: int
    height: int


@njit(cache=True, nogil=True)
def window_corners(R: np.ndarray, t: np.ndarray, K: np.ndarray, centre: np.ndarray, size: int) -> np.ndarray:
    """The corners of windows of ``size`` pixels centred on each camera's projection of
    ``centre``: the pixel nearest to centre - size / 2 (a fit places windows some 400 times a
    frame). R (K, 3, 3), t (K, 3), K (K, 3, 3) pinhole cameras without distortion; centre (3,)
    world -> (K, 2) int (x0, y0)."""
    n = R.shape[0]
    corners = np.empty((n, 2), np.int64)
    for k in range(n):
        xc = np.empty(3)
        for i in range(3):
            xc[i] = centre[0] * R[k, i, 0] + centre[1] * R[k, i, 1] + centre[2] * R[k, i, 2] + t[k, i]
        x, y = xc[0] / xc[2], xc[1] / xc[2]
        u = K[k, 0, 0] * x + K[k, 0, 1] * y + K[k, 0, 2]
        v = K[k, 1, 1] * y + K[k, 1, 2]
        corners[k, 0] = int(np.floor(u - size / 2 + 0.5))
        corners[k, 1] = int(np.floor(v - size / 2 + 0.5))
    return corners


# --------------------------------------------------------------------------- geometry

def ellipsoid_world(model: BodyModel, rotations: np.ndarray, origins: np.ndarray, segments) -> tuple:
    """Posed ellipsoids of ``segments``.

    rotations (B, 16, 3, 3), origins (B, 16, 3) -> centres (B, S, 3), shape matrices A (B, S, 3, 3)
    with the ellipsoid = {c + A u : |u| <= 1}.
    """
    seg = np.asarray(segments, dtype=np.int64)
    local_A = model.ellipsoid_axes[seg] * model.ellipsoid_radii[seg][:, None, :]  # (S, 3, 3)
    return _pose_ellipsoids(rotations, origins, seg, np.ascontiguousarray(model.ellipsoid_centres[seg]), local_A)


@njit(cache=True, nogil=True)
def _pose_ellipsoids(rotations, origins, seg, local_centres, local_A):
    B, S = rotations.shape[0], len(seg)
    centres = np.empty((B, S, 3))
    A = np.empty((B, S, 3, 3))
    for b in range(B):
        for n in range(S):
            R = rotations[b, seg[n]]
            for i in range(3):
                centres[b, n, i] = (R[i, 0] * local_centres[n, 0] + R[i, 1] * local_centres[n, 1]
                                    + R[i, 2] * local_centres[n, 2] + origins[b, seg[n], i])
                for j in range(3):
                    A[b, n, i, j] = R[i, 0] * local_A[n, 0, j] + R[i, 1] * local_A[n, 1, j] + R[i, 2] * local_A[n, 2, j]
    return centres, A


@njit(cache=True, nogil=True)
def image_conics(P: np.ndarray, centres: np.ndarray, A: np.ndarray) -> tuple:
    """Project ellipsoids to image conics (compiled: called once per evaluation).

    P (K, 3, 4) camera matrices, centres (B, S, 3), A (B, S, 3, 3) ->
    conic matrices C (B, K, S, 3, 3) scaled so that x^T C x < 0 inside, and a (B, K, S) bool
    of conics that are drawable (ellipsoid in front of the camera).
    """
    B, S, K = centres.shape[0], centres.shape[1], P.shape[0]
    C = np.empty((B, K, S, 3, 3))
    drawable = np.empty((B, K, S), np.bool_)
    M = np.empty((3, 3))
    x = np.empty(3)
    for b in range(B):
        for s in range(S):
            c, a = centres[b, s], A[b, s]
            for k in range(K):
                # the dual conic D = P Q* P^T, Q* = T diag(1, 1, 1, -1) T^T the dual quadric,
                # T = [[A, c], [0, 1]]: with P T = [M, x], D = M M^T - x x^T (x: the projected
                # centre), two thirds of the arithmetic of P Q* P^T
                for i in range(3):
                    p0, p1, p2 = P[k, i, 0], P[k, i, 1], P[k, i, 2]
                    for j in range(3):
                        M[i, j] = p0 * a[0, j] + p1 * a[1, j] + p2 * a[2, j]
                    x[i] = p0 * c[0] + p1 * c[1] + p2 * c[2] + P[k, i, 3]
                d00 = M[0, 0] * M[0, 0] + M[0, 1] * M[0, 1] + M[0, 2] * M[0, 2] - x[0] * x[0]
                d11 = M[1, 0] * M[1, 0] + M[1, 1] * M[1, 1] + M[1, 2] * M[1, 2] - x[1] * x[1]
                d22 = M[2, 0] * M[2, 0] + M[2, 1] * M[2, 1] + M[2, 2] * M[2, 2] - x[2] * x[2]
                d01 = M[0, 0] * M[1, 0] + M[0, 1] * M[1, 1] + M[0, 2] * M[1, 2] - x[0] * x[1]
                d02 = M[0, 0] * M[2, 0] + M[0, 1] * M[2, 1] + M[0, 2] * M[2, 2] - x[0] * x[2]
                d12 = M[1, 0] * M[2, 0] + M[1, 1] * M[2, 1] + M[1, 2] * M[2, 2] - x[1] * x[2]
                # adjugate of the (symmetric) dual conic = conic up to a scale whose sign is fixed
                # by the projected centre, which is inside
                a00 = d11 * d22 - d12 * d12
                a11 = d00 * d22 - d02 * d02
                a22 = d00 * d11 - d01 * d01
                a01 = d02 * d12 - d01 * d22
                a02 = d01 * d12 - d02 * d11
                a12 = d01 * d02 - d00 * d12
                inside = (x[0] * (a00 * x[0] + a01 * x[1] + a02 * x[2]) + x[1] * (a01 * x[0] + a11 * x[1] + a12 * x[2])
                          + x[2] * (a02 * x[0] + a12 * x[1] + a22 * x[2]))
                sign = -1.0 if inside > 0 else 1.0
                C[b, k, s, 0, 0], C[b, k, s, 1, 1], C[b, k, s, 2, 2] = a00 * sign, a11 * sign, a22 * sign
                C[b, k, s, 0, 1] = C[b, k, s, 1, 0] = a01 * sign
                C[b, k, s, 0, 2] = C[b, k, s, 2, 0] = a02 * sign
                C[b, k, s, 1, 2] = C[b, k, s, 2, 1] = a12 * sign
                drawable[b, k, s] = x[2] > MIN_DEPTH_M
    return C, drawable


@njit(cache=True, nogil=True)
def xor_span_sums(C: np.ndarray, drawable: np.ndarray, y0: np.ndarray, x0: np.ndarray, rows: int, width: int,
                  gain: np.ndarray, loss: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Sum of per-pixel values over the union of the conics' covered spans, each camera's
    times its weight, per batch entry: the evaluation's inner loop. Covers the pixels
    ``conic_coverage`` covers.

    C (B, K, S, 3, 3) conics (negative inside); drawable (B, K, S); y0, x0 (K,) window corners;
    gain, loss (K, rows, words) the values as bit masks (``xor_bits``); weights (K,) float64
    (``camera_weights``) -> (B,) float64 sums.
    """
    B, K, S = C.shape[0], C.shape[1], C.shape[2]
    words = gain.shape[2]
    out = np.zeros(B, np.float64)
    union = np.zeros((rows, words), np.uint64)  # the covered pixels of one camera, zeroed as summed
    fw = float(width)
    for b in range(B):
        total = 0.0
        for k in range(K):
            camera = 0
            top, bottom = rows, 0
            for s in range(S):
                first, last = _conic_rows(C[b, k, s], drawable[b, k, s], y0[k], rows)
                if last <= first:
                    continue
                top, bottom = min(top, first), max(bottom, last)
                cu, cv, q0, q1, q2 = _conic_row_form(C[b, k, s], x0[k])
                for row in range(first, last):
                    start, end = _row_span(cu, cv, q0, q1, q2, float(row) + y0[k], fw)
                    if end > start:
                        _or_span(union, row, start, end)
            for row in range(top, bottom):
                u, g, l = union[row], gain[k, row], loss[k, row]
                for j in range(words):
                    camera += np.int64(_popcount(u[j] & g[j])) - np.int64(_popcount(u[j] & l[j]))
                    u[j] = np.uint64(0)
            total += weights[k] * camera
        out[b] = total
    return out


@njit(cache=True, nogil=True)
def pose_energies(p, rest_offsets, param_joint, param_axis, parents, offsets, head_top_offset, needed, seg,
                  local_centres, local_A, P, y0, x0, rows, width, gain, loss, weights) -> np.ndarray:
    """The moving parts' XOR sums of a batch of poses in one compiled call: forward kinematics,
    posed ellipsoids, conics and spans (each step the same arithmetic as its own kernel).

    p (B, 35); the kinematic tables (``BodyModel.kinematic_tables``), segment parents (16,)
    and the segments needed (16,) bool; seg (S,) the moving segments, their local ellipsoid
    centres (S, 3) and axes scaled by radii (S, 3, 3); then as ``xor_span_sums`` -> (B,) float64.
    One call instead of four kernels and their numpy glue: the glue cost as much as the work.
    Large batches (a limb's grid) go through in chunks of POSE_CHUNK poses, whose conics stay
    in the cache: a re-detection's grid of 2,916 poses made 5 MB of conics at once.
    """
    B = p.shape[0]
    out = np.empty(B, np.float64)
    for c0 in range(0, B, POSE_CHUNK):
        c1 = min(B, c0 + POSE_CHUNK)
        C, drawable = pose_conics(p[c0:c1], rest_offsets, param_joint, param_axis, parents, offsets, head_top_offset,
                                  needed, seg, local_centres, local_A, P)
        out[c0:c1] = xor_span_sums(C, drawable, y0, x0, rows, width, gain, loss, weights)
    return out


@njit(cache=True, nogil=True, inline="always")
def pose_conics(p, rest_offsets, param_joint, param_axis, parents, offsets, head_top_offset, needed, seg,
                local_centres, local_A, P) -> tuple:
    """``pose_energies``' geometry: poses p (B, 35) and the tables as it takes them -> the
    moving segments' conics (B, K, S, 3, 3) and drawable (B, K, S), as ``image_conics``."""
    rot, org, _ = _forward_kinematics(p, rest_offsets, param_joint, param_axis, parents, offsets, head_top_offset,
                                      needed)
    centres, A = _pose_ellipsoids(rot, org, seg, local_centres, local_A)
    return image_conics(P, centres, A)


# ------------------------------------------------------------------------ the energy

@dataclass(frozen=True)
class EnergySetup:
    """Everything that stays fixed during one sub-optimization.

    studio: cameras (already scaled for half-resolution work); windows: one per camera;
    inputs: (K, h, w) bool input silhouette windows, h and w the largest window height and
    width, window k's pixels at [:height, :width] (windows of one size fill it; whole images of
    cameras of different sizes are padded, as ``packing.pad_stack``): pixels beyond a window
    are outside it and count for nothing, whatever covers them; or None where ``packed`` is
    given; moving: segments that move; static_params: (35,) pose whose other segments are
    pre-rendered; packed: (K, H, words) uint64 the whole images' silhouettes as row bits
    (``conic_bits.pack_rows``, each camera's pixels beyond its own image clear), which windows
    of one size are cut from (``input_windows``) and which the cpu energy reads without cutting
    byte windows. Where both are given they must hold the same pixels; the cpu energy reads
    ``packed``. bounds: (K, 4) int64 x_lo, y_lo, x_hi, y_hi, the pixels of each camera that
    count (``counted_bounds``: a camera's image edges that its silhouette touches, past which a
    body may reach unseen), or None: every pixel; a window's pixels beyond them count for
    nothing, whatever covers them. weights: (K,) float64, each camera's pixels' worth
    (``camera_weights``), or None: 1 each.
    """

    studio: Studio
    windows: tuple
    inputs: np.ndarray | None
    moving: tuple
    static_params: np.ndarray
    prerender: bool = True
    volume_points: np.ndarray | None = None  # (n, 3) surface voxel centres, for the volume energy
    packed: np.ndarray | None = None
    bounds: np.ndarray | None = None
    weights: np.ndarray | None = None

    def __post_init__(self):
        if self.inputs is None and self.packed is None:
            raise ValueError("an energy setup needs its input windows or the packed silhouettes they are cut from")
        if self.packed is not None:
            if not len(self.studio) == len(self.windows) == self.packed.shape[0]:
                raise ValueError(f"{len(self.studio)} cameras need as many windows and packed silhouettes, got "
                                 f"{len(self.windows)} and {self.packed.shape[0]}")
            if len({(w.width, w.height) for w in self.windows}) != 1:
                raise ValueError("windows cut from packed silhouettes must be of one size")
        if self.inputs is not None:
            K, h, w = self.inputs.shape
            if len(self.studio) != K or len(self.windows) != K:
                raise ValueError(f"{len(self.studio)} cameras need as many windows and input windows, got "
                                 f"{len(self.windows)} and {K}")
            largest = padded_shape([(win.width, win.height) for win in self.windows])
            if largest != (h, w):
                raise ValueError(f"input windows are {w}x{h}, the windows' largest width and height "
                                 f"{largest[1]}x{largest[0]}")
        if self.weights is not None:
            w = np.asarray(self.weights)
            if w.shape != (len(self.studio),) or not (np.all(np.isfinite(w)) and np.all(w > 0)):
                raise ValueError(f"{len(self.studio)} cameras need as many positive weights, got {w.tolist()}")

    @property
    def camera_weights(self) -> np.ndarray:
        """(K,) float64: ``weights``, or 1 for every camera where None."""
        return (np.ones(len(self.studio)) if self.weights is None
                else np.ascontiguousarray(self.weights, dtype=np.float64))

    @property
    def input_windows(self) -> np.ndarray:
        """(K, h, w) bool: ``inputs``, or the windows cut from ``packed`` (cut on each call: the
        byte energies, gl, read them once per build)."""
        if self.inputs is not None:
            return self.inputs
        x0, y0 = window_origins(self.windows)
        return cut_windows(self.packed, x0, y0, self.windows[0].height, self.windows[0].width)


def window_origins(windows) -> tuple:
    """The windows' corners as (K,) int64 arrays (x0, y0)."""
    return (np.array([w.x0 for w in windows], dtype=np.int64), np.array([w.y0 for w in windows], dtype=np.int64))


EDGE_TOUCH_PX = 2  # silhouette pixels this near an image's edge touch it (masks are cleaned, resampled)
EDGE_RUN_PX = 3    # ... in a run at least this long along it: a speck of noise is not a body crossing
_FAR_PX = 1 << 30  # a bound no window reaches


def open_image_edges(masks: np.ndarray, sizes) -> np.ndarray:
    """(K, H, W) bool silhouettes of cameras of ``sizes`` (K, 2) (width, height) pixels, each
    at [:h_k, :w_k] -> (K, 4) bool: whether camera k's silhouette touches its image's left,
    top, right and bottom edge (``EDGE_RUN_PX`` pixels in a row along it, within
    ``EDGE_TOUCH_PX`` of it); all four for an empty silhouette. A body seen in part that
    reaches past an edge crosses it, so the edges its silhouette does not touch are edges it
    stays inside; a body not seen at all may be anywhere outside the image."""
    sizes = np.asarray(sizes, dtype=np.int64).reshape(-1, 2)
    out = np.ones((len(sizes), 4), dtype=bool)
    e = EDGE_TOUCH_PX
    for k, (w, h) in enumerate(sizes):
        m = masks[k, :h, :w]
        if m.any():
            out[k] = [_longest_run(strip) >= EDGE_RUN_PX
                      for strip in (m[:, :e].any(1), m[:e].any(0), m[:, w - e:].any(1), m[h - e:].any(0))]
    return out


def _longest_run(flags: np.ndarray) -> int:
    """The most True values in a row in (n,) bool ``flags``."""
    edges = np.diff(np.concatenate(([0], flags.astype(np.int8), [0])))
    return int((np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)).max(initial=0))


def counted_bounds(studio: Studio, open_edges: np.ndarray | None) -> np.ndarray:
    """(K, 4) int64 x_lo, y_lo, x_hi, y_hi: the pixels of each camera an energy counts
    (``EnergySetup.bounds``), its image's edges where ``open_edges`` (K, 4) bool
    (``open_image_edges``) are set: a body may reach past them unseen; no bound elsewhere: past
    an edge the silhouette does not touch the body cannot be (it would cross the edge), so it
    pays there as anywhere outside the silhouette."""
    far = np.array([-_FAR_PX, -_FAR_PX, _FAR_PX, _FAR_PX], dtype=np.int64)
    bounds = np.tile(far, (len(studio), 1))
    if open_edges is not None:
        edges = np.array([(0, 0, w, h) for w, h in studio.sizes], dtype=np.int64).reshape(-1, 4)
        bounds = np.where(np.asarray(open_edges, dtype=bool), edges, bounds)
    return bounds


# A camera that sees the body at s times the median camera's scale (focal length over depth)
# sees it s^2 times larger, and the body model's misfit to the actor with it: a walk 2.2 m
# from the middle of the 3 m ring neared one camera to 0.8 m, which then held 60% of all
# silhouette pixels and fitted an arm past the edges of the views that saw it
# (docs/accuracy.md, "A near camera").
# Up to this many times the median camera's scale a camera counts in full, as in the paper's
# energy. At 1 (every camera nearer than the median down-weighted, up to 0.4 with the actor 1 m
# from the middle of the ring) the posture takes moved by chance with the changed landscape,
# 6.30 -> 6.78 mm on average, the chair's first frame to another pose; at 1.5 the default
# ring's cameras count in full wherever an actor stands within 0.9 m of its middle.
FULL_WEIGHT_SCALE = 1.5
# Weights are multiples of this: integer pixel counts times them add up exactly in float64, in
# any order, so a pre-rendered window's energy still equals the whole render's, and ties stay ties
WEIGHT_STEP = 1.0 / 1024


def camera_weights(studio: Studio, centre: np.ndarray | None) -> np.ndarray | None:
    """(K,) float64: what a pixel of each camera is worth (``EnergySetup.weights``), 1 for a
    camera that sees a body at ``centre`` (3,) m no larger than FULL_WEIGHT_SCALE times the
    median camera does, else (FULL_WEIGHT_SCALE median scale / its scale)^2, scale being focal
    length (pixels) over the centre's depth: a camera much nearer or sharper than the others
    counts as if it saw the body at FULL_WEIGHT_SCALE times the median's size; multiples of
    WEIGHT_STEP, at least WEIGHT_STEP. None (every weight 1) where ``centre`` is None (fewer than
    two cameras see a silhouette: ``voxels.silhouette_centre``)."""
    if centre is None:
        return None
    cams = studio.cameras
    depth = np.array([c.depth(centre) for c in cams])
    scale = np.array([0.5 * (c.K[0, 0] + c.K[1, 1]) for c in cams]) / np.maximum(depth, MIN_DEPTH_M)
    weights = np.minimum(1.0, (FULL_WEIGHT_SCALE * np.median(scale) / scale) ** 2)
    return np.maximum(WEIGHT_STEP, np.round(weights / WEIGHT_STEP) * WEIGHT_STEP)


def whole_energy(value) -> int:
    """An energy (pixels, weighted by ``camera_weights``: float64) as the whole number results
    carry and compare, rounded: the same on the server, which checks a client's claim, and on
    every client."""
    return int(round(float(value)))


def window_pixels(setup: EnergySetup) -> np.ndarray | None:
    """(K, h, w) bool: the pixels of ``setup.input_windows`` an energy counts and a render
    shows, those inside each camera's window and its ``bounds`` (``EnergySetup``, which checks
    that the windows fit the inputs); None when that is all of them."""
    shape = padded_shape([(win.width, win.height) for win in setup.windows])
    counted = inside_images([(win.width, win.height) for win in setup.windows], shape)
    if setup.bounds is not None:
        x_lo, y_lo, x_hi, y_hi = setup.bounds.T
        x0, y0 = window_origins(setup.windows)
        ys = y0[:, None] + np.arange(shape[0])[None, :]  # (K, h) image rows
        xs = x0[:, None] + np.arange(shape[1])[None, :]  # (K, w) image columns
        counted &= ((ys >= y_lo[:, None]) & (ys < y_hi[:, None]))[:, :, None]
        counted &= ((xs >= x_lo[:, None]) & (xs < x_hi[:, None]))[:, None, :]
    return None if counted.all() else counted


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
    """The ``cpu`` backend: analytic ellipsoid silhouettes, spans ORed into bit masks."""

    backend = "cpu"

    def __init__(self, model: BodyModel, setup: EnergySetup):
        self.model = model
        self.setup = setup
        self.evaluations = 0
        studio, windows = setup.studio, setup.windows
        if setup.inputs is None:
            self.rows, self.width = windows[0].height, windows[0].width
        else:
            self.rows, self.width = setup.inputs.shape[1:]
        self.P = studio.projection_matrices
        x0, y0 = window_origins(windows)
        self.x0, self.y0 = x0.astype(np.float64), y0.astype(np.float64)
        self.moving = tuple(setup.moving) if setup.prerender else tuple(range(16))
        self._static = tuple(s for s in range(16) if s not in self.moving)
        self._static_mask = None
        if setup.packed is not None:  # straight from the row bits (windows of one size)
            if self._static:
                C, drawable = self._conics(np.atleast_2d(setup.static_params)[:1], self._static)
            else:
                C, drawable = np.zeros((1, len(studio), 0, 3, 3)), np.zeros((1, len(studio), 0), np.bool_)
            bounds = setup.bounds if setup.bounds is not None else counted_bounds(studio, None)
            self.gain, self.loss, base = window_value_bits(setup.packed, x0, y0, self.rows, self.width, C, drawable,
                                                           bounds)
        else:
            self._static_mask = M = self._render_static()
            inputs = np.ascontiguousarray(setup.input_windows, dtype=np.bool_)
            if self.counted is not None:  # beyond what is counted static and input both set: v = 0, no base
                M, inputs = M | ~self.counted, inputs | ~self.counted
            self.gain, self.loss, base = xor_bits(M, inputs)
        self.weights = setup.camera_weights
        self.base = float(base @ self.weights)
        seg = np.asarray(self.moving, dtype=np.int64)
        self.kernel_tables = (*model.kinematic_tables[:3], _SEGMENT_PARENTS, *model.kinematic_tables[3:],
                               _segment_mask(self.moving), seg,
                               np.ascontiguousarray(model.ellipsoid_centres[seg]),
                               model.ellipsoid_axes[seg] * model.ellipsoid_radii[seg][:, None, :],
                               self.P, self.y0, self.x0, self.rows, self.width, self.gain, self.loss, self.weights)

    @cached_property
    def counted(self) -> np.ndarray | None:
        """``window_pixels``: what the energy counts and a render shows (drawn on first use where
        the energy was built from packed rows, whose value bits hold it: a fit builds thousands)."""
        return window_pixels(self.setup)

    @property
    def static_mask(self) -> np.ndarray:
        """(K, h, w) bool: the pre-rendered parts' pixels (drawn on first use where the energy
        was built from packed rows)."""
        if self._static_mask is None:
            self._static_mask = self._render_static()
        return self._static_mask

    def _render_static(self) -> np.ndarray:
        if self._static:
            return self._render(self.setup.static_params, self._static)
        return np.zeros((len(self.setup.studio), self.rows, self.width), dtype=bool)

    def _conics(self, params: np.ndarray, segments) -> tuple:
        pose = forward_kinematics(self.model, params, tuple(segments))
        centres, A = ellipsoid_world(self.model, pose.rotations, pose.origins, segments)
        return image_conics(self.P, centres, A)

    def _render(self, params: np.ndarray, segments) -> np.ndarray:
        C, drawable = self._conics(np.atleast_2d(params)[:1], segments)
        covered = conic_coverage(C, drawable, self.y0, self.x0, self.rows, self.width)[0]
        return covered if self.counted is None else covered & self.counted

    def __call__(self, params: np.ndarray) -> np.ndarray:
        """(B, 35) or (35,) -> (B,) float64 energies (pixels, weighted: ``camera_weights``)."""
        p = np.atleast_2d(np.asarray(params, dtype=np.float64))
        if p.shape[1] != PARAM_COUNT:
            raise ValueError(f"expected {PARAM_COUNT} parameters, got {p.shape[1]}")
        self.evaluations += len(p)
        return self.base + pose_energies(p, *self.kernel_tables)

    def render(self, params: np.ndarray) -> np.ndarray:
        """(35,) -> (K, h, w) bool: the model's silhouette windows (moving and static parts)."""
        return self._render(params, self.moving) | self.static_mask
