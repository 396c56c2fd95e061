"""Each frame's camera refined against the other frames' dense points (``sl4slam.refine``)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sl4slam.geometry import pixel_grid
from sl4slam.refine import camera_points_and_normals, refine_frame_poses

H, W = 60, 80
K = np.array([[70.0, 0, 40], [0, 70.0, 30], [0, 0, 1]])


def render_room(T_cam_submap: np.ndarray) -> np.ndarray:
    """``(S, H, W)`` z-depth inside a box room (back wall z = 3, floor y = 1, ceiling y = -1, side walls
    x = +-1.5): every direction of a camera's motion is fixed by some wall it sees."""
    depths = []
    rays = pixel_grid(H, W).reshape(-1, 3) @ np.linalg.inv(K).T
    for T in T_cam_submap:
        R, t = T[:3, :3], T[:3, 3]
        centre, directions = -R.T @ t, rays @ R  # rays in the submap frame (R^T d)
        hits = np.full(len(rays), np.inf)
        for axis, level in ((2, 3.0), (1, 1.0), (1, -1.0), (0, -1.5), (0, 1.5)):
            s = (level - centre[axis]) / np.where(np.abs(directions[:, axis]) > 1e-12, directions[:, axis], np.nan)
            hits = np.where((s > 0) & (s < hits), s, hits)
        depths.append(hits.reshape(H, W))  # rays have z = 1 in the camera: s is the z-depth
    return np.stack(depths)


def room(seed: int = 1, frames: int = 9):
    """True poses (the first the identity), their depth maps and validity, and the generator."""
    rng = np.random.default_rng(seed)
    truth = np.zeros((frames, 3, 4))
    truth[0, :, :3] = np.eye(3)
    for i in range(1, frames):
        R = Rotation.from_rotvec(rng.normal(0, 0.08, 3)).as_matrix()
        truth[i, :, :3], truth[i, :, 3] = R, -R @ rng.normal(0, 0.15, 3)
    depth = render_room(truth)
    valid = np.isfinite(depth) & (depth > 0)
    return truth, np.where(valid, depth, 0.0).astype(np.float32), valid, rng


def errors(T: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (degrees) and centre (metres) errors of frames 1.."""
    turned = np.einsum("sji,sjk->sik", T[:, :, :3], truth[:, :, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(turned, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    centre = lambda P: -np.einsum("sji,sj->si", P[:, :, :3], P[:, :, 3])  # noqa: E731
    return angle[1:], np.linalg.norm(centre(T) - centre(truth), axis=1)[1:]


def test_normals_of_a_plane_face_the_camera():
    points, normals = camera_points_and_normals(np.full((20, 30), 2.0), K)
    np.testing.assert_allclose(normals[1:-1, 1:-1], np.broadcast_to([0, 0, -1.0], (18, 28, 3)), atol=1e-12)
    assert not normals[0].any() and not normals[:, 0].any()  # no central difference on the border
    np.testing.assert_allclose(points[..., 2], 2.0)


def test_true_poses_stay():
    truth, depth, valid, _ = room()
    same = refine_frame_poses(depth, np.repeat(K[None], len(truth), 0), truth, valid)
    # 0.1 mm in a 3 m room: float32 depth, and the few interpolations across an edge of two walls
    np.testing.assert_allclose(same, truth, atol=1e-4)


def test_independent_pose_errors_shrink():
    truth, depth, valid, rng = room()
    wrong = truth.copy()
    for i in range(1, len(truth)):  # each frame's own error, drawn independently (what the refinement rests on)
        dR = Rotation.from_rotvec(rng.normal(0, np.radians(1.0), 3)).as_matrix()
        wrong[i, :, :3] = dR @ truth[i, :, :3]
        wrong[i, :, 3] = dR @ truth[i, :, 3] + rng.normal(0, 0.03, 3)
    Ks = np.repeat(K[None], len(truth), 0)
    refined = refine_frame_poses(depth, Ks, wrong, valid)
    before, after = errors(wrong, truth), errors(refined, truth)
    assert np.median(after[0]) < 0.3 * np.median(before[0]), (before[0], after[0])
    assert np.median(after[1]) < 0.5 * np.median(before[1]), (before[1], after[1])
    assert np.array_equal(refined[0], wrong[0])  # the submap frame stays
    assert np.array_equal(refine_frame_poses(depth, Ks, wrong, valid), refined)  # deterministic


def test_smooth_depth_warps_are_taken_for_pose_errors():
    """What keeps the lever off: frames whose depth maps are warped (each its own tilt of up to a
    few per cent across the image, the true poses untouched) are turned to make their surfaces
    agree, away from their true poses."""
    truth, depth, valid, rng = room()
    warped = depth.copy()
    for i in range(1, len(truth)):
        warped[i] *= (1.0 + rng.normal(0, 0.02) * np.linspace(-1, 1, W))[None, :].astype(np.float32)
    refined = refine_frame_poses(warped, np.repeat(K[None], len(truth), 0), truth, valid)
    angle, _ = errors(refined, truth)
    assert np.median(angle) > 0.1, angle  # against < 0.01 degrees for the same poses without warps
