"""Whole ``sl4slam`` runs on a GPU, measured: frames per second, time per submap by stage, memory.

Two steps, because the GPU machine has no package index:

    python benchmarks/bench_gpu_run.py prepare            # here: GTSAM and evo, TUM fr1/desk -> .gpu/
    python benchmarks/bench_gpu_run.py run --out DIR      # there: installs from .gpu/, runs, reports

``prepare`` (on a machine with PyPI and the project's data folder ``../shared``) fetches what the GPU
machine's Python (3.12, x86-64, with torch, numpy, scipy, OpenCV and matplotlib of its own) lacks:
GTSAM and evo, as one zip of their packages (GTSAM's example data and its unstable module left
out), and copies TUM RGB-D fr1/desk into the working tree (its RGB frames as JPEG, quality 85, so
the tree stays within what travels to the GPU machine: 64 MiB). ``.gpu/`` is excluded from git.

``run`` unpacks the zip into ``/tmp/sl4slam-site``, makes VGGT-1B with random weights (full size,
bf16: the cost of a forward does not depend on the values) and runs in a fresh process each:

- TUM fr1/desk, VGGT bf16, the model overlapping the graph work (the default) and sequential, side
  by side; with ``--all-frames`` as well;
- the synthetic world (600 frames at 640x480), VGGT bf16, overlapped.

Each run reports input frames and keyframes per second over the whole run and over its last tenth
(does it slow down as the map grows?), the median seconds per submap of every stage, the latency
from a keyframe's arrival to its pose (when its submap's graph work ends), GPU peak memory
(``torch.cuda.max_memory_allocated``) and host peak RSS. Without a GPU it ends with one line.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
STAGE_DIR = REPO / ".gpu"
SITE = Path("/tmp/sl4slam-site")
WHEELS = {"gtsam": "gtsam==4.3.0", "evo": "evo==1.38.1"}
GPU_PYTHON = "3.12"
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64")
TRAVEL_LIMIT = 64 * 2**20
VGGT_SOTA_FPS = 8.4  # VGGT-SLAM 2.0's published speed on an RTX 3090, w = 16 (a different GPU)


# ------------------------------------------------------------------------------------------ prepare
def prepare(shared: Path, quality: int) -> None:
    """Stage the packages and the sequence in ``.gpu/`` (run where PyPI and ``../shared`` are)."""
    import cv2

    STAGE_DIR.mkdir(exist_ok=True)
    exclude = REPO / ".git" / "info" / "exclude"
    if exclude.parent.is_dir() and "/.gpu/" not in (exclude.read_text() if exclude.is_file() else ""):
        with open(exclude, "a") as handle:
            handle.write("/.gpu/\n")
    downloads = STAGE_DIR / "downloads"
    downloads.mkdir(exist_ok=True)
    for requirement in WHEELS.values():
        command = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
                   "--python-version", GPU_PYTHON, "--implementation", "cp", "-d", str(downloads), requirement]
        for tag in PLATFORMS:
            command += ["--platform", tag]
        subprocess.run(command, check=True)
    with zipfile.ZipFile(STAGE_DIR / "site.zip", "w", zipfile.ZIP_DEFLATED, compresslevel=9) as site:
        for wheel in sorted(downloads.glob("*.whl")):
            with zipfile.ZipFile(wheel) as source:
                for name in source.namelist():
                    if name.startswith(("gtsam/Data/", "gtsam_unstable", "gtsam.libs/libgtsam_unstable")):
                        continue  # example data and the unstable module: nothing of ours reads them
                    site.writestr(name, source.read(name))
    sequence = shared / "data" / "tum_rgbd_fr1_desk"
    target = STAGE_DIR / "tum_rgbd_fr1_desk"
    (target / "rgb").mkdir(parents=True, exist_ok=True)
    lines = []
    for line in (sequence / "rgb.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            lines.append(line)
            continue
        stamp, name = line.split()[:2]
        jpeg = Path(name).with_suffix(".jpg")
        if not (target / jpeg).is_file():
            cv2.imwrite(str(target / jpeg), cv2.imread(str(sequence / name)), [cv2.IMWRITE_JPEG_QUALITY, quality])
        lines.append(f"{stamp} {jpeg}")
    (target / "rgb.txt").write_text("\n".join(lines) + "\n")
    shutil.copyfile(sequence / "groundtruth.txt", target / "groundtruth.txt")
    shutil.rmtree(downloads)
    staged = sum(p.stat().st_size for p in STAGE_DIR.rglob("*") if p.is_file())
    tracked = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=REPO, capture_output=True,
                             check=True).stdout.decode().split("\0")
    tree = sum((REPO / f).stat().st_size for f in tracked if f and (REPO / f).is_file())
    print(f"staged {staged / 2**20:.1f} MiB in {STAGE_DIR} (packages {(STAGE_DIR / 'site.zip').stat().st_size / 2**20:.1f} MiB); "
          f"with the working tree {(staged + tree) / 2**20:.1f} MiB of the {TRAVEL_LIMIT / 2**20:.0f} MiB that travel")
    if staged + tree > TRAVEL_LIMIT:
        raise SystemExit("bench_gpu_run: too large to travel; lower --jpeg-quality")


# ------------------------------------------------------------------------------------------ run
def require_gpu() -> None:
    """One line and exit status 2 where there is no CUDA GPU."""
    try:
        import torch
    except ImportError:
        raise SystemExit("bench_gpu_run: torch is not installed; run this on the GPU machine") from None
    if not torch.cuda.is_available():
        print("bench_gpu_run: no CUDA GPU on this machine; run `prepare` here and `run` on a GPU machine",
              file=sys.stderr)
        raise SystemExit(2)


def install_site() -> None:
    """Unpack the staged packages where this process (and the runs it starts) import them."""
    if not (STAGE_DIR / "site.zip").is_file():
        raise SystemExit(f"bench_gpu_run: {STAGE_DIR / 'site.zip'} is missing; run `prepare` first and carry .gpu")
    with zipfile.ZipFile(STAGE_DIR / "site.zip") as site:
        site.extractall(SITE)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(SITE), str(REPO / "src"), os.environ.get("PYTHONPATH", "")])
    sys.path[:0] = [str(SITE), str(REPO / "src")]


def random_vggt(path: Path) -> Path:
    """VGGT-1B with random weights, saved in bf16 (what the runs load)."""
    import torch

    from sl4slam.models.vggt.model import VGGT, VGGTModelConfig, init_random_weights
    from sl4slam.models.vggt.weights import save_checkpoint

    if not path.is_file():
        with torch.device("cuda"):
            model = init_random_weights(VGGT(VGGTModelConfig()), seed=0)
        save_checkpoint({k: v.to(torch.bfloat16) for k, v in model.state_dict().items()}, path, VGGTModelConfig())
        del model
        torch.cuda.empty_cache()
    return path


def one_run(spec: dict) -> dict:
    """One measured run in this process (``--one`` mode): the figures as a dict."""
    import numpy as np
    import torch

    from sl4slam.config import SLAMConfig
    from sl4slam.io import open_source
    from sl4slam.resolve import resolve
    from sl4slam.runner import run_slam

    from _timing import TimedSource  # benchmarks/ is on sys.path: the script runs from there

    config = SLAMConfig(frontend="vggt", device="cuda", overlap=spec["overlap"])
    config.model.weights, config.model.dtype = spec["weights"], "bf16"
    config.retrieval.kind = "orb"  # SALAD's weights are not here either; ORB needs none
    config.output.keyframes = "none"
    arrivals: dict[int, float] = {}
    finished: list[tuple[float, int, int]] = []  # (time, input frames read, keyframes)
    latencies: list[float] = []
    source = TimedSource(open_source(spec["source"], resolve(config).config.source), arrivals)

    def on_submap(pipeline, submap_id: int) -> None:
        now = time.perf_counter()
        finished.append((now, len(arrivals), len(pipeline.keyframes)))
        latencies.extend(now - arrivals[k.frame_index] for k in pipeline.keyframes if k.submap_id == submap_id)

    torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    summary = run_slam(source, spec["out"], config, progress=False, overwrite=True, on_submap=on_submap,
                       all_frames=spec["all_frames"])
    total = time.perf_counter() - start
    frames, keyframes = len(arrivals), summary["counts"]["keyframes"]
    tail = finished[int(0.9 * len(finished)) - 1] if len(finished) >= 10 else finished[0]
    last_seconds = finished[-1][0] - tail[0]
    per_submap = summary["seconds"]["per_submap_median"]
    return {
        "name": spec["name"], "frames": frames, "keyframes": keyframes, "submaps": summary["counts"]["submaps"],
        "seconds": round(total, 2), "fps": round(frames / total, 2), "keyframes_per_s": round(keyframes / total, 2),
        "fps_last_tenth": round((finished[-1][1] - tail[1]) / last_seconds, 2) if last_seconds > 0 else None,
        "keyframes_per_s_last_tenth": round((finished[-1][2] - tail[2]) / last_seconds, 2) if last_seconds > 0 else None,
        "per_submap_median_s": per_submap,
        "latency_s": {"median": round(float(np.median(latencies)), 3), "max": round(float(np.max(latencies)), 3)},
        "gpu_peak_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2),
        "host_peak_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
    }


def run(out: Path, frames: int) -> None:
    require_gpu()
    install_site()
    import torch

    out.mkdir(parents=True, exist_ok=True)
    weights = random_vggt(Path("/tmp/vggt_random_bf16.safetensors"))
    tum = STAGE_DIR / "tum_rgbd_fr1_desk"
    from sl4slam.synthetic import write_synthetic_sequence

    world = write_synthetic_sequence(Path("/tmp/sl4slam-world"), num_frames=frames, width=640, height=480, seed=0,
                                     overwrite=True)
    specs = [
        {"name": "TUM fr1/desk, overlapped", "source": str(tum), "overlap": True, "all_frames": False},
        {"name": "TUM fr1/desk, sequential", "source": str(tum), "overlap": False, "all_frames": False},
        {"name": "TUM fr1/desk, overlapped, --all-frames", "source": str(tum), "overlap": True, "all_frames": True},
        {"name": f"synthetic world ({frames} frames, 640x480), overlapped", "source": str(world), "overlap": True,
         "all_frames": False},
    ]
    rows = []
    for k, spec in enumerate(specs):
        spec = {**spec, "weights": str(weights), "out": f"/tmp/sl4slam-run-{k}"}
        proc = subprocess.run([sys.executable, __file__, "--one", json.dumps(spec)], capture_output=True, text=True,
                              env=os.environ)
        if proc.returncode != 0:
            rows.append({"name": spec["name"], "error": proc.stderr.strip().splitlines()[-1:]})
            continue
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    device = torch.cuda.get_device_name(0)
    (out / "gpu_run.json").write_text(json.dumps({"device": device, "rows": rows}, indent=2))
    lines = [f"## Whole runs on a GPU ({device})", "",
             f"Date: {datetime.date.today()}; torch {torch.__version__}, Python {platform.python_version()}. "
             "VGGT-1B, random weights, bf16; ORB retrieval; keyframes not written. Command: "
             "`python benchmarks/bench_gpu_run.py run --out DIR` (after `prepare` here).", "",
             "| run | frames | keyframes | submaps | s | frames/s | keyframes/s | frames/s last tenth | "
             "frontend s/submap | model-free s/submap | latency median / max s | GPU peak GiB | host peak GiB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        if "error" in row:
            lines.append(f"| {row['name']} | failed: {row['error']} |")
            continue
        stages = row["per_submap_median_s"]
        model_free = sum(v for k, v in stages.items() if k not in ("frontend", "retrieval_describe"))
        lines.append(f"| {row['name']} | {row['frames']} | {row['keyframes']} | {row['submaps']} | {row['seconds']} | "
                     f"{row['fps']} | {row['keyframes_per_s']} | {row['fps_last_tenth']} | {stages.get('frontend', 0):.3f} | "
                     f"{model_free:.3f} | {row['latency_s']['median']} / {row['latency_s']['max']} | "
                     f"{row['gpu_peak_gib']} | {row['host_peak_gib']} |")
    tum_rows = [r for r in rows if r["name"].startswith("TUM fr1/desk, overlapped") and "fps" in r]
    if tum_rows:
        lines += ["", f"TUM fr1/desk overlapped: {tum_rows[0]['fps']} frames/s, "
                      f"{tum_rows[0]['fps'] / VGGT_SOTA_FPS:.1f}x VGGT-SLAM 2.0's published {VGGT_SOTA_FPS} on an RTX 3090 "
                      f"(different GPUs); target >= 30 (the sequence's 30 Hz)."]
    (out / "gpu_run.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--one":  # a child run: its figures as the last line
        install_site()
        print(json.dumps(one_run(json.loads(sys.argv[2]))))
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    verbs = parser.add_subparsers(dest="verb", required=True)
    staging = verbs.add_parser("prepare", help="stage packages and TUM fr1/desk in .gpu/ (here)")
    staging.add_argument("--shared", type=Path, default=REPO.parent / "shared", help="the project's data folder")
    staging.add_argument("--jpeg-quality", type=int, default=85)
    running = verbs.add_parser("run", help="the runs (on the GPU machine)")
    running.add_argument("--out", type=Path, required=True)
    running.add_argument("--world-frames", type=int, default=600)
    args = parser.parse_args()
    if args.verb == "prepare":
        prepare(args.shared, args.jpeg_quality)
    else:
        run(args.out, args.world_frames)


if __name__ == "__main__":
    main()
