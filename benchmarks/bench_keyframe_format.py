"""Bytes, write and read time of a keyframe file at 518x392: the compact layout against the full one.

One run of the pipeline (simulated frontend, VGGT-like errors, the SL(4) submap graph with a 0.1
perspective distortion per submap and no metric upgrade, so that the world map is projective) on
realistic frames, and its keyframes written from the same in-memory result in both layouts of
``sl4slam.result.reading``. The frames are the real TUM excerpt in ``shared/data/`` resized to
518x392 (colours by area, depth by nearest pixel, the intrinsics scaled) and the synthetic world
rendered at 518x392. For each: bytes per keyframe and per array, write and read time per keyframe
(median; read warm, from the page cache), and what the compact file loses against the full one:
world points (distance relative to the point's depth), mask, colours (JPEG) and confidence.
A short table of alternatives (depth along the world camera's axis, raw float16 depth, other JPEG
settings) measured on the same keyframes justifies the choices.

Writes ``benchmarks/results/keyframe_format.md`` (``--out`` for another file).
Usage: ``python benchmarks/bench_keyframe_format.py [--width 518] [--height 392] [--synthetic-frames 90]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import tempfile
import time
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np

from harness import (date_text, result_file, run_sequence, shared_sequence, simulated_config, synthetic_world,
                     write_report)
from sl4slam.geometry import se3_inverse
from sl4slam.result.outputs import keyframe_world_points, write_keyframe_file
from sl4slam.result.reading import JPEG_QUALITY, load_result

TUM = shared_sequence("xyz37")
RESULTS = result_file("keyframe_format")
TUM_K = (517.3, 516.5, 318.6, 255.3)  # fr1 RGB camera at 640x480 (CALIBRATION.txt)


def resized_tum(target: Path, width: int, height: int) -> Path:
    """A copy of the TUM excerpt at ``width`` x ``height`` with its intrinsics scaled."""
    (target / "rgb").mkdir(parents=True)
    (target / "depth").mkdir()
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        shutil.copy(TUM / name, target / name)
    for path in sorted((TUM / "rgb").glob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        cv2.imwrite(str(target / "rgb" / path.name), cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA))
    for path in sorted((TUM / "depth").glob("*.png")):
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(target / "depth" / path.name), cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST))
    sx, sy = width / 640.0, height / 480.0
    fx, fy, cx, cy = TUM_K
    (target / "calibration.txt").write_text(
        f"fx = {fx * sx} fy = {fy * sy} cx = {(cx + 0.5) * sx - 0.5} cy = {(cy + 0.5) * sy - 0.5}\n")
    return target


def run_config(tau_disparity: float):
    """The run's settings: a projective world map (submap graph, perspective 0.1, no metric upgrade)."""
    return simulated_config({"sim.profile": "vggt", "sim.perspective": 0.1, "backend.graph": "submap",
                             "upgrade.mode": "off", "submap.size": 4, "retrieval.kind": "none",
                             "keyframes.tau_disparity": tau_disparity})


def member_bytes(path: Path) -> dict[str, int]:
    with zipfile.ZipFile(path) as archive:
        return {info.filename.removesuffix(".npy"): info.compress_size for info in archive.infolist()}


def measure(name: str, sequence: Path, tau_disparity: float, scratch: Path, repeats: int) -> dict:
    """Run once, write every keyframe in both layouts (``repeats`` times, timed), read them back."""
    result = run_sequence(run_config(tau_disparity), sequence, retrieval=None).result
    folders = {layout: scratch / name / layout / "keyframes" for layout in ("full", "compact")}
    write_ms = {layout: [] for layout in folders}  # (wall, CPU) per file
    for folder in folders.values():
        folder.mkdir(parents=True)
    for index, keyframe in enumerate(result.keyframes):
        H = result.H_world(keyframe)
        X, valid = keyframe_world_points(keyframe, H)
        colors = result.keyframe_colors(keyframe)
        for _ in range(repeats):
            for layout, folder in folders.items():
                start, cpu = time.perf_counter(), time.process_time()
                write_keyframe_file(layout, folder, keyframe, X, valid, colors, result, index, H)
                write_ms[layout].append((1000 * (time.perf_counter() - start), 1000 * (time.process_time() - cpu)))
    for layout, folder in folders.items():  # load_result needs the folder's trajectory and summary
        shutil.copy(sequence / "groundtruth.txt", folder.parent / "trajectory.txt")
        (folder.parent / "summary.json").write_text('{"counts": {}}')
    records = {layout: load_result(folder.parent).keyframes for layout, folder in folders.items()}
    read_ms = {layout: [] for layout in folders}
    data = {}
    for _ in range(repeats):
        for layout in folders:
            for record in records[layout]:
                start, cpu = time.perf_counter(), time.process_time()
                data[layout, record.frame_index] = record.load()
                read_ms[layout].append((1000 * (time.perf_counter() - start), 1000 * (time.process_time() - cpu)))
    point_error, colour_error, confidence_error, masks_equal = [], [], [], True
    for full, compact in zip(records["full"], records["compact"]):
        a, b = data["full", full.frame_index], data["compact", compact.frame_index]
        masks_equal &= bool(np.array_equal(a.mask, b.mask))
        T_cam_world = se3_inverse(full.T_world_cam)
        depth = np.abs(a.points_world[a.mask].astype(np.float64) @ T_cam_world[2, :3] + T_cam_world[2, 3])
        point_error.append(np.linalg.norm(a.points_world[a.mask].astype(np.float64) - b.points_world[b.mask], axis=1) / depth)
        colour_error.append(np.abs(a.colors.astype(np.int16) - b.colors).ravel())
        confidence_error.append(float(np.abs(a.confidence - b.confidence).max()))
    sizes = {layout: [r.path.stat().st_size for r in records[layout]] for layout in folders}
    members: dict[str, list[int]] = {}
    for record in records["compact"]:
        for member, size in member_bytes(record.path).items():
            members.setdefault(member, []).append(size)
    colour = np.concatenate(colour_error)
    points = np.concatenate(point_error)
    perspective = max(float(np.abs(d.H_world_local[3, :3]).max()) for (layout, _), d in data.items() if layout == "compact")
    return {
        "name": name, "keyframes": len(result.keyframes), "shape": result.keyframes[0].shape,
        "bytes": {k: statistics.mean(v) for k, v in sizes.items()},
        "write_ms": {k: tuple(np.median(np.array(v), axis=0)) for k, v in write_ms.items()},
        "read_ms": {k: tuple(np.median(np.array(v), axis=0)) for k, v in read_ms.items()},
        "members": {k: statistics.mean(v) for k, v in members.items()},
        "point_error_max": float(points.max()), "masks_equal": masks_equal,
        "colour_mean": float(colour.mean()), "colour_p99": float(np.percentile(colour, 99)), "colour_max": int(colour.max()),
        "confidence_max": max(confidence_error), "perspective": perspective,
        "alternatives": alternatives(result, data, records),
    }


def alternatives(result, data, records) -> dict[str, tuple[float, str]]:
    """Depth and colour codings not chosen, on the same keyframes: mean bytes (deflated) and error."""
    out: dict[str, list] = {}
    for keyframe, record in zip(result.keyframes, records["full"]):
        full = data["full", record.frame_index]
        mask = full.mask
        T_cam_world = se3_inverse(record.T_world_cam)
        X = full.points_world.astype(np.float64)
        z = X @ T_cam_world[2, :3] + T_cam_world[2, 3]  # depth along the world camera's axis
        height, width = mask.shape
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(record.K).T
        for dtype in (np.float16, np.float32):
            stored = np.where(mask, z, 0).astype(dtype)
            X_back = (rays * stored.astype(np.float64)[..., None]) @ record.T_world_cam[:3, :3].T + record.T_world_cam[:3, 3]
            error = np.linalg.norm(X_back - X, axis=-1)[mask] / np.abs(z[mask])
            planes = stored.view(np.uint16 if dtype == np.float16 else np.uint32)
            shuffled = [((planes >> (8 * b)) & 0xFF).astype(np.uint8) for b in range(stored.dtype.itemsize)]
            size = sum(len(zlib.compress(p.tobytes(), 6)) for p in shuffled)
            label = f"depth along the world camera's axis, {np.dtype(dtype).name}, byte planes, deflated"
            out.setdefault(label, []).append((size, float(error.max())))
        raw = np.where(mask, keyframe.depth, 0).astype(np.float16)
        out.setdefault("the run's float16 depth, raw, deflated (no row coding)", []).append(
            (len(zlib.compress(raw.tobytes(), 6)), 0.0))
        bgr = cv2.cvtColor(full.colors, cv2.COLOR_RGB2BGR)
        for quality, sampling, label in ((JPEG_QUALITY, "444", "chosen"), (90, "444", ""), (95, "444", ""),
                                         (90, "420", ""), (95, "420", "")):
            factor = cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444 if sampling == "444" else cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420
            ok, encoded = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_OPTIMIZE, 1,
                                                     cv2.IMWRITE_JPEG_PROGRESSIVE, 1,
                                                     cv2.IMWRITE_JPEG_SAMPLING_FACTOR, factor])
            error = np.abs(cv2.imdecode(encoded, cv2.IMREAD_COLOR).astype(np.int16) - bgr)
            name = f"colours JPEG q{quality} {sampling[0]}:{sampling[1]}:{sampling[2]}" + (f" ({label})" if label else "")
            out.setdefault(name, []).append((len(encoded), float(error.mean()), float(np.percentile(error, 99)), int(error.max())))
        ok, png = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        out.setdefault("colours PNG (lossless)", []).append((len(png), 0.0, 0.0, 0))
    summary = {}
    for label, values in out.items():
        values = np.array(values, dtype=np.float64)
        if label.startswith("colours"):
            summary[label] = (values[:, 0].mean(), f"mean {values[:, 1].mean():.2f}, p99 {values[:, 2].mean():.0f}, "
                                                   f"max {values[:, 3].max():.0f} levels")
        else:
            summary[label] = (values[:, 0].mean(), "lossless" if values[:, 1].max() == 0 else
                              f"max {values[:, 1].max():.2g} of the depth")
    return summary


def _ms(wall_cpu: tuple[float, float]) -> str:
    return f"{wall_cpu[0]:.0f} ({wall_cpu[1]:.0f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=518)
    parser.add_argument("--height", type=int, default=392)
    parser.add_argument("--synthetic-frames", type=int, default=90)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        if TUM.is_dir():
            tum = resized_tum(scratch / "tum", args.width, args.height)
            rows.append(measure("TUM fr1/xyz excerpt (real images, 37 frames)", tum, 10.0, scratch, args.repeats))
        world = synthetic_world(args.width, args.height, frames=args.synthetic_frames)
        rows.append(measure(f"synthetic world ({args.synthetic_frames} frames)", world, 0.06 * args.width, scratch,
                            args.repeats))
    date = date_text()
    load = os.getloadavg()[0]
    lines = [
        "## Keyframe files: compact and full layouts",
        "",
        f"Machine: {os.cpu_count()}-core {platform.machine()} CPU, no GPU, shared (1-minute load average {load:.1f} at "
        f"the end). Python {platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}. Date: {date}.",
        f"Command: `python benchmarks/bench_keyframe_format.py --width {args.width} --height {args.height} "
        f"--synthetic-frames {args.synthetic_frames} --repeats {args.repeats}`",
        "",
        "One pipeline run per sequence (simulated frontend, `--sim-profile vggt --sim-perspective 0.1 --graph submap "
        "--metric-upgrade off --submap-size 4`: a projective world map), its keyframes written from the same result in "
        f"both layouts of `sl4slam.result.reading` at {args.width}x{args.height}. Write time: the file alone (the world "
        "points, which the run computes for `map.ply` anyway, are given to both); read time: `KeyframeRecord.load()` "
        f"to the same `KeyframeData` (warm page cache). Medians over keyframes and {args.repeats} repeats, wall time "
        "and, in brackets, the process's CPU time (less sensitive to the machine's other jobs).",
        "",
        "| frames | keyframes | full (MB per keyframe) | compact (MB) | smaller by | write full / compact (ms) | "
        "read full / compact (ms) |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        full, compact = row["bytes"]["full"], row["bytes"]["compact"]
        lines.append(f"| {row['name']} | {row['keyframes']} | {full / 1e6:.2f} | {compact / 1e6:.3f} | "
                     f"{full / compact:.1f}x | {_ms(row['write_ms']['full'])} / {_ms(row['write_ms']['compact'])} | "
                     f"{_ms(row['read_ms']['full'])} / {_ms(row['read_ms']['compact'])} |")
    lines += ["", "What the compact file gives back, against the full one (same keyframes):", "",
              "| frames | world points (max distance / depth) | masks | colours (abs. error, levels of 255) | "
              "confidence (max, percentile points) | perspective of H_world_local |",
              "|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['name']} | {row['point_error_max']:.2g} | {'equal' if row['masks_equal'] else 'DIFFER'} | "
                     f"mean {row['colour_mean']:.2f}, p99 {row['colour_p99']:.0f}, max {row['colour_max']} | "
                     f"{row['confidence_max']:.3f} (float16 of the full layout) | {row['perspective']:.3f} |")
    lines += ["", "Bytes per array of a compact file (deflated, mean per keyframe; the rest is the zip directory):", "",
              "| frames | " + " | ".join(rows[0]["members"]) + " |", "|---|" + "---|" * len(rows[0]["members"])]
    for row in rows:
        lines.append(f"| {row['name']} | " + " | ".join(f"{v:,.0f}" for v in row["members"].values()) + " |")
    lines += ["", "Alternatives on the same keyframes (bytes of that part alone, mean per keyframe):", "",
              "| coding | " + " | ".join(row["name"] for row in rows) + " |", "|---|" + "---|" * len(rows)]
    for label in rows[0]["alternatives"]:
        lines.append(f"| {label} | " + " | ".join(f"{row['alternatives'][label][0]:,.0f} B, {row['alternatives'][label][1]}"
                                                  for row in rows) + " |")
    lines += ["", "The chosen depth coding (`depth_bytes` above) is the run's own float16 depth in the keyframe's "
              "submap frame, with each row differenced and zigzag-mapped: lossless, so the world points are the "
              "run's to the last bit. Storing the depth along the world camera's axis instead needs a second "
              "rounding (float16) or twice the bytes (float32), because the projective map changes every pixel's "
              "depth by its own factor."]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
