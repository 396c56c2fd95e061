"""Relative alignment: DLT, RANSAC in SL(4) and Sim(3), fallbacks, shared-frame Sim(3)."""

from __future__ import annotations

import numpy as np
import pytest

from sl4slam.alignment import (
    dlt_sl4,
    estimate_sim3,
    estimate_sl4,
    minimal_sl4_batch,
    normalize_points,
    sim3_from_shared_frame,
)
from sl4slam.alignment.ransac import hypotheses_needed, ransac_best
from sl4slam.config import AlignmentConfig
from sl4slam.synthetic.correspondences import frame_correspondences, near_identity_sl4, random_rotation
from sl4slam.geometry import apply_transform, normalize_sl4, se3_inverse


def frame_points(
    rng: np.random.Generator,
    H_a_b: np.ndarray,
    height: int = 74,
    width: int = 130,
    noise: float = 0.002,
    outlier_fraction: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame's confident points in submaps ``b`` and ``a`` (see ``frame_correspondences``)."""
    return frame_correspondences(rng, H_a_b, height, width, noise, outlier_fraction)


def points_in_front(rng: np.random.Generator, H: np.ndarray, count: int) -> np.ndarray:
    """``count`` random points in a box whose image under ``H`` has ``w > 0.2``."""
    X = rng.uniform(-1.5, 1.5, size=(20 * count, 3)) + [0, 0, 2]
    w = X @ H[3, :3] + H[3, 3]
    return X[w > 0.2][:count]


def transfer_rms(H_est: np.ndarray, H_true: np.ndarray, X_b: np.ndarray) -> float:
    """RMS distance between the points ``X_b (N, 3)`` mapped by the estimate and by the truth."""
    return float(np.sqrt(((apply_transform(H_est, X_b) - apply_transform(H_true, X_b)) ** 2).sum(1).mean()))


def random_sl4(rng: np.random.Generator) -> np.ndarray:
    while True:
        H = np.eye(4) + 0.4 * rng.normal(size=(4, 4))
        if np.linalg.det(H) > 0:
            return normalize_sl4(H)


@pytest.mark.parametrize("count", [5, 1000])
def test_dlt_recovers_random_sl4_exactly(count: int) -> None:
    rng = np.random.default_rng(count)
    for _ in range(5):
        H = random_sl4(rng)
        X_b = points_in_front(rng, H, count)
        assert len(X_b) == count
        H_est = dlt_sl4(apply_transform(H, X_b), X_b)
        assert np.linalg.det(H_est) == pytest.approx(1.0, abs=1e-9)
        np.testing.assert_allclose(H_est, H, atol=1e-8 * np.abs(H).max())


def test_dlt_fixes_sign_and_rejects_too_few_points() -> None:
    rng = np.random.default_rng(3)
    H = random_sl4(rng)
    X_b = points_in_front(rng, H, 50)
    X_a = apply_transform(H, X_b)
    # Whatever sign the null vector comes out with, w > 0 on the points decides it.
    w = X_b @ dlt_sl4(X_a, X_b)[3, :3] + dlt_sl4(X_a, X_b)[3, 3]
    assert (w > 0).all()
    with pytest.raises(ValueError, match="at least 5"):
        dlt_sl4(X_a[:4], X_b[:4])


def test_minimal_batch_matches_truth_and_discards_degenerate_samples() -> None:
    rng = np.random.default_rng(4)
    H = near_identity_sl4(rng)
    X_b = points_in_front(rng, H, 40).reshape(8, 5, 3)
    X_a = apply_transform(H, X_b)
    # Sample 0: four coplanar points (z = 2); sample 1: a repeated point.
    X_b[0, :4, 2] = 2.0
    X_a[0] = apply_transform(H, X_b[0])
    X_b[1, 4], X_a[1, 4] = X_b[1, 0], X_a[1, 0]
    H_batch, valid = minimal_sl4_batch(X_a, X_b)
    assert valid.tolist() == [False, False] + [True] * 6
    for H_est in H_batch[valid]:
        np.testing.assert_allclose(H_est, H, atol=1e-8)


def test_minimal_batch_discards_samples_split_by_the_plane_at_infinity() -> None:
    # Points on both sides of the plane w = 0 of H: such a hypothesis is not a valid alignment.
    H = np.eye(4)
    H[3, 2] = 1.0  # w = z + 1
    X_b = np.array([[0.3, 0.1, 0.5], [-0.4, 0.2, 1.0], [0.1, -0.3, 2.0], [0.5, 0.5, -3.0], [-0.2, 0.4, 0.2]])
    X_a = apply_transform(H, X_b)
    _, valid = minimal_sl4_batch(X_a[None], X_b[None])
    assert not valid[0]


def test_normalize_points_is_hartley() -> None:
    rng = np.random.default_rng(5)
    X = rng.normal(size=(100, 3)) * 7 + 40
    X_n, T = normalize_points(X)
    np.testing.assert_allclose(X_n.mean(0), 0, atol=1e-12)
    assert np.linalg.norm(X_n, axis=1).mean() == pytest.approx(np.sqrt(3))
    np.testing.assert_allclose(apply_transform(T, X), X_n, atol=1e-12)


def test_ransac_recovers_h_with_40_percent_clustered_outliers() -> None:
    rng = np.random.default_rng(6)
    H = near_identity_sl4(rng)
    # Half the 518x294 prediction grid: ~26k confident points, ~15k inliers.
    X_a, X_b, is_inlier = frame_points(rng, H, height=147, width=259, outlier_fraction=0.4)
    assert 0.38 < 1 - is_inlier.mean() < 0.55 and len(X_a) > 20000
    result = estimate_sl4(X_a, X_b, AlignmentConfig(), seed=0)
    assert result.model == "sl4" and result.fallback is None
    assert np.linalg.det(result.H) == pytest.approx(1.0, abs=1e-9)
    assert np.abs(result.H - H).max() < 1e-3
    assert (result.inliers == is_inlier).mean() > 0.995
    # As accurate as a least-squares fit that knows which points are inliers.
    oracle = dlt_sl4(X_a[is_inlier], X_b[is_inlier])
    assert transfer_rms(result.H, H, X_b[is_inlier]) < 1.2 * transfer_rms(oracle, H, X_b[is_inlier])
    assert result.inlier_ratio == pytest.approx(is_inlier.mean(), abs=0.005)
    # Noise sigma 0.002 per axis: inlier RMS ~ 0.002 * sqrt(3).
    assert 0.002 < result.rms < 0.005
    assert result.extras["degenerate_samples"] < result.extras["hypotheses"]


def test_hypotheses_needed_is_the_classic_bound() -> None:
    # log(1 - p) / log(1 - w^k): 5-point samples at 50 % inliers need ~218 for p = 0.999
    assert hypotheses_needed(0.5, 5, 0.999) == pytest.approx(np.log(0.001) / np.log(1 - 0.5**5))
    assert 217 < hypotheses_needed(0.5, 5, 0.999) < 218
    assert hypotheses_needed(1.0, 5, 0.999) == 0.0
    assert hypotheses_needed(0.0, 5, 0.999) == float("inf")


def test_ransac_draws_hypotheses_adaptively() -> None:
    rng = np.random.default_rng(11)
    H = near_identity_sl4(rng)
    drawn = {}
    for outliers in (0.0, 0.6):
        X_a, X_b, is_inlier = frame_points(rng, H, outlier_fraction=outliers)
        result = estimate_sl4(X_a, X_b, AlignmentConfig(), seed=0)
        drawn[outliers] = result.extras["hypotheses"]
        assert np.abs(result.H - H).max() < 1e-2 and result.fallback is None
        assert (result.inliers == is_inlier).mean() > 0.99
        # the same batches with a lower confidence stop no later
        quick = estimate_sl4(X_a, X_b, AlignmentConfig(ransac_confidence=0.5), seed=0)
        assert quick.extras["hypotheses"] <= drawn[outliers]
    # clean points: the first batch holds an all-inlier sample; ~60 % clustered outliers
    # (w^5 ~ 1 %) need several batches, and never more than the paper's 300
    assert drawn[0.0] == AlignmentConfig().hypothesis_batch
    assert AlignmentConfig().hypothesis_batch < drawn[0.6] <= 300


def test_early_stop_needs_well_spread_inliers() -> None:
    """A hypothesis that explains only a dominant plane may not end the sampling early."""
    rng = np.random.default_rng(12)
    H = near_identity_sl4(rng)
    X_a, X_b, _ = frame_points(rng, H)
    X_a_n, T_a = normalize_points(X_a)
    X_b_n, _ = normalize_points(X_b)
    config = AlignmentConfig()
    threshold = config.inlier_threshold * T_a[0, 0]  # in the normalized units
    seen: list[int] = []

    def refuse(inliers_b: np.ndarray) -> bool:
        seen.append(len(inliers_b))
        return False

    for hook, drawn in ((None, AlignmentConfig().hypothesis_batch), (lambda inliers_b: True, AlignmentConfig().hypothesis_batch), (refuse, 300)):
        _, stats = ransac_best(X_a_n, X_b_n, minimal_sl4_batch, 5, threshold, config, np.random.default_rng(0), hook)
        assert stats["hypotheses"] == drawn
        assert stats["stopped_early"] == (drawn < 300)
    assert seen and seen[0] > 0.9 * min(len(X_a), config.max_points)  # the best hypothesis' inliers are checked


def test_ransac_is_deterministic_given_the_seed() -> None:
    rng = np.random.default_rng(7)
    H = near_identity_sl4(rng)
    X_a, X_b, _ = frame_points(rng, H, outlier_fraction=0.3)
    config = AlignmentConfig(max_points=2000)
    first = estimate_sl4(X_a, X_b, config, seed=3)
    second = estimate_sl4(X_a, X_b, config, seed=3)
    np.testing.assert_array_equal(first.H, second.H)
    np.testing.assert_array_equal(first.inliers, second.inliers)
    assert first.extras["degenerate_samples"] == second.extras["degenerate_samples"]
    other = estimate_sl4(X_a, X_b, AlignmentConfig(max_points=2000, seed=1), seed=3)
    assert np.abs(other.H - H).max() < 1e-3


def test_planar_points_fall_back_to_sim3() -> None:
    rng = np.random.default_rng(8)
    T_a_b = np.eye(4)
    T_a_b[:3, :3] = 1.3 * random_rotation(rng, 0.4)
    T_a_b[:3, 3] = [0.2, -0.1, 0.3]
    X_b = np.column_stack([rng.uniform(-1, 1, 3000), rng.uniform(-1, 1, 3000), np.full(3000, 2.0)])
    X_a = apply_transform(T_a_b, X_b)
    result = estimate_sl4(X_a, X_b, AlignmentConfig(), seed=0)
    assert result.model == "sim3"
    assert "coplanar" in result.fallback
    assert np.isfinite(result.H).all() and not np.allclose(result.H, np.eye(4))
    np.testing.assert_allclose(result.H, T_a_b, atol=1e-9)
    assert result.inliers.all()


def test_coplanar_inliers_with_scattered_outliers_fall_back() -> None:
    # The input is not flat (outliers fill a volume) but the consensus set is a plane.
    rng = np.random.default_rng(9)
    plane = np.column_stack([rng.uniform(-1, 1, 3000), rng.uniform(-1, 1, 3000), np.full(3000, 2.0)])
    scattered = rng.uniform([-1, -1, 1], [1, 1, 3], size=(600, 3))
    X_b = np.concatenate([plane, scattered])
    X_a = X_b + [0.1, 0.0, 0.0]
    X_a[3000:] += rng.normal(scale=0.3, size=(600, 3))
    result = estimate_sl4(X_a, X_b, AlignmentConfig(), seed=0)
    assert result.model == "sim3" and result.fallback is not None
    assert np.isfinite(result.H).all()
    np.testing.assert_allclose(result.H[:3, 3], [0.1, 0, 0], atol=1e-6)
    assert result.inliers[:3000].all()


def test_too_few_points_fall_back_or_raise() -> None:
    rng = np.random.default_rng(10)
    H = near_identity_sl4(rng)
    X_b = points_in_front(rng, H, 20)
    X_a = apply_transform(H, X_b)
    result = estimate_sl4(X_a, X_b, AlignmentConfig(min_inliers=50), seed=0)
    assert result.model == "sim3" and "20 correspondences" in result.fallback
    X_a[2:] = np.nan
    with pytest.raises(ValueError, match="at least 5 finite correspondences, got 2"):
        estimate_sl4(X_a, X_b, AlignmentConfig(), seed=0)


def test_non_finite_rows_are_dropped() -> None:
    rng = np.random.default_rng(11)
    H = near_identity_sl4(rng)
    X_a, X_b, is_inlier = frame_points(rng, H, outlier_fraction=0.2)
    X_a[::7, 1] = np.nan
    X_b[3::11, 0] = np.inf
    result = estimate_sl4(X_a, X_b, AlignmentConfig(), seed=0)
    assert result.model == "sl4"
    assert not result.inliers[::7].any() and not result.inliers[3::11].any()
    finite = np.isfinite(X_a).all(1) & np.isfinite(X_b).all(1)
    assert (result.inliers[finite] == is_inlier[finite]).mean() > 0.995
    assert transfer_rms(result.H, H, X_b[finite & is_inlier]) < 2e-4
    assert result.extras["dropped_nonfinite"] == len(np.unique(np.r_[np.arange(0, len(X_a), 7), np.arange(3, len(X_a), 11)]))


def test_refit_improves_on_the_best_minimal_hypothesis() -> None:
    rng = np.random.default_rng(12)
    H = near_identity_sl4(rng)
    X_a, X_b, is_inlier = frame_points(rng, H, outlier_fraction=0.3)
    clean = X_b[is_inlier]
    refit = estimate_sl4(X_a, X_b, AlignmentConfig(refit=True), seed=0)
    plain = estimate_sl4(X_a, X_b, AlignmentConfig(refit=False), seed=0)
    assert plain.model == refit.model == "sl4"
    assert transfer_rms(refit.H, H, clean) < 0.5 * transfer_rms(plain.H, H, clean)
    assert transfer_rms(refit.H, H, clean) < 2e-4


def test_estimate_sim3_with_outliers() -> None:
    rng = np.random.default_rng(13)
    T_a_b = np.eye(4)
    T_a_b[:3, :3] = 0.8 * random_rotation(rng, 1.0)
    T_a_b[:3, 3] = [0.5, 0.2, -0.4]
    X_a, X_b, is_inlier = frame_points(rng, T_a_b, outlier_fraction=0.4)
    result = estimate_sim3(X_a, X_b, AlignmentConfig(), seed=0)
    assert result.model == "sim3" and result.fallback is None
    np.testing.assert_allclose(result.H, T_a_b, atol=1e-3)
    assert (result.inliers == is_inlier).mean() > 0.995
    with pytest.raises(ValueError, match="at least 3"):
        estimate_sim3(X_a[:2], X_b[:2], AlignmentConfig())


def test_sim3_from_shared_frame() -> None:
    rng = np.random.default_rng(14)
    # The shared frame's camera sits at different poses in the two submaps, and submap b's
    # reconstruction is 0.6 times the scale of submap a's.
    T_cam_a = se3_inverse(np.block([[random_rotation(rng, 1.0), rng.normal(size=(3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    T_cam_b = se3_inverse(np.block([[random_rotation(rng, 1.0), rng.normal(size=(3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    scale_b = 0.6
    X_cam = rng.uniform([-1, -1, 0.5], [1, 1, 3], size=(500, 3))
    X_a = apply_transform(se3_inverse(T_cam_a), X_cam)
    X_b = apply_transform(se3_inverse(T_cam_b), X_cam * scale_b)
    X_b[:100] *= 1.5  # a minority of bad depths does not move the median ratio
    X_a[0] = np.nan
    result = sim3_from_shared_frame(T_cam_a[:3], T_cam_b, X_a, X_b)
    assert result.model == "sim3"
    assert result.extras["scale"] == pytest.approx(1 / scale_b, rel=1e-12)
    expected = se3_inverse(T_cam_a) @ np.diag([1 / scale_b] * 3 + [1]) @ T_cam_b
    np.testing.assert_allclose(result.H, expected, atol=1e-12)
    np.testing.assert_allclose(apply_transform(result.H, X_b[100:]), X_a[100:], atol=1e-9)
    assert result.inliers[100:].all() and not result.inliers[:100].any()
    assert result.inlier_ratio == pytest.approx(0.8)


def test_points_mapped_through_infinity_are_outliers() -> None:
    from sl4slam.alignment.ransac import score_one

    H = np.eye(4)
    H[3, 2] = -0.5  # w = 1 - z / 2: points with z >= 2 go through the plane at infinity
    X_b = np.array([[0.0, 0.0, 1.0], [0.1, 0.2, 3.0], [0.0, 0.0, 2.0]])
    # Even a target that equals the projectively mapped point does not count behind infinity.
    X_a = np.array([[0.0, 0.0, 2.0], [-0.2, -0.4, -6.0], [0.0, 0.0, 0.0]])
    cost, inliers, r2 = score_one(H, X_a, X_b, 0.01)
    assert inliers.tolist() == [True, False, False]
    assert r2[0] == pytest.approx(0.0)
    assert cost == pytest.approx(2 * 0.01**2)


def test_matrix_log_and_exp_agree_with_scipy_and_invert_each_other() -> None:
    """The series logarithm and exponential of 4x4 transforms (the tangent means and scatters of
    links) match SciPy's ``logm``/``expm`` to float64 rounding, invert each other, and take the
    general path for a matrix far from the identity; a batch equals its matrices one by one."""
    from scipy.linalg import expm, logm

    from sl4slam.geometry import LOG_SERIES_RADIUS, matrix_exp, matrix_log

    rng = np.random.default_rng(5)
    for scale in (1e-4, 0.01, 0.05, 0.3, 1.5):
        A = rng.normal(size=(6, 4, 4)) * scale
        M = np.stack([expm(a) for a in A])
        near = np.linalg.norm(M - np.eye(4), axis=(1, 2)) <= LOG_SERIES_RADIUS
        if scale >= 1.5:
            assert not near.any()  # the general path is taken, and must agree too
        L = matrix_log(M)
        for m, l in zip(M, L):
            np.testing.assert_allclose(l, np.real(logm(m)), rtol=0, atol=1e-12 * max(1.0, np.abs(l).max()))
        np.testing.assert_allclose(matrix_exp(L), M, rtol=0, atol=1e-12 * np.abs(M).max())
        E = matrix_exp(A)
        for a, e in zip(A, E):
            np.testing.assert_allclose(e, expm(a), rtol=0, atol=1e-12 * np.abs(e).max())
        assert np.array_equal(matrix_log(M[2]), L[2]) and np.array_equal(matrix_exp(A[2]), E[2])


@pytest.mark.parametrize("link_ratio, fit_ratio, chosen, fitted", [
    (0.5, 1.0, "link", False),    # the fit cannot explain 2.5x the link's share: not measured
    (0.3, 0.99, "fit", True),     # 0.99 >= 2.5 * 0.3 and >= 0.97: the fit
    (0.3, 0.74, "link", True),    # measured, and short of 2.5x
    (0.39, 0.96, "link", True),   # measured, 2.5x but below planar_fit_min_inlier_ratio
])
def test_by_support_measures_the_constrained_fit_only_where_it_can_win(monkeypatch, link_ratio, fit_ratio,
                                                                        chosen, fitted) -> None:
    """A degenerate frame under ``planar_model = "by-support"``: the camera-constrained fit wins only
    with ``planar_support_margin`` times the link's inlier share and at least
    ``planar_fit_min_inlier_ratio``; where the link's share makes the first impossible, the fit is
    not measured at all."""
    import sl4slam.alignment.aligner as aligner_module
    from sl4slam.alignment.aligner import SL4Aligner
    from sl4slam.types import Alignment, FrameView

    def alignment(ratio: float) -> Alignment:
        return Alignment(np.eye(4), np.ones(10, bool), ratio, 0.0, "sl4")

    calls = []
    monkeypatch.setattr(SL4Aligner, "camera_edge", lambda self, view_a, view_b: alignment(link_ratio))
    monkeypatch.setattr(aligner_module, "camera_constrained_sl4",
                        lambda *args: calls.append(args) or alignment(fit_ratio))
    view = FrameView(np.zeros((2, 2, 3), np.float32), np.ones((2, 2), bool), np.eye(3), np.eye(4))
    result = SL4Aligner(AlignmentConfig())._degenerate(np.zeros((10, 3)), np.zeros((10, 3)), view, view, 0, "flat")
    assert result.inlier_ratio == (fit_ratio if chosen == "fit" else link_ratio)
    assert ("camera-constrained" in result.fallback) == (chosen == "fit")
    assert bool(calls) == fitted
