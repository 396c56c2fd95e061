"""What a kill costs a run that is then resumed (``sl4slam run ... --resume``), and what its recording costs.

    python benchmarks/bench_resume.py

1. Kills. On the synthetic world's lap (360 frames at 160x120, seed 1: 12 submaps of 8 keyframes,
   one loop closed; simulated frontend, ORB retrieval), for each graph design: a run never
   interrupted, then for each kill point a run killed there by SIGKILL and its resumption, each
   ``sl4slam run`` in a fresh process (a ``python -c`` child that patches the function where it
   dies: no timing decides where). Per point: the wall seconds of the killed run and of the
   resumption against the uninterrupted run (time lost = killed + resumed - uninterrupted, Python
   start-up included), the seconds per replayed submap (the resumption's own line: the time until
   the last replayed submap was finished, over their count) against the model's and the graph's per
   submap in the uninterrupted run, the forwards the model ran twice, and whether every output is
   byte-identical (trajectory, map, keyframes; summary.json but its timings and memory).
2. The recording's costs per submap at VGGT-1B's grid (518x294, 20 frames: 2 shared, 16 new, 2 loop
   frames): its bytes (computed from the arrays' shapes and dtypes, and measured on a file of the
   simulated frontend at that size), the seconds to write it stored and deflated and to read it
   back, and the input digest of 20 frames of 640x480.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from harness import cpu_model, date_text, load_average, result_file, synthetic_world, table, write_report

ARGS = ["--frontend", "simulated", "--tau-disparity", "12", "--submap-size", "8", "--retrieval", "orb"]
GRAPH = {"keyframe": [], "submap": ["--graph", "submap"]}
POINTS = {"model:5": "in the model (submap 5's forward)",
          "graph:6": "in the graph update of submap 6",
          "recording:4": "half-way through writing submap 4's recording",
          "outputs:40": "half-way through writing the 40th keyframe file of the outputs"}

KILL_POINTS = Path(__file__).resolve().parent / "harness" / "kill_points.py"
"""The child that dies at a chosen point (``harness/kill_points.py``)."""


READING = [
    "Reading: a kill costs the forwards that were under way (one; none when the kill falls in the graph work or "
    "the outputs, whose forward was recorded first), a process start, and the replay: each recorded submap's "
    "graph work again (points, alignment, graph, loops), about the graph's own seconds per submap, with no model. "
    "With VGGT-1B the forward of a 17-frame submap takes 0.43 s on an H100 and about 15 minutes on this CPU "
    "(sections \"VGGT-1B forward\"), so on a CPU a kill after k submaps costs one forward and k replays of a "
    "fraction of a second each, instead of k forwards; on a GPU, where the forward is as quick as the graph work, "
    "the replay saves the model's share of each submap. The stored recording's write (31 ms for 32 MiB, on the "
    "model's worker, beside the graph work) and the input digest (13 ms) are what a run that is never killed pays.",
]


def child(world: Path, out: Path, point: str, log: Path, *extra: str) -> tuple[float, subprocess.CompletedProcess]:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, str(KILL_POINTS), point, str(log), "run", str(world), "--out", str(out), *ARGS,
                           *extra], capture_output=True, text=True, timeout=1200)
    return time.perf_counter() - start, done


def calls(log: Path) -> list[int]:
    return [int(line) for line in log.read_text().split()] if log.exists() else []


def untimed(value):
    if isinstance(value, dict):
        return {k: untimed(v) for k, v in value.items() if k not in ("seconds", "memory")}
    if isinstance(value, list):
        return [untimed(v) for v in value]
    return value


def identical(a: Path, b: Path) -> bool:
    for name in ("trajectory.txt", "trajectory_gt.txt", "map.ply"):
        if (a / name).read_bytes() != (b / name).read_bytes():
            return False
    names = sorted(p.name for p in (a / "keyframes").iterdir())
    if names != sorted(p.name for p in (b / "keyframes").iterdir()):
        return False
    if any((a / "keyframes" / n).read_bytes() != (b / "keyframes" / n).read_bytes() for n in names):
        return False
    return untimed(json.loads((a / "summary.json").read_text())) == untimed(json.loads((b / "summary.json").read_text()))


def kills(world: Path, tmp: Path, repeats: int) -> tuple[list[list], dict]:
    rows, facts = [], {}
    for graph, flags in GRAPH.items():
        walls = []
        for repeat in range(repeats):
            reference = tmp / f"{graph}-reference-{repeat}"
            wall, done = child(world, reference, "", tmp / f"{reference.name}.log", *flags, "--quiet")
            assert done.returncode == 0, done.stderr[-2000:]
            walls.append(wall)
        wall = statistics.median(walls)
        summary = json.loads((reference / "summary.json").read_text())
        per_submap = summary["seconds"]["per_submap_median"]
        model = per_submap["frontend"]
        graph_work = sum(v for k, v in per_submap.items() if k != "frontend")
        submaps = summary["counts"]["submaps"]
        facts[graph] = {"wall": wall, "model": model, "graph": graph_work, "submaps": submaps,
                        "loops": summary["counts"]["loops"], "total": summary["seconds"]["total"]}
        for point, where in POINTS.items():
            measured = []
            for repeat in range(repeats):
                out = tmp / f"{graph}-{point.replace(':', '-')}-{repeat}"
                killed_log, resumed_log = tmp / f"{out.name}-killed.log", tmp / f"{out.name}-resumed.log"
                killed_wall, killed = child(world, out, point, killed_log, *flags, "--quiet")
                assert killed.returncode == -9, killed.stderr[-2000:]
                if point.startswith("model") and "recorded" not in facts:
                    files = sorted((out / "frontend_cache").glob("submap_*.npz"))
                    frames = [len(np.load(f)["frame_indices"]) for f in files]
                    facts["recorded"] = (sum(f.stat().st_size for f in files) / len(files), sum(frames) / len(frames))
                resumed_wall, resumed = child(world, out, "", resumed_log, *flags, "--resume")
                assert resumed.returncode == 0, resumed.stderr[-2000:]
                line = re.search(r"resumed: (\d+) submap\(s\) replayed from the recording in ([\d.]+) s",
                                 resumed.stderr)
                replayed = int(line.group(1))
                measured.append((killed_wall, resumed_wall, replayed, float(line.group(2)) / max(replayed, 1),
                                 set(calls(killed_log)) & set(calls(resumed_log)), identical(reference, out)))
            killed_wall = statistics.median(m[0] for m in measured)
            resumed_wall = statistics.median(m[1] for m in measured)
            replayed = sorted({m[2] for m in measured})
            twice = sorted(set().union(*(m[4] for m in measured)))
            rows.append([graph, where, f"{killed_wall:.1f}", f"{resumed_wall:.1f}", f"{wall:.1f}",
                         f"{killed_wall + resumed_wall - wall:.1f}", f"{'-'.join(map(str, replayed))}/{submaps}",
                         f"{statistics.median(m[3] for m in measured):.3f}", f"{model:.3f}", f"{graph_work:.3f}",
                         ", ".join(map(str, twice)) or "none", f"{sum(m[5] for m in measured)}/{len(measured)}"])
            print(rows[-1], flush=True)
    return rows, facts


def recording_costs(tmp: Path) -> list[list]:
    """The recording of one VGGT-1B-size submap: bytes, write and read seconds, input digest."""
    from sl4slam.atomic import atomic_write_npz
    from sl4slam.config import SLAMConfig
    from sl4slam.frontend.cache import input_digest
    from sl4slam.frontend.simulated import SimulatedFrontend
    from sl4slam.io import open_source
    from sl4slam.resolve import resolve
    from sl4slam.resume import recording_bytes
    from sl4slam.types import Frame

    world = synthetic_world(518, 294, 40, seed=0)
    source = open_source(str(world))
    frames = [source.get(i) for i in range(0, 40, 2)]
    config = SLAMConfig(frontend="simulated")
    config.sim.profile = "vggt"
    prediction = SimulatedFrontend(resolve(config).config.sim).reconstruct(frames, 3)
    arrays = {k: v for k, v in vars(prediction).items() if v is not None}
    arrays.update(frame_indices=np.arange(20), inputs=np.array("0" * 64), frontend=np.array("simulated"),
                  requires_ground_truth=np.array(True), image_to_grid=np.tile(np.eye(3), (20, 1, 1)))
    rows = []
    computed = recording_bytes(20, 294, 518)
    for compressed in (False, True):
        path = tmp / f"submap_{int(compressed)}.npz"
        writes, reads = [], []
        for _ in range(3):
            start = time.perf_counter()
            atomic_write_npz(path, arrays, compressed=compressed)
            writes.append(time.perf_counter() - start)
            start = time.perf_counter()
            with np.load(path) as data:
                {k: data[k] for k in data.files}
            reads.append(time.perf_counter() - start)
        size = path.stat().st_size
        rows.append(["deflated (--cache-frontend)" if compressed else "stored (the default)", f"{size / 2**20:.1f}",
                     f"{computed / 2**20:.1f}" if not compressed else "-", f"{statistics.median(writes):.3f}",
                     f"{statistics.median(reads):.3f}"])
    rng = np.random.default_rng(0)
    camera = [Frame(i, i / 30, rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)) for i in range(20)]
    digests = []
    for _ in range(5):
        start = time.perf_counter()
        input_digest(camera, {"match_pairs": [(0, 18), (1, 18)]})
        digests.append(time.perf_counter() - start)
    rows.append(["input digest, 20 frames of 640x480 RGB", "-", "-", f"{statistics.median(digests):.3f}", "-"])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(result_file("resume")))
    parser.add_argument("--repeats", type=int, default=3, help="runs of each case (medians are reported)")
    args = parser.parse_args()
    from sl4slam.resume import recording_bytes

    world = synthetic_world(160, 120, 360, seed=1)
    with tempfile.TemporaryDirectory() as tmp:
        rows, facts = kills(world, Path(tmp), args.repeats)
        costs = recording_costs(Path(tmp))
    lines = [
        "## Resuming a killed run (`--resume`)",
        "",
        f"Machine: {os.cpu_count()}-core {cpu_model()}, no GPU; Python {platform.python_version()}. "
        f"Date: {date_text('%Y-%m-%d')}. 1-minute load average at the end: {load_average():.1f}.",
        f"Command: `python benchmarks/bench_resume.py --repeats {args.repeats}`.",
        "",
        "### Time lost to a kill",
        "",
        "The synthetic world's lap (360 frames at 160x120, 12 submaps of 8 keyframes, "
        f"{facts['keyframe']['loops']} loop closed), simulated frontend, ORB retrieval; each run a fresh "
        "`sl4slam run` process, killed by SIGKILL where the table says (a child that patches that function), "
        "then `--resume`d; each case run `--repeats` times in fresh folders, medians reported. Wall seconds "
        "include Python's start-up (about 3.5 s a process here). "
        "*replay s/submap*: the resumption's own line (time until the last replayed submap was finished, over "
        "their count); *replayed*: submaps served from the recording (a range when the repeats differ: the next "
        "forward may or may not have been recorded when the graph was killed); *model*, *graph*: medians per submap "
        "of an uninterrupted run (frontend; everything else: "
        "points, alignment, graph, loops, store, retrieval). *identical*: trajectory, map, every keyframe file, "
        "and summary.json but its timings and memory, byte for byte against an uninterrupted run (repeats that "
        "were).",
        "",
        *table(["graph", "killed", "killed run (s)", "resumed run (s)", "uninterrupted (s)", "time lost (s)",
                "replayed", "replay s/submap", "model s/submap", "graph s/submap", "forwards run twice", "identical"],
               rows),
        "",
        "### The recording",
        "",
        "One submap at VGGT-1B's grid, 518x294, 20 frames (2 shared, 16 new, 2 loop frames; the simulated "
        "frontend's float32 depth and confidence, uint8 colours, and the cameras): its file, stored as the run "
        "records it and deflated as `--cache-frontend` keeps it, written through `sl4slam.atomic` and read back "
        "(median of 3; the page cache holds the file). *computed*: `sl4slam.resume.recording_bytes(20, 294, 518)`, "
        "11 bytes per pixel and frame. The input digest (SHA-256 of every frame the model is given) is computed "
        "for each forward, recorded or replayed.",
        "",
        *table(["file", "MiB", "computed MiB", "write (s)", "read (s)"], costs),
        "",
        f"The lap above (160x120) recorded {facts['recorded'][0] / 2**20:.2f} MiB per submap of "
        f"{facts['recorded'][1]:.1f} frames on average (`recording_bytes`: "
        f"{recording_bytes(1, 120, 160) * facts['recorded'][1] / 2**20:.2f} MiB).",
        "",
        *READING,
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
