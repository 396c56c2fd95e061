"""Exports of a large run: seconds to write COLMAP (binary, and binary + text), nerfstudio and
per-submap PLY for ``--keyframes`` keyframes at the VGGT grid size (518x294 by default).

The result folder is fabricated (keyframes with exactly known cameras and dense points, as the
tests make them) so that the figure does not depend on running the pipeline for hours. Each
export reads every keyframe file once (two threads), writes its image (PNG, fast compression)
and samples up to 1M points. The files are in the page cache after being written (warm reads).

Writes ``benchmarks/results/export.md`` (``--out`` for another file).
Usage: ``python benchmarks/bench_export.py [--keyframes 1000] [--width 518] [--height 294] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from harness import REPO, result_file, table, timed, write_report

sys.path.insert(0, str(REPO / "tests"))

from result_folders import write_known_result  # noqa: E402

from sl4slam.export import export_colmap, export_nerfstudio, export_submap_ply  # noqa: E402
from sl4slam.result.reading import load_result  # noqa: E402

RESULTS = result_file("export")


def export_row(name: str, values: list[tuple[float, float, int]], keyframes: int) -> list[str]:
    """An export's row from its (wall s, CPU s, points) per repeat: medians, points, wall per keyframe."""
    wall, cpu = statistics.median(v[0] for v in values), statistics.median(v[1] for v in values)
    return [name, f"{wall:.1f}", f"{cpu:.1f}", f"{values[0][2]:,}", f"{1000 * wall / keyframes:.1f}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=1000)
    parser.add_argument("--width", type=int, default=518)
    parser.add_argument("--height", type=int, default=294)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        start = time.perf_counter()
        write_known_result(scratch / "run", count=args.keyframes, width=args.width, height=args.height, submap_size=16)
        made = time.perf_counter() - start
        size = sum(p.stat().st_size for p in (scratch / "run" / "keyframes").glob("*.npz")) / 2**30
        jobs = {
            "COLMAP binary": lambda out: export_colmap(load_result(scratch / "run"), out),
            "COLMAP binary, JPEG images": lambda out: export_colmap(load_result(scratch / "run"), out, image_ext=".jpg"),
            "COLMAP binary + text": lambda out: export_colmap(load_result(scratch / "run"), out, text=True),
            "nerfstudio": lambda out: export_nerfstudio(load_result(scratch / "run"), out),
            "PLY per submap (all points)": lambda out: export_submap_ply(load_result(scratch / "run"), out),
        }
        for name, job in jobs.items():
            for repeat in range(args.repeats):
                report, wall, cpu = timed(job, scratch / f"out_{repeat}")
                rows.setdefault(name, []).append((wall, cpu, report.points))
                shutil.rmtree(scratch / f"out_{repeat}")
    load = os.getloadavg()[0]
    lines = [
        "## Exports: COLMAP, nerfstudio, PLY",
        "",
        f"Machine: {os.cpu_count()}-core CPU, no GPU, shared (1-minute load average {load:.1f} at the end of the run). "
        f"Python {platform.python_version()}. Date: {time.strftime('%Y-%m-%d')}.",
        f"Command: `python benchmarks/bench_export.py --keyframes {args.keyframes} --width {args.width} "
        f"--height {args.height} --repeats {args.repeats}`",
        "",
        f"{args.keyframes} keyframes at {args.width}x{args.height} ({size:.2f} GiB of keyframe files, fabricated in "
        f"{made:.0f} s, read warm from the page cache); medians of {args.repeats} runs. Each export writes every "
        "keyframe image (PNG unless stated; the fabricated images are smooth, like photographs) and, for COLMAP / nerfstudio, up to 1M points (evenly spread over the keyframes).",
        "",
        *table(["export", "wall (s)", "CPU (s)", "points", "wall per keyframe (ms)"],
               [export_row(name, values, args.keyframes) for name, values in rows.items()]),
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
