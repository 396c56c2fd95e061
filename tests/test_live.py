"""The live source: a video file played at its frame rate stands in for a camera; a slow consumer
drops frames (counted, never queued), keyframes are kept for re-reading, Ctrl-C ends cleanly, and
a missing camera or an unreachable stream is one line within 5 s."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from sl4slam.errors import UserError
from sl4slam.io import LiveSource, open_source

FPS = 30


def write_video(path: Path, frames: int, fps: int = FPS, size: tuple[int, int] = (64, 48)) -> Path:
    """An MJPG AVI whose frame i shows the number i as a grey level band and a moving square."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    for i in range(frames):
        image = np.full((size[1], size[0], 3), 40, np.uint8)
        image[:8] = (i * 4) % 256
        x = 4 + (i % (size[0] - 16))
        image[20:32, x:x + 12] = 220
        writer.write(image)
    writer.release()
    return path


def test_slow_consumer_drops_frames_and_counts_them(tmp_path: Path) -> None:
    video = write_video(tmp_path / "v.avi", frames=60)
    source = LiveSource(video, realtime=True)
    start = time.monotonic()
    frames = []
    for frame in source:
        frames.append((frame.index, frame.timestamp, int(frame.path.split("#")[1])))
        time.sleep(0.1)  # a consumer at 10 frames/s behind a 30 frames/s stream
    elapsed = time.monotonic() - start
    source.close()
    indices, stamps, raw = map(np.array, zip(*frames))
    assert elapsed >= 0.9 * 60 / FPS  # played at its frame rate, not as fast as it decodes
    assert source.delivered + source.dropped == 60  # every frame was either handed out or dropped
    assert source.dropped >= 30 and 12 <= source.delivered <= 30
    np.testing.assert_array_equal(indices, np.arange(len(frames)))  # indices count delivered frames
    assert np.all(np.diff(raw) >= 1) and np.all(np.diff(stamps) > 0)
    np.testing.assert_allclose(stamps, raw / FPS)


def test_fast_consumer_sees_every_frame_in_order(tmp_path: Path) -> None:
    video = write_video(tmp_path / "v.avi", frames=20)
    with LiveSource(video, realtime=True) as source:
        raw = [int(frame.path.split("#")[1]) for frame in source]
    # a consumer that waits on the slot never falls behind a 30 frames/s file
    assert source.dropped <= 1 and raw == sorted(raw) and raw[-1] == 19


def test_kept_keyframes_are_re_readable_exactly(tmp_path: Path) -> None:
    video = write_video(tmp_path / "v.avi", frames=30)
    decided = {"count": 0}
    source = LiveSource(video, realtime=False, keyframe_counter=lambda: decided["count"], spool_dir=tmp_path / "spool")
    seen = {}
    for frame in source:
        seen[frame.index] = frame.rgb.copy()
        if frame.index % 7 == 0:  # the consumer decides this one is a keyframe
            decided["count"] += 1
    assert source.kept == [i for i in seen if i % 7 == 0]
    for index in source.kept:
        np.testing.assert_array_equal(source.get(index).rgb, seen[index])
    with pytest.raises(UserError, match="not kept"):
        source.get(1)
    assert len(list((tmp_path / "spool").glob("*.png"))) == len(source.kept)
    source.close()


def test_without_a_counter_the_source_keeps_its_own_keyframes(tmp_path: Path) -> None:
    from sl4slam.keyframes import KeyframeSelector

    video = write_video(tmp_path / "v.avi", frames=40)
    with LiveSource(video) as source:
        frames = [frame for frame in source]  # (list() would size itself by len(), an upper bound here)
        selector = KeyframeSelector()
        expected = [f.index for f in frames if selector.is_keyframe(f.rgb)]
        assert source.kept == expected and len(expected) >= 2
        spool = source.spool_dir
    assert not spool.exists()  # a temporary spool folder goes with the source


@pytest.mark.parametrize("spec, words", [("7", "no camera at index 7"), ("rtsp://127.0.0.1:9/none", "unreachable"),
                                         ("http://127.0.0.1:9/stream.mjpg", "unreachable")])
def test_missing_camera_or_stream_is_one_line_within_5_s(tmp_path: Path, spec: str, words: str) -> None:
    start = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "sl4slam.cli", "run", spec, "--out", str(tmp_path / "o"),
                           "--frontend", "simulated", "--quiet"], capture_output=True, text=True, timeout=120)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and words in lines[0], proc.stderr
    with pytest.raises(UserError, match=words):
        open_source(spec)
    assert time.monotonic() - start < 5.0 + 30.0  # interpreter start-up included; the open itself:
    start = time.monotonic()
    with pytest.raises(UserError):
        LiveSource(spec)
    assert time.monotonic() - start < 5.0


def test_ctrl_c_ends_the_iteration_cleanly(tmp_path: Path) -> None:
    video = write_video(tmp_path / "v.avi", frames=300)  # 10 s at 30 frames/s
    script = textwrap.dedent(f"""
        import time
        from sl4slam.io import LiveSource
        source = LiveSource({str(video)!r}, realtime=True)
        print("ready", flush=True)
        count = 0
        for frame in source:
            count += 1
        print("ended after", count, "frames;", source.dropped, "dropped", flush=True)
        source.close()
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ})
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "ended after" in out and "Traceback" not in err
    count = int(out.split("ended after")[1].split()[0])
    assert 5 <= count < 300


def test_pipeline_runs_on_a_video_played_at_its_frame_rate(tmp_path: Path) -> None:
    """End to end: the synthetic world as a video at 30 frames/s; the simulated frontend takes its
    ground truth from the world by raw frame number (a live camera has none)."""
    from result_folders import small_world_config
    from sl4slam.frontend.simulated import SimulatedFrontend
    from sl4slam.pipeline import SLAMPipeline
    from sl4slam.synthetic import write_synthetic_sequence

    world = open_source(str(write_synthetic_sequence(tmp_path / "w", num_frames=120, width=96, height=72, seed=0)))
    writer = cv2.VideoWriter(str(tmp_path / "w.avi"), cv2.VideoWriter_fourcc(*"FFV1"), FPS, (96, 72))
    for frame in world:
        writer.write(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    writer.release()

    class WithTruth(SimulatedFrontend):
        requires_ground_truth = False

        def reconstruct(self, frames, submap_id):
            full = []
            for frame in frames:
                truth = world.get(int(frame.path.split("#")[1]))
                full.append(type(truth)(**{**truth.__dict__, "index": frame.index, "rgb": frame.rgb}))
            return super().reconstruct(full, submap_id)

    config = small_world_config(perspective=0.05)
    config.retrieval.kind = "none"
    source = LiveSource(tmp_path / "w.avi", realtime=True)
    pipeline = SLAMPipeline(config, WithTruth(config.sim))
    source.keyframe_counter = lambda: pipeline.selector.num_keyframes
    result = pipeline.run(source, progress=False)
    source.close()
    assert source.delivered + source.dropped == 120
    assert result.stats["frames"] == source.delivered and len(result.keyframes) >= 2
    assert source.kept == [k.frame_index for k in result.keyframes]  # exactly the keyframes were kept
    assert np.isfinite(result.T_world_cam).all()
