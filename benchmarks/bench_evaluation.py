"""The evaluation suite on synthetic datasets in the TUM RGB-D and 7-Scenes layouts.

Writes synthetic sequences in both layouts (``sl4slam synth --layout``), runs the paper's
protocol on them with the simulated frontend (5 runs, run r = seed r), and measures:

1. the paper-layout tables (ATE; on 7-Scenes also accuracy / completion / chamfer) and the time
   per sequence;
2. the wall time of the same 7-Scenes evaluation (runs and dense metrics) with a pool of 2 local
   workers against a pool of 1, and against runs in the calling process (medians of repeats,
   side by side, alternating);
3. whether Ray (a local instance, 2 workers) gives exactly the local pool's numbers.

Optionally (``--tum-root``) also a real TUM RGB-D root (images and motion-capture ground truth)
with the simulated frontend. Settings of the frontend come after ``--``, so the table can be
re-made with another simulator profile::

    python benchmarks/bench_evaluation.py                                   # default: --sim-perspective 0.1
    python benchmarks/bench_evaluation.py -- --sim-profile vggt              # the VGGT-calibrated simulator
    python benchmarks/bench_evaluation.py --tum-root datasets/tum --sequences-tum desk
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from harness import result_file, synthetic_world, timed, write_report
from sl4slam.cli import build_parser, config_from_args
from sl4slam.evaluation import EvalSettings, LocalExecutor, evaluate
from sl4slam.evaluation.executors import cpu_count

DEFAULT_FRONTEND_ARGS = ["--sim-perspective", "0.1"]


def make_datasets(work: Path, sequences: int, frames: int, width: int, height: int) -> tuple[Path, Path, list[str]]:
    """``sequences`` synthetic worlds (seeds 0..n-1) in both layouts; returns the roots and the names."""
    tum, seven = work / "tum", work / "7scenes"
    names = [f"world-{seed}" for seed in range(sequences)]
    for seed, name in enumerate(names):
        synthetic_world(width, height, frames, seed, folder=tum / name)
        synthetic_world(width, height, frames, seed, layout="7scenes", folder=seven / name / "seq-01")
    return tum, seven, names


def run_config(run_args: list[str]):
    """The SLAM config the command line ``sl4slam eval ... RUN_ARGS`` would use."""
    args = build_parser().parse_args(["eval", ".", "--dataset", "tum", "--out", ".", *run_args])
    return config_from_args(args)


def table_block(path: Path) -> str:
    """The tables of an evaluation's tables.md, without its title and headings."""
    text = path.read_text()
    text = text[text.index("## "):] if "## " in text else text
    return "\n".join(line for line in text.splitlines() if line != "## Results").strip()


def timed_evaluation(**kwargs):
    """:func:`sl4slam.evaluation.evaluate` and its wall seconds."""
    outcome, seconds, _ = timed(evaluate, **kwargs)
    return outcome, seconds


def scaling(root: Path, names: list[str], config, runs: int, repeats: int) -> list[str]:
    """Wall time of one 7-Scenes evaluation in this process, on a pool of 1 and on a pool of 2."""
    runs = max(2, runs // 2)
    threads = max(1, cpu_count() // 2)
    variants = {"this process": lambda: None, "pool of 1": lambda: LocalExecutor(1, threads),
                "pool of 2": lambda: LocalExecutor(2, threads)}
    seconds: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats):
        for name, make in variants.items():
            out = root.parent / "scaling"
            shutil.rmtree(out, ignore_errors=True)
            executor = make()
            try:
                _, elapsed = timed_evaluation(root=root, out_dir=out, settings=EvalSettings(dataset="7scenes", runs=runs),
                                              config=config, sequences=names, workers=1, executor=executor,
                                              progress=False)
            finally:
                if executor is not None:
                    executor.close()
            seconds[name].append(elapsed)
    median = {name: statistics.median(values) for name, values in seconds.items()}
    lines = ["### Local parallelism\n",
             f"7-Scenes layout (SLAM and dense metrics), {len(names)} sequences x {runs} runs, fresh output folder "
             f"each time, {repeats} repeats alternating; each worker process has {threads} thread(s) and its start-up "
             "(imports) is included; \"this process\" runs one after the other in the calling process, whose imports "
             "are already done.\n",
             "| executor | wall s (median) | all repeats |", "|---|---|---|"]
    lines += [f"| {name} | {median[name]:.1f} | {', '.join(f'{v:.1f}' for v in values)} |" for name, values in seconds.items()]
    lines.append(f"\n2-worker / 1-worker wall time (pools): **{median['pool of 2'] / median['pool of 1']:.2f}**; pool of 2 / "
                 f"this process: {median['pool of 2'] / median['this process']:.2f} (load average during: "
                 f"{os.getloadavg()[0]:.1f}).\n")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "sl4slam_bench_evaluation"),
                        help="folder for the datasets and evaluations (datasets are reused)")
    parser.add_argument("--sequences", type=int, default=3, help="synthetic sequences per layout")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=96)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2, help="workers of the table runs")
    parser.add_argument("--repeats", type=int, default=2, help="repeats of the 1- vs 2-worker timing")
    parser.add_argument("--tum-root", help="a real TUM RGB-D root to evaluate too (simulated frontend)")
    parser.add_argument("--sequences-tum", nargs="+", help="sequences of --tum-root (default: all found)")
    parser.add_argument("--parts", nargs="+", default=["tables", "scaling", "ray"], choices=["tables", "scaling", "ray"],
                        help="what to measure (the report holds these parts only)")
    parser.add_argument("--output", default=str(result_file("evaluation")))
    parser.add_argument("run_args", nargs="*", help="run settings after --, e.g. -- --sim-profile vggt")
    args = parser.parse_args()
    frontend_args = args.run_args or DEFAULT_FRONTEND_ARGS
    # keyframes every ~25 px at 640 px wide, scaled to the rendered width; 16 keyframes per submap
    tau = 25.0 * args.width / 640.0
    run_args = ["--frontend", "simulated", "--tau-disparity", f"{tau:g}", "--retrieval", "orb", *frontend_args]
    config = run_config(run_args)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    tum, seven, names = make_datasets(work, args.sequences, args.frames, args.width, args.height)
    seconds_data = time.perf_counter() - t0
    load_before = os.getloadavg()

    report = []
    command = "python benchmarks/bench_evaluation.py " + " ".join(sys.argv[1:])
    report.append("## Evaluation suite: the paper's protocol on synthetic TUM RGB-D / 7-Scenes layouts\n")
    report.append(f"Machine: {cpu_count()}-core {platform.machine()} CPU, no GPU; Python {platform.python_version()}. "
                  f"Date: {datetime.date.today().isoformat()}. Load average at the start: "
                  f"{load_before[0]:.1f} (the machine is shared).")
    report.append(f"Command: `{command.strip()}`.")
    report.append(f"Data: {args.sequences} synthetic worlds (seeds 0-{args.sequences - 1}) written in both layouts "
                  f"(`sl4slam synth --layout tum|7scenes`), {args.frames} frames at {args.width}x{args.height} each "
                  f"({seconds_data:.0f} s to write). Run settings: `{' '.join(run_args)}` "
                  f"(keyframes every {tau:g} px = 25 px at 640 px scaled; other settings default). "
                  f"{args.runs} runs per sequence, run r = seed r; {args.workers} local workers.\n")

    timings = {}
    for key, root in (("tum", tum), ("7scenes", seven)) if "tables" in args.parts else ():
        out = work / f"eval_{key}"
        shutil.rmtree(out, ignore_errors=True)
        outcome, seconds = timed_evaluation(root=root, out_dir=out, settings=EvalSettings(dataset=key, runs=args.runs),
                                            config=config, sequences=names, workers=args.workers, progress=True)
        timings[key] = seconds
        failed = sum(r["status"] != "ok" for r in outcome.results)
        report.append(f"### {'TUM RGB-D' if key == 'tum' else '7-Scenes'} layout ({len(outcome.results)} runs, "
                      f"{failed} failed, {seconds:.0f} s wall with {args.workers} workers)\n")
        report.append(table_block(out / "tables.md") + "\n")
        per_sequence = {}
        for r in outcome.results:
            per_sequence.setdefault(r["sequence"], []).append(r)
        report.append("| sequence | keyframes (median) | SLAM s (median) | metrics s (median) | run total s (median) |")
        report.append("|---|---|---|---|---|")
        for name, runs in per_sequence.items():
            ok = [r for r in runs if r["status"] == "ok"]
            report.append(f"| {name} | {statistics.median(r['counts']['keyframes'] for r in ok):.0f} | "
                          f"{statistics.median(r['seconds']['slam'] for r in ok):.1f} | "
                          f"{statistics.median(r['seconds']['evaluation'] for r in ok):.1f} | "
                          f"{statistics.median(r['seconds']['total'] for r in ok):.1f} |")
        report.append("")

    if args.tum_root and "tables" in args.parts:
        out = work / "eval_real_tum"
        shutil.rmtree(out, ignore_errors=True)
        real_config = run_config(["--frontend", "simulated", "--retrieval", "orb", *frontend_args])
        outcome, seconds = timed_evaluation(root=args.tum_root, out_dir=out,
                                            settings=EvalSettings(dataset="tum", runs=args.runs), config=real_config,
                                            sequences=args.sequences_tum, workers=args.workers, progress=True)
        report.append(f"### Real TUM RGB-D images and ground truth, simulated frontend ({seconds:.0f} s wall)\n")
        report.append(f"Run settings: `--frontend simulated --retrieval orb {' '.join(frontend_args)}` (paper keyframe "
                      "threshold 25 px at 640x480).\n")
        report.append(table_block(out / "tables.md") + "\n")

    if "scaling" in args.parts:
        report += scaling(seven, names, config, args.runs, args.repeats)

    if "ray" in args.parts:
        try:
            import ray  # noqa: F401

            local_out, ray_out = work / "equality_local", work / "equality_ray"
            for path in (local_out, ray_out):
                shutil.rmtree(path, ignore_errors=True)
            common = dict(root=tum, settings=EvalSettings(dataset="tum", runs=2), config=config, sequences=names,
                          grid=["backend.kind=sl4,sim3"], workers=2, threads=1, progress=False)
            local, seconds_local = timed_evaluation(out_dir=local_out, **common)
            on_ray, seconds_ray = timed_evaluation(out_dir=ray_out, ray=True, **common)
            same = [(r["point"], r["sequence"], r["run"], r["metrics"]) for r in local.results] == \
                   [(r["point"], r["sequence"], r["run"], r["metrics"]) for r in on_ray.results]
            report.append("### Ray against the local pool\n")
            report.append(f"TUM layout, {len(names)} sequences x 2 runs x grid `backend.kind=sl4,sim3` "
                          f"({len(local.results)} runs), 2 workers x 1 thread each way. Ray: {on_ray.executor}.\n")
            report.append(f"Every metric of every run identical: **{same}**. Wall time: local pool {seconds_local:.1f} s, "
                          f"Ray {seconds_ray:.1f} s (including starting the Ray instance).\n")
        except ImportError:
            report.append("Ray is not installed: the Ray comparison was skipped.\n")

    write_report(args.output, "\n".join(report).splitlines())


if __name__ == "__main__":
    main()
