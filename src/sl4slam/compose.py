"""The composition root: one function makes a run's stages from its resolved config.

``build_stages`` is the only place that turns names into objects: the frontend (a model, the
simulator, or a recording replayed, optionally recorded to a cache), the retrieval (with injected
false loops when asked), the aligner and the graph. The runner, the demo, the evaluation and
library users all call it, so a run is assembled the same way wherever it starts; a stage given
explicitly (a test's failing frontend, a benchmark's instrumented graph) replaces the built one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from .alignment import make_aligner
from .backend import Backend
from .registry import graph_entry, retrieval_entry
from .resolve import ResolvedConfig, resolve
from .types import Aligner, Frontend, FrontendCapabilities, Retrieval

_BUILD = object()  # "build this stage from the config" (``None`` is a valid retrieval: no loops)


@dataclass
class Stages:
    """The stage objects of one run (``sl4slam.types`` interfaces)."""

    frontend: Frontend
    retrieval: Retrieval | None
    aligner: Aligner
    backend: Backend


def replay_capabilities(replay_dir: str | os.PathLike) -> FrontendCapabilities:
    """What a recorded frontend cache can give a replay (``resolve(..., capabilities=...)``)."""
    from .frontend.cache import ReplayFrontend

    return ReplayFrontend(replay_dir).capabilities


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
    frontend = build_frontend(resolved, frontend, replay_dir, cache_dir)
    if retrieval is _BUILD:
        retrieval = retrieval_entry(resolved.retrieval.value).build(resolved)
    aligner = aligner if aligner is not None else make_aligner(resolved)
    backend = backend if backend is not None else graph_entry(resolved.graph.value).build(resolved)
    return Stages(frontend, retrieval, aligner, backend)


def build_frontend(resolved: ResolvedConfig, frontend: Frontend | None = None,
                   replay_dir: str | os.PathLike | None = None, cache_dir: str | os.PathLike | None = None) -> Frontend:
    """The run's frontend: ``frontend`` if given, else a replay of ``replay_dir``, else the registered
    one; recorded to ``cache_dir`` when given."""
    from .frontend.cache import CachingFrontend, ReplayFrontend

    if frontend is None:
        frontend = ReplayFrontend(replay_dir) if replay_dir is not None else resolved.frontend.build(resolved)
    if cache_dir is not None:
        frontend = CachingFrontend(frontend, cache_dir)
    return frontend


def stages_for(config, **stages: Any) -> tuple[ResolvedConfig, Stages]:
    """``resolve(config)`` and :func:`build_stages` in one call (for library use)."""
    resolved = resolve(config)
    return resolved, build_stages(resolved, **stages)
