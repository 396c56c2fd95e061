"""The benchmark datasets of the paper: which sequences, where they lie, and their ground truth.

- **TUM RGB-D**, the nine freiburg1 sequences of VGGT-SLAM's Table 1 (and of MASt3R-SLAM's), laid
  out as the archives unpack: ``ROOT/rgbd_dataset_freiburg1_desk/`` with ``rgb.txt``,
  ``depth.txt``, ``groundtruth.txt``. Ground truth is ``groundtruth.txt`` itself (100 Hz motion
  capture), associated with the keyframes by timestamp as ``evo_ape`` does.
- **7-Scenes**, ``seq-01`` of the seven scenes, as the archives unpack:
  ``ROOT/chess/seq-01/frame-000000.color.png`` ... Ground truth is the per-frame ``.pose.txt``
  with the frame number as timestamp (the reference evaluations' ground-truth files number the
  frames 0, 1, 2, ...); keyframe timestamps (frame number / 30 Hz in
  :class:`sl4slam.io.SevenScenesSource`) are converted to frame numbers, so association is exact.

A sequence may also be named by its folder under the root (``--sequences my_recording``): any
folder in the dataset's layout is evaluated with the same protocol.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..io import SevenScenesSource, TumSource, read_tum_trajectory
from ..io.seven_scenes import SEVEN_SCENES_FPS, is_seven_scenes_folder, read_seven_scenes_pose, seven_scenes_intrinsics

TUM_SEQUENCES = ("360", "desk", "desk2", "floor", "plant", "room", "rpy", "teddy", "xyz")
"""TUM RGB-D freiburg1 sequences of the paper's Table 1 (reference script ``evals/eval_tum.sh``)."""
SEVEN_SCENES_SEQUENCES = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs")
"""7-Scenes scenes of the paper's 7-Scenes tables, ``seq-01`` of each (``evals/eval_7scenes.sh``)."""

_POSE_FILE = re.compile(r"^frame-(\d+)\.pose\.txt$")


@dataclass(frozen=True)
class Sequence:
    """One sequence to evaluate.

    Attributes:
        dataset: ``"tum"`` or ``"7scenes"``.
        name: the column name in the tables (``"desk"``, ``"chess"``, or the folder name).
        path: the sequence folder.
    """

    dataset: str
    name: str
    path: Path


@dataclass(frozen=True)
class Dataset:
    """A benchmark's sequence list, folder layout and ground-truth conventions."""

    key: str
    title: str
    sequences: tuple[str, ...]
    dense: bool
    """Whether the paper reports dense accuracy / completion / chamfer on it."""
    ate_max_time_diff: float
    """Association tolerance of the ATE, in the ground truth's time unit (evo's default 0.01)."""

    # ---------------------------------------------------------------- layout
    def folder(self, name: str) -> str:
        """Folder of a named sequence, relative to the root."""
        return f"rgbd_dataset_freiburg1_{name}" if self.key == "tum" else f"{name}/seq-01"

    def is_sequence(self, path: Path) -> bool:
        if self.key == "tum":
            return (path / "rgb.txt").is_file()
        return is_seven_scenes_folder(path)

    def found(self, root: Path) -> list[str]:
        """Sequence folders (relative to ``root``) in this dataset's layout."""
        if not root.is_dir():
            return []
        candidates = root.glob("*/seq-*") if self.key == "7scenes" else root.iterdir()
        return sorted(str(p.relative_to(root)) for p in candidates if p.is_dir() and self.is_sequence(p))

    def resolve(self, root: str | Path, requested: list[str] | None = None) -> tuple[list[Sequence], list[str]]:
        """The sequences to evaluate under ``root`` and the paper's sequences that are missing.

        Args:
            root: the dataset root.
            requested: sequence names (``desk``, ``chess``) or folders under the root
                (``my_recording``, ``chess/seq-02``), or ``None`` for every paper sequence present.

        Raises:
            UserError: a requested sequence is absent, or nothing is found; the message lists
                what was found and what was expected.
        """
        root = Path(root).expanduser()
        if not root.is_dir():
            raise UserError(f"dataset root {root} does not exist; pass the folder that holds the {self.title} sequences")
        expected = [self.folder(name) for name in self.sequences]
        chosen: list[Sequence] = []
        missing: list[str] = []
        for name in requested if requested else self.sequences:
            folder = next((root / f for f in (self.folder(name), name) if self.is_sequence(root / f)), None)
            if folder is None:
                missing.append(name)
            else:
                chosen.append(Sequence(self.key, name, folder))
        if (requested and missing) or not chosen:
            found = ", ".join(self.found(root)) or "nothing"
            problem = (f"sequence(s) {', '.join(missing)} not found in the {self.title} layout" if requested
                       else f"none of the {self.title} sequences found")
            raise UserError(f"{root}: {problem}; found: {found}; expected folders such as {', '.join(expected)}")
        names = [s.name for s in chosen]
        if len(set(names)) != len(names):
            raise UserError(f"--sequences names a sequence twice: {' '.join(names)}")
        return chosen, missing

    # ---------------------------------------------------------------- sources and ground truth
    def open(self, sequence: Sequence, stride: int = 1, max_frames: int = 0):
        """The frame source of a sequence (what the run reads)."""
        if self.key == "tum":
            return TumSource(sequence.path, stride=stride, max_frames=max_frames)
        return SevenScenesSource(sequence.path, stride=stride, max_frames=max_frames)

    def ground_truth(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        """``(M,)`` timestamps and ``(M, 4, 4)`` camera-to-world ground-truth poses.

        TUM: ``groundtruth.txt`` (seconds). 7-Scenes: every readable ``.pose.txt`` with its frame
        number as timestamp.
        """
        if self.key == "tum":
            return read_tum_trajectory(sequence.path / "groundtruth.txt")
        numbers, poses = [], []
        for path in sequence.path.iterdir():
            match = _POSE_FILE.match(path.name)
            if match is None:
                continue
            pose = read_seven_scenes_pose(path)
            if pose is not None:
                numbers.append(int(match.group(1)))
                poses.append(pose)
        if not poses:
            raise UserError(f"{sequence.path} has no readable frame-XXXXXX.pose.txt; 7-Scenes ground truth is missing")
        order = np.argsort(numbers)
        return np.asarray(numbers, np.float64)[order], np.stack(poses)[order]

    def intrinsics(self, width: int, height: int) -> np.ndarray:
        """``(3, 3)`` ground-truth intrinsics at ``width`` x ``height`` (the dense evaluation's resolution).

        7-Scenes: the published (585, 585, 320, 240) at 640x480, scaled per axis.
        """
        if self.key != "7scenes":
            raise UserError(f"dense metrics are defined for 7-Scenes only, not {self.title}")
        return seven_scenes_intrinsics(width, height)

    def estimate_times(self, timestamps: np.ndarray) -> np.ndarray:
        """Keyframe timestamps in the ground truth's time unit (7-Scenes: frame numbers)."""
        timestamps = np.asarray(timestamps, np.float64)
        return np.round(timestamps * SEVEN_SCENES_FPS) if self.key == "7scenes" else timestamps


DATASETS = {
    "tum": Dataset("tum", "TUM RGB-D", TUM_SEQUENCES, dense=False, ate_max_time_diff=0.01),
    "7scenes": Dataset("7scenes", "7-Scenes", SEVEN_SCENES_SEQUENCES, dense=True, ate_max_time_diff=0.01),
}


def get_dataset(key: str) -> Dataset:
    if key not in DATASETS:
        raise UserError(f"unknown dataset '{key}': use --dataset {' or '.join(DATASETS)}")
    return DATASETS[key]
