"""Each frame's camera in a submap corrected by the image features it shares with the other frames.

A feed-forward model predicts each frame's camera in the submap, and the frame's points are its
depth placed by that camera: an error in the camera moves all of them, and the link to the next
submap inherits the errors of the frames it shares. Two frames of a window also measure their
relative pose without the model's cameras: ORB features matched between them, the first frame's
features lifted to 3D by its predicted depth, and the pose that projects them onto the second
frame's features, with the second frame's focal length left free (the model's focal lengths of
the two frames may disagree). The rotation rests on the images alone (the depth enters it only
through the parallax, small between the frames of a window); the translation takes its scale
from the depth, so a depth error of a few per cent moves it by that fraction of the baseline.

Every pair of frames ``i < j <= i + span`` with enough matches gives one such measurement; the
model's cameras are the prior. The weights follow what the run measures: each pair's covariance
from its fit (its inliers' reprojection residuals) plus the spread with which the measurements
fail to close around triangles of frames, and the model's spread from how far its relative poses
are from the measured ones, less the measurements' own share. A model whose cameras already agree
with the images is left as it is. The first frame (the submap frame) is kept; a pair that
disagrees with the solution beyond chance is left out and the solve repeated.

It is a lever, off by default (``SubmapConfig.feature_poses``): in the simulator it corrects the
frames' rotations three- to seven-fold and their centres little, and whole runs come out no
better, worse on repetitive texture (decision: docs/decisions/feature-poses.md).

Frames: ``T_cam_submap`` maps submap points into each camera, ``X_cam = R X_sub + t``, the centre
``C = -R^T t``; pixel coordinates are integer at pixel centres. Tangent errors are left
perturbations: ``R <- exp(w) R``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .types import SubmapPrediction

CHI2_3_MEDIAN = 2.366
"""Median of a chi-square variable with 3 degrees of freedom."""
CHI2_999 = {3: 16.27, 6: 22.46}
"""The 99.9 % points of chi-square variables with 3 and 6 degrees of freedom: the gate on a pair
measuring one part (rotation or centre) or both."""


@dataclass
class PairPose:
    """One pair's measured relative pose: ``X_j = R X_i + t`` (``R = R_j R_i^T``, ``t = R_j (C_i -
    C_j)``); ``covariance`` ``(6, 6)`` of its error ``(w, v)``, ``R <- exp(w) R``, ``t <- t + v``;
    ``inliers``: the matches that agree with it."""

    i: int
    j: int
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray
    inliers: int


def skew(v: np.ndarray) -> np.ndarray:
    """``(3, 3)`` cross-product matrix of ``v`` ``(3,)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation ``(3, 3)`` of the rotation vector ``w`` ``(3,)``."""
    return Rotation.from_rotvec(w).as_matrix()


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` of the rotation ``R`` ``(3, 3)``."""
    return Rotation.from_matrix(R).as_rotvec()


def orb_features(colors: np.ndarray, features: int) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """ORB keypoints ``(k, 2)`` (pixel coordinates) and descriptors ``(k, 32)`` uint8 of each image
    of ``colors`` ``(S, H, W, 3)`` uint8 RGB."""
    import cv2

    orb = cv2.ORB_create(nfeatures=int(features))
    found = []
    for image in colors:
        gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
        keypoints, descriptors = orb.detectAndCompute(gray, None)
        found.append((np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2), descriptors))
    return found


def mutual_matches(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray:
    """``(m, 2)`` indices of descriptors of ``a`` and ``b`` that are each other's nearest (Hamming)."""
    import cv2

    if a is None or b is None or not len(a) or not len(b):
        return np.zeros((0, 2), dtype=np.int64)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a, b)
    return np.array([(m.queryIdx, m.trainIdx) for m in matches], dtype=np.int64).reshape(-1, 2)


def fit_pose(P: np.ndarray, uv: np.ndarray, K: np.ndarray, R0: np.ndarray, t0: np.ndarray, max_turn_deg: float = 5.0,
             iterations: int = 6, min_inliers: int = 30,
             min_inlier_ratio: float = 0.3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The pose ``(R, t)`` that projects points ``P`` ``(n, 3)`` (first camera) through ``K``
    ``(3, 3)`` onto pixels ``uv`` ``(n, 2)`` of the second camera, ``x ~ K diag(g, g, 1) (R P + t)``
    with a free focal gain ``g`` (the two frames' predicted focal lengths may disagree, and a fit
    that must keep them turns the disagreement into a wrong translation): robust Gauss-Newton from
    ``(R0, t0, 1)``. Matches farther from ``(R0, t0)``'s projection than a turn of
    ``max_turn_deg`` never count; then residuals beyond 3 robust standard deviations (at least
    1.5 px) are left out of each step.

    Returns:
        ``(R, t, covariance (6, 6) of (w, v) with the gain marginalized, inliers (n,) bool)``, or ``None`` with fewer than
        ``min_inliers`` inliers or under ``min_inlier_ratio`` of the matches, or a singular system.
    """
    R, t = np.array(R0, dtype=np.float64), np.array(t0, dtype=np.float64)
    gain = 1.0
    cap = float(np.tan(np.radians(max_turn_deg)) * max(K[0, 0], K[1, 1]))
    inliers = np.zeros(len(P), dtype=bool)
    for step in range(iterations + 1):
        fx, fy = gain * K[0, 0], gain * K[1, 1]
        rotated = P @ R.T
        X = rotated + t
        z = X[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        r = np.stack([fx * X[:, 0] / zs + K[0, 2] - uv[:, 0], fy * X[:, 1] / zs + K[1, 2] - uv[:, 1]], axis=1)
        norm = np.linalg.norm(r, axis=1)
        limit = cap if step == 0 else min(max(3.0 * 1.4826 * np.median(norm[inliers]), 1.5), cap)
        inliers = front & (norm <= limit)
        if inliers.sum() < max(min_inliers, min_inlier_ratio * len(P)):
            return None
        Xi, zi, Ri = X[inliers], zs[inliers], rotated[inliers]
        du = np.stack([fx / zi, np.zeros_like(zi), -fx * Xi[:, 0] / zi**2], axis=1)  # d u / d X
        dv = np.stack([np.zeros_like(zi), fy / zi, -fy * Xi[:, 1] / zi**2], axis=1)
        # dX/dw = -[R P]x (so d u / d w = (R P) x du), dX/dv = I
        J = np.concatenate([np.hstack([np.cross(Ri, du), du]), np.hstack([np.cross(Ri, dv), dv])])
        # d u / d log(gain) = u - cx
        J = np.hstack([J, np.concatenate([fx * Xi[:, 0] / zi, fy * Xi[:, 1] / zi])[:, None]])
        res = np.concatenate([r[inliers, 0], r[inliers, 1]])
        JtJ = J.T @ J
        if np.linalg.cond(JtJ) > 1e12:
            return None
        if step == iterations:
            sigma2 = float(res @ res) / max(len(res) - J.shape[1], 1)
            return R, t, (sigma2 * np.linalg.inv(JtJ))[:6, :6], inliers
        delta = -np.linalg.solve(JtJ, J.T @ res)
        R = so3_exp(delta[:3]) @ R
        t = t + delta[3:6]
        gain *= float(np.exp(delta[6]))
    return None


def measure_pairs(prediction: SubmapPrediction, mask: np.ndarray, features: int = 1000, span: int = 4,
                  min_inliers: int = 30) -> list[PairPose]:
    """The relative pose of every pair of frames ``i < j <= i + span`` measured from their matched
    ORB features (module doc); only features on pixels of ``mask`` ``(S, H, W)`` with a positive
    depth are lifted."""
    S = len(prediction.depth)
    found = orb_features(prediction.colors, features)
    T = np.asarray(prediction.T_cam_submap, dtype=np.float64)[:, :3, :4]
    H, W = prediction.depth.shape[1:]
    measured = []
    for i in range(S):
        points_i, descriptors_i = found[i]
        if not len(points_i):
            continue
        col = np.clip(np.rint(points_i[:, 0]).astype(np.int64), 0, W - 1)
        row = np.clip(np.rint(points_i[:, 1]).astype(np.int64), 0, H - 1)
        depth = prediction.depth[i][row, col].astype(np.float64)
        usable = mask[i][row, col] & (depth > 0)
        rays = np.column_stack([points_i, np.ones(len(points_i))]) @ np.linalg.inv(prediction.K[i]).T
        lifted = rays * depth[:, None]
        for j in range(i + 1, min(S, i + span + 1)):
            matches = mutual_matches(descriptors_i, found[j][1])
            matches = matches[usable[matches[:, 0]]] if len(matches) else matches
            if len(matches) < min_inliers:
                continue
            R0 = T[j, :, :3] @ T[i, :, :3].T
            t0 = T[j, :, 3] - R0 @ T[i, :, 3]
            fit = fit_pose(lifted[matches[:, 0]], found[j][0][matches[:, 1]], prediction.K[j], R0, t0,
                           min_inliers=min_inliers)
            if fit is not None:
                measured.append(PairPose(i, j, fit[0], fit[1], fit[2], int(fit[3].sum())))
    return measured


def measurement_spread(pairs: list[PairPose]) -> tuple[float, float]:
    """Per-axis spread of the pairs' rotations (radians) and translations (submap units), from how
    far they fail to close around triangles of frames ``i < j < k``: ``(R_jk R_ij) R_ik^T`` and
    ``R_jk t_ij + t_jk - t_ik`` vanish for exact measurements and carry three measurements' errors
    otherwise. ``(0, 0)`` without a triangle."""
    found = {(p.i, p.j): p for p in pairs}
    closures = [(found[i, j], found[j, k], found[i, k]) for (i, j) in found for (jj, k) in found
                if jj == j and (i, k) in found]
    if not closures:
        return 0.0, 0.0
    turns = np.array([np.sum(so3_log(jk.R @ ij.R @ ik.R.T) ** 2) for ij, jk, ik in closures])
    shifts = np.array([np.sum((jk.R @ ij.t + jk.t - ik.t) ** 2) for ij, jk, ik in closures])
    return (float(np.sqrt(np.median(turns) / (CHI2_3_MEDIAN * 3.0))),
            float(np.sqrt(np.median(shifts) / (CHI2_3_MEDIAN * 3.0))))


def _residual(R: np.ndarray, C: np.ndarray, pair: PairPose) -> np.ndarray:
    """``(6,)`` the pair's measurement against the poses ``R`` ``(S, 3, 3)``, ``C`` ``(S, 3)``."""
    R_ji = R[pair.j] @ R[pair.i].T
    return np.concatenate([so3_log(R_ji @ pair.R.T), R[pair.j] @ (C[pair.i] - C[pair.j]) - pair.t])


def _apply(R_model: np.ndarray, C_model: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The poses corrected by ``x`` ``(S, 6)`` (rotation, centre)."""
    return np.stack([so3_exp(x[s, :3]) @ R_model[s] for s in range(len(x))]), C_model + x[:, 3:]


def _solve(R_model: np.ndarray, C_model: np.ndarray, pairs: list[PairPose], infos: list[np.ndarray], used: np.ndarray,
           prior: np.ndarray, free: np.ndarray, iterations: int) -> np.ndarray:
    """Gauss-Newton for the corrections ``(S, 6)`` of :func:`corrected_poses` from the ``used`` pairs
    (the first frame's zero); ``prior`` ``(6,)``: the inverse variances of the model's errors;
    ``free`` ``(6,)`` bool: the parts corrected (the others stay zero)."""
    S = len(R_model)
    x = np.zeros((S, 6))
    keep = np.flatnonzero(np.tile(free, S))
    keep = keep[keep >= 6]  # the first frame is the submap frame
    for _ in range(iterations):
        A = np.diag(np.tile(prior, S))
        b = -(x * prior).reshape(-1)
        R, C = _apply(R_model, C_model, x)
        for p, info in (item for item, u in zip(zip(pairs, infos), used) if u):
            r = _residual(R, C, p)
            J_i, J_j = np.zeros((6, 6)), np.zeros((6, 6))  # the residual's derivatives by frame i's and j's (w, c)
            J_j[:3, :3] = np.eye(3)
            J_i[:3, :3] = -(R[p.j] @ R[p.i].T)
            J_j[3:, :3] = -skew(R[p.j] @ (C[p.i] - C[p.j]))
            J_i[3:, 3:] = R[p.j]
            J_j[3:, 3:] = -R[p.j]
            for a, J_a in ((p.i, J_i), (p.j, J_j)):
                b[6 * a:6 * a + 6] -= J_a.T @ info @ r
                for c, J_c in ((p.i, J_i), (p.j, J_j)):
                    A[6 * a:6 * a + 6, 6 * c:6 * c + 6] += J_a.T @ info @ J_c
        step = np.zeros(6 * S)
        step[keep] = np.linalg.solve(A[np.ix_(keep, keep)], b[keep])
        x += step.reshape(S, 6)
    return x


@dataclass
class Correction:
    """What :func:`corrected_poses` found: the model's per-axis spread it assumed (rotation in
    radians, centre in submap units), the measurements' own, and the pairs it used."""

    model_spread: tuple[float, float]
    measurement_spread: tuple[float, float]
    pairs_used: int


def corrected_poses(T_cam_submap: np.ndarray, pairs: list[PairPose], iterations: int = 3,
                    gate: float | None = None) -> tuple[np.ndarray, Correction]:
    """Camera-from-submap poses ``(S, 3, 4)`` that best agree with the model's ``T_cam_submap``
    ``(S, 3|4, 4)`` and the pairs' measurements (module doc), the first frame's kept; and what the
    weights rested on. While the worst pair's residual after a solve exceeds ``gate`` (default:
    :data:`CHI2_999` for the parts corrected), it is left out and the solve repeated. A part (rotations or
    centres) where the model agrees with the measurements as closely as they agree among
    themselves is held; with both held, or no pair, the poses come back as they were
    (``pairs_used`` 0)."""
    T = np.array(T_cam_submap, dtype=np.float64)[:, :3, :4]
    R_model, C_model = T[:, :, :3], -np.einsum("sji,sj->si", T[:, :, :3], T[:, :, 3])
    spread = measurement_spread(pairs)
    unchanged = T, Correction((0.0, 0.0), spread, 0)
    if len(T) < 2 or not pairs:
        return unchanged
    floor = np.repeat(np.square(spread), 3)
    disagreement = np.array([_residual(R_model, C_model, p) for p in pairs])
    own = np.array([np.diag(p.covariance) for p in pairs]) + floor
    # per axis E r^2 = 2 sigma_model^2 + sigma_measured^2; a squared 3-vector's median is 2.366 times
    # its per-axis variance (medians keep a wrong pair from setting the weight)
    model = []
    for part in (slice(0, 3), slice(3, 6)):
        typical = float(np.median((disagreement[:, part] ** 2).sum(axis=1))) / CHI2_3_MEDIAN
        model.append(max((typical - float(np.median(own[:, part].mean(axis=1)))) / 2.0, 0.0))
    if max(model) <= 0.0:
        return unchanged
    # a part (rotations, centres) the model gets as right as the pairs measure it is held: its
    # corrections stay zero and the measurements of it do not count
    free = np.repeat([m > 0.0 for m in model], 3)
    prior = np.repeat([1.0 / m if m > 0.0 else 0.0 for m in model], 3)
    infos = []
    for p in pairs:
        info = np.zeros((6, 6))
        info[np.ix_(free, free)] = np.linalg.inv((p.covariance + np.diag(floor))[np.ix_(free, free)])
        infos.append(info)
    gate = CHI2_999[int(free.sum())] if gate is None else gate
    used = np.ones(len(pairs), dtype=bool)
    while True:
        x = _solve(R_model, C_model, pairs, infos, used, prior, free, iterations)
        R, C = _apply(R_model, C_model, x)
        chi2 = np.array([r @ info @ r for r, info in ((_residual(R, C, p), info) for p, info in zip(pairs, infos))])
        worst = int(np.argmax(np.where(used, chi2, -np.inf)))
        if chi2[worst] <= gate:
            break
        used[worst] = False  # the worst pair out, one at a time: a wrong pair bends the others' residuals too
        if not used.any():
            return unchanged
    corrected = np.concatenate([R, -np.einsum("sij,sj->si", R, C)[:, :, None]], axis=2)
    if not free[3]:  # the centres held: exactly the model's
        corrected[:, :, 3] = -np.einsum("sij,sj->si", R, C_model)
    return corrected, Correction((float(np.sqrt(model[0])), float(np.sqrt(model[1]))), spread, int(used.sum()))


def correct_prediction(prediction: SubmapPrediction, mask: np.ndarray, features: int = 1000) -> SubmapPrediction:
    """``prediction`` with its frames' cameras corrected by their image features (module doc):
    depth and intrinsics as they were (a point map, if given, is not moved); the prediction itself
    when nothing was corrected."""
    corrected, found = corrected_poses(prediction.T_cam_submap, measure_pairs(prediction, mask, features))
    if not found.pairs_used:
        return prediction
    T = np.array(prediction.T_cam_submap, dtype=np.float64)
    T[:, :3, :4] = corrected
    return dataclasses.replace(prediction, T_cam_submap=T)
