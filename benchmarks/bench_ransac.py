"""SL(4) RANSAC versus the reference scheme on one frame's dense points.

Both estimators run side by side in one process on the same points: a 518x294 prediction grid
whose ~68 % confident pixels (~100k points, depth 0.5-3 units) are mapped by a near-identity
SL(4) transform (perspective row entries 0.05-0.2, shear, scale), with Gaussian noise
(sigma 0.002 per axis) and spatially clustered outliers (image blobs shifted coherently by
0.05-0.3 units).

- reference: 300 hypotheses, each a 5-point DLT with its own null-space SVD (no normalization),
  each scored on every point by inlier count, best hypothesis returned as is (no refit);
- ours: ``sl4slam.alignment.estimate_sl4`` with the default ``AlignmentConfig``.

Errors are against the true H: RMS transfer error over the clean points (``|H_est X_b -
H_true X_b|``, in submap units) and the largest entry difference of the SL(4)-normalized
matrices. Writes ``benchmarks/results/ransac.md`` (``--out`` for another file).

    python benchmarks/bench_ransac.py [--repeats 3] [--scenes 2]
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time
from pathlib import Path

import numpy as np

from harness import load_average, result_file, table, write_report
from sl4slam.alignment import estimate_sl4
from sl4slam.config import AlignmentConfig
from sl4slam.geometry import apply_transform
from sl4slam.synthetic.correspondences import frame_correspondences, near_identity_sl4

RESULTS = result_file("ransac")
HEIGHT, WIDTH = 294, 518


def frame_points(rng: np.random.Generator, H_a_b: np.ndarray, outlier_fraction: float, noise: float = 0.002):
    """``X_a (N, 3)``, ``X_b (N, 3)``, ``is_inlier (N,)`` for one 518x294 frame's confident pixels."""
    return frame_correspondences(rng, H_a_b, HEIGHT, WIDTH, noise, outlier_fraction,
                                 confidence_period_px=(37.0, 23.0), outlier_cell_px=40)


def reference_ransac(X_a: np.ndarray, X_b: np.ndarray, iterations: int = 300, threshold: float = 0.01, seed: int = 0) -> np.ndarray:
    """The reference scheme: per-hypothesis 5-point DLT (one SVD) scored on every point, no refit."""
    rng = np.random.default_rng(seed)
    N = len(X_a)
    B = np.concatenate([X_b, np.ones((N, 1))], axis=1)
    best_count, best_H = -1, np.eye(4)
    for _ in range(iterations):
        sample = rng.integers(0, N, 5)
        while len(np.unique(sample)) < 5:
            sample = rng.integers(0, N, 5)
        A = np.zeros((5, 3, 16))
        for i in range(3):
            A[:, i, 4 * i : 4 * i + 4] = B[sample]
            A[:, i, 12:16] = -X_a[sample, i : i + 1] * B[sample]
        H = np.linalg.svd(A.reshape(15, 16))[2][-1].reshape(4, 4)
        mapped = B @ H.T
        errors = np.linalg.norm(mapped[:, :3] / mapped[:, 3:4] - X_a, axis=1)
        count = int((errors < threshold).sum())
        if count > best_count:
            best_count, best_H = count, H
    return best_H


def as_sl4(H: np.ndarray, X_b: np.ndarray) -> np.ndarray:
    """Sign by ``w > 0`` on most points, scale by ``|det|^(1/4)`` (for comparing estimates)."""
    w = X_b @ H[3, :3] + H[3, 3]
    H = -H if np.median(w) < 0 else H
    return H / abs(np.linalg.det(H)) ** 0.25


def errors(H_est: np.ndarray, H_true: np.ndarray, X_b_clean: np.ndarray) -> tuple[float, float]:
    H_est = as_sl4(H_est, X_b_clean)
    diff = apply_transform(H_est, X_b_clean) - apply_transform(H_true, X_b_clean)
    return float(np.sqrt((diff**2).sum(axis=1).mean())), float(np.abs(H_est - H_true).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each estimator per scene")
    parser.add_argument("--scenes", type=int, default=2, help="random scenes per outlier level")
    parser.add_argument("--outliers", type=float, nargs="+", default=[0.2, 0.4], help="clustered outlier fractions")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    config = AlignmentConfig()
    loads = [load_average()]
    rows = []
    for fraction in args.outliers:
        t_ref, t_ours, e_ref, e_ours, m_ref, m_ours, ratios, sizes, drawn = [], [], [], [], [], [], [], [], []
        for scene in range(args.scenes):
            rng = np.random.default_rng([scene, int(fraction * 100)])
            H_true = near_identity_sl4(rng)
            X_a, X_b, is_inlier = frame_points(rng, H_true, fraction)
            sizes.append(len(X_a))
            clean = X_b[is_inlier]
            for repeat in range(args.repeats):
                # Alternate the order so neither estimator always runs on a warm cache.
                order = ("ref", "ours") if repeat % 2 == 0 else ("ours", "ref")
                times = {}
                for name in order:
                    start = time.perf_counter()
                    if name == "ref":
                        H_ref = reference_ransac(X_a, X_b, config.ransac_iterations, config.inlier_threshold, seed=repeat)
                    else:
                        result = estimate_sl4(X_a, X_b, config, seed=repeat)
                    times[name] = time.perf_counter() - start
                assert result.model == "sl4", result.fallback
                drawn.append(result.extras["hypotheses"])
                t_ref.append(times["ref"])
                t_ours.append(times["ours"])
                ratios.append(times["ref"] / times["ours"])
                rms_ref, max_ref = errors(H_ref, H_true, clean)
                rms_ours, max_ours = errors(result.H, H_true, clean)
                e_ref.append(rms_ref)
                e_ours.append(rms_ours)
                m_ref.append(max_ref)
                m_ours.append(max_ours)
        row = {
            "fraction": fraction,
            "points": int(np.median(sizes)),
            "t_ref": np.median(t_ref),
            "t_ours": np.median(t_ours),
            "ratio": np.median(ratios),
            "e_ref": np.median(e_ref),
            "e_ours": np.median(e_ours),
            "m_ref": np.median(m_ref),
            "m_ours": np.median(m_ours),
            "runs": len(ratios),
            "drawn": int(np.median(drawn)),
        }
        rows.append(row)
        loads.append(load_average())
        print(row, flush=True)

    command = "python benchmarks/bench_ransac.py" + (
        f" --repeats {args.repeats} --scenes {args.scenes} --outliers {' '.join(map(str, args.outliers))}"
    )
    lines = [
        "## SL(4) RANSAC: ours vs the reference scheme",
        "",
        "Machine: 2-core CPU, 24 GiB RAM, no GPU; "
        f"Python {platform.python_version()}, numpy {np.__version__}. Date: {datetime.date.today()}.",
        f"Command: `{command}`",
        f"1-minute load average during the run: {min(loads):.1f}-{max(loads):.1f} on 2 cores; absolute "
        "times grow with it, the speed-up is measured side by side and is the figure to compare.",
        "",
        f"One {WIDTH}x{HEIGHT} frame's confident pixels (~68 %), depth 0.5-3 units, true H near identity "
        "(perspective row 0.05-0.2, shear, scale), noise sigma 0.002 per axis, clustered outliers "
        "(image blobs, each 40 px cell shifted by 0.05-0.3 units). Both estimators run side by side in one "
        "process on the same points, alternating order; figures are medians over scenes x repeats.",
        "",
        "- reference: 300 hypotheses, one 15x16 null-space SVD each, every hypothesis scored on every point "
        "(inlier count), no refit;",
        "- ours: `estimate_sl4` with the default `AlignmentConfig` (Hartley normalization; hypotheses built and "
        "scored in batches of 50, adaptively up to 300 at confidence 0.999; preemptive MSAC scoring on 1024 then "
        f"{config.max_points} points; weighted DLT refit on the inliers, re-scored on all points).",
        "",
        "Errors against the true H: transfer RMS over the clean points (units) and the largest entry "
        "difference of the SL(4)-normalized matrices.",
        "",
        *table(["outliers", "points", "runs", "ours: hypotheses drawn", "reference time (s)", "ours time (s)",
                "speed-up (median of per-run ratios)", "reference transfer RMS", "ours transfer RMS",
                "reference max entry err", "ours max entry err"],
               [[f"{row['fraction']:.0%}", row["points"], row["runs"], row["drawn"], f"{row['t_ref']:.3f}",
                 f"{row['t_ours']:.3f}", f"{row['ratio']:.1f}x", f"{row['e_ref']:.2e}", f"{row['e_ours']:.2e}",
                 f"{row['m_ref']:.2e}", f"{row['m_ours']:.2e}"] for row in rows]),
    ]
    write_report(args.out, lines)


if __name__ == "__main__":
    main()
