"""Loop-closure retrieval behind the ``Retrieval`` interface (``sl4slam.types``), by name:

- ``orb``: weights-free ORB features, bag-of-words ranking and geometric verification (CPU, no download).
- ``salad``: DINOv2 + SALAD descriptors as in the paper (needs ``dino_salad.ckpt``).
- ``none``: no loop closure.

Each has a ``registry_entry()`` (``none``: :func:`none_entry`), named in the catalog
(``sl4slam.registry``). "auto" (the default) is settled by ``sl4slam.resolve``: SALAD when its
weights are found locally, else ORB. ``false_loops.FalseLoopRetrieval`` wraps any of them to inject
wrong places (measuring the loop checks); ``sl4slam.compose`` adds it when ``[false_loops] rate``
is positive.
"""

from __future__ import annotations

from ..registry import RetrievalEntry


def none_entry() -> RetrievalEntry:
    """No loop closure, in the catalog (``sl4slam.registry``): its ``build`` returns ``None``."""
    return RetrievalEntry("none", lambda resolved: None, "no loop closure")


__all__ = ["none_entry"]
