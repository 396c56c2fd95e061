"""Frames from a video file, decoded with OpenCV."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from sl4slam.errors import UserError
from sl4slam.io._common import check_stride, logger, native_stderr_silenced
from sl4slam.types import Frame

DEFAULT_FPS = 30.0


class VideoSource:
    """Every ``stride``-th frame of a video file.

    ``Frame.index`` counts output frames (0, 1, 2, ...); ``Frame.timestamp`` is the raw frame
    number divided by the container's frame rate (30 fps when it reports none). ``len`` comes
    from the container's frame count (counted by decoding when the container has none); a
    frame that fails to decode mid-stream ends iteration early, recorded in ``skipped``.

    Args:
        path: video file.
        stride: keep every ``stride``-th frame.
        max_frames: keep at most this many frames (0 = all).
        K: optional ``(3, 3)`` intrinsics attached to every frame.
    """

    def __init__(self, path: str | Path, stride: int = 1, max_frames: int = 0, K: np.ndarray | None = None):
        path = Path(path)
        check_stride(stride, max_frames)
        if not path.exists():
            raise UserError(f"video file {path} does not exist; pass an existing video file")
        if not path.is_file():
            raise UserError(f"{path} is not a file; pass a video file")
        self.path = path
        self.name = path.stem
        self.stride = int(stride)
        self.skipped: list[str] = []
        self.has_ground_truth = False
        self.K = None if K is None else np.asarray(K, np.float64).reshape(3, 3)
        with native_stderr_silenced():  # a broken file is reported below in one line, not in FFmpeg's words
            capture = self._open()
            try:
                ok, first = capture.read()
                fps = capture.get(cv2.CAP_PROP_FPS)
                raw_count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
                if ok and first is not None and raw_count <= 0:
                    raw_count = 1
                    while capture.grab():
                        raw_count += 1
            finally:
                capture.release()
        if not ok or first is None:
            raise UserError(f"video {path} contains no decodable frames; re-encode it (e.g. H.264 mp4) or check the file")
        self.fps = float(fps) if fps and math.isfinite(fps) and fps > 0 else DEFAULT_FPS
        self.raw_frame_count = raw_count
        count = math.ceil(raw_count / self.stride)
        self._len = min(count, int(max_frames)) if max_frames else count

    def _open(self) -> cv2.VideoCapture:
        with native_stderr_silenced():  # FFmpeg's messages about the container; a failure is one line below
            capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            capture.release()
            raise UserError(f"cannot open video {self.path}: OpenCV does not recognise it; check the file or convert it to mp4")
        return capture

    def __len__(self) -> int:
        return self._len

    def image_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the frames, from the container (no frame decoded)."""
        capture = self._open()
        try:
            return int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        finally:
            capture.release()

    def calibration(self) -> np.ndarray | None:
        """The intrinsics given to the source, or ``None`` (a video file states none)."""
        return None if self.K is None else self.K.copy()

    def _frame(self, index: int, bgr: np.ndarray) -> Frame:
        raw_index = index * self.stride
        return Frame(
            index=index,
            timestamp=raw_index / self.fps,
            rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
            K=None if self.K is None else self.K.copy(),
            path=f"{self.path}#{raw_index}",
        )

    def __iter__(self) -> Iterator[Frame]:
        capture = self._open()
        try:
            for index in range(self._len):
                if index > 0:
                    # Skip the frames between two kept ones without decoding them.
                    for _ in range(self.stride - 1):
                        if not capture.grab():
                            break
                ok, bgr = capture.read()
                if not ok or bgr is None:
                    entry = f"{self.path.name} frame {index * self.stride}: could not be decoded (stream ended early)"
                    if entry not in self.skipped:
                        self.skipped.append(entry)
                        logger.warning("%s", entry)
                    return
                yield self._frame(index, bgr)
        finally:
            capture.release()

    def get(self, index: int) -> Frame:
        """Random access by ``Frame.index`` (seeks; exact for intra-only codecs, close otherwise)."""
        if not 0 <= int(index) < self._len:
            raise UserError(f"frame index {index} is out of range for video {self.name} ({self._len} frames)")
        capture = self._open()
        try:
            capture.set(cv2.CAP_PROP_POS_FRAMES, int(index) * self.stride)
            ok, bgr = capture.read()
        finally:
            capture.release()
        if not ok or bgr is None:
            raise UserError(f"frame {int(index) * self.stride} of video {self.path} could not be decoded")
        return self._frame(int(index), bgr)

    def __repr__(self) -> str:
        return f"VideoSource(name={self.name!r}, frames={len(self)}, fps={self.fps:g}, stride={self.stride})"
