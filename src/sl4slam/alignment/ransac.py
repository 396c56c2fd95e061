"""Robust relative alignment of two submaps from one frame's points (paper 4.2).

``estimate_sl4`` fits the 15-DOF projective map ``H_a_b`` (``X_a ~ H_a_b X_b``) with RANSAC over
5-point DLT samples; ``estimate_sim3`` fits a 7-DOF similarity with RANSAC over 3-point Umeyama
samples. Both share the machinery below:

1. Hypotheses are built in batches (``batch x sample_size`` indices drawn from the seeded
   generator, one batched solver call per batch); degenerate samples are discarded, never
   replaced. Drawing stops adaptively once the best hypothesis' inlier fraction says an
   all-inlier sample has been drawn with ``config.ransac_confidence`` (for SL(4), only if that
   hypothesis' inliers are not confined to a plane), and at ``config.ransac_iterations`` (the
   paper's 300) at most.
2. Hypotheses are scored in batch with the MSAC cost (truncated squared transfer error) of
   ``|X_a - H X_b|`` after homogeneous division, in ``X_a``'s units; points that ``H`` maps to
   ``w <= 0`` (behind the plane sent to infinity) are outliers. Scoring uses a seeded random
   subset of at most ``config.max_points`` correspondences, preceded by a preemptive round on a
   small subset that keeps only the best hypotheses (Nister's preemptive RANSAC idea).
3. The best hypothesis is refitted by least squares on all its inliers and re-scored on all
   correspondences, for a few rounds while the cost decreases.

When the projective fit is degenerate (too few correspondences or inliers, nearly coplanar points,
every sample degenerate) ``estimate_sl4`` falls back to the Sim(3) model on the same points and
says so in ``Alignment.fallback``.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from .settings import AlignmentConfig
from ..geometry import normalize_sl4, umeyama_sim3, umeyama_sim3_batch
from ..types import Alignment
from .common import clean_correspondences, make_alignment
from .dlt import (DLT_SVD_POINTS, dlt_homogeneous, dlt_normal_matrix_from_terms, dlt_normal_solution, dlt_normal_terms,
                  fix_sign_by_w, minimal_sl4_batch, normalize_points)

SCORE_BLOCK = 1 << 21
"""Hypothesis x point entries scored at once (bounds the temporary memory to ~100 MB; no effect
on results)."""

Solver = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


# --------------------------------------------------------------------------------------------
# Shared machinery


def transfer_errors(H: np.ndarray, X_a: np.ndarray, X_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared transfer errors ``|X_a - H X_b|^2`` for a batch of hypotheses.

    Args:
        H: ``(M, 4, 4)`` hypotheses with the sign convention ``w > 0`` for points in front.
        X_a, X_b: ``(n, 3)`` correspondences; their dtype (float32 or float64) is used throughout.

    Returns:
        r2: ``(M, n)`` squared distances in ``X_a``'s units (after homogeneous division);
            meaningless (computed with ``w = 1``) where ``in_front`` is False.
        in_front: ``(M, n)`` bool, ``w > 0``.
    """
    M, n = len(H), len(X_b)
    dtype = X_b.dtype
    # One (4M, 3) x (3, n) product maps every point through every hypothesis.
    mapped = (H[:, :, :3].reshape(4 * M, 3).astype(dtype) @ X_b.T).reshape(M, 4, n)
    mapped += H[:, :, 3].astype(dtype)[:, :, None]
    w = mapped[:, 3]
    in_front = w > 0
    inv_w = np.divide(dtype.type(1.0), w, out=np.ones_like(w), where=in_front)
    # x, y, z components, each vectorized over hypotheses and points; the first one starts the
    # sum (0 + d^2 is d^2 exactly), so no zeroed array is added to
    r2 = mapped[:, 0] * inv_w
    r2 -= X_a[:, 0]
    r2 *= r2
    for axis in (1, 2):
        d = mapped[:, axis] * inv_w
        d -= X_a[:, axis]
        d *= d
        r2 += d
    return r2, in_front


def msac_costs(H: np.ndarray, X_a: np.ndarray, X_b: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """MSAC cost ``sum min(r^2, t^2)`` per hypothesis ``(M,)`` (points with ``w <= 0`` cost ``t^2``)
    and the inlier count of each hypothesis ``(M,)``."""
    thr2 = threshold**2
    block = max(1, SCORE_BLOCK // max(len(X_a), 1))
    costs = np.empty(len(H))
    counts = np.empty(len(H), dtype=np.int64)
    for start in range(0, len(H), block):  # blocks of hypotheses bound the temporary memory
        r2, in_front = transfer_errors(H[start : start + block], X_a, X_b)
        inliers = in_front & (r2 < thr2)
        costs[start : start + block] = np.where(inliers, r2, thr2).sum(axis=1)
        counts[start : start + block] = inliers.sum(axis=1)
    return costs, counts


def hypotheses_needed(inlier_fraction: float, sample_size: int, confidence: float) -> float:
    """Samples needed to draw one all-inlier sample with probability ``confidence`` (the classic
    RANSAC bound ``log(1 - p) / log(1 - w^k)``); ``inf`` when ``w^k`` is zero."""
    all_inliers = inlier_fraction**sample_size
    if all_inliers <= 0:
        return float("inf")
    if all_inliers >= 1:
        return 0.0
    return float(np.log(1.0 - confidence) / np.log1p(-all_inliers))


def score_one(H: np.ndarray, X_a: np.ndarray, X_b: np.ndarray, threshold: float) -> tuple[float, np.ndarray, np.ndarray]:
    """One hypothesis on all points: ``(msac_cost, inliers (n,), squared_errors (n,))``."""
    r2, in_front = transfer_errors(H[None], X_a, X_b)
    r2, in_front = r2[0], in_front[0]
    thr2 = threshold**2
    inliers = in_front & (r2 < thr2)
    return float(np.where(inliers, r2, thr2).sum()), inliers, r2


def draw_samples(
    num_points: int, sample_size: int, num_samples: int, rng: np.random.Generator, small_set: int = 4096
) -> tuple[np.ndarray, np.ndarray]:
    """Index samples ``(num_samples, sample_size)`` and a mask of samples without repeated indices.

    Up to ``small_set`` points, each sample is a prefix of a random permutation (no repeats)."""
    if num_points <= small_set:
        order = rng.permuted(np.broadcast_to(np.arange(num_points), (num_samples, num_points)), axis=1)
        return order[:, :sample_size], np.ones(num_samples, dtype=bool)
    samples = rng.integers(0, num_points, size=(num_samples, sample_size))
    ordered = np.sort(samples, axis=1)
    return samples, (np.diff(ordered, axis=1) > 0).all(axis=1)


def ransac_best(
    X_a: np.ndarray,
    X_b: np.ndarray,
    solver: Solver,
    sample_size: int,
    threshold: float,
    config: AlignmentConfig,
    rng: np.random.Generator,
    may_stop_early: Callable[[np.ndarray], bool] | None = None,
) -> tuple[np.ndarray | None, dict]:
    """Batched, adaptive hypothesize-and-score; returns the lowest-cost hypothesis (or None) and statistics.

    Hypotheses come in batches of ``config.hypothesis_batch`` (one solver call and one scoring pass each);
    ``stats["top"]`` keeps the ``config.refit_candidates`` lowest-cost ones for local optimization.
    After every batch the best hypothesis' inlier fraction ``w`` on the scoring subset updates the
    number of samples needed to have drawn an all-inlier sample with probability
    ``config.ransac_confidence``; drawing stops there, and never goes beyond
    ``config.ransac_iterations``. Well-aligned submaps (most inliers) thus need one batch.

    Args:
        X_a, X_b: ``(N, 3)`` finite correspondences (in whatever frame the solver expects).
        solver: ``(M, k, 3), (M, k, 3) -> (H (M, 4, 4), valid (M,))``, fitting ``X_a ~ H X_b``.
        sample_size: ``k``.
        threshold: inlier distance in ``X_a``'s units.
        may_stop_early: given the ``X_b`` inliers (on the scoring subset) of the best hypothesis,
            whether the adaptive stop may trust it; if not, every hypothesis up to
            ``config.ransac_iterations`` is drawn. The confidence bound assumes that an all-inlier
            sample gives the right model, which fails when the inliers are a near-degenerate
            configuration (a dominant plane for the 15-DOF map).
    """
    N = len(X_a)
    scored = rng.permutation(N)[: config.max_points]  # random order: any prefix is a random subset
    # Ranking hypotheses needs far less precision than float64 (errors ~1e-7 vs a 1e-2 threshold).
    sub_a = np.take(X_a, scored, axis=0).astype(np.float32)
    sub_b = np.take(X_b, scored, axis=0).astype(np.float32)
    preemptive_points = int(config.preemptive_points)
    preemptive = len(scored) > 2 * preemptive_points
    limit = int(config.ransac_iterations)
    needed = float(limit)
    stats = {"hypotheses": 0, "degenerate_samples": 0, "fully_scored_hypotheses": 0, "scored_points": int(len(scored))}
    best_H, best_cost = None, np.inf
    top_H, top_cost = np.zeros((0, 4, 4)), np.zeros(0)  # the config.refit_candidates best so far
    while stats["hypotheses"] < min(limit, needed):
        count = min(int(config.hypothesis_batch), limit - stats["hypotheses"])
        samples, distinct = draw_samples(N, sample_size, count, rng, int(config.small_set))
        H, valid = solver(X_a[samples], X_b[samples])
        valid &= distinct
        stats["hypotheses"] += count
        stats["degenerate_samples"] += int((~valid).sum())
        if not valid.any():
            continue
        H = H[valid]
        keep = max(int(config.preemptive_min_keep), int(np.ceil(config.preemptive_keep * len(H))))
        if preemptive and len(H) > keep:
            costs, _ = msac_costs(H, sub_a[:preemptive_points], sub_b[:preemptive_points], threshold)
            H = H[np.argpartition(costs, keep - 1)[:keep]]
        stats["fully_scored_hypotheses"] += int(len(H))
        costs, counts = msac_costs(H, sub_a, sub_b, threshold)
        order = np.argsort(np.concatenate([top_cost, costs]), kind="stable")[: int(config.refit_candidates)]
        top_H, top_cost = np.concatenate([top_H, H])[order], np.concatenate([top_cost, costs])[order]
        best = int(np.argmin(costs))
        if costs[best] < best_cost:
            best_H, best_cost = H[best], float(costs[best])
            needed = hypotheses_needed(counts[best] / len(scored), sample_size, config.ransac_confidence)
            if may_stop_early is not None and needed <= stats["hypotheses"]:
                _, inliers, _ = score_one(best_H, sub_a, sub_b, threshold)
                if not may_stop_early(sub_b[inliers]):
                    needed = float(limit)
    stats["stopped_early"] = stats["hypotheses"] < limit
    stats["top"] = top_H
    return best_H, stats


def refine(
    H: np.ndarray,
    X_a: np.ndarray,
    X_b: np.ndarray,
    threshold: float,
    fit: Callable[[np.ndarray, np.ndarray], np.ndarray],
    min_points: int,
    config: AlignmentConfig,
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, int]:
    """Least-squares refit on the inliers, re-score on all points, repeat (at most
    ``config.refit_rounds`` times) while the inlier set changes and the cost drops by at least
    ``config.refit_min_gain`` (relative).

    With ``config.max_refit_points > 0`` the fit uses an evenly strided subset of at most that many
    inliers (dense points are spatially ordered, so the subset covers the frame evenly): the
    estimate is as good for a fraction of the cost; scoring always uses every point.

    Args:
        H: ``(4, 4)`` starting hypothesis (``X_a ~ H X_b``).
        fit: ``(chosen, H_current) -> H_new``, the fit on the rows ``chosen`` ``(n,)`` of ``X_a, X_b``
            (indices, so that a fit may reuse per-point terms it computed once); may raise ``ValueError``.
        min_points: fewest inliers the fit accepts.

    Returns:
        ``(H, cost, inliers (N,), squared_errors (N,), accepted_refits)``.
    """
    cost, inliers, r2 = score_one(H, X_a, X_b, threshold)
    accepted = 0
    max_fit_points = int(config.max_refit_points)
    for _ in range(int(config.refit_rounds)):
        if inliers.sum() < min_points:
            break
        chosen = np.flatnonzero(inliers)
        if max_fit_points > 0 and len(chosen) > max_fit_points:
            chosen = chosen[:: -(-len(chosen) // max_fit_points)]
        try:
            H_new = fit(chosen, H)
        except ValueError:  # degenerate least-squares fit: keep the current estimate
            break
        cost_new, inliers_new, r2_new = score_one(H_new, X_a, X_b, threshold)
        if not cost_new < cost:
            break
        # same inlier set, or a negligible gain: another refit would only nudge the 1/w^2 weights
        settled = np.array_equal(inliers_new, inliers) or cost - cost_new < config.refit_min_gain * cost
        H, cost, inliers, r2 = H_new, cost_new, inliers_new, r2_new
        accepted += 1
        if settled:
            break
    return H, cost, inliers, r2, accepted


def planarity(X: np.ndarray, max_points: int = 20000) -> float:
    """Thickness / extent of points ``(N, 3)``: 0 for coplanar points, ~1 for a round blob.

    The ratio of the smallest to the largest singular value of the centred points, measured
    robustly: spreads along the principal axes are interdecile ranges, so a handful of off-plane
    points (which alone make a plane look three-dimensional to a plain SVD, yet leave the 15-DOF
    fit degenerate) do not count. Uses an evenly strided subset of at most ``max_points`` rows.
    """
    X = X[:: max(1, len(X) // max_points)]
    centred = X - X.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)  # columns sorted by increasing variance
    along = centred @ axes[:, [0, 2]]
    low, high = np.quantile(along, [0.1, 0.9], axis=0)
    spread = high - low
    return float(spread[0] / spread[1]) if spread[1] > 0 else 0.0


def relief(X: np.ndarray, centre: np.ndarray, max_points: int = 20000) -> float:
    """Relief of points ``(N, 3)`` off their best-fit plane, relative to their distance from a
    camera centre ``(3,)``: the interdecile range along the thinnest principal axis over the median
    distance (0 for coplanar points; a room corner seen from 2 m is about 0.2-0.3). Unlike
    :func:`planarity`, it compares the structure with what depth errors can fake, which grow with
    depth. Uses an evenly strided subset of at most ``max_points`` rows."""
    X = X[:: max(1, len(X) // max_points)]
    centred = X - X.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    low, high = np.quantile(centred @ axes[:, 0], [0.1, 0.9])
    distance = float(np.median(np.linalg.norm(X - centre, axis=1)))
    return float((high - low) / distance) if distance > 0 else 0.0


def _rng(config: AlignmentConfig, seed: int) -> np.random.Generator:
    # The configured seed and the caller's seed (e.g. the submap id) both select the stream.
    return np.random.default_rng([int(config.seed), int(seed)])


# --------------------------------------------------------------------------------------------
# Sim(3)


def _sim3_fit(X_a: np.ndarray, X_b: np.ndarray) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The Umeyama refit of :func:`refine` on the rows ``chosen`` of ``X_a, X_b`` ``(N, 3)``."""

    def fit(chosen: np.ndarray, _H: np.ndarray) -> np.ndarray:
        # take: the same rows as fancy indexing, several times faster for (n, 3) arrays
        return umeyama_sim3(np.take(X_b, chosen, axis=0), np.take(X_a, chosen, axis=0))

    return fit


def estimate_sim3(X_a: np.ndarray, X_b: np.ndarray, config: AlignmentConfig, seed: int = 0) -> Alignment:
    """Robust similarity ``T_a_b = [s R t; 0 1]`` with ``X_a ~ T_a_b X_b``: RANSAC + Umeyama.

    Args:
        X_a: ``(N, 3)`` points in submap ``a``; rows with NaN/Inf (in either set) are ignored.
        X_b: ``(N, 3)`` the same points in submap ``b``.
        config: iterations, inlier threshold (``X_a`` units), scoring subset size, seed.
        seed: combined with ``config.seed`` (e.g. the submap id).

    Returns:
        ``Alignment`` with ``model="sim3"``; ``inliers`` covers all N input rows.

    Raises:
        ValueError: fewer than 3 finite correspondences, or every sample collinear.
    """
    start = time.perf_counter()
    X_a, X_b, finite = clean_correspondences(X_a, X_b, 3, "Sim(3)")
    rng = _rng(config, seed)
    threshold = float(config.inlier_threshold)
    H, stats = ransac_best(X_a, X_b, umeyama_sim3_batch, 3, threshold, config, rng)
    stats.pop("top")
    if H is None:
        raise ValueError("Sim(3) alignment failed: every 3-point sample is collinear; the shared frame's points are degenerate")
    H, _, inliers, r2, refits = refine(H, X_a, X_b, threshold, _sim3_fit(X_a, X_b), 3, config)
    stats.update(refits=refits, dropped_nonfinite=int(len(finite) - finite.sum()), seconds=time.perf_counter() - start)
    return make_alignment(H, X_a, X_b, finite, inliers, r2, "sim3", extras=stats)


# --------------------------------------------------------------------------------------------
# SL(4)


class _WeightedDltFit:
    """Weighted DLT refit of :func:`refine` on already normalized points ``X_a, X_b`` ``(N, 3)``.

    Weights ``1 / w^2`` (``w`` from the current ``H``) turn the algebraic error into the transfer
    error in ``X_a``; repeated refits in :func:`refine` iterate the weights. Each refit's normal
    matrix sums per-point terms (``sl4slam.alignment.dlt.dlt_normal_terms``) that do not depend on
    ``H``: they are computed once for all points here and gathered for the chosen rows, which gives
    the very same sums as computing them from the chosen rows. Raises ``ValueError`` when the fit
    has ``det <= 0``.
    """

    def __init__(self, X_a: np.ndarray, X_b: np.ndarray) -> None:
        self.X_a, self.X_b = X_a, X_b
        self.terms: tuple[np.ndarray, np.ndarray] | None = None  # built at the first large refit

    def __call__(self, chosen: np.ndarray, H: np.ndarray) -> np.ndarray:
        X_b = np.take(self.X_b, chosen, axis=0)
        w = X_b @ H[3, :3] + H[3, 3]
        weights = 1.0 / np.maximum(w, 1e-12) ** 2
        if len(chosen) <= DLT_SVD_POINTS:  # dlt_homogeneous's own small-system path
            H_new = dlt_homogeneous(np.take(self.X_a, chosen, axis=0), X_b, weights=weights)
        else:
            if self.terms is None:
                self.terms = dlt_normal_terms(self.X_a, self.X_b)
            coefficients, outer = (np.take(terms, chosen, axis=0) for terms in self.terms)
            H_new = dlt_normal_solution(dlt_normal_matrix_from_terms(coefficients, outer, weights))
        return normalize_sl4(fix_sign_by_w(H_new, X_b))


def estimate_sl4(X_a: np.ndarray, X_b: np.ndarray, config: AlignmentConfig, seed: int = 0) -> Alignment:
    """Robust projective map ``H_a_b`` in SL(4) with ``X_a ~ H_a_b X_b`` (5-point DLT in RANSAC).

    Both point sets are Hartley-normalized for sampling and scoring; the threshold is converted
    so that it stays ``config.inlier_threshold`` in ``X_a``'s units. The best hypothesis is refitted
    on all its inliers (weighted DLT, when ``config.refit``) and re-scored on all points.

    Falls back to :func:`estimate_sim3` on the same points (``model="sim3"``, ``fallback`` says
    why) when the 15-DOF fit is degenerate: fewer than ``config.min_inliers`` correspondences or
    inliers, points or inliers nearly coplanar (``planarity < config.planarity_threshold``), or
    every 5-point sample degenerate.

    Args:
        X_a: ``(N, 3)`` points of the shared frame in submap ``a``; NaN/Inf rows are ignored.
        X_b: ``(N, 3)`` the same pixels' points in submap ``b``.
        config: alignment settings.
        seed: combined with ``config.seed`` (e.g. the submap id) to seed the sampler.

    Returns:
        ``Alignment``: ``H`` ``(4, 4)`` with det = +1 and ``w > 0`` on the inliers, ``inliers``
        ``(N,)``, inlier ratio, inlier RMS in ``X_a`` units; ``extras`` holds the statistics.

    Raises:
        ValueError: fewer than 5 finite correspondences, or a fallback whose points are collinear.
    """
    start = time.perf_counter()
    X_a_in, X_b_in = X_a, X_b
    X_a, X_b, finite = clean_correspondences(X_a, X_b, 5, "SL(4)")
    stats: dict = {"dropped_nonfinite": int(len(finite) - finite.sum())}

    def fallback(reason: str) -> Alignment:
        result = estimate_sim3(X_a_in, X_b_in, config, seed)
        result.fallback = reason
        result.extras = {**result.extras, "sl4": stats}
        return result

    N = len(X_a)
    if N < config.min_inliers:
        return fallback(f"only {N} correspondences (< min_inliers {config.min_inliers})")
    flatness = planarity(X_b, config.max_points)
    stats["planarity"] = flatness
    if flatness < config.planarity_threshold:
        return fallback(f"points nearly coplanar (planarity {flatness:.3g} < {config.planarity_threshold})")

    rng = _rng(config, seed)
    X_a_n, T_a = normalize_points(X_a)
    X_b_n, T_b = normalize_points(X_b)
    threshold = float(config.inlier_threshold)
    # Sampling, scoring and refits all work on the normalized points: T_a is a similarity with
    # scale T_a[0, 0], so distances there are that scale times distances in X_a's units.
    threshold_n = threshold * T_a[0, 0]
    # Only a hypothesis whose inliers are about as three-dimensional as the points may end the
    # sampling early: one that explains just a dominant plane (and calls the rest outliers) is the
    # near-degenerate case where more samples find the full 15-DOF map.
    spread_needed = max(config.planarity_threshold, config.early_stop_spread * flatness)

    def well_spread(inliers_b: np.ndarray) -> bool:
        return len(inliers_b) >= config.min_inliers and planarity(inliers_b, config.max_points) >= spread_needed

    H_n, ransac_stats = ransac_best(X_a_n, X_b_n, minimal_sl4_batch, 5, threshold_n, config, rng, well_spread)
    candidates = ransac_stats.pop("top")
    stats.update(ransac_stats)
    if H_n is None:
        return fallback("every 5-point sample degenerate")
    if config.refit:
        # Local optimization from the few best hypotheses: with realistic (non-projective) depth
        # errors a noisy minimal sample's hypothesis can refit into a wrong local optimum whose
        # perspective row is far off, while a near-best one refits into the right one.
        fit = _WeightedDltFit(X_a_n, X_b_n)  # one for all candidates: they share its per-point terms
        refitted = [refine(H0, X_a_n, X_b_n, threshold_n, fit, config.min_inliers, config) for H0 in candidates]
        H_n, _, inliers, r2, refits = min(refitted, key=lambda result: result[1])
    else:
        _, inliers, r2 = score_one(H_n, X_a_n, X_b_n, threshold_n)
        refits = 0
    H = normalize_sl4(np.linalg.solve(T_a, H_n @ T_b))  # back to submap units: T_a^-1 H_n T_b
    r2 = r2 / T_a[0, 0] ** 2
    count = int(inliers.sum())
    stats.update(refits=refits, inliers=count)
    if count < config.min_inliers:
        return fallback(f"{count} inliers (< min_inliers {config.min_inliers})")
    inlier_flatness = planarity(X_b[inliers], config.max_points)
    stats["inlier_planarity"] = inlier_flatness
    if inlier_flatness < config.planarity_threshold:
        return fallback(f"inliers nearly coplanar (planarity {inlier_flatness:.3g} < {config.planarity_threshold})")
    stats["seconds"] = time.perf_counter() - start
    return make_alignment(H, X_a, X_b, finite, inliers, r2, "sl4", extras=stats)
