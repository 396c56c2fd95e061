"""The CPU estimate a run prints before it starts: the per-model work it rests on, and how close it comes.

    python benchmarks/bench_cpu_estimate.py calibrate [--models da3-small vggt ...] [--frames 17]
    python benchmarks/bench_cpu_estimate.py check --source DIR [--models da3-small vggt] [--max-frames 40]

``calibrate``: each model in its own child process, its full-size network with seeded random weights
(float32, CPU) in its SLAM frontend, reconstructs one window of ``--frames`` random 640x480 frames
after a two-frame warm-up (as ``bench_models.py``); the machine's float32 matmul speed
(``sl4slam.frontend.cost.matmul_rate``) is measured in the same process before and after. The
model's work per frame, in GFLOP-equivalents, is seconds per frame x speed: the number its registry
entry stores (``FrontendEntry.cpu_work``).

``check``: whole ``sl4slam run`` calls on a real sequence excerpt with random full-size weights written
to a file (``--weights``), on the CPU: the estimate line the run prints before it starts against the
frontend seconds per submap it then measures (``summary.json``: the median over the run's submaps).

Results go to ``benchmarks/results/cpu_estimate.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from bench_models import build_frontend
from harness import OUT as SCRATCH
from harness import date_text, random_frames, result_file, torch_machine, write_report

OUT = SCRATCH / "cpu_estimate"
RECORDS = OUT / "records.jsonl"


def calibrate_child(name: str, frames: int) -> dict:
    import numpy as np
    import torch

    from sl4slam.frontend.cost import matmul_rate
    from sl4slam.types import Frame

    frontend = build_frontend(name)
    images = random_frames(frames, seed=2)
    window = [Frame(index=i, timestamp=float(i), rgb=image) for i, image in enumerate(images)]
    with torch.inference_mode():
        frontend.reconstruct(window[:2], submap_id=0)  # warm-up: kernels and allocator
        rate_before = matmul_rate()
        start = time.perf_counter()
        prediction = frontend.reconstruct(window, submap_id=1)
        seconds = time.perf_counter() - start
        rate_after = matmul_rate()
    rate = (rate_before + rate_after) / 2
    assert np.isfinite(prediction.depth).all()
    return {"kind": "calibrate", "model": name, "frames": frames, "seconds": seconds, "rate": rate,
            "rates": [rate_before, rate_after], "cpu_work": seconds / frames * rate,
            "threads": torch.get_num_threads(), "load": os.getloadavg()[0], "date": date_text()}


def run_child(args: list[str], threads: int, timeout: float) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    command = [sys.executable, __file__, *args, "--threads", str(threads)]
    print("$", " ".join(command[1:]), flush=True)
    try:
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"over {timeout:.0f} s", "args": args}
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1][:300], "args": args}
    record = json.loads(done.stdout.strip().splitlines()[-1])
    OUT.mkdir(parents=True, exist_ok=True)
    with open(RECORDS, "a") as log:
        log.write(json.dumps(record) + "\n")
    return record


def random_weights_file(name: str) -> Path:
    """The model's full-size network with seeded random weights, saved where ``--weights`` can read it
    (``bench_gpu_run.random_weights``: VGGT's camera head biased to finite cameras, in bf16; the
    others as built; a CPU run computes in float32 whatever the file's precision)."""
    from bench_gpu_run import random_weights

    OUT.mkdir(parents=True, exist_ok=True)
    return random_weights(name, OUT / f"{name}_random.safetensors", dtype=None)


def check_child(name: str, source: str, max_frames: int) -> dict:
    weights = random_weights_file(name)
    out = OUT / f"run_{name}"
    command = ["sl4slam", "run", source, "--out", str(out), "--overwrite", "--model", name, "--weights", str(weights),
               "--device", "cpu", "--max-frames", str(max_frames), "--retrieval", "none", "--keyframes", "none"]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(done.stderr[-2000:])
    line = next((l for l in done.stderr.splitlines() if "on this CPU" in l), "")
    match = re.search(r"matmul ([\d.]+) GFLOP/s\) \S+ needs about [\d.]+ (?:s|min|h) per (\d+)-frame submap", line)
    from sl4slam.registry import frontend_entry

    # the run's own estimate before rounding: the model's work per frame x frames / the speed it measured
    estimated = frontend_entry(name).cpu_work * int(match.group(2)) / float(match.group(1)) if match else None
    summary = json.loads((out / "summary.json").read_text())
    window = int(match.group(2)) if match else None
    if estimated is not None and summary["counts"]["submaps"] == 1:  # one window of the first keyframes only
        estimated *= summary["counts"]["keyframes"] / window  # the estimate's own work per frame, for that window
        window = summary["counts"]["keyframes"]
    return {"kind": "check", "model": name, "source": Path(source).name, "max_frames": max_frames,
            "estimate_line": line, "estimated_s_per_submap": estimated, "window_frames": window,
            "measured_s_per_submap": summary["seconds"]["per_submap_median"]["frontend"],
            "submaps": summary["counts"]["submaps"], "keyframes": summary["counts"]["keyframes"],
            "frontend_s": summary["seconds"]["by_stage"]["frontend"],
            "window_frames_total": summary["counts"]["keyframes"] + 2 * (summary["counts"]["submaps"] - 1),
            "wall_s": wall, "load": os.getloadavg()[0], "date": date_text()}


def report(records: list[dict], threads: int) -> list[str]:
    records = [r for r in records if "error" not in r]
    calibrations = [r for r in records if r.get("kind") == "calibrate"]  # every one: their spread is the noise
    latest = {(r["model"], r["max_frames"]): r for r in records if r.get("kind") == "check"}  # the newest of each
    checks = list(latest.values())
    lines = ["## The CPU estimate: each model's work, and the estimate against whole runs", "",
             f"Machine: {torch_machine()}; {threads} torch threads. Random full-size weights, float32.", "",
             "### Work per frame (`FrontendEntry.cpu_work`)", "",
             "`python benchmarks/bench_cpu_estimate.py calibrate`: one window of random 640x480 frames after a "
             "two-frame warm-up; the float32 matmul speed measured in the same process before and after.", "",
             "| model | frames | seconds | matmul GFLOP/s (before, after) | GFLOP-equivalent per frame | load | date |",
             "|---|---|---|---|---|---|---|"]
    for r in calibrations:
        lines.append(f"| {r['model']} | {r['frames']} | {r['seconds']:.1f} | {r['rates'][0]:.0f}, {r['rates'][1]:.0f} | "
                     f"{r['cpu_work']:.0f} | {r['load']:.1f} | {r['date']} |")
    if checks:
        lines += ["", "### The estimate against whole runs", "",
                  "`python benchmarks/bench_cpu_estimate.py check`: `sl4slam run` on the excerpt on the CPU; the "
                  "estimate is the run's own line, printed before the first frame (for a run of one submap, scaled from "
                  "its 18-frame window to the frames that submap had); measured = the median frontend seconds per "
                  "submap over the run (`summary.json`). Per frame: the estimate's work per frame over the speed the "
                  "run measured, against the run's frontend seconds over the frames of all its windows (new "
                  "keyframes plus two shared frames per later submap).", "",
                  "| model | source | frames | submaps | window frames | estimated s per submap | measured s per submap | "
                  "estimated s per frame | measured s per frame | estimate / measured (per frame) | load | date |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in checks:
            measured = r.get("measured_s_per_submap")
            ratio = f"{r['estimated_s_per_submap'] / measured:.2f}" if measured and r["estimated_s_per_submap"] else ""
            window = r.get("window_frames", 18)
            estimated = r["estimated_s_per_submap"]
            per_frame = estimated / window if estimated else None
            measured_frame = r["frontend_s"] / r["window_frames_total"] if "frontend_s" in r else None
            ratio = f"{per_frame / measured_frame:.2f}" if per_frame and measured_frame else ""
            lines.append(f"| {r['model']} | {r['source']} | {r['max_frames']} | {r['submaps']} | {window} | "
                         f"{estimated:.1f} | {measured:.1f} | {per_frame:.2f} | "
                         f"{measured_frame:.2f} | {ratio} | {r['load']:.1f} | {r['date']} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("mode", choices=["calibrate", "check", "report"])
    parser.add_argument("--models", nargs="+", default=["da3-small", "vggt"])
    parser.add_argument("--frames", type=int, default=17)
    parser.add_argument("--source", help="check: a sequence folder (TUM RGB-D)")
    parser.add_argument("--max-frames", type=int, default=40)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=3600.0)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        import torch

        torch.set_num_threads(args.threads)
        record = (calibrate_child(args.child, args.frames) if args.mode == "calibrate"
                  else check_child(args.child, args.source, args.max_frames))
        print(json.dumps(record))
        return
    if args.mode != "report":
        for name in args.models:
            extra = ["--frames", str(args.frames)] if args.mode == "calibrate" else [
                "--source", args.source, "--max-frames", str(args.max_frames)]
            print(json.dumps(run_child([args.mode, "--child", name, *extra], args.threads, args.timeout)))
    records = [json.loads(line) for line in RECORDS.read_text().splitlines() if line.strip()] if RECORDS.exists() else []
    write_report(result_file("cpu_estimate"), report(records, args.threads))


if __name__ == "__main__":
    main()
