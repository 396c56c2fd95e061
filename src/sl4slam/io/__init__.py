"""Sequence input/output: frame sources and TUM-format trajectories.

``open_source(path)`` picks the reader from what ``path`` is:

- a video file (by extension)                             -> :class:`VideoSource`
- a folder with ``rgb.txt`` (or that ``rgb.txt`` itself)  -> :class:`TumSource`
- a folder with ``frame-XXXXXX.color.*`` files            -> :class:`SevenScenesSource`
- any other folder                                        -> :class:`ImageFolderSource`
- a camera index (``0``) or a stream URL (rtsp://, http://) -> :class:`LiveSource` (frames as
  they arrive; see ``sl4slam.io.live``)

Every source yields :class:`sl4slam.types.Frame` records lazily (images are decoded when
iterated or fetched with ``get``) and lists unreadable inputs in ``skipped``.
"""

from __future__ import annotations

from pathlib import Path

from sl4slam.errors import UserError
from sl4slam.io._common import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, natural_key, read_depth, read_rgb
from sl4slam.io.image_folder import ImageFolderSource
from sl4slam.io.settings import SourceConfig
from sl4slam.io.live import LiveSource, is_live_spec
from sl4slam.io.memory import ListSource
from sl4slam.io.seven_scenes import SevenScenesSource, is_seven_scenes_folder
from sl4slam.io.tum import (
    TUM_DEPTH_SCALE,
    TumSource,
    associate,
    read_tum_trajectory,
    tum_intrinsics,
    write_tum_trajectory,
)
from sl4slam.io.video import VideoSource
from sl4slam.types import FrameSource

__all__ = [
    "open_source",
    "ImageFolderSource",
    "VideoSource",
    "TumSource",
    "SevenScenesSource",
    "ListSource",
    "LiveSource",
    "read_tum_trajectory",
    "write_tum_trajectory",
    "tum_intrinsics",
    "associate",
    "natural_key",
    "read_rgb",
    "read_depth",
    "TUM_DEPTH_SCALE",
]

_KINDS = "an image folder, a video file, a TUM RGB-D / 7-Scenes sequence folder, a camera index or a stream URL"


def open_source(path: str | Path, settings: "SourceConfig | None" = None, *, stride: int | None = None,
                max_frames: int | None = None) -> FrameSource:
    """Open ``path`` as a frame source, detecting its kind (see the module docstring).

    Args:
        path: video file, image folder, TUM sequence folder (or its ``rgb.txt``), 7-Scenes
            sequence folder, camera index or stream URL.
        settings: the run's ``[source]`` settings (``config.source``): stride and max_frames.
        stride: keep every ``stride``-th frame (overrides ``settings``).
        max_frames: keep at most this many frames, 0 = all (overrides ``settings``).

    Raises:
        UserError: the path does not exist, is an unsupported file, or holds no readable frames.
    """
    stride = int(stride if stride is not None else settings.stride if settings is not None else 1)
    max_frames = int(max_frames if max_frames is not None else settings.max_frames if settings is not None else 0)
    if is_live_spec(str(path)) and not Path(path).exists():
        return LiveSource(str(path), max_frames=max_frames, stride=stride)
    path = Path(path).expanduser()
    if not path.exists():
        raise UserError(f"input {path} does not exist; pass {_KINDS}")
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix in VIDEO_EXTENSIONS:
            return VideoSource(path, stride=stride, max_frames=max_frames)
        if path.name == "rgb.txt":
            return TumSource(path.parent, stride=stride, max_frames=max_frames)
        if suffix in IMAGE_EXTENSIONS:
            raise UserError(f"{path} is a single image; pass the folder that holds the sequence ({path.parent})")
        raise UserError(f"{path} is not a supported input (unknown file type {suffix or 'without extension'}); pass {_KINDS}")
    if (path / "rgb.txt").is_file():
        return TumSource(path, stride=stride, max_frames=max_frames)
    if is_seven_scenes_folder(path):
        return SevenScenesSource(path, stride=stride, max_frames=max_frames)
    sequences = sorted(p.name for p in path.glob("seq-*") if is_seven_scenes_folder(p))
    if sequences:
        raise UserError(f"{path} is a 7-Scenes scene with several sequences; pass one of them, e.g. {path / sequences[0]}")
    return ImageFolderSource(path, stride=stride, max_frames=max_frames)
