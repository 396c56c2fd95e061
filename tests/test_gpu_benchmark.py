"""The GPU benchmark script, where there is no GPU: one clear line, nothing run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_gpu_run.py"


def test_the_gpu_benchmark_says_in_one_line_that_it_needs_a_gpu(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, str(SCRIPT), "run", "--out", str(tmp_path / "out")], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "no CUDA GPU" in lines[0] and "prepare" in lines[0]
    assert not (tmp_path / "out").exists()
