"""Each frame's camera in a submap refined against the dense points of the submap's other frames.

A feed-forward model predicts every frame's depth in that frame's own camera and, separately, the
frame's pose in the submap; a pose error moves all of that frame's points rigidly, which the frame's
own points cannot show but the other frames that see the same surfaces can. The points of a pixel
grid of each frame are carried into every other frame; where they land on its measured surface
(depth within ``depth_tolerance``), the point of that frame's ray at its measured depth and the
surface normal there make one point-to-plane residual between the two frames. Every frame's pose
but the first (whose camera is the submap frame) is then corrected by one joint Gauss-Newton
solve over all residuals (those beyond ``trim`` times their median left out), repeated
``iterations`` times.

:func:`window_disagreement` measures the same disagreement without correcting anything: how far
one frame's points land from the next frame's surface, which is what the keyframe graph sets the
stiffness inside a window by (``BackendConfig.window_agreement_factor``).

The refinement rests on the frames' pose errors being the only thing their surfaces disagree by. A per-frame
depth error (a smooth warp of one frame's depth) is absorbed into that frame's pose instead:
decision: docs/decisions/frame-refinement.md, which keeps it off (``SubmapConfig.refine_cameras``).

Frames: ``T_cam_submap`` maps submap points into each camera, ``X_cam = R X_sub + t``; pixels have
integer coordinates at their centres.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .geometry import pixel_grid
from .types import SubmapPrediction


def camera_points_and_normals(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W, 3)`` points and unit normals (facing the camera; 0 where undefined) of one depth map
    ``(H, W)`` with intrinsics ``K`` ``(3, 3)``, in its camera frame (normals from the central
    differences of the points; none on the border)."""
    H, W = depth.shape
    points = (pixel_grid(H, W) @ np.linalg.inv(K).T) * depth[..., None].astype(np.float64)
    du = np.zeros_like(points); dv = np.zeros_like(points)
    du[:, 1:-1] = points[:, 2:] - points[:, :-2]
    dv[1:-1] = points[2:] - points[:-2]
    normals = np.cross(du, dv)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.where(length > 0, normals / np.where(length > 0, length, 1.0), 0.0)
    normals *= -np.sign(np.einsum("hwi,hwi->hw", normals, points))[..., None]
    return points, normals


def _bilinear_depth(inverse: np.ndarray, valid: np.ndarray, row: np.ndarray, col: np.ndarray, fx: np.ndarray,
                    fy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth at ``(col + fx, row + fy)`` from the four pixels around it, interpolated in the inverse
    depth (exact on a plane), and whether all four are valid. ``inverse``: the inverse depth ``(H, W)``."""
    known = valid[row, col] & valid[row, col + 1] & valid[row + 1, col] & valid[row + 1, col + 1]
    corners = (inverse[row, col], inverse[row, col + 1], inverse[row + 1, col], inverse[row + 1, col + 1])
    return _interpolated_depth(corners, fx, fy), known


def _interpolated_depth(inverse: tuple[np.ndarray, ...], fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Depth at fractions ``(fx, fy)`` between four pixels' inverse depths ``(top left, top right,
    bottom left, bottom right)``, interpolated in the inverse depth."""
    top = inverse[0] * (1 - fx) + inverse[1] * fx
    bottom = inverse[2] * (1 - fx) + inverse[3] * fx
    with np.errstate(divide="ignore", invalid="ignore"):  # pixels with an invalid corner are not known
        return 1.0 / (top * (1 - fy) + bottom * fy)


def _bilinear_depth_flat(depth: np.ndarray, valid: np.ndarray, row: np.ndarray, col: np.ndarray, fx: np.ndarray,
                         fy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_bilinear_depth` from the depth ``(H, W)`` itself, read at the four pixels around each
    point only (by flat index; the map is not inverted as a whole): the interpolated depth and
    whether all four are ``valid`` ``(H, W)``. ``row, col`` must index pixels whose right and lower
    neighbours exist."""
    W = depth.shape[1]
    depth, valid = depth.reshape(-1), valid.reshape(-1)
    corners = row * W + col
    corners = (corners, corners + 1, corners + W, corners + W + 1)
    ok = [np.take(valid, at) for at in corners]
    inverse = tuple(1.0 / np.where(good, np.take(depth, at), 1.0).astype(np.float64) for good, at in zip(ok, corners))
    return _interpolated_depth(inverse, fx, fy), ok[0] & ok[1] & ok[2] & ok[3]


def _pairs(inverses, K, T, valid, grids, normals, frame, other, tol):
    """Point-to-plane pairs of ``frame``'s grid points on ``other``'s surface: ``(p, q, n)`` in the
    submap frame, ``(m, 3)`` each (``q`` on ``other``'s ray at its measured depth, ``n`` its normal)."""
    H, W = inverses.shape[1:]
    R, t = T[frame, :, :3], T[frame, :, 3]
    Ro, to = T[other, :, :3], T[other, :, 3]
    p = (grids[frame] - t) @ R
    X = p @ Ro.T + to
    z = X[:, 2]
    front = np.flatnonzero(z > 1e-9)
    uvw = X[front] @ K[other].T
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (col >= 0) & (col < W - 1) & (row >= 0) & (row < H - 1)
    front, col, row, u, v = front[inside], col[inside], row[inside], u[inside], v[inside]
    measured, known = _bilinear_depth(inverses[other], valid[other], row, col, u - col, v - row)
    n_cam = normals[other][np.rint(v).astype(np.int64), np.rint(u).astype(np.int64)]
    keep = known & (np.abs(z[front] - measured) <= tol * measured) & (np.abs(n_cam).sum(axis=1) > 0)
    ray = np.stack([u[keep], v[keep], np.ones(int(keep.sum()))], axis=-1) @ np.linalg.inv(K[other]).T
    q = (ray * measured[keep][:, None] - to) @ Ro
    return p[front[keep]], q, n_cam[keep] @ Ro


def window_disagreement(depth: np.ndarray, K: np.ndarray, T_cam_submap: np.ndarray, valid: np.ndarray,
                        stride: int = 8, block: int = 4, tol: float = 0.2) -> float | None:
    """How well the frames of one window agree about their surfaces, their pixel noise averaged out.

    Each frame's grid points (every ``stride``-th pixel) are carried into the next frame of the
    window and back; a point's signed relative gap ``z_carried / z_measured - 1`` to that frame's
    depth (interpolated in inverse depth, exact on a plane) says how far the two frames disagree
    there. The gaps are averaged over blocks of ``block x block`` grid points, where a per-frame
    camera error or depth warp (smooth over the image) stays and the depth maps' independent pixel
    noise averages out. A window that is one consistent reconstruction, however distorted as a
    whole (a per-submap projective error), reads near zero; per-frame camera errors and depth
    warps read their size.

    Args:
        depth: ``(S, H, W)`` depth along each camera's z axis; K: ``(S, 3, 3)``.
        T_cam_submap: ``(S, 3|4, 4)`` camera-from-submap poses.
        valid: ``(S, H, W)`` bool, the pixels whose depth counts.
        stride: pixel step of each frame's grid.
        block: grid points per side of a block; a block counts with at least half of its points
            on the other frame's surface.
        tol: gaps beyond this are occlusions or another surface, not disagreement.

    Returns:
        The median over the pairs of consecutive frames (both ways) of the median absolute block
        mean gap (dimensionless); ``None`` with fewer than two frames or no pair with a block.
    """
    S, H, W = depth.shape
    T = np.asarray(T_cam_submap, dtype=np.float64)[:, :3, :4]
    K = np.asarray(K, dtype=np.float64)
    rows, cols = np.arange(stride // 2, H, stride), np.arange(stride // 2, W, stride)
    rows, cols = rows[:len(rows) // block * block], cols[:len(cols) // block * block]
    if len(rows) == 0 or len(cols) == 0:
        return None
    grid = np.stack(np.broadcast_arrays(cols[None, :].astype(np.float64), rows[:, None].astype(np.float64), 1.0),
                    axis=-1)  # pixel_grid(H, W)[np.ix_(rows, cols)] without the whole image's grid
    keep = valid[:, rows][:, :, cols]
    sampled = depth[:, rows][:, :, cols].astype(np.float64)
    rays = [grid @ np.linalg.inv(K[s]).T for s in range(S)]
    submap_points = [(rays[s] * sampled[s][..., None] - T[s, :, 3]) @ T[s, :, :3] for s in range(S)]  # (R, C, 3)
    gaps = []
    for a in range(S - 1):
        for frame, other in ((a, a + 1), (a + 1, a)):
            X = submap_points[frame] @ T[other, :, :3].T + T[other, :, 3]
            z = X[..., 2]
            front = keep[frame] & (z > 1e-9)
            uvw = X @ K[other].T
            w = np.where(front, uvw[..., 2], 1.0)
            u, v = uvw[..., 0] / w, uvw[..., 1] / w
            inside = front & (u >= 0) & (u < W - 1) & (v >= 0) & (v < H - 1)
            col = np.where(inside, np.floor(u), 0).astype(np.int64)
            row = np.where(inside, np.floor(v), 0).astype(np.int64)
            measured, known = _bilinear_depth_flat(depth[other], valid[other], row, col, u - col, v - row)
            on = inside & known
            gap = np.where(on, z / np.where(on, measured, 1.0) - 1.0, 0.0)
            on &= np.abs(gap) <= tol
            shape = (len(rows) // block, block, len(cols) // block, block)
            counts = on.reshape(shape).sum(axis=(1, 3))
            sums = np.where(on, gap, 0.0).reshape(shape).sum(axis=(1, 3))
            enough = counts >= block * block / 2
            if enough.any():
                gaps.append(float(np.median(np.abs(sums[enough] / counts[enough]))))
    return float(np.median(gaps)) if gaps else None


def refine_frame_poses(depth: np.ndarray, K: np.ndarray, T_cam_submap: np.ndarray, valid: np.ndarray,
                       iterations: int = 3, stride: int = 8, tol: float = 0.05, trim: float = 3.0,
                       min_pairs: int = 50, damping: float = 1e-3) -> np.ndarray:
    """Every frame's pose but the first refined against the other frames' surfaces (module doc).

    Args:
        depth: ``(S, H, W)`` depth along each camera's z axis; K: ``(S, 3, 3)``.
        T_cam_submap: ``(S, 3|4, 4)`` camera-from-submap poses (the first is the submap frame).
        valid: ``(S, H, W)`` bool, the pixels whose depth counts.
        iterations: Gauss-Newton steps; stride: pixel step of each frame's grid.
        tol: relative depth gap within which a carried point is on another frame's surface.
        trim: residuals beyond this many times their median are left out of a step.
        min_pairs: a frame in fewer pairs keeps its pose.
        damping: each frame's normal equations get this fraction of their largest diagonal entry
            added, so that directions the surfaces leave free (sliding along a plane) stay put.

    Returns:
        ``(S, 3, 4)`` float64 refined poses.
    """
    S = len(depth)
    T = np.array(T_cam_submap, dtype=np.float64)[:, :3, :4]
    H, W = depth.shape[1:]
    rows, cols = np.arange(stride // 2, H, stride), np.arange(stride // 2, W, stride)
    grids, normals = [], []
    for s in range(S):
        points, n = camera_points_and_normals(depth[s], K[s])
        grids.append(points[np.ix_(rows, cols)][valid[s][np.ix_(rows, cols)]])
        normals.append(n)
    inverses = 1.0 / np.where(valid, depth, 1.0).astype(np.float64)  # (S, H, W), read by every pair
    for _ in range(iterations):
        blocks = []
        for f in range(S):
            for o in range(S):
                if o != f:
                    p, q, n = _pairs(inverses, K, T, valid, grids, normals, f, o, tol)
                    if len(p):
                        blocks.append((f, o, p, q, n))
        if not blocks:
            break
        res = np.concatenate([np.einsum("ki,ki->k", n, p - q) for _, _, p, q, n in blocks])
        limit = trim * np.median(np.abs(res)) + 1e-12
        A = np.zeros((6 * S, 6 * S)); b = np.zeros(6 * S); pairs = np.zeros(S, np.int64)
        for f, o, p, q, n in blocks:
            r = np.einsum("ki,ki->k", n, p - q); keep = np.abs(r) <= limit
            J = np.concatenate([np.cross(p[keep], n[keep]), n[keep], -np.cross(q[keep], n[keep]), -n[keep]], axis=1)
            idx = np.r_[6 * f:6 * f + 6, 6 * o:6 * o + 6]
            A[np.ix_(idx, idx)] += J.T @ J; b[idx] -= J.T @ r[keep]; pairs[[f, o]] += int(keep.sum())
        free = [s for s in range(1, S) if pairs[s] >= min_pairs]
        if not free:
            break
        idx = np.concatenate([np.arange(6 * s, 6 * s + 6) for s in free])
        M = A[np.ix_(idx, idx)]
        for k, s in enumerate(free):
            blk = slice(6 * k, 6 * k + 6); M[blk, blk] += damping * np.diag(M[blk, blk]).max() * np.eye(6)
        step = np.linalg.solve(M, b[idx])
        for k, s in enumerate(free):
            w, v = step[6 * k:6 * k + 3], step[6 * k + 3:6 * k + 6]
            a = np.linalg.norm(w); ax = w / a if a > 0 else np.zeros(3)
            X = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
            C = np.eye(3) + np.sin(a) * X + (1 - np.cos(a)) * X @ X
            # the frame's submap points X -> C X + v: its pose becomes T C^-1
            T[s, :, :3] = T[s, :, :3] @ C.T
            T[s, :, 3] = T[s, :, 3] - T[s, :, :3] @ v
    return T


def refine_prediction(prediction: SubmapPrediction, mask: np.ndarray, iterations: int) -> SubmapPrediction:
    """``prediction`` with its frames' poses refined by :func:`refine_frame_poses` over the pixels of
    ``mask`` ``(S, H, W)`` (the confident ones); everything else as it was (a point map, if the
    frontend gave one, is not moved)."""
    return dataclasses.replace(prediction, T_cam_submap=refine_frame_poses(prediction.depth, prediction.K, prediction.T_cam_submap, mask, iterations))
