"""Direct linear transform (DLT) for 3D projective maps ``X_a ~ H_a_b X_b`` in SL(4).

Each correspondence ``(X_a, X_b)`` with ``B = [X_b, 1]`` gives three linear equations in the 16
entries of ``H`` (rows ``h_1 .. h_4``)::

    h_i . B - X_a[i] * (h_4 . B) = 0,    i = 1, 2, 3,

so five points in general position fix the 15 degrees of freedom of ``H`` (the minimal case used
inside RANSAC) and more points give a homogeneous least-squares problem. Both point sets are
first normalized (Hartley): centred and scaled so the mean distance to the centroid is sqrt(3),
which keeps the design matrix well conditioned whatever the submap's units.

Sign convention: ``H`` and ``-H`` are the same projective map and have the same determinant, so
the sign is fixed by requiring the homogeneous coordinate ``w = h_4 . B`` to be positive on the
points (they lie on the same side of the plane that ``H`` sends to infinity). A fit with
``det <= 0`` has no SL(4) representative and is reported as degenerate.
"""

from __future__ import annotations

import numpy as np

from ..geometry import normalize_sl4, sl4_valid
from .common import clean_correspondences

# Smallest / largest singular value of a minimal 15x16 system below which its null space is not
# one-dimensional (e.g. four of the five points coplanar, or a repeated point).
MINIMAL_RANK_TOLERANCE = 1e-7
DLT_SVD_POINTS = 64
"""Up to this many points the DLT least squares takes the SVD of the design matrix itself (no
squaring of the condition number); beyond, the eigenvector of the 16x16 normal matrix."""


def normalize_points(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalization of 3D points.

    Args:
        X: ``(N, 3)`` points.

    Returns:
        X_n: ``(N, 3)`` float64 points ``T X``: centroid at the origin, mean distance sqrt(3).
        T: ``(4, 4)`` the similarity applied (``X_n = apply_transform(T, X)``).
    """
    X = np.asarray(X, dtype=np.float64)
    centroid = X.mean(axis=0)
    centred = X - centroid
    mean_distance = np.sqrt((centred**2).sum(axis=1)).mean()
    scale = np.sqrt(3.0) / mean_distance if mean_distance > 0 else 1.0
    T = np.eye(4)
    T[:3, :3] *= scale
    T[:3, 3] = -scale * centroid
    return centred * scale, T


def dlt_design_matrix(X_a: np.ndarray, X_b: np.ndarray) -> np.ndarray:
    """Rows of the DLT system ``A h = 0`` (``h`` = ``H`` flattened row-major).

    Args:
        X_a, X_b: ``(..., n, 3)`` corresponding points.

    Returns:
        ``(..., 3 n, 16)``: rows ``3k .. 3k+2`` belong to correspondence ``k``.
    """
    X_a = np.asarray(X_a, dtype=np.float64)
    X_b = np.asarray(X_b, dtype=np.float64)
    B = np.concatenate([X_b, np.ones(X_b.shape[:-1] + (1,))], axis=-1)  # (..., n, 4)
    A = np.zeros(X_b.shape[:-1] + (3, 16))
    for i in range(3):  # three equation rows per point; the work per row is vectorized
        A[..., i, 4 * i : 4 * i + 4] = B
        A[..., i, 12:16] = -X_a[..., i : i + 1] * B
    return A.reshape(X_b.shape[:-2] + (3 * X_b.shape[-2], 16))


def _dlt_normal_matrix(X_a: np.ndarray, X_b: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """``A^T W A`` ``(16, 16)`` of the DLT system without building the ``(3N, 16)`` matrix.

    Rows of point ``k`` are ``e_i (x) B - a_i e_4 (x) B``, so ``A^T A`` has blocks
    ``sum B B^T`` (diagonal, i <= 3), ``-sum a_i B B^T`` (i, 4) and ``sum |a|^2 B B^T`` (4, 4):
    five weighted sums of the outer products ``B B^T``, one BLAS product for all of them.
    """
    coefficients, outer = dlt_normal_terms(X_a, X_b)
    return dlt_normal_matrix_from_terms(coefficients, outer, weights)


def dlt_normal_terms(X_a: np.ndarray, X_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-point terms of the DLT normal matrix: ``coefficients`` ``(N, 5)`` = ``[1, a_1, a_2, a_3, |a|^2]``
    and ``outer`` ``(N, 16)`` = ``B B^T`` flattened, ``B = [X_b, 1]``; both C-contiguous float64."""
    n = len(X_b)
    B = np.concatenate([X_b, np.ones((n, 1))], axis=1)
    outer = (B[:, :, None] * B[:, None, :]).reshape(n, 16)
    coefficients = np.concatenate([np.ones((n, 1)), X_a, (X_a**2).sum(axis=1, keepdims=True)], axis=1)
    return coefficients, outer


def dlt_normal_matrix_from_terms(coefficients: np.ndarray, outer: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """``A^T W A`` ``(16, 16)`` from :func:`dlt_normal_terms` ``(n, 5), (n, 16)`` (C-contiguous) and
    optional weights ``(n,)``."""
    if weights is not None:
        coefficients = coefficients * weights[:, None]
    sums = (coefficients.T @ outer).reshape(5, 4, 4)  # [sum BB^T, sum a_1 BB^T, .., sum |a|^2 BB^T]
    M = np.zeros((4, 4, 4, 4))  # block (p, q) = M[p, :, q, :]
    for i in range(3):
        M[i, :, i, :] = sums[0]
        M[i, :, 3, :] = -sums[1 + i]
        M[3, :, i, :] = -sums[1 + i]
    M[3, :, 3, :] = sums[4]
    return M.reshape(16, 16)


def dlt_normal_solution(M: np.ndarray) -> np.ndarray:
    """Unit-norm ``(4, 4)`` minimizer of ``h^T M h``: the eigenvector of the smallest eigenvalue of
    the normal matrix ``M`` ``(16, 16)``."""
    return np.linalg.eigh(M)[1][:, 0].reshape(4, 4)


def fix_sign_by_w(H: np.ndarray, X_b: np.ndarray) -> np.ndarray:
    """Flip ``H`` ``(4, 4)`` so the majority of ``X_b`` ``(N, 3)`` map to ``w > 0`` (``median(w) < 0``)."""
    w = X_b @ H[3, :3] + H[3, 3]
    return -H if median_is_negative(w) else H


def median_is_negative(values: np.ndarray) -> bool:
    """``np.median(values) < 0`` for ``(n,)`` floats, from counts instead of a partition.

    An odd count's median is negative when more than half the values are; an even count's, the
    mean of the two middle values, when more than half are, or, with exactly half negative, when
    the largest negative and the smallest non-negative value sum below zero (as ``np.median``
    computes it). NaN anywhere makes the median NaN: not negative.
    """
    n = len(values)
    negative = int(np.count_nonzero(values < 0))
    if n == 0 or negative + int(np.count_nonzero(values >= 0)) < n:
        return False
    if 2 * negative != n:  # the middle value(s) all on one side of zero
        return 2 * negative > n
    below, above = values[values < 0].max(), values[values >= 0].min()
    return bool((below + above) / 2.0 < 0)


def dlt_sl4(X_a: np.ndarray, X_b: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares projective map ``H_a_b`` with ``X_a ~ H_a_b X_b``, normalized into SL(4).

    Args:
        X_a: ``(N, 3)`` points in frame ``a``; N >= 5, not all coplanar; NaN/Inf rows are ignored.
        X_b: ``(N, 3)`` the same points in frame ``b``.
        weights: optional ``(N,)`` non-negative weights of each point's squared algebraic error
            (``1 / w^2`` from a previous estimate turns it into the transfer error in ``a``).

    Returns:
        ``(4, 4)`` float64 ``H_a_b`` with det = +1 and ``w > 0`` on most points.

    Raises:
        ValueError: fewer than 5 finite points, or a degenerate fit (det <= 0).
    """
    X_a, X_b, finite = clean_correspondences(X_a, X_b, 5, "SL(4) DLT")
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)[finite]
    X_a_n, T_a = normalize_points(X_a)
    X_b_n, T_b = normalize_points(X_b)
    H = np.linalg.solve(T_a, dlt_homogeneous(X_a_n, X_b_n, weights) @ T_b)  # undo the normalizations
    H = fix_sign_by_w(H, X_b)
    return normalize_sl4(H)


def dlt_homogeneous(X_a: np.ndarray, X_b: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Unit-norm least-squares solution ``(4, 4)`` of the DLT system, with no normalization.

    The caller supplies well-conditioned (Hartley-normalized) ``(N, 3)`` float64 points, N >= 5,
    and fixes sign and scale. Small systems use the SVD of the design matrix itself (no squaring
    of the condition number); large ones the eigenvector of the 16x16 normal matrix.
    """
    if len(X_a) <= DLT_SVD_POINTS:
        A = dlt_design_matrix(X_a, X_b)
        if weights is not None:
            A = A * np.sqrt(np.repeat(np.asarray(weights, dtype=np.float64), 3))[:, None]
        # Vt is 16x16 either way; full U is only needed when A has fewer than 16 rows.
        return np.linalg.svd(A, full_matrices=len(A) < 16)[2][-1].reshape(4, 4)
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    return dlt_normal_solution(_dlt_normal_matrix(X_a, X_b, w))


def minimal_sl4_batch(X_a: np.ndarray, X_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Five-point DLT for a batch of samples (the RANSAC hypothesis generator).

    Args:
        X_a, X_b: ``(M, 5, 3)`` sampled correspondences (already normalized coordinates).

    Returns:
        H: ``(M, 4, 4)`` hypotheses ``X_a ~ H X_b`` scaled into SL(4) where valid, sign chosen so
            that ``w > 0`` on the sample.
        valid: ``(M,)`` bool. A sample is degenerate, and discarded, when its 15x16 system is
            rank deficient, when the fit sends some sample points through infinity (mixed signs
            of ``w``), or when ``det H <= 0``.
    """
    A = dlt_design_matrix(X_a, X_b)  # (M, 15, 16)
    _, singular, Vt = np.linalg.svd(A, full_matrices=True)
    H = Vt[:, -1, :].reshape(-1, 4, 4)
    well_posed = singular[:, -1] > MINIMAL_RANK_TOLERANCE * singular[:, 0]
    w = np.einsum("mkj,mj->mk", X_b, H[:, 3, :3]) + H[:, 3, 3][:, None]  # (M, 5)
    sign = np.where(w.sum(axis=1) < 0, -1.0, 1.0)
    H = H * sign[:, None, None]
    same_side = ((w * sign[:, None]) > 0).all(axis=1)
    valid = well_posed & same_side & sl4_valid(H)
    det = np.linalg.det(H)
    H[valid] = H[valid] / (det[valid] ** 0.25)[:, None, None]
    return H, valid
