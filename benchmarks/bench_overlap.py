"""Wall time of a run with the model overlapping the graph work, against one submap after the other.

The model is a stand-in: the simulated frontend's submaps (from the sequence's ground truth) plus a
sleep as long as VGGT-1B's forward of the submap on an H100 in bf16 (0.43 s for 17 frames, scaled
with the frames; benchmarks/results/vggt.md), so that the CPU here does the SLAM work while the
"GPU" waits, as on a GPU machine. Both schedules run the same sequence in turn, ``--repeats``
times; the report gives the median wall time of each, their ratio, input frames per second and
the latency from a keyframe's arrival to its pose (when its submap's graph work ends).

    python benchmarks/bench_overlap.py --sequence ../shared/data/tum_rgbd_fr1_desk --repeats 3
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time
from pathlib import Path

import numpy as np

from harness import TimedSource, result_file, run_sequence, shared_sequence, simulated_config, write_report
from sl4slam.frontend.simulated import SimulatedFrontend

VGGT_SECONDS_17 = 0.43  # VGGT-1B forward of 17 frames, H100, bf16 (benchmarks/results/vggt.md)


class ModelStandIn(SimulatedFrontend):
    """The simulator's submap after a sleep as long as VGGT's forward of as many frames on an H100."""

    def reconstruct(self, frames, submap_id, **kwargs):
        start = time.perf_counter()
        prediction = super().reconstruct(frames, submap_id, **kwargs)
        time.sleep(max(0.0, VGGT_SECONDS_17 * len(frames) / 17 - (time.perf_counter() - start)))
        return prediction


def one_run(sequence: Path, overlap: bool, profile: str) -> dict:
    """One run of ``sequence`` with the model stand-in; its wall time, sizes and keyframe latency."""
    from sl4slam.io import open_source

    config = simulated_config({"overlap": overlap, "sim.profile": profile, "retrieval.kind": "orb"})
    arrivals: dict[int, float] = {}
    latencies: list[float] = []

    def on_submap(pipeline, submap_id: int) -> None:
        now = time.perf_counter()
        latencies.extend(now - arrivals[k.frame_index] for k in pipeline.keyframes if k.submap_id == submap_id)

    run = run_sequence(config, source=TimedSource(open_source(str(sequence), config.source), arrivals),
                       frontend=ModelStandIn(config.sim), on_submap=on_submap)
    result = run.result
    return {"seconds": run.seconds, "frames": len(arrivals), "keyframes": len(result.keyframes),
            "submaps": result.stats["submaps"], "latency": float(np.median(latencies)),
            "trajectory": result.T_world_cam}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, default=shared_sequence("desk"))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", default="vggt")
    parser.add_argument("--out", type=Path, default=result_file("overlap"))
    args = parser.parse_args()
    runs: dict[bool, list[dict]] = {False: [], True: []}
    for _ in range(args.repeats):
        for overlap in (False, True):  # in turn, so that the machine's drift reaches both alike
            runs[overlap].append(one_run(args.sequence, overlap, args.profile))
    same = all(np.array_equal(a["trajectory"], b["trajectory"]) for a, b in zip(runs[False], runs[True]))
    rows = []
    for overlap in (False, True):
        seconds = [r["seconds"] for r in runs[overlap]]
        first = runs[overlap][0]
        rows.append((overlap, float(np.median(seconds)), min(seconds), max(seconds), first["frames"] / np.median(seconds),
                     float(np.median([r["latency"] for r in runs[overlap]])), first))
    ratio = rows[1][1] / rows[0][1]
    first = rows[0][6]
    lines = [
        "## The model overlapping the graph work (CPU, model stand-in)", "",
        f"Date: {datetime.date.today()}; machine: {platform.machine()}, {os.cpu_count()} cores, load average "
        f"{os.getloadavg()[0]:.1f} at the end; Python {platform.python_version()}.",
        f"Command: `python benchmarks/bench_overlap.py --sequence {args.sequence.name} --repeats {args.repeats} "
        f"--profile {args.profile}`.",
        f"Sequence: {args.sequence.name}, {first['frames']} frames, {first['keyframes']} keyframes, {first['submaps']} "
        f"submaps; simulated frontend ({args.profile} profile) plus a sleep as long as VGGT-1B's forward on an H100 in "
        f"bf16 ({VGGT_SECONDS_17} s per 17 frames); ORB retrieval. Schedules run in turn, {args.repeats} times each.", "",
        "| schedule | wall s (median) | range | input frames/s | keyframe latency, median s |",
        "|---|---|---|---|---|"]
    for overlap, median, low, high, fps, latency, _ in rows:
        lines.append(f"| {'overlapped' if overlap else 'sequential'} | {median:.2f} | {low:.2f}-{high:.2f} | {fps:.1f} | "
                     f"{latency:.2f} |")
    lines += ["", f"Overlapped / sequential wall time: {ratio:.2f} (median of each). Trajectories identical in every "
                  f"pair: {'yes' if same else 'NO'}."]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
