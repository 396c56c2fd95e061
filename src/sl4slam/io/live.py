"""Live frames from a camera (an index such as ``0``) or a stream URL (rtsp://, http://, ...).

A reader thread pulls frames from OpenCV's capture as they arrive and puts each into a one-slot
buffer; the consumer (the pipeline) takes the newest frame when it is ready for one. When the
consumer falls behind, the frame waiting in the slot is replaced by the newer one and counted in
``dropped``: nothing queues up, so latency and memory stay bounded. A video file can be played
the same way at its own frame rate (``realtime=True``).

A video file can also be played on a :class:`ManualClock` (``clock=``), which makes the same
policy deterministic: no reader thread; when the consumer asks for a frame, every frame whose
time (``raw index / fps``) has come on the clock goes through the one-slot buffer (the newest
wins, the others are dropped), and when none has come the clock jumps to the next one (the
consumer waits for it). The consumer's processing time is whatever it advances the clock by, so
a slow consumer drops exactly the frames it would drop at that speed in real time, whatever the
machine's load: this is how the drop policy is tested.

Length: unknown up front. ``len()`` is an upper bound (``max_frames``, or ``sys.maxsize``) so that
a consumer written for finite sources runs unchanged, and ``live = True`` tells a consumer not to
trust it (iterate; ``list(source)`` would try to size itself by it); iteration ends when the stream ends, after
``max_frames`` frames, or on Ctrl-C (the first Ctrl-C during iteration ends it cleanly so the run
can write its outputs; a second one interrupts as usual).

Random access: ``get(index)`` answers only for frames the source kept. The pipeline re-reads old
keyframes (loop-closure frames) by index, so the source keeps exactly the keyframes: it learns
which frames were keyframes from a keyframe counter it is given (``keyframe_counter``, e.g. the
pipeline's ``KeyframeSelector.num_keyframes``; the counter grows by one when the frame just
handed out became a keyframe), or, without one, from a keyframe selector of its own with the
default settings. Kept frames are written losslessly (PNG) to a spool folder on disk (a
temporary folder unless given), so memory does not grow with the run; the folder holds one image
per keyframe and is removed by ``close()`` when it was temporary.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from sl4slam.errors import UserError
from sl4slam.types import Frame

logger = logging.getLogger("sl4slam")

STREAM_PREFIXES = ("rtsp://", "rtsps://", "rtmp://", "http://", "https://", "udp://", "tcp://", "srt://")
OPEN_TIMEOUT_S = 5.0
"""Seconds to wait for a camera or stream to deliver its first frame before giving up."""


class ManualClock:
    """A clock that moves only when told (seconds from 0): the time base of a video file played
    deterministically by :class:`LiveSource` (``clock=``); a consumer advances it by the time its
    work would take."""

    def __init__(self, start: float = 0.0) -> None:
        self._now = float(start)

    def now(self) -> float:
        return self._now

    def advance(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError(f"a clock does not go back ({seconds} s)")
        self._now += float(seconds)

    def advance_to(self, time: float) -> None:
        self._now = max(self._now, float(time))


def is_live_spec(spec: str) -> bool:
    """True for a camera index (``"0"``) or a stream URL."""
    spec = str(spec).strip()
    return spec.isdigit() or spec.lower().startswith(STREAM_PREFIXES)


def _quiet_opencv() -> None:
    # OpenCV's backends (and FFmpeg inside them) log their own warnings for a missing camera or an
    # unreachable stream; our one line says it all. FFmpeg reads its level when first used.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # pragma: no cover - very old OpenCV
        pass


class LiveSource:
    """Frames of a camera, a stream, or a video file played at its frame rate.

    Args:
        spec: camera index (``0`` or ``"0"``), stream URL, or video file path (with ``realtime``).
        max_frames: stop after this many delivered frames (0: until the stream ends or Ctrl-C).
        realtime: for a file, play it at its frame rate (frames the consumer misses are dropped).
        open_timeout: seconds to wait for the first frame (a clear error after that).
        spool_dir: where kept frames are written (a temporary folder when ``None``).
        keyframe_counter: callable returning how many keyframes the consumer has selected so far.
        stride: keep every ``stride``-th frame read from the device (before the one-slot buffer).
        clock: play a video file on this :class:`ManualClock` (deterministic; see the module
            docstring) instead of in a reader thread; ``realtime`` is implied.

    Attributes:
        delivered: frames handed to the consumer; dropped: frames replaced in the slot unseen;
        read: frames read from the device (``delivered + dropped + stride skips`` at the end).
        fps: the device's reported frame rate (30 when unknown).
    """

    live = True
    has_ground_truth = False

    def __init__(self, spec: str | int | Path, max_frames: int = 0, realtime: bool = False,
                 open_timeout: float = OPEN_TIMEOUT_S, spool_dir: str | Path | None = None,
                 keyframe_counter: Callable[[], int] | None = None, stride: int = 1,
                 clock: ManualClock | None = None) -> None:
        if int(max_frames) < 0 or int(stride) < 1:
            raise UserError(f"max_frames must be >= 0 and stride >= 1, got {max_frames} and {stride}")
        self.spec = str(spec)
        self.max_frames = int(max_frames)
        self.stride = int(stride)
        self.realtime = bool(realtime) or clock is not None
        self.clock = clock
        self.skipped: list[str] = []
        self.delivered = 0
        self.dropped = 0
        self.read = 0
        self.is_file = not is_live_spec(self.spec)
        if self.is_file and not Path(self.spec).is_file():
            raise UserError(f"{self.spec} is neither a camera index, a stream URL nor a video file")
        if clock is not None and not self.is_file:
            raise UserError(f"only a video file can be played on a manual clock, not {self.spec}")
        self.name = f"camera{self.spec}" if self.spec.isdigit() else (Path(self.spec).stem if self.is_file else self.spec)
        self.keyframe_counter = keyframe_counter
        self._own_selector = None
        self._spool_owned = spool_dir is None
        self.spool_dir = Path(tempfile.mkdtemp(prefix="sl4slam_live_")) if spool_dir is None else Path(spool_dir)
        self.spool_dir.mkdir(parents=True, exist_ok=True)
        self._kept: dict[int, tuple[Path, float]] = {}
        self._last: Frame | None = None  # the frame handed out last (kept or not yet decided)
        self._capture, first = self._open(open_timeout)
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and np.isfinite(fps) and 0 < fps < 1000 else 30.0
        self._slot: tuple[int, float, np.ndarray] | None = None
        self._cond = threading.Condition()
        self._ended = False
        self._stop = threading.Event()
        self._started = time.monotonic()
        self._reader: threading.Thread | None = None
        self._next_raw, self._next_bgr = 0, first  # the manual clock's read position
        if clock is None:
            self._reader = threading.Thread(target=self._read_loop, args=(first,), name=f"sl4slam-live-{self.name}",
                                            daemon=True)
            self._reader.start()

    # ------------------------------------------------------------------ opening
    def _open(self, timeout: float) -> tuple[cv2.VideoCapture, np.ndarray]:
        """Open the device and read its first frame within ``timeout`` seconds, or one clear error."""
        _quiet_opencv()
        box: dict = {}

        def attempt() -> None:
            try:
                if self.spec.isdigit():
                    capture = cv2.VideoCapture(int(self.spec))
                elif self.is_file:
                    capture = cv2.VideoCapture(self.spec)
                else:
                    # FFmpeg gives up first (at 80 % of the time), so that its thread has ended when
                    # the open fails; our own join below is the bound for a backend that ignores it
                    # (a process that exits while FFmpeg still waits in a thread aborts)
                    ms = max(1, int(timeout * 800))
                    capture = cv2.VideoCapture(self.spec, cv2.CAP_FFMPEG,
                                               [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms])
                ok, bgr = capture.read() if capture.isOpened() else (False, None)
                box["capture"], box["frame"] = capture, (bgr if ok else None)
            except cv2.error as exc:  # pragma: no cover - backend-specific failures
                box["error"] = str(exc)

        thread = threading.Thread(target=attempt, name=f"sl4slam-open-{self.name}", daemon=True)
        thread.start()
        thread.join(timeout)
        what = (f"no camera at index {self.spec}" if self.spec.isdigit()
                else f"video {self.spec} cannot be read" if self.is_file else f"stream {self.spec} is unreachable")
        if thread.is_alive():
            raise UserError(f"{what} (nothing within {timeout:g} s); check the device or the URL")
        if box.get("frame") is None:
            if box.get("capture") is not None:
                box["capture"].release()
            fix = "check the index (ls /dev/video*)" if self.spec.isdigit() else "check the file or the URL and the network"
            raise UserError(f"{what}: no frame received; {fix}")
        return box["capture"], box["frame"]

    # ------------------------------------------------------------------ reader thread
    def _read_loop(self, first: np.ndarray) -> None:
        bgr, raw = first, 0
        try:
            while not self._stop.is_set():
                if bgr is None:
                    break
                if raw % self.stride == 0:
                    stamp = raw / self.fps if self.is_file else time.monotonic() - self._started
                    if self.realtime and self.is_file:  # pace the file at its frame rate
                        delay = self._started + raw / self.fps - time.monotonic()
                        if delay > 0 and self._stop.wait(delay):
                            break
                    with self._cond:
                        self._offer(raw, stamp, bgr)
                        self._cond.notify_all()
                self.read += 1
                raw += 1
                ok, bgr = self._capture.read()
                if not ok:
                    bgr = None
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify_all()
            self._capture.release()

    def _offer(self, raw: int, stamp: float, bgr: np.ndarray) -> None:
        """Put a frame into the one-slot buffer (the caller holds the lock in threaded mode)."""
        if self._slot is not None:
            self.dropped += 1  # the consumer did not take the previous frame in time
            if self.dropped == 1:  # said once: the run cannot keep up, and what it does about it
                logger.warning("%s: the run is slower than the stream (%.0f Hz): it takes the newest frame when it "
                               "is ready and drops the ones in between (counted in summary.json live.dropped)",
                               self.name, self.fps)
        self._slot = (raw, stamp, bgr)

    def _play_on_clock(self) -> None:
        """Manual clock: offer every frame whose time has come; with none waiting in the slot, move
        the clock to the next kept frame's time (the consumer waits for it)."""
        while self._next_bgr is not None and not self._stop.is_set():
            raw = self._next_raw
            due = raw / self.fps
            if self._slot is not None and due > self.clock.now() + 1e-9:
                break  # not yet: the consumer takes what is in the slot
            if raw % self.stride == 0:
                self.clock.advance_to(due)
                self._offer(raw, due, self._next_bgr)
            self.read += 1
            self._next_raw += 1
            ok, bgr = self._capture.read()
            self._next_bgr = bgr if ok else None
        if self._next_bgr is None and not self._ended:
            self._ended = True
            self._capture.release()

    # ------------------------------------------------------------------ consumer side
    def __len__(self) -> int:
        return self.max_frames if self.max_frames else sys.maxsize

    def image_size(self) -> tuple[int, int] | None:
        """Unknown before the first frame arrives."""
        return None

    def calibration(self) -> np.ndarray | None:
        """A camera or stream states no intrinsics."""
        return None

    @property
    def stopped(self) -> bool:
        """True once :meth:`stop` (or Ctrl-C during iteration) asked the iteration to end."""
        return self._stop.is_set()

    def stop(self) -> None:
        """End iteration after the current frame (what Ctrl-C does)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()

    def _next_frame(self) -> tuple[int, float, np.ndarray] | None:
        if self.clock is not None:
            self._play_on_clock()
        with self._cond:
            self._cond.wait_for(lambda: self._slot is not None or self._ended or self._stop.is_set())
            if self._stop.is_set() or self._slot is None:
                return None
            item, self._slot = self._slot, None
            return item

    def _keyframe_count(self, rgb: np.ndarray | None) -> int:
        if self.keyframe_counter is not None:
            return int(self.keyframe_counter())
        if self._own_selector is None:
            from sl4slam.keyframes import KeyframeSelector

            self._own_selector = KeyframeSelector()
        if rgb is not None:
            self._own_selector.is_keyframe(rgb)
        return self._own_selector.num_keyframes

    def __iter__(self) -> Iterator[Frame]:
        previous_handler = None
        if threading.current_thread() is threading.main_thread():
            def on_interrupt(signum, stack):  # first Ctrl-C: finish cleanly; second: interrupt
                logger.warning("Ctrl-C: ending the live run after this frame (press again to abort)")
                signal.signal(signal.SIGINT, previous_handler or signal.default_int_handler)
                self.stop()

            previous_handler = signal.signal(signal.SIGINT, on_interrupt)
        try:
            seen = self._keyframe_count(None) if self.keyframe_counter is not None else 0
            while not (self.max_frames and self.delivered >= self.max_frames):
                item = self._next_frame()
                if item is None:
                    break
                raw, stamp, bgr = item
                frame = Frame(index=self.delivered, timestamp=float(stamp), rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
                              path=f"{self.name}#{raw}")
                if self.keyframe_counter is None:
                    if self._keyframe_count(frame.rgb) > seen:
                        self._keep(frame)
                        seen += 1
                self.delivered += 1
                self._last = frame
                yield frame
                if self.keyframe_counter is not None:
                    # the consumer has decided on the frame it just received
                    count = self._keyframe_count(None)
                    if count > seen:
                        self._keep(frame)
                        seen = count
        finally:
            self.stop()
            if previous_handler is not None and signal.getsignal(signal.SIGINT) is not previous_handler:
                signal.signal(signal.SIGINT, previous_handler)

    def _keep(self, frame: Frame) -> None:
        path = self.spool_dir / f"{frame.index:08d}.png"
        if not cv2.imwrite(str(path), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise UserError(f"cannot write kept frame {path}; check free space in {self.spool_dir}")
        self._kept[frame.index] = (path, frame.timestamp)

    @property
    def kept(self) -> list[int]:
        """Indices of the frames ``get`` can return."""
        return sorted(self._kept)

    def get(self, index: int) -> Frame:
        """A kept frame (or the frame handed out last) by ``Frame.index``, bit-identical to the one delivered."""
        last = self._last
        if last is not None and last.index == int(index):
            return last
        if int(index) not in self._kept:
            raise UserError(f"frame {index} of live source {self.name} was not kept (only keyframes are); "
                            "a live source cannot re-read other frames")
        path, stamp = self._kept[int(index)]
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise UserError(f"kept frame {path} cannot be read; was the spool folder removed?")
        return Frame(index=int(index), timestamp=stamp, rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), path=str(path))

    def close(self) -> None:
        """Stop the reader and remove the spool folder when it was temporary."""
        self.stop()
        if self._reader is not None:
            self._reader.join(timeout=2.0)
        elif not self._ended:
            self._ended = True
            self._capture.release()
        if self._spool_owned:
            shutil.rmtree(self.spool_dir, ignore_errors=True)

    def __enter__(self) -> "LiveSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"LiveSource(name={self.name!r}, delivered={self.delivered}, dropped={self.dropped}, "
                f"kept={len(self._kept)})")
