"""The alignment's settings (``[alignment]``): how two submaps' shared frames measure their link."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ..registry import aligner_entry, aligner_names
from ..section import Section, setting


@dataclass
class AlignmentConfig(Section):
    """Relative alignment of submaps from a shared frame's points (paper 4.2)."""

    section: ClassVar[str] = "alignment"
    flag_prefix: ClassVar[str] = "ransac-"

    model: str = setting("auto", choices=("auto", *aligner_names()), flag='--alignment')
    """What measures the relative transform: "sl4" (15-DOF DLT in RANSAC, the paper), "sim3-points"
    (7-DOF Umeyama in RANSAC on the same points), "sim3-cameras" (the shared frame's two cameras and
    the median depth ratio), "calibration" (VGGT-SLAM 2.0: the shared frame's two cameras, their
    intrinsics and the median depth ratio, no free projective terms; ``calibration_scale_link``),
    "hybrid" (that link, or the 15-DOF fit where it explains the frame ``hybrid_margin`` times
    better), "select" (that link or the 15-DOF fit, whichever predicts the shared frames it was not
    fitted on better: ``sl4slam.alignment.select``; needs two or more shared frames, else the link),
    or "auto": "select" for the keyframe graph, "sl4" for the SL(4) submap graph, "sim3-cameras" for
    the Sim(3) graph. A Sim(3) graph needs a Sim(3) model (decision: docs/decisions/select-link.md)."""
    ransac_iterations: int = setting(300, check=lambda v: v >= 1, allowed="at least 1")
    """Most RANSAC hypotheses (paper: 300, always drawn in full there)."""
    ransac_confidence: float = setting(0.999, check=lambda v: 0 < v < 1, allowed="between 0 and 1 (exclusive)")
    """Stop drawing hypotheses once an all-inlier sample has been drawn with this probability,
    judged from the best hypothesis' inlier fraction (classic adaptive RANSAC; the reference code
    always draws all of them)."""
    inlier_threshold: float = setting(0.01, check=lambda v: v > 0, allowed="a positive distance in submap units")
    """Inlier distance in submap units (paper: 0.01)."""
    max_correspondences: int = setting(30000, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: all)")
    """Pixels of the shared frame passed to the alignment (0: all); beyond this an evenly strided
    subset (decision: docs/decisions/ransac-budget.md)."""
    max_points: int = setting(10000, advanced=True,
                              check=lambda v: v >= 5, allowed="at least 5 (one minimal sample)")
    """Correspondences each hypothesis is scored on; larger sets are subsampled (seeded). The
    final inlier mask is computed on every point."""
    max_refit_points: int = setting(20000, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: all)")
    """Inliers used by each least-squares refit (0: all; an evenly strided subset beyond this)."""
    fit_threads: int = setting(2, advanced=True, flag='--alignment-fit-threads',
                               check=lambda v: v >= 1, allowed="at least 1")
    """Threads on which one link's independent 15-DOF fits (each shared frame's, and all frames'
    together) run at once; 1: one after another. The results do not depend on it
    (``sl4slam.alignment.parallel``); the time does (decision: docs/decisions/fit-threads.md)."""
    min_inliers: int = setting(50, check=lambda v: v >= 5, allowed="at least 5 (one minimal sample)")
    """Fewer inliers than this makes the 15-DOF fit degenerate: use a constrained model instead."""
    planarity_threshold: float = setting(0.02, advanced=True, check=lambda v: 0 <= v < 1, allowed="in [0, 1)")
    """Spread of the points along their thinnest principal axis relative to the widest
    (interdecile ranges, robust to a few off-plane points) below which they count as coplanar:
    the 15-DOF fit is degenerate and a constrained model is used instead."""
    min_relief: float = setting(0.1, advanced=True, check=lambda v: 0 <= v < 1, allowed="in [0, 1)")
    """Relief of the shared frame's points off their best plane (interdecile thickness / median
    distance to the camera, unitless) below which the 15-DOF fit counts as degenerate
    (decision: docs/decisions/planar-frames.md)."""
    hybrid_margin: float = setting(4.0, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """"hybrid" alignment: the 15-DOF fit replaces the calibration-and-scale link when the link's
    median transfer error on the shared frame is more than this many times the fit's
    (decision: docs/decisions/select-link.md)."""
    select_confidence: float = setting(0.95, advanced=True, check=lambda v: 0.5 <= v < 1, allowed="in [0.5, 1)")
    """"select" alignment: with three or more held-out shared frames, the confidence at which the
    15-DOF fit must predict them better than the calibration-and-scale link (one-sided paired t-test
    over the held-out frames, ``sl4slam.alignment.select``); below it the link, the model that
    assumes less, is kept. Two held-out frames are one comparison seen from both sides and face no
    t-test: each must be predicted better (decision: docs/decisions/select-link.md)."""
    select_min_gain: float = setting(2.0, advanced=True,
                                     check=lambda v: v >= 1, allowed="at least 1 (1: the t-test alone)")
    """"select" alignment: the 15-DOF fit must also predict the held-out shared frames at least this
    many times better than the link (geometric mean of the held-out error ratios); 1: the t-test
    alone (decision: docs/decisions/select-link.md)."""
    planar_model: str = setting("by-support", choices=("by-support", "calibration-scale", "camera-constrained"),
                                advanced=True)
    """What measures a degenerate shared frame: "calibration-scale" (its two cameras and depth
    ratio: VGGT-SLAM 2.0's link, immune to depth warps, blind to a relative projective
    distortion), "camera-constrained" (a projective fit whose free part the points choose), or
    "by-support" (called "auto" before): both are measured and the link is kept unless the constrained fit explains
    ``planar_support_margin`` times as many points and nearly all of them
    (``planar_fit_min_inlier_ratio``: a real distortion the link cannot express; decision:
    docs/decisions/planar-frames.md)."""
    planar_support_margin: float = setting(2.5, advanced=True, check=lambda v: v >= 1, allowed=">= 1")
    """"by-support": how many times the link's inliers the camera-constrained fit must explain to win
    (as inlier ratios; decision: docs/decisions/planar-frames.md)."""
    planar_fit_min_inlier_ratio: float = setting(0.97, advanced=True,
                                                 check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """"by-support": the camera-constrained fit wins only if it also explains at least this fraction of
    the points, i.e. the frame really is a projective image of the other
    (decision: docs/decisions/planar-frames.md)."""
    near_planar_threshold: float = setting(0.15, advanced=True)
    """Below this planarity (but above ``planarity_threshold``) the shared frame is dominated by a
    plane, where RANSAC may settle on the plane and call the rest outliers: the camera-constrained
    fit competes and wins when it explains more points (decision: docs/decisions/planar-frames.md)."""
    refit: bool = setting(True, advanced=True)
    """Least-squares refit of H on all inliers, then re-score (the reference code does not)."""
    refit_candidates: int = setting(5, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Hypotheses refitted (the best by MSAC cost); the best refit wins (LO-RANSAC;
    decision: docs/decisions/ransac-budget.md)."""
    seed: int = setting(0, check=lambda v: v >= 0, allowed=">= 0")
    """Seed of the RANSAC sampler (combined with the submap id)."""
    hypothesis_batch: int = setting(50, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Hypotheses drawn, solved and scored together before the adaptive stopping test
    (decision: docs/decisions/ransac-budget.md)."""
    early_stop_spread: float = setting(0.5, advanced=True, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """RANSAC may stop early only if the best hypothesis' inliers keep at least this fraction of
    the points' planarity: one that explains just a dominant plane is the near-degenerate case
    where more samples find the full 15-DOF map."""
    preemptive_points: int = setting(1024, advanced=True, check=lambda v: v >= 5, allowed="at least 5")
    """Correspondences of the preemptive scoring round (every valid hypothesis is scored on them;
    Nister's preemptive RANSAC)."""
    preemptive_keep: float = setting(0.1, advanced=True, check=lambda v: 0 < v <= 1, allowed="in (0, 1]")
    """Fraction of hypotheses (at least ``preemptive_min_keep``) scored on the full subset."""
    preemptive_min_keep: int = setting(8, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Fewest hypotheses that survive the preemptive round."""
    refit_rounds: int = setting(5, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Most refit / re-score rounds after RANSAC; they stop earlier once the inlier set stops
    changing or the cost stops decreasing by more than ``refit_min_gain``."""
    refit_min_gain: float = setting(1e-3, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Relative MSAC cost decrease below which another refit is not worth it
    (decision: docs/decisions/ransac-budget.md)."""
    small_set: int = setting(4096, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Up to this many points, samples are drawn without repetition by permuting all indices."""
    camera_constrained_iterations: int = setting(6, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Reweighting rounds of the camera-constrained fit used for planar shared frames."""
    camera_constrained_ridge: float = setting(1e-6, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Ridge term (relative to the normal matrix's trace) that picks, among the camera-constrained
    maps the plane cannot tell apart, the one nearest the Sim(3) guess."""
    min_points: int = setting(5, advanced=True, flag='--alignment-min-points',
                              check=lambda v: v >= 5, allowed="at least 5")
    """Fewest pixels confident in both submaps for any alignment (the 5-point minimal sample)."""
    min_inlier_ratio: float = setting(0.1, advanced=True, flag='--alignment-min-inlier-ratio',
                                      check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """A fitted edge that explains fewer of the shared pixels is not trusted (a model that failed);
    the shared frame's camera edge takes its place (decision: docs/decisions/alignment-checks.md)."""
    max_condition: float = setting(1e4, advanced=True, flag='--alignment-max-condition',
                                   check=lambda v: v > 1, allowed="greater than 1")
    """Largest condition number of a measured 4x4 transform; beyond it the fit counts as
    degenerate (decision: docs/decisions/alignment-checks.md)."""
    weight_reference_frame: bool = setting(True, advanced=True, flag='--alignment-weight-reference-frame')
    """Where several shared frames' camera links are averaged, weigh each by the inverse of the pose
    errors it carries: a frame that is its submap's reference (the first camera, ``[I | 0]`` by
    construction in VGGT) has none there, so the new submap's first shared frame counts twice
    (``sl4slam.alignment.shared.pose_error_weights``). Off: the plain mean
    (decision: docs/decisions/shared-frames.md)."""

    def setup(self, resolved: Any) -> Any:
        """The aligner of the settled ``model``, built by its catalog entry (``sl4slam.registry``).

        Args:
            resolved: the run's resolved config (``sl4slam.resolve.ResolvedConfig``), whose tree
                holds this section.
        """
        return aligner_entry(self.model).build(resolved)

    def validate(self) -> None:
        super().validate()
        self._require("near_planar_threshold", self.planarity_threshold <= self.near_planar_threshold <= 1,
                      "between --ransac-planarity-threshold and 1")
