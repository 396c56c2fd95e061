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

import importlib
from typing import Any

_HOMES = {
    "CalibrationAligner": "aligner",
    "HybridAligner": "aligner",
    "SL4Aligner": "aligner",
    "Sim3CameraAligner": "aligner",
    "Sim3PointAligner": "aligner",
    "make_aligner": "aligner",
    "shared_pixels": "aligner",
    "camera_constrained_sl4": "camera_constrained",
    "dlt_design_matrix": "dlt",
    "dlt_sl4": "dlt",
    "minimal_sl4_batch": "dlt",
    "normalize_points": "dlt",
    "estimate_sim3": "ransac",
    "estimate_sl4": "ransac",
    "sim3_from_shared_frame": "sim3",
}
"""Where each name lives: the package imports a module only when one of its names is asked for, so
that its settings (``sl4slam.alignment.settings``) load without the fits."""

__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    if name in _HOMES:
        return getattr(importlib.import_module(f"{__name__}.{_HOMES[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
