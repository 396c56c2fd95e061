"""The authors-v1 comparison benchmark: its one-line refusal of a bad checkout, and the conversion of
our recorded submap layout into the authors' (no checkout of their code needed)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_authors_v1.py"


@pytest.fixture(scope="module")
def bench():
    """The benchmark script loaded as a module by its path."""
    spec = importlib.util.spec_from_file_location("bench_authors_v1_under_test", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("make_path", [
    lambda tmp: tmp / "does-not-exist",   # no such directory
    lambda tmp: tmp,                      # a directory without vggt_slam/solver.py
])
def test_a_bad_checkout_is_one_line_and_exit_code_2(tmp_path: Path, make_path) -> None:
    proc = _run("--vggt-slam", str(make_path(tmp_path)), "--worlds", "synthetic", "--seeds", "1")
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert "--vggt-slam" in lines[0] and "version1.0" in lines[0]
    assert proc.stdout == ""  # refused before any work


def test_no_checkout_given_is_one_line_too() -> None:
    proc = _run("--worlds", "synthetic", "--seeds", "1")
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "--vggt-slam" in lines[0], proc.stderr


def test_help_works() -> None:
    proc = _run("--help")
    assert proc.returncode == 0
    assert "--vggt-slam" in proc.stdout and "--ours" in proc.stdout


def test_first_submap_keeps_its_frames_and_has_no_shared_frame(bench) -> None:
    layout = bench.their_layout([0, 4, 9, 13], None)
    assert layout.slots == (0, 1, 2, 3)
    assert layout.last_non_loop == 3
    assert layout.loop_frames == ()


def test_two_shared_frames_and_two_loop_frames_become_their_layout(bench) -> None:
    # previous submap: shared 20, new 30 40 50 (and a loop frame 3 that is not one of its non-loop frames)
    previous = bench.their_layout([20, 30, 40, 50, 3], [10, 20], [3]).non_loop_frames
    assert previous == (20, 30, 40, 50)
    # this one: shared 40 50 (overlap 2), new 60 70 80, loop frames 9 and 5; only the loop at 5 was accepted
    recorded = [40, 50, 60, 70, 80, 9, 5]
    layout = bench.their_layout(recorded, previous, kept_loop_frames=[5])
    assert layout.slots == (1, 2, 3, 4, 6)           # the last shared frame, the new ones, the kept loop frame
    assert layout.frame_indices == (50, 60, 70, 80, 5)
    assert layout.last_non_loop == 3                   # their loop frame k sits at last_non_loop + 1 + k
    assert layout.loop_frames == (5,)
    assert layout.non_loop_frames == (50, 60, 70, 80)
    # both loops kept: in recorded order
    both = bench.their_layout(recorded, previous, kept_loop_frames=[5, 9])
    assert both.slots == (1, 2, 3, 4, 5, 6) and both.loop_frames == (9, 5)


def test_one_shared_frame_is_kept_as_it_is(bench) -> None:
    layout = bench.their_layout([50, 60, 70, 8], [20, 30, 40, 50])
    assert layout.slots == (0, 1, 2) and layout.last_non_loop == 2 and layout.loop_frames == ()


def test_layout_problems_are_named(bench) -> None:
    with pytest.raises(ValueError, match="shares no frame"):
        bench.their_layout([60, 70], [20, 30])
    with pytest.raises(ValueError, match="not among the loop frames"):
        bench.their_layout([30, 60, 70, 5], [20, 30], kept_loop_frames=[6])


def test_reanchoring_puts_the_kept_frame_at_the_origin_and_keeps_relative_poses(bench) -> None:
    rng = np.random.default_rng(0)
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    for i in range(3):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        T[i, :3, :3] = q * np.sign(np.linalg.det(q))
        T[i, :3, 3] = rng.normal(size=3)
    moved = bench.reanchor(T[:, :3, :], 1)
    np.testing.assert_allclose(moved[1], np.eye(4), atol=1e-12)
    # camera-from-camera transforms are unchanged
    np.testing.assert_allclose(moved[2] @ np.linalg.inv(moved[0]), T[2] @ np.linalg.inv(T[0]), atol=1e-10)


def test_geometry_stand_ins(bench) -> None:
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    T_cam_world = np.concatenate([q, rng.normal(size=(3, 1))], axis=1)[None]
    inverse = bench.closed_form_inverse_se3(T_cam_world)
    np.testing.assert_allclose(inverse[0] @ np.vstack([T_cam_world[0], [0, 0, 0, 1]]), np.eye(4), atol=1e-12)
    K = np.array([[[100.0, 0.5, 8.0], [0.0, 110.0, 6.0], [0.0, 0.0, 1.0]]])
    depth = rng.uniform(1.0, 3.0, size=(1, 12, 16, 1)).astype(np.float32)
    world = bench.unproject_depth_map_to_point_map(depth, T_cam_world, K)
    assert world.shape == (1, 12, 16, 3)
    # back into the camera and through K: the pixel grid and the depth again
    cam = world[0].reshape(-1, 3).astype(np.float64) @ q.T + T_cam_world[0, :, 3]
    np.testing.assert_allclose(cam[:, 2], depth.reshape(-1), rtol=1e-5)
    uv = (cam @ K[0].T)[:, :2] / cam[:, 2:]
    v, u = np.mgrid[0:12, 0:16]
    np.testing.assert_allclose(uv, np.stack([u.ravel(), v.ravel()], axis=1), atol=1e-3)


def test_our_settings_are_parsed_as_json_values(bench) -> None:
    assert bench.parse_settings(["submap.overlap=2", "backend.kind=sim3", "loops.enabled=false"]) == {
        "submap.overlap": 2, "backend.kind": "sim3", "loops.enabled": False}
    with pytest.raises(ValueError, match="section.name=value"):
        bench.parse_settings(["overlap2"])
