"""Dense metrics and the ground-truth cloud of the 7-Scenes protocol, against exact cases."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.io import write_tum_trajectory
from sl4slam.config import SLAMConfig
from sl4slam.errors import UserError
from sl4slam.evaluation import get_dataset
from sl4slam.evaluation.datasets import Sequence
from sl4slam.evaluation.metrics import (
    accuracy_completion,
    dense_metrics,
    ground_truth_points,
    icp_refine,
    nearest_distances,
    resize_depth,
)
from sl4slam.evaluation.protocol import keyframe_clouds
from sl4slam.io import SevenScenesSource
from sl4slam.io.seven_scenes import seven_scenes_intrinsics
from sl4slam.synthetic import make_world, render_frames, write_seven_scenes_sequence
from sl4slam.synthetic.world import _path_from_layout, path_parameters


def _grid(spacing: float = 0.2, n: int = 8) -> np.ndarray:
    """A 3-D lattice of points (n^3), ``spacing`` apart; not planar, so ICP is well posed."""
    axis = np.arange(n) * spacing
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)


def test_identical_clouds_give_zero() -> None:
    cloud = _grid()
    assert accuracy_completion(cloud, cloud) == (0.0, 0.0)
    result = dense_metrics(cloud, cloud)  # with ICP
    assert result.accuracy == pytest.approx(0.0, abs=1e-9)
    assert result.completion == pytest.approx(0.0, abs=1e-9)
    assert result.chamfer == pytest.approx(0.0, abs=1e-9)
    assert result.icp_fitness == pytest.approx(1.0)


def test_known_offset_gives_its_length_and_icp_removes_it() -> None:
    truth = _grid()
    offset = np.array([0.03, -0.02, 0.0])  # shorter than half the lattice spacing: each point's neighbour is its partner
    estimate = truth + offset
    accuracy, completion = accuracy_completion(estimate, truth)
    assert accuracy == pytest.approx(np.linalg.norm(offset), abs=1e-12)
    assert completion == pytest.approx(np.linalg.norm(offset), abs=1e-12)
    without_icp = dense_metrics(estimate, truth, icp=False)
    assert without_icp.chamfer == pytest.approx(np.linalg.norm(offset), abs=1e-12)
    refined = dense_metrics(estimate, truth)
    assert refined.chamfer < 1e-6
    np.testing.assert_allclose(refined.T_gt_est[:3, 3], -offset, atol=1e-6)


def test_trajectory_similarity_is_applied_before_icp() -> None:
    truth = _grid()
    T_gt_est = np.eye(4)
    T_gt_est[:3, :3] = 2.5 * Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()
    T_gt_est[:3, 3] = [1.0, -4.0, 0.5]
    estimate = (truth - T_gt_est[:3, 3]) @ np.linalg.inv(T_gt_est[:3, :3]).T  # truth = T_gt_est * estimate
    result = dense_metrics(estimate, truth, T_gt_est)
    assert result.accuracy < 1e-6 and result.completion < 1e-6
    # without the similarity the clouds do not even overlap: every distance is clipped at 0.5 m
    far = dense_metrics(estimate, truth, icp=False)
    assert far.accuracy > 0.3


def test_distances_are_clipped_at_max_error() -> None:
    truth = _grid()
    far = truth[:10] + np.array([0.0, 0.0, 5.0])  # 10 points 3.6 m or more above the lattice
    estimate = np.concatenate([truth, far])
    accuracy, completion = accuracy_completion(estimate, truth, max_error=0.5)
    assert accuracy == pytest.approx(np.sqrt(10 * 0.5**2 / len(estimate)), rel=1e-12)
    assert completion == 0.0
    # a larger clip lets the true distances through (each far point is 5 m - 1.4 m from the lattice's top)
    accuracy_10, _ = accuracy_completion(estimate, truth, max_error=10.0)
    top = truth[:, 2].max()
    expected = np.sqrt(np.sum((far[:, 2] - top) ** 2) / len(estimate))
    assert accuracy_10 == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(nearest_distances(far, truth, max_distance=0.5), 0.5)


def test_icp_recovers_a_small_rigid_motion() -> None:
    rng = np.random.default_rng(0)
    truth = _grid(0.1, 12) + rng.normal(0, 0.002, (12**3, 3))
    R = Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    estimate = (truth - truth.mean(0)) @ R.T + truth.mean(0) + [0.02, 0.0, -0.01]
    T, fitness = icp_refine(estimate, truth, voxel_size=0.0)
    moved = estimate @ T[:3, :3].T + T[:3, 3]
    assert np.abs(moved - truth).max() < 1e-6
    assert fitness == pytest.approx(1.0)


def test_empty_cloud_is_a_clear_error() -> None:
    with pytest.raises(UserError, match="non-empty"):
        accuracy_completion(np.zeros((0, 3)), _grid())


def test_ground_truth_drops_invalid_and_far_depth_and_uses_scaled_intrinsics(tmp_path) -> None:
    sequence = tmp_path / "chess" / "seq-01"
    sequence.mkdir(parents=True)
    raw = np.full((24, 32), 2000, np.uint16)  # 2 m
    raw[0, 0] = 65535  # invalid in 7-Scenes
    raw[0, 1] = 0  # no measurement
    raw[1, 0] = 4600  # beyond the 4.5 m Kinect range
    raw[1, 1] = 4500  # at the limit: kept, as the reference keeps it
    cv2.imwrite(str(sequence / "frame-000000.color.png"), np.zeros((24, 32, 3), np.uint8))
    cv2.imwrite(str(sequence / "frame-000000.depth.png"), raw)
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    np.savetxt(sequence / "frame-000000.pose.txt", pose)
    frame = SevenScenesSource(sequence).get(0)
    K = seven_scenes_intrinsics(32, 24)
    np.testing.assert_allclose(K, [[29.25, 0, 16], [0, 29.25, 12], [0, 0, 1]])
    points, valid = ground_truth_points(frame.depth, K, frame.T_world_cam)
    assert not valid[0, 0] and not valid[0, 1] and not valid[1, 0] and valid[1, 1]
    assert valid.sum() == 24 * 32 - 3 and len(points) == valid.sum()
    # pixel (u=1, v=1) at 4.5 m: x = (u - cx) z / fx in the camera, then shifted by the pose
    first_row_kept = np.flatnonzero(valid.ravel())
    index = int(np.flatnonzero(first_row_kept == 1 * 32 + 1)[0])
    np.testing.assert_allclose(points[index], [(1 - 16) * 4.5 / 29.25 + 1, (1 - 12) * 4.5 / 29.25 + 2, 4.5 + 3], atol=1e-5)


def test_resize_depth_is_nearest_neighbour() -> None:
    depth = np.arange(48, dtype=np.float32).reshape(6, 8)
    half = resize_depth(depth, 3, 4)
    np.testing.assert_array_equal(half, depth[::2, ::2])  # picks pixels, never averages depths
    assert resize_depth(depth, 6, 8) is not None and np.array_equal(resize_depth(depth, 6, 8), depth)


def _complete_result_folder(run_dir: Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """The rest of a result folder around hand-written keyframe files (the dense evaluation reads
    them through ``sl4slam.result.reading``, as every consumer does)."""
    write_tum_trajectory(run_dir / "trajectory.txt", stamps, poses)
    (run_dir / "summary.json").write_text(json.dumps({"format": {"name": "sl4slam-result", "version": 3}, "edges": [],
                                                      "counts": {"keyframes": len(stamps)}}))


def test_keyframe_clouds_match_a_render_at_the_model_resolution(tmp_path) -> None:
    """A perfect estimate at half the dataset's resolution has zero dense error.

    The dataset is rendered at 64x48 with the published camera scaled to that size; the
    "model" sees 32x24 and its points are an independent render at 32x24 with the camera scaled
    to 32x24. The protocol's ground truth (nearest-resized depth, scaled intrinsics) must give the
    same points, up to the millimetre quantization of the depth files.
    """
    root = tmp_path / "root"
    write_seven_scenes_sequence(root / "chess" / "seq-01", num_frames=12, width=64, height=48, seed=4)
    world = make_world(4)
    poses = _path_from_layout(world.layout, path_parameters(12))
    K_model = seven_scenes_intrinsics(32, 24)
    run_dir = tmp_path / "run"
    (run_dir / "keyframes").mkdir(parents=True)
    for index in (0, 5, 11):
        _, depth = render_frames(world, poses[index : index + 1], K_model, 32, 24)
        points, _ = ground_truth_points(depth[0], K_model, poses[index], max_depth=np.inf)
        mask = np.ones((24, 32), bool)
        mask[:4] = False  # unconfident pixels are left out of the estimate
        np.savez(run_dir / "keyframes" / f"{index:06d}.npz", points_world=points.reshape(24, 32, 3).astype(np.float32),
                 mask=mask, K=K_model, T_world_cam=poses[index], timestamp=index / 30.0, submap_id=0,
                 colors=np.zeros((24, 32, 3), np.uint8))
    _complete_result_folder(run_dir, np.array([0, 5, 11]) / 30.0, poses[[0, 5, 11]])
    dataset = get_dataset("7scenes")
    sequence = Sequence("7scenes", "chess", root / "chess" / "seq-01")
    estimate, truth, used = keyframe_clouds(run_dir, dataset, sequence, SLAMConfig(), max_depth=4.5)
    assert used == 3
    depth_valid = truth.shape[0]
    assert estimate.shape[0] < depth_valid  # masked pixels left out
    accuracy, completion = accuracy_completion(estimate, truth)
    assert accuracy < 2e-3  # mm depth quantization at up to 4.5 m
    # each estimated point has its ground-truth twin at the same pixel
    assert np.median(nearest_distances(estimate, truth)) < 1e-3


def test_keyframe_clouds_refuse_a_run_made_with_other_frames(tmp_path) -> None:
    root = tmp_path / "root"
    sequence = root / "chess" / "seq-01"
    sequence.mkdir(parents=True)
    for k in range(6):
        cv2.imwrite(str(sequence / f"frame-{k:06d}.color.png"), np.full((24, 32, 3), 40 * k, np.uint8))
        cv2.imwrite(str(sequence / f"frame-{k:06d}.depth.png"), np.full((24, 32), 1000, np.uint16))
        np.savetxt(sequence / f"frame-{k:06d}.pose.txt", np.eye(4))
    run_dir = tmp_path / "run"
    (run_dir / "keyframes").mkdir(parents=True)
    np.savez(run_dir / "keyframes" / "000002.npz", points_world=np.zeros((24, 32, 3), np.float32), mask=np.ones((24, 32), bool),
             K=np.eye(3), T_world_cam=np.eye(4), timestamp=4 / 30.0, submap_id=0,
             colors=np.zeros((24, 32, 3), np.uint8))  # frame 2 of a stride-2 run is frame-000004
    _complete_result_folder(run_dir, np.array([4 / 30.0]), np.eye(4)[None])
    with pytest.raises(UserError, match="stride"):
        keyframe_clouds(run_dir, get_dataset("7scenes"), Sequence("7scenes", "chess", root / "chess" / "seq-01"),
                        SLAMConfig(), 4.5)
