"""Edges weighted by their evidence: the information matrix of a relative measurement.

An alignment ``X_a ~ H X_b`` (submap ``a`` the older node ``i``, ``b`` the newer ``j``) enters the
graph as the factor ``(j, i, Z = H^-1)`` whose noise lives in the tangent space of ``Z``
(``Z_true = Z exp(xi)``, GTSAM's convention; see ``sl4slam.backend.pose_graph``). With ``H_true =
exp(-xi) H`` the transfer residual of inlier ``k`` is ``r_k(xi) = pi(exp(-xi) Y_k) - X_a,k`` with
``Y_k = H [X_b,k; 1]`` and ``pi`` the homogeneous division, so its Jacobian column for generator
``G_m`` is

    J_k[:, m] = -D pi(Y_k) G_m Y_k,    D pi(Y) = [I / w,  -y / w^2]   (Y = [y; w]),

and the Gauss-Newton information of the fit is ``sum_k J_k^T J_k / sigma^2`` with ``sigma^2`` the
per-axis variance of the inlier residuals (``rms^2 / 3``). Three corrections make it honest:

- dense residuals are not independent (a model errs in smooth blobs, not per pixel), so the sum
  counts at most ``BackendConfig.effective_points`` points per shared frame however many pixels
  were aligned (a link measured on several shared frames, ``extras["shared_frames"]``, has that
  many independent witnesses);
- its eigenvalues are clamped to ``[1 / max_sigma^2, 1 / min_sigma^2]``: directions the points do
  not observe (a planar shared frame leaves the plane's projective family free) get a weak but
  finite weight, and no edge claims a precision beyond ``min_sigma``;
- a fallback measurement (camera-constrained fit, Sim(3) stand-in, camera edge) is divided by
  ``fallback_sigma_scale^2``, so loops correct those links first.

With ``BackendConfig.weighting = "fixed"`` every edge gets the isotropic ``sigma`` (the reference
code's 0.05), still inflated for fallbacks; with "auto" (the default) so do the edges read from the
cameras (:func:`sl4slam.edges.is_camera_link`): their error is the shared frames' camera errors,
which the residuals of their points do not measure, while a fitted edge's error is what its points
say.
"""

from __future__ import annotations

import numpy as np

from .settings import BackendConfig
from ..edges import is_camera_link
from ..types import Alignment


def transfer_jacobians(H: np.ndarray, X_b: np.ndarray, generators: np.ndarray) -> np.ndarray:
    """Jacobians ``(n, 3, dim)`` of the transfer residuals with respect to the measurement's tangent.

    Args:
        H: ``(4, 4)`` the measurement ``X_a ~ H X_b``.
        X_b: ``(n, 3)`` inlier points in submap ``b`` (their images must have ``w > 0``).
        generators: ``(dim, 4, 4)`` tangent basis of the graph's group.
    """
    Y = np.concatenate([X_b, np.ones((len(X_b), 1))], axis=1) @ np.asarray(H, dtype=np.float64).T  # (n, 4)
    w = Y[:, 3:4]
    dim = len(generators)
    GY = (Y @ np.asarray(generators, dtype=np.float64).reshape(dim * 4, 4).T).reshape(len(Y), dim, 4)  # G_m Y_k
    d_pi = (GY[:, :, :3] - (Y[:, None, :3] / w[:, None]) * GY[:, :, 3:4]) / w[:, None]  # (n, dim, 3)
    return -np.swapaxes(d_pi, 1, 2)


def clamp_information(information: np.ndarray, min_sigma: float, max_sigma: float) -> np.ndarray:
    """Symmetric ``information`` with its eigenvalues clamped to ``[1 / max_sigma^2, 1 / min_sigma^2]``."""
    values, vectors = np.linalg.eigh(0.5 * (information + information.T))
    values = np.clip(values, 1.0 / max_sigma**2, 1.0 / min_sigma**2)
    return (vectors * values) @ vectors.T


def isotropic_information(dim: int, sigma: float) -> np.ndarray:
    return np.eye(dim) / sigma**2


def edge_information(alignment: Alignment, generators: np.ndarray, config: BackendConfig) -> np.ndarray:
    """Information matrix ``(dim, dim)`` of an edge measured by ``alignment`` (see the module doc)."""
    dim = len(generators)
    inflation = config.fallback_sigma_scale**2 if alignment.fallback else 1.0
    support = alignment.support
    if config.weighting == "fixed" or (config.weighting == "by-link" and is_camera_link(alignment)):
        return isotropic_information(dim, config.sigma) / inflation
    if support is None or len(support[1]) < 3:
        return isotropic_information(dim, config.max_sigma) / inflation
    X_a, X_b = support
    J = transfer_jacobians(alignment.H, X_b, generators)  # (n, 3, dim)
    variance = max(alignment.rms, 1e-12) ** 2 / 3.0  # per axis; exact fits are bounded by the clamp below
    witnesses = int(alignment.extras.get("shared_frames", 1))
    independent = min(float(alignment.support_count or len(X_b)), float(config.effective_points) * witnesses)
    rows = J.reshape(-1, dim)  # (3 n, dim): one row per residual component
    information = (rows.T @ rows) * (independent / len(X_b)) / variance
    return clamp_information(information, config.min_sigma, config.max_sigma) / inflation


def tangent_coordinates(step: np.ndarray, generators: np.ndarray) -> np.ndarray:
    """``(dim,)`` coordinates ``xi`` of a Lie algebra element ``step`` ``(4, 4)`` on ``generators``
    ``(dim, 4, 4)`` (least squares: ``step ~ sum_m xi_m G_m``)."""
    basis = generators.reshape(len(generators), 16).T
    return np.linalg.lstsq(basis, np.asarray(step, dtype=np.float64).reshape(16), rcond=None)[0]


def link_scatter(combined: Alignment, per_frame: list[Alignment], information, generators: np.ndarray) -> float:
    """How much more the shared frames' own links scatter about their combined link than their
    evidence says: ``N / (N - 1) * mean_f xi_f^T I_f xi_f / dim``, with ``exp(-xi_f) H_f = H``
    (``H_true = exp(-xi) H``, the module doc's convention), ``I_f = information(frame f's own link)``
    and ``N / (N - 1)`` for the combined link being their mean. About 1 when the information is
    honest; the frames' camera errors, which the evidence of one frame's points cannot see, raise it.

    Args:
        combined: the link of every shared frame together (``sl4slam.alignment.shared``).
        per_frame: each frame's own link (at least two).
        information: ``Alignment -> (dim, dim)`` the graph's information of an edge.
        generators: ``(dim, 4, 4)`` the graph group's tangent basis.
    """
    from ..geometry import matrix_log, normalize_sl4

    def unit(H: np.ndarray) -> np.ndarray:  # SL(4) links to det 1; a similarity's scale stays in its log
        return normalize_sl4(H) if len(generators) == 15 else np.asarray(H, dtype=np.float64)

    target = unit(combined.H)
    values = []
    for own in per_frame:
        xi = -tangent_coordinates(matrix_log(target @ np.linalg.inv(unit(own.H))), generators)
        values.append(float(xi @ information(own) @ xi) / len(generators))
    return len(per_frame) / (len(per_frame) - 1) * float(np.mean(values))


class NoiseScale:
    """How much the graph's edges understate their noise, measured while the run goes on: the
    median :func:`link_scatter` of the links made from several shared frames so far (1 before any,
    and never below 1: the evidence is a floor, not a ceiling). The loop gate divides its
    chi-square by it, i.e. scales the map's covariance, so that a loop is judged against the drift
    the map really accumulated (``sl4slam.loops``)."""

    def __init__(self) -> None:
        self.scatters: list[float] = []

    def add(self, scatter: float) -> None:
        if np.isfinite(scatter):
            self.scatters.append(float(scatter))

    @property
    def value(self) -> float:
        return max(1.0, float(np.median(self.scatters))) if self.scatters else 1.0
