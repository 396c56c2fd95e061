"""Projective-to-metric upgrade: exact recovery from projectively distorted cameras, robustness to
cameras that break the model, detection of degenerate motions, composition of the helpers, and
one-line errors for bad settings and input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.cli import build_parser, config_from_args
from sl4slam.config import UpgradeConfig, config_from_dict
from sl4slam.errors import UserError
from sl4slam.geometry import apply_transform, decompose_projection, normalize_sl4, se3_inverse, umeyama_sim3
from sl4slam.synthetic.correspondences import near_identity_sl4
from sl4slam.synthetic.world import camera_path
from sl4slam.upgrade import (
    estimate_metric_upgrade,
    intrinsic_constraint_residuals,
    upgrade_graph_nodes,
)


def upgrade_cameras(P_world: np.ndarray, H_metric_world: np.ndarray) -> np.ndarray:
    """Cameras ``(..., 3, 4)`` in the metric frame: ``P H^-1``."""
    return np.asarray(P_world, dtype=np.float64) @ np.linalg.inv(np.asarray(H_metric_world, dtype=np.float64))


def upgrade_points(X_world: np.ndarray, H_metric_world: np.ndarray) -> np.ndarray:
    """Points in the metric frame: homogeneous ``(..., 4)`` -> ``H X``; Euclidean ``(..., 3)`` after division."""
    X, H = np.asarray(X_world, dtype=np.float64), np.asarray(H_metric_world, dtype=np.float64)
    return X @ H.T if X.shape[-1] == 4 else apply_transform(H, X)


WIDTH, HEIGHT = 640, 480
PP = np.array([(WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0])  # the synthetic world's convention
FOCAL = 500.0


def intrinsics(focals: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` ideal intrinsics: zero skew, square pixels, principal point ``PP``."""
    K = np.zeros((len(focals), 3, 3))
    K[:, 0, 0] = K[:, 1, 1] = focals
    K[:, :2, 2] = PP
    K[:, 2, 2] = 1.0
    return K


def cameras(T_world_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Metric cameras ``K [R | t]`` ``(N, 3, 4)`` from poses."""
    return K @ se3_inverse(T_world_cam)[:, :3]


def random_distortion(rng: np.random.Generator, centres: np.ndarray, strength: float = 0.3) -> np.ndarray:
    """A random projective map (det > 0) whose plane at infinity stays clear of the cameras."""
    while True:
        G = np.eye(4)
        G[:3, :3] += rng.normal(scale=strength, size=(3, 3))
        G[:3, 3] = rng.normal(scale=strength, size=3)
        G[3, :3] = rng.normal(scale=0.3 * strength, size=3)
        w = np.c_[centres, np.ones(len(centres))] @ G[3]
        if np.linalg.det(G) > 0 and np.all(w > 0.2):
            return normalize_sl4(G)


def scene_scale(P: np.ndarray) -> float:
    """A stand-in for the map's depth in a distorted world: the spread of the camera centres."""
    _, _, C = decompose_projection(P)
    return float(np.median(np.linalg.norm(C - np.median(C, axis=0), axis=1)))


def centre_error(P_metric: np.ndarray, T_true: np.ndarray, subset: np.ndarray | None = None) -> float:
    """Largest camera-centre error after a Umeyama Sim(3) alignment onto the truth, in units of
    the true trajectory's size."""
    subset = np.ones(len(T_true), dtype=bool) if subset is None else subset
    _, _, C = decompose_projection(P_metric[subset])
    C_true = T_true[subset, :3, 3]
    aligned = apply_transform(umeyama_sim3(C, C_true), C)
    size = np.linalg.norm(C_true - C_true.mean(0), axis=1).max()
    return float(np.linalg.norm(aligned - C_true, axis=1).max() / size)


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``T_world_cam`` of a camera at ``centre`` looking at ``target`` (world z up)."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    T[:3, 3] = centre
    return T


# --------------------------------------------------------------------------- exact recovery
@pytest.mark.parametrize("num_cameras, seed", [(50, 1), (200, 2), (500, 3)])
def test_shared_focal_recovered_exactly_from_a_distorted_loop(num_cameras, seed):
    rng = np.random.default_rng(seed)
    T_true = camera_path(num_cameras, seed)
    K_true = intrinsics(np.full(num_cameras, FOCAL))
    P = cameras(T_true, K_true) @ np.linalg.inv(random_distortion(rng, T_true[:, :3, 3]))

    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig(), scene_scale=scene_scale(P))

    assert upgrade.applied, upgrade.reason
    assert upgrade.inliers.all()
    assert upgrade.residual_before > 0.01  # the distortion is visible in the constraints ...
    assert upgrade.residual_after < 1e-9  # ... and gone after the upgrade
    K, _, _ = decompose_projection(upgrade_cameras(P, upgrade.H_metric_world))
    assert np.abs(K - K_true).max() < 1e-7 * FOCAL
    assert abs(upgrade.focal - FOCAL) < 1e-7 * FOCAL
    assert centre_error(upgrade_cameras(P, upgrade.H_metric_world), T_true) < 1e-9
    assert abs(np.linalg.det(upgrade.H_metric_world) - 1.0) < 1e-9


def test_varying_focal_recovered_exactly():
    rng = np.random.default_rng(4)
    num_cameras = 150
    T_true = camera_path(num_cameras, 4)
    focals = FOCAL * (1.0 + 0.3 * np.sin(np.linspace(0.0, 3.0, num_cameras)))  # a zoom
    K_true = intrinsics(focals)
    P = cameras(T_true, K_true) @ np.linalg.inv(random_distortion(rng, T_true[:, :3, 3]))

    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig(focal_model="varying"), scene_scale=scene_scale(P))

    assert upgrade.applied, upgrade.reason
    assert upgrade.residual_after < 1e-9
    np.testing.assert_allclose(upgrade.focals, focals, rtol=1e-8)
    assert centre_error(upgrade_cameras(P, upgrade.H_metric_world), T_true) < 1e-9
    # The shared model cannot explain a zoom: it keeps only the cameras near the median focal.
    shared = estimate_metric_upgrade(P, PP, UpgradeConfig(focal_model="shared"), scene_scale=scene_scale(P))
    assert not shared.applied or not shared.inliers.all()


def test_principal_point_is_an_input_per_camera():
    """Cameras with different (known) principal points, as after a crop: each is honoured."""
    rng = np.random.default_rng(5)
    T_true = camera_path(80, 5)
    K_true = intrinsics(np.full(80, FOCAL))
    pp = PP + rng.uniform(-40.0, 40.0, size=(80, 2))
    K_true[:, :2, 2] = pp
    P = cameras(T_true, K_true) @ np.linalg.inv(random_distortion(rng, T_true[:, :3, 3]))

    upgrade = estimate_metric_upgrade(P, pp, UpgradeConfig(), image_sizes=(WIDTH, HEIGHT), scene_scale=scene_scale(P))

    assert upgrade.applied and upgrade.residual_after < 1e-9
    assert upgrade.details["f0"] == (WIDTH + HEIGHT) / 2.0  # the image size sets the rough focal
    K, _, _ = decompose_projection(upgrade_cameras(P, upgrade.H_metric_world))
    np.testing.assert_allclose(K[:, :2, 2], pp, atol=1e-6)


def test_gauge_keeps_first_camera_and_spread():
    rng = np.random.default_rng(6)
    T_true = camera_path(60, 6)
    P = cameras(T_true, intrinsics(np.full(60, FOCAL))) @ np.linalg.inv(random_distortion(rng, T_true[:, :3, 3]))
    _, T_in, C_in = decompose_projection(P)

    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig(), scene_scale=scene_scale(P))

    _, T_out, C_out = decompose_projection(upgrade_cameras(P, upgrade.H_metric_world))
    np.testing.assert_allclose(T_out[0], T_in[0], atol=1e-9)
    spread_in = np.median(np.linalg.norm(C_in[1:] - C_in[0], axis=1))
    spread_out = np.median(np.linalg.norm(C_out[1:] - C_out[0], axis=1))
    assert abs(spread_out / spread_in - 1.0) < 1e-9


def test_metric_input_is_left_alone():
    """Never worse: cameras already metric up to noise are not 'corrected' by fitting the noise."""
    rng = np.random.default_rng(7)
    T_true = camera_path(100, 7)
    K = intrinsics(np.full(100, FOCAL))
    K[:, :2, 2] += rng.normal(scale=1.0, size=(100, 2))  # 1 px principal-point noise
    upgrade = estimate_metric_upgrade(cameras(T_true, K), PP, UpgradeConfig())
    assert not upgrade.applied
    assert upgrade.reason.startswith(("no clear improvement", "already metric"))
    np.testing.assert_array_equal(upgrade.H_metric_world, np.eye(4))
    assert upgrade.residual_after == upgrade.residual_before


# --------------------------------------------------------------------------- robustness
def misaligned(P: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A camera seen through its own wrong projective map, like a badly aligned submap."""
    return P @ np.linalg.inv(near_identity_sl4(rng))


@pytest.mark.parametrize("bend, applied", [(0.01, True), (0.03, False)])
def test_a_map_of_two_projective_frames_is_not_upgraded(bend, applied):
    """Never worse: when half the cameras sit in a frame bent against the other half's (a link that
    fixed only its shared camera), no one transform makes them all metric; beyond the noise, and
    with no much larger distortion removed, the upgrade is skipped instead of trading one
    distortion for another (a large distortion under the same errors is still removed:
    test_noise_degrades_gracefully)."""
    n = 200
    T_true = camera_path(n, 11)
    P = cameras(T_true, intrinsics(np.full(n, FOCAL)))
    B = np.eye(4)
    B[3, :3] = np.array([1.0, -0.5, 0.8]) * bend / scene_scale(P)
    P[n // 2:] = P[n // 2:] @ B
    # a mild common distortion, no larger than the bend: what the vggt profile's maps carry
    P = P @ np.linalg.inv(random_distortion(np.random.default_rng(12), T_true[:, :3, 3], strength=0.03))
    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig(), scene_scale=scene_scale(P))
    assert upgrade.applied == applied, upgrade.reason
    if not applied:
        assert upgrade.reason.startswith("the cameras are not one projective frame")
        assert upgrade.residual_before > 0.02  # there was a distortion to remove
        np.testing.assert_array_equal(upgrade.H_metric_world, np.eye(4))


@pytest.mark.parametrize("fraction", [0.1, 0.2])
def test_cameras_that_break_the_model_do_not_bend_the_result(fraction):
    rng = np.random.default_rng(8)
    num_cameras = 200
    T_true = camera_path(num_cameras, 8)
    K = intrinsics(np.full(num_cameras, FOCAL))
    P_true = cameras(T_true, K)
    bad = rng.permutation(num_cameras)[: int(fraction * num_cameras)]
    kinds = np.array_split(bad, 4)
    P_true[kinds[0]] = cameras(T_true[kinds[0]], intrinsics(np.full(len(kinds[0]), 1.4 * FOCAL)))  # wrong focal
    K_off = intrinsics(np.full(len(kinds[1]), FOCAL))
    K_off[:, :2, 2] += rng.choice([-1.0, 1.0], size=(len(kinds[1]), 2)) * 50.0  # principal point 10 % of f off
    P_true[kinds[1]] = cameras(T_true[kinds[1]], K_off)
    for i in kinds[2]:
        P_true[i] = misaligned(P_true[i], rng)
    gross = T_true[kinds[3]].copy()  # gross pose error: still an ideal camera, just elsewhere
    gross[:, :3, :3] = Rotation.random(len(gross), random_state=9).as_matrix()
    gross[:, :3, 3] += rng.normal(scale=2.0, size=(len(gross), 3))
    P_true[kinds[3]] = cameras(gross, intrinsics(np.full(len(gross), FOCAL)))
    P = P_true @ np.linalg.inv(random_distortion(rng, T_true[:, :3, 3]))

    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig(), scene_scale=scene_scale(P))

    assert upgrade.applied, upgrade.reason
    breaks_constraints = np.concatenate(kinds[:3])
    assert not upgrade.inliers[breaks_constraints].any()
    good = np.ones(num_cameras, dtype=bool)
    good[bad] = False
    assert upgrade.inliers[good].all()
    assert upgrade.residual_after < 1e-9  # on the kept cameras
    assert abs(upgrade.focal - FOCAL) < 1e-7 * FOCAL
    assert centre_error(upgrade_cameras(P, upgrade.H_metric_world), T_true, good) < 1e-9


def test_noise_degrades_gracefully():
    """Noise the model does not know (each run of 16 keyframes shares one small projective error,
    as a submap does): the upgraded cameras are as good as the noisy cameras are in the true
    frame (the best any upgrade can do), and the focal error stays below the noise level."""
    num_cameras = 160
    T_true = camera_path(num_cameras, 10)
    centres = T_true[:, :3, 3]
    size = np.linalg.norm(centres - centres.mean(0), axis=1).max()
    to_unit = np.eye(4)  # the noise acts in coordinates centred on the path, in units of its size
    to_unit[:3, :3] /= size
    to_unit[:3, 3] = -centres.mean(0) / size
    P_metric = cameras(T_true, intrinsics(np.full(num_cameras, FOCAL)))
    errors = []
    for noise in (0.001, 0.003, 0.01):
        rng = np.random.default_rng(11)
        P_noisy = P_metric.copy()
        for start in range(0, num_cameras, 16):
            E = np.linalg.inv(to_unit) @ (np.eye(4) + rng.normal(scale=noise, size=(4, 4))) @ to_unit
            P_noisy[start : start + 16] = P_noisy[start : start + 16] @ E
        P = P_noisy @ np.linalg.inv(random_distortion(rng, centres))
        upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig(), scene_scale=scene_scale(P))
        assert upgrade.applied, upgrade.reason
        assert upgrade.residual_after < 0.3 * upgrade.residual_before
        assert abs(upgrade.focal / FOCAL - 1.0) < noise
        error = centre_error(upgrade_cameras(P, upgrade.H_metric_world), T_true)
        assert error < 1.2 * centre_error(P_noisy, T_true)
        errors.append(error)
    assert errors[0] < errors[1] < errors[2]
    # Far noisier than loss_scale: too few cameras agree and nothing is applied.
    rng = np.random.default_rng(11)
    P_noisy = P_metric @ np.linalg.inv(to_unit) @ (np.eye(4) + rng.normal(scale=0.1, size=(num_cameras, 4, 4))) @ to_unit
    upgrade = estimate_metric_upgrade(P_noisy, PP, UpgradeConfig(), scene_scale=scene_scale(P_noisy))
    assert not upgrade.applied and upgrade.reason.startswith("too few consistent cameras")


# --------------------------------------------------------------------------- degenerate motion
def noisy_cameras(T_world_cam: np.ndarray, rng: np.random.Generator, noise: float = 0.002) -> np.ndarray:
    """Cameras with small intrinsic noise (principal point, skew, aspect), distorted."""
    K = intrinsics(np.full(len(T_world_cam), FOCAL))
    K[:, 0, 1] += rng.normal(scale=noise * FOCAL, size=len(K))
    K[:, :2, 2] += rng.normal(scale=noise * FOCAL, size=(len(K), 2))
    K[:, 1, 1] *= 1.0 + rng.normal(scale=noise, size=len(K))
    return cameras(T_world_cam, K) @ np.linalg.inv(near_identity_sl4(rng))


def fixed_orientation(rng: np.random.Generator, centres: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(centres), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    T[:, :3, 3] = centres
    return T


def pure_rotation(rng):
    T = np.tile(np.eye(4), (80, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.5, size=(80, 3))).as_matrix()
    T[:, :3, 3] = [0.5, -0.3, 1.2]
    return T


def pan_about_one_axis(rng):
    T = pure_rotation(rng)
    T[:, :3, :3] = Rotation.from_rotvec(np.outer(np.linspace(0.0, 2.0, 80), [0.0, 1.0, 0.0])).as_matrix()
    return T


def planar_parallel_axes(rng):
    centres = np.c_[rng.uniform(-1.0, 1.0, (80, 2)), np.zeros(80)]
    return fixed_orientation(rng, centres)


def pure_translation(rng):
    return fixed_orientation(rng, rng.uniform(-1.0, 1.0, (80, 3)))


def forward_while_rolling(rng):
    """Rotation about the optical axis while moving along it (critical for the focal length)."""
    T = np.tile(np.eye(4), (80, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(np.outer(np.linspace(0.0, 2.0, 80), [0.0, 0.0, 1.0])).as_matrix()
    T[:, 2, 3] = np.linspace(0.0, 2.0, 80)
    return T


@pytest.mark.parametrize("motion, undetermined", [
    (pure_rotation, "plane at infinity"),
    (pan_about_one_axis, "plane at infinity"),
    (planar_parallel_axes, "calibration"),
    (pure_translation, "calibration"),
    (forward_while_rolling, "calibration"),
])
@pytest.mark.parametrize("focal_model", ["shared", "varying"])
def test_degenerate_motion_is_detected_and_skipped(motion, undetermined, focal_model):
    rng = np.random.default_rng(12)
    upgrade = estimate_metric_upgrade(noisy_cameras(motion(rng), rng), PP, UpgradeConfig(focal_model=focal_model))
    assert not upgrade.applied
    assert upgrade.reason.startswith("degenerate motion")
    assert undetermined in upgrade.reason
    assert upgrade.condition < UpgradeConfig().min_condition
    np.testing.assert_array_equal(upgrade.H_metric_world, np.eye(4))


@pytest.mark.parametrize("baseline, applied", [(0.003, False), (0.05, True)])
def test_near_pure_rotation_is_judged_by_its_uncertainty(baseline, applied):
    """Rotation with a small baseline against a scene 1 unit away: determined in principle, but
    with noisy cameras a baseline of 3 thousandths leaves the plane at infinity far too uncertain."""
    rng = np.random.default_rng(18)
    T = pure_rotation(rng)
    T[:, :3, 3] += rng.normal(scale=baseline, size=(len(T), 3))
    upgrade = estimate_metric_upgrade(noisy_cameras(T, rng), PP, UpgradeConfig(), scene_scale=1.0)
    assert upgrade.applied is applied, upgrade.reason
    if not applied:
        assert upgrade.reason.startswith("degenerate motion: the plane at infinity")
        assert "poorly determined" in upgrade.reason
        assert upgrade.uncertainty > UpgradeConfig().max_uncertainty
    else:
        assert upgrade.uncertainty < UpgradeConfig().max_uncertainty


def test_orbit_about_one_axis_is_not_degenerate_with_square_pixels():
    """A turntable orbit (one rotation axis, planar motion) is critical for a general constant
    calibration (the scale along the axis is free), but that scale changes the aspect ratio,
    which is known here: the upgrade is determined and recovered."""
    rng = np.random.default_rng(13)
    angles = np.linspace(0.0, 2.0 * np.pi, 60, endpoint=False)
    T_true = np.stack([look_at(np.array([2.0 * np.cos(a), 2.0 * np.sin(a), 0.0]), np.zeros(3)) for a in angles])
    P = cameras(T_true, intrinsics(np.full(60, FOCAL))) @ np.linalg.inv(near_identity_sl4(rng))
    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig())
    assert upgrade.applied and upgrade.condition > 0.1
    assert centre_error(upgrade_cameras(P, upgrade.H_metric_world), T_true) < 1e-9


@pytest.mark.parametrize("count", [0, 2])
def test_too_few_keyframes_are_skipped(count):
    rng = np.random.default_rng(14)
    P = cameras(camera_path(10, 0)[:count], intrinsics(np.full(count, FOCAL))) @ np.linalg.inv(near_identity_sl4(rng))
    upgrade = estimate_metric_upgrade(P, np.zeros((count, 2)) + PP, UpgradeConfig())
    assert not upgrade.applied
    assert upgrade.reason == f"too few keyframes ({count} < 3)"
    np.testing.assert_array_equal(upgrade.H_metric_world, np.eye(4))


def test_switched_off_is_skipped():
    P = cameras(camera_path(20, 0), intrinsics(np.full(20, FOCAL)))
    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig(mode="off"))
    assert (upgrade.applied, upgrade.reason) == (False, "upgrade off")


def test_mostly_inconsistent_cameras_are_skipped():
    rng = np.random.default_rng(15)
    T_true = camera_path(60, 15)
    P = cameras(T_true, intrinsics(np.full(60, FOCAL)))
    for i in range(0, 60, 4):
        P[i:i + 4] = P[i:i + 4] @ np.linalg.inv(near_identity_sl4(rng))  # every run of 4 its own frame
    upgrade = estimate_metric_upgrade(P, PP, UpgradeConfig())
    assert not upgrade.applied
    assert upgrade.reason.startswith(("too few consistent cameras", "no clear improvement"))


# --------------------------------------------------------------------------- composition
def test_points_and_cameras_compose_to_the_same_pixels():
    rng = np.random.default_rng(16)
    T_true = camera_path(40, 16)
    P = cameras(T_true, intrinsics(np.full(40, FOCAL))) @ np.linalg.inv(random_distortion(rng, T_true[:, :3, 3]))
    H = estimate_metric_upgrade(P, PP, UpgradeConfig(), scene_scale=scene_scale(P)).H_metric_world
    # Points in front of every camera: along each optical axis, 1-3 scene units ahead.
    K, T_in, C_in = decompose_projection(P)
    X = C_in + T_in[:, :3, 2] * rng.uniform(1.0, 3.0, size=(40, 1)) * scene_scale(P)
    X_h = np.c_[X, np.ones(40)]
    pixels_before = np.einsum("nij,nj->ni", P, X_h)
    pixels_after = np.einsum("nij,nj->ni", upgrade_cameras(P, H), upgrade_points(X_h, H))
    np.testing.assert_allclose(pixels_after[:, :2] / pixels_after[:, 2:], pixels_before[:, :2] / pixels_before[:, 2:], atol=1e-8)
    np.testing.assert_allclose(upgrade_points(X, H), upgrade_points(X_h, H)[:, :3] / upgrade_points(X_h, H)[:, 3:], atol=1e-9)
    # Still in front of the upgraded cameras: depth along the decomposed optical axis > 0.
    _, T_out, C_out = decompose_projection(upgrade_cameras(P, H))
    depth = np.einsum("ni,ni->n", upgrade_points(X, H) - C_out, T_out[:, :3, 2])
    assert np.all(depth > 0)
    assert np.all(upgrade_points(X_h, H)[:, 3] > 0)


def test_graph_nodes_give_the_same_cameras():
    rng = np.random.default_rng(17)
    T_true = camera_path(48, 17)
    submap = np.repeat(np.arange(3), 16)
    nodes = {s: near_identity_sl4(rng) for s in range(3)}
    T_cam_submap = se3_inverse(T_true)  # any rigid extrinsics
    K = intrinsics(np.full(48, FOCAL))
    P = np.stack([K[i] @ T_cam_submap[i, :3] @ np.linalg.inv(nodes[submap[i]]) for i in range(48)])
    H = near_identity_sl4(rng)  # the helpers are exact for any SL(4) map

    upgraded = upgrade_graph_nodes(nodes, H)
    P_nodes = np.stack([K[i] @ T_cam_submap[i, :3] @ np.linalg.inv(upgraded[submap[i]]) for i in range(48)])
    np.testing.assert_allclose(P_nodes, upgrade_cameras(P, H), atol=1e-9 * np.abs(P).max())
    np.testing.assert_allclose(np.linalg.det(np.stack(list(upgraded.values()))), 1.0, atol=1e-9)
    stacked = upgrade_graph_nodes(np.stack([nodes[s] for s in range(3)]), H)
    np.testing.assert_allclose(stacked, np.stack([upgraded[s] for s in range(3)]))


def test_constraint_residuals_are_exact_for_known_intrinsics():
    K = np.array([[[500.0, 5.0, 330.0], [0.0, 510.0, 230.0], [0.0, 0.0, 1.0]]])
    f = np.sqrt(500.0 * 510.0)
    np.testing.assert_allclose(intrinsic_constraint_residuals(K, [[320.0, 240.0]]),
                               [[5.0 / f, 510.0 / 500.0 - 1.0, 10.0 / f, -10.0 / f]])


# --------------------------------------------------------------------------- settings and input
@pytest.mark.parametrize("change, flag", [
    (dict(focal_model="zoom"), "--upgrade-focal-model"),
    (dict(loss="l2"), "--upgrade-loss"),
    (dict(loss_scale=0.0), "--upgrade-loss-scale"),
    (dict(loss_scale=float("nan")), "--upgrade-loss-scale"),
    (dict(min_keyframes=2), "--upgrade-min-keyframes"),
    (dict(min_condition=1.5), "--upgrade-min-condition"),
    (dict(max_uncertainty=0.0), "--upgrade-max-uncertainty"),
    (dict(max_residual_ratio=0.0), "--upgrade-max-residual-ratio"),
    (dict(min_inlier_fraction=1.2), "--upgrade-min-inlier-fraction"),
    (dict(outlier_factor=0.5), "--upgrade-outlier-factor"),
    (dict(max_iterations=0), "--upgrade-max-iterations"),
    (dict(focal_weight=-1.0), "--upgrade-focal-weight"),
])
def test_bad_settings_give_one_clear_line(change, flag):
    config = UpgradeConfig(**change)
    with pytest.raises(UserError) as error:
        config.validate()
    assert flag in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(UserError):  # checked before any work
        estimate_metric_upgrade(np.zeros((5, 3, 4)), np.zeros((5, 2)), config)


def test_settings_from_file_and_flags():
    config = config_from_dict({"upgrade": {"focal_model": "varying", "loss_scale": 0.02}})
    assert (config.upgrade.focal_model, config.upgrade.loss_scale) == ("varying", 0.02)
    args = build_parser().parse_args(["run", "src", "--out", "o", "--metric-upgrade", "off", "--upgrade-focal-model", "varying"])
    config = config_from_args(args)
    assert config.upgrade.mode == "off" and config.upgrade.focal_model == "varying"


@pytest.mark.parametrize("P, pp, message", [
    (np.zeros((4, 3, 3)), np.zeros((4, 2)), "(N, 3, 4)"),
    (np.ones((4, 3, 4)), np.zeros((3, 2)), "principal_points"),
    (np.full((4, 3, 4), np.nan), np.zeros((4, 2)), "NaN"),
    (np.zeros((4, 3, 4)), np.zeros((4, 2)), "singular"),
])
def test_bad_input_gives_one_clear_line(P, pp, message):
    with pytest.raises(UserError) as error:
        estimate_metric_upgrade(P, pp, UpgradeConfig())
    assert message in str(error.value) and "\n" not in str(error.value)


def test_bad_scene_scale_and_image_sizes():
    P = cameras(camera_path(10, 0), intrinsics(np.full(10, FOCAL)))
    with pytest.raises(UserError, match="scene_scale"):
        estimate_metric_upgrade(P, PP, UpgradeConfig(), scene_scale=-1.0)
    with pytest.raises(UserError, match="image_sizes"):
        estimate_metric_upgrade(P, PP, UpgradeConfig(), image_sizes=[640, 0])
