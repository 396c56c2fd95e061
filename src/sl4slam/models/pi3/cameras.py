"""From π³ / Pi3X outputs to what the SLAM frontend returns (pure numpy functions).

π³ predicts per frame a point map in the frame's own camera (``local_points``, OpenCV axes), a
confidence logit per pixel and a camera-to-world pose in a frame of its choosing; it predicts no
intrinsics. The frontend needs, on the model's grid (the project's pixel convention: pixel
``(u, v)`` has its centre at integer ``(u, v)``):

- depth ``(S, H, W)``: the z of the local points (:func:`depth_from_local_points`);
- confidence ``(S, H, W)`` >= 1: ``1 + exp(logit)`` (:func:`confidence_from_logits`), the activation
  VGGT's confidence has. It equals ``1 / (1 - sigmoid(logit))``, so it orders pixels as the
  authors' ``sigmoid(conf)`` does (their mask ``sigmoid > 0.1`` is confidence > 1.11);
- ``T_cam_submap`` ``(S, 3, 4)``: camera-from-first-camera extrinsics
  (:func:`extrinsics_from_poses`);
- ``K`` ``(S, 3, 3)``: a pinhole camera per frame recovered from its local points
  (:func:`intrinsics_from_local_points`), principal point at the grid centre.

Pi3X's ``rays`` output is the direction of its local points, so the same recovery serves both
models (it is what the authors' ``recover_intrinsic_from_rays_d`` does with a centred principal
point); Pi3X predicts no K either.
"""

from __future__ import annotations

import numpy as np

MAX_LOGIT = 80.0
"""Logits are capped here before ``exp`` (``1 + e^80`` ~ 5.5e34 fits float32)."""
MIN_DEPTH = 1e-6
"""Points closer than this (or behind the camera) do not enter the focal fit."""


def depth_from_local_points(local_points: np.ndarray) -> np.ndarray:
    """``(S, H, W, 3)`` camera-frame points -> ``(S, H, W)`` float32 depth (their z)."""
    return np.ascontiguousarray(np.asarray(local_points)[..., 2], dtype=np.float32)


def confidence_from_logits(logits: np.ndarray) -> np.ndarray:
    """``1 + exp(min(logit, 80))`` as float32, >= 1 (see the module docstring)."""
    logits = np.minimum(np.asarray(logits, dtype=np.float64), MAX_LOGIT)
    return (1.0 + np.exp(logits)).astype(np.float32)


def probability_from_logits(logits: np.ndarray) -> np.ndarray:
    """``sigmoid(logit)`` in float64 (the authors' reading of the confidence)."""
    logits = np.asarray(logits, dtype=np.float64)
    return 0.5 * (1.0 + np.tanh(0.5 * logits))


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` rigid transforms -> their inverses ``[R^T | -R^T t]`` (float64)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros(T.shape, dtype=np.float64)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R_t, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def extrinsics_from_poses(camera_to_world: np.ndarray) -> np.ndarray:
    """``(S, 4, 4)`` camera-to-world poses in any shared frame -> ``(S, 3, 4)`` float64
    ``T_cam_submap`` = ``T_cam_i_world @ T_world_cam_0``: the submap frame is the first camera's,
    so ``T_cam_submap[0]`` is ``[I | 0]`` (exactly, up to rounding). Translations keep the model's
    units (Pi3X's are approximately metric)."""
    poses = np.asarray(camera_to_world, dtype=np.float64)
    return (invert_rigid(poses) @ poses[0])[:, :3, :]


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)``, each ``(H, W)`` float64: the column and row of every pixel centre."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return u, v


def grid_centre(height: int, width: int) -> np.ndarray:
    """``(2,)`` the centre of an H x W grid, ``((W - 1) / 2, (H - 1) / 2)`` in the project's pixels."""
    return np.array([(width - 1) / 2.0, (height - 1) / 2.0])


def focal_from_local_points(local_points: np.ndarray, principal_point: np.ndarray,
                            weights: np.ndarray | None = None) -> tuple[float, float]:
    """``(f_x, f_y)`` of one frame by weighted least squares on its pixels' reprojection.

    A pixel ``(u, v)`` with local point ``(x, y, z)`` should satisfy ``u - c_x = f_x x / z`` and
    ``v - c_y = f_y y / z``; minimising ``sum w (u - c_x - f_x x/z)^2`` gives
    ``f_x = sum w (x/z)(u - c_x) / sum w (x/z)^2`` (and f_y alike): the reprojection error in
    pixels, with the principal point held at ``principal_point``.

    How exact: for noise-free points of a pinhole camera with that principal point the result is
    exact (to rounding), whatever the weights. Otherwise it is the best pinhole fit: points that
    do not lie on the rays of any pinhole (lens distortion, a principal point elsewhere, which
    leaks into f through the pixels' spread) bias it, and noise in the predicted ray directions
    ``x/z`` shrinks it (errors in the regressor: ``f * var(x/z) / (var(x/z) + var(noise))``),
    least near the image borders, which carry the most weight. Pixels with non-finite points or
    ``z <= MIN_DEPTH`` are left out; ``weights`` (e.g. the confidence probability) scale each
    pixel's squared error.

    Args:
        local_points: ``(H, W, 3)`` points in the camera frame.
        principal_point: ``(2,)`` ``(c_x, c_y)`` in pixels.
        weights: optional ``(H, W)`` non-negative weights.

    Raises:
        ValueError: no usable pixel, or the points give no ray spread along an axis.
    """
    points = np.asarray(local_points, dtype=np.float64)
    height, width = points.shape[:2]
    u, v = pixel_grid(height, width)
    z = points[..., 2]
    usable = np.isfinite(points).all(axis=-1) & (z > MIN_DEPTH)
    w = np.ones((height, width)) if weights is None else np.asarray(weights, dtype=np.float64)
    usable &= np.isfinite(w) & (w > 0)
    if not usable.any():
        raise ValueError("no pixel has a finite point in front of the camera: the focal length is undefined")
    w = w[usable]
    x_over_z = points[..., 0][usable] / z[usable]
    y_over_z = points[..., 1][usable] / z[usable]
    cx, cy = float(principal_point[0]), float(principal_point[1])
    denominators = (np.sum(w * x_over_z**2), np.sum(w * y_over_z**2))
    if min(denominators) <= 0:
        raise ValueError("the points have no spread of ray directions: the focal length is undefined")
    fx = np.sum(w * x_over_z * (u[usable] - cx)) / denominators[0]
    fy = np.sum(w * y_over_z * (v[usable] - cy)) / denominators[1]
    return float(fx), float(fy)


def intrinsics_from_local_points(local_points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """``(S, H, W, 3)`` local points -> ``(S, 3, 3)`` float64 pinhole ``K`` per frame: principal point at
    the grid centre (:func:`grid_centre`), focal lengths by :func:`focal_from_local_points`
    with per-pixel ``weights`` ``(S, H, W)`` (optional)."""
    points = np.asarray(local_points)
    frames, height, width = points.shape[:3]
    centre = grid_centre(height, width)
    K = np.tile(np.eye(3), (frames, 1, 1))
    for i in range(frames):
        fx, fy = focal_from_local_points(points[i], centre, None if weights is None else weights[i])
        K[i, 0, 0], K[i, 1, 1] = fx, fy
        K[i, :2, 2] = centre
    return K


def to_model_intrinsics(K: np.ndarray) -> np.ndarray:
    """Intrinsics in the project's convention (pixel centres at integers) -> the authors' convention
    (pixel ``(u, v)`` centred at ``(u + 0.5, v + 0.5)``): ``c_x`` and ``c_y`` + 0.5. ``(..., 3, 3)``."""
    K = np.array(K, dtype=np.float64, copy=True)
    K[..., 0, 2] += 0.5 * K[..., 2, 2]
    K[..., 1, 2] += 0.5 * K[..., 2, 2]
    return K
