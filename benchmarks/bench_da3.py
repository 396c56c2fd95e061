"""Depth Anything 3 at full size: bitwise parity with the authors' code, and the cost of a submap.

    python benchmarks/bench_da3.py --reference REF_CHECKOUT --parity [--sizes small base large giant]
    python benchmarks/bench_da3.py --reference REF_CHECKOUT --timing [--frames 17]
    python benchmarks/bench_da3.py --attention

``REF_CHECKOUT`` is a checkout of ByteDance-Seed/Depth-Anything-3 (its ``src/`` is imported by the
child processes, with the stand-ins of ``tests/fixtures/make_da3_fixtures.py`` for torchvision and
the exporters). Every measurement runs in its own child process (float32, CPU, ``--threads`` torch
threads, 2 by default):

* ``--parity``: the authors' network of each size built with their ``create_object`` (their random
  initialisation), every parameter then perturbed by seeded noise (0.02 N(0, 1)), and ours adopting
  the same tensors (``load_state_dict(assign=True)``: one copy of the weights); ``--parity-frames``
  random 640x480 frames (3: the reference view is chosen) through both preprocessings (compared),
  then both networks: camera decoder with the ray maps, the ray fit (same seed), and the camera
  encoder with known cameras. Each output: ``torch.equal`` and the largest absolute difference.
* ``--timing``: a ``--frames``-frame window of random 640x480 frames at the authors' resolution
  (504x378), forward only (the preprocessing excluded), ours (camera decoder, as the frontend) and
  the authors' ``DepthAnything3Net.forward`` (their default: camera decoder; their head also runs the
  ray branch), each size and implementation in its own process, one after the other. Seconds of the
  forward and the process's peak resident set size (``resource.getrusage(RUSAGE_SELF).ru_maxrss``,
  model construction included).
* ``--attention``: which ``scaled_dot_product_attention`` kernel the CPU runs for a global-attention
  layer of DA3-Small over a 17-frame window at 504x378 (16 541 tokens, 6 heads of 64), and the peak
  memory that call adds (the full attention table would be 6.6 GB).

Sections are written into ``benchmarks/results/da3.md`` (each run replaces its own section).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from harness import (REPO, date_text, max_rss_bytes, peak_rss_bytes, random_frames, replace_section, reset_peak_rss,
                     result_file, torch_machine)

RESULTS = result_file("da3")
FIXTURE_SCRIPT = REPO / "tests" / "fixtures" / "make_da3_fixtures.py"
SIZES = ("small", "base", "large", "giant")
RAY_SEED = 5
PERTURB_SEED = 3


# ------------------------------------------------------------------------------------ helpers
def _reference(checkout: Path):
    spec = importlib.util.spec_from_file_location("make_da3_fixtures", FIXTURE_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.import_reference(checkout)


def _compare(ours, theirs) -> dict:
    import torch

    return {"equal": bool(torch.equal(ours, theirs)),
            "max_abs_diff": float((ours.double() - theirs.double()).abs().max()) if ours.numel() else 0.0,
            "shape": list(ours.shape)}


def _known_cameras(frames: int):
    import torch

    generator = torch.Generator().manual_seed(11)
    angles = 0.2 * torch.randn(frames, generator=generator)
    extrinsics = torch.eye(4).repeat(1, frames, 1, 1)
    extrinsics[0, :, 0, 0], extrinsics[0, :, 0, 2] = angles.cos(), angles.sin()
    extrinsics[0, :, 2, 0], extrinsics[0, :, 2, 2] = -angles.sin(), angles.cos()
    extrinsics[0, :, :3, 3] = 0.3 * torch.randn(frames, 3, generator=generator)
    intrinsics = torch.tensor([[420.0, 0.0, 252.0], [0.0, 415.0, 189.0], [0.0, 0.0, 1.0]]).repeat(1, frames, 1, 1)
    return extrinsics, intrinsics


# --------------------------------------------------------------------------------- child: parity
def child_parity(size: str, checkout: Path, frames: int) -> dict:
    import torch

    from sl4slam.models.da3 import build_da3, load_state_dict_into, preprocess_images
    from sl4slam.models.da3.camera import normalize_extrinsics
    from sl4slam.models.da3.config import ARCHITECTURES
    from sl4slam.models.da3.rays import extrinsics_intrinsics_from_rays

    ref = _reference(checkout)
    started = time.perf_counter()
    theirs = ref.create_object(ref.load_config(ref.MODEL_REGISTRY[f"da3-{size}"])).eval()
    generator = torch.Generator().manual_seed(PERTURB_SEED)
    with torch.no_grad():
        for param in theirs.parameters():
            param.add_(0.02 * torch.randn(param.shape, generator=generator))
    ours = build_da3(ARCHITECTURES[size], device="meta")
    load_state_dict_into(ours, dict(theirs.state_dict()), assign=True)  # the same tensors: one copy
    ours.eval()
    shared = all(a.data_ptr() == b.data_ptr() for a, b in zip(ours.backbone.parameters(),
                                                                 theirs.backbone.parameters()))
    build_s = time.perf_counter() - started
    images = random_frames(frames, seed=1)
    theirs_images, _, _ = ref.InputProcessor()(images, None, None, 504, "upper_bound_resize", sequential=True)
    batch = preprocess_images(images)
    results = {"preprocess.images": _compare(batch.images, theirs_images)}
    x = batch.images[None]
    height, width = x.shape[-2:]
    captured: dict = {}
    hook = theirs.head.register_forward_hook(lambda m, a, out: captured.update({k: v.clone() for k, v in out.items()}))
    timings = {}
    with torch.no_grad():
        start = time.perf_counter()
        reference = theirs(x)
        timings["theirs"] = time.perf_counter() - start
        start = time.perf_counter()
        mine = ours(x, keep_rays=True)
        timings["ours"] = time.perf_counter() - start
        reference_view = int(mine["reference_view"][0])
        for key in ("depth", "depth_conf", "extrinsics", "intrinsics"):
            results[f"head.{key}"] = _compare(mine[key], reference[key])
        for key in ("ray", "ray_conf"):
            results[f"head.{key}"] = _compare(mine[key], captured[key])
        hook.remove()
        from addict import Dict

        torch.manual_seed(RAY_SEED)
        fitted = theirs._process_ray_pose_estimation(Dict(ray=captured["ray"], ray_conf=captured["ray_conf"]),
                                                     height, width)
        ray_ext, ray_int = extrinsics_intrinsics_from_rays(mine["ray"], mine["ray_conf"], (height, width),
                                                           torch.Generator().manual_seed(RAY_SEED))
        results["rays.extrinsics"] = _compare(ray_ext, fitted["extrinsics"])
        results["rays.intrinsics"] = _compare(ray_int, fitted["intrinsics"])
        extrinsics, intrinsics = _known_cameras(frames)
        theirs_poses = ref.api.DepthAnything3._normalize_extrinsics(None, extrinsics.clone())
        our_poses = normalize_extrinsics(extrinsics)
        results["cond.normalised_extrinsics"] = _compare(our_poses, theirs_poses)
        reference = theirs(x, theirs_poses, intrinsics)
        mine = ours(x, our_poses, intrinsics)
        for key in ("depth", "depth_conf", "extrinsics", "intrinsics"):
            results[f"cond.{key}"] = _compare(mine[key], reference[key])
    return {"size": size, "frames": frames, "image_hw": [height, width], "weights_shared": shared,
            "build_s": build_s, "forward_s": timings, "peak_rss_bytes": max_rss_bytes(), "results": results,
            "reference_view": reference_view}


# --------------------------------------------------------------------------------- child: timing
def child_timing(size: str, implementation: str, checkout: Path | None, frames: int) -> dict:
    import torch

    from sl4slam.models.da3 import build_da3, init_random_weights, preprocess_images
    from sl4slam.models.da3.config import ARCHITECTURES

    images = preprocess_images(random_frames(frames, seed=2)).images[None]
    started = time.perf_counter()
    if implementation == "ours":
        model = init_random_weights(build_da3(ARCHITECTURES[size], device="meta"), seed=0).eval()

        def forward():
            with torch.inference_mode():
                return model(images)
    else:
        ref = _reference(checkout)
        model = ref.create_object(ref.load_config(ref.MODEL_REGISTRY[f"da3-{size}"])).eval()

        def forward():
            with torch.inference_mode():
                return model(images)
    build_s = time.perf_counter() - started
    rss_built = max_rss_bytes()
    with torch.inference_mode():  # one tiny forward first: kernels and allocator warmed up
        model(images[:, :2, :, :56, :56])
    start = time.perf_counter()
    out = forward()
    seconds = time.perf_counter() - start
    assert torch.isfinite(out["depth"]).all()
    return {"size": size, "implementation": implementation, "frames": frames, "image_hw": list(images.shape[-2:]),
            "seconds": seconds, "build_s": build_s, "peak_rss_bytes": max_rss_bytes(),
            "peak_rss_after_build_bytes": rss_built, "load": os.getloadavg(),
            "parameters": sum(p.numel() for p in model.parameters())}


# ------------------------------------------------------------------------------ child: attention
def child_attention() -> dict:
    import torch
    import torch.nn.functional as F

    heads, tokens, dim = 6, 17 * (1 + 27 * 36), 64
    generator = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(1, heads, tokens, dim, generator=generator) for _ in range(3))
    choice = int(torch._fused_sdp_choice(q, k, v))
    names = {-1: "error", 0: "math", 1: "flash attention (CPU)", 2: "efficient attention", 3: "cudnn"}
    with torch.inference_mode():
        F.scaled_dot_product_attention(q[:, :, :64], k[:, :, :64], v[:, :, :64])
        reset_peak_rss()
        before = peak_rss_bytes(fallback=False)
        start = time.perf_counter()
        out = F.scaled_dot_product_attention(q, k, v)
        seconds = time.perf_counter() - start
        added = peak_rss_bytes(fallback=False) - before
    table = heads * tokens * tokens * 4
    return {"tokens": tokens, "heads": heads, "head_dim": dim, "kernel": names.get(choice, str(choice)),
            "seconds": seconds, "added_peak_bytes": added, "output_bytes": out.numel() * 4, "table_bytes": table}


# ---------------------------------------------------------------------------------------- parent
def run_child(args: list[str], threads: int, timeout: float) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    command = ["nice", "-n", "10", sys.executable, __file__, "--threads", str(threads), "--child", *args]
    print("$", " ".join(command[3:]), flush=True)
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=timeout)
    if done.returncode != 0:
        raise RuntimeError(f"child {args} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def machine() -> str:
    """The machine in one line (CPU, cores, memory, kernel, torch, Python)."""
    return torch_machine()


def _date() -> str:
    return date_text()


def _gib(value: float) -> str:
    return f"{value / 2**30:.2f}"


def parity_section(records: list[dict], command: str, threads: int) -> list[str]:
    lines = ["## Bitwise parity with the authors' code, full size", "",
             f"Date: {_date()}. Machine: {machine()}. {threads} threads, float32, CPU.",
             f"Command: `{command}`", "",
             "Random weights (the authors' initialisation, every parameter then perturbed by 0.02 N(0, 1), seeded), "
             "shared by both networks; random 640x480 frames through both preprocessings (504x378). `equal` is "
             "`torch.equal`; the difference is the largest absolute one.", "",
             "| size | output | shape | equal | max abs diff |", "|---|---|---|---|---|"]
    for record in records:
        for key, value in record["results"].items():
            lines.append(f"| {record['size']} | {key} | {'x'.join(map(str, value['shape']))} | "
                         f"{'yes' if value['equal'] else 'NO'} | {value['max_abs_diff']:.3g} |")
    lines += ["", "| size | frames | reference view chosen | weights shared | forward ours / theirs (s) | peak RSS (GiB) |",
              "|---|---|---|---|---|---|"]
    for record in records:
        lines.append(f"| {record['size']} | {record['frames']} | {record['reference_view']} | {record['weights_shared']} | "
                     f"{record['forward_s']['ours']:.1f} / {record['forward_s']['theirs']:.1f} | "
                     f"{_gib(record['peak_rss_bytes'])} |")
    return lines


def timing_section(records: list[dict], command: str, threads: int, frames: int) -> list[str]:
    lines = [f"## A {frames}-frame submap at 504x378, ours beside the authors' code", "",
             f"Date: {_date()}. Machine: {machine()}. {threads} threads (`OMP_NUM_THREADS`), float32, CPU, "
             "`nice -n 10`, one process at a time.",
             f"Command: `{command}`", "",
             "Forward only (preprocessing excluded), random weights, after one 2-frame 56x56 warm-up forward. "
             "Ours: camera decoder (the frontend's default path; the ray branch is not run). Theirs: "
             "`DepthAnything3Net.forward` in float32 (their default path, whose head also computes the ray "
             "branch; their API would run it under fp16 autocast on a CPU). Peak RSS: `ru_maxrss` of the "
             "process (model construction included; theirs holds the Giant's Gaussian head too).", "",
             "| size | parameters | ours (s) | theirs (s) | ours / theirs | ours peak RSS (GiB) | theirs peak RSS (GiB) | 1-min load at the end (ours, theirs) |",
             "|---|---|---|---|---|---|---|---|"]
    by_size: dict[str, list[dict]] = {}
    for record in records:
        by_size.setdefault(record["size"], []).append(record)
    for size, runs in by_size.items():
        ours = [r for r in runs if r["implementation"] == "ours"]
        theirs = [r for r in runs if r["implementation"] == "theirs"]
        for index in range(max(len(ours), len(theirs))):
            mine = ours[index] if index < len(ours) else None
            ref = theirs[index] if index < len(theirs) else None
            ratio = f"{mine['seconds'] / ref['seconds']:.2f}" if mine and ref else "-"
            load = ", ".join(f"{r['load'][0]:.1f}" for r in (mine, ref) if r)
            lines.append(f"| {size} | {(mine or ref)['parameters'] / 1e6:.1f} M | "
                         f"{mine['seconds'] if mine else float('nan'):.1f} | {ref['seconds'] if ref else float('nan'):.1f} | "
                         f"{ratio} | {_gib(mine['peak_rss_bytes']) if mine else '-'} | "
                         f"{_gib(ref['peak_rss_bytes']) if ref else '-'} | {load} |")
    return lines


def attention_section(record: dict, command: str) -> list[str]:
    return ["## Attention kernel on the CPU", "",
            f"Date: {_date()}. Machine: {machine()}.", f"Command: `{command}`", "",
            f"One global-attention call of DA3-Small's size over a 17-frame window at 504x378: {record['tokens']} tokens, "
            f"{record['heads']} heads of {record['head_dim']}. `scaled_dot_product_attention` (what both implementations "
            f"call) runs **{record['kernel']}** in float32 without gradients: {record['seconds']:.1f} s, and the call "
            f"raised the process's peak memory by {record['added_peak_bytes'] / 2**20:.0f} MiB (its output is "
            f"{record['output_bytes'] / 2**20:.0f} MiB), where the full attention table would take "
            f"{record['table_bytes'] / 2**30:.1f} GiB. The authors' attention therefore never holds the table on a "
            "CPU, and no second kernel is needed."]


def write_section(name: str, lines: list[str], path: Path) -> None:
    """Replace section ``name`` of ``path`` (kept between markers), keeping the others."""
    start, end = f"<!-- section:{name} -->", f"<!-- /section:{name} -->"
    replace_section(path, start, end, [start, *lines, end], ["# Depth Anything 3 benchmarks"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", type=Path, help="checkout of ByteDance-Seed/Depth-Anything-3")
    parser.add_argument("--parity", action="store_true")
    parser.add_argument("--timing", action="store_true")
    parser.add_argument("--attention", action="store_true")
    parser.add_argument("--sizes", nargs="*", default=list(SIZES), choices=SIZES)
    parser.add_argument("--frames", type=int, default=17, help="frames of the timed window")
    parser.add_argument("--parity-frames", type=int, default=3)
    parser.add_argument("--implementations", nargs="*", default=["ours", "theirs"])
    parser.add_argument("--repeats", type=int, default=1, help="timing: alternate ours / theirs this many times")
    parser.add_argument("--section", default="timing", help="timing: the results section to (re)write")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per child process")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--child", nargs="*", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        import torch

        torch.set_num_threads(args.threads)
        kind, *rest = args.child
        if kind == "parity":
            result = child_parity(rest[0], Path(rest[1]), int(rest[2]))
        elif kind == "timing":
            result = child_timing(rest[0], rest[1], Path(rest[2]) if rest[2] != "-" else None, int(rest[3]))
        else:
            result = child_attention()
        print(json.dumps(result))
        return
    command = "python benchmarks/bench_da3.py " + " ".join(sys.argv[1:])
    if (args.parity or args.timing) and args.reference is None:
        parser.error("--parity and --timing need --reference")
    if args.attention:
        write_section("attention", attention_section(run_child(["attention"], args.threads, args.timeout), command),
                      args.out)
    if args.parity:
        records = []
        for size in args.sizes:
            records.append(run_child(["parity", size, str(args.reference.resolve()), str(args.parity_frames)],
                                     args.threads, args.timeout))
            print(json.dumps(records[-1]), flush=True)
        write_section("parity", parity_section(records, command, args.threads), args.out)
    if args.timing:
        records = []
        for size in args.sizes:
            for _ in range(args.repeats):
                for implementation in args.implementations:
                    checkout = str(args.reference.resolve()) if implementation == "theirs" else "-"
                    records.append(run_child(["timing", size, implementation, checkout, str(args.frames)],
                                             args.threads, args.timeout))
                    print(json.dumps(records[-1]), flush=True)
        write_section(args.section, timing_section(records, command, args.threads, args.frames), args.out)


if __name__ == "__main__":
    main()
