"""Accuracy levers beyond VGGT-SLAM 2.0, measured on the same simulated frames: a grid of variants
(graph design, link model, shared frames, known intrinsics, sensor scale) x simulator profiles x
sequences x seeds, each run once and cached, with loops on (ORB retrieval).

The baseline is VGGT-SLAM 2.0's design: the keyframe graph with one shared frame and the model's own
intrinsics (calibration-and-scale links, no metric upgrade). Every variant is run on the same
simulated submaps (same sequence, profile and seed), so the ratios compare designs, not draws.

    python benchmarks/bench_levers.py --worlds synthetic,desk --profiles vggt,hard,strong --seeds 5 \\
        --variants baseline,submap,sim3,known-k --workers 2

Results accumulate in ``benchmarks/out/levers/runs.jsonl`` (a run already there is not run again);
``--report`` writes ``benchmarks/results/levers.md`` from whatever is there. BLAS runs
single-threaded: the runs are spread over processes instead. ``--cost`` times two variants' whole
runs side by side instead (each seed's pair at once, nothing else running):

    python benchmarks/bench_levers.py --cost --worlds desk --profiles vggt --variants baseline,defaults --seeds 3

``--suite HALF`` runs the variants over the development suite's sequences instead
(:mod:`sl4slam.synthetic.suite`: ``tune``, ``validate`` or ``all``; ``--sequences`` picks some by
name, ``--suite-frames N`` renders the synthetic ones at N frames for a quick run) and writes the
per-sequence ratios (variant / baseline ATE), with each half's median, worst and wins (ratio < 1),
into ``benchmarks/results/suite.md``; runs accumulate in ``benchmarks/out/levers/suite_runs.jsonl``:

    python benchmarks/bench_levers.py --suite tune --profiles vggt --variants baseline,defaults --seeds 3
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from harness import (OUT, add_parallel_arguments, parallel_options, result_file, run_all, run_sequence,  # noqa: E402
                     seed_settings, shared_sequence, simulated_config, synthetic_world, write_report)

WORK = OUT / "levers"
WORLDS = {"synthetic": "synthetic world (600 frames, 320x240, one lap)", "desk": "TUM fr1/desk (613 frames)"}
WINDOW_OFF = "its distortion common to a window (perspective, shear 0)"
POSES_OFF = "its per-frame pose errors (camera rotation, translation 0)"
ROTATION_OFF = "its per-frame rotation errors (camera rotation 0)"
SHIFT_OFF = "its per-frame camera centre errors (camera translation 0)"
FOCAL_OFF = "its per-frame focal errors (focal_error 0)"
WARP_OFF = "its smooth depth warps (depth_warp 0)"
PIXELS_OFF = "its per-pixel depth errors (depth noise, flying pixels, outlier blobs 0)"
PROFILES = {
    # name: (sim profile, explicit magnitudes, what it is)
    "vggt": ("vggt", {}, "VGGT-like errors (per-frame cameras, focal, smooth depth warps, flying pixels)"),
    "hard": ("hard", {}, "about twice the vggt errors"),
    "strong": ("exact", {"perspective": 0.2, "shear": 0.05, "scale": 0.1},
               "a strong projective distortion per submap and nothing else (the paper's premise)"),
    "vggt-focal": ("vggt", {"focal_consistency": 0.0},
                   "the vggt profile with each frame's focal error drawn afresh in every window"),
    # Diagnostics: one error term of a profile switched off, to name the term a missed target rests on.
    "vggt-nowin": ("vggt", {"perspective": 0.0, "shear": 0.0},
                   f"diagnostic: the vggt profile without {WINDOW_OFF}"),
    "hard-nowin": ("hard", {"perspective": 0.0, "shear": 0.0},
                   f"diagnostic: the hard profile without {WINDOW_OFF}"),
    "vggt-nocam": ("vggt", {"camera_rotation_deg": 0.0, "camera_translation": 0.0},
                   f"diagnostic: the vggt profile without {POSES_OFF}"),
    "vggt-norot": ("vggt", {"camera_rotation_deg": 0.0}, f"diagnostic: the vggt profile without {ROTATION_OFF}"),
    "vggt-noshift": ("vggt", {"camera_translation": 0.0}, f"diagnostic: the vggt profile without {SHIFT_OFF}"),
    "vggt-nofocal": ("vggt", {"focal_error": 0.0}, f"diagnostic: the vggt profile without {FOCAL_OFF}"),
    "vggt-nowarp": ("vggt", {"depth_warp": 0.0}, f"diagnostic: the vggt profile without {WARP_OFF}"),
    "vggt-nopixel": ("vggt", {"depth_noise": 0.0, "flying_px": 0.0, "outlier_fraction": 0.0},
                     f"diagnostic: the vggt profile without {PIXELS_OFF}"),
}
DIAGNOSTIC = {"vggt-nowin": ("vggt", WINDOW_OFF), "hard-nowin": ("hard", WINDOW_OFF), "vggt-nocam": ("vggt", POSES_OFF),
              "vggt-norot": ("vggt", ROTATION_OFF), "vggt-noshift": ("vggt", SHIFT_OFF),
              "vggt-nofocal": ("vggt", FOCAL_OFF), "vggt-nowarp": ("vggt", WARP_OFF),
              "vggt-nopixel": ("vggt", PIXELS_OFF)}
"""Each diagnostic profile: the full profile it is compared with, and the term it switches off."""
VARIANTS = {
    # name: (settings, what it is)
    "baseline": ({}, "VGGT-SLAM 2.0: keyframe graph, calibration links, 1 shared frame, the model's K, one sigma "
                     "(0.05) on every link and loop as its code"),
    "submap": ({"backend.graph": "submap"}, "VGGT-SLAM: submap graph, 15-DOF links, metric upgrade"),
    "sim3": ({"backend.kind": "sim3"}, "submap graph in Sim(3)"),
    "keyframe+sl4": ({"alignment.model": "sl4"}, "keyframe graph with 15-DOF links"),
    "hybrid": ({"alignment.model": "hybrid"}, "keyframe graph, calibration link unless the fit is 4x better"),
    "known-k": ({"source.intrinsics": "auto"}, "baseline with the sequence's known K"),
    "overlap2": ({"submap.overlap": 2}, "baseline with 2 shared frames"),
    "overlap3": ({"submap.overlap": 3}, "baseline with 3 shared frames"),
    "overlap2-known-k": ({"submap.overlap": 2, "source.intrinsics": "auto"}, "baseline with 2 shared frames and the known K"),
    "select": ({"alignment.model": "select", "upgrade.mode": "on"},
               "keyframe graph, link chosen per link by cross-validation, metric upgrade"),
    "select2": ({"alignment.model": "select", "upgrade.mode": "on", "submap.overlap": 2},
                "select with 2 shared frames"),
    "select2-noup": ({"alignment.model": "select", "submap.overlap": 2}, "select2 without the metric upgrade"),
    "submap2": ({"backend.graph": "submap", "submap.overlap": 2}, "submap graph with 2 shared frames"),
    "defaults-sim3": ({"__defaults__": True, "backend.kind": "sim3"}, "the current defaults in Sim(3)"),
    "defaults": ({"__defaults__": True}, "the library's defaults on the date of its runs (a cached run is not made "
                                         "again when the defaults change; the variants that pin a setting say which "
                                         "defaults they are)"),
    "defaults-known-k": ({"__defaults__": True, "source.intrinsics": "auto"}, "the defaults with the sequence's known K"),
    "defaults-lf1": ({"__defaults__": True, "submap.loop_frames": 1},
                     "the defaults with one loop frame per loop (as VGGT-SLAM): nothing held out to judge a loop's fit"),
    "defaults-noattn-false1": ({"__defaults__": True, "loops.verify_attention": "off", "false_loops.rate": 1.0},
                              "the defaults without the attention check (the simulator's stand-in for it is the true "
                              "overlap), every proposal replaced by a wrong place: the loop gate alone"),
    "submap2-false1": ({"backend.graph": "submap", "submap.overlap": 2, "false_loops.rate": 1.0},
                       "submap graph with 2 shared frames (no attention check), every proposal a wrong place"),
    "defaults-corr8000": ({"__defaults__": True, "alignment.max_correspondences": 8000},
                          "the defaults with at most 8000 shared pixels per frame in a link's fits (30000 by default)"),
    "defaults-overlap3": ({"__defaults__": True, "submap.overlap": 3},
                          "the defaults with 3 shared frames between submaps (2 by default)"),
    "defaults-features": ({"__defaults__": True, "submap.feature_poses": 1000},
                     "the defaults with every frame's camera corrected by its ORB features"),
    "defaults-refine": ({"__defaults__": True, "submap.refine_cameras": 3},
                        "the defaults with every frame's pose refined against the other frames' dense points in its "
                        "submap (3 Gauss-Newton steps; docs/decisions/frame-refinement.md)"),
    "defaults-noagree": ({"__defaults__": True, "backend.window_agreement_factor": 0.0},
                         "the defaults without links inside each window as stiff as its frames agree (the defaults "
                         "before 2026-11-30; docs/decisions/window-agreement.md)"),
    "defaults-noscatter": ({"__defaults__": True, "backend.frame_scatter_factor": 0.0},
                           "the defaults without stiffening windows behind a 15-DOF link by the disagreement between "
                           "windows (docs/decisions/frame-scatter.md)"),
    "defaults-agree-x1": ({"__defaults__": True, "backend.window_agreement_factor": 1.0},
                          "the defaults with every window's links at most 1 times how far its frames disagree"),
    "defaults-agree-x2": ({"__defaults__": True, "backend.window_agreement_factor": 2.0,
                           "upgrade.completion_residual": 0.002, "submap.centre_smoothing": False},
                          "the defaults with every window's links at most 2 times how far its frames disagree (the "
                          "defaults of 2026-11-30 before planar links were completed below a residual of 0.002 and "
                          "before centre smoothing)"),
    "defaults-agree-x1-noscatter": ({"__defaults__": True, "backend.window_agreement_factor": 1.0,
                                     "backend.frame_scatter_factor": 0.0},
                                    "the defaults with every window's links at most how far its frames disagree, "
                                    "and not by the disagreement between windows"),
    "defaults-complete0": ({"__defaults__": True, "upgrade.completion_residual": 0.0, "submap.centre_smoothing": False},
                           "the defaults completing every planar link whose completion clearly lowers the next "
                           "submap's constraint residual, however small it was, without centre smoothing (the "
                           "defaults of 2026-11-30 until centre smoothing)"),
    "defaults-complete-002": ({"__defaults__": True, "upgrade.completion_residual": 0.002,
                               "submap.centre_smoothing": False},
                              "the defaults leaving a planar link as measured below a constraint residual of 0.002 "
                              "(the defaults before 2026-11-30)"),
    "defaults-smooth": ({"__defaults__": True, "upgrade.completion_residual": 0.0, "submap.centre_smoothing": True},
                        "the defaults of 2026-11-30 with each window's camera centres smoothed as far as the centre "
                        "noise measured on the shared frames allows (the defaults since 2026-11-30, "
                        "docs/decisions/centre-smoothing.md)"),
    "defaults-sensor": ({"__defaults__": True, "source.metric_depth": "sensor"},
                        "the defaults with metric scale from the depth sensor"),
}


BASELINE = {"backend.graph": "keyframe", "alignment.model": "calibration", "submap.overlap": 1, "submap.loop_frames": 1,
            "upgrade.mode": "off"}
"""The baseline's settings, pinned, so that the baseline stays VGGT-SLAM 2.0 whatever the defaults become."""


def world_path(name: str) -> Path:
    """The sequence of a world name: TUM fr1/desk, or the synthetic world at 320x240."""
    return shared_sequence("desk") if name == "desk" else synthetic_world(320, 240)


def variant_settings(variant: str) -> dict:
    """The settings of a variant: on top of the library defaults (``__defaults__``) or of the baseline."""
    settings, _ = VARIANTS[variant]
    if settings.get("__defaults__"):
        return {key: value for key, value in settings.items() if key != "__defaults__"}
    chosen = {**BASELINE, **settings}
    if settings.get("backend.graph") == "submap" or settings.get("backend.kind") == "sim3":
        chosen.update({"alignment.model": "auto", "upgrade.mode": "auto"})
        if settings.get("backend.kind") == "sim3":
            chosen["backend.graph"] = "submap"
    return chosen


def make_config(profile: str, variant: str, seed: int):
    """The config of one run: the profile's simulator, ORB retrieval, the seeds, the variant's settings."""
    sim_profile, magnitudes, _ = PROFILES[profile]
    return simulated_config({"sim.profile": sim_profile, "sim.seed": seed,
                             **{f"sim.{key}": value for key, value in magnitudes.items()}, "retrieval.kind": "orb",
                             **seed_settings(seed, "retrieval.seed", "alignment.seed", "false_loops.seed"),
                             **variant_settings(variant)})


def one_run(world: str, profile: str, variant: str, seed: int) -> dict:
    run = run_sequence(make_config(profile, variant, seed), world_path(world))
    return {"world": world, **_measured(run, profile, variant, seed)}


def _measured(run, profile: str, variant: str, seed: int) -> dict:
    """What a grid row records of a finished run (ATE, loops, links, cost)."""
    result = run.result
    loops = run.loops()
    models = [e.model for e in result.edges if e.kind == "odometry" and e.accepted]
    return {"profile": profile, "variant": variant, "seed": seed, "ate": run.ate(),
            "ate_se3": run.ate(correct_scale=False), "scale": run.ate_result().scale,
            "keyframes": len(result.keyframes),
            "frames": result.stats["frames"], "submaps": result.stats["submaps"], "loops": loops["accepted"],
            "proposed": loops["proposed"], "fallbacks": result.stats["fallbacks"], "segments": result.stats["segments"],
            "sl4_links": models.count("sl4"), "links": len(models), "seconds": run.seconds,
            "frontend_seconds": result.stats["seconds_by_stage"].get("frontend", 0.0),
            "frontend_frames": run.model_frames,
            "false_proposed": loops["false"], "false_accepted": loops["false_accepted"],
            "date": str(datetime.date.today())}


def variant_legend(runs: list[dict]) -> str:
    """One line naming each variant that has runs in ``runs``, with what it is, in catalogue order."""
    shown = {r["variant"] for r in runs}
    return "Variants: " + "; ".join(f"**{name}**: {text}" for name, (_, text) in VARIANTS.items() if name in shown) + "."


def load_runs() -> list[dict]:
    path = WORK / "runs.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def run_grid(worlds: list[str], profiles: list[str], variants: list[str], seeds: list[int], parallel: dict) -> None:
    WORK.mkdir(parents=True, exist_ok=True)
    for world in worlds:
        world_path(world)  # rendered once, before the workers start
    done = {(r["world"], r["profile"], r["variant"], r["seed"]) for r in load_runs()}
    todo = [(w, p, v, s) for w in worlds for p in profiles for s in seeds for v in variants if (w, p, v, s) not in done]
    print(f"{len(todo)} runs to do ({len(done)} cached)", flush=True)
    with open(WORK / "runs.jsonl", "a") as log:

        def record(index: int, row) -> None:
            if isinstance(row, BaseException):  # a run that breaks is reported, the grid goes on
                print(f"{todo[index]}: FAILED {type(row).__name__}: {row}", flush=True)
                return
            log.write(json.dumps(row) + "\n")
            log.flush()
            print(f"{todo[index]}: ATE {row['ate']:.4f} m, {row['loops']}/{row['proposed']} loops, "
                  f"{row['seconds']:.0f} s", flush=True)

        run_all(one_run, todo, on_result=record, raise_errors=False, **parallel)


def report(out: Path) -> None:
    runs = load_runs()
    if not runs:
        raise SystemExit(f"bench_levers: no runs to report in {WORK / 'runs.jsonl'}; "
                         "--seeds is a count (3: seeds 0-2) or a list (0,3,4)")
    lines = ["## Accuracy levers on the same frames (simulated frontend, loops on)", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores; runs dated {min(r['date'] for r in runs)} to "
             f"{max(r['date'] for r in runs)}. Command: `python benchmarks/bench_levers.py ...` (grid in the tables). "
             "ATE RMSE in metres after Sim(3) alignment (`evo_ape -as`), median and range over the seeds; "
             "ratio: median of the per-seed ratios to the baseline on the same simulated frames. \"run s\": wall "
             "time under whatever load the grid ran (two workers, at times beside other benchmarks), not a cost "
             "comparison: the side-by-side cost is its own table below the targets.", ""]
    for world in WORLDS:
        for profile in PROFILES:
            rows = [r for r in runs if r["world"] == world and r["profile"] == profile]
            if not rows:
                continue
            base = {r["seed"]: r["ate"] for r in rows if r["variant"] == "baseline"}
            lines += [f"**{WORLDS[world]}, {profile} profile** ({PROFILES[profile][2]})", "",
                      "| variant | seeds | ATE median | range | / baseline (median, range) | SE(3) ATE median | "
                      "loops accepted / proposed | 15-DOF links | fallbacks | segments | model frames / keyframe | "
                      "run s (median) | false loops accepted / injected |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
            for variant in VARIANTS:
                chosen = sorted((r for r in rows if r["variant"] == variant), key=lambda r: r["seed"])
                if not chosen:
                    continue
                ates = np.array([r["ate"] for r in chosen])
                ratios = np.array([r["ate"] / base[r["seed"]] for r in chosen if r["seed"] in base])
                ratio = f"{np.median(ratios):.2f} ({ratios.min():.2f}-{ratios.max():.2f})" if len(ratios) else "-"
                lines.append(f"| {variant} | {len(chosen)} | {np.median(ates):.4f} | {ates.min():.4f}-{ates.max():.4f} | "
                             f"{ratio} | {np.median([r['ate_se3'] for r in chosen]):.4f} | "
                             f"{sum(r['loops'] for r in chosen)}/{sum(r['proposed'] for r in chosen)} | "
                             f"{sum(r['sl4_links'] for r in chosen)}/{sum(r['links'] for r in chosen)} | "
                             f"{np.mean([r['fallbacks'] for r in chosen]):.1f} | {np.mean([r['segments'] for r in chosen]):.1f} | "
                             f"{_cost(chosen)} | {np.median([r['seconds'] for r in chosen]):.0f} | {_false(chosen)} |")
            lines.append("")
    lines += targets(runs)
    lines += diagnostics(runs)
    lines += cost_lines()
    lines += [variant_legend(runs), "",
              "What each gain rests on in the simulator (`sl4slam.frontend.simulated`, `SimConfig`):", "",
              "- **select** (the default link): the simulator draws each frame's depth warp and camera error on "
              "its own (`depth_warp`, `camera_rotation`, ..., independent between frames of a window), while the "
              "`strong` profile's distortion is one projective map per window, common to all its frames. The "
              "cross-validation takes the 15-DOF fit only where it predicts the left-out shared frame, which a "
              "window-wide distortion does and a frame's own warp does not; a real model whose frames of one window "
              "err alike would make it keep the link more often. A flat shared frame votes in its fold through its "
              "camera-constrained fit; that vote rests on the same term (one desk run under `strong`: 0.0094 -> "
              "0.0007 m; under `vggt` and `hard` no run changed). The fit must also predict the left-out frames at "
              "least 2x better (`--ransac-select-min-gain`): with two shared frames the two folds are one comparison "
              "seen from both sides (log ratios correlated at 0.995 over 239 links), so the t-test alone took 7 fits "
              "that predicted 1.02-1.2x better in 5 of the 20 `vggt` and `hard` runs; without them 4 of those 5 runs "
              "came out better and 1 worse (TUM fr1/desk under vggt: 0.0127 -> 0.0115 m median). Under `strong` the "
              "chosen fits predict 7-60x better and no choice changed.",
              "- **more shared frames**: the link averages the shared frames' own links, so its gain rests on their "
              "errors being independent (in the simulator: per frame, and per window up to `frame_consistency`). "
              "It weighs the new submap's first shared frame twice (`--alignment-weight-reference-frame`, on): that "
              "frame is the submap's reference, `[I | 0]` by construction as in VGGT, so its link carries one pose "
              "error where the others carry two; a small gain (0.97x the unweighted defaults on the synthetic world "
              "under vggt, 0.99x on TUM fr1/desk, 5 seeds each), resting on the same independence.",
              "- **known K**: it removes the model's focal error, of which the `vggt` profile keeps 80 % the same "
              "for a frame in every window (`frame_consistency`); `vggt-focal` sets `focal_consistency` 0 (drawn "
              "afresh in every window), the case where a calibration pays most. With the defaults it loses on the "
              "synthetic world because of the profile's distortion common to a window (`perspective`, `shear`): the "
              "simulated model reports it through its K (`P H^-1` decomposed: a changed focal, skew and principal "
              "point, which VGGT's camera head, a field of view per axis about the image centre, cannot output), "
              "the calibration link carries the relative part of it between windows, and a known K takes that away. "
              "With the term switched off (`vggt-nowin`, `hard-nowin`) the known K wins (table above).",
              "- **SL(4) against Sim(3)**: what SL(4) expresses beyond Sim(3) here is a window's distortion "
              "(through the 15-DOF fit, or the model's K in the calibration link); the per-frame pose errors "
              "(`camera_rotation`, `camera_translation`) err alike in both groups and dilute the ratio. With them "
              "switched off (`vggt-nocam`) the ratio falls well below the full profile's; with the window's "
              "distortion switched off (`vggt-nowin`) SL(4) has nothing left to win.",
              "- **loop gate**: the links' scatter is measured from two or more shared frames; with one the gate is "
              "VGGT-SLAM 2.0's, unchanged.",
              "- **loop frames** (two per loop): a loop is measured like a link, so `select` can take the 15-DOF fit for "
              "it; the gain rests on the same term as **select** (a distortion common to a window's frames), and "
              "shows where loops tie submaps that such a distortion bends (`strong` on TUM fr1/desk, 14 loops). The "
              "synthetic lap's one loop frame is a flat floor, where any loop keeps the calibration link.",
              "- **stiff distorted windows** (`--backend-frame-scatter-factor 2`): a submap joined by a 15-DOF fit gets "
              "links inside it twice as stiff as consecutive windows disagree about their shared frames' relative "
              "rotations, capped at `frame_sigma`; it rests on the same term (a distortion common to a window's "
              "frames, which keeps the window consistent inside: 0.3-0.8 degrees of disagreement under `strong`). "
              "The simulator's per-frame camera errors make windows disagree by 1.6-2.3 degrees under `vggt`, "
              "where it changes nothing.",
              "- **edge weights** (`--backend-weighting by-link`): links read from the cameras get one sigma, fitted "
              "links their points' evidence. It rests on the shared frames' camera errors being what a camera link "
              "errs by (in the simulator: `camera_rotation`, `camera_translation`, `focal_error` per frame), which "
              "the residuals of the frame's points cannot show because the model places its depth with the same "
              "camera; the evidence then weighs links by something unrelated to their error. The baseline has "
              "taken the same weights since, as VGGT-SLAM 2.0's code gives every factor 0.05.", ""]
    write_report(out, lines)


def _cost(rows: list[dict]) -> str:
    """Frames the model was given per keyframe (runs recorded before this was counted: "-")."""
    counted = [r["frontend_frames"] / r["keyframes"] for r in rows if "frontend_frames" in r]
    return f"{np.median(counted):.2f}" if counted else "-"


def _false(rows: list[dict]) -> str:
    """Injected false loops accepted / injected over the seeds ("-": none injected)."""
    injected = sum(r.get("false_proposed", 0) for r in rows)
    return f"{sum(r.get('false_accepted', 0) for r in rows)}/{injected}" if injected else "-"


def _paired(runs: list[dict], world: str, profile: str, variant: str, other: str) -> np.ndarray:
    """Per-seed ATE ratios ``variant / other`` on the same frames."""
    mine = {r["seed"]: r["ate"] for r in runs if (r["world"], r["profile"], r["variant"]) == (world, profile, variant)}
    theirs = {r["seed"]: r["ate"] for r in runs if (r["world"], r["profile"], r["variant"]) == (world, profile, other)}
    return np.array([mine[k] / theirs[k] for k in sorted(mine) if k in theirs])


TARGET_CHECKS = [("defaults / baseline", "defaults", "baseline", 0.8),
                 ("defaults with known K / defaults", "defaults-known-k", "defaults", 1.0),
                 ("baseline with known K / baseline", "known-k", "baseline", 1.0),
                 ("defaults (SL(4)) / defaults in Sim(3)", "defaults", "defaults-sim3", 0.75)]
"""(name, variant, the variant it is divided by, target) of each ratio the defaults are held to."""


def targets(runs: list[dict]) -> list[str]:
    """The figures the defaults are held to, each a median of per-seed ratios (range)."""
    lines = ["**Targets** (median of per-seed ratios, range; a dash: not run)", "",
             "| world | profile | ratio | target | median (range) | seeds | met |", "|---|---|---|---|---|---|---|"]
    for world in WORLDS:
        for profile in (p for p in PROFILES if p not in DIAGNOSTIC):
            rows = [(name, _paired(runs, world, profile, a, b), goal) for name, a, b, goal in TARGET_CHECKS]
            medians = {v: np.median([r["ate"] for r in runs if (r["world"], r["profile"], r["variant"]) == (world, profile, v)])
                       for v in ("defaults", "baseline", "submap")
                       if any((r["world"], r["profile"], r["variant"]) == (world, profile, v) for r in runs)}
            for name, ratios, goal in rows:
                if len(ratios):
                    lines.append(f"| {world} | {profile} | {name} | <= {goal:g} | {np.median(ratios):.2f} "
                                 f"({ratios.min():.2f}-{ratios.max():.2f}) | {len(ratios)} | "
                                 f"{'yes' if np.median(ratios) <= goal else 'no'} |")
            if {"defaults", "baseline", "submap"} <= medians.keys():
                best = min(medians["baseline"], medians["submap"])
                ratio = medians["defaults"] / best
                lines.append(f"| {world} | {profile} | defaults / better of keyframe and submap graph (medians) | <= 1.5 | "
                             f"{ratio:.2f} | | {'yes' if ratio <= 1.5 else 'no'} |")
    return lines + [""]


def diagnostics(runs: list[dict]) -> list[str]:
    """The missed targets' ratios with one error term switched off, beside the full profile's."""
    lines = ["**Which simulator term a ratio rests on** (the ratio with one error term of the profile switched off, "
             "beside the full profile; median of per-seed ratios, range)", "",
             "| world | ratio | full profile | full | term switched off | without it |", "|---|---|---|---|---|---|"]
    for world in WORLDS:
        for profile, (full, term) in DIAGNOSTIC.items():
            for name, a, b, _ in TARGET_CHECKS:
                off, on = _paired(runs, world, profile, a, b), _paired(runs, world, full, a, b)
                if len(off) and len(on):
                    lines.append(f"| {world} | {name} | {full} | {np.median(on):.2f} ({on.min():.2f}-{on.max():.2f}) | "
                                 f"{term} | "
                                 f"{np.median(off):.2f} ({off.min():.2f}-{off.max():.2f}) |")
    return lines + [""] if len(lines) > 4 else []


def run_cost(world: str, profile: str, variants: list[str], seeds: list[int]) -> None:
    """Whole runs of two variants side by side: each seed's pair at once on two workers and nothing
    else, so both see the same load (the grid's "run s" column is whatever load the grid ran under)."""
    rows = []
    world_path(world)
    for seed in seeds:
        for row in run_all(one_run, [(world, profile, variant, seed) for variant in variants], jobs=2):
            rows.append({k: row[k] for k in ("variant", "seed", "ate", "seconds", "frontend_frames", "keyframes")})
            print(f"{world} {profile} {row['variant']} seed {seed}: {row['seconds']:.1f} s, ATE {row['ate']:.4f} m",
                  flush=True)
    WORK.mkdir(parents=True, exist_ok=True)
    (WORK / "cost.json").write_text(json.dumps({"world": world, "profile": profile, "date": str(datetime.date.today()),
                                                "rows": rows}, indent=1))


def cost_lines() -> list[str]:
    """The side-by-side cost section of the report (empty before ``--cost`` was run)."""
    path = WORK / "cost.json"
    if not path.is_file():
        return []
    cost = json.loads(path.read_text())
    variants = list(dict.fromkeys(r["variant"] for r in cost["rows"]))
    lines = [f"**Cost side by side** ({WORLDS[cost['world']]}, {cost['profile']} profile, {cost['date']}; each seed's "
             f"runs at once on the two cores, nothing else running; command: `python benchmarks/bench_levers.py --cost "
             f"--worlds {cost['world']} --profiles {cost['profile']} --variants {','.join(variants)} --seeds "
             f"{len({r['seed'] for r in cost['rows']})}`)", "",
             "| variant | runs | whole run s (median, range) | model frames / keyframe | ATE median |", "|---|---|---|---|---|"]
    for variant in variants:
        rows = [r for r in cost["rows"] if r["variant"] == variant]
        seconds = [r["seconds"] for r in rows]
        lines.append(f"| {variant} | {len(rows)} | {np.median(seconds):.1f} ({min(seconds):.1f}-{max(seconds):.1f}) | "
                     f"{np.median([r['frontend_frames'] / r['keyframes'] for r in rows]):.2f} | "
                     f"{np.median([r['ate'] for r in rows]):.4f} |")
    return lines + [""]


# ------------------------------------------------------------------ the development suite

SUITE_RUNS = WORK / "suite_runs.jsonl"
SUITE_COMMANDS = WORK / "suite_commands.txt"
"""The commands whose runs are in :data:`SUITE_RUNS`, one a line."""
SUITE_START, SUITE_END = "<!-- section:levers -->", "<!-- /section:levers -->"


def one_suite_run(sequence: str, frames: int | None, profile: str, variant: str, seed: int) -> dict:
    """One run of a variant on a sequence of the suite (its synthetic ones at ``frames`` frames when
    given); a run that raises is a row with its error, not the end of the grid."""
    from harness.worlds import suite_sequence
    from sl4slam.synthetic.suite import get_sequence

    entry = get_sequence(sequence)
    folder = suite_sequence(sequence, frames=frames)
    key = {"sequence": sequence, "split": entry.split, "length": None if entry.real else int(frames or entry.frames),
           "path": _path_digest(folder), "profile": profile, "variant": variant, "seed": seed,
           "date": str(datetime.date.today())}
    start = time.perf_counter()
    try:
        run = run_sequence(make_config(profile, variant, seed), folder)
        return {**key, **_measured(run, profile, variant, seed)}
    except Exception as exc:  # a finding of the suite: which variant fails where
        return {**key, "ate": None, "error": f"{type(exc).__name__}: {' '.join(str(exc).split())[:160]}",
                "seconds": time.perf_counter() - start}


def _path_digest(folder: Path) -> str | None:
    """The camera path's digest a synthetic sequence's folder records (None for a real sequence): a
    cached run counts only for the rendering it ran on."""
    try:
        return json.loads((folder / "synthetic.json").read_text())["style"]["path_sha256"]
    except (OSError, ValueError, KeyError):
        return None


def load_suite_runs(current: bool = False) -> list[dict]:
    """The suite's runs so far; with ``current``, of each sequence and length only those on its latest
    rendering (the path digest of the last row recorded for it)."""
    rows = [json.loads(line) for line in SUITE_RUNS.read_text().splitlines() if line.strip()] if SUITE_RUNS.is_file() else []
    if not current:
        return rows
    latest = {(r["sequence"], r["length"]): r.get("path") for r in rows}
    return [r for r in rows if r.get("path") == latest[(r["sequence"], r["length"])]]


def _suite_key(row: dict) -> tuple:
    return row["sequence"], row["length"], row.get("path"), row["profile"], row["variant"], row["seed"]


def run_suite(split: str, names: list[str] | None, frames: int | None, profiles: list[str], variants: list[str],
              seeds: list[int], parallel: dict) -> None:
    """Every variant x profile x seed on the chosen sequences of the suite, each run once and cached."""
    from harness.worlds import suite_sequence
    from sl4slam.synthetic.suite import suite_sequences

    chosen = suite_sequences(None if split == "all" else split, names)
    sequences = []
    for entry in chosen:
        if entry.real and not suite_sequence(entry.name).is_dir():
            print(f"{entry.name}: not here ({suite_sequence(entry.name)}), skipped", flush=True)
            continue
        folder = suite_sequence(entry.name, frames=frames)  # rendered once, before the workers start
        sequences.append((entry, _path_digest(folder)))
    done = {_suite_key(r) for r in load_suite_runs()}
    todo = [(e.name, frames, p, v, s) for e, path in sequences for p in profiles for s in seeds for v in variants
            if (e.name, None if e.real else int(frames or e.frames), path, p, v, s) not in done]
    print(f"{len(todo)} suite runs to do ({len(done)} cached)", flush=True)
    WORK.mkdir(parents=True, exist_ok=True)
    with open(SUITE_RUNS, "a") as log:

        def record(index: int, row) -> None:
            if isinstance(row, BaseException):
                print(f"{todo[index]}: FAILED {type(row).__name__}: {row}", flush=True)
                return
            log.write(json.dumps(row) + "\n")
            log.flush()
            outcome = f"ATE {row['ate']:.4f} m" if row.get("ate") is not None else f"failed: {row['error']}"
            print(f"{todo[index]}: {outcome}, {row['seconds']:.0f} s", flush=True)

        run_all(one_suite_run, todo, on_result=record, raise_errors=False, **parallel)


def suite_ratios(runs: list[dict], profile: str, variant: str) -> dict[tuple, list]:
    """Per sequence (name, rendered length) of a profile: the per-seed ratios ``variant / baseline`` ATE on the
    same frames (``None`` for a seed where the variant failed and the baseline did not)."""
    base = {(r["sequence"], r["length"], r["seed"]): r.get("ate") for r in runs
            if r["profile"] == profile and r["variant"] == "baseline"}
    ratios: dict[tuple, list] = {}
    for r in runs:
        if r["profile"] != profile or r["variant"] != variant:
            continue
        reference = base.get((r["sequence"], r["length"], r["seed"]))
        if reference is None:
            continue
        ratios.setdefault((r["sequence"], r["length"]), []).append(
            r["ate"] / reference if r.get("ate") is not None else None)
    return ratios


GRAPH_DESIGNS = ("baseline", "submap")
"""The two graph designs a variant is held against under a per-submap distortion (``strong``): VGGT-SLAM 2.0's
keyframe graph (the baseline) and VGGT-SLAM's submap graph."""


def better_graph_ratios(runs: list[dict], profile: str, variant: str) -> dict[tuple, list]:
    """Per sequence (name, rendered length) of a profile: the per-seed ratios ``variant / better graph`` ATE, the
    better graph being the lower ATE of :data:`GRAPH_DESIGNS` run on that seed (at least one of them); two ATEs both
    below 1 micrometre (one submap: every design's error is float rounding) count as equal (ratio 1)."""
    designs: dict[tuple, float] = {}
    for r in runs:
        if r["profile"] == profile and r["variant"] in GRAPH_DESIGNS and r.get("ate") is not None:
            key = (r["sequence"], r["length"], r["seed"])
            designs[key] = min(designs.get(key, np.inf), r["ate"])
    ratios: dict[tuple, list] = {}
    for r in runs:
        if r["profile"] != profile or r["variant"] != variant or r.get("ate") is None:
            continue
        better = designs.get((r["sequence"], r["length"], r["seed"]))
        if better is not None:
            ratio = 1.0 if max(r["ate"], better) < 1e-6 else r["ate"] / better
            ratios.setdefault((r["sequence"], r["length"]), []).append(ratio)
    return ratios


def _better_graph_table(rows: list[dict], profile: str, keys: list[tuple]) -> list[str]:
    """The lines of a profile's table of every variant (but the graph designs) against the better graph design,
    with each half's median, worst and how many sequences are within 1.5x; empty without submap-graph runs."""
    from harness import table

    if not any(r["variant"] == "submap" for r in rows):
        return []
    variants = [v for v in VARIANTS if v not in GRAPH_DESIGNS and any(r["variant"] == v for r in rows)]
    per_variant = {v: better_graph_ratios(rows, profile, v) for v in variants}
    body = []
    for half in ("tune", "validate"):
        half_keys = [k for k in keys if any(r["sequence"] == k[0] and r["split"] == half for r in rows)]
        medians = {v: [float(np.median(per_variant[v][k])) for k in half_keys if per_variant[v].get(k)] for v in variants}
        for key in half_keys:
            body.append([key[0], half, key[1] or "all",
                         *[f"{np.median(per_variant[v][key]):.2f} ({len(per_variant[v][key])})" if per_variant[v].get(key)
                           else "-" for v in variants]])
        for label, of in (("median", lambda x: f"{np.median(x):.2f}"), ("worst", lambda x: f"{max(x):.2f}"),
                          ("within 1.5x", lambda x: f"{sum(v <= 1.5 for v in x)}/{len(x)}")):
            body.append([f"**{half}: {label}**", half, "", *[of(medians[v]) if medians[v] else "-" for v in variants]])
    return [f"**{profile} profile against the better graph design** (each cell: the median over seeds of the "
            "per-seed ratio variant / the lower ATE of the baseline's keyframe graph and the submap graph on that seed, "
            "two ATEs below 1 micrometre counting as equal; in brackets the seeds)", "",
            *table(["sequence", "half", "frames", *[f"{v} / better graph" for v in variants]], body), ""]


def _half_summary(values: list) -> tuple[str, str, str]:
    """Median, worst and wins (ratio < 1) of per-sequence ratios (None: the variant failed there)."""
    numbers = [v for v in values if v is not None]
    failed = len(values) - len(numbers)
    if not values:
        return "-", "-", "-"
    median = f"{np.median(numbers):.2f}" if numbers else "-"
    worst = "failed" if failed else f"{max(numbers):.2f}"
    return median, worst, f"{sum(v < 1.0 for v in numbers)}/{len(values)}"


def projected_seconds(runs: list[dict]) -> tuple[float, float, int, float, int] | None:
    """The time one variant, seed and profile would take over the whole suite, from the runs made at
    a sequence's own length: their median seconds per keyframe times the suite's keyframes, and per
    frame times its frames (as ``bench_suite.py`` counted them, ``benchmarks/out/suite/properties.json``).

    Returns:
        ``(seconds by keyframes, seconds per keyframe, keyframes, seconds by frames, frames)``, or
        None without those runs or counts.
    """
    from harness.worlds import SUITE_OUT
    from sl4slam.synthetic.suite import SUITE, get_sequence

    counts_file = SUITE_OUT / "properties.json"
    if not counts_file.is_file():
        return None
    counts = json.loads(counts_file.read_text())
    measured = [counts[e.name] for e in SUITE if isinstance(counts.get(e.name), dict) and "keyframes" in counts[e.name]]
    keyframes, frames = sum(c["keyframes"] for c in measured), sum(c["frames"] for c in measured)
    full = [r for r in runs if r.get("ate") is not None and r.get("keyframes")
            and (r["length"] is None or r["length"] == get_sequence(r["sequence"]).frames)]
    if not full or not keyframes:
        return None
    per_keyframe = float(np.median([r["seconds"] / r["keyframes"] for r in full]))
    per_frame = float(np.median([r["seconds"] / r["frames"] for r in full]))
    return per_keyframe * keyframes, per_keyframe, keyframes, per_frame * frames, frames


def suite_report(out: Path) -> None:
    """The levers section of ``benchmarks/results/suite.md``: per-sequence ratios to the baseline and
    each half's median, worst and wins."""
    from harness import cpu_model, replace_section, table
    from sl4slam.synthetic.suite import SUITE

    runs = load_suite_runs(current=True)
    if not runs:
        return
    order = {entry.name: index for index, entry in enumerate(SUITE)}
    commands = SUITE_COMMANDS.read_text().splitlines() if SUITE_COMMANDS.is_file() else []
    lines = [SUITE_START, "## Accuracy levers on the development suite (simulated frontend, loops on)", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores; runs dated {min(r['date'] for r in runs)} to "
             f"{max(r['date'] for r in runs)}. Commands: {'; '.join(f'`{c}`' for c in commands) or '-'}. "
             "Each cell: the median over seeds of the per-seed ratio variant / baseline ATE RMSE (Sim(3)-aligned, "
             "keyframes) on the same simulated frames; the baseline column is its median ATE in metres over its seeds (the "
             "seeds column: how many; a variant's cell uses the seeds it ran). Per half: the "
             "median of the per-sequence ratios, the worst (largest; \"failed\" when a run of the variant raised) and "
             "the wins (ratio < 1) over the sequences. Choose on the tune half only; the validate half is reported.", "",
             variant_legend(runs), ""]
    for profile in PROFILES:
        rows = [r for r in runs if r["profile"] == profile]
        if not rows:
            continue
        variants = [v for v in VARIANTS if v != "baseline" and any(r["variant"] == v for r in rows)]
        keys = sorted({(r["sequence"], r["length"]) for r in rows}, key=lambda k: (order.get(k[0], 1e9), k[1] or 0))
        per_variant = {v: suite_ratios(rows, profile, v) for v in variants}
        seeds = sorted({r["seed"] for r in rows})
        body = []
        for half in ("tune", "validate"):
            half_keys = [k for k in keys if any(r["sequence"] == k[0] and r["split"] == half for r in rows)]
            for key in half_keys:
                base = [r.get("ate") for r in rows
                        if (r["sequence"], r["length"]) == key and r["variant"] == "baseline" and r.get("ate") is not None]
                cells = []
                for v in variants:
                    ratios = per_variant[v].get(key, [])
                    numbers = [x for x in ratios if x is not None]
                    cells.append("-" if not ratios else ("failed" if not numbers else f"{np.median(numbers):.2f}"))
                body.append([key[0], half, key[1] or "all", len(base), f"{np.median(base):.4f}" if base else "failed",
                             *cells])
            for label, pick in (("median", 0), ("worst", 1), ("wins", 2)):
                cells = []
                for v in variants:
                    values = []
                    for key in half_keys:
                        ratios = per_variant[v].get(key, [])
                        numbers = [x for x in ratios if x is not None]
                        if ratios:
                            values.append(float(np.median(numbers)) if numbers else None)
                    cells.append(_half_summary(values)[pick])
                body.append([f"**{half}: {label}**", half, "", "", "", *cells])
        lines += [f"**{profile} profile** ({PROFILES[profile][2]}; seeds {', '.join(map(str, seeds))})", "",
                  *table(["sequence", "half", "frames", "seeds", "baseline ATE m", *[f"{v} / baseline" for v in variants]],
                        body),
                  "", *_better_graph_table(rows, profile, keys)]
    failures = [r for r in runs if r.get("error")]
    if failures:
        lines += ["Runs that raised: " + "; ".join(f"{r['sequence']} {r['variant']} seed {r['seed']}: {r['error']}"
                                                   for r in failures) + ".", ""]
    seconds = [r["seconds"] / r["frames"] for r in runs if r.get("ate") is not None and r.get("frames")]
    if seconds:
        lines += [f"Run time: {1000 * np.median(seconds):.1f} ms per frame (median over the runs above, wall, one "
                  "worker, under whatever load they ran).", ""]
    projection = projected_seconds(runs)
    if projection:
        by_keyframes, per_keyframe, keyframes, by_frames, frames = projection
        low, high = sorted((by_keyframes, by_frames))
        lines += [f"A full run, every sequence of the suite at its own length, from the runs at a sequence's own "
                  f"length: {keyframes} keyframes x {per_keyframe:.3f} s per keyframe = {by_keyframes / 60:.0f} min, "
                  f"or {frames} frames x {1000 * by_frames / frames:.1f} ms per frame = {by_frames / 60:.0f} min, per "
                  f"variant, seed and profile on one worker; the levers' usual grid (5 variants, 5 seeds, 3 profiles): "
                  f"{75 * low / 3600 / 2:.1f}-{75 * high / 3600 / 2:.1f} h on two workers.", ""]
    lines.append(SUITE_END)
    replace_section(out, SUITE_START, SUITE_END, lines, ["# Development suite", ""])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worlds", default="synthetic,desk")
    parser.add_argument("--profiles", default="vggt,hard,strong")
    parser.add_argument("--variants", default="baseline,submap,sim3,hybrid,known-k")
    parser.add_argument("--seeds", default="5", help="a count (seeds 0..n-1) or a list (0,3,4)")
    add_parallel_arguments(parser, "--workers", 2)
    parser.add_argument("--report", action="store_true", help="only write the report from the runs there are")
    parser.add_argument("--cost", action="store_true",
                        help="time two variants side by side (first world and profile) instead of the grid")
    parser.add_argument("--out", type=Path, default=result_file("levers"))
    parser.add_argument("--suite", choices=["tune", "validate", "all"],
                        help="run on the development suite's sequences of this half instead of --worlds")
    parser.add_argument("--sequences", help="with --suite: only these sequences (comma-separated names)")
    parser.add_argument("--suite-frames", type=int, help="with --suite: render the synthetic sequences at this length")
    parser.add_argument("--suite-report", action="store_true", help="only write the suite report from the runs there are")
    args = parser.parse_args()
    seeds = list(range(int(args.seeds))) if "," not in args.seeds else [int(s) for s in args.seeds.split(",")]
    if args.suite or args.suite_report:
        if args.suite:
            run_suite(args.suite, args.sequences.split(",") if args.sequences else None, args.suite_frames,
                      args.profiles.split(","), args.variants.split(","), seeds, parallel_options(args, "--workers"))
        if args.suite:
            command = "python benchmarks/bench_levers.py " + " ".join(sys.argv[1:])
            known = SUITE_COMMANDS.read_text().splitlines() if SUITE_COMMANDS.is_file() else []
            if command not in known:
                WORK.mkdir(parents=True, exist_ok=True)
                SUITE_COMMANDS.write_text("\n".join([*known, command]) + "\n")
        suite_report(result_file("suite"))
        return
    if args.cost:
        run_cost(args.worlds.split(",")[0], args.profiles.split(",")[0], args.variants.split(",")[:2], seeds)
    elif not args.report:
        run_grid(args.worlds.split(","), args.profiles.split(","), args.variants.split(","), seeds,
                 parallel_options(args, "--workers"))
    report(args.out)


if __name__ == "__main__":
    main()
