"""Similarity (Sim(3)) alignment from the shared frame's two cameras.

``T_a_b = [s R  t; 0 1]`` maps points of submap ``b`` into submap ``a``. Two ways to get it:

- from point correspondences (Umeyama's least squares in RANSAC, three non-collinear points being
  the minimal case: :func:`sl4slam.alignment.estimate_sim3`);
- from the shared frame itself (:func:`sim3_from_shared_frame`, here): the same camera is
  reconstructed in both submaps, so its two extrinsics give the rotation and translation, and the
  depth ratio of its points gives the scale. This is the Sim(3) counterpart of the SL(4)
  alignment, and it needs no point fit, so it also serves as the weaker edge when a fit fails.
"""

from __future__ import annotations

import numpy as np

from ..geometry import apply_transform, se3_inverse, to_4x4
from ..types import Alignment
from .common import clean_correspondences, make_alignment


def calibration_scale_link(
    K_a: np.ndarray,
    T_cam_a: np.ndarray,
    K_b: np.ndarray,
    T_cam_b: np.ndarray,
    X_a: np.ndarray,
    X_b: np.ndarray,
    inlier_threshold: float = 0.01,
) -> Alignment:
    """``H_a_b`` from one frame's two cameras: only calibration and scale, no free projective terms.

    The same pixel ``u`` is ``X_cam_a = z_a K_a^-1 u`` in submap ``a`` and ``X_cam_b = z_b K_b^-1 u``
    in ``b``; with ``z_a = s z_b`` (``s`` the median depth ratio of the frame's points),
    ``X_cam_a = s K_a^-1 K_b X_cam_b``, so

        H_a_b = T_a_cam [[s K_a^-1 K_b, 0], [0, 1]] T_cam_b,

    VGGT-SLAM 2.0's link between the two nodes of a shared frame (``K_prev^-1 K_cur diag(s,s,s,1)``),
    here as a submap-to-submap measurement. It satisfies the camera constraint ``P_a H ~ P_b``
    exactly and reads nothing from the points but their depth ratio, so a warped or planar frame
    cannot bend it; it cannot express a relative projective distortion. With ``K_a = K_b`` it is the
    shared-frame similarity of :func:`sim3_from_shared_frame`.

    Args:
        K_a, T_cam_a: ``(3, 3)`` intrinsics and ``(3|4, 4)`` extrinsic of the frame in submap ``a``.
        K_b, T_cam_b: the same in submap ``b``.
        X_a, X_b: ``(N, 3)`` the frame's points in submaps ``a`` and ``b``; NaN/Inf rows are ignored.
        inlier_threshold: distance in ``X_a`` units used for the inlier mask and RMS.

    Returns:
        ``Alignment`` with ``model="sl4"`` (a 4x4 map, not normalized), ``extras["scale"] = s``.
    """
    A = np.linalg.solve(np.asarray(K_a, dtype=np.float64), np.asarray(K_b, dtype=np.float64))
    return _shared_frame_link(T_cam_a, T_cam_b, X_a, X_b, inlier_threshold, A, "sl4", "calibration_scale")


def sim3_from_shared_frame(
    T_cam_a: np.ndarray,
    T_cam_b: np.ndarray,
    X_a: np.ndarray,
    X_b: np.ndarray,
    inlier_threshold: float = 0.01,
) -> Alignment:
    """Sim(3) ``T_a_b`` from one frame reconstructed in both submaps.

    The shared frame's camera is ``T_cam_a`` (camera-from-submap-a) in submap ``a`` and
    ``T_cam_b`` in submap ``b``. Submap ``b``'s camera-frame points are ``s`` times too small
    (or large), with ``s`` the median of ``|X_cam_a| / |X_cam_b|`` (distances from the camera
    centre), so ``X_a = T_a_cam (s T_cam_b X_b)`` and ``T_a_b = T_a_cam S(s) T_cam_b``.

    Args:
        T_cam_a: ``(3|4, 4)`` extrinsic of the shared frame in submap ``a``.
        T_cam_b: ``(3|4, 4)`` extrinsic of the same frame in submap ``b``.
        X_a: ``(N, 3)`` the frame's points in submap ``a``; NaN/Inf rows are ignored.
        X_b: ``(N, 3)`` the same pixels' points in submap ``b``.
        inlier_threshold: distance in ``X_a`` units used for the inlier mask and RMS.

    Returns:
        ``Alignment`` with ``model="sim3"``, ``H = T_a_b`` and ``extras["scale"] = s``.

    Raises:
        ValueError: no finite point pair with positive distances, or non-finite cameras.
    """
    return _shared_frame_link(T_cam_a, T_cam_b, X_a, X_b, inlier_threshold, np.eye(3), "sim3", "shared_frame")


def _shared_frame_link(T_cam_a: np.ndarray, T_cam_b: np.ndarray, X_a: np.ndarray, X_b: np.ndarray, threshold: float,
                       A: np.ndarray, model: str, method: str) -> Alignment:
    """``T_a_cam [[s A, 0], [0, 1]] T_cam_b`` with ``s`` the median depth ratio (see the callers)."""
    T_cam_a = to_4x4(T_cam_a)
    T_cam_b = to_4x4(T_cam_b)
    if not (np.isfinite(T_cam_a).all() and np.isfinite(T_cam_b).all() and np.isfinite(A).all()):
        raise ValueError("the shared frame's cameras are not finite")
    X_a_c, X_b_c, finite = clean_correspondences(X_a, X_b, 1, "shared-frame")
    z_a = apply_transform(T_cam_a, X_a_c)[:, 2]
    z_b = apply_transform(T_cam_b, X_b_c)[:, 2]
    usable = (z_a > 0) & (z_b > 0)
    if not usable.any():
        raise ValueError("shared frame has no finite points with positive depth in both submaps; cannot estimate scale")
    scale = float(np.median(z_a[usable] / z_b[usable]))
    link = np.eye(4)
    link[:3, :3] = scale * A
    H_a_b = se3_inverse(T_cam_a) @ link @ T_cam_b
    r2 = ((apply_transform(H_a_b, X_b_c) - X_a_c) ** 2).sum(axis=1)
    inliers = r2 < threshold**2
    return make_alignment(H_a_b, X_a_c, X_b_c, finite, inliers, r2, model, extras={"scale": scale, "method": method},
                          fitted=False)
