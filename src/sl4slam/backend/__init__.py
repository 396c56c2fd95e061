"""Factor-graph backends: the interface the pipeline talks to (``interface``), the iSAM2 pose-graph
engine in SL(4) and Sim(3) (``pose_graph``, ``sl4``, ``sim3``), and the two graph designs on it:
the submap graph (VGGT-SLAM, ``submap``) and the keyframe graph (VGGT-SLAM 2.0, ``keyframe``).

Each design's module has a ``registry_entry()`` (``sl4slam.registry.GraphEntry``), named in the
catalog (``sl4slam.registry``); ``make_backend`` builds a built-in design from a ``BackendConfig``
alone. ``sl4slam.backend.evidence`` turns an alignment into the information matrix of its edge.
"""

from __future__ import annotations

import importlib
from typing import Any

from .settings import BackendConfig

_HOMES = {"Backend": "interface", "BackendUpdateError": "interface", "SubmapFrames": "interface",
          "WorldEstimate": "interface", "KeyframeBackend": "keyframe", "PoseGraph": "pose_graph",
          "Sim3PoseGraph": "sim3", "SL4PoseGraph": "sl4", "Sim3Backend": "submap", "SL4Backend": "submap",
          "SubmapBackend": "submap", "submap_backend": "submap"}
"""Where each name lives: the package imports a module only when one of its names is asked for, so
that its settings (``sl4slam.backend.settings``) load without GTSAM."""

__all__ = ["BackendConfig", "make_backend", *_HOMES]


def __getattr__(name: str) -> Any:
    if name in _HOMES:
        return getattr(importlib.import_module(f"{__name__}.{_HOMES[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_backend(config: BackendConfig, design: str | None = None) -> Any:
    """The graph design ``design`` ("submap" or "keyframe"; default: ``config.graph``, which must
    then be settled, as in a resolved config) in the group ``config.kind`` ("sl4" or "sim3")."""
    from .keyframe import KeyframeBackend
    from .submap import submap_backend

    design = design or config.graph
    if design == "keyframe":
        return KeyframeBackend(config)
    if design != "submap":
        raise ValueError(f"unknown graph design {design!r} (resolve the config first: 'auto' is settled there)")
    return submap_backend(config)
