"""The GPU benchmark script without a GPU: its install step, a child run and its report, the
device-less one-line exit, what travels, and the bad-input lines of ``sl4slam run`` it relies on."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from sl4slam.errors import UserError

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "bench_gpu_run.py"
NO_GPU = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
#: A VGGT small enough for a whole run in seconds (the dry run's shape, narrower).
TINY = {"embed_dim": 32, "depth": 2, "num_heads": 2, "patch_embed_depth": 1, "patch_embed_num_heads": 2,
        "camera_trunk_depth": 1, "camera_num_heads": 2, "dpt_features": 8, "dpt_out_channels": [8, 8, 8, 8],
        "dpt_layers": [0, 1, 1, 1]}


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_gpu_run", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def tiny_run(bench, tmp_path_factory):
    """A whole run of a tiny random VGGT on a short synthetic world, in a child process as the script
    makes it; returns (its row, the weights file, the world)."""
    from sl4slam.synthetic import write_synthetic_sequence

    work = tmp_path_factory.mktemp("gpu_bench")
    weights = bench.random_vggt(work / "tiny.safetensors", TINY)
    world = write_synthetic_sequence(work / "world", num_frames=24, width=128, height=96, seed=0)
    capped = next(spec for spec in bench.run_specs(world, 0, bench.CAP_GB) if spec["memory_cap_gb"] > 0)
    spec = {**capped, "weights": str(weights), "out": str(work / "run"),
            "device": "cpu", "model_depth": TINY["depth"]}
    return bench.child_run(spec, timeout=240), weights, world


def test_the_gpu_benchmark_says_in_one_line_that_it_needs_a_gpu(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, str(SCRIPT), "run", "--out", str(tmp_path / "out")], capture_output=True,
                          text=True, timeout=300, env=NO_GPU)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "no CUDA GPU" in lines[0] and "prepare" in lines[0]
    assert "--dry-run" in lines[0]
    assert not (tmp_path / "out").exists()


def test_install_site_unpacks_the_packages_first_on_the_path(bench, tmp_path, monkeypatch):
    archive = tmp_path / "site.zip"
    with zipfile.ZipFile(archive, "w") as packages:
        packages.writestr("staged_probe/__init__.py", "VALUE = 7\n")
    monkeypatch.setenv("PYTHONPATH", "/elsewhere")
    monkeypatch.setattr(sys, "path", list(sys.path))
    bench.install_site(archive, tmp_path / "site", tmp_path / "src")
    assert (tmp_path / "site" / "staged_probe" / "__init__.py").is_file()
    assert os.environ["PYTHONPATH"].split(os.pathsep) == [str(tmp_path / "site"), str(tmp_path / "src"), "/elsewhere"]
    assert sys.path[:2] == [str(tmp_path / "site"), str(tmp_path / "src")]
    # a child process finds the unpacked package through PYTHONPATH alone
    probe = subprocess.run([sys.executable, "-c", "import staged_probe; print(staged_probe.VALUE)"],
                           capture_output=True, text=True, env=os.environ, timeout=60)
    assert probe.stdout.strip() == "7"
    with pytest.raises(SystemExit, match="run `prepare` first"):
        bench.install_site(tmp_path / "missing.zip", tmp_path / "site", tmp_path / "src")


def test_random_weights_give_finite_cameras_and_a_whole_run_reports(bench, tiny_run):
    """The random camera head is biased so the frontend keeps its submaps (plain random weights gave
    non-finite intrinsics and a run with no keyframe); the child's figures fill the report's row."""
    row, _, _ = tiny_run
    assert "error" not in row, row
    assert row["frames"] == 24 and row["keyframes"] > 0 and row["submaps"] >= 1
    assert row["fps"] > 0 and row["host_peak_gib"] > 0
    assert row["gpu_peak_gib"] is None and row["gpu_cap_gib"] is None  # no GPU: nothing measured, no cap
    assert row["per_submap_median_s"]["frontend"] > 0
    assert 0 < row["outside_loop_s"] < row["seconds"]  # loading the model, writing the outputs
    failed = {"name": "TUM fr1/desk, sequential", "error": "UserError: a | in the message"}
    lines = bench.report([row, failed], "CPU", "a tiny VGGT", "python benchmarks/bench_gpu_run.py run --dry-run",
                         dry_run=True)
    assert lines[0].startswith("## Whole runs on a GPU: the dry run on the CPU")
    table = [line for line in lines if line.startswith(f"| {row['name']} |")]
    assert len(table) == 1 and table[0].count("|") == 16
    assert f"| {row['frames']} | {row['keyframes']} | {row['submaps']} |" in table[0]
    assert "| TUM fr1/desk, sequential | failed: UserError: a | in the message |" in lines
    assert lines[-1] == "1 of 2 runs finished; failed: TUM fr1/desk, sequential."
    gpu = bench.report([{**row, "gpu_peak_gib": 6.5, "gpu_cap_gib": 8.0, "name": "TUM fr1/desk, overlapped"}],
                       "NVIDIA H100", "VGGT-1B", "run", dry_run=False)
    assert gpu[0] == "## Whole runs on a GPU (NVIDIA H100)" and "| 6.5 (8) |" in gpu[-3]
    assert "VGGT-SLAM 2.0's published 8.4" in gpu[-1]


def test_each_model_named_gets_its_run_and_an_unknown_one_is_one_line(bench, tmp_path):
    specs = bench.run_specs(tmp_path, 0, bench.CAP_GB, ("vggt", "da3-small", "pi3x"))
    assert [s["frontend"] for s in specs] == ["vggt", "vggt", "vggt", "da3-small", "pi3x", "vggt"]
    assert [s["name"] for s in specs][:3] == ["TUM fr1/desk, overlapped", "TUM fr1/desk, sequential",
                                              "TUM fr1/desk, overlapped, within 8 GB (--max-memory 8)"]
    assert all(s["overlap"] for s in specs[3:]) and specs[-1]["all_frames"]
    proc = subprocess.run([sys.executable, str(SCRIPT), "run", "--dry-run", "--models", "vggt,da3-tiny", "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 1 and len(lines) == 1 and "'da3-tiny'" in lines[0] and "da3-small" in lines[0]
    assert not (tmp_path / "out").exists()


def test_a_spent_budget_reports_the_runs_it_did_not_make(bench, tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPT.parent))  # the script's own imports (its harness)
    monkeypatch.setattr(bench, "install_site", lambda: None)
    monkeypatch.setattr(bench, "child_run", lambda spec, timeout: pytest.fail("no run fits a 30 s budget"))
    assert bench.run(tmp_path / "out", 0, True, 60.0, ("vggt",), budget=30.0, only=(0, 2)) == 2
    report = (tmp_path / "out" / "gpu_run.md").read_text()
    assert report.count("failed: not run: the call's 30 s were spent") == 2 and "sequential" not in report


def test_a_failing_child_run_is_one_row_with_its_last_line(bench, tiny_run, tmp_path):
    _, weights, _ = tiny_run
    spec = {**bench.run_specs(tmp_path / "no_such_sequence", 0, bench.CAP_GB)[0], "weights": str(weights),
            "out": str(tmp_path / "run"), "device": "cpu", "model_depth": TINY["depth"]}
    row = bench.child_run(spec, timeout=120)
    assert set(row) == {"name", "error"} and "no_such_sequence" in row["error"] and "\n" not in row["error"]


def test_the_staged_tree_fits_what_travels(bench):
    if not (bench.STAGE_DIR / "site.zip").is_file():
        pytest.skip("nothing staged: run `python benchmarks/bench_gpu_run.py prepare`")
    staged, tree = bench.travel_bytes()
    assert staged + tree <= bench.TRAVEL_LIMIT, f"{(staged + tree) / 2**20:.1f} MiB"


def _run_line(args: list[str], env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sl4slam.cli", "run", *args, "--quiet"], capture_output=True,
                          text=True, timeout=240, env=env or os.environ)


def test_device_cuda_without_a_gpu_is_one_line(tiny_run, tmp_path):
    _, weights, _ = tiny_run
    proc = _run_line([str(tmp_path), "--out", str(tmp_path / "out"), "--frontend", "vggt", "--weights", str(weights),
                      "--device", "cuda"], env=NO_GPU)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "--device cuda" in lines[0] and "no CUDA GPU" in lines[0] and "--device cpu" in lines[0]
    assert not (tmp_path / "out").exists()


def test_a_budget_nothing_fits_is_one_line_naming_what_a_submap_needs(tiny_run, tmp_path):
    _, weights, world = tiny_run
    proc = _run_line([str(world), "--out", str(tmp_path / "out"), "--frontend", "vggt", "--weights", str(weights),
                      "--match-layer", "1", "--device", "cpu", "--max-memory", "0.1"])
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode != 0 and len(lines) == 1, proc.stderr
    assert "--max-memory is 0.1 GiB, below the smallest budget any setting fits" in lines[0]
    smallest = float(re.search(r"give --max-memory ([\d.]+) or more", lines[0]).group(1))
    assert smallest > 0.1
    from sl4slam.models.memory import MemoryPlan, plan_memory

    def peak(frames, chunk):  # a model whose one-frame window needs 1.05 GiB
        return int((1 + 0.05 * frames * chunk) * 2**30)

    assert isinstance(plan_memory(peak, 1.1, 1, 1, lambda needed, largest: "refused"), MemoryPlan)
    with pytest.raises(UserError, match=r"smallest budget any setting fits: 1\.1 GiB"):
        plan_memory(peak, 1.0, 16, 8, lambda needed, largest: "refused")
    with pytest.raises(UserError, match="refused"):  # one frame fits, sixteen do not: the model's own line
        plan_memory(peak, 1.2, 16, 8, lambda needed, largest: "refused")
