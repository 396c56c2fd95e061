"""The metric upgrade in whole runs: keyframe ATE with and without it, per distortion and graph.

    python benchmarks/bench_upgrade_pipeline.py --seeds 3 --jobs 2

Synthetic world (600 frames, one lap; ``--world-size 320x240`` is the demo's world and keyframe
threshold, 160x120 the same keyframes at half the threshold) and the real TUM fr1/desk (613 frames, ground-truth depth and poses), simulated
frontend with the first submap distorted like every other (the default), per-submap perspective
0 / 0.05 / 0.1 / 0.2 (the ``exact`` profile) and the ``vggt`` profile; graphs ``--graphs``: the SL(4)
keyframe graph (the default), the SL(4) submap graph and the Sim(3) graph;
loops on (ORB retrieval). Each run is measured twice from one graph: the result as written
(upgraded when the estimate is applied) and the same polished graph without the upgrade.
Targets: with / without <= 0.2 at perspective 0.1 (SL(4) graphs); no case worse than 1.05x.
Writes ``benchmarks/results/upgrade_pipeline.md``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time
from pathlib import Path

import numpy as np

from harness import (Failure, add_parallel_arguments, attempt, parallel_options, result_ate, result_file, run_all,
                     run_sequence, shared_sequence, simulated_config, synthetic_world, table, with_settings,
                     write_report)

# world size: keyframe threshold (the demo's 25 px at 320x240; the same keyframes at half the size)
WORLD_SIZES = {"160x120": 12.5, "320x240": 25.0}
# name: (graph group, graph design, label)
GRAPHS = {"sl4": ("sl4", "keyframe", "SL(4) keyframe"), "sl4-submap": ("sl4", "submap", "SL(4) submap"),
          "sim3": ("sim3", "submap", "Sim(3)")}
SETTINGS = ("perspective 0", "perspective 0.05", "perspective 0.1", "perspective 0.2", "vggt profile")


def world_path(sequence: str) -> Path:
    """``"desk"`` or a synthetic world size (``"320x240"``) -> its folder."""
    if sequence == "desk":
        return shared_sequence("desk")
    width, height = map(int, sequence.split("x"))
    return synthetic_world(width, height)


def run(sequence: str, setting: str, graph: str, seed: int) -> dict:
    """One run measured twice: the ATE as written (upgraded) and without the upgrade."""
    kind, design, _ = GRAPHS[graph]
    simulator = {"sim.profile": "vggt"} if setting == "vggt profile" else {"sim.perspective": float(setting.split()[1])}
    keyframes = {"keyframes.tau_disparity": WORLD_SIZES[sequence]} if sequence in WORLD_SIZES else {}
    config = simulated_config({**simulator, "sim.seed": seed, "alignment.seed": seed, "backend.kind": kind,
                               "backend.graph": design,
                               "upgrade.mode": "on",  # measured on every graph ("auto" leaves it to the submap graph)
                               "retrieval.kind": "orb",
                               **keyframes})
    world = world_path(sequence)
    upgraded = attempt(config, world)
    if isinstance(upgraded, Failure):  # a run that aborts is a finding, not a crash of the benchmark
        return {"error": str(upgraded)}
    completed = sum("completed from" in (e.fallback or "") for e in upgraded.result.edges)
    if completed:
        # the upgrade also completed planar links, which changed the graph: "without" is a run without both
        plain = run_sequence(with_settings(config, {"upgrade.mode": "off"}), world).result
    else:
        pipeline = upgraded.pipeline  # the same polished graph, not upgraded
        plain = pipeline.result_for(pipeline.backend.world_estimate(final=True))
    metric = upgraded.stats["metric_upgrade"]
    outcome = {"with": upgraded.ate(), "without": result_ate(plain).rmse, "completed": completed,
               "applied": sum(u["applied"] for u in metric), "segments": len(metric),
               "reasons": sorted({u["reason"] for u in metric}), "seconds": upgraded.seconds}
    print(f"{world.name} {setting} {graph} seed {seed}: {outcome}", flush=True)
    return outcome


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=3)
    add_parallel_arguments(parser, "--jobs", 2)
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=SETTINGS, help="simulator settings to run")
    parser.add_argument("--graphs", nargs="+", default=list(GRAPHS), choices=list(GRAPHS))
    parser.add_argument("--world-size", default="320x240", choices=list(WORLD_SIZES), help="synthetic world")
    parser.add_argument("--sequences", nargs="+", default=["synthetic", "desk"], choices=["synthetic", "desk"])
    parser.add_argument("--out", default=str(result_file("upgrade_pipeline")))
    args = parser.parse_args()
    world_path(args.world_size)  # rendered once, before the workers start
    worlds = ([("synthetic", args.world_size)] if "synthetic" in args.sequences else []) + (
        [("TUM fr1/desk", "desk")] if shared_sequence("desk").is_dir() and "desk" in args.sequences else [])
    cases = [(name, sequence, setting, graph) for name, sequence in worlds for setting in args.settings
             for graph in args.graphs]
    jobs = [(case, seed) for case in cases for seed in range(args.seeds)]
    start, load_start = time.perf_counter(), os.getloadavg()[0]
    outcomes = run_all(run, [(sequence, setting, backend, seed) for (_, sequence, setting, backend), seed in jobs],
                       **parallel_options(args))
    runs: dict[tuple, list] = {}
    for (case, _), outcome in zip(jobs, outcomes):
        runs.setdefault(case, []).append(outcome)

    rows, worst, target = [], 0.0, []
    for (name, _, setting, graph), found in runs.items():
        ok = [r for r in found if "error" not in r]
        ratios = np.array([r["with"] / r["without"] for r in ok]) if ok else np.array([np.nan])
        without = np.array([r["without"] for r in ok]) if ok else np.array([np.nan])
        with_ = np.array([r["with"] for r in ok]) if ok else np.array([np.nan])
        worst = max(worst, float(np.nanmax(ratios)))
        applied = sum(r["applied"] for r in ok)
        total = sum(r["segments"] for r in ok)
        reasons = sorted({reason for r in ok for reason in r["reasons"]})
        completed = sum(r.get("completed", 0) for r in ok)
        rows.append([name, setting, GRAPHS[graph][2],
                     f"{np.median(without):.4f} ({without.min():.4f}-{without.max():.4f})",
                     f"{np.median(with_):.4f} ({with_.min():.4f}-{with_.max():.4f})",
                     f"{np.median(ratios):.3f} ({ratios.min():.3f}-{ratios.max():.3f})", f"{applied}/{total}", completed,
                     len(found) - len(ok), "; ".join(reasons)[:160]])
        if setting == "perspective 0.1" and graph != "sim3":
            target.append(f"{name}, {GRAPHS[graph][2]}: median {np.median(ratios):.3f}")
    text = [
        "## The metric upgrade in whole runs (ATE RMSE, metres)",
        "",
        f"Machine: {os.cpu_count()}-core x86_64 CPU, no GPU, shared (1-minute load average {load_start:.1f} at the start); "
        f"Python {platform.python_version()}. Date: {datetime.date.today()}. Total {(time.perf_counter() - start) / 60:.0f} min.",
        f"Command: `python benchmarks/bench_upgrade_pipeline.py --seeds {args.seeds} --jobs {args.jobs} --world-size "
        f"{args.world_size} --graphs {' '.join(args.graphs)} --sequences {' '.join(args.sequences)}"
        + (" --settings " + " ".join(f'"{x}"' for x in args.settings) if list(args.settings) != list(SETTINGS) else "") + "`.",
        f"Synthetic world (600 frames at {args.world_size}, one lap) and TUM fr1/desk (613 frames); simulated frontend with every "
        "submap distorted, the first one included; loops on (ORB). Each run is measured twice from one polished graph: "
        "without the upgrade and as written (upgraded where it was applied); where the upgrade also completes planar "
        "links (`--upgrade-complete-links`), which changes the graph itself, *without* is a second run with "
        f"`--metric-upgrade off`. Median and range over {args.seeds} seeds.",
        "",
        *table(["sequence", "simulator", "graph", "ATE without", "ATE with", "with / without", "upgrades applied",
                "links completed", "aborted", "outcomes"], rows),
        "",
        f"Targets: with / without <= 0.2 at perspective 0.1 on an SL(4) graph ({'; '.join(target)}); no case worse than "
        f"1.05x (worst single run: {worst:.3f}).",
        "",
    ]
    write_report(args.out, text)


if __name__ == "__main__":
    main()
