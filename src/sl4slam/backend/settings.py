"""The factor graph's settings (``[backend]``): its group, design, edge weights and solver."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ..registry import graph_entry, graph_names
from ..section import Section, setting


@dataclass
class BackendConfig(Section):
    """Factor graph over submap transforms (paper 4.4)."""

    section: ClassVar[str] = "backend"
    flag_prefix: ClassVar[str] = "backend-"

    kind: str = setting("sl4", choices=("sl4", "sim3"), common=True)
    """"sl4" (15-DOF projective, the paper) or "sim3" (7-DOF similarity, for comparison)."""
    graph: str = setting("auto", choices=("auto", *graph_names()), common=True, flag='--graph')
    """Graph design: "keyframe" (one SL(4) node per keyframe with rigid links inside a submap and
    calibration-and-scale links between submaps, VGGT-SLAM 2.0; ``sl4slam.backend.keyframe``),
    "submap" (one node per submap joined by 15-DOF links, VGGT-SLAM), or "auto": the keyframe graph
    for the SL(4) group, the submap graph for Sim(3). The keyframe graph needs ``kind`` "sl4"
    (decision: docs/decisions/keyframe-graph.md)."""
    frame_sigma: float = setting(0.05, advanced=True)
    """Keyframe graph: isotropic sigma (SL(4) tangent units) of the link between consecutive
    keyframes of a submap, their relative pose from the frontend (reference code: 0.05; the
    frontend reports no per-camera uncertainty to weigh it by)."""
    frame_scatter_factor: float = setting(2.0, advanced=True,
                                          check=lambda v: v >= 0, allowed=">= 0 (0 keeps --backend-frame-sigma)")
    """Keyframe graph: in a submap whose link to the previous one is a 15-DOF fit (``select``
    found a distortion of the whole window, ``sl4slam.alignment.select``), the links between its
    keyframes get this many times the run's median disagreement between consecutive windows about
    their shared frames' relative rotations (radians; at least ``min_sigma``, at most
    ``frame_sigma``); 0 keeps ``frame_sigma`` everywhere. Such a window is consistent inside, and a
    loop must move it whole, as the submap graph's one node does, not bend it
    (decision: docs/decisions/frame-scatter.md)."""
    window_agreement_factor: float = setting(2.0, advanced=True,
                                             check=lambda v: v >= 0, allowed=">= 0 (0: not used)")
    """Keyframe graph: the links between the keyframes of every submap get at most this many times
    how far the window's frames disagree about their surfaces (``sl4slam.refine.window_disagreement``:
    one frame's points on the next frame's surface, their relative depth gaps averaged over blocks
    so that pixel noise drops out; at least ``min_sigma``); 0 does not measure it. A window whose
    frames agree is one reconstruction, however distorted as a whole, which a loop must move whole,
    not bend (decision: docs/decisions/window-agreement.md)."""
    weighting: str = setting("by-link", choices=("by-link", "evidence", "fixed"))
    """Noise of each edge: "evidence" (information from the alignment's own inliers, residuals and
    point spread; see ``sl4slam.backend.evidence``), "fixed" (one isotropic ``sigma`` for every
    edge, as the reference code: VGGT-SLAM 2.0 gives every factor 0.05), or "by-link" (called
    "auto" before): ``sigma`` for
    the edges read from the cameras (calibration-and-scale links, shared-frame similarity), the
    evidence for fitted ones (decision: docs/decisions/edge-weighting.md)."""
    sigma: float = 0.05
    """Isotropic sigma (SL(4) or Sim(3) tangent units) of between factors with fixed weighting, and
    of camera links with "by-link" (reference code: 0.05; decision: docs/decisions/edge-weighting.md)."""
    prior_sigma: float = setting(1e-6, advanced=True)
    """Sigma of the prior on the first submap (reference code: 1e-6)."""
    fallback_sigma_scale: float = setting(2.0, check=lambda v: v >= 1, allowed="at least 1")
    """Sigma multiplier for an edge measured by a fallback (camera-constrained or Sim(3) fit of a
    degenerate frame, or the camera edge of a failed fit), so that loop closures correct those links
    first (decision: docs/decisions/edge-weighting.md)."""
    loop_kernel: str = setting("none", choices=("none", "huber", "cauchy"), advanced=True)
    """Robust kernel on loop factors: "none", "huber" or "cauchy" (loops are verified before they
    reach the graph; see the [loops] settings)."""
    loop_kernel_width: float = setting(1.0, advanced=True)
    """Width of the robust kernel, in whitened residual units."""
    effective_points: float = setting(20.0, advanced=True)
    """Evidence weighting: the alignment residuals of dense points are spatially correlated (the
    model errs in smooth blobs, not per pixel), so an edge counts at most this many independent
    points however many pixels it aligned (decision: docs/decisions/edge-weighting.md)."""
    min_sigma: float = setting(1e-3, advanced=True)
    """Evidence weighting: smallest sigma of any edge direction (tangent units); no edge is more
    certain than this, whatever its point count."""
    max_sigma: float = setting(1.0, advanced=True)
    """Evidence weighting: directions the points do not observe (e.g. a planar shared frame) get
    at most this sigma, which keeps the graph determined without pulling on them."""
    segment_sigma: float = setting(1.0, advanced=True)
    """Sigma of the weak prior that anchors a new map segment (after an edge that failed its checks
    or a graph update that failed): loops can still join segments. At most 1000 ``min_sigma``:
    GTSAM reports weights that span more than about 1e7 as an indeterminate system."""
    relinearize_threshold: float = setting(1e-2, advanced=True)
    """iSAM2 relinearizes a variable whose tangent step (tangent units) exceeds this; GTSAM's
    default: 0.1 (decision: docs/decisions/isam2.md)."""
    relinearize_skip: int = setting(10, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """iSAM2 checks for variables to relinearize at every this many updates (GTSAM's default), and
    at every iteration after a loop (decision: docs/decisions/isam2.md)."""
    wildfire_threshold: float = setting(1e-9, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """iSAM2 stops back-substitution below this change of the step; small, so that one node's
    estimate agrees with the full estimate after a loop."""
    loop_step_threshold: float = setting(5e-2, advanced=True)
    """After loop factors arrive, iSAM2 iterates while some tangent step exceeds this (one default
    sigma): a loop that corrects real drift is absorbed at once, a consistent one costs one step."""
    max_loop_iterations: int = setting(30, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Cap on those extra iterations."""
    revisit_priors: bool = setting(True, advanced=True)
    """Keyframe graph: a loop whose older node lies on a cycle that an earlier loop closed (a revisit of a settled
    place) reaches iSAM2 as a prior on its newer node, the older held at its estimate; the final
    polish at the end of a run optimizes every loop between its two nodes. Keeps the cost of a loop
    update flat in a map that revisits its places lap after lap (decision: docs/decisions/isam2.md)."""
    polish_memory_mib: int = setting(2048, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: no limit)")
    """Memory (MiB) the final polish of the graph may take. A graph whose exact polish would take
    more (estimated from its structure before any work: a long run that revisits its places many
    times, every visit tied to the others) is polished in consecutive blocks of nodes, oldest
    first, each exact given the blocks before it; the run's notes say so. 0: always the whole graph
    at once (decision: docs/decisions/polish-memory.md)."""

    def setup(self, resolved: Any) -> Any:
        """The graph of the settled design ``graph``, built by its catalog entry (``sl4slam.registry``).

        Args:
            resolved: the run's resolved config (``sl4slam.resolve.ResolvedConfig``), whose tree
                holds this section.
        """
        return graph_entry(self.graph).build(resolved)

    def validate(self) -> None:
        super().validate()
        for name in ("sigma", "prior_sigma", "loop_kernel_width", "effective_points", "min_sigma", "max_sigma",
                     "segment_sigma", "relinearize_threshold", "loop_step_threshold", "frame_sigma"):
            self._require(name, getattr(self, name) > 0, "a positive number")
        self._require("max_sigma", self.min_sigma <= self.max_sigma <= 1000 * self.min_sigma,
                      f"between --backend-min-sigma and 1000 times it ({self.min_sigma}, {1000 * self.min_sigma})")
        self._require("segment_sigma", self.segment_sigma <= 1000 * self.min_sigma,
                      f"at most 1000 times --backend-min-sigma ({1000 * self.min_sigma})")
        self._require("frame_sigma", self.frame_sigma <= 1000 * self.min_sigma,
                      f"at most 1000 times --backend-min-sigma ({1000 * self.min_sigma})")
