"""The pose-graph engine in Sim(3): 7-DOF similarity transforms, so loop closures can correct scale drift."""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np

from ..geometry import project_to_so3, sim3_decompose
from .pose_graph import PoseGraph, check_matrix

ORTHOGONALITY_TOLERANCE = 1e-6
"""Largest ``|R^T R - I|`` entry accepted for the rotation part of a similarity input."""


def similarity_to_gtsam(T: np.ndarray) -> gtsam.Similarity3:
    """``[sR t; 0 1]`` (4, 4) -> ``gtsam.Similarity3`` acting the same way on points.

    GTSAM's ``Similarity3(R, t_g, s)`` maps ``p -> s (R p + t_g)`` and its ``matrix()`` is
    ``[R t_g; 0 1/s]``, so ``t_g = t / s``. (Its 4x4 constructor would read ``sR`` as the rotation.)
    """
    s, R, t = sim3_decompose(T)
    return gtsam.Similarity3(gtsam.Rot3(R), t / s, s)


def similarity_from_gtsam(S: gtsam.Similarity3) -> np.ndarray:
    """``gtsam.Similarity3`` -> ``[sR t; 0 1]`` (4, 4) float64."""
    s = float(S.scale())
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(S.rotation().matrix(), dtype=np.float64)
    T[:3, 3] = s * np.asarray(S.translation(), dtype=np.float64)
    return T


class Sim3PoseGraph(PoseGraph):
    """Nodes and factors in ``gtsam.Similarity3``; inputs are ``[sR t; 0 1]`` with ``s > 0``."""

    kind = "sim3"
    dim = 7

    def _check(self, name: str, M: np.ndarray) -> np.ndarray:
        M = check_matrix(name, M)
        if np.abs(M[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-12 * max(1.0, np.abs(M).max()):
            raise ValueError(f"{name} is not a similarity: its last row is {M[3]}, expected [0 0 0 1]")
        det = np.linalg.det(M[:3, :3])
        if not det > 0:
            raise ValueError(f"{name}: similarity with det <= 0 (reflection or zero scale)")
        s, R, t = sim3_decompose(M)
        if np.abs(R.T @ R - np.eye(3)).max() > ORTHOGONALITY_TOLERANCE:
            raise ValueError(f"{name} is not a similarity: its 3x3 block is not a scaled rotation")
        out = np.eye(4)
        out[:3, :3] = s * project_to_so3(R)
        out[:3, 3] = t
        return out

    def _inverse(self, M: np.ndarray) -> np.ndarray:
        s, R, t = sim3_decompose(M)
        out = np.eye(4)
        out[:3, :3] = R.T / s
        out[:3, 3] = -(R.T @ t) / s
        return out

    def _to_gtsam(self, M: np.ndarray) -> gtsam.Similarity3:
        return similarity_to_gtsam(M)

    def _from_gtsam(self, element: gtsam.Similarity3) -> np.ndarray:
        return similarity_from_gtsam(element)

    def _at(self, values: gtsam.Values, key: int) -> gtsam.Similarity3:
        return values.atSimilarity3(key)

    def _hat(self, xi: np.ndarray) -> np.ndarray:
        return np.asarray(gtsam.Similarity3.Hat(np.asarray(xi, dtype=np.float64)), dtype=np.float64)

    def _isam_estimate_one(self, key: int) -> gtsam.Similarity3:
        return self._isam.calculateEstimateSimilarity3(key)

    def _between_factor(
        self, key_a: int, key_b: int, Z_a_b: gtsam.Similarity3, noise: Any
    ) -> gtsam.BetweenFactorSimilarity3:
        return gtsam.BetweenFactorSimilarity3(key_a, key_b, Z_a_b, noise)

    def _prior_factor(self, key: int, Z: gtsam.Similarity3, noise: Any) -> gtsam.PriorFactorSimilarity3:
        return gtsam.PriorFactorSimilarity3(key, Z, noise)

    def _equality_factor(self, key: int, value: gtsam.Similarity3) -> gtsam.NonlinearEqualitySimilarity3:
        return gtsam.NonlinearEqualitySimilarity3(key, value)
