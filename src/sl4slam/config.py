"""One dataclass tree for every setting of the pipeline.

Defaults cite VGGT-SLAM (Maggio, Lim, Carlone, NeurIPS 2025), section 5.1 ("paper"), or the
authors' code ("reference code"). The command line is generated from this tree
(``sl4slam.cli``) and the same tree can be read from a TOML or JSON file.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import UserError


@dataclass
class KeyframeConfig:
    """Keyframe selection by Lucas-Kanade disparity (paper 4.1)."""

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


@dataclass
class SubmapConfig:
    """Submap assembly (paper 4.1, 5.1)."""

    size: int = 16
    """New keyframes per submap, w. Paper evaluates 8/16/32 (tables use 32); reference CLI: 16."""
    w_loop: int = 1
    """Loop frames appended to a submap (paper: 1)."""
    tau_conf: float = 25.0
    """Percentile of the submap's confidence below which pixels are dropped (reference code: 25)."""
    use_point_head: bool = False
    """Use the frontend's point map instead of unprojecting depth (VGGT offers both)."""


@dataclass
class AlignmentConfig:
    """Relative alignment of consecutive submaps (paper 4.2)."""

    ransac_iterations: int = 300
    """Most RANSAC hypotheses (paper: 300, always drawn in full there)."""
    ransac_confidence: float = 0.999
    """Stop drawing hypotheses once an all-inlier sample has been drawn with this probability,
    judged from the best hypothesis' inlier fraction (classic adaptive RANSAC; the reference code
    always draws all of them)."""
    inlier_threshold: float = 0.01
    """Inlier distance in submap units (paper: 0.01)."""
    max_correspondences: int = 30000
    """Pixels of the shared frame passed to the alignment; beyond this an evenly strided subset
    (about a quarter of a 518x294 frame's confident pixels) — as accurate, several times faster."""
    max_points: int = 10000
    """Correspondences each hypothesis is scored on; larger sets are subsampled (seeded). The
    final inlier mask is computed on every point."""
    max_refit_points: int = 20000
    """Inliers used by each least-squares refit (an evenly strided subset beyond this)."""
    min_inliers: int = 50
    """Fewer inliers than this makes the 15-DOF fit degenerate: fall back to Sim(3)."""
    planarity_threshold: float = 0.02
    """Spread of the points along their thinnest principal axis relative to the widest
    (interdecile ranges, robust to a few off-plane points) below which they count as coplanar:
    the 15-DOF fit is degenerate and a constrained model is used instead."""
    refit: bool = True
    """Least-squares refit of H on all inliers, then re-score (the reference code does not)."""
    seed: int = 0
    """Seed of the RANSAC sampler (combined with the submap id)."""


@dataclass
class BackendConfig:
    """Factor graph over submap transforms (paper 4.4)."""

    kind: str = "sl4"
    """"sl4" (15-DOF projective, the paper) or "sim3" (7-DOF similarity, for comparison)."""
    sigma: float = 0.05
    """Isotropic sigma of between factors (reference code: 0.05)."""
    prior_sigma: float = 1e-6
    """Sigma of the prior on the first submap (reference code: 1e-6)."""
    fallback_sigma_scale: float = 10.0
    """Sigma multiplier for odometry measured by a fallback (degenerate-scene) fit, so that loop
    closures correct those links first."""
    loop_kernel: str = "none"
    """Robust kernel on loop factors: "none", "huber" or "cauchy"."""
    loop_kernel_width: float = 1.0
    """Width of the robust kernel, in whitened residual units."""


@dataclass
class RetrievalConfig:
    """Loop-closure retrieval (paper 4.3)."""

    kind: str = "auto"
    """"salad" (the paper's SALAD descriptors), "orb" (weights-free, CPU), "none", or "auto": SALAD
    when its weights are found locally (``salad_weights`` or the user cache), else ORB."""
    tau_interval: int = 2
    """Most recent submaps excluded from retrieval (paper: 2)."""
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
    min_loop_inlier_ratio: float = 0.3
    """A retrieved loop is added to the graph only if its alignment keeps this inlier fraction
    (or half the odometry's median, if that is lower) and needed no fallback: one false loop
    bends the whole map."""


@dataclass
class SimulatorConfig:
    """Corruption model of the simulated frontend (``sl4slam.frontend.simulated`` documents it in full).

    Every submap gets its own projective distortion ``H_s`` in SL(4); every frame of every submap
    gets its own depth noise, outlier blobs and confidence. All of it is drawn from ``seed``, the
    submap id and the frame indices, so a run is exactly reproducible.
    """

    perspective: float = 0.0
    """Norm of the perspective row ``p`` of ``H_s`` (what Sim(3) cannot model), in units of
    1 / (the submap's mean point distance): a point at the mean distance has its homogeneous
    weight changed by up to this fraction. 0: none."""
    shear: float = 0.0
    """Spread of the shear / anisotropic stretch ``B`` of ``H_s`` (upper triangular, det 1):
    off-diagonal entries ~ N(0, shear^2), log stretches ~ N(0, shear^2) minus their mean. 0: none."""
    scale: float = 0.0
    """Standard deviation of the log of the per-submap global scale of ``H_s``. 0: none."""
    normalize_scale: bool = True
    """Scale each submap so the mean distance of its valid true points to the first camera is 1,
    as VGGT normalizes its outputs; off: submaps keep metric units (before ``scale``)."""
    depth_noise: float = 0.002
    """Relative depth noise sigma: depth is multiplied by ``exp(depth_noise * n)``, n ~ N(0, 1)
    per pixel, so the error grows with depth."""
    outlier_fraction: float = 0.02
    """Fraction of each frame's pixels inside outlier blobs (spatially coherent errors)."""
    outlier_blob_px: float = 12.0
    """Typical outlier blob radius in px (correlation length of the blob field)."""
    outlier_magnitude: float = 0.3
    """Relative depth error inside outlier blobs: depth is multiplied by ``(1 + m)^s`` with
    ``m`` this value and ``s`` in (-1, 1) a smooth field, mostly near -1 or +1."""
    confidence_scale: float = 5.0
    """Confidence of a clean pixel at the submap's median depth is about ``1 + confidence_scale``;
    it falls inversely with depth (VGGT's confidence is ``1 + exp(x)`` >= 1)."""
    confidence_jitter: float = 0.2
    """Log-normal spread of the confidence of clean pixels (so it is not a function of depth alone)."""
    outlier_confidence: float = 0.02
    """Factor on the confidence excess (confidence - 1) inside outlier blobs; pixels with no
    measured depth (filled from their nearest neighbour) get confidence exactly 1."""
    distort_first_submap: bool = True
    """Distort submap 0 too. The world frame is submap 0's frame, so its distortion is inherited
    by every backend alike; switching it off isolates the error that alignment adds."""
    seed: int = 0
    """Seed (>= 0); ``H_s`` is drawn from (seed, submap id), noise from (seed, submap id, frame index)."""


@dataclass
class VGGTConfig:
    """VGGT frontend."""

    weights: str = "facebook/VGGT-1B"
    """Local ``.pt`` / ``.safetensors`` file or Hugging Face hub id (model.pt)."""
    device: str = "auto"
    """"auto" (CUDA when available), "cpu" or "cuda"."""
    dtype: str = "auto"
    """"auto" (bf16 on GPUs that support it, else fp16; fp32 on CPU), "fp32", "bf16", "fp16"."""
    preprocess_mode: str = "crop"
    """VGGT preprocessing: "crop" (width 518) or "pad" (square 518)."""


@dataclass
class OutputConfig:
    """What a run writes."""

    voxel_size: float = 0.0
    """Voxel downsampling of ``map.ply`` in world units (0: off)."""
    max_map_points: int = 2_000_000
    """Cap on points written to ``map.ply`` (evenly subsampled, seeded)."""
    save_keyframe_points: bool = True
    """Write per-keyframe world points and masks for dense evaluation."""
    cache_frontend: bool = False
    """Store the frontend's outputs so the backend can be re-run without the model."""


UPGRADE_FOCAL_MODELS = ("shared", "varying")
UPGRADE_LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


@dataclass
class UpgradeConfig:
    """Projective-to-metric upgrade of the finished map (``sl4slam.upgrade``): self-calibration
    through the absolute dual quadric (Hartley & Zisserman, Multiple View Geometry, 2nd ed., ch. 19,
    "H&Z") from zero skew, square pixels, a known principal point and one focal length.

    Residuals are unitless: skew / f, fy / fx - 1, principal-point offset / f (and, for the focal
    model, log focal ratios), so 0.01 reads "a hundredth of the focal length"."""

    enabled: bool = True
    """Estimate the upgrade (it is applied only when well conditioned and clearly better)."""
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
    0.0008-0.008 after the upgrade (benchmarks/results/upgrade.md)."""
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

    def validate(self) -> None:
        """Raise ``UserError`` (one line) for settings the upgrade cannot run with."""
        if not isinstance(self.enabled, bool):
            raise UserError(f"--upgrade-enabled must be true or false, got {self.enabled!r}")
        if self.focal_model not in UPGRADE_FOCAL_MODELS:
            raise UserError(f"unknown --upgrade-focal-model '{self.focal_model}': use 'shared' or 'varying'")
        if self.loss not in UPGRADE_LOSSES:
            raise UserError(f"unknown --upgrade-loss '{self.loss}': use one of {', '.join(UPGRADE_LOSSES)}")
        checks = [
            ("focal-weight", self.focal_weight, self.focal_weight > 0, "> 0"),
            ("loss-scale", self.loss_scale, self.loss_scale > 0, "> 0"),
            ("outlier-factor", self.outlier_factor, self.outlier_factor >= 1, ">= 1"),
            ("min-inlier-fraction", self.min_inlier_fraction, 0 < self.min_inlier_fraction <= 1, "in (0, 1]"),
            ("min-keyframes", self.min_keyframes, self.min_keyframes >= 3, ">= 3 (H&Z 19.3)"),
            ("min-condition", self.min_condition, 0 <= self.min_condition < 1, "in [0, 1)"),
            ("max-uncertainty", self.max_uncertainty, self.max_uncertainty > 0, "> 0"),
            ("max-iterations", self.max_iterations, self.max_iterations >= 1, ">= 1"),
            ("max-residual-ratio", self.max_residual_ratio, 0 < self.max_residual_ratio <= 1, "in (0, 1]"),
        ]
        for flag, value, ok, allowed in checks:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (np.isfinite(value) and ok):
                raise UserError(f"--upgrade-{flag} must be {allowed}, got {value!r}")


@dataclass
class SLAMConfig:
    """Everything a run needs."""

    frontend: str = "vggt"
    """"vggt" or "simulated"."""
    max_frames: int = 0
    """Stop after this many input frames (0: all)."""
    stride: int = 1
    """Use every n-th input frame."""
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    submap: SubmapConfig = field(default_factory=SubmapConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    sim: SimulatorConfig = field(default_factory=SimulatorConfig)
    vggt: VGGTConfig = field(default_factory=VGGTConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    upgrade: UpgradeConfig = field(default_factory=UpgradeConfig)


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
            if current is not None and value is not None and not isinstance(value, type(current)):
                if isinstance(current, float) and isinstance(value, int):
                    value = float(value)
                else:
                    raise UserError(
                        f"setting '{where}{key}' must be {type(current).__name__}, got {value!r}"
                    )
            setattr(target, key, value)


def config_from_dict(values: dict, base: SLAMConfig | None = None) -> SLAMConfig:
    """Overlay ``values`` (nested dict) on ``base`` (default: the defaults)."""
    config = base if base is not None else SLAMConfig()
    _apply(config, values, "")
    return config


def load_config(path: str | Path, base: SLAMConfig | None = None) -> SLAMConfig:
    """Read a TOML (``.toml``) or JSON file of settings over the defaults."""
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
    return config_from_dict(values, base)
