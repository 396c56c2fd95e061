"""Projective-to-metric upgrade of the map: self-calibration through the absolute dual quadric.

SL(4) alignment chains every submap into the frame of the first one, so the whole map inherits the
first submap's projective distortion. What we know of the true cameras removes it: zero skew,
square pixels, a known principal point and one focal length for the whole video. In a metric
frame every camera ``P_i = K_i [R_i | t_i]`` has ``P_i Q* P_i^T ~ K_i K_i^T`` with the absolute
dual quadric ``Q* = diag(1, 1, 1, 0)``; in the distorted world frame ``Q* = H^-1 diag(1,1,1,0) H^-T``
for the sought ``H = H_metric_world`` (Hartley & Zisserman, Multiple View Geometry, 2nd ed., ch. 19,
"H&Z"). ``H`` is found up to a similarity (the gauge):

1. Normalization (H&Z 19.3.3): each camera is divided by ``N_i = [[f0, 0, u_i], [0, f0, v_i],
   [0, 0, 1]]`` (known principal point, a rough focal ``f0``) and scaled to unit norm; the world is
   centred on the median camera centre and measured in units of ``scene_scale``.
2. Linear estimate (H&Z 19.3.1): with the normalized cameras ``w_i = P_i Q* P_i^T`` should be
   ``diag(g^2, g^2, 1)``: four equations per camera linear in the 10 entries of ``Q*``
   (``w_12 = w_13 = w_23 = 0``, ``w_11 = w_22``), solved in the least-squares sense; rank 3 is
   enforced by zeroing the smallest eigenvalue.
3. Robust refinement over the 8 (+1) parameters of ``H^-1 = [[A, 0], [-p^T A, 1]]``: ``A`` upper
   triangular with ``A_33 = 1`` (5) and the plane at infinity ``(p, 1)`` (3), plus the shared log
   focal length for the "shared" model; this form already fixes rotation, translation and scale
   of the metric frame. Each camera ``P_i H^-1 = K_i [R_i | t_i]`` contributes the residuals of
   :func:`intrinsic_constraint_residuals` and a focal residual, minimized by
   ``scipy.optimize.least_squares`` with a robust loss from the linear estimate and, unless that
   already explains most cameras, from the identity (the input is often nearly metric), keeping
   the lower cost; then the cameras whose residual is within ``outlier_factor`` loss scales are
   kept and the fit repeated on them alone.
4. Degeneracy, at the solution: numerically, the smallest over largest singular value of the
   refinement's (loss-weighted) Jacobian; statistically, the predicted standard deviation of the
   upgrade from the residuals and the Jacobian. Pure rotation leaves the plane at infinity free,
   pure translation and other critical motions (H&Z 19.9) a calibration direction, a small
   baseline with noisy cameras leaves the plane at infinity uncertain: the upgrade is then
   skipped and the reason names the part that is not determined.
5. Never worse: skipped when the kept cameras already satisfy the constraints to within
   ``metric_residual``, unless their constraint residual falls clearly (``max_residual_ratio``),
   and when it stays above the noise (``max_residual_after``) without having fallen far
   (``inconsistent_ratio``): the cameras are then not one projective frame (submaps with errors of
   their own as large as the common distortion), and one transform would trade one distortion
   for another. Links that only their shared camera fixes are what splits a map into several
   frames; ``sl4slam.completion`` completes them while the map is built.
6. Gauge: the similarity is chosen so that the first kept keyframe keeps its camera centre and
   orientation (as decomposed from the input), and the median distance of the kept camera centres
   to it is kept too, so trajectory files stay readable. The result is in SL(4), orientation
   preserving (``det > 0``) and gives the camera centres a positive homogeneous weight, so it can
   premultiply graph nodes directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import Enum
from typing import ClassVar, Mapping

import numpy as np
from scipy.optimize import least_squares


from .errors import UserError
from .geometry import decompose_projection, normalize_sl4, projection_intrinsics, rq_decomposition
from .section import Section, setting


@dataclass
class UpgradeConfig(Section):
    """Projective-to-metric upgrade of the finished map (``sl4slam.upgrade``): self-calibration
    through the absolute dual quadric (Hartley & Zisserman, Multiple View Geometry, 2nd ed., ch. 19,
    "H&Z") from zero skew, square pixels, a known principal point and one focal length.

    Residuals are unitless: skew / f, fy / fx - 1, principal-point offset / f (and, for the focal
    model, log focal ratios), so 0.01 reads "a hundredth of the focal length"."""

    section: ClassVar[str] = "upgrade"
    builds: ClassVar[str] = "sl4slam.metric_frame:MetricFrame"
    flag_prefix: ClassVar[str] = "upgrade-"

    mode: str = setting("auto", choices=("auto", "on", "off"), flag='--metric-upgrade')
    """"on": estimate the upgrade at the end of a run and apply it to every node, pose and map point
    when it is well conditioned and clearly better; "off": leave the map in the first submap's
    projective frame; "auto": on where links may be 15-DOF, which make the whole map inherit the
    first submap's projective distortion (the SL(4) submap graph, and the keyframe graph with
    "select" links), off for calibration links and for the Sim(3) graph
    (decision: docs/decisions/metric-upgrade.md)."""
    focal_model: str = setting("shared", choices=("shared", "varying"))
    """"shared": one focal length for every keyframe (one physical camera films the video).
    "varying": each keyframe's focal free (a zoom, or a frontend whose focal wanders), with no
    smoothness prior: the four other constraints per camera determine the focal (H&Z 19.3)
    (decision: docs/decisions/metric-upgrade.md)."""
    focal_weight: float = setting(1.0, advanced=True, check=lambda v: v > 0, allowed="> 0")
    """Shared model: weight of the focal residual log(f_i / f) against the skew / aspect /
    principal-point residuals; 1: a focal deviation of 0.01 (relative) counts like a principal
    point 0.01 focal lengths off."""
    loss: str = setting("cauchy", choices=("cauchy", "soft_l1", "huber", "arctan", "linear"), advanced=True)
    """Robust loss of the refinement (scipy.optimize.least_squares): "cauchy", "soft_l1", "huber",
    "arctan" or "linear" (none) (decision: docs/decisions/metric-upgrade.md)."""
    loss_scale: float = setting(0.01, advanced=True, check=lambda v: v > 0, allowed="> 0")
    """Residual (unitless) beyond which the robust loss down-weights, the noise expected of a good
    camera (decision: docs/decisions/metric-upgrade.md)."""
    outlier_factor: float = setting(3.0, advanced=True, check=lambda v: v >= 1, allowed=">= 1")
    """After the robust fit a camera is kept when its residual (RMS of its constraints) is below
    this many ``loss_scale``s; 3: the usual 3-sigma rule with ``loss_scale`` as the noise."""
    min_inlier_fraction: float = setting(0.5, advanced=True, check=lambda v: 0 < v <= 1, allowed="in (0, 1]")
    """Skip when fewer cameras than this fraction are kept: most keyframes must agree."""
    min_keyframes: int = setting(3, advanced=True, check=lambda v: v >= 3, allowed="at least 3 (H&Z 19.3)")
    """Fewest keyframes: the linear absolute-dual-quadric estimate with a known principal point,
    zero skew and unit aspect ratio needs 3 views (H&Z 19.3)."""
    min_condition: float = setting(1e-3, advanced=True, check=lambda v: 0 <= v < 1, allowed="in [0, 1)")
    """Skip when the refinement's Jacobian at the solution has smallest / largest singular value
    below this (plane at infinity in units of the scene depth): pure rotation, pure translation and
    other critical motions (H&Z 19.9) leave a direction undetermined
    (decision: docs/decisions/metric-upgrade.md)."""
    max_uncertainty: float = setting(0.01, advanced=True, check=lambda v: v > 0, allowed="> 0")
    """Skip when the predicted standard deviation of the upgrade (plane at infinity in units of the
    scene depth, calibration in units of the focal; from the residuals and the Jacobian) is above
    this, i.e. a distortion of the map by a hundredth: near-degenerate motion with noisy cameras,
    e.g. a rotation with a baseline of a hundredth of the scene depth
    (decision: docs/decisions/metric-upgrade.md)."""
    max_iterations: int = setting(100, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Most residual evaluations of each robust refinement (scipy's ``max_nfev``)
    (decision: docs/decisions/metric-upgrade.md)."""
    max_residual_ratio: float = setting(0.8, advanced=True, check=lambda v: 0 < v <= 1, allowed="in (0, 1]")
    """Never make it worse: apply only when the constraint residual after the upgrade is below
    this fraction of the one before (on the kept cameras), so an already metric map (the residual
    is noise) is left untouched."""
    max_residual_after: float = setting(0.015, advanced=True, check=lambda v: v > 0, allowed="> 0")
    """Never make it worse: when the kept cameras' constraint residual after the upgrade is still
    above this (1.5 ``loss_scale``s), one transform could not make them metric: the map is not one
    projective frame. The upgrade is then skipped unless the distortion it removed was clearly
    larger than that inconsistency (``inconsistent_ratio``), so it does not trade one distortion
    for another (decision: docs/decisions/metric-upgrade.md)."""
    inconsistent_ratio: float = setting(0.3, advanced=True, check=lambda v: 0 < v <= 1, allowed="in (0, 1]")
    """See ``max_residual_after``: above it, apply only when the residual fell below this fraction of
    the one before (decision: docs/decisions/metric-upgrade.md)."""
    complete_links: bool = setting(True, advanced=True)
    """While a run ends with the upgrade (and its graph holds SL(4) links), a fallback link on a
    planar shared frame, which only its two cameras fix, is completed from the next submap's
    cameras (``sl4slam.completion``): the perspective bending the link left free is chosen so those
    cameras are metric in the running upgrade of the map so far, keeping the map one projective
    frame for the upgrade (decision: docs/decisions/planar-link-completion.md)."""
    running_keyframes: int = setting(32, advanced=True)
    """The running upgrade that completes planar links estimates the map's metric frame from at most
    this many keyframes of the segment (half of them the newest, where the link is, the other half
    spread evenly over the rest), so its cost stays flat as the map grows. The upgrade's 8 unknowns
    need 3 cameras (H&Z 19.3). The final upgrade uses every keyframe
    (decision: docs/decisions/planar-link-completion.md)."""
    running_refresh: float = setting(0.1, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: for every link)")
    """The running upgrade is estimated again once its segment has grown by this fraction of its
    keyframes since the last estimate (0: for every completed link). Each estimate reads iSAM2's
    estimate of the whole map, so a fixed interval would make a link's cost grow with the map; a
    fractional one keeps the cost per submap flat (decision: docs/decisions/planar-link-completion.md)."""
    metric_residual: float = setting(0.002, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Never make it worse: cameras whose constraint residual (skew, aspect and principal-point
    offset over the focal length) is already below this are metric to within the upgrade's own
    noise and are left alone (decision: docs/decisions/metric-upgrade.md)."""

    completion_residual: float = setting(0.0, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """A planar link whose next submap's cameras already satisfy the constraints through it to
    within this is left as measured (0: never on that ground alone). Either way the completion
    must lower their constraint residual clearly (``max_residual_ratio``) and determine the
    bending (``max_uncertainty``), which leaves cameras metric to within their noise alone
    (decision: docs/decisions/planar-link-completion.md)."""

    def validate(self) -> None:
        super().validate()
        self._require("running_keyframes", self.running_keyframes >= self.min_keyframes,
                      f"at least --upgrade-min-keyframes ({self.min_keyframes})")

NUM_CALIBRATION = 5
"""Free entries of the upper-triangular ``A`` (``A_33 = 1``)."""
NUM_GEOMETRY = NUM_CALIBRATION + 3
"""``A`` and the plane at infinity ``p``: the 8 degrees of freedom of a projective-to-metric upgrade."""


class UpgradeStatus(str, Enum):
    """What :func:`estimate_metric_upgrade` did."""

    APPLIED = "applied"
    ALREADY_METRIC = "already metric"
    """Skipped: the cameras already satisfy the constraints to within the upgrade's own noise."""
    SKIPPED = "skipped"
    """Skipped for another reason (too few or inconsistent cameras, degenerate motion, no gain)."""


@dataclass
class MetricUpgrade:
    """Outcome of :func:`estimate_metric_upgrade`.

    Attributes:
        H_metric_world: ``(4, 4)`` SL(4) map of world points into the metric frame
            (``X_metric ~ H X_world``; cameras become ``P H^-1``); the identity when skipped.
        status: applied, already metric, or skipped.
        reason: why it was skipped (a short phrase for a run summary); ``"applied"`` otherwise.
        residual_before: RMS over the kept cameras (all cameras when no fit ran) and over the four
            unitless constraints of :func:`intrinsic_constraint_residuals` (skew / f,
            fy / fx - 1, (cx - u0) / f, (cy - v0) / f with f = sqrt(fx fy)) of the input cameras.
        residual_after: the same for the cameras under the returned ``H_metric_world`` (equal to
            ``residual_before`` when skipped).
        focal: median focal length (px, ``sqrt(fx fy)``) of the kept cameras under the returned
            transform.
        focals: ``(N,)`` focal length (px) of every keyframe under the returned transform.
        condition: smallest / largest singular value of the refinement's Jacobian at the solution
            (0 when no fit ran): the numerical degeneracy figure.
        uncertainty: largest predicted standard deviation of the upgrade's parameters (plane at
            infinity in units of ``scene_scale``, calibration in units of the focal), from the
            residuals and the Jacobian: the statistical degeneracy figure (inf when no fit ran).
        inliers: ``(N,)`` bool, the cameras kept by the robust fit (all false when no fit ran).
        seconds: wall time of the estimate.
    """

    H_metric_world: np.ndarray
    status: UpgradeStatus
    reason: str
    residual_before: float
    residual_after: float
    focal: float
    focals: np.ndarray
    condition: float
    uncertainty: float
    inliers: np.ndarray
    seconds: float
    details: dict = field(default_factory=dict)
    """Diagnostics: the fit's own residual, the start it came from, inlier count, f0."""

    @property
    def applied(self) -> bool:
        """Whether ``H_metric_world`` is a real upgrade (false: skipped, identity)."""
        return self.status is UpgradeStatus.APPLIED

    def summary(self) -> dict:
        """Plain JSON-friendly figures for a run summary."""
        return {
            "applied": self.applied,
            "status": self.status.value,
            "reason": self.reason,
            "residual_before": round(self.residual_before, 6),
            "residual_after": round(self.residual_after, 6),
            "focal_px": round(self.focal, 3),
            "condition": float(f"{self.condition:.3g}"),
            "uncertainty": float(f"{self.uncertainty:.3g}") if np.isfinite(self.uncertainty) else None,
            "inliers": int(self.inliers.sum()),
            "keyframes": int(self.inliers.size),
            "seconds": round(self.seconds, 4),
        }


# ------------------------------------------------------------------------------ constraints
def intrinsic_constraint_residuals(K: np.ndarray, principal_points: np.ndarray) -> np.ndarray:
    """How far intrinsics are from zero skew, square pixels and the given principal point.

    Args:
        K: ``(N, 3, 3)`` upper-triangular intrinsics with ``K_33 = 1`` (``decompose_projection``).
        principal_points: ``(N, 2)`` the principal point each camera should have, px.

    Returns:
        ``(N, 4)`` unitless: ``[skew / f, fy / fx - 1, (cx - u0) / f, (cy - v0) / f]`` with
        ``f = sqrt(fx fy)``; zero for an ideal camera.
    """
    K = np.asarray(K, dtype=np.float64)
    pp = np.asarray(principal_points, dtype=np.float64)
    fx, fy = K[..., 0, 0], K[..., 1, 1]
    f = np.sqrt(fx * fy)
    return np.stack([K[..., 0, 1] / f, fy / fx - 1.0, (K[..., 0, 2] - pp[..., 0]) / f, (K[..., 1, 2] - pp[..., 1]) / f], axis=-1)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values.size else 0.0


def _calibration_from_rows(r0: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Constraint terms and focal of cameras whose left 3x3 blocks have rows ``r0, r1, r2``
    ``(..., 3)`` (pixels centred on the wanted principal point).

    ``M M^T = K K^T`` gives ``K = [[a, s, u], [0, b, v], [0, 0, 1]]`` in closed form (the K of an
    RQ decomposition, without the rotation); ``M M^T`` is positive definite for any invertible M.
    Returns ``(..., 4)`` terms as in :func:`intrinsic_constraint_residuals` (target principal point
    0) and ``(...)`` focal ``sqrt(a b)``.
    """
    w22 = np.einsum("...i,...i->...", r2, r2)
    u = np.einsum("...i,...i->...", r0, r2) / w22
    v = np.einsum("...i,...i->...", r1, r2) / w22
    tiny = 1e-300
    b = np.sqrt(np.maximum(np.einsum("...i,...i->...", r1, r1) / w22 - v * v, tiny))
    s = (np.einsum("...i,...i->...", r0, r1) / w22 - u * v) / b
    a = np.sqrt(np.maximum(np.einsum("...i,...i->...", r0, r0) / w22 - u * u - s * s, tiny))
    f = np.sqrt(a * b)
    return np.stack([s / f, b / a - 1.0, u / f, v / f], axis=-1), f


# ------------------------------------------------------------------------------ the fit
class _ConstraintFit:
    """Residuals of normalized cameras ``(N, 3, 4)`` under ``H^-1 = [[A, 0], [-p^T A, 1]]``.

    Parameters ``theta``: ``A_11 A_12 A_13 A_22 A_23`` (``A_33 = 1``), ``p`` (3) and, for the
    shared focal model, the log of the shared (normalized) focal length. Everything is evaluated
    for a batch of parameter vectors at once, so the Jacobian (central differences) costs one
    vectorized call.
    """

    def __init__(self, P_n: np.ndarray, config: UpgradeConfig):
        self.left = P_n[:, :, :3]
        self.last = P_n[:, :, 3]
        self.shared = config.focal_model == "shared"
        self.weight = config.focal_weight
        self.config = config

    @staticmethod
    def calibration(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``A (..., 3, 3)`` and ``p (..., 3)`` of parameter vectors ``(..., P)``."""
        theta = np.asarray(theta, dtype=np.float64)
        A = np.zeros(theta.shape[:-1] + (3, 3))
        A[..., 0, :] = theta[..., 0:3]
        A[..., 1, 1:] = theta[..., 3:5]
        A[..., 2, 2] = 1.0
        return A, theta[..., NUM_CALIBRATION:NUM_GEOMETRY]

    def calibration_terms(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Constraint terms ``(..., N, 4)`` and focal lengths ``(..., N)`` (normalized) of the
        cameras ``P_i H^-1`` for parameters ``(..., P)``."""
        A, p = self.calibration(theta)
        # Row by row, the left blocks (M_i - m_i p^T) A of P_i H^-1.
        rows = [(self.left[:, row] - self.last[:, row, None] * p[..., None, :]) @ A for row in range(3)]
        return _calibration_from_rows(*rows)

    def terms(self, theta: np.ndarray) -> np.ndarray:
        """``(..., N, 4)`` per-camera residuals for parameters ``(..., P)``, with the shared
        model's weighted ``log(f_i / f)`` as a fifth column."""
        terms, focal = self.calibration_terms(theta)
        if not self.shared:
            return terms
        log_shared = np.asarray(theta)[..., NUM_GEOMETRY]
        return np.concatenate([terms, self.weight * (np.log(focal) - log_shared[..., None])[..., None]], axis=-1)

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        return self.terms(theta).ravel()

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """Central differences, all parameters in one batch: ``(N * k, P)``."""
        step = 6e-6 * np.maximum(1.0, np.abs(theta))  # ~ eps^(1/3): truncation and rounding balanced
        shifts = np.concatenate([np.diag(step), -np.diag(step)])
        values = self.terms(theta[None, :] + shifts).reshape(2 * len(theta), -1)
        return ((values[: len(theta)] - values[len(theta):]) / (2.0 * step[:, None])).T

    def camera_rms(self, theta: np.ndarray) -> np.ndarray:
        """``(N,)`` RMS of each camera's residuals."""
        return np.sqrt(np.mean(self.terms(theta) ** 2, axis=-1))

    def with_focal(self, theta_geometry: np.ndarray) -> np.ndarray:
        """Full parameter vector from ``A, p``: the shared log focal starts at the median."""
        if not self.shared:
            return np.asarray(theta_geometry, dtype=np.float64)
        _, focal = self.calibration_terms(theta_geometry)
        return np.append(theta_geometry, np.median(np.log(focal)))

    def solve(self, theta0: np.ndarray):
        config = self.config
        return least_squares(
            self.residuals, theta0, jac=self.jacobian, method="trf", loss=config.loss, f_scale=config.loss_scale,
            max_nfev=config.max_iterations, ftol=1e-15, xtol=1e-15, gtol=1e-15, x_scale=1.0,
        )


def _normalized_cameras(P: np.ndarray, principal_points: np.ndarray, f0: float, T_norm: np.ndarray) -> np.ndarray:
    """``N_i^-1 P_i T_norm^-1`` with unit Frobenius norm, ``N_i = [[f0, 0, u_i], [0, f0, v_i], [0, 0, 1]]``:
    pixels centred on the wanted principal point over a rough focal, the world in normalized units
    (H&Z 19.3.3: well-scaled equations)."""
    N_inv = np.zeros((len(P), 3, 3))
    N_inv[:, 0, 0] = N_inv[:, 1, 1] = 1.0 / f0
    N_inv[:, :2, 2] = -principal_points / f0
    N_inv[:, 2, 2] = 1.0
    P_n = N_inv @ P @ np.linalg.inv(T_norm)
    return P_n / np.linalg.norm(P_n, axis=(1, 2), keepdims=True)


def _linear_start(P_n: np.ndarray) -> np.ndarray | None:
    """``A, p`` (8,) from the linear absolute dual quadric of normalized cameras, or ``None``.

    Four equations per camera, linear in the 10 entries of the symmetric ``Q*``:
    ``w_12 = w_13 = w_23 = 0`` and ``w_11 - w_22 = 0`` with ``w = P Q* P^T`` (H&Z 19.3.1).
    """
    rows = P_n  # (N, 3, 4)
    upper = np.triu_indices(4)
    halve = np.where(upper[0] == upper[1], 0.5, 1.0)

    def coefficients(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        outer = a[:, :, None] * b[:, None, :]
        return (outer + np.swapaxes(outer, 1, 2))[:, upper[0], upper[1]] * halve

    r0, r1, r2 = rows[:, 0], rows[:, 1], rows[:, 2]
    system = np.concatenate([
        coefficients(r0, r1), coefficients(r0, r2), coefficients(r1, r2),
        coefficients(r0, r0) - coefficients(r1, r1),
    ])
    # Least-squares null vector from the 10x10 normal matrix (a tall SVD costs far more on a
    # busy machine; the refinement polishes what squaring the condition number loses).
    _, null = np.linalg.eigh(system.T @ system)
    Q = np.zeros((4, 4))
    Q[upper] = null[:, 0]
    Q = Q + np.triu(Q, 1).T
    eigenvalues, vectors = np.linalg.eigh(Q)
    if eigenvalues.sum() < 0:
        eigenvalues = -eigenvalues
    order = np.argsort(eigenvalues)[::-1]
    eigenvalues, vectors = eigenvalues[order], vectors[:, order]
    if eigenvalues[2] <= 1e-12 * eigenvalues[0]:
        return None  # not positive semi-definite of rank 3: no valid quadric
    # Q* = L diag(1, 1, 1, 0) L^T with L = H^-1 (metric -> normalized world); rank 3 enforced.
    L = vectors * np.append(np.sqrt(eigenvalues[:3]), 1.0)
    return _geometry_parameters(L)


def _geometry_parameters(L: np.ndarray) -> np.ndarray | None:
    """``A, p`` (8,) of the upgrade ``L = H^-1`` after a similarity of the metric frame that brings
    it to ``[[A, 0], [-p^T A, 1]]`` (``A`` upper triangular, ``A_33 = 1``); ``None`` when the world
    origin lies on the plane at infinity."""
    origin = np.linalg.solve(L, np.array([0.0, 0.0, 0.0, 1.0]))  # the metric point seen as the world origin
    if abs(origin[3]) < 1e-12 * np.abs(origin[:3]).max():
        return None
    shift = np.eye(4)
    shift[:3, 3] = origin[:3] / origin[3]
    L = L @ shift
    U, R = rq_decomposition(L[:3, :3])
    signs = np.where(np.diag(U) < 0, -1.0, 1.0)
    U, R = U * signs, signs[:, None] * R
    rotate = np.eye(4)
    rotate[:3, :3] = R.T
    L = L @ rotate
    L = L / L[3, 3]
    L = L @ np.diag([1.0 / L[2, 2]] * 3 + [1.0])
    A = L[:3, :3]
    p = -np.linalg.solve(A.T, L[3, :3])
    theta = np.array([A[0, 0], A[0, 1], A[0, 2], A[1, 1], A[1, 2], *p])
    return theta if np.all(np.isfinite(theta)) else None


# ------------------------------------------------------------------------------ public API
def _check_inputs(P_world, principal_points, image_sizes, scene_scale) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    P = np.asarray(P_world, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (3, 4):
        raise UserError(f"P_world must be an (N, 3, 4) array of camera matrices, got shape {P.shape}")
    N = len(P)
    pp = np.asarray(principal_points, dtype=np.float64)
    if pp.shape == (2,):
        pp = np.broadcast_to(pp, (N, 2))
    if pp.shape != (N, 2):
        raise UserError(f"principal_points must be (N, 2) = ({N}, 2) px or one (2,) point, got shape {pp.shape}")
    sizes = None
    if image_sizes is not None:
        sizes = np.asarray(image_sizes, dtype=np.float64)
        if sizes.shape == (2,):
            sizes = np.broadcast_to(sizes, (N, 2))
        if sizes.shape != (N, 2) or not np.all(np.isfinite(sizes) & (sizes > 0)):
            raise UserError(f"image_sizes must be positive (width, height) px, (N, 2) or (2,), got shape {sizes.shape}")
    for name, value in (("P_world", P), ("principal_points", pp)):
        if not np.all(np.isfinite(value)):
            raise UserError(f"{name} contains NaN or Inf; check the graph estimate before the upgrade")
    if N:
        det = np.linalg.det(P[:, :, :3])
        scale = np.abs(P[:, :, :3]).max(axis=(1, 2))
        singular = np.flatnonzero(~(np.abs(det) > 1e-12 * scale**3))
        if singular.size:
            raise UserError(f"P_world[{singular[0]}] has a singular left 3x3 block (a camera at infinity); "
                            "pass finite cameras P = K [R | t] H_world_submap^-1")
    scale = 1.0 if scene_scale is None else float(scene_scale)
    if not (np.isfinite(scale) and scale > 0):
        raise UserError(f"scene_scale must be a positive distance in world units, got {scene_scale!r}")
    return P, pp, sizes, scale


def estimate_metric_upgrade(
    P_world: np.ndarray,
    principal_points: np.ndarray,
    config: UpgradeConfig | None = None,
    image_sizes: np.ndarray | None = None,
    scene_scale: float | None = None,
) -> MetricUpgrade:
    """Estimate ``H_metric_world`` so that every camera ``P_i H^-1`` has zero skew, square pixels,
    the given principal point and a shared (or slowly varying) focal length.

    Args:
        P_world: ``(N, 3, 4)`` keyframe cameras in the (projectively distorted) world frame,
            ``P_i = K_i [R_i | t_i] H_world_submap^-1``, in keyframe order.
        principal_points: ``(N, 2)`` (or one ``(2,)``) principal point each camera should have, px
            on the grid of ``K_i`` (VGGT: ``(W/2, H/2)``).
        config: thresholds and the focal model (``UpgradeConfig``; default settings when None).
        image_sizes: optional ``(N, 2)`` or ``(2,)`` ``(width, height)`` px; the rough focal that
            normalizes the cameras is then ``(width + height) / 2`` instead of the input cameras'
            median focal.
        scene_scale: typical distance of the map from its cameras in world units (e.g. the median
            keyframe depth). The world is measured in this unit, so the conditioning judges a
            camera baseline against the scene: a baseline far shorter than the scene is the near
            pure rotation it is. None: one world unit (the pipeline's world is the first submap's
            frame, which VGGT scales to a mean point distance of 1).

    Returns:
        :class:`MetricUpgrade`; ``H_metric_world`` is the identity when skipped (``reason`` says
        why: upgrade off, too few keyframes, degenerate motion, too few consistent cameras, no
        clear improvement).

    Raises:
        UserError: malformed input (shapes, NaN, singular cameras) or settings.
    """
    start = time.perf_counter()
    config = config if config is not None else UpgradeConfig()  # checked by sl4slam.resolve in a run
    P, pp, sizes, scene_scale = _check_inputs(P_world, principal_points, image_sizes, scene_scale)
    N = len(P)
    K_in, T_in, C_in = decompose_projection(P) if N else (np.zeros((0, 3, 3)), np.zeros((0, 4, 4)), np.zeros((0, 3)))
    constraints_in = intrinsic_constraint_residuals(K_in, pp)
    focals_in = np.sqrt(K_in[:, 0, 0] * K_in[:, 1, 1])

    def skipped(reason: str, inliers: np.ndarray | None = None, condition: float = 0.0, uncertainty: float = float("inf"),
                status: UpgradeStatus = UpgradeStatus.SKIPPED, **details) -> MetricUpgrade:
        kept = inliers if inliers is not None and inliers.any() else np.ones(N, dtype=bool)
        before = _rms(constraints_in[kept])
        return MetricUpgrade(
            H_metric_world=np.eye(4), status=status, reason=reason, residual_before=before, residual_after=before,
            focal=float(np.median(focals_in[kept])) if N else 0.0, focals=focals_in, condition=float(condition),
            uncertainty=float(uncertainty),
            inliers=inliers if inliers is not None else np.zeros(N, dtype=bool),
            seconds=time.perf_counter() - start, details=details,
        )

    if config.mode == "off":
        return skipped("upgrade off")
    if N < config.min_keyframes:
        return skipped(f"too few keyframes ({N} < {config.min_keyframes})")

    # 1. Normalization: centred pixels over a rough focal; world centred, in units of scene_scale.
    f0 = float(np.median(sizes.sum(axis=1)) / 2.0) if sizes is not None else float(np.median(focals_in))
    T_norm = np.eye(4)
    T_norm[:3, :3] /= scene_scale
    T_norm[:3, 3] = -np.median(C_in, axis=0) / scene_scale
    P_n = _normalized_cameras(P, pp, f0, T_norm)

    # 2.-3. Robust refinement from the linear estimate, and from the identity unless the first
    # already explains most cameras within the noise; the lower robust cost wins.
    fit = _ConstraintFit(P_n, config)
    starts = {"linear": _linear_start(P_n), "identity": np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0])}
    best, best_start = None, ""
    for name, theta0 in starts.items():
        if theta0 is None:
            continue
        result = fit.solve(fit.with_focal(theta0))
        if np.isfinite(result.cost) and (best is None or result.cost < best.cost):
            best, best_start = result, name
        if best is not None and _fits_most(fit.camera_rms(best.x), config):
            break
    if best is None:
        return skipped("refinement failed (non-finite residuals)")

    camera_rms = fit.camera_rms(best.x)
    inliers = camera_rms <= config.outlier_factor * config.loss_scale
    if inliers.sum() < max(config.min_inlier_fraction * N, config.min_keyframes):
        return skipped(f"too few consistent cameras ({inliers.sum()} of {N})", inliers, start=best_start)
    kept_fit = _ConstraintFit(P_n[inliers], config)
    final = kept_fit.solve(best.x)

    # 4. Is the solution determined? Numerically (condition) and statistically (uncertainty).
    condition, uncertainty, weak_part = _determination(kept_fit, final)
    if not condition >= config.min_condition:
        return skipped(f"degenerate motion: {weak_part} is undetermined (condition {condition:.1e} < {config.min_condition:.0e})",
                       inliers, condition, start=best_start)
    if not uncertainty <= config.max_uncertainty:
        return skipped(f"degenerate motion: {weak_part} is poorly determined (uncertainty {uncertainty:.2g} > {config.max_uncertainty:g})",
                       inliers, condition, uncertainty, start=best_start)

    # 6. Gauge, then 5. the never-worse check on the cameras as they will be.
    A, p = fit.calibration(final.x)
    H_normalized = np.eye(4)
    H_normalized[:3, :3] = np.linalg.inv(A)
    H_normalized[3, :3] = p
    H = _similarity_gauge(H_normalized @ T_norm, P, T_in, C_in, inliers)
    if H is None:
        return skipped("refinement failed (upgrade not invertible)", inliers, condition, uncertainty, start=best_start)
    K_out = projection_intrinsics(P @ np.linalg.inv(H))
    constraints_out = intrinsic_constraint_residuals(K_out, pp)
    before, after = _rms(constraints_in[inliers]), _rms(constraints_out[inliers])
    details = {"start": best_start, "f0": f0, "fit_rms": _rms(final.fun), "kept": int(inliers.sum())}
    if before < config.metric_residual:
        return skipped(f"already metric (constraint residual {before:.2g} < {config.metric_residual:g})", inliers,
                       condition, uncertainty, UpgradeStatus.ALREADY_METRIC, **details)
    if not after <= config.max_residual_ratio * before:
        return skipped(f"no clear improvement (constraint residual {before:.2g} -> {after:.2g})", inliers, condition, uncertainty,
                       **details)
    if after > config.max_residual_after and after > config.inconsistent_ratio * before:
        return skipped(f"the cameras are not one projective frame (constraint residual {before:.2g} -> {after:.2g}: "
                       f"above {config.max_residual_after:g} and not below {config.inconsistent_ratio:g}x the "
                       "distortion removed)", inliers, condition, uncertainty, **details)
    focals = np.sqrt(K_out[:, 0, 0] * K_out[:, 1, 1])
    return MetricUpgrade(
        H_metric_world=H, status=UpgradeStatus.APPLIED, reason="applied", residual_before=before, residual_after=after,
        focal=float(np.median(focals[inliers])), focals=focals, condition=condition, uncertainty=uncertainty, inliers=inliers,
        seconds=time.perf_counter() - start, details=details,
    )


def _determination(fit: _ConstraintFit, solution) -> tuple[float, float, str]:
    """How well the cameras determine the upgrade at ``solution`` (a least_squares result).

    Returns the condition (smallest / largest singular value of the loss-weighted Jacobian, from
    the eigenvalues of ``J^T J``: resolves down to ~1e-8), the uncertainty (largest standard
    deviation of the 8 upgrade parameters, ``sigma^2 (J^T J)^-1`` with the plain Jacobian and
    sigma from the residuals: the plane at infinity in units of ``scene_scale``, the calibration in
    units of the focal length, so it reads as a relative distortion of the map) and the name of
    the part the weakest direction mostly moves.
    """
    eigenvalues, eigenvectors = np.linalg.eigh(solution.jac.T @ solution.jac)
    singular_values = np.sqrt(np.maximum(eigenvalues, 0.0))
    condition = float(singular_values[0] / singular_values[-1]) if singular_values[-1] > 0 else 0.0
    J, r = fit.jacobian(solution.x), fit.residuals(solution.x)
    sigma2 = float(r @ r) / max(r.size - J.shape[1], 1)
    normal = J.T @ J
    try:
        covariance = sigma2 * np.linalg.inv(normal)[:NUM_GEOMETRY, :NUM_GEOMETRY]
        uncertainty = float(np.sqrt(max(np.linalg.eigvalsh(covariance).max(), 0.0)))
    except np.linalg.LinAlgError:
        uncertainty = float("inf")
    weak = eigenvectors[:, 0]
    plane = np.linalg.norm(weak[NUM_CALIBRATION:NUM_GEOMETRY]) > np.linalg.norm(np.delete(weak, np.s_[NUM_CALIBRATION:NUM_GEOMETRY]))
    part = ("the plane at infinity (camera centres barely move against the scene: pure rotation)" if plane
            else "the calibration (critical motion, e.g. pure translation or one rotation axis)")
    return condition, uncertainty if np.isfinite(uncertainty) else float("inf"), part


def _fits_most(camera_rms: np.ndarray, config: UpgradeConfig) -> bool:
    """Whether the median camera is within the noise and enough cameras would be kept."""
    kept = camera_rms <= config.outlier_factor * config.loss_scale
    return bool(np.median(camera_rms) <= config.loss_scale and kept.mean() >= config.min_inlier_fraction)


def _similarity_gauge(H: np.ndarray, P: np.ndarray, T_in: np.ndarray, C_in: np.ndarray, inliers: np.ndarray) -> np.ndarray | None:
    """Fix the similarity left free by the upgrade ``H`` (world -> some metric frame).

    The first kept keyframe keeps its input camera centre and orientation, the median distance of
    the kept centres to it is kept, the map keeps its handedness (``det H > 0``: a projective map
    preserves orientation where ``det > 0``, since its Jacobian determinant is ``det H / w^4``) and
    the camera centres keep a positive homogeneous weight. Returns ``H`` in SL(4), or ``None``.
    """
    kept = np.flatnonzero(inliers)
    weights = (np.c_[C_in[kept], np.ones(len(kept))] @ H[3])
    if np.median(weights) < 0:
        H = -H
    if np.linalg.det(H) < 0:
        H = np.diag([1.0, 1.0, -1.0, 1.0]) @ H
    first = kept[0]
    _, T_metric, C_metric = decompose_projection(P[kept] @ np.linalg.inv(H))
    R_in = T_in[first, :3, :3].T  # camera-from-world rotation of the input
    R_metric = T_metric[0, :3, :3].T
    rotation = R_in.T @ R_metric  # S rotates the metric frame so the first camera's rotation is R_in
    spread_in = np.median(np.linalg.norm(C_in[kept[1:]] - C_in[first], axis=1))
    spread_metric = np.median(np.linalg.norm(C_metric[1:] - C_metric[0], axis=1))
    if not (spread_metric > 0 and spread_in > 0):
        return None
    scale = spread_in / spread_metric
    S = np.eye(4)
    S[:3, :3] = scale * rotation
    S[:3, 3] = C_in[first] - scale * rotation @ C_metric[0]
    try:
        return normalize_sl4(S @ H)
    except ValueError:
        return None


def upgrade_graph_nodes(H_world_submap: Mapping[int, np.ndarray] | np.ndarray, H_metric_world: np.ndarray):
    """Graph nodes in the metric frame: ``H_metric_world @ H_world_submap`` for a dict
    ``{submap_id: (4, 4)}`` (returns a dict) or an ``(M, 4, 4)`` array. Both factors are in SL(4),
    so the nodes stay in SL(4), and every keyframe camera ``P = K [R|t] H_world_submap^-1`` becomes
    ``P H_metric_world^-1``."""
    H = np.asarray(H_metric_world, dtype=np.float64)
    if isinstance(H_world_submap, Mapping):
        return {key: H @ np.asarray(node, dtype=np.float64) for key, node in H_world_submap.items()}
    return H @ np.asarray(H_world_submap, dtype=np.float64)
