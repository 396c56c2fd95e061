"""Completing a camera-anchored link from the cameras' known calibration.

A shared frame that sees one plane cannot fix a 15-DOF ``H_a_b``: the fallback links
(``sl4slam.alignment``: the calibration-and-scale link, the camera-constrained fit) only make the
frame's two cameras agree, ``P_a H_a_b ~ P_b``. Every map that does so is ``H_a_b G`` with

    G = T^-1 (I + e_4 w^T) T,    w = (p, -p . x_c),

written in submap b's coordinates moved to the shared camera's centre and scaled by the shared
frame's median depth (``T``): ``G`` fixes the shared camera (``P_b G ~ P_b``, because its centre is
the origin) and the depth of the shared points' centroid ``x_c``, and bends space by the
perspective row ``p`` (3 unknowns, in units of that depth, like the simulator's ``perspective``).
The link picked one ``p`` by a guess (``p = 0`` for the calibration link, the smallest perspective
part for the camera-constrained fit), so a projective distortion that differs between the two
submaps goes into the link, and every later submap inherits it: the map is then no longer one
projective frame, and the metric upgrade (``sl4slam.upgrade``), which removes one distortion,
cannot make it metric.

Submap b's other cameras see ``p``: moved into a metric frame of submap a (``H_metric_a``, from the
upgrade of the map built so far), they must have zero skew, square pixels, the known principal
point and the map's focal length, as a's cameras do. :func:`complete_camera_link` finds the ``p``
that makes them so (robust least squares, scipy), and keeps the link as it was when the cameras do
not determine ``p`` (b's cameras too close to the shared one: the predicted uncertainty of ``p``
exceeds ``UpgradeConfig.max_uncertainty``) or do not fit clearly better
(``UpgradeConfig.max_residual_ratio``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .upgrade import UpgradeConfig
from .geometry import normalize_sl4, projection_intrinsics
from .upgrade import intrinsic_constraint_residuals


@dataclass
class LinkCompletion:
    """What :func:`complete_camera_link` did.

    Attributes:
        H_a_b: ``(4, 4)`` the completed link (SL(4)); the input link when not ``applied``.
        applied: whether the link was changed.
        reason: "completed", or why not.
        perspective: ``(3,)`` the perspective row ``p`` found (zeros when not applied).
        residual_before, residual_after: RMS of b's camera constraints (unitless, as in
            :func:`sl4slam.upgrade.intrinsic_constraint_residuals`) with the input and completed link.
        uncertainty: predicted standard deviation of ``p`` (inf when not solved).
    """

    H_a_b: np.ndarray
    applied: bool
    reason: str
    perspective: np.ndarray
    residual_before: float
    residual_after: float
    uncertainty: float

    def summary(self) -> dict:
        return {"applied": self.applied, "reason": self.reason, "perspective": [round(float(v), 6) for v in self.perspective],
                "residual_before": round(self.residual_before, 6), "residual_after": round(self.residual_after, 6),
                "uncertainty": round(self.uncertainty, 6)}


def shared_camera_agreement(P_a: np.ndarray, P_b: np.ndarray, H_a_b: np.ndarray) -> float:
    """Relative difference of ``P_a H_a_b`` and ``P_b`` ``(3, 4)`` up to scale: 0 when the link keeps the
    shared frame's camera, as every link :func:`complete_camera_link` completes must."""
    mapped = np.asarray(P_a, dtype=np.float64) @ np.asarray(H_a_b, dtype=np.float64)
    P_b = np.asarray(P_b, dtype=np.float64)
    scale = float((mapped * P_b).sum() / (P_b * P_b).sum())
    return float(np.linalg.norm(mapped - scale * P_b) / max(np.linalg.norm(mapped), 1e-300))


def bending(perspective: np.ndarray, centre_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """``G`` ``(4, 4)`` of the module docstring in submap b's coordinates.

    Args:
        perspective: ``(3,)`` the perspective row ``p`` (in units of the shared frame's median depth).
        centre_b: ``(3,)`` the shared camera's centre in submap b.
        points_b: ``(N, 3)`` the shared frame's points in submap b (finite rows), whose centroid keeps
            its depth and whose median distance from the centre is the unit of ``p``.
    """
    return BendingFrame.of(centre_b, points_b).bending(perspective)


@dataclass(frozen=True)
class BendingFrame:
    """What :func:`bending` takes from the shared frame's points, computed once for the many
    bendings a fit evaluates: the normalization ``T`` (centre at the origin, median distance 1)
    ``(4, 4)`` and the points' centroid ``(3,)`` in that frame."""

    T: np.ndarray
    centroid: np.ndarray
    T_inv: np.ndarray
    """``T``'s inverse ``(4, 4)``, computed once for every bending."""

    @classmethod
    def of(cls, centre_b: np.ndarray, points_b: np.ndarray) -> "BendingFrame":
        centre_b = np.asarray(centre_b, dtype=np.float64)
        offsets = np.asarray(points_b, dtype=np.float64) - centre_b
        depth = float(np.median(np.linalg.norm(offsets, axis=1)))
        T = np.eye(4)
        T[:3, :3] /= depth
        T[:3, 3] = -centre_b / depth
        return cls(T, offsets.mean(axis=0) / depth, np.linalg.inv(T))

    def bending(self, perspective: np.ndarray) -> np.ndarray:
        """``G`` ``(4, 4)`` for the perspective row ``perspective`` ``(3,)``."""
        p = np.asarray(perspective, dtype=np.float64)
        bend = np.eye(4)
        bend[3, :3] = p
        bend[3, 3] = 1.0 - p @ self.centroid
        return self.T_inv @ bend @ self.T


def _camera_residuals(P: np.ndarray, principal_points: np.ndarray, focal: float, focal_weight: float) -> np.ndarray:
    """``(M, 5)`` skew, aspect, principal point (``intrinsic_constraint_residuals``) and weighted log focal ratio."""
    K = projection_intrinsics(P)
    constraints = intrinsic_constraint_residuals(K, principal_points)
    log_focal = focal_weight * np.log(np.sqrt(K[:, 0, 0] * K[:, 1, 1]) / focal)
    return np.concatenate([constraints, log_focal[:, None]], axis=1)


def complete_camera_link(
    H_a_b: np.ndarray,
    centre_b: np.ndarray,
    points_b: np.ndarray,
    cameras_b: np.ndarray,
    principal_points_b: np.ndarray,
    H_metric_a: np.ndarray,
    focal: float,
    config: UpgradeConfig | None = None,
    free: np.ndarray | None = None,
) -> LinkCompletion:
    """The perspective row ``p`` that makes submap b's cameras metric through the link (module doc).

    Args:
        H_a_b: ``(4, 4)`` a link keeping the shared camera (``X_a ~ H_a_b X_b``).
        centre_b, points_b: the shared camera's centre ``(3,)`` and the shared frame's points
            ``(N, 3)`` in submap b (see :func:`bending`).
        cameras_b: ``(M, 3, 4)`` submap b's other cameras in its own frame (not the shared one, which
            ``p`` does not change).
        principal_points_b: ``(M, 2)`` px, the principal point each should have.
        H_metric_a: ``(4, 4)`` maps submap a's coordinates into a metric frame (the upgrade of the
            map so far composed with submap a's place in it).
        focal: px, the map's focal length in that frame (the upgrade's).
        config: the upgrade's robust loss, noise scale, focal weight, uncertainty and
            improvement thresholds (``UpgradeConfig``).
        free: ``(k, 3)`` rows spanning the ``p`` to search (None: all three). A camera-constrained
            fit has fixed the plane's tilt from its points: only ``p`` along the plane's normal,
            which moves no point of the plane, is left free (:func:`plane_normal`).

    Returns:
        :class:`LinkCompletion`.
    """
    config = config if config is not None else UpgradeConfig()
    H_a_b = np.asarray(H_a_b, dtype=np.float64)
    cameras_b = np.asarray(cameras_b, dtype=np.float64).reshape(-1, 3, 4)
    pp = np.broadcast_to(np.asarray(principal_points_b, dtype=np.float64), (len(cameras_b), 2))
    points_b = np.asarray(points_b, dtype=np.float64).reshape(-1, 3)
    points_b = points_b[np.isfinite(points_b).all(axis=1)]
    into_metric = np.linalg.inv(np.asarray(H_metric_a, dtype=np.float64) @ H_a_b)
    basis = np.eye(3) if free is None else np.asarray(free, dtype=np.float64).reshape(-1, 3)
    frame = BendingFrame.of(centre_b, points_b) if len(points_b) else None

    def residuals(u: np.ndarray) -> np.ndarray:
        P = cameras_b @ np.linalg.inv(frame.bending(u @ basis)) @ into_metric
        return _camera_residuals(P, pp, focal, config.focal_weight).ravel()

    def kept(reason: str, before: float, uncertainty: float = float("inf")) -> LinkCompletion:
        return LinkCompletion(H_a_b, False, reason, np.zeros(3), before, before, uncertainty)

    if len(cameras_b) < 2 or len(points_b) < 3:
        return kept(f"too few cameras or points ({len(cameras_b)} cameras, {len(points_b)} points)", 0.0)
    start = residuals(np.zeros(len(basis)))
    before = float(np.sqrt(np.mean(start**2)))
    if not np.isfinite(start).all():
        return kept("the link's cameras cannot be decomposed", before)
    if before < config.completion_residual:
        return kept(f"already metric (constraint residual {before:.2g} < {config.completion_residual:g})", before)
    try:
        solution = least_squares(residuals, np.zeros(len(basis)), loss=config.loss, f_scale=config.loss_scale,
                                 x_scale=0.01, max_nfev=config.max_iterations)
    except (ValueError, np.linalg.LinAlgError) as exc:  # a bending that sends a camera to infinity
        return kept(f"the fit failed ({exc})", before)
    after = float(np.sqrt(np.mean(solution.fun**2)))
    # standard deviation of p for constraints of noise loss_scale: b's cameras must pin the bending
    # down to a hundredth of the depth (max_uncertainty), as the upgrade its plane at infinity
    weakest = float(np.linalg.svd(solution.jac, compute_uv=False)[-1])
    uncertainty = config.loss_scale / weakest if weakest > 0 else float("inf")
    if not np.isfinite(after) or not uncertainty <= config.max_uncertainty:
        return kept(f"the new submap's cameras do not determine the bending (uncertainty {uncertainty:.2g} > "
                    f"{config.max_uncertainty:g})", before, uncertainty)
    if not after <= config.max_residual_ratio * before:
        return kept(f"no clear improvement (constraint residual {before:.2g} -> {after:.2g})", before, uncertainty)
    p = solution.x @ basis
    H = normalize_sl4(H_a_b @ frame.bending(p))
    return LinkCompletion(H, True, "completed", p, before, after, uncertainty)


def plane_normal(points: np.ndarray) -> np.ndarray:
    """``(1, 3)`` unit normal of the best plane through ``points`` ``(N, 3)`` (smallest principal axis)."""
    points = np.asarray(points, dtype=np.float64)
    return np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[2][-1:]
