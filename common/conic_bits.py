"""Ellipsoid conics drawn as row spans into bit masks: the energy's pixel arithmetic.

A conic covers one span of columns per image row (``_conic_rows``, ``_row_span``); spans are
ORed into 64-pixel words, and a sum of per-pixel values +1 / -1 over them is two population
counts per word (``common.energy.xor_span_sums``, against ``xor_bits``' masks).

A frame's silhouettes are packed into row bits once (``pack_rows``), and an energy's windows are
cut from them straight into its value masks (``window_value_bits``): a limb's solve builds two
energies, and cutting 8 byte windows, drawing the parts that do not move into 8 more and
gathering both into bits took most of a build's 0.38 ms (a limb's; now 0.16). A window's row is two
shifted words of its image row, and the still parts' spans are ORed as an evaluation ORs the
moving ones; the masks are the bits ``xor_bits`` makes of the byte windows
(``tests/test_energy.py``), so the energies, and the poses, are the same.
"""
from __future__ import annotations

import numpy as np
from numba import njit, types
from numba.extending import intrinsic


@njit(cache=True, nogil=True, inline="always")
def _conic_rows(C: np.ndarray, drawable: bool, y0: float, rows: int) -> tuple:
    """Window rows [first, last) a conic C (3, 3) covers (pixel centres at integer coordinates
    are inside where the conic is negative); (0, 0) when it covers none."""
    c00, c01, c02 = C[0, 0], C[0, 1], C[0, 2]
    c11, c12, c22 = C[1, 1], C[1, 2], C[2, 2]
    # y-extent: where the quadratic in x has a double root
    qa = c01 * c01 - c00 * c11
    qb = 2.0 * (c01 * c02 - c00 * c12)
    qc = c02 * c02 - c00 * c22
    disc_y = qb * qb - 4.0 * qa * qc
    if not (drawable and qa < 0 and c00 > 0 and disc_y > 0):
        return 0, 0
    sq = np.sqrt(disc_y)
    y_lo = (-qb + sq) / (2.0 * qa)  # qa < 0: this is the smaller root
    y_hi = (-qb - sq) / (2.0 * qa)
    first = int(min(max(np.ceil(y_lo - y0), 0.0), float(rows)))
    last = int(min(max(np.floor(y_hi - y0) + 1.0, 0.0), float(rows)))
    return first, max(first, last)


@njit(cache=True, nogil=True, inline="always")
def _conic_row_form(C: np.ndarray, x0: float) -> tuple:
    """A conic C (3, 3) drawn on rows (``_conic_rows``) as its span on image row y: centre
    cu + cv y and squared half-width q0 + y (q1 + y q2), window columns (x0 the window's
    left edge). -> (cu, cv, q0, q1, q2)."""
    c00, c01, c02 = C[0, 0], C[0, 1], C[0, 2]
    inv = 1.0 / c00
    inv2 = inv * inv
    return (-c02 * inv - x0, -c01 * inv, (c02 * c02 - c00 * C[2, 2]) * inv2,
            2.0 * (c01 * c02 - c00 * C[1, 2]) * inv2, (c01 * c01 - c00 * C[1, 1]) * inv2)


@njit(cache=True, nogil=True, inline="always")
def _row_span(cu: float, cv: float, q0: float, q1: float, q2: float, y: float, width: float) -> tuple:
    """Window columns [start, end) a conic in row form covers on image row y (end <= start: none)."""
    centre = cu + cv * y
    half = np.sqrt(max(q0 + y * (q1 + y * q2), 0.0))
    return (int(min(max(np.ceil(centre - half), 0.0), width)),
            int(min(max(np.floor(centre + half) + 1.0, 0.0), width)))


@njit(cache=True, nogil=True)
def conic_coverage(C: np.ndarray, drawable: np.ndarray, y0: np.ndarray, x0: np.ndarray, rows: int,
                   width: int) -> np.ndarray:
    """Pixels covered by any of the conics: C (B, K, S, 3, 3) (negative inside), drawable
    (B, K, S), y0, x0 (K,) window corners -> (B, K, rows, width) bool."""
    B, K, S = C.shape[0], C.shape[1], C.shape[2]
    out = np.zeros((B, K, rows, width), np.bool_)
    for b in range(B):
        for k in range(K):
            for s in range(S):
                first, last = _conic_rows(C[b, k, s], drawable[b, k, s], y0[k], rows)
                if last <= first:
                    continue
                cu, cv, q0, q1, q2 = _conic_row_form(C[b, k, s], x0[k])
                for row in range(first, last):
                    start, end = _row_span(cu, cv, q0, q1, q2, float(row) + y0[k], float(width))
                    out[b, k, row, start:end] = True
    return out


@intrinsic
def _popcount(typingctx, x):
    """The set bits of a uint64 (LLVM's ctpop: one instruction where the CPU has one)."""
    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])
    return types.uint64(types.uint64), codegen


_ALL_BITS = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(cache=True, nogil=True, inline="always")
def _or_span(words: np.ndarray, row: int, start: int, end: int) -> None:
    """Set columns [start, end) (end > start) of ``row`` of (rows, n) 64-pixel words, bit c % 64
    of word c // 64 (indexed in place: a row view per span cost the energy's loop 4%)."""
    ws, we = start >> 6, (end - 1) >> 6
    head = _ALL_BITS << np.uint64(start & 63)
    tail = _ALL_BITS >> np.uint64(63 - ((end - 1) & 63))
    if ws == we:
        words[row, ws] |= head & tail
    else:
        words[row, ws] |= head
        for j in range(ws + 1, we):
            words[row, j] = _ALL_BITS
        words[row, we] |= tail


def xor_bits(static: np.ndarray, inputs: np.ndarray) -> tuple:
    """static, inputs (K, h, w) bool -> the value a moving part adds by covering a pixel
    (0 where static covers it, else 1 - 2 * input) as two bit masks per row, gain (+1: neither
    static nor input) and loss (-1: input, not static), (K, h, ceil(w / 64)) uint64, bit
    c % 64 of word c // 64 for column c; and the static parts' own XOR count |static xor inputs|
    per camera, (K,) int64.
    Rows are read 8 pixels (bytes) at a time, as uint64 words; a row of another width is
    padded to a multiple of 8 with pixels static and input both cover (no bits, no count), as
    a window's pixels beyond its camera's image are (``CpuEnergy``)."""
    K, h, w = inputs.shape
    spare = -w % 8
    static, inputs = (np.pad(np.asarray(a, dtype=np.bool_), ((0, 0), (0, 0), (0, spare)), constant_values=True)
                      if spare else np.ascontiguousarray(a, dtype=np.bool_) for a in (static, inputs))
    return _xor_bits_octets(static.view(np.uint64), inputs.view(np.uint64), (w + 63) // 64)


# Eight bytes of 0 or 1 (pixels c..c+7, c first in memory) times this, shifted down by 56: the
# byte whose bit i is pixel c + i (each byte's bit lands at its own place among the top 8 bits,
# the other products below them or past the top, with no carry into them)
_GATHER_BYTES = np.uint64(0x0102040810204080)
_BYTE_LOW_BITS = np.uint64(0x0101010101010101)


@njit(cache=True, nogil=True)
def _xor_bits_octets(static: np.ndarray, inputs: np.ndarray, words: int) -> tuple:
    """``xor_bits`` of rows whose 8-pixel groups are read as uint64: static, inputs (K, h, w / 8)."""
    K, h, octets = inputs.shape
    gain = np.zeros((K, h, words), np.uint64)
    loss = np.zeros((K, h, words), np.uint64)
    base = np.zeros(K, np.int64)
    for k in range(K):
        for r in range(h):
            for o in range(octets):
                s, i = static[k, r, o], inputs[k, r, o]
                base[k] += _popcount(s ^ i)
                shift = np.uint64(8 * (o & 7))
                gain[k, r, o >> 3] |= (((~s & ~i & _BYTE_LOW_BITS) * _GATHER_BYTES) >> np.uint64(56)) << shift
                loss[k, r, o >> 3] |= (((~s & i & _BYTE_LOW_BITS) * _GATHER_BYTES) >> np.uint64(56)) << shift
    return gain, loss, base


WORD_BITS = 64


def pack_rows(masks: np.ndarray) -> np.ndarray:
    """(K, H, W) bool -> (K, H, ceil(W / 64)) uint64: bit c % 64 of word c // 64 is column c
    (columns past W clear). A padded stack of cameras of different sizes must have each
    camera's pixels beyond its own image cleared first (``packing.clear_padding``): windows cut
    from the rows take them for outside the image."""
    masks = np.asarray(masks, dtype=np.bool_)
    K, H, W = masks.shape
    words = (W + WORD_BITS - 1) // WORD_BITS
    padded = np.zeros((K, H, words * WORD_BITS), np.bool_)
    padded[:, :, :W] = masks
    octets = np.packbits(padded, axis=2, bitorder="little")  # byte b's bit i: column 8 b + i
    return np.ascontiguousarray(octets).view("<u8").astype(np.uint64, copy=False).reshape(K, H, words)


@njit(cache=True, nogil=True, inline="always")
def _bits_at(row: np.ndarray, column: int) -> np.uint64:
    """The 64 bits of a packed row from ``column`` on (may be negative or past the row's end:
    the columns there are clear), column first in bit 0."""
    word = column >> 6  # floor division: -1 for columns -64..-1
    shift = column & 63
    n = row.shape[0]
    low = row[word] if 0 <= word < n else np.uint64(0)
    if shift == 0:
        return low
    high = row[word + 1] if 0 <= word + 1 < n else np.uint64(0)
    return (low >> np.uint64(shift)) | (high << np.uint64(64 - shift))


@njit(cache=True, nogil=True)
def window_value_bits(packed: np.ndarray, x0: np.ndarray, y0: np.ndarray, rows: int, width: int,
                      C: np.ndarray, drawable: np.ndarray, bounds: np.ndarray) -> tuple:
    """The value bit masks of windows of ``rows`` x ``width`` pixels with corners (x0, y0) (K,)
    int, cut from ``packed`` (K, H, words) masks (``pack_rows``; rows and columns outside an
    image are clear), with the still parts drawn as the conics C (1, K, S, 3, 3), drawable
    (1, K, S) (S may be 0): gain (+1: neither still part nor silhouette) and loss (-1:
    silhouette, no still part), (K, rows, ceil(width / 64)) uint64, and |still xor silhouette|
    per camera, (K,) int64, as ``xor_bits`` of the byte windows. Only pixels inside ``bounds`` (K, 4) int, each camera's
    x_lo, y_lo, x_hi, y_hi (``energy.counted_bounds``), are worth anything; the rest are worth
    nothing whatever covers them."""
    K, H = packed.shape[0], packed.shape[1]
    S = C.shape[2]
    words = (width + 63) // 64
    gain = np.zeros((K, rows, words), np.uint64)
    loss = np.zeros((K, rows, words), np.uint64)
    still = np.zeros((rows, words), np.uint64)
    base = np.zeros(K, np.int64)
    fw = float(width)
    spare = words * 64 - width
    last_word = _ALL_BITS >> np.uint64(spare) if spare else _ALL_BITS
    for k in range(K):
        for s in range(S):
            first, last = _conic_rows(C[0, k, s], drawable[0, k, s], float(y0[k]), rows)
            if last <= first:
                continue
            cu, cv, q0, q1, q2 = _conic_row_form(C[0, k, s], float(x0[k]))
            for r in range(first, last):
                start, end = _row_span(cu, cv, q0, q1, q2, float(r) + float(y0[k]), fw)
                if end > start:
                    _or_span(still, r, start, end)
        for r in range(rows):
            y = y0[k] + r
            if not bounds[k, 1] <= y < bounds[k, 3]:
                still[r, :] = np.uint64(0)
                continue
            inside_rows = 0 <= y < H
            for j in range(words):
                x = x0[k] + 64 * j
                mask = _span_bits(x, bounds[k, 0], bounds[k, 2]) & (last_word if j == words - 1 else _ALL_BITS)
                silhouette = np.uint64(0)
                if inside_rows:
                    silhouette = _bits_at(packed[k, y], x) & mask
                s_bits = still[r, j] & mask
                gain[k, r, j] = ~s_bits & ~silhouette & mask
                loss[k, r, j] = ~s_bits & silhouette
                base[k] += _popcount(s_bits ^ silhouette)
                still[r, j] = np.uint64(0)
    return gain, loss, base


@njit(cache=True, nogil=True, inline="always")
def _span_bits(x: int, lo: int, hi: int) -> np.uint64:
    """The bits of the 64 columns x..x+63 that lie in [lo, hi), column x in bit 0."""
    first, end = max(0, lo - x), min(64, hi - x)
    if end <= first:
        return np.uint64(0)
    span = _ALL_BITS if end - first == 64 else (np.uint64(1) << np.uint64(end - first)) - np.uint64(1)
    return span << np.uint64(first)


@njit(cache=True, nogil=True)
def cut_windows(packed: np.ndarray, x0: np.ndarray, y0: np.ndarray, rows: int, width: int) -> np.ndarray:
    """(K, rows, width) bool windows with corners (x0, y0) (K,) cut from ``packed`` masks
    (``pack_rows``), clear outside the images: what the byte energies (gl) are given."""
    K, H = packed.shape[0], packed.shape[1]
    out = np.zeros((K, rows, width), np.bool_)
    for k in range(K):
        for r in range(rows):
            y = y0[k] + r
            if not 0 <= y < H:
                continue
            for j in range(0, width, 64):
                bits = _bits_at(packed[k, y], x0[k] + j)
                for c in range(min(64, width - j)):
                    out[k, r, j + c] = (bits >> np.uint64(c)) & np.uint64(1) != 0
    return out
