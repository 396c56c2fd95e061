"""The keyframe graph (VGGT-SLAM 2.0) against the submap graph (VGGT-SLAM): accuracy, cost, loops.

Three parts, each a section of the report:

- **accuracy**: ATE (``evo_ape -as`` RMSE, metres) over several simulator seeds, loops accepted and
  rejected, fallbacks (shared frames measured by a weaker model, e.g. on the floor-only stretch of the
  synthetic world) and map segments, for the graph designs of :data:`DESIGNS`, on the synthetic world
  (600 frames, 320x240, one lap with a floor-only stretch), the TUM fr1/xyz excerpt (37 frames) and
  TUM fr1/desk (613 frames; both real depth and poses) with the simulated frontend under a simulator
  profile (``--profile``, default ``vggt``); ``--worlds`` and ``--designs`` pick a subset;
- **cost**: the synthetic world (160x120) replayed lap after lap for ``--submaps`` submaps with each
  graph, each in its own process: per-submap milliseconds of the graph steps (``backend``: adding the
  submap and the iSAM2 update; ``loops``: verifying and adding loops) at submaps 10-20 and at the
  last ten, timed side by side (two replays of the same run advancing in turn, see :func:`cost_child`),
  graph size, process peak memory, the final polish and the ATE; the keyframe graph twice:
  as configured (revisits of closed places held as priors in iSAM2) and with every loop in iSAM2;
- **verification**: the attention loop check (the simulated frontend's true-overlap stand-in for
  VGGT's image-match ratio) at false-loop rates 0.1 and 0.3 (``--false-loop-rate``): injected
  false loops rejected, and true loops accepted, with the check on and off, on three laps of the
  synthetic world (160x120) so that retrieval proposes many loops.

    python benchmarks/bench_keyframe_graph.py --seeds 5 --submaps 300

The report is written to ``benchmarks/results/keyframe_graph.md``; ``--parts`` runs a subset. BLAS runs
single-threaded (set before numpy loads): on a shared 2-core machine OpenBLAS's worker threads spin
against the other processes, and one 16x16 normal matrix of the DLT took 0.7 s instead of 3 ms.
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import dataclasses  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable, Iterator  # noqa: E402

import numpy as np  # noqa: E402

from harness import (LapSource, add_parallel_arguments, grid, loop_counts, make_pipeline, parallel_options, result_ate,  # noqa: E402
                     result_file, run_all, run_sequence, shared_sequence, simulated_config, synthetic_world,
                     write_report)

TUM = {"TUM fr1/xyz (37 frames)": shared_sequence("xyz37"), "TUM fr1/desk": shared_sequence("desk")}
WORLDS = {"synthetic": "synthetic world", "xyz": "TUM fr1/xyz (37 frames)", "desk": "TUM fr1/desk"}
DESIGNS = {
    # name: (graph, alignment model, what it is)
    "submap": ("submap", "auto", "VGGT-SLAM: a node per submap, 15-DOF fit (calibration link on degenerate frames)"),
    "keyframe": ("keyframe", "auto", "VGGT-SLAM 2.0: a node per keyframe, calibration-and-scale links"),
    "keyframe+15dof": ("keyframe", "sl4", "a node per keyframe, the submap graph's links"),
    "submap+calibration": ("submap", "calibration", "a node per submap, calibration-and-scale links"),
    "keyframe+hybrid": ("keyframe", "hybrid", "a node per keyframe, the calibration link unless the 15-DOF fit "
                                              "explains the shared frame markedly better"),
    "submap+hybrid": ("submap", "hybrid", "a node per submap, hybrid links"),
}


def design_config(design: str, profile: str, seed: int, retrieval: str = "orb", perspective: float | None = None,
                  **settings):
    """The config of a graph design under a simulator profile (the metric upgrade off), ``settings`` on top."""
    graph, model, _ = DESIGNS[design]
    distortion = {"sim.perspective": perspective} if perspective is not None else {}
    return simulated_config({"sim.profile": profile, **distortion, "sim.seed": seed, "backend.graph": graph,
                             "alignment.model": model, "retrieval.kind": retrieval,
                             # the trajectory is Sim(3)-aligned for the ATE: the upgrade changes nothing there
                             "upgrade.mode": "off", **settings})


def worlds(names: list[str]) -> dict[str, Path]:
    """The accuracy part's sequences (``names`` from :data:`WORLDS`); TUM ones only where present."""
    out = {}
    for name in names:
        title = WORLDS[name]
        if name == "synthetic":
            out[title] = synthetic_world(320, 240)
        elif (TUM[title] / "groundtruth.txt").is_file():
            out[title] = TUM[title]
    return out


# ---------------------------------------------------------------------------- accuracy
def accuracy_run(world: Path, design: str, profile: str, seed: int, perspective: float | None = None) -> dict:
    run = run_sequence(design_config(design, profile, seed, perspective=perspective), world)
    result = run.result
    edges = result.edges
    planar = [e for e in edges if e.kind == "odometry" and e.accepted and e.fallback
              and ("flat" in e.fallback or "planar" in e.fallback)]
    return {"ate": run.ate(), "loops": result.stats["loops"], "rejected": result.stats["loops_rejected"],
            "fallbacks": result.stats["fallbacks"], "planar_fallbacks": len(planar), "segments": result.stats["segments"],
            "submaps": result.stats["submaps"], "seconds": run.seconds,
            "reasons": sorted({e.reason.split(" (")[0] for e in edges if e.kind == "loop" and not e.accepted and e.reason})}


def accuracy(profile: str, seeds: int, names: list[str], designs: list[str], perspective: float | None = None,
             parallel: dict | None = None) -> list[str]:
    setting = f"{profile} profile" + (f", perspective {perspective}" if perspective is not None else "")
    lines = [f"### Accuracy ({setting}, {seeds} seeds)", "",
             "ATE RMSE in metres (`evo_ape -as`), median and range over the seeds; counts are means per run. "
             "Fallbacks: odometry edges a weaker model measured (planar: those on a flat or planar shared frame).", ""]
    for world_name, world in worlds(names).items():
        outcomes = run_all(accuracy_run, [(world, design, profile, seed, perspective) for design in designs
                                          for seed in range(seeds)], **(parallel or {}))
        table = {design: outcomes[number * seeds:(number + 1) * seeds] for number, design in enumerate(designs)}
        for design, runs in table.items():
            print(f"{world_name} {design}: ATE median {np.median([r['ate'] for r in runs]):.4f}", flush=True)
        base = np.median([r["ate"] for r in table[designs[0]]])
        lines += [f"**{world_name}** ({table[designs[0]][0]['submaps']} submaps)", "",
                  f"| design | ATE median | range | / {designs[0]} | loops accepted | rejected | fallbacks (planar) "
                  "| segments | seconds | rejection reasons |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for design, runs in table.items():
            ates = np.array([r["ate"] for r in runs])

            def mean(key: str) -> float:
                return float(np.mean([r[key] for r in runs]))

            reasons = sorted({reason for r in runs for reason in r["reasons"]})
            lines.append(f"| {design} | {np.median(ates):.4f} | {ates.min():.4f}-{ates.max():.4f} | "
                         f"{np.median(ates) / base:.2f} | {mean('loops'):.1f} | {mean('rejected'):.1f} | "
                         f"{mean('fallbacks'):.1f} ({mean('planar_fallbacks'):.1f}) | {mean('segments'):.1f} | "
                         f"{mean('seconds'):.0f} | {'; '.join(reasons)} |")
        lines += ["", "Per seed (ATE): " + "; ".join(
            f"{design} " + " ".join(f"{r['ate']:.4f}" for r in runs) for design, runs in table.items()), ""]
    lines += ["Designs: " + "; ".join(f"**{name}**: {DESIGNS[name][2]}" for name in designs) + ".", ""]
    return lines


# ---------------------------------------------------------------------------- cost
def small_world() -> Path:
    """The lap replays' world: 600 frames at 160x120."""
    return synthetic_world(160, 120)


def lap_config(design: str, profile: str, seed: int, **settings):
    """The lap replay's config: the 160x120 world's keyframe threshold (half the pixels of the 320x240
    threshold), one submap after the other (each submap done when its frame is fed), ``settings`` on top."""
    return design_config(design, profile, seed, **{"keyframes.tau_disparity": 12.0, "overlap": False, **settings})


def lap_replay(world: Path, config, prepare: Callable | None = None) -> Iterator:
    """The lap replay through the pipeline, yielding the pipeline after each submap; ``prepare`` is
    called on the pipeline before the first."""
    from sl4slam.io import open_source

    source = LapSource(open_source(str(world)), laps=100_000, preload=True)  # the replay does not time PNG decoding
    pipeline = make_pipeline(config)
    pipeline.start(source, progress=False)
    if prepare is not None:
        prepare(pipeline)
    for frame in source:
        before = pipeline.num_submaps
        pipeline.feed(frame)
        if pipeline.num_submaps > before:
            yield pipeline


def advance_to(replay: Iterator, submaps: int):
    """Advance a :func:`lap_replay` until ``submaps`` submaps are done."""
    for pipeline in replay:
        if pipeline.num_submaps % 50 == 0:
            print(f"  submap {pipeline.num_submaps}, loops {pipeline.num_loops}", file=sys.stderr, flush=True)
        if pipeline.num_submaps >= submaps:
            return pipeline
    raise AssertionError("the lap replay is endless")


def replay_laps(world: Path, config, submaps: int, prepare: Callable | None = None):
    """Feed the lap replay through the pipeline until ``submaps`` submaps are done."""
    return advance_to(lap_replay(world, config, prepare), submaps)


COST_GRAPHS = {
    # row: (design, every loop held exactly by iSAM2)
    "submap": ("submap", False),
    "keyframe": ("keyframe", False),
    "keyframe, every loop in iSAM2": ("keyframe", True),
}


EARLY = (10, 20)  # the early window; the late one is the last ten submaps
WINDOW = EARLY[1] - EARLY[0]


def side_by_side(advance_early: Callable[[], None], advance_late: Callable[[], None]) -> None:
    """Advance the early and the late end in turn, ``WINDOW`` steps each, with the heap built so far
    frozen (``gc.freeze``): a garbage collection that one end triggers would otherwise walk the
    other's objects too, at its expense."""
    gc.collect()
    gc.freeze()
    try:
        for step in range(WINDOW):
            for advance in (advance_early, advance_late) if step % 2 == 0 else (advance_late, advance_early):
                advance()
    finally:
        gc.unfreeze()


def cost_child(graph: str, profile: str, submaps: int) -> dict:
    """One graph's lap replay (run in a process of its own, so the peak memory is its own).

    The early and the late submaps are timed side by side: one replay is run to ``submaps - WINDOW``
    submaps, a second, identical replay (same seeds) to ``EARLY[0]``, and then the two advance in
    turn, a submap each (:func:`side_by_side`), so that both ends of the map are timed within the
    same seconds and the machine's drift in speed over minutes cancels from the ratio."""
    from sl4slam.result.outputs import peak_memory

    design, exact = COST_GRAPHS[graph]

    def replay() -> Iterator:
        every_loop_exact = {"backend.revisit_priors": False} if exact else {}
        return lap_replay(small_world(), lap_config(design, profile, 0, **every_loop_exact))

    late_replay, early_replay = replay(), replay()
    late, early = advance_to(late_replay, submaps - WINDOW), advance_to(early_replay, EARLY[0])
    side_by_side(lambda: next(early_replay), lambda: next(late_replay))
    start = time.perf_counter()
    result = late.result()
    polish = time.perf_counter() - start

    def window(pipeline) -> dict:
        per = pipeline.ledger.submap_seconds[-WINDOW:]
        return {"backend": [s.get("backend", 0.0) for s in per], "loops": [s.get("loops", 0.0) for s in per],
                "closed": list(pipeline.ledger.submap_loops[-WINDOW:])}

    nodes = getattr(late.backend, "num_nodes", late.backend.num_submaps)
    return {"early": window(early), "late": window(late), "nodes": nodes, "keyframes": len(late.keyframes),
            "segments": len(late.backend.segments),
            "failed_updates": sum(1 for e in late.edges if e.reason and "could not be solved" in e.reason),
            "loops_total": late.num_loops, "polish": polish, "ate": result_ate(result).rmse,
            "revisits": getattr(getattr(late.backend, "nodes", late.backend), "num_revisit_priors", 0),
            **peak_memory()}


BACKEND_CALLS = ("add_submap", "start_segment", "add_loop", "loop_chi2", "update")
BACKEND_SETTINGS = {
    # row: BackendConfig overrides
    "as configured (relinearization check every 10th update and in loop iterations)": {},
    "relinearization check at every update": {"relinearize_skip": 1},
}
BACKEND_REPEATS = 3


def record_backend_calls(pipeline) -> list[list[tuple]]:
    """Record every graph call the pipeline makes, one list per submap (from its ``add_submap``)."""
    per_submap: list[list[tuple]] = []
    backend = pipeline.backend
    for name in BACKEND_CALLS:
        method = getattr(backend, name)

        def recorded(*args, _method=method, _name=name, **kwargs):
            if _name in ("add_submap", "start_segment"):
                per_submap.append([])
            per_submap[-1].append((_name, args, kwargs))
            return _method(*args, **kwargs)

        setattr(backend, name, recorded)
    return per_submap


def replay_calls(backend, calls: list[tuple]) -> float:
    """Make one submap's recorded graph calls; returns their wall time in seconds."""
    from sl4slam.backend import BackendUpdateError

    start = time.perf_counter()
    for name, args, kwargs in calls:
        try:
            getattr(backend, name)(*args, **kwargs)
        except BackendUpdateError:  # as in the run: the graph rolled the update back
            pass
    return time.perf_counter() - start


def backend_child(profile: str, submaps: int) -> dict:
    """The keyframe graph's own work, without the pipeline around it: the graph calls of the lap
    replay are recorded, then replayed into fresh graphs per setting, early and late side by side
    (as in :func:`cost_child`), ``BACKEND_REPEATS`` times."""
    from sl4slam.backend import make_backend

    config = lap_config("keyframe", profile, 0)
    recorder: list[list[list[tuple]]] = []
    replay_laps(small_world(), config, submaps,
                prepare=lambda pipeline: recorder.append(record_backend_calls(pipeline)))
    calls = recorder[0]
    out = {}
    for setting, overrides in BACKEND_SETTINGS.items():
        backend_config = dataclasses.replace(config.backend, **overrides)
        runs = []
        for _ in range(BACKEND_REPEATS):
            graphs = {"early": make_backend(backend_config), "late": make_backend(backend_config)}
            for end, start in (("late", len(calls) - WINDOW), ("early", EARLY[0])):
                for chunk in calls[:start]:
                    replay_calls(graphs[end], chunk)
            windows = {"early": iter(calls[EARLY[0]:EARLY[1]]), "late": iter(calls[len(calls) - WINDOW:])}
            times: dict[str, list[float]] = {"early": [], "late": []}

            def advance(end: str) -> None:
                times[end].append(replay_calls(graphs[end], next(windows[end])))

            side_by_side(lambda: advance("early"), lambda: advance("late"))
            runs.append(times)
        out[setting] = runs
    return out


def backend_rows(data: dict) -> list[str]:
    rows = []
    for setting, runs in data.items():
        early = [1000 * float(np.median(run["early"])) for run in runs]
        late = [1000 * float(np.median(run["late"])) for run in runs]
        ratios = [b / a for a, b in zip(early, late)]
        rows.append(f"| {setting} | {np.median(early):.1f} | {np.median(late):.1f} | **{np.median(ratios):.2f}** | "
                    f"{min(ratios):.2f}-{max(ratios):.2f} |")
    return rows


def cost(profile: str, submaps: int) -> list[str]:
    small_world()
    rows = []
    for design in COST_GRAPHS:
        print(f"cost: {design} graph, {submaps} submaps", flush=True)
        out = subprocess.run([sys.executable, __file__, "--cost-child", design, "--profile", profile, "--submaps",
                              str(submaps)], check=True, capture_output=True, text=True)
        data = json.loads(out.stdout.strip().splitlines()[-1])
        ms = {end: {key: np.array(data[end][key]) * 1000 for key in ("backend", "loops")} for end in ("early", "late")}
        for end in ms.values():
            end["work"] = end["backend"] + end["loops"]  # everything the graph does per submap
        median = {key: {end: float(np.median(ms[end][key])) for end in ms} for key in ("backend", "loops", "work")}
        ratio = {key: value["late"] / value["early"] for key, value in median.items()}
        rows.append(f"| {design} | {data['nodes']} | {median['backend']['early']:.1f} | {median['backend']['late']:.1f} | "
                    f"**{ratio['backend']:.2f}** | {median['loops']['early']:.1f} | {median['loops']['late']:.1f} | "
                    f"{ratio['loops']:.2f} | **{ratio['work']:.2f}** | {data['loops_total']} | {data['revisits']} | "
                    f"{data['polish'] * 1000:.0f} | {data['ate']:.4f} | {data['peak_rss_mib']:.0f} | "
                    f"{data['segments']} | {data['failed_updates']} |")
    return [f"### Per-submap cost ({submaps} submaps, lap replay of the synthetic world at 160x120, {profile} profile, "
            "ORB retrieval)", "",
            f"Milliseconds per submap, medians over submaps {EARLY[0]}-{EARLY[1]} (early) and the last {WINDOW} "
            "(late). The two ends are timed side by side: a second replay of the same run (same seeds) is brought to "
            f"submap {EARLY[0]}, and then the two advance in turn, a submap each, so the machine's drift in speed "
            "over minutes does not enter the ratios. Peak memory: the process running that graph (frames of the lap "
            f"held decoded; the second replay adds {EARLY[1]} submaps).", "",
            "*backend*: adding the submap and its iSAM2 update; *loops*: verifying the loop candidates (the "
            "chi-square against the map included), adding them and their iSAM2 update; *all*: backend + loops. "
            "*revisit priors*: loops iSAM2 held as priors (`BackendConfig.revisit_priors`); the ATE (`evo_ape -as`, "
            "metres) is after the final polish, which optimizes every loop exactly.", "",
            "| graph | nodes | backend early | backend late | backend late / early | loops early | loops late | "
            "loops late / early | all late / early | loops closed | revisit priors | final polish (ms) | ATE | "
            "peak RSS (MiB) | map segments | failed graph updates |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|", *rows, "",
            *backend_section(profile, submaps)]


def backend_section(profile: str, submaps: int) -> list[str]:
    print(f"cost: the keyframe graph alone, {submaps} submaps", flush=True)
    out = subprocess.run([sys.executable, __file__, "--backend-child", "--profile", profile, "--submaps", str(submaps)],
                         check=True, capture_output=True, text=True)
    data = json.loads(out.stdout.strip().splitlines()[-1])
    return [f"**The keyframe graph alone.** The graph calls of the keyframe replay (adding each submap, the loop "
            f"chi-squares, the loops, the iSAM2 updates) recorded and made again into fresh graphs, without the "
            f"pipeline's own per-submap work (alignment, loop evidence, verification), early and late side by side "
            f"as above, {BACKEND_REPEATS} times per setting: milliseconds per submap (medians over the window, then "
            f"over the repeats) and the range of the ratio.", "",
            "| iSAM2 setting | early | late | late / early | range |", "|---|---|---|---|---|",
            *backend_rows(data), ""]


# ---------------------------------------------------------------------------- verification
VERIFICATION_GRID = grid({"false_loops.rate": [0.1, 0.3], "loops.verify_attention": ["on", "off"]})
"""The verification part's settings: false-loop rates, each with the attention check on and off."""


def verification_run(point: dict, seed: int, design: str, laps_submaps: int) -> dict:
    config = lap_config(design, "vggt", seed, **point, **{"false_loops.seed": seed})
    pipeline = replay_laps(small_world(), config, laps_submaps)
    counts = loop_counts(pipeline.edges, pipeline.retrieval)
    return {key: counts[key] for key in ("false", "false_rejected", "false_by_attention", "true", "true_accepted",
                                         "true_by_attention")}


def verification(seeds: int, submaps: int, graphs: list[str]) -> list[str]:
    rows = []
    for design in graphs:
        for point in VERIFICATION_GRID:
            rate, attention = point["false_loops.rate"], point["loops.verify_attention"]
            runs = [verification_run(point, seed, design, submaps) for seed in range(seeds)]
            total = {k: sum(r[k] for r in runs) for k in runs[0]}
            print(f"verification {design} rate {rate} attention {attention}: {total}", flush=True)
            rows.append(f"| {design} | {rate} | {attention} | {total['false']} | {total['false_rejected']} "
                        f"({total['false_by_attention']} by attention) | {total['true']} | {total['true_accepted']} "
                        f"({total['true_by_attention']} rejected by attention) |")
    return ["### Attention loop check against false loops", "",
            f"The synthetic world (160x120) replayed for {submaps} submaps (about three laps, so retrieval proposes "
            f"many loops), `vggt` profile, {seeds} seeds summed. False loops: proposals the false-loop wrapper replaced "
            "by a wrong place (at least 1 m or 30 degrees away, at most 5 % shared view). The attention score is the "
            "simulated frontend's stand-in from the true overlap (`sl4slam.frontend.overlap`), not VGGT's: these rows "
            "measure the check's logic and its interplay with the other checks, not VGGT's attention.", "",
            "| graph | false-loop rate | attention check | false loops | rejected | true loops | accepted |",
            "|---|---|---|---|---|---|---|", *rows, ""]


# ---------------------------------------------------------------------------- main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--profile", default="vggt", help="simulator profile of the accuracy part (exact, vggt, hard)")
    parser.add_argument("--perspective", type=float, default=None,
                        help="accuracy part: per-submap perspective distortion on top of the profile")
    parser.add_argument("--submaps", type=int, default=300, help="submaps of the cost part")
    parser.add_argument("--verification-submaps", type=int, default=24, help="submaps of each verification run")
    parser.add_argument("--verification-seeds", type=int, default=0, help="seeds of the verification part (0: --seeds)")
    parser.add_argument("--verification-graphs", default="keyframe,submap", help="graphs of the verification part")
    parser.add_argument("--parts", default="accuracy,cost,verification")
    parser.add_argument("--worlds", default="synthetic,xyz,desk", help="accuracy part: " + ", ".join(WORLDS))
    parser.add_argument("--designs", default=",".join(DESIGNS), help="accuracy part: " + ", ".join(DESIGNS))
    add_parallel_arguments(parser, "--jobs", 1)
    parser.add_argument("--work", default=None, help=argparse.SUPPRESS)  # older command lines (worlds are shared now)
    parser.add_argument("--out", default=str(result_file("keyframe_graph")))
    parser.add_argument("--cost-child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--backend-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.cost_child:
        print(json.dumps(cost_child(args.cost_child, args.profile, args.submaps)))
        return
    if args.backend_child:
        print(json.dumps(backend_child(args.profile, args.submaps)))
        return
    start = time.perf_counter()
    load = os.getloadavg()[0]
    parts = args.parts.split(",")
    sections: list[str] = []
    if "accuracy" in parts:
        sections += accuracy(args.profile, args.seeds, args.worlds.split(","), args.designs.split(","),
                             args.perspective, parallel_options(args))
    if "cost" in parts:
        sections += cost(args.profile, args.submaps)
    if "verification" in parts:
        sections += verification(args.verification_seeds or args.seeds, args.verification_submaps,
                                 args.verification_graphs.split(","))
    lines = ["## Keyframe graph (VGGT-SLAM 2.0) vs submap graph (VGGT-SLAM)", "",
             f"Machine: {os.cpu_count()}-core {platform.machine()} CPU, no GPU, shared (load average {load:.1f} at the "
             f"start); Python {platform.python_version()}. Date: {datetime.date.today()}. "
             f"Total {(time.perf_counter() - start) / 60:.0f} min.",
             f"Command: `python benchmarks/bench_keyframe_graph.py --seeds {args.seeds} --profile {args.profile} "
        + (f"--perspective {args.perspective} " if args.perspective is not None else "") +
             f"--submaps {args.submaps} --parts {args.parts} --worlds {args.worlds} --designs {args.designs} "
             f"--verification-submaps {args.verification_submaps} --verification-seeds {args.verification_seeds} "
             f"--verification-graphs {args.verification_graphs}`.", "", *sections]
    write_report(args.out, lines)


if __name__ == "__main__":
    sys.exit(main())
