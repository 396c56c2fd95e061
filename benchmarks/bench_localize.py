"""Poses for every frame: accuracy of the localized non-keyframes against the keyframes, and cost.

For each sequence the pipeline runs with the simulated frontend (SL(4) graph, perspective
distortion 0.1, seeded), then every non-keyframe is localized against its nearest keyframe
(``sl4slam.localize``). One Sim(3) alignment of all posed frames onto the ground truth; the RMSE is
then split into keyframes and non-keyframes. Time per frame: median wall time of localizing one
non-keyframe (tracking, PnP, decomposition), measured in the same process.

Sequences: the synthetic world (``--frames`` at 160x120, as the pipeline tests), the TUM fr1/xyz
excerpt (37 frames) and, with ``--desk``, the whole TUM fr1/desk (613 frames), from ``shared/data``.

Writes ``benchmarks/results/localize.md``.
Usage: ``python benchmarks/bench_localize.py [--frames 600] [--desk]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

from sl4slam.config import SLAMConfig
from sl4slam.io import open_source
from sl4slam.localize import localize_frames, split_ate, views_from_pipeline
from sl4slam.pipeline import SLAMPipeline
from sl4slam.synthetic import write_synthetic_sequence

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "localize.md"
SHARED = HERE.parent.parent / "shared" / "data"


def measure(name: str, path: Path, tau_disparity: float, submap_size: int, retrieval: str) -> str:
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = tau_disparity
    config.submap.size = submap_size
    config.retrieval.kind = retrieval
    config.sim.perspective = 0.1
    config.backend.graph = "submap"  # the graph the recorded figures were measured on
    source = open_source(str(path))
    pipeline = SLAMPipeline(config)
    result = pipeline.run(source, progress=False)
    start = time.perf_counter()
    poses = localize_frames(source, views_from_pipeline(result))
    total = time.perf_counter() - start
    split = split_ate(poses)
    frame = source.get(0).rgb.shape
    return (f"| {name} | {frame[1]}x{frame[0]} | {len(source)} | {split.count_keyframes} | {split.count_non_keyframes} | "
            f"{len(poses.failed)} | {split.keyframes:.4f} | {split.non_keyframes:.4f} | "
            f"{split.non_keyframes / split.keyframes:.2f} | {1000 * poses.seconds_per_frame:.1f} | {total:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--desk", action="store_true", help="also the whole TUM fr1/desk (613 frames)")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        world = write_synthetic_sequence(Path(scratch) / "w", num_frames=args.frames, width=160, height=120, seed=0)
        rows.append(measure("synthetic world", world, 12.0, 16, "orb"))
    if (SHARED / "tum_rgbd_fr1_xyz_first37").is_dir():
        rows.append(measure("TUM fr1/xyz, first 37", SHARED / "tum_rgbd_fr1_xyz_first37", 25.0, 4, "none"))
    if args.desk and (SHARED / "tum_rgbd_fr1_desk").is_dir():
        rows.append(measure("TUM fr1/desk", SHARED / "tum_rgbd_fr1_desk", 25.0, 16, "orb"))
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
        "| sequence | size | frames | keyframes | non-keyframes | failed | ATE keyframes | ATE non-keyframes | ratio | "
        "ms/frame | total (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    RESULTS.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
