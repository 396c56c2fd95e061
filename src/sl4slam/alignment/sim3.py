"""Similarity (Sim(3)) alignment: a batched minimal solver for RANSAC and the shared-frame model.

``T_a_b = [s R  t; 0 1]`` maps points of submap ``b`` into submap ``a``. Two ways to get it:

- from point correspondences (Umeyama's least squares; three non-collinear points is the minimal
  case used inside RANSAC, see :func:`sl4slam.alignment.estimate_sim3`);
- from the shared frame itself (:func:`sim3_from_shared_frame`): the same camera is reconstructed
  in both submaps, so its two extrinsics give the rotation and translation, and the depth ratio of
  its points gives the scale. This is the Sim(3) counterpart of the SL(4) alignment.
"""

from __future__ import annotations

import numpy as np

from ..geometry import apply_transform, se3_inverse, to_4x4
from ..types import Alignment

# Second / first singular value of a centred 3-point sample below which it counts as collinear.
COLLINEAR_TOLERANCE = 1e-6


def umeyama_sim3_batch(X_dst: np.ndarray, X_src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Umeyama similarity ``T_dst_src`` for a batch of small samples.

    Args:
        X_dst: ``(M, k, 3)`` points in the target frame.
        X_src: ``(M, k, 3)`` corresponding points in the source frame (k >= 3).

    Returns:
        T: ``(M, 4, 4)`` similarities with ``X_dst ~ s R X_src + t``.
        valid: ``(M,)`` bool, False for (near-)collinear or repeated source points.
    """
    X_dst = np.asarray(X_dst, dtype=np.float64)
    X_src = np.asarray(X_src, dtype=np.float64)
    k = X_src.shape[1]
    mu_src = X_src.mean(axis=1)
    mu_dst = X_dst.mean(axis=1)
    src = X_src - mu_src[:, None]
    dst = X_dst - mu_dst[:, None]
    cov = np.einsum("mki,mkj->mij", dst, src) / k  # (M, 3, 3)
    U, sing, Vt = np.linalg.svd(cov)
    reflect = np.linalg.det(U) * np.linalg.det(Vt) < 0
    D = np.ones((len(cov), 3))
    D[reflect, 2] = -1.0
    R = (U * D[:, None, :]) @ Vt
    var_src = (src**2).sum(axis=(1, 2)) / k
    src_sing = np.linalg.svd(src, compute_uv=False)  # (M, 3) spread of the source sample
    valid = (var_src > 0) & (src_sing[:, 1] > COLLINEAR_TOLERANCE * src_sing[:, 0])
    scale = np.where(valid, (sing * D).sum(axis=1) / np.where(var_src > 0, var_src, 1.0), 1.0)
    valid &= scale > 0
    T = np.zeros((len(cov), 4, 4))
    T[:, :3, :3] = scale[:, None, None] * R
    T[:, :3, 3] = mu_dst - np.einsum("mij,mj->mi", T[:, :3, :3], mu_src)
    T[:, 3, 3] = 1.0
    return T, valid


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
        X_a: ``(N, 3)`` the frame's points in submap ``a``.
        X_b: ``(N, 3)`` the same pixels' points in submap ``b``.
        inlier_threshold: distance in ``X_a`` units used for the inlier mask and RMS.

    Returns:
        ``Alignment`` with ``model="sim3"``, ``H = T_a_b`` and ``extras["scale"] = s``.

    Raises:
        ValueError: no finite point pair with positive distances.
    """
    X_a = np.asarray(X_a, dtype=np.float64)
    X_b = np.asarray(X_b, dtype=np.float64)
    if X_a.shape != X_b.shape or X_a.ndim != 2 or X_a.shape[1] != 3:
        raise ValueError(f"need two (N, 3) point arrays of equal shape, got {X_a.shape} and {X_b.shape}")
    T_cam_a = to_4x4(T_cam_a)
    T_cam_b = to_4x4(T_cam_b)
    finite = np.isfinite(X_a).all(axis=1) & np.isfinite(X_b).all(axis=1)
    dist_a = np.linalg.norm(apply_transform(T_cam_a, X_a[finite]), axis=1)
    dist_b = np.linalg.norm(apply_transform(T_cam_b, X_b[finite]), axis=1)
    usable = (dist_a > 0) & (dist_b > 0)
    if not usable.any():
        raise ValueError("shared frame has no finite points with positive depth in both submaps; cannot estimate scale")
    scale = float(np.median(dist_a[usable] / dist_b[usable]))
    S = np.diag([scale, scale, scale, 1.0])
    T_a_b = se3_inverse(T_cam_a) @ S @ T_cam_b
    inliers = np.zeros(len(X_a), dtype=bool)
    residual = np.linalg.norm(apply_transform(T_a_b, X_b[finite]) - X_a[finite], axis=1)
    inliers[np.flatnonzero(finite)] = residual < inlier_threshold
    # RMS over the inliers; over all finite points when there is none (the ratio 0 tells why).
    rms_over = residual[inliers[finite]] if inliers.any() else residual
    rms = float(np.sqrt(np.mean(rms_over**2))) if len(rms_over) else 0.0
    return Alignment(
        H=T_a_b,
        inliers=inliers,
        inlier_ratio=float(inliers.mean()) if len(inliers) else 0.0,
        rms=rms,
        model="sim3",
        fallback=None,
        extras={"scale": scale, "method": "shared_frame"},
    )
