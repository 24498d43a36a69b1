"""Background subtraction: colour camera images -> binary silhouettes.

Two methods, each a small class with ``fit(backgrounds)`` (empty-studio frames) and
``segment(image)`` / ``segment_many(images)``:

* ``CheungSegmenter`` (Cheung et al. 2000, section 3.1): the distance d between the
  image colour and the background colour is compared with an upper and a lower threshold;
  pixels in between are silhouette only if the colour angle exceeds a third threshold
  (a shadow keeps the colour direction and loses brightness). The background is split into
  colour regions by k-means on chromaticity (floor / non-floor with the default two) and
  each region has its own three thresholds, estimated automatically from the background
  frames' noise and brightness unless given.
* ``BottinoSegmenter`` (Bottino & Laurentini, "Cameras and Silhouettes"): per-pixel YUV
  mean and min/max over the empty frames, T_c = alpha_tol * max(n_max - mu, mu - n_min)
  per channel, the U/V and Y tests, a shadow test (darker, same colour) and a running-average
  update of the background where the frame shows background.

Both finish with the same post-processing: blobs smaller than an area are removed and small
holes filled (connected components). Everything is vectorised numpy on float32 planes; the
per-frame cost at 320x240 is well under a millisecond plus the labelling.

Parameters are frozen dataclasses with documented defaults; ``load_params`` reads them from
a TOML file and refuses unknown keys.

One module of about 570 lines: the background models (Cheung's RGB, Bottino's YUV), shadows and
mask cleaning share the per-pixel statistics.
"""
from __future__ import annotations

import time
import tomllib
from dataclasses import asdict, dataclass, fields

import numpy as np
from scipy import ndimage

from common.errors import FieldChecks, InputFileError, UserError

REFERENCE_AREA = 320 * 240  # pixels; blob and hole areas are given at this resolution
KMEANS_ITERATIONS = 12
KMEANS_SAMPLE = 20_000  # background pixels used to place the region centres
CHROMA_SCALE = 765.0  # chromaticity r/(r+g+b) in grey levels x 3: grey is (255, 255, 255)
BRIGHTNESS_WEIGHT = 0.3  # weight of the mean grey level beside chromaticity in the clustering
EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)  # foreground blobs; holes use 4-connectivity

# BT.601 RGB -> YUV with U, V centred on zero, so a shadow (RGB scaled by g) scales Y, U, V by g.
RGB_TO_YUV = np.array([[0.299, 0.587, 0.114],
                       [-0.14713, -0.28886, 0.436],
                       [0.615, -0.51499, -0.10001]], dtype=np.float32)


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class CheungParams:
    """Thresholds of Cheung's method; grey levels (0-255) and radians.

    regions: colour regions of the background (k-means), each with its own thresholds.
    thresholds: manual (T_L, T_U, T_C) per region, in region order (darkest first); empty = automatic.
    lower_noise_factor: automatic T_L = factor * noise sigma (per channel) of the region.
    upper_noise_factor: automatic T_U is at least factor * noise sigma.
    shadow_depth: deepest shadow expected, the fraction of brightness it removes; T_U is at
        least this fraction of the region's bright (90th percentile) background colour norm,
        so that shadows fall into the band where the colour test decides.
    colour_noise_factor: automatic T_C = factor * the colour-angle noise of a pixel of the
        region's median brightness darkened by ``shadow_depth``.
    min_colour_angle, max_colour_angle: bounds of the automatic T_C, radians.
    single_frame_noise: noise sigma assumed when only one background frame is given.
    min_blob_area: foreground blobs smaller than this are removed (pixels at 320x240,
        scaled with the image area).
    max_hole_area: holes up to this size are filled (pixels at 320x240, scaled); 0 = none.
    """

    regions: int = 2
    thresholds: tuple = ()
    lower_noise_factor: float = 4.0
    upper_noise_factor: float = 12.0
    shadow_depth: float = 0.65
    colour_noise_factor: float = 2.5
    min_colour_angle: float = 0.03
    max_colour_angle: float = 0.2
    single_frame_noise: float = 2.0
    min_blob_area: int = 40
    max_hole_area: int = 200

    def validate(self, source: str = "<params>") -> None:
        _check(source, "regions", 1 <= self.regions <= 8, "must be 1..8")
        if self.thresholds:
            _check(source, "thresholds", len(self.thresholds) == self.regions,
                   f"needs one [T_L, T_U, T_C] per region ({self.regions})")
            for i, row in enumerate(self.thresholds):
                _check(source, f"thresholds[{i}]", len(row) == 3 and 0 <= row[0] <= row[1] and row[2] > 0,
                       "expected [T_L, T_U, T_C] with 0 <= T_L <= T_U and T_C > 0")
        _check(source, "shadow_depth", 0.0 <= self.shadow_depth < 1.0, "must be in [0, 1)")
        _check(source, "min_colour_angle", 0.0 < self.min_colour_angle <= self.max_colour_angle,
               "must be positive and <= max_colour_angle")
        for name in ("lower_noise_factor", "upper_noise_factor", "colour_noise_factor", "single_frame_noise"):
            _check(source, name, getattr(self, name) > 0, "must be positive")
        _check_post(self, source)


@dataclass(frozen=True)
class BottinoParams:
    """Per-pixel YUV statistics (Bottino & Laurentini); grey levels (0-255).

    alpha_tol: tolerance factor on the observed spread, T = alpha_tol * max(n_max - mu, mu - n_min).
    min_threshold: floor of every channel threshold (quantisation and too few empty frames).
    alpha_shadow: widening of the colour tolerance in the shadow test (the paper's 1.2).
    max_shadow_darkening: a shadow removes at most this fraction of the brightness (Y).
    adapt_rate: running-average rate of the background update, mu <- a p + (1 - a) mu; 0 = off.
    min_blob_area, max_hole_area: post-processing, as in CheungParams.
    """

    alpha_tol: float = 0.9
    min_threshold: float = 4.0
    alpha_shadow: float = 1.2
    max_shadow_darkening: float = 0.7
    adapt_rate: float = 0.05
    min_blob_area: int = 40
    max_hole_area: int = 200

    def validate(self, source: str = "<params>") -> None:
        _check(source, "alpha_tol", self.alpha_tol > 0, "must be positive")
        _check(source, "min_threshold", self.min_threshold >= 0, "must be >= 0")
        _check(source, "alpha_shadow", self.alpha_shadow >= 1.0, "must be >= 1")
        _check(source, "max_shadow_darkening", 0.0 <= self.max_shadow_darkening < 1.0, "must be in [0, 1)")
        _check(source, "adapt_rate", 0.0 <= self.adapt_rate <= 1.0, "must be in [0, 1]")
        _check_post(self, source)


def _check(source: str, key: str, ok: bool, problem: str) -> None:
    if not ok:
        raise UserError(f"{source}: {key}: {problem}")


def _check_post(params, source: str) -> None:
    _check(source, "min_blob_area", params.min_blob_area >= 0, "must be >= 0")
    _check(source, "max_hole_area", params.max_hole_area >= 0, "must be >= 0")


def params_from_mapping(method: str, doc: dict, source: str = "<params>"):
    """Build the parameters of ``method`` from a mapping (e.g. a parsed TOML file).

    Unknown keys and values of the wrong type raise UserError naming ``source`` and the key.
    """
    cls = _method(method)[0]
    defaults = cls()
    known = {f.name for f in fields(cls)}
    values = {}
    for key, value in doc.items():
        if key not in known:
            raise UserError(f"{source}: unknown key {key!r} for method {method} "
                            f"(known: {', '.join(sorted(known))})")
        values[key] = _coerce(source, key, value, getattr(defaults, key))
    params = cls(**values)
    params.validate(source)
    return params


def _coerce(source: str, key: str, value, default):
    checks = FieldChecks(source)
    if isinstance(default, bool):
        return checks.flag(value, key)
    if isinstance(default, int):
        return checks.whole(value, key)
    if isinstance(default, float):
        return checks.number(value, key)
    if isinstance(default, tuple):  # thresholds: list of [T_L, T_U, T_C]
        rows = checks.items(value, key)
        return tuple(tuple(checks.numbers(row, f"{key}[{i}]", 3)) for i, row in enumerate(rows))
    raise UserError(f"{source}: {key}: unsupported value {value!r}")


def load_params(method: str, path=None):
    """Parameters of ``method`` from a TOML file of flat keys (defaults where absent or path None)."""
    if path is None:
        params = _method(method)[0]()
        params.validate()
        return params
    checks = FieldChecks(path)
    try:
        doc = tomllib.loads(checks.decode(checks.read()))
    except tomllib.TOMLDecodeError as exc:
        raise InputFileError(path, f"not valid TOML ({exc})") from None
    return params_from_mapping(method, doc, str(path))


def make_segmenter(method: str, params=None):
    """A fresh, unfitted segmenter of ``method`` ('cheung' or 'bottino')."""
    cls, seg_cls = _method(method)
    params = cls() if params is None else params
    params.validate()
    return seg_cls(params)


# --------------------------------------------------------------------------- post-processing
def _scaled_area(area: int, pixels: int) -> int:
    return int(round(area * pixels / REFERENCE_AREA)) if area > 0 else 0


def clean_mask(mask: np.ndarray, min_blob_area: int, max_hole_area: int) -> np.ndarray:
    """(H, W) bool -> (H, W) bool without 8-connected blobs of fewer than ``min_blob_area``
    pixels and with 4-connected holes (background not reaching the border) of at most
    ``max_hole_area`` pixels filled. Areas are in pixels of this image."""
    mask = np.asarray(mask, dtype=bool)
    if min_blob_area > 1 and mask.any():
        lab, n = ndimage.label(mask, structure=EIGHT_CONNECTED)
        sizes = np.bincount(lab[mask], minlength=n + 1)  # only the foreground pixels: cheap
        keep = sizes >= min_blob_area
        keep[0] = False
        mask = np.take(keep, lab)
    if max_hole_area > 0 and mask.any():
        lab, n = ndimage.label(~mask)
        if n > 1:
            outside = np.zeros(n + 1, dtype=bool)
            for edge in (lab[0], lab[-1], lab[:, 0], lab[:, -1]):
                outside[edge] = True
            outside[0] = True
            inner = ~np.take(outside, lab)
            sizes = np.bincount(lab[inner], minlength=n + 1)
            fill = (sizes > 0) & (sizes <= max_hole_area)
            mask = mask | np.take(fill, lab)
    return mask


# --------------------------------------------------------------------------- helpers
def _as_frames(backgrounds: np.ndarray) -> np.ndarray:
    bg = np.asarray(backgrounds)
    if bg.ndim == 3:
        bg = bg[None]
    if bg.ndim != 4 or bg.shape[-1] != 3 or bg.shape[0] < 1:
        raise ValueError(f"backgrounds must be (N, H, W, 3), got {bg.shape}")
    return bg


def _planes(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, H*W) float32 colour planes."""
    image = np.asarray(image)
    if image.shape != shape + (3,):
        raise ValueError(f"image is {image.shape}, the background model is {shape + (3,)}")
    return np.ascontiguousarray(image.reshape(-1, 3).T, dtype=np.float32)


def kmeans_regions(features: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Split (P, F) float features into k clusters: ((P,) int labels, (k, F) centres).

    Deterministic: centres start at quantiles along the main axis of the features.
    """
    features = np.asarray(features, dtype=np.float32)
    step = max(1, features.shape[0] // KMEANS_SAMPLE)
    sample = features[::step]
    mean = sample.mean(0)
    _, _, vt = np.linalg.svd(sample - mean, full_matrices=False)
    axis = vt[0] if vt[0].sum() >= 0 else -vt[0]
    proj = (sample - mean) @ axis
    centres = mean + np.quantile(proj, (np.arange(k) + 0.5) / k)[:, None] * axis
    for _ in range(KMEANS_ITERATIONS):
        labels = _nearest(sample, centres)
        for j in range(k):
            members = sample[labels == j]
            if len(members):
                centres[j] = members.mean(0)
    return _nearest(features, centres), centres


def colour_regions(colours: np.ndarray, k: int) -> np.ndarray:
    """(P, 3) background colours -> (P,) region index, regions numbered darkest first.

    Clusters on chromaticity (colour without brightness, so a floor's bright and dark tiles
    and its vignetted corners stay one surface) plus a little brightness, which splits a
    surface of uniform colour into light and dark parts.
    """
    colours = np.asarray(colours, dtype=np.float32)
    total = colours.sum(1, keepdims=True) + 1.0
    features = np.hstack([colours / total * CHROMA_SCALE, colours.mean(1, keepdims=True) * BRIGHTNESS_WEIGHT])
    labels, _ = kmeans_regions(features, k)
    brightness = np.array([colours[labels == j].sum(1).mean() if np.any(labels == j) else np.inf
                           for j in range(k)])
    rank = np.empty(k, dtype=np.int64)
    rank[np.argsort(brightness, kind="stable")] = np.arange(k)
    return rank[labels]


def _nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    d = (x * x).sum(1)[:, None] - 2.0 * x @ centres.T + (centres * centres).sum(1)[None]
    return np.argmin(d, axis=1)


# --------------------------------------------------------------------------- Cheung
class CheungSegmenter:
    """Cheung et al.'s background subtraction with per-region thresholds.

    After ``fit``: ``region_map`` (H, W) region index per pixel, ``thresholds`` (R, 3)
    (T_L, T_U in grey levels of the RGB distance, T_C in radians) and ``noise`` (R,) sigma.
    """

    name = "cheung"

    def __init__(self, params: CheungParams = CheungParams()):
        params.validate()
        self.params = params
        self.shape: tuple[int, int] | None = None

    def fit(self, backgrounds: np.ndarray) -> "CheungSegmenter":
        """backgrounds: (N, H, W, 3) uint8 empty-studio frames (N >= 1)."""
        p = self.params
        bg = _as_frames(backgrounds)
        n, h, w, _ = bg.shape
        self.shape = (h, w)
        # Frame by frame, so that hundreds of large empty frames need no float copy of them all.
        total = np.zeros((h * w, 3))
        for frame in bg:
            total += frame.reshape(-1, 3)
        mean = (total / n).astype(np.float32)  # (P, 3)
        labels = colour_regions(mean, p.regions)
        norm = np.linalg.norm(mean, axis=1)
        if n >= 2:
            # Sensor noise after removing each frame's global gain (lighting flicker), which
            # changes brightness, not colour angle, and is covered by the band of T_L..T_U.
            mean_norm2 = max(float((mean * mean).sum()), 1.0)
            var = np.zeros(h * w)
            for frame in bg:
                f = frame.reshape(-1, 3).astype(np.float32)
                resid = f - (float((f * mean).sum()) / mean_norm2) * mean
                var += (resid * resid).sum(1)
            var /= 3.0 * (n - 1)  # (P,) per channel
        else:
            var = np.full(h * w, p.single_frame_noise ** 2, dtype=np.float32)
        rows, sigmas = [], []
        for r in range(p.regions):
            sel = labels == r
            if not sel.any():
                rows.append((0.0, 0.0, p.min_colour_angle))
                sigmas.append(0.0)
                continue
            sigma = float(np.sqrt(var[sel].mean() * (1.0 + 1.0 / n)))  # image noise + mean's noise
            t_low = p.lower_noise_factor * sigma
            t_up = max(p.upper_noise_factor * sigma, p.shadow_depth * float(np.percentile(norm[sel], 90)))
            dark = (1.0 - p.shadow_depth) * max(float(np.median(norm[sel])), 1.0)
            t_col = float(np.clip(p.colour_noise_factor * sigma * np.sqrt(2.0) / dark,
                                  p.min_colour_angle, p.max_colour_angle))
            rows.append((t_low, max(t_up, t_low), t_col))
            sigmas.append(sigma)
        if p.thresholds:
            rows = [tuple(row) for row in p.thresholds]
        self.thresholds = np.array(rows, dtype=np.float64)
        self.noise = np.array(sigmas)
        self.region_map = labels.reshape(h, w)
        # Per-pixel squared thresholds, so segmenting needs neither sqrt nor arccos.
        self._bg = np.ascontiguousarray(mean.T)  # (3, P)
        self._bg_norm2 = (mean * mean).sum(1).astype(np.float32)
        self._t_low2 = (self.thresholds[labels, 0] ** 2).astype(np.float32)
        self._t_up2 = (self.thresholds[labels, 1] ** 2).astype(np.float32)
        self._cos2_bg = (np.cos(self.thresholds[labels, 2]) ** 2 * self._bg_norm2).astype(np.float32)
        return self

    def classify(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W) bool raw silhouette, before post-processing."""
        if self.shape is None:
            raise RuntimeError("fit() the segmenter on background frames first")
        r, g, b = _planes(image, self.shape)
        bg = self._bg
        dot = r * bg[0]
        dot += g * bg[1]
        dot += b * bg[2]
        norm2 = r * r
        norm2 += g * g
        norm2 += b * b
        d2 = norm2 - 2.0 * dot
        d2 += self._bg_norm2
        band = d2 >= self._t_low2
        # theta > T_C  <=>  cos^2 theta < cos^2 T_C  (the colours are non-negative: cos >= 0)
        dot *= dot
        norm2 *= self._cos2_bg
        fg = (d2 > self._t_up2) | (band & (dot < norm2))
        return fg.reshape(self.shape)

    def segment(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W) bool silhouette."""
        return _post(self.classify(image), self.params)

    def segment_many(self, images: np.ndarray) -> np.ndarray:
        """(F, H, W, 3) uint8 -> (F, H, W) bool silhouettes."""
        return _many(self, images)


# --------------------------------------------------------------------------- Bottino
class BottinoSegmenter:
    """Bottino & Laurentini's per-pixel YUV model with shadow test and adaptive update.

    A pixel is silhouette when |p_c - mu_c| >= T_c for both U and V, or for Y and one of
    U, V. The paper's shadow test re-checks Y with T_s = alpha_shadow * T_Y for darker
    pixels of similar colour; with noise-sized T_Y that would only forgive faint shadows,
    so here a darker pixel (by at most ``max_shadow_darkening``) is a shadow when its U, V
    match the background's scaled by the same darkening, within alpha_shadow * T_U, T_V.
    T_s still bounds the adaptive update: pixels darker than it are not blended in.

    Stateful: with ``adapt_rate`` > 0 every segmented frame updates the background mean
    where the frame shows background, so frames should be given in time order.
    After ``fit``: ``mean`` and ``threshold`` (3, H, W) float32 for Y, U, V.
    """

    name = "bottino"

    def __init__(self, params: BottinoParams = BottinoParams()):
        params.validate()
        self.params = params
        self.shape: tuple[int, int] | None = None

    def fit(self, backgrounds: np.ndarray) -> "BottinoSegmenter":
        """backgrounds: (N, H, W, 3) uint8 empty frames (the paper uses about 200; >= 10 advised)."""
        p = self.params
        bg = _as_frames(backgrounds)
        n, h, w, _ = bg.shape
        self.shape = (h, w)
        total = np.zeros((3, h * w))
        low = np.full((3, h * w), np.inf, dtype=np.float32)
        high = np.full((3, h * w), -np.inf, dtype=np.float32)
        for frame in bg:  # one at a time: no float copy of all the empty frames
            yuv = np.stack(self._yuv(frame))
            total += yuv
            np.minimum(low, yuv, out=low)
            np.maximum(high, yuv, out=high)
        mu = (total / n).astype(np.float32)
        spread = np.maximum(high - mu, mu - low)
        self._mu = np.ascontiguousarray(mu, dtype=np.float32)  # (3, P), updated while segmenting
        self._t = np.maximum(p.alpha_tol * spread, p.min_threshold).astype(np.float32)
        self._t_shadow = (p.alpha_shadow * self._t).astype(np.float32)
        return self

    @property
    def mean(self) -> np.ndarray:
        return self._mu.reshape((3,) + self.shape)

    @property
    def threshold(self) -> np.ndarray:
        return self._t.reshape((3,) + self.shape)

    def _yuv(self, image: np.ndarray):
        """(H, W, 3) uint8 -> Y, U, V planes, (P,) float32 each (elementwise: no BLAS threads)."""
        r, g, b = _planes(image, self.shape)
        m = RGB_TO_YUV
        return (m[0, 0] * r + m[0, 1] * g + m[0, 2] * b,
                m[1, 0] * r + m[1, 1] * g + m[1, 2] * b,
                m[2, 0] * r + m[2, 1] * g + m[2, 2] * b)

    def _tests(self, y: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Y, U, V planes -> ((P,) bool raw silhouette, (P,) float32 Y difference)."""
        p = self.params
        mu_y, mu_u, mu_v = self._mu
        t_y, t_u, t_v = self._t
        dy = y - mu_y
        ok_y = np.abs(dy) < t_y
        ok_u = np.abs(u - mu_u) < t_u
        ok_v = np.abs(v - mu_v) < t_v
        # Silhouette: U and V both differ, or Y and at least one of U, V differ.
        fg = ~(ok_u | ok_v) | ~(ok_y | (ok_u & ok_v))
        # Shadow test on the few darker candidates: darker by at most max_shadow_darkening
        # and the background's colour scaled by the same factor (U, V are zero-centred, so a
        # shadow scales them as it scales Y), within alpha_shadow times the thresholds.
        idx = np.flatnonzero(fg & (dy < 0))
        if idx.size:
            gain = y[idx] / np.maximum(mu_y[idx], 1.0)
            shadow = gain >= 1.0 - p.max_shadow_darkening
            shadow &= np.abs(u[idx] - gain * mu_u[idx]) < self._t_shadow[1, idx]
            shadow &= np.abs(v[idx] - gain * mu_v[idx]) < self._t_shadow[2, idx]
            fg[idx[shadow]] = False
        return fg, dy

    def classify(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W) bool raw silhouette (no post-processing, no update)."""
        if self.shape is None:
            raise RuntimeError("fit() the segmenter on background frames first")
        return self._tests(*self._yuv(image))[0].reshape(self.shape)

    def segment(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W) bool silhouette; updates the background model."""
        if self.shape is None:
            raise RuntimeError("fit() the segmenter on background frames first")
        yuv = self._yuv(image)
        raw, dy = self._tests(*yuv)
        mask = _post(raw.reshape(self.shape), self.params)
        if self.params.adapt_rate > 0.0:
            # Update where the final silhouette shows background and the pixel is not darker
            # than the shadow threshold T_s = alpha_shadow * T_Y, so that neither the actor nor
            # its shadow leaks into the model while slow lighting changes are followed.
            weight = ~mask.reshape(-1)
            weight &= dy > -self._t_shadow[0]
            weight = weight.astype(np.float32)
            weight *= np.float32(self.params.adapt_rate)
            for channel, mu in zip(yuv, self._mu):
                channel -= mu
                channel *= weight
                mu += channel
        return mask

    def segment_many(self, images: np.ndarray) -> np.ndarray:
        """(F, H, W, 3) uint8 -> (F, H, W) bool, frames in time order."""
        return _many(self, images)


def _post(raw: np.ndarray, params) -> np.ndarray:
    pixels = raw.size
    return clean_mask(raw, _scaled_area(params.min_blob_area, pixels), _scaled_area(params.max_hole_area, pixels))


def _many(segmenter, images: np.ndarray) -> np.ndarray:
    # Frame by frame: one 320x240 frame's float32 planes stay in cache, a batch would not.
    images = np.asarray(images)
    if images.ndim != 4:
        raise ValueError(f"images must be (F, H, W, 3), got {images.shape}")
    out = np.empty(images.shape[:3], dtype=bool)
    for i, image in enumerate(images):
        out[i] = segmenter.segment(image)
    return out


METHODS = {"cheung": (CheungParams, CheungSegmenter), "bottino": (BottinoParams, BottinoSegmenter)}


def _method(method: str):
    try:
        return METHODS[method]
    except KeyError:
        raise UserError(f"unknown segmentation method {method!r} (known: {', '.join(METHODS)})") from None


def params_dict(params) -> dict:
    """Parameters as a plain dict (for logs and sequence.json)."""
    return {k: ([list(r) for r in v] if isinstance(v, tuple) else v) for k, v in asdict(params).items()}


# --------------------------------------------------------------------------- measuring
def error_rates(predicted: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(eta, xi): missed foreground / true foreground, false foreground / true background.

    predicted, truth: (..., H, W) bool, pooled over all frames given.
    """
    predicted = np.asarray(predicted, dtype=bool)
    truth = np.asarray(truth, dtype=bool)
    fg = int(truth.sum())
    bg = truth.size - fg
    eta = float((truth & ~predicted).sum()) / max(fg, 1)
    xi = float((predicted & ~truth).sum()) / max(bg, 1)
    return eta, xi


def bench_segmentation(sizes=((320, 240), (640, 480)), frames: int = 20, seed: int = 0,
                       cameras: int = 8, background_frames: int = 30,
                       methods=("cheung", "bottino")) -> list[dict]:
    """Speed and accuracy of each method on colour-studio frames with cast shadows.

    For each image size, a studio of ``cameras`` cameras films the toy actor walking about
    for ``frames`` frames (lighting flicker, sensor noise, shadows). Returns one row per
    (method, size): {"method", "size": [W, H], "frames_per_second" (per camera, segmentation
    with post-processing), "eta", "xi", "frames", "cameras"}.
    """
    from common.colour_studio import studio_scene

    rows = []
    for width, height in sizes:
        scene = studio_scene(width, height, cameras=cameras, frames=frames,
                             background_frames=background_frames, seed=seed)
        for method in methods:
            seconds = 0.0
            masks = np.empty(scene.truth.shape, dtype=bool)
            for k in range(scene.images.shape[0]):
                segmenter = make_segmenter(method).fit(scene.backgrounds[k])
                t0 = time.perf_counter()
                masks[k] = segmenter.segment_many(scene.images[k])
                seconds += time.perf_counter() - t0
            eta, xi = error_rates(masks, scene.truth)
            rows.append({"method": method, "size": [int(width), int(height)],
                         "frames_per_second": masks.shape[0] * masks.shape[1] / seconds,
                         "eta": eta, "xi": xi, "frames": int(frames), "cameras": int(scene.images.shape[0])})
    return rows
