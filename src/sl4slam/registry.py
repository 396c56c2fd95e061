"""Named stages: frontends (models and the simulator), retrievals and graph designs.

Each stage registers under a name with what a run needs to know of it before building it: a
frontend its capabilities (``sl4slam.types.FrontendCapabilities``), its weights and licence; a
graph the groups it holds. ``sl4slam.resolve`` reads the entries to settle a config,
``sl4slam.compose`` calls their ``build`` to make a run's stages. The built-in entries are
registered by ``sl4slam.frontend``, ``sl4slam.retrieval`` and ``sl4slam.backend`` (one line each);
a new model adds one line there (docs/architecture.md, "How to add a model").

A frontend entry may be registered lazily, as ``"module:function"`` (or ``"module:function:argument"``
for one member of a family, e.g. a model size) returning the entry, so that naming a model does not
import its code (and torch) until a run or a listing asks for it.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping

from .errors import UserError
from .types import FrontendCapabilities

if TYPE_CHECKING:
    from .backend import Backend
    from .models.hub import WeightsSource
    from .resolve import ResolvedConfig
    from .types import Frontend, Retrieval


@dataclass(frozen=True)
class FrontendEntry:
    """A frontend a run can name (``--frontend`` / ``--model``).

    Attributes:
        name: its name on the command line ("vggt", "da3-small", "simulated").
        build: makes the frontend of a resolved config.
        capabilities: what it can do (declared, never guessed).
        description: one line for ``sl4slam models``.
        weights: where its released weights live (``None``: it has none, as the simulator).
        licence: the weights' licence, in words.
        parameters: parameters of the full-size model, when it has weights.
        settings: the config section that holds its settings ("model", "sim").
        recognizes: whether a state dict's key names are this model's (``--model FILE``).
        convert: ``convert(src, dst, dtype)`` writes a ``.safetensors`` copy of a checkpoint of it
            (``sl4slam convert``; dtype "fp32", "bf16" or "fp16").
        cpu_work: its float32 work per frame of a window on a CPU, in GFLOP-equivalents (the matmul work
            that takes as long; ``sl4slam.frontend.cost``); ``None``: no model to estimate.
    """

    name: str
    build: Callable[["ResolvedConfig"], "Frontend"]
    capabilities: FrontendCapabilities
    description: str
    weights: "WeightsSource | None" = None
    licence: str = ""
    parameters: int | None = None
    settings: str = "model"
    recognizes: Callable[[Mapping[str, Any]], bool] | None = None
    convert: Callable[[str, str, str], Any] | None = None
    cpu_work: float | None = None


@dataclass(frozen=True)
class RetrievalEntry:
    """A loop-closure retrieval (``--retrieval``); ``build`` returns ``None`` for no retrieval."""

    name: str
    build: Callable[["ResolvedConfig"], "Retrieval | None"]
    description: str
    uses_device: bool = False


@dataclass(frozen=True)
class GraphEntry:
    """A graph design (``--graph``) and the groups (``--backend``) whose measurements it holds."""

    name: str
    build: Callable[["ResolvedConfig"], "Backend"]
    description: str
    groups: tuple[str, ...]


_FRONTENDS: dict[str, FrontendEntry | str] = {}
_RETRIEVALS: dict[str, RetrievalEntry] = {}
_GRAPHS: dict[str, GraphEntry] = {}


def register_frontend(entry: FrontendEntry | str, name: str | None = None) -> None:
    """Register a frontend: an entry, or (lazily) ``"module:function"`` that returns one, under ``name``."""
    key = entry.name if isinstance(entry, FrontendEntry) else name
    if not key:
        raise ValueError("a lazily registered frontend needs its name")
    _FRONTENDS[key] = entry


def register_retrieval(entry: RetrievalEntry) -> None:
    _RETRIEVALS[entry.name] = entry


def register_graph(entry: GraphEntry) -> None:
    _GRAPHS[entry.name] = entry


def _builtins() -> None:
    """Import the packages whose import registers the built-in entries (once)."""
    for module in ("sl4slam.frontend", "sl4slam.retrieval", "sl4slam.backend"):
        importlib.import_module(module)


def frontend_names() -> list[str]:
    _builtins()
    return list(_FRONTENDS)


def frontend_entry(name: str) -> FrontendEntry:
    """The entry of frontend ``name``; ``UserError`` listing the available ones otherwise."""
    _builtins()
    entry = _FRONTENDS.get(name)
    if entry is None:
        raise UserError(f"unknown model or frontend '{name}' (--model / --frontend); available: "
                        f"{', '.join(_FRONTENDS)} (sl4slam models lists them), or a model's weights file or hub id")
    if isinstance(entry, str):
        module, _, function = entry.partition(":")
        function, _, argument = function.partition(":")  # "module:function:argument" for a family of models
        factory = getattr(importlib.import_module(module), function)
        entry = factory(argument) if argument else factory()
        _FRONTENDS[name] = entry
    return entry


def frontend_entries() -> list[FrontendEntry]:
    """Every registered frontend (lazy ones loaded)."""
    return [frontend_entry(name) for name in frontend_names()]


def retrieval_entry(name: str) -> RetrievalEntry:
    _builtins()
    if name not in _RETRIEVALS:
        raise UserError(f"unknown retrieval '{name}' (--retrieval); available: {', '.join(_RETRIEVALS)}")
    return _RETRIEVALS[name]


def graph_entry(name: str) -> GraphEntry:
    _builtins()
    if name not in _GRAPHS:
        raise UserError(f"unknown graph design '{name}' (--graph); available: {', '.join(_GRAPHS)}")
    return _GRAPHS[name]
