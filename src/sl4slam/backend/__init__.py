"""Factor-graph backends: the submap graph in SL(4) (the paper) or Sim(3) (for comparison), and the
keyframe graph in SL(4) (VGGT-SLAM 2.0, ``sl4slam.backend.keyframe``).

``Backend`` is the interface the pipeline talks to; ``make_backend`` builds the one a config names.
``sl4slam.backend.evidence`` turns an alignment into the information matrix of its edge.
"""

from __future__ import annotations

from ..config import BackendConfig
from .base import Backend, BackendUpdateError, FactorGraphBackend, SubmapFrames, WorldEstimate
from .keyframe import KeyframeBackend
from .sim3 import Sim3Backend
from .sl4 import SL4Backend

__all__ = ["Backend", "BackendUpdateError", "FactorGraphBackend", "KeyframeBackend", "SL4Backend", "Sim3Backend",
           "SubmapFrames", "WorldEstimate", "make_backend"]


def make_backend(config: BackendConfig) -> Backend:
    """The graph design ``config.design`` ("submap" or "keyframe") in the group ``config.kind``
    ("sl4" or "sim3"); ``UserError`` for bad settings."""
    config.validate()
    if config.design == "keyframe":
        return KeyframeBackend(config)
    if config.kind == "sim3":
        return Sim3Backend(config)
    return SL4Backend(config)
