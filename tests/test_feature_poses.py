"""Each frame's camera corrected by the image features it shares with the other frames of its
submap (``sl4slam.feature_poses``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.feature_poses import (PairPose, correct_prediction, corrected_poses, fit_pose, measure_pairs,
                                   measurement_spread, so3_exp, so3_log)
from sl4slam.synthetic import camera_path, default_intrinsics, make_world, render_frames
from sl4slam.types import SubmapPrediction

W, H = 256, 192


def angles_deg(T: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Degrees between each frame's rotation and the true one, frames 1.."""
    turned = np.einsum("sij,skj->sik", T[:, :, :3], truth[:, :, :3])
    return np.degrees(np.arccos(np.clip((np.trace(turned, axis1=1, axis2=2) - 1) / 2, -1, 1)))[1:]


def centres(T: np.ndarray) -> np.ndarray:
    return -np.einsum("sji,sj->si", T[:, :, :3], T[:, :, 3])


@pytest.fixture(scope="module")
def window():
    """Nine frames of the synthetic world (every 6th of its lap from frame 120): true camera-from-
    submap poses (the first the identity), depth, intrinsics and images."""
    poses = camera_path(600, 0)[120:174:6]
    K = default_intrinsics(W, H)
    rgb, depth = render_frames(make_world(0), poses, K, W, H)
    truth = np.einsum("ij,sjk->sik", np.linalg.inv(poses[0]), poses)  # T_ref_cam
    T_cam_submap = np.linalg.inv(truth)[:, :3, :4]
    return T_cam_submap, depth, np.repeat(K[None], len(poses), 0), rgb


def prediction(T_cam_submap, depth, K, rgb) -> SubmapPrediction:
    return SubmapPrediction(depth=depth.astype(np.float32), confidence=np.full(depth.shape, 2.0, np.float32),
                            T_cam_submap=np.array(T_cam_submap, dtype=np.float64), K=K, colors=rgb)


def perturbed(T_cam_submap: np.ndarray, degrees: float, shift: float, seed: int) -> np.ndarray:
    """Every frame but the first turned about its centre by an independent rotation of about
    ``degrees`` per axis and its centre moved by about ``shift`` per axis (the simulator's per-frame
    camera errors)."""
    rng = np.random.default_rng(seed)
    wrong = np.array(T_cam_submap, dtype=np.float64)
    for s in range(1, len(wrong)):
        dR = Rotation.from_rotvec(rng.normal(0, np.radians(degrees), 3)).as_matrix()
        centre = -wrong[s, :, :3].T @ wrong[s, :, 3] + rng.normal(0, shift, 3)
        wrong[s, :, :3] = dR @ wrong[s, :, :3]
        wrong[s, :, 3] = -wrong[s, :, :3] @ centre
    return wrong


def test_rotation_vectors_round_trip():
    for w in (np.array([0.3, -0.2, 0.1]), np.array([1e-9, 0, 0]), np.array([0.0, 2.5, 1.0])):
        np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-12)
    np.testing.assert_allclose(so3_exp(np.array([0, 0, np.pi / 2])) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_fit_pose_finds_the_pose_among_outliers():
    rng = np.random.default_rng(0)
    K = np.array([[200.0, 0, 128], [0, 200.0, 96], [0, 0, 1]])
    P = np.column_stack([rng.uniform(-1, 1, 400), rng.uniform(-0.8, 0.8, 400), rng.uniform(2, 4, 400)])
    R = Rotation.from_rotvec([0.05, -0.1, 0.02]).as_matrix()
    t = np.array([0.1, 0.0, -0.05])
    X = P @ R.T + t
    uv = X[:, :2] / X[:, 2:] * 200.0 + [128, 96]
    uv[:100] = rng.uniform([0, 0], [256, 192], (100, 2))  # a quarter of the matches wrong
    start = so3_exp(np.radians([1.5, -1.0, 2.0])) @ R
    fitted, shift, covariance, inliers = fit_pose(P, uv, K, start, t + [0.02, -0.01, 0.03])
    assert np.degrees(np.linalg.norm(so3_log(fitted @ R.T))) < 1e-6
    np.testing.assert_allclose(shift, t, atol=1e-7)
    assert inliers[100:].all() and inliers[:100].sum() < 10
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    # the second frame's focal length 3 % off: the free gain takes it, the pose stays
    zoomed = (uv - [128, 96]) * 1.03 + [128, 96]
    fitted, shift, _, _ = fit_pose(P, zoomed, K, start, t)
    assert np.degrees(np.linalg.norm(so3_log(fitted @ R.T))) < 1e-6
    np.testing.assert_allclose(shift, t, atol=1e-7)
    # the same matches from a start farther than the allowed turn: nothing within it, no fit
    assert fit_pose(P, uv, K, so3_exp(np.radians([0, 12.0, 0])) @ R, t) is None


def chain(seed: int, frames: int = 8):
    """True camera-from-submap poses ``(frames, 3, 4)`` (the first the identity) along a short walk."""
    rng = np.random.default_rng(seed)
    T = np.zeros((frames, 3, 4))
    T[0, :, :3] = np.eye(3)
    for s in range(1, frames):
        R = Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_matrix()
        T[s, :, :3], T[s, :, 3] = R, -R @ (np.array([0.1 * s, 0.0, 0.02 * s]) + rng.normal(0, 0.02, 3))
    return T


def exact_pairs(T: np.ndarray, span: int = 3, covariance: np.ndarray | None = None) -> list:
    cov = np.diag([np.radians(0.01) ** 2] * 3 + [1e-4 ** 2] * 3) if covariance is None else covariance
    pairs = []
    for i in range(len(T)):
        for j in range(i + 1, min(len(T), i + span + 1)):
            R = T[j, :, :3] @ T[i, :, :3].T
            pairs.append(PairPose(i, j, R, T[j, :, 3] - R @ T[i, :, 3], cov, 100))
    return pairs


def errors(T: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (degrees) and centre errors of frames 1.."""
    return angles_deg(T, truth), np.linalg.norm(centres(T) - centres(truth), axis=1)[1:]


def test_exact_measurements_remove_independent_errors():
    truth = chain(1)
    model = perturbed(truth, 1.0, 0.01, seed=11)
    corrected, found = corrected_poses(model, exact_pairs(truth))
    before, after = errors(model, truth), errors(corrected, truth)
    assert np.median(after[0]) < 0.05 * np.median(before[0]), (before[0], after[0])
    assert np.median(after[1]) < 0.1 * np.median(before[1]), (before[1], after[1])
    assert found.pairs_used == len(exact_pairs(truth))
    assert np.degrees(found.model_spread[0]) > 0.3 and found.model_spread[1] > 0.003
    np.testing.assert_array_equal(corrected[0], model[0])
    # the model already agreeing with the images: nothing to correct, the poses as they were
    same, found = corrected_poses(truth, exact_pairs(truth))
    assert found.pairs_used == 0 and np.array_equal(same, truth)


def test_a_wrong_pair_is_left_out():
    truth = chain(2)
    model = perturbed(truth, 1.0, 0.01, seed=12)
    pairs = exact_pairs(truth)
    pairs[3] = PairPose(pairs[3].i, pairs[3].j, so3_exp(np.radians([0, 4.0, 0])) @ pairs[3].R, pairs[3].t,
                        pairs[3].covariance, 100)
    corrected, found = corrected_poses(model, pairs)
    assert found.pairs_used == len(pairs) - 1
    rotation, centre = errors(corrected, truth)
    assert rotation.max() < 0.1 and centre.max() < 1e-3


def test_triangles_measure_the_spread_of_the_measurements():
    rng = np.random.default_rng(3)
    truth = chain(3, frames=12)
    sigma_r, sigma_t = np.radians(0.2), 0.004
    pairs = [PairPose(p.i, p.j, so3_exp(rng.normal(0, sigma_r, 3)) @ p.R, p.t + rng.normal(0, sigma_t, 3), p.covariance, 50)
             for p in exact_pairs(truth, span=4)]
    turn, shift = measurement_spread(pairs)
    assert 0.7 * sigma_r < turn < 1.4 * sigma_r
    assert 0.6 * sigma_t < shift < 1.6 * sigma_t  # rotation noise times the baselines adds a little
    assert measurement_spread(pairs[:2]) == (0.0, 0.0)  # no triangle


def test_rendered_window_cameras_corrected(window):
    T_true, depth, K, rgb = window
    wrong = perturbed(T_true, 1.0, 0.01, seed=4)
    predicted = prediction(wrong, depth, K, rgb)
    mask = np.ones(depth.shape, dtype=bool)
    corrected = correct_prediction(predicted, mask, 1000)
    before, after = errors(wrong, T_true), errors(corrected.T_cam_submap, T_true)
    assert np.median(after[0]) < 0.4 * np.median(before[0]), (before[0], after[0])
    # the centres less so: the focal length is left free in each pair's fit (the model's may be wrong)
    assert np.median(after[1]) < 0.8 * np.median(before[1]), (before[1], after[1])
    np.testing.assert_array_equal(corrected.T_cam_submap[0], wrong[0])
    assert corrected.depth is predicted.depth and corrected.K is predicted.K
    # deterministic: the same input, the same bytes
    assert np.array_equal(correct_prediction(predicted, mask, 1000).T_cam_submap, corrected.T_cam_submap)


def test_true_cameras_stay_close(window):
    T_true, depth, K, rgb = window
    corrected = correct_prediction(prediction(T_true, depth, K, rgb), np.ones(depth.shape, dtype=bool), 1000)
    rotation, centre = errors(corrected.T_cam_submap, T_true)
    assert rotation.max() < 0.05 and centre.max() < 2e-3  # metres, in a room of a few metres


def test_textureless_frames_are_left_as_they_are(window):
    T_true, depth, K, rgb = window
    wrong = perturbed(T_true, 1.0, 0.01, seed=5)
    flat = prediction(wrong, depth, K, np.full_like(rgb, 128))
    mask = np.ones(depth.shape, dtype=bool)
    assert measure_pairs(flat, mask, 1000) == []
    assert correct_prediction(flat, mask, 1000) is flat


def test_centres_are_held_where_the_pairs_measure_them_no_better():
    """Rotations corrected, centres exactly the model's, when the pairs' translations scatter as much
    as the model's relative centres disagree with them (the centres' spread comes out 0)."""
    rng = np.random.default_rng(6)
    truth = chain(6)
    model = perturbed(truth, 1.0, 0.0, seed=16)
    pairs = [PairPose(p.i, p.j, p.R, p.t + rng.normal(0, 0.05, 3), p.covariance, 100) for p in exact_pairs(truth)]
    corrected, found = corrected_poses(model, pairs)
    assert found.model_spread[1] == 0.0 and found.model_spread[0] > 0.0
    rotation_before, _ = errors(model, truth)
    rotation, _ = errors(corrected, truth)
    assert np.median(rotation) < 0.2 * np.median(rotation_before)
    np.testing.assert_allclose(centres(corrected), centres(model), atol=1e-12)
