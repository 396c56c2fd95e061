"""Viewer: time to its port opening, to first frame, and memory for a 2-million-point map.

A result folder with ``--keyframes`` keyframes at 518x294 looking into a room with a desk (about
2M confident points on its surfaces; fabricated with exactly known cameras, as the tests make
them: ``write_known_result(scene="room")``) is shown with ``sl4slam view`` in a subprocess and
opened in headless Chromium (software WebGL: no GPU here, so browser-side times are pessimistic).
For each point budget (250k, the default 1M, and one above the map's size, i.e. no decimation),
per run:

* port open: from starting ``sl4slam view`` to its port accepting a TCP connection;
* ready: from starting ``sl4slam view`` to its "loaded" line (read, decimate, measure the point
  spacing, serve);
* first frame: from starting ``sl4slam view`` to the first screenshot whose 3D canvas shows the
  map (the browser is already open; the page is loaded when the server is ready);
* drawn: the fraction of the canvas that first screenshot covers (``tests/browser.py``);
* memory: peak resident memory of the viewer process (VmHWM) after the first frame.

Writes ``benchmarks/results/viewer.md`` (or ``--results PATH``).
Usage: ``python benchmarks/bench_viewer.py [--keyframes 17] [--repeats 3]``.

``--open-only`` (no browser): port open and ready only, for two maps: the room above with
``--keyframes`` keyframes, and a run of the simulated frontend on a synthetic sequence
(``sl4slam synth --frames 200 --width 640 --height 480`` then ``sl4slam run --frontend simulated``:
133 keyframes in 9 submaps, tens of millions of confident points decimated to the 1M budget), or
the result folder ``--result DIR`` instead of both. ``--before-src DIR`` also runs, alternately in
each repeat, the viewer of another source tree (e.g. the committed code:
``git archive HEAD src | tar -x -C /tmp/before``, then ``--before-src /tmp/before/src``). Writes
``benchmarks/results/viewer_open.md``.
Usage: ``python benchmarks/bench_viewer.py --open-only --keyframes 8 --repeats 5 [--before-src DIR]``.
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


from harness import REPO, cpu_model, peak_rss_bytes, result_file, synthetic_world, table, write_report

sys.path.insert(0, str(REPO / "tests"))

from browser import chromium_path, drawn_fraction, interrupt, launch  # noqa: E402
from result_folders import write_known_result  # noqa: E402

RESULTS = result_file("viewer")
OPEN_RESULTS = result_file("viewer_open")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peak_rss_mib(pid: int) -> float:
    """Peak resident memory of process ``pid`` in MiB (NaN where it cannot be read)."""
    peak = peak_rss_bytes(pid, fallback=False)
    return peak / 2**20 if peak else float("nan")


def wait_for_port(proc: subprocess.Popen, port: int, start: float, bound_s: float = 600.0) -> float:
    """Seconds from ``start`` to ``port`` accepting a TCP connection (tried every 10 ms); the
    connection then makes one HTTP request, so that the server sees a well-formed one."""
    while True:
        try:
            connection = socket.create_connection(("127.0.0.1", port), timeout=bound_s)
        except OSError:
            if proc.poll() is not None:
                raise RuntimeError(f"the viewer exited before its port opened: {proc.stderr.read()}") from None
            if time.perf_counter() - start > bound_s:
                raise RuntimeError(f"port {port} not open within {bound_s:.0f} s") from None
            time.sleep(0.01)
            continue
        opened = time.perf_counter() - start
        with connection:
            connection.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
            while connection.recv(65536):
                pass
        return opened


def start_viewer(folder: Path, budget: int, env: dict | None = None) -> tuple[subprocess.Popen, int, float]:
    """``sl4slam view folder`` on a free port: (process, port, start time)."""
    port = free_port()
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "sl4slam.cli", "view", str(folder), "--port", str(port),
                             "--point-budget", str(budget)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    return proc, port, start


def wait_until_loaded(proc: subprocess.Popen, start: float) -> float:
    """Seconds from ``start`` to the viewer's "loaded" line."""
    while True:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(proc.stderr.read())
        if line.startswith("loaded"):
            return time.perf_counter() - start


def open_run(folder: Path, budget: int, env: dict | None = None, name: str = "") -> tuple[float, float]:
    """One ``sl4slam view`` without a browser: (port open, ready) in seconds."""
    proc, port, start = start_viewer(folder, budget, env)
    try:
        opened = wait_for_port(proc, port, start)
        ready = wait_until_loaded(proc, start)
    finally:
        try:
            interrupt(proc, bound_s=60.0)
        except AssertionError as exc:  # reported, not fatal: the timings above are complete
            print(f"warning ({name}): {exc}", file=sys.stderr)
    return opened, ready


def one_run(page, folder: Path, budget: int) -> tuple[float, float, float, float, float]:
    proc, port, start = start_viewer(folder, budget)
    try:
        opened = wait_for_port(proc, port, start)
        ready = wait_until_loaded(proc, start)
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
    return ready, first, drawn, memory, opened


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=17)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--results", type=Path, default=None, help="where to write the table")
    parser.add_argument("--open-only", action="store_true", help="no browser: port open and ready only")
    parser.add_argument("--result", type=Path, default=None, help="--open-only: this result folder only")
    parser.add_argument("--before-src", type=Path, default=None,
                        help="--open-only: also run the viewer of this source tree (its src/ folder), alternately")
    args = parser.parse_args()
    if args.open_only:
        open_only(args)
        return
    from playwright.sync_api import sync_playwright

    args.results = args.results or RESULTS
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
        *table(["point budget", "points sent", "port open (s)", "ready (s)", "first frame (s)", "drawn",
                "viewer memory (MiB)"],
               [[f"{budget:,}" if budget <= points else f"{budget:,} (all points)", f"{min(budget, points):,}",
                 f"{statistics.median(v[4] for v in values):.2f}", f"{statistics.median(v[0] for v in values):.1f}",
                 f"{statistics.median(v[1] for v in values):.1f}", f"{statistics.median(v[2] for v in values):.2f}",
                 f"{statistics.median(v[3] for v in values):.0f}"] for budget, values in rows.items()]),
    ]
    write_report(args.results, lines)


def simulated_run(scratch: Path, frames: int = 200) -> Path:
    """A result folder written by ``sl4slam run --frontend simulated`` on the synthetic world of
    ``frames`` frames at 640x480 (what ``sl4slam synth --frames N --width 640 --height 480`` writes)."""
    world, out = synthetic_world(640, 480, frames), scratch / "simulated_run"
    subprocess.run([sys.executable, "-m", "sl4slam.cli", "run", str(world), "--out", str(out),
                    "--frontend", "simulated", "--quiet"], check=True, stdout=subprocess.DEVNULL)
    return out


def map_size(folder: Path, budget: int) -> tuple[int, int, int, int]:
    """(keyframes, submaps, confident points, points shown) of a result folder."""
    from sl4slam.result.reading import load_result
    from sl4slam.viewer.result import expected_totals, mask_count, submap_groups

    records = load_result(folder).keyframes
    masks = [mask_count(r.path) for r in records]
    totals = expected_totals(records, masks, min(1.0, budget / max(1, sum(n for n, _ in masks))))
    return len(records), len(submap_groups(records)), totals.full, totals.shown


def open_only(args) -> None:
    """Port open and ready for each map, with ``--before-src`` alternately before this tree's viewer."""
    budget = 1_000_000
    results = args.results or OPEN_RESULTS
    trees = {"this tree": None}
    if args.before_src is not None:
        trees = {"before": {**os.environ, "PYTHONPATH": str(args.before_src.resolve())}, "after": None}
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        if args.result is not None:
            maps = {f"`{args.result.name}`": args.result}
        else:
            room = scratch / "room"
            write_known_result(room, count=args.keyframes, width=518, height=294, submap_size=4, confidence=True,
                               scene="room")
            maps = {f"room, {args.keyframes} keyframes at 518x294 (`write_known_result`)": room,
                    "simulated run, 200 frames at 640x480 (`sl4slam synth` + `sl4slam run --frontend simulated`)":
                        simulated_run(scratch)}
        for label, folder in maps.items():
            times = {name: [] for name in trees}
            for _ in range(args.repeats):
                for name, env in trees.items():
                    times[name].append(open_run(folder, budget, env, name))
            keyframes, submaps, confident, shown = map_size(folder, budget)
            for name, values in times.items():
                rows.append([label, f"{keyframes} / {submaps}", f"{confident:,}", f"{shown:,}", name,
                             f"{statistics.median(v[0] for v in values):.2f}", f"{statistics.median(v[1] for v in values):.1f}"])
    load = os.getloadavg()[0]
    command = ("python benchmarks/bench_viewer.py --open-only"
               + (f" --result {args.result}" if args.result is not None else f" --keyframes {args.keyframes}")
               + f" --repeats {args.repeats}"
               + (f" --before-src {args.before_src}" if args.before_src is not None else ""))
    lines = [
        "## Viewer: time to its port opening",
        "",
        f"Machine: {os.cpu_count()}-core CPU ({cpu_model()}), shared (1-minute load average {load:.1f} at the end of "
        f"the run). Python {platform.python_version()}. Date: {time.strftime('%Y-%m-%d')}.",
        f"Command: `{command}`" + (f" (before: another source tree, e.g. the committed code through "
                                   f"`git archive HEAD src | tar -x -C {args.before_src.parent}`)"
                                   if args.before_src is not None else ""),
        "",
        f"`sl4slam view` at the default point budget of 1M, no browser; medians of {args.repeats} runs"
        + (", before and after alternating" if args.before_src is not None else "")
        + ". *Port open*: `sl4slam view` started -> its port accepts a TCP connection (Python's start and imports "
        "included). *Ready*: started -> its \"loaded\" line (map read, decimated, point spacing measured, scene sent).",
        "",
        *table(["map", "keyframes / submaps", "confident points", "points shown", "viewer", "port open (s)",
                "ready (s)"], rows),
    ]
    write_report(results, lines)


if __name__ == "__main__":
    main()
