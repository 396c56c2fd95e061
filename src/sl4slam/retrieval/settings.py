"""Loop retrieval's settings (``[retrieval]``) and the injected false loops' (``[false_loops]``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ..registry import retrieval_entry, retrieval_names
from ..section import Section, setting


@dataclass
class RetrievalConfig(Section):
    """Loop-closure retrieval (paper 4.3)."""

    section: ClassVar[str] = "retrieval"

    kind: str = setting("auto", choices=("auto", *retrieval_names()), common=True)
    """"salad" (the paper's SALAD descriptors), "orb" (weights-free, CPU), "none", or "auto": SALAD
    when its weights are found locally (``salad_weights`` or the user cache), else ORB."""
    tau_interval: int = setting(2, check=lambda v: v >= 0, allowed=">= 0")
    """Most recent submaps excluded from retrieval (paper: 2)."""
    seed: int = setting(0, flag='--retrieval-seed', check=lambda v: v >= 0, allowed=">= 0")
    """Seed of the ORB retrieval's geometric verification (fundamental-matrix RANSAC)."""
    tau_desc: float = setting(0.8, check=lambda v: v > 0, allowed="a positive descriptor distance")
    """SALAD only: accept when the L2 descriptor distance is below this (paper: 0.8)."""
    salad_weights: str | None = None
    """Path to ``dino_salad.ckpt``; ``None`` uses the user cache (downloaded on first use)."""
    salad_image_size: int = setting(224, advanced=True,
                                    check=lambda v: v >= 14 and v % 14 == 0,
                                    allowed="a positive multiple of 14 px (DINOv2 patches)")
    """SALAD input size in px (reference SLAM code: 224; SALAD's evaluation: 322)."""
    orb_features: int = setting(1000, advanced=True,
                                check=lambda v: v >= 8,
                                allowed="at least 8 (the fundamental matrix needs 8 matches)")
    """ORB: features per keyframe."""
    orb_min_inliers: int = setting(40, check=lambda v: v >= 8, allowed="at least 8")
    """ORB: geometrically verified matches (fundamental-matrix RANSAC inliers) to accept a loop."""
    orb_candidates: int = setting(5, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """ORB: (query, stored) pairs per submap, ranked by bag-of-words similarity, that are
    geometrically verified (a fixed budget, so the cost does not grow with the submap size)."""
    orb_ratio: float = setting(0.8, advanced=True, check=lambda v: 0 < v <= 1, allowed="in (0, 1]")
    """ORB: Lowe's ratio test threshold of a tentative match (Lowe 2004: 0.8)."""
    orb_max_hamming: float = setting(64.0, advanced=True, check=lambda v: 0 < v <= 256, allowed="in (0, 256]")
    """ORB: largest Hamming distance (of 256 bits) of a tentative match (ORB-SLAM uses 50-100)."""
    orb_epipolar_threshold_px: float = setting(1.5, advanced=True,
                                               check=lambda v: v > 0, allowed="a positive distance in px")
    """ORB: fundamental-matrix RANSAC inlier distance to the epipolar line, px at the working
    resolution."""
    orb_max_image_side: int = setting(640, advanced=True, check=lambda v: v >= 64, allowed="at least 64 px")
    """ORB: images whose longer side exceeds this (px) are downscaled to it before extraction, so
    cost and the epipolar threshold do not depend on the input size."""

    orb_coarse_flat_rows: int = setting(4096, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: always by groups)")
    """ORB: up to this many eligible stored keyframes, the coarse ranking scores every one; beyond,
    it first ranks groups of consecutive keyframes by their mean similarity and scores only the
    keyframes of each query's ``orb_coarse_groups`` best groups, so the ranking's cost grows 16
    times slower than the map (decision: docs/decisions/bounded-retrieval.md)."""
    orb_coarse_groups: int = setting(32, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """ORB: groups of consecutive stored keyframes kept per query keyframe by the grouped coarse
    ranking (``orb_coarse_flat_rows``)."""

    def setup(self, resolved: Any) -> Any:
        """The retrieval of the settled ``kind`` (``None`` for "none"), built by its catalog entry
        (``sl4slam.registry``).

        Args:
            resolved: the run's resolved config (``sl4slam.resolve.ResolvedConfig``), whose tree
                holds this section.
        """
        return retrieval_entry(self.kind).build(resolved)


@dataclass
class FalseLoopConfig(Section):
    """Wrong places injected into the retrieval's loop proposals, to measure the loop checks
    (``sl4slam.retrieval.false_loops``; needs ground-truth poses and depth)."""

    section: ClassVar[str] = "false_loops"
    flag_prefix: ClassVar[str] = "false-loop-"

    rate: float = setting(0.0, flag='--false-loop-rate', aliases=('--sim-false-loop-rate',),
                          check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """Fraction of the retrieval's loop proposals replaced by wrong places. 0: off."""
    min_distance: float = setting(1.0, advanced=True, aliases=('--sim-false-loop-min-distance',),
                                  check=lambda v: v >= 0, allowed=">= 0 m")
    """A wrong place is a keyframe at least this far (metres) from the query's true position ..."""
    min_angle: float = setting(30.0, advanced=True, aliases=('--sim-false-loop-min-angle',),
                               check=lambda v: 0 <= v <= 180, allowed="in [0, 180] degrees")
    """... or whose true viewing direction differs by at least this many degrees ..."""
    max_overlap: float = setting(0.05, advanced=True, aliases=('--sim-false-loop-max-overlap',),
                                 check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """... and which sees at most this fraction of what the query sees (else it is a true revisit
    seen from elsewhere, which a frontend reconstructs correctly)."""
    seed: int = setting(0, advanced=True, flag='--false-loop-seed', check=lambda v: v >= 0, allowed=">= 0")
    """Seed of which proposals are replaced and by which wrong place."""
