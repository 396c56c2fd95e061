"""Projective alignment constrained by the shared frame's two cameras (for degenerate scenes).

When the shared frame sees a single plane, its points fix a 15-DOF ``H_a_b`` only up to a
4-parameter family ``H + v pi^T`` (``pi`` the plane): the points alone cannot say how space off
the plane is mapped. The frame's camera, reconstructed in both submaps, adds what the points
lack: the same image means ``P_a H ~ P_b`` (11 equations), so ``H = H_p + c_a v^T`` with ``H_p``
one solution, ``c_a`` the camera centre in submap ``a`` (homogeneous) and ``v`` in R^4. The points
then fix ``v`` up to its component along the plane, which a small ridge term sets to the value
nearest the particular solution ``H_p`` — the camera-consistent map closest to the guess (the
RANSAC fit where there is one, else the frame's calibration-and-scale link).
Unlike a Sim(3) fallback, this keeps the projective part that the plane does observe.
"""

from __future__ import annotations

import numpy as np

from .settings import AlignmentConfig
from ..geometry import normalize_sl4, sl4_valid
from ..types import Alignment
from .common import clean_correspondences, make_alignment
from .dlt import fix_sign_by_w
from .ransac import score_one


def camera_constrained_sl4(
    X_a: np.ndarray,
    X_b: np.ndarray,
    P_a: np.ndarray,
    P_b: np.ndarray,
    H_guess: np.ndarray,
    config: AlignmentConfig,
) -> Alignment | None:
    """``H_a_b`` in SL(4) consistent with one frame's cameras ``P_a ~ K_a [R_a|t_a]`` and ``P_b``.

    Args:
        X_a, X_b: ``(N, 3)`` the frame's points in submaps a and b (NaN rows ignored).
        P_a, P_b: ``(3, 4)`` the frame's camera matrices in submaps a and b.
        H_guess: ``(4, 4)`` an initial map (a RANSAC fit, or the frame's calibration-and-scale link)
            selecting the particular solution.
        config: inlier threshold, minimum inlier count, reweighting rounds, ridge and planarity.

    Returns:
        An ``Alignment`` (model "sl4") or ``None`` when no valid SL(4) map results.
    """
    X_a_c, X_b_c, finite = clean_correspondences(X_a, X_b, 4, "SL(4)")
    P_a = np.asarray(P_a, dtype=np.float64)
    P_b = np.asarray(P_b, dtype=np.float64)
    S = np.asarray(H_guess, dtype=np.float64)
    # Particular solution of P_a H = lambda P_b nearest to S (pseudo-inverse correction).
    PaS = P_a @ S
    lam = float((PaS * P_b).sum() / (P_b * P_b).sum())
    P_a_pinv = P_a.T @ np.linalg.inv(P_a @ P_a.T)
    H_p = S + P_a_pinv @ (lam * P_b - PaS)
    c_a = np.append(-np.linalg.solve(P_a[:, :3], P_a[:, 3]), 1.0)

    x_b = np.c_[X_b_c, np.ones(len(X_b_c))]  # (N, 4)
    mapped = x_b @ H_p.T  # (N, 4)
    g = mapped[:, :3] - X_a_c * mapped[:, 3:4]  # (N, 3) algebraic residual of H_p
    d = c_a[:3] - X_a_c  # (N, 3): residual(v) = g + (x_b . v) d
    threshold = float(config.inlier_threshold)
    use = np.ones(len(x_b), dtype=bool)
    weights = 1.0 / np.maximum(np.abs(mapped[:, 3]), 1e-9)
    H = H_p
    d_norm2 = (d * d).sum(axis=1)  # (N,)
    d_dot_g = (d * g).sum(axis=1)  # (N,)
    iterations = int(config.camera_constrained_iterations)
    for iteration in range(iterations):
        # Normal equations of min sum w^2 |g + (x_b . v) d|^2 over the points in use, formed
        # directly as 4x4 sums: A^T A = sum w^2 |d|^2 x_b x_b^T, A^T b = sum w^2 (d . g) x_b.
        w2 = np.where(use, weights * weights, 0.0)
        AtA = (x_b * (w2 * d_norm2)[:, None]).T @ x_b
        Atb = x_b.T @ (w2 * d_dot_g)
        v = -np.linalg.solve(AtA + config.camera_constrained_ridge * np.trace(AtA) / 4 * np.eye(4), Atb)
        H = H_p + np.outer(c_a, v)
        H = fix_sign_by_w(H, X_b_c)  # H and -H are one map: keep w > 0 on the points (det cannot tell them apart)
        _, inliers, r2 = score_one(H, X_a_c, X_b_c, threshold)
        w_now = x_b @ H[3]
        weights = 1.0 / np.maximum(np.abs(w_now), 1e-9)
        # Shrink the fitting set towards the inliers gradually, so early outliers cannot lock in.
        median_r2 = float(np.partition(r2, len(r2) // 2)[len(r2) // 2])
        cut = max(threshold, np.sqrt(median_r2)) * (4.0 if iteration < iterations // 2 else 1.0)
        use = (r2 < cut**2) & (w_now > 0)
        if use.sum() < 4:
            return None
    if not sl4_valid(H) or inliers.sum() < config.min_inliers:
        return None
    H = _least_perspective(H, c_a, X_b_c[inliers], config.planarity_threshold)
    _, inliers, r2 = score_one(H, X_a_c, X_b_c, threshold)
    if not sl4_valid(H) or inliers.sum() < config.min_inliers:
        return None
    return make_alignment(normalize_sl4(H), X_a_c, X_b_c, finite, inliers, r2, "sl4", extras={"camera_constrained": True})


def _least_perspective(H: np.ndarray, c_a: np.ndarray, X_plane: np.ndarray, planar: float) -> np.ndarray:
    """Within the unobserved family ``H + mu c_a pi^T`` (points on plane ``pi``), the member whose
    perspective row is smallest relative to its last entry: consecutive submaps' distortions are
    both near identity, so their relative map has a small perspective part.

    Returns ``H`` unchanged when the points are not planar (smallest / largest singular value of
    the centred points above ``planar``: nothing is unobserved).
    """
    centre = X_plane.mean(axis=0)
    _, sing, Vt = np.linalg.svd(X_plane - centre, full_matrices=False)
    if sing[-1] > planar * sing[0]:
        return H
    normal = Vt[-1]
    pi = np.append(normal, -normal @ centre)  # pi . [X; 1] = 0 on the plane
    pi = pi / c_a[3]  # the last row of H changes by mu * c_a[3] * pi
    a, c = H[3, :3], H[3, 3]
    b, d = pi[:3], pi[3]
    # f(mu) = |a + mu b|^2 / (c + mu d)^2 has one stationary point (the numerator of f' is linear)
    denominator = (b @ b) * c - (a @ b) * d
    if abs(denominator) < 1e-15:
        return H
    mu = ((a @ a) * d - (a @ b) * c) / denominator
    if c + mu * d <= 0:
        return H
    return H + mu * np.outer(c_a, pi)
