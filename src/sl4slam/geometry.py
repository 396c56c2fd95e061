"""Pure geometry helpers: rigid, similarity and projective transforms, cameras, unprojection.

Conventions (docs/architecture.md): ``T_a_b`` maps points in frame ``b`` to frame ``a`` (``x_a = T_a_b x_b``);
``H_a_b`` is a 4x4 projective map with the same reading on homogeneous points. Pixel coordinates are
``(u, v) = (column, row)`` with integer values at pixel centres, as in VGGT and TUM. All functions
are vectorized over leading batch dimensions and use float64 unless stated.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .errors import UserError


def to_4x4(T: np.ndarray) -> np.ndarray:
    """``(..., 3, 4)`` or ``(..., 4, 4)`` -> ``(..., 4, 4)`` float64 with last row ``[0 0 0 1]``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] == (4, 4):
        return T.copy()
    out = np.zeros(T.shape[:-2] + (4, 4))
    out[..., :3, :] = T
    out[..., 3, 3] = 1.0
    return out


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(..., 3|4, 4)`` -> ``(..., 4, 4)``: ``T_b_a`` from ``T_a_b``."""
    T = to_4x4(T)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def apply_transform(H_a_b: np.ndarray, X_b: np.ndarray) -> np.ndarray:
    """Map points ``X_b`` ``(..., 3)`` through a rigid/similarity/projective ``H_a_b`` ``(4, 4)``.

    Returns ``X_a`` ``(..., 3)`` after division by the homogeneous coordinate (no division when the
    last row is ``[0 0 0 1]`` exactly, which keeps rigid maps cheap and exact).
    """
    H = np.asarray(H_a_b, dtype=np.float64)
    X = np.asarray(X_b, dtype=np.float64)
    out = X @ H[:3, :3].T + H[:3, 3]
    if not (H[3, :3] == 0).all() or H[3, 3] != 1.0:
        w = X @ H[3, :3] + H[3, 3]
        out = out / w[..., None]
    return out


def pixel_grid(height: int, width: int) -> np.ndarray:
    """Homogeneous pixel coordinates ``(H, W, 3)`` float64: ``[u, v, 1]`` with ``u`` the column."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([u, v, np.ones_like(u)], axis=-1)


@lru_cache(maxsize=8)
def _pixel_rays(height: int, width: int) -> np.ndarray:
    """``pixel_grid(height, width)`` as read-only ``(H * W, 3)`` float32 rows: every unprojection of a
    grid size uses the same rays, and building them costs more than the unprojection itself."""
    rays = pixel_grid(height, width).reshape(height * width, 3).astype(np.float32)
    rays.flags.writeable = False
    return rays


def unproject_depth(depth: np.ndarray, K: np.ndarray, T_cam_ref: np.ndarray | None = None) -> np.ndarray:
    """Back-project depth maps to 3D points.

    Args:
        depth: ``(S, H, W)`` depth along each camera's z axis.
        K: ``(S, 3, 3)`` intrinsics (skew allowed).
        T_cam_ref: ``(S, 3|4, 4)`` camera-from-reference extrinsics, or ``None`` for camera frame.

    Returns:
        ``(S, H, W, 3)`` float32 points in the reference frame (``X_ref = T_ref_cam X_cam``).
    """
    depth = np.asarray(depth)
    S, H, W = depth.shape
    # X_ref = depth * (R_ref_cam K^-1 [u v 1]^T) + t_ref_cam: one 3x3 per frame, applied by BLAS
    # in float32 (relative error ~1e-7, far below any depth noise).
    M = np.linalg.inv(np.asarray(K, dtype=np.float64))
    offset = np.zeros((S, 3))
    if T_cam_ref is not None:
        T_ref_cam = se3_inverse(T_cam_ref)
        M = T_ref_cam[:, :3, :3] @ M
        offset = T_ref_cam[:, :3, 3]
    rays = _pixel_rays(H, W)
    X = np.einsum("nj,sij->sni", rays, M.astype(np.float32), optimize=True)  # (S, HW, 3)
    X *= depth.reshape(S, H * W, 1).astype(np.float32, copy=False)
    X += offset[:, None, :].astype(np.float32)
    return X.reshape(S, H, W, 3)


def project_points(K: np.ndarray, T_cam_ref: np.ndarray, X_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project reference-frame points ``(..., 3)`` with one camera; returns ``(uv (..., 2), z (...))``."""
    T = to_4x4(T_cam_ref)
    X_cam = np.asarray(X_ref, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    z = X_cam[..., 2]
    uvw = X_cam @ np.asarray(K, dtype=np.float64).T
    return uvw[..., :2] / uvw[..., 2:3], z


def normalize_sl4(H: np.ndarray) -> np.ndarray:
    """Scale projective matrices ``(..., 4, 4)`` into SL(4): divide by ``det^(1/4)``.

    Note that flipping the sign of a 4x4 matrix does not change its determinant
    (``det(-H) = det(H)``), so a projective map with ``det < 0`` (orientation-reversing, e.g. a
    fit that swapped the plane at infinity through the scene) has no SL(4) representative at all.
    Such input, and (near-)singular input, raises ``ValueError``: callers treat it as a
    degenerate estimate rather than handing it to GTSAM, whose ``SL4`` would silently alter it.
    """
    H = np.asarray(H, dtype=np.float64)
    det = np.linalg.det(H)
    magnitude = np.abs(H).max(axis=(-1, -2))
    if np.any(~np.isfinite(det)) or np.any(det <= 1e-12 * magnitude**4):
        raise ValueError("projective matrix with det <= 0 (or singular) has no SL(4) representative")
    return H / (det ** 0.25)[..., None, None]


def sl4_valid(H: np.ndarray) -> np.ndarray:
    """Boolean ``(...)``: which ``(..., 4, 4)`` matrices are finite with a clearly positive det."""
    H = np.asarray(H, dtype=np.float64)
    det = np.linalg.det(H)
    magnitude = np.abs(H).max(axis=(-1, -2))
    return np.isfinite(det) & (det > 1e-12 * magnitude**4)


def rq_decomposition(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batch RQ: ``M (..., 3, 3) = U @ Q`` with ``U`` upper triangular, ``Q`` orthogonal."""
    flip = np.eye(3)[::-1]
    Q_, R_ = np.linalg.qr(np.swapaxes(flip @ M, -1, -2))
    U = flip @ np.swapaxes(R_, -1, -2) @ flip
    Q = flip @ np.swapaxes(Q_, -1, -2)
    return U, Q


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split camera matrices ``P (..., 3, 4) ~ K [R | t]`` into intrinsics and pose.

    Returns:
        K: ``(..., 3, 3)`` upper triangular, positive diagonal, ``K[2, 2] = 1`` (skew kept).
        T_world_cam: ``(..., 4, 4)`` proper rigid camera pose (camera-to-world) in P's frame.
        C: ``(..., 3)`` camera centre, the right null vector of P.
    """
    P, U, Q = _positive_rq(P)
    K = U / U[..., 2:3, 2:3]
    M = P[..., :3, :3]
    C = -np.einsum("...ij,...j->...i", np.linalg.inv(M), P[..., :3, 3])
    T_world_cam = np.zeros(P.shape[:-2] + (4, 4))
    T_world_cam[..., :3, :3] = np.swapaxes(Q, -1, -2)
    T_world_cam[..., :3, 3] = C
    T_world_cam[..., 3, 3] = 1.0
    return K, T_world_cam, C


def projection_intrinsics(P: np.ndarray) -> np.ndarray:
    """``K`` ``(..., 3, 3)`` of :func:`decompose_projection` (the same values) without the pose, for
    fits that read only the intrinsics of many cameras."""
    _, U, _ = _positive_rq(P)
    return U / U[..., 2:3, 2:3]


def _positive_rq(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``P`` ``(..., 3, 4)`` float64 with the sign that makes its rotation proper, and the RQ
    decomposition ``U Q`` of its left 3x3 block with a positive diagonal of ``U``."""
    P = np.asarray(P, dtype=np.float64)
    M = P[..., :3, :3]
    # P and -P are the same camera; choose the sign that makes the rotation proper.
    sign = np.where(np.linalg.det(M) < 0, -1.0, 1.0)
    P = P * sign[..., None, None]
    M = P[..., :3, :3]
    U, Q = rq_decomposition(M)
    # Make the diagonal of U positive: U D, D Q with D = diag(sign(U_ii)), D^2 = I.
    D = np.where(np.diagonal(U, axis1=-2, axis2=-1) < 0, -1.0, 1.0)
    return P, U * D[..., None, :], Q * D[..., :, None]


COLLINEAR_TOLERANCE = 1e-6
"""Second / first singular value of a centred point set below which it counts as collinear."""


def umeyama_sim3_batch(X_dst: np.ndarray, X_src: np.ndarray, with_scale: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares similarity ``T_dst_src`` (Umeyama 1991) for a batch of point sets.

    Args:
        X_dst: ``(M, k, 3)`` points in the target frame.
        X_src: ``(M, k, 3)`` corresponding points in the source frame (k >= 3).
        with_scale: estimate the scale (else a rigid transform, s = 1).

    Returns:
        T: ``(M, 4, 4)`` with ``X_dst ~ s R X_src + t``.
        valid: ``(M,)`` bool, False for (near-)collinear or repeated source points.
    """
    X_dst = np.asarray(X_dst, dtype=np.float64)
    X_src = np.asarray(X_src, dtype=np.float64)
    k = X_src.shape[1]
    mu_src = X_src.mean(axis=1)
    mu_dst = X_dst.mean(axis=1)
    src = X_src - mu_src[:, None]
    dst = X_dst - mu_dst[:, None]
    cov = np.einsum("mki,mkj->mij", dst, src) / k  # (M, 3, 3)
    U, sing, Vt = np.linalg.svd(cov)
    reflect = np.linalg.det(U) * np.linalg.det(Vt) < 0
    D = np.ones((len(cov), 3))
    D[reflect, 2] = -1.0
    R = (U * D[:, None, :]) @ Vt
    var_src = (src**2).sum(axis=(1, 2)) / k
    src_sing = np.linalg.svd(src, compute_uv=False)  # (M, 3) spread of the source points
    valid = (var_src > 0) & (src_sing[:, 1] > COLLINEAR_TOLERANCE * src_sing[:, 0])
    if with_scale:
        scale = np.where(valid, (sing * D).sum(axis=1) / np.where(var_src > 0, var_src, 1.0), 1.0)
        valid &= scale > 0
    else:
        scale = np.ones(len(cov))
    T = np.zeros((len(cov), 4, 4))
    T[:, :3, :3] = scale[:, None, None] * R
    T[:, :3, 3] = mu_dst - np.einsum("mij,mj->mi", T[:, :3, :3], mu_src)
    T[:, 3, 3] = 1.0
    return T, valid


def umeyama_sim3(X_src: np.ndarray, X_dst: np.ndarray, with_scale: bool = True) -> np.ndarray:
    """Least-squares similarity ``T_dst_src`` ``(4, 4)`` with ``X_dst ~ s R X_src + t``.

    Args:
        X_src, X_dst: ``(N, 3)`` corresponding points, N >= 3, not collinear.

    Raises:
        ValueError: the source points are collinear or repeated.
    """
    T, valid = umeyama_sim3_batch(np.asarray(X_dst)[None], np.asarray(X_src)[None], with_scale)
    if not valid[0]:
        raise ValueError("Umeyama alignment needs at least 3 non-collinear points")
    return T[0]


def sim3_decompose(T: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``[sR t; 0 1]`` -> ``(s, R, t)``."""
    T = np.asarray(T, dtype=np.float64)
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    return s, T[:3, :3] / s, T[:3, 3].copy()


def project_to_so3(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (Frobenius) to each ``(..., 3, 3)`` matrix."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.ones(U.shape[:-1])
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def require_finite(name: str, value: np.ndarray) -> np.ndarray:
    """Raise a one-line error when ``value`` has NaN/Inf (results are never written with NaN)."""
    if not np.all(np.isfinite(value)):
        raise UserError(f"{name} contains NaN or Inf; the input is degenerate — check the source frames")
    return value


LOG_SERIES_RADIUS = 0.25
"""Largest Frobenius norm of ``M - I`` that :func:`matrix_log` takes by its series; beyond it,
SciPy's general algorithm."""


def matrix_log(M: np.ndarray) -> np.ndarray:
    """Principal logarithm of real square matrices ``(..., n, n)``, real ``(..., n, n)``.

    Matrices near the identity (``|M - I|_F <= LOG_SERIES_RADIUS``: the steps between measurements
    of one link, the scatter of a link about its mean) use the series
    ``log M = 2 sum_k Z^(2k+1) / (2k+1)``, ``Z = (M - I)(M + I)^-1`` (``|Z| <= 1/7`` there; terms
    up to ``Z^21``, below 1e-18), vectorized over the batch; others SciPy's ``logm`` (real part).
    Both agree to about 1e-15 where both apply.
    """
    M = np.asarray(M, dtype=np.float64)
    n = M.shape[-1]
    flat = M.reshape(-1, n, n)
    eye = np.eye(n)
    out = np.empty_like(flat)
    near = np.linalg.norm(flat - eye, axis=(1, 2)) <= LOG_SERIES_RADIUS
    if near.any():
        A = flat[near]
        # Z = (A - I)(A + I)^-1; A - I and A + I commute, so the order of the product is free
        Z = np.linalg.solve(np.swapaxes(A + eye, 1, 2), np.swapaxes(A - eye, 1, 2)).swapaxes(1, 2)
        Z2 = Z @ Z
        term, total = Z, Z.copy()
        for k in range(3, 23, 2):
            term = term @ Z2
            total += term / k
        out[near] = 2.0 * total
    if not near.all():
        from scipy.linalg import logm

        for i in np.flatnonzero(~near):
            out[i] = np.real(logm(flat[i]))
    return out.reshape(M.shape)


def matrix_exp(A: np.ndarray) -> np.ndarray:
    """Matrix exponential of real square matrices ``(..., n, n)``: Taylor series of degree 16 of
    ``A / 2^s`` with ``|A / 2^s|_F <= 1/4`` (truncation below 1e-20), squared ``s`` times;
    vectorized over the batch."""
    A = np.asarray(A, dtype=np.float64)
    n = A.shape[-1]
    flat = A.reshape(-1, n, n)
    norms = np.linalg.norm(flat, axis=(1, 2))
    squarings = np.maximum(0, np.ceil(np.log2(np.maximum(norms, 1e-300) / 0.25))).astype(int)
    B = flat / (2.0 ** squarings)[:, None, None]
    total = np.broadcast_to(np.eye(n), flat.shape).copy()
    term = total.copy()
    for k in range(1, 17):
        term = term @ B / k
        total += term
    for s in range(int(squarings.max(initial=0))):
        again = squarings > s
        total[again] = total[again] @ total[again]
    return total.reshape(A.shape)
