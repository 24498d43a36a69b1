"""Colour images of a known body, so that background subtraction can be measured.

A virtual room (textured walls, a tiled floor at z = 0, a ceiling) is ray-cast through each
camera, so the floor lines up in every view. A body (triangle mesh) is composited over it
with per-pixel clothing colours, its shadow is cast on the floor along a light direction
(darkening the floor by 30-60 % while keeping its colour), and each frame gets a global
lighting gain and Gaussian sensor noise. Wall and clothing colours differ in hue, as in a
capture studio (skin-coloured walls would camouflage the actor for any colour method). The true silhouette is known exactly, so the missed
(η) and false (ξ) foreground rates of a segmentation can be counted.

Pixel (0, 0) is the centre of the top-left pixel (common.camera's convention).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from common.body import SEGMENT_NAMES
from common.camera import Camera, Studio, circle_studio

ROOM_HALF_SIZE = 5.0  # metres; the room is [-5, 5] x [-5, 5] x [0, ROOM_HEIGHT]
ROOM_HEIGHT = 4.0  # metres
FLOOR_TILE = 0.5  # metres, tile pitch
GROUT_WIDTH = 0.012  # metres
SHADOW_DARKENING = (0.3, 0.6)  # fraction of the floor's light a cast shadow removes
PENUMBRA = 3  # pixels, box width over which a shadow edge fades
RASTER_CHUNK = 2_000_000  # candidate pixels per vectorised rasterisation pass
DEFAULT_BODY_COLOUR = (150, 40, 45)  # RGB used when no per-pixel body colours are given

# Clothing palette (RGB): what a plain-dressed actor wears.
CLOTHING = {
    "shirt": (150, 40, 45),
    "trousers": (45, 55, 95),
    "skin": (205, 155, 125),
    "shoes": (95, 62, 40),
}
_SEGMENT_CLOTHING = {
    "pelvis": "trousers", "abdomen": "shirt", "chest": "shirt", "head": "skin",
    "upperarm": "shirt", "forearm": "skin", "hand": "skin",
    "thigh": "trousers", "shin": "trousers", "foot": "shoes",
}
SEGMENT_PALETTE = np.array(
    [CLOTHING[_SEGMENT_CLOTHING[name.split("_")[-1]]] for name in SEGMENT_NAMES], dtype=np.uint8)

_FLOOR_RGB = np.array([150.0, 148.0, 140.0])
_WALL_RGB = np.array([[125.0, 138.0, 160.0], [150.0, 138.0, 168.0],
                      [118.0, 148.0, 118.0], [100.0, 140.0, 150.0]])  # x+, x-, y+, y-
_CEILING_RGB = np.array([222.0, 222.0, 216.0])
_SKIRTING_RGB = np.array([70.0, 58.0, 50.0])
_POSTER_RGB = np.array([[200.0, 190.0, 60.0], [60.0, 120.0, 190.0], [40.0, 40.0, 45.0],
                        [220.0, 220.0, 225.0], [170.0, 70.0, 150.0], [90.0, 160.0, 90.0]])
_POSTERS_PER_WALL = 3


# --------------------------------------------------------------------------- palette
def clothing_colours(segment_index_image: np.ndarray) -> np.ndarray:
    """(H, W) int segment ids (0..15 as common.body.SEGMENT_NAMES, < 0 for none) -> (H, W, 3) uint8.

    Shirt on the trunk and upper arms, skin on the head, forearms and hands, trousers on the
    pelvis and legs, brown shoes. Pixels without a segment are black.
    """
    ids = np.asarray(segment_index_image)
    out = np.zeros(ids.shape + (3,), dtype=np.uint8)
    valid = (ids >= 0) & (ids < len(SEGMENT_PALETTE))
    out[valid] = SEGMENT_PALETTE[ids[valid]]
    return out


# --------------------------------------------------------------------------- rasterising
def _triangle_candidates(tri: np.ndarray, width: int, height: int):
    """Yield (triangle index, x, y, barycentric (M, 3)) for pixel centres inside triangles.

    tri: (T, 3, 2) pixel coordinates. Processes triangles in chunks so memory stays bounded.
    """
    tri = np.asarray(tri, dtype=np.float64)
    finite = np.all(np.isfinite(tri), axis=(1, 2))
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    lo = np.ceil(np.min(np.where(finite[:, None, None], tri, 0.0), axis=1))
    hi = np.floor(np.max(np.where(finite[:, None, None], tri, 0.0), axis=1))
    x0 = np.clip(lo[:, 0], 0, width - 1).astype(np.int64)
    y0 = np.clip(lo[:, 1], 0, height - 1).astype(np.int64)
    x1 = np.clip(hi[:, 0], 0, width - 1).astype(np.int64)
    y1 = np.clip(hi[:, 1], 0, height - 1).astype(np.int64)
    bw = x1 - x0 + 1
    bh = y1 - y0 + 1
    ok = finite & (area2 != 0) & (hi[:, 0] >= 0) & (lo[:, 0] <= width - 1) & \
        (hi[:, 1] >= 0) & (lo[:, 1] <= height - 1) & (bw > 0) & (bh > 0)
    idx_all = np.flatnonzero(ok)
    counts_all = bw[idx_all] * bh[idx_all]
    start = 0
    while start < idx_all.size:
        cum = np.cumsum(counts_all[start:])
        stop = start + max(1, int(np.searchsorted(cum, RASTER_CHUNK, side="right")))
        idx = idx_all[start:stop]
        counts = counts_all[start:stop]
        start = stop
        owner = np.repeat(np.arange(idx.size), counts)
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        local = np.arange(owner.size) - offsets[owner]
        t = idx[owner]
        px = x0[t] + local % bw[t]
        py = y0[t] + local // bw[t]
        ax, ay = a[t, 0] - px, a[t, 1] - py
        bx, by = b[t, 0] - px, b[t, 1] - py
        cx, cy = c[t, 0] - px, c[t, 1] - py
        sign = np.sign(area2[t])
        w_a = (bx * cy - by * cx) * sign  # twice the area of (p, b, c): weight of vertex a
        w_b = (cx * ay - cy * ax) * sign
        w_c = (ax * by - ay * bx) * sign
        inside = (w_a >= 0) & (w_b >= 0) & (w_c >= 0)
        bary = np.stack([w_a[inside], w_b[inside], w_c[inside]], axis=1) / np.abs(area2[t[inside], None])
        yield t[inside], px[inside], py[inside], bary


def rasterise_mask(tri: np.ndarray, width: int, height: int) -> np.ndarray:
    """(T, 3, 2) pixel-coordinate triangles -> (height, width) bool coverage of pixel centres."""
    mask = np.zeros((height, width), dtype=bool)
    for _, px, py, _ in _triangle_candidates(tri, width, height):
        mask[py, px] = True
    return mask


def rasterise_labels(tri: np.ndarray, depth: np.ndarray, labels: np.ndarray, width: int, height: int,
                     fill: int = -1) -> np.ndarray:
    """Z-buffered label image: the label of the nearest triangle at each pixel centre.

    tri: (T, 3, 2) pixels; depth: (T, 3) per-vertex depth (interpolated linearly on screen);
    labels: (T,) int. Returns (height, width) int64, ``fill`` where no triangle covers a pixel.
    """
    depth = np.asarray(depth, dtype=np.float64)
    labels = np.asarray(labels)
    zbuf = np.full(height * width, np.inf)
    out = np.full(height * width, fill, dtype=np.int64)
    for t, px, py, bary in _triangle_candidates(tri, width, height):
        z = np.einsum("mi,mi->m", bary, depth[t])
        pix = py * width + px
        order = np.lexsort((z, pix))
        pix_s = pix[order]
        first = np.ones(pix_s.size, dtype=bool)
        first[1:] = pix_s[1:] != pix_s[:-1]
        sel = order[first]
        nearer = z[sel] < zbuf[pix[sel]]
        sel = sel[nearer]
        zbuf[pix[sel]] = z[sel]
        out[pix[sel]] = labels[t[sel]]
    return out.reshape(height, width)


def project_mesh(camera: Camera, points_world: np.ndarray, faces: np.ndarray):
    """Triangles of a mesh as seen by ``camera``: ((T', 3, 2) pixels, (T', 3) depth, (T',) face index).

    Triangles with a vertex behind the camera (depth <= 1 cm) are dropped.
    """
    faces = np.asarray(faces, dtype=np.int64)
    pix = camera.project(points_world)
    z = camera.depth(points_world)
    keep = np.all(z[faces] > 0.01, axis=1)
    return pix[faces[keep]], z[faces[keep]], np.flatnonzero(keep)


def floor_shadow_mask(camera: Camera, points_world: np.ndarray, light_dir, faces: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of the floor z = 0 in the body's cast shadow.

    points_world: (N, 3) mesh vertices, metres; light_dir: (3,) direction the light travels
    (must point downwards, z < 0); faces: (T, 3) vertex indices. Each vertex is slid along
    the light direction onto the floor, the floor points are projected into the camera and
    the shadow triangles rasterised. Occlusion of the floor by the body itself is the
    compositor's business (the body is drawn over the shadow).
    """
    d = np.asarray(light_dir, dtype=np.float64).reshape(3)
    if not d[2] < 0.0:
        raise ValueError(f"light_dir must point downwards (z < 0), got {d.tolist()}")
    pts = np.asarray(points_world, dtype=np.float64)
    s = -pts[:, 2] / d[2]
    on_floor = pts + s[:, None] * d
    on_floor[:, 2] = 0.0
    tri, _, _ = project_mesh(camera, on_floor, faces)
    return rasterise_mask(tri, camera.width, camera.height)


# --------------------------------------------------------------------------- the room
def _hash01(*ints: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer tuple (vectorised)."""
    h = np.zeros(np.broadcast(*ints).shape, dtype=np.uint64)
    for k, v in zip((0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D), ints):
        h = (h ^ (np.asarray(v).astype(np.int64).astype(np.uint64) * np.uint64(k))) * np.uint64(0x27D4EB2F165667C5)
        h ^= h >> np.uint64(29)
    return (h >> np.uint64(40)).astype(np.float64) / float(1 << 24)


def pixel_rays(camera: Camera) -> np.ndarray:
    """(H, W, 3) unit world directions of the rays through each pixel centre."""
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    return camera.rays(np.stack([u, v], axis=-1))


def _smooth_noise(p: np.ndarray, q: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Smooth world-space variation in about [-1, 1]: a few random plane waves."""
    out = np.zeros_like(p)
    for _ in range(4):
        ang = rng.uniform(0, np.pi)
        freq = rng.uniform(0.5, 2.0) / scale
        out += np.sin(freq * (np.cos(ang) * p + np.sin(ang) * q) + rng.uniform(0, 2 * np.pi))
    return out / 4.0


def _floor_texture(x: np.ndarray, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    ix = np.floor(x / FLOOR_TILE)
    iy = np.floor(y / FLOOR_TILE)
    tile = 0.93 + 0.14 * _hash01(ix, iy)
    fx = x / FLOOR_TILE - ix
    fy = y / FLOOR_TILE - iy
    g = GROUT_WIDTH / FLOOR_TILE
    grout = (np.minimum(fx, 1 - fx) < g) | (np.minimum(fy, 1 - fy) < g)
    shade = tile * (1.0 + 0.04 * _smooth_noise(x, y, rng, 0.7))
    shade = np.where(grout, 0.72, shade)
    return shade[..., None] * _FLOOR_RGB


def _wall_texture(s: np.ndarray, z: np.ndarray, wall: int, rng: np.random.Generator) -> np.ndarray:
    """s: horizontal coordinate along the wall, z: height, metres."""
    base = _WALL_RGB[wall]
    shade = 1.0 + 0.05 * _smooth_noise(s, z, rng, 0.5)
    panel = np.abs(s / 1.2 - np.round(s / 1.2)) * 1.2 < 0.01  # vertical panel joints
    shade = np.where(panel, 0.8, shade)
    rgb = shade[..., None] * base
    rgb = np.where((z < 0.15)[..., None], _SKIRTING_RGB, rgb)
    for _ in range(_POSTERS_PER_WALL):
        cs = rng.uniform(-ROOM_HALF_SIZE + 0.8, ROOM_HALF_SIZE - 0.8)
        cz = rng.uniform(1.0, 2.6)
        hw, hh = rng.uniform(0.25, 0.6), rng.uniform(0.2, 0.5)
        colour = _POSTER_RGB[rng.integers(len(_POSTER_RGB))]
        inside = (np.abs(s - cs) < hw) & (np.abs(z - cz) < hh)
        stripes = 1.0 + 0.12 * np.sign(np.sin((z - cz) * 40.0))
        rgb = np.where(inside[..., None], colour * stripes[..., None], rgb)
    return rgb


def make_background(camera: Camera, rng: np.random.Generator, scene_seed: int = 0) -> np.ndarray:
    """(H, W, 3) uint8: the empty room as seen by ``camera`` (noise-free).

    The room (floor tiles, wall colours, posters) is drawn from ``scene_seed`` so that it is
    the same for every camera; ``rng`` draws what differs per camera: its colour balance
    (a few per cent per channel) and lens vignetting.
    """
    d = pixel_rays(camera)
    o = camera.center
    L, Hc = ROOM_HALF_SIZE, ROOM_HEIGHT
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = np.stack([(L - o[0]) / d[..., 0], (-L - o[0]) / d[..., 0],
                       (L - o[1]) / d[..., 1], (-L - o[1]) / d[..., 1],
                       (0.0 - o[2]) / d[..., 2], (Hc - o[2]) / d[..., 2]], axis=-1)
    ts = np.where(np.isfinite(ts) & (ts > 1e-9), ts, np.inf)
    plane = np.argmin(ts, axis=-1)  # 0..3 walls x+, x-, y+, y-; 4 floor; 5 ceiling
    t = np.take_along_axis(ts, plane[..., None], axis=-1)[..., 0]
    t = np.where(np.isfinite(t), t, 1.0)
    p = o + t[..., None] * d
    scene = np.random.default_rng(scene_seed)
    rgb = np.empty(d.shape, dtype=np.float64)
    floor = plane == 4
    rgb[floor] = _floor_texture(p[floor][:, 0], p[floor][:, 1], scene)
    for wall in range(4):
        sel = plane == wall
        along = p[sel][:, 1] if wall < 2 else p[sel][:, 0]
        rgb[sel] = _wall_texture(along, p[sel][:, 2], wall, scene)
    rgb[plane == 5] = _CEILING_RGB
    balance = rng.uniform(0.96, 1.04, size=3)
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    r2 = ((u - camera.K[0, 2]) ** 2 + (v - camera.K[1, 2]) ** 2) / (camera.K[0, 0] ** 2)
    vignette = 1.0 - rng.uniform(0.05, 0.15) * r2
    rgb = rgb * balance * vignette[..., None]
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- compositing
def composite_frame(camera: Camera, mask: np.ndarray, body_colour_image: np.ndarray | None,
                    shadow_mask: np.ndarray | None, background: np.ndarray, rng: np.random.Generator,
                    lighting_gain: float = 1.0, noise_sigma: float = 2.0,
                    shadow_darkening: float | None = None, psf_sigma: float = 0.0) -> np.ndarray:
    """One camera image: (H, W, 3) uint8.

    mask: (H, W) bool true silhouette; body_colour_image: (H, W, 3) colours of the body
    (None: a plain shirt colour); shadow_mask: (H, W) bool cast shadow on the floor (or
    None); background: (H, W, 3) uint8 from make_background. The shadow removes
    ``shadow_darkening`` of the light (drawn from 30-60 % when None) with a soft edge, keeping
    the floor's colour; the optics blur it with a Gaussian of ``psf_sigma`` pixels (so the
    actor's edge pixels mix with the background, as in a real camera), the whole image is
    scaled by ``lighting_gain`` and Gaussian noise of ``noise_sigma`` grey levels is added.
    Pass a ``background`` made with the same ``psf_sigma`` blur applied, as a real camera's
    empty frames would be (``composite_frame`` with an empty mask does that).
    """
    shape = (camera.height, camera.width)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != shape or background.shape != shape + (3,):
        raise ValueError(f"mask {mask.shape} / background {background.shape} do not match "
                         f"camera {camera.name} ({camera.width}x{camera.height})")
    img = background.astype(np.float32)
    if shadow_mask is not None and np.any(shadow_mask):
        if shadow_darkening is None:
            shadow_darkening = rng.uniform(*SHADOW_DARKENING)
        soft = ndimage.uniform_filter(np.asarray(shadow_mask, dtype=np.float32), size=PENUMBRA)
        img *= (1.0 - shadow_darkening * soft)[..., None]
    if body_colour_image is None:
        img[mask] = DEFAULT_BODY_COLOUR
    else:
        img[mask] = np.asarray(body_colour_image)[mask]
    if psf_sigma > 0.0:
        img = ndimage.gaussian_filter(img, sigma=(psf_sigma, psf_sigma, 0.0))
    img *= lighting_gain
    img += rng.normal(0.0, noise_sigma, size=img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- a toy body
def _ellipsoid_mesh(centre, radii, axis_z, rings: int = 8, sectors: int = 12):
    """UV ellipsoid: ((V, 3) points, (F, 3) faces).

    radii: (3,) semi-axes along a side axis, a second side axis and ``axis_z``; the first side
    axis is horizontal (world x for an upright ellipsoid) unless ``axis_z`` is along y.
    """
    axis_z = np.asarray(axis_z, dtype=np.float64)
    axis_z = axis_z / np.linalg.norm(axis_z)
    helper = np.array([0.0, 1.0, 0.0]) if abs(axis_z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    ax = np.cross(helper, axis_z)
    ax /= np.linalg.norm(ax)
    ay = np.cross(axis_z, ax)
    th = np.linspace(0, np.pi, rings + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, sectors, endpoint=False)
    st, ct = np.sin(th)[:, None], np.cos(th)[:, None]
    local = np.stack([st * np.cos(ph), st * np.sin(ph), np.broadcast_to(ct, (th.size, ph.size))], -1).reshape(-1, 3)
    local = np.vstack([[0, 0, 1], local, [0, 0, -1]]) * radii
    pts = np.asarray(centre) + local @ np.stack([ax, ay, axis_z])
    faces = []
    n_ring = th.size
    for j in range(sectors):
        k = (j + 1) % sectors
        faces.append((0, 1 + j, 1 + k))
        last = 1 + (n_ring - 1) * sectors
        faces.append((len(pts) - 1, last + k, last + j))
        for i in range(n_ring - 1):
            a, b = 1 + i * sectors + j, 1 + i * sectors + k
            faces.append((a, a + sectors, b))
            faces.append((b, a + sectors, b + sectors))
    return pts, np.array(faces, dtype=np.int64)


def toy_body(position=(0.0, 0.0), heading: float = 0.0, swing: float = 0.0):
    """A standing actor made of 16 ellipsoids, one per common.body segment.

    position: (x, y) of the pelvis on the floor, metres; heading: rotation about z, radians;
    swing: arm and leg swing, radians (walking). Returns ((V, 3) points, (F, 3) faces,
    (F,) segment id per face), segment ids as common.body.SEGMENT_NAMES.
    """
    def limb(top, angle, side_tilt, length):
        direction = np.array([np.sin(side_tilt), np.sin(angle), -np.cos(angle) * np.cos(side_tilt)])
        direction /= np.linalg.norm(direction)
        return np.asarray(top, dtype=np.float64), direction, length

    parts = {}
    parts["pelvis"] = ((0, 0, 0.95), (0.17, 0.11, 0.10), (0, 0, 1))
    parts["abdomen"] = ((0, 0, 1.12), (0.15, 0.10, 0.11), (0, 0, 1))
    parts["chest"] = ((0, 0, 1.33), (0.18, 0.11, 0.14), (0, 0, 1))
    parts["head"] = ((0, 0, 1.62), (0.085, 0.10, 0.115), (0, 0, 1))
    for side, sx in (("l", 1.0), ("r", -1.0)):
        s = swing * sx
        top, d, ln = limb((0.2 * sx, 0, 1.44), s, 0.08 * sx, 0.29)
        parts[f"{side}_upperarm"] = (top + d * ln / 2, (0.055, 0.055, ln / 2), d)
        top2, d2, ln2 = limb(top + d * ln, s + 0.3 * abs(swing) + 0.1, 0.06 * sx, 0.26)
        parts[f"{side}_forearm"] = (top2 + d2 * ln2 / 2, (0.045, 0.045, ln2 / 2), d2)
        parts[f"{side}_hand"] = (top2 + d2 * (ln2 + 0.07), (0.035, 0.02, 0.07), d2)
        top, d, ln = limb((0.1 * sx, 0, 0.9), -s, 0.02 * sx, 0.42)
        parts[f"{side}_thigh"] = (top + d * ln / 2, (0.085, 0.085, ln / 2), d)
        top2, d2, ln2 = limb(top + d * ln, -s - 0.4 * max(0.0, s), 0.0, 0.4)
        parts[f"{side}_shin"] = (top2 + d2 * ln2 / 2, (0.06, 0.06, ln2 / 2), d2)
        ankle = top2 + d2 * ln2
        parts[f"{side}_foot"] = ((ankle[0], ankle[1] - 0.06, 0.04), (0.04, 0.045, 0.12), (0, 1, 0))
    c, s = np.cos(heading), np.sin(heading)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    offset = np.array([position[0], position[1], 0.0])
    points, faces, seg = [], [], []
    count = 0
    for seg_id, name in enumerate(SEGMENT_NAMES):
        centre, radii, axis = parts[name]
        p, f = _ellipsoid_mesh(centre, radii, axis)
        points.append(p @ rot.T + offset)
        faces.append(f + count)
        seg.append(np.full(len(f), seg_id))
        count += len(p)
    return np.vstack(points), np.vstack(faces), np.concatenate(seg)


def render_body(camera: Camera, points_world: np.ndarray, faces: np.ndarray, face_segment: np.ndarray,
                light_dir=(0.3, 0.2, -1.0)):
    """Rasterise a mesh: ((H, W) bool mask, (H, W, 3) uint8 shaded clothing colours).

    Flat shading: ambient plus Lambert from the light, so the body is not a flat colour.
    """
    tri, depth, face_idx = project_mesh(camera, points_world, faces)
    ids = rasterise_labels(tri, depth, face_idx, camera.width, camera.height)
    mask = ids >= 0
    p = np.asarray(points_world)[np.asarray(faces)]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    light = -np.asarray(light_dir, dtype=np.float64)
    light /= np.linalg.norm(light)
    shade = 0.55 + 0.45 * np.abs(normals @ light)  # two-sided: winding need not be consistent
    seg_img = np.where(mask, np.asarray(face_segment)[np.maximum(ids, 0)], -1)
    colour = clothing_colours(seg_img).astype(np.float32)
    colour *= np.where(mask, shade[np.maximum(ids, 0)], 0.0)[..., None].astype(np.float32)
    return mask, np.clip(np.rint(colour), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- test scenes
LIGHT_DIR = (0.35, 0.25, -1.0)  # direction the key light travels (down and sideways)
GAIN_JITTER = 0.03  # per-frame lighting gain drawn from 1 +- this
NOISE_SIGMA = 2.0  # grey levels of sensor noise
PSF_SIGMA = 0.6  # pixels, optical blur that mixes the actor's edge pixels with the background


@dataclass(frozen=True)
class StudioScene:
    """Colour frames of the toy actor with their truth, per camera.

    backgrounds: (K, N, H, W, 3) uint8 empty frames; images: (K, F, H, W, 3) uint8;
    truth: (K, F, H, W) bool silhouettes; shadows: (K, F, H, W) bool cast shadow visible
    on the floor (not covered by the actor).
    """

    studio: Studio
    backgrounds: np.ndarray
    images: np.ndarray
    truth: np.ndarray
    shadows: np.ndarray


def studio_scene(width: int = 320, height: int = 240, cameras: int = 8, frames: int = 10,
                 background_frames: int = 30, seed: int = 0, noise_sigma: float = NOISE_SIGMA,
                 gain_jitter: float = GAIN_JITTER, light_dir=LIGHT_DIR,
                 psf_sigma: float = PSF_SIGMA) -> StudioScene:
    """The toy actor walking about a circle studio (common.camera.circle_studio).

    Per frame: a random position within 0.8 m of the centre, heading and limb swing; one
    lighting gain and shadow depth shared by all cameras. Deterministic in ``seed``.
    """
    studio = circle_studio(cameras, width, height)
    rng = np.random.default_rng(seed)
    poses = [(rng.uniform(-0.8, 0.8, size=2) / np.sqrt(2), rng.uniform(-np.pi, np.pi),
              rng.uniform(-0.5, 0.5)) for _ in range(frames)]
    gains = 1.0 + rng.uniform(-gain_jitter, gain_jitter, size=frames)
    bg_gains = 1.0 + rng.uniform(-gain_jitter, gain_jitter, size=background_frames)
    darkening = rng.uniform(*SHADOW_DARKENING, size=frames)
    bodies = [toy_body(*pose) for pose in poses]
    k_count = len(studio)
    backgrounds = np.empty((k_count, background_frames, height, width, 3), dtype=np.uint8)
    images = np.empty((k_count, frames, height, width, 3), dtype=np.uint8)
    truth = np.empty((k_count, frames, height, width), dtype=bool)
    shadows = np.empty_like(truth)
    empty = np.zeros((height, width), dtype=bool)
    for k, cam in enumerate(studio):
        background = make_background(cam, rng)
        for i in range(background_frames):
            backgrounds[k, i] = composite_frame(cam, empty, None, None, background, rng, bg_gains[i],
                                                noise_sigma, psf_sigma=psf_sigma)
        for f, (points, faces, seg) in enumerate(bodies):
            mask, colour = render_body(cam, points, faces, seg, light_dir)
            shadow = floor_shadow_mask(cam, points, light_dir, faces)
            images[k, f] = composite_frame(cam, mask, colour, shadow, background, rng, gains[f],
                                           noise_sigma, darkening[f], psf_sigma)
            truth[k, f] = mask
            shadows[k, f] = shadow & ~mask
    return StudioScene(studio, backgrounds, images, truth, shadows)
