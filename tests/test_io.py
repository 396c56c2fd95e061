"""Sequence IO: sources, association, intrinsics, trajectories, and one-line errors on bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.errors import UserError
from sl4slam.io import (
    ImageFolderSource,
    ListSource,
    SevenScenesSource,
    TumSource,
    VideoSource,
    associate,
    natural_key,
    open_source,
    read_tum_trajectory,
    tum_intrinsics,
    write_tum_trajectory,
)
from sl4slam.types import Frame, FrameSource

TUM_EXCERPT = "data/tum_rgbd_fr1_xyz_first37"


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _pattern(value: int, height: int = 24, width: int = 32) -> np.ndarray:
    """An image whose red channel encodes ``value`` and green a gradient (so RGB order is testable)."""
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[..., 0] = value
    rgb[..., 1] = np.arange(width, dtype=np.uint8)[None, :] * 4
    rgb[..., 2] = 7
    return rgb


def _assert_one_line_user_error(excinfo) -> None:
    message = str(excinfo.value)
    assert message and "\n" not in message


# ------------------------------------------------------------------------------------------
# The real TUM excerpt
# ------------------------------------------------------------------------------------------


def _brute_force_associate(first: list[float], second: list[float], max_difference: float = 0.02) -> dict:
    """TUM associate.py's algorithm, written out literally (quadratic)."""
    candidates = sorted((abs(a - b), a, b) for a in first for b in second if abs(a - b) < max_difference)
    free_first, free_second, pairs = set(first), set(second), {}
    for _, a, b in candidates:
        if a in free_first and b in free_second:
            free_first.remove(a)
            free_second.remove(b)
            pairs[a] = b
    return pairs


def _stamps(path: Path) -> list[tuple[float, str]]:
    rows = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            stamp, name = line.split()[:2]
            rows.append((float(stamp), name))
    return rows


def test_tum_excerpt_frames_depth_poses_and_intrinsics(shared_dir):
    folder = shared_dir / TUM_EXCERPT
    source = open_source(folder)
    assert isinstance(source, TumSource) and isinstance(source, FrameSource)
    assert len(source) == 37
    frames = list(source)
    assert [f.index for f in frames] == list(range(37))

    rgb_rows, depth_rows = _stamps(folder / "rgb.txt"), _stamps(folder / "depth.txt")
    pairs = _brute_force_associate([s for s, _ in rgb_rows], [s for s, _ in depth_rows])
    assert len(pairs) == 32  # what TUM's associate.py gives on this excerpt
    depth_name = dict(depth_rows)
    for frame, (stamp, name) in zip(frames, rgb_rows):
        assert frame.timestamp == stamp
        assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
        bgr = cv2.imread(str(folder / name))
        np.testing.assert_array_equal(frame.rgb, bgr[..., ::-1])
        if stamp in pairs:
            raw = cv2.imread(str(folder / depth_name[pairs[stamp]]), cv2.IMREAD_UNCHANGED)
            assert frame.depth.dtype == np.float32
            np.testing.assert_allclose(frame.depth, raw.astype(np.float32) / 5000.0, rtol=1e-6)
        else:
            assert frame.depth is None
        np.testing.assert_allclose(frame.K, [[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]])

    # Ground truth: the nearest line of groundtruth.txt, parsed independently here.
    table = np.loadtxt(folder / "groundtruth.txt", comments="#")
    for frame in frames[::6]:
        row = table[np.argmin(np.abs(table[:, 0] - frame.timestamp))]
        assert abs(row[0] - frame.timestamp) < 0.02
        np.testing.assert_allclose(frame.T_world_cam[:3, 3], row[1:4])
        np.testing.assert_allclose(frame.T_world_cam[:3, :3], Rotation.from_quat(row[4:8]).as_matrix(), atol=1e-9)

    again = source.get(5)
    np.testing.assert_array_equal(again.rgb, frames[5].rgb)


def test_tum_excerpt_stride_and_max_frames(shared_dir):
    source = open_source(shared_dir / TUM_EXCERPT, stride=4, max_frames=5)
    stamps = [s for s, _ in _stamps(shared_dir / TUM_EXCERPT / "rgb.txt")]
    assert [f.timestamp for f in source] == stamps[::4][:5]
    assert open_source(shared_dir / TUM_EXCERPT / "rgb.txt").name == "tum_rgbd_fr1_xyz_first37"


def test_tum_groundtruth_round_trip_matches_file(shared_dir, tmp_path):
    stamps, poses = read_tum_trajectory(shared_dir / TUM_EXCERPT / "groundtruth.txt")
    assert stamps.shape == (3000,) and poses.shape == (3000, 4, 4)
    out = write_tum_trajectory(tmp_path / "gt.txt", stamps, poses)
    stamps2, poses2 = read_tum_trajectory(out)
    np.testing.assert_allclose(stamps2, stamps, atol=1e-9)
    np.testing.assert_allclose(poses2, poses, atol=1e-8)


# ------------------------------------------------------------------------------------------
# Association and intrinsics
# ------------------------------------------------------------------------------------------


def test_associate_matches_tum_algorithm_on_jittered_streams():
    rng = np.random.default_rng(4)
    first = np.cumsum(rng.uniform(0.02, 0.045, 300))
    second = np.sort(first + rng.normal(0, 0.012, 300))[rng.permutation(300)]  # unsorted on purpose
    match = associate(first, second)
    expected = _brute_force_associate(first.tolist(), second.tolist())
    got = {first[i]: second[j] for i, j in enumerate(match) if j >= 0}
    assert got == expected
    assert 0 < len(got) < 300


def test_tum_intrinsics_defaults_by_folder_name(tmp_path):
    fr2 = tmp_path / "rgbd_dataset_freiburg2_desk"
    fr2.mkdir()
    np.testing.assert_allclose(tum_intrinsics(fr2), [[520.9, 0, 325.1], [0, 521.0, 249.7], [0, 0, 1]])
    other = tmp_path / "my_sequence"
    other.mkdir()
    assert tum_intrinsics(other) is None
    (other / "intrinsics.txt").write_text("fx: 300.5\nfy: 301\ncx: 160\ncy: 120.25\n")
    np.testing.assert_allclose(tum_intrinsics(other), [[300.5, 0, 160], [0, 301, 120.25], [0, 0, 1]])


# ------------------------------------------------------------------------------------------
# Trajectories
# ------------------------------------------------------------------------------------------


def test_trajectory_round_trip_is_exact_and_atomic(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (20, 1, 1))
    poses[:, :3, :3] = Rotation.random(20, random_state=1).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(20, 3))
    stamps = 1000.0 + np.arange(20) / 30.0
    path = write_tum_trajectory(tmp_path / "sub" / "traj.txt", stamps, poses)
    assert sorted(p.name for p in path.parent.iterdir()) == ["traj.txt"]  # no temporary left behind
    lines = [l for l in path.read_text().splitlines() if not l.startswith("#")]
    assert len(lines) == 20 and all(len(l.split()) == 8 for l in lines)
    assert all(float(l.split()[7]) >= 0 for l in lines)  # canonical quaternion sign qw >= 0
    stamps2, poses2 = read_tum_trajectory(path)
    np.testing.assert_allclose(stamps2, stamps, atol=1e-9)
    np.testing.assert_allclose(poses2, poses, atol=1e-8)


def test_trajectory_refuses_nan_and_keeps_old_file(tmp_path):
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, np.zeros(1), np.eye(4)[None])
    before = path.read_text()
    bad = np.tile(np.eye(4), (2, 1, 1))
    bad[1, 0, 3] = np.nan
    with pytest.raises(UserError) as excinfo:
        write_tum_trajectory(path, np.arange(2.0), bad)
    _assert_one_line_user_error(excinfo)
    assert path.read_text() == before
    with pytest.raises(UserError):
        write_tum_trajectory(path, np.arange(3.0), bad)  # length mismatch


@pytest.mark.parametrize(
    "content", ["1 2 3\n", "0 0 0 0 0 0 0 0\n", "0 0 0 x 0 0 0 1\n", "# only a comment\n", "0 nan 0 0 0 0 0 1\n"]
)
def test_trajectory_malformed_files_raise_user_error(tmp_path, content):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(UserError) as excinfo:
        read_tum_trajectory(path)
    _assert_one_line_user_error(excinfo)


# ------------------------------------------------------------------------------------------
# Image folders
# ------------------------------------------------------------------------------------------


def test_natural_key_uses_number_nearest_extension():
    names = ["cam2_frame10.png", "cam2_frame9.png", "zzz.png", "cam2_frame100.png", "1305031102.5.png", "a_7_b_2.png"]
    ordered = [p.name for p in sorted((Path(n) for n in names), key=natural_key)]
    assert ordered == ["a_7_b_2.png", "cam2_frame9.png", "cam2_frame10.png", "cam2_frame100.png", "1305031102.5.png", "zzz.png"]


def test_image_folder_order_skips_and_stride(tmp_path, caplog):
    for number in (10, 2, 1, 33):
        _write_rgb(tmp_path / f"shot_{number}.png", _pattern(number))
    _write_rgb(tmp_path / "shot_5.jpg", _pattern(5))  # jpg: lossy, checked loosely
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "shot_7.png").write_bytes(b"this is not a png at all" * 10)
    with caplog.at_level(logging.WARNING, logger="sl4slam"):
        source = open_source(tmp_path)
    assert isinstance(source, ImageFolderSource)
    assert [p.name for p in source.paths] == ["shot_1.png", "shot_2.png", "shot_5.jpg", "shot_10.png", "shot_33.png"]
    assert len(source.skipped) == 1 and "shot_7.png" in source.skipped[0]
    assert "shot_7.png" in caplog.text
    frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [int(f.rgb[0, 0, 0]) for f in frames if not f.path.endswith(".jpg")] == [1, 2, 10, 33]
    np.testing.assert_array_equal(frames[0].rgb, _pattern(1))  # RGB order, not BGR
    assert all(f.depth is None and f.T_world_cam is None and f.K is None for f in frames)

    strided = open_source(tmp_path, stride=2, max_frames=2)
    assert [Path(f.path).name for f in strided] == ["shot_1.png", "shot_5.jpg"]


def test_image_folder_truncated_image_skipped_on_read(tmp_path, caplog):
    for number in range(3):
        _write_rgb(tmp_path / f"{number:03d}.png", _pattern(number, 64, 64))
    data = (tmp_path / "001.png").read_bytes()
    (tmp_path / "001.png").write_bytes(data[:60])  # valid signature, truncated data
    source = open_source(tmp_path)
    with caplog.at_level(logging.WARNING, logger="sl4slam"):
        frames = list(source)
    assert [f.index for f in frames] == [0, 2]
    assert len(source.skipped) == 1 and "001.png" in source.skipped[0]
    with pytest.raises(UserError) as excinfo:
        source.get(1)
    _assert_one_line_user_error(excinfo)
    assert len(source.skipped) == 1  # counted once


# ------------------------------------------------------------------------------------------
# Video
# ------------------------------------------------------------------------------------------


def test_video_stride_timestamps_and_random_access(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (32, 24))
    assert writer.isOpened()
    for k in range(10):
        writer.write(np.full((24, 32, 3), 20 * k + 10, np.uint8))
    writer.release()

    source = open_source(path, stride=3)
    assert isinstance(source, VideoSource)
    assert len(source) == 4
    frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    np.testing.assert_allclose([f.timestamp for f in frames], [0.0, 0.3, 0.6, 0.9])
    brightness = [float(f.rgb.mean()) for f in frames]
    np.testing.assert_allclose(brightness, [10, 70, 130, 190], atol=3)
    assert abs(float(source.get(2).rgb.mean()) - 130) < 3
    assert len(open_source(path, max_frames=6)) == 6


# ------------------------------------------------------------------------------------------
# 7-Scenes
# ------------------------------------------------------------------------------------------


def test_seven_scenes_depth_invalid_and_pose_projection(tmp_path):
    scene = tmp_path / "chess"
    sequence = scene / "seq-01"
    sequence.mkdir(parents=True)
    rng = np.random.default_rng(2)
    true_rotations = Rotation.random(3, random_state=3).as_matrix()
    for k in range(3):
        _write_rgb(sequence / f"frame-{k:06d}.color.png", _pattern(k))
        raw = np.full((24, 32), 1500 + k, np.uint16)
        raw[0, :5] = 65535
        raw[1, :2] = 0
        assert cv2.imwrite(str(sequence / f"frame-{k:06d}.depth.png"), raw)
        pose = np.eye(4)
        pose[:3, :3] = true_rotations[k] + rng.normal(0, 1e-3, (3, 3))  # not exactly orthonormal, as published
        pose[:3, 3] = [k, 2.0, -1.0]
        np.savetxt(sequence / f"frame-{k:06d}.pose.txt", pose, fmt="%.7e")

    with pytest.raises(UserError, match="seq-01"):
        open_source(scene)
    source = open_source(sequence)
    assert isinstance(source, SevenScenesSource) and len(source) == 3
    frames = list(source)
    for k, frame in enumerate(frames):
        assert frame.timestamp == pytest.approx(k / 30.0)
        assert frame.depth[5, 5] == pytest.approx((1500 + k) / 1000.0)
        assert np.all(frame.depth[0, :5] == 0) and np.all(frame.depth[1, :2] == 0)
        R = frame.T_world_cam[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R, true_rotations[k], atol=5e-3)
        np.testing.assert_allclose(frame.T_world_cam[:3, 3], [k, 2.0, -1.0])
        # the published 640x480 intrinsics, scaled to these 32x24 images
        np.testing.assert_allclose(frame.K, [[29.25, 0, 16], [0, 29.25, 12], [0, 0, 1]])


# ------------------------------------------------------------------------------------------
# In-memory source
# ------------------------------------------------------------------------------------------


def test_list_source_random_access():
    frames = [Frame(index=i * 2, timestamp=i * 0.1, rgb=_pattern(i)) for i in range(4)]
    source = ListSource(frames, name="mem")
    assert isinstance(source, FrameSource)
    assert len(source) == 4 and list(source) == frames
    assert source.get(4) is frames[2]
    with pytest.raises(UserError):
        source.get(3)
    with pytest.raises(UserError):
        ListSource(frames + frames)


# ------------------------------------------------------------------------------------------
# Bad inputs: one-line UserError each
# ------------------------------------------------------------------------------------------


def _make_bad_input(kind: str, root: Path) -> Path:
    if kind == "missing folder":
        return root / "does_not_exist"
    if kind == "empty folder":
        (root / "empty").mkdir()
        return root / "empty"
    if kind == "corrupt image":
        folder = root / "corrupt"
        folder.mkdir()
        (folder / "0001.png").write_bytes(b"\x00\x01garbage" * 50)
        (folder / "0002.jpg").write_bytes(b"")
        return folder
    if kind == "unreadable video":
        path = root / "broken.mp4"
        path.write_bytes(b"not a video" * 100)
        return path
    if kind == "tum without groundtruth":
        folder = root / "tum"
        (folder / "rgb").mkdir(parents=True)
        _write_rgb(folder / "rgb" / "1.000000.png", _pattern(1))
        (folder / "rgb.txt").write_text("# color images\n1.000000 rgb/1.000000.png\n")
        return folder
    if kind == "single image file":
        path = root / "image.png"
        _write_rgb(path, _pattern(1))
        return path
    if kind == "unknown file":
        path = root / "data.xyz"
        path.write_text("x")
        return path
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind",
    [
        "missing folder",
        "empty folder",
        "corrupt image",
        "unreadable video",
        "tum without groundtruth",
        "single image file",
        "unknown file",
    ],
)
def test_bad_inputs_give_one_line_user_error(tmp_path, kind):
    path = _make_bad_input(kind, tmp_path)
    with pytest.raises(UserError) as excinfo:
        open_source(path)
    _assert_one_line_user_error(excinfo)
    assert str(path.name) in str(excinfo.value)


def test_tum_without_groundtruth_can_be_opened_explicitly(tmp_path):
    folder = _make_bad_input("tum without groundtruth", tmp_path)
    source = TumSource(folder, require_groundtruth=False)
    frame = source.get(0)
    assert frame.T_world_cam is None and frame.depth is None and frame.timestamp == 1.0


def test_bad_stride_is_user_error(tmp_path):
    _write_rgb(tmp_path / "1.png", _pattern(1))
    with pytest.raises(UserError):
        open_source(tmp_path, stride=0)
    with pytest.raises(UserError):
        open_source(tmp_path, max_frames=-1)


def test_a_random_bytes_video_is_one_clean_line_without_library_noise(tmp_path, capfd):
    from sl4slam.cli import main

    video = tmp_path / "noise.mp4"
    video.write_bytes(np.random.default_rng(0).integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    assert main(["run", str(video), "--out", str(tmp_path / "out"), "--frontend", "simulated", "--quiet"]) == 2
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("sl4slam: error:") and "noise.mp4" in err[0], err
    assert not (tmp_path / "out").exists()
