"""Pieces shared by the frame sources: image decoding, natural ordering, the indexed-source base."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import sys
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from sl4slam.errors import UserError
from sl4slam.types import Frame

logger = logging.getLogger("sl4slam")

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm"})
VIDEO_EXTENSIONS = frozenset(
    {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".3gp", ".mts", ".ts"}
)

_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def natural_key(path: Path) -> tuple:
    """Sort key: the number nearest the extension (``img_2_0010.png`` -> 10), then the name.

    Names without any number sort after the numbered ones, alphabetically. Decimal numbers
    (TUM-style ``1305031102.175304.png``) compare by value.
    """
    numbers = _NUMBER.findall(path.stem)
    if not numbers:
        return (1, 0.0, path.name)
    return (0, float(numbers[-1]), path.name)


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Within the block, what native libraries write to the process's stderr (file descriptor 2) is
    dropped: FFmpeg's "moov atom not found" and OpenCV's warnings while a video is probed, which the
    source reports itself in one line. Python's own ``sys.stderr`` is flushed first; when the
    descriptor cannot be duplicated nothing is redirected."""
    try:
        sys.stderr.flush()
    except (AttributeError, OSError, ValueError):
        pass
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def is_truncated(data: bytes) -> bool:
    """Whether an encoded JPEG or PNG stops before its end marker (a partial copy or download).

    OpenCV decodes a truncated JPEG into a half-grey image without an error, and prints library
    messages for a truncated PNG: both are caught here first. Other formats fail to decode.
    """
    if data[:2] == b"\xff\xd8":  # JPEG: must end with the EOI marker (trailing padding allowed)
        return not data.rstrip(b"\x00").endswith(b"\xff\xd9")
    if data[:8] == b"\x89PNG\r\n\x1a\n":  # PNG: the last chunk is IEND (length, type, CRC)
        return data[-8:-4] != b"IEND"
    return False


def decode_image(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray | None:
    """The decoded image, or ``None`` for a missing, empty, truncated or undecodable file."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return None
    if not data or is_truncated(data):
        return None
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # the caller reports failures once
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    finally:
        cv2.utils.logging.setLogLevel(level)
    return image if image is not None and image.size else None


def read_rgb(path: Path) -> np.ndarray | None:
    """Decode an image as ``(H, W, 3)`` uint8 RGB; ``None`` when it cannot be decoded or is truncated.

    Grey images are replicated to 3 channels, alpha is dropped, 16-bit colour is scaled to 8 bits.
    """
    image = decode_image(path)
    if image is None:
        return None
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        # Float images (EXR, TIFF): assume [0, 1].
        image = np.clip(np.asarray(image, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.shape[2] == 1:
        return np.repeat(image, 3, axis=2)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, metres_per_unit: float, invalid_value: int | None = None) -> np.ndarray | None:
    """Decode a 16-bit depth PNG as ``(H, W)`` float32 metres (0 where invalid); ``None`` on failure.

    Args:
        metres_per_unit: e.g. 1/5000 for TUM, 1/1000 for 7-Scenes.
        invalid_value: raw value meaning "no measurement" besides 0 (7-Scenes uses 65535).
    """
    raw = decode_image(path)
    if raw is None or raw.ndim != 2 or raw.dtype not in (np.uint16, np.uint8):
        return None
    depth = raw.astype(np.float32) * np.float32(metres_per_unit)
    if invalid_value is not None:
        depth[raw == invalid_value] = 0.0
    return depth


def check_stride(stride: int, max_frames: int) -> None:
    if int(stride) < 1:
        raise UserError(f"stride must be a positive integer, got {stride}; use 1 to keep every frame")
    if int(max_frames) < 0:
        raise UserError(f"max_frames must be >= 0 (0 = all frames), got {max_frames}")


def select(items: Sequence, stride: int, max_frames: int) -> list:
    """Every ``stride``-th item, at most ``max_frames`` of them (0 = no limit)."""
    check_stride(stride, max_frames)
    chosen = list(items)[:: int(stride)]
    return chosen[: int(max_frames)] if max_frames else chosen


class IndexedSource(ABC):
    """Base of the sources whose frames are known up front (folders, datasets).

    Subclasses fill ``self._items`` (one entry per output frame, already strided) and
    implement ``_load(position) -> Frame | None``; ``None`` marks an unreadable input, which
    iteration skips with a warning and records in ``skipped``. ``Frame.index`` is the
    position in ``_items``, so a skipped input leaves a gap in the indices.
    """

    name: str
    skipped: list[str]
    _items: list
    K: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self._items)

    @abstractmethod
    def _image_path(self, position: int) -> Path:
        """The image file of ``position`` (for its size, read from the header alone)."""

    def image_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the first frame, from its file's header (no pixels decoded)."""
        if not self._items:
            return None
        from PIL import Image

        try:
            with Image.open(self._image_path(0)) as image:
                return tuple(image.size)
        except (OSError, NotImplementedError):
            return None

    def calibration(self) -> np.ndarray | None:
        """``(3, 3)`` intrinsics the source knows for its frames (a dataset's published ones), or ``None``."""
        return None if self.K is None else self.K.copy()

    @abstractmethod
    def _load(self, position: int) -> Frame | None:
        """The frame at ``position``, or ``None`` when that input cannot be read."""

    def _describe(self, position: int) -> str:
        return f"frame {position}"

    def _record_skip(self, position: int) -> None:
        entry = f"{self._describe(position)}: could not be decoded"
        if entry not in self.skipped:
            self.skipped.append(entry)
            logger.warning("skipping unreadable input %s", entry)

    def __iter__(self) -> Iterator[Frame]:
        for position in range(len(self._items)):
            frame = self._load(position)
            if frame is None:
                self._record_skip(position)
                continue
            yield frame

    def get(self, index: int) -> Frame:
        """Random access by ``Frame.index``; raises UserError when out of range or unreadable."""
        if not 0 <= int(index) < len(self._items):
            raise UserError(f"frame index {index} is out of range for {self.name} ({len(self._items)} frames)")
        frame = self._load(int(index))
        if frame is None:
            self._record_skip(int(index))
            raise UserError(f"{self._describe(int(index))} in {self.name} could not be decoded; check or remove that file")
        return frame

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, frames={len(self)}, skipped={len(self.skipped)})"
