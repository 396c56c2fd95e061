"""Exports of a result folder for other tools: COLMAP sparse model, nerfstudio, per-submap PLY.

Conventions (docs/exports.md has the full table):

- Our poses are ``T_world_cam`` (world-from-camera) with OpenCV camera axes (x right, y down,
  z forward). COLMAP stores camera-from-world ``T_cam_world = T_world_cam^-1`` as a quaternion
  ``(qw, qx, qy, qz)`` and a translation, same axes. nerfstudio stores world-from-camera
  ``transform_matrix`` with OpenGL camera axes (x right, y up, z back):
  ``T_world_cam @ diag(1, -1, -1, 1)``; the world axes are left as they are.
- Our pixel coordinates have integer values at pixel centres; COLMAP and nerfstudio put the
  centre of the top-left pixel at ``(0.5, 0.5)``: principal points and observations get ``+0.5``.
- Intrinsics come per keyframe, decomposed from the world camera matrix, and may carry a small
  skew ``K[0, 1]``. Each keyframe gets its own PINHOLE camera ``(fx, fy, cx, cy)`` with the skew
  dropped; the reprojection error this causes is stored per 3D point (COLMAP) and reported.
- The world may be slightly projective (SL(4) graph): poses are the rigid parts of the decomposed
  world cameras, so every exported point projects onto the pixel it came from up to the dropped
  skew, whatever the world's distortion.
- Images are the keyframes' colours on the reconstruction grid (the grid ``K`` refers to).

Every file is written to a temporary name and renamed into place.
"""

from __future__ import annotations

import json
import struct
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from .errors import UserError
from .geometry import se3_inverse
from .atomic import atomic_path, atomic_write_bytes
from .result.outputs import write_ply
from .result.reading import KeyframeData, KeyframeRecord, RunResult, load_result

FORMATS = ("colmap", "nerfstudio", "ply")
PINHOLE_MODEL_ID = 1  # COLMAP's camera model id for PINHOLE (fx, fy, cx, cy)
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
DEFAULT_MAX_POINTS = 1_000_000
"""Points in the COLMAP / nerfstudio point cloud: a common initial size for Gaussian splatting
and well inside what COLMAP's tools load quickly."""


@dataclass
class ExportReport:
    """What an export wrote: the folder, counts, the largest skew dropped and seconds taken."""

    format: str
    path: Path
    images: int
    points: int
    max_skew_px: float
    mean_reprojection_px: float
    seconds: float

    def line(self) -> str:
        extra = f", {self.points} points" if self.points else ""
        skew = (f"; skew up to {self.max_skew_px:.3g} px dropped (mean reprojection {self.mean_reprojection_px:.3g} px)"
                if self.max_skew_px > 0 else "")
        return f"wrote {self.format} export of {self.images} keyframes{extra} to {self.path} in {self.seconds:.1f} s{skew}"


# ------------------------------------------------------------------------- conventions
def pinhole_params(K: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` intrinsics -> ``(..., 4)`` ``(fx, fy, cx, cy)`` in the pixel-corner convention
    of COLMAP / nerfstudio (top-left pixel centre at 0.5); the skew ``K[0, 1]`` is dropped."""
    K = np.asarray(K, np.float64)
    K = K / K[..., 2:3, 2:3]
    return np.stack([K[..., 0, 0], K[..., 1, 1], K[..., 0, 2] + 0.5, K[..., 1, 2] + 0.5], axis=-1)


def colmap_pose(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(N, 4, 4)`` world-from-camera -> COLMAP ``qvec (N, 4)`` ``(qw, qx, qy, qz)`` and ``tvec (N, 3)``
    of camera-from-world."""
    T_cam_world = se3_inverse(T_world_cam)
    xyzw = Rotation.from_matrix(T_cam_world[:, :3, :3]).as_quat()
    qvec = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    qvec *= np.where(qvec[:, :1] < 0, -1.0, 1.0)
    return qvec, T_cam_world[:, :3, 3]


def nerfstudio_transform(T_world_cam: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` world-from-camera with OpenCV axes -> nerfstudio's ``transform_matrix``
    (world-from-camera, OpenGL axes: y up, z back)."""
    return np.asarray(T_world_cam, np.float64) @ OPENCV_TO_OPENGL


# ------------------------------------------------------------------------- keyframe pass
@dataclass
class _KeyframeSample:
    record: KeyframeRecord
    xyz: np.ndarray  # (M, 3) float64 world points
    rgb: np.ndarray  # (M, 3) uint8
    uv: np.ndarray  # (M, 2) float64 observed pixel, pixel-corner convention
    error: np.ndarray  # (M,) reprojection error (px) under the exported PINHOLE camera


def _evenly(count: int, limit: int) -> np.ndarray:
    """Indices of at most ``limit`` of ``count`` items, evenly spread (deterministic)."""
    if limit <= 0 or count <= limit:
        return np.arange(count)
    return np.round(np.linspace(0, count - 1, limit)).astype(np.int64)


def _sample_keyframe(record: KeyframeRecord, data: KeyframeData, limit: int) -> _KeyframeSample:
    rows, cols = np.nonzero(data.mask)
    pick = _evenly(len(rows), limit)
    rows, cols = rows[pick], cols[pick]
    xyz = data.points_world[rows, cols].astype(np.float64)
    fx, fy, cx, cy = pinhole_params(record.K)
    T_cam_world = se3_inverse(record.T_world_cam)
    X_cam = xyz @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = np.where(np.abs(X_cam[:, 2]) > 1e-12, X_cam[:, 2], 1e-12)
    projected = np.stack([fx * X_cam[:, 0] / z + cx, fy * X_cam[:, 1] / z + cy], axis=1)
    uv = np.stack([cols + 0.5, rows + 0.5], axis=1).astype(np.float64)
    return _KeyframeSample(record, xyz, data.colors[rows, cols], uv, np.linalg.norm(projected - uv, axis=1))


def _write_image(path: Path, rgb: np.ndarray) -> None:
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1] if path.suffix == ".png" else [cv2.IMWRITE_JPEG_QUALITY, 95]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params):
            raise UserError(f"cannot write image {path}; check that the output folder is writable")


def _keyframe_pass(records: Sequence[KeyframeRecord], images_dir: Path | None, points_per_keyframe: int,
                   image_ext: str, workers: int = 2) -> Iterator[_KeyframeSample]:
    """Read each keyframe once: write its image (when ``images_dir``) and sample its points."""

    def one(record: KeyframeRecord) -> _KeyframeSample:
        data = record.load()
        if images_dir is not None:
            _write_image(images_dir / image_name(record, image_ext), data.colors)
        return _sample_keyframe(record, data, points_per_keyframe)

    # numpy loading, PNG encoding and the projections release the GIL: two threads use both cores
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        yield from pool.map(one, records)


def image_name(record: KeyframeRecord, ext: str = ".png") -> str:
    return f"{record.frame_index:06d}{ext}"


def _quota(records: Sequence[KeyframeRecord], max_points: int) -> int:
    return max(1, max_points // max(1, len(records))) if max_points > 0 else 0


# ------------------------------------------------------------------------- COLMAP
def _colmap_binary(samples: Sequence[_KeyframeSample], image_ext: str) -> tuple[bytes, bytes, bytes]:
    """cameras.bin, images.bin, points3D.bin (COLMAP's documented binary layout, little-endian)."""
    records = [s.record for s in samples]
    params = pinhole_params(np.stack([r.K for r in records]))
    qvec, tvec = colmap_pose(np.stack([r.T_world_cam for r in records]))
    camera_dtype = np.dtype([("id", "<i4"), ("model", "<i4"), ("width", "<u8"), ("height", "<u8"), ("params", "<f8", 4)])
    cameras = np.zeros(len(records), camera_dtype)
    cameras["id"] = np.arange(1, len(records) + 1)
    cameras["model"] = PINHOLE_MODEL_ID
    cameras["width"] = [r.image_size[0] for r in records]
    cameras["height"] = [r.image_size[1] for r in records]
    cameras["params"] = params
    cameras_bin = struct.pack("<Q", len(records)) + cameras.tobytes()

    counts = np.array([len(s.xyz) for s in samples], dtype=np.int64)
    first_id = np.concatenate([[1], 1 + np.cumsum(counts)[:-1]])
    point2d_dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
    parts = [struct.pack("<Q", len(records))]
    for i, sample in enumerate(samples):
        parts.append(struct.pack("<i7di", i + 1, *qvec[i], *tvec[i], i + 1))
        parts.append(image_name(sample.record, image_ext).encode() + b"\x00")
        observations = np.empty(counts[i], point2d_dtype)
        observations["x"], observations["y"] = sample.uv[:, 0], sample.uv[:, 1]
        observations["id"] = first_id[i] + np.arange(counts[i])
        parts.append(struct.pack("<Q", counts[i]) + observations.tobytes())
    images_bin = b"".join(parts)

    point_dtype = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("track", "<u8"),
                            ("image", "<i4"), ("point2d", "<i4")])
    points = np.empty(int(counts.sum()), point_dtype)
    points["id"] = np.arange(1, len(points) + 1)
    points["xyz"] = np.concatenate([s.xyz for s in samples]) if samples else np.zeros((0, 3))
    points["rgb"] = np.concatenate([s.rgb for s in samples]) if samples else np.zeros((0, 3), np.uint8)
    points["error"] = np.concatenate([s.error for s in samples]) if samples else np.zeros(0)
    points["track"] = 1  # each point is one keyframe pixel: observed once, by that keyframe
    points["image"] = np.repeat(np.arange(1, len(samples) + 1), counts)
    points["point2d"] = np.concatenate([np.arange(c) for c in counts]) if samples else np.zeros(0)
    points3d_bin = struct.pack("<Q", len(points)) + points.tobytes()
    return cameras_bin, images_bin, points3d_bin


def _rows(fmt: str, columns: Sequence[np.ndarray]) -> str:
    return "".join(fmt % row for row in zip(*(c.tolist() for c in columns)))


def _colmap_text(samples: Sequence[_KeyframeSample], image_ext: str) -> tuple[str, str, str]:
    """cameras.txt, images.txt, points3D.txt (COLMAP's documented text layout)."""
    records = [s.record for s in samples]
    params = pinhole_params(np.stack([r.K for r in records]))
    qvec, tvec = colmap_pose(np.stack([r.T_world_cam for r in records]))
    ids = np.arange(1, len(records) + 1)
    cameras = ("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
               f"# Number of cameras: {len(records)}\n")
    cameras += _rows("%d PINHOLE %d %d %.17g %.17g %.17g %.17g\n",
                     [ids, np.array([r.image_size[0] for r in records]), np.array([r.image_size[1] for r in records]),
                      *params.T])
    counts = np.array([len(s.xyz) for s in samples], dtype=np.int64)
    first_id = np.concatenate([[1], 1 + np.cumsum(counts)[:-1]])
    lines = ["# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
             f"#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: {len(records)}, mean observations per image: "
             f"{counts.mean() if len(counts) else 0:.6f}\n"]
    for i, sample in enumerate(samples):
        lines.append("%d %s %s %d %s\n" % (i + 1, " ".join(f"{v:.17g}" for v in qvec[i]), " ".join(f"{v:.17g}" for v in tvec[i]),
                                           i + 1, image_name(sample.record, image_ext)))
        point_ids = first_id[i] + np.arange(counts[i])
        lines.append(_rows("%.17g %.17g %d ", [sample.uv[:, 0], sample.uv[:, 1], point_ids]).rstrip() + "\n")
    images = "".join(lines)
    header = ("# 3D point list with one line of data per point:\n"
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
              f"# Number of points: {int(counts.sum())}, mean track length: 1\n")
    if not samples:
        return cameras, images, header
    xyz = np.concatenate([s.xyz for s in samples])
    rgb = np.concatenate([s.rgb for s in samples]).astype(np.int64)
    error = np.concatenate([s.error for s in samples])
    image_ids = np.repeat(ids, counts)
    point2d = np.concatenate([np.arange(c) for c in counts])
    points = header + _rows("%d %.17g %.17g %.17g %d %d %d %.6g %d %d\n",
                            [np.arange(1, len(xyz) + 1), *xyz.T, *rgb.T, error, image_ids, point2d])
    return cameras, images, points


def export_colmap(result: RunResult, out_dir: str | Path, max_points: int = DEFAULT_MAX_POINTS, binary: bool = True,
                  text: bool = False, image_ext: str = ".png", progress: Callable[[int, int], None] | None = None) -> ExportReport:
    """Write a COLMAP sparse model of the keyframes.

    Layout: ``out_dir/images/NNNNNN.png`` (keyframe colours) and ``out_dir/sparse/0/`` with
    ``cameras``, ``images``, ``points3D`` as ``.bin`` (``binary``) and/or ``.txt`` (``text``).
    One PINHOLE camera per keyframe (image ``i`` uses camera ``i``); each 3D point is one
    confident keyframe pixel (evenly spread, ``max_points`` in all), with a track of length one
    (that keyframe and pixel) and its reprojection error under the exported camera.
    """
    if not (binary or text):
        raise UserError("choose binary and/or text COLMAP files")
    start = time.perf_counter()
    records = result.require_keyframes("the COLMAP export")
    out_dir = Path(out_dir)
    images_dir, sparse_dir = out_dir / "images", out_dir / "sparse" / "0"
    images_dir.mkdir(parents=True, exist_ok=True)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    samples = _collect(records, images_dir, _quota(records, max_points), image_ext, progress)
    if binary:
        for name, data in zip(("cameras.bin", "images.bin", "points3D.bin"), _colmap_binary(samples, image_ext)):
            atomic_write_bytes(sparse_dir / name, data)
    if text:
        for name, data in zip(("cameras.txt", "images.txt", "points3D.txt"), _colmap_text(samples, image_ext)):
            atomic_write_bytes(sparse_dir / name, data.encode())
    return _report("colmap", out_dir, samples, start)


def _collect(records, images_dir, quota, image_ext, progress) -> list[_KeyframeSample]:
    samples = []
    for sample in _keyframe_pass(records, images_dir, quota, image_ext):
        samples.append(sample)
        if progress is not None:
            progress(len(samples), len(records))
    return samples


def _report(fmt: str, path: Path, samples: Sequence[_KeyframeSample], start: float) -> ExportReport:
    skew = max((abs(s.record.K[0, 1] / s.record.K[2, 2]) for s in samples), default=0.0)
    errors = np.concatenate([s.error for s in samples]) if samples else np.zeros(0)
    return ExportReport(fmt, path, len(samples), int(len(errors)), float(skew),
                        float(errors.mean()) if len(errors) else 0.0, time.perf_counter() - start)


# ------------------------------------------------------------------------- nerfstudio
def export_nerfstudio(result: RunResult, out_dir: str | Path, max_points: int = DEFAULT_MAX_POINTS,
                      image_ext: str = ".png", progress: Callable[[int, int], None] | None = None) -> ExportReport:
    """Write ``out_dir/transforms.json``, the keyframe images in ``out_dir/images/`` and the point
    cloud ``out_dir/sparse_pc.ply`` (``ply_file_path``, nerfstudio's Gaussian-splatting seed).

    Per-frame intrinsics (``fl_x, fl_y, cx, cy, w, h``; PINHOLE, skew dropped) and
    ``transform_matrix`` = world-from-camera with OpenGL camera axes.
    """
    start = time.perf_counter()
    records = result.require_keyframes("the nerfstudio export")
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    samples = _collect(records, out_dir / "images", _quota(records, max_points), image_ext, progress)
    frames = []
    for sample in samples:
        record = sample.record
        fx, fy, cx, cy = pinhole_params(record.K).tolist()
        frames.append({
            "file_path": f"images/{image_name(record, image_ext)}",
            "transform_matrix": nerfstudio_transform(record.T_world_cam).tolist(),
            "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": record.image_size[0], "h": record.image_size[1],
            "timestamp": record.timestamp, "frame_index": record.frame_index, "submap_id": record.submap_id,
        })
    xyz = np.concatenate([s.xyz for s in samples]).astype(np.float32)
    rgb = np.concatenate([s.rgb for s in samples])
    write_ply(out_dir / "sparse_pc.ply", xyz, rgb)
    transforms = {"camera_model": "PINHOLE", "ply_file_path": "sparse_pc.ply",
                  "frames": frames}
    atomic_write_bytes(out_dir / "transforms.json", json.dumps(transforms, indent=2).encode())
    return _report("nerfstudio", out_dir, samples, start)


# ------------------------------------------------------------------------- PLY per submap
def export_submap_ply(result: RunResult, out_dir: str | Path,
                      progress: Callable[[int, int], None] | None = None) -> ExportReport:
    """One coloured PLY per submap, ``out_dir/submap_NNNN.ply``, with every confident pixel of its
    keyframes in world coordinates (``map.ply`` of the run is the subsampled union)."""
    start = time.perf_counter()
    records = result.require_keyframes("the PLY export")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    by_submap: dict[int, list[_KeyframeSample]] = {}
    done = 0
    for sample in _keyframe_pass(records, None, 0, ".png"):
        by_submap.setdefault(sample.record.submap_id, []).append(sample)
        done += 1
        if progress is not None:
            progress(done, len(records))
    for submap_id, samples in sorted(by_submap.items()):
        write_ply(out_dir / f"submap_{submap_id:04d}.ply", np.concatenate([s.xyz for s in samples]).astype(np.float32),
                  np.concatenate([s.rgb for s in samples]))
    report = _report("ply", out_dir, [s for group in by_submap.values() for s in group], start)
    report.max_skew_px = 0.0  # no camera model is written
    return report


# ------------------------------------------------------------------------- entry point
def export_result(result_dir: str | Path, fmt: str, out_dir: str | Path | None = None, **options) -> ExportReport:
    """Export the result folder ``result_dir`` as ``fmt`` ("colmap", "nerfstudio" or "ply") into
    ``out_dir`` (default ``result_dir/export_<fmt>``)."""
    if fmt not in FORMATS:
        raise UserError(f"unknown export format '{fmt}'; use one of {', '.join(FORMATS)}")
    result = load_result(result_dir)
    result.require_keyframes(f"the {fmt} export")
    target = Path(out_dir) if out_dir is not None else result.path / f"export_{fmt}"
    if target.exists() and not target.is_dir():
        raise UserError(f"--out {target} exists and is not a folder; choose another output folder")
    writer = {"colmap": export_colmap, "nerfstudio": export_nerfstudio, "ply": export_submap_ply}[fmt]
    return writer(result, target, **options)

