"""The synthetic RGB-D world: geometry against brute-force ground truth, path properties,
depth/pose/intrinsics consistency by reprojection, and the written TUM folder."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sl4slam.errors import UserError
from sl4slam.io import TumSource, open_source
from sl4slam.synthetic import (
    CEILING_SURFACE,
    FLOOR_SURFACE,
    camera_path,
    default_intrinsics,
    floor_hold_frames,
    make_layout,
    make_world,
    render_frames,
    render_pixels,
    write_synthetic_sequence,
)
from sl4slam.synthetic.textures import make_texture

W, H = 160, 120


@pytest.fixture(scope="module")
def world():
    return make_world(0)


def _brute_force_hit(layout, origin: np.ndarray, direction: np.ndarray) -> tuple[float, int]:
    """Nearest hit by testing every face plane separately (a different algorithm from the renderer's)."""
    best_t, best_surface = np.inf, -1
    faces = []
    for axis in range(3):
        for side, bound in enumerate((layout.room_min, layout.room_max)):
            faces.append((2 * axis + side, axis, bound[axis], layout.room_min, layout.room_max))
    for box, (lo, hi) in enumerate(zip(layout.boxes_min, layout.boxes_max)):
        for axis in range(3):
            for side, bound in enumerate((lo, hi)):
                faces.append((6 + 6 * box + 2 * axis + side, axis, bound[axis], lo, hi))
    for surface, axis, plane, lo, hi in faces:
        if abs(direction[axis]) < 1e-15:
            continue
        t = (plane - origin[axis]) / direction[axis]
        if t <= 1e-9 or t >= best_t:
            continue
        point = origin + t * direction
        others = [a for a in range(3) if a != axis]
        if all(lo[a] - 1e-9 <= point[a] <= hi[a] + 1e-9 for a in others):
            best_t, best_surface = t, surface
    return best_t, best_surface


def test_ray_casting_matches_brute_force(world):
    rng = np.random.default_rng(0)
    poses = camera_path(600, 0)[rng.choice(600, 6, replace=False)]
    K = default_intrinsics(W, H)
    pixels = rng.uniform((0, 0), (W - 1, H - 1), size=(60, 2))
    for T in poses:
        depth, surface = render_pixels(world, T, K, pixels)
        rays = np.concatenate([pixels, np.ones((60, 1))], 1) @ np.linalg.inv(K).T @ T[:3, :3].T
        for k in range(60):
            t, expected_surface = _brute_force_hit(world.layout, T[:3, 3], rays[k])
            assert surface[k] == expected_surface
            assert depth[k] == pytest.approx(t, rel=1e-9)  # z of the ray is 1, so t is the depth


def test_depth_is_exact_for_floor_and_ceiling_views(world):
    layout = world.layout
    K = default_intrinsics(W, H)
    centre = np.array([*layout.path_centre, 1.2])
    down = np.eye(4)
    down[:3, :3] = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1]]).T  # x right, y down, z forward = -z world
    assert np.linalg.det(down[:3, :3]) == pytest.approx(1)
    hold = camera_path(600, 0)[floor_hold_frames(600)][0]
    down[:3, 3] = hold[:3, 3]
    _, depth, surfaces = render_frames(world, down, K, W, H, return_surfaces=True)
    assert np.all(surfaces == FLOOR_SURFACE)
    np.testing.assert_allclose(depth, hold[2, 3], rtol=1e-6)
    up = np.eye(4)  # camera axes = world axes: x right, y down, looking along +z (up)
    up[:3, 3] = centre
    _, depth, surfaces = render_frames(world, up, K, W, H, return_surfaces=True)
    visible_ceiling = surfaces == CEILING_SURFACE
    assert visible_ceiling.mean() > 0.5
    np.testing.assert_allclose(depth[visible_ceiling], layout.room_max[2] - centre[2], rtol=1e-6)


def _reproject(depth_i, T_i, T_j, K_i, K_j):
    """Pixels of frame i moved into frame j: ``(P, 2)`` uv in j, ``(P,)`` depth in j, ``(P,)`` flat index in i."""
    height, width = depth_i.shape
    v, u = np.mgrid[0:height, 0:width]
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(K_i).T
    points_i = rays * depth_i.reshape(-1, 1).astype(np.float64)
    T_j_i = np.linalg.inv(T_j) @ T_i
    points_j = points_i @ T_j_i[:3, :3].T + T_j_i[:3, 3]
    z = points_j[:, 2]
    uv = (points_j @ K_j.T)[:, :2] / z[:, None]
    inside = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= height - 1)
    return uv[inside], z[inside], np.flatnonzero(inside)


def _photometric_error(rgb_i, rgb_j, uv_j, index) -> float:
    """Mean absolute colour difference between frame i's pixels and frame j sampled where they reproject."""
    height, width = rgb_i.shape[:2]
    map_x = np.full((height, width), -1, np.float32)
    map_y = np.full((height, width), -1, np.float32)
    map_x.ravel()[index] = uv_j[:, 0]
    map_y.ravel()[index] = uv_j[:, 1]
    warped = cv2.remap(rgb_j, map_x, map_y, cv2.INTER_LINEAR).astype(np.float32)
    return float(np.abs(warped.reshape(-1, 3)[index] - rgb_i.reshape(-1, 3)[index].astype(np.float32)).mean())


@pytest.mark.parametrize("i, j", [(100, 106), (420, 431), (0, 599), (300, 310)])
def test_depth_poses_and_intrinsics_agree_by_reprojection(world, i, j):
    K = default_intrinsics(W, H)
    poses = camera_path(600, 0)
    rgb, depth = render_frames(world, poses[[i, j]], K, W, H)
    uv_j, z_j, index = _reproject(depth[0], poses[i], poses[j], K, K)
    assert index.size > 0.5 * W * H
    # Geometric: the ray through the reprojected position hits the same point (unless occluded).
    depth_at_j, _ = render_pixels(world, poses[j], K, uv_j)
    visible = np.abs(depth_at_j - z_j) < 1e-3 * z_j
    assert visible.mean() > 0.8
    np.testing.assert_allclose(depth_at_j[visible], z_j[visible], rtol=2e-6)
    # Photometric: same surface point, same colour (view-independent shading) ...
    error = _photometric_error(rgb[0], rgb[1], uv_j[visible], index[visible])
    assert error < 3.0
    # ... and the check is sensitive: a 3 % focal error or a 0.5 degree pose error fail it clearly.
    K_wrong = K @ np.diag([1.03, 1.03, 1.0])
    uv_w, _, index_w = _reproject(depth[0], poses[i], poses[j], K_wrong, K)
    assert _photometric_error(rgb[0], rgb[1], uv_w, index_w) > 2 * error + 3.0
    T_wrong = poses[j].copy()
    T_wrong[:3, :3] = T_wrong[:3, :3] @ cv2.Rodrigues(np.array([0.0, np.radians(0.5), 0.0]))[0]
    uv_w, _, index_w = _reproject(depth[0], poses[i], T_wrong, K, K)
    assert _photometric_error(rgb[0], rgb[1], uv_w, index_w) > 2 * error + 3.0


def test_camera_path_loop_smoothness_and_floor_stretch():
    poses = camera_path(600, 0)
    assert poses.shape == (600, 4, 4)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(poses[-1], poses[0], atol=1e-12)  # returns to its start pose
    relative = np.einsum("nji,njk->nik", R[:-1], R[1:])
    angles = np.degrees(np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert angles.max() < 2.5 and steps.max() < 0.04  # a few px per frame at 320 px width
    hold = floor_hold_frames(600)
    assert 40 <= hold.sum() <= 80
    np.testing.assert_allclose(poses[hold][:, :3, 2], np.broadcast_to([0, 0, -1], (hold.sum(), 3)), atol=1e-9)
    layout = make_layout(0)
    inside = np.all((poses[:, :3, 3] > layout.room_min + 0.5) & (poses[:, :3, 3] < layout.room_max - 0.5), axis=1)
    assert inside.all()


def test_floor_hold_frames_see_only_floor_and_other_frames_see_the_room(world):
    K = default_intrinsics(W, H)
    poses = camera_path(600, 0)
    hold = np.flatnonzero(floor_hold_frames(600))
    picks = hold[:: max(1, len(hold) // 4)]
    _, _, surfaces = render_frames(world, poses[picks], K, W, H, return_surfaces=True)
    assert np.all(surfaces == FLOOR_SURFACE)
    _, depth, surfaces = render_frames(world, poses[[0, 150, 450]], K, W, H, return_surfaces=True)
    for view in surfaces:
        assert len(np.unique(view)) >= 3  # walls, floor, furniture: a real 3-D view
    assert depth.min() > 0.4 and depth.max() < 12.0


def test_textures_give_trackable_corners(world):
    K = default_intrinsics(320, 240)
    poses = camera_path(600, 0)
    hold = np.flatnonzero(floor_hold_frames(600))
    rgb, _ = render_frames(world, poses[[0, 200, hold[len(hold) // 2]]], K, 320, 240)
    for image in rgb:
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        corners = cv2.goodFeaturesToTrack(grey, maxCorners=1000, qualityLevel=0.01, minDistance=8)
        # For scale: the first TUM fr1_xyz frame resized to 320x240 gives 268 such corners.
        assert corners is not None and len(corners) > 250


def test_world_is_seeded():
    a, b, c = make_layout(3), make_layout(3), make_layout(4)
    np.testing.assert_array_equal(a.boxes_min, b.boxes_min)
    np.testing.assert_array_equal(a.room_max, b.room_max)
    assert a.room_max[0] != c.room_max[0]
    t1 = make_texture(np.random.default_rng(9), 0.6, 0.4, 0.01, "furniture")
    t2 = make_texture(np.random.default_rng(9), 0.6, 0.4, 0.01, "furniture")
    t3 = make_texture(np.random.default_rng(10), 0.6, 0.4, 0.01, "furniture")
    assert t1.shape == (40, 60, 3)
    np.testing.assert_array_equal(t1, t2)
    assert np.abs(t1.astype(int) - t3).mean() > 10


def test_written_sequence_loads_with_depth_poses_and_intrinsics(tmp_path):
    out = write_synthetic_sequence(tmp_path / "synth", num_frames=40, width=96, height=72, seed=3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["synth"]  # no staging folder left
    source = open_source(out)
    assert isinstance(source, TumSource) and len(source) == 40
    frames = list(source)
    K = default_intrinsics(96, 72)
    poses = camera_path(40, 3)
    world = make_world(3)
    rgb, depth = render_frames(world, poses[[0, 21]], K, 96, 72)
    for frame in frames:
        np.testing.assert_allclose(frame.K, K, rtol=1e-12)
        np.testing.assert_allclose(frame.T_world_cam, poses[frame.index], atol=2e-8)
        assert frame.timestamp == pytest.approx(frame.index / 30.0, abs=1e-6)
        assert frame.rgb.shape == (72, 96, 3) and frame.depth.shape == (72, 96)
    np.testing.assert_array_equal(frames[0].rgb, rgb[0])
    np.testing.assert_allclose(frames[21].depth, depth[1], atol=0.5 / 5000 + 1e-6)  # 16-bit quantization only
    np.testing.assert_allclose(frames[-1].T_world_cam, frames[0].T_world_cam, atol=1e-8)

    meta = json.loads((out / "synthetic.json").read_text())
    floor = meta["floor_only"]
    assert floor["count"] >= 3 and floor["stop"] - floor["start"] == floor["count"]
    designed = np.flatnonzero(floor_hold_frames(40))
    assert floor["start"] <= designed.min() and designed.max() < floor["stop"]
    np.testing.assert_allclose(meta["K"], K)
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet is not None and sheet.shape[1] == 6 * 96

    with pytest.raises(UserError) as excinfo:
        write_synthetic_sequence(out, num_frames=4, width=32, height=24)
    assert "\n" not in str(excinfo.value)
    write_synthetic_sequence(out, num_frames=4, width=32, height=24, overwrite=True)
    assert len(open_source(out)) == 4


@pytest.mark.slow
def test_full_sequence_keyframe_count(tmp_path):
    from sl4slam.keyframes import KeyframeSelector

    out = write_synthetic_sequence(tmp_path / "synth600", num_frames=600, seed=0)
    selector = KeyframeSelector()
    keyframes = sum(selector.is_keyframe(frame.rgb) for frame in open_source(out))
    assert 30 <= keyframes <= 110
    meta = json.loads((out / "synthetic.json").read_text())
    assert meta["floor_only"]["count"] >= 60
    assert meta["depth_range_m"][1] > 4.0
