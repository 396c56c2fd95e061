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
  their intrinsics and the median depth ratio, as an SL(4) map, for every frame (no point fit);
- :class:`HybridAligner` (``"hybrid"``): that link, or the 15-DOF fit where the points show a relative
  projective distortion well beyond what depth errors explain;
- :class:`SelectAligner` (``"select"``): that link or the 15-DOF fit, whichever predicts held-out
  shared points better (``sl4slam.alignment.select``).

Consecutive submaps may share several frames (``SubmapConfig.overlap``): :meth:`PointAligner.align_frames`
makes one link of them all (``sl4slam.alignment.shared``).

Any of them offers :meth:`~sl4slam.types.Aligner.camera_edge`, the camera-and-depth measurement
the pipeline falls back to when a fit fails (with an inflated sigma).
"""

from __future__ import annotations

from abc import abstractmethod
from typing import ClassVar, Sequence

import numpy as np

from .settings import AlignmentConfig
from ..edges import is_camera_link
from ..registry import AlignerEntry, aligner_entry
from ..types import Aligner, Alignment, FrameView
from .camera_constrained import camera_constrained_sl4
from .select import choose_link
from .shared import link_from_shared_frames
from .ransac import estimate_sim3, estimate_sl4, relief, transfer_errors
from .sim3 import calibration_scale_link, sim3_from_shared_frame


def shared_pixels(view_a: FrameView, view_b: FrameView, limit: int) -> np.ndarray:
    """Flat indices of the pixels confident in both views, evenly strided down to ``limit`` (0: all)."""
    both = np.flatnonzero(view_a.mask & view_b.mask)
    if limit > 0 and len(both) > limit:
        both = both[:: -(-len(both) // limit)]  # evenly strided over the frame
    return both


class PointAligner(Aligner):
    """Shared part of the aligners: pixel selection, several shared frames and the camera edge.

    Attributes:
        fits_points: the model is fitted to the points (several frames' points are then fitted
            together); otherwise it reads the frame's cameras (several frames' links are averaged).
        description: one line on what the model measures (its catalog entry's).
        projective: its links may be 15-DOF fits (``sl4slam.registry.AlignerEntry.projective``).
    """

    fits_points: bool = True
    description: ClassVar[str] = ""
    projective: ClassVar[bool] = False

    def __init__(self, config: AlignmentConfig) -> None:
        self.config = config

    @classmethod
    def registry_entry(cls) -> AlignerEntry:
        """This model in the catalog (``sl4slam.registry``): built from the run's ``[alignment]`` section."""
        return AlignerEntry(name=cls.model, build=lambda resolved: cls(resolved.config.alignment),
                            description=cls.description, group=cls.group, projective=cls.projective)

    def align_frames(self, pairs: Sequence[tuple[FrameView, FrameView]], seed: int) -> Alignment:
        """One link from several shared frames, robust to a frame with bad depth
        (``sl4slam.alignment.shared``)."""
        return link_from_shared_frames(self, pairs, seed)

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
        X_a, X_b = self._scale_pairs(view_a, view_b)
        edge = sim3_from_shared_frame(view_a.T_cam_submap, view_b.T_cam_submap, X_a, X_b,
                                      self.config.inlier_threshold)
        edge.extras["camera_edge"] = True
        return edge

    def _scale_pairs(self, view_a: FrameView, view_b: FrameView) -> tuple[np.ndarray, np.ndarray]:
        """Point pairs that vote on a camera link's scale: the shared confident pixels, or every
        pixel when fewer than ``min_points`` are confident in both."""
        limit = int(self.config.max_correspondences)
        pixels = shared_pixels(view_a, view_b, limit)
        if len(pixels) < self.config.min_points:  # no confident overlap: every pixel votes on the scale
            everywhere = np.ones_like(view_a.mask)
            pixels = shared_pixels(FrameView(view_a.points, everywhere, view_a.K, view_a.T_cam_submap),
                                   FrameView(view_b.points, everywhere, view_b.K, view_b.T_cam_submap), limit)
        return view_a.points.reshape(-1, 3)[pixels], view_b.points.reshape(-1, 3)[pixels]


class SL4Aligner(PointAligner):
    """15-DOF projective alignment (paper 4.2), with constrained models where the points cannot
    determine it.

    The 15-DOF fit needs three-dimensional structure well beyond the model's depth errors: a frame
    whose points are nearly coplanar (``planarity < planarity_threshold``) or whose relief off its
    best plane is small against its depth (``relief < min_relief``: a warped floor looks 3-D to
    the planarity test, and RANSAC then turns the warp into a projective error) is degenerate, and
    ``planar_model`` measures it instead: the calibration-and-scale link of the frame's two cameras
    (:func:`calibration_scale_link`), or the camera-constrained projective fit. On nearly planar
    frames (``planarity < near_planar_threshold``) the camera-constrained fit competes with RANSAC,
    which may settle on the dominant plane. Every such choice is reported as a fallback.
    """

    model = "sl4"
    group = "sl4"
    description = "15-DOF projective fit of the shared frames' points, DLT in RANSAC (the paper's)"
    projective = True

    def camera_edge(self, view_a: FrameView, view_b: FrameView) -> Alignment:
        """The calibration-and-scale link of the frame's two cameras (no point fit)."""
        X_a, X_b = self._scale_pairs(view_a, view_b)
        edge = calibration_scale_link(view_a.K, view_a.T_cam_submap, view_b.K, view_b.T_cam_submap, X_a, X_b,
                                      self.config.inlier_threshold)
        edge.extras["camera_edge"] = True
        return edge

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        cfg = self.config
        low = relief(X_b, view_b.centre, cfg.max_points)
        if low < cfg.min_relief:
            return self._flagged(self._degenerate(
                X_a, X_b, view_a, view_b, seed, f"shared frame nearly flat against its depth errors (relief {low:.3g} < {cfg.min_relief})"))
        alignment = estimate_sl4(X_a, X_b, cfg, seed=seed)
        if alignment.fallback is not None:
            return self._flagged(self._degenerate(X_a, X_b, view_a, view_b, seed, alignment.fallback, alignment))
        flatness = alignment.extras.get("planarity", 1.0)
        if flatness >= cfg.near_planar_threshold:
            return alignment
        # RANSAC may have settled on the dominant plane and called the rest outliers: the frame's
        # cameras constrain what the plane leaves free; keep that fit when it explains more points.
        constrained = camera_constrained_sl4(X_a, X_b, view_a.camera, view_b.camera, alignment.H, cfg)
        if constrained is not None and constrained.num_inliers > alignment.num_inliers:
            constrained.fallback = (f"nearly planar shared frame (planarity {flatness:.3g}): the camera-constrained fit "
                                    f"explains more points ({constrained.inlier_ratio:.3f} vs {alignment.inlier_ratio:.3f})")
            return constrained
        return alignment

    @staticmethod
    def _flagged(alignment: Alignment) -> Alignment:
        """``alignment`` marked as the measurement of a degenerate frame (``extras["degenerate"]``)."""
        alignment.extras["degenerate"] = True
        return alignment

    def _degenerate(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int, why: str,
                    stand_in: Alignment | None = None) -> Alignment:
        """The ``planar_model`` measurement of a degenerate frame (``why`` says what made it so)."""
        if self.config.planar_model == "calibration-scale":
            link = self.camera_edge(view_a, view_b)
            link.fallback = f"{why}; used the calibration-and-scale link of the frame's cameras"
            return link
        # the particular solution nearest to the RANSAC fit, or else to the cameras' own link (which
        # keeps the shared camera already); on a plane the least perspective member is taken anyway
        link = self.camera_edge(view_a, view_b)
        margin = self.config.planar_support_margin
        if self.config.planar_model == "by-support" and margin * link.inlier_ratio > 1.0:
            # no fit can explain margin times the link's share of the points: the link, unmeasured
            link.fallback = f"{why}; used the calibration-and-scale link of the frame's cameras"
            return link
        guess = stand_in.H if stand_in is not None else link.H
        constrained = camera_constrained_sl4(X_a, X_b, view_a.camera, view_b.camera, guess, self.config)
        if self.config.planar_model == "by-support":
            if (constrained is None or constrained.inlier_ratio < margin * link.inlier_ratio
                    or constrained.inlier_ratio < self.config.planar_fit_min_inlier_ratio):
                link.fallback = f"{why}; used the calibration-and-scale link of the frame's cameras"
                return link
            constrained.fallback = (f"{why}; used the camera-constrained projective fit (it explains "
                                    f"{constrained.inlier_ratio:.3f} of the points, the camera link {link.inlier_ratio:.3f})")
            return constrained
        if constrained is not None and (stand_in is None or constrained.inlier_ratio >= stand_in.inlier_ratio):
            constrained.fallback = f"{why}; used the camera-constrained projective fit"
            return constrained
        if stand_in is not None:
            return stand_in
        link.fallback = f"{why}; used the calibration-and-scale link of the frame's cameras"
        return link


class Sim3PointAligner(PointAligner):
    """7-DOF similarity by Umeyama in RANSAC on the shared frame's points."""

    model = "sim3-points"
    group = "sim3"
    description = "7-DOF similarity of the shared frames' points, Umeyama in RANSAC"

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        return estimate_sim3(X_a, X_b, self.config, seed=seed)


class Sim3CameraAligner(PointAligner):
    """7-DOF similarity from the shared frame's two cameras and its median depth ratio."""

    model = "sim3-cameras"
    group = "sim3"
    fits_points = False
    description = "7-DOF similarity from the shared frames' two cameras and their median depth ratio"

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        return sim3_from_shared_frame(view_a.T_cam_submap, view_b.T_cam_submap, X_a, X_b, self.config.inlier_threshold)


class CalibrationAligner(SL4Aligner):
    """The shared frame's calibration-and-scale link for every edge (VGGT-SLAM 2.0): its two cameras,
    their intrinsics and the median depth ratio (:func:`calibration_scale_link`), never a point fit."""

    model = "calibration"
    fits_points = False
    description = "the shared frames' cameras, intrinsics and median depth ratio as an SL(4) map (VGGT-SLAM 2.0's)"
    projective = False

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        return calibration_scale_link(view_a.K, view_a.T_cam_submap, view_b.K, view_b.T_cam_submap, X_a, X_b,
                                      self.config.inlier_threshold)


class HybridAligner(SL4Aligner):
    """The calibration-and-scale link, unless the 15-DOF fit explains the shared frame markedly better.

    Both are measured on the shared frame. The link trusts the two cameras for all but the scale, so
    what it leaves unexplained is the depth error of the two reconstructions plus any relative
    projective distortion; the 15-DOF fit also absorbs smooth depth warps as a projective error,
    which then drifts from link to link. The fit replaces the link only where the points show a
    distortion well beyond that: its median transfer error must be ``hybrid_margin`` times smaller
    than the link's. A degenerate or nearly planar frame always gets the link, never the
    camera-constrained fit (``planar_model`` is not consulted); the link is then this model's own
    choice, not a fallback (``extras["degenerate"]`` says why). Decisions:
    docs/decisions/select-link.md, docs/decisions/planar-frames.md.
    ``Alignment.extras["hybrid_ratio"]`` records the ratio.
    """

    model = "hybrid"
    description = "the calibration link, or the 15-DOF fit where it explains the shared frame markedly better"

    def _degenerate(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int, why: str,
                    stand_in: Alignment | None = None) -> Alignment:
        link = self.camera_edge(view_a, view_b)
        link.fallback = why
        return link

    def fit(self, X_a: np.ndarray, X_b: np.ndarray, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        fitted = super().fit(X_a, X_b, view_a, view_b, seed)
        if fitted.fallback is not None:  # degenerate or nearly planar: the link
            link = fitted if is_camera_link(fitted) else self.camera_edge(view_a, view_b)
            link.extras["degenerate"], link.fallback = fitted.fallback, None
            return link
        link = calibration_scale_link(view_a.K, view_a.T_cam_submap, view_b.K, view_b.T_cam_submap, X_a, X_b,
                                      self.config.inlier_threshold)
        sample = slice(None, None, max(1, len(X_b) // self.config.max_points))
        errors = [np.median(transfer_errors(H[None], X_a[sample], X_b[sample])[0][0]) for H in (link.H, fitted.H)]
        ratio = float(np.sqrt(errors[0] / max(errors[1], 1e-30)))
        chosen = fitted if ratio > self.config.hybrid_margin else link
        chosen.extras["hybrid_ratio"] = ratio
        return chosen


class SelectAligner(SL4Aligner):
    """The calibration-and-scale link or the 15-DOF fit, chosen per link by which predicts the
    shared points it was not fitted on better: other shared frames, or the other half of a single
    one (``sl4slam.alignment.select``, where the reasons are). ``Alignment.extras["select"]`` records
    the held-out errors and the choice."""

    model = "select"
    description = "the calibration link or the 15-DOF fit, whichever predicts held-out shared points better"

    def __init__(self, config: AlignmentConfig) -> None:
        super().__init__(config)
        self._fit = SL4Aligner(config)
        self._link = CalibrationAligner(config)

    def align(self, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        return choose_link(self._fit, self._link, [(view_a, view_b)], seed)

    def align_frames(self, pairs: Sequence[tuple[FrameView, FrameView]], seed: int) -> Alignment:
        return choose_link(self._fit, self._link, pairs, seed)


def make_aligner(resolved) -> Aligner:
    """The aligner of a run's settled alignment model, built by its catalog entry (``sl4slam.registry``).

    Args:
        resolved: the run's resolved config (``sl4slam.resolve.ResolvedConfig``).
    """
    return aligner_entry(resolved.alignment.value).build(resolved)
