"""The graph interface the pipeline talks to: :class:`Backend`, the records it takes
(:class:`SubmapFrames`) and gives (:class:`WorldEstimate`), and its failure (:class:`BackendUpdateError`).

Graph designs. The submap graph (VGGT-SLAM: one node per submap, ``sl4slam.backend.submap``) and
the keyframe graph (VGGT-SLAM 2.0: one node per keyframe, ``sl4slam.backend.keyframe``) take the
same calls: a submap's odometry measurement ``H_prev_cur`` and loops ``H_i_j`` in *submap*
coordinates, with :class:`SubmapFrames` (the submap's keyframes and their extrinsics) and the
loop's two frames, which the submap graph does not need and the keyframe graph uses to place the
measurement between keyframe nodes; both return a :class:`WorldEstimate`. Both run on the iSAM2
pose-graph engine of ``sl4slam.backend.pose_graph``.

Map segments. A measurement that fails its checks, or an update that GTSAM cannot solve, never
ends a run: :meth:`Backend.start_segment` adds the submap with a weak prior at a guess instead of
an odometry factor, and a failed update is rolled back before :class:`BackendUpdateError` is raised.
"""

from __future__ import annotations

import bisect
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Collection

import numpy as np


class BackendUpdateError(RuntimeError):
    """GTSAM could not solve the graph with the latest factors; they were removed again."""


@dataclass(frozen=True)
class SubmapFrames:
    """The keyframes of one submap, as a keyframe graph needs them (the submap graph ignores them).

    Attributes:
        frame_indices: the frames in submap order: the frames shared with the previous submap first
            (``shared`` of them), then the new keyframes (the last ``SubmapConfig.overlap`` of which
            open the next submap).
        T_cam_submap: ``(n, 4, 4)`` float64 their extrinsics (camera-from-submap) in this submap.
        shared: how many leading frames are shared with the previous submap (new there); 0 for a
            submap that shares none. ``True``/``False`` read as 1/0.
        fitted_link: whether the submap's link to the previous one is a 15-DOF fit (the evidence
            of a distortion of the whole window), not a camera link; the keyframe graph then sets
            the stiffness inside the submap from the run's evidence
            (``BackendConfig.frame_scatter_factor``).
        disagreement: how far the window's frames disagree about their surfaces
            (``sl4slam.refine.window_disagreement``, dimensionless); ``None``: not measured. The
            keyframe graph stiffens the links inside the submap by it
            (``BackendConfig.window_agreement_factor``).
    """

    frame_indices: tuple[int, ...]
    T_cam_submap: np.ndarray
    shared: int
    fitted_link: bool = False
    disagreement: float | None = None

    @property
    def new(self) -> range:
        """Positions of the new keyframes."""
        return range(int(self.shared), len(self.frame_indices))


@dataclass
class WorldEstimate:
    """Where the map sits in the world under one estimate of the graph.

    Attributes:
        H_world_submap: ``{submap_id: (4, 4)}`` maps each submap's points into the world (the
            keyframe graph: through the node of the submap's first frame).
        H_world_keyframe: ``{frame_index: (4, 4)}`` maps the points of each keyframe's own submap
            into the world through that keyframe's node, for graphs with a node per keyframe (empty
            for the submap graph, where every keyframe goes through its submap's node).
        polish_blocks: for a polished estimate, how many consecutive blocks of the graph the polish
            took to stay within ``BackendConfig.polish_memory_mib`` (1: the whole graph at once, its
            optimum).
    """

    H_world_submap: dict[int, np.ndarray]
    H_world_keyframe: dict[int, np.ndarray] = field(default_factory=dict)
    polish_blocks: int = 1


class Backend(ABC):
    """A pose graph over the submaps of a run: the interface the pipeline talks to.

    Measurements arrive in submap coordinates (a submap's odometry ``H_prev_cur`` on its shared
    frame, loops ``H_i_j``), with the submap's keyframes (:class:`SubmapFrames`) and each loop's
    two frames, which a graph with a node per keyframe uses to place them; answers come back as a
    :class:`WorldEstimate`. Two designs implement it: the submap graph (``sl4slam.backend.submap``)
    and the keyframe graph (``sl4slam.backend.keyframe``), both on the iSAM2 engine of
    ``sl4slam.backend.pose_graph``.

    Attributes:
        kind: the group ("sl4" or "sim3"); dim: its tangent dimension (15 or 7).
        design: "submap" or "keyframe".
        last_update_seconds: wall time of the most recent :meth:`update` call.
    """

    kind: str = ""
    dim: int = 0
    design: str = ""
    last_update_seconds: float = 0.0

    @abstractmethod
    def add_submap(self, submap_id: int, H_prev_cur: np.ndarray | None, information: np.ndarray | None = None,
                   frames: SubmapFrames | None = None) -> None:
        """Add a submap; ``H_prev_cur`` (4, 4) maps its points into the previously added submap's
        (measured on the shared frame). The first submap takes ``None`` and is anchored at the
        identity. ``information`` ``(dim, dim)`` is the measurement's (``None``: the isotropic
        default), in the tangent of ``H_prev_cur``. ``frames``: the submap's keyframes."""

    @abstractmethod
    def start_segment(self, submap_id: int, H_world_guess: np.ndarray, frames: SubmapFrames | None = None) -> None:
        """Add a submap without odometry: a weak prior at ``H_world_guess`` starts a new map segment."""

    @abstractmethod
    def add_loop(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray | None = None,
                 frames: tuple[int, int] | None = None) -> None:
        """Add a loop closure ``x_i ~ H_i_j x_j`` (4, 4) between existing submaps ``i`` and ``j``;
        ``frames``: the keyframe of ``i`` and the keyframe of ``j`` it ties (the retrieved frame
        and the query keyframe)."""

    @abstractmethod
    def update(self) -> None:
        """Optimize incrementally with everything added since the last call; on failure roll the
        additions back and raise :class:`BackendUpdateError`."""

    @abstractmethod
    def H_world_submap(self, submap_id: int) -> np.ndarray:
        """Current estimate of where submap ``submap_id`` sits, (4, 4) float64."""

    @abstractmethod
    def world_estimate(self, final: bool = False, submaps: Collection[int] | None = None) -> WorldEstimate:
        """The map under iSAM2's current estimate, or (``final``) polished to convergence (O(map)).

        Args:
            final: polish the whole graph first.
            submaps: only these submaps and their keyframes (``None``: every one); each transform is
                the one the whole estimate holds, without converting the rest of the map.
        """

    @abstractmethod
    def freeze(self) -> bool:
        """The run adds nothing more: keep the current estimate and free the incremental solver's
        state (most of the graph's memory), so that the final polish has that room. Reading the
        estimate (:meth:`world_estimate`, ``final`` or not) gives what it gave before; adding to the
        graph, updating it and :meth:`loop_chi2` raise ``RuntimeError`` afterwards. Returns whether
        it is frozen (not while an update is pending: then nothing is freed)."""

    @property
    @abstractmethod
    def num_submaps(self) -> int:
        """Submaps in the graph."""

    @property
    @abstractmethod
    def segments(self) -> list[int]:
        """First submap of every map segment, ascending (the first is the first submap's)."""

    @abstractmethod
    def generators(self) -> np.ndarray:
        """``(dim, 4, 4)`` the tangent basis of the group (``Hat`` of the unit vectors), in which
        information matrices are expressed."""

    @abstractmethod
    def loop_chi2(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray,
                  frames: tuple[int, int] | None = None) -> float:
        """Squared Mahalanobis distance of the loop ``H_i_j`` from the current estimate, under the
        joint covariance of the nodes it ties plus the measurement's own (``information^-1``)."""

    def segment_of(self, submap_id: int) -> int:
        """The map segment (0, 1, ...) that submap ``submap_id`` belongs to: the last one that
        starts at or before it."""
        return bisect.bisect_right(self.segments, submap_id) - 1

    def segments_of(self, submap_ids) -> np.ndarray:
        """``(N,)`` int :meth:`segment_of` of many submaps at once."""
        return np.searchsorted(np.asarray(self.segments), np.asarray(submap_ids), side="right") - 1
