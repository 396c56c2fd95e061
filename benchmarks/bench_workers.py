"""Wall time of a run with the model's windows on N local worker processes (``--workers N``).

The model is a stand-in that costs no CPU: the simulated frontend's submaps, recorded once, replayed
in each worker after a sleep as long as a model's forward of as many frames (``--forward-seconds``,
per 17 frames: 0.43 s is VGGT-1B's on an H100 in bf16, benchmarks/results/vggt.md), so that this
CPU does the graph work while the "GPUs" wait. Every worker count runs the same sequence in turn
(``--repeats`` times); the report gives the median wall time of each, its ratio to one model in the
run's own process (the overlapped schedule), input frames per second, whether the trajectories
are the same bytes, and the bound the graph work sets (its seconds per submap: with enough workers
the model's time hides behind it, and no number of workers goes below it).

    python benchmarks/bench_workers.py --sequence ../shared/data/tum_rgbd_fr1_desk --workers 1 2 3 --repeats 3
"""

from __future__ import annotations

import argparse
import shutil
import time
from functools import partial
from pathlib import Path

import numpy as np

from harness import OUT, cpu_model, date_text, result_file, run_sequence, shared_sequence, simulated_config, write_report

from sl4slam.frontend.cache import CachingFrontend, ReplayFrontend
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.frontend.workers import ProcessWorkers, WorkerFrontend


class SleepingReplay(ReplayFrontend):
    """A recorded prediction, served after a sleep as long as the model's forward of as many frames."""

    def __init__(self, directory: Path, seconds_per_17: float) -> None:
        super().__init__(directory)
        self.seconds_per_17 = seconds_per_17

    def reconstruct(self, frames, submap_id, **kwargs):
        start = time.perf_counter()
        prediction = super().reconstruct(frames, submap_id, **kwargs)
        time.sleep(max(0.0, self.seconds_per_17 * len(frames) / 17 - (time.perf_counter() - start)))
        return prediction


def stand_in(directory: str, seconds_per_17: float, index: int) -> SleepingReplay:
    """A worker's model stand-in (built in the worker process)."""
    return SleepingReplay(Path(directory), seconds_per_17)


def config_for(profile: str, workers: int):
    return simulated_config({"sim.profile": profile, "retrieval.kind": "orb", "workers": workers})


def record(sequence: Path, profile: str, directory: Path) -> None:
    """The simulated frontend's submaps of ``sequence``, recorded into ``directory``."""
    shutil.rmtree(directory, ignore_errors=True)
    config = config_for(profile, 1)
    frontend = CachingFrontend(SimulatedFrontend(config.sim), directory, compressed=False)
    run_sequence(config, sequence, frontend=frontend)


def one_run(sequence: Path, directory: Path, workers: int, profile: str, seconds_per_17: float) -> dict:
    """One run of ``sequence`` with ``workers`` model processes (1: the model in this process)."""
    config = config_for(profile, workers)
    pool = None
    if workers > 1:
        pool = ProcessWorkers(partial(stand_in, str(directory), seconds_per_17), workers, threads=1)
        pool.start()
        frontend = WorkerFrontend(SleepingReplay(directory, seconds_per_17), pool)
    else:
        frontend = SleepingReplay(directory, seconds_per_17)
    try:
        start = time.perf_counter()
        run = run_sequence(config, sequence, frontend=frontend)
        seconds = time.perf_counter() - start
    finally:
        if pool is not None:
            pool.close()
    result, ledger = run.result, run.pipeline.ledger
    graph = [sum(v for k, v in s.items() if k not in ("frontend", "retrieval_describe")) for s in ledger.submap_seconds]
    return {"seconds": seconds, "frames": ledger.frames, "submaps": result.stats["submaps"],
            "trajectory": result.T_world_cam.tobytes(), "graph": float(np.median(graph)) if graph else float("nan")}


def model_run(sequence: Path, model: str, workers: int, max_frames: int) -> dict:
    """``sl4slam run`` of the first ``max_frames`` frames with ``model`` on random full-size weights on
    this CPU, ``workers`` model processes; its wall time and trajectory bytes."""
    import subprocess

    from bench_cpu_estimate import random_weights_file

    out = OUT / f"workers_{model}_{workers}"
    command = ["sl4slam", "run", str(sequence), "--out", str(out), "--overwrite", "--model", model,
               "--weights", str(random_weights_file(model)), "--device", "cpu", "--max-frames", str(max_frames),
               "--workers", str(workers), "--keyframes", "none", "--quiet"]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(done.stderr[-2000:])
    return {"seconds": seconds, "trajectory": (out / "trajectory.txt").read_bytes()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", default=str(shared_sequence("tum_rgbd_fr1_desk")))
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", default="vggt")
    parser.add_argument("--forward-seconds", type=float, nargs="+", default=[0.43, 1.72],
                        help="the stand-in's forward per 17 frames (0.43: VGGT-1B bf16 on an H100; 1.72: four times that)")
    parser.add_argument("--model", default="", help="also time this model on random weights on this CPU (e.g. da3-small)")
    parser.add_argument("--model-frames", type=int, default=150, help="frames of the sequence the model runs read")
    parser.add_argument("--out", default=str(result_file("workers")))
    args = parser.parse_args()
    sequence = Path(args.sequence)
    directory = OUT / "workers_recording"
    record(sequence, args.profile, directory)
    tables = []
    for seconds_per_17 in args.forward_seconds:
        runs: dict[int, list[dict]] = {n: [] for n in args.workers}
        for repeat in range(args.repeats):  # the counts in turn, so that load changes hit each alike
            for n in args.workers:
                runs[n].append(one_run(sequence, directory, n, args.profile, seconds_per_17))
                print(f"forward {seconds_per_17} s, repeat {repeat}: {n} worker(s) {runs[n][-1]['seconds']:.1f} s",
                      flush=True)
        base = float(np.median([r["seconds"] for r in runs[args.workers[0]]]))
        reference = runs[args.workers[0]][0]["trajectory"]
        tables += [f"Forward {seconds_per_17} s per 17 frames:", "",
                   "| workers | wall s | ratio to the first row | input frames/s | submaps | graph work s/submap (median) | "
                   "model s/submap | same trajectory bytes |", "|---|---|---|---|---|---|---|---|"]
        for n in args.workers:
            seconds = float(np.median([r["seconds"] for r in runs[n]]))
            first = runs[n][0]
            same = all(r["trajectory"] == reference for r in runs[n])
            tables.append(f"| {n} | {seconds:.1f} | {seconds / base:.2f} | {first['frames'] / seconds:.1f} | "
                          f"{first['submaps']} | {first['graph']:.2f} | {seconds_per_17 * 18 / 17:.2f} | "
                          f"{'yes' if same else 'NO'} |")
        tables.append("")
    if args.model:
        runs_model = {n: [model_run(sequence, args.model, n, args.model_frames) for _ in range(args.repeats)]
                      for n in args.workers}
        base = float(np.median([r["seconds"] for r in runs_model[args.workers[0]]]))
        reference = runs_model[args.workers[0]][0]["trajectory"]
        tables += [f"{args.model} on random full-size weights on this CPU (`sl4slam run ... --device cpu --max-frames "
                   f"{args.model_frames} --workers N`, wall time of the whole command):", "",
                   "| workers | wall s | ratio to the first row | same trajectory bytes |", "|---|---|---|---|"]
        for n in args.workers:
            seconds = float(np.median([r["seconds"] for r in runs_model[n]]))
            same = all(r["trajectory"] == reference for r in runs_model[n])
            tables.append(f"| {n} | {seconds:.1f} | {seconds / base:.2f} | {'yes' if same else 'NO'} |")
        tables.append("")
    lines = [
        "## Model windows on worker processes (--workers)",
        "",
        f"Machine: {cpu_model()}; date {date_text()}. Command: `python benchmarks/bench_workers.py --sequence "
        f"{sequence.name} --workers {' '.join(map(str, args.workers))} --repeats {args.repeats} --forward-seconds "
        f"{' '.join(map(str, args.forward_seconds))}" + (f" --model {args.model}" if args.model else "") + "`.",
        f"Model stand-in: the simulated frontend's submaps ({args.profile} profile) recorded once, replayed in each worker "
        "process after a sleep as long as the forward (per 17 frames as given; a submap has 17-19 frames); ORB "
        f"retrieval. Median of {args.repeats} runs each, the worker counts in turn. 1 worker: the model in the run's "
        "own process, overlapping the graph work.",
        "",
        *tables,
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
