"""Open-vocabulary 3D object queries on a finished map ("red mug" -> the mug's 3D box).

- :mod:`.interfaces`: the model interfaces (``ImageEmbedder``, ``TextSegmenter``, ``Mask2D``);
- :mod:`.store`: the keyframe embeddings of a result folder (``objects/embeddings.npz``);
- :mod:`.lift`: a 2D mask to the keyframe's world points; :mod:`.fusion`: views to instances with
  oriented boxes, and box overlap;
- :mod:`.query`: :func:`query_result`, text in, :class:`QueryAnswer` out;
- :mod:`.oracle`: oracle models and ground truth for the synthetic world.

Submodules load on first use, so importing the package loads no model.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "ImageEmbedder": "interfaces", "TextSegmenter": "interfaces", "Mask2D": "interfaces",
    "KeyframeEmbeddings": "store", "read_embeddings": "store", "write_embeddings": "store",
    "ObjectInstance": "fusion", "box_iou": "fusion",
    "QueryAnswer": "query", "query_result": "query",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
