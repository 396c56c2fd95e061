"""Synthetic point correspondences of one camera frame, for testing and benchmarking alignment.

They look like the real case: a frame's confident pixels on a smooth non-planar surface at depth
0.5-3 units, a projective map near the identity between two submaps, depth noise, and outliers in
image-space blobs that are shifted coherently (a model's errors are locally consistent).
"""

from __future__ import annotations

import numpy as np

from ..geometry import apply_transform, normalize_sl4


def random_rotation(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    """Random rotation ``(3, 3)`` with angle below ``max_angle`` radians (Rodrigues)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(-max_angle, max_angle)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def near_identity_sl4(rng: np.random.Generator) -> np.ndarray:
    """An SL(4) map like the projective ambiguity between two submaps: rotation, scale, shear,
    translation and a perspective row with entries of magnitude 0.05-0.2."""
    while True:
        H = np.eye(4)
        H[:3, :3] = rng.uniform(0.7, 1.4) * random_rotation(rng, 0.3) @ (np.eye(3) + rng.uniform(-0.1, 0.1, (3, 3)))
        H[:3, 3] = rng.uniform(-0.3, 0.3, 3)
        H[3, :3] = rng.choice([-1.0, 1.0], 3) * rng.uniform(0.05, 0.2, 3)
        if np.linalg.det(H) > 0:
            return normalize_sl4(H)


def frame_correspondences(
    rng: np.random.Generator,
    H_a_b: np.ndarray,
    height: int,
    width: int,
    noise: float = 0.002,
    outlier_fraction: float = 0.0,
    confidence_period_px: tuple[float, float] = (9.0, 6.0),
    outlier_cell_px: int = 10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One camera frame's confident points in submaps ``b`` and ``a``.

    Depth 0.5-3 units on a smooth non-planar surface, a random camera pose in submap ``b``,
    ``X_a = H_a_b X_b`` plus Gaussian noise ``noise``, ~68 % of pixels kept by a blotchy
    confidence mask (blotches of ``confidence_period_px`` along u and v), and outliers in
    image-space blobs covering ``outlier_fraction`` of the kept pixels, shifted by 0.05-0.3 units
    coherently within cells of ``outlier_cell_px``.

    Returns:
        ``X_a (N, 3)``, ``X_b (N, 3)``, ``is_inlier (N,)``.
    """
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    focal = 0.8 * width
    x, y = (u - width / 2) / focal, (v - height / 2) / focal
    depth = 1.7 + 1.6 * y + 0.35 * np.sin(8.2 * u / width + 0.4) * np.cos(5.0 * v / height) + 0.25 * np.cos(9 * x)
    depth = np.clip(depth, 0.5, 3.0)
    X_cam = np.stack([x * depth, y * depth, depth], axis=-1)
    X_b = X_cam @ random_rotation(rng, 0.5).T + rng.uniform(-0.5, 0.5, 3)
    period_u, period_v = confidence_period_px
    confidence = np.sin(u / period_u + rng.uniform(0, 6)) * np.cos(v / period_v + rng.uniform(0, 6))
    confidence += 0.3 * rng.normal(size=u.shape)
    confident = confidence > np.quantile(confidence, 0.32)
    outlier = np.zeros((height, width), dtype=bool)
    while outlier[confident].mean() < outlier_fraction:
        centre = rng.uniform([0, 0], [height, width])
        radius = rng.uniform(0.03, 0.12) * width
        outlier |= (v - centre[0]) ** 2 + (u - centre[1]) ** 2 < radius**2
    X_a = apply_transform(H_a_b, X_b)
    cell = (v // outlier_cell_px * 1000 + u // outlier_cell_px).astype(int)[outlier]
    _, cell_index = np.unique(cell, return_inverse=True)
    shifts = rng.normal(size=(cell_index.max() + 1 if cell.size else 0, 3))
    shifts *= rng.uniform(0.05, 0.3, (len(shifts), 1)) / np.linalg.norm(shifts, axis=1, keepdims=True)
    X_a[outlier] += shifts[cell_index]
    X_a += rng.normal(scale=noise, size=X_a.shape)
    return X_a[confident], X_b[confident], ~outlier[confident]
