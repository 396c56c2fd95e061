"""Frames from a folder of images, in natural order."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from sl4slam.errors import UserError
from sl4slam.io._common import IMAGE_EXTENSIONS, IndexedSource, logger, natural_key, read_rgb, select
from sl4slam.types import Frame


class ImageFolderSource(IndexedSource):
    """Every image file directly inside ``folder``, ordered by the number nearest the extension.

    Non-image files are ignored. Files whose header is not a known image format are skipped at
    construction; files that pass the header check but fail to decode are skipped when first read.
    Both kinds are listed in ``skipped`` with a warning. ``Frame.timestamp`` is the frame index
    (no timing information exists); ``depth``, ``T_world_cam`` and ``K`` are ``None`` unless
    ``K`` is given.

    Args:
        folder: directory holding the images.
        stride: keep every ``stride``-th image.
        max_frames: keep at most this many frames (0 = all).
        K: optional ``(3, 3)`` intrinsics attached to every frame.
    """

    def __init__(self, folder: str | Path, stride: int = 1, max_frames: int = 0, K: np.ndarray | None = None):
        folder = Path(folder)
        if not folder.exists():
            raise UserError(f"image folder {folder} does not exist; pass an existing folder of images")
        if not folder.is_dir():
            raise UserError(f"{folder} is not a folder; pass a folder of images")
        self.name = folder.name or str(folder)
        self.folder = folder
        self.skipped: list[str] = []
        self.has_ground_truth = False
        self.K = None if K is None else np.asarray(K, np.float64).reshape(3, 3)
        candidates = sorted(
            (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS), key=natural_key
        )
        if not candidates:
            raise UserError(
                f"folder {folder} contains no images ({', '.join(sorted(IMAGE_EXTENSIONS))}); "
                "pass a folder of images, a video file, or a TUM / 7-Scenes sequence folder"
            )
        readable = []
        for path in candidates:
            # Header check only (cheap); full decoding happens lazily.
            if path.stat().st_size > 0 and cv2.haveImageReader(str(path)):
                readable.append(path)
            else:
                self.skipped.append(f"{path.name}: not a readable image")
                logger.warning("skipping unreadable image %s", path)
        if not readable:
            raise UserError(f"none of the {len(candidates)} image files in {folder} can be read; they look corrupt")
        self._items: list[Path] = select(readable, stride, max_frames)

    @property
    def paths(self) -> list[Path]:
        """The image files, in frame order."""
        return list(self._items)

    def _image_path(self, position: int) -> Path:
        return self._items[position]

    def _describe(self, position: int) -> str:
        return self._items[position].name

    def _load(self, position: int) -> Frame | None:
        path = self._items[position]
        rgb = read_rgb(path)
        if rgb is None:
            return None
        return Frame(
            index=position,
            timestamp=float(position),
            rgb=rgb,
            K=None if self.K is None else self.K.copy(),
            path=str(path),
        )
