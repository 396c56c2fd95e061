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


SIM_PROFILES = ("exact", "vggt", "hard")
"""Error profiles of the simulated frontend (:data:`SIM_PROFILE_VALUES` holds their settings)."""


@dataclass
class SimulatorConfig:
    """Corruption model of the simulated frontend (``sl4slam.frontend.simulated`` documents it in full).

    Every submap gets its own projective distortion ``H_s`` in SL(4) and scale gauge; every frame of
    every submap gets its own camera and focal error, depth noise, smooth depth warp, flying pixels at
    depth edges, outlier blobs and confidence. All of it is drawn from ``seed``, the submap id and the
    frame indices, so a run is exactly reproducible. ``profile`` sets the defaults of all error
    magnitudes at once (``SimulatorConfig.from_profile``, ``--sim-profile``, ``[sim] profile``);
    explicit settings override it.
    """

    profile: str = "exact"
    """Error profile the settings started from: "exact" (each setting's own default: one exact SL(4)
    transform per submap, cameras exact, small depth noise), "vggt" (calibrated to published VGGT
    figures, cited in ``sl4slam.frontend.simulated``) or "hard" (the upper ends of those ranges, more
    flying pixels and outliers). Applied before any explicit setting; recorded in summary.json."""
    perspective: float = 0.0
    """Norm of the perspective row ``p`` of ``H_s`` (what Sim(3) cannot model), in units of
    1 / (the submap's mean point distance): a point at the mean distance has its homogeneous
    weight changed by up to this fraction. 0: none."""
    shear: float = 0.0
    """Spread of the shear / anisotropic stretch ``B`` of ``H_s`` (upper triangular, det 1):
    off-diagonal entries ~ N(0, shear^2), log stretches ~ N(0, shear^2) minus their mean. 0: none."""
    scale: float = 0.0
    """Standard deviation of the log of the per-submap global scale of ``H_s``. 0: none."""
    gauge_scale_ratio: float = 1.0
    """Scale gauge of each submap: its points and camera centres are multiplied by a factor drawn
    log-uniformly in [r^-1/2, r^1/2], so one window's scale relative to any other is within
    [1/r, r] (VGGT: ratios of 0.5 to 2 between consecutive windows are seen in practice, r = 2).
    Rotation and translation of a Sim(3) gauge are fixed by the first camera being [I | 0]. 1: none."""
    normalize_scale: bool = True
    """Scale each submap so the mean distance of its valid true points to the first camera is 1,
    as VGGT normalizes its outputs; off: submaps keep metric units (before ``scale``)."""
    camera_rotation_deg: float = 0.0
    """Per-frame camera rotation error inside a submap (all frames but the first, which stays
    [I | 0] as VGGT's does): std in degrees of each component of a rotation vector about the
    camera centre. A pair of frames then disagrees by about 2.2x this in median (VGGT on indoor
    video: 1-3 degrees median relative rotation error, Depth Anything 3's table). 0: none."""
    camera_translation: float = 0.0
    """Per-frame camera centre error (all frames but the first): std of each coordinate as a
    fraction of the submap's mean true point distance. 0: none."""
    focal_error: float = 0.0
    """Per-frame focal error: fx and fy are multiplied by ``exp(focal_error * n)``, n ~ N(0, 1),
    about the principal point, which stays where it is (VGGT assumes the image centre; its focal
    length is off by up to about 7 %). 0: none."""
    camera_window_frames: int = 100
    """Window length (frames) beyond which the camera rotation, translation and focal errors grow
    in proportion to the length (VGGT's quality falls as windows grow past about 100 frames)."""
    depth_noise: float = 0.002
    """Relative depth noise sigma: depth is multiplied by ``exp(depth_noise * n)``, n ~ N(0, 1)
    per pixel, so the error grows with depth."""
    depth_warp: float = 0.0
    """Smooth non-projective depth error per frame: depth is multiplied by ``exp(depth_warp * f)``
    with ``f`` a zero-mean, unit-variance smooth random field (VGGT's depth errors are mostly
    low-frequency; AbsRel 2-4 % indoors). 0: none."""
    depth_warp_length: float = 0.3
    """Correlation length of the depth warp field as a fraction of the image width."""
    frame_consistency: float = 0.0
    """Share of the variance of a frame's focal error and depth warp that belongs to the frame
    itself, the same in every submap that contains it; the rest is drawn per submap. VGGT's depth
    and focal length come mostly from the image itself, so two windows sharing a frame predict it
    alike (the paper's RANSAC inlier threshold, 1 % of the scene scale between the shared frame's
    two predictions, presumes so). 0: independent per submap."""
    flying_px: float = 0.0
    """Flying pixels: within this many px of a depth discontinuity, the depth is interpolated
    between the local foreground and background (a random mix per pixel, smooth over the band),
    with the low confidence of outliers (``outlier_confidence``), as a regression head blurs
    depth edges. 0: none."""
    flying_jump: float = 0.1
    """Relative depth jump (local background / foreground - 1 within ``flying_px``) that counts as
    a depth discontinuity for ``flying_px``."""
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
    """Factor on the confidence excess (confidence - 1) inside outlier blobs and on flying pixels;
    pixels with no measured depth (filled from their nearest neighbour) get confidence exactly 1."""
    distort_first_submap: bool = True
    """Distort submap 0 too (``H_s`` and the scale gauge). The world frame is submap 0's frame, so
    its distortion is inherited by every backend alike; switching it off isolates the error that
    alignment adds."""
    seed: int = 0
    """Seed (>= 0); ``H_s`` and the gauge are drawn from (seed, submap id), per-frame errors from
    (seed, submap id, frame index)."""

    @classmethod
    def from_profile(cls, profile: str, **overrides: Any) -> "SimulatorConfig":
        """Settings of ``profile`` with ``overrides`` on top (the Python form of ``--sim-profile``)."""
        config = cls()
        apply_sim_profile(config, profile)
        for key, value in overrides.items():
            if key not in {f.name for f in dataclasses.fields(cls)} or key == "profile":
                raise UserError(f"unknown simulator setting '{key}'")
            setattr(config, key, value)
        return config


# Settings a profile sets; the others (seed, normalize_scale, distort_first_submap) say how to run.
_PROFILED = (
    "perspective", "shear", "scale", "gauge_scale_ratio", "camera_rotation_deg", "camera_translation",
    "focal_error", "camera_window_frames", "depth_noise", "depth_warp", "depth_warp_length", "frame_consistency", "flying_px",
    "flying_jump", "outlier_fraction", "outlier_blob_px", "outlier_magnitude", "confidence_scale",
    "confidence_jitter", "outlier_confidence",
)

SIM_PROFILE_VALUES: dict[str, dict[str, Any]] = {
    # The defaults above, bit for bit.
    "exact": {},
    # VGGT on indoor video; each value's source is in sl4slam.frontend.simulated's docstring,
    # the resulting statistics are measured by tests/test_sim_profile.py.
    "vggt": dict(
        perspective=0.02, shear=0.01, gauge_scale_ratio=2.0, camera_rotation_deg=0.75, camera_translation=0.003,
        focal_error=0.03, depth_noise=0.005, depth_warp=0.025, frame_consistency=0.8, flying_px=1.5, outlier_fraction=0.02,
        outlier_magnitude=0.3,
    ),
    # The upper ends of the published ranges, more flying pixels and outliers.
    "hard": dict(
        perspective=0.05, shear=0.03, gauge_scale_ratio=2.0, camera_rotation_deg=1.3, camera_translation=0.006,
        focal_error=0.05, depth_noise=0.01, depth_warp=0.04, frame_consistency=0.6, flying_px=3.0, outlier_fraction=0.05,
        outlier_magnitude=0.5,
    ),
}
"""Settings of each profile that differ from the defaults (``exact`` is the defaults)."""


def apply_sim_profile(sim: SimulatorConfig, profile: str) -> SimulatorConfig:
    """Set every error magnitude of ``sim`` to ``profile``'s value (in place; returns ``sim``).

    Settings the profile does not name get their default, so applying a profile undoes any earlier
    setting: apply it first, then explicit settings. ``seed``, ``normalize_scale`` and
    ``distort_first_submap`` are left alone.
    """
    if not isinstance(profile, str) or profile not in SIM_PROFILES:
        raise UserError(f"unknown simulator profile {profile!r} (--sim-profile / [sim] profile); use one of "
                        f"{', '.join(SIM_PROFILES)}")
    defaults = SimulatorConfig()
    for name in _PROFILED:
        setattr(sim, name, SIM_PROFILE_VALUES[profile].get(name, getattr(defaults, name)))
    sim.profile = profile
    return sim


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
    """Overlay ``values`` (nested dict) on ``base`` (default: the defaults).

    A ``profile`` key of the ``sim`` table is applied before the table's other keys, whatever
    their order, so explicit simulator settings override the profile's.
    """
    config = base if base is not None else SLAMConfig()
    sim_values = values.get("sim")
    if isinstance(sim_values, dict) and "profile" in sim_values:
        apply_sim_profile(config.sim, sim_values["profile"])
    _apply(config, values, "")
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
