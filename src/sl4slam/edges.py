"""What every edge must satisfy before it reaches the graph, and how edges are reported.

A relative measurement from a model that failed (degenerate frames, garbage weights, a black or
blurred window) must never reach GTSAM, where it can make the system indeterminate, and must never
end a run. :func:`edge_problem` and :func:`camera_problem` name what is wrong; the pipeline then
falls back to the shared frame's camera edge, and if that is unusable too, starts a new map
segment (see ``sl4slam.pipeline``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .types import Alignment, FrameView


@dataclass
class EdgeReport:
    """One relative measurement, added to the graph or not.

    Attributes:
        kind: "odometry", "loop" or "segment" (a submap that starts a new map segment).
        submap_from, submap_to: the older and the newer submap.
        frame_index: the frame whose two reconstructions were aligned (the shared frame, or the loop frame).
        model: the model that measured it ("sl4", "calibration" for the calibration-and-scale link
            of the frame's cameras (an SL(4) map), "sim3", or "" when nothing was measured).
        inlier_ratio, rms, num_points: the alignment's quality (0 when nothing was measured).
        fallback: why a weaker model replaced the requested one, or ``None``.
        query_frame: for loops, the new keyframe that retrieval matched with ``frame_index``.
        accepted: whether it reached the graph; reason: why not (or why a segment started).
        checks: figures behind a loop's verdict.
    """

    kind: str
    submap_from: int
    submap_to: int
    frame_index: int
    model: str = ""
    inlier_ratio: float = 0.0
    rms: float = 0.0
    num_points: int = 0
    fallback: str | None = None
    query_frame: int | None = None
    accepted: bool = True
    reason: str | None = None
    checks: dict = field(default_factory=dict)

    @classmethod
    def measured(cls, kind: str, a: int, b: int, frame_index: int, alignment: Alignment, **kwargs) -> "EdgeReport":
        model = "calibration" if alignment.extras.get("method") == "calibration_scale" else alignment.model
        return cls(kind=kind, submap_from=a, submap_to=b, frame_index=frame_index, model=model,
                   inlier_ratio=float(alignment.inlier_ratio), rms=float(alignment.rms),
                   num_points=int(alignment.inliers.size), fallback=alignment.fallback, **kwargs)

    def as_dict(self) -> dict:
        """JSON-ready summary entry."""
        out = {"kind": self.kind, "submaps": [self.submap_from, self.submap_to], "frame": self.frame_index,
               "query_frame": self.query_frame, "model": self.model, "inlier_ratio": round(self.inlier_ratio, 4),
               "rms": round(self.rms, 6), "points": self.num_points, "accepted": self.accepted}
        if self.fallback:
            out["fallback"] = self.fallback
        if self.reason:
            out["reason"] = self.reason
        if self.checks:
            out["checks"] = {k: round(float(v), 4) for k, v in self.checks.items()}
        return out


def camera_problem(view: FrameView) -> str | None:
    """Why a frontend camera cannot be used (non-finite, non-positive focal lengths, improper
    rotation), or ``None``."""
    K, T = np.asarray(view.K, dtype=np.float64), np.asarray(view.T_cam_submap, dtype=np.float64)
    if not (np.isfinite(K).all() and np.isfinite(T).all()):
        return "the frontend's camera is not finite"
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        return f"the frontend predicted a non-positive focal length ({K[0, 0]:.3g}, {K[1, 1]:.3g} px)"
    if abs(np.linalg.det(T[:3, :3]) - 1.0) > 1e-3:
        return "the frontend's camera rotation is not a rotation"
    return None


def is_camera_link(alignment: Alignment) -> bool:
    """Whether an edge was measured by the frame's cameras and depth ratio (the calibration-and-scale
    link or the shared-frame similarity), not by a point fit."""
    return alignment.extras.get("method") in ("calibration_scale", "shared_frame")


def edge_problem(alignment: Alignment, config: Any, fitted: bool = True) -> str | None:
    """Why a measured edge must not reach the graph, or ``None``.

    ``config`` is the ``[alignment]`` section (``sl4slam.alignment.settings.AlignmentConfig``).

    Every edge: finite, orientation-preserving (det > 0: a projective map with det < 0 has no
    SL(4) representative), condition number at most ``config.max_condition``. A fitted edge (not a
    camera link, :func:`is_camera_link`) also needs ``config.min_inliers`` inliers and
    ``config.min_inlier_ratio`` of the points.
    """
    H = np.asarray(alignment.H, dtype=np.float64)
    if H.shape != (4, 4) or not np.isfinite(H).all():
        return "the measured transform is not finite"
    det = np.linalg.det(H)
    if not det > 1e-12 * np.abs(H).max() ** 4:
        return "the measured transform reverses orientation or is singular (det <= 0)"
    condition = np.linalg.cond(H)
    if not condition <= config.max_condition:
        return f"the measured transform is ill-conditioned (condition number {condition:.3g} > {config.max_condition:.3g})"
    if fitted and not is_camera_link(alignment):
        count = alignment.num_inliers
        if count < config.min_inliers:
            return f"only {count} inliers (< {config.min_inliers})"
        if alignment.inlier_ratio < config.min_inlier_ratio:
            return f"it explains only {100 * alignment.inlier_ratio:.2f} % of the points (< {100 * config.min_inlier_ratio:g} %)"
    return None
