"""Loop-closure verification: which retrieved loops may reach the graph.

A retrieved loop frame is re-reconstructed inside the new submap next to the query keyframe that
retrieval matched it with; its points there and its stored points in its old submap give the loop
measurement ``H_old_new``. That alignment alone cannot tell a wrong place: it compares two
reconstructions of the *same image*, which agree (inlier ratios near 1) whatever the model made of
the place. Independent checks therefore stand between a candidate and the graph, each with a
reason the run summary lists:

0. **Attention** (VGGT-SLAM 2.0; ``LoopConfig.verify_attention``). The frontend, given the query
   keyframe and the loop frame together, scores how strongly the second image's tokens attend to
   the first's (``sl4slam.models.vggt.attention``; with the simulated frontend a stand-in computed
   from the true overlap, ``sl4slam.frontend.overlap``); below ``min_match_ratio`` the images are
   taken not to overlap. A frontend that gave no score (a replayed cache recorded without the check)
   skips this check, which the decision's figures show by the missing ``match_ratio``.
1. **Alignment.** The loop frame's two reconstructions (with the keyframes appended next to it,
   ``SubmapConfig.loop_frames``, one link of them all as between consecutive submaps, so the
   "select" link can choose the 15-DOF fit for a loop too) must align with the model the graph uses
   (a constrained model of that group for a degenerate frame, never a weaker stand-in), a point fit
   keeping ``LoopConfig.min_inlier_ratio`` of the points (or half the odometry's median, when the
   model fits consecutive submaps worse than that), and pass the same edge checks as odometry
   (finite, orientation-preserving, conditioned). A link from the frame's cameras (no point fit) is
   judged by the view and graph checks alone.
2. **Views** (:func:`view_agreement`). Inside the new submap, the loop frame's confident points are
   projected into the query keyframe: enough of them must land in its image in front of the camera
   (overlap), agree with its own depth (consistency), and the two images must look alike there
   (normalized cross-correlation of slightly blurred grey values, which ignores exposure). A model
   given two images of different places still places both cameras somewhere; what it cannot do is
   make one image's surfaces reproject onto the other's with matching depth and appearance.
3. **Graph** (``Backend.loop_chi2``). The loop measurement is compared with the current map: the
   squared Mahalanobis distance of its factor's error under the joint covariance of its two nodes
   plus its own noise must stay below the chi-square quantile ``LoopConfig.consistency_quantile``.
   A true revisit disagrees with the map by its drift, which the odometry's covariance accounts for;
   a wrong place disagrees by the distance between the places.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Sequence

import cv2
import numpy as np

from .alignment.settings import AlignmentConfig
from .edges import edge_problem, is_camera_link
from .section import Section, setting
from .types import Aligner, Alignment, FrameView

if TYPE_CHECKING:
    from .alignment.parallel import Pending


@dataclass
class LoopConfig(Section):
    """Which retrieved loops reach the graph (``sl4slam.loops``): one false loop bends the whole map."""

    section: ClassVar[str] = "loops"
    builds: ClassVar[str] = "sl4slam.loops:LoopVerifier"
    flag_prefix: ClassVar[str] = "loop-"

    min_inlier_ratio: float = setting(0.3, check=lambda v: 0 < v <= 1, allowed="in (0, 1]")
    """The loop frame's own alignment (its points in the old and the new submap) must keep this
    inlier fraction (or half the odometry's median, if that is lower) without a fallback."""
    verify_attention: str = setting("auto", choices=("auto", "on", "off"))
    """Check, before anything else, that the frontend's attention says the query keyframe and the loop
    frame overlap (VGGT-SLAM 2.0's image-match ratio, ``sl4slam.models.vggt.attention``; the simulated
    frontend's stand-in is the true overlap, ``sl4slam.frontend.overlap``): "on", "off", or "auto"
    (on with the keyframe graph, as in VGGT-SLAM 2.0; off with the submap graph, as in VGGT-SLAM)."""
    min_match_ratio: float = setting(0.85, check=lambda v: v >= 0, allowed=">= 0")
    """Attention check: image-match ratio from which a loop is kept (VGGT-SLAM 2.0 reference code: 0.85)."""
    verify_view: bool = True
    """Check inside the new submap that the query keyframe and the loop frame see the same surfaces:
    the loop frame's points, projected into the query keyframe, must land in its image, agree with
    its depth and look alike (the loop frame's alignment compares two reconstructions of one image,
    so it cannot tell a wrong place)."""
    check_points: int = setting(4000, advanced=True, check=lambda v: v >= 100, allowed="at least 100")
    """Pixels of the loop frame used by the view check (an evenly strided subset)."""
    min_overlap: float = setting(0.15, advanced=True, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """View check: fraction of the loop frame's confident pixels that must project into the query
    keyframe's image in front of its camera."""
    depth_tolerance: float = setting(0.1, advanced=True,
                                     check=lambda v: v > 0, allowed="a positive relative depth difference")
    """View check: relative depth difference under which a projected point agrees with the query
    keyframe's own depth."""
    min_consistent: float = setting(0.3, advanced=True, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """View check: fraction of the overlapping points whose depth must agree."""
    min_correlation: float = setting(0.3, advanced=True, check=lambda v: -1 <= v <= 1, allowed="in [-1, 1]")
    """View check: normalized cross-correlation of the grey values of the depth-consistent points in
    the two images (exposure-invariant); unrelated textures score about 0."""
    verify_graph: bool = True
    """Check that the loop agrees with the current graph: chi-square test of the loop factor's
    whitened error under the joint covariance of its two nodes and the loop's own noise."""
    consistency_quantile: float = setting(0.999, advanced=True, check=lambda v: 0 < v < 1, allowed="in (0, 1)")
    """Chi-square quantile of that test (15 degrees of freedom for SL(4), 7 for Sim(3))."""

BLUR_FRACTION = 0.01
"""Gaussian blur sigma of the view check's grey images, as a fraction of the image width: the
projected points land a few pixels off under realistic pose errors, and fine texture would then
decorrelate even on a true revisit."""
MIN_CORRELATION_POINTS = 30
"""Fewest depth-consistent points on which the correlation is computed (fewer: no agreement)."""


@dataclass
class LoopDecision:
    """Verdict on one loop candidate.

    Attributes:
        accepted: whether it reaches the graph.
        reason: why it was rejected (``None`` when accepted).
        alignment: the loop frame's alignment (``None`` if it failed).
        information: ``(dim, dim)`` of the edge, when it got that far.
        checks: the figures behind the verdict (inlier ratio, overlap, consistency, correlation, chi2).
    """

    accepted: bool
    reason: str | None = None
    alignment: Alignment | None = None
    information: np.ndarray | None = None
    checks: dict = field(default_factory=dict)


def grey_for_check(colors: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 grey image, blurred by ``BLUR_FRACTION`` of its width, from ``(H, W, 3)`` uint8."""
    grey = cv2.cvtColor(np.ascontiguousarray(colors, dtype=np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32)
    sigma = max(1.0, BLUR_FRACTION * grey.shape[1])
    return cv2.GaussianBlur(grey, (0, 0), sigma)


def view_agreement(
    X: np.ndarray,
    grey_X: np.ndarray,
    depth: np.ndarray,
    mask: np.ndarray,
    grey: np.ndarray,
    K: np.ndarray,
    T_cam_submap: np.ndarray,
    depth_tolerance: float,
) -> dict:
    """How well points of one frame reproject into another frame of the same submap.

    Args:
        X: ``(n, 3)`` points of the first frame, in the submap frame.
        grey_X: ``(n,)`` their grey values in the first frame's image.
        depth: ``(H, W)`` the second frame's depth; mask: ``(H, W)`` its confident pixels;
            grey: ``(H, W)`` its grey image.
        K, T_cam_submap: the second frame's intrinsics ``(3, 3)`` and extrinsics ``(4, 4)``.
        depth_tolerance: relative depth difference under which a point agrees.

    Returns:
        ``{"overlap": fraction of the points in the second image in front of its camera,
        "consistent": fraction of those that hit a confident pixel of about their own depth,
        "correlation": normalized cross-correlation of the grey values at the consistent points
        (0 when fewer than MIN_CORRELATION_POINTS)}``.
    """
    height, width = depth.shape
    X_cam = X @ T_cam_submap[:3, :3].T + T_cam_submap[:3, 3]
    z = X_cam[:, 2]
    in_front = z > 1e-9
    uvw = X_cam @ np.asarray(K, dtype=np.float64).T
    u = np.where(in_front, uvw[:, 0] / np.where(in_front, uvw[:, 2], 1.0), -1.0)
    v = np.where(in_front, uvw[:, 1] / np.where(in_front, uvw[:, 2], 1.0), -1.0)
    column, row = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    inside = in_front & (column >= 0) & (column < width) & (row >= 0) & (row < height)
    column, row = column[inside], row[inside]
    measured = depth[row, column].astype(np.float64)
    agree = mask[row, column] & (np.abs(z[inside] - measured) <= depth_tolerance * measured)
    overlap = float(inside.mean()) if len(X) else 0.0
    consistent = float(agree.mean()) if len(agree) else 0.0
    correlation = 0.0
    if agree.sum() >= MIN_CORRELATION_POINTS:
        a = grey_X[inside][agree].astype(np.float64)
        b = grey[row[agree], column[agree]].astype(np.float64)
        a, b = a - a.mean(), b - b.mean()
        denominator = np.sqrt((a * a).sum() * (b * b).sum())
        correlation = float((a * b).sum() / denominator) if denominator > 0 else 0.0
    return {"overlap": overlap, "consistent": consistent, "correlation": correlation}


def chi2_threshold(config: LoopConfig, dim: int) -> float:
    """The graph check's bound on the squared Mahalanobis distance (``dim`` degrees of freedom)."""
    from scipy.stats import chi2

    return float(chi2.ppf(config.consistency_quantile, dim))


def check_view(config: LoopConfig, agreement: dict) -> str | None:
    """Reason the view check fails, or ``None``."""
    if agreement["overlap"] < config.min_overlap:
        return f"the loop frame does not face the query keyframe (overlap {agreement['overlap']:.2f} < {config.min_overlap})"
    if agreement["consistent"] < config.min_consistent:
        return (f"the loop frame's depth disagrees with the query keyframe's "
                f"(consistent {agreement['consistent']:.2f} < {config.min_consistent})")
    if agreement["correlation"] < config.min_correlation:
        return (f"the loop frame does not look like the query keyframe where they overlap "
                f"(correlation {agreement['correlation']:.2f} < {config.min_correlation})")
    return None


@dataclass
class LoopEvidence:
    """What the new submap says about one loop candidate.

    Attributes:
        pairs: ``(old, new)`` views of every frame the loop is measured on, each as stored in its old
            submap and as reconstructed in the new one: the loop frame first, then the keyframes of
            the same old submap appended with it (``SubmapConfig.loop_frames``).
        grey_new: ``(H, W)`` the loop frame's grey image for the view check (:func:`grey_for_check`).
        query_depth, query_mask, query_grey: ``(H, W)`` the query keyframe in the new submap.
        query_K, query_T_cam_submap: its camera there.
        match_ratio: the frontend's image-match ratio of (query keyframe, loop frame), or ``None``.
    """

    pairs: list[tuple[FrameView, FrameView]]
    grey_new: np.ndarray
    query_depth: np.ndarray
    query_mask: np.ndarray
    query_grey: np.ndarray
    query_K: np.ndarray
    query_T_cam_submap: np.ndarray
    match_ratio: float | None = None

    @property
    def old(self) -> FrameView:
        """The loop frame as stored in its old submap."""
        return self.pairs[0][0]

    @property
    def new(self) -> FrameView:
        """The loop frame reconstructed in the new submap."""
        return self.pairs[0][1]


class LoopVerifier:
    """Runs the checks of the module docstring on a candidate.

    Args:
        config: the ``[loops]`` settings; alignment_config: the edge checks' thresholds.
        aligner: the alignment stage (its model must match the graph's group).
        backend: the graph, for the consistency check.
        information: ``alignment -> (dim, dim)`` information of an edge (``sl4slam.backend.evidence``).
        attention: run the attention check (``sl4slam.resolve`` settles the setting).
    """

    def __init__(self, config: LoopConfig, alignment_config: AlignmentConfig, aligner: Aligner, backend: Any,
                 information: Callable[[Alignment], np.ndarray], attention: bool = False,
                 noise_scale: Any = None) -> None:
        self.config = config
        self.alignment_config = alignment_config
        self.aligner = aligner
        self.backend = backend
        self.information = information
        self.attention = bool(attention)
        self.threshold = chi2_threshold(config, backend.dim)
        self.noise_scale = noise_scale

    def inlier_gate(self, odometry_ratios: Sequence[float]) -> float:
        """Inlier ratio a loop alignment must reach: ``min_inlier_ratio``, or half the median ratio
        of the odometry so far when the model fits consecutive submaps worse than that (Sim(3)
        under a projective distortion): a loop must fit about as well as odometry does."""
        gate = self.config.min_inlier_ratio
        return min(gate, 0.5 * float(np.median(odometry_ratios))) if len(odometry_ratios) else gate

    def start_alignment(self, evidence: LoopEvidence, seed: int) -> Pending[Alignment]:
        """The loop's link (:meth:`verify`'s alignment, seed ``seed``) started now, on the link pool of
        ``alignment.fit_threads`` threads (deferred with one): the pipeline measures it beside the
        odometry link, which it does not depend on (``sl4slam.alignment.parallel``)."""
        from .alignment.parallel import start  # a stage's module: not loaded with the settings

        return start(partial(self.aligner.align_frames, evidence.pairs, seed=seed),
                     int(self.alignment_config.fit_threads), kind="link")

    def verify(self, old_submap: int, new_submap: int, evidence: LoopEvidence, odometry_ratios: Sequence[float],
               seed: int, frames: tuple[int, int] | None = None,
               alignment: Pending[Alignment] | None = None) -> LoopDecision:
        """The verdict on a loop between ``old_submap`` and ``new_submap`` (which is in the graph);
        ``frames``: the (loop frame, query keyframe) whose nodes a keyframe graph ties; ``alignment``:
        the loop's link as :meth:`start_alignment` started it with the same evidence and seed (else
        it is measured here)."""
        checks: dict = {}
        if self.attention and evidence.match_ratio is not None:
            checks["match_ratio"] = evidence.match_ratio
            if not evidence.match_ratio >= self.config.min_match_ratio:
                return LoopDecision(False, f"the frontend's attention says the images do not overlap "
                                           f"(match ratio {evidence.match_ratio:.2f} < {self.config.min_match_ratio})",
                                    checks=checks)
        try:  # one link of them all, as odometry
            alignment = (alignment.result() if alignment is not None
                         else self.aligner.align_frames(evidence.pairs, seed=seed))
        except ValueError as exc:
            return LoopDecision(False, f"the loop frame's alignment failed: {exc}", checks=checks)
        checks["inlier_ratio"] = alignment.inlier_ratio
        gate = self.inlier_gate(odometry_ratios)
        camera_link = is_camera_link(alignment)
        problem = edge_problem(alignment, self.alignment_config)
        if alignment.model != self.aligner.group:
            problem = f"the loop frame's alignment fell back to a weaker model ({alignment.fallback})"
        elif problem is None and not camera_link and alignment.inlier_ratio < gate:
            problem = f"inlier ratio {alignment.inlier_ratio:.2f} < {gate:.2f}"
        if problem:
            return LoopDecision(False, problem, alignment, checks=checks)
        if self.config.verify_view:
            X = evidence.new.points.reshape(-1, 3)
            pixels = np.flatnonzero(evidence.new.mask)
            pixels = pixels[:: max(1, len(pixels) // self.config.check_points)]
            agreement = view_agreement(
                X[pixels].astype(np.float64), evidence.grey_new.reshape(-1)[pixels], evidence.query_depth,
                evidence.query_mask, evidence.query_grey, evidence.query_K, evidence.query_T_cam_submap,
                self.config.depth_tolerance)
            checks.update(agreement)
            problem = check_view(self.config, agreement)
            if problem:
                return LoopDecision(False, problem, alignment, checks=checks)
        information = self.information(alignment)
        if self.config.verify_graph:
            scale = self.noise_scale.value if self.noise_scale is not None else 1.0
            distance = self.backend.loop_chi2(old_submap, new_submap, alignment.H, information, frames=frames) / scale
            checks["chi2"] = distance
            if scale != 1.0:
                checks["noise_scale"] = scale
            if not distance <= self.threshold:
                return LoopDecision(False, f"it disagrees with the map (chi-square {distance:.3g} > {self.threshold:.3g})",
                                    alignment, information, checks)
        return LoopDecision(True, None, alignment, information, checks)
