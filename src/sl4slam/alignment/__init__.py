"""Relative alignment of submaps from a shared frame's points (paper 4.2).

- :func:`make_aligner`: the pipeline's alignment stage, by the resolved ``AlignmentConfig.model``:
  :class:`SL4Aligner` ("sl4", the paper's 15-DOF fit), :class:`CalibrationAligner` ("calibration",
  VGGT-SLAM 2.0's link of the shared frame's two cameras; the keyframe graph's default),
  :class:`HybridAligner` ("hybrid": that link, or the 15-DOF fit where it explains the frame
  markedly better), :class:`Sim3PointAligner` ("sim3-points") and :class:`Sim3CameraAligner`
  ("sim3-cameras", the Sim(3) graph's default).
- :func:`estimate_sl4`: 15-DOF projective ``H_a_b`` (SL(4)) by 5-point DLT in RANSAC, with a
  Sim(3) fallback when the projective fit is degenerate.
- :func:`estimate_sim3`: 7-DOF similarity by 3-point Umeyama in RANSAC.
- :func:`sim3_from_shared_frame`: similarity from the shared frame's two extrinsics and the
  median depth ratio of its points.
- :func:`camera_constrained_sl4`: projective fit constrained by the shared frame's cameras, for
  planar scenes where the 15-DOF point fit is degenerate.
- :func:`dlt_sl4` / :func:`minimal_sl4_batch`: the least-squares and batched minimal DLT solvers.
"""

from .aligner import CalibrationAligner, HybridAligner, SL4Aligner, Sim3CameraAligner, Sim3PointAligner, make_aligner, shared_pixels
from .camera_constrained import camera_constrained_sl4
from .dlt import dlt_design_matrix, dlt_sl4, minimal_sl4_batch, normalize_points
from .ransac import estimate_sim3, estimate_sl4
from .sim3 import sim3_from_shared_frame

__all__ = [
    "CalibrationAligner",
    "HybridAligner",
    "SL4Aligner",

    "Sim3CameraAligner",
    "Sim3PointAligner",
    "make_aligner",
    "shared_pixels",
    "camera_constrained_sl4",
    "dlt_design_matrix",
    "dlt_sl4",
    "estimate_sim3",
    "estimate_sl4",
    "minimal_sl4_batch",
    "normalize_points",
    "sim3_from_shared_frame",
]
