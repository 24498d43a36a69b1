"""Silhouette bit planes, packed as the Theobalt paper packs them for the stencil buffer.

K binary masks of one size (H, W) become P = ceil(K / 8) byte planes: camera k lives in
bit (k % 8) of plane k // 8, so one byte per pixel carries eight cameras and the XOR energy
of all of them is one pass over the buffer. ``packbits_masks`` is the compact form for disk
and the wire (one bit per pixel). Windows for the paper's sub-window speed-up are cut from
either masks or planes; ``downsample_masks`` gives the half-resolution torso images.

A studio whose cameras differ in image size keeps one frame's silhouettes as a padded stack
(``pad_stack``): (K, H, W) with H, W the largest camera height and width, camera k's pixels
at [:h_k, :w_k] and False beyond. Everything here works on that stack as on any other;
``inside_images`` tells which of its pixels belong to each camera (consumers count only those)
and ``clear_padding`` clears the others.
"""
from __future__ import annotations

import numpy as np

CAMERAS_PER_PLANE = 8  # bits in a uint8 plane


def plane_count(cameras: int) -> int:
    """Number of uint8 planes P = ceil(K / 8) that hold ``cameras`` masks."""
    return -(-int(cameras) // CAMERAS_PER_PLANE)


def packed_length(cameras: int, height: int, width: int) -> int:
    """Bytes of ``packbits_masks`` for (K, H, W) masks: ceil(K * H * W / 8)."""
    return -(-int(cameras) * int(height) * int(width) // 8)


def padded_shape(sizes) -> tuple[int, int]:
    """(H, W) of the padded stack of cameras of ``sizes`` (K, 2) (width, height) pixels: the
    largest height and the largest width."""
    sizes = np.asarray(sizes, dtype=np.int64).reshape(-1, 2)
    if len(sizes) == 0:
        raise ValueError("no camera sizes")
    return int(sizes[:, 1].max()), int(sizes[:, 0].max())


def inside_images(sizes, shape) -> np.ndarray:
    """sizes (K, 2) (width, height) pixels, shape (H, W) -> (K, H, W) bool: True on camera k's
    own pixels [:h_k, :w_k] of a padded stack, False on the padding."""
    sizes = np.asarray(sizes, dtype=np.int64).reshape(-1, 2)
    H, W = (int(n) for n in shape)
    rows = np.arange(H)[None, :, None] < sizes[:, 1, None, None]
    cols = np.arange(W)[None, None, :] < sizes[:, 0, None, None]
    return rows & cols


def clear_padding(masks: np.ndarray, sizes) -> np.ndarray:
    """(K, H, W) bool padded stack of cameras of ``sizes`` (K, 2) (width, height) pixels -> the
    same with every pixel beyond camera k's [:h_k, :w_k] False. Cameras of one size have no
    padding: ``masks`` itself comes back."""
    masks = np.asarray(masks)
    sizes = np.asarray(sizes, dtype=np.int64).reshape(-1, 2)
    if np.all(sizes == sizes[0]):
        return masks
    return masks & inside_images(sizes, masks.shape[-2:])


def pad_stack(arrays, dtype=bool) -> np.ndarray:
    """K arrays of shapes (h_k, w_k, ...) -> (K, H, W, ...) ``dtype`` padded stack (see the module
    docstring): array k at [k, :h_k, :w_k], zero (False) beyond. The trailing dimensions (an
    image's colour channels) must agree. Arrays of one size give the plain stack.

    With dtype bool any non-zero value counts as set.
    """
    arrays = [np.asarray(a) for a in arrays]
    if not arrays or any(a.ndim < 2 or a.shape[2:] != arrays[0].shape[2:] for a in arrays):
        raise ValueError(f"expected K >= 1 (h, w, ...) arrays with the same trailing dimensions, got shapes "
                         f"{[a.shape for a in arrays]}")
    H, W = padded_shape([(a.shape[1], a.shape[0]) for a in arrays])
    out = np.zeros((len(arrays), H, W) + arrays[0].shape[2:], dtype=dtype)
    for k, a in enumerate(arrays):
        out[k, :a.shape[0], :a.shape[1]] = a
    return out




def pack_planes(masks: np.ndarray) -> np.ndarray:
    """(K, H, W) bool masks -> (P, H, W) uint8 planes, camera k in bit (k % 8) of plane k // 8.

    Any non-zero value counts as set. Bits of cameras beyond K in the last plane are 0.
    """
    masks = np.asarray(masks)
    if masks.ndim != 3 or masks.shape[0] == 0:
        raise ValueError(f"expected (K, H, W) masks with K >= 1, got shape {masks.shape}")
    return np.packbits(masks != 0, axis=0, bitorder="little")


def unpack_planes(planes: np.ndarray, cameras: int) -> np.ndarray:
    """(P, H, W) uint8 planes -> (K, H, W) bool masks for K = ``cameras`` <= 8 P."""
    planes = np.asarray(planes)
    if planes.ndim != 3 or planes.dtype != np.uint8:
        raise ValueError(f"expected (P, H, W) uint8 planes, got {planes.dtype} {planes.shape}")
    if not 1 <= cameras <= CAMERAS_PER_PLANE * planes.shape[0]:
        raise ValueError(f"{planes.shape[0]} planes hold 1..{CAMERAS_PER_PLANE * planes.shape[0]} "
                         f"cameras, not {cameras}")
    return np.unpackbits(planes, axis=0, count=int(cameras), bitorder="little").view(bool)


def packbits_masks(masks: np.ndarray) -> bytes:
    """(K, H, W) bool masks -> ``packed_length(K, H, W)`` bytes.

    One bit per pixel in C order over (K, H, W), most significant bit first (numpy.packbits'
    default), the last byte padded with zero bits. Any non-zero value counts as set.
    """
    masks = np.asarray(masks)
    if masks.ndim != 3:
        raise ValueError(f"expected (K, H, W) masks, got shape {masks.shape}")
    return np.packbits(masks != 0, axis=None).tobytes()


def unpackbits_masks(data: bytes, cameras: int, height: int, width: int) -> np.ndarray:
    """Inverse of ``packbits_masks``: bytes -> (K, H, W) bool masks.

    Raises ValueError when ``len(data)`` is not ``packed_length(K, H, W)``.
    """
    expected = packed_length(cameras, height, width)
    buffer = np.frombuffer(data, dtype=np.uint8)
    if buffer.size != expected:
        raise ValueError(f"{cameras}x{height}x{width} masks pack to {expected} bytes, got {buffer.size}")
    count = int(cameras) * int(height) * int(width)
    return np.unpackbits(buffer, count=count).view(bool).reshape(int(cameras), int(height), int(width))


def window(planes: np.ndarray, x0: int, y0: int, w: int, h: int) -> np.ndarray:
    """Cut the (h, w) window whose top-left pixel is (x0, y0) from (..., H, W) planes or masks.

    Returns (..., h, w) of the same dtype, a copy. Pixels outside the image are 0 (no camera
    sees the body there), so windows near or past the border keep their size.
    """
    planes = np.asarray(planes)
    x0, y0, w, h = int(x0), int(y0), int(w), int(h)
    if w < 0 or h < 0:
        raise ValueError(f"window size must be >= 0, got {w}x{h}")
    height, width = planes.shape[-2:]
    out = np.zeros(planes.shape[:-2] + (h, w), dtype=planes.dtype)
    xa, xb = max(x0, 0), min(x0 + w, width)
    ya, yb = max(y0, 0), min(y0 + h, height)
    if xa < xb and ya < yb:
        out[..., ya - y0:yb - y0, xa - x0:xb - x0] = planes[..., ya:yb, xa:xb]
    return out


def downsample_masks(masks: np.ndarray, factor: int = 2) -> np.ndarray:
    """(..., H, W) bool masks -> (..., H // factor, W // factor) bool masks.

    Each output pixel covers a factor x factor block of source pixels and is set when at
    least half of them are set: at factor 2, at least 2 of the 4. Ties count as set so that
    thin limbs one source pixel wide survive as often as not. A last row or column that
    does not fill a whole block (odd H or W at factor 2) is dropped.

    On a padded stack camera k's output pixels are [:h_k // factor, :w_k // factor], as
    downsampling its own image gives; a block that straddles its last odd row or column and
    the padding may be set, so clear the output beyond (``inside_images``) before counting.
    """
    masks = np.asarray(masks)
    if int(factor) != factor or factor < 1:
        raise ValueError(f"factor must be a positive integer, got {factor!r}")
    factor = int(factor)
    if masks.ndim < 2:
        raise ValueError(f"expected (..., H, W) masks, got shape {masks.shape}")
    height, width = masks.shape[-2] // factor, masks.shape[-1] // factor
    source = (masks[..., :height * factor, :width * factor] != 0).view(np.uint8)
    # the block's pixels added as factor x factor strided views: numpy's sum over two strided
    # axes of a bool array is 12 times slower (6 ms for 8 images of 320x240), and every client
    # downsamples every frame
    counts = np.zeros(masks.shape[:-2] + (height, width), dtype=np.uint8 if factor * factor < 256 else np.int32)
    for row in range(factor):
        for column in range(factor):
            counts += source[..., row::factor, column::factor]
    return counts >= -(-factor * factor // 2)
