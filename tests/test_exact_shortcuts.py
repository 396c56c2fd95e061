"""The per-submap shortcuts of the hot path give exactly what the plain NumPy they replace gives.

Each shortcut (a bracketed k-th smallest value, bucketed confidence ranks, OpenCV's float16
conversion, a sign test of the median by counts, shared DLT terms) claims bit-for-bit equality
with a one-line NumPy expression; these tests hold it to that on awkward inputs: ties, NaN,
negative zero, values outside the levels, huge and tiny magnitudes.
"""

from __future__ import annotations

import numpy as np
import pytest

from sl4slam.alignment.dlt import (_dlt_normal_matrix, dlt_normal_matrix_from_terms, dlt_normal_terms,
                                   median_is_negative)
from sl4slam.geometry import decompose_projection, projection_intrinsics
from sl4slam.submap import (KTH_SAMPLE, _kth_smallest, confidence_levels, confidence_mask, confidence_mask_and_levels,
                            confidence_ranks, to_float16)


@pytest.mark.parametrize("seed", range(4))
def test_kth_smallest_equals_a_full_partition(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = KTH_SAMPLE * 12 + seed
    values = [rng.standard_normal(n).astype(np.float32),
              rng.integers(0, 5, n).astype(np.float32),  # heavy ties
              np.sort(rng.random(n).astype(np.float32)),  # sorted: the strided sample is not random
              np.exp(rng.normal(0, 8, n)).astype(np.float32)]
    for v in values:
        for k in (0, 1, n // 3, n // 2, n - 2, n - 1):
            assert _kth_smallest(v, k) == np.partition(v, k)[k]


def test_confidence_mask_and_levels_match_their_definitions() -> None:
    rng = np.random.default_rng(1)
    confidence = rng.gamma(2.0, 1.0, (5, 60, 80)).astype(np.float32)
    depth = rng.uniform(0.5, 4, confidence.shape).astype(np.float32)
    depth[0, :3] = np.nan
    depth[1, 5, :] = 0.0
    confidence[2, 7, 7] = np.inf
    valid = np.isfinite(depth) & (depth > 0) & np.isfinite(confidence)
    values = confidence[valid]
    k = int(round(0.25 * (len(values) - 1)))
    expected_mask = valid & (confidence > np.partition(values, k)[k])
    np.testing.assert_array_equal(confidence_mask(confidence, depth, 25.0), expected_mask)
    mask, levels = confidence_mask_and_levels(confidence, depth, 25.0)
    np.testing.assert_array_equal(mask, expected_mask)
    np.testing.assert_array_equal(levels, confidence_levels(confidence, depth))


def test_confidence_ranks_equal_searchsorted() -> None:
    rng = np.random.default_rng(2)
    confidence = rng.gamma(2.0, 1.0, (120, 160)).astype(np.float32)
    levels = confidence_levels(confidence[None], np.ones((1, 120, 160), np.float32))
    query = np.concatenate([confidence.ravel(), levels, np.nextafter(levels, np.float32(np.inf)),
                            np.array([np.nan, -0.0, 0.0, -1.0, 1e30, -np.inf, np.inf], np.float32)])
    expected = np.searchsorted(levels, query).astype(np.uint8)
    np.testing.assert_array_equal(confidence_ranks(levels, query), expected)
    # levels with repeats, and negative levels
    levels2 = np.sort(np.concatenate([levels[:100], levels[:100], -levels[100:]])).astype(np.float32)
    np.testing.assert_array_equal(confidence_ranks(levels2, query), np.searchsorted(levels2, query).astype(np.uint8))


def test_float16_conversion_is_numpys_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    x = (rng.standard_normal((64, 96)) * np.exp(rng.uniform(-20, 14, (64, 96)))).astype(np.float32)
    x[0, :6] = [np.nan, np.inf, -np.inf, -0.0, 65520.0, 6e-8]
    with np.errstate(over="ignore"):  # values beyond float16's range become inf in both
        expected = x.astype(np.float16)
    np.testing.assert_array_equal(to_float16(x).view(np.uint16), expected.view(np.uint16))


def test_median_sign_by_counts_equals_numpy_median() -> None:
    rng = np.random.default_rng(4)
    cases = [rng.standard_normal(n) for n in (1, 2, 7, 8, 101, 1000)]
    cases += [np.array([-1.0, 1.0]), np.array([-2.0, 1.0]), np.array([-1.0, 2.0]), np.array([-1.0, 0.0]),
              np.array([np.nan, -1.0, -2.0]), np.zeros(0), np.array([-3.0, -1.0, 0.5, 4.0])]
    for values in cases:
        with np.errstate(invalid="ignore"):
            expected = bool(np.median(values) < 0) if len(values) else False
        assert median_is_negative(values) == expected


def test_shared_dlt_terms_give_the_same_normal_matrix() -> None:
    rng = np.random.default_rng(5)
    X_a, X_b = rng.standard_normal((500, 3)), rng.standard_normal((500, 3))
    weights = rng.uniform(0.5, 2.0, 200)
    chosen = rng.choice(500, 200, replace=False)
    coefficients, outer = dlt_normal_terms(X_a, X_b)
    np.testing.assert_array_equal(
        dlt_normal_matrix_from_terms(np.take(coefficients, chosen, 0), np.take(outer, chosen, 0), weights),
        _dlt_normal_matrix(X_a[chosen], X_b[chosen], weights))


def test_projection_intrinsics_equal_the_full_decomposition() -> None:
    rng = np.random.default_rng(6)
    P = rng.standard_normal((10, 3, 4))
    np.testing.assert_array_equal(projection_intrinsics(P), decompose_projection(P)[0])
