"""The pose-graph engine in SL(4): 15-DOF projective transforms, the paper's factor graph (section 4.4)."""

from __future__ import annotations

from typing import Any, Sequence

import gtsam
import numpy as np

from ..geometry import normalize_sl4
from .pose_graph import PoseGraph, check_matrix


class SL4PoseGraph(PoseGraph):
    """Nodes and factors in ``gtsam.SL4``; inputs are any 4x4 with det > 0 (scaled to det = 1).

    ``gtsam.SL4`` rescales its input by ``det^(1/4)`` and, for ``det <= 0``, silently flips a
    singular vector, which changes the projective map. Every matrix is therefore normalized here
    with :func:`normalize_sl4`, which refuses ``det <= 0``, before GTSAM sees it.
    """

    kind = "sl4"
    dim = 15

    def _check(self, name: str, M: np.ndarray) -> np.ndarray:
        M = check_matrix(name, M)
        try:
            return normalize_sl4(M)
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None

    def _inverse(self, M: np.ndarray) -> np.ndarray:
        return normalize_sl4(np.linalg.inv(M))

    def _to_gtsam(self, M: np.ndarray) -> gtsam.SL4:
        return gtsam.SL4(M)

    def _from_gtsam(self, element: gtsam.SL4) -> np.ndarray:
        return normalize_sl4(np.array(element.matrix(), dtype=np.float64))

    def _at(self, values: gtsam.Values, key: int) -> gtsam.SL4:
        return values.atSL4(key)

    def _hat(self, xi: np.ndarray) -> np.ndarray:
        return np.asarray(gtsam.SL4.Hat(np.asarray(xi, dtype=np.float64)), dtype=np.float64)

    def _isam_estimate_one(self, key: int) -> gtsam.SL4:
        return self._isam.calculateEstimateSL4(key)

    def _between_factor(self, key_a: int, key_b: int, Z_a_b: gtsam.SL4, noise: Any) -> gtsam.BetweenFactorSL4:
        return gtsam.BetweenFactorSL4(key_a, key_b, Z_a_b, noise)

    def _prior_factor(self, key: int, Z: gtsam.SL4, noise: Any) -> gtsam.PriorFactorSL4:
        return gtsam.PriorFactorSL4(key, Z, noise)

    def _equality_factor(self, key: int, value: gtsam.SL4) -> gtsam.NonlinearEqualitySL4:
        return gtsam.NonlinearEqualitySL4(key, value)

    def estimate_matrices(self, final: bool = False, nodes: Sequence[int] | None = None) -> np.ndarray:
        """``(N, 4, 4)`` every node's estimate in insertion order (or those of ``nodes``, in that
        order), as GTSAM holds it (det 1): the fast form of :meth:`estimates` (``final``:
        :meth:`final_estimates`) for graphs of thousands of nodes, without a per-node normalization."""
        if final and (self._pending_factors.size() or self._pending_values.size()):
            self.update()
        values = self._best_estimate()
        if final and values.size():
            values = self.polished_values(start=values)
        keys = [self.key(node) for node in (self._order if nodes is None else nodes)]
        return np.array([(self._pending_values if self._pending_values.exists(key) else values).atSL4(key).matrix()
                         for key in keys], dtype=np.float64).reshape(-1, 4, 4)
