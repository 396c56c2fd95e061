"""Completing camera-anchored links from the cameras' calibration (sl4slam.completion), against exact truth."""

from __future__ import annotations

import numpy as np
import pytest

from sl4slam.completion import bending, complete_camera_link, plane_normal, shared_camera_agreement
from sl4slam.geometry import normalize_sl4
from sl4slam.upgrade import UpgradeConfig

K = np.array([[256.0, 0.0, 160.0], [0.0, 256.0, 120.0], [0.0, 0.0, 1.0]])
PP = np.array([160.0, 120.0])


def camera_from_world(centre: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R_world_cam = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    T = np.eye(4)
    T[:3, :3] = R_world_cam.T
    T[:3, 3] = -R_world_cam.T @ centre
    return T


def distortion(rng: np.random.Generator, perspective: float) -> np.ndarray:
    D = np.eye(4)
    D[:3, :3] += rng.normal(size=(3, 3)) * 0.02
    D[:3, 3] = rng.normal(size=3) * 0.1
    D[3, :3] = rng.normal(size=3) * perspective
    return D


def two_submaps(seed: int, spread: float = 3.0):
    """Submaps a and b of one metric world, each projectively distorted (``X_s = D_s X_world``);
    b's first camera is the shared frame, looking at a plane. ``spread`` scales how far b's other
    cameras move from it (0: all at the shared camera's centre)."""
    rng = np.random.default_rng(seed)
    D_a, D_b = distortion(rng, 0.1), distortion(rng, 0.1)
    cameras = [K @ camera_from_world(spread * np.array([0.1 * i, 0.02 * i, 0.05 * i]), 0.05 * i)[:3] for i in range(16)]
    plane = np.c_[rng.uniform(-1, 1, (300, 2)), np.full(300, 3.0), np.ones(300)]
    X_b = plane @ D_b.T
    X_b = X_b[:, :3] / X_b[:, 3:]
    P_b = np.array([P @ np.linalg.inv(D_b) for P in cameras])
    P_a_shared = cameras[0] @ np.linalg.inv(D_a)
    centre = np.linalg.svd(P_b[0])[2][-1]
    return dict(H_true=normalize_sl4(D_a @ np.linalg.inv(D_b)), D_a=D_a, P_b=P_b, P_a_shared=P_a_shared,
                centre=centre[:3] / centre[3], X_b=X_b)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_bent_link_is_completed_to_the_truth(seed):
    w = two_submaps(seed)
    p = np.random.default_rng(seed + 10).normal(size=3) * 0.08
    link = normalize_sl4(w["H_true"] @ bending(p, w["centre"], w["X_b"]))
    assert shared_camera_agreement(w["P_a_shared"], w["P_b"][0], link) < 1e-12  # bending keeps the shared camera
    assert np.abs(link - w["H_true"]).max() > 0.01
    result = complete_camera_link(link, w["centre"], w["X_b"], w["P_b"][1:], PP, np.linalg.inv(w["D_a"]), 256.0)
    assert result.applied and result.reason == "completed"
    assert np.abs(result.H_a_b - w["H_true"]).max() < 1e-8
    assert result.residual_before > 0.005 and result.residual_after < 1e-9 and result.uncertainty < 0.01


def test_a_camera_constrained_link_is_completed_along_the_plane_normal_only():
    w = two_submaps(3)
    normal = plane_normal(w["X_b"])
    # bending along the normal moves no point of the plane: what the points leave free
    moved = np.c_[w["X_b"], np.ones(len(w["X_b"]))] @ bending(0.1 * normal[0], w["centre"], w["X_b"]).T
    assert np.allclose(moved[:, :3] / moved[:, 3:], w["X_b"], atol=1e-9)
    link = normalize_sl4(w["H_true"] @ bending(0.1 * normal[0], w["centre"], w["X_b"]))
    result = complete_camera_link(link, w["centre"], w["X_b"], w["P_b"][1:], PP, np.linalg.inv(w["D_a"]), 256.0,
                                  free=normal)
    assert result.applied and np.abs(result.H_a_b - w["H_true"]).max() < 1e-8
    assert abs(abs(result.perspective @ normal[0]) - np.linalg.norm(result.perspective)) < 1e-9


def test_bending_keeps_the_shared_camera_and_the_centroid_depth():
    w = two_submaps(4)
    G = bending(np.array([0.1, -0.2, 0.05]), w["centre"], w["X_b"])
    assert shared_camera_agreement(w["P_b"][0], w["P_b"][0], G) < 1e-12
    centroid = np.append(w["X_b"].mean(axis=0), 1.0)
    moved = G @ centroid
    assert np.allclose(moved[:3] / moved[3], centroid[:3], atol=1e-12)
    other = np.append(w["X_b"][0], 1.0)
    moved = G @ other
    assert not np.allclose(moved[:3] / moved[3], other[:3], atol=1e-3)  # elsewhere it bends


def test_an_exact_link_is_left_alone():
    w = two_submaps(5)
    result = complete_camera_link(w["H_true"], w["centre"], w["X_b"], w["P_b"][1:], PP, np.linalg.inv(w["D_a"]), 256.0)
    assert not result.applied and result.reason.startswith("no clear improvement")
    assert np.array_equal(result.H_a_b, w["H_true"])
    told = complete_camera_link(w["H_true"], w["centre"], w["X_b"], w["P_b"][1:], PP, np.linalg.inv(w["D_a"]), 256.0,
                                UpgradeConfig(completion_residual=0.002))
    assert not told.applied and told.reason.startswith("already metric")
    assert np.array_equal(told.H_a_b, w["H_true"])


def test_a_slight_bending_is_completed_only_below_the_residual_it_is_told():
    w = two_submaps(9)
    link = normalize_sl4(w["H_true"] @ bending(np.array([0.002, -0.001, 0.0014]), w["centre"], w["X_b"]))
    kept = complete_camera_link(link, w["centre"], w["X_b"], w["P_b"][1:], PP, np.linalg.inv(w["D_a"]), 256.0,
                                UpgradeConfig(completion_residual=0.002))
    assert not kept.applied and kept.reason.startswith("already metric")
    assert 0.0005 < kept.residual_before < 0.002
    assert np.array_equal(kept.H_a_b, link)
    result = complete_camera_link(link, w["centre"], w["X_b"], w["P_b"][1:], PP, np.linalg.inv(w["D_a"]), 256.0)
    assert result.applied and np.abs(result.H_a_b - w["H_true"]).max() < 1e-8


def test_cameras_metric_to_within_their_noise_are_not_completed_without_the_threshold():
    # an exact link, and b's cameras off by noise the bending cannot explain (skew, principal point)
    w = two_submaps(9)
    rng = np.random.default_rng(0)
    noisy = []
    for P in w["P_b"][1:]:
        J = np.eye(3)
        J[0, 1] = rng.normal() * 1e-4 * 256.0
        J[:2, 2] += rng.normal(size=2) * 1e-4 * 256.0
        noisy.append(J @ P)
    result = complete_camera_link(w["H_true"], w["centre"], w["X_b"], np.array(noisy), PP, np.linalg.inv(w["D_a"]), 256.0,
                                  UpgradeConfig(completion_residual=0.0))
    assert not result.applied and result.reason.startswith("no clear improvement")
    assert np.array_equal(result.H_a_b, w["H_true"])


def test_cameras_at_the_shared_centre_do_not_determine_the_bending():
    # b's cameras only rotate about the shared camera's centre: the bending changes none of them
    w = two_submaps(6, spread=0.0)
    link = normalize_sl4(w["H_true"] @ bending(np.array([0.05, 0.0, 0.05]), w["centre"], w["X_b"]))
    wrong_metric = np.linalg.inv(w["D_a"]) @ distortion(np.random.default_rng(1), 0.1)  # cameras are not metric
    result = complete_camera_link(link, w["centre"], w["X_b"], w["P_b"][1:], PP, wrong_metric, 256.0)
    assert not result.applied and "do not determine" in result.reason and result.uncertainty > 1
    assert np.array_equal(result.H_a_b, link)


def test_a_link_that_moves_the_shared_camera_is_told_apart():
    w = two_submaps(7)
    assert shared_camera_agreement(w["P_a_shared"], w["P_b"][0], w["H_true"]) < 1e-12
    other = w["H_true"].copy()
    other[0, 3] += 0.1
    assert shared_camera_agreement(w["P_a_shared"], w["P_b"][0], other) > 1e-3


def test_a_failing_fit_keeps_the_link(monkeypatch):
    import sl4slam.completion as completion

    def failing(*args, **kwargs):
        raise ValueError("Residuals are not finite")

    monkeypatch.setattr(completion, "least_squares", failing)
    w = two_submaps(8)
    link = normalize_sl4(w["H_true"] @ bending(np.array([0.05, 0.02, 0.05]), w["centre"], w["X_b"]))
    result = complete_camera_link(link, w["centre"], w["X_b"], w["P_b"][1:], PP, np.linalg.inv(w["D_a"]), 256.0)
    assert not result.applied and result.reason.startswith("the fit failed")
    assert np.array_equal(result.H_a_b, link)
