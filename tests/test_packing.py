import numpy as np
import pytest

from common.packing import (downsample_masks, pack_planes, packbits_masks, packed_length, plane_count,
                            unpack_planes, unpackbits_masks, window)

CAMERA_COUNTS = [1, 5, 8, 9, 16]
SIZES = [(1, 1), (7, 13), (17, 31), (240, 320)]


def random_masks(K, H, W, seed=0, p=0.4):
    return np.random.default_rng(seed).random((K, H, W)) < p


@pytest.mark.parametrize("K", CAMERA_COUNTS)
@pytest.mark.parametrize("H, W", SIZES)
def test_planes_round_trip(K, H, W):
    masks = random_masks(K, H, W, seed=K * 1000 + H)
    planes = pack_planes(masks)
    assert planes.shape == (plane_count(K), H, W) and planes.dtype == np.uint8
    out = unpack_planes(planes, K)
    assert out.dtype == bool and out.shape == (K, H, W)
    np.testing.assert_array_equal(out, masks)


@pytest.mark.parametrize("K", CAMERA_COUNTS)
def test_camera_k_is_bit_k_mod_8_of_plane_k_div_8(K):
    for k in range(K):
        masks = np.zeros((K, 2, 3), dtype=bool)
        masks[k, 1, 2] = True
        planes = pack_planes(masks)
        expected = np.zeros_like(planes)
        expected[k // 8, 1, 2] = 1 << (k % 8)
        np.testing.assert_array_equal(planes, expected)


def test_planes_bits_beyond_K_are_zero_and_nonzero_counts_as_set():
    planes = pack_planes(np.full((5, 3, 4), 255, dtype=np.uint8))
    assert np.all(planes == 0b00011111)


def test_plane_count():
    assert [plane_count(k) for k in (1, 7, 8, 9, 16, 17, 64)] == [1, 1, 1, 2, 2, 3, 8]


def test_unpack_planes_rejects_bad_input():
    planes = pack_planes(random_masks(9, 4, 4))
    with pytest.raises(ValueError):
        unpack_planes(planes, 17)
    with pytest.raises(ValueError):
        unpack_planes(planes, 0)
    with pytest.raises(ValueError):
        unpack_planes(planes.astype(np.uint16), 9)
    with pytest.raises(ValueError):
        pack_planes(np.zeros((4, 4), dtype=bool))


@pytest.mark.parametrize("K", CAMERA_COUNTS)
@pytest.mark.parametrize("H, W", SIZES)
def test_packbits_round_trip(K, H, W):
    masks = random_masks(K, H, W, seed=K + W)
    data = packbits_masks(masks)
    assert isinstance(data, bytes)
    assert len(data) == packed_length(K, H, W) == -(-K * H * W // 8)
    np.testing.assert_array_equal(unpackbits_masks(data, K, H, W), masks)


def test_packbits_layout_is_c_order_msb_first():
    masks = np.zeros((2, 1, 5), dtype=bool)
    masks[0, 0, 0] = True  # bit 0 of the stream
    masks[1, 0, 4] = True  # bit 9 of the stream
    assert packbits_masks(masks) == bytes([0b10000000, 0b01000000])


def test_unpackbits_rejects_wrong_length():
    data = packbits_masks(random_masks(3, 5, 7))
    with pytest.raises(ValueError, match="bytes"):
        unpackbits_masks(data[:-1], 3, 5, 7)
    with pytest.raises(ValueError, match="bytes"):
        unpackbits_masks(data + b"\0", 3, 5, 7)


def test_window_inside_is_a_slice():
    planes = pack_planes(random_masks(9, 20, 30))
    out = window(planes, 4, 3, 10, 8)
    assert out.shape == (2, 8, 10) and out.dtype == np.uint8
    np.testing.assert_array_equal(out, planes[:, 3:11, 4:14])
    out[:] = 0  # a copy, not a view
    assert planes[:, 3:11, 4:14].any()


@pytest.mark.parametrize("x0, y0", [(-3, -2), (25, 15), (-5, 14), (27, -4)])
def test_window_pads_zeros_at_edges(x0, y0):
    planes = np.arange(1, 1 + 2 * 18 * 30, dtype=np.int64).reshape(2, 18, 30)  # no zeros inside
    w, h = 8, 6
    out = window(planes, x0, y0, w, h)
    assert out.shape == (2, h, w)
    for j in range(h):
        for i in range(w):
            y, x = y0 + j, x0 + i
            inside = 0 <= y < 18 and 0 <= x < 30
            np.testing.assert_array_equal(out[:, j, i], planes[:, y, x] if inside else 0)


def test_window_outside_and_larger_than_image():
    masks = random_masks(3, 5, 6)
    assert not window(masks, 100, 100, 4, 4).any()
    assert not window(masks, -10, 0, 4, 4).any()
    big = window(masks, -2, -1, 10, 8)
    assert big.shape == (3, 8, 10) and big.dtype == bool
    np.testing.assert_array_equal(big[:, 1:6, 2:8], masks)
    assert big.sum() == masks.sum()
    assert window(masks, 0, 0, 0, 0).shape == (3, 0, 0)
    with pytest.raises(ValueError):
        window(masks, 0, 0, -1, 4)


def test_downsample_rule_at_least_2_of_4():
    # one 2x2 block per output pixel, with 0..4 source pixels set
    blocks = [np.zeros((2, 2), dtype=bool) for _ in range(5)]
    for n, b in enumerate(blocks):
        b.flat[:n] = True
    masks = np.concatenate(blocks, axis=1)[None]  # (1, 2, 10)
    out = downsample_masks(masks)
    assert out.shape == (1, 1, 5) and out.dtype == bool
    assert out[0, 0].tolist() == [False, False, True, True, True]
    diagonal = np.array([[[True, False], [False, True]]])
    assert downsample_masks(diagonal)[0, 0, 0]


def test_downsample_matches_block_count_and_drops_odd_edge():
    masks = random_masks(5, 17, 31, seed=3, p=0.5)
    out = downsample_masks(masks)
    assert out.shape == (5, 8, 15)
    counts = (masks[:, 0:16:2, 0:30:2].astype(int) + masks[:, 1:16:2, 0:30:2]
              + masks[:, 0:16:2, 1:30:2] + masks[:, 1:16:2, 1:30:2])
    np.testing.assert_array_equal(out, counts >= 2)


def test_downsample_other_factors():
    masks = random_masks(2, 9, 12, seed=4, p=0.5)
    np.testing.assert_array_equal(downsample_masks(masks, 1), masks)
    out = downsample_masks(masks, 3)
    assert out.shape == (2, 3, 4)
    counts = masks.reshape(2, 3, 3, 4, 3).sum(axis=(2, 4))
    np.testing.assert_array_equal(out, counts >= 5)  # at least half of 9
    with pytest.raises(ValueError):
        downsample_masks(masks, 0)
    with pytest.raises(ValueError):
        downsample_masks(masks, 1.5)
