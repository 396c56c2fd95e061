"""Open-vocabulary object queries on the synthetic world: 3D box IoU of every furniture object,
one keyframe deciding against several fused.

For each world seed: the synthetic world rendered at ``--width`` x ``--height`` along its lap
(``--frames``), one run with the simulated frontend under its VGGT-like error profile
(``sim.profile = "vggt"``, every other setting at its default) writing a result folder, and the
oracle models of ``sl4slam.objects.oracle`` (embeddings: the share of each keyframe a box covers;
masks: the box's rendered pixels). Every furniture box ``b`` is queried as ``"box b"``:

- single view: ``top_k = 1``, the keyframe whose embedding is most similar decides alone (as
  VGGT-SLAM 2.0 answers a query);
- fused: ``top_k = 5`` (and 10) keyframes, their views merged into one instance (the default query);
- ablations of the fusion: without the hidden-back extension, without the offset refinement.

The answer's best instance is moved into the ground-truth frame by the Sim(3) that aligns the run's
keyframe trajectory with the ground truth (Umeyama, ``sl4slam.metrics.ate``) and compared with the
true axis-aligned box: IoU of the two oriented boxes, exact (the intersection polytope's convex
hull, ``sl4slam.objects.fusion.box_iou``). A box no keyframe of the run sees is listed as not seen
and left out of the medians (its IoU would be 0 whatever the fusion does).

Writes ``benchmarks/results/objects.md`` (``--out`` for another file).
Usage: ``python benchmarks/bench_objects.py [--seeds 0 1 2] [--frames 600] [--width 320 --height 240]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from harness import OUT, cpu_model, date_text, memory_gib, result_file, simulated_config, synthetic_world, table, write_report

VARIANTS = {
    "single view (top-1)": dict(top_k=1),
    "fused, top-5 (default)": dict(top_k=5),
    "fused, top-10": dict(top_k=10),
    "fused top-5, no hidden-back extension": dict(top_k=5, amodal=False),
    "fused top-5, no offset refinement": dict(top_k=5, refine=False),
    "single view, no hidden-back extension": dict(top_k=1, amodal=False),
}
SINGLE, FUSED = "single view (top-1)", "fused, top-5 (default)"


def run_world(seed: int, width: int, height: int, frames: int) -> Path:
    """The result folder of one run on world ``seed`` (made once, reused)."""
    from sl4slam.runner import run_slam

    world = synthetic_world(width, height, frames=frames, seed=seed)
    out = OUT / "objects" / f"{world.name}_vggt"
    if not (out / "summary.json").is_file() or '"complete"' not in (out / "summary.json").read_text():
        run_slam(world, out, simulated_config({"sim.profile": "vggt"}), progress=False, overwrite=True)
    return out


def measure(seed: int, width: int, height: int, frames: int) -> tuple[list[dict], dict]:
    """Every box of world ``seed`` under every variant: rows ``{seed, box, size, seen, iou: {variant: IoU}}``."""
    from sl4slam.objects.fusion import box_iou
    from sl4slam.objects.oracle import (OracleEmbedder, OracleSegmenter, SyntheticOracle, align_map_to_truth,
                                        box_to_truth, object_text, write_oracle_embeddings)
    from sl4slam.objects.query import query_result
    from sl4slam.result.reading import load_result

    out = run_world(seed, width, height, frames)
    result = load_result(out)
    oracle = SyntheticOracle(synthetic_world(width, height, frames=frames, seed=seed))
    oracle.register_result(result)
    write_oracle_embeddings(result, oracle)
    T_gt_map = align_map_to_truth(result, oracle)
    embedder, segmenter = OracleEmbedder(oracle), OracleSegmenter(oracle)
    shape = (result.keyframes[0].image_size[1], result.keyframes[0].image_size[0])
    coverage = np.stack([oracle.coverage(k.frame_index, shape) for k in result.keyframes])[:, :-1]
    rows, seconds = [], []
    for box in range(oracle.num_boxes):
        truth = oracle.true_box(box)
        row = {"seed": seed, "box": box, "size": truth[2], "keyframes": int((coverage[:, box] > 0).sum()),
               "best_cover": float(coverage[:, box].max()), "iou": {}}
        for name, options in VARIANTS.items():
            started = time.perf_counter()
            answer = query_result(result, object_text(box), embedder, segmenter, **options)
            if name == FUSED:
                seconds.append(time.perf_counter() - started)
            best = answer.instances[0] if answer.instances else None
            row["iou"][name] = box_iou(box_to_truth(best.centre, best.axes, best.extents, T_gt_map), truth) if best else 0.0
            if name == FUSED:
                row["instances"] = len(answer.instances)
                row["views"] = len(best.views) if best else 0
        rows.append(row)
    run = {"seed": seed, "keyframes": len(result.keyframes), "ate": result.summary.get("ate", {}).get("rmse"),
           "query_seconds": statistics.median(seconds) if seconds else 0.0}
    return rows, run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--out", type=Path, default=result_file("objects"))
    args = parser.parse_args()
    started = time.perf_counter()
    rows, runs = [], []
    for seed in args.seeds:
        world_rows, run = measure(seed, args.width, args.height, args.frames)
        rows += world_rows
        runs.append(run)
    seen = [r for r in rows if r["keyframes"] > 0]
    medians = {name: statistics.median(r["iou"][name] for r in seen) for name in VARIANTS}
    means = {name: statistics.fmean(r["iou"][name] for r in seen) for name in VARIANTS}
    wins = sum(r["iou"][FUSED] > r["iou"][SINGLE] + 1e-9 for r in seen)
    losses = sum(r["iou"][FUSED] < r["iou"][SINGLE] - 1e-9 for r in seen)
    lines = [
        "## Open-vocabulary object queries: 3D boxes on the synthetic world",
        "",
        f"Machine: {cpu_model()}, {os.cpu_count()} cores, {memory_gib():.0f} GiB, Python {platform.python_version()}; "
        f"{date_text('%Y-%m-%d')}.",
        f"Command: `python benchmarks/bench_objects.py --seeds {' '.join(map(str, args.seeds))} --frames {args.frames} "
        f"--width {args.width} --height {args.height}` ({time.perf_counter() - started:.0f} s).",
        "",
        f"Synthetic worlds (seeds {', '.join(map(str, args.seeds))}), {args.frames} frames at {args.width}x{args.height}, "
        "simulated frontend with VGGT-like errors (`--sim-profile vggt`, other settings default); oracle embedder and "
        "segmenter (`sl4slam.objects.oracle`); every furniture box queried as \"box b\"; the best instance moved into "
        "the ground-truth frame by the run's Sim(3) trajectory alignment and compared with the true box by exact "
        "oriented-box IoU (convex hull of the intersection polytope, `sl4slam.objects.fusion.box_iou`). "
        f"{len(seen)} of {len(rows)} boxes are seen by at least one keyframe; the medians are over those.",
        "",
        *table(["run (seed)", "keyframes", "ATE RMSE (m)", "median query time, top-5 (s)"],
               [[r["seed"], r["keyframes"], f"{r['ate']:.4f}" if r["ate"] is not None else "-",
                 f"{r['query_seconds']:.3f}"] for r in runs]),
        "",
        *table(["variant", "median IoU", "mean IoU", "boxes with IoU >= 0.5"],
               [[name, f"{medians[name]:.3f}", f"{means[name]:.3f}",
                 f"{sum(r['iou'][name] >= 0.5 for r in seen)} / {len(seen)}"] for name in VARIANTS]),
        "",
        f"Fused (top-5) against single view, box by box: better on {wins}, worse on {losses}, equal on "
        f"{len(seen) - wins - losses} of {len(seen)}.",
        "",
        "Per object (size in metres; keyframes: the run's keyframes that see it; cover: the largest share of "
        "one keyframe it covers; views: keyframes merged into the fused instance):",
        "",
        *table(["seed", "box", "size (m)", "keyframes", "cover", "single IoU", "fused IoU", "top-10 IoU", "views",
                "instances"],
               [[r["seed"], r["box"], " x ".join(f"{s:.2f}" for s in r["size"]), r["keyframes"],
                 f"{r['best_cover']:.3f}", f"{r['iou'][SINGLE]:.3f}" if r["keyframes"] else "not seen",
                 f"{r['iou'][FUSED]:.3f}" if r["keyframes"] else "not seen",
                 f"{r['iou']['fused, top-10']:.3f}" if r["keyframes"] else "not seen", r.get("views", 0),
                 r.get("instances", 0)] for r in rows]),
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
