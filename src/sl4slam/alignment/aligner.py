"""The alignment stage: an :class:`~sl4slam.types.Aligner` per model, chosen by the config.

Every aligner takes one frame as reconstructed in two submaps (a :class:`~sl4slam.types.FrameView`
each), keeps the pixels confident in both (an evenly strided subset beyond
``AlignmentConfig.max_correspondences``) and fits ``X_a ~ H_a_b X_b``:

- :class:`SL4Aligner` (``model="sl4"``, the paper): 15-DOF DLT in RANSAC; when that fit is
  degenerate (a planar shared frame) the frame's two cameras supply the missing constraints
  (:func:`camera_constrained_sl4`), or the Sim(3) point fit stands in; either way
  ``Alignment.fallback`` says so;
- :class:`Sim3PointAligner` (``"sim3-points"``): 7-DOF Umeyama in RANSAC on the same points;
- :class:`Sim3CameraAligner` (``"sim3-cameras"``): the shared frame's two cameras and the median
  ratio of its depths (no point fit);
- :class:`CalibrationAligner` (``"calibration"``, VGGT-SLAM 2.0): the shared frame's two cameras with
  their intrinsics and the median depth ratio, as an SL(4) map (no point fit).

Any of them offers :meth:`~sl4slam.types.Aligner.camera_edge`, the camera-and-depth measurement
the pipeline falls back to when a fit fails (with an inflated sigma).
"""

from __future__ import annotations

from abc import abstractmethod

import numpy as np

from ..config import AlignmentConfig, SLAMConfig, alignment_model
from ..types import Aligner, Alignment, FrameView
from .calibration import calibration_from_shared_frame
from .camera_constrained import camera_constrained_sl4
from .ransac import estimate_sim3, estimate_sl4
from .sim3 import sim3_from_shared_frame


def shared_pixels(view_a: FrameView, view_b: FrameView, limit: int) -> np.ndarray:
    """Flat indices of the pixels confident in both views, evenly strided down to ``limit`` (0: all)."""
    both = np.flatnonzero(view_a.mask & view_b.mask)
    if limit > 0 and len(both) > limit:
        both = both[:: -(-len(both) // limit)]  # evenly strided over the frame
    return both


class PointAligner(Aligner):
    """Shared part of the aligners: pixel selection and the camera edge."""

    def __init__(self, config: AlignmentConfig) -> None:
        self.config = config

    def pairs(self, view_a: FrameView, view_b: FrameView) -> tuple[np.ndarray, np.ndarray]:
        """``(X_a, X_b)`` ``(N, 3)`` float64 of the shared confident pixels; ``ValueError`` if too few."""
        pixels = shared_pixels(view_a, view_b, int(self.config.max_correspondences))
        if len(pixels) < self.config.min_points:
            raise ValueError(
                f"only {len(pixels)} pixels are confident in both submaps (need {self.config.min_points}); "
                "the frontend's confidence is too low there")
        X_a = view_a.points.reshape(-1, 3)[pixels].astype(np.float64)
        X_b = view_b.points.reshape(-1, 3)[pixels].astype(np.float64)
        return X_a, X_b

    def align(self, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        X_a, X_b = self.pairs(view_a, view_b)
        return self.fit(X_a, X_b, view_a, view_b, seed)

    @abstractmethod
    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        """The model's fit on the shared pixels' points ``(N, 3)`` (the views give the cameras)."""

    def camera_edge(self, view_a: FrameView, view_b: FrameView) -> Alignment:
        """Sim(3) from the frame's two cameras; its depth ratio from the shared confident pixels, or
        from every pixel when fewer than ``min_points`` are confident in both."""
        limit = int(self.config.max_correspondences)
        pixels = shared_pixels(view_a, view_b, limit)
        if len(pixels) < self.config.min_points:  # no confident overlap: every pixel votes on the scale
            everywhere = np.ones_like(view_a.mask)
            pixels = shared_pixels(FrameView(view_a.points, everywhere, view_a.K, view_a.T_cam_submap),
                                   FrameView(view_b.points, everywhere, view_b.K, view_b.T_cam_submap), limit)
        X_a = view_a.points.reshape(-1, 3)[pixels]
        X_b = view_b.points.reshape(-1, 3)[pixels]
        edge = sim3_from_shared_frame(view_a.T_cam_submap, view_b.T_cam_submap, X_a, X_b,
                                      self.config.inlier_threshold)
        edge.extras["camera_edge"] = True
        return edge


class SL4Aligner(PointAligner):
    """15-DOF projective alignment (paper 4.2) with the camera-constrained fit for degenerate scenes."""

    model = "sl4"
    group = "sl4"

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        alignment = estimate_sl4(X_a, X_b, self.config, seed=seed)
        if alignment.fallback is None:
            return alignment
        # Degenerate 15-DOF fit (e.g. a planar shared frame): the frame's two cameras supply the
        # constraints the points lack; keep it when it explains at least as many points.
        constrained = camera_constrained_sl4(X_a, X_b, view_a.camera, view_b.camera, alignment.H, self.config)
        if constrained is not None and constrained.inlier_ratio >= alignment.inlier_ratio:
            constrained.fallback = f"{alignment.fallback}; used the camera-constrained projective fit"
            return constrained
        return alignment


class Sim3PointAligner(PointAligner):
    """7-DOF similarity by Umeyama in RANSAC on the shared frame's points."""

    model = "sim3-points"
    group = "sim3"

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        return estimate_sim3(X_a, X_b, self.config, seed=seed)


class Sim3CameraAligner(PointAligner):
    """7-DOF similarity from the shared frame's two cameras and its median depth ratio."""

    model = "sim3-cameras"
    group = "sim3"

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        return sim3_from_shared_frame(view_a.T_cam_submap, view_b.T_cam_submap, X_a, X_b, self.config.inlier_threshold)


class CalibrationAligner(PointAligner):
    """The shared frame's calibration-and-scale link (VGGT-SLAM 2.0; ``sl4slam.alignment.calibration``)."""

    model = "calibration"
    group = "sl4"

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        return calibration_from_shared_frame(view_a, view_b, X_a, X_b, self.config.inlier_threshold)


ALIGNERS: dict[str, type[PointAligner]] = {
    "sl4": SL4Aligner, "calibration": CalibrationAligner, "sim3-points": Sim3PointAligner,
    "sim3-cameras": Sim3CameraAligner}


def make_aligner(config: SLAMConfig) -> Aligner:
    """The aligner of ``config.alignment.model`` ("auto": the one that fits ``config.backend.kind``)."""
    return ALIGNERS[alignment_model(config)](config.alignment)
