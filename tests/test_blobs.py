"""The compiled blob kernels (common.blobs) against scipy.ndimage, whose pixels they must give."""
import numpy as np
import pytest
from scipy import ndimage

from common.blobs import big_blobs_centroid, dilate, label_blobs, supported_blobs

pytestmark = pytest.mark.timeout(120)


def _masks(seed: int, count: int):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        yield rng.random((h, w)) < rng.random()


def test_label_blobs_numbers_the_blobs_as_scipy_does():
    for mask in _masks(1, 200):
        expected, count = ndimage.label(mask)
        labels, n = label_blobs(mask)
        assert n == count
        np.testing.assert_array_equal(labels, expected)


def test_label_blobs_of_a_checkerboard_and_of_a_spiral():
    board = (np.indices((9, 11)).sum(axis=0) % 2 == 0)  # the most blobs an image can hold
    for mask, count in ((board, 50), (~board, 49)):
        labels, n = label_blobs(mask)
        assert n == count
        np.testing.assert_array_equal(labels, ndimage.label(mask)[0])
    spiral = np.zeros((15, 15), dtype=bool)  # one blob whose two arms meet late: labels merged
    spiral[0, :] = spiral[:, 14] = spiral[14, :] = spiral[2:, 0] = spiral[2, :12] = spiral[2:12, 12] = True
    spiral[12, 3:13] = spiral[4:12, 3] = spiral[4, 3:11] = True
    labels, n = label_blobs(spiral)
    np.testing.assert_array_equal(labels, ndimage.label(spiral)[0])


@pytest.mark.parametrize("square", [False, True])
def test_dilate_is_scipys_iterated_dilation(square):
    structure = ndimage.generate_binary_structure(2, 2 if square else 1)
    for mask in _masks(2, 150):
        for radius in range(1, 6):
            np.testing.assert_array_equal(dilate(mask, radius, square),
                                          ndimage.binary_dilation(mask, structure, iterations=radius))
        np.testing.assert_array_equal(dilate(mask, 0, square), mask)


def test_supported_blobs_keeps_the_blobs_the_support_covers_enough():
    mask = np.zeros((20, 30), dtype=bool)
    mask[2:10, 2:10] = True    # 64 pixels, 24 supported (0.375): kept
    mask[12:18, 2:8] = True    # 36 pixels, 6 supported (0.17), a quarter of the best: dropped
    mask[2:6, 20:24] = True    # 16 pixels, 14 supported: kept
    mask[12:14, 20:22] = True  # 4 pixels, none supported: dropped
    support = np.zeros_like(mask)
    support[2:5, 2:10] = True
    support[12:13, 2:8] = True
    support[2:6, 20:24] = True
    support[2, 20:22] = False
    out = supported_blobs(mask, support, 0.3, 0.5)
    expected = np.zeros_like(mask)
    expected[2:10, 2:10] = expected[2:6, 20:24] = True
    np.testing.assert_array_equal(out, expected)
    # half of the best blob's support keeps a blob whose own share is low
    out = supported_blobs(mask, support, 0.3, 0.2)
    expected[12:18, 2:8] = True
    np.testing.assert_array_equal(out, expected)


def test_big_blobs_centroid_leaves_out_small_blobs():
    mask = np.zeros((40, 50), dtype=bool)
    mask[10:20, 30:40] = True  # 100 pixels, centroid (34.5, 14.5)
    mask[0, 0] = mask[39, 49] = True  # specks
    x, y, n = big_blobs_centroid(mask, 50)
    assert (x, y, n) == (34.5, 14.5, 100)
    assert big_blobs_centroid(mask, 101)[2] == 0
    assert big_blobs_centroid(np.zeros((5, 5), dtype=bool), 1.0) == (0.0, 0.0, 0)
