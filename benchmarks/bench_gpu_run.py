"""Whole ``sl4slam`` runs on a GPU, measured: frames per second, time per submap by stage, memory.

Two steps, because the GPU machine has no package index:

    python benchmarks/bench_gpu_run.py prepare            # here: GTSAM, evo, safetensors, TUM fr1/desk -> .gpu/
    python benchmarks/bench_gpu_run.py run --out DIR      # there: installs from .gpu/, runs, reports
    python benchmarks/bench_gpu_run.py run --dry-run --out DIR   # here: the same, on the CPU, small

``prepare`` (on a machine with PyPI and the project's data folder ``../shared``) fetches what the GPU
machine's Python (3.12, x86-64, with torch, numpy, scipy, OpenCV and matplotlib of its own) lacks:
GTSAM, evo and safetensors, as one zip of their packages (GTSAM's example data, tests and unstable
module left out), and copies TUM RGB-D fr1/desk into the working tree (its RGB frames as JPEG,
quality 75, so the tree stays within what travels to the GPU machine: 64 MiB, :data:`TRAVEL_LIMIT`).
``.gpu/`` is excluded from git. The project itself is not installed there: ``run`` puts ``src/`` and
the unpacked packages on ``PYTHONPATH`` (its own and its child processes').

``run`` unpacks the zip into ``/tmp/sl4slam-site``, makes VGGT-1B with random weights (full size,
bf16: the cost of a forward does not depend on the values) and runs in a fresh process each:

- TUM fr1/desk, VGGT bf16, the model overlapping the graph work (the default) and sequential, side
  by side; with ``--all-frames`` as well;
- TUM fr1/desk, overlapped, within 8 GB: the process capped with
  ``torch.cuda.set_per_process_memory_fraction`` to 8 GiB and ``--max-memory 8`` (the planner picks
  the dense heads' chunk);
- TUM fr1/desk, overlapped, with each other model that ``--models`` names (DA3, π³/Pi3X: full
  size, random weights, bf16);
- with ``--world-frames N``, the synthetic world (N frames at 640x480, rendered first: about 0.2 s
  a frame), VGGT bf16, overlapped.

Before the first run the parent builds matplotlib's font cache (a one-off per machine that the
first run's plot would otherwise pay). ``--budget S`` bounds the whole call (a run that cannot start with a minute left is reported as
not run), ``--runs 0,2`` makes only those runs and ``--profile`` writes each run's cProfile
summary to ``DIR/profile-K.txt``. ``colors`` (here) times the map colours' two paths side by side.

Each run reports input frames and keyframes per second over the whole run and over its last tenth
(does it slow down as the map grows?), the median seconds per submap of every stage, the latency
from a keyframe's arrival to its pose (when its submap's graph work ends), GPU peak memory
(``torch.cuda.max_memory_allocated``) and host peak RSS. Figures go to ``DIR/gpu_run.json`` (after
each run, so a stopped call keeps the finished ones) and the Markdown section to ``DIR/gpu_run.md``
(copied into ``benchmarks/results/gpu_run.md``). Without a GPU, ``run`` ends with one line.

``run --dry-run`` goes through the same steps on the CPU: the same unpacking of ``.gpu/site.zip``,
the same child processes, runs and report, with a small VGGT (:data:`DRY_MODEL`, random weights,
bf16) on the first :data:`DRY_FRAMES` frames of the staged fr1/desk and a small synthetic world;
the 8 GB run keeps ``--max-memory 8`` (the cap itself needs a GPU). Proved in a fresh virtual
environment holding only what the GPU machine has (the project on ``PYTHONPATH``, not installed)::

    ~/.pyenv/versions/3.12.1/bin/python -m venv /tmp/gpuvenv
    /tmp/gpuvenv/bin/pip install torch==2.13.0 numpy scipy opencv-python-headless matplotlib
    python benchmarks/bench_gpu_run.py prepare
    /tmp/gpuvenv/bin/python benchmarks/bench_gpu_run.py run --dry-run --out /tmp/gpu_dry

Outcome (2 CPU cores, shared): the 4 runs finished, exit status 0, in about 6 minutes; staged 37.8
MiB, 59.5 MiB with the working tree. Section and findings: ``benchmarks/results/gpu_run.md``. On the
GPU machine: ``python3 benchmarks/bench_gpu_run.py run --out $OUT`` with ``.gpu`` carried.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
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
WHEELS = {"gtsam": "gtsam==4.3.0", "evo": "evo==1.38.1", "safetensors": "safetensors==0.8.0"}
#: Parts of the wheels that nothing of ours reads: GTSAM's example data, tests and unstable module.
SKIPPED_IN_WHEELS = ("gtsam/Data/", "gtsam/tests/", "gtsam_unstable", "gtsam.libs/libgtsam_unstable")
GPU_PYTHON = "3.12"
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64")
TRAVEL_LIMIT = 64 * 2**20
VGGT_SOTA_FPS = 8.4  # VGGT-SLAM 2.0's published speed on an RTX 3090, w = 16 (a different GPU)
GIB = 2**30
#: The models ``--models`` may name (the dry run builds every one but VGGT at full size).
MODELS = ("vggt", "da3-small", "da3-base", "da3-large", "da3-giant", "pi3", "pi3x")
#: The memory budget of the capped run, GiB (an 8 GB card).
CAP_GB = 8.0
#: The dry run's VGGT: the full model's structure (24-layer-deep aggregator replaced by 4), small widths.
DRY_MODEL = {"embed_dim": 64, "depth": 4, "num_heads": 2, "patch_embed_depth": 2, "patch_embed_num_heads": 2,
             "camera_trunk_depth": 1, "camera_num_heads": 2, "dpt_features": 16, "dpt_out_channels": [16, 16, 32, 32],
             "dpt_layers": [0, 1, 2, 3]}
#: Input frames of fr1/desk the dry run reads, and the size of its synthetic world.
DRY_FRAMES = 48
DRY_WORLD = {"frames": 40, "width": 160, "height": 120}


# ------------------------------------------------------------------------------------------ prepare
def travel_bytes(stage_dir: Path = STAGE_DIR, repo: Path = REPO) -> tuple[int, int]:
    """(bytes staged in ``stage_dir``, bytes of the working tree that travels: tracked and untracked,
    not ignored, files of ``repo``)."""
    staged = sum(p.stat().st_size for p in stage_dir.rglob("*") if p.is_file()) if stage_dir.is_dir() else 0
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=repo, capture_output=True,
                            check=True).stdout.decode().split("\0")
    tree = sum((repo / f).stat().st_size for f in listed if f and (repo / f).is_file())
    return staged, tree


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
                    if not name.startswith(SKIPPED_IN_WHEELS):
                        site.writestr(name, source.read(name))
    sequence = shared / "data" / "tum_rgbd_fr1_desk"
    target = STAGE_DIR / "tum_rgbd_fr1_desk"
    if target.is_dir():
        shutil.rmtree(target)  # frames of another quality must not stay
    (target / "rgb").mkdir(parents=True)
    lines = []
    for line in (sequence / "rgb.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            lines.append(line)
            continue
        stamp, name = line.split()[:2]
        jpeg = Path(name).with_suffix(".jpg")
        cv2.imwrite(str(target / jpeg), cv2.imread(str(sequence / name)), [cv2.IMWRITE_JPEG_QUALITY, quality])
        lines.append(f"{stamp} {jpeg}")
    (target / "rgb.txt").write_text("\n".join(lines) + "\n")
    shutil.copyfile(sequence / "groundtruth.txt", target / "groundtruth.txt")
    shutil.rmtree(downloads)
    staged, tree = travel_bytes()
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
        print("bench_gpu_run: no CUDA GPU on this machine; run `prepare` here and `run` on a GPU machine "
              "(`run --dry-run` runs it small on the CPU)", file=sys.stderr)
        raise SystemExit(2)


def install_site(archive: Path = STAGE_DIR / "site.zip", site: Path = SITE, source: Path = REPO / "src") -> None:
    """Unpack the staged packages into ``site`` and put it and the project's ``source`` first on the
    import path of this process and (through ``PYTHONPATH``) of the processes it starts."""
    if not archive.is_file():
        raise SystemExit(f"bench_gpu_run: {archive} is missing; run `prepare` first and carry .gpu")
    with zipfile.ZipFile(archive) as packages:
        packages.extractall(site)
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(site), str(source), os.environ.get("PYTHONPATH", "")) if p)
    sys.path[:0] = [str(site), str(source)]


def random_vggt(path: Path, model_config: dict) -> Path:
    """VGGT of ``model_config`` (``{}``: VGGT-1B) with seeded random weights, made on the CPU (as in
    the dry run) and saved in bf16 (what the runs load) at ``path``; an existing file is reused.

    The camera head's last layer is shrunk and biased towards the identity rotation and a 60-degree
    field of view: with plain random weights the decoded intrinsics can be non-finite, and the
    frontend then drops every submap (the run ends with no keyframe).
    """
    import torch

    from sl4slam.models.vggt.model import VGGT, VGGTModelConfig, init_random_weights
    from sl4slam.models.vggt.weights import save_checkpoint

    if not path.is_file():
        config = VGGTModelConfig(**model_config)
        model = init_random_weights(VGGT(config), seed=0)
        with torch.no_grad():
            last = model.camera_head.pose_branch.fc2
            last.weight.mul_(0.01)
            # translation 0, quaternion (0, 0, 0, 1), field of view 1.05 x 1.3 rad; the head adds its
            # iterations' outputs, so each gives its share of the target
            target = torch.tensor([0, 0, 0, 0, 0, 0, 1.0, 1.05, 1.3])
            last.bias.copy_(target / config.camera_iterations)
        save_checkpoint({k: v.to(torch.bfloat16).contiguous() for k, v in model.state_dict().items()}, path, config)
    return path


def random_weights(name: str, path: Path, model_config: dict | None = None, dtype: str | None = "bf16") -> Path:
    """The full-size network of model ``name`` (one of :data:`MODELS`) with seeded random weights,
    saved at ``path`` (made on the CPU; an existing file is reused).

    Args:
        model_config: VGGT only: its :class:`VGGTModelConfig` fields (``{}``: VGGT-1B).
        dtype: "bf16" saves the weights in bfloat16 (what the GPU runs load); ``None`` as built.
    """
    if name == "vggt":
        return random_vggt(path, model_config or {})
    if not path.is_file():
        import torch

        from bench_models import build_frontend
        if name.startswith("da3-"):
            from sl4slam.models.da3 import save_checkpoint
        else:
            from sl4slam.models.pi3 import save_checkpoint
        model = build_frontend(name).model
        cast = (lambda v: v.to(torch.bfloat16)) if dtype == "bf16" else (lambda v: v)
        tmp = path.with_suffix(".tmp.safetensors")
        with torch.no_grad():
            save_checkpoint({k: cast(v).contiguous() for k, v in model.state_dict().items()}, tmp, model.config)
        os.replace(tmp, path)
    return path


def run_specs(tum: Path, max_frames: int, cap_gb: float, models: tuple[str, ...] = ("vggt",)) -> list[dict]:
    """The runs on ``tum`` (its first ``max_frames``; 0: all), in the order of what matters most:
    what each child process is told besides weights, device and output. VGGT overlapped, sequential
    and within ``cap_gb`` GiB; each other model of ``models`` overlapped; VGGT with ``--all-frames``."""
    base = {"source": str(tum), "frontend": "vggt", "overlap": True, "all_frames": False, "max_frames": max_frames,
            "max_memory_gb": 0.0, "memory_cap_gb": 0.0}
    return [
        {**base, "name": "TUM fr1/desk, overlapped"},
        {**base, "name": "TUM fr1/desk, sequential", "overlap": False},
        {**base, "name": f"TUM fr1/desk, overlapped, within {cap_gb:g} GB (--max-memory {cap_gb:g})",
         "max_memory_gb": cap_gb, "memory_cap_gb": cap_gb},
        *({**base, "name": f"TUM fr1/desk, {name}, overlapped", "frontend": name} for name in models if name != "vggt"),
        {**base, "name": "TUM fr1/desk, overlapped, --all-frames", "all_frames": True},
    ]


def one_run(spec: dict) -> dict:
    """One measured run in this process (``--one`` mode): the figures as a dict."""
    import torch

    from sl4slam.config import SLAMConfig
    from sl4slam.io import open_source
    from sl4slam.resolve import resolve
    from sl4slam.runner import run_slam

    from harness import TimedSource, peak_rss_bytes  # benchmarks/ is on sys.path: the script runs from there

    cuda = spec["device"] == "cuda"
    capped = cuda and spec["memory_cap_gb"] > 0
    if capped:
        total = torch.cuda.get_device_properties(0).total_memory
        torch.cuda.set_per_process_memory_fraction(min(1.0, spec["memory_cap_gb"] * GIB / total), 0)
    config = SLAMConfig(frontend=spec["frontend"], device=spec["device"], overlap=spec["overlap"])
    config.model.weights, config.model.dtype = spec["weights"], "bf16"
    config.model.max_memory_gb = spec["max_memory_gb"]
    if spec["frontend"] == "vggt":  # the dry run's VGGT is shallower than the layer matched by default
        config.model.match_layer = min(config.model.match_layer, spec["model_depth"] - 1)
    config.source.max_frames = spec["max_frames"]
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

    if cuda:
        torch.cuda.reset_peak_memory_stats()
    profiler = None
    if spec.get("profile"):
        import cProfile

        profiler = cProfile.Profile()
        profiler.enable()
    start = time.perf_counter()
    summary = run_slam(source, spec["out"], config, progress=False, overwrite=True, on_submap=on_submap,
                       all_frames=spec["all_frames"])
    seconds = time.perf_counter() - start
    if profiler is not None:
        write_profile(profiler, Path(spec["profile"]), f"{spec['name']}: {seconds:.1f} s")
    return summarize(spec["name"], seconds, len(arrivals), summary, finished, latencies,
                     torch.cuda.max_memory_allocated() if cuda else None, peak_rss_bytes(),
                     spec["memory_cap_gb"] if capped else None)


def write_profile(profiler, path: Path, title: str, lines: int = 45) -> None:
    """The ``lines`` functions of ``profiler`` with the most time of their own, and those with the
    most time including callees (threads other than the caller's are not seen), as text at ``path``."""
    import io
    import pstats

    text = io.StringIO()
    text.write(title + "\n")
    stats = pstats.Stats(profiler, stream=text)
    stats.sort_stats("tottime").print_stats(lines)
    stats.sort_stats("cumulative").print_stats(lines)
    path.write_text(text.getvalue())


def summarize(name: str, seconds: float, frames: int, summary: dict, finished: list[tuple[float, int, int]],
              latencies: list[float], gpu_peak_bytes: int | None, host_peak_bytes: int,
              cap_gb: float | None) -> dict:
    """A run's figures: rates over the whole run and over its last tenth of submaps.

    Args:
        seconds: the run's wall time; frames: input frames read.
        summary: ``run_slam``'s summary (``counts``, ``seconds.per_submap_median``).
        finished: (time, input frames read, keyframes) when each submap's graph work ended.
        latencies: seconds from each keyframe's arrival to its pose.
        gpu_peak_bytes: ``torch.cuda.max_memory_allocated`` (``None``: no GPU); host_peak_bytes: peak RSS.
        cap_gb: the process's GPU memory cap, GiB (``None``: none).
    """
    import numpy as np

    keyframes = summary["counts"]["keyframes"]
    tail = finished[int(0.9 * len(finished)) - 1] if len(finished) >= 10 else finished[0] if finished else None
    last_seconds = finished[-1][0] - tail[0] if tail else 0.0
    return {
        "name": name, "frames": frames, "keyframes": keyframes, "submaps": summary["counts"]["submaps"],
        "seconds": round(seconds, 2), "fps": round(frames / seconds, 2), "keyframes_per_s": round(keyframes / seconds, 2),
        "fps_last_tenth": round((finished[-1][1] - tail[1]) / last_seconds, 2) if last_seconds > 0 else None,
        "keyframes_per_s_last_tenth": round((finished[-1][2] - tail[2]) / last_seconds, 2) if last_seconds > 0 else None,
        "per_submap_median_s": summary["seconds"]["per_submap_median"],
        # before the first frame (loading the model) and after the graph (writing the map and files)
        "outside_loop_s": round(seconds - summary["seconds"]["total"], 2),
        "latency_s": {"median": round(float(np.median(latencies)), 3) if latencies else None,
                      "max": round(float(np.max(latencies)), 3) if latencies else None},
        "gpu_peak_gib": None if gpu_peak_bytes is None else round(gpu_peak_bytes / GIB, 2),
        "host_peak_gib": round(host_peak_bytes / GIB, 2),
        "gpu_cap_gib": cap_gb,
    }


def child_run(spec: dict, timeout: float) -> dict:
    """``spec`` run by this script in a fresh process (``--one``): its figures, or ``name`` and ``error``."""
    try:
        proc = subprocess.run([sys.executable, __file__, "--one", json.dumps(spec)], capture_output=True, text=True,
                              env=os.environ, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"name": spec["name"], "error": f"stopped after {timeout:.0f} s"}
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
        return {"name": spec["name"], "error": last.replace("|", "/")[:300]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _value(value, form: str = "{}") -> str:
    return "-" if value is None else form.format(value)


def report(rows: list[dict], device: str, model: str, command: str, dry_run: bool) -> list[str]:
    """The Markdown section of ``rows`` (each a :func:`summarize` dict, or ``name`` and ``error``)."""
    import torch

    title = (f"## Whole runs on a GPU: the dry run on the CPU ({device})" if dry_run
             else f"## Whole runs on a GPU ({device})")
    lines = [title, "",
             f"Date: {datetime.date.today()}; torch {torch.__version__}, Python {platform.python_version()}. "
             f"{model}, random weights, bf16; ORB retrieval; keyframes not written. Command: `{command}`"
             + (" (after `prepare`)." if not dry_run else " (after `prepare`; the same install, child processes and "
                "report as on the GPU, small: only the device and the sizes differ)."), "",
             "| run | frames | keyframes | submaps | s | frames/s | keyframes/s | frames/s last tenth | "
             "keyframes/s last tenth | loading + outputs s | frontend s/submap | model-free s/submap | latency median / max s | "
             "GPU peak GiB (cap) | host peak GiB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        if "error" in row:
            lines.append(f"| {row['name']} | failed: {row['error']} |")
            continue
        stages = row["per_submap_median_s"]
        model_free = sum(v for k, v in stages.items() if k not in ("frontend", "retrieval_describe"))
        gpu = _value(row["gpu_peak_gib"]) + (f" ({row['gpu_cap_gib']:g})" if row.get("gpu_cap_gib") else "")
        lines.append(f"| {row['name']} | {row['frames']} | {row['keyframes']} | {row['submaps']} | {row['seconds']} | "
                     f"{row['fps']} | {row['keyframes_per_s']} | {_value(row['fps_last_tenth'])} | "
                     f"{_value(row['keyframes_per_s_last_tenth'])} | {_value(row.get('outside_loop_s'))} | "
                     f"{stages.get('frontend', 0):.3f} | {model_free:.3f} | "
                     f"{_value(row['latency_s']['median'])} / {_value(row['latency_s']['max'])} | {gpu} | {row['host_peak_gib']} |")
    tum_rows = [r for r in rows if r["name"] == "TUM fr1/desk, overlapped" and "fps" in r]
    if tum_rows and not dry_run:
        lines += ["", f"TUM fr1/desk overlapped: {tum_rows[0]['fps']} frames/s, "
                      f"{tum_rows[0]['fps'] / VGGT_SOTA_FPS:.1f}x VGGT-SLAM 2.0's published {VGGT_SOTA_FPS} on an RTX 3090 "
                      f"(different GPUs); target >= 30 (the sequence's 30 Hz)."]
    failed = [r["name"] for r in rows if "error" in r]
    if dry_run:
        lines += ["", f"{len(rows) - len(failed)} of {len(rows)} runs finished"
                      + (f"; failed: {', '.join(failed)}." if failed else ".")]
    return lines


def warm_font_cache() -> None:
    """Build matplotlib's font cache once, before any timed run: on a machine where matplotlib never
    ran, the first run's trajectory plot would otherwise pay for scanning the system's fonts (a
    one-off, which a user's second run does not pay)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.font_manager  # noqa: F401  (imported for its side effect: the cache file)


def run(out: Path, frames: int, dry_run: bool, timeout: float, models: tuple[str, ...] = ("vggt",),
        budget: float = 0.0, only: tuple[int, ...] = (), profile: bool = False) -> int:
    """The runs and their report in ``out``; returns the number of runs that failed.

    Args:
        models: the models measured (:data:`MODELS`; VGGT's runs always).
        budget: seconds the whole call may take (0: no limit): a run gets at most what is left, and
            one that cannot start with a minute left is reported as not run.
        only: the runs made, as indices into :func:`run_specs`'s list (empty: all).
        profile: each run under cProfile, its top functions written to ``DIR/profile-K.txt``.
    """
    began = time.perf_counter()
    if not dry_run:
        require_gpu()
    install_site()
    import torch

    warm_font_cache()

    out.mkdir(parents=True, exist_ok=True)
    device = "cpu" if dry_run else "cuda"
    model_config = DRY_MODEL if dry_run else {}
    work = Path(f"/tmp/sl4slam-{'dry' if dry_run else 'gpu'}")
    work.mkdir(exist_ok=True)
    from harness import synthetic_world
    from sl4slam.models.vggt.model import VGGTModelConfig

    specs = run_specs(STAGE_DIR / "tum_rgbd_fr1_desk", DRY_FRAMES if dry_run else 0, CAP_GB, models)
    if frames > 0:  # the synthetic world: rendered here, before the runs (about 0.2 s a frame on one core)
        size = DRY_WORLD if dry_run else {"frames": frames, "width": 640, "height": 480}
        world = synthetic_world(size["width"], size["height"], size["frames"], folder=work / "world")
        specs.append({**specs[0], "name": f"synthetic world ({size['frames']} frames, {size['width']}x{size['height']}), "
                      "overlapped", "source": str(world), "max_frames": 0})
    depth = VGGTModelConfig(**model_config).depth
    rows = []
    name = "CPU" if dry_run else torch.cuda.get_device_name(0)
    for k, spec in enumerate(specs):
        if only and k not in only:
            continue
        left = budget - (time.perf_counter() - began) if budget > 0 else timeout
        if left < 60:
            rows.append({"name": spec["name"], "error": f"not run: the call's {budget:.0f} s were spent"})
            print(f"bench_gpu_run: {spec['name']}: not run (budget spent)", flush=True)
            continue
        started = time.perf_counter()
        weights = random_weights(spec["frontend"], work / f"{spec['frontend']}_random_bf16.safetensors", model_config)
        spec = {**spec, "weights": str(weights), "out": str(work / f"run-{k}"), "device": device, "model_depth": depth,
                "profile": str(out / f"profile-{k}.txt") if profile else ""}
        rows.append(child_run(spec, min(timeout, left - (time.perf_counter() - started) - 10)))
        print(f"bench_gpu_run: {spec['name']}: {rows[-1].get('error') or 'done'} "
              f"({time.perf_counter() - started:.0f} s)", flush=True)
        (out / "gpu_run.json").write_text(json.dumps({"device": name, "dry_run": dry_run, "rows": rows}, indent=2))
    others = [m for m in models if m != "vggt"]
    model = ("a small VGGT (bench_gpu_run.DRY_MODEL)" if dry_run else "VGGT-1B") + "".join(f", {m}" for m in others)
    command = ("python benchmarks/bench_gpu_run.py run " + ("--dry-run " if dry_run else "")
               + (f"--models {','.join(models)} " if others else "") + (f"--budget {budget:g} " if budget else "") + "--out DIR")
    lines = report(rows, name, model, command, dry_run)
    (out / "gpu_run.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return sum("error" in r for r in rows)


def colour_paths(frames: int = 20) -> list[str]:
    """Median ms per 640x480 frame of each model's map colours (``grid_colors``, read for every
    keyframe when the map is written), the float round trip they took before against the uint8 path,
    side by side in this process; the outputs are checked equal. Returns the Markdown lines."""
    import statistics

    import numpy as np

    from harness import random_frames
    from sl4slam.models.da3.preprocess import grid_uint8
    from sl4slam.models.da3.preprocess import preprocess_images as da3_preprocess
    from sl4slam.models.pi3.preprocess import preprocess_images as pi3_preprocess
    from sl4slam.models.pi3.preprocess import resize_to_grid
    from sl4slam.models.vggt.preprocess import channels_last, preprocess_images, preprocess_uint8, to_uint8_rgb

    paths = {
        "VGGT": (lambda im: to_uint8_rgb(preprocess_images([im])[0])[0], lambda im: channels_last(preprocess_uint8([im])[0])[0]),
        "Depth Anything 3": (lambda im: da3_preprocess([im]).colors[0], lambda im: grid_uint8([im])[0][0]),
        "π³ / Pi3X": (lambda im: pi3_preprocess([im])[1][0], lambda im: resize_to_grid([im])[0][0]),
    }
    images = random_frames(frames, seed=0)
    lines = ["| model | float round trip, ms/frame | uint8, ms/frame | ratio |", "|---|---|---|---|"]
    for name, (before, after) in paths.items():
        times = {0: [], 1: []}
        for image in images:
            for which, path in ((0, before), (1, after)):
                start = time.perf_counter()
                colours = path(image)
                times[which].append(time.perf_counter() - start)
            assert np.array_equal(before(image), colours)
        old, new = (1000 * statistics.median(times[k]) for k in (0, 1))
        lines.append(f"| {name} | {old:.1f} | {new:.1f} | {new / old:.2f} |")
    return lines


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--one":  # a child run: its figures as the last line
        print(json.dumps(one_run(json.loads(sys.argv[2]))))
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    verbs = parser.add_subparsers(dest="verb", required=True)
    staging = verbs.add_parser("prepare", help="stage packages and TUM fr1/desk in .gpu/ (here)")
    staging.add_argument("--shared", type=Path, default=REPO.parent / "shared", help="the project's data folder")
    staging.add_argument("--jpeg-quality", type=int, default=75)
    verbs.add_parser("colors", help="the map colours' cost per frame, before and after the uint8 path (here)")
    running = verbs.add_parser("run", help="the runs (on the GPU machine)")
    running.add_argument("--out", type=Path, required=True)
    running.add_argument("--world-frames", type=int, default=0,
                         help="also run the synthetic world of this many frames at 640x480 (0: not)")
    running.add_argument("--dry-run", action="store_true",
                         help="the same install, runs and report on the CPU, with a small model and short inputs")
    running.add_argument("--run-timeout", type=float, default=150.0, help="seconds one run may take")
    running.add_argument("--models", default="vggt",
                         help=f"comma-separated models to measure ({', '.join(MODELS)}); VGGT's runs always")
    running.add_argument("--runs", default="", help="comma-separated indices of the runs to make (default all)")
    running.add_argument("--profile", action="store_true", help="profile each run (cProfile; DIR/profile-K.txt)")
    running.add_argument("--budget", type=float, default=0.0,
                         help="seconds the whole call may take (0: no limit); runs that would not fit are reported as not run")
    args = parser.parse_args()
    if args.verb == "prepare":
        prepare(args.shared, args.jpeg_quality)
    elif args.verb == "colors":
        print("\n".join(colour_paths()))
    else:
        models = tuple(m.strip() for m in args.models.split(",") if m.strip())
        unknown = [m for m in models if m not in MODELS]
        if unknown:
            raise SystemExit(f"bench_gpu_run: unknown model {unknown[0]!r}; --models takes {', '.join(MODELS)}")
        raise SystemExit(1 if run(args.out, args.world_frames, args.dry_run, args.run_timeout, models, args.budget,
                                   tuple(int(k) for k in args.runs.split(",") if k.strip()), args.profile) else 0)


if __name__ == "__main__":
    main()
