"""Microsoft 7-Scenes sequence folders (``seq-XX`` with ``frame-XXXXXX.{color,depth,pose}.*``).

Colour is ``.color.png`` (or ``.jpg``), depth ``.depth.png`` in millimetres with 65535 = invalid,
pose ``.pose.txt`` a 4x4 camera-to-world matrix whose rotation is not exactly orthonormal (it is
projected to SO(3) here). The Kinect recorded at 30 Hz; the published intrinsics are
fx = fy = 585, cx = 320, cy = 240 at 640x480. Images of another size (a resized copy, or the
synthetic 7-Scenes-style sequences of ``sl4slam synth --layout 7scenes``) get those intrinsics
scaled to their size (:func:`seven_scenes_intrinsics`), as the reference evaluations of
VGGT-SLAM and MASt3R-SLAM scale them to their model's resolution.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from sl4slam.errors import UserError
from sl4slam.geometry import project_to_so3
from sl4slam.io._common import IndexedSource, logger, read_depth, read_rgb, select
from sl4slam.types import Frame

SEVEN_SCENES_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
SEVEN_SCENES_SIZE = (640, 480)
"""(width, height) at which ``SEVEN_SCENES_K`` holds."""
SEVEN_SCENES_FPS = 30.0
SEVEN_SCENES_INVALID_DEPTH = 65535

_COLOR = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)


def seven_scenes_intrinsics(width: int, height: int) -> np.ndarray:
    """``(3, 3)`` published intrinsics scaled from 640x480 to ``width`` x ``height`` px.

    Each axis scales by its own ratio (``fx * width / 640``, ``cx * width / 640``, likewise
    ``fy``, ``cy`` with the height), the convention of the reference 7-Scenes evaluations.
    """
    K = SEVEN_SCENES_K.copy()
    K[0] *= float(width) / SEVEN_SCENES_SIZE[0]
    K[1] *= float(height) / SEVEN_SCENES_SIZE[1]
    return K


def is_seven_scenes_folder(folder: Path) -> bool:
    """True when ``folder`` directly holds at least one ``frame-*.color.*`` file."""
    return folder.is_dir() and any(_COLOR.match(p.name) for p in folder.glob("frame-*.color.*"))


def read_seven_scenes_pose(path: Path) -> np.ndarray | None:
    """``(4, 4)`` float64 camera-to-world pose with its rotation projected to SO(3); ``None`` if unreadable."""
    try:
        values = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError):
        return None
    if values.size != 16 or not np.all(np.isfinite(values)):
        return None
    T = values.reshape(4, 4).copy()
    T[:3, :3] = project_to_so3(T[:3, :3])
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


class SevenScenesSource(IndexedSource):
    """One 7-Scenes sequence folder (e.g. ``chess/seq-01``).

    ``Frame.timestamp`` is the frame number / 30 Hz; ``depth`` is in metres (0 = invalid);
    ``T_world_cam`` the projected pose (``None`` if its file is missing or unreadable);
    ``K`` the published 585 px intrinsics scaled to the image's size
    (:func:`seven_scenes_intrinsics`) unless ``K`` is given.

    Args:
        folder: the sequence folder.
        stride: keep every ``stride``-th frame.
        max_frames: keep at most this many frames (0 = all).
        K: override the intrinsics (used as given, whatever the image size).
    """

    def __init__(self, folder: str | Path, stride: int = 1, max_frames: int = 0, K: np.ndarray | None = None):
        folder = Path(folder)
        if not folder.is_dir():
            raise UserError(f"7-Scenes sequence folder {folder} does not exist")
        frames: dict[int, Path] = {}
        for path in folder.iterdir():
            match = _COLOR.match(path.name)
            if match is not None:
                frames.setdefault(int(match.group(1)), path)
        if not frames:
            raise UserError(f"{folder} holds no 7-Scenes frames (frame-XXXXXX.color.png); pass a sequence folder such as seq-01")
        self.folder = folder
        self.name = folder.resolve().name
        self.skipped: list[str] = []
        self.has_ground_truth = True  # every frame has depth and a pose file (unreadable ones are dropped)
        self.K = None if K is None else np.asarray(K, np.float64).reshape(3, 3)
        self._items = select(sorted(frames.items()), stride, max_frames)

    def _describe(self, position: int) -> str:
        return self._items[position][1].name

    def _image_path(self, position: int) -> Path:
        return self._items[position][1]

    def calibration(self) -> np.ndarray | None:
        """The given intrinsics, else 7-Scenes' published ones for the frames' size."""
        if self.K is not None:
            return self.K.copy()
        size = self.image_size()
        return None if size is None else seven_scenes_intrinsics(*size)

    def _load(self, position: int) -> Frame | None:
        number, color_path = self._items[position]
        rgb = read_rgb(color_path)
        if rgb is None:
            return None
        stem = color_path.name[: color_path.name.lower().index(".color.")]
        depth_path = color_path.with_name(f"{stem}.depth.png")
        pose_path = color_path.with_name(f"{stem}.pose.txt")
        depth = None
        if depth_path.is_file():
            depth = read_depth(depth_path, 1e-3, invalid_value=SEVEN_SCENES_INVALID_DEPTH)
        pose = read_seven_scenes_pose(pose_path) if pose_path.is_file() else None
        if (depth_path.is_file() and depth is None) or (pose_path.is_file() and pose is None):
            entry = f"{stem}: depth or pose could not be read (frame kept without it)"
            if entry not in self.skipped:
                self.skipped.append(entry)
                logger.warning("%s", entry)
        return Frame(
            index=position,
            timestamp=number / SEVEN_SCENES_FPS,
            rgb=rgb,
            depth=depth,
            T_world_cam=pose,
            K=seven_scenes_intrinsics(rgb.shape[1], rgb.shape[0]) if self.K is None else self.K.copy(),
            path=str(color_path),
        )
