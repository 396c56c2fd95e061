"""Reading a result folder written by ``sl4slam run`` (one place for every consumer).

The viewer, the exports and the all-frame localization read a finished run through
:func:`load_result`. Two layouts are accepted:

- version 1: ``summary.json`` without a ``"format"`` entry; loops only as
  ``summary["loops"] = [{"submaps": [i, j], "frame": F}, ...]``; no ground-truth file.
- version 2: ``summary["format"] = {"name": "sl4slam-result", "version": 2}``; every graph edge in
  ``summary["edges"] = [{"kind": "odometry"|"loop", "submaps": [i, j], "frame": F,
  "query_frame": Q | null, ...}]``; keyframe ground truth in ``trajectory_gt.txt`` when known.

In both, ``trajectory.txt`` holds the keyframe poses ``T_world_cam`` (TUM format) and
``keyframes/NNNNNN.npz`` (NNNNNN = frame index; written unless the run had
``--no-save-keyframe-points``) the dense keyframe data: ``points_world (H, W, 3)`` float32,
``mask (H, W)`` bool, ``colors (H, W, 3)`` uint8, ``K (3, 3)``, ``T_world_cam (4, 4)``,
``timestamp``, ``submap_id`` and, when written, ``confidence (H, W)`` float16.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError

FORMAT_NAME = "sl4slam-result"
SUPPORTED_VERSIONS = (1, 2)
KEYFRAMES_OPTION = "--save-keyframe-points"


@dataclass
class KeyframeData:
    """Dense data of one keyframe (what its ``.npz`` holds).

    Attributes:
        points_world: ``(H, W, 3)`` float32 world points (zeros where ``mask`` is false).
        mask: ``(H, W)`` bool, the run's confidence mask (and valid projective weight).
        colors: ``(H, W, 3)`` uint8 RGB on the same grid.
        confidence: ``(H, W)`` float32 per-pixel confidence, or ``None`` when the run saved only
            the mask.
    """

    points_world: np.ndarray
    mask: np.ndarray
    colors: np.ndarray
    confidence: np.ndarray | None


@dataclass
class KeyframeRecord:
    """One keyframe: identity, camera, and where its dense data lives.

    Attributes:
        frame_index, timestamp: the source frame.
        submap_id: the submap in which it was a new keyframe.
        K: ``(3, 3)`` intrinsics on the keyframe's grid (decomposed; may carry a small skew).
        T_world_cam: ``(4, 4)`` world-from-camera pose (OpenCV axes: x right, y down, z forward).
        image_size: ``(width, height)`` of the grid.
        path: the ``.npz`` file.
    """

    frame_index: int
    timestamp: float
    submap_id: int
    K: np.ndarray
    T_world_cam: np.ndarray
    image_size: tuple[int, int]
    path: Path

    def load(self) -> KeyframeData:
        """Read the dense arrays (a few MB at 518x294)."""
        with np.load(self.path) as data:
            confidence = data["confidence"].astype(np.float32) if "confidence" in data.files else None
            return KeyframeData(points_world=data["points_world"], mask=data["mask"].astype(bool),
                                colors=data["colors"], confidence=confidence)


@dataclass
class GraphEdge:
    """One edge of the submap graph: ``kind`` is "odometry" or "loop".

    ``frame`` is the frame both submaps saw (for a loop, the stored keyframe that was matched);
    ``query_frame`` the new keyframe that retrieved it (``None`` when the run did not record it).
    """

    kind: str
    submaps: tuple[int, int]
    frame: int
    query_frame: int | None = None


@dataclass
class RunResult:
    """A result folder, read.

    Attributes:
        path: the folder.
        version: 1 or 2 (see the module docstring).
        summary: ``summary.json`` as a dict.
        timestamps, T_world_cam: ``(N,)`` and ``(N, 4, 4)`` keyframe trajectory (``trajectory.txt``).
        keyframes: one record per ``keyframes/*.npz`` in frame order (empty when not saved).
        edges: graph edges (version 1: loops only, from ``summary["loops"]``).
        gt: ``(timestamps, T_world_cam)`` keyframe ground truth, or ``None``.
        all_frames: ``(timestamps, T_world_cam)`` from ``trajectory_all.txt``, or ``None``.
    """

    path: Path
    version: int
    summary: dict
    timestamps: np.ndarray
    T_world_cam: np.ndarray
    keyframes: list[KeyframeRecord] = field(default_factory=list)
    edges: list[GraphEdge] = field(default_factory=list)
    gt: tuple[np.ndarray, np.ndarray] | None = None
    all_frames: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def loops(self) -> list[GraphEdge]:
        return [e for e in self.edges if e.kind == "loop"]

    def require_keyframes(self, purpose: str) -> list[KeyframeRecord]:
        """The keyframe records, or a one-line error naming the run option that writes them."""
        if not self.keyframes:
            raise UserError(f"{self.path} has no keyframes/*.npz, which {purpose} needs; re-run `sl4slam run` with "
                            f"{KEYFRAMES_OPTION} (on by default)")
        return self.keyframes

    def submap_ids(self) -> list[int]:
        return sorted({k.submap_id for k in self.keyframes})

    def loop_segments(self) -> np.ndarray:
        """Loop edges as camera-centre segments ``(L, 2, 3)`` (see :func:`loop_segments`)."""
        if not self.keyframes:
            return np.zeros((0, 2, 3))
        return loop_segments(np.array([k.frame_index for k in self.keyframes]), np.array([k.submap_id for k in self.keyframes]),
                             np.stack([k.T_world_cam[:3, 3] for k in self.keyframes]), self.loops)


def loop_segments(frame_indices: np.ndarray, submap_ids: np.ndarray, centres: np.ndarray,
                  loops: list[GraphEdge]) -> np.ndarray:
    """Loop edges as segments ``(L, 2, 3)`` between keyframe camera centres.

    Args:
        frame_indices, submap_ids: ``(N,)`` of the keyframes; centres: ``(N, 3)`` their positions.
        loops: loop edges; ``submaps = (older, newer)``.

    Each segment joins the older submap's keyframe nearest to ``frame`` (in frame index) and the
    query keyframe when recorded, else the newer submap's keyframe nearest in space to the first end.
    """
    segments = []
    for edge in loops:
        old, new = edge.submaps
        in_old, in_new = np.flatnonzero(submap_ids == old), np.flatnonzero(submap_ids == new)
        if not len(in_old) or not len(in_new):
            continue
        a = in_old[np.argmin(np.abs(frame_indices[in_old] - edge.frame))]
        query = np.flatnonzero(frame_indices[in_new] == edge.query_frame) if edge.query_frame is not None else []
        if len(query):
            b = in_new[query[0]]
        else:
            b = in_new[np.argmin(np.linalg.norm(centres[in_new] - centres[a], axis=1))]
        segments.append((centres[a], centres[b]))
    return np.array(segments, dtype=np.float64).reshape(-1, 2, 3)


def _format_version(summary: dict, path: Path) -> int:
    fmt = summary.get("format")
    if fmt is None:
        return 1
    if not isinstance(fmt, dict) or fmt.get("name") != FORMAT_NAME:
        raise UserError(f"{path} is not an sl4slam result (summary.json format {fmt!r}); pass a folder written by `sl4slam run`")
    version = fmt.get("version")
    if version not in SUPPORTED_VERSIONS:
        raise UserError(f"{path} was written in result format version {version}, which this sl4slam does not read "
                        f"(it reads versions {', '.join(map(str, SUPPORTED_VERSIONS))}); upgrade sl4slam or re-run")
    return int(version)


def _edges(summary: dict, version: int) -> list[GraphEdge]:
    if version >= 2 and "edges" in summary:
        # edges that reached the graph; rejected loops and segment starts are reported, not drawn
        raw = [e for e in summary["edges"] if e.get("accepted", True) and e.get("kind") in ("odometry", "loop")]
    else:
        raw = [{**loop, "kind": "loop"} for loop in summary.get("loops", [])]
    edges = []
    for item in raw:
        try:
            i, j = item["submaps"]
            query = item.get("query_frame")
            edges.append(GraphEdge(kind=str(item["kind"]), submaps=(int(i), int(j)), frame=int(item["frame"]),
                                   query_frame=None if query is None else int(query)))
        except (KeyError, TypeError, ValueError):
            raise UserError(f"summary.json has a malformed edge {item!r}; the result folder is damaged — re-run") from None
    return edges


def _keyframe_record(path: Path) -> KeyframeRecord:
    try:
        with np.load(path) as data:
            H, W = data["mask"].shape
            return KeyframeRecord(frame_index=int(path.stem), timestamp=float(data["timestamp"]),
                                  submap_id=int(data["submap_id"]), K=np.asarray(data["K"], np.float64),
                                  T_world_cam=np.asarray(data["T_world_cam"], np.float64), image_size=(int(W), int(H)),
                                  path=path)
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"keyframe file {path} cannot be read ({exc}); the result folder is damaged — re-run") from None


def load_result(path: str | Path, keyframes: bool = True) -> RunResult:
    """Read a result folder (any supported format version).

    Args:
        path: the ``--out`` folder of ``sl4slam run``.
        keyframes: read the keyframe records (camera and metadata; the dense arrays stay on disk
            until :meth:`KeyframeRecord.load`).

    Raises:
        UserError: not a result folder, a format this version does not read, or damaged files.
    """
    from ..io import read_tum_trajectory

    path = Path(path).expanduser()
    if not path.is_dir():
        raise UserError(f"{path} is not a folder; pass the --out folder of `sl4slam run`")
    summary_path, trajectory_path = path / "summary.json", path / "trajectory.txt"
    if not summary_path.is_file() or not trajectory_path.is_file():
        missing = "summary.json" if not summary_path.is_file() else "trajectory.txt"
        raise UserError(f"{path} is not an sl4slam result folder (no {missing}); pass the --out folder of `sl4slam run`")
    try:
        summary = json.loads(summary_path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise UserError(f"{summary_path} is not valid JSON ({exc}); the result folder is damaged — re-run") from None
    if not isinstance(summary, dict) or "counts" not in summary:
        raise UserError(f"{summary_path} is not an sl4slam run summary; pass the --out folder of `sl4slam run`")
    version = _format_version(summary, path)
    timestamps, T_world_cam = read_tum_trajectory(trajectory_path)
    result = RunResult(path=path, version=version, summary=summary, timestamps=timestamps, T_world_cam=T_world_cam,
                       edges=_edges(summary, version))
    if keyframes and (path / "keyframes").is_dir():
        files = sorted(p for p in (path / "keyframes").glob("*.npz") if p.stem.isdigit())
        result.keyframes = [_keyframe_record(p) for p in files]
    if (path / "trajectory_gt.txt").is_file():
        result.gt = read_tum_trajectory(path / "trajectory_gt.txt")
    if (path / "trajectory_all.txt").is_file():
        result.all_frames = read_tum_trajectory(path / "trajectory_all.txt")
    return result


def keyframe_colors(keyframe, colors=None) -> np.ndarray:
    """``(H, W, 3)`` uint8 grid colours of a keyframe: the ones it holds (a keyframe read from a
    result folder), else ``colors(keyframe)`` (a run's ``SLAMResult.keyframe_colors`` or
    ``SLAMPipeline.colors``, which re-read the frame from the source), else mid-grey.

    The viewer and the all-frame localization read keyframe colours only through this function.
    """
    stored = keyframe.colors if isinstance(keyframe, KeyframeData) else None
    if stored is not None:
        return stored
    if colors is not None:
        try:
            return colors(keyframe)
        except UserError:
            pass
    return np.full(tuple(keyframe.shape) + (3,), 128, dtype=np.uint8)
