"""Frontends: feed-forward reconstruction of a window of frames into one submap.

- ``vggt``: our VGGT-1B implementation (``sl4slam.frontend.vggt.VGGTFrontend``).
- ``simulated``: VGGT-like submaps from ground-truth RGB-D with a controlled projective distortion
  and noise (``sl4slam.frontend.simulated.SimulatedFrontend``).
- ``CachingFrontend`` / ``ReplayFrontend``: record a frontend's outputs and replay them, so the
  backend can be re-run on a CPU without the model.
"""

from __future__ import annotations

from ..config import SLAMConfig, attention_check
from ..errors import UserError
from ..types import Frontend
from .cache import CachingFrontend, ReplayFrontend


def make_frontend(config: SLAMConfig, replay_dir: str | None = None, cache_dir: str | None = None) -> Frontend:
    """The frontend named by ``config.frontend``, optionally replayed from or recorded to a cache."""
    frontend: Frontend
    if replay_dir is not None:
        return ReplayFrontend(replay_dir)
    if config.frontend == "simulated":
        from .simulated import SimulatedFrontend

        frontend = SimulatedFrontend(config.sim)
    elif config.frontend == "vggt":
        from .vggt import VGGTFrontend

        frontend = VGGTFrontend(config.vggt, with_points=config.submap.use_point_head,
                                match_scores=attention_check(config))
    else:
        raise UserError(f"unknown frontend '{config.frontend}': use --frontend vggt or --frontend simulated")
    if cache_dir is not None:
        frontend = CachingFrontend(frontend, cache_dir)
    return frontend


def frontend_requires_ground_truth(config: SLAMConfig, replay_dir: str | None = None) -> bool:
    """Whether the frontend a run would use reads depth and poses from the frames (without building it)."""
    if replay_dir is not None:
        return ReplayFrontend(replay_dir).requires_ground_truth
    return config.frontend == "simulated"


__all__ = ["make_frontend", "frontend_requires_ground_truth", "CachingFrontend", "ReplayFrontend"]
