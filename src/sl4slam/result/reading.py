"""Reading a result folder written by ``sl4slam run`` (one place for every consumer).

The viewer, the exports and the all-frame localization read a finished run through
:func:`load_result`. Three format versions are accepted:

- version 1: ``summary.json`` without a ``"format"`` entry; loops only as
  ``summary["loops"] = [{"submaps": [i, j], "frame": F}, ...]``; no ground-truth file.
- version 2: ``summary["format"] = {"name": "sl4slam-result", "version": 2}``; every graph edge in
  ``summary["edges"] = [{"kind": "odometry"|"loop", "submaps": [i, j], "frame": F,
  "query_frame": Q | null, ...}]``; keyframe ground truth in ``trajectory_gt.txt`` when known.
- version 3: as version 2, with keyframe files in the compact layout below (the default) as well
  as the full one, so that a reader from before that layout says it cannot read the folder
  instead of failing on a missing key.

In all of them, ``trajectory.txt`` holds the keyframe poses ``T_world_cam`` (TUM format) and
``keyframes/NNNNNN.npz`` (NNNNNN = frame index; ``--keyframes compact``, the default, or ``full``;
none with ``--keyframes none``) the dense keyframe data. Every keyframe file holds ``mask (H, W)``
bool (the run's confidence mask, and a finite world point with projective weight w > 0), ``K (3, 3)``
and ``T_world_cam (4, 4)`` (the decomposed world camera), ``timestamp``, ``frame_index``,
``submap_id`` and ``segment``; the dense arrays come in one of two layouts, told apart by their keys:

- **full** (``--keyframes full``, and every folder written before the compact layout):
  ``points_world (H, W, 3)`` float32 (zeros where ``mask`` is false), ``colors (H, W, 3)`` uint8
  and, when written, ``confidence (H, W)`` float16 (percentile of the pixel's confidence in its
  submap). Uncompressed ``.npz``: 18 bytes per pixel, 3.66 MB per keyframe at 518x392.
- **compact** (``--keyframes compact``, the default): what the run itself kept of the keyframe,
  from which it computed the full layout's points, so no point is lost or moved
  (:data:`COMPACT_POINT_TOLERANCE`); only the colours are lossy (JPEG; decision:
  docs/decisions/keyframe-format.md):

  - ``depth_bytes (B, H, W)`` uint8: the keyframe's depth in its local (submap) frame, float16
    (``B = 2``; float32 when ``B = 4``), exactly as the run stored it where ``mask`` is true (a
    pixel where it is false repeats the previous valid depth of its row, or the row's first valid
    one; 0 in a row without any), coded losslessly for deflate: the bit patterns ``bits`` (as
    unsigned B-byte integers) differenced along each row (``d[:, 0] = bits[:, 0]``,
    ``d[:, j] = bits[:, j] - bits[:, j - 1]`` modulo 2^(8B)), read as signed and zigzag-mapped
    (0, -1, 1, -2, 2, ... -> 0, 1, 2, 3, 4, ...), then split into byte planes, least significant
    first. :func:`decode_depth` undoes it.
  - ``K_local (3, 3)``, ``T_cam_local (4, 4)``: the keyframe's camera in that local frame, and
    ``H_world_local (4, 4)``: the projective map of the local frame into the world (its submap's
    graph node, or its own node in the keyframe graph). The world points are
    ``X_world = H_world_local (T_cam_local^-1 (depth K_local^-1 [u, v, 1]))`` (homogeneous division;
    ``(u, v)`` = (column, row), integer at pixel centres, as ``sl4slam.geometry.unproject_depth``),
    computed exactly as the run computed them (:func:`compact_world_points`). They lie on the
    rays of the world camera ``K [R|t]`` (``T_world_cam``), whatever the projective map, but their
    depth along that camera's axis is the local depth times a per-pixel factor (1 / w): stored
    that way it would need a second float16 rounding (up to 7.6e-4 of the depth measured) or twice
    the bytes as float32, where the local depth is exact and smaller still.
  - ``confidence_rank (ceil(H / 2), ceil(W / 2))`` uint8: the run's half-resolution confidence
    percentile, 0..255 for 0..100 % (``sl4slam.submap.StoredKeyframe.confidence_rank``).
  - ``colors_jpeg (n,)`` uint8: the colours as one JPEG (quality :data:`JPEG_QUALITY`, no chroma
    subsampling, progressive).
  - ``mask`` stays a bool array: deflated, it costs 4 kB at 518x392 on the TUM excerpt, and
    bit-packing it first would save under 10 % while breaking readers that open ``mask`` directly.
  - written with ``np.savez_compressed`` (deflate).

:meth:`KeyframeRecord.load` returns the same :class:`KeyframeData` for both layouts.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..geometry import unproject_depth
from ..submap import RANK_LEVELS

FORMAT_NAME = "sl4slam-result"
SUPPORTED_VERSIONS = (1, 2, 3)
KEYFRAMES_OPTION = "--keyframes compact"
"""The run option that writes ``keyframes/`` (named in the error of a tool that needs it)."""
_OBJECT_QUERY = "sl4slam.objects.query"
"""The module of :meth:`RunResult.query` (loaded on first use)."""
KEYFRAME_LAYOUTS = ("compact", "full")
"""The layouts of a keyframe file (``output.keyframes`` adds "none": no files)."""
JPEG_QUALITY = 85
"""Quality of a compact keyframe's colours (4:4:4, no chroma subsampling, progressive; decision:
docs/decisions/keyframe-format.md)."""
COMPACT_POINT_TOLERANCE = 1e-6
"""Largest distance between a compact keyframe's world point and the full layout's, relative to
the point's depth along the keyframe's camera axis. Both are computed by the same float32 and
float64 steps from the same float16 depth, so they agree to the last bit in practice
(``tests/test_keyframe_format.py`` measures 0 on a projective SL(4) world); the bound leaves room
for another BLAS summing in another order."""


@dataclass
class KeyframeData:
    """Dense data of one keyframe (what its ``.npz`` holds), the same for both layouts.

    Attributes:
        points_world: ``(H, W, 3)`` float32 world points (zeros where ``mask`` is false).
        mask: ``(H, W)`` bool, the run's confidence mask (and valid projective weight).
        colors: ``(H, W, 3)`` uint8 RGB on the same grid (JPEG-decoded in the compact layout).
        confidence: ``(H, W)`` float32 per-pixel confidence, or ``None`` when the run saved only
            the mask.
        depth: ``(H, W)`` float32 depth in the keyframe's local (submap) frame, zero where ``mask``
            is false; ``None`` in the full layout. With ``K_local``, ``T_cam_local`` (the camera
            in that frame) and ``H_world_local`` (local frame -> world), see :meth:`points_local`.
    """

    points_world: np.ndarray
    mask: np.ndarray
    colors: np.ndarray
    confidence: np.ndarray | None
    depth: np.ndarray | None = None
    K_local: np.ndarray | None = None
    T_cam_local: np.ndarray | None = None
    H_world_local: np.ndarray | None = None

    def points_local(self) -> np.ndarray | None:
        """``(H, W, 3)`` float32 points in the keyframe's local frame (compact layout), else ``None``."""
        if self.depth is None:
            return None
        return unproject_depth(self.depth[None], self.K_local[None], self.T_cam_local[None])[0]


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
        layout: "compact" or "full" (see the module docstring).
    """

    frame_index: int
    timestamp: float
    submap_id: int
    K: np.ndarray
    T_world_cam: np.ndarray
    image_size: tuple[int, int]
    path: Path
    layout: str = "full"

    def load(self) -> KeyframeData:
        """Read the dense arrays (either layout gives 3.7 MB of arrays at 518x392; a compact file
        is inflated, its points recomputed and its JPEG decoded, which costs more CPU than a full
        file; decision: docs/decisions/keyframe-format.md)."""
        try:
            with np.load(self.path) as data:
                if "depth_bytes" in data.files:
                    return _load_compact(data)
                confidence = data["confidence"].astype(np.float32) if "confidence" in data.files else None
                return KeyframeData(points_world=data["points_world"], mask=data["mask"].astype(bool),
                                    colors=data["colors"], confidence=confidence)
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            raise UserError(f"keyframe file {self.path} cannot be read ({exc}); the result folder is damaged — re-run") from None


# ------------------------------------------------------------------------- the compact layout
def encode_depth(depth: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` float16 (or float32) depth -> ``(B, H, W)`` uint8 planes (lossless where ``mask``;
    the coding is in the module docstring). Pixels outside ``mask`` repeat their row's previous
    valid depth, so that the row differences there are zero and deflate packs the planes tightly
    (decision: docs/decisions/keyframe-format.md)."""
    depth = np.ascontiguousarray(depth)
    count = depth.dtype.itemsize
    if depth.ndim != 2 or depth.dtype.kind != "f" or count not in (2, 4):
        raise ValueError(f"depth must be a (H, W) float16 or float32 array, got {depth.dtype} {depth.shape}")
    unsigned, signed = {2: (np.uint16, np.int16), 4: (np.uint32, np.int32)}[count]
    bits = depth.view(unsigned)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        columns = np.where(mask, np.arange(depth.shape[1]), -1)
        np.maximum.accumulate(columns, axis=1, out=columns)
        columns = np.where(columns < 0, np.argmax(mask, axis=1)[:, None], columns)  # before the first: the first
        bits = np.where(mask.any(axis=1)[:, None], np.take_along_axis(bits, columns, axis=1), unsigned(0))
    delta = bits.copy()
    delta[:, 1:] -= bits[:, :-1]  # unsigned: modulo 2^(8B)
    signed_delta = delta.view(signed)
    zigzag = (signed_delta.astype(np.int64) << 1) ^ (signed_delta.astype(np.int64) >> (8 * count - 1))
    zigzag = zigzag.astype(unsigned)
    return np.stack([((zigzag >> unsigned(8 * byte)) & unsigned(0xFF)).astype(np.uint8) for byte in range(count)])


def decode_depth(planes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_depth`: ``(B, H, W)`` uint8 -> ``(H, W)`` float16 (B = 2) or
    float32 (B = 4); pixels outside the encoder's mask hold a neighbour's depth."""
    planes = np.asarray(planes, dtype=np.uint8)
    if planes.ndim != 3 or planes.shape[0] not in (2, 4):
        raise ValueError(f"depth_bytes has shape {planes.shape}, expected (2 or 4, H, W)")
    count = planes.shape[0]
    unsigned, floating = {2: (np.uint16, np.float16), 4: (np.uint32, np.float32)}[count]
    zigzag = np.zeros(planes.shape[1:], dtype=unsigned)
    for byte in range(count):
        zigzag |= planes[byte].astype(unsigned) << unsigned(8 * byte)
    delta = (zigzag >> unsigned(1)) ^ (unsigned(0) - (zigzag & unsigned(1)))  # unsigned: modulo 2^(8B)
    return np.cumsum(delta, axis=1, dtype=unsigned).view(floating)


def encode_colors(colors: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB -> JPEG bytes ``(n,)`` uint8 (quality :data:`JPEG_QUALITY`, 4:4:4)."""
    import cv2

    # progressive with optimized Huffman tables: the same pixels in about 8 % fewer bytes
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY, cv2.IMWRITE_JPEG_OPTIMIZE, 1, cv2.IMWRITE_JPEG_PROGRESSIVE, 1]
    if hasattr(cv2, "IMWRITE_JPEG_SAMPLING_FACTOR"):
        params += [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(colors, dtype=np.uint8), cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise UserError("cannot encode a keyframe's colours as JPEG")
    return encoded.reshape(-1)


def decode_colors(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_colors`: JPEG bytes -> ``(H, W, 3)`` uint8 RGB."""
    import cv2

    image = cv2.imdecode(np.asarray(encoded, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError("colors_jpeg is not a readable JPEG")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def to_world(X_local: np.ndarray, H_world_local: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W, 3)`` local points through the projective ``H_world_local`` -> world points
    ``(H, W, 3)`` float32 and the validity mask: ``mask``, a homogeneous weight w > 0 (in front of
    the plane at infinity) and a finite result. The one computation of a keyframe's world points,
    used when a run writes them and when a compact file is read."""
    X = np.asarray(X_local, dtype=np.float64)
    H = np.asarray(H_world_local, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite points (float16 overflow) end invalid
        w = X @ H[3, :3] + H[3, 3]
        valid = np.asarray(mask, dtype=bool) & (w > 1e-9)
        X_world = (X @ H[:3, :3].T + H[:3, 3]) / np.where(valid, w, 1.0)[..., None]
    valid &= np.isfinite(X_world).all(axis=-1)
    return X_world.astype(np.float32), valid


def compact_world_points(depth: np.ndarray, K_local: np.ndarray, T_cam_local: np.ndarray, H_world_local: np.ndarray,
                         mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(H, W, 3)`` float32 (zeros where invalid) and validity of a depth map in a
    keyframe's local frame, computed exactly as the run computes them (``unproject_depth`` of the
    float32 depth, then :func:`to_world`)."""
    X_local = unproject_depth(np.asarray(depth, dtype=np.float32)[None], np.asarray(K_local, np.float64)[None],
                              np.asarray(T_cam_local, np.float64)[None])[0]
    X_world, valid = to_world(X_local, H_world_local, mask)
    return np.where(valid[..., None], X_world, np.float32(0.0)), valid


def confidence_from_rank(rank: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(ceil(H / 2), ceil(W / 2))`` uint8 ranks -> ``(H, W)`` float32 percentile (0..100), as
    ``StoredKeyframe.confidence_percentile``."""
    H, W = shape
    full = np.repeat(np.repeat(np.asarray(rank), 2, axis=0), 2, axis=1)[:H, :W]
    return full.astype(np.float32) * np.float32(100.0 / RANK_LEVELS)


def _load_compact(data) -> KeyframeData:
    mask = data["mask"].astype(bool)
    depth = decode_depth(data["depth_bytes"])
    if depth.shape != mask.shape:
        raise ValueError(f"depth {depth.shape} and mask {mask.shape} differ in shape")
    K_local, T_cam_local, H_world_local = (np.asarray(data[k], np.float64) for k in ("K_local", "T_cam_local", "H_world_local"))
    points, valid = compact_world_points(depth, K_local, T_cam_local, H_world_local, mask)
    colors = decode_colors(data["colors_jpeg"])
    if colors.shape[:2] != mask.shape:
        raise ValueError(f"colours {colors.shape[:2]} and mask {mask.shape} differ in shape")
    confidence = confidence_from_rank(data["confidence_rank"], mask.shape) if "confidence_rank" in data.files else None
    return KeyframeData(points_world=points, mask=mask & valid, colors=colors, confidence=confidence,
                        depth=np.where(mask, depth.astype(np.float32), np.float32(0.0)), K_local=K_local,
                        T_cam_local=T_cam_local, H_world_local=H_world_local)


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
                            f"{KEYFRAMES_OPTION} (the default; or --keyframes full)")
        return self.keyframes

    def submap_ids(self) -> list[int]:
        return sorted({k.submap_id for k in self.keyframes})

    def query(self, text: str, embedder=None, segmenter=None, top_k: int = 5, threshold: float = 0.5, **options):
        """Find the objects ``text`` names in this map: ``sl4slam.objects.query.query_result`` on this
        result (it needs keyframe embeddings, a run with ``--objects``); returns its ``QueryAnswer``.
        ``embedder``, ``segmenter``: the models (default: the embedder that made the embeddings and
        SAM 3, loaded on first use). The object package sits above this one, so it is named here, not
        imported (as the catalog names its stages)."""
        import importlib

        module = importlib.import_module(_OBJECT_QUERY)
        if embedder is None or segmenter is None:
            module.check_query(text, top_k, threshold)  # bad input before a model loads
            _, embeddings = module.open_for_query(self)
            embedder, segmenter = module.default_models(embeddings.model, embedder, segmenter)
        return module.query_result(self, text, embedder, segmenter, top_k=top_k, threshold=threshold, **options)

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
                                  path=path, layout="compact" if "depth_bytes" in data.files else "full")
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
