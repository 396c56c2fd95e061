"""Factor-graph backends over submap transforms: SL(4) (the paper) and Sim(3) (for comparison)."""

from __future__ import annotations

from ..config import BackendConfig
from .base import Backend, FactorGraphBackend, validate_backend_config
from .sim3 import Sim3Backend
from .sl4 import SL4Backend

__all__ = ["Backend", "FactorGraphBackend", "SL4Backend", "Sim3Backend", "make_backend"]


def make_backend(config: BackendConfig) -> FactorGraphBackend:
    """The backend named by ``config.kind`` ("sl4" or "sim3"); ``UserError`` for bad settings."""
    validate_backend_config(config)
    if config.kind == "sim3":
        return Sim3Backend(config)
    return SL4Backend(config)
