"""VGGT-1B forward cost: time and peak memory per forward for S frames at 518x294, per precision mode.

Full-size model (aggregator + camera head + depth head, as the SLAM frontend runs it) with random
weights: the cost does not depend on the values. Every point runs in its own process so that its
peak memory is its own:

* CPU: peak = the process's peak resident set size during the forward (the high-water mark is
  reset once the model is built), beside the resident size after the weights and the weights'
  own size.
* CUDA: peak = ``torch.cuda.max_memory_allocated`` during the forward (weights included), beside
  the VGGT authors' H100 table for the aggregator (1/8/20/50/100 frames: 0.04/0.11/0.31/1.04/3.12 s,
  1.88/3.23/5.58/11.41/21.15 GB).

Each point also prints ``sl4slam.models.vggt.memory.estimate_peak_bytes``, what ``--max-memory``
plans with. ``--dtypes`` picks the precision modes (fp32, bf16, fp16, int8; default the device's
"auto"); ``--head-chunk`` the frames the dense heads decode at once.

``--compare`` (CPU): every mode of ``--dtypes`` built from the same float32 weights in one process,
forwards interleaved, time ratios to fp32 and the max / median relative errors of depth,
confidence and pose encoding against fp32. ``--frontend-submaps N``: per-submap wall time of
``VGGTFrontend.reconstruct`` on ``--frames[0]`` random 640x480 frames. ``--load-check``: process
RSS after ``load_vggt`` of a full-size ``.safetensors`` checkpoint (one copy of the weights).

Usage: ``python benchmarks/bench_vggt.py [--device cpu|cuda] [--frames 1 4 8 16 32] [--dtypes fp32 int8]
[--repeats 3] [--head-chunk 8] [--compare] [--frontend-submaps 5] [--load-check]``. Writes a section per
device and mode set into ``benchmarks/results/vggt.md`` (``--out`` for another file).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from harness import peak_rss_bytes, replace_heading, reset_peak_rss, result_file, rss_bytes

RESULTS = result_file("vggt")
HEIGHT, WIDTH = 294, 518
ANCHOR_H100 = {1: (0.04, 1.88), 8: (0.11, 3.23), 20: (0.31, 5.58), 50: (1.04, 11.41), 100: (3.12, 21.15)}  # frames: (s, GB), aggregator only
DATE = "2026-11-23"
HEAD_CHUNK = 8  # the dense heads' default chunk (frames decoded at once)


def _random_model(seed: int, heads: tuple[str, ...] = ("camera", "depth")):
    """Full-size VGGT with seeded random weights and only ``heads`` (float32, CPU)."""
    from sl4slam.models.vggt.model import VGGT, VGGTModelConfig, init_random_weights

    import torch

    config = VGGTModelConfig(enable_point="point" in heads)
    with torch.device("meta"):
        model = VGGT(config)
    init_random_weights(model, seed=seed)
    return model.eval()


def run_point(frames: int, device: str, repeats: int, warmup: int, seed: int, mode: str = "auto",
              height: int = HEIGHT, width: int = WIDTH) -> dict:
    """One measurement in this process (called in a fresh child process)."""
    import torch

    from sl4slam.models.vggt.memory import estimate_peak_bytes
    from sl4slam.models.vggt.precision import apply_precision, resolve_precision

    torch.manual_seed(seed)
    model = _random_model(seed)
    dev = torch.device(device)
    precision = resolve_precision(mode, dev)
    apply_precision(model, precision).to(dev)
    model.set_head_chunk_frames(HEAD_CHUNK)
    weight_bytes = sum(p.numel() * p.element_size() for p in model.parameters()) + sum(
        b.numel() * b.element_size() for b in model.buffers())
    if precision.mode == "int8":  # packed int8 weights are not parameters
        weight_bytes = estimate_weights(model.config, precision)
    rss_after_weights = rss_bytes()
    generator = torch.Generator().manual_seed(seed)
    images = torch.rand(frames, 3, height, width, generator=generator).to(dev)
    autocast = precision.autocast

    def forward():
        with torch.inference_mode(), torch.autocast(dev.type, dtype=autocast or torch.float32, enabled=autocast is not None):
            out = model(images, heads=("camera", "depth"))
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return out

    build_peak = peak_rss_bytes()
    reset = reset_peak_rss()
    for _ in range(warmup):
        forward()
    times = []
    peak_gpu = 0
    for _ in range(repeats):
        if dev.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        out = forward()
        times.append(time.perf_counter() - start)
        if dev.type == "cuda":
            peak_gpu = max(peak_gpu, torch.cuda.max_memory_allocated())
        assert torch.isfinite(out["depth"]).all()
        del out
    return {
        "frames": frames,
        "mode": precision.mode,
        "times_s": times,
        "median_s": statistics.median(times),
        "peak_rss_bytes": peak_rss_bytes(),
        "peak_rss_is_forward": reset,
        "build_peak_rss_bytes": build_peak,
        "head_chunk": HEAD_CHUNK,
        "rss_after_weights_bytes": rss_after_weights,
        "weight_bytes": weight_bytes,
        "estimate_bytes": estimate_peak_bytes(model.config, precision, frames, height, width, HEAD_CHUNK, dev.type),
        "peak_gpu_bytes": peak_gpu,
        "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or "cpu",
        "dtype": precision.mode,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "load": os.getloadavg()[0],
    }


def estimate_weights(config, precision) -> int:
    from sl4slam.models.vggt.memory import weight_bytes

    return weight_bytes(config, precision)


def compare_modes(frames_list: list[int], modes: list[str], repeats: int, seed: int, slow_modes: set[str]) -> list[dict]:
    """Time and error of each precision mode against float32, side by side in this process.

    Models of every mode are built from the same random weights; for each S the forwards are
    interleaved (fp32, mode 1, mode 2, fp32, ...) so load changes hit every mode alike. Modes in
    ``slow_modes`` run once, at S = 1 only.
    """
    import copy

    import torch

    from sl4slam.models.vggt.precision import apply_precision, relative_errors, resolve_precision

    base = _random_model(seed)
    cpu = torch.device("cpu")
    models = {"fp32": base}
    for mode in modes:
        if mode != "fp32":
            models[mode] = apply_precision(copy.deepcopy(base), resolve_precision(mode, cpu))
    rows = []
    for frames in frames_list:
        images = torch.rand(frames, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(seed + frames))
        times: dict[str, list[float]] = {m: [] for m in models}
        outputs: dict[str, dict] = {}
        loads = []
        for rep in range(repeats):
            for mode, model in models.items():
                if mode in slow_modes and (rep > 0 or frames > 1):
                    continue
                precision = resolve_precision(mode, cpu)
                autocast = precision.autocast
                start = time.perf_counter()
                with torch.inference_mode(), torch.autocast("cpu", dtype=autocast or torch.float32, enabled=autocast is not None):
                    out = model(images, heads=("camera", "depth"))
                times[mode].append(time.perf_counter() - start)
                loads.append(os.getloadavg()[0])
                outputs[mode] = {k: out[k].float() for k in ("depth", "depth_conf", "pose_enc")}
                print(f"S={frames} {mode} {times[mode][-1]:.1f} s (load {loads[-1]:.1f})", flush=True)
        fp32_time = statistics.median(times["fp32"])
        for mode in [m for m in models if times[m]]:
            row = {"frames": frames, "mode": mode, "times_s": times[mode], "median_s": statistics.median(times[mode]),
                   "ratio": statistics.median(times[mode]) / fp32_time, "load_min": min(loads), "load_max": max(loads)}
            for key in ("depth", "depth_conf", "pose_enc"):
                row[key] = relative_errors(outputs[mode][key], outputs["fp32"][key])
            rows.append(row)
    return rows


def load_check(seed: int) -> dict:
    """RSS after loading a full-size .safetensors checkpoint with load_vggt (child process)."""
    from sl4slam.models.vggt.weights import load_vggt

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "vggt_random.safetensors"
        # Written by a helper process so this one starts clean.
        subprocess.run(
            [sys.executable, __file__, "--write-checkpoint", str(path), "--seed", str(seed)], check=True
        )
        baseline = rss_bytes()
        model = load_vggt(str(path))
        loaded = rss_bytes()
        # Read every weight once, so pages of a memory-mapped file count in the resident size.
        checksum = sum(float(p.double().sum()) for p in model.parameters())
        weight_bytes = sum(p.numel() * p.element_size() for p in model.parameters())
        return {
            "file_bytes": path.stat().st_size,
            "weight_bytes": weight_bytes,
            "rss_before_bytes": baseline,
            "rss_after_load_bytes": loaded,
            "rss_after_bytes": rss_bytes(),
            "checksum": checksum,
            "peak_rss_bytes": peak_rss_bytes(),
        }


def write_checkpoint(path: str, seed: int) -> None:
    import torch

    from sl4slam.models.vggt.model import VGGT, init_random_weights
    from sl4slam.models.vggt.weights import save_checkpoint

    with torch.device("meta"):
        model = VGGT()
    init_random_weights(model, seed=seed)
    save_checkpoint(model.state_dict(), path, model.config)


def _child(args: list[str], timeout: float) -> dict | str:
    try:
        proc = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"not finished within {timeout:.0f} s"
    if proc.returncode != 0:
        return f"failed (exit {proc.returncode}): {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else ''}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


def frontend_submaps(frames: int, submaps: int, seed: int) -> dict:
    """Per-submap wall time of the VGGT frontend (preprocessing, transfer, forward, decoding) on
    synthetic 640x480 frames resized to 518 px, with the default dtype of the device."""
    import numpy as np
    import torch

    from sl4slam.config import ModelConfig
    from sl4slam.frontend.vggt import VGGTFrontend
    from sl4slam.types import Frame

    device = "cuda" if torch.cuda.is_available() else "cpu"
    frontend = VGGTFrontend(ModelConfig(dtype="fp32"), model=_random_model(seed), device=device)
    rng = np.random.default_rng(seed)
    times = []
    for submap in range(submaps + 1):  # the first is a warm-up
        batch = [Frame(index=i, timestamp=float(i), rgb=rng.integers(0, 256, (480, 640, 3), dtype=np.uint8))
                 for i in range(frames)]
        if frontend.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        prediction = frontend.reconstruct(batch, submap_id=submap)
        times.append(time.perf_counter() - start)
        assert np.isfinite(prediction.depth).all()
    peak = torch.cuda.max_memory_allocated() if frontend.device.type == "cuda" else peak_rss_bytes()
    return {"frames": frames, "grid": list(prediction.depth.shape[1:]), "times_s": times[1:],
            "median_s": statistics.median(times[1:]), "peak_bytes": peak, "mode": frontend.precision.mode,
            "device": frontend.device.type}


def main() -> None:
    global HEAD_CHUNK
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--frames", type=int, nargs="+", default=None, help="sequence lengths S")
    parser.add_argument("--dtypes", nargs="+", default=None,
                        help="precision modes (fp32 bf16 fp16 int8 auto); default: the device's auto")
    parser.add_argument("--repeats", type=int, default=3, help="timed forwards per point (median reported)")
    parser.add_argument("--single-above", type=int, default=4, help="on CPU, one timed forward and no warm-up above this S")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per point")
    parser.add_argument("--load-check", action="store_true", help="also measure RSS after loading a checkpoint file")
    parser.add_argument("--compare", action="store_true",
                        help="CPU: time and error of --dtypes against fp32, side by side in one process")
    parser.add_argument("--compare-once", nargs="*", default=[], help="modes timed once and at S = 1 only in --compare (slow ones)")
    parser.add_argument("--frontend-submaps", type=int, default=0,
                        help="also time this many submaps of --frames[0] frames through the VGGT frontend")
    parser.add_argument("--head-chunk", type=int, default=HEAD_CHUNK, help="frames the dense heads decode at once")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-mode", default="auto", help=argparse.SUPPRESS)
    parser.add_argument("--child-repeats", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--child-warmup", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--child-load-check", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--child-frontend", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--write-checkpoint", help=argparse.SUPPRESS)
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args()

    if args.write_checkpoint:
        write_checkpoint(args.write_checkpoint, args.seed)
        return
    if args.child_load_check:
        print(json.dumps(load_check(args.seed)))
        return
    import torch

    device = ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    HEAD_CHUNK = args.head_chunk
    if args.child_frontend is not None:
        print(json.dumps(frontend_submaps(args.child, args.child_frontend, args.seed)))
        return
    if args.child is not None:
        print(json.dumps(run_point(args.child, device, args.child_repeats, args.child_warmup, args.seed, args.child_mode)))
        return
    argv = " ".join(sys.argv[1:])
    if args.compare:
        frames_list = args.frames or [1, 4]
        modes = args.dtypes or ["fp32", "int8"]
        rows = compare_modes(frames_list, modes, args.repeats, args.seed, set(args.compare_once))
        write_compare_report(Path(args.out), rows, argv)
        return

    frames_list = args.frames or ([1, 8, 16, 20, 32, 64] if device == "cuda" else [1, 2, 4, 8, 16, 32])
    modes = args.dtypes or ["auto"]
    results = []
    for mode in modes:
        for frames in frames_list:
            single = device == "cpu" and frames > args.single_above
            repeats, warmup = (1, 0) if single else (args.repeats, 1)
            child_args = ["--child", str(frames), "--device", device, "--child-repeats", str(repeats),
                          "--child-warmup", str(warmup), "--seed", str(args.seed), "--child-mode", mode,
                          "--head-chunk", str(args.head_chunk)]
            result = _child(child_args, args.timeout)
            print(mode, frames, result if isinstance(result, str) else
                  f"{result['median_s']:.2f} s, peak RSS {result['peak_rss_bytes'] / 2**30:.2f} GiB, "
                  f"GPU {result['peak_gpu_bytes'] / 2**30:.2f} GiB, estimate {result['estimate_bytes'] / 2**30:.2f} GiB",
                  flush=True)
            results.append((frames, repeats, result))
    load = _child(["--child-load-check", "--seed", str(args.seed)], args.timeout) if args.load_check else None
    frontend = None
    if args.frontend_submaps:
        frontend = _child(["--child", str(frames_list[0]), "--child-frontend", str(args.frontend_submaps),
                           "--device", device, "--seed", str(args.seed)], args.timeout)
        print("frontend", frontend, flush=True)
    write_report(Path(args.out), device, results, load, argv, frontend)


def write_section(path: Path, header: str, lines: list[str]) -> None:
    """Replace (or append) the section ``header`` of the results file ``path``."""
    replace_heading(path, header, lines, ["# VGGT benchmarks"])


def write_compare_report(path: Path, rows: list[dict], argv: str) -> None:
    import torch

    lines = [
        f"Machine: {os.cpu_count()}-core CPU ({torch.get_num_threads()} torch threads), shared; torch {torch.__version__}. "
        f"Date: {DATE}.",
        f"Command: `python benchmarks/bench_vggt.py {argv}`",
        "",
        f"Full-size VGGT-1B with random weights (seeded; every mode made from the same float32 weights), aggregator + "
        f"camera head + depth head, S frames at {WIDTH}x{HEIGHT}. All modes in one process, forwards interleaved "
        "(fp32, then each mode, repeated); time = median; ratio = median / fp32 median of the same S. Errors against "
        "the fp32 outputs of the same images: |d| / max(|ref|, 0.01 rms(ref)), max and median over all elements "
        "(depth and confidence are positive, so this is their plain relative error; pose encoding: translation, "
        "quaternion, field of view).",
        "",
        "| S | mode | runs | time (s) | / fp32 | depth max | depth median | conf max | conf median | pose max | pose median | load avg |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['frames']} | {r['mode']} | {len(r['times_s'])} | {r['median_s']:.1f} | {r['ratio']:.2f} | "
            f"{r['depth'][0]:.2e} | {r['depth'][1]:.2e} | {r['depth_conf'][0]:.2e} | {r['depth_conf'][1]:.2e} | "
            f"{r['pose_enc'][0]:.2e} | {r['pose_enc'][1]:.2e} | {r['load_min']:.1f}-{r['load_max']:.1f} |"
        )
    write_section(path, "## VGGT-1B precision modes, CPU", lines)


def write_report(path: Path, device: str, results: list, load, argv: str, frontend=None) -> None:
    gib = 1024**3
    ok = [r for _, _, r in results if isinstance(r, dict)]
    info = ok[0] if ok else {}
    if device == "cuda":
        machine = f"GPU {info.get('device_name', '?')}, torch {info.get('torch', '?')}"
    else:
        machine = (f"{os.cpu_count()}-core CPU ({info.get('threads', '?')} torch threads), "
                   f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / gib:.0f} GiB; torch {info.get('torch', '?')}")
    lines = [
        f"Machine: {machine}. Date: {DATE}.",
        f"Command: `python benchmarks/bench_vggt.py {argv}`",
        "",
        "Whole frontend forward (aggregator + camera head + depth head, VGGT-1B sizes, random weights, dense "
        f"heads {HEAD_CHUNK} frames at a time), S frames at {WIDTH}x{HEIGHT}; each point in a fresh process. "
        "Time: median of the timed forwards (after one warm-up forward when repeats > 1). Peak RSS: the "
        "forward's (the high-water mark is reset after the model is built, so it excludes building the model, "
        "which in int8 and bf16 starts from float32 weights here). Estimate: "
        "`sl4slam.models.vggt.memory.estimate_peak_bytes` (what --max-memory plans with).",
        "",
    ]
    if device == "cuda":
        lines += ["| mode | S | repeats | time (s) | peak GPU memory (GB) | estimate (GB) | authors' time (s) | authors' mem (GB) "
                  "| time / authors' | mem / authors' |", "|---|---|---|---|---|---|---|---|---|---|"]
    else:
        lines += ["| mode | S | repeats | time (s) | peak RSS (GiB) | estimate (GiB) | RSS after weights (GiB) | weights (GiB) "
                  "| load avg |", "|---|---|---|---|---|---|---|---|---|"]
    for frames, repeats, r in results:
        if isinstance(r, str):
            lines.append(f"| | {frames} | {repeats} | {r} | | | | | |")
            continue
        if device == "cuda":
            anchor = ANCHOR_H100.get(frames)
            peak_gb = r["peak_gpu_bytes"] / 1e9
            extra = (f"{anchor[0]} | {anchor[1]} | {r['median_s'] / anchor[0]:.2f} | {peak_gb / anchor[1]:.2f}"
                     if anchor else " | | | ")
            lines.append(f"| {r['mode']} | {frames} | {repeats} | {r['median_s']:.3f} | {peak_gb:.2f} "
                         f"| {r['estimate_bytes'] / 1e9:.2f} | {extra} |")
        else:
            lines.append(
                f"| {r['mode']} | {frames} | {repeats} | {r['median_s']:.1f} | {r['peak_rss_bytes'] / gib:.2f} "
                f"| {r['estimate_bytes'] / gib:.2f} | {r['rss_after_weights_bytes'] / gib:.2f} | {r['weight_bytes'] / gib:.2f} "
                f"| {r['load']:.1f} |"
            )
    if device == "cuda":
        lines += ["", "Authors' figures: the VGGT README's H100 table (1/8/20/50/100 frames; the aggregator only, "
                  "GB = 1e9 bytes, flash attention 3). Ours include the camera and depth heads and the weights "
                  "(peak = `torch.cuda.max_memory_allocated`, also GB = 1e9 bytes here). "
                  "Targets: time <= 1.2x and memory <= 1.0x at 8 and 20 frames."]
    if load is not None:
        lines.append("")
        if isinstance(load, str):
            lines.append(f"Checkpoint load check: {load}.")
        else:
            lines.append(
                f"Checkpoint load check: `load_vggt` of a {load['file_bytes'] / gib:.2f} GiB .safetensors file "
                f"({load['weight_bytes'] / gib:.2f} GiB of parameters) took the process RSS from "
                f"{load['rss_before_bytes'] / gib:.2f} GiB to {load['rss_after_load_bytes'] / gib:.2f} GiB right after loading "
                f"(the file is memory-mapped) and to {load['rss_after_bytes'] / gib:.2f} GiB after reading every weight "
                f"(peak {load['peak_rss_bytes'] / gib:.2f} GiB): the weights are held once."
            )
    if isinstance(frontend, dict):
        lines += ["", f"Frontend per submap ({frontend['device']}, {frontend['mode']}): `VGGTFrontend.reconstruct` of "
                  f"{frontend['frames']} random 640x480 frames (grid {frontend['grid'][1]}x{frontend['grid'][0]}: "
                  f"preprocessing, transfer, forward, decoding to numpy), median of {len(frontend['times_s'])} submaps "
                  f"after one warm-up: {frontend['median_s']:.3f} s; peak {frontend['peak_bytes'] / 1e9:.2f} GB."]
    elif frontend is not None:
        lines += ["", f"Frontend per submap: {frontend}."]
    modes = "/".join(sorted({r["mode"] for r in ok})) or "?"
    write_section(path, f"## VGGT-1B forward, {device.upper()}, {modes}", lines)


if __name__ == "__main__":
    main()
