"""Backend cost per submap: flat for odometry, and the price of absorbing a loop closure.

Measures, for the SL(4) and Sim(3) backends side by side in one process:
  * wall time of ``add_submap`` + ``update`` per submap along a 300-submap chain with noisy
    odometry (median over submaps 10-20 and over 290-300: flat means the ratio stays near 1);
  * wall time of the ``update`` that absorbs one loop closure (first node to last) after 100 and
    after 300 submaps (that update relinearizes the whole loop, so it grows with the map);
  * wall time of the final Gauss-Newton polish (``final_estimates``) at 300 submaps, and how far
    it moves iSAM2's estimate and how close it lands to a tight batch Levenberg-Marquardt.

Writes ``benchmarks/results/backend.md`` (``--out`` for another file).
Usage: ``python benchmarks/bench_backend.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import numpy as np
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from harness import result_file, table, write_report
from sl4slam.backend import make_backend
from sl4slam.config import BackendConfig

NUM_SUBMAPS = 300
LOOP_SIZES = (100, 300)
LOOP_EVERY = 50
LOOP_SPAN = 45
RESULTS = result_file("backend")


def random_step(kind: str, rng: np.random.Generator, scale: float) -> np.ndarray:
    """A random relative transform near the identity (4, 4): SL(4) or a similarity."""
    if kind == "sl4":
        A = rng.normal(scale=scale, size=(4, 4))
        A -= np.trace(A) / 4.0 * np.eye(4)
        return expm(A)
    T = np.eye(4)
    T[:3, :3] = np.exp(rng.normal(scale=scale)) * Rotation.from_rotvec(rng.normal(scale=scale, size=3)).as_matrix()
    T[:3, 3] = rng.normal(scale=10 * scale, size=3)
    return T


def make_problem(kind: str, num_submaps: int, seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Ground-truth nodes and noisy odometry ``H_{k-1}_k`` (k = 1..num_submaps-1)."""
    rng = np.random.default_rng(seed)
    steps = [random_step(kind, rng, 0.05) for _ in range(num_submaps - 1)]
    truth = [np.eye(4)]
    for step in steps:
        truth.append(truth[-1] @ step)
    odometry = [step @ random_step(kind, rng, 0.005) for step in steps]
    return truth, odometry


def odometry_times(kind: str, seed: int, loop_every: int = 0) -> np.ndarray:
    """Seconds of add_submap (+ add_loop) + update for each of NUM_SUBMAPS submaps.

    With ``loop_every > 0``, every ``loop_every``-th submap also closes a loop to the submap
    ``LOOP_SPAN`` before it; the odometry-only submaps around 290-300 then show whether earlier
    loops leave later updates more expensive.
    """
    truth, odometry = make_problem(kind, NUM_SUBMAPS, seed)
    backend = make_backend(BackendConfig(kind=kind, graph="submap"))
    times = np.empty(NUM_SUBMAPS)
    for k in range(NUM_SUBMAPS):
        start = time.perf_counter()
        backend.add_submap(k, None if k == 0 else odometry[k - 1])
        if loop_every and k % loop_every == 0 and k >= LOOP_SPAN:
            backend.add_loop(k - LOOP_SPAN, k, np.linalg.inv(truth[k - LOOP_SPAN]) @ truth[k])
        backend.update()
        times[k] = time.perf_counter() - start
    return times


def loop_update_time(kind: str, num_submaps: int, seed: int) -> tuple[float, int]:
    """Seconds (and iSAM2 iterations) of the update absorbing a loop from the last node to the first."""
    truth, odometry = make_problem(kind, num_submaps, seed)
    backend = make_backend(BackendConfig(kind=kind, graph="submap"))
    for k in range(num_submaps):
        backend.add_submap(k, None if k == 0 else odometry[k - 1])
        backend.update()
    last = num_submaps - 1
    backend.add_loop(0, last, np.linalg.inv(truth[0]) @ truth[last])
    start = time.perf_counter()
    backend.update()
    return time.perf_counter() - start, backend.graph.last_update_iterations


def final_polish(kind: str, num_submaps: int, seed: int) -> tuple[float, float, float]:
    """A chain with a loop every LOOP_EVERY submaps and one from the last node to the first, fed
    through iSAM2; then ``final_estimates``. Returns its seconds, the largest entry change it made
    to iSAM2's estimate, and the largest entry difference to a tight batch Levenberg-Marquardt."""
    import gtsam

    truth, odometry = make_problem(kind, num_submaps, seed)
    backend = make_backend(BackendConfig(kind=kind, graph="submap"))
    for k in range(num_submaps):
        backend.add_submap(k, None if k == 0 else odometry[k - 1])
        if k % LOOP_EVERY == 0 and k >= LOOP_SPAN:
            backend.add_loop(k - LOOP_SPAN, k, np.linalg.inv(truth[k - LOOP_SPAN]) @ truth[k])
        backend.update()
    last = num_submaps - 1
    backend.add_loop(0, last, np.linalg.inv(truth[0]) @ truth[last])
    backend.update()
    incremental = backend.world_estimate().H_world_submap
    start = time.perf_counter()
    final = backend.world_estimate(final=True).H_world_submap
    seconds = time.perf_counter() - start
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(100)
    batch = gtsam.LevenbergMarquardtOptimizer(backend.graph.factor_graph(), backend.graph.isam_values(), params).optimize()
    batched = backend.graph.matrices_in(batch)
    change = max(float(np.abs(final[k] - incremental[k]).max()) for k in final)
    gap = max(float(np.abs(final[k] - batched[k]).max()) for k in final)
    return seconds, change, gap


def polish_row(kind: str, runs: list[tuple[float, float, float]]) -> list[str]:
    """The final-polish row of a backend: medians of its seconds, change and gap over the runs."""
    seconds, change, gap = (np.median([r[i] for r in runs]) for i in range(3))
    return [kind, f"{seconds * 1e3:.1f}", f"{change:.1e}", f"{gap:.1e}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="independent runs per measurement (median)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    kinds = ("sl4", "sim3")

    early, late = {}, {}
    for kind in kinds:
        for loop_every in (0, LOOP_EVERY):
            runs = [odometry_times(kind, seed, loop_every) for seed in range(args.repeats)]
            early[kind, loop_every] = float(np.median([np.median(t[10:20]) for t in runs]))
            late[kind, loop_every] = float(np.median([np.median(t[290:300]) for t in runs]))

    loop_seconds, loop_iterations = {}, {}
    for kind in kinds:
        for size in LOOP_SIZES:
            results = [loop_update_time(kind, size, seed) for seed in range(args.repeats)]
            loop_seconds[kind, size] = float(np.median([r[0] for r in results]))
            loop_iterations[kind, size] = int(np.median([r[1] for r in results]))

    polish = {kind: [final_polish(kind, NUM_SUBMAPS, seed) for seed in range(args.repeats)] for kind in kinds}

    ms = 1e3
    lines = [
        "## Backend: cost per submap and per loop closure",
        "",
        f"Machine: 2-core CPU, 24 GiB RAM, no GPU. Date: {datetime.date.today()}.",
        f"Command: `python benchmarks/bench_backend.py --repeats {args.repeats}`",
        "",
        f"A chain of {NUM_SUBMAPS} random submap transforms near the identity with noisy odometry, "
        "fed one submap at a time (iSAM2). Times are medians over submaps in the window and then over "
        f"{args.repeats} seeded runs; both backends measured in the same process.",
        "",
        f"The second row per backend also closes a loop (span {LOOP_SPAN}) every {LOOP_EVERY} submaps; "
        "submaps 290-300 are odometry-only in both.",
        "",
        *table(["backend", "loops", "add_submap+update, submaps 10-20 (ms)", "submaps 290-300 (ms)", "late / early"],
               [[kind, f"every {loop_every}" if loop_every else "none", f"{early[kind, loop_every] * ms:.3f}",
                 f"{late[kind, loop_every] * ms:.3f}", f"{late[kind, loop_every] / early[kind, loop_every]:.2f}"]
                for kind in kinds for loop_every in (0, LOOP_EVERY)]),
    ]
    lines += [
        "",
        "Update that absorbs one loop closure (node 0 to the newest node; the loop corrects the odometry's "
        "drift, so iSAM2 iterates, relinearizing, while some step exceeds 5e-2; the cost grows with the "
        "loop's length):",
        "",
        *table(["backend", "submaps", "loop update (ms)", "iSAM2 iterations"],
               [[kind, size, f"{loop_seconds[kind, size] * ms:.2f}", loop_iterations[kind, size]]
                for kind in kinds for size in LOOP_SIZES]),
    ]
    lines += [
        "",
        f"End of a run ({NUM_SUBMAPS} submaps, a loop every {LOOP_EVERY} and one from the last node to the "
        "first): iSAM2 relinearizes only variables whose step exceeds 1e-2, so `final_estimates` polishes "
        "the whole graph once by Gauss-Newton:",
        "",
        *table(["backend", "final polish (ms)", "largest entry change to iSAM2's estimate",
                "largest entry difference to batch LM"], [polish_row(kind, polish[kind]) for kind in kinds]),
    ]
    lines += [
        "",
        f"Sim(3) / SL(4) per-submap time at 290-300: {late['sim3', 0] / late['sl4', 0]:.2f}; "
        f"loop update at 300: {loop_seconds['sim3', 300] / loop_seconds['sl4', 300]:.2f}.",
        "",
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
