"""π³ / Pi3X at full size: parity with the authors' code, and the cost of a 17-frame submap on a CPU.

Random weights throughout (the cost of a forward does not depend on them; the parity does not
either, but random weights are perturbed so that no block is near the identity).

``--parity``: for each variant, the authors' full-size model (``pi3.models.pi3.Pi3`` /
``pi3x.Pi3X`` from ``--reference``, their initialisation plus seeded noise on every parameter)
and ours sharing its tensors (``load_state_dict(assign=True)``: one copy of the weights) run the
same ``--parity-frames`` frames at the native resolution (640x480 frames -> 574x434, float32, CPU):
theirs, ours with the reference kernel (bitwise equality of every output expected), ours with the
memory-efficient kernel (max / median absolute and relative differences reported). Pi3X runs
with known intrinsics (its ray condition, what the frontend gives it).

``--timing``: in fresh child processes (peak resident set size of the forward, the high-water
mark reset once the model is built; a watchdog kills a child above ``--memory-cap`` GiB):
``Pi3Frontend.reconstruct`` of ``--frames`` frames (640x480 -> 574x434) with our efficient kernel;
the authors' forward at ``--frames`` (their CPU float32 attention holds the whole attention table:
recorded as it fails) and at ``--ref-frames``; ours at ``--ref-frames`` beside it.

Usage (one variant or both; run with ``nice -n 10`` on a shared machine)::

    python benchmarks/bench_pi3.py --reference PATH/TO/Pi3 --parity
    python benchmarks/bench_pi3.py --reference PATH/TO/Pi3 --timing --frames 17 --ref-frames 4

Each mode rewrites its own section of ``benchmarks/results/pi3.md`` (``--out`` for another file).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

from harness import (cpu_model, cpu_seconds, date_text, memory_gib, peak_rss_bytes, replace_section, reset_peak_rss,
                     result_file, rss_bytes)

RESULTS = result_file("pi3")
GIB = 1024**3
FRAME_HW = (480, 640)
SEED = 7


# ---- helpers --------------------------------------------------------------------------------------

def synthetic_frames(count: int, seed: int = SEED):
    """``count`` 640x480 uint8 RGB frames of a smooth random pattern (a camera panning over it)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    height, width = FRAME_HW
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    phases = rng.uniform(0, 2 * np.pi, (3, 4))
    frames = []
    for i in range(count):
        shift = 9.0 * i
        channels = [127 + 60 * np.sin((x + shift) / (17 + 5 * c) + phases[c, 0]) + 50 * np.cos(y / (23 + 3 * c) + phases[c, 1])
                    for c in range(3)]
        image = np.stack(channels, -1) + rng.normal(0, 6, (height, width, 3))
        frames.append(np.clip(image, 0, 255).astype(np.uint8))
    return frames


def frame_intrinsics(count: int):
    import numpy as np

    K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])  # TUM-like, integer pixel centres
    return np.tile(K, (count, 1, 1))


def import_reference(checkout: str):
    sys.path.insert(0, str(Path(checkout).resolve()))
    import pi3.models.pi3 as pi3_module
    import pi3.models.pi3x as pi3x_module

    return pi3_module, pi3x_module


def perturb(model, seed: int) -> None:
    """Seeded noise on every parameter (LayerScales 0.05-0.1, norm scales 1 +- 0.02, the rest
    + N(0, 0.01^2)): no block is near the identity, no activation overflows."""
    import torch

    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, param in model.named_parameters():
            noise = torch.randn(param.shape, generator=generator)
            if name.endswith("gamma"):
                param.copy_(0.05 + 0.05 * noise.abs().clamp(max=1.0))
            elif param.ndim == 1 and "norm" in name and name.endswith("weight"):
                param.copy_(1.0 + 0.02 * noise)
            else:
                param.add_(0.01 * noise)


def machine() -> str:
    """The machine in one line (cores, CPU and its torch capability, memory, torch and its threads, Python)."""
    import torch

    return (f"{os.cpu_count()}-core {cpu_model()} ({torch.backends.cpu.get_cpu_capability()}), "
            f"{memory_gib():.0f} GiB RAM, torch {torch.__version__}, {torch.get_num_threads()} threads, Python {platform.python_version()}")


def today() -> str:
    return date_text("%Y-%m-%d %H:%M %Z")


# ---- parity ---------------------------------------------------------------------------------------

def parity_child(variant: str, reference: str, frames: int) -> dict:
    import numpy as np
    import torch

    from sl4slam.models.pi3 import Pi3Config, build_pi3, preprocess_images
    from sl4slam.models.pi3.cameras import to_model_intrinsics
    from sl4slam.models.pi3.weights import load_state_dict_into

    pi3_module, pi3x_module = import_reference(reference)
    torch.manual_seed(SEED)
    start = time.perf_counter()
    theirs = (pi3x_module.Pi3X() if variant == "pi3x" else pi3_module.Pi3()).eval()
    perturb(theirs, SEED + 1)
    ours = build_pi3(Pi3Config(variant=variant), device="meta").eval()
    load_state_dict_into(ours, theirs.state_dict(), assign=True)  # the same tensors: one copy
    build_s = time.perf_counter() - start
    images, _, transforms = preprocess_images(synthetic_frames(frames))
    kwargs_theirs, kwargs_ours = {}, {}
    if variant == "pi3x":
        K = np.stack([t.intrinsics_to_output(k) for t, k in zip(transforms, frame_intrinsics(frames))])
        K = torch.tensor(to_model_intrinsics(K), dtype=torch.float32)[None]
        kwargs_theirs, kwargs_ours = {"intrinsics": K}, {"intrinsics": K}
    rows = {}
    timings = {}
    with torch.no_grad():
        start = time.perf_counter()
        reference_out = theirs(images[None], **kwargs_theirs)
        timings["theirs"] = time.perf_counter() - start
        for kernel in ("reference", "efficient"):
            ours.set_attention_kernel(kernel)
            start = time.perf_counter()
            out = ours(images[None], **kwargs_ours)
            timings[kernel] = time.perf_counter() - start
            for key, expected in reference_out.items():
                value = out[key]
                diff = (value.double() - expected.double()).abs().flatten()
                scale = expected.double().abs().flatten()
                floor = 1e-2 * float(expected.double().pow(2).mean().sqrt()) + 1e-30
                relative = diff / scale.clamp(min=floor)
                rows.setdefault(key, {})[kernel] = {
                    "equal": bool(torch.equal(value, expected)),
                    "max_abs": float(diff.max()), "median_abs": float(diff.median()),
                    "max_rel": float(relative.max()), "median_rel": float(relative.median()),
                    "ref_max_abs": float(scale.max()), "finite": bool(torch.isfinite(expected).all()),
                }
    return {"variant": variant, "frames": frames, "hw": list(images.shape[-2:]), "rows": rows, "times_s": timings,
            "build_s": build_s, "peak_rss_bytes": peak_rss_bytes(fallback=False), "load": os.getloadavg()[0]}


def parity_section(results: list[dict], argv: str) -> list[str]:
    lines = ["<!-- parity -->", "## Parity with the authors' code, full size (CPU, float32)", "",
             f"Date: {today()}. Machine: {machine()}; load average {results[0]['load']:.1f} at the end.",
             f"Command: `nice -n 10 python benchmarks/bench_pi3.py {argv}`", "",
             "The authors' full-size model (their initialisation plus seeded noise on every parameter) and ours "
             "holding the same tensors; the same frames (640x480 synthetic frames resized by our preprocessing). "
             "Pi3X is given known intrinsics (its ray condition). `equal`: `torch.equal` of our output with "
             "theirs; differences of our memory-efficient kernel (flash attention) from theirs: absolute, and "
             "relative to max(|theirs|, 1e-2 rms(theirs)).", ""]
    for result in results:
        h, w = result["hw"]
        times = result["times_s"]
        lines += [f"### {result['variant']}: {result['frames']} frames at {w}x{h}", "",
                  f"Forward times: theirs {times['theirs']:.1f} s, ours (reference kernel) {times['reference']:.1f} s, "
                  f"ours (efficient kernel) {times['efficient']:.1f} s; peak RSS of the process "
                  f"{result['peak_rss_bytes'] / GIB:.2f} GiB (one copy of the weights, both models).", "",
                  "| output | reference kernel: bitwise equal | efficient: max abs | median abs | max rel | median rel | max abs of output |",
                  "|---|---|---|---|---|---|---|"]
        for key, row in result["rows"].items():
            ref, eff = row["reference"], row["efficient"]
            lines.append(f"| {key} | {'yes' if ref['equal'] else 'NO (max abs %.3g)' % ref['max_abs']} | "
                         f"{eff['max_abs']:.3g} | {eff['median_abs']:.3g} | {eff['max_rel']:.3g} | "
                         f"{eff['median_rel']:.3g} | {eff['ref_max_abs']:.3g} |")
        lines.append("")
    lines.append("<!-- /parity -->")
    return lines


# ---- timing ---------------------------------------------------------------------------------------


def random_frontend_model(variant: str, seed: int):
    """Full-size π³ / Pi3X with seeded random weights, as the frontend loads it (Pi3X: its intrinsics
    branch only), the image normalisation buffers restored."""
    import torch

    from sl4slam.models.pi3 import Pi3Config, build_pi3
    from sl4slam.models.pi3.model import IMAGE_MEAN, IMAGE_STD
    from sl4slam.models.random_weights import init_random_weights

    config = Pi3Config(variant=variant)
    if variant == "pi3x":
        config.depth_condition, config.pose_inject_blocks = False, 0
    model = init_random_weights(build_pi3(config, device="meta"), seed=seed).eval()
    with torch.no_grad():  # buffers are not parameters
        model.image_mean.copy_(torch.tensor(IMAGE_MEAN).view(1, 3, 1, 1))
        model.image_std.copy_(torch.tensor(IMAGE_STD).view(1, 3, 1, 1))
    return model

def timing_child(variant: str, who: str, frames: int, reference: str | None) -> dict:
    """One forward of ``frames`` frames: ``who`` = "ours" (the frontend's reconstruct, efficient
    kernel) or "theirs" (the authors' forward, float32 CPU)."""
    import torch

    from sl4slam.models.pi3 import preprocess_images

    torch.manual_seed(SEED)
    images_u8 = synthetic_frames(frames)
    start = time.perf_counter()
    if who == "ours":
        from sl4slam.frontend.pi3 import Pi3Frontend
        from sl4slam.types import Frame

        frontend = Pi3Frontend(variant, device="cpu", model=random_frontend_model(variant, SEED))
        frame_list = [Frame(index=i, timestamp=float(i), rgb=image) for i, image in enumerate(images_u8)]
        kwargs = {"intrinsics": frame_intrinsics(frames)} if variant == "pi3x" else {}
        weight_bytes = frontend.weight_bytes()
        build_s = time.perf_counter() - start
        reset = reset_peak_rss()
        start, cpu_start = time.perf_counter(), cpu_seconds()
        prediction = frontend.reconstruct(frame_list, 0, **kwargs)
        seconds, cpu_s = time.perf_counter() - start, cpu_seconds() - cpu_start
        from sl4slam.frontend.pi3 import estimate_peak_bytes

        h, w = prediction.depth.shape[1:]
        estimate = estimate_peak_bytes(frontend.model.config, frames, h, w, frontend.model.head_chunk_frames, weight_bytes)
        finite = bool(all(map(lambda a: __import__("numpy").isfinite(a).all(),
                              (prediction.depth, prediction.K, prediction.T_cam_submap))))
        extra = {"estimate_bytes": estimate, "finite": finite, "head_chunk": frontend.model.head_chunk_frames}
    else:
        pi3_module, pi3x_module = import_reference(reference)
        model = (pi3x_module.Pi3X() if variant == "pi3x" else pi3_module.Pi3()).eval()
        if variant == "pi3x":
            model.disable_multimodal()  # no conditions: as their example_mm.py does
        images, _, _ = preprocess_images(images_u8)
        weight_bytes = sum(p.numel() * p.element_size() for p in model.parameters())
        build_s = time.perf_counter() - start
        reset = reset_peak_rss()
        start, cpu_start = time.perf_counter(), cpu_seconds()
        with torch.no_grad():
            out = model(images[None])
        seconds, cpu_s = time.perf_counter() - start, cpu_seconds() - cpu_start
        h, w = images.shape[-2:]
        extra = {"finite": bool(torch.isfinite(out["local_points"]).all())}
    return {"variant": variant, "who": who, "frames": frames, "hw": [int(h), int(w)], "seconds": seconds,
            "cpu_s": cpu_s,
            "build_s": build_s, "peak_rss_bytes": peak_rss_bytes(fallback=False), "peak_is_forward": reset,
            "weight_bytes": weight_bytes, "threads": torch.get_num_threads(), "load": os.getloadavg()[0], **extra}


def run_child(args: list[str], cap_bytes: int, timeout: float) -> dict:
    """Run this script as a child; kill it when its RSS passes ``cap_bytes`` or time runs out."""
    command = [sys.executable, __file__, *args]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    state = {"peak": 0, "killed": None}

    def watch() -> None:
        start = time.time()
        while process.poll() is None:
            rss = rss_bytes(process.pid)
            state["peak"] = max(state["peak"], rss)
            if rss > cap_bytes:
                state["killed"] = f"killed at {rss / GIB:.1f} GiB resident (cap {cap_bytes / GIB:.0f} GiB)"
                process.kill()
                return
            if time.time() - start > timeout:
                state["killed"] = f"killed after {timeout:.0f} s"
                process.kill()
                return
            time.sleep(0.05)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    stdout, stderr = process.communicate()
    watcher.join()
    if process.returncode == 0:
        result = json.loads(stdout.strip().splitlines()[-1])
        result["watch_peak_bytes"] = state["peak"]
        return result
    reason = state["killed"] or (stderr.strip().splitlines()[-1] if stderr.strip() else f"exit code {process.returncode}")
    return {"failed": reason[:300], "watch_peak_bytes": state["peak"]}


def timing_section(results: list[dict], argv: str, cap_gib: float) -> list[str]:
    lines = ["<!-- timing -->", "## Cost of a submap on this CPU (float32)", "",
             f"Date: {today()}. Machine: {machine()}; shared with other jobs (load average in the table).",
             f"Command: `nice -n 10 python benchmarks/bench_pi3.py {argv}`", "",
             "One forward per row, each in a fresh process. Ours: `Pi3Frontend.reconstruct` (preprocessing, "
             "forward with the memory-efficient kernel, adapter; Pi3X given known intrinsics and holding only "
             "its intrinsics branch). Theirs: the authors' forward on the preprocessed frames (Pi3X without "
             "conditions, `disable_multimodal()`, as their example does). Wall seconds depend on the load "
             "(2 cores shared); CPU seconds (user + system, both threads) much less. Peak RSS: the process's "
             "high-water mark during the forward (weights included); a watchdog stops a process above "
             f"{cap_gib:g} GiB. Estimate: `sl4slam.frontend.pi3.estimate_peak_bytes` (what `max_memory_gb` plans with).",
             "",
             "| variant | code | frames | grid | wall s | CPU s | peak RSS (GiB) | weights (GiB) | estimate (GiB) | load | note |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in results:
        if "failed" in row:
            lines.append(f"| {row['variant']} | {row['who']} | {row['frames']} | | | | "
                         f">= {row['watch_peak_bytes'] / GIB:.2f} | | | | failed: {row['failed']} |")
            continue
        h, w = row["hw"]
        estimate = f"{row['estimate_bytes'] / GIB:.2f}" if "estimate_bytes" in row else ""
        cpu = f"{row['cpu_s']:.0f}" if "cpu_s" in row else ""
        note = "" if row.get("finite", True) else "non-finite outputs"
        lines.append(f"| {row['variant']} | {row['who']} | {row['frames']} | {w}x{h} | {row['seconds']:.0f} | {cpu} | "
                     f"{row['peak_rss_bytes'] / GIB:.2f} | {row['weight_bytes'] / GIB:.2f} | {estimate} | "
                     f"{row['load']:.1f} | {note} |")
    lines.append("<!-- /timing -->")
    return lines


# ---- report ---------------------------------------------------------------------------------------

def write_section(path: Path, tag: str, section: list[str]) -> None:
    """Replace the ``tag`` section of ``path`` (or append it), keeping the rest of the file."""
    header = ["# π³ / Pi3X benchmarks", "",
              "Our implementation (`sl4slam.models.pi3`) against the authors' (github.com/yyfz/Pi3), full size, "
              "random weights. Written by `benchmarks/bench_pi3.py`; each mode rewrites its own section.", ""]
    replace_section(path, f"<!-- {tag} -->", f"<!-- /{tag} -->", section, header)


def argv_of_log(lines: list[str]) -> str:
    """The command line recorded in an earlier run's report line (``Command: ...``), if any."""
    for line in lines:
        match = re.search(r"bench_pi3\.py (.+?)`", line)
        if match:
            return match.group(1)
    return "--timing"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--reference", required=False, help="checkout of github.com/yyfz/Pi3")
    parser.add_argument("--parity", action="store_true", help="bitwise parity and kernel differences at full size")
    parser.add_argument("--timing", action="store_true", help="time and peak memory of a submap")
    parser.add_argument("--variants", nargs="+", default=["pi3", "pi3x"])
    parser.add_argument("--parity-frames", type=int, default=2)
    parser.add_argument("--frames", type=int, default=17, help="submap size for --timing")
    parser.add_argument("--ref-frames", type=int, default=4, help="frames the authors' code is timed at")
    parser.add_argument("--skip-theirs-full", action="store_true", help="do not attempt the authors' code at --frames")
    parser.add_argument("--memory-cap", type=float, default=10.0, help="GiB; a child above it is killed")
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per child")
    parser.add_argument("--out", default=str(RESULTS))
    parser.add_argument("--child", choices=["parity", "timing"], help=argparse.SUPPRESS)
    parser.add_argument("--who", choices=["ours", "theirs"], help=argparse.SUPPRESS)
    parser.add_argument("--rewrite-from", help="rewrite the timing section from the JSON lines of an earlier run's output")
    args = parser.parse_args()

    if args.child == "parity":
        print(json.dumps(parity_child(args.variants[0], args.reference, args.parity_frames)))
        return
    if args.child == "timing":
        print(json.dumps(timing_child(args.variants[0], args.who, args.frames, args.reference)))
        return
    if args.rewrite_from:
        lines = Path(args.rewrite_from).read_text().splitlines()
        results = [json.loads(line) for line in lines if line.startswith("{") and '"who"' in line]
        write_section(Path(args.out), "timing", timing_section(results, argv_of_log(lines), args.memory_cap))
        return
    if not (args.parity or args.timing):
        parser.error("pick --parity and/or --timing")
    if not args.reference:
        parser.error("--reference (a checkout of github.com/yyfz/Pi3) is needed")
    argv = " ".join(sys.argv[1:])
    cap = int(args.memory_cap * GIB)
    common = ["--reference", args.reference]
    if args.parity:
        results = []
        for variant in args.variants:
            result = run_child(["--child", "parity", "--variants", variant, "--parity-frames", str(args.parity_frames),
                                *common], cap, args.timeout)
            if "failed" in result:
                raise SystemExit(f"parity run of {variant} failed: {result['failed']}")
            results.append(result)
            print(json.dumps(result), flush=True)
        write_section(Path(args.out), "parity", parity_section(results, argv))
    if args.timing:
        plan = []
        for variant in args.variants:
            plan.append((variant, "ours", args.frames))
            if not args.skip_theirs_full and variant == "pi3":
                plan.append((variant, "theirs", args.frames))
            plan += [(variant, "theirs", args.ref_frames), (variant, "ours", args.ref_frames)]
        results = []
        for variant, who, frames in plan:
            result = run_child(["--child", "timing", "--variants", variant, "--who", who, "--frames", str(frames),
                                *common], cap, args.timeout)
            result.update({"variant": variant, "who": who, "frames": frames})
            results.append(result)
            print(json.dumps(result), flush=True)
        write_section(Path(args.out), "timing", timing_section(results, argv, args.memory_cap))


if __name__ == "__main__":
    main()
