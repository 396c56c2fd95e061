"""One dataclass tree for every setting that changes a run's results.

Defaults cite VGGT-SLAM (Maggio, Lim, Carlone, NeurIPS 2025), section 5.1 ("paper"), the authors'
code ("reference code"), or a measurement of ours (named with the benchmark that made it). The
command line is generated from this tree (``sl4slam.cli``) and the same tree can be read from a
TOML or JSON file. Each section checks its own values in ``validate()``; ``sl4slam.resolve.resolve``
calls it once per run, before any frame is read, and settles every "auto" (the rules live there,
not here); a bad value is one line that names the flag, the config-file key and the allowed range.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from .errors import UserError
from .registry import aligner_names, graph_names, retrieval_names


class Section:
    """Behaviour shared by the config sections: flag names and range checks.

    Class attributes (not settings):
        section: the section's key in the tree (``[alignment]`` in a config file).
        flag_prefix: prefix of the section's command-line flags (``--ransac-...``).
        flag_names: per-field flag overrides (e.g. the paper's short names).
        flag_aliases: per-field further flags that set the same field (older or shorter names).
        choices: per-field allowed values of string settings.
        advanced: fields listed under the section's "advanced" group of ``run --help-all``.
        common: fields most runs touch, the ones ``run --help`` shows.
    """

    section: ClassVar[str] = ""
    flag_prefix: ClassVar[str] = ""
    flag_names: ClassVar[dict[str, str]] = {}
    flag_aliases: ClassVar[dict[str, tuple[str, ...]]] = {}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {}
    advanced: ClassVar[frozenset[str]] = frozenset()
    common: ClassVar[frozenset[str]] = frozenset()

    @classmethod
    def flag(cls, name: str) -> str:
        """The command-line flag of field ``name``."""
        if name in cls.flag_names:
            return cls.flag_names[name]
        if name == "kind":
            return f"--{cls.section}"
        dashed = name.replace("_", "-")
        return "--" + (dashed if dashed.startswith(cls.flag_prefix) else cls.flag_prefix + dashed)

    def _require(self, name: str, ok: bool, allowed: str) -> None:
        """Raise a one-line ``UserError`` naming the flag and config key unless ``ok``."""
        value = getattr(self, name)
        finite = not isinstance(value, float) or math.isfinite(value)
        if not (ok and finite):
            key = f"{self.section}.{name}" if self.section else name
            raise UserError(f"{self.flag(name)} (config key {key}) must be {allowed}, got {value!r}")

    @classmethod
    def field_default(cls, name: str) -> Any:
        """The value field ``name`` has when not set (for help texts and flag types)."""
        return getattr(cls(), name)

    def _require_choice(self, name: str) -> None:
        allowed = self.choices[name]
        self._require(name, getattr(self, name) in allowed, "one of " + ", ".join(allowed))

    def validate(self) -> None:
        """Raise ``UserError`` for a value outside its meaningful range."""
        for name in self.choices:
            self._require_choice(name)


@dataclass
class KeyframeConfig(Section):
    """Keyframe selection by Lucas-Kanade disparity (paper 4.1)."""

    section: ClassVar[str] = "keyframes"
    advanced: ClassVar[frozenset[str]] = frozenset(
        {"max_corners", "corner_quality", "corner_min_distance", "lk_window", "lk_levels", "min_tracked"})

    tau_disparity: float = 25.0
    """Mean tracked displacement (px) that makes a keyframe. Paper: 25; reference code: 50."""
    max_corners: int = 1000
    """Shi-Tomasi corners detected on the last keyframe (reference code)."""
    corner_quality: float = 0.01
    """Shi-Tomasi quality level (reference code)."""
    corner_min_distance: float = 8.0
    """Minimum distance between corners in px (reference code)."""
    lk_window: int = 21
    """Lucas-Kanade window size in px (OpenCV default, used by the reference code)."""
    lk_levels: int = 3
    """Lucas-Kanade pyramid levels above the full image (OpenCV's maxLevel; reference code: 3)."""
    min_tracked: int = 10
    """A frame with fewer successfully tracked corners is always a keyframe."""

    def validate(self) -> None:
        super().validate()
        self._require("tau_disparity", self.tau_disparity > 0, "a positive number of pixels")
        self._require("max_corners", self.max_corners >= 1, "at least 1")
        self._require("corner_quality", 0 < self.corner_quality < 1, "in (0, 1)")
        self._require("corner_min_distance", self.corner_min_distance >= 0, ">= 0 px")
        self._require("lk_window", self.lk_window >= 3, "at least 3 px")
        self._require("lk_levels", self.lk_levels >= 0, ">= 0")
        self._require("min_tracked", self.min_tracked >= 1, "at least 1")


@dataclass
class SubmapConfig(Section):
    """Submap assembly (paper 4.1, 5.1)."""

    section: ClassVar[str] = "submap"
    common: ClassVar[frozenset[str]] = frozenset({"size"})
    flag_prefix: ClassVar[str] = "submap-"
    flag_names: ClassVar[dict[str, str]] = {"tau_conf": "--tau-conf", "w_loop": "--w-loop", "loop_frames": "--loop-frames"}

    size: int = 16
    """New keyframes per submap, w. Paper evaluates 8/16/32 (tables use 32); reference CLI: 16."""
    overlap: int = 2
    """Frames shared by consecutive submaps: the last ``overlap`` keyframes of a submap open the next
    one, and the link between the two uses all of them (``sl4slam.alignment.shared``). Each costs one
    more frame per forward. VGGT-SLAM shares one ("only default of 1 supported" in its code); two
    let the "select" link judge the 15-DOF fit on a frame it was not fitted on and the loop gate
    measure the links' real noise (benchmarks/results/levers.md)."""
    w_loop: int = 1
    """Loop candidates per submap, each appending its loop frame (paper: 1)."""
    loop_frames: int = 2
    """Frames of the old submap each loop candidate appends: its loop frame and the keyframes of that
    submap nearest to it. The loop is then measured like a link over several shared frames
    (``sl4slam.alignment.shared``), so the "select" link can judge the 15-DOF fit on a frame it was
    not fitted on; with one frame it keeps the calibration link, which a per-submap projective
    distortion bends (benchmarks/results/levers.md). Each costs one more frame per forward in the
    submaps that propose a loop. VGGT-SLAM appends one."""
    tau_conf: float = 25.0
    """Percentile of the submap's confidence below which pixels are dropped (reference code: 25)."""
    use_point_head: bool = False
    """Use the frontend's point map instead of unprojecting depth (VGGT offers both)."""

    def validate(self) -> None:
        super().validate()
        self._require("size", self.size >= 1, "at least 1")
        # the next submap opens with this one's newest keyframes: at most all of them (a small submap
        # with the default overlap then shares every new keyframe, never an older shared frame again)
        self._require("overlap", 1 <= self.overlap <= max(self.size, 1),
                      f"at least 1 and at most the submap size ({self.size}): the shared frames are the newest keyframes "
                      "of the submap before")
        self._require("w_loop", self.w_loop >= 0, ">= 0")
        self._require("loop_frames", self.loop_frames >= 1, "at least 1: the loop frame itself")
        # 100 would drop every pixel (an empty map); the percentile is over the whole submap
        self._require("tau_conf", 0 <= self.tau_conf < 100, "a percentile in [0, 100)")


@dataclass
class AlignmentConfig(Section):
    """Relative alignment of submaps from a shared frame's points (paper 4.2)."""

    section: ClassVar[str] = "alignment"
    flag_prefix: ClassVar[str] = "ransac-"
    flag_names: ClassVar[dict[str, str]] = {
        "model": "--alignment", "min_points": "--alignment-min-points",
        "weight_reference_frame": "--alignment-weight-reference-frame",
        "min_inlier_ratio": "--alignment-min-inlier-ratio", "max_condition": "--alignment-max-condition"}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {
        "model": ("auto", *aligner_names()),
        "planar_model": ("auto", "calibration-scale", "camera-constrained")}
    advanced: ClassVar[frozenset[str]] = frozenset({
        "max_correspondences", "max_points", "max_refit_points", "planarity_threshold", "min_relief", "planar_model",
        "planar_support_margin", "planar_fit_min_inlier_ratio", "hybrid_margin", "select_confidence",
        "select_min_gain", "near_planar_threshold", "refit", "refit_candidates",
        "hypothesis_batch", "early_stop_spread", "preemptive_points", "preemptive_keep",
        "preemptive_min_keep", "refit_rounds", "refit_min_gain", "small_set", "weight_reference_frame",
        "camera_constrained_iterations", "camera_constrained_ridge", "min_points", "min_inlier_ratio",
        "max_condition"})

    model: str = "auto"
    """What measures the relative transform: "sl4" (15-DOF DLT in RANSAC, the paper), "sim3-points"
    (7-DOF Umeyama in RANSAC on the same points), "sim3-cameras" (the shared frame's two cameras and
    the median depth ratio), "calibration" (VGGT-SLAM 2.0: the shared frame's two cameras, their
    intrinsics and the median depth ratio, no free projective terms; ``calibration_scale_link``),
    "hybrid" (that link, or the 15-DOF fit where it explains the frame ``hybrid_margin`` times
    better), "select" (that link or the 15-DOF fit, whichever predicts the shared frames it was not
    fitted on better: ``sl4slam.alignment.select``; needs two or more shared frames, else the link),
    or "auto": "select" for the keyframe graph, "sl4" for the SL(4) submap graph, "sim3-cameras" for
    the Sim(3) graph. A Sim(3) graph needs a Sim(3) model."""
    ransac_iterations: int = 300
    """Most RANSAC hypotheses (paper: 300, always drawn in full there)."""
    ransac_confidence: float = 0.999
    """Stop drawing hypotheses once an all-inlier sample has been drawn with this probability,
    judged from the best hypothesis' inlier fraction (classic adaptive RANSAC; the reference code
    always draws all of them)."""
    inlier_threshold: float = 0.01
    """Inlier distance in submap units (paper: 0.01)."""
    max_correspondences: int = 30000
    """Pixels of the shared frame passed to the alignment (0: all); beyond this an evenly strided
    subset (about a quarter of a 518x294 frame's confident pixels) — as accurate, several times
    faster (benchmarks/bench_pipeline.py)."""
    max_points: int = 10000
    """Correspondences each hypothesis is scored on; larger sets are subsampled (seeded). The
    final inlier mask is computed on every point."""
    max_refit_points: int = 20000
    """Inliers used by each least-squares refit (0: all; an evenly strided subset beyond this)."""
    min_inliers: int = 50
    """Fewer inliers than this makes the 15-DOF fit degenerate: use a constrained model instead."""
    planarity_threshold: float = 0.02
    """Spread of the points along their thinnest principal axis relative to the widest
    (interdecile ranges, robust to a few off-plane points) below which they count as coplanar:
    the 15-DOF fit is degenerate and a constrained model is used instead."""
    min_relief: float = 0.1
    """Relief of the shared frame's points off their best plane (interdecile thickness / median
    distance to the camera) below which the 15-DOF fit is degenerate: VGGT's depth errors (AbsRel
    2-4 %, smooth) fake about that much structure on a flat floor, which RANSAC then turns into a
    projective error (benchmarks/bench_robustness.py). Rooms and desks seen from 1-3 m: 0.2-0.3."""
    hybrid_margin: float = 4.0
    """"hybrid" alignment: the 15-DOF fit replaces the calibration-and-scale link when the link's
    median transfer error on the shared frame is more than this many times the fit's. Measured on the
    synthetic world (benchmarks/bench_keyframe_graph.py): 1.2-3.8 under the vggt profile's depth warps,
    4.3-16 under a relative perspective distortion of 0.1 (non-degenerate frames)."""
    select_confidence: float = 0.95
    """"select" alignment: confidence at which the 15-DOF fit must predict the held-out shared
    frames better than the calibration-and-scale link (one-sided paired t-test over the held-out
    frames, ``sl4slam.alignment.select``); below it the link, the model that assumes less, is kept.
    0.95: the conventional level, not tuned."""
    select_min_gain: float = 2.0
    """"select" alignment: the 15-DOF fit must also predict the held-out shared frames at least this
    many times better than the link (geometric mean of the held-out error ratios). The t-test alone
    treats each held-out frame as an independent observation; with two shared frames the two folds
    are one comparison seen from both sides (their log ratios correlated at 0.995 over 239 links of
    benchmarks/bench_levers.py), so it passed wherever the fit was better at all. On that grid the
    fits the test passed predicted 7-60x better under a strong window distortion and 1.02-1.2x under
    the vggt and hard profiles' per-frame errors; any value from 1.25 to 7 makes the same choices."""
    planar_model: str = "auto"
    """What measures a degenerate shared frame: "calibration-scale" (its two cameras and depth
    ratio: VGGT-SLAM 2.0's link, immune to depth warps, blind to a relative projective
    distortion), "camera-constrained" (a projective fit whose free part the points choose), or
    "auto": both are measured and the link is kept unless the constrained fit explains
    ``planar_support_margin`` times as many points and nearly all of them
    (``planar_fit_min_inlier_ratio``: a real distortion the link cannot express)."""
    planar_support_margin: float = 2.5
    """"auto": how many times the link's inliers the camera-constrained fit must explain to win
    (as inlier ratios). On the synthetic world's floor frames under a 0.2 projective distortion
    the fit explains 3.7-4.3x the link's points (1.0 against 0.23-0.27; tests/test_pipeline.py);
    under the vggt profile's smooth depth warps it explained 1.7x (0.91 against 0.55) and chose
    the warp over the link, doubling the ATE (benchmarks/bench_robustness.py)."""
    planar_fit_min_inlier_ratio: float = 0.97
    """"auto": the camera-constrained fit wins only if it also explains at least this fraction of
    the points, i.e. the frame really is a projective image of the other (synthetic floor frames
    under a 0.2 distortion: 0.999-1.0). Under depth warps the fit explains more than the link but
    not all: 0.91 under the vggt profile; under the hard profile such a fit bent the map by 1.5 m
    where the link kept it at 0.33 m (benchmarks/bench_robustness.py)."""
    near_planar_threshold: float = 0.15
    """Below this planarity (but above ``planarity_threshold``) the shared frame is dominated by a
    plane, where RANSAC may settle on the plane and call the rest outliers (on the synthetic world:
    a 0.08-planarity frame with 2.5 % "outliers" and a 0.4-unit error off the plane): the
    camera-constrained fit competes and wins when it explains more points."""
    refit: bool = True
    """Least-squares refit of H on all inliers, then re-score (the reference code does not)."""
    refit_candidates: int = 5
    """Hypotheses refitted (the best by MSAC cost); the best refit wins (LO-RANSAC). Under the vggt
    simulator profile the best minimal hypothesis of a shared frame refitted into a wrong optimum
    (perspective row ~0.6, 73 % inliers against 80 %) for 2 of 5 RANSAC seeds; refitting the best 3
    left 1 of 10 seeds there, the best 5 none (benchmarks/bench_robustness.py)."""
    seed: int = 0
    """Seed of the RANSAC sampler (combined with the submap id)."""
    hypothesis_batch: int = 50
    """Hypotheses drawn, solved and scored together before the adaptive stopping test: 50
    five-point samples contain an all-inlier one with probability 0.999 from about 2/3 inliers,
    so a well-aligned pair needs one batch instead of all 300 (benchmarks/bench_ransac.py)."""
    early_stop_spread: float = 0.5
    """RANSAC may stop early only if the best hypothesis' inliers keep at least this fraction of
    the points' planarity: one that explains just a dominant plane is the near-degenerate case
    where more samples find the full 15-DOF map."""
    preemptive_points: int = 1024
    """Correspondences of the preemptive scoring round (every valid hypothesis is scored on them;
    Nister's preemptive RANSAC)."""
    preemptive_keep: float = 0.1
    """Fraction of hypotheses (at least ``preemptive_min_keep``) scored on the full subset."""
    preemptive_min_keep: int = 8
    """Fewest hypotheses that survive the preemptive round."""
    refit_rounds: int = 5
    """Most refit / re-score rounds after RANSAC; they stop earlier once the inlier set stops
    changing or the cost stops decreasing by more than ``refit_min_gain``."""
    refit_min_gain: float = 1e-3
    """Relative MSAC cost decrease below which another refit is not worth it (on the synthetic
    world the remaining rounds change the cost by < 0.1 % each, with no visible change of H)."""
    small_set: int = 4096
    """Up to this many points, samples are drawn without repetition by permuting all indices."""
    camera_constrained_iterations: int = 6
    """Reweighting rounds of the camera-constrained fit used for planar shared frames."""
    camera_constrained_ridge: float = 1e-6
    """Ridge term (relative to the normal matrix's trace) that picks, among the camera-constrained
    maps the plane cannot tell apart, the one nearest the Sim(3) guess."""
    min_points: int = 5
    """Fewest pixels confident in both submaps for any alignment (the 5-point minimal sample)."""
    min_inlier_ratio: float = 0.1
    """A fitted edge that explains fewer of the shared pixels is not trusted (a model that failed:
    e.g. 0.16 % with random VGGT weights); the shared frame's camera edge takes its place."""
    max_condition: float = 1e4
    """Largest condition number of a measured 4x4 transform: consecutive windows differ by a scale
    of 0.5-2 and a mild projective part (condition < 20 on the synthetic world), so beyond this the
    fit has degenerated."""
    weight_reference_frame: bool = True
    """Where several shared frames' camera links are averaged, weigh each by the inverse of the pose
    errors it carries: a frame that is its submap's reference (the first camera, ``[I | 0]`` by
    construction in VGGT) has none there, so the new submap's first shared frame counts twice
    (``sl4slam.alignment.shared.pose_error_weights``). Off: the plain mean."""

    def validate(self) -> None:
        super().validate()
        self._require("ransac_iterations", self.ransac_iterations >= 1, "at least 1")
        self._require("ransac_confidence", 0 < self.ransac_confidence < 1, "between 0 and 1 (exclusive)")
        self._require("inlier_threshold", self.inlier_threshold > 0, "a positive distance in submap units")
        self._require("max_correspondences", self.max_correspondences >= 0, ">= 0 (0: all)")
        self._require("max_points", self.max_points >= 5, "at least 5 (one minimal sample)")
        self._require("max_refit_points", self.max_refit_points >= 0, ">= 0 (0: all)")
        self._require("min_inliers", self.min_inliers >= 5, "at least 5 (one minimal sample)")
        self._require("planarity_threshold", 0 <= self.planarity_threshold < 1, "in [0, 1)")
        self._require("min_relief", 0 <= self.min_relief < 1, "in [0, 1)")
        self._require("hybrid_margin", self.hybrid_margin >= 1, "at least 1")
        self._require("select_confidence", 0.5 <= self.select_confidence < 1, "in [0.5, 1)")
        self._require("select_min_gain", self.select_min_gain >= 1, "at least 1 (1: the t-test alone)")
        self._require("planar_support_margin", self.planar_support_margin >= 1, ">= 1")
        self._require("planar_fit_min_inlier_ratio", 0 <= self.planar_fit_min_inlier_ratio <= 1, "in [0, 1]")
        self._require("near_planar_threshold", self.planarity_threshold <= self.near_planar_threshold <= 1,
                      "between --ransac-planarity-threshold and 1")
        self._require("seed", self.seed >= 0, ">= 0")
        self._require("hypothesis_batch", self.hypothesis_batch >= 1, "at least 1")
        self._require("early_stop_spread", 0 <= self.early_stop_spread <= 1, "in [0, 1]")
        self._require("preemptive_points", self.preemptive_points >= 5, "at least 5")
        self._require("preemptive_keep", 0 < self.preemptive_keep <= 1, "in (0, 1]")
        self._require("preemptive_min_keep", self.preemptive_min_keep >= 1, "at least 1")
        self._require("refit_rounds", self.refit_rounds >= 0, ">= 0")
        self._require("refit_candidates", self.refit_candidates >= 1, "at least 1")
        self._require("refit_min_gain", self.refit_min_gain >= 0, ">= 0")
        self._require("small_set", self.small_set >= 0, ">= 0")
        self._require("camera_constrained_iterations", self.camera_constrained_iterations >= 1, "at least 1")
        self._require("camera_constrained_ridge", self.camera_constrained_ridge >= 0, ">= 0")
        self._require("min_points", self.min_points >= 5, "at least 5")
        self._require("min_inlier_ratio", 0 <= self.min_inlier_ratio <= 1, "in [0, 1]")
        self._require("max_condition", self.max_condition > 1, "greater than 1")


@dataclass
class BackendConfig(Section):
    """Factor graph over submap transforms (paper 4.4)."""

    section: ClassVar[str] = "backend"
    common: ClassVar[frozenset[str]] = frozenset({"kind", "graph"})
    flag_prefix: ClassVar[str] = "backend-"
    flag_names: ClassVar[dict[str, str]] = {"graph": "--graph"}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {
        "kind": ("sl4", "sim3"), "graph": ("auto", *graph_names()), "loop_kernel": ("none", "huber", "cauchy"),
        "weighting": ("auto", "evidence", "fixed")}
    advanced: ClassVar[frozenset[str]] = frozenset({
        "prior_sigma", "loop_kernel", "loop_kernel_width", "effective_points", "min_sigma", "max_sigma",
        "segment_sigma", "relinearize_threshold", "relinearize_skip", "wildfire_threshold", "loop_step_threshold",
        "max_loop_iterations", "frame_sigma", "frame_scatter_factor", "revisit_priors"})

    kind: str = "sl4"
    """"sl4" (15-DOF projective, the paper) or "sim3" (7-DOF similarity, for comparison)."""
    graph: str = "auto"
    """Graph design: "keyframe" (one SL(4) node per keyframe with rigid links inside a submap and
    calibration-and-scale links between submaps, VGGT-SLAM 2.0; ``sl4slam.backend.keyframe``),
    "submap" (one node per submap joined by 15-DOF links, VGGT-SLAM), or "auto": the keyframe graph
    for the SL(4) group, the submap graph for Sim(3). The keyframe graph's ATE is 0.49x the submap
    graph's on the synthetic world under the vggt simulator profile, 0.31x on TUM fr1/desk, 0.30x
    under a pure per-submap projective distortion of 0.1 (both without the metric upgrade; with it
    and its completed planar links the submap graph is 7x better there:
    benchmarks/results/upgrade_pipeline.md), and 0.85x the Sim(3) graph's under the vggt profile
    (benchmarks/results/keyframe_graph.md, robustness.md; VGGT-SLAM 2.0 reports 0.041 against
    0.053 m on TUM). The demo keeps the submap graph: it shows what 15-DOF links model. The
    keyframe graph needs ``kind`` "sl4"."""
    frame_sigma: float = 0.05
    """Keyframe graph: isotropic sigma (SL(4) tangent units) of the link between consecutive
    keyframes of a submap, their relative pose from the frontend (reference code: 0.05; the
    frontend reports no per-camera uncertainty to weigh it by)."""
    frame_scatter_factor: float = 2.0
    """Keyframe graph: in a submap whose link to the previous one is a 15-DOF fit (``select``
    found a distortion of the whole window, ``sl4slam.alignment.select``), the links between its
    keyframes get this many times the run's median disagreement between consecutive windows about
    their shared frames' relative rotations (radians; at least ``min_sigma``, at most
    ``frame_sigma``); 0 keeps ``frame_sigma`` everywhere. Such a window is consistent inside, and a
    loop must move it whole, as the submap graph's one node does, not bend it. Under a strong
    per-submap distortion, where the windows agreed to 0.3-0.8 degrees, TUM fr1/desk went from
    0.0010 to 0.0005 m (submap graph 0.0006 m) and the synthetic lap from 0.0021 to 0.0016 m; under
    per-frame camera errors (vggt, hard) the windows disagree by 1.6-2.3 degrees, twice that is above
    ``frame_sigma`` and nothing changes (benchmarks/results/levers.md). 2 because the disagreement
    of two windows is sqrt(2) times one window's error: about 3 standard errors of margin. Only
    submaps with a 15-DOF link: the same stiffness for every submap left desk at 0.0010 m
    (exploratory runs, 3 seeds)."""
    weighting: str = "auto"
    """Noise of each edge: "evidence" (information from the alignment's own inliers, residuals and
    point spread; see ``sl4slam.backend.evidence``), "fixed" (one isotropic ``sigma`` for every
    edge, as the reference code: VGGT-SLAM 2.0 gives every factor 0.05), or "auto": ``sigma`` for
    the edges read from the cameras (calibration-and-scale links, shared-frame similarity), the
    evidence for fitted ones. A camera link's error is the shared frames' camera errors, which the
    residuals of its points do not see: weighted by them, the links of one run (synthetic world,
    vggt profile) spanned 0.02-1.1 in sigma for reasons unrelated to their accuracy, and a loop's
    correction went to the links the points happened to call weak. Against "evidence", "auto"
    brought the defaults' ATE from 0.0241 to 0.0214 m on the synthetic lap under vggt, 0.066 to
    0.045 m under hard, on TUM fr1/desk 0.0128 to 0.0127 m (vggt) and 0.0254 to 0.0243 m (hard),
    and left strong distortion, whose links are fitted, where it was (5 seeds, medians;
    benchmarks/results/levers.md); the Sim(3) and submap graphs gained too. ``sigma`` from 0.035 to
    0.1 moved the synthetic medians by at most 3 % (exploratory runs)."""
    sigma: float = 0.05
    """Isotropic sigma of between factors with fixed weighting, and of camera links with "auto"
    (reference code: 0.05)."""
    prior_sigma: float = 1e-6
    """Sigma of the prior on the first submap (reference code: 1e-6)."""
    fallback_sigma_scale: float = 2.0
    """Sigma multiplier for an edge measured by a fallback (camera-constrained or Sim(3) fit of a
    degenerate frame, or the camera edge of a failed fit), so that loop closures correct those links
    first. Evidence weighting already leaves the directions a planar frame does not observe weak;
    on the synthetic world without distortion a factor of 10 made a loop worsen the ATE
    (0.6 -> 2.9 mm), 2 lets it help (0.6 -> 0.6 mm, 2.8 -> 0.6 mm, 1.6 -> 1.4 mm over three seeds)."""
    loop_kernel: str = "none"
    """Robust kernel on loop factors: "none", "huber" or "cauchy" (loops are verified before they
    reach the graph; see the [loops] settings)."""
    loop_kernel_width: float = 1.0
    """Width of the robust kernel, in whitened residual units."""
    effective_points: float = 20.0
    """Evidence weighting: the alignment residuals of dense points are spatially correlated (the
    model errs in smooth blobs, not per pixel), so an edge counts at most this many independent
    points however many pixels it aligned. Calibrated on the synthetic world under the vggt
    simulator profile: with 200, true loops disagreed with the map by chi-square 105-140 (> 37.7,
    rejected) because the odometry edges claimed too much certainty; with 20 they are accepted
    while false loops still score 2e3-9e4 (benchmarks/bench_robustness.py)."""
    min_sigma: float = 1e-3
    """Evidence weighting: smallest sigma of any edge direction (tangent units); no edge is more
    certain than this, whatever its point count."""
    max_sigma: float = 1.0
    """Evidence weighting: directions the points do not observe (e.g. a planar shared frame) get
    at most this sigma, which keeps the graph determined without pulling on them."""
    segment_sigma: float = 1.0
    """Sigma of the weak prior that anchors a new map segment (after an edge that failed its checks
    or a graph update that failed): loops can still join segments. At most 1000 ``min_sigma``:
    GTSAM reports weights that span more than about 1e7 as an indeterminate system."""
    relinearize_threshold: float = 1e-2
    """iSAM2 relinearizes a variable whose tangent step exceeds this (a fifth of the default sigma;
    GTSAM's default 0.1 leaves loops half-absorbed; benchmarks/bench_backend.py)."""
    relinearize_skip: int = 10
    """iSAM2 checks for variables to relinearize at every this many updates (GTSAM's default), and
    at every iteration after a loop. The check and the search for the cliques it touches walk the
    whole map: checked at every update, the keyframe graph's own work per submap grew 1.42x over
    300 submaps instead of 1.26x, with the same final ATE (benchmarks/results/keyframe_graph.md)."""
    wildfire_threshold: float = 1e-9
    """iSAM2 stops back-substitution below this change of the step; small, so that one node's
    estimate agrees with the full estimate after a loop."""
    loop_step_threshold: float = 5e-2
    """After loop factors arrive, iSAM2 iterates while some tangent step exceeds this (one default
    sigma): a loop that corrects real drift is absorbed at once, a consistent one costs one step."""
    max_loop_iterations: int = 30
    """Cap on those extra iterations."""
    revisit_priors: bool = True
    """Keyframe graph: a loop whose older node lies on a cycle that an earlier loop closed (a revisit of a settled
    place) reaches iSAM2 as a prior on its newer node, the older held at its estimate; the final
    polish at the end of a run optimizes every loop between its two nodes. Keeps the cost of a loop
    update flat in a map that revisits its places lap after lap (whose cliques otherwise grow with
    the laps: 3.5-3.9x slower per submap after 17 laps without it; benchmarks/results/keyframe_graph.md)."""

    def validate(self) -> None:
        super().validate()
        for name in ("sigma", "prior_sigma", "loop_kernel_width", "effective_points", "min_sigma", "max_sigma",
                     "segment_sigma", "relinearize_threshold", "loop_step_threshold", "frame_sigma"):
            self._require(name, getattr(self, name) > 0, "a positive number")
        self._require("fallback_sigma_scale", self.fallback_sigma_scale >= 1, "at least 1")
        self._require("max_sigma", self.min_sigma <= self.max_sigma <= 1000 * self.min_sigma,
                      f"between --backend-min-sigma and 1000 times it ({self.min_sigma}, {1000 * self.min_sigma})")
        self._require("segment_sigma", self.segment_sigma <= 1000 * self.min_sigma,
                      f"at most 1000 times --backend-min-sigma ({1000 * self.min_sigma})")
        self._require("wildfire_threshold", self.wildfire_threshold >= 0, ">= 0")
        self._require("frame_scatter_factor", self.frame_scatter_factor >= 0, ">= 0 (0 keeps --backend-frame-sigma)")
        self._require("max_loop_iterations", self.max_loop_iterations >= 0, ">= 0")
        self._require("relinearize_skip", self.relinearize_skip >= 1, "at least 1")
        self._require("frame_sigma", self.frame_sigma <= 1000 * self.min_sigma,
                      f"at most 1000 times --backend-min-sigma ({1000 * self.min_sigma})")
        self._require("graph", self.graph != "keyframe" or self.kind == "sl4",
                      "submap or auto with --backend sim3 (the keyframe graph is an SL(4) graph)")



@dataclass
class RetrievalConfig(Section):
    """Loop-closure retrieval (paper 4.3)."""

    section: ClassVar[str] = "retrieval"
    common: ClassVar[frozenset[str]] = frozenset({"kind"})
    flag_names: ClassVar[dict[str, str]] = {"seed": "--retrieval-seed"}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"kind": ("auto", *retrieval_names())}
    advanced: ClassVar[frozenset[str]] = frozenset({
        "salad_image_size", "orb_features", "orb_candidates", "orb_ratio", "orb_max_hamming",
        "orb_epipolar_threshold_px", "orb_max_image_side"})

    kind: str = "auto"
    """"salad" (the paper's SALAD descriptors), "orb" (weights-free, CPU), "none", or "auto": SALAD
    when its weights are found locally (``salad_weights`` or the user cache), else ORB."""
    tau_interval: int = 2
    """Most recent submaps excluded from retrieval (paper: 2)."""
    seed: int = 0
    """Seed of the ORB retrieval's geometric verification (fundamental-matrix RANSAC)."""
    tau_desc: float = 0.8
    """SALAD only: accept when the L2 descriptor distance is below this (paper: 0.8)."""
    salad_weights: str | None = None
    """Path to ``dino_salad.ckpt``; ``None`` uses the user cache (downloaded on first use)."""
    salad_image_size: int = 224
    """SALAD input size in px (reference SLAM code: 224; SALAD's evaluation: 322)."""
    orb_features: int = 1000
    """ORB: features per keyframe."""
    orb_min_inliers: int = 40
    """ORB: geometrically verified matches (fundamental-matrix RANSAC inliers) to accept a loop."""
    orb_candidates: int = 5
    """ORB: (query, stored) pairs per submap, ranked by bag-of-words similarity, that are
    geometrically verified (a fixed budget, so the cost does not grow with the submap size)."""
    orb_ratio: float = 0.8
    """ORB: Lowe's ratio test threshold of a tentative match (Lowe 2004: 0.8)."""
    orb_max_hamming: float = 64.0
    """ORB: largest Hamming distance (of 256 bits) of a tentative match (ORB-SLAM uses 50-100)."""
    orb_epipolar_threshold_px: float = 1.5
    """ORB: fundamental-matrix RANSAC inlier distance to the epipolar line, px at the working
    resolution."""
    orb_max_image_side: int = 640
    """ORB: images whose longer side exceeds this (px) are downscaled to it before extraction, so
    cost and the epipolar threshold do not depend on the input size."""

    def validate(self) -> None:
        super().validate()
        self._require("tau_interval", self.tau_interval >= 0, ">= 0")
        self._require("seed", self.seed >= 0, ">= 0")
        self._require("tau_desc", self.tau_desc > 0, "a positive descriptor distance")
        self._require("salad_image_size", self.salad_image_size >= 14 and self.salad_image_size % 14 == 0,
                      "a positive multiple of 14 px (DINOv2 patches)")
        self._require("orb_features", self.orb_features >= 8, "at least 8 (the fundamental matrix needs 8 matches)")
        self._require("orb_min_inliers", self.orb_min_inliers >= 8, "at least 8")
        self._require("orb_candidates", self.orb_candidates >= 1, "at least 1")
        self._require("orb_ratio", 0 < self.orb_ratio <= 1, "in (0, 1]")
        self._require("orb_max_hamming", 0 < self.orb_max_hamming <= 256, "in (0, 256]")
        self._require("orb_epipolar_threshold_px", self.orb_epipolar_threshold_px > 0, "a positive distance in px")
        self._require("orb_max_image_side", self.orb_max_image_side >= 64, "at least 64 px")


@dataclass
class LoopConfig(Section):
    """Which retrieved loops reach the graph (``sl4slam.loops``): one false loop bends the whole map."""

    section: ClassVar[str] = "loops"
    flag_prefix: ClassVar[str] = "loop-"
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"verify_attention": ("auto", "on", "off")}
    advanced: ClassVar[frozenset[str]] = frozenset({
        "check_points", "depth_tolerance", "min_overlap", "min_consistent", "min_correlation",
        "consistency_quantile"})

    min_inlier_ratio: float = 0.3
    """The loop frame's own alignment (its points in the old and the new submap) must keep this
    inlier fraction (or half the odometry's median, if that is lower) without a fallback."""
    verify_attention: str = "auto"
    """Check, before anything else, that the frontend's attention says the query keyframe and the loop
    frame overlap (VGGT-SLAM 2.0's image-match ratio, ``sl4slam.models.vggt.attention``; the simulated
    frontend's stand-in is the true overlap, ``sl4slam.frontend.overlap``): "on", "off", or "auto"
    (on with the keyframe graph, as in VGGT-SLAM 2.0; off with the submap graph, as in VGGT-SLAM)."""
    min_match_ratio: float = 0.85
    """Attention check: image-match ratio from which a loop is kept (VGGT-SLAM 2.0 reference code: 0.85)."""
    verify_view: bool = True
    """Check inside the new submap that the query keyframe and the loop frame see the same surfaces:
    the loop frame's points, projected into the query keyframe, must land in its image, agree with
    its depth and look alike (the loop frame's alignment compares two reconstructions of one image,
    so it cannot tell a wrong place)."""
    check_points: int = 4000
    """Pixels of the loop frame used by the view check (an evenly strided subset)."""
    min_overlap: float = 0.15
    """View check: fraction of the loop frame's confident pixels that must project into the query
    keyframe's image in front of its camera."""
    depth_tolerance: float = 0.1
    """View check: relative depth difference under which a projected point agrees with the query
    keyframe's own depth."""
    min_consistent: float = 0.3
    """View check: fraction of the overlapping points whose depth must agree."""
    min_correlation: float = 0.3
    """View check: normalized cross-correlation of the grey values of the depth-consistent points in
    the two images (exposure-invariant); unrelated textures score about 0."""
    verify_graph: bool = True
    """Check that the loop agrees with the current graph: chi-square test of the loop factor's
    whitened error under the joint covariance of its two nodes and the loop's own noise."""
    consistency_quantile: float = 0.999
    """Chi-square quantile of that test (15 degrees of freedom for SL(4), 7 for Sim(3))."""

    def validate(self) -> None:
        super().validate()
        self._require("min_inlier_ratio", 0 < self.min_inlier_ratio <= 1, "in (0, 1]")
        self._require("check_points", self.check_points >= 100, "at least 100")
        self._require("min_overlap", 0 <= self.min_overlap <= 1, "in [0, 1]")
        self._require("depth_tolerance", self.depth_tolerance > 0, "a positive relative depth difference")
        self._require("min_consistent", 0 <= self.min_consistent <= 1, "in [0, 1]")
        self._require("min_correlation", -1 <= self.min_correlation <= 1, "in [-1, 1]")
        self._require("consistency_quantile", 0 < self.consistency_quantile < 1, "in (0, 1)")
        self._require("min_match_ratio", self.min_match_ratio >= 0, ">= 0")


SIM_PROFILES = ("exact", "vggt", "hard")
"""Error profiles of the simulated frontend (:data:`SIM_PROFILE_VALUES` holds their settings)."""


@dataclass
class SimulatorConfig(Section):
    """Corruption model of the simulated frontend (``sl4slam.frontend.simulated`` documents it in full).

    Every submap gets its own projective distortion ``H_s`` in SL(4) and scale gauge; every frame of
    every submap gets its own camera and focal error, depth noise, smooth depth warp, flying pixels at
    depth edges, outlier blobs and confidence. All of it is drawn from ``seed``, the submap id and the
    frame indices, so a run is exactly reproducible.

    ``profile`` gives every error magnitude left at ``None`` its value (``--sim-profile``,
    ``[sim] profile``, or ``config.sim.profile = "vggt"`` in Python); a magnitude set explicitly
    overrides it, whatever the order. :meth:`resolved` is the copy with every magnitude filled in,
    which the simulator reads and ``summary.json`` records. Each magnitude's "exact" value is given
    in its description (:data:`SIM_PROFILE_VALUES` holds the others).
    """

    section: ClassVar[str] = "sim"
    common: ClassVar[frozenset[str]] = frozenset({"profile", "seed"})
    flag_prefix: ClassVar[str] = "sim-"
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"profile": SIM_PROFILES}

    profile: str = "exact"
    """Error profile the settings started from: "exact" (each setting's own default: one exact SL(4)
    transform per submap, cameras exact, small depth noise), "vggt" (calibrated to published VGGT
    figures, cited in ``sl4slam.frontend.simulated``) or "hard" (the upper ends of those ranges, more
    flying pixels and outliers). Fills every magnitude not set explicitly; recorded in summary.json."""
    perspective: float | None = None
    """Norm of the perspective row ``p`` of ``H_s`` (what Sim(3) cannot model), in units of
    1 / (the submap's mean point distance): a point at the mean distance has its homogeneous
    weight changed by up to this fraction. 0: none."""
    shear: float | None = None
    """Spread of the shear / anisotropic stretch ``B`` of ``H_s`` (upper triangular, det 1):
    off-diagonal entries ~ N(0, shear^2), log stretches ~ N(0, shear^2) minus their mean. 0: none."""
    scale: float | None = None
    """Standard deviation of the log of the per-submap global scale of ``H_s``. 0: none."""
    gauge_scale_ratio: float | None = None
    """Scale gauge of each submap: its points and camera centres are multiplied by a factor drawn
    log-uniformly in [r^-1/2, r^1/2], so one window's scale relative to any other is within
    [1/r, r] (VGGT: ratios of 0.5 to 2 between consecutive windows are seen in practice, r = 2).
    Rotation and translation of a Sim(3) gauge are fixed by the first camera being [I | 0]. 1: none."""
    normalize_scale: bool = True
    """Scale each submap so the mean distance of its valid true points to the first camera is 1,
    as VGGT normalizes its outputs; off: submaps keep metric units (before ``scale``)."""
    camera_rotation_deg: float | None = None
    """Per-frame camera rotation error inside a submap (all frames but the first, which stays
    [I | 0] as VGGT's does): std in degrees of each component of a rotation vector about the
    camera centre. A pair of frames then disagrees by about 2.2x this in median (VGGT on indoor
    video: 1-3 degrees median relative rotation error, Depth Anything 3's table). 0: none."""
    camera_translation: float | None = None
    """Per-frame camera centre error (all frames but the first): std of each coordinate as a
    fraction of the submap's mean true point distance. 0: none."""
    focal_error: float | None = None
    """Per-frame focal error: fx and fy are multiplied by ``exp(focal_error * n)``, n ~ N(0, 1),
    about the principal point, which stays where it is (VGGT assumes the image centre; its focal
    length is off by up to about 7 %). 0: none."""
    camera_window_frames: int | None = None
    """Window length (frames) beyond which the camera rotation, translation and focal errors grow
    in proportion to the length (VGGT's quality falls as windows grow past about 100 frames)."""
    depth_noise: float | None = None
    """Relative depth noise sigma: depth is multiplied by ``exp(depth_noise * n)``, n ~ N(0, 1)
    per pixel, so the error grows with depth."""
    depth_warp: float | None = None
    """Smooth non-projective depth error per frame: depth is multiplied by ``exp(depth_warp * f)``
    with ``f`` a zero-mean, unit-variance smooth random field (VGGT's depth errors are mostly
    low-frequency; AbsRel 2-4 % indoors). 0: none."""
    depth_warp_length: float | None = None
    """Correlation length of the depth warp field as a fraction of the image width."""
    focal_consistency: float = -1.0
    """Share of the focal error's variance that belongs to the frame itself; -1: the same as
    ``frame_consistency``. 0 draws each frame's focal length afresh in every window (VGGT-SLAM's
    premise of an uncalibrated model whose focal wanders between windows; where a known calibration
    pays most)."""
    frame_consistency: float | None = None
    """Share of the variance of a frame's focal error and depth warp that belongs to the frame
    itself, the same in every submap that contains it; the rest is drawn per submap. VGGT's depth
    and focal length come mostly from the image itself, so two windows sharing a frame predict it
    alike (the paper's RANSAC inlier threshold, 1 % of the scene scale between the shared frame's
    two predictions, presumes so). 0: independent per submap."""
    unrelated_overlap: float | None = None
    """A frame that shares at most this fraction of its view with every other frame of its window
    (true geometry) is an unrelated image to the model, which still places it: at the pose of the
    window frame it looks most like, moved by ``unrelated_jitter`` (VGGT has no "no overlap" output;
    this is what makes a wrong-place loop candidate dangerous). 0: every frame keeps its true pose."""
    unrelated_jitter: float | None = None
    """Spread of that placement: rotation ~ N(0, (unrelated_jitter rad)^2) per axis, centre moved by
    ~ N(0, (unrelated_jitter d)^2) per axis (d the submap's mean point distance)."""
    flying_px: float | None = None
    """Flying pixels: within this many px of a depth discontinuity, the depth is interpolated
    between the local foreground and background (a random mix per pixel, smooth over the band),
    with the low confidence of outliers (``outlier_confidence``), as a regression head blurs
    depth edges. 0: none."""
    flying_jump: float | None = None
    """Relative depth jump between two adjacent pixels (larger / smaller - 1) that makes a depth
    discontinuity for ``flying_px``; smooth surfaces, even at grazing angles, stay below it."""
    outlier_fraction: float | None = None
    """Fraction of each frame's pixels inside outlier blobs (spatially coherent errors)."""
    outlier_blob_px: float | None = None
    """Typical outlier blob radius in px (correlation length of the blob field)."""
    outlier_magnitude: float | None = None
    """Relative depth error inside outlier blobs: depth is multiplied by ``(1 + m)^s`` with
    ``m`` this value and ``s`` in (-1, 1) a smooth field, mostly near -1 or +1."""
    confidence_scale: float | None = None
    """Confidence of a clean pixel at the submap's median depth is about ``1 + confidence_scale``;
    it falls inversely with depth (VGGT's confidence is ``1 + exp(x)`` >= 1)."""
    confidence_jitter: float | None = None
    """Log-normal spread of the confidence of clean pixels (so it is not a function of depth alone)."""
    outlier_confidence: float | None = None
    """Factor on the confidence excess (confidence - 1) inside outlier blobs and on flying pixels;
    pixels with no measured depth (filled from their nearest neighbour) get confidence exactly 1."""
    distort_first_submap: bool = True
    """Distort submap 0 too (``H_s`` and the scale gauge). The world frame is submap 0's frame, so
    its distortion is inherited by every backend alike; switching it off isolates the error that
    alignment adds."""
    seed: int = 0
    """Seed (>= 0); ``H_s`` and the gauge are drawn from (seed, submap id), per-frame errors from
    (seed, submap id, frame index)."""
    def validate(self) -> None:
        super().validate()
        self._require("profile", self.profile in SIM_PROFILES, "one of " + ", ".join(SIM_PROFILES))
        self.resolved()._check_magnitudes()

    def _check_magnitudes(self) -> None:
        checks = [
            ("perspective", self.perspective >= 0, ">= 0"),
            ("shear", self.shear >= 0, ">= 0"),
            ("scale", self.scale >= 0, ">= 0"),
            ("gauge_scale_ratio", 1 <= self.gauge_scale_ratio <= 10, "in [1, 10] (1: no scale gauge)"),
            ("camera_rotation_deg", 0 <= self.camera_rotation_deg <= 30, "in [0, 30] degrees"),
            ("camera_translation", 0 <= self.camera_translation <= 1, "in [0, 1] (a fraction of the mean point distance)"),
            ("focal_error", 0 <= self.focal_error <= 0.5, "in [0, 0.5]"),
            ("camera_window_frames", self.camera_window_frames >= 1, ">= 1"),
            ("depth_noise", self.depth_noise >= 0, ">= 0"),
            ("depth_warp", 0 <= self.depth_warp <= 1, "in [0, 1]"),
            ("depth_warp_length", self.depth_warp_length > 0, "> 0 (a fraction of the image width)"),
            ("flying_px", self.flying_px == 0 or 1 <= self.flying_px <= 50, "0 (off) or in [1, 50] px"),
            ("flying_jump", self.flying_jump > 0, "> 0"),
            ("unrelated_overlap", 0 <= self.unrelated_overlap <= 1, "in [0, 1]"),
            ("unrelated_jitter", self.unrelated_jitter >= 0, ">= 0"),
            ("frame_consistency", 0 <= self.frame_consistency <= 1, "in [0, 1]"),
            ("focal_consistency", self.focal_consistency == -1 or 0 <= self.focal_consistency <= 1,
             "-1 (as --sim-frame-consistency) or in [0, 1]"),
            ("outlier_fraction", 0 <= self.outlier_fraction < 1, "in [0, 1)"),
            ("outlier_blob_px", self.outlier_blob_px > 0, "> 0"),
            ("outlier_magnitude", self.outlier_magnitude >= 0, ">= 0"),
            ("confidence_scale", self.confidence_scale > 0, "> 0"),
            ("confidence_jitter", self.confidence_jitter >= 0, ">= 0"),
            ("outlier_confidence", 0 <= self.outlier_confidence <= 1, "in [0, 1]"),
            ("seed", self.seed >= 0, ">= 0"),
        ]
        for name, ok, allowed in checks:
            self._require(name, bool(ok), allowed)

    @classmethod
    def from_profile(cls, profile: str, **overrides: Any) -> "SimulatorConfig":
        """Settings of ``profile`` with ``overrides`` on top (the same as ``SimulatorConfig(profile=...,
        **overrides)``, with a clear error for an unknown setting)."""
        names = {f.name for f in dataclasses.fields(cls)} - {"profile"}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise UserError(f"unknown simulator setting '{unknown[0]}'")
        profile_values(profile)
        return cls(profile=profile, **overrides)

    def resolved(self) -> "SimulatorConfig":
        """A copy with every magnitude left at ``None`` taken from :attr:`profile`."""
        values = profile_values(self.profile)
        return dataclasses.replace(self, **{name: values[name] for name in _PROFILED if getattr(self, name) is None})

    @classmethod
    def field_default(cls, name: str) -> Any:
        """What a magnitude left at ``None`` means under the "exact" profile (for help texts and types)."""
        return SIM_EXACT.get(name, getattr(cls(), name))


# Settings a profile sets; the others (seed, normalize_scale, distort_first_submap) say how to run.
_PROFILED = (
    "perspective", "shear", "scale", "gauge_scale_ratio", "camera_rotation_deg", "camera_translation",
    "focal_error", "camera_window_frames", "depth_noise", "depth_warp", "depth_warp_length",
    "frame_consistency", "unrelated_overlap", "unrelated_jitter", "flying_px", "flying_jump", "outlier_fraction",
    "outlier_blob_px",
    "outlier_magnitude", "confidence_scale", "confidence_jitter", "outlier_confidence",
)

SIM_EXACT: dict[str, Any] = {
    "perspective": 0.0,
    "shear": 0.0,
    "scale": 0.0,
    "gauge_scale_ratio": 1.0,
    "camera_rotation_deg": 0.0,
    "camera_translation": 0.0,
    "focal_error": 0.0,
    "camera_window_frames": 100,
    "depth_noise": 0.002,
    "depth_warp": 0.0,
    "depth_warp_length": 0.3,
    "frame_consistency": 0.0,
    "unrelated_overlap": 0.0,
    "unrelated_jitter": 0.2,
    "flying_px": 0.0,
    "flying_jump": 0.1,
    "outlier_fraction": 0.02,
    "outlier_blob_px": 12.0,
    "outlier_magnitude": 0.3,
    "confidence_scale": 5.0,
    "confidence_jitter": 0.2,
    "outlier_confidence": 0.02,
}
"""The "exact" profile: one exact SL(4) transform per submap, cameras exact, small depth noise."""

SIM_PROFILE_VALUES: dict[str, dict[str, Any]] = {
    "exact": {},
    # VGGT on indoor video; each value's source is in sl4slam.frontend.simulated's docstring,
    # the resulting statistics are measured by tests/test_sim_profile.py.
    "vggt": dict(
        perspective=0.02, shear=0.01, gauge_scale_ratio=2.0, camera_rotation_deg=0.75,
        camera_translation=0.003, focal_error=0.03, depth_noise=0.005, depth_warp=0.025, frame_consistency=0.8,
        unrelated_overlap=0.05, flying_px=1.5, outlier_fraction=0.02, outlier_magnitude=0.3,
    ),
    # The upper ends of the published ranges, more flying pixels and outliers.
    "hard": dict(
        perspective=0.05, shear=0.03, gauge_scale_ratio=2.0, camera_rotation_deg=1.3,
        camera_translation=0.006, focal_error=0.05, depth_noise=0.01, depth_warp=0.04, frame_consistency=0.6,
        unrelated_overlap=0.1, flying_px=3.0, outlier_fraction=0.05, outlier_magnitude=0.5,
    ),
}
"""Settings of each profile that differ from :data:`SIM_EXACT`."""


def profile_values(profile: str) -> dict[str, Any]:
    """Every error magnitude of ``profile`` (``UserError`` for an unknown one)."""
    if not isinstance(profile, str) or profile not in SIM_PROFILES:
        raise UserError(f"unknown simulator profile {profile!r} (--sim-profile / [sim] profile); use one of "
                        f"{', '.join(SIM_PROFILES)}")
    return {**SIM_EXACT, **SIM_PROFILE_VALUES[profile]}


def apply_sim_profile(sim: SimulatorConfig, profile: str) -> SimulatorConfig:
    """Switch ``sim`` to ``profile`` and forget every explicit error magnitude (in place; returns
    ``sim``), so set explicit values after it. ``seed``, ``normalize_scale`` and
    ``distort_first_submap`` are left alone."""
    profile_values(profile)
    for name in _PROFILED:
        setattr(sim, name, None)
    sim.profile = profile
    return sim


@dataclass
class ModelConfig(Section):
    """The feed-forward model of the frontend (``--model``): its weights and how it computes.

    Settings marked "VGGT" or "Depth Anything 3" apply to that model only; the others to every
    model (``sl4slam models`` lists them)."""

    section: ClassVar[str] = "model"
    common: ClassVar[frozenset[str]] = frozenset({"weights", "dtype"})
    choices: ClassVar[dict[str, tuple[str, ...]]] = {
        "dtype": ("auto", "fp32", "bf16", "fp16", "int8"), "preprocess_mode": ("crop", "pad"),
        "cameras": ("head", "rays")}
    flag_names: ClassVar[dict[str, str]] = {"max_memory_gb": "--max-memory"}
    advanced: ClassVar[frozenset[str]] = frozenset({"match_layer", "head_chunk_frames", "cameras"})

    weights: str = "auto"
    """Local ``.pt`` / ``.safetensors`` file, a folder holding one, or a Hugging Face hub id
    (``owner/name`` or ``owner/name:file``); "auto": the model's released weights (VGGT-1B:
    facebook/VGGT-1B; ``sl4slam models`` lists every model's)."""
    dtype: str = "auto"
    """"auto" (bf16 on GPUs that support it, else fp16; fp32 on CPU), "fp32", "bf16", "fp16", or
    "int8" (VGGT on a CPU: int8 linear layers in the aggregator; measured speed and error in
    benchmarks/results/vggt.md)."""
    preprocess_mode: str = "crop"
    """VGGT preprocessing: "crop" (width 518) or "pad" (square 518)."""
    max_memory_gb: float = 0.0
    """Memory budget of a model forward in GiB (CPU: resident size; GPU: allocated memory), 0: no
    limit. VGGT: picks the dense heads' chunk size per submap and refuses a submap that cannot fit."""
    head_chunk_frames: int = 8
    """VGGT: frames the dense heads decode at once (reference VGGT: 8); the most --max-memory may pick."""
    match_layer: int = 21
    """VGGT: global-attention block (0-based) whose attention gives the loop check's image-match ratio
    (VGGT-SLAM 2.0: 21, the 22nd of VGGT-1B's 24; ``sl4slam.models.vggt.attention``)."""
    cameras: str = "head"
    """Depth Anything 3: where the cameras come from: "head" (its camera decoder, the authors'
    default) or "rays" (recovered from its ray map)."""

    def validate(self) -> None:
        super().validate()
        self._require("weights", bool(self.weights.strip()), "a file path, a Hugging Face hub id, or auto")
        self._require("match_layer", self.match_layer >= 0, ">= 0")
        self._require("max_memory_gb", self.max_memory_gb >= 0, ">= 0 GiB (0: no limit)")
        self._require("head_chunk_frames", self.head_chunk_frames >= 1, "at least 1 frame")


@dataclass
class SourceConfig(Section):
    """Which input frames a run reads (stride and max_frames, applied by the source:
    ``sl4slam.io.open_source``), and what else it knows that the run can use."""

    section: ClassVar[str] = "source"
    common: ClassVar[frozenset[str]] = frozenset({"intrinsics", "max_frames", "stride"})
    flag_names: ClassVar[dict[str, str]] = {"intrinsics": "--intrinsics", "metric_depth": "--metric-depth",
                                            "intrinsics_to_model": "--intrinsics-to-model"}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"metric_depth": ("off", "sensor")}

    stride: int = 1
    """Use every n-th input frame."""
    max_frames: int = 0
    """Stop after this many input frames (after the stride; 0: all)."""
    intrinsics: str = ""
    """A known calibration of the camera: "fx,fy,cx,cy" in the source's pixels, a file (TUM-style
    ``fx = .. fy = .. cx = .. cy = ..``, or a COLMAP cameras.txt), "auto" (the source's own: TUM
    RGB-D and 7-Scenes), or "" (none: the model's guess, the paper's setting). Each frame's points
    are then rebuilt along the known camera's rays from the model's depth, the links between
    submaps carry no calibration term, and the metric upgrade is skipped (``sl4slam.intrinsics``)."""
    intrinsics_to_model: bool = True
    """Also give the known intrinsics to a model that takes a calibration as input (Pi3X, Depth
    Anything 3); off: the points are rebuilt along the known rays only (to tell the two effects apart)."""
    metric_depth: str = "off"
    """"sensor": scale each submap (points and camera translations) by the median ratio of the
    sensor's depth to the model's over its confident pixels with a valid sensor depth (an RGB-D
    source: TUM, 7-Scenes), so that the trajectory and the map come out in metres; "off": the
    model's units (the first submap's)."""

    def validate(self) -> None:
        super().validate()
        self._require("max_frames", self.max_frames >= 0, ">= 0 (0: all)")
        self._require("stride", self.stride >= 1, "at least 1")


@dataclass
class FalseLoopConfig(Section):
    """Wrong places injected into the retrieval's loop proposals, to measure the loop checks
    (``sl4slam.retrieval.false_loops``; needs ground-truth poses and depth)."""

    section: ClassVar[str] = "false_loops"
    flag_prefix: ClassVar[str] = "false-loop-"
    flag_names: ClassVar[dict[str, str]] = {"rate": "--false-loop-rate", "seed": "--false-loop-seed"}
    flag_aliases: ClassVar[dict[str, tuple[str, ...]]] = {
        "rate": ("--sim-false-loop-rate",), "min_distance": ("--sim-false-loop-min-distance",),
        "min_angle": ("--sim-false-loop-min-angle",), "max_overlap": ("--sim-false-loop-max-overlap",)}
    advanced: ClassVar[frozenset[str]] = frozenset({"min_distance", "min_angle", "max_overlap", "seed"})

    rate: float = 0.0
    """Fraction of the retrieval's loop proposals replaced by wrong places. 0: off."""
    min_distance: float = 1.0
    """A wrong place is a keyframe at least this far (metres) from the query's true position ..."""
    min_angle: float = 30.0
    """... or whose true viewing direction differs by at least this many degrees ..."""
    max_overlap: float = 0.05
    """... and which sees at most this fraction of what the query sees (else it is a true revisit
    seen from elsewhere, which a frontend reconstructs correctly)."""
    seed: int = 0
    """Seed of which proposals are replaced and by which wrong place."""

    def validate(self) -> None:
        super().validate()
        self._require("rate", 0 <= self.rate <= 1, "in [0, 1]")
        self._require("min_distance", self.min_distance >= 0, ">= 0 m")
        self._require("min_angle", 0 <= self.min_angle <= 180, "in [0, 180] degrees")
        self._require("max_overlap", 0 <= self.max_overlap <= 1, "in [0, 1]")
        self._require("seed", self.seed >= 0, ">= 0")


@dataclass
class LocalizationConfig(Section):
    """Poses of every frame (``--all-frames``, ``sl4slam.localize``): tracking into the nearest keyframe
    and PnP against its points (defaults: OpenCV's and our measurements on the synthetic world and
    TUM fr1/xyz, benchmarks/results/localize.md)."""

    section: ClassVar[str] = "localize"
    flag_prefix: ClassVar[str] = "localize-"
    advanced: ClassVar[frozenset[str]] = frozenset({
        "max_corners", "corner_quality", "corner_min_distance", "lk_window", "lk_levels", "max_round_trip_px",
        "ransac_threshold_px", "ransac_iterations", "min_inliers", "min_inlier_ratio", "seed"})

    max_corners: int = 500
    """Shi-Tomasi corners per keyframe: a few hundred PnP inliers pin a pose; tracking cost grows
    linearly with the corners."""
    corner_quality: float = 0.01
    """Shi-Tomasi quality level (as the keyframe selector)."""
    corner_min_distance: float = 5.0
    """Minimum spacing of corners, px on the keyframe grid."""
    lk_window: int = 15
    """Lucas-Kanade window, px: tracks travel a few px between neighbouring frames, so a smaller
    window than the keyframe selector's 21 suffices and costs half as much."""
    lk_levels: int = 3
    """Lucas-Kanade pyramid levels above the full image (as the keyframe selector)."""
    max_round_trip_px: float = 1.0
    """Forward-backward tracking error above which a track is dropped."""
    ransac_threshold_px: float = 2.0
    """PnP RANSAC inlier threshold, px."""
    ransac_iterations: int = 200
    """PnP RANSAC hypotheses at most."""
    min_inliers: int = 15
    """Fewer PnP inliers than this is a failed localization."""
    min_inlier_ratio: float = 0.3
    """A pose whose inliers are fewer than this fraction of the tracks is a failed localization."""
    seed: int = 0
    """Seed of OpenCV's RANSAC (combined with the frame index)."""

    def validate(self) -> None:
        super().validate()
        self._require("max_corners", self.max_corners >= 4, "at least 4")
        self._require("min_inliers", self.min_inliers >= 4, "at least 4")
        self._require("corner_quality", 0 < self.corner_quality < 1, "in (0, 1)")
        self._require("corner_min_distance", self.corner_min_distance >= 0, ">= 0 px")
        self._require("lk_window", self.lk_window >= 3, "at least 3 px")
        self._require("lk_levels", self.lk_levels >= 0, ">= 0")
        self._require("ransac_threshold_px", self.ransac_threshold_px > 0, "a positive distance in px")
        self._require("max_round_trip_px", self.max_round_trip_px > 0, "a positive distance in px")
        self._require("ransac_iterations", self.ransac_iterations >= 1, "at least 1")
        self._require("min_inlier_ratio", 0 <= self.min_inlier_ratio <= 1, "in [0, 1]")
        self._require("seed", self.seed >= 0, ">= 0")


@dataclass
class OutputConfig(Section):
    """What a run writes, and how it reports."""

    section: ClassVar[str] = "output"
    flag_names: ClassVar[dict[str, str]] = {"seed": "--map-seed"}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"keyframes": ("compact", "full", "none")}
    advanced: ClassVar[frozenset[str]] = frozenset({"checkpoint_seconds", "progress_every", "seed"})

    voxel_size: float = 0.0
    """Voxel downsampling of ``map.ply`` in world units (0: off)."""
    max_map_points: int = 2_000_000
    """Cap on points written to ``map.ply`` (subsampled at random, seeded by ``seed``)."""
    seed: int = 0
    """Seed of the map's subsampling to ``max_map_points``."""
    keyframes: str = "compact"
    """What ``keyframes/NNNNNN.npz`` holds per keyframe (the exports, the viewer's map, dense
    evaluation and ``--all-frames`` from a folder read it). "compact": the run's own float16 depth
    with the keyframe's camera and projective map, mask, confidence percentile and JPEG colours,
    deflated: the same world points as "full" (0 difference measured), 0.22 MB per keyframe at
    518x392 on the TUM excerpt, 17x smaller (13.5x on the synthetic world;
    ``benchmarks/results/keyframe_format.md``). "full": float32 world points,
    uint8 colours, float16 confidence, uncompressed (3.66 MB at 518x392), for tools that read the
    raw points. "none": no ``keyframes/`` (trajectory and ``map.ply`` only)."""
    cache_frontend: bool = False
    """Store the frontend's outputs so the backend can be re-run without the model."""
    checkpoint_seconds: float = 10.0
    """``trajectory.txt`` and ``summary.json`` are rewritten from the current graph after a submap
    once this many seconds have passed since the last write (0: after every submap), so an
    interrupted run keeps its work."""
    progress_every: int = 10
    """When the output is not a terminal, one progress line every this many submaps."""

    def validate(self) -> None:
        super().validate()
        self._require("voxel_size", self.voxel_size >= 0, ">= 0 world units (0: off)")
        self._require("max_map_points", self.max_map_points >= 1, "at least 1")
        self._require("seed", self.seed >= 0, ">= 0")
        self._require("checkpoint_seconds", self.checkpoint_seconds >= 0, ">= 0 s")
        self._require("progress_every", self.progress_every >= 1, "at least 1")


@dataclass
class UpgradeConfig(Section):
    """Projective-to-metric upgrade of the finished map (``sl4slam.upgrade``): self-calibration
    through the absolute dual quadric (Hartley & Zisserman, Multiple View Geometry, 2nd ed., ch. 19,
    "H&Z") from zero skew, square pixels, a known principal point and one focal length.

    Residuals are unitless: skew / f, fy / fx - 1, principal-point offset / f (and, for the focal
    model, log focal ratios), so 0.01 reads "a hundredth of the focal length"."""

    section: ClassVar[str] = "upgrade"
    flag_prefix: ClassVar[str] = "upgrade-"
    flag_names: ClassVar[dict[str, str]] = {"mode": "--metric-upgrade"}
    choices: ClassVar[dict[str, tuple[str, ...]]] = {
        "mode": ("auto", "on", "off"),
        "focal_model": ("shared", "varying"),
        "loss": ("cauchy", "soft_l1", "huber", "arctan", "linear"),
    }
    advanced: ClassVar[frozenset[str]] = frozenset({
        "focal_weight", "loss", "loss_scale", "outlier_factor", "min_inlier_fraction", "min_keyframes", "running_keyframes",
        "min_condition", "max_uncertainty", "max_iterations", "max_residual_ratio", "metric_residual", "complete_links",
        "max_residual_after", "inconsistent_ratio"})

    mode: str = "auto"
    """"on": estimate the upgrade at the end of a run and apply it to every node, pose and map point
    when it is well conditioned and clearly better; "off": leave the map in the first submap's
    projective frame; "auto": on where links may be 15-DOF, which make the whole map inherit the
    first submap's projective distortion: the SL(4) submap graph (median ATE with / without 0.075 on
    the synthetic world and 0.021 on TUM fr1/desk at perspective 0.1; no run worse than 1.02x;
    benchmarks/results/upgrade_pipeline.md) and the keyframe graph with "select" links
    (benchmarks/results/levers.md); off for calibration links, which carry no such common distortion
    (forced: median 0.84-1.10, single runs up to 1.21x worse), and for the Sim(3) graph, where it is
    almost always skipped anyway."""
    focal_model: str = "shared"
    """"shared": one focal length for every keyframe (one physical camera films the video; the
    strongest constraint, with the fewest critical motions: Sturm, CVPR 1997, vs. varying focal,
    Sturm, ICCV 1999). "varying": each keyframe's focal free (a zoom, or a frontend whose focal
    wanders); no smoothness prior, which would bias a real zoom: the four other constraints per
    camera determine the focal (H&Z 19.3)."""
    focal_weight: float = 1.0
    """Shared model: weight of the focal residual log(f_i / f) against the skew / aspect /
    principal-point residuals; 1: a focal deviation of 0.01 (relative) counts like a principal
    point 0.01 focal lengths off (our choice: the constraints are of like accuracy)."""
    loss: str = "cauchy"
    """Robust loss of the refinement (scipy.optimize.least_squares): "cauchy", "soft_l1", "huber",
    "arctan" or "linear" (none). Our measurement (benchmarks/results/upgrade.md): with 0.1 to 0.4
    of the cameras broken, only "cauchy" was applied every time (at the noise floor); "linear" failed."""
    loss_scale: float = 0.01
    """Residual (unitless) beyond which the robust loss down-weights, the noise expected of a good
    camera. Our measurement on simulated pipeline runs: the kept keyframes fit to an RMS of
    0.0004-0.008 after the upgrade (benchmarks/results/upgrade.md)."""
    outlier_factor: float = 3.0
    """After the robust fit a camera is kept when its residual (RMS of its constraints) is below
    this many ``loss_scale``s; 3: the usual 3-sigma rule with ``loss_scale`` as the noise."""
    min_inlier_fraction: float = 0.5
    """Skip when fewer cameras than this fraction are kept: most keyframes must agree (our choice)."""
    min_keyframes: int = 3
    """Fewest keyframes: the linear absolute-dual-quadric estimate with a known principal point,
    zero skew and unit aspect ratio needs 3 views (H&Z 19.3)."""
    min_condition: float = 1e-3
    """Skip when the refinement's Jacobian at the solution has smallest / largest singular value
    below this (plane at infinity in units of the scene depth): pure rotation, pure translation and
    other critical motions (H&Z 19.9) leave a direction undetermined. Our measurement: hand-held
    paths >= 0.02, degenerate motions <= 1e-4 with 0.003 noise (benchmarks/results/upgrade.md)."""
    max_uncertainty: float = 0.01
    """Skip when the predicted standard deviation of the upgrade (plane at infinity in units of the
    scene depth, calibration in units of the focal; from the residuals and the Jacobian) is above
    this, i.e. a distortion of the map by a hundredth: near-degenerate motion with noisy cameras,
    e.g. a rotation with a baseline of a hundredth of the scene depth. Our measurement: hand-held
    paths and pipeline runs 2e-4 to 7e-3 (benchmarks/results/upgrade.md)."""
    max_iterations: int = 100
    """Most residual evaluations of each robust refinement (scipy's ``max_nfev``); our tests and
    pipeline runs converge within 75, degenerate motions wander until this cap."""
    max_residual_ratio: float = 0.8
    """Never make it worse: apply only when the constraint residual after the upgrade is below
    this fraction of the one before (on the kept cameras), so an already metric map (the residual
    is noise) is left untouched (our choice)."""
    max_residual_after: float = 0.015
    """Never make it worse: when the kept cameras' constraint residual after the upgrade is still
    above this (1.5 ``loss_scale``s), one transform could not make them metric: the map is not one
    projective frame. The upgrade is then skipped unless the distortion it removed was clearly
    larger than that inconsistency (``inconsistent_ratio``), so it does not trade one distortion
    for another. Our measurement (vggt profile, submap graph, 10 runs): runs it helped or left as
    they were ended at 0.009-0.014, the one it made 1.20x worse at 0.016 (a thin margin;
    benchmarks/results/upgrade_pipeline.md)."""
    inconsistent_ratio: float = 0.3
    """See ``max_residual_after``: above it, apply only when the residual fell below this fraction of
    the one before (a large distortion under moderate per-submap errors: 0.7 -> 0.017 in
    tests/test_upgrade.py; the harmful run above: 0.042 -> 0.016)."""
    complete_links: bool = True
    """While a run ends with the upgrade (and its graph holds SL(4) links), a fallback link on a
    planar shared frame, which only its two cameras fix, is completed from the next submap's
    cameras (``sl4slam.completion``): the perspective bending the link left free is chosen so those
    cameras are metric in the running upgrade of the map so far, keeping the map one projective
    frame for the upgrade. Our measurement (synthetic world, perspective 0.1, submap graph, 5 seeds):
    upgraded ATE 0.002-0.016 m with it, 0.015-0.17 m without; links replaced by the exact ones
    gave 0.001-0.005 m (benchmarks/results/upgrade_pipeline.md)."""
    running_keyframes: int = 32
    """The running upgrade that completes planar links estimates the map's metric frame from at most
    this many keyframes of the segment (half of them the newest, where the link is, the other half
    spread evenly over the rest), so its cost stays flat as the map grows: from every keyframe it
    took 1.7 s per submap at 1600 keyframes on this CPU (benchmarks/bench_pipeline.py). The upgrade's
    8 unknowns need 3 cameras (H&Z 19.3); 32 give 160 constraints. The final upgrade uses every
    keyframe."""
    metric_residual: float = 0.002
    """Never make it worse: cameras whose constraint residual (skew, aspect and principal-point
    offset over the focal length) is already below this are metric to within the upgrade's own
    noise and are left alone. TUM fr1/desk with an undistorted first submap: 0.0008, where the
    upgrade moved the keyframes by 0.2 mm (2x the ATE of 0.15 mm, 20x the Sim(3) graph's); a
    0.05 distortion: 0.006 and more (benchmarks/bench_upgrade_pipeline.py)."""

    def validate(self) -> None:
        super().validate()
        self._require("metric_residual", self.metric_residual >= 0, ">= 0")
        self._require("focal_weight", self.focal_weight > 0, "> 0")
        self._require("loss_scale", self.loss_scale > 0, "> 0")
        self._require("outlier_factor", self.outlier_factor >= 1, ">= 1")
        self._require("min_inlier_fraction", 0 < self.min_inlier_fraction <= 1, "in (0, 1]")
        self._require("min_keyframes", self.min_keyframes >= 3, "at least 3 (H&Z 19.3)")
        self._require("running_keyframes", self.running_keyframes >= self.min_keyframes,
                      f"at least --upgrade-min-keyframes ({self.min_keyframes})")
        self._require("min_condition", 0 <= self.min_condition < 1, "in [0, 1)")
        self._require("max_uncertainty", self.max_uncertainty > 0, "> 0")
        self._require("max_iterations", self.max_iterations >= 1, "at least 1")
        self._require("max_residual_ratio", 0 < self.max_residual_ratio <= 1, "in (0, 1]")
        self._require("max_residual_after", self.max_residual_after > 0, "> 0")
        self._require("inconsistent_ratio", 0 < self.inconsistent_ratio <= 1, "in (0, 1]")


@dataclass
class SLAMConfig(Section):
    """Everything a run needs. ``sl4slam.resolve.resolve`` checks it once and settles every "auto"."""

    flag_names: ClassVar[dict[str, str]] = {"frontend": "--frontend"}
    flag_aliases: ClassVar[dict[str, tuple[str, ...]]] = {"frontend": ("--model",)}
    advanced: ClassVar[frozenset[str]] = frozenset({"max_frontend_failures", "overlap"})
    common: ClassVar[frozenset[str]] = frozenset({"frontend", "device"})

    frontend: str = "vggt"
    """The frontend that reconstructs each submap: a model ("vggt", "pi3", "pi3x", "da3-small",
    "da3-base", "da3-large", "da3-giant"; ``sl4slam models`` lists them with their weights and
    licences), "simulated" (VGGT-like submaps from an RGB-D sequence's ground truth), or a model's
    weights (a hub id or a file), whose model is recognized. VGGT-1B is the paper's."""
    device: str = "auto"
    """Where the models run (the frontend's and SALAD's): "auto" (CUDA when available), "cpu",
    "cuda" or "cuda:N"."""
    max_frontend_failures: int = 3
    """A submap on which the frontend fails (an exception, or non-finite output) is skipped; this
    many failures in a row end the run (with its outputs written): the frontend is broken, not the
    frames."""
    overlap: bool = True
    """Run the model on the next submap while the graph, the loop checks and the outputs work on
    this one (one worker, at most one submap waiting; ``sl4slam.schedule``). The results are the same
    as one submap after the other, byte for byte; it needs ``--tau-interval`` >= 1 (the default, 2),
    so that a loop frame never comes from the submap still being worked on."""
    source: SourceConfig = field(default_factory=SourceConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    submap: SubmapConfig = field(default_factory=SubmapConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)
    false_loops: FalseLoopConfig = field(default_factory=FalseLoopConfig)
    sim: SimulatorConfig = field(default_factory=SimulatorConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    upgrade: UpgradeConfig = field(default_factory=UpgradeConfig)
    localize: LocalizationConfig = field(default_factory=LocalizationConfig)

    def validate(self) -> None:
        """Check every section, then the settings that depend on each other (the frontend's name
        and the "auto" rules are checked by ``sl4slam.resolve.resolve``)."""
        super().validate()
        self._require("frontend", bool(self.frontend.strip()), "a model name, simulated, or a model's weights")
        device_ok = self.device in ("auto", "cpu", "cuda") or (self.device.startswith("cuda:") and self.device[5:].isdigit())
        self._require("device", device_ok, "auto, cpu, cuda or cuda:N")
        self._require("max_frontend_failures", self.max_frontend_failures >= 1, "at least 1")
        for section in sections(self):
            section.validate()
        if self.model.dtype == "int8" and self.device.startswith("cuda"):
            raise UserError("--dtype (config key model.dtype) must be auto, fp32, bf16 or fp16 on a GPU "
                            "(int8 runs on the CPU only), got 'int8'")


def sections(config: SLAMConfig) -> list[Section]:
    """The sections of ``config`` in tree order."""
    return [getattr(config, f.name) for f in dataclasses.fields(config) if isinstance(getattr(config, f.name), Section)]


def config_to_dict(config: Any) -> dict:
    """A plain, JSON-serialisable dict of a config tree."""
    return dataclasses.asdict(config)


def _apply(target: Any, values: dict, where: str) -> None:
    names = {f.name: f for f in dataclasses.fields(target)}
    for key, value in values.items():
        if key not in names:
            raise UserError(f"unknown setting '{where}{key}' in config file; valid: {', '.join(sorted(names))}")
        current = getattr(target, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise UserError(f"setting '{where}{key}' must be a table/object of settings")
            _apply(current, value, f"{where}{key}.")
        else:
            expected = current if current is not None else type(target).field_default(key)
            if expected is not None and value is not None and not isinstance(value, type(expected)):
                if isinstance(expected, float) and isinstance(value, int) and not isinstance(value, bool):
                    value = float(value)
                else:
                    raise UserError(
                        f"setting '{where}{key}' must be {type(expected).__name__}, got {value!r}"
                    )
            setattr(target, key, value)


# Settings that moved: (old table, old key) -> (new table, new key); "" is the top level.
_MOVED = {
    ("", "stride"): ("source", "stride"), ("", "max_frames"): ("source", "max_frames"),
    ("vggt", "device"): ("", "device"),
    **{("vggt", key): ("model", key) for key in ("weights", "dtype", "preprocess_mode", "max_memory_gb",
                                                 "head_chunk_frames", "match_layer")},
    **{("sim", f"false_loop_{key}"): ("false_loops", key) for key in ("rate", "min_distance", "min_angle", "max_overlap")},
    ("output", "save_keyframe_points"): ("output", "keyframes"),
}
_MOVED_VALUES = {("output", "save_keyframe_points"): {True: "compact", False: "none"}}
"""Moved settings whose values changed too: (old table, old key) -> {old value: new value}."""


def _move_renamed(values: dict) -> dict:
    """``values`` with settings of earlier releases (``[vggt] weights``, top-level ``stride``,
    ``[sim] false_loop_rate`` ...) under their current keys, with their values translated where
    those changed too (``[output] save_keyframe_points = true / false`` is ``keyframes = "compact" /
    "none"``); the current key wins if both are given."""
    moved = {key: dict(value) if isinstance(value, dict) else value for key, value in values.items()}
    for (old_table, old_key), (new_table, new_key) in _MOVED.items():
        old = moved if not old_table else moved.get(old_table)
        if not isinstance(old, dict) or old_key not in old:
            continue
        value = old.pop(old_key)
        mapping = _MOVED_VALUES.get((old_table, old_key))
        if mapping is not None and isinstance(value, bool):
            value = mapping[value]
        new = moved if not new_table else moved.setdefault(new_table, {})
        if isinstance(new, dict):
            new.setdefault(new_key, value)
    if isinstance(moved.get("vggt"), dict) and not moved["vggt"]:
        del moved["vggt"]
    return moved


def config_from_dict(values: dict, base: SLAMConfig | None = None) -> SLAMConfig:
    """Overlay ``values`` (nested dict) on ``base`` (default: the defaults); keys of earlier
    releases are read under their current names."""
    config = base if base is not None else SLAMConfig()
    _apply(config, _move_renamed(values), "")
    return config


def load_config(path: str | Path, base: SLAMConfig | None = None) -> SLAMConfig:
    """Read a TOML (``.toml``) or JSON file of settings over the defaults."""
    return config_from_dict(read_config_file(path), base)


def read_config_file(path: str | Path) -> dict:
    """The nested dict of settings in a TOML (``.toml``) or JSON file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"config file not found: {path}")
    try:
        if path.suffix.lower() == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib  # type: ignore[no-redef]
            values = tomllib.loads(path.read_text())
        else:
            values = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot parse config file {path}: {exc}") from None
    if not isinstance(values, dict):
        raise UserError(f"config file {path} must hold a table/object of settings")
    return values
