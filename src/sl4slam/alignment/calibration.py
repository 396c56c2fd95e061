"""The calibration-and-scale link between two reconstructions of one frame (VGGT-SLAM 2.0).

A frame reconstructed in two submaps has, in each, a camera ``K [R | t]`` and per-pixel points. In
each reconstruction's *camera* frame the camera is ``K [I | 0]``; the two agree on the image when
the cur-camera coordinates are mapped by ``K_a^-1 K_b`` (as 4x4 matrices ``diag(K, 1)``), which moves
every point of ``b`` onto the ray of its own pixel in ``a``. What the image cannot say, each point's
distance along its ray, is one scale ``s``: the median of ``|X_cam,a| / |K_a^-1 K_b X_cam,b|`` over
the pixels confident in both (a median depth ratio). So the link between the frame's two camera
frames is

    L_a_b = diag(K_a, 1)^-1 diag(K_b, 1) diag(s, s, s, 1)        (x_cam,a ~ L_a_b x_cam,b)

with no free projective terms and no RANSAC: what VGGT-SLAM 2.0 puts between the shared frame's two
graph nodes. In submap coordinates it is ``H_a_b = T_cam,a^-1 L_a_b T_cam,b`` (``T_cam`` the frame's
extrinsic in each submap), an SL(4) map after normalisation, so either graph design can hold it.

Unlike a 15-DOF fit it cannot degenerate on a planar frame; unlike it, it does not follow a relative
projective distortion of the two reconstructions (it assumes they agree up to intrinsics and scale
at this camera).
"""

from __future__ import annotations

import numpy as np

from ..geometry import apply_transform, normalize_sl4, se3_inverse, to_4x4
from ..types import Alignment, FrameView
from .common import clean_correspondences, make_alignment
from .ransac import score_one


def calibration_link(K_a: np.ndarray, K_b: np.ndarray, scale: float) -> np.ndarray:
    """``L_a_b = diag(K_a, 1)^-1 diag(K_b, 1) diag(s, s, s, 1)`` (4, 4): camera frame ``b`` -> ``a``."""
    K4_a, K4_b = np.eye(4), np.eye(4)
    K4_a[:3, :3], K4_b[:3, :3] = K_a, K_b
    return np.linalg.solve(K4_a, K4_b) @ np.diag([scale, scale, scale, 1.0])


def calibration_scale(X_cam_a: np.ndarray, X_cam_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray) -> float:
    """Median of ``|X_cam,a| / |K_a^-1 K_b X_cam,b|`` over rows where both are finite and positive.

    Args:
        X_cam_a, X_cam_b: ``(N, 3)`` the same pixels' points in the frame's two camera frames.
        K_a, K_b: ``(3, 3)`` the frame's intrinsics in each reconstruction.

    Raises:
        ValueError: no usable pair.
    """
    mapped = X_cam_b @ np.linalg.solve(K_a, K_b).T
    dist_a, dist_b = np.linalg.norm(X_cam_a, axis=1), np.linalg.norm(mapped, axis=1)
    usable = np.isfinite(dist_a) & np.isfinite(dist_b) & (dist_a > 0) & (dist_b > 0)
    if not usable.any():
        raise ValueError("the shared frame has no finite points at positive distance in both submaps; "
                         "cannot estimate the scale")
    return float(np.median(dist_a[usable] / dist_b[usable]))


def calibration_from_shared_frame(view_a: FrameView, view_b: FrameView, X_a: np.ndarray, X_b: np.ndarray,
                                  inlier_threshold: float = 0.01) -> Alignment:
    """``H_a_b`` (submap ``b`` -> submap ``a``) from the calibration-and-scale link of one frame.

    Args:
        view_a, view_b: the frame in submaps ``a`` and ``b`` (their ``K`` and ``T_cam_submap``).
        X_a, X_b: ``(N, 3)`` the pixels confident in both, as points of each submap.
        inlier_threshold: transfer distance (``X_a`` units) for the inlier mask and RMS.

    Returns:
        ``Alignment`` with ``model="calibration"``, ``H`` in SL(4), ``extras["scale"] = s`` and
        ``extras["link"]`` the camera-frame link ``L_a_b`` (4, 4).

    Raises:
        ValueError: non-finite cameras or no usable point pair.
    """
    T_a, T_b = to_4x4(view_a.T_cam_submap), to_4x4(view_b.T_cam_submap)
    K_a, K_b = np.asarray(view_a.K, dtype=np.float64), np.asarray(view_b.K, dtype=np.float64)
    if not all(np.isfinite(M).all() for M in (T_a, T_b, K_a, K_b)):
        raise ValueError("the shared frame's cameras are not finite")
    X_a_c, X_b_c, finite = clean_correspondences(X_a, X_b, 1, "calibration")
    scale = calibration_scale(apply_transform(T_a, X_a_c), apply_transform(T_b, X_b_c), K_a, K_b)
    link = calibration_link(K_a, K_b, scale)
    H = normalize_sl4(se3_inverse(T_a) @ link @ T_b)
    _, inliers, r2 = score_one(H, X_a_c, X_b_c, inlier_threshold)
    return make_alignment(H, X_a_c, X_b_c, finite, inliers, r2, "calibration",
                          extras={"scale": scale, "link": link})
