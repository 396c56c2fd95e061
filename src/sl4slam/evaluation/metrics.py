"""Evaluation metrics, each a plain function: trajectory error and dense-map accuracy / completion.

- :func:`ate` (re-exported from :mod:`sl4slam.metrics`): keyframe ATE RMSE after evo's Umeyama
  Sim(3) alignment, the number ``evo_ape tum GT EST -as`` prints as ``rmse``.
- :func:`ground_truth_points`: a depth map's valid points in the world frame (the dense
  ground truth of 7-Scenes: depth 0 / 65535 and beyond 4.5 m dropped).
- :func:`accuracy_completion`: RMSE of estimate-to-truth (accuracy) and truth-to-estimate
  (completion) nearest-neighbour distances, each clipped at ``max_error``.
- :func:`icp_refine`: point-to-point ICP on voxel-downsampled copies (Open3D).
- :func:`dense_metrics`: the whole dense protocol of VGGT-SLAM's and MASt3R-SLAM's 7-Scenes
  evaluation: trajectory Sim(3) on the estimate, ICP refinement, then accuracy / completion /
  chamfer (their mean).

Distances are in the ground truth's units (metres). Open3D is an optional dependency
(``pip install "sl4slam[eval]"``); only :func:`icp_refine` needs it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..errors import UserError
from ..geometry import se3_inverse, unproject_depth
from ..metrics import ATEResult, ate

DENSE_MAX_DEPTH = 4.5
"""Metres; ground-truth depth beyond this is dropped (Kinect range; reference evaluation)."""
DENSE_MAX_ERROR = 0.5
"""Metres; nearest-neighbour distances are clipped here (reference evaluation)."""
ICP_VOXEL_SIZE = 0.05
"""Metres; voxel size of the copies ICP runs on (reference evaluation)."""
ICP_MAX_CORRESPONDENCE = 0.1
"""Metres; ICP's maximum correspondence distance (reference evaluation)."""

__all__ = [
    "ate",
    "ATEResult",
    "DenseResult",
    "ground_truth_points",
    "resize_depth",
    "nearest_distances",
    "accuracy_completion",
    "icp_refine",
    "dense_metrics",
    "require_open3d",
]


@dataclass
class DenseResult:
    """Dense-map quality of an estimated point cloud against the ground-truth cloud.

    Attributes:
        accuracy: RMSE of clipped estimate-to-truth nearest-neighbour distances (m).
        completion: RMSE of clipped truth-to-estimate nearest-neighbour distances (m).
        chamfer: ``(accuracy + completion) / 2`` (m).
        num_estimate, num_ground_truth: points in each cloud.
        T_gt_est: ``(4, 4)`` the transform applied to the estimate (Sim(3) then ICP).
        icp_fitness: fraction of the downsampled estimate with a correspondence after ICP
            (``None`` without ICP).
    """

    accuracy: float
    completion: float
    chamfer: float
    num_estimate: int
    num_ground_truth: int
    T_gt_est: np.ndarray
    icp_fitness: float | None = None


def require_open3d():
    """The ``open3d`` module, or a UserError that says how to install it."""
    try:
        import open3d
    except ImportError as exc:  # the cause matters: not installed, or installed but failing to load
        raise UserError(
            f"dense metrics need Open3D (ICP), which cannot be imported ({type(exc).__name__}: {exc}): "
            "pip install \"sl4slam[eval]\", or skip them with --no-dense") from None
    return open3d


def resize_depth(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """``(H, W)`` depth resampled to ``(height, width)`` by nearest neighbour (never mixes depths)."""
    depth = np.asarray(depth, np.float32)
    if depth.shape == (height, width):
        return depth
    return cv2.resize(depth, (int(width), int(height)), interpolation=cv2.INTER_NEAREST)


def ground_truth_points(
    depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, max_depth: float = DENSE_MAX_DEPTH
) -> tuple[np.ndarray, np.ndarray]:
    """World points of a depth map's valid pixels.

    Args:
        depth: ``(H, W)`` metres along the optical axis, 0 = no measurement.
        K: ``(3, 3)`` intrinsics at this resolution.
        T_world_cam: ``(4, 4)`` camera-to-world pose.
        max_depth: depths above this are dropped (kept when equal, as the reference does).

    Returns:
        points: ``(N, 3)`` float64 world points of the valid pixels, row-major pixel order.
        valid: ``(H, W)`` bool, the pixels kept.
    """
    depth = np.asarray(depth, np.float32)
    valid = np.isfinite(depth) & (depth > 0) & (depth <= max_depth)
    T_cam_world = se3_inverse(np.asarray(T_world_cam, np.float64)[None])
    X = unproject_depth(np.where(valid, depth, 0.0)[None], np.asarray(K, np.float64)[None], T_cam_world)[0]
    return X[valid].astype(np.float64), valid


def nearest_distances(query: np.ndarray, reference: np.ndarray, workers: int = 1,
                      max_distance: float = np.inf) -> np.ndarray:
    """``(N,)`` distance from each ``query`` point ``(N, 3)`` to its nearest ``reference`` point ``(M, 3)``.

    With a finite ``max_distance`` the distances are clipped there; the search then stops at
    that radius, which is what keeps far-off points (a misaligned estimate) cheap.
    """
    reference = np.asarray(reference, np.float64)
    query = np.asarray(query, np.float64)
    if len(reference) == 0 or len(query) == 0:
        raise UserError(f"nearest-neighbour distances need two non-empty clouds, got {len(query)} and {len(reference)} points")
    distances, _ = cKDTree(reference).query(query, k=1, workers=workers, distance_upper_bound=max_distance)
    return np.minimum(distances, max_distance)


def accuracy_completion(
    estimate: np.ndarray, ground_truth: np.ndarray, max_error: float = DENSE_MAX_ERROR, workers: int = 1
) -> tuple[float, float]:
    """``(accuracy, completion)``: RMSE of the clipped nearest-neighbour distances, both ways.

    Accuracy takes every estimated point's distance to the ground truth, completion every
    ground-truth point's distance to the estimate; each distance is clipped at ``max_error``
    before the RMSE (so a far outlier costs at most ``max_error``).

    Args:
        estimate: ``(N, 3)`` estimated points, already in the ground truth's frame.
        ground_truth: ``(M, 3)`` ground-truth points.
    """
    to_truth = nearest_distances(estimate, ground_truth, workers, max_error)
    to_estimate = nearest_distances(ground_truth, estimate, workers, max_error)
    return float(np.sqrt(np.mean(to_truth**2))), float(np.sqrt(np.mean(to_estimate**2)))


def _cloud(points: np.ndarray, voxel_size: float):
    o3d = require_open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    return cloud.voxel_down_sample(voxel_size) if voxel_size > 0 else cloud


def icp_refine(
    estimate: np.ndarray,
    ground_truth: np.ndarray,
    voxel_size: float = ICP_VOXEL_SIZE,
    max_correspondence: float = ICP_MAX_CORRESPONDENCE,
) -> tuple[np.ndarray, float]:
    """Rigid ``T_gt_est`` (4, 4) from point-to-point ICP (Open3D), started at the identity.

    Both clouds are voxel-downsampled (``voxel_size``; 0 = not downsampled) for the ICP only;
    apply the result to the full estimate. Returns the transform and ICP's fitness (fraction of
    downsampled estimate points with a correspondence within ``max_correspondence``).
    """
    o3d = require_open3d()
    source = _cloud(estimate, voxel_size)
    target = _cloud(ground_truth, voxel_size)
    result = o3d.pipelines.registration.registration_icp(
        source, target, max_correspondence, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
    )
    return np.asarray(result.transformation, np.float64).copy(), float(result.fitness)


def dense_metrics(
    estimate: np.ndarray,
    ground_truth: np.ndarray,
    T_gt_est: np.ndarray | None = None,
    icp: bool = True,
    voxel_size: float = ICP_VOXEL_SIZE,
    max_correspondence: float = ICP_MAX_CORRESPONDENCE,
    max_error: float = DENSE_MAX_ERROR,
    workers: int = 1,
) -> DenseResult:
    """Accuracy, completion and chamfer of an estimated cloud, after alignment.

    The protocol of VGGT-SLAM's and MASt3R-SLAM's 7-Scenes evaluation: the trajectory's Sim(3)
    alignment ``T_gt_est`` (from :func:`ate`) maps the estimate into the ground truth's frame,
    point-to-point ICP on 5 cm voxels with 10 cm maximum correspondence refines it, and the
    clipped nearest-neighbour RMSEs are taken on the full clouds.

    Args:
        estimate: ``(N, 3)`` estimated points in the estimate's world frame.
        ground_truth: ``(M, 3)`` ground-truth points (metres).
        T_gt_est: ``(4, 4)`` similarity applied first (``None``: identity).
        icp: refine with ICP.
    """
    estimate = np.asarray(estimate, np.float64).reshape(-1, 3)
    ground_truth = np.asarray(ground_truth, np.float64).reshape(-1, 3)
    T = np.eye(4) if T_gt_est is None else np.asarray(T_gt_est, np.float64)
    aligned = estimate @ T[:3, :3].T + T[:3, 3]
    fitness = None
    if icp:
        T_icp, fitness = icp_refine(aligned, ground_truth, voxel_size, max_correspondence)
        aligned = aligned @ T_icp[:3, :3].T + T_icp[:3, 3]
        T = T_icp @ T
    accuracy, completion = accuracy_completion(aligned, ground_truth, max_error, workers)
    return DenseResult(
        accuracy=accuracy, completion=completion, chamfer=0.5 * (accuracy + completion),
        num_estimate=len(estimate), num_ground_truth=len(ground_truth), T_gt_est=T, icp_fitness=fitness,
    )
