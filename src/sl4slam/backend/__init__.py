"""Factor-graph backends: the interface the pipeline talks to (``interface``), the iSAM2 pose-graph
engine in SL(4) and Sim(3) (``pose_graph``, ``sl4``, ``sim3``), and the two graph designs on it:
the submap graph (VGGT-SLAM, ``submap``) and the keyframe graph (VGGT-SLAM 2.0, ``keyframe``).

Each design's module has a ``registry_entry()`` (``sl4slam.registry.GraphEntry``), named in the
catalog (``sl4slam.registry``); ``make_backend`` builds a built-in design from a ``BackendConfig``
alone. ``sl4slam.backend.evidence`` turns an alignment into the information matrix of its edge.
"""

from __future__ import annotations

from ..config import BackendConfig
from .interface import Backend, BackendUpdateError, SubmapFrames, WorldEstimate
from .keyframe import KeyframeBackend
from .pose_graph import PoseGraph
from .sim3 import Sim3PoseGraph
from .sl4 import SL4PoseGraph
from .submap import Sim3Backend, SL4Backend, SubmapBackend, submap_backend

__all__ = ["Backend", "BackendUpdateError", "KeyframeBackend", "PoseGraph", "SL4Backend", "SL4PoseGraph", "Sim3Backend",
           "Sim3PoseGraph", "SubmapBackend", "SubmapFrames", "WorldEstimate", "make_backend"]


def make_backend(config: BackendConfig, design: str | None = None) -> Backend:
    """The graph design ``design`` ("submap" or "keyframe"; default: ``config.graph``, which must
    then be settled, as in a resolved config) in the group ``config.kind`` ("sl4" or "sim3")."""
    design = design or config.graph
    if design == "keyframe":
        return KeyframeBackend(config)
    if design != "submap":
        raise ValueError(f"unknown graph design {design!r} (resolve the config first: 'auto' is settled there)")
    return submap_backend(config)
