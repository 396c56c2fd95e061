"""Edges: evidence weighting, the checks every edge passes, the aligners and the camera-constrained fit."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from scipy.linalg import logm
from scipy.spatial.transform import Rotation

from sl4slam.alignment import camera_constrained_sl4, estimate_sl4, make_aligner, shared_pixels
from sl4slam.resolve import resolve
from sl4slam.backend import SL4Backend
from sl4slam.backend.evidence import edge_information, tangent_coordinates, transfer_jacobians
from sl4slam.config import AlignmentConfig, BackendConfig, SLAMConfig
from sl4slam.edges import camera_problem, edge_problem, is_camera_link
from sl4slam.geometry import apply_transform, decompose_projection, normalize_sl4, se3_inverse
from sl4slam.pipeline import keyframe_cameras
from sl4slam.submap import StoredKeyframe
from sl4slam.synthetic.correspondences import near_identity_sl4, random_rotation
from sl4slam.types import Alignment, FrameView, SubmapPrediction

GENERATORS = SL4Backend(BackendConfig()).generators()


def submap_graph_config() -> SLAMConfig:
    """The submap graph's settings: its aligner fits 15 DOF and measures degenerate frames otherwise."""
    config = SLAMConfig()
    config.backend.graph = "submap"
    return config


def alignment_from(H: np.ndarray, X_b: np.ndarray, rms: float, count: int | None = None, fallback: str | None = None) -> Alignment:
    n = len(X_b) if count is None else count
    return Alignment(H=H, inliers=np.ones(n, bool), inlier_ratio=1.0, rms=rms, model="sl4", fallback=fallback,
                     support=(apply_transform(H, X_b), X_b))


def test_transfer_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    H = near_identity_sl4(rng)
    X_b = rng.uniform([-1, -1, 1], [1, 1, 3], size=(20, 3))
    J = transfer_jacobians(H, X_b, GENERATORS)
    step = 1e-6
    for m in range(15):
        moved = np.asarray(gtsam.SL4.Expmap(-step * np.eye(15)[m]).matrix()) @ H  # H_true = exp(-xi) H
        numeric = (apply_transform(moved, X_b) - apply_transform(H, X_b)) / step
        np.testing.assert_allclose(J[:, :, m], numeric, atol=1e-4)


def test_information_sums_every_residual_component() -> None:
    rng = np.random.default_rng(4)
    H = near_identity_sl4(rng)
    X_b = rng.uniform([-1, -1, 1], [1, 1, 3], size=(300, 3))
    config = BackendConfig(effective_points=1e9, min_sigma=1e-9, max_sigma=1e9)
    J = transfer_jacobians(H, X_b, GENERATORS)
    rms = 0.004
    expected = sum(J[k].T @ J[k] for k in range(len(X_b))) / (rms**2 / 3.0)
    information = edge_information(alignment_from(H, X_b, rms=rms), GENERATORS, config)
    np.testing.assert_allclose(information, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


def test_weight_grows_with_evidence() -> None:
    rng = np.random.default_rng(1)
    H = near_identity_sl4(rng)
    X_b = rng.uniform([-1, -1, 1], [1, 1, 3], size=(2000, 3))
    config = BackendConfig(effective_points=1000.0, min_sigma=1e-6)
    base = edge_information(alignment_from(H, X_b[:100], rms=0.004), GENERATORS, config)
    more_points = edge_information(alignment_from(H, X_b[:800], rms=0.004), GENERATORS, config)
    less_noise = edge_information(alignment_from(H, X_b[:100], rms=0.002), GENERATORS, config)
    assert np.trace(more_points) == pytest.approx(8 * np.trace(base), rel=0.2)  # information ~ count
    np.testing.assert_allclose(less_noise, 4 * base, rtol=1e-9)  # ~ 1 / rms^2
    assert np.linalg.eigvalsh(more_points - base).min() > -1e-6 * np.trace(base)  # more evidence: larger in every direction
    # correlated dense residuals: the count stops helping beyond effective_points
    capped = dataclasses.replace(config, effective_points=100.0)
    many = edge_information(alignment_from(H, X_b[:800], rms=0.004), GENERATORS, capped)
    few = edge_information(alignment_from(H, X_b[:100], rms=0.004), GENERATORS, capped)
    assert np.trace(many) == pytest.approx(np.trace(few), rel=0.25)


def test_unobserved_directions_get_the_weak_floor_and_fallbacks_are_inflated() -> None:
    rng = np.random.default_rng(2)
    H = near_identity_sl4(rng)
    plane = np.column_stack([rng.uniform(-1, 1, 500), rng.uniform(-1, 1, 500), np.full(500, 2.0)])
    config = BackendConfig()
    information = edge_information(alignment_from(H, plane, rms=0.003), GENERATORS, config)
    values = np.linalg.eigvalsh(information)
    assert values.min() == pytest.approx(1 / config.max_sigma**2, rel=1e-6)  # the plane's projective family
    assert values.max() <= 1 / config.min_sigma**2 * (1 + 1e-9)
    fallback = edge_information(alignment_from(H, plane, rms=0.003, fallback="planar"), GENERATORS, config)
    np.testing.assert_allclose(fallback, information / config.fallback_sigma_scale**2, rtol=1e-12)
    fixed = dataclasses.replace(config, weighting="fixed")
    np.testing.assert_allclose(edge_information(alignment_from(H, plane, rms=0.003, fallback="x"), GENERATORS, fixed),
                               np.eye(15) / (config.sigma * config.fallback_sigma_scale) ** 2)


def test_information_predicts_the_spread_of_repeated_fits() -> None:
    """With independent Gaussian noise, the inverse information is the covariance of the refitted H."""
    rng = np.random.default_rng(3)
    H = near_identity_sl4(rng)
    X_b = rng.uniform([-1, -1, 1], [1, 1, 3], size=(400, 3))
    sigma = 0.002
    errors, informations = [], []
    for _ in range(120):
        X_a = apply_transform(H, X_b) + rng.normal(scale=sigma, size=X_b.shape)
        fit = estimate_sl4(X_a, X_b, AlignmentConfig(inlier_threshold=0.02), seed=0)
        errors.append(np.asarray(gtsam.SL4(np.linalg.inv(fit.H)).localCoordinates(gtsam.SL4(np.linalg.inv(H)))))
        informations.append(edge_information(fit, GENERATORS, BackendConfig(effective_points=1e6, min_sigma=1e-9)))
    empirical = np.cov(np.array(errors).T)
    predicted = np.linalg.inv(np.mean(informations, axis=0))
    ratio = np.trace(empirical) / np.trace(predicted)
    assert 0.6 < ratio < 1.6, ratio


def test_edge_checks_refuse_degenerate_measurements() -> None:
    config = AlignmentConfig()
    rng = np.random.default_rng(4)
    H = near_identity_sl4(rng)
    X_b = rng.uniform([-1, -1, 1], [1, 1, 3], size=(200, 3))
    good = alignment_from(H, X_b, rms=0.003)
    assert edge_problem(good, config) is None
    bad_det = dataclasses.replace(good, H=np.diag([-1.0, 1, 1, 1]))
    assert "det" in edge_problem(bad_det, config)
    assert "finite" in edge_problem(dataclasses.replace(good, H=np.full((4, 4), np.nan)), config)
    assert "ill-conditioned" in edge_problem(dataclasses.replace(good, H=np.diag([300.0, 1, 1, 1 / 300])), config)
    few = dataclasses.replace(good, inliers=np.r_[np.ones(10, bool), np.zeros(9990, bool)], inlier_ratio=0.001)
    assert "inliers" in edge_problem(few, config)
    assert edge_problem(few, config, fitted=False) is None  # the camera edge has no inlier requirement
    view = FrameView(np.zeros((2, 2, 3), np.float32), np.ones((2, 2), bool), np.diag([-300.0, 300, 1]), np.eye(4))
    assert "focal" in camera_problem(view)
    assert camera_problem(dataclasses.replace(view, K=np.diag([300.0, 300, 1]))) is None


def test_correspondences_are_strided_evenly_over_the_confident_pixels() -> None:
    mask_a = np.zeros((30, 40), bool)
    mask_a[5:25] = True
    mask_b = np.ones((30, 40), bool)
    mask_b[:, :10] = False
    view = lambda mask: FrameView(np.zeros((30, 40, 3), np.float32), mask, np.eye(3), np.eye(4))  # noqa: E731
    both = np.flatnonzero(mask_a & mask_b)
    np.testing.assert_array_equal(shared_pixels(view(mask_a), view(mask_b), 0), both)
    strided = shared_pixels(view(mask_a), view(mask_b), 100)
    assert len(strided) <= 100 and set(strided) <= set(both)
    np.testing.assert_array_equal(strided, both[:: -(-len(both) // 100)])  # every k-th: all rows are covered
    assert np.unique(strided // 40).size == 20


def test_camera_constrained_fit_recovers_a_planar_frame() -> None:
    """A planar shared frame leaves the 15-DOF point fit degenerate; the frame's two cameras fix it."""
    rng = np.random.default_rng(5)
    H = near_identity_sl4(rng)
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    T_cam_b = se3_inverse(np.block([[random_rotation(rng, 0.2), np.array([[0.1], [0.0], [-0.2]])], [np.zeros((1, 3)), 1]]))
    P_b = K @ T_cam_b[:3]
    plane_cam = np.column_stack([rng.uniform(-1, 1, 3000), rng.uniform(-0.8, 0.8, 3000), np.full(3000, 2.0)])
    X_b = apply_transform(se3_inverse(T_cam_b), plane_cam)
    X_a = apply_transform(H, X_b)
    P_a = P_b @ np.linalg.inv(H)  # the same image in submap a
    guess = np.eye(4)
    result = camera_constrained_sl4(X_a, X_b, P_a, P_b, guess, AlignmentConfig())
    assert result is not None and result.inlier_ratio > 0.99
    assert result.extras["camera_constrained"] and np.linalg.det(result.H) == pytest.approx(1.0)
    # the camera constraint holds: P_a H ~ P_b
    mapped = P_a @ result.H
    np.testing.assert_allclose(mapped / np.linalg.norm(mapped), P_b / np.linalg.norm(P_b), atol=1e-6)
    # w > 0 on the points whatever sign the least squares produced (det cannot tell H from -H)
    w = np.c_[X_b, np.ones(len(X_b))] @ result.H[3]
    assert (w > 0).all()
    # and the aligner uses it for such a frame when asked to
    view_a = FrameView(X_a.reshape(60, 50, 3).astype(np.float32), np.ones((60, 50), bool), *decompose_pose(P_a))
    view_b = FrameView(X_b.reshape(60, 50, 3).astype(np.float32), np.ones((60, 50), bool), K, T_cam_b)
    config = submap_graph_config()
    config.alignment.planar_model = "camera-constrained"
    aligned = make_aligner(resolve(config)).align(view_a, view_b, seed=0)
    assert aligned.model == "sl4" and "camera-constrained" in aligned.fallback
    np.testing.assert_allclose(apply_transform(aligned.H, X_b), X_a, atol=1e-4)
    # the hybrid link never takes that fit: a degenerate frame gets the frame's camera link, as its own choice
    config.alignment.model = "hybrid"
    linked = make_aligner(resolve(config)).align(view_a, view_b, seed=0)
    assert is_camera_link(linked) and linked.fallback is None and "flat" in linked.extras["degenerate"]
    camera_link = make_aligner(resolve(config)).camera_edge(view_a, view_b)
    np.testing.assert_allclose(linked.H, camera_link.H, atol=1e-12)


def test_calibration_scale_link_measures_a_flat_frame_without_its_points() -> None:
    """The default for a degenerate frame: the two cameras and the depth ratio. Exact when the two
    reconstructions differ by a calibration and a scale; a depth warp of the plane cannot bend it."""
    rng = np.random.default_rng(11)
    K_a = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    K_b = np.array([[290.0, 0, 160], [0, 290, 120], [0, 0, 1]])  # the frontend's focal differs by 3 %
    T_cam_a = se3_inverse(np.block([[random_rotation(rng, 0.3), np.array([[0.2], [0.1], [-0.3]])], [np.zeros((1, 3)), 1]]))
    T_cam_b = np.eye(4)
    v, u = np.mgrid[0:60, 0:80] * 4.0
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
    depth_b = 2.0 + 0.3 * pixels[:, 1] / 240  # a floor seen at an angle
    scale = 1.7
    X_b = (np.linalg.inv(K_b) @ pixels.T).T * depth_b[:, None]
    X_a_cam = (np.linalg.inv(K_a) @ pixels.T).T * (scale * depth_b)[:, None]
    X_a = apply_transform(se3_inverse(T_cam_a), X_a_cam)
    warped = X_a_cam * (1 + 0.03 * np.sin(pixels[:, :1] / 40.0))  # a smooth depth warp in submap a
    view_a = FrameView(apply_transform(se3_inverse(T_cam_a), warped).reshape(60, 80, 3).astype(np.float32),
                       np.ones((60, 80), bool), K_a, T_cam_a)
    view_b = FrameView(X_b.reshape(60, 80, 3).astype(np.float32), np.ones((60, 80), bool), K_b, T_cam_b)
    aligned = make_aligner(resolve(submap_graph_config())).align(view_a, view_b, seed=0)
    assert "calibration-and-scale" in aligned.fallback and aligned.extras["scale"] == pytest.approx(scale, rel=0.02)
    np.testing.assert_allclose(apply_transform(aligned.H, X_b), X_a, atol=0.02 * 2.5 * scale)
    exact = make_aligner(resolve(submap_graph_config())).camera_edge(
        dataclasses.replace(view_a, points=X_a.reshape(60, 80, 3).astype(np.float32)), view_b)
    np.testing.assert_allclose(apply_transform(exact.H, X_b), X_a, atol=1e-5)


def test_camera_links_are_weighted_by_their_cameras_fitted_edges_by_their_points() -> None:
    """A camera link's error is its frame's camera error, which its points cannot show: the model
    places the frame's depth with the same wrong camera, so the link maps the points exactly
    whatever the error. Evidence weighting then claims a precision the link does not have (the
    true error scores a huge chi-square); "auto" gives it the single sigma, under which it scores
    as the error it is. A fitted edge keeps its evidence under "auto"."""
    rng = np.random.default_rng(12)
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    v, u = np.mgrid[0:60, 0:80] * 4.0
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
    depth = 2.0 + 0.5 * np.sin(pixels[:, 0] / 50.0) * np.cos(pixels[:, 1] / 40.0)
    X_cam = (np.linalg.inv(K) @ pixels.T).T * depth[:, None]
    T_cam_a = se3_inverse(np.block([[random_rotation(rng, 0.3), np.array([[0.2], [0.1], [-0.3]])], [np.zeros((1, 3)), 1]]))
    wrong = np.eye(4)  # the model's camera of the frame in submap a: turned 2 degrees about its centre
    wrong[:3, :3] = Rotation.from_rotvec(np.deg2rad(2.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    wrong_T_cam_a = wrong @ T_cam_a
    views = [FrameView(apply_transform(se3_inverse(T), X_cam).reshape(60, 80, 3).astype(np.float32),
                       np.ones((60, 80), bool), K, T) for T in (wrong_T_cam_a, np.eye(4))]
    link = make_aligner(resolve(SLAMConfig())).camera_edge(*views)
    true_link = make_aligner(resolve(SLAMConfig())).camera_edge(
        dataclasses.replace(views[0], points=apply_transform(se3_inverse(T_cam_a), X_cam).reshape(60, 80, 3).astype(np.float32),
                            T_cam_submap=T_cam_a), views[1])
    assert is_camera_link(link) and link.rms < 1e-5  # the points agree with the wrong camera exactly
    xi = tangent_coordinates(np.real(logm(normalize_sl4(true_link.H) @ np.linalg.inv(normalize_sl4(link.H)))), GENERATORS)
    evidence = edge_information(link, GENERATORS, BackendConfig(weighting="evidence"))
    auto = edge_information(link, GENERATORS, BackendConfig())
    assert xi @ evidence @ xi / 15 > 100  # overconfident: the error sits far outside what it claims
    assert xi @ auto @ xi / 15 < 3
    np.testing.assert_allclose(auto, np.eye(15) / BackendConfig().sigma**2)
    H = near_identity_sl4(rng)
    fitted = alignment_from(H, rng.uniform([-1, -1, 1], [1, 1, 3], size=(300, 3)), rms=0.003)
    np.testing.assert_allclose(edge_information(fitted, GENERATORS, BackendConfig()),
                               edge_information(fitted, GENERATORS, BackendConfig(weighting="evidence")))


def decompose_pose(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K, T_world_cam, _ = decompose_projection(P)
    return K, se3_inverse(T_world_cam)


def test_keyframe_cameras_follow_a_known_node() -> None:
    rng = np.random.default_rng(6)
    H = near_identity_sl4(rng)
    K_true = np.array([[200.0, 0, 80], [0, 200, 60], [0, 0, 1]])
    T_world_cam = np.eye(4)
    T_world_cam[:3, :3], T_world_cam[:3, 3] = random_rotation(rng, 0.5), [0.3, -0.2, 0.1]
    # world camera P = P_submap H^-1, so the keyframe's camera in its (distorted) submap is P H
    P_submap = K_true @ se3_inverse(T_world_cam)[:3] @ H
    K_sub, T_submap_cam, _ = decompose_projection(P_submap)
    prediction = SubmapPrediction(depth=np.ones((1, 4, 4), np.float32), confidence=np.full((1, 4, 4), 2, np.float32),
                                  T_cam_submap=se3_inverse(T_submap_cam)[None, :3], K=K_sub[None],
                                  colors=np.zeros((1, 4, 4, 3), np.uint8))
    keyframe = StoredKeyframe.from_prediction(prediction, np.ones((1, 4, 4), bool), np.zeros(255, np.float32), 0, 7, 0.0, 3)
    T, K = keyframe_cameras([keyframe], {3: normalize_sl4(H)})
    np.testing.assert_allclose(T[0], T_world_cam, atol=1e-9)
    np.testing.assert_allclose(K[0], K_true, atol=1e-9)


def test_a_keyframe_is_kept_in_at_most_0_4_mb_at_518x294() -> None:
    height, width = 294, 518
    prediction = SubmapPrediction(depth=np.ones((1, height, width), np.float32), confidence=np.ones((1, height, width), np.float32),
                                  T_cam_submap=np.eye(4)[None, :3], K=np.eye(3)[None], colors=np.zeros((1, height, width, 3), np.uint8))
    keyframe = StoredKeyframe.from_prediction(prediction, np.ones((1, height, width), bool), np.zeros(255, np.float32), 0, 0, 0.0, 0)
    assert keyframe.nbytes <= 0.4e6


def test_float16_stored_depth_is_harmless_for_loop_alignment() -> None:
    """Loop alignment reads the old keyframe's float16 depth (relative rounding up to 2.4e-4: 0.008
    units at depth 32, near the 0.01 inlier threshold). With the depth noise any model has (here
    0.2 % per pixel) the rounding changes neither the inliers nor the estimate measurably, even
    with a far background up to depth 32."""
    rng = np.random.default_rng(7)
    H = near_identity_sl4(rng)
    height, width = 120, 160
    v, u = np.mgrid[0:height, 0:width]
    depth = np.where(v < 40, rng.uniform(16, 32), 1.0 + 2.0 * v / height + 0.3 * np.sin(u / 9.0))  # far wall on top
    K = np.array([[130.0, 0, width / 2], [0, 130, height / 2], [0, 0, 1]])
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)
    noisy = depth * np.exp(0.002 * rng.standard_normal(depth.shape))  # the old keyframe's own depth
    X_a_full = (rays * noisy[..., None]).reshape(-1, 3)
    X_a_half = (rays * noisy.astype(np.float16).astype(np.float64)[..., None]).reshape(-1, 3)  # as StoredKeyframe keeps it
    X_b = apply_transform(np.linalg.inv(H), (rays * depth[..., None]).reshape(-1, 3))  # the loop frame in the new submap
    config = AlignmentConfig()
    full = estimate_sl4(X_a_full, X_b, config, seed=0)
    half = estimate_sl4(X_a_half, X_b, config, seed=0)
    assert full.model == half.model == "sl4"
    # only points on the threshold's edge change sides (0.2 % noise puts many there at depth 2-3)
    assert abs(full.inlier_ratio - half.inlier_ratio) < 0.01
    near = depth.reshape(-1) < 4
    error_full = np.linalg.norm(apply_transform(full.H, X_b[near]) - apply_transform(H, X_b[near]), axis=1)
    error_half = np.linalg.norm(apply_transform(half.H, X_b[near]) - apply_transform(H, X_b[near]), axis=1)
    assert np.median(error_half) < 1.1 * np.median(error_full) + 1e-5
