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
                       seed: int = 0, loops: list | None = None, scene: str = "noise") -> dict:
    """A result folder whose cameras and points are exactly known; returns the truth.

    ``scene="noise"``: each keyframe sees a depth map of 2-4 m drawn independently per pixel through
    ``K`` (``skew`` in K[0, 1]; focal length about 40 px whatever the width), with colours that are
    a pattern in the image. ``scene="room"``: the keyframes look into a room with a desk
    (:func:`room_view`: the depth of the surfaces each pixel sees, with 0.2 % noise, colours painted
    on the surfaces so that all views agree) through a focal length of 0.8 image widths: the points
    lie on surfaces, as the dense map of a run does. Either way a keyframe's world points are exact
    unprojections of its depth, so they project back onto their pixels.
    """
    if scene not in ("noise", "room"):
        raise ValueError(f"scene must be 'noise' or 'room', got {scene!r}")
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    T = known_cameras(count, seed)
    if scene == "room":
        f = 0.8 * width
        K = np.array([[f, skew, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    else:
        K = np.array([[40.0, skew, (width - 1) / 2 + 0.7], [0.0, 42.0, (height - 1) / 2 - 0.4], [0.0, 0.0, 1.0]])
    frame_indices = np.arange(count) * 3
    timestamps = frame_indices / 30.0
    truth = {"T_world_cam": T, "K": K, "frame_indices": frame_indices, "points": {}, "masks": {}}
    if keyframes:
        (folder / "keyframes").mkdir(exist_ok=True)
    for i in range(count):
        if scene == "room":
            depth, colors = room_view(T[i], K, width, height)
            depth = (depth * (1.0 + 0.002 * rng.standard_normal(depth.shape)))[None]
        else:
            depth = rng.uniform(2.0, 4.0, (1, height, width))
        T_cam_world = np.linalg.inv(T[i])
        points = unproject_depth(depth, K[None], T_cam_world[None])[0]
        mask = rng.random((height, width)) > 0.2
        points[~mask] = 0.0
        if scene != "room":
            v, u = np.mgrid[0:height, 0:width]
            colors = np.stack([128 + 100 * np.sin(u / 7.0 + i), 128 + 100 * np.cos(v / 5.0 - i),
                               128 + 60 * np.sin((u + v) / 11.0)],
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


ROOM = (np.array([-3.5, -1.8, -4.0]), np.array([3.5, 1.0, 3.5]))
"""The room of ``scene="room"``: an axis-aligned box (world y points down, floor at y = 1)."""
DESK = (np.array([-0.9, 0.25, -0.5]), np.array([0.9, 1.0, 0.5]))
"""A desk standing on the floor in the middle of the room (its top 0.75 m above the floor)."""


def room_view(T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """What a camera inside :data:`ROOM` sees: depth ``(H, W)`` along its z axis of the nearest
    surface (walls, floor, ceiling, desk) and colours ``(H, W, 3)`` uint8 painted on those
    surfaces (a checkered floor, striped walls, a dark desk; mid tones, none near white)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # camera z = 1
    d = rays.reshape(-1, 3) @ T_world_cam[:3, :3].T
    C = T_world_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        lo, hi = (ROOM[0] - C) / d, (ROOM[1] - C) / d
        t = np.where(d > 0, hi, np.where(d < 0, lo, np.inf)).min(axis=1)  # leaving the room (the camera is in it)
        near = np.minimum((DESK[0] - C) / d, (DESK[1] - C) / d).max(axis=1)
        far = np.maximum((DESK[0] - C) / d, (DESK[1] - C) / d).min(axis=1)
    on_desk = (near <= far) & (near > 0) & (near < t)
    t = np.where(on_desk, near, t)
    X = C + t[:, None] * d
    x, y, z = X.T
    floor = np.abs(y - ROOM[1][1]) < 1e-6
    checker = (np.floor(x / 0.5) + np.floor(z / 0.5)) % 2
    wall = 0.5 + 0.5 * np.sin(2.0 * (x + z)) * np.cos(3.0 * y)
    colors = np.where(floor[:, None], np.array([150.0, 110, 70]) + 40 * checker[:, None],
                      np.array([90.0, 120, 160]) + 60 * wall[:, None] * np.array([1.0, 0.6, -0.3]))
    colors = np.where(on_desk[:, None], np.array([70.0, 45, 30]) + 25 * np.sin(8 * x + 5 * z)[:, None], colors)
    return t.reshape(height, width), np.clip(colors, 0, 255).astype(np.uint8).reshape(height, width, 3)


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
