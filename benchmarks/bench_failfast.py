"""Time from start to the first error line for mistakes that must be caught before any frame is read.

    python benchmarks/bench_failfast.py --repeats 5

Each case runs ``sl4slam run`` in a fresh process on the complete TUM fr1/desk sequence (613 frames)
and measures the wall time until the process has printed its error and exited:

- missing VGGT weights with the hub switched off (``HF_HUB_OFFLINE=1``, empty Hugging Face cache);
- missing VGGT weights without network access (no offline switch: the hub is probed once);
- an output folder that cannot be created (``--out`` under a regular file).

Targets: 5 s for the weights, 2 s for the output folder.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from harness import markdown_row, result_file, shared_sequence, table, write_report

SEQUENCE = shared_sequence("desk")


def timed(args: list[str], env: dict) -> tuple[float, str, int, float]:
    """Wall seconds, first stderr line, exit code and the child's CPU seconds (user + system: what
    the wall time would be on an idle machine, less any waiting on the network or the disk)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "sl4slam.cli", "run", *args], capture_output=True, text=True, env=env,
                          timeout=600)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    return wall, lines[0] if lines else "", proc.returncode, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sequence", default=str(SEQUENCE))
    parser.add_argument("--out", default=str(result_file("failfast")))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "a_file").write_text("x")
        base = {**os.environ, "HF_HOME": str(tmp / "hf")}
        offline = {**base, "HF_HUB_OFFLINE": "1"}
        cases = {
            "missing weights, HF_HUB_OFFLINE=1": ([args.sequence, "--out", str(tmp / "o1"), "--quiet"], offline, 5.0),
            "missing weights, no network": ([args.sequence, "--out", str(tmp / "o2"), "--quiet"], base, 5.0),
            "--out under a regular file": ([args.sequence, "--out", str(tmp / "a_file" / "out"), "--quiet"], base, 2.0),
        }
        rows = []
        for name, (cli_args, env, target) in cases.items():
            runs = [timed(cli_args, env) for _ in range(args.repeats)]
            seconds = [r[0] for r in runs]
            cpu = [r[3] for r in runs]
            codes = {r[2] for r in runs}
            rows.append([name, f"{statistics.median(seconds):.2f}", f"{min(seconds):.2f}-{max(seconds):.2f}",
                         f"{statistics.median(cpu):.2f}", f"{target:g}", ",".join(map(str, sorted(codes))),
                         f"{runs[0][1][:90]}..."])
            print(markdown_row(rows[-1]), flush=True)
    load = os.getloadavg()[0]
    lines = [
        "## Fail fast: time to the first error line",
        "",
        f"Machine: {os.cpu_count()}-core x86_64 CPU, no GPU; Python {platform.python_version()}. Date: {datetime.date.today()}. "
        f"1-minute load average at the end: {load:.1f}.",
        f"Command: `python benchmarks/bench_failfast.py --repeats {args.repeats}`.",
        "`sl4slam run` on TUM fr1/desk (613 frames) in a fresh process; wall time until the process exited with its one "
        "error line (Python start-up and imports included), and the CPU time it used (what the wall time is on an idle "
        "machine, less waiting on the network probe). Median (range) over the repeats.",
        "",
        *table(["case", "wall median (s)", "wall range (s)", "CPU median (s)", "target (s)", "exit code", "first line"],
               rows),
        "",
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    sys.exit(main())
