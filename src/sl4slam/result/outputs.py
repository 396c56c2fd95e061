"""Writing a run's results: trajectory, dense map, per-keyframe points, summary, plots.

Every file is written to a temporary name and renamed into place, so an interrupted run never
leaves a partial file, and nothing non-finite is ever written. During a run,
:func:`write_checkpoint` keeps ``trajectory.txt`` and ``summary.json`` current; at the end (or on
an interruption) :func:`write_outputs` writes everything.

A result folder (format version 3, ``summary.json["format"]``):

| file | content |
|---|---|
| ``trajectory.txt`` | keyframe poses ``T_world_cam``, TUM format |
| ``trajectory_gt.txt`` | ground truth of the same keyframes, when known |
| ``map.ply`` | coloured, confidence-filtered dense map |
| ``keyframes/NNNNNN.npz`` | per keyframe (NNNNNN its frame index), ``output.keyframes``: "compact" (default) the run's own float16 depth in the keyframe's local frame with that frame's camera and projective map into the world (the same world points, recomputed), ``mask``, half-resolution uint8 confidence percentile, colours as one JPEG, deflated (decision: docs/decisions/keyframe-format.md); "full" ``points_world`` (H, W, 3) float32, ``mask`` (H, W), ``confidence`` (H, W) float16 percentile in its submap, ``colors`` (H, W, 3) uint8, uncompressed (3.66 MB); both with ``K``, ``T_world_cam``, ``timestamp``, ``frame_index``, ``submap_id``, ``segment``; "none": no folder. ``sl4slam.result.reading`` documents both layouts and reads either into the same world points |
| ``summary.json`` | status, settings, counts, every edge (loops with their verdicts), segments, timings, memory, ATE |
| ``trajectory.png`` | top view of the trajectory (and ground truth) |
"""

from __future__ import annotations

import dataclasses
import json
import resource
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import UserError
from ..metrics import ATEResult, ate
from ..atomic import atomic_path, atomic_write_bytes, atomic_write_npz
from ..parallel import cpu_count, ordered_map
from ..submap import StoredKeyframe
from . import SLAMResult
from .reading import KEYFRAME_LAYOUTS, encode_colors, encode_depth, to_world

RESULT_FORMAT = {"name": "sl4slam-result", "version": 3}


def output_workers() -> int:
    """Threads for the per-keyframe output work: the CPUs this process may use, at most 8."""
    return min(8, cpu_count())


def keyframe_world_points(keyframe: StoredKeyframe, H_world_submap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(H, W, 3)`` float32 of one keyframe and a validity mask ``(H, W)``.

    Points go through the projective ``H_world_submap``; a point is valid when it passed the
    confidence mask, and maps to a finite point in front of the plane at infinity (w > 0).
    """
    return to_world(keyframe.points(), H_world_submap, keyframe.mask())


def write_map_and_keyframes(result: SLAMResult, out_dir: Path, max_points: int, voxel_size: float = 0.0, seed: int = 0,
                            keyframe_dir: Path | None = None, layout: str = "compact",
                            workers: int | None = None) -> int:
    """``map.ply`` (and, with ``keyframe_dir``, one ``.npz`` per keyframe in ``layout``, "compact"
    or "full") from one pass over the keyframes: each keyframe's world points are computed once.
    Returns the map's point count.

    The map is confidence-filtered, subsampled (seeded) to at most ``max_points`` and optionally
    reduced to one point (centroid, mean colour) per voxel of size ``voxel_size``. The keyframes
    are processed in ``workers`` threads (default :func:`output_workers`); the outputs do not depend
    on it.
    """
    counts = [int(np.unpackbits(k.mask_bits).sum()) for k in result.keyframes]
    keep_fraction = min(1.0, max_points / max(1, sum(counts)))
    rng = np.random.default_rng(seed)
    if keyframe_dir is not None:
        keyframe_dir.mkdir(parents=True, exist_ok=True)
    chunks_xyz, chunks_rgb = [], []
    if keyframe_dir is not None and layout not in KEYFRAME_LAYOUTS:
        raise ValueError(f"keyframe layout must be 'compact' or 'full', got {layout!r}")

    def one(item: tuple[int, StoredKeyframe]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        index, keyframe = item
        H = result.H_world(keyframe)
        X, valid = keyframe_world_points(keyframe, H)
        colors = result.keyframe_colors(keyframe)
        if keyframe_dir is not None:
            write = _write_compact_keyframe if layout == "compact" else _write_keyframe
            write(keyframe_dir, keyframe, X, valid, colors, result, index, H)
        return X, valid, colors

    # each keyframe's points, colours and file are independent (numpy, OpenCV and torch release the
    # GIL); the random draws below stay in keyframe order, so the map is the same for any worker count
    for X, valid, colors in ordered_map(one, enumerate(result.keyframes), output_workers() if workers is None else workers):
        pick = valid if keep_fraction >= 1.0 else valid & (rng.random(valid.shape) < keep_fraction)
        chunks_xyz.append(X[pick])
        chunks_rgb.append(colors[pick])
    xyz = np.concatenate(chunks_xyz) if chunks_xyz else np.zeros((0, 3), np.float32)
    rgb = np.concatenate(chunks_rgb) if chunks_rgb else np.zeros((0, 3), np.uint8)
    if len(xyz) > max_points:  # the per-keyframe draw is only about right: cap it exactly
        chosen = np.sort(rng.choice(len(xyz), size=max_points, replace=False))
        xyz, rgb = xyz[chosen], rgb[chosen]
    if voxel_size > 0 and len(xyz):
        xyz, rgb = voxel_downsample(xyz, rgb, voxel_size)
    write_ply(out_dir / "map.ply", xyz, rgb)
    return len(xyz)


def _identity(keyframe: StoredKeyframe, result: SLAMResult, index: int) -> dict:
    """What both keyframe layouts hold besides the dense arrays."""
    return dict(K=result.K[index], T_world_cam=result.T_world_cam[index], timestamp=keyframe.timestamp,
                frame_index=keyframe.frame_index, submap_id=keyframe.submap_id, segment=int(result.segments[index]))


def _write_keyframe(directory: Path, keyframe: StoredKeyframe, X: np.ndarray, valid: np.ndarray, colors: np.ndarray,
                    result: SLAMResult, index: int, H_world_local: np.ndarray | None = None) -> None:
    """The full layout: float32 world points, uncompressed (18 bytes per pixel)."""
    atomic_write_npz(directory / f"{keyframe.frame_index:06d}.npz", dict(
        points_world=np.where(valid[..., None], X, 0.0).astype(np.float32), mask=valid, colors=colors,
        confidence=keyframe.confidence_percentile().astype(np.float16), **_identity(keyframe, result, index)),
        compressed=False)


def _write_compact_keyframe(directory: Path, keyframe: StoredKeyframe, X: np.ndarray, valid: np.ndarray,
                            colors: np.ndarray, result: SLAMResult, index: int, H_world_local: np.ndarray) -> None:
    """The compact layout (``sl4slam.result.reading`` documents it): the keyframe's own depth
    (where ``valid``) with its local camera and the map ``H_world_local`` that gave ``X``, so a
    reader recomputes ``X`` exactly; the mask; the stored half-resolution confidence ranks; the
    colours as JPEG. ``X`` itself is not written."""
    atomic_write_npz(directory / f"{keyframe.frame_index:06d}.npz", dict(
        depth_bytes=encode_depth(keyframe.depth, valid), mask=valid, confidence_rank=keyframe.confidence_rank,
        colors_jpeg=encode_colors(colors), K_local=np.asarray(keyframe.K, np.float64),
        T_cam_local=np.asarray(keyframe.T_cam_submap, np.float64), H_world_local=np.asarray(H_world_local, np.float64),
        **_identity(keyframe, result, index)), compressed=True)


def write_keyframe_file(layout: str, directory: Path, keyframe: StoredKeyframe, X: np.ndarray, valid: np.ndarray,
                        colors: np.ndarray, result: SLAMResult, index: int, H_world_local: np.ndarray) -> None:
    """Write one keyframe file, ``directory/NNNNNN.npz``, in ``layout`` ("compact" or "full"), as a run does.

    Args:
        keyframe: the stored keyframe; ``index`` its position in ``result.keyframes``.
        X, valid: its world points and their mask (:func:`keyframe_world_points` with ``H_world_local``).
        colors: its colours (``result.keyframe_colors``).
        H_world_local: the map from its submap to the world that gave ``X``.
    """
    if layout not in KEYFRAME_LAYOUTS:
        raise ValueError(f"keyframe layout must be 'compact' or 'full', got {layout!r}")
    write = _write_compact_keyframe if layout == "compact" else _write_keyframe
    write(directory, keyframe, X, valid, colors, result, index, H_world_local)


def voxel_downsample(xyz: np.ndarray, rgb: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Average points and colours per voxel: ``(N, 3)`` -> ``(M, 3)``."""
    keys = np.floor(xyz / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, xyz)
    colour_sums = np.zeros((len(counts), 3))
    np.add.at(colour_sums, inverse, rgb.astype(np.float64))
    return (sums / counts[:, None]).astype(np.float32), np.round(colour_sums / counts[:, None]).astype(np.uint8)


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY with float32 xyz and uint8 rgb (atomic)."""
    if not np.all(np.isfinite(xyz)):
        raise UserError("refusing to write a point cloud with NaN/Inf coordinates")
    vertex = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    vertex["red"], vertex["green"], vertex["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    atomic_write_bytes(Path(path), header.encode("ascii") + vertex.tobytes())


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a PLY written by ``write_ply``: ``(N, 3)`` float32 xyz, ``(N, 3)`` uint8 rgb."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = int([line for line in data[:end].decode("ascii").splitlines() if line.startswith("element vertex")][0].split()[-1])
    vertex = np.frombuffer(data[end:], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")], count=count)
    return np.stack([vertex["x"], vertex["y"], vertex["z"]], -1), np.stack([vertex["red"], vertex["green"], vertex["blue"]], -1)


def peak_memory() -> dict:
    """Process peak resident memory (and CUDA peak when used), in MiB."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rss_mib = rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024
    out = {"peak_rss_mib": round(rss_mib, 1)}
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
        out["peak_cuda_mib"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    return out


def compute_ate(result: SLAMResult) -> ATEResult | None:
    """ATE of the keyframe trajectory when ground truth is known (same timestamps)."""
    if result.T_world_cam_gt is None or len(result.keyframes) < 3:
        return None
    return ate(result.timestamps, result.T_world_cam, result.timestamps, result.T_world_cam_gt)


def plot_trajectories(path: Path, curves: dict[str, np.ndarray], gt: np.ndarray | None, title: str) -> None:
    """Top view of trajectories ``{label: (N, 3)}`` (and ground truth) on their principal plane.

    The plane is spanned by the two main directions of the ground truth (or of the first curve),
    a top view whatever the dataset's world axes are; the axis labels say so. Starts are marked
    with a circle, ends with a square. Units are the trajectory's (metres once aligned to ground truth).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reference = gt if gt is not None else next(iter(curves.values()))
    centre = reference.mean(0)
    _, _, Vt = np.linalg.svd(reference - centre)  # full: two directions even for a single keyframe
    axes = Vt[:2]
    unit = "m" if gt is not None else "map units"
    fig, ax = plt.subplots(figsize=(6, 6))
    if gt is not None:
        p = (gt - centre) @ axes.T
        ax.plot(p[:, 0], p[:, 1], "k--", lw=1.5, label="ground truth")
    for label, positions in curves.items():
        p = (positions - centre) @ axes.T
        ax.plot(p[:, 0], p[:, 1], "-", lw=1.2, label=label)
        colour = ax.lines[-1].get_color()
        ax.plot(p[:1, 0], p[:1, 1], "o", ms=6, color=colour, label=f"{label} start")
        ax.plot(p[-1:, 0], p[-1:, 1], "s", ms=6, color=colour, label=f"{label} end")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"first principal direction of the trajectory ({unit})")
    ax.set_ylabel(f"second principal direction ({unit})")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)


def summarize(result: SLAMResult, config_dict: dict, ate_result: ATEResult | None, extra: dict | None = None) -> dict:
    """The content of ``summary.json``."""
    odometry = [e for e in result.edges if e.kind == "odometry" and e.accepted]
    loops = [e for e in result.edges if e.kind == "loop" and e.accepted]

    def ratios(edges: Sequence) -> dict:
        values = np.array([e.inlier_ratio for e in edges]) if edges else np.zeros(0)
        return {"count": len(values), "median": float(np.median(values)) if len(values) else None,
                "min": float(values.min()) if len(values) else None}

    stats = result.stats
    summary = {
        "format": dict(RESULT_FORMAT),
        "counts": {k: stats[k] for k in ("frames", "keyframes", "submaps", "loops", "loops_rejected", "fallbacks",
                                         "segments") if k in stats},
        "dropped_frames": stats.get("dropped_frames", {}),
        "frontend_failures": stats.get("frontend_failures", []),
        "notes": stats.get("notes", []),
        "inlier_ratio": {"odometry": ratios(odometry), "loops": ratios(loops)},
        "fallbacks": [{"submaps": [e.submap_from, e.submap_to], "frame": e.frame_index, "reason": e.fallback}
                      for e in odometry if e.fallback],
        "loops": [e.as_dict() for e in loops],
        "rejected_loops": [e.as_dict() for e in result.edges if e.kind == "loop" and not e.accepted],
        "segments": [{"first_submap": e.submap_to, "reason": e.reason} for e in result.edges if e.kind == "segment"],
        "edges": [e.as_dict() for e in result.edges],
        "seconds": {"total": round(stats.get("seconds_total", 0.0), 3),
                    "by_stage": {k: round(v, 3) for k, v in stats.get("seconds_by_stage", {}).items()},
                    "per_submap_median": stats.get("seconds_per_submap", {}),
                    "final_optimization": stats.get("seconds_final_optimization", 0.0)},
        "memory": {**peak_memory(), "stored_keyframe_bytes": stats.get("stored_bytes", 0),
                   "stored_bytes_per_keyframe": round(stats.get("stored_bytes", 0) / max(1, len(result.keyframes)))},
        "metric_upgrade": stats.get("metric_upgrade", []),
        **{key: stats[key] for key in ("intrinsics", "metric_depth") if key in stats},
        "config": config_dict,
    }
    if ate_result is not None:
        summary["ate"] = {"rmse": ate_result.rmse, "mean": ate_result.mean, "median": ate_result.median,
                          "max": ate_result.max, "poses": ate_result.num_poses, "scale": ate_result.scale,
                          "unit": "m", "metric": "evo_ape -as (translation, Sim(3) Umeyama alignment)"}
    if extra:
        summary.update(extra)
    return summary


def _settings(resolved) -> tuple[Any, dict]:
    """The resolved config of a run (``sl4slam.resolve.ResolvedConfig``) and what the summary records of it."""
    return resolved, {"config": dataclasses.asdict(resolved.config), "resolved": resolved.choices(),
                      "graph": {"group": resolved.group.value, "design": resolved.graph.value,
                                "alignment": resolved.alignment.value}}


def write_checkpoint(result: SLAMResult, out_dir: Path, config, extra: dict | None = None) -> dict:
    """``trajectory.txt`` and ``summary.json`` of the current state (cheap; called during a run).
    ``config``: the run's resolved config (``sl4slam.resolve.ResolvedConfig``)."""
    from ..io import write_tum_trajectory

    out_dir = Path(out_dir)
    if len(result.keyframes) and np.all(np.isfinite(result.T_world_cam)):
        write_tum_trajectory(out_dir / "trajectory.txt", result.timestamps, result.T_world_cam)
    _, recorded = _settings(config)
    summary = summarize(result, recorded.pop("config"), None, {"status": "running", **recorded, **(extra or {})})
    atomic_write_bytes(out_dir / "summary.json", json.dumps(summary, indent=2).encode())
    return summary


def write_outputs(result: SLAMResult, out_dir: Path, config, source_name: str = "", skipped: Sequence[str] = (),
                  status: str = "complete", extra: dict | None = None) -> dict:
    """Write ``trajectory.txt`` (and ``trajectory_gt.txt``), ``map.ply``, ``keyframes/``,
    ``summary.json``, ``trajectory.png``. Returns the summary dict. ``config``: the run's resolved
    config (``sl4slam.resolve.ResolvedConfig``).

    Raises ``UserError`` when a file cannot be written (the message names it).
    """
    from ..io import write_tum_trajectory

    resolved, recorded = _settings(config)
    config = resolved.config
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        if not np.all(np.isfinite(result.T_world_cam)):
            raise UserError("the optimized trajectory has non-finite poses; the alignment degenerated — see summary fallbacks")
        if len(result.keyframes):
            write_tum_trajectory(out_dir / "trajectory.txt", result.timestamps, result.T_world_cam)
        if result.T_world_cam_gt is not None:
            write_tum_trajectory(out_dir / "trajectory_gt.txt", result.timestamps, result.T_world_cam_gt)
        layout = config.output.keyframes
        keyframe_dir = out_dir / "keyframes" if layout != "none" else None
        map_points = write_map_and_keyframes(result, out_dir, config.output.max_map_points, config.output.voxel_size,
                                             seed=config.output.seed, keyframe_dir=keyframe_dir, layout=layout)
        ate_result = compute_ate(result)
        if len(result.keyframes):
            curves = {"estimate": ate_result.positions_aligned if ate_result else result.T_world_cam[:, :3, 3]}
            name = f"{source_name}, " if source_name else ""
            title = f"{name}{resolved.group.value} {resolved.graph.value} graph, top view"
            if ate_result is not None:
                title += f"\nATE RMSE {ate_result.rmse:.4f} m over {ate_result.num_poses} keyframes (Sim(3)-aligned)"
            plot_trajectories(out_dir / "trajectory.png", curves, ate_result.positions_gt if ate_result else None, title)
        summary = summarize(result, recorded.pop("config"), ate_result,
                            {"status": status, "source": source_name, "skipped_inputs": list(skipped),
                             "map_points": int(map_points), **recorded, **(extra or {})})
        atomic_write_bytes(out_dir / "summary.json", json.dumps(summary, indent=2).encode())
    except OSError as exc:
        raise UserError(f"cannot write the results into {out_dir}: {exc.strerror or exc} ({exc.filename or out_dir})") from None
    return summary
