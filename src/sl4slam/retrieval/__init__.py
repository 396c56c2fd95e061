"""Loop-closure retrieval behind the ``Retrieval`` interface (``sl4slam.types``).

- ``orb``: weights-free ORB features, bag-of-words ranking and geometric verification (CPU, no download).
- ``salad``: DINOv2 + SALAD descriptors as in the paper (needs ``dino_salad.ckpt``).
- ``none``: no loop closure.
- ``auto`` (default): SALAD when its weights are found locally, else ORB (with a notice).

``false_loops.FalseLoopRetrieval`` wraps any of them to inject wrong places (measuring the loop checks).
"""

from __future__ import annotations

import logging

from ..config import RetrievalConfig, SimulatorConfig
from ..errors import UserError
from ..types import Retrieval

log = logging.getLogger("sl4slam")


def make_retrieval(config: RetrievalConfig, device: str = "cpu", seed: int = 0,
                   false_loops: SimulatorConfig | None = None) -> Retrieval | None:
    """The retrieval named by ``config.kind`` (``None`` for "none"); with ``false_loops`` whose
    ``false_loop_rate`` is positive, wrapped in :class:`FalseLoopRetrieval` (a simulation tool)."""
    inner = _make(config, device, seed)
    if inner is not None and false_loops is not None and false_loops.false_loop_rate > 0:
        from .false_loops import FalseLoopRetrieval

        return FalseLoopRetrieval(inner, false_loops, config.tau_interval)
    return inner


def _make(config: RetrievalConfig, device: str, seed: int) -> Retrieval | None:
    config.validate()
    kind = config.kind
    if kind == "auto":
        from ..models.salad import find_salad_weights, salad_cache_dir

        if config.salad_weights is not None or find_salad_weights() is not None:
            kind = "salad"
        else:
            log.warning(
                "SALAD weights not found (pass --salad-weights or put dino_salad.ckpt in %s); "
                "using the weights-free ORB retrieval", salad_cache_dir())
            kind = "orb"
    if kind == "none":
        return None
    if kind == "salad":
        from .salad import SaladRetrieval

        return SaladRetrieval(config, device=device)
    if kind == "orb":
        from .orb import OrbRetrieval

        return OrbRetrieval(config, seed=seed)
    raise UserError(f"unknown retrieval '{kind}': use --retrieval auto, salad, orb or none")


__all__ = ["make_retrieval"]
