"""Synthetic world: cost of building the world, rendering, and writing the TUM folder.

For each of ``--repeats`` runs (same seed), in one process:
  * ``make_world``: texture synthesis;
  * ``render_frames`` of the whole path (``--frames`` at ``--width`` x ``--height``), in memory;
  * ``write_synthetic_sequence``: world + rendering + PNG encoding + text files + contact sheet.
Wall and CPU (process) time are both reported: on a shared machine the wall time is inflated by
other processes, the CPU time much less. Once, on the written folder, it also counts the
keyframes the default ``KeyframeSelector`` picks (the pipeline's first stage).

Writes ``benchmarks/results/render.md`` (``--out`` for another file).
Usage: ``python benchmarks/bench_render.py [--repeats 3] [--frames 600] [--width 320] [--height 240]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
from pathlib import Path

import cv2
import numpy as np

from harness import result_file, table, timed, write_report
from sl4slam.io import open_source
from sl4slam.keyframes import KeyframeSelector
from sl4slam.synthetic import camera_path, default_intrinsics, make_world, render_frames, write_synthetic_sequence

RESULTS = result_file("render")


def step_row(name: str, samples: list[tuple[float, float]], frames: int) -> list[str]:
    """A step's row: median wall and CPU seconds, and per frame for the steps that render frames."""
    wall = statistics.median(s[0] for s in samples)
    cpu = statistics.median(s[1] for s in samples)
    per_frame = [f"{1000 * wall / frames:.1f}", f"{1000 * cpu / frames:.1f}"] if name != "make_world" else ["-", "-"]
    return [f"`{name}`", f"{wall:.1f}", f"{cpu:.1f}", *per_frame]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    K = default_intrinsics(args.width, args.height)
    poses = camera_path(args.frames, args.seed)
    rows = {"make_world": [], "render_frames": [], "write_synthetic_sequence": []}
    keyframes = None
    metadata = None
    with tempfile.TemporaryDirectory() as scratch:
        for repeat in range(args.repeats):
            world, wall, cpu = timed(make_world, args.seed)
            rows["make_world"].append((wall, cpu))
            _, wall, cpu = timed(render_frames, world, poses, K, args.width, args.height)
            rows["render_frames"].append((wall, cpu))
            del world
            out = Path(scratch) / f"run{repeat}"
            _, wall, cpu = timed(write_synthetic_sequence, out, args.frames, args.width, args.height, args.seed)
            rows["write_synthetic_sequence"].append((wall, cpu))
            print(f"run {repeat}: " + ", ".join(f"{k} {v[-1][0]:.1f}s wall / {v[-1][1]:.1f}s cpu" for k, v in rows.items()))
            if repeat == 0:
                metadata = json.loads((out / "synthetic.json").read_text())
                selector = KeyframeSelector()
                keyframes = sum(selector.is_keyframe(frame.rgb) for frame in open_source(out))
    load = os.getloadavg()[0]

    lines = [
        "## Synthetic world: rendering and writing a sequence",
        "",
        f"Machine: 2-core CPU, 24 GiB RAM, no GPU (shared with other work; 1-minute load average {load:.1f} at the end "
        f"of the run, so wall times are pessimistic). Python {platform.python_version()}, numpy {np.__version__}, "
        f"OpenCV {cv2.__version__}. Date: 2026-11-21.",
        f"Command: `python benchmarks/bench_render.py --repeats {args.repeats} --frames {args.frames} "
        f"--width {args.width} --height {args.height}`",
        "",
        f"{args.frames} frames at {args.width}x{args.height}, seed {args.seed}; medians of {args.repeats} runs in one process. "
        "`render_frames` is the vectorized ray casting + trilinear texture sampling + shading, in memory; "
        "`write_synthetic_sequence` is the whole CLI job (world, rendering, 16-bit depth and RGB PNGs, text files, "
        "contact sheet). Target: under 60 s for the whole job on 2 cores.",
        "",
        *table(["step", "wall (s)", "CPU (s)", "wall per frame (ms)", "CPU per frame (ms)"],
               [step_row(name, samples, args.frames) for name, samples in rows.items()]),
    ]
    write_wall = statistics.median(s[0] for s in rows["write_synthetic_sequence"])
    write_cpu = statistics.median(s[1] for s in rows["write_synthetic_sequence"])
    lines += [
        "",
        f"Whole job / 60 s budget: {write_wall / 60:.2f} (wall), {write_cpu / 60:.2f} (CPU).",
        "",
        f"The written sequence: {keyframes} keyframes with the default `KeyframeSelector` (tau_disparity 25 px); "
        f"floor-only frames {metadata['floor_only']['start']}..{metadata['floor_only']['stop'] - 1} "
        f"({metadata['floor_only']['count']} frames); depth range {metadata['depth_range_m'][0]:.2f}-"
        f"{metadata['depth_range_m'][1]:.2f} m; room {' x '.join(f'{v:.2f}' for v in metadata['room_size_m'])} m "
        f"with {metadata['num_boxes']} furniture boxes.",
        "",
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
