"""The submap graph (VGGT-SLAM): one pose-graph node ``H_world_submap`` per submap.

A submap's odometry measurement links its node to the previous submap's, each accepted loop joins
two submap nodes, and a new map segment starts with a weak prior: the engine's chain
(``sl4slam.backend.pose_graph``) with submap ids as node ids, in SL(4) (the paper) or Sim(3) (for
comparison). The submap's keyframes (``SubmapFrames``) and a loop's frames are not needed: every
keyframe reaches the world through its submap's node.
"""

from __future__ import annotations

from typing import Collection

import numpy as np

from .settings import BackendConfig
from ..registry import GraphEntry
from .interface import Backend, SubmapFrames, WorldEstimate
from .pose_graph import PoseGraph
from .sim3 import Sim3PoseGraph
from .sl4 import SL4PoseGraph


class SubmapBackend(Backend):
    """The submap graph on a pose-graph engine.

    Args:
        graph: the engine (:class:`SL4PoseGraph` or :class:`Sim3PoseGraph`); its node ids are
            submap ids.

    Attributes:
        graph: the engine, for inspection (factors, iSAM2 counters).
    """

    design = "submap"

    def __init__(self, graph: PoseGraph) -> None:
        self.graph = graph
        self.kind = graph.kind
        self.dim = graph.dim

    def add_submap(self, submap_id: int, H_prev_cur: np.ndarray | None, information: np.ndarray | None = None,
                   frames: SubmapFrames | None = None) -> None:
        self.graph.add_node(submap_id, H_prev_cur, information)

    def start_segment(self, submap_id: int, H_world_guess: np.ndarray, frames: SubmapFrames | None = None) -> None:
        self.graph.start_segment(submap_id, H_world_guess)

    def add_loop(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray | None = None,
                 frames: tuple[int, int] | None = None) -> None:
        self.graph.add_loop(i, j, H_i_j, information)

    def update(self) -> None:
        try:
            self.graph.update()
        finally:
            self.last_update_seconds = self.graph.last_update_seconds

    def H_world_submap(self, submap_id: int) -> np.ndarray:
        return self.graph.estimate(submap_id)

    def freeze(self) -> bool:
        return self.graph.freeze()

    def world_estimate(self, final: bool = False, submaps: Collection[int] | None = None) -> WorldEstimate:
        estimates = self.graph.final_estimates() if final else self.graph.estimates()
        if submaps is not None:
            estimates = {s: H for s, H in estimates.items() if s in submaps}
        return WorldEstimate(estimates, polish_blocks=self.graph.polish_block_count if final else 1)

    def loop_chi2(self, i: int, j: int, H_i_j: np.ndarray, information: np.ndarray,
                  frames: tuple[int, int] | None = None) -> float:
        return self.graph.loop_chi2(i, j, H_i_j, information)

    def generators(self) -> np.ndarray:
        return self.graph.generators()

    @property
    def num_submaps(self) -> int:
        return self.graph.num_nodes

    @property
    def segments(self) -> list[int]:
        return self.graph.segments

    @property
    def submap_ids(self) -> list[int]:
        return self.graph.node_ids

    @property
    def num_loops(self) -> int:
        return self.graph.num_loops


class SL4Backend(SubmapBackend):
    """The submap graph in SL(4), the paper's (VGGT-SLAM)."""

    def __init__(self, config: BackendConfig, revisit_priors: bool = False) -> None:
        super().__init__(SL4PoseGraph(config, revisit_priors))


class Sim3Backend(SubmapBackend):
    """The submap graph in Sim(3), for comparison."""

    def __init__(self, config: BackendConfig, revisit_priors: bool = False) -> None:
        super().__init__(Sim3PoseGraph(config, revisit_priors))


def submap_backend(config: BackendConfig) -> SubmapBackend:
    """The submap graph in the group ``config.kind`` ("sl4" or "sim3")."""
    return Sim3Backend(config) if config.kind == "sim3" else SL4Backend(config)


def registry_entry() -> GraphEntry:
    """The submap graph in the catalog (``sl4slam.registry``): built from the run's ``[backend]`` section."""
    return GraphEntry("submap", lambda resolved: submap_backend(resolved.config.backend),
                      "VGGT-SLAM: a node per submap, 15-DOF (or Sim(3)) links", ("sl4", "sim3"))
