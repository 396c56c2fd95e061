"""Result folders for the viewer, export and localization tests: hand-made ones with exactly known
cameras and points, and small real runs of the pipeline on the synthetic world."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sl4slam.geometry import unproject_depth
from sl4slam.io import write_tum_trajectory


def known_cameras(count: int, seed: int = 0) -> np.ndarray:
    """``(count, 4, 4)`` world-from-camera poses on an arc, each looking roughly at the origin."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i in range(count):
        angle = 0.6 * i / max(1, count - 1)
        R = Rotation.from_euler("yxz", [angle, 0.1 * rng.standard_normal(), 0.05 * rng.standard_normal()]).as_matrix()
        poses[i, :3, :3] = R
        poses[i, :3, 3] = -R @ np.array([0.0, 0.0, 3.0]) + 0.1 * rng.standard_normal(3)
    return poses


def write_known_result(folder: Path, count: int = 6, width: int = 48, height: int = 36, skew: float = 0.0,
                       submap_size: int = 3, version: int = 1, confidence: bool = False, keyframes: bool = True,
                       seed: int = 0, loops: list | None = None) -> dict:
    """A result folder whose cameras and points are exactly known; returns the truth.

    Each keyframe sees a depth map of 2-4 m through ``K`` (``skew`` in K[0, 1]); its world points
    are exact unprojections, so they project back onto their pixels.
    """
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    T = known_cameras(count, seed)
    K = np.array([[40.0, skew, (width - 1) / 2 + 0.7], [0.0, 42.0, (height - 1) / 2 - 0.4], [0.0, 0.0, 1.0]])
    frame_indices = np.arange(count) * 3
    timestamps = frame_indices / 30.0
    truth = {"T_world_cam": T, "K": K, "frame_indices": frame_indices, "points": {}, "masks": {}}
    if keyframes:
        (folder / "keyframes").mkdir(exist_ok=True)
    for i in range(count):
        depth = rng.uniform(2.0, 4.0, (1, height, width))
        T_cam_world = np.linalg.inv(T[i])
        points = unproject_depth(depth, K[None], T_cam_world[None])[0]
        mask = rng.random((height, width)) > 0.2
        points[~mask] = 0.0
        v, u = np.mgrid[0:height, 0:width]
        colors = np.stack([128 + 100 * np.sin(u / 7.0 + i), 128 + 100 * np.cos(v / 5.0 - i), 128 + 60 * np.sin((u + v) / 11.0)],
                          axis=-1).astype(np.uint8)  # smooth, like a photograph (and as costly to encode)
        truth["points"][int(frame_indices[i])], truth["masks"][int(frame_indices[i])] = points, mask
        if keyframes:
            extra = {"confidence": rng.uniform(1, 10, (height, width)).astype(np.float16)} if confidence else {}
            np.savez(folder / "keyframes" / f"{frame_indices[i]:06d}.npz", points_world=points, mask=mask, colors=colors,
                     K=K, T_world_cam=T[i], timestamp=timestamps[i], submap_id=i // submap_size, **extra)
    write_tum_trajectory(folder / "trajectory.txt", timestamps, T)
    summary = {"counts": {"frames": int(frame_indices[-1] + 1), "keyframes": count,
                          "submaps": int((count - 1) // submap_size + 1), "loops": len(loops or []), "fallbacks": 0},
               "loops": loops or [], "source": "known"}
    if version >= 2:
        summary["format"] = {"name": "sl4slam-result", "version": version}
        summary["edges"] = [{"kind": "loop", "query_frame": None, **loop} for loop in (loops or [])]
        write_tum_trajectory(folder / "trajectory_gt.txt", timestamps, T)
    (folder / "summary.json").write_text(json.dumps(summary))
    return truth


def run_small_world(root: Path, frames: int = 120, perspective: float = 0.1, retrieval: str = "none") -> Path:
    """A real result folder: the pipeline with the simulated frontend on a small synthetic world."""
    from sl4slam.runner import run_slam
    from sl4slam.synthetic import write_synthetic_sequence

    world = write_synthetic_sequence(root / "world", num_frames=frames, width=96, height=72, seed=0)
    config = small_world_config(perspective, retrieval)
    run_slam(world, root / "result", config, progress=False)
    return root / "result"


def small_world_config(perspective: float = 0.1, retrieval: str = "none"):
    from sl4slam.config import SLAMConfig

    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 7.5  # px at 96 px wide: 75 keyframes of 120 frames, 10 submaps of 8
    config.submap.size = 8
    config.retrieval.kind = retrieval
    config.sim.perspective = perspective
    return config
