"""Loop-closure retrieval behind the ``Retrieval`` interface (``sl4slam.types``), by name:

- ``orb``: weights-free ORB features, bag-of-words ranking and geometric verification (CPU, no download).
- ``salad``: DINOv2 + SALAD descriptors as in the paper (needs ``dino_salad.ckpt``).
- ``none``: no loop closure.

"auto" (the default) is settled by ``sl4slam.resolve``: SALAD when its weights are found locally,
else ORB. ``false_loops.FalseLoopRetrieval`` wraps any of them to inject wrong places (measuring the
loop checks); ``sl4slam.compose`` adds it when ``[false_loops] rate`` is positive.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..config import FalseLoopConfig, RetrievalConfig
from ..registry import RetrievalEntry, register_retrieval
from ..types import Retrieval

if TYPE_CHECKING:
    from ..resolve import ResolvedConfig


def make_retrieval(config: RetrievalConfig, device: str = "cpu", seed: int | None = None,
                   false_loops: FalseLoopConfig | None = None) -> Retrieval | None:
    """The retrieval named by ``config.kind`` (settled: "salad", "orb" or "none"; ``None`` for "none"),
    wrapped in :class:`FalseLoopRetrieval` when ``false_loops.rate`` is positive."""
    if config.kind == "none":
        return None
    if config.kind == "salad":
        from .salad import SaladRetrieval

        inner: Retrieval = SaladRetrieval(config, device=device)
    elif config.kind == "orb":
        from .orb import OrbRetrieval

        inner = OrbRetrieval(config, seed=seed)
    else:
        raise ValueError(f"retrieval {config.kind!r} is not settled (resolve the config first)")
    if false_loops is not None and false_loops.rate > 0:
        from .false_loops import FalseLoopRetrieval

        return FalseLoopRetrieval(inner, false_loops, config.tau_interval)
    return inner


def _build(resolved: "ResolvedConfig") -> Retrieval | None:
    config = resolved.config
    return make_retrieval(config.retrieval, device=resolved.device, false_loops=config.false_loops)


register_retrieval(RetrievalEntry("salad", _build, "DINOv2 + SALAD descriptors (the paper's); needs dino_salad.ckpt",
                                  uses_device=True))
register_retrieval(RetrievalEntry("orb", _build, "ORB features, bag of words and geometric verification; no weights"))
register_retrieval(RetrievalEntry("none", _build, "no loop closure"))

__all__ = ["make_retrieval"]
