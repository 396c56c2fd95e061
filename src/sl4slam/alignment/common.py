"""Pieces every alignment model shares: checking point pairs, and summarising residuals.

Every estimator (RANSAC in SL(4) or Sim(3), the camera-constrained fit, the shared-frame Sim(3))
validates its input with :func:`clean_correspondences` and reports with :func:`make_alignment`, so
inlier masks always cover every input row and ratios and RMS mean the same thing everywhere.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from .settings import AlignmentConfig
from ..types import Alignment, FrameView

class FrameFitter(Protocol):
    """What measuring a link from shared frames needs of an aligner (``sl4slam.alignment.shared``,
    ``sl4slam.alignment.select``); every ``sl4slam.alignment.aligner.PointAligner`` is one.

    Attributes:
        config: its alignment settings.
        fits_points: the model is fitted to points (several frames' points are fitted together);
            otherwise it reads the frames' cameras (several frames' links are averaged).
    """

    config: AlignmentConfig
    fits_points: bool

    def pairs(self, view_a: FrameView, view_b: FrameView) -> tuple[np.ndarray, np.ndarray]:
        """``(X_a, X_b)`` ``(N, 3)`` float64 of the frame's shared confident pixels."""

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        """The model's fit ``X_a ~ H_a_b X_b`` on the shared pixels' points ``(N, 3)``."""

    def align(self, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        """The link measured on one shared frame."""


SUPPORT_POINTS = 2000
"""Inlier pairs an ``Alignment`` keeps (an evenly strided subset) for weighting its edge by its
evidence (``sl4slam.backend.evidence``); enough for a 15x15 information matrix, cheap to keep."""


def clean_correspondences(X_a: np.ndarray, X_b: np.ndarray, minimum: int, model: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop rows with NaN/Inf in either set.

    Args:
        X_a, X_b: ``(N, 3)`` corresponding points.
        minimum: fewest finite correspondences the model can use.
        model: model name for the error message.

    Returns:
        ``(X_a, X_b)`` finite rows as C-contiguous float64 (the inputs themselves when every row is
        finite and they are so already: callers only read them) and the ``(N,)`` bool mask of kept rows.

    Raises:
        ValueError: shapes disagree, or fewer than ``minimum`` finite rows remain.
    """
    X_a = np.asarray(X_a, dtype=np.float64)
    X_b = np.asarray(X_b, dtype=np.float64)
    if X_a.shape != X_b.shape or X_a.ndim != 2 or X_a.shape[1] != 3:
        raise ValueError(f"{model} alignment needs two (N, 3) point arrays of equal shape, got {X_a.shape} and {X_b.shape}")
    if len(X_a) >= minimum and np.isfinite(X_a).all() and np.isfinite(X_b).all():
        # the usual case: no row to drop, so no copy (C-contiguous like the copies below, so that
        # later products see the same memory layout)
        return np.ascontiguousarray(X_a), np.ascontiguousarray(X_b), np.ones(len(X_a), dtype=bool)
    finite = np.isfinite(X_a).all(axis=1) & np.isfinite(X_b).all(axis=1)
    count = int(finite.sum())
    if count < minimum:
        raise ValueError(
            f"{model} alignment needs at least {minimum} finite correspondences, got {count} of {len(X_a)}; "
            "the shared frame has too few confident points"
        )
    return X_a[finite], X_b[finite], finite


def inlier_rms(r2: np.ndarray, inliers: np.ndarray) -> float:
    """RMS of the inliers' errors (``r2`` squared distances); of all errors when there is no inlier."""
    values = r2[inliers] if inliers.any() else r2
    return float(np.sqrt(values.mean())) if len(values) else 0.0


def make_alignment(
    H: np.ndarray,
    X_a: np.ndarray,
    X_b: np.ndarray,
    finite: np.ndarray,
    inliers: np.ndarray,
    r2: np.ndarray,
    model: str,
    fallback: str | None = None,
    extras: dict | None = None,
    fitted: bool = True,
) -> Alignment:
    """An :class:`Alignment` over every input row.

    Args:
        H: ``(4, 4)`` the estimate, ``X_a ~ H X_b``.
        X_a, X_b: ``(n, 3)`` the finite correspondences the estimate was scored on.
        finite: ``(N,)`` bool, which input rows those are (``n = finite.sum()``).
        inliers, r2: ``(n,)`` inlier mask and squared transfer errors on those rows.
        fitted: the estimate was fitted to the inliers. A measurement that was not (a link from the
            frame's cameras) keeps every point as its support and reports the RMS over all of them:
            its evidence is how well it explains the frame, not a consensus set.
    """
    full = np.zeros(len(finite), dtype=bool)
    full[np.flatnonzero(finite)] = inliers
    chosen = np.flatnonzero(inliers if fitted else np.ones(len(inliers), dtype=bool))
    support_count = len(chosen)
    if len(chosen) > SUPPORT_POINTS:
        chosen = chosen[:: -(-len(chosen) // SUPPORT_POINTS)]
    return Alignment(
        H=H,
        inliers=full,
        inlier_ratio=float(inliers.sum() / len(finite)) if len(finite) else 0.0,
        rms=inlier_rms(r2, inliers if fitted else np.ones(len(r2), dtype=bool)),
        model=model,
        fallback=fallback,
        extras=dict(extras or {}),
        support=(X_a[chosen].copy(), X_b[chosen].copy()),
        support_count=support_count,
    )
