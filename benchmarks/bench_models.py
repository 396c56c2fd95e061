"""Every registered model's frontend side by side: seconds and peak memory of one submap.

    python benchmarks/bench_models.py [--models vggt da3-small ...] [--frames 17] [--threads 2]

Each model runs in its own child process, one after the other, in one invocation: its full-size
network with seeded random weights (float32, CPU), wrapped in its SLAM frontend exactly as a run
uses it, reconstructs one window of ``--frames`` random 640x480 frames (smooth ramps plus noise) at
the model's native resolution (VGGT 518 px wide, Depth Anything 3 504 px, π³/Pi3X 255 000 pixels).
The time is the whole ``reconstruct`` call (preprocessing, forward, decoding to depth, cameras and
intrinsics), after one warm-up call on two frames; peak memory is the process's resident
high-water mark (``VmHWM``) over that call, weights included. Ratios are to VGGT-1B in the same
invocation. The comparison of each model with its authors' code is in ``da3.md`` and ``pi3.md``.

Results go to ``benchmarks/results/models.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from harness import (OUT, date_text, peak_rss_bytes, random_frames, reset_peak_rss, result_file, torch_machine,
                     write_report)

RECORDS = OUT / "models" / "records.jsonl"
MODELS = ("vggt", "da3-small", "da3-base", "da3-large", "da3-giant", "pi3", "pi3x")
SEED = 0


def build_frontend(name: str):
    """The frontend of ``name`` around its full-size network with seeded random weights."""
    import torch

    from sl4slam.models.vggt.model import init_random_weights

    if name == "vggt":
        from sl4slam.config import ModelConfig
        from sl4slam.frontend.vggt import VGGTFrontend
        from sl4slam.models.vggt.model import VGGT, VGGTModelConfig

        with torch.device("meta"):  # as the frontend runs it: camera and depth heads, no point head
            model = VGGT(VGGTModelConfig(enable_point=False))
        init_random_weights(model, seed=SEED)
        return VGGTFrontend(ModelConfig(dtype="fp32"), model=model.eval())
    if name.startswith("da3-"):
        from sl4slam.frontend.da3 import DA3Frontend
        from sl4slam.models.da3 import build_da3
        from sl4slam.models.da3 import init_random_weights as init_da3
        from sl4slam.models.da3.config import ARCHITECTURES

        size = name.split("-", 1)[1]
        model = init_da3(build_da3(ARCHITECTURES[size], device="meta"), seed=SEED).eval()
        return DA3Frontend(size=size, device="cpu", dtype="fp32", model=model)
    if name in ("pi3", "pi3x"):
        from bench_pi3 import random_frontend_model
        from sl4slam.frontend.pi3 import Pi3Frontend

        return Pi3Frontend(name, device="cpu", dtype="fp32", model=random_frontend_model(name, SEED))
    raise SystemExit(f"unknown model {name!r}: use one of {', '.join(MODELS)}")


def child(name: str, frames: int) -> dict:
    import numpy as np
    import torch

    from sl4slam.types import Frame

    start = time.perf_counter()
    frontend = build_frontend(name)
    build_s = time.perf_counter() - start
    images = random_frames(frames, seed=2)
    window = [Frame(index=i, timestamp=float(i), rgb=image) for i, image in enumerate(images)]
    with torch.inference_mode():
        frontend.reconstruct(window[:2], submap_id=0)  # warm-up: kernels and allocator
        reset_peak_rss()
        start = time.perf_counter()
        prediction = frontend.reconstruct(window, submap_id=1)
        seconds = time.perf_counter() - start
    finite = all(bool(np.isfinite(a).all()) for a in (prediction.depth, prediction.K, prediction.T_cam_submap))
    parameters = sum(p.numel() for p in frontend.model.parameters()) if hasattr(frontend, "model") else None
    return {"model": name, "frames": frames, "grid": list(prediction.depth.shape[1:]), "seconds": seconds,
            "build_s": build_s, "peak_bytes": peak_rss_bytes(fallback=False), "parameters": parameters,
            "finite": finite,
            "threads": torch.get_num_threads(), "load": os.getloadavg()[0]}


def run_child(name: str, frames: int, threads: int, timeout: float) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    command = [sys.executable, __file__, "--child", name, "--frames", str(frames), "--threads", str(threads)]
    print("$", " ".join(command[1:]), flush=True)
    try:
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"model": name, "frames": frames, "error": f"over {timeout:.0f} s"}
    if done.returncode != 0:
        return {"model": name, "frames": frames, "error": done.stderr.strip().splitlines()[-1][:200]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def report(records: list[dict], command: str, threads: int) -> list[str]:
    base = {r["frames"]: r["seconds"] for r in records if r["model"] == "vggt" and "seconds" in r}
    lines = ["## Every model's frontend, one submap (random full-size weights, fp32, CPU)", "",
             f"Machine: {torch_machine()}; {threads} torch threads; {date_text()}. Command: `{command}`.", "",
             "Whole `reconstruct` of one window of random 640x480 frames at the model's native grid, after a "
             "two-frame warm-up; peak = resident high-water mark over the call (weights included). Each model in "
             "its own process, one after the other. Ours against each model's authors' code: `da3.md`, `pi3.md`.",
             "", "| model | parameters | frames | grid (HxW) | seconds | VGGT-1B / model | peak RSS (GiB) | load |",
             "|---|---|---|---|---|---|---|---|"]
    for r in records:
        if "error" in r:
            lines.append(f"| {r['model']} | | {r['frames']} | | failed: {r['error']} | | | |")
            continue
        ratio = base.get(r["frames"])
        lines.append(f"| {r['model']} | {r['parameters']:,} | {r['frames']} | {r['grid'][0]}x{r['grid'][1]} | "
                     f"{r['seconds']:.1f} | {ratio / r['seconds']:.1f}x | {r['peak_bytes'] / 2**30:.2f} | "
                     f"{r['load']:.1f} |" if ratio else
                     f"| {r['model']} | {r['parameters']:,} | {r['frames']} | {r['grid'][0]}x{r['grid'][1]} | "
                     f"{r['seconds']:.1f} | | {r['peak_bytes'] / 2**30:.2f} | {r['load']:.1f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS))
    parser.add_argument("--frames", type=int, default=17)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per model")
    parser.add_argument("--out", type=Path, default=result_file("models"))
    parser.add_argument("--report", action="store_true", help="only write the report from the kept records")
    parser.add_argument("--report-command", default="--frames 17", help="the command line the records came from")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        import torch

        torch.set_num_threads(args.threads)
        record = child(args.child, args.frames)
        RECORDS.parent.mkdir(parents=True, exist_ok=True)
        with open(RECORDS, "a") as log:  # kept as each model finishes: a long grid loses nothing
            log.write(json.dumps(record) + "\n")
        print(json.dumps(record))
        return
    if args.report:
        records = [json.loads(line) for line in RECORDS.read_text().splitlines() if line.strip()]
        latest = {(r["model"], r["frames"]): r for r in records}  # the newest record of each model and size
        write_report(args.out, report(list(latest.values()), "python benchmarks/bench_models.py " + args.report_command,
                                      args.threads))
        return
    records = [run_child(name, args.frames, args.threads, args.timeout) for name in args.models]
    command = "python benchmarks/bench_models.py " + " ".join(sys.argv[1:])
    write_report(args.out, report(records, command.strip(), args.threads))
    seconds = [r["seconds"] for r in records if "seconds" in r]
    if seconds:
        print(f"median seconds per submap over {len(seconds)} models: {statistics.median(seconds):.1f}")


if __name__ == "__main__":
    main()
