"""The composition root: one function makes a run's stages from its resolved config.

``build_stages`` is the only place that turns names into objects, through the catalog
(``sl4slam.registry``): the frontend (a model, the simulator, or a recording replayed, optionally
recorded to a cache), the retrieval (with injected false loops when asked), the aligner and the
graph. The runner, the demo, the evaluation and library users all call it, so a run is assembled
the same way wherever it starts; a stage given explicitly (a test's failing frontend, a
benchmark's instrumented graph) replaces the built one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

from .backend import Backend
from .config import SLAMConfig
from .errors import UserError
from .frontend import build_frontend, replay_capabilities
from .resolve import ResolvedConfig, resolve
from .retrieval.false_loops import FalseLoopRetrieval
from .types import Aligner, Frontend, Retrieval

__all__ = ["Stages", "build_frontend", "build_retrieval", "build_stages", "make_frontend", "replay_capabilities",
           "stages_for"]

_BUILD = object()  # "build this stage from the config" (``None`` is a valid retrieval: no loops)


@dataclass
class Stages:
    """The stage objects of one run (``sl4slam.types`` interfaces)."""

    frontend: Frontend
    retrieval: Retrieval | None
    aligner: Aligner
    backend: Backend


def build_stages(resolved: ResolvedConfig, frontend: Frontend | None = None, retrieval: Any = _BUILD,
                 aligner: Aligner | None = None, backend: Backend | None = None,
                 replay_dir: str | os.PathLike | None = None, cache_dir: str | os.PathLike | None = None) -> Stages:
    """The stages of a run; any stage given replaces the one the config names.

    Args:
        resolved: the run's settled config (``sl4slam.resolve.resolve``).
        frontend, retrieval, aligner, backend: stages to use as given (``retrieval=None``: no loops).
        replay_dir: replay the frontend outputs recorded there instead of running the frontend.
        cache_dir: record the frontend's outputs there.
    """
    if frontend is None and replay_dir is None and (resolved.workers > 1 or resolved.config.ray_address):
        frontend = worker_frontend(resolved)
    frontend = build_frontend(resolved, frontend, replay_dir, cache_dir)
    if retrieval is _BUILD:
        retrieval = build_retrieval(resolved)
    given = aligner is not None or backend is not None
    aligner = aligner if aligner is not None else resolved.config.alignment.setup(resolved)
    backend = backend if backend is not None else resolved.config.backend.setup(resolved)
    if given and aligner.group == "sl4" and backend.kind != "sl4":  # the config's pair is checked by resolve
        raise UserError(f"the {aligner.model} aligner measures projective transforms, which a "
                        f"{backend.kind} graph cannot hold; use a Sim(3) alignment model")
    return Stages(frontend, retrieval, aligner, backend)


def worker_frontend(resolved: ResolvedConfig) -> Frontend:
    """The run's frontend on ``workers`` local processes, or actors of the Ray cluster at
    ``ray_address`` (``sl4slam.frontend.workers``); each builds its own with
    :func:`frontend_for_worker`."""
    from .frontend.workers import ProcessWorkers, RayWorkers, WorkerFrontend

    config = resolved.config
    factory = partial(frontend_for_worker, config)
    workers = (RayWorkers(factory, config.workers, config.ray_address) if config.ray_address
               else ProcessWorkers(factory, config.workers))
    return WorkerFrontend(resolved.frontend.build(resolved), workers)


def frontend_for_worker(config: SLAMConfig, index: int) -> Frontend:
    """The frontend worker ``index`` builds from the run's settled ``config``: on a machine with
    several GPUs, on GPU ``index`` modulo their count."""
    if config.device.startswith("cuda"):
        import torch

        count = torch.cuda.device_count()
        if count > 1:
            config = replace(config, device=f"cuda:{index % count}")
    resolved = resolve(config)
    return resolved.frontend.build(resolved)


def build_retrieval(resolved: ResolvedConfig) -> Retrieval | None:
    """The retrieval the config names (``None``: no loop closure), wrapped in
    :class:`~sl4slam.retrieval.false_loops.FalseLoopRetrieval` when ``[false_loops] rate`` is positive."""
    config = resolved.config
    retrieval = config.retrieval.setup(resolved)
    if retrieval is not None and config.false_loops.rate > 0:
        return FalseLoopRetrieval(retrieval, config.false_loops, config.retrieval.tau_interval)
    return retrieval


def stages_for(config: SLAMConfig, **stages: Any) -> tuple[ResolvedConfig, Stages]:
    """``resolve(config)`` and :func:`build_stages` in one call (the entry point of library use)."""
    resolved = resolve(config)
    return resolved, build_stages(resolved, **stages)


def make_frontend(config: SLAMConfig, replay_dir: str | os.PathLike | None = None,
                  cache_dir: str | os.PathLike | None = None) -> Frontend:
    """The frontend the user's settings name (resolved here), optionally replayed from or recorded
    to a cache (:func:`build_frontend`)."""
    resolved = resolve(config, capabilities=replay_capabilities(replay_dir) if replay_dir is not None else None)
    return build_frontend(resolved, replay_dir=replay_dir, cache_dir=cache_dir)
