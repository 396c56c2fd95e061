"""Runs that never lose work: the output folder checked first, progressive outputs, interruption,
missing weights found before any frame is read, unreadable inputs reported."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import sl4slam.io as io
from sl4slam.config import SLAMConfig
from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.io import read_tum_trajectory
from sl4slam.result.outputs import read_ply
from sl4slam.result.reading import load_result
from sl4slam.runner import RunInterrupted, format_length, prepare_output, run_slam
from sl4slam.synthetic import write_synthetic_sequence


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("runner") / "world", num_frames=240, width=96, height=72, seed=2)


def sim_config() -> SLAMConfig:
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 7.5
    config.submap.size = 6
    config.retrieval.kind = "none"
    return config


@pytest.fixture
def no_frame_reads(monkeypatch):
    """Fail the test if any source is opened: what the runner checks first must come first."""
    def refuse(*args, **kwargs):
        raise AssertionError("a frame source was opened before the settings and --out were checked")

    monkeypatch.setattr(io, "open_source", refuse)


def test_an_out_path_under_a_file_fails_before_any_frame_is_read(tmp_path: Path, no_frame_reads) -> None:
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(UserError, match="cannot create the output folder"):
        run_slam(tmp_path / "anything", tmp_path / "file.txt" / "out", sim_config())
    with pytest.raises(UserError, match="not a folder"):
        run_slam(tmp_path / "anything", tmp_path / "file.txt", sim_config())


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root may write anywhere")
def test_a_read_only_out_fails_before_any_frame_is_read(tmp_path: Path, no_frame_reads) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(UserError, match="cannot"):
            run_slam(tmp_path / "anything", locked / "out", sim_config())
    finally:
        locked.chmod(0o700)


def test_an_earlier_run_is_refused_unless_overwritten(world: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    first = run_slam(world, out, sim_config(), progress=False)
    stale = out / "keyframes" / "999999.npz"
    stale.write_bytes(b"from an earlier run")
    with pytest.raises(UserError, match="--overwrite"):
        prepare_output(out)
    second = run_slam(world, out, sim_config(), progress=False, overwrite=True)
    assert not stale.exists()  # the old run's files were removed first
    assert len(list((out / "keyframes").glob("*.npz"))) == second["counts"]["keyframes"] == first["counts"]["keyframes"]
    # a cache being replayed from inside the folder is never deleted
    with pytest.raises(UserError, match="replays"):
        prepare_output(out, overwrite=True, keep=out / "frontend_cache")


def test_outputs_follow_the_run_and_map_respects_its_cap(world: Path, tmp_path: Path) -> None:
    config = sim_config()
    config.output.checkpoint_seconds = 0.0
    config.output.max_map_points = 5000
    seen = []

    def watch(pipeline, submap_id):  # the checkpoint of the previous submap is on disk already
        if submap_id >= 2:
            summary = json.loads((tmp_path / "out" / "summary.json").read_text())
            seen.append((summary["status"], summary["counts"]["submaps"]))

    summary = run_slam(world, tmp_path / "out", config, progress=False, on_submap=watch)
    assert seen and all(status == "running" for status, _ in seen)
    assert [count for _, count in seen] == list(range(2, 2 + len(seen)))
    assert summary["status"] == "complete" and summary["format"]["version"] == 3
    xyz, _ = read_ply(tmp_path / "out" / "map.ply")
    assert len(xyz) == summary["map_points"] == 5000
    stamps, _ = read_tum_trajectory(tmp_path / "out" / "trajectory_gt.txt")
    assert len(stamps) == summary["counts"]["keyframes"]
    keyframe = load_result(tmp_path / "out").keyframes[0].load()
    assert keyframe.confidence.shape == keyframe.mask.shape and keyframe.colors.dtype == np.uint8
    # the mask keeps the top 75 % (exact at the stored, every-second pixels)
    assert keyframe.confidence[::2, ::2][keyframe.mask[::2, ::2]].min() >= 25 - 0.5


def test_sigint_finishes_the_submap_and_writes_everything(tmp_path: Path) -> None:
    world = write_synthetic_sequence(tmp_path / "long", num_frames=900, width=96, height=72, seed=3)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "sl4slam.cli", "run", str(world), "--out", str(out), "--frontend", "simulated",
         "--tau-disparity", "7.5", "--submap-size", "4", "--retrieval", "none", "--checkpoint-seconds", "0", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (out / "summary.json").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "interrupted after" in stderr and str(out) in stderr and "Traceback" not in stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["counts"]["keyframes"] > 0
    stamps, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(stamps) == summary["counts"]["keyframes"] and np.isfinite(poses).all()
    assert len(read_ply(out / "map.ply")[0]) == summary["map_points"] > 0
    assert not list(out.rglob("*.tmp*"))
    frames_total = len((world / "rgb.txt").read_text().splitlines()) - 1
    assert summary["counts"]["frames"] < frames_total  # it really stopped early


@pytest.mark.parametrize("metres, text", [(0.0312, "0.0312 m"), (0.00421, "4.21 mm"), (9.03e-6, "9.03 µm"),
                                          (1.4e-9, "1.4 nm"), (1.4e-15, "< 1 nm"), (0.0, "0 m")])
def test_lengths_read_well_down_to_a_nanometre(metres: float, text: str) -> None:
    assert format_length(metres) == text


@pytest.mark.parametrize("signum, exit_code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_ends_the_run_with_128_plus_its_number(world: Path, tmp_path: Path, signum, exit_code) -> None:
    def send(pipeline, submap_id):
        if submap_id == 1:
            os.kill(os.getpid(), signum)

    with pytest.raises(RunInterrupted, match="interrupted after") as caught:
        run_slam(world, tmp_path / "out", sim_config(), progress=False, on_submap=send)
    assert caught.value.exit_code == exit_code
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["status"] == "interrupted"


def test_missing_weights_offline_fail_before_any_frame_is_read(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
    read = []
    original = io.ImageFolderSource._load
    monkeypatch.setattr(io.ImageFolderSource, "_load", lambda self, position: read.append(position) or original(self, position))
    config = SLAMConfig()  # the VGGT frontend with its default hub id
    config.retrieval.kind = "none"
    start = time.perf_counter()
    with pytest.raises(MissingWeightsError, match="HF_HUB_OFFLINE") as caught:
        run_slam(folder, tmp_path / "out", config, progress=False)
    assert "\n" not in str(caught.value) and "--weights" in str(caught.value)
    assert read == []
    assert time.perf_counter() - start < 30  # generous: the check itself is a cache lookup


def test_the_simulated_frontend_on_plain_images_says_what_it_needs(tmp_path: Path) -> None:
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
    with pytest.raises(UserError, match="depth and ground-truth poses"):
        run_slam(folder, tmp_path / "out", sim_config(), progress=False)


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_a_truncated_image_is_skipped_once_and_listed(tmp_path: Path, suffix: str, caplog) -> None:
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        cv2.imwrite(str(folder / f"{i:04d}{suffix}"), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    data = (folder / f"0002{suffix}").read_bytes()
    (folder / f"0002{suffix}").write_bytes(data[: len(data) // 2])
    source = io.open_source(folder)
    with caplog.at_level("WARNING", logger="sl4slam"):
        frames = list(source)
    assert [f.index for f in frames] == [0, 1, 3]
    assert len(source.skipped) == 1 and f"0002{suffix}" in source.skipped[0]
    assert len([r for r in caplog.records if "0002" in r.getMessage()]) == 1


def test_progress_outside_a_terminal_is_plain_lines(world: Path, tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "sl4slam.cli", "run", str(world), "--out", str(tmp_path / "out"), "--frontend", "simulated",
         "--tau-disparity", "7.5", "--submap-size", "4", "--retrieval", "none", "--progress-every", "2"],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr and "\r" not in proc.stdout
    lines = [line for line in proc.stderr.splitlines() if line.startswith("sl4slam: ")]
    assert lines and all("submaps" in line and "frames" in line for line in lines)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    # a line every second submap, and a last one with the final count unless the last line had it
    # already (a log never ends stale)
    assert summary["counts"]["submaps"] // 2 <= len(lines) <= summary["counts"]["submaps"] // 2 + 1
    assert lines[-1].startswith(f"sl4slam: {summary['counts']['frames']}/") and f"{summary['counts']['submaps']} submaps" in lines[-1]
    assert f"ATE RMSE {format_length(summary['ate']['rmse'])}" in proc.stdout
