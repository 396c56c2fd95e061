"""Relative alignment of submaps from a shared frame's points (paper 4.2).

- :func:`estimate_sl4`: 15-DOF projective ``H_a_b`` (SL(4)) by 5-point DLT in RANSAC, with a
  Sim(3) fallback when the projective fit is degenerate.
- :func:`estimate_sim3`: 7-DOF similarity by 3-point Umeyama in RANSAC.
- :func:`sim3_from_shared_frame`: similarity from the shared frame's two extrinsics and the
  median depth ratio of its points.
- :func:`camera_constrained_sl4`: projective fit constrained by the shared frame's cameras, for
  planar scenes where the 15-DOF point fit is degenerate.
- :func:`dlt_sl4` / :func:`minimal_sl4_batch`: the least-squares and batched minimal DLT solvers.
"""

from .camera_constrained import camera_constrained_sl4
from .dlt import dlt_design_matrix, dlt_sl4, minimal_sl4_batch, normalize_points
from .ransac import estimate_sim3, estimate_sl4
from .sim3 import sim3_from_shared_frame, umeyama_sim3_batch

__all__ = [
    "camera_constrained_sl4",
    "dlt_design_matrix",
    "dlt_sl4",
    "estimate_sim3",
    "estimate_sl4",
    "minimal_sl4_batch",
    "normalize_points",
    "sim3_from_shared_frame",
    "umeyama_sim3_batch",
]
