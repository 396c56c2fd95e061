"""ORB retrieval's coarse ranking as the map grows: every stored keyframe scored, or groups first.

Two measurements, in one process:

- **Agreement.** Every sequence of the development suite (``sl4slam.synthetic.suite``: the
  synthetic ones and the real TUM RGB-D ones found in the shared data), one after another, as one
  long stream of keyframes (the run's keyframe selector at its defaults), cut into submaps of 16
  keyframes. Each submap queries the database (``max_results = 1``, as the pipeline asks) twice:
  with the coarse ranking over every stored keyframe (``orb_coarse_flat_rows`` above the database
  size) and by groups (``orb_coarse_flat_rows = 0``, so that every query of the stream goes
  through the groups, from a few hundred stored keyframes to the whole suite's). Reported: the
  loops each finds, how many are the same pair, and the loops that match a keyframe of another
  sequence (wrong by construction: the sequences are different places); plus the share of the
  flat ranking's candidate rows the grouped one also holds.
- **Cost.** The coarse ranking of a submap's 17 query keyframes against databases of 4096, 16000
  and 48000 stored keyframes (the stream's hashed rows repeated to that size), flat and by groups,
  interleaved, median of the rounds.

Writes ``benchmarks/results/retrieval_scale.md`` (``--out`` for another file). Run from the
repository root:

    python benchmarks/bench_retrieval_scale.py

The suite's synthetic sequences are rendered into ``benchmarks/out/suite`` if they are not there
(about 13 minutes on two cores; ``--suite-root`` for another folder).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from harness import (OUT, cpu_model, date_text, interleaved_times, memory_gib, result_file, table,
                     write_report)
from harness.worlds import suite_sequence
from sl4slam.config import KeyframeConfig, RetrievalConfig
from sl4slam.io import open_source
from sl4slam.io.memory import frames_from_images
from sl4slam.keyframes import KeyframeSelector
from sl4slam.retrieval.orb import COARSE_CANDIDATES, GROUP_ROWS, OrbRetrieval, _global_vector
from sl4slam.synthetic import write_synthetic_sequence
from sl4slam.synthetic.styles import STYLES
from sl4slam.synthetic.suite import SUITE, SUITE_HEIGHT, SUITE_WIDTH, SuiteSequence, is_rendered

RESULT = result_file("retrieval_scale")
SUBMAP = 16
SIZES = (4096, 16000, 48000)
ROUNDS = 15
FLAT = 10**9  # orb_coarse_flat_rows above any database: every row scored


def sequence_folder(name: str, root) -> Path:
    """The folder of a suite sequence, or of a suite style at another seed (``<style>-s<seed>``),
    rendered at the suite's size if it is not there yet."""
    style, _, seed = name.rpartition("-s")
    if name in {s.name for s in SUITE} or style not in STYLES:
        return suite_sequence(name, root=root)
    sequence = SuiteSequence(name, style, int(seed), STYLES[style].frames, None, STYLES[style].description)
    folder = Path(root) / name
    if not is_rendered(folder, sequence, SUITE_WIDTH, SUITE_HEIGHT):
        write_synthetic_sequence(folder, num_frames=sequence.frames, width=SUITE_WIDTH, height=SUITE_HEIGHT,
                                 seed=sequence.seed, overwrite=True, style=style)
    return folder


def stream_names(split: str, seeds: list[int]) -> list[str]:
    """Every style of the suite at each of ``seeds`` in the ``split`` half (even seeds: tune, odd:
    validate, as the suite splits), and the real sequences in the validate half."""
    names = [f"{style}-s{seed}" for style in STYLES for seed in seeds
             if split == "all" or (seed % 2 == 0) == (split == "tune")]
    if split != "tune":
        names += [s.name for s in SUITE if s.real]
    return names


def keyframe_stream(names: list[str], root) -> tuple[list[np.ndarray], list[str]]:
    """Every listed sequence's keyframes (the default keyframe selector), one sequence after
    another, and the sequence each came from."""
    images, owners = [], []
    for name in names:
        folder = sequence_folder(name, root)
        if not folder.is_dir():
            print(f"{name}: not found at {folder}; left out", file=sys.stderr)
            continue
        selector = KeyframeSelector(KeyframeConfig())
        source = open_source(folder)
        kept = 0
        for frame in source:
            if selector.is_keyframe(frame.rgb):
                images.append(frame.rgb)
                owners.append(name)
                kept += 1
        print(f"{name}: {kept} keyframes", file=sys.stderr)
    return images, owners


def agreement(images: list[np.ndarray], owners: list[str], kept_groups: list[int]) -> dict:
    """Loops found with the flat ranking and with the grouped one keeping each of ``kept_groups``
    groups per query keyframe, on one database (module doc)."""
    config = RetrievalConfig(orb_coarse_flat_rows=FLAT)
    retrieval = OrbRetrieval(config)
    modes = {"flat": config, **{f"{g} groups": replace(config, orb_coarse_flat_rows=0, orb_coarse_groups=g)
                                 for g in kept_groups}}
    counts = {mode: {"loops": 0, "same": 0, "other_sequence": 0, "rows_kept": [], "ms": []} for mode in modes}
    per_sequence = {name: {mode: 0 for mode in modes} for name in dict.fromkeys(owners)}  # loops of its queries
    submaps = 0
    for submap_id, first in enumerate(range(0, len(images), SUBMAP)):
        indices = list(range(first, min(first + SUBMAP, len(images))))
        frames = frames_from_images(indices, [images[i] for i in indices])
        eligible = np.flatnonzero(retrieval._submap_ids <= submap_id - 1 - config.tau_interval)
        queries = np.stack([_global_vector(retrieval.extract(images[i])) for i in indices])
        found, ranked = {}, {}
        for mode, settings in modes.items():
            retrieval.config = settings
            retrieval.forget_query_features()  # each query extracts its features, as in a run
            start = time.perf_counter()
            candidates = retrieval.query(frames, submap_id, max_results=1)
            counts[mode]["ms"].append(1e3 * (time.perf_counter() - start))
            found[mode] = {(c.query_frame, c.match_frame) for c in candidates}
            counts[mode]["loops"] += len(candidates)
            counts[mode]["other_sequence"] += sum(owners[q] != owners[m] for q, m in found[mode])
            counts[mode]["same"] += len(found[mode] & found["flat"])
            for query, _ in found[mode]:
                per_sequence[owners[query]][mode] += 1
            if len(eligible) > COARSE_CANDIDATES:
                ranked[mode] = set(retrieval.coarse_rows(queries, eligible).tolist())
                counts[mode]["rows_kept"].append(len(ranked[mode] & ranked["flat"]) / len(ranked["flat"]))
        retrieval.config = config
        retrieval.add(frames, submap_id)
        submaps += 1
    return {"submaps": submaps, "stored": len(retrieval), "modes": counts, "per_sequence": per_sequence,
            "hashed_rows": retrieval._global[: len(retrieval)].copy()}


def cost(rows: np.ndarray, groups: int, queries: np.ndarray) -> list[dict]:
    """Milliseconds of the coarse ranking of ``queries`` against ``SIZES`` stored rows (``rows``
    repeated), flat and by groups."""
    results = []
    for size in SIZES:
        retrieval = OrbRetrieval(RetrievalConfig(orb_coarse_groups=groups))
        for position in range(size):
            retrieval._append_global_row(position, rows[position % len(rows)])
        eligible = np.arange(size)
        flat = replace(retrieval.config, orb_coarse_flat_rows=FLAT)
        grouped = replace(retrieval.config, orb_coarse_flat_rows=0)

        def ranked(config):
            def run():
                retrieval.config = config
                retrieval.coarse_rows(queries, eligible)
            return run

        times = interleaved_times({"flat": ranked(flat), "grouped": ranked(grouped)}, ROUNDS)
        results.append({"size": size, "flat_ms": 1e3 * statistics.median(times["flat"]),
                        "grouped_ms": 1e3 * statistics.median(times["grouped"])})
        print(f"{size} rows: flat {results[-1]['flat_ms']:.1f} ms, grouped {results[-1]['grouped_ms']:.1f} ms",
              file=sys.stderr)
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(RESULT))
    parser.add_argument("--suite-root", default=str(OUT / "suite"), help="where the suite's renderings are kept")
    parser.add_argument("--sequences", default=None, help="comma-separated suite sequences (default: all)")
    parser.add_argument("--split", default="all", choices=("tune", "validate", "all"),
                        help="the suite's half whose sequences make the stream (default: all)")
    parser.add_argument("--groups", default="8,16,32", help="groups kept per query keyframe to compare")
    parser.add_argument("--seeds", default="0,1", help="the seeds of the suite's styles (the suite's own: 0,1; "
                        "others are rendered into --suite-root at the suite's size)")
    args = parser.parse_args()
    seeds = [int(seed) for seed in args.seeds.split(",")]
    names = args.sequences.split(",") if args.sequences else stream_names(args.split, seeds)
    kept_groups = [int(g) for g in args.groups.split(",")]
    images, owners = keyframe_stream(names, args.suite_root)
    found = agreement(images, owners, kept_groups)
    rows = found.pop("hashed_rows")
    queries = rows[len(rows) // 2: len(rows) // 2 + SUBMAP + 1]
    costs = {g: cost(rows, g, queries) for g in kept_groups}
    sequences = sorted(set(owners))
    modes = found["modes"]

    def kept(mode):
        share = np.array(modes[mode]["rows_kept"])
        return (f"{100 * share.mean():.1f} % ({100 * np.mean(share == 1):.0f} % of submaps all, "
                f"worst {100 * share.min():.0f} %)")

    lines = [
        "## ORB retrieval's coarse ranking as the map grows: every keyframe, or groups first",
        "",
        f"Machine: {cpu_model()}, {memory_gib():.0f} GiB, no GPU. Date: {date_text()}.",
        f"Command: `python benchmarks/bench_retrieval_scale.py --split {args.split} --seeds {args.seeds} "
        f"--groups {args.groups}`.",
        "",
        f"### Agreement: {len(sequences)} sequences of the suite ({args.split}) as one stream",
        "",
        f"{found['stored']} keyframes (the default keyframe selector) from {', '.join(sequences)}, one after "
        f"another, in {found['submaps']} submaps of {SUBMAP}; each submap queried (one loop at most) with the "
        f"coarse ranking over every stored keyframe and by groups of {GROUP_ROWS}, forced for every query here. "
        "A loop that matches a keyframe of another sequence is wrong (they are different places). "
        f"Rows kept: of the rows the flat ranking passes to the exact tf-idf (up to {COARSE_CANDIDATES} per query "
        "keyframe), the share the grouped one passes too.",
        "",
        *table(["coarse ranking", "loops found", "the same pair as the flat ranking", "matched another sequence (wrong)",
                "rows kept", "query ms with features (median)"],
               [["every keyframe" if mode == "flat" else f"by groups, {mode} kept", m["loops"], m["same"],
                 m["other_sequence"], "100 %" if mode == "flat" else kept(mode), f"{statistics.median(m['ms']):.1f}"]
                for mode, m in modes.items()]),
        "",
        "Loops found per sequence (by its query keyframes):",
        "",
        *table(["sequence", "every keyframe", *[f"{g} groups kept" for g in kept_groups]],
               [[name, *[counts[mode] for mode in modes]] for name, counts in found["per_sequence"].items()]),
        "",
        "### Cost of the coarse ranking (17 query keyframes)",
        "",
        *table(["stored keyframes", "every keyframe (ms)", *[f"by groups, {g} kept (ms)" for g in kept_groups]],
               [[c["size"], f"{c['flat_ms']:.1f}", *[f"{costs[g][k]['grouped_ms']:.1f}" for g in kept_groups]]
                for k, c in enumerate(costs[kept_groups[0]])]),
        "",
        f"Medians of {ROUNDS} interleaved rounds; the stream's hashed rows repeated to each size (the cost "
        "depends on the sizes only).",
    ]
    write_report(args.out, lines)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
