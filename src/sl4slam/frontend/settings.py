"""The frontend's settings: the model's (``[model]``), and the simulated frontend's (``[sim]``) with
its error profiles."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

from ..errors import UserError
from ..section import Section, setting


SIM_PROFILES = ("exact", "vggt", "hard")
"""Error profiles of the simulated frontend (:data:`SIM_PROFILE_VALUES` holds their settings)."""


def magnitude(exact: Any, check: Callable[[Any], bool], allowed: str) -> Any:
    """An error magnitude of the simulator: ``None`` (its profile's value) until set.

    Args:
        exact: its value under the "exact" profile (:data:`SIM_EXACT`).
        check, allowed: its range, as :func:`~sl4slam.section.setting` takes them.
    """
    return setting(None, check=check, allowed=allowed, extra={"exact": exact})


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
    builds: ClassVar[str] = "sl4slam.frontend.simulated:SimulatedFrontend"
    flag_prefix: ClassVar[str] = "sim-"

    profile: str = setting("exact", choices=SIM_PROFILES, common=True)
    """Error profile the settings started from: "exact" (each setting's own default: one exact SL(4)
    transform per submap, cameras exact, small depth noise), "vggt" (calibrated to published VGGT
    figures, cited in ``sl4slam.frontend.simulated``) or "hard" (the upper ends of those ranges, more
    flying pixels and outliers). Fills every magnitude not set explicitly; recorded in summary.json."""
    perspective: float | None = magnitude(0.0, check=lambda v: v >= 0, allowed=">= 0")
    """Norm of the perspective row ``p`` of ``H_s`` (what Sim(3) cannot model), in units of
    1 / (the submap's mean point distance): a point at the mean distance has its homogeneous
    weight changed by up to this fraction. 0: none."""
    shear: float | None = magnitude(0.0, check=lambda v: v >= 0, allowed=">= 0")
    """Spread of the shear / anisotropic stretch ``B`` of ``H_s`` (upper triangular, det 1):
    off-diagonal entries ~ N(0, shear^2), log stretches ~ N(0, shear^2) minus their mean. 0: none."""
    scale: float | None = magnitude(0.0, check=lambda v: v >= 0, allowed=">= 0")
    """Standard deviation of the log of the per-submap global scale of ``H_s``. 0: none."""
    gauge_scale_ratio: float | None = magnitude(1.0,
                                                check=lambda v: 1 <= v <= 10,
                                                allowed="in [1, 10] (1: no scale gauge)")
    """Scale gauge of each submap: its points and camera centres are multiplied by a factor drawn
    log-uniformly in [r^-1/2, r^1/2], so one window's scale relative to any other is within
    [1/r, r] (VGGT: ratios of 0.5 to 2 between consecutive windows are seen in practice, r = 2).
    Rotation and translation of a Sim(3) gauge are fixed by the first camera being [I | 0]. 1: none."""
    normalize_scale: bool = True
    """Scale each submap so the mean distance of its valid true points to the first camera is 1,
    as VGGT normalizes its outputs; off: submaps keep metric units (before ``scale``)."""
    camera_rotation_deg: float | None = magnitude(0.0, check=lambda v: 0 <= v <= 30, allowed="in [0, 30] degrees")
    """Per-frame camera rotation error inside a submap (all frames but the first, which stays
    [I | 0] as VGGT's does): std in degrees of each component of a rotation vector about the
    camera centre. A pair of frames then disagrees by about 2.2x this in median. 0: none
    (decision: docs/decisions/simulator-profiles.md)."""
    camera_translation: float | None = magnitude(0.0,
                                                 check=lambda v: 0 <= v <= 1,
                                                 allowed="in [0, 1] (a fraction of the mean point distance)")
    """Per-frame camera centre error (all frames but the first): std of each coordinate as a
    fraction of the submap's mean true point distance. 0: none."""
    focal_error: float | None = magnitude(0.0, check=lambda v: 0 <= v <= 0.5, allowed="in [0, 0.5]")
    """Per-frame focal error: fx and fy are multiplied by ``exp(focal_error * n)``, n ~ N(0, 1),
    about the principal point, which stays where it is. 0: none
    (decision: docs/decisions/simulator-profiles.md)."""
    camera_window_frames: int | None = magnitude(100, check=lambda v: v >= 1, allowed=">= 1")
    """Window length (frames) beyond which the camera rotation, translation and focal errors grow
    in proportion to the length (decision: docs/decisions/simulator-profiles.md)."""
    depth_noise: float | None = magnitude(0.002, check=lambda v: v >= 0, allowed=">= 0")
    """Relative depth noise sigma: depth is multiplied by ``exp(depth_noise * n)``, n ~ N(0, 1)
    per pixel, so the error grows with depth."""
    depth_warp: float | None = magnitude(0.0, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """Smooth non-projective depth error per frame: depth is multiplied by ``exp(depth_warp * f)``
    with ``f`` a zero-mean, unit-variance smooth random field. 0: none
    (decision: docs/decisions/simulator-profiles.md)."""
    depth_warp_length: float | None = magnitude(0.3,
                                                check=lambda v: v > 0, allowed="> 0 (a fraction of the image width)")
    """Correlation length of the depth warp field as a fraction of the image width."""
    focal_consistency: float = setting(-1.0,
                                       check=lambda v: v == -1 or 0 <= v <= 1,
                                       allowed="-1 (as --sim-frame-consistency) or in [0, 1]")
    """Share of the focal error's variance that belongs to the frame itself; -1: the same as
    ``frame_consistency``. 0 draws each frame's focal length afresh in every window (an uncalibrated
    model whose focal wanders between windows, VGGT-SLAM's premise)."""
    frame_consistency: float | None = magnitude(0.0, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """Share of the variance of a frame's focal error and depth warp that belongs to the frame
    itself, the same in every submap that contains it; the rest is drawn per submap. 0: independent
    per submap (decision: docs/decisions/simulator-profiles.md)."""
    unrelated_overlap: float | None = magnitude(0.0, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """A frame that shares at most this fraction of its view with every other frame of its window
    (true geometry) is an unrelated image to the model, which still places it: at the pose of the
    window frame it looks most like, moved by ``unrelated_jitter`` (VGGT has no "no overlap"
    output). 0: every frame keeps its true pose."""
    unrelated_jitter: float | None = magnitude(0.2, check=lambda v: v >= 0, allowed=">= 0")
    """Spread of that placement: rotation ~ N(0, (unrelated_jitter rad)^2) per axis, centre moved by
    ~ N(0, (unrelated_jitter d)^2) per axis (d the submap's mean point distance)."""
    flying_px: float | None = magnitude(0.0,
                                        check=lambda v: v == 0 or 1 <= v <= 50, allowed="0 (off) or in [1, 50] px")
    """Flying pixels: within this many px of a depth discontinuity, the depth is interpolated
    between the local foreground and background (a random mix per pixel, smooth over the band),
    with the low confidence of outliers (``outlier_confidence``), as a regression head blurs
    depth edges. 0: none."""
    flying_jump: float | None = magnitude(0.1, check=lambda v: v > 0, allowed="> 0")
    """Relative depth jump between two adjacent pixels (larger / smaller - 1) that makes a depth
    discontinuity for ``flying_px``; smooth surfaces, even at grazing angles, stay below it."""
    outlier_fraction: float | None = magnitude(0.02, check=lambda v: 0 <= v < 1, allowed="in [0, 1)")
    """Fraction of each frame's pixels inside outlier blobs (spatially coherent errors)."""
    outlier_blob_px: float | None = magnitude(12.0, check=lambda v: v > 0, allowed="> 0")
    """Typical outlier blob radius in px (correlation length of the blob field)."""
    outlier_magnitude: float | None = magnitude(0.3, check=lambda v: v >= 0, allowed=">= 0")
    """Relative depth error inside outlier blobs: depth is multiplied by ``(1 + m)^s`` with
    ``m`` this value and ``s`` in (-1, 1) a smooth field, mostly near -1 or +1."""
    confidence_scale: float | None = magnitude(5.0, check=lambda v: v > 0, allowed="> 0")
    """Confidence of a clean pixel at the submap's median depth is about ``1 + confidence_scale``;
    it falls inversely with depth (VGGT's confidence is ``1 + exp(x)`` >= 1)."""
    confidence_jitter: float | None = magnitude(0.2, check=lambda v: v >= 0, allowed=">= 0")
    """Log-normal spread of the confidence of clean pixels (so it is not a function of depth alone)."""
    outlier_confidence: float | None = magnitude(0.02, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """Factor on the confidence excess (confidence - 1) inside outlier blobs and on flying pixels;
    pixels with no measured depth (filled from their nearest neighbour) get confidence exactly 1."""
    distort_first_submap: bool = True
    """Distort submap 0 too (``H_s`` and the scale gauge). The world frame is submap 0's frame, so
    its distortion is inherited by every backend alike; switching it off isolates the error that
    alignment adds."""
    seed: int = setting(0, common=True, check=lambda v: v >= 0, allowed=">= 0")
    """Seed (>= 0); ``H_s`` and the gauge are drawn from (seed, submap id), per-frame errors from
    (seed, submap id, frame index)."""
    def validate(self) -> None:
        """The profile's name, then every magnitude's range as the profile fills it in."""
        for name in self.choices:
            self._require_choice(name)
        Section.validate(self.resolved())

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


SIM_EXACT: dict[str, Any] = {f.name: f.metadata["exact"] for f in dataclasses.fields(SimulatorConfig)
                             if "exact" in f.metadata}
"""The "exact" profile: one exact SL(4) transform per submap, cameras exact, small depth noise (the
magnitudes' own values, :func:`magnitude`)."""
_PROFILED = tuple(SIM_EXACT)
"""Settings a profile sets; the others (seed, normalize_scale, distort_first_submap) say how to run."""


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

    weights: str = setting("auto", common=True,
                           check=lambda v: bool(v.strip()), allowed="a file path, a Hugging Face hub id, or auto")
    """Local ``.pt`` / ``.safetensors`` file, a folder holding one, or a Hugging Face hub id
    (``owner/name`` or ``owner/name:file``); "auto": the model's released weights (VGGT-1B:
    facebook/VGGT-1B; ``sl4slam models`` lists every model's)."""
    dtype: str = setting("auto", choices=("auto", "fp32", "bf16", "fp16", "int8"), common=True)
    """"auto" (bf16 on GPUs that support it, else fp16; fp32 on CPU), "fp32", "bf16" (fp16 on a GPU
    that does not run bf16; the run's notes say so), "fp16", or "int8" (VGGT on a CPU: int8 linear
    layers in the aggregator; decision: docs/decisions/int8-cpu.md)."""
    preprocess_mode: str = setting("crop", choices=("crop", "pad"))
    """VGGT preprocessing: "crop" (width 518) or "pad" (square 518)."""
    max_memory_gb: float = setting(0.0, flag='--max-memory',
                                   check=lambda v: v >= 0, allowed=">= 0 GiB (0: no limit)")
    """Memory budget of a model forward in GiB (CPU: resident size; GPU: allocated memory), 0: no
    limit. VGGT: picks the dense heads' chunk size per submap and refuses a submap that cannot fit."""
    head_chunk_frames: int = setting(8, advanced=True, check=lambda v: v >= 1, allowed="at least 1 frame")
    """VGGT: frames the dense heads decode at once (reference VGGT: 8); the most --max-memory may pick."""
    match_layer: int = setting(21, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """VGGT: global-attention block (0-based) whose attention gives the loop check's image-match ratio
    (VGGT-SLAM 2.0: 21, the 22nd of VGGT-1B's 24; ``sl4slam.models.vggt.attention``)."""
    cameras: str = setting("head", choices=("head", "rays"), advanced=True)
    """Depth Anything 3: where the cameras come from: "head" (its camera decoder, the authors'
    default) or "rays" (recovered from its ray map)."""
