"""Simulated frontend: exact truth without corruption, H_s applied to the truth with a distortion,
seeded noise, blob outliers with low confidence, and clear errors on unusable input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from sl4slam.config import SimulatorConfig, config_from_dict
from sl4slam.errors import UserError
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.geometry import apply_transform, se3_inverse, to_4x4, umeyama_sim3, unproject_depth
from sl4slam.submap import confidence_mask
from sl4slam.types import Frame, Frontend

HEIGHT, WIDTH = 96, 128
# Planes n . X = c of a closed room around the cameras (world frame, y down, z forward).
ROOM_PLANES = [
    (np.array([0.0, 0.0, 1.0]), 4.0),  # back wall
    (np.array([0.0, 0.0, 1.0]), -3.0),  # wall behind
    (np.array([1.0, 0.0, 0.0]), -2.0),  # left wall
    (np.array([1.0, 0.0, 0.0]), 2.5),  # right wall
    (np.array([0.0, 1.0, 0.0]), 1.2),  # floor
    (np.array([0.0, 1.0, 0.0]), -1.5),  # ceiling
]

ZERO_CORRUPTION = SimulatorConfig(
    perspective=0.0, shear=0.0, scale=0.0, depth_noise=0.0, outlier_fraction=0.0, normalize_scale=False
)


def render_room_depth(K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """Exact ``(H, W)`` depth (camera z) of the room seen by one camera: nearest plane hit."""
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1, so t = depth
    rays_world = rays_cam @ T_world_cam[:3, :3].T
    centre = T_world_cam[:3, 3]
    depth = np.full((HEIGHT, WIDTH), np.inf)
    for normal, offset in ROOM_PLANES:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (offset - normal @ centre) / (rays_world @ normal)
        depth = np.where((t > 1e-6) & (t < depth), t, depth)
    assert np.isfinite(depth).all()
    return depth.astype(np.float32)


def make_frames(count: int = 4, holes: bool = False) -> list[Frame]:
    """Frames in the room with known poses and (per-frame different) intrinsics."""
    rng = np.random.default_rng(7)
    frames = []
    for i in range(count):
        K = np.array([[110.0 + 5 * i, 0.0, 63.5 + i], [0.0, 108.0 + 3 * i, 47.5 - i], [0.0, 0.0, 1.0]])
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.12, 3)).as_matrix()
        T[:3, 3] = [0.3 * i, -0.1 * i, 0.2 * i - 0.5]
        depth = render_room_depth(K, T)
        if holes:
            depth[10:20, 30:45] = 0.0
            depth[-5:, :] = 0.0
        rgb = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
        frames.append(Frame(index=10 + 3 * i, timestamp=float(i), rgb=rgb, depth=depth, T_world_cam=T, K=K))
    return frames


def true_points(frames: list[Frame]) -> tuple[np.ndarray, np.ndarray]:
    """Truth in the first camera: points ``(S, H, W, 3)`` float64 and ``T_cam_i_cam_0`` ``(S, 4, 4)``."""
    T_world_cam = np.stack([f.T_world_cam for f in frames])
    T_cam_ref = se3_inverse(T_world_cam) @ T_world_cam[0]
    depth = np.stack([f.depth for f in frames]).astype(np.float64)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    pixels = np.stack([u, v, np.ones_like(u)], -1)
    points = []
    for i, frame in enumerate(frames):
        X_cam = (pixels @ np.linalg.inv(frame.K).T) * depth[i][..., None]
        T_ref_cam = se3_inverse(T_cam_ref[i])
        points.append(X_cam @ T_ref_cam[:3, :3].T + T_ref_cam[:3, 3])
    return np.stack(points), T_cam_ref


def relative_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(estimate - truth, axis=-1) / np.linalg.norm(truth, axis=-1)


def test_is_a_frontend():
    frontend = SimulatedFrontend(SimulatorConfig())
    assert isinstance(frontend, Frontend)
    assert frontend.name == "simulated"


def test_zero_corruption_returns_exact_truth():
    frames = make_frames()
    frontend = SimulatedFrontend(ZERO_CORRUPTION)
    prediction = frontend.reconstruct(frames, submap_id=0)
    X_true, T_cam_ref = true_points(frames)

    assert prediction.depth.shape == (4, HEIGHT, WIDTH) and prediction.depth.dtype == np.float32
    assert prediction.confidence.shape == (4, HEIGHT, WIDTH) and prediction.confidence.dtype == np.float32
    assert prediction.T_cam_submap.shape == (4, 3, 4) and prediction.K.shape == (4, 3, 3)
    np.testing.assert_allclose(prediction.depth, np.stack([f.depth for f in frames]), rtol=1e-6)
    np.testing.assert_allclose(prediction.K, np.stack([f.K for f in frames]), atol=1e-9)
    np.testing.assert_allclose(prediction.T_cam_submap, T_cam_ref[:, :3, :], atol=1e-9)
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap)
    assert relative_error(points, X_true).max() < 1e-5
    np.testing.assert_allclose(frontend.last_distortion, np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(prediction.colors, np.stack([f.rgb for f in frames]))
    assert prediction.points is None


def test_scale_normalization_gives_unit_mean_distance():
    frames = make_frames()
    config = dataclasses.replace(ZERO_CORRUPTION, normalize_scale=True)
    frontend = SimulatedFrontend(config)
    prediction = frontend.reconstruct(frames, submap_id=2)
    X_true, T_cam_ref = true_points(frames)
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap).astype(np.float64)

    assert abs(np.linalg.norm(points, axis=-1).mean() - 1.0) < 1e-5
    kappa = 1.0 / np.linalg.norm(X_true, axis=-1).mean()
    assert relative_error(points, kappa * X_true).max() < 1e-5
    H = frontend.last_distortion
    np.testing.assert_allclose(apply_transform(H, np.eye(3)), kappa * np.eye(3), rtol=1e-7)
    np.testing.assert_allclose(prediction.T_cam_submap[:, :, 3], kappa * T_cam_ref[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(prediction.K, np.stack([f.K for f in frames]), atol=1e-9)


@pytest.mark.parametrize("normalize", [False, True])
def test_distortion_maps_truth_through_H(normalize):
    frames = make_frames()
    config = SimulatorConfig(
        perspective=0.15, shear=0.1, scale=0.3, depth_noise=0.0, outlier_fraction=0.0, normalize_scale=normalize, seed=3
    )
    frontend = SimulatedFrontend(config)
    prediction = frontend.reconstruct(frames, submap_id=5)
    H = frontend.last_distortion
    X_true, _ = true_points(frames)

    assert abs(np.linalg.det(H) - 1.0) < 1e-9
    assert np.linalg.norm(H[3, :3]) > 1e-3  # a real perspective row ...
    similarity = umeyama_sim3(X_true.reshape(-1, 3), apply_transform(H, X_true).reshape(-1, 3))
    sim3_residual = relative_error(apply_transform(similarity, X_true), apply_transform(H, X_true)).mean()
    assert sim3_residual > 1e-3  # ... that no similarity explains

    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap)
    assert relative_error(points, apply_transform(H, X_true)).max() < 1e-5
    np.testing.assert_allclose(prediction.T_cam_submap[0], np.eye(4)[:3], atol=1e-12)
    assert (prediction.depth > 0).all()
    # Intrinsics stay upper triangular with positive diagonal; the shear shows up as skew.
    assert np.allclose(np.tril(prediction.K, -1), 0.0) and (np.diagonal(prediction.K, axis1=1, axis2=2) > 0).all()
    assert abs(prediction.K[0, 0, 1]) > 1e-3
    np.testing.assert_allclose(frontend.distortion(frames, 5), H, atol=1e-12)
    assert frontend.distortions[5] is H


def test_each_magnitude_controls_its_own_part_of_H():
    frames = make_frames(2)
    base = dict(depth_noise=0.0, outlier_fraction=0.0, normalize_scale=False, seed=1)

    H = SimulatedFrontend(SimulatorConfig(perspective=0.2, **base)).distortion(frames, 0)
    X_true, _ = true_points(frames)
    mean_distance = np.linalg.norm(X_true, axis=-1).mean()
    block = H[:3, :3] / H[3, 3]
    np.testing.assert_allclose(block, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(H[3, :3] / H[3, 3]) * mean_distance, 0.2, rtol=1e-6)

    H = SimulatedFrontend(SimulatorConfig(shear=0.2, **base)).distortion(frames, 0)
    assert np.allclose(H[3, :3], 0.0) and np.allclose(H[:3, 3], 0.0)
    block = H[:3, :3] / H[3, 3]
    assert np.allclose(np.tril(block, -1), 0.0) and abs(np.linalg.det(block) - 1.0) < 1e-9
    assert np.abs(block - np.eye(3)).max() > 0.02

    H = SimulatedFrontend(SimulatorConfig(scale=0.3, **base)).distortion(frames, 0)
    block = H[:3, :3] / H[3, 3]
    np.testing.assert_allclose(block, block[0, 0] * np.eye(3), atol=1e-12)
    assert abs(np.log(block[0, 0])) > 1e-3 and np.allclose(H[3, :3], 0.0)


def test_noise_is_repeatable_and_independent_across_submaps():
    frames = make_frames()
    config = SimulatorConfig(depth_noise=0.01, outlier_fraction=0.05, normalize_scale=False, seed=11)
    truth = np.stack([f.depth for f in frames])

    first = SimulatedFrontend(config).reconstruct(frames, submap_id=4)
    again = SimulatedFrontend(config).reconstruct(frames, submap_id=4)
    np.testing.assert_array_equal(first.depth, again.depth)
    np.testing.assert_array_equal(first.confidence, again.confidence)

    # The same frame in another submap: independent noise (uncorrelated relative errors).
    other = SimulatedFrontend(config).reconstruct(frames, submap_id=9)
    error_first = np.log(first.depth / truth).ravel()
    error_other = np.log(other.depth / truth).ravel()
    assert abs(np.corrcoef(error_first, error_other)[0, 1]) < 0.1
    assert not np.array_equal(first.confidence, other.confidence)

    # Noise depends on (seed, submap, frame index) only, not on the other frames of the submap.
    subset = SimulatedFrontend(config).reconstruct(frames[2:], submap_id=4)
    np.testing.assert_allclose(subset.depth[1] / truth[3], first.depth[3] / truth[3], rtol=1e-6)

    # A different seed gives different noise.
    reseeded = SimulatedFrontend(dataclasses.replace(config, seed=12)).reconstruct(frames, submap_id=4)
    assert not np.allclose(reseeded.depth, first.depth)

    # The relative noise has the configured spread outside the outlier blobs.
    clean = np.abs(error_first) < 0.05
    assert abs(error_first[clean].std() / 0.01 - 1.0) < 0.05


def test_distortion_is_repeatable_per_submap():
    frames = make_frames(2)
    config = SimulatorConfig(perspective=0.1, shear=0.1, scale=0.2, seed=5)
    H_a = SimulatedFrontend(config).distortion(frames, 3)
    H_b = SimulatedFrontend(config).distortion(frames, 3)
    H_c = SimulatedFrontend(config).distortion(frames, 4)
    np.testing.assert_array_equal(H_a, H_b)
    assert np.abs(H_a - H_c).max() > 1e-3


def test_outliers_form_blobs_with_low_confidence():
    frames = make_frames(3)
    config = SimulatorConfig(
        depth_noise=0.002, outlier_fraction=0.1, outlier_blob_px=6.0, outlier_magnitude=0.3, normalize_scale=False
    )
    prediction = SimulatedFrontend(config).reconstruct(frames, submap_id=1)
    truth = np.stack([f.depth for f in frames])
    outliers = np.abs(np.log(prediction.depth / truth)) > 0.05

    assert (prediction.confidence >= 1.0).all()
    assert 0.06 < outliers.mean() < 0.1  # fraction in blobs; |error| is near 0.3 on most of them
    for i in range(3):  # spatially coherent: few, large components rather than salt-and-pepper
        labels, count = ndimage.label(outliers[i])
        assert outliers[i].sum() / count > 20
    assert prediction.confidence[outliers].mean() < 0.2 * prediction.confidence[~outliers].mean()
    kept = confidence_mask(prediction.confidence, prediction.depth, 25.0)
    assert (kept & outliers).sum() < 0.02 * outliers.sum()

    # Confidence falls with depth on clean pixels.
    clean = ~outliers
    near = truth[clean] < np.percentile(truth[clean], 25)
    far = truth[clean] > np.percentile(truth[clean], 75)
    assert prediction.confidence[clean][near].mean() > 1.5 * prediction.confidence[clean][far].mean()


def test_holes_are_filled_with_minimal_confidence():
    frames = make_frames(2, holes=True)
    prediction = SimulatedFrontend(dataclasses.replace(ZERO_CORRUPTION, seed=2)).reconstruct(frames, 0)
    holes = np.stack([f.depth for f in frames]) == 0
    assert holes.any()
    assert (prediction.depth > 0).all() and np.isfinite(prediction.depth).all()
    np.testing.assert_array_equal(prediction.confidence[holes], 1.0)
    assert (prediction.confidence[~holes] > 1.0).all()
    X_true, _ = true_points(frames)
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap)
    assert relative_error(points[~holes], X_true[~holes]).max() < 1e-5
    # A filled pixel takes its nearest measured neighbour's depth (here the row above the band).
    np.testing.assert_allclose(prediction.depth[0, -1, :], frames[0].depth[-6, :], rtol=1e-6)


def test_bad_input_raises_user_error():
    frames = make_frames(2)
    frontend = SimulatedFrontend(SimulatorConfig())
    for missing in ("depth", "T_world_cam", "K"):
        broken = [frames[0], dataclasses.replace(frames[1], **{missing: None})]
        with pytest.raises(UserError, match="RGB-D sequence with ground-truth"):
            frontend.reconstruct(broken, 0)
    with pytest.raises(UserError, match="no frames"):
        frontend.reconstruct([], 0)
    small = dataclasses.replace(
        frames[1], rgb=frames[1].rgb[:50], depth=frames[1].depth[:50]
    )
    with pytest.raises(UserError, match="same size"):
        frontend.reconstruct([frames[0], small], 0)
    empty = dataclasses.replace(frames[1], depth=np.zeros_like(frames[1].depth))
    with pytest.raises(UserError, match="no valid depth"):
        frontend.reconstruct([frames[0], empty], 0)
    with pytest.raises(UserError, match="--sim-perspective"):
        SimulatedFrontend(SimulatorConfig(perspective=3.0, seed=2)).reconstruct(make_frames(4), 0)
    for setting in ({"outlier_fraction": 1.5}, {"depth_noise": -0.1}, {"seed": -1}, {"outlier_blob_px": 0.0}):
        with pytest.raises(UserError, match="--sim-"):
            SimulatedFrontend(SimulatorConfig(**setting))


def test_settings_come_from_a_config_file_tree():
    config = config_from_dict({"frontend": "simulated", "sim": {"perspective": 0.05, "depth_noise": 0, "seed": 4}})
    assert config.sim.perspective == 0.05 and config.sim.depth_noise == 0.0 and config.sim.seed == 4
    defaults = SimulatorConfig().resolved()
    assert defaults.perspective == 0.0 and defaults.shear == 0.0 and defaults.scale == 0.0
    assert 0 < defaults.depth_noise < 0.05 and 0 < defaults.outlier_fraction < 0.1


def _tum_frames(shared_dir, positions):
    io = pytest.importorskip("sl4slam.io")
    source = io.open_source(shared_dir / "data" / "tum_rgbd_fr1_xyz_first37")
    frames = [source.get(i) for i in positions]
    assert all(f.depth is not None and f.T_world_cam is not None and f.K is not None for f in frames)
    return frames


def _tum_truth(frames):
    T_world_cam = np.stack([f.T_world_cam for f in frames])
    T_cam_ref = se3_inverse(T_world_cam) @ T_world_cam[0]
    depth = np.stack([f.depth for f in frames])
    points = unproject_depth(depth, np.stack([f.K for f in frames]), T_cam_ref).astype(np.float64)
    return depth, points, T_cam_ref


def test_tum_zero_corruption_and_distortion(shared_dir):
    frames = _tum_frames(shared_dir, [0, 18, 36])
    depth, X_true, T_cam_ref = _tum_truth(frames)
    measured = depth > 0
    assert 0 < (~measured).mean() < 0.5  # real Kinect depth has holes

    prediction = SimulatedFrontend(ZERO_CORRUPTION).reconstruct(frames, 0)
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap)
    assert relative_error(points[measured], X_true[measured]).max() < 1e-5
    np.testing.assert_allclose(prediction.T_cam_submap, T_cam_ref[:, :3, :], atol=1e-9)
    assert (prediction.depth > 0).all() and (prediction.confidence[~measured] == 1.0).all()

    config = SimulatorConfig(perspective=0.1, shear=0.05, scale=0.2, depth_noise=0.0, outlier_fraction=0.0)
    frontend = SimulatedFrontend(config)
    prediction = frontend.reconstruct(frames, 7)
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap)
    expected = apply_transform(frontend.last_distortion, X_true[measured])
    assert relative_error(points[measured], expected).max() < 1e-5
    np.testing.assert_allclose(prediction.T_cam_submap[0], np.eye(4)[:3], atol=1e-12)


def test_tum_default_noise_is_mild(shared_dir):
    frames = _tum_frames(shared_dir, [0, 10, 20])
    depth, _, _ = _tum_truth(frames)
    measured = depth > 0
    config = dataclasses.replace(SimulatorConfig(), normalize_scale=False)
    prediction = SimulatedFrontend(config).reconstruct(frames, 1)
    log_error = np.abs(np.log(prediction.depth[measured] / depth[measured]))
    assert np.median(log_error) < 0.003  # depth_noise 0.002
    assert 0.01 < (log_error > 0.05).mean() < 0.03  # 2 % of pixels in blobs
    assert (prediction.confidence >= 1.0).all()


# ---------------------------------------------------------------- VGGT-like error terms, each on its own


def _rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(R).magnitude())


def _one_term(frames: list[Frame], submap_id: int, **term):
    """Prediction with only ``term`` switched on (metric units, no other corruption)."""
    return SimulatedFrontend(dataclasses.replace(ZERO_CORRUPTION, **term)).reconstruct(frames, submap_id)


def test_camera_error_moves_cameras_but_keeps_each_frames_own_depth():
    frames = make_frames(4)
    prediction = _one_term(frames, 3, camera_rotation_deg=2.0, camera_translation=0.02, seed=4)
    X_true, T_cam_ref = true_points(frames)
    T_pred = to_4x4(prediction.T_cam_submap)

    np.testing.assert_allclose(prediction.T_cam_submap[0], np.eye(4)[:3], atol=1e-12)  # [I | 0] as VGGT's
    np.testing.assert_allclose(prediction.depth, np.stack([f.depth for f in frames]), rtol=1e-6)
    np.testing.assert_allclose(prediction.K, np.stack([f.K for f in frames]), atol=1e-9)
    rotation_error = _rotation_angles_deg(T_pred[1:, :3, :3] @ np.swapaxes(T_cam_ref[1:, :3, :3], 1, 2))
    assert (rotation_error > 0.2).all() and (rotation_error < 12).all()
    mean_distance = np.linalg.norm(X_true, axis=-1).mean()
    centre_error = np.linalg.norm(se3_inverse(T_pred)[1:, :3, 3] - se3_inverse(T_cam_ref)[1:, :3, 3], axis=-1)
    assert (centre_error > 0.001 * mean_distance).all() and (centre_error < 0.15 * mean_distance).all()

    # In its own (wrong) camera each frame's points are exactly right; in the submap they are misplaced.
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap).astype(np.float64)
    in_camera = np.einsum("sij,shwj->shwi", T_pred[:, :3, :3], points) + T_pred[:, None, None, :3, 3]
    true_in_camera = np.einsum("sij,shwj->shwi", T_cam_ref[:, :3, :3], X_true) + T_cam_ref[:, None, None, :3, 3]
    assert relative_error(in_camera, true_in_camera).max() < 1e-5
    assert relative_error(points[0], X_true[0]).max() < 1e-5
    assert (np.median(relative_error(points[1:], X_true[1:]), axis=(1, 2)) > 0.005).all()


def test_camera_error_has_the_configured_spread_and_grows_past_the_window_length():
    frames = make_frames(4)
    config = dataclasses.replace(ZERO_CORRUPTION, camera_rotation_deg=1.5, camera_translation=0.01, seed=9)
    _, T_cam_ref = true_points(frames)
    rotation_vectors, centre_shifts = [], []
    for submap_id in range(20):
        T_pred = to_4x4(SimulatedFrontend(config).reconstruct(frames, submap_id).T_cam_submap)
        R_error = np.swapaxes(T_cam_ref[1:, :3, :3], 1, 2) @ T_pred[1:, :3, :3]  # R_ref_cam_true^T R_ref_cam_pred
        rotation_vectors.append(Rotation.from_matrix(R_error).as_rotvec())
        centre_shifts.append(se3_inverse(T_pred)[1:, :3, 3] - se3_inverse(T_cam_ref)[1:, :3, 3])
    X_true, _ = true_points(frames)
    mean_distance = np.linalg.norm(X_true, axis=-1).mean()
    assert abs(np.degrees(np.std(rotation_vectors)) / 1.5 - 1) < 0.2  # 180 draws
    assert abs(np.std(centre_shifts) / (0.01 * mean_distance) - 1) < 0.2

    # Four frames in windows of at most 2 "good" frames: every error twice as large, same draws.
    short = dataclasses.replace(config, camera_window_frames=2)
    base = to_4x4(SimulatedFrontend(config).reconstruct(frames, 0).T_cam_submap)
    grown = to_4x4(SimulatedFrontend(short).reconstruct(frames, 0).T_cam_submap)
    error_base = Rotation.from_matrix(np.swapaxes(T_cam_ref[1:, :3, :3], 1, 2) @ base[1:, :3, :3]).as_rotvec()
    error_grown = Rotation.from_matrix(np.swapaxes(T_cam_ref[1:, :3, :3], 1, 2) @ grown[1:, :3, :3]).as_rotvec()
    np.testing.assert_allclose(error_grown, 2.0 * error_base, rtol=1e-9)


def test_focal_error_scales_the_focal_lengths_about_the_principal_point():
    frames = make_frames(4)
    prediction = _one_term(frames, 1, focal_error=0.05, seed=2)
    K_true = np.stack([f.K for f in frames])
    X_true, T_cam_ref = true_points(frames)

    factor = prediction.K[:, 0, 0] / K_true[:, 0, 0]
    np.testing.assert_allclose(prediction.K[:, 1, 1] / K_true[:, 1, 1], factor, rtol=1e-12)
    np.testing.assert_allclose(prediction.K[:, :2, 2], K_true[:, :2, 2], atol=1e-9)  # principal point kept
    np.testing.assert_allclose(prediction.principal_point, K_true[:, :2, 2], atol=0)
    assert (np.abs(np.log(factor)) > 1e-4).all() and (np.abs(np.log(factor)) < 0.25).all()
    assert len(np.unique(np.round(factor, 9))) == 4  # one draw per frame, the first frame included
    np.testing.assert_allclose(prediction.depth, np.stack([f.depth for f in frames]), rtol=1e-6)
    np.testing.assert_allclose(prediction.T_cam_submap, T_cam_ref[:, :3, :], atol=1e-9)

    # Depth stays, so the points' lateral offsets from the principal ray shrink by the focal factor.
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap).astype(np.float64)
    true_cam = np.einsum("sij,shwj->shwi", T_cam_ref[:, :3, :3], X_true) + T_cam_ref[:, None, None, :3, 3]
    pred_cam = np.einsum("sij,shwj->shwi", T_cam_ref[:, :3, :3], points) + T_cam_ref[:, None, None, :3, 3]
    np.testing.assert_allclose(pred_cam[..., 2], true_cam[..., 2], rtol=1e-5)
    np.testing.assert_allclose(pred_cam[..., :2], true_cam[..., :2] / factor[:, None, None, None], rtol=1e-4, atol=1e-6)


def test_frame_consistency_shares_a_frames_focal_error_and_warp_across_submaps():
    frames = make_frames(3)
    for share, same in ((1.0, True), (0.0, False)):
        config = dataclasses.replace(ZERO_CORRUPTION, focal_error=0.05, depth_warp=0.05, frame_consistency=share)
        a = SimulatedFrontend(config).reconstruct(frames, 1)
        b = SimulatedFrontend(config).reconstruct(frames, 2)
        assert np.allclose(a.K, b.K, rtol=1e-12) == same
        assert np.allclose(a.depth, b.depth, rtol=1e-6) == same
    # A share in between: the submaps' warps of one frame are correlated, not equal.
    config = dataclasses.replace(ZERO_CORRUPTION, depth_warp=0.05, frame_consistency=0.8)
    truth = np.stack([f.depth for f in frames])
    warp_a = np.log(SimulatedFrontend(config).reconstruct(frames, 1).depth / truth)
    warp_b = np.log(SimulatedFrontend(config).reconstruct(frames, 2).depth / truth)
    correlation = np.corrcoef(warp_a.ravel(), warp_b.ravel())[0, 1]
    assert 0.5 < correlation < 0.99


def test_depth_warp_is_smooth_and_not_projective():
    frames = make_frames(3)
    prediction = _one_term(frames, 0, depth_warp=0.05, seed=6)
    truth = np.stack([f.depth for f in frames])
    X_true, T_cam_ref = true_points(frames)
    np.testing.assert_allclose(prediction.T_cam_submap, T_cam_ref[:, :3, :], atol=1e-9)
    np.testing.assert_allclose(prediction.K, np.stack([f.K for f in frames]), atol=1e-9)

    log_ratio = np.log(prediction.depth.astype(np.float64) / truth)
    np.testing.assert_allclose(log_ratio.std(axis=(1, 2)), 0.05, rtol=1e-3)  # a unit field times depth_warp
    assert np.abs(log_ratio.mean(axis=(1, 2))).max() < 1e-3
    step = np.diff(log_ratio, axis=2).std()  # neighbouring pixels: almost the same factor
    assert step < 0.05 * 0.05
    # A projective map fixing the camera scales depth by 1 / (a . X_cam + b); the warp is not that.
    for i in range(3):
        X_cam = np.einsum("ij,hwj->hwi", T_cam_ref[i, :3, :3], X_true[i]) + T_cam_ref[i, :3, 3]
        design = np.concatenate([X_cam.reshape(-1, 3), np.ones((X_cam[..., 0].size, 1))], axis=1)
        inverse_ratio = np.exp(-log_ratio[i]).ravel()
        coefficients = np.linalg.lstsq(design, inverse_ratio, rcond=None)[0]
        assert (inverse_ratio - design @ coefficients).std() > 0.01


def _step_frame(width: int = 64, height: int = 48) -> Frame:
    """A frontal wall at 4 m with a square at 2 m in front of it: sharp depth edges."""
    K = np.array([[60.0, 0.0, (width - 1) / 2], [0.0, 60.0, (height - 1) / 2], [0.0, 0.0, 1.0]])
    depth = np.full((height, width), 4.0, np.float32)
    depth[14:34, 20:44] = 2.0
    rgb = np.zeros((height, width, 3), np.uint8)
    return Frame(index=0, timestamp=0.0, rgb=rgb, depth=depth, T_world_cam=np.eye(4), K=K)


def test_flying_pixels_sit_between_foreground_and_background_on_edges_with_low_confidence():
    frame = _step_frame()
    config = dataclasses.replace(ZERO_CORRUPTION, flying_px=2.0, seed=3)
    prediction = SimulatedFrontend(config).reconstruct([frame], 0)
    truth = frame.depth

    # Expected band: pixels within 2 px of a pixel whose 4-neighbour lies on the other side of the step.
    square = truth < 3.0
    edge = square ^ ndimage.binary_erosion(square, border_value=1)
    edge |= ~square & ndimage.binary_dilation(square, structure=ndimage.generate_binary_structure(2, 1))
    dy, dx = np.mgrid[-2:3, -2:3]
    band = ndimage.binary_dilation(edge, structure=dx**2 + dy**2 <= 4)
    changed = np.abs(prediction.depth[0] - truth) > 1e-6
    np.testing.assert_array_equal(changed, band)
    flying = prediction.depth[0][band]
    assert flying.min() >= 2.0 - 1e-6 and flying.max() <= 4.0 + 1e-6
    assert flying.std() > 0.3  # strung out between the two surfaces, not stuck on one
    clean_excess = (prediction.confidence[0][~band] - 1).mean()
    assert (prediction.confidence[0][band] - 1).mean() < 0.05 * clean_excess

    # Smooth surfaces (the room's walls, even at grazing angles and in corners) have none.
    room = make_frames(3)
    smooth = SimulatedFrontend(config).reconstruct(room, 0)
    np.testing.assert_allclose(smooth.depth, np.stack([f.depth for f in room]), rtol=1e-6)


def test_scale_gauge_scales_whole_submaps_within_the_ratio():
    frames = make_frames(2)
    config = dataclasses.replace(ZERO_CORRUPTION, gauge_scale_ratio=2.0, seed=8)
    frontend = SimulatedFrontend(config)
    X_true, T_cam_ref = true_points(frames)
    scales = []
    for submap_id in range(30):
        H = frontend.distortion(frames, submap_id)
        block = H[:3, :3] / H[3, 3]
        np.testing.assert_allclose(block, block[0, 0] * np.eye(3), atol=1e-12)
        assert np.allclose(H[3, :3], 0) and np.allclose(H[:3, 3], 0)
        scales.append(block[0, 0])
    scales = np.array(scales)
    assert scales.max() / scales.min() <= 2.0 and scales.max() / scales.min() > 1.6

    prediction = frontend.reconstruct(frames, 7)
    s = scales[7]
    points = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap)
    assert relative_error(points, s * X_true).max() < 1e-5
    np.testing.assert_allclose(prediction.T_cam_submap[0], np.eye(4)[:3], atol=1e-12)
    np.testing.assert_allclose(prediction.T_cam_submap[:, :, :3], T_cam_ref[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(prediction.T_cam_submap[:, :, 3], s * T_cam_ref[:, :3, 3], atol=1e-9)
    # Submap 0 defines the world frame: left alone when distort_first_submap is off.
    first = SimulatedFrontend(dataclasses.replace(config, distort_first_submap=False)).distortion(frames, 0)
    np.testing.assert_allclose(first, np.eye(4), atol=1e-12)


def test_principal_point_is_recorded_and_replayed(tmp_path):
    from sl4slam.frontend.cache import CachingFrontend, ReplayFrontend

    frames = make_frames(2)
    recorded = CachingFrontend(SimulatedFrontend(ZERO_CORRUPTION), tmp_path).reconstruct(frames, 0)
    np.testing.assert_array_equal(recorded.principal_point, np.stack([f.K[:2, 2] for f in frames]))
    assert recorded.principal_point.dtype == np.float64
    replayed = ReplayFrontend(tmp_path).reconstruct(frames, 0)
    np.testing.assert_array_equal(replayed.principal_point, recorded.principal_point)


@pytest.mark.parametrize("setting, flag", [
    ({"camera_rotation_deg": -1.0}, "--sim-camera-rotation-deg"), ({"camera_translation": 2.0}, "--sim-camera-translation"),
    ({"focal_error": 0.9}, "--sim-focal-error"), ({"camera_window_frames": 0}, "--sim-camera-window-frames"),
    ({"depth_warp": -0.1}, "--sim-depth-warp"), ({"depth_warp_length": 0.0}, "--sim-depth-warp-length"),
    ({"flying_px": 0.5}, "--sim-flying-px"), ({"flying_jump": 0.0}, "--sim-flying-jump"),
    ({"gauge_scale_ratio": 0.5}, "--sim-gauge-scale-ratio"), ({"frame_consistency": 1.5}, "--sim-frame-consistency"),
    ({"depth_warp": float("nan")}, "--sim-depth-warp"), ({"profile": "vgg"}, "--sim-profile"),
])
def test_new_settings_out_of_range_are_one_line_errors_at_construction(setting, flag):
    with pytest.raises(UserError, match=flag) as error:
        SimulatedFrontend(SimulatorConfig(**setting))
    assert "\n" not in str(error.value)
