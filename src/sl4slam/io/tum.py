"""TUM RGB-D sequences and TUM-format trajectory files.

Sequence layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats): ``rgb.txt`` and
``depth.txt`` list ``timestamp filename`` (``#`` comments), ``groundtruth.txt`` lists
``timestamp tx ty tz qx qy qz qw`` = camera-to-world pose of the RGB optical centre. Depth PNGs are
16-bit with 5000 units per metre, 0 = no measurement.

Association follows TUM's ``associate.py``: rgb and depth are paired one-to-one, greedily by
smallest time difference, among pairs closer than 0.02 s. Each rgb frame takes the ground-truth
pose nearest in time when it is within 0.02 s (the ground truth runs at 100 Hz, so poses may be
shared). Frames without a match keep ``depth`` / ``T_world_cam`` = ``None``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sl4slam.atomic import atomic_write_text
from sl4slam.errors import UserError
from sl4slam.geometry import project_to_so3
from sl4slam.io._common import IndexedSource, logger, read_depth, read_rgb, select
from sl4slam.types import Frame

TUM_DEPTH_SCALE = 5000.0
"""Raw depth units per metre in TUM RGB-D depth PNGs."""

MAX_TIME_DIFFERENCE = 0.02
"""Seconds; TUM associate.py's default ``--max_difference``."""

TUM_DEFAULT_INTRINSICS = {
    # (fx, fy, cx, cy) of the RGB cameras, TUM's published calibration (640x480).
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}

CALIBRATION_FILE_NAMES = ("calibration.txt", "intrinsics.txt", "camera.txt")
"""Files (any letter case) in a sequence folder that may state ``fx = .. fy = .. cx = .. cy = ..``."""

_FREIBURG = re.compile(r"(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)


# --------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------


def _read_table(path: Path, columns: int, what: str) -> list[list[str]]:
    """Rows of a whitespace-separated text file, comments and blank lines removed."""
    if not path.is_file():
        raise UserError(f"{what} {path} does not exist")
    rows = []
    with open(path, "r", encoding="utf-8", errors="replace") as handle:
        for line_number, line in enumerate(handle, start=1):
            text = line.replace(",", " ").strip()
            if not text or text.startswith("#"):
                continue
            fields = text.split()
            if len(fields) < columns:
                raise UserError(f"{path} line {line_number}: expected {columns} columns, found {len(fields)}; is it a {what}?")
            rows.append(fields[:columns] + [str(line_number)])
    return rows


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory ``timestamp tx ty tz qx qy qz qw`` (one pose per line, ``#`` comments).

    Returns:
        timestamps: ``(N,)`` float64 seconds, in file order.
        T_world_cam: ``(N, 4, 4)`` float64 camera-to-world poses (quaternions are normalized).

    Raises:
        UserError: missing file, malformed line, non-finite or zero-norm values, or no poses.
    """
    path = Path(path)
    rows = _read_table(path, 8, "TUM trajectory file")
    if not rows:
        raise UserError(f"trajectory file {path} contains no poses")
    values = np.empty((len(rows), 8), np.float64)
    for row_index, row in enumerate(rows):
        try:
            values[row_index] = [float(v) for v in row[:8]]
        except ValueError:
            raise UserError(f"{path} line {row[8]}: not a number; expected 'timestamp tx ty tz qx qy qz qw'") from None
    if not np.all(np.isfinite(values)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(values), axis=1))[0])
        raise UserError(f"{path} line {rows[bad][8]}: NaN or Inf in the pose")
    quaternion_norm = np.linalg.norm(values[:, 4:8], axis=1)
    if np.any(quaternion_norm < 1e-9):
        bad = int(np.flatnonzero(quaternion_norm < 1e-9)[0])
        raise UserError(f"{path} line {rows[bad][8]}: zero quaternion")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(values[:, 4:8] / quaternion_norm[:, None]).as_matrix()
    T[:, :3, 3] = values[:, 1:4]
    return values[:, 0].copy(), T


def write_tum_trajectory(path: str | Path, timestamps: np.ndarray, T_world_cam: np.ndarray) -> Path:
    """Write camera-to-world poses as a TUM trajectory, atomically (temp file, then rename).

    Args:
        path: output file; missing parent folders are created.
        timestamps: ``(N,)`` seconds.
        T_world_cam: ``(N, 4, 4)`` or ``(N, 3, 4)`` camera-to-world poses. The rotation block is
            projected to SO(3) (a similarity's scale cannot be stored in this format).

    Returns:
        The written path. Raises UserError on shape mismatch or NaN / Inf values.
    """
    path = Path(path)
    timestamps = np.asarray(timestamps, np.float64).reshape(-1)
    T = np.asarray(T_world_cam, np.float64)
    if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)) or T.shape[0] != timestamps.shape[0]:
        raise UserError(
            f"cannot write trajectory {path}: expected timestamps (N,) and poses (N, 4, 4), got {timestamps.shape} and {T.shape}"
        )
    if not (np.all(np.isfinite(timestamps)) and np.all(np.isfinite(T))):
        raise UserError(f"refusing to write trajectory {path}: it contains NaN or Inf poses (the estimate diverged)")
    R = project_to_so3(T[:, :3, :3])
    quaternions = Rotation.from_matrix(R).as_quat()  # (x, y, z, w)
    quaternions *= np.where(quaternions[:, 3:4] < 0, -1.0, 1.0)  # canonical sign: qw >= 0
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, translation, quaternion in zip(timestamps, T[:, :3, 3], quaternions):
        numbers = " ".join(f"{v:.9f}" for v in (*translation, *quaternion))
        lines.append(f"{stamp:.9f} {numbers}")
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------------------------
# Association
# --------------------------------------------------------------------------------------------


def associate(first: np.ndarray, second: np.ndarray, max_difference: float = MAX_TIME_DIFFERENCE) -> np.ndarray:
    """One-to-one pairing of two timestamp lists, as TUM ``associate.py`` does.

    All pairs closer than ``max_difference`` are candidates; they are accepted greedily by
    increasing time difference, each timestamp used at most once.

    Args:
        first: ``(N,)`` timestamps; second: ``(M,)`` timestamps (any order).

    Returns:
        ``(N,)`` int64: index into ``second`` matched to each entry of ``first``, -1 if none.
    """
    first = np.asarray(first, np.float64).reshape(-1)
    second = np.asarray(second, np.float64).reshape(-1)
    match = np.full(first.shape[0], -1, np.int64)
    if first.size == 0 or second.size == 0:
        return match
    order = np.argsort(second, kind="stable")
    sorted_second = second[order]
    lo = np.searchsorted(sorted_second, first - max_difference, side="right")
    hi = np.searchsorted(sorted_second, first + max_difference, side="left")
    counts = np.maximum(hi - lo, 0)
    first_idx = np.repeat(np.arange(first.size), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    second_sorted_idx = np.repeat(lo, counts) + offsets
    differences = np.abs(first[first_idx] - sorted_second[second_sorted_idx])
    keep = differences < max_difference
    first_idx, second_sorted_idx, differences = first_idx[keep], second_sorted_idx[keep], differences[keep]
    used_second = np.zeros(second.size, bool)
    # Greedy acceptance in order of difference; a loop over candidate pairs (about one per frame).
    for k in np.argsort(differences, kind="stable"):
        a, b = first_idx[k], second_sorted_idx[k]
        if match[a] < 0 and not used_second[b]:
            match[a] = order[b]
            used_second[b] = True
    return match


def nearest_within(query: np.ndarray, reference: np.ndarray, max_difference: float = MAX_TIME_DIFFERENCE) -> np.ndarray:
    """Index of the nearest ``reference`` timestamp for each ``query``, -1 if farther than ``max_difference``.

    Args:
        query: ``(N,)``; reference: ``(M,)`` timestamps (any order).

    Returns:
        ``(N,)`` int64 indices into ``reference``.
    """
    query = np.asarray(query, np.float64).reshape(-1)
    reference = np.asarray(reference, np.float64).reshape(-1)
    if reference.size == 0:
        return np.full(query.shape[0], -1, np.int64)
    order = np.argsort(reference, kind="stable")
    sorted_reference = reference[order]
    right = np.clip(np.searchsorted(sorted_reference, query), 0, reference.size - 1)
    left = np.clip(right - 1, 0, reference.size - 1)
    pick = np.where(np.abs(sorted_reference[left] - query) <= np.abs(sorted_reference[right] - query), left, right)
    result = order[pick].astype(np.int64)
    result[np.abs(sorted_reference[pick] - query) > max_difference] = -1
    return result


# --------------------------------------------------------------------------------------------
# Intrinsics
# --------------------------------------------------------------------------------------------


def parse_calibration_text(text: str) -> np.ndarray | None:
    """``K`` from the first ``fx = .., fy = .., cx = .., cy = ..`` values found in ``text``, else ``None``."""
    values = {}
    for key in ("fx", "fy", "cx", "cy"):
        found = re.search(rf"\b{key}\s*[=:]\s*([-+0-9.eE]+)", text)
        if found is None:
            return None
        try:
            values[key] = float(found.group(1))
        except ValueError:
            return None
    return np.array([[values["fx"], 0.0, values["cx"]], [0.0, values["fy"], values["cy"]], [0.0, 0.0, 1.0]])


def tum_intrinsics(folder: str | Path) -> np.ndarray | None:
    """Intrinsics of a TUM sequence: its calibration file if any, else the published freiburg default.

    The calibration file is any of ``CALIBRATION_FILE_NAMES`` (letter case ignored) stating
    ``fx = .. fy = .. cx = .. cy = ..``; the first values found are used (TUM's own notes list the
    calibrated RGB camera first). Otherwise a folder name containing ``freiburg1|2|3`` (or
    ``fr1|2|3``) selects TUM's published values. ``None`` when neither is available.
    """
    folder = Path(folder)
    for path in sorted(folder.iterdir()) if folder.is_dir() else []:
        if path.is_file() and path.name.lower() in CALIBRATION_FILE_NAMES:
            K = parse_calibration_text(path.read_text(encoding="utf-8", errors="replace"))
            if K is not None:
                return K
    found = _FREIBURG.search(folder.resolve().name)
    if found is not None:
        fx, fy, cx, cy = TUM_DEFAULT_INTRINSICS[f"freiburg{found.group(1)}"]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return None


# --------------------------------------------------------------------------------------------
# Sequence
# --------------------------------------------------------------------------------------------


def _read_file_list(path: Path, folder: Path) -> tuple[np.ndarray, list[Path]]:
    rows = _read_table(path, 2, "TUM file list (timestamp filename)")
    try:
        stamps = np.array([float(row[0]) for row in rows], np.float64)
    except ValueError:
        raise UserError(f"{path}: a timestamp is not a number; expected 'timestamp filename' lines") from None
    return stamps, [folder / row[1] for row in rows]


class TumSource(IndexedSource):
    """A TUM RGB-D sequence folder (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``).

    Frames follow ``rgb.txt`` order; ``timestamp`` is the rgb timestamp, ``depth`` the associated
    depth in metres (``None`` without a match or without ``depth.txt``), ``T_world_cam`` the
    nearest ground-truth pose within 0.02 s (``None`` otherwise), ``K`` from :func:`tum_intrinsics`.

    Args:
        folder: the sequence folder.
        stride: keep every ``stride``-th rgb frame.
        max_frames: keep at most this many frames (0 = all).
        require_groundtruth: raise UserError when ``groundtruth.txt`` is missing (default); pass
            False for sequences published without ground truth.
        K: override the intrinsics.
    """

    def __init__(
        self,
        folder: str | Path,
        stride: int = 1,
        max_frames: int = 0,
        require_groundtruth: bool = True,
        K: np.ndarray | None = None,
    ):
        folder = Path(folder)
        if not folder.is_dir():
            raise UserError(f"TUM sequence folder {folder} does not exist")
        rgb_list = folder / "rgb.txt"
        if not rgb_list.is_file():
            raise UserError(f"{folder} is not a TUM RGB-D sequence: rgb.txt is missing")
        self.folder = folder
        self.name = folder.resolve().name
        self.skipped: list[str] = []
        rgb_stamps, rgb_paths = _read_file_list(rgb_list, folder)
        if not rgb_paths:
            raise UserError(f"{rgb_list} lists no images")

        depth_paths: list[Path | None] = [None] * len(rgb_paths)
        depth_list = folder / "depth.txt"
        if depth_list.is_file():
            depth_stamps, all_depth_paths = _read_file_list(depth_list, folder)
            for i, j in enumerate(associate(rgb_stamps, depth_stamps)):
                if j >= 0:
                    depth_paths[i] = all_depth_paths[j]

        poses: list[np.ndarray | None] = [None] * len(rgb_paths)
        groundtruth = folder / "groundtruth.txt"
        if groundtruth.is_file():
            gt_stamps, gt_poses = read_tum_trajectory(groundtruth)
            for i, j in enumerate(nearest_within(rgb_stamps, gt_stamps)):
                if j >= 0:
                    poses[i] = gt_poses[j]
        elif require_groundtruth:
            raise UserError(
                f"TUM sequence {folder} has no groundtruth.txt; add it, or open it with require_groundtruth=False"
            )

        self.K = tum_intrinsics(folder) if K is None else np.asarray(K, np.float64).reshape(3, 3)
        items = list(zip(rgb_stamps.tolist(), rgb_paths, depth_paths, poses))
        self._items = select(items, stride, max_frames)
        self.has_ground_truth = self.K is not None and any(
            depth is not None and pose is not None for _, _, depth, pose in self._items)

    def _image_path(self, position: int) -> Path:
        return self._items[position][1]

    def _describe(self, position: int) -> str:
        return str(self._items[position][1].relative_to(self.folder))

    def _load(self, position: int) -> Frame | None:
        stamp, rgb_path, depth_path, pose = self._items[position]
        rgb = read_rgb(rgb_path)
        if rgb is None:
            return None
        depth = None
        if depth_path is not None:
            depth = read_depth(depth_path, 1.0 / TUM_DEPTH_SCALE)
            if depth is None:
                entry = f"{depth_path.name}: depth could not be decoded (frame kept without depth)"
                if entry not in self.skipped:
                    self.skipped.append(entry)
                    logger.warning("%s", entry)
        return Frame(
            index=position,
            timestamp=float(stamp),
            rgb=rgb,
            depth=depth,
            T_world_cam=None if pose is None else pose.copy(),
            K=None if self.K is None else self.K.copy(),
            path=str(rgb_path),
        )
