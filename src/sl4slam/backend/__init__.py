"""Factor-graph backends over submap transforms: SL(4) (the paper) and Sim(3) (for comparison).

``Backend`` is the interface the pipeline talks to; ``make_backend`` builds the one a config names.
``sl4slam.backend.evidence`` turns an alignment into the information matrix of its edge.
"""

from __future__ import annotations

from ..config import BackendConfig
from .base import Backend, BackendUpdateError, FactorGraphBackend
from .sim3 import Sim3Backend
from .sl4 import SL4Backend

__all__ = ["Backend", "BackendUpdateError", "FactorGraphBackend", "SL4Backend", "Sim3Backend", "make_backend"]


def make_backend(config: BackendConfig) -> Backend:
    """The backend named by ``config.kind`` ("sl4" or "sim3"); ``UserError`` for bad settings."""
    config.validate()
    if config.kind == "sim3":
        return Sim3Backend(config)
    return SL4Backend(config)
