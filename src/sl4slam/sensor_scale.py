"""Metric scale from a depth sensor (``--metric-depth sensor``): each submap scaled to metres.

A feed-forward model's submaps come in units of its own (VGGT normalizes each window), and a
monocular map is defined up to one scale. An RGB-D source (TUM, 7-Scenes, a RealSense-style
camera) measures depth in metres: the median ratio of the sensor's depth to the model's, over the
submap's confident pixels where the sensor has a valid (positive, finite) depth, scales the submap
(its depth, its points and its cameras' translations together), so the links between submaps carry
a scale of about 1 and the trajectory and the map come out in metres. The median keeps the ratio
robust to flying pixels and to the sensor's holes at depth edges.

A submap with fewer than ``min_pixels`` such pixels (no sensor depth on its frames) keeps the scale
of the submap before it; the summary counts them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .types import Frame, SubmapPrediction

MIN_PIXELS = 500
"""Fewest confident pixels with a valid sensor depth that give a submap its own scale (our choice:
a few hundred pixels make the median's standard error a fraction of a percent)."""


def sensor_scale(frames: list[Frame], prediction: SubmapPrediction, mask: np.ndarray,
                 min_pixels: int = MIN_PIXELS) -> tuple[float | None, int]:
    """The median of sensor depth over model depth, and how many pixels voted (``None`` when fewer
    than ``min_pixels``).

    Args:
        frames: the submap's input frames (``Frame.depth`` in metres, 0 where invalid, or ``None``).
        prediction: the frontend's prediction (depth on its grid, ``image_to_grid``).
        mask: ``(S, H, W)`` the confident pixels.
    """
    ratios = []
    S, H, W = prediction.depth.shape
    rows, cols = np.mgrid[0:H, 0:W]
    grid = np.stack([cols.ravel(), rows.ravel(), np.ones(H * W)]).astype(np.float64)  # (3, HW)
    for s, frame in enumerate(frames):
        if frame.depth is None:
            continue
        sensor = np.asarray(frame.depth, np.float32)
        A = np.eye(3) if prediction.image_to_grid is None else np.asarray(prediction.image_to_grid[s], np.float64)
        u, v = (np.linalg.inv(A) @ grid)[:2].round().astype(np.int64)  # nearest input pixel of each grid pixel
        inside = (u >= 0) & (u < sensor.shape[1]) & (v >= 0) & (v < sensor.shape[0])
        measured = np.zeros(H * W, np.float32)
        measured[inside] = sensor[v[inside], u[inside]]
        model = prediction.depth[s].ravel()
        valid = mask[s].ravel() & (measured > 0) & np.isfinite(measured) & (model > 0) & np.isfinite(model)
        ratios.append(measured[valid] / model[valid])
    votes = np.concatenate(ratios) if ratios else np.zeros(0, np.float32)
    if len(votes) < min_pixels:
        return None, int(len(votes))
    return float(np.median(votes)), int(len(votes))


def scaled(prediction: SubmapPrediction, scale: float) -> SubmapPrediction:
    """``prediction`` in units ``scale`` times its own: depth, points and camera translations."""
    T = np.array(prediction.T_cam_submap, dtype=np.float64, copy=True)
    T[:, :3, 3] *= scale
    return dataclasses.replace(
        prediction, depth=(prediction.depth * scale).astype(np.float32), T_cam_submap=T,
        points=None if prediction.points is None else (prediction.points * scale).astype(np.float32))
