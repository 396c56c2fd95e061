"""Viewer: time to first frame and memory for a 2-million-point map.

A result folder with ``--keyframes`` keyframes at 518x294 looking into a room with a desk (about
2M confident points on its surfaces; fabricated with exactly known cameras, as the tests make
them: ``write_known_result(scene="room")``) is shown with ``sl4slam view`` in a subprocess and
opened in headless Chromium (software WebGL: no GPU here, so browser-side times are pessimistic).
For each point budget (250k, the default 1M, and one above the map's size, i.e. no decimation),
per run:

* ready: from starting ``sl4slam view`` to its "loaded" line (read, decimate, measure the point
  spacing, serve);
* first frame: from starting ``sl4slam view`` to the first screenshot whose 3D canvas shows the
  map (the browser is already open; the page is loaded when the server is ready);
* drawn: the fraction of the canvas that first screenshot covers (``tests/browser.py``);
* memory: peak resident memory of the viewer process (VmHWM) after the first frame.

Writes ``benchmarks/results/viewer.md`` (or ``--results PATH``).
Usage: ``python benchmarks/bench_viewer.py [--keyframes 17] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from browser import chromium_path, drawn_fraction, interrupt, launch  # noqa: E402
from result_folders import write_known_result  # noqa: E402

RESULTS = HERE / "results" / "viewer.md"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peak_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def one_run(page, folder: Path, budget: int) -> tuple[float, float, float, float]:
    port = free_port()
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "sl4slam.cli", "view", str(folder), "--port", str(port),
                             "--point-budget", str(budget)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        while True:
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError(proc.stderr.read())
            if line.startswith("loaded"):
                ready = time.perf_counter() - start
                break
        page.goto(f"http://127.0.0.1:{port}")
        # a screenshot waits for the next rendered frame: software WebGL draws a large cloud slowly
        while (drawn := drawn_fraction(page.screenshot(timeout=600_000))) < 0.05:
            if time.perf_counter() - start > 600:
                raise RuntimeError("no frame within 600 s")
            time.sleep(0.1)
        first = time.perf_counter() - start
        memory = peak_rss_mib(proc.pid)
    finally:
        page.goto("about:blank")  # disconnect first, so the server is not busy sending when it stops
        interrupt(proc)
    return ready, first, drawn, memory


def main() -> None:
    from playwright.sync_api import sync_playwright

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=17)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--results", type=Path, default=RESULTS, help="where to write the table")
    args = parser.parse_args()
    chromium = chromium_path()
    rows = {}
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch) / "run"
        truth = write_known_result(folder, count=args.keyframes, width=518, height=294, submap_size=4, confidence=True,
                                   scene="room")
        points = sum(int(m.sum()) for m in truth["masks"].values())
        with sync_playwright() as playwright:
            browser = launch(playwright, Path(scratch) / "profile", chromium)
            page = browser.new_page()
            page.set_default_timeout(600_000)
            for budget in (250_000, 1_000_000, points + 1):
                for _ in range(args.repeats):
                    rows.setdefault(budget, []).append(one_run(page, folder, budget))
            browser.close()
    load = os.getloadavg()[0]
    lines = [
        "## Viewer: time to first frame, memory",
        "",
        f"Machine: {os.cpu_count()}-core CPU, no GPU (headless Chromium with software WebGL), shared (1-minute load "
        f"average {load:.1f} at the end of the run). Python {platform.python_version()}. Date: {time.strftime('%Y-%m-%d')}.",
        f"Command: `python benchmarks/bench_viewer.py --keyframes {args.keyframes} --repeats {args.repeats}`",
        "",
        f"A room with a desk, {points:,} confident points ({args.keyframes} keyframes at 518x294, "
        f"{(args.keyframes + 3) // 4} submaps, float16 confidence saved); medians of {args.repeats} runs. *Ready*: "
        "`sl4slam view` started -> map read, decimated, point spacing measured, served. *First frame*: `sl4slam view` "
        "started -> the browser's 3D canvas shows the map; *drawn*: the fraction of the canvas it covers then. "
        "*Memory*: peak resident memory of the viewer process.",
        "",
        "| point budget | points sent | ready (s) | first frame (s) | drawn | viewer memory (MiB) |",
        "|---|---|---|---|---|---|",
    ]
    for budget, values in rows.items():
        sent = min(budget, points)
        label = f"{budget:,}" if budget <= points else f"{budget:,} (all points)"
        lines.append(f"| {label} | {sent:,} | {statistics.median(v[0] for v in values):.1f} | "
                     f"{statistics.median(v[1] for v in values):.1f} | {statistics.median(v[2] for v in values):.2f} | "
                     f"{statistics.median(v[3] for v in values):.0f} |")
    args.results.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
