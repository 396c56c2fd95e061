"""The live source: a video file played at its frame rate stands in for a camera; a slow consumer
drops frames (counted, never queued), keyframes are kept for re-reading, Ctrl-C ends cleanly, and
a missing camera or an unreachable stream is one line within 5 s.

No assertion depends on how fast this machine runs: the drop policy is checked on a video played
on a manual clock (the consumer's work advances it, so the frames dropped are exact), the reader
thread's real-time playback only by what load cannot change (every frame delivered or dropped,
in order, never faster than its frame rate), Ctrl-C is sent once the consumer has said it holds
a frame and waits for it, and the open timeout by a stream that never answers.
"""

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
from sl4slam.io.live import ManualClock

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


def _raw(frame) -> int:
    """The frame's index in the video (``Frame.index`` counts delivered frames)."""
    return int(frame.path.split("#")[1])


def test_slow_consumer_drops_frames_and_counts_them(tmp_path: Path, caplog) -> None:
    """A consumer that needs 0.1 s per frame behind a 30 frames/s stream: it gets the newest frame
    each time it asks (every third), the two before it are dropped and counted, nothing queues, and
    the run is told once that it cannot keep up."""
    caplog.set_level("WARNING", logger="sl4slam")
    video = write_video(tmp_path / "v.avi", frames=60)
    clock = ManualClock()
    source = LiveSource(video, clock=clock)
    frames = []
    for frame in source:
        frames.append((frame.index, frame.timestamp, _raw(frame)))
        clock.advance(0.1)  # the consumer's work: 10 frames/s
    source.close()
    indices, stamps, raw = map(np.array, zip(*frames))
    # at 0.1 s, 0.2 s, ... frames 3, 6, ... have just arrived; the last frame (59) is handed out after the end
    np.testing.assert_array_equal(raw, list(range(0, 60, 3)) + [59])
    assert source.delivered == 21 and source.dropped == 39 and source.read == 60
    assert source.delivered + source.dropped == 60  # every frame was either handed out or dropped
    np.testing.assert_array_equal(indices, np.arange(len(frames)))  # indices count delivered frames
    np.testing.assert_allclose(stamps, raw / FPS)  # a file's frames are stamped with their time in it
    assert clock.now() == pytest.approx(2.1)  # the stream's 2 s, then the last frame's 0.1 s
    notices = [r for r in caplog.records if "slower than the stream" in r.getMessage()]
    assert len(notices) == 1 and "live.dropped" in notices[0].getMessage()


def test_a_stride_thins_before_the_slot(tmp_path: Path) -> None:
    video = write_video(tmp_path / "v.avi", frames=30)
    clock = ManualClock()
    with LiveSource(video, clock=clock, stride=2) as source:
        raw = []
        for frame in source:
            raw.append(_raw(frame))
            clock.advance(0.1)
    # kept frames 0, 2, 4, ...; at 0.1 s frame 2 (0.067 s) is the newest kept one, at 0.2 s frame 6
    assert raw == [0, 2, 6, 8, 12, 14, 18, 20, 24, 26, 28]
    assert source.read == 30 and source.delivered + source.dropped == 15


def test_real_time_playback_in_a_reader_thread(tmp_path: Path) -> None:
    """The reader thread plays the file at its frame rate; a slow consumer gets a subsequence of
    the frames in order (which ones depends on the machine's speed), every frame handed out or
    dropped, the first and the last one always handed out."""
    video = write_video(tmp_path / "v.avi", frames=60)
    source = LiveSource(video, realtime=True)
    start = time.monotonic()
    frames = []
    for frame in source:
        frames.append((frame.index, frame.timestamp, _raw(frame)))
        time.sleep(0.1)  # a consumer at most 10 frames/s behind a 30 frames/s stream
    elapsed = time.monotonic() - start
    source.close()
    indices, stamps, raw = map(np.array, zip(*frames))
    assert elapsed >= 0.9 * 60 / FPS  # played at its frame rate, not as fast as it decodes (load only slows it)
    assert source.delivered + source.dropped == 60 and source.read == 60
    np.testing.assert_array_equal(indices, np.arange(len(frames)))  # indices count delivered frames
    assert np.all(np.diff(raw) >= 1) and np.all(np.diff(stamps) > 0) and raw[0] == 0 and raw[-1] == 59
    np.testing.assert_allclose(stamps, raw / FPS)


def test_fast_consumer_sees_every_frame_in_order(tmp_path: Path) -> None:
    video = write_video(tmp_path / "v.avi", frames=20)
    clock = ManualClock()
    with LiveSource(video, clock=clock) as source:
        raw = []
        for frame in source:
            raw.append(_raw(frame))
            clock.advance(0.01)  # faster than the stream's 1/30 s
    # a consumer that waits on the slot never falls behind: every frame, in order, at its time
    assert source.dropped == 0 and raw == list(range(20)) and clock.now() == pytest.approx(19 / FPS + 0.01)


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
    # a delivered frame that is neither kept nor the last one handed out (the one-slot reader may drop
    # frames when the consumer is slow, so which frames arrived depends on the machine's load)
    last = max(seen)
    not_kept = next((i for i in seen if i % 7 != 0 and i != last), last + 1000)
    with pytest.raises(UserError, match="not kept"):
        source.get(not_kept)
    assert len(list((tmp_path / "spool").glob("*.png"))) == len(source.kept)
    source.close()


def test_without_a_counter_the_source_keeps_its_own_keyframes(tmp_path: Path) -> None:
    from sl4slam.keyframes import KeyframeSelector

    video = write_video(tmp_path / "v.avi", frames=40)
    # on a manual clock that the test never advances, every frame is delivered: a reader thread's
    # one-slot buffer drops frames when the machine is loaded, which left too few to compare
    with LiveSource(video, clock=ManualClock()) as source:
        frames = [frame for frame in source]  # (list() would size itself by len(), an upper bound here)
        selector = KeyframeSelector()
        expected = [f.index for f in frames if selector.is_keyframe(f.rgb)]
        assert source.kept == expected and len(expected) >= 2
        spool = source.spool_dir
    assert not spool.exists()  # a temporary spool folder goes with the source


@pytest.mark.parametrize("spec, words", [("7", "no camera at index 7"), ("rtsp://127.0.0.1:9/none", "unreachable"),
                                         ("http://127.0.0.1:9/stream.mjpg", "unreachable")])
def test_missing_camera_or_stream_is_one_line(tmp_path: Path, spec: str, words: str) -> None:
    """A missing device or a refused connection is one line (how long the open may wait: the next test)."""
    proc = subprocess.run([sys.executable, "-m", "sl4slam.cli", "run", spec, "--out", str(tmp_path / "o"),
                           "--frontend", "simulated", "--quiet"], capture_output=True, text=True, timeout=300)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and words in lines[0], proc.stderr
    with pytest.raises(UserError, match=words):
        open_source(spec)


def test_a_stream_that_never_answers_is_given_up_after_the_open_timeout() -> None:
    """The open waits at most ``open_timeout`` (5 s by default) for a first frame, then one line: a
    server that accepts the connection and never sends a byte would otherwise hold the open. FFmpeg
    is told to give up at 80 % of it, so that no thread of it is left waiting when the open fails
    (a process that exits meanwhile aborts)."""
    import socket
    import threading

    from sl4slam.io.live import OPEN_TIMEOUT_S

    assert OPEN_TIMEOUT_S == 5.0  # "within 5 s": the default that open_source and the command line use

    def accept(server, accepted):
        try:
            accepted.append(server.accept()[0])
        except OSError:  # closed before FFmpeg connected
            pass

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        accepted: list = []
        threading.Thread(target=accept, args=(server, accepted), daemon=True).start()
        start = time.monotonic()
        with pytest.raises(UserError, match="unreachable") as error:
            LiveSource(f"http://127.0.0.1:{port}/stream.mjpg", open_timeout=0.5)
        elapsed = time.monotonic() - start
        opening = [t.name for t in threading.enumerate() if t.name.startswith("sl4slam-open-")]
        for connection in accepted:
            connection.close()
    assert len(str(error.value).splitlines()) == 1
    assert opening == []  # the thread that tried to open the stream has ended
    assert elapsed >= 0.35  # the wait was ended by a timeout (0.4 s: FFmpeg's), the server never answered ...
    assert elapsed < 60.0  # ... and nothing else held it: a bound only a hang reaches, not a measurement


def test_ctrl_c_ends_the_iteration_cleanly(tmp_path: Path) -> None:
    """Ctrl-C while the consumer holds its fifth frame: the iteration ends after that frame and the
    program goes on (exit 0, no traceback). The consumer says when it holds the frame and then
    waits for the stop, so the count does not depend on when the signal arrives."""
    video = write_video(tmp_path / "v.avi", frames=300)  # 10 s at 30 frames/s
    script = textwrap.dedent(f"""
        import time
        from sl4slam.io import LiveSource
        source = LiveSource({str(video)!r}, realtime=True)
        count = 0
        for frame in source:
            count += 1
            if count == 5:
                print("holding frame", frame.index, flush=True)
                while not source.stopped:  # a consumer busy until Ctrl-C
                    time.sleep(0.01)
        print("ended after", count, "frames;", source.dropped, "dropped", flush=True)
        source.close()
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ})
    try:
        assert proc.stdout.readline().strip() == "holding frame 4"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=300)  # a bound for a hang, not a measurement
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "Ctrl-C" in err
    assert out.startswith("ended after 5 frames;"), out


def test_pipeline_runs_on_a_video_played_at_its_frame_rate(tmp_path: Path) -> None:
    """End to end: the synthetic world as a video at 30 frames/s, played on a manual clock on which
    the pipeline takes 1/60 s per frame and 0.1 s more per keyframe (so it drops the frames that
    arrive meanwhile, the same ones on any machine: the clock moves when the source asks how many
    keyframes the pipeline has made, at each frame, whatever thread finishes the submaps); the
    simulated frontend takes its ground truth from the world by raw frame number (a live camera has
    none)."""
    import dataclasses

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
        capabilities = dataclasses.replace(SimulatedFrontend.capabilities, needs_ground_truth=False)

        def reconstruct(self, frames, submap_id, **options):
            full = []
            for frame in frames:
                truth = world.get(int(frame.path.split("#")[1]))
                full.append(type(truth)(**{**truth.__dict__, "index": frame.index, "rgb": frame.rgb}))
            return super().reconstruct(full, submap_id, **options)

    config = small_world_config(perspective=0.05)
    config.retrieval.kind = "none"
    clock = ManualClock()
    source = LiveSource(tmp_path / "w.avi", clock=clock)
    pipeline = SLAMPipeline.from_config(config, WithTruth(config.sim))
    made = [0]

    def keyframes_made() -> int:  # asked by the source when the pipeline wants the next frame
        count = pipeline.selector.num_keyframes
        clock.advance(1 / 60 + 0.1 * (count - made[0]))  # the work on the frame it just had
        made[0] = count
        return count

    source.keyframe_counter = keyframes_made
    result = pipeline.run(source, progress=False)
    source.close()
    assert source.delivered + source.dropped == 120
    # each keyframe's 0.1 s lets 3 frames arrive, 2 of them dropped (the last keyframe may meet the end)
    assert source.dropped >= 2 * (len(source.kept) - 1) > 0
    assert result.stats["frames"] == source.delivered and len(result.keyframes) >= 2
    assert source.kept == [k.frame_index for k in result.keyframes]  # exactly the keyframes were kept
    assert np.isfinite(result.T_world_cam).all()
