"""Trajectory metrics through evo (the community's reference implementation).

``ate`` is the number ``evo_ape tum GT EST -as`` prints as ``rmse``: absolute translation error
after a Umeyama Sim(3) alignment of the estimate onto the ground truth.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from .errors import UserError


@dataclass
class ATEResult:
    """Absolute trajectory error after alignment.

    Attributes:
        rmse, mean, median, max: translation error statistics (ground-truth units).
        num_poses: associated pose pairs.
        scale: Sim(3) scale applied to the estimate.
        T_gt_est: ``(4, 4)`` the alignment (``[sR t; 0 1]``).
        positions_aligned: ``(N, 3)`` aligned estimate positions; positions_gt: ``(N, 3)``.
    """

    rmse: float
    mean: float
    median: float
    max: float
    num_poses: int
    scale: float
    T_gt_est: np.ndarray
    positions_aligned: np.ndarray
    positions_gt: np.ndarray


def _trajectory(timestamps: np.ndarray, T_world_cam: np.ndarray):
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(timestamps=np.asarray(timestamps, dtype=np.float64), poses_se3=list(np.asarray(T_world_cam, dtype=np.float64)))


def ate(
    timestamps_est: np.ndarray,
    T_world_cam_est: np.ndarray,
    timestamps_gt: np.ndarray,
    T_world_cam_gt: np.ndarray,
    max_time_diff: float = 0.01,
    correct_scale: bool = True,
) -> ATEResult:
    """ATE of an estimated trajectory against ground truth (evo: associate, align, APE translation).

    Args:
        timestamps_est, timestamps_gt: ``(N,)`` and ``(M,)`` seconds.
        T_world_cam_est, T_world_cam_gt: ``(N, 4, 4)``, ``(M, 4, 4)`` poses; rotations must be proper.
        max_time_diff: association tolerance in seconds (evo's default 0.01).
        correct_scale: Sim(3) alignment (``-as``) when true, SE(3) (``-a``) otherwise.
    """
    from evo.core import metrics, sync

    if len(timestamps_est) < 3:
        raise UserError(f"ATE needs at least 3 estimated poses, got {len(timestamps_est)}")
    gt = _trajectory(timestamps_gt, T_world_cam_gt)
    est = _trajectory(timestamps_est, T_world_cam_est)
    try:
        gt, est = sync.associate_trajectories(gt, est, max_diff=max_time_diff)
    except Exception as exc:  # evo raises its own SyncException
        raise UserError(f"cannot associate estimate with ground truth by timestamp: {exc}") from None
    est_aligned = copy.deepcopy(est)
    rotation, translation, scale = est_aligned.align(gt, correct_scale=correct_scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((gt, est_aligned))
    stats = ape.get_all_statistics()
    T = np.eye(4)
    T[:3, :3] = scale * rotation
    T[:3, 3] = translation
    return ATEResult(
        rmse=float(stats["rmse"]), mean=float(stats["mean"]), median=float(stats["median"]), max=float(stats["max"]),
        num_poses=int(gt.num_poses), scale=float(scale), T_gt_est=T,
        positions_aligned=est_aligned.positions_xyz.copy(), positions_gt=gt.positions_xyz.copy(),
    )
