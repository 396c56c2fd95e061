"""Poses for every frame: accuracy of the localized non-keyframes against the keyframes, and cost.

For each sequence the pipeline runs with the simulated frontend (SL(4) graph, perspective
distortion 0.1, seeded), then every non-keyframe is localized against its nearest keyframe
(``sl4slam.localize``). One Sim(3) alignment of all posed frames onto the ground truth; the RMSE is
then split into keyframes and non-keyframes. Time per frame: median wall time of localizing one
non-keyframe (tracking, PnP, decomposition), measured in the same process.

Sequences: the synthetic world (``--frames`` at 160x120, as the pipeline tests), the TUM fr1/xyz
excerpt (37 frames) and, with ``--desk``, the whole TUM fr1/desk (613 frames), from ``shared/data``.

Writes ``benchmarks/results/localize.md`` (``--out`` for another file).
Usage: ``python benchmarks/bench_localize.py [--frames 600] [--desk]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

from harness import result_file, run_sequence, shared_sequence, simulated_config, synthetic_world, table, write_report


def measure(name: str, path: Path, tau_disparity: float, submap_size: int, retrieval: str) -> list:
    """One run on ``path`` and every non-keyframe localized: the table's row."""
    from sl4slam.io import open_source
    from sl4slam.localize import localize_frames, split_ate, views_from_pipeline

    config = simulated_config({"keyframes.tau_disparity": tau_disparity, "submap.size": submap_size,
                               "retrieval.kind": retrieval, "sim.perspective": 0.1,
                               "backend.graph": "submap"})  # the graph the recorded figures were measured on
    source = open_source(str(path))
    result = run_sequence(config, source=source).result
    start = time.perf_counter()
    poses = localize_frames(source, views_from_pipeline(result))
    total = time.perf_counter() - start
    split = split_ate(poses)
    frame = source.get(0).rgb.shape
    return [name, f"{frame[1]}x{frame[0]}", len(source), split.count_keyframes, split.count_non_keyframes,
            len(poses.failed), f"{split.keyframes:.4f}", f"{split.non_keyframes:.4f}",
            f"{split.non_keyframes / split.keyframes:.2f}", f"{1000 * poses.seconds_per_frame:.1f}", f"{total:.1f}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--desk", action="store_true", help="also the whole TUM fr1/desk (613 frames)")
    parser.add_argument("--out", type=Path, default=result_file("localize"))
    args = parser.parse_args()
    rows = [measure("synthetic world", synthetic_world(160, 120, frames=args.frames), 12.0, 16, "orb")]
    if shared_sequence("xyz37").is_dir():
        rows.append(measure("TUM fr1/xyz, first 37", shared_sequence("xyz37"), 25.0, 4, "none"))
    if args.desk and shared_sequence("desk").is_dir():
        rows.append(measure("TUM fr1/desk", shared_sequence("desk"), 25.0, 16, "orb"))
    load = os.getloadavg()[0]
    lines = [
        "## All-frame poses: non-keyframes against keyframes",
        "",
        f"Machine: {os.cpu_count()}-core CPU, no GPU, shared (1-minute load average {load:.1f} at the end of the run). "
        f"Python {platform.python_version()}. Date: {time.strftime('%Y-%m-%d')}.",
        f"Command: `python benchmarks/bench_localize.py --frames {args.frames}{' --desk' if args.desk else ''}`",
        "",
        "Simulated frontend, SL(4) graph, perspective distortion 0.1, seeded. ATE: RMSE of the translation after one "
        "Sim(3) alignment of all posed frames onto the ground truth, split by kind (metres). ms/frame: median time to "
        "localize one non-keyframe; total: all of them.",
        "",
        *table(["sequence", "size", "frames", "keyframes", "non-keyframes", "failed", "ATE keyframes",
                "ATE non-keyframes", "ratio", "ms/frame", "total (s)"], rows),
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
