"""Per-submap CPU cost of the SLAM back end (everything but the frontend model), by stage.

The synthetic world (rendered at 518x294, VGGT's working size) is replayed lap after lap through
the full pipeline with the simulated frontend, submaps of 16 new keyframes (17 frames with the
shared one, 18 with a loop frame) and ORB retrieval. Every stage's time is recorded per submap;
the report gives medians over submaps 10-20 and the last ten, to show the cost does not grow with
the map, and the memory kept per keyframe.

    python benchmarks/bench_pipeline.py --submaps 300

With ``--fits-record PATH`` and then, in a second run with the same settings, ``--fits-replay PATH``,
the second run hands back the first one's link fits instead of fitting (``harness/fit_memo.py``):
its per-submap cost is the model-free work without the fits.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import resource
import sys
import tempfile
import time

import numpy as np

from harness import (LapSource, make_pipeline, parse_settings, result_file, simulated_config, synthetic_world,
                     write_report)

STAGES = ("retrieval", "points", "alignment", "loops", "backend", "store")
RANGES = ((10, 20), (290, 300), (990, 1000), (2990, 3000))
"""Submap ranges of the long-run table (the ones a run reaches)."""


def _status_mib(field: str) -> float:
    """A memory field of ``/proc/self/status`` in MiB (the whole run's peak where /proc is missing)."""
    try:
        for line in open("/proc/self/status", encoding="ascii"):
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def resident_mib() -> float:
    """The process's resident memory now, MiB (``VmRSS``)."""
    return _status_mib("VmRSS")


def peak_mib() -> float:
    """The process's peak resident memory since the last :func:`reset_peak`, MiB (``VmHWM``)."""
    return _status_mib("VmHWM")


def settled_mib() -> float:
    """Resident memory after a garbage collection and, where glibc allows, returning freed heap
    pages to the system (``malloc_trim``), MiB: what the live objects hold."""
    from sl4slam.heap import return_freed_memory

    return_freed_memory()
    return resident_mib()


def memory_parts(pipeline, source) -> list[tuple[str, float]]:
    """What each part of a finished run holds, MiB: the resident memory each release frees, in this
    order (the preloaded lap when held in RAM, retrieval, the graph with the readers that keep it, the keyframe
    store, the rest of the pipeline). Destroys the pipeline's parts; call it last."""
    steps = [("the preloaded lap (the replay's own)", lambda: setattr(source, "_frames", None))] if source.preloaded_bytes else []
    steps += [
        ("retrieval (ORB features, words, hashed rows)", lambda: setattr(pipeline, "retrieval", None)),
        ("the graph (iSAM2 and its factors)", lambda: [setattr(pipeline, name, None)
                                                      for name in ("backend", "metric_frame", "loop_verifier")]),
        ("the keyframe store", lambda: setattr(pipeline, "keyframe_store", None)),
        ("the rest of the pipeline (ledger, frontend, selector)", lambda: pipeline.__dict__.clear()),
    ]
    parts, before = [], settled_mib()
    for name, release in steps:
        release()
        after = settled_mib()
        parts.append((name, before - after))
        before = after
    parts.append(("left: the interpreter and its libraries", before))
    return parts


def reset_peak() -> bool:
    """Start a new peak-memory mark (Linux: ``/proc/self/clear_refs``); whether that was possible."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as handle:
            handle.write("5")
        return True
    except OSError:
        return False


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--submaps", type=int, default=300)
    parser.add_argument("--retrieval", default="orb")
    parser.add_argument("--graph", default=None, help="backend.graph (default: the setting's default, the keyframe graph)")
    parser.add_argument("--perspective", type=float, default=0.1)
    parser.add_argument("--overlap", type=int, default=1, help="shared frames between submaps (the recorded figures: 1)")
    parser.add_argument("--keyframes-in-ram", type=int, default=None,
                        help="submap.keyframes_in_ram (default: the setting's default; 0: every keyframe in RAM)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="another setting for the run, as a config key (repeatable), e.g. alignment.max_correspondences=8000")
    parser.add_argument("--plot", help="also draw ms per submap and RSS against the submap index into this PNG")
    parser.add_argument("--memory-parts", action="store_true",
                        help="at the end, release the run's parts one by one and report what each held")
    parser.add_argument("--lap-in-ram", action="store_true",
                        help="hold the decoded lap in the process (as the figures before 2026-11-29 did: 610 MiB "
                             "of the resident memory) instead of reading its frames back from files")
    parser.add_argument("--keep-running-state", action="store_true",
                        help="finish() without releasing retrieval's database and iSAM2 first (as the figures "
                             "before 2026-11-29 did), to measure what the release saves")
    parser.add_argument("--fits-record", metavar="PATH",
                        help="keep every link fit's result in PATH, for a second run with --fits-replay")
    parser.add_argument("--fits-replay", metavar="PATH",
                        help="hand back the fits recorded in PATH instead of fitting (the same settings and "
                             "--submaps as the recording run): the model-free cost without the fits "
                             "(harness/fit_memo.py)")
    parser.add_argument("--out", default=str(result_file("pipeline")))
    args = parser.parse_args()
    if args.fits_record and args.fits_replay:
        parser.error("--fits-record and --fits-replay exclude each other")
    memo = None
    if args.fits_record or args.fits_replay:
        from harness.fit_memo import FitMemo

        memo = FitMemo("record" if args.fits_record else "replay", args.fits_record or args.fits_replay)
        memo.install()
    from sl4slam.io import open_source

    config = simulated_config({
        "retrieval.kind": args.retrieval, "sim.perspective": args.perspective, "sim.distort_first_submap": False,
        **({"backend.graph": args.graph} if args.graph else {}),
        "submap.overlap": args.overlap,  # ... with one shared frame (the frames per forward set the cost)
        "overlap": False,  # one submap after the other: each submap's stages timed on their own
        **({"submap.keyframes_in_ram": args.keyframes_in_ram} if args.keyframes_in_ram is not None else {}),
        **parse_settings(args.set, "--set"),
    })
    # the lap decoded once, so the benchmark does not time PNG decoding; its frames are read back from
    # raw files (the page cache), so that the process holds only what the run holds
    lap_folder = tempfile.TemporaryDirectory(prefix="sl4slam-lap-")
    source = LapSource(open_source(str(synthetic_world(518, 294))), laps=10_000, preload=True,
                       folder=None if args.lap_in_ram else lap_folder.name)
    pipeline = make_pipeline(config)
    keyframe_seconds: list[float] = []  # frames whose feed ran no submap: keyframe selection
    rss_trace: list[tuple[int, float]] = []  # (keyframes stored, resident MiB) every 10 submaps
    submap_trace: list[int] = []  # the submap count of each RSS sample
    pipeline.start(source, progress=False)
    start = time.perf_counter()
    for frame in source:
        before = pipeline.num_submaps
        t0 = time.perf_counter()
        pipeline.feed(frame)
        if pipeline.num_submaps == before:
            keyframe_seconds.append(time.perf_counter() - t0)
            continue
        done = pipeline.num_submaps
        if done % 10 == 0:
            rss_trace.append((len(pipeline.keyframes), resident_mib()))
            submap_trace.append(done)
            recent = [sum(s.get(k, 0.0) for k in STAGES) for s in pipeline.ledger.submap_seconds[-10:]]
            print(f"submap {done}: {time.perf_counter() - start:.0f} s, loops {pipeline.num_loops}, "
                  f"RSS {rss_trace[-1][1]:.0f} MiB, model-free median of the last 10 "
                  f"{np.median(recent) * 1000:.0f} ms", flush=True)
        if done >= args.submaps:
            break
    pipeline.stop_requested = True  # the keyframes still waiting make no last submap
    loop_peak, loop_end = peak_mib(), resident_mib()
    in_ram = pipeline.keyframe_store.ram_bytes() / len(pipeline.keyframes)  # before the release spills the newest
    t0 = time.perf_counter()
    # once per run, as `sl4slam run` ends (`finish(release=True)`): the input closed, the running state
    # released and its memory returned, the final polish, every keyframe's pose; the peak mark is reset
    # after the release so that the polish's own peak is measured from what the run then holds
    pipeline.flush()
    if not args.keep_running_state:
        pipeline.release()
    released = resident_mib()
    separate_peak = reset_peak()
    polish_notes = [note for note in pipeline.result().stats["notes"] if "final polish" in note]
    result_seconds = time.perf_counter() - t0
    finish_peak = peak_mib()
    per_submap = pipeline.ledger.submap_seconds
    totals = np.array([sum(s.get(k, 0.0) for k in STAGES) for s in per_submap])
    n = len(per_submap)
    # the fixed ranges of the long-run table that this run reaches, then its last ten submaps
    windows = [(f"submaps {a}-{b}", slice(a, b)) for a, b in RANGES if b <= n - 10 or (a, b) == RANGES[0]]
    windows.append(("last 10 submaps", slice(n - 10, n)))
    early, late = windows[0][1], windows[-1][1]

    def med(values, window) -> float:
        return float(np.median(np.asarray(values)[window])) * 1000

    rows = []
    for stage in STAGES + ("retrieval_describe", "frontend"):
        values = [s.get(stage, 0.0) for s in per_submap]
        rows.append(f"| {stage} | " + " | ".join(f"{med(values, w):.1f}" for _, w in windows) + " |")
    odometry_only = np.array([n == 0 for n in pipeline.ledger.submap_loops])
    loop_backend = [s.get("backend", 0.0) * 1000 for s, n in zip(per_submap, pipeline.ledger.submap_loops) if n]
    stored = sum(k.nbytes for k in pipeline.keyframes) / len(pipeline.keyframes)
    store = pipeline.keyframe_store
    on_disk = (sum(p.stat().st_size for p in store.folder.glob("*.npz")) / store.spilled) if store.spilled else 0.0
    half_trace = rss_trace[len(rss_trace) // 2:]
    growth = (np.polyfit([k for k, _ in half_trace], [m for _, m in half_trace], 1)[0] * 1024 * 1024
              if len(half_trace) >= 2 else float("nan"))
    H, W = pipeline.keyframes[0].shape
    rss = max(loop_peak, finish_peak) if separate_peak else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    lines = [
        "## Per-submap cost of the back end (CPU)",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, 24 GiB, no GPU; "
        f"Python {platform.python_version()}. Date: {datetime.date.today()}.",
        f"Command: `python benchmarks/bench_pipeline.py {' '.join(sys.argv[1:])}`.",
        f"Synthetic world at {W}x{H}, replayed lap after lap; submaps of 16 new keyframes (17 frames, 18 with a "
        f"loop frame); simulated frontend (perspective 0.1, noise and outlier blobs at their defaults); "
        f"{args.retrieval} retrieval; SL(4) {getattr(pipeline.backend, 'design', '')} graph. {len(per_submap)} submaps, {len(pipeline.keyframes)} keyframes, "
        f"{pipeline.num_loops} loops.",
        "",
        "Median milliseconds per submap:",
        "",
        "| stage | " + " | ".join(name for name, _ in windows) + " |",
        "|---|" + "---|" * len(windows),
        *rows,
        "| **total without frontend and descriptors** | " + " | ".join(f"**{med(totals, w):.1f}**" for _, w in windows) + " |",
        "",
        f"Last 10 / submaps 10-20, total: {med(totals, late) / med(totals, early):.2f}"
        + "".join(f"; last 10 / {name}: {med(totals, late) / med(totals, w):.2f}" for name, w in windows[1:-1])
        + f". Over the run the "
        f"median total is {np.median(totals) * 1000:.1f} ms and the 90th percentile {np.percentile(totals, 90) * 1000:.1f} ms.",
        "",
        f"Submaps that closed a loop: {int((~odometry_only).sum())}; their backend update (iSAM2 steps "
        f"again only while some step exceeds 5e-2) took median "
        f"{np.median(loop_backend) if loop_backend else 0:.1f} ms, max {max(loop_backend) if loop_backend else 0:.1f} ms. "
        f"The loops found here reach back to the first lap, so their span grows with the map.",
        "",
        f"Once per run, `finish()` ({'' if args.keep_running_state else 'retrieval and iSAM2 released, then '}"
        f"Gauss-Newton polish of the graph, then every keyframe's pose): "
        f"{result_seconds * 1000:.0f} ms for {len(per_submap)} submaps"
        + (f"; resident memory {loop_end:.0f} MiB at the end of the loop (its peak {loop_peak:.0f} MiB), "
           f"{'' if args.keep_running_state else f'{released:.0f} MiB once released, '}"
           f"peak during the polish and the poses {finish_peak:.0f} MiB." if separate_peak else ".")
        + (f" The polish: {'; '.join(polish_notes)}." if polish_notes else
           f" The polish took the whole graph at once (within `backend.polish_memory_mib` = {config.backend.polish_memory_mib})."),
        "",
        f"Keyframe selection (runs on every input frame, not per submap): median "
        f"{np.median(keyframe_seconds) * 1000:.1f} ms per frame.",
        "",
        (f"Of the resident memory, {source.preloaded_bytes / 2**20:.0f} MiB is the preloaded lap "
         f"({len(source.base)} frames' images and depth maps): the replay's own, not held by a run that "
         f"reads its frames from a source." if source.preloaded_bytes else
         f"The lap's {len(source.base)} decoded frames are read back from raw files (the page cache): the "
         f"resident memory is the run's own."),
        "",
        f"Memory kept per keyframe: {stored / 1e6:.3f} MB (float16 depth, bit-packed mask, half-resolution uint8 confidence rank, camera; no colours); "
        f"process peak RSS {rss:.0f} MiB after {len(pipeline.keyframes)} keyframes.",
        "",
        f"Keyframes with their arrays in RAM: "
        f"{f'the newest {config.submap.keyframes_in_ram}' if config.submap.keyframes_in_ram else 'all'} "
        f"(`submap.keyframes_in_ram`); {store.spilled} spilled to files. Keyframe arrays held in RAM: "
        f"{in_ram:.0f} bytes per keyframe on average over the run; on disk {on_disk / 1e6:.3f} MB per spilled "
        f"keyframe. Resident memory grew by {growth / 1e3:.1f} kB per keyframe over the second half of the run "
        f"(a line through RSS against keyframes, sampled every 10 submaps).",
        "",
    ]
    if args.memory_parts:
        keyframes = len(pipeline.keyframes)
        del store  # the report's own reference: the store is released with the pipeline's
        lines += ["What the finished run holds, part by part (resident memory freed by releasing each, "
                  "after a garbage collection and `malloc_trim`):", "", "| part | MiB | bytes per keyframe |", "|---|---|---|"]
        lines += [f"| {name} | {mib:.0f} | {mib * 2**20 / keyframes:.0f} |" for name, mib in memory_parts(pipeline, source)]
        lines.append("")
    if memo is not None:
        memo.save()
        lines += [f"Link fits {'recorded in' if memo.mode == 'record' else 'replayed from'} `{memo.path.name}`"
                  + (f": {memo.hits} handed back, {memo.misses} not recorded (fitted)." if memo.mode == "replay"
                     else f": {len(memo.fits)} fits."), ""]
    write_report(args.out, lines)
    if args.plot:
        plot(args.plot, totals, submap_trace, [m for _, m in rss_trace])


def plot(path: str, totals: np.ndarray, submaps: list[int], rss_mib: list[float]) -> None:
    """Milliseconds per submap (each, and a running median over 51) and RSS against the submap index."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ms = totals * 1000
    half = 25
    running = [np.median(ms[max(0, i - half): i + half + 1]) for i in range(len(ms))]
    figure, axis = plt.subplots(figsize=(9, 4))
    axis.plot(ms, ",", color="0.6", label="model-free ms per submap")
    axis.plot(running, color="C0", label="running median (51 submaps)")
    axis.set_xlabel("submap")
    axis.set_ylabel("ms per submap")
    axis.set_ylim(0, float(np.percentile(ms, 99)) * 1.2)
    memory = axis.twinx()
    memory.plot(submaps, np.asarray(rss_mib) / 1024, color="C3", label="RSS")
    memory.set_ylabel("RSS (GiB)")
    memory.set_ylim(0, max(rss_mib) / 1024 * 1.2)
    lines = axis.get_legend_handles_labels()
    more = memory.get_legend_handles_labels()
    axis.legend(lines[0] + more[0], lines[1] + more[1], loc="upper left")
    figure.tight_layout()
    figure.savefig(path, dpi=100)


if __name__ == "__main__":
    sys.exit(main())
