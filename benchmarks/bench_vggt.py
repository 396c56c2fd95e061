"""VGGT-1B forward cost: time and peak memory per forward for S frames at 518x294.

Full-size model (aggregator + camera head + depth head, as the SLAM frontend runs it) with random
weights: the cost does not depend on the values. Every point runs in its own process so that its
peak memory is its own:

* CPU: float32; peak = the process's peak resident set size (weights included), and the resident
  size right after the weights are in place, against the weights' own size (one copy).
* CUDA: aggregator weights and compute in bf16 (fp16 where bf16 is unsupported) under autocast,
  heads in float32 as in the released model; peak = ``torch.cuda.max_memory_allocated`` during
  the forward (weights included). The VGGT authors' H100 table for the aggregator is printed
  beside it: 8 frames 0.11 s / 3.23 GB, 20 frames 0.31 s / 5.58 GB, 50 frames 1.04 s / 11.41 GB.

Also measured once (``--load-check``): process RSS after ``load_vggt`` of a full-size
``.safetensors`` checkpoint, to show that loading keeps one copy of the weights.

Usage: ``python benchmarks/bench_vggt.py [--device cpu|cuda] [--frames 1 2 4 8 17] [--repeats 3]
[--load-check]``. Writes ``benchmarks/results/vggt.md`` (a section per device).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "vggt.md"
HEIGHT, WIDTH = 294, 518
ANCHOR_H100 = {8: (0.11, 3.23), 20: (0.31, 5.58), 50: (1.04, 11.41)}  # frames: (s, GB), aggregator only
DATE = "2026-11-21"


def _rss_bytes() -> int:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def run_point(frames: int, device: str, repeats: int, warmup: int, seed: int) -> dict:
    """One measurement in this process (called in a fresh child process)."""
    import torch

    from sl4slam.frontend.vggt import resolve_compute_dtype
    from sl4slam.models.vggt.model import VGGT, VGGTModelConfig, init_random_weights

    torch.manual_seed(seed)
    config = VGGTModelConfig(enable_point=False)  # the frontend's heads: camera + depth
    with torch.device("meta"):
        model = VGGT(config)
    init_random_weights(model, seed=seed)
    model.eval()
    weight_bytes = sum(p.numel() * p.element_size() for p in model.parameters())
    rss_after_weights = _rss_bytes()
    dev = torch.device(device)
    dtype = resolve_compute_dtype("auto", dev)
    if dev.type == "cuda":
        model.to(dev)
        model.aggregator.to(dtype)
        weight_bytes = sum(p.numel() * p.element_size() for p in model.parameters())
    generator = torch.Generator().manual_seed(seed)
    images = torch.rand(frames, 3, HEIGHT, WIDTH, generator=generator).to(dev)

    def forward():
        with torch.inference_mode(), torch.autocast(dev.type, dtype=dtype, enabled=dtype != torch.float32):
            out = model(images, heads=("camera", "depth"))
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return out

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
        "times_s": times,
        "median_s": statistics.median(times),
        "peak_rss_bytes": _peak_rss_bytes(),
        "rss_after_weights_bytes": rss_after_weights,
        "weight_bytes": weight_bytes,
        "peak_gpu_bytes": peak_gpu,
        "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or "cpu",
        "dtype": str(dtype).replace("torch.", ""),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
    }


def load_check(seed: int) -> dict:
    """RSS after loading a full-size .safetensors checkpoint with load_vggt (child process)."""
    from sl4slam.models.vggt.weights import load_vggt

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "vggt_random.safetensors"
        # Written by a helper process so this one starts clean.
        subprocess.run(
            [sys.executable, __file__, "--write-checkpoint", str(path), "--seed", str(seed)], check=True
        )
        baseline = _rss_bytes()
        model = load_vggt(str(path))
        loaded = _rss_bytes()
        # Read every weight once, so pages of a memory-mapped file count in the resident size.
        checksum = sum(float(p.double().sum()) for p in model.parameters())
        weight_bytes = sum(p.numel() * p.element_size() for p in model.parameters())
        return {
            "file_bytes": path.stat().st_size,
            "weight_bytes": weight_bytes,
            "rss_before_bytes": baseline,
            "rss_after_load_bytes": loaded,
            "rss_after_bytes": _rss_bytes(),
            "checksum": checksum,
            "peak_rss_bytes": _peak_rss_bytes(),
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto")
    parser.add_argument("--frames", type=int, nargs="+", default=None, help="sequence lengths S")
    parser.add_argument("--repeats", type=int, default=3, help="timed forwards per point (median reported)")
    parser.add_argument("--single-above", type=int, default=4, help="on CPU, one timed forward and no warm-up above this S")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per point")
    parser.add_argument("--load-check", action="store_true", help="also measure RSS after loading a checkpoint file")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-repeats", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--child-warmup", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--child-load-check", action="store_true", help=argparse.SUPPRESS)
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
    if args.child is not None:
        print(json.dumps(run_point(args.child, device, args.child_repeats, args.child_warmup, args.seed)))
        return

    frames_list = args.frames or ([1, 2, 4, 8, 16, 20, 32, 50] if device == "cuda" else [1, 2, 4, 8, 16, 32])
    results = []
    for frames in frames_list:
        single = device == "cpu" and frames > args.single_above
        repeats, warmup = (1, 0) if single else (args.repeats, 1)
        child_args = ["--child", str(frames), "--device", device, "--child-repeats", str(repeats),
                      "--child-warmup", str(warmup), "--seed", str(args.seed)]
        result = _child(child_args, args.timeout)
        print(frames, result if isinstance(result, str) else f"{result['median_s']:.2f} s", flush=True)
        results.append((frames, repeats, result))
    load = _child(["--child-load-check", "--seed", str(args.seed)], args.timeout) if args.load_check else None
    write_report(Path(args.out), device, results, load, " ".join(sys.argv[1:]))


def write_report(path: Path, device: str, results: list, load, argv: str) -> None:
    gib = 1024**3
    ok = [r for _, _, r in results if isinstance(r, dict)]
    info = ok[0] if ok else {}
    if device == "cuda":
        machine = f"GPU {info.get('device_name', '?')}, torch {info.get('torch', '?')}"
    else:
        machine = f"{os.cpu_count()}-core CPU ({info.get('threads', '?')} torch threads), 24 GiB, no GPU; torch {info.get('torch', '?')}"
    lines = [
        f"## VGGT-1B forward, {device.upper()}",
        "",
        f"Machine: {machine}. Date: {DATE}.",
        f"Command: `python benchmarks/bench_vggt.py {argv}`".rstrip(),
        "",
        f"Whole frontend forward (aggregator + camera head + depth head, VGGT-1B sizes, random weights), "
        f"S frames at {WIDTH}x{HEIGHT}, compute dtype {info.get('dtype', '?')}; each point in a fresh process. "
        "Time: median of the timed forwards (after one warm-up forward when repeats > 1).",
        "",
    ]
    if device == "cuda":
        lines += ["| S | repeats | time (s) | peak GPU memory (GiB) | anchor time (s) | anchor mem (GB) | time / anchor | mem / anchor |",
                  "|---|---|---|---|---|---|---|---|"]
    else:
        lines += ["| S | repeats | time (s) | s / frame | peak RSS (GiB) | RSS after weights (GiB) | weights (GiB) |",
                  "|---|---|---|---|---|---|---|"]
    for frames, repeats, r in results:
        if isinstance(r, str):
            lines.append(f"| {frames} | {repeats} | {r} | | | | |")
            continue
        if device == "cuda":
            anchor = ANCHOR_H100.get(frames)
            peak_gb = r["peak_gpu_bytes"] / 1e9
            extra = (f"{anchor[0]} | {anchor[1]} | {r['median_s'] / anchor[0]:.2f} | {peak_gb / anchor[1]:.2f}"
                     if anchor else " | | | ")
            lines.append(f"| {frames} | {repeats} | {r['median_s']:.3f} | {r['peak_gpu_bytes'] / gib:.2f} | {extra} |")
        else:
            lines.append(
                f"| {frames} | {repeats} | {r['median_s']:.1f} | {r['median_s'] / frames:.1f} | {r['peak_rss_bytes'] / gib:.2f} "
                f"| {r['rss_after_weights_bytes'] / gib:.2f} | {r['weight_bytes'] / gib:.2f} |"
            )
    if device == "cuda":
        lines += ["", "Anchor: the VGGT authors' H100 table (aggregator only, GB = 1e9 bytes); "
                  "targets: time <= 1.2x and memory <= 1.0x at 8, 20 and 50 frames."]
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
    section = "\n".join(lines) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    existing = path.read_text() if path.is_file() else "# VGGT benchmarks\n"
    header = f"## VGGT-1B forward, {device.upper()}"
    if header in existing:  # replace this device's section, keep the others
        before, _, rest = existing.partition(header)
        after = rest[rest.find("\n## ") + 1:] if "\n## " in rest else ""
        existing = before.rstrip() + "\n\n" + after
    path.write_text(existing.rstrip() + "\n\n" + section)
    print(section)


if __name__ == "__main__":
    main()
