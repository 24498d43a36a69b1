"""Voxel reconstruction from K silhouettes by SPOT (Cheung et al. 2000, section 3.2-3.3).

The volume of interest is cut into an N x N x N grid. For every voxel and camera a lookup
table holds Q sample pixels spread over the voxel's image (sample points inside the voxel,
projected once at build time). A voxel is INSIDE for camera k when at least ``eps * Q`` of
its samples are silhouette pixels (the paper's Is_Overlap); cameras are tested in turn and
a voxel rejected by one camera is never tested again (early rejection). Surface voxels are
occupied voxels with at least one empty 6-neighbour (section 3.3).

Speed comes from the data layout: the K masks are one flat uint8 buffer, the lookup table
holds flat int32 indices into it, the alive set is a compacted index array per camera, and
a coarse pass over blocks of B^3 voxels first discards blocks whose whole image footprint
is empty in some camera (an exact test: then every sample of every voxel in it is
background, so SPOT would reject them all). Results are identical with and without it.

Error model (section 3.2, with eps * Q = 1): if silhouette pixels are lost with probability
eta and background pixels turn into silhouette with probability xi, independently, then
P(FA) = [1 - (1 - xi)^Q]^K and P(FR) = eta^Q sum_{i<K} (1 - eta^Q)^i; see
``false_acceptance_probability`` and ``false_rejection_probability``.

One module of about 600 lines: SPOT's lookup tables, the reconstruction and the hull's surface
share one grid layout.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from common.blobs import big_blobs_centroid
from common.camera import Studio, circle_studio
from common.errors import InputFileError, UserError
from common.packing import pad_stack

DEFAULT_EXTENT = np.array([2.4, 2.4, 2.2])  # metres: x, y, z size of the volume of interest
SAMPLE_RADIUS = 0.45  # sample offsets from the voxel centre, in voxel edges (< 0.5 stays inside)
MIN_VIEWS = 2  # a voxel seen by fewer cameras is never occupied (no constraint on it)
UNSEEN_IS_FOREGROUND = True  # a camera cannot carve what it does not see
TILE = 4  # pixels per side of the tiles the coarse pass counts silhouette pixels in
BUILD_CHUNK = 1 << 18  # voxels projected at a time while building the lookup table
VOXEL_FORMAT = "silhouette-mocap-voxels"  # tag of the .npz files of save_voxels
VOXEL_VERSION = 1


def studio_target(studio: Studio) -> np.ndarray:
    """(3,) the point closest (least squares) to all cameras' optical axes, metres."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for cam in studio:
        d = cam.R[2]  # optical axis in world coordinates
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    return np.linalg.lstsq(A, b, rcond=None)[0]


def default_bounds(studio: Studio) -> np.ndarray:
    """(2, 3) lower and upper corners: a DEFAULT_EXTENT box centred on the studio target, z from 0."""
    c = studio_target(studio)
    lo = np.array([c[0] - DEFAULT_EXTENT[0] / 2, c[1] - DEFAULT_EXTENT[1] / 2, 0.0])
    return np.stack([lo, lo + DEFAULT_EXTENT])


BOUNDS_LATTICE_M = 0.25  # actor-centred boxes snap to this lattice, so their lookup tables repeat


# Silhouette blobs smaller than this fraction of the image are noise: Cheung-noise specks
# measured up to 69 of 76800 pixels (1,500 of them per image), while an actor's silhouette,
# even a sliver at the image's border, is larger.
MIN_BLOB_FRACTION = 0.002


def silhouette_centre(studio: Studio, masks: np.ndarray) -> np.ndarray | None:
    """(3,) the point closest (least squares) to the rays through each silhouette's centroid,
    metres; None when fewer than two cameras see a silhouette. The centroid is that of the
    mask's blobs of MIN_BLOB_FRACTION of the image or more (masks: (K, H, W) bool, the padded
    stack of ``packing.pad_stack`` when the cameras differ in size): a camera the actor has left
    sees only noise, whose centroid is the image's middle, and its ray would pull the centre
    (06_02 from source frame 262: three of eight cameras, the centre 1.6 m off)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for cam, mask in zip(studio, masks):
        mask = np.asarray(mask[:cam.height, :cam.width], dtype=bool)  # the camera's own image of a padded stack
        x, y, n = big_blobs_centroid(mask, MIN_BLOB_FRACTION * mask.size)
        if n == 0:
            continue
        ray = cam.R.T @ np.linalg.solve(cam.K, np.array([x, y, 1.0]))
        ray /= np.linalg.norm(ray)
        proj = np.eye(3) - np.outer(ray, ray)
        A += proj
        b += proj @ cam.center
    if np.linalg.matrix_rank(A) < 3:
        return None
    return np.linalg.solve(A, b)


def actor_bounds(studio: Studio, masks: np.ndarray) -> np.ndarray:
    """(2, 3) a DEFAULT_EXTENT box centred on the actor (the silhouettes' centre, snapped to
    BOUNDS_LATTICE_M), z from 0: the studio's default box misses an actor who walks out of
    the middle of a large capture area. Falls back to ``default_bounds``."""
    return bounds_around(studio, [silhouette_centre(studio, masks)])


def bounds_around(studio: Studio, centres: list) -> np.ndarray:
    """(2, 3) the DEFAULT_EXTENT box around each of ``centres`` ((3,) actor centres, metres, or
    None), all in one box, its sides snapped to BOUNDS_LATTICE_M, z from 0: where an actor
    moves through a take. ``default_bounds`` where no centre is known."""
    known = np.array([c[:2] for c in centres if c is not None]).reshape(-1, 2)
    if not len(known):
        return default_bounds(studio)
    low = np.round(known.min(axis=0) / BOUNDS_LATTICE_M) * BOUNDS_LATTICE_M
    high = np.round(known.max(axis=0) / BOUNDS_LATTICE_M) * BOUNDS_LATTICE_M
    lo = np.array([*(low - DEFAULT_EXTENT[:2] / 2), 0.0])
    return np.stack([lo, lo + DEFAULT_EXTENT + np.array([*(high - low), 0.0])])


def false_acceptance_probability(xi: float, q: int, k: int) -> float:
    """Eq. 3: an outside voxel passes all K cameras, each on at least one of Q false pixels."""
    return float((1.0 - (1.0 - xi) ** q) ** k)


def false_rejection_probability(eta: float, q: int, k: int) -> float:
    """Eq. 4: an inside voxel loses all Q samples in one of the K cameras (tested in turn)."""
    p = eta ** q
    return float(p * sum((1.0 - p) ** i for i in range(k)))


@dataclass(frozen=True)
class VoxelResult:
    """One frame's reconstruction.

    occupied: (N, N, N) bool, index [i, j, k] along x, y, z; surface: (N, N, N) bool or None
    when not asked for; origin (3,) the grid's lower corner and voxel_size (3,), metres;
    tests: pixel samples read (the cost SPOT saves by early rejection); box: half-open index
    ranges ((i0, i1), (j0, j1), (k0, k1)) bounding the occupied voxels, None if unknown or empty.
    """

    occupied: np.ndarray
    surface: np.ndarray | None
    origin: np.ndarray
    voxel_size: np.ndarray
    tests: int
    box: tuple | None = None

    def centres(self, mask: np.ndarray) -> np.ndarray:
        """(N, N, N) bool -> (n, 3) centres of the selected voxels, metres.

        A mask inside the occupied voxels (occupied, surface) is only scanned within ``box``.
        """
        if self.box is not None and (mask is self.occupied or mask is self.surface):
            lo = np.array([b[0] for b in self.box])
            idx = np.stack(np.nonzero(mask[tuple(slice(a, b) for a, b in self.box)]), axis=1) + lo
        else:
            idx = np.stack(np.nonzero(mask), axis=1)
        return self.origin + (idx + 0.5) * self.voxel_size

    def surface_points(self) -> np.ndarray:
        """(n, 3) centres of the surface voxels."""
        if self.surface is None:
            raise ValueError("reconstructed without surface extraction")
        return self.centres(self.surface)

    def turned(self, rotation: np.ndarray) -> "VoxelResult":
        """The same voxels in another frame, x_other = rotation @ x (3, 3), a signed permutation
        (a world's up axis turned onto ours, ``common.world``): the arrays' axes permuted and
        flipped so that index [i, j, k] runs along the other frame's x, y, z."""
        rotation = np.rint(np.asarray(rotation, dtype=np.float64)).astype(int)
        if sorted(np.abs(rotation).sum(axis=0)) != [1, 1, 1] or sorted(np.abs(rotation).sum(axis=1)) != [1, 1, 1]:
            raise ValueError("a voxel grid turns only by a signed permutation of its axes")
        source = np.abs(rotation).argmax(axis=1)              # other axis i is this frame's axis source[i]
        sign = rotation[np.arange(3), source]
        shape = np.array(self.occupied.shape)[source]
        size = self.voxel_size[source]
        far = self.origin[source] + shape * size               # the upper corner along each axis
        origin = np.where(sign > 0, self.origin[source], -far)

        def turn(a):
            if a is None:
                return None
            a = np.transpose(a, source)
            return np.flip(a, axis=tuple(int(i) for i in np.nonzero(sign < 0)[0])) if (sign < 0).any() else a

        return VoxelResult(np.ascontiguousarray(turn(self.occupied)), None if self.surface is None else
                           np.ascontiguousarray(turn(self.surface)), origin, size, self.tests)


def sample_offsets(q: int) -> np.ndarray:
    """(Q, 2) sample positions in the image plane, in voxel edges from the centre.

    Q = 1: the centre; otherwise Q points on a circle, so that their pixels are distinct
    whenever the voxel's image spans a few pixels (what Eq. 3 and 4 assume).
    """
    if q == 1:
        return np.zeros((1, 2))
    a = 2.0 * np.pi * (np.arange(q) + 0.5) / q
    return SAMPLE_RADIUS * np.stack([np.cos(a), np.sin(a)], axis=1)


class SpotGrid:
    """The voxel grid of one studio with its SPOT lookup tables; reusable for every frame.

    Build with ``SpotGrid.build``. Voxels are stored block-major (blocks of B^3 voxels are
    contiguous) so that the coarse pass selects whole rows of the lookup table.
    """

    def __init__(self, studio, bounds, grid, q, threshold, block, lut, block_sat, block_unseen,
                 live_blocks, bm_to_grid, image_shape):
        self.studio = studio
        self.bounds = bounds
        self.grid = grid
        self.q = q
        self.threshold = threshold
        self.block = block
        self.lut = lut  # (K, Q, nblocks, B^3) int32 indices into the frame buffer
        self.block_sat = block_sat  # (K, 4, nblocks) int32 indices into the tile SAT buffer
        self.block_unseen = block_unseen  # (K, nblocks) bool: some sample outside camera k
        self.live_blocks = live_blocks  # (n,) int32 blocks holding a voxel seen by MIN_VIEWS cameras
        self.bm_to_grid = bm_to_grid  # (M,) int32 block-major voxel -> grid flat index i N^2 + j N + k
        self.image_shape = image_shape  # (H, W) of the frames' mask stack: the largest camera height, width
        self.voxel_size = (bounds[1] - bounds[0]) / grid
        H, W = image_shape
        self._pixels = len(studio) * H * W
        self._tiles = (-(-H // TILE), -(-W // TILE))

    # ------------------------------------------------------------------ build
    @classmethod
    def build(cls, studio: Studio, grid: int = 64, q: int = 2, bounds=None, epsilon: float | None = None,
              block: int | None = None) -> "SpotGrid":
        """Precompute the lookup tables of an N^3 grid with Q samples per voxel and camera.

        bounds: (2, 3) lower and upper corners in metres (default ``default_bounds``);
        epsilon: the paper's eps, a voxel is inside for a camera when at least eps * Q of its
        samples are silhouette (default 1 / Q, as in the paper); block: voxels per coarse
        block edge (default: 4, or smaller when it does not divide N).
        """
        if not isinstance(grid, (int, np.integer)) or grid < 2:
            raise UserError(f"grid: expected an integer >= 2, got {grid!r}")
        if not isinstance(q, (int, np.integer)) or not 1 <= q <= 64:
            raise UserError(f"q: expected an integer in 1..64, got {q!r}")
        eps = 1.0 / q if epsilon is None else float(epsilon)
        if not 0.0 < eps <= 1.0:
            raise UserError(f"epsilon: expected 0 < eps <= 1, got {epsilon!r}")
        threshold = int(np.ceil(eps * q - 1e-9))
        bounds = default_bounds(studio) if bounds is None else np.asarray(bounds, dtype=np.float64)
        if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)) or np.any(bounds[1] <= bounds[0]):
            raise UserError(f"bounds: expected (2, 3) lower and upper corners with lower < upper, got {bounds!r}")
        # cameras of different sizes: frames are padded stacks (packing.pad_stack), each
        # camera's samples inside its own image
        H, W = studio.padded_shape
        if block is None:
            block = next(b for b in (4, 2, 1) if grid % b == 0)
        if grid % block:
            raise UserError(f"block: {block} does not divide grid {grid}")

        N, B, K = int(grid), int(block), len(studio)
        nb = N // B
        B3 = B ** 3
        M = N ** 3
        voxel = (bounds[1] - bounds[0]) / N
        # Block-major order: voxel m = block * B^3 + local; block = (bi, bj, bk), local = (li, lj, lk).
        m = np.arange(M, dtype=np.int64)
        blk, loc = np.divmod(m, B3)
        bi, rem = np.divmod(blk, nb * nb)
        bj, bk = np.divmod(rem, nb)
        li, rem = np.divmod(loc, B * B)
        lj, lk = np.divmod(rem, B)
        ijk = np.stack([bi * B + li, bj * B + lj, bk * B + lk], axis=1)
        del m, blk, loc, bi, bj, bk, li, lj, lk, rem
        bm_to_grid = ((ijk[:, 0] * N + ijk[:, 1]) * N + ijk[:, 2]).astype(np.int32)

        pixels = K * H * W
        unseen_index, dead_index = pixels, pixels + 1  # the frame buffer's two trailing bytes
        offsets = sample_offsets(q)
        nblocks = nb ** 3
        lut = np.empty((K, q, M), dtype=np.int32)
        views = np.zeros(M, dtype=np.int8)
        rect = np.empty((4, K, nblocks), dtype=np.int64)  # tile x0, y0, x1, y1 per camera and block
        chunk = max(B3, BUILD_CHUNK - BUILD_CHUNK % B3)
        for start in range(0, M, chunk):
            sl = slice(start, min(M, start + chunk))
            bsl = slice(sl.start // B3, sl.stop // B3)
            centres = bounds[0] + (ijk[sl] + 0.5) * voxel
            for k, cam in enumerate(studio):
                # Spread the samples along the camera's image axes so that their pixels differ.
                pts = centres[None] + (offsets @ cam.R[:2])[:, None, :] * voxel  # (Q, n, 3)
                uv = np.rint(cam.project(pts)).astype(np.int64)
                inside = ((cam.depth(pts) > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < cam.width)
                          & (uv[..., 1] >= 0) & (uv[..., 1] < cam.height))
                lut[k, :, sl] = np.where(inside, k * H * W + uv[..., 1] * W + uv[..., 0], unseen_index)
                views[sl] += inside.all(axis=0)
                tiles = np.where(inside[..., None], uv // TILE, 0).reshape(q, -1, B3, 2)
                ins = inside.reshape(q, -1, B3, 1)
                big = np.iinfo(np.int32).max
                rect[0:2, k, bsl] = np.where(ins, tiles, big).min(axis=(0, 2)).T
                rect[2:4, k, bsl] = np.where(ins, tiles, -1).max(axis=(0, 2)).T
        del ijk
        dead = views < min(MIN_VIEWS, K)
        lut[:, :, dead] = dead_index
        unseen = (lut == unseen_index).any(axis=1).reshape(K, nblocks, B3).any(axis=2)

        # Coarse blocks: SAT corners of the tile rectangle covering every in-image sample.
        th, tw = -(-H // TILE), -(-W // TILE)
        x0, y0, x1, y1 = rect
        empty = x1 < 0  # no sample inside the image: all four corners at S[0, 0] = 0
        base = (np.arange(K) * (th + 1) * (tw + 1))[:, None]
        corners = [np.where(empty, base, base + y * (tw + 1) + x)
                   for y, x in ((y1 + 1, x1 + 1), (y0, x1 + 1), (y1 + 1, x0), (y0, x0))]
        block_sat = np.stack(corners, axis=1).astype(np.int32)  # (K, 4, nblocks)
        live_blocks = np.flatnonzero(~dead.reshape(nblocks, B3).all(axis=1)).astype(np.int32)
        return cls(studio, bounds, N, q, threshold, B, lut.reshape(K, q, nblocks, B3),
                   block_sat, unseen, live_blocks, bm_to_grid, (H, W))

    # ------------------------------------------------------------------ per frame
    def frame_buffer(self, masks) -> np.ndarray:
        """(K, H, W) masks -> (K*H*W + 2,) uint8: the masks, then the 'unseen' and 'dead' bytes."""
        return self._buffer(self._checked(masks))

    def _buffer(self, masks: np.ndarray) -> np.ndarray:
        buf = np.empty(self._pixels + 2, dtype=np.uint8)
        buf[:-2] = masks.reshape(-1).view(np.uint8)
        buf[-2] = UNSEEN_IS_FOREGROUND
        buf[-1] = 0
        return buf

    def reconstruct(self, masks, surface: bool = True) -> VoxelResult:
        """(K, H, W) bool silhouettes -> VoxelResult (occupied and, if asked, surface voxels).

        Cameras of different sizes: the padded stack (``packing.pad_stack``); no sample falls
        on the padding, so the voxels are those of the cameras' own images.
        """
        masks = self._checked(masks)
        buf = self._buffer(masks)
        sat = self._tile_sat(masks)
        # Test the camera with the fewest silhouette tiles first: it rejects the most voxels.
        order = np.argsort(sat[:, -1, -1], kind="stable")
        sat = sat.reshape(-1)
        blocks = self.live_blocks
        for k in order:  # coarse pass: exact rejection of blocks with an empty footprint
            v = sat[self.block_sat[k][:, blocks]]
            keep = (v[0] - v[1] - v[2] + v[3]) > 0
            if UNSEEN_IS_FOREGROUND:
                keep |= self.block_unseen[k, blocks]
            blocks = blocks[keep]
        B3 = self.block ** 3
        first = order[0]
        counts = buf[self.lut[first][:, blocks]].sum(axis=0, dtype=np.uint8)  # (n, B^3)
        tests = self.q * counts.size
        local = np.flatnonzero(counts.reshape(-1) >= self.threshold)
        alive = blocks[local // B3].astype(np.int64) * B3 + local % B3  # block-major voxel indices
        for k in order[1:]:  # early rejection: only voxels still alive are tested
            lut = self.lut[k].reshape(self.q, -1)
            counts = buf[lut[:, alive]].sum(axis=0, dtype=np.uint8)
            tests += self.q * alive.size
            alive = alive[counts >= self.threshold]
        return self._result(self.bm_to_grid[alive], surface, tests)

    def _result(self, index: np.ndarray, surface: bool, tests: int) -> VoxelResult:
        N = self.grid
        occ = np.zeros(N ** 3, dtype=bool)
        occ[index] = True
        occupied = occ.reshape(N, N, N)
        box = None
        if index.size:
            box = tuple((int(a.min()), int(a.max()) + 1) for a in np.unravel_index(index, occupied.shape))
        surf = surface_voxels(occupied, box) if surface else None
        return VoxelResult(occupied, surf, self.bounds[0].copy(), self.voxel_size.copy(), int(tests), box)

    def _checked(self, masks) -> np.ndarray:
        masks = np.asarray(masks)
        K, (H, W) = len(self.studio), self.image_shape
        if masks.shape != (K, H, W):
            raise UserError(f"masks: expected shape {(K, H, W)} (cameras, height, width), got {masks.shape}")
        if masks.dtype != np.bool_:
            masks = masks != 0
        return np.ascontiguousarray(masks)

    def _tile_sat(self, masks: np.ndarray) -> np.ndarray:
        """(K, H, W) bool -> (K, th + 1, tw + 1) int32 summed-area table of tiles holding silhouette."""
        K, H, W = masks.shape
        th, tw = self._tiles
        if (H, W) != (th * TILE, tw * TILE):
            padded = np.zeros((K, th * TILE, tw * TILE), dtype=bool)
            padded[:, :H, :W] = masks
            masks = padded
        # One uint32 word is TILE = 4 pixels of a row; OR the TILE rows of each tile.
        words = masks.view(np.uint32).reshape(K, th, TILE, tw)
        tiles = np.bitwise_or.reduce(words, axis=2) != 0
        sat = np.zeros((K, th + 1, tw + 1), dtype=np.int32)
        np.cumsum(tiles, axis=1, dtype=np.int32, out=sat[:, 1:, 1:])
        np.cumsum(sat[:, 1:, 1:], axis=2, out=sat[:, 1:, 1:])
        return sat

    # ------------------------------------------------------------------ analysis
    def sample_counts(self, masks) -> np.ndarray:
        """(K, H, W) masks -> (K, N, N, N) uint8 silhouette samples per camera, every voxel tested.

        SPOT's decision is ``(counts >= threshold).all(axis=0)``; ``reconstruct`` gives the same
        result faster. For analysis and tests.
        """
        buf = self.frame_buffer(masks)
        K, N = len(self.studio), self.grid
        counts = buf[self.lut.reshape(K, self.q, -1)].sum(axis=1, dtype=np.uint8)
        out = np.empty((K, N ** 3), dtype=np.uint8)
        out[:, self.bm_to_grid] = counts
        return out.reshape(K, N, N, N)

    def sample_pixels(self) -> np.ndarray:
        """(K, Q, N, N, N) int64 pixel index y * W + x of each sample in its camera, -1 if unseen
        (W: the mask stack's width, ``image_shape[1]``)."""
        K, N = len(self.studio), self.grid
        H, W = self.image_shape
        lut = self.lut.reshape(K, self.q, -1).astype(np.int64)
        local = np.where(lut < self._pixels, lut - (np.arange(K) * H * W)[:, None, None], -1)
        out = np.empty((K, self.q, N ** 3), dtype=np.int64)
        out[:, :, self.bm_to_grid] = local
        return out.reshape(K, self.q, N, N, N)

    def voxel_centres(self) -> np.ndarray:
        """(N, N, N, 3) voxel centres in metres, index [i, j, k] along x, y, z."""
        idx = np.stack(np.meshgrid(*(np.arange(self.grid),) * 3, indexing="ij"), axis=-1)
        return self.bounds[0] + (idx + 0.5) * self.voxel_size


def surface_voxels(occupied, box=None) -> np.ndarray:
    """(N, N, N) bool -> (N, N, N) bool: occupied voxels with an empty 6-neighbour (section 3.3).

    Voxels outside the grid count as empty. box: ((i0, i1), (j0, j1), (k0, k1)) bounding all
    occupied voxels, if known (saves scanning the grid for it).
    """
    occupied = np.asarray(occupied, dtype=bool)
    out = np.zeros_like(occupied)
    if box is None:
        spans = [np.flatnonzero(occupied.any(axis=tuple(a for a in range(3) if a != d))) for d in range(3)]
        if spans[0].size == 0:
            return out
        box = tuple((int(s[0]), int(s[-1]) + 1) for s in spans)
    sl = tuple(slice(lo, hi) for lo, hi in box)
    sub = occupied[sl]
    p = np.pad(sub, 1)  # outside the box is empty, as it bounds every occupied voxel
    c = slice(1, -1)
    interior = (p[:-2, c, c] & p[2:, c, c] & p[c, :-2, c] & p[c, 2:, c] & p[c, c, :-2] & p[c, c, 2:])
    out[sl] = sub & ~interior
    return out


def save_voxels(path, result: VoxelResult, **meta) -> None:
    """One frame as a compact .npz: packbits of occupancy (and surface) plus grid metadata.

    ``meta``: extra scalars stored alongside (frame number, q, threshold, ...).
    """
    arrays = {"format": np.array(VOXEL_FORMAT), "version": np.array(VOXEL_VERSION),
              "shape": np.array(result.occupied.shape), "origin": result.origin,
              "voxel_size": result.voxel_size, "tests": np.array(result.tests),
              "occupied": np.packbits(result.occupied.reshape(-1))}
    if result.surface is not None:
        arrays["surface"] = np.packbits(result.surface.reshape(-1))
    arrays.update({k: np.array(v) for k, v in meta.items()})
    np.savez_compressed(path, **arrays)


def load_voxels(path) -> VoxelResult:
    """Read a file written by ``save_voxels``; InputFileError if it is not one."""
    try:
        with np.load(path) as data:
            if str(data["format"]) != VOXEL_FORMAT:
                raise InputFileError(path, f"not a voxel file (format {str(data['format'])!r})")
            shape = tuple(int(n) for n in data["shape"])
            count = int(np.prod(shape))
            occupied = np.unpackbits(data["occupied"], count=count).astype(bool).reshape(shape)
            surface = (np.unpackbits(data["surface"], count=count).astype(bool).reshape(shape)
                       if "surface" in data.files else None)
            return VoxelResult(occupied, surface, np.array(data["origin"], dtype=np.float64),
                               np.array(data["voxel_size"], dtype=np.float64), int(data["tests"]))
    except FileNotFoundError:
        raise InputFileError(path, "missing") from None
    except (OSError, KeyError, ValueError) as exc:
        raise InputFileError(path, f"not a voxel file ({exc})") from None


# ---------------------------------------------------------------------- synthetic masks

def render_ellipsoids(studio: Studio, centres, axes, radii) -> np.ndarray:
    """Exact silhouettes of solid ellipsoids by ray casting (lens distortion ignored).

    centres (E, 3), axes (E, 3, 3) unit axes as columns, radii (E, 3), metres ->
    (K, H, W) bool, True where a pixel's ray meets an ellipsoid in front of the camera (the
    padded stack of ``packing.pad_stack`` when the cameras differ in size).
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1, 3)
    # Quadric matrices A_e = V diag(1 / r^2) V^T: inside when (x - c)^T A (x - c) <= 1.
    A = np.einsum("eij,ej,ekj->eik", axes, 1.0 / radii ** 2, axes)
    out = []
    for cam in studio:
        v, u = np.mgrid[0:cam.height, 0:cam.width]
        pix = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3).astype(np.float64)
        rays = pix @ np.linalg.inv(cam.K).T @ cam.R  # world directions, (P, 3)
        mask = np.zeros(rays.shape[0], dtype=bool)
        for c, Ae in zip(centres, A):
            m = cam.center - c
            Ad = rays @ Ae
            a = np.einsum("pi,pi->p", Ad, rays)
            b = 2.0 * (Ad @ m)
            cc = m @ Ae @ m - 1.0
            disc = b * b - 4.0 * a * cc
            far = (-b + np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)  # the larger root
            mask |= (disc >= 0.0) & (far > 0.0)
        out.append(mask.reshape(cam.height, cam.width))
    return pad_stack(out)


def corrupt(masks, eta: float, xi: float, rng: np.random.Generator) -> np.ndarray:
    """Independent pixel errors: silhouette pixels lost with probability eta, background
    pixels turned silhouette with probability xi. (K, H, W) bool -> (K, H, W) bool."""
    masks = np.asarray(masks, dtype=bool)
    u = rng.random(masks.shape)
    return np.where(masks, u >= eta, u < xi)


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def person_ellipsoids(position=(0.0, 0.0), heading: float = 0.0, arm_raise: float = 0.4,
                      leg_spread: float = 0.1):
    """A synthetic 1.75 m person of 17 ellipsoids: (centres (17, 3), axes (17, 3, 3), radii (17, 3)).

    Arms hang ``arm_raise`` and legs ``leg_spread`` radians away from the body; the figure
    faces -y (feet point that way), turned by ``heading`` about z.
    """
    parts = [  # centre (x, y, z), radii, tilt about y (radians)
        ((0.0, 0.0, 1.30), (0.18, 0.11, 0.22), 0.0),  # chest
        ((0.0, 0.0, 1.05), (0.15, 0.10, 0.16), 0.0),  # abdomen
        ((0.0, 0.0, 0.92), (0.16, 0.11, 0.11), 0.0),  # pelvis
        ((0.0, 0.0, 1.63), (0.08, 0.095, 0.115), 0.0),  # head
        ((0.0, 0.0, 1.51), (0.05, 0.05, 0.07), 0.0),  # neck
    ]
    for side in (-1.0, 1.0):
        a = -side * arm_raise  # about y: positive turns -z towards -x
        b = -side * leg_spread
        shoulder = np.array([side * 0.17, 0.0, 1.42])
        hip = np.array([side * 0.09, 0.0, 0.9])
        arm = _rot_y(a) @ np.array([0.0, 0.0, -1.0])
        leg = _rot_y(b) @ np.array([0.0, 0.0, -1.0])
        parts += [(tuple(shoulder + 0.14 * arm), (0.05, 0.05, 0.18), a),
                  (tuple(shoulder + 0.44 * arm), (0.04, 0.04, 0.16), a),
                  (tuple(shoulder + 0.66 * arm), (0.035, 0.05, 0.08), a),  # hand
                  (tuple(hip + 0.22 * leg), (0.075, 0.075, 0.24), b),
                  (tuple(hip + 0.65 * leg), (0.055, 0.055, 0.23), b),
                  (tuple(hip + 0.86 * leg + [0.0, -0.07, 0.0]), (0.045, 0.11, 0.035), b)]  # foot
    Rh = _rot_z(heading)
    offset = np.array([position[0], position[1], 0.0])
    centres = np.array([Rh @ np.array(c) + offset for c, _, _ in parts])
    axes = np.array([Rh @ _rot_y(t) for _, _, t in parts])
    radii = np.array([r for _, r, _ in parts])
    return centres, axes, radii


# ---------------------------------------------------------------------- benchmark

BENCH_SECONDS = 1.0  # wall time per measurement
CHEUNG_ETA, CHEUNG_XI = 0.043, 0.021  # the paper's measured silhouette error rates (Eq. 1, 2)
BENCH_POSES = 4  # distinct synthetic frames cycled through


def median_rate(fn, frames) -> float:
    """1 / median seconds per call over BENCH_SECONDS (the median resists other load on the machine)."""
    fn(frames[0])  # warm up
    times = []
    start = time.perf_counter()
    while time.perf_counter() - start < BENCH_SECONDS or len(times) < len(frames):
        t0 = time.perf_counter()
        fn(frames[len(times) % len(frames)])
        times.append(time.perf_counter() - t0)
    return 1.0 / float(np.median(times))


def bench_voxels(configs=((64, 5), (64, 8), (128, 5), (128, 8)), q: int = 2, width: int = 320,
                 height: int = 240) -> list[dict]:
    """SPOT frames per second on synthetic person silhouettes in ``circle_studio`` cameras.

    Returns one row per (grid, cameras): {"grid", "cameras", "q", "frames_per_second" (occupancy
    only), "surface_frames_per_second" (with surface extraction), "noisy_frames_per_second"
    (occupancy, silhouettes corrupted at Cheung's eta and xi: the coarse pass then rejects
    little), "build_seconds", "occupied", "surface", "tests_per_frame"}.
    """
    rows = []
    for grid, cameras in configs:
        studio = circle_studio(cameras, width, height)
        frames = [render_ellipsoids(studio, *person_ellipsoids((0.1 * i, -0.05 * i), 0.7 * i, 0.2 + 0.3 * i))
                  for i in range(BENCH_POSES)]
        rng = np.random.default_rng(0)
        noisy = [corrupt(m, CHEUNG_ETA, CHEUNG_XI, rng) for m in frames]
        start = time.perf_counter()
        spot = SpotGrid.build(studio, grid=grid, q=q)
        build = time.perf_counter() - start
        result = spot.reconstruct(frames[0])
        rows.append({
            "grid": grid, "cameras": cameras, "q": q,
            "frames_per_second": median_rate(lambda m: spot.reconstruct(m, surface=False), frames),
            "surface_frames_per_second": median_rate(spot.reconstruct, frames),
            "noisy_frames_per_second": median_rate(lambda m: spot.reconstruct(m, surface=False), noisy),
            "build_seconds": build,
            "occupied": int(result.occupied.sum()),
            "surface": int(result.surface.sum()),
            "tests_per_frame": result.tests,
        })
    return rows
