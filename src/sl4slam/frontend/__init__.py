"""Frontends: feed-forward reconstruction of a window of frames into one submap, registered by name.

- ``vggt``: our VGGT-1B implementation (``sl4slam.frontend.vggt.VGGTFrontend``).
- ``da3-small`` ... ``da3-giant-1.1``: Depth Anything 3, every released size
  (``sl4slam.frontend.da3.DA3Frontend``).
- ``pi3`` / ``pi3x``: π³ and its successor Pi3X (``sl4slam.frontend.pi3.Pi3Frontend``).
- ``simulated``: VGGT-like submaps from ground-truth RGB-D with a controlled projective distortion
  and noise (``sl4slam.frontend.simulated.SimulatedFrontend``).
- ``CachingFrontend`` / ``ReplayFrontend``: record a frontend's outputs and replay them, so the
  backend can be re-run on a CPU without the model.

Each frontend module has a ``registry_entry()`` (``sl4slam.registry.FrontendEntry``: its name,
capabilities, weights, licence and builder); the lines below register them lazily, so a run
imports only the model it uses. A new model adds its line here.
"""

from __future__ import annotations

import os

from ..registry import register_frontend
from ..types import Frontend
from .cache import CachingFrontend, ReplayFrontend

register_frontend("sl4slam.frontend.vggt:registry_entry", "vggt")
for _size in ("small", "base", "large", "large-1.1", "giant", "giant-1.1"):
    register_frontend(f"sl4slam.frontend.da3:registry_entry:{_size}", f"da3-{_size}")
for _variant in ("pi3", "pi3x"):
    register_frontend(f"sl4slam.frontend.pi3:registry_entry:{_variant}", _variant)
register_frontend("sl4slam.frontend.simulated:registry_entry", "simulated")


def make_frontend(config, replay_dir: str | os.PathLike | None = None,
                  cache_dir: str | os.PathLike | None = None) -> Frontend:
    """The frontend a config names (``SLAMConfig`` or resolved), optionally replayed from or
    recorded to a cache (``sl4slam.compose.build_frontend``)."""
    from ..compose import build_frontend, replay_capabilities
    from ..resolve import resolve

    resolved = resolve(config, capabilities=replay_capabilities(replay_dir) if replay_dir is not None else None)
    return build_frontend(resolved, replay_dir=replay_dir, cache_dir=cache_dir)


__all__ = ["make_frontend", "CachingFrontend", "ReplayFrontend"]
