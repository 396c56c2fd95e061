"""Frontends: feed-forward reconstruction of a window of frames into one submap, named in the catalog.

- ``vggt``: our VGGT-1B implementation (``sl4slam.frontend.vggt.VGGTFrontend``).
- ``da3-small`` ... ``da3-giant-1.1``: Depth Anything 3, every released size
  (``sl4slam.frontend.da3.DA3Frontend``).
- ``pi3`` / ``pi3x``: π³ and its successor Pi3X (``sl4slam.frontend.pi3.Pi3Frontend``).
- ``simulated``: VGGT-like submaps from ground-truth RGB-D with a controlled projective distortion
  and noise (``sl4slam.frontend.simulated.SimulatedFrontend``).
- ``CachingFrontend`` / ``ReplayFrontend``: record a frontend's outputs and replay them, so the
  backend can be re-run on a CPU without the model.

Each frontend module has a ``registry_entry()`` (``sl4slam.registry.FrontendEntry``: its name,
capabilities, weights, licence and builder), named lazily in the catalog (``sl4slam.registry``),
so a run imports only the model it uses. A new model adds its line there.
"""

from __future__ import annotations

import os
from typing import Any

from ..types import Frontend, FrontendCapabilities


def __getattr__(name: str) -> Any:
    if name in ("CachingFrontend", "ReplayFrontend"):  # loaded on first use, like every frontend module
        from . import cache

        return getattr(cache, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def replay_capabilities(replay_dir: str | os.PathLike) -> FrontendCapabilities:
    """What a recorded frontend cache can give a replay (``resolve(..., capabilities=...)``)."""
    from .cache import ReplayFrontend

    return ReplayFrontend(replay_dir).capabilities


def build_frontend(resolved, frontend: Frontend | None = None,
                   replay_dir: str | os.PathLike | None = None, cache_dir: str | os.PathLike | None = None) -> Frontend:
    """The run's frontend: ``frontend`` if given, else a replay of ``replay_dir``, else the one the
    catalog builds for the resolved config ``resolved`` (``sl4slam.resolve.ResolvedConfig``);
    recorded to ``cache_dir`` when given."""
    from .cache import CachingFrontend, ReplayFrontend

    if frontend is None:
        frontend = ReplayFrontend(replay_dir) if replay_dir is not None else resolved.frontend.build(resolved)
    if cache_dir is not None:
        frontend = CachingFrontend(frontend, cache_dir)
    return frontend


__all__ = ["build_frontend", "replay_capabilities", "CachingFrontend", "ReplayFrontend"]
