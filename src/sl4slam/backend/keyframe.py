"""The keyframe graph (VGGT-SLAM 2.0): one SL(4) node per keyframe.

Nodes. ``X_n = H_world_cam`` for every keyframe of every submap: it maps that keyframe's camera frame,
as the submap reconstructed it, into the world. The keyframe's world camera is ``K [I | 0] X_n^-1``
and its submap's points reach the world through ``X_n T_cam_submap`` (so a submap graph node
``H_world_submap`` corresponds to ``X_n T_cam_submap`` of any of its keyframes). The shared frame of two
consecutive submaps has a node in each.

Factors (``x_a ~ Z x_b`` read as in ``sl4slam.backend.pose_graph``, whose factor residual they use):

- inside a submap, between consecutive keyframes ``a`` and ``b``: the frontend's relative pose
  ``T_cam_a_submap T_cam_b_submap^-1`` (rigid), isotropic ``BackendConfig.frame_sigma``; in a
  submap whose link is a 15-DOF fit, stiffer where consecutive windows agree about their shared
  frames better than that (:meth:`KeyframeBackend.chain_sigma`);
- between submaps, between the previous submap's last node and this submap's first: the odometry
  measurement, which the pipeline hands over in submap coordinates (``H_prev_cur``, measured on the
  frames the two submaps share), moved onto the nodes: ``L = T_cam,prev H_prev_cur T_cam,cur^-1``.
  With one shared frame these are that frame's two nodes. For the "calibration" alignment this is exactly the
  calibration-and-scale link ``K_prev^-1 K_cur diag(s, s, s, 1)`` (``sl4slam.alignment.sim3.calibration_scale_link``);
  for a 15-DOF fit it is that fit seen from the shared camera. Its information (from
  ``sl4slam.backend.evidence``, in the tangent of ``H_prev_cur``) is moved with it by the adjoint
  (:func:`transport_information`), so the edge claims the same certainty about the same thing;
- loops: between the retrieved frame's node (in its old submap) and the query keyframe's node, the
  loop measurement moved the same way;
- a prior (``prior_sigma``) on the first node at ``T_cam_submap^-1`` of the first keyframe, so the
  world frame is submap 0's as in the submap graph; a weak prior (``segment_sigma``) on the first
  node of every new map segment.

Without loops the graph is a tree (chains joined by single links), so every factor is met exactly
and the estimate equals the submap graph's with the same odometry measurements, whatever the sigmas:
the designs differ only where loops close, where this graph also bends the links inside submaps.

Incremental: the nodes live in the iSAM2 pose-graph engine (:class:`~sl4slam.backend.sl4.SL4PoseGraph`,
node numbers as ids); a submap adds a chain of nodes hanging off the previous submap's last node, which
iSAM2 eliminates at the top of its Bayes tree, so the cost of a submap does not grow with the map.
A failed update is rolled back (nodes and submaps) before :class:`BackendUpdateError` is raised.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Collection

import numpy as np

from .settings import BackendConfig
from ..geometry import normalize_sl4, se3_inverse, to_4x4
from ..registry import GraphEntry
from .interface import Backend, BackendUpdateError, SubmapFrames, WorldEstimate
from .pose_graph import transport_information
from .sl4 import SL4PoseGraph


def relative_rotation_disagreement(T_older: np.ndarray, T_newer: np.ndarray) -> np.ndarray:
    """How much two windows disagree about the relative rotation of consecutive shared frames.

    Args:
        T_older: ``(n, 4, 4)`` the shared frames' extrinsics (camera-from-submap) in the older submap.
        T_newer: ``(n, 4, 4)`` the same frames' extrinsics in the newer submap, same order.

    Returns:
        ``(n - 1,)`` radians: the angle of ``R_k R_k+1^T`` (older) against the same in the newer
        submap, for each pair ``k, k + 1``. Rotations only: each window has its own scale, which
        the translations carry. Empty for fewer than two frames.
    """
    from scipy.spatial.transform import Rotation

    R_older, R_newer = np.asarray(T_older)[:, :3, :3], np.asarray(T_newer)[:, :3, :3]
    if len(R_older) < 2:
        return np.zeros(0)
    rel_older = R_older[:-1] @ np.swapaxes(R_older[1:], 1, 2)
    rel_newer = R_newer[:-1] @ np.swapaxes(R_newer[1:], 1, 2)
    return Rotation.from_matrix(rel_older @ np.swapaxes(rel_newer, 1, 2)).magnitude()


@dataclass
class _Submap:
    nodes: list[int]
    frames: SubmapFrames

    def node_of(self, frame_index: int) -> tuple[int, np.ndarray]:
        """The node of ``frame_index`` in this submap and the frame's extrinsic here."""
        if frame_index not in self.frames.frame_indices:
            raise ValueError(f"frame {frame_index} has no node in this submap (frames {list(self.frames.frame_indices)})")
        k = self.frames.frame_indices.index(frame_index)
        return self.nodes[k], self.frames.T_cam_submap[k]


class KeyframeBackend(Backend):
    """The keyframe graph of the module docstring, behind the same interface as the submap graph.

    Args:
        config: sigmas (``frame_sigma`` for the links inside submaps), the loop kernel and iSAM2's
            thresholds (``BackendConfig``).

    Attributes:
        nodes: the iSAM2 graph of keyframe nodes (ids: node numbers).
    """

    kind = "sl4"
    dim = 15
    design = "keyframe"

    def __init__(self, config: BackendConfig) -> None:
        self.config = config
        self.nodes = SL4PoseGraph(config, revisit_priors=config.revisit_priors)
        self._generators = self.nodes.generators()
        self._frame_scatters: list[float] = []  # radians, one per pair of consecutive shared frames
        self._submaps: dict[int, _Submap] = {}
        self._order: list[int] = []
        self._segments: list[int] = []
        self._pending: list[int] = []
        self._next_node = 0

    # ------------------------------------------------------------------ building
    def _check_frames(self, submap_id: int, frames: SubmapFrames | None) -> SubmapFrames:
        if isinstance(submap_id, bool) or not isinstance(submap_id, (int, np.integer)) or submap_id < 0:
            raise ValueError(f"submap id must be a non-negative integer, got {submap_id!r}")
        if submap_id in self._submaps:
            raise ValueError(f"submap {submap_id} was already added")
        if frames is None or len(frames.frame_indices) == 0:
            raise ValueError(f"the keyframe graph needs the keyframes of submap {submap_id} (frames=SubmapFrames(...))")
        T = np.asarray(frames.T_cam_submap, dtype=np.float64)
        if T.shape != (len(frames.frame_indices), 4, 4) or not np.isfinite(T).all():
            raise ValueError(f"submap {submap_id}: T_cam_submap must be finite, shape ({len(frames.frame_indices)}, 4, 4)")
        return SubmapFrames(tuple(int(i) for i in frames.frame_indices), T, int(frames.shared), bool(frames.fitted_link),
                            frames.disagreement)

    def _new_nodes(self, count: int) -> list[int]:
        nodes = list(range(self._next_node, self._next_node + count))
        self._next_node += count
        return nodes

    def chain_sigma(self, frames: SubmapFrames) -> float:
        """Sigma of the links between the keyframes of the submap ``frames``: ``frame_sigma``, or
        less where the run measured the window to be consistent inside, at least ``min_sigma``:

        - for a submap joined by a 15-DOF fit (``frames.fitted_link``), ``frame_scatter_factor``
          times the median disagreement between windows so far (:func:`relative_rotation_disagreement`);
        - for any submap whose frames' agreement was measured (``frames.disagreement``),
          ``window_agreement_factor`` times it.
        """
        sigma = self.config.frame_sigma
        factor = self.config.frame_scatter_factor
        if factor > 0 and self._frame_scatters and frames.fitted_link:
            sigma = min(sigma, factor * float(np.median(self._frame_scatters)))
        agreement = self.config.window_agreement_factor
        if agreement > 0 and frames.disagreement is not None:
            sigma = min(sigma, agreement * frames.disagreement)
        return float(np.clip(sigma, self.config.min_sigma, self.config.frame_sigma))

    def _chain(self, nodes: list[int], frames: SubmapFrames) -> None:
        """Consecutive keyframes of a submap: their relative pose, isotropic :meth:`chain_sigma`."""
        T = frames.T_cam_submap
        information = np.eye(self.dim) / self.chain_sigma(frames)**2
        for k in range(1, len(nodes)):
            self.nodes.add_node(nodes[k], T[k - 1] @ se3_inverse(T[k]), information)

    def _register(self, submap_id: int, nodes: list[int], frames: SubmapFrames, segment: bool) -> None:
        self._submaps[submap_id] = _Submap(nodes, frames)
        self._order.append(submap_id)
        self._pending.append(submap_id)
        if segment:
            self._segments.append(submap_id)

    def add_submap(self, submap_id: int, H_prev_cur: np.ndarray | None, information: np.ndarray | None = None,
                   frames: SubmapFrames | None = None) -> None:
        """Add the submap's keyframe nodes, chained, and link its first (shared) frame to the same
        frame's node in the previous submap by ``H_prev_cur`` (see the module doc). The first
        submap takes ``H_prev_cur=None`` and anchors the world."""
        frames = self._check_frames(submap_id, frames)
        nodes = self._new_nodes(len(frames.frame_indices))
        T = frames.T_cam_submap
        if not self._order:
            if H_prev_cur is not None:
                raise ValueError("the first submap anchors the world frame: pass H_prev_cur=None")
            self.nodes.anchor(nodes[0], se3_inverse(T[0]))
        else:
            if H_prev_cur is None:
                raise ValueError(f"submap {submap_id} needs H_prev_cur (only the first submap takes None)")
            previous = self._submaps[self._order[-1]]
            shared = frames.frame_indices[:frames.shared]
            if not shared or any(f not in previous.frames.frame_indices for f in shared):
                raise ValueError(f"submap {submap_id} must start with keyframes of the previous submap "
                                 f"({list(previous.frames.frame_indices)}) to be linked to it; "
                                 f"got frames {list(frames.frame_indices)} with {frames.shared} shared")
            self._frame_scatters.extend(relative_rotation_disagreement(
                previous.frames.T_cam_submap[-len(shared):], T[:len(shared)]).tolist())
            T_prev = previous.frames.T_cam_submap[-1]  # the engine links a new node to the last one added
            link = T_prev @ np.asarray(H_prev_cur, dtype=np.float64) @ se3_inverse(T[0])
            moved = None if information is None else transport_information(information, T_prev, self._generators)
            self.nodes.add_node(nodes[0], normalize_sl4(link), moved)
        self._chain(nodes, frames)
        self._register(submap_id, nodes, frames, segment=not self._order)

    def start_segment(self, submap_id: int, H_world_guess: np.ndarray, frames: SubmapFrames | None = None) -> None:
        """Add the submap's chain with a weak prior (``segment_sigma``) on its first node at
        ``H_world_guess T_cam_submap^-1``."""
        frames = self._check_frames(submap_id, frames)
        nodes = self._new_nodes(len(frames.frame_indices))
        guess = to_4x4(np.asarray(H_world_guess, dtype=np.float64)) @ se3_inverse(frames.T_cam_submap[0])
        self.nodes.start_segment(nodes[0], guess)
        self._chain(nodes, frames)
        self._register(submap_id, nodes, frames, segment=True)

    def _placed(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray | None,
                frames: tuple[int, int] | None) -> tuple[int, int, np.ndarray, np.ndarray | None]:
        """A loop ``H_i_j`` (submap coordinates) as a measurement between two keyframe nodes."""
        for submap_id in (i, j):
            if submap_id not in self._submaps:
                raise ValueError(f"loop refers to submap {submap_id}, which was not added")
        if i == j:
            raise ValueError(f"a loop needs two different submaps, got {i} twice")
        frame_i, frame_j = frames if frames is not None else (self._submaps[i].frames.frame_indices[0],
                                                              self._submaps[j].frames.frame_indices[0])
        node_i, T_i = self._submaps[i].node_of(frame_i)
        node_j, T_j = self._submaps[j].node_of(frame_j)
        H = normalize_sl4(T_i @ np.asarray(H_i_j, dtype=np.float64) @ se3_inverse(T_j))
        moved = None if information is None else transport_information(information, T_i, self._generators)
        return node_i, node_j, H, moved

    def add_loop(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray | None = None,
                 frames: tuple[int, int] | None = None) -> None:
        """Add a loop between the node of ``frames[0]`` in submap ``i`` and of ``frames[1]`` in ``j``
        (default: the submaps' first keyframes)."""
        self.nodes.add_loop(*self._placed(i, j, H_i_j, information, frames))

    def loop_chi2(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray,
                  frames: tuple[int, int] | None = None) -> float:
        """See :meth:`Backend.loop_chi2`, on the two keyframe nodes the loop ties."""
        node_i, node_j, H, moved = self._placed(i, j, H_i_j, information, frames)
        return self.nodes.loop_chi2(node_i, node_j, H, moved)

    def update(self) -> None:
        """One iSAM2 step (see :meth:`PoseGraph.update`); on failure the submaps added since the last
        update are dropped with their nodes."""
        try:
            self.nodes.update()
        except BackendUpdateError:
            for submap_id in self._pending:
                del self._submaps[submap_id]
                self._order.remove(submap_id)
                if submap_id in self._segments:
                    self._segments.remove(submap_id)
            self._pending = []
            raise
        finally:
            self.last_update_seconds = self.nodes.last_update_seconds
        self._pending = []

    # ------------------------------------------------------------------ results
    def H_world_submap(self, submap_id: int) -> np.ndarray:
        """Current estimate of submap ``submap_id`` through its first keyframe's node."""
        if submap_id not in self._submaps:
            raise KeyError(f"submap {submap_id} was not added")
        submap = self._submaps[submap_id]
        return normalize_sl4(self.nodes.estimate(submap.nodes[0]) @ submap.frames.T_cam_submap[0])

    def freeze(self) -> bool:
        return self.nodes.freeze()

    def world_estimate(self, final: bool = False, submaps: Collection[int] | None = None) -> WorldEstimate:
        """Every submap and every keyframe (through its own node), from iSAM2 or polished (``final``);
        with ``submaps``, only those and their keyframes (only their nodes are read out).

        Vectorized over the nodes (thousands of them): ``X_n T_cam_submap`` for all at once.
        """
        chosen = self._order if submaps is None else [s for s in self._order if s in submaps]
        wanted = None if submaps is None else [node for s in chosen for node in self._submaps[s].nodes]
        X = self.nodes.estimate_matrices(final, wanted)
        row = {node: k for k, node in enumerate(self.nodes.node_ids if wanted is None else wanted)}
        nodes, T, frame_of, first = [], [], [], []
        for submap_id in chosen:
            submap = self._submaps[submap_id]
            for k, node in enumerate(submap.nodes):
                nodes.append(row[node])
                T.append(submap.frames.T_cam_submap[k])
                frame_of.append(submap.frames.frame_indices[k] if k in submap.frames.new else None)
                first.append(submap_id if k == 0 else None)
        H = np.matmul(X[nodes], np.asarray(T)) if nodes else np.zeros((0, 4, 4))
        per_submap = {s: H[i] for i, s in enumerate(first) if s is not None}
        per_keyframe = {f: H[i] for i, f in enumerate(frame_of) if f is not None}
        return WorldEstimate(per_submap, per_keyframe, self.nodes.polish_block_count if final else 1)

    @property
    def num_submaps(self) -> int:
        return len(self._order)

    @property
    def num_nodes(self) -> int:
        return self.nodes.num_nodes

    @property
    def num_loops(self) -> int:
        return self.nodes.num_loops

    @property
    def segments(self) -> list[int]:
        return list(self._segments)

    @property
    def submap_ids(self) -> list[int]:
        return list(self._order)

    def generators(self) -> np.ndarray:
        return self._generators


def registry_entry() -> GraphEntry:
    """The keyframe graph in the catalog (``sl4slam.registry``): built from the run's ``[backend]`` section."""
    return GraphEntry("keyframe", lambda resolved: KeyframeBackend(resolved.config.backend),
                      "VGGT-SLAM 2.0: a node per keyframe, calibration links between submaps", ("sl4",))
