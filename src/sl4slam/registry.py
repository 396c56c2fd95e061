"""The catalog of stages a run can name: frontends, retrievals, aligners and graph designs.

Each kind of stage is one table below, a line per name: ``"module:function"`` (or
``"module:function:argument"`` for one member of a family, e.g. a model size), where ``function``
(a dotted path inside the module, such as ``Class.registry_entry``) returns the stage's entry. An
entry says what a run needs to know of the stage before building it (a frontend its capabilities,
weights and licence; an aligner its group; a graph the groups it holds) and how to ``build`` it
from a resolved config. The stage's module is imported the first time its entry is asked for, so
this module imports no stage and naming a model does not import its code (and torch) until a run
or a listing needs it.

``sl4slam.config`` takes the names (the allowed values of ``--alignment``, ``--graph`` and
``--retrieval``), ``sl4slam.resolve`` reads the entries to settle a config, ``sl4slam.compose``
calls their ``build`` to make a run's stages. A new stage is its module plus one line in its table
(docs/architecture.md, "How to add a model", "Add an aligner", "Add a graph"); a program may also
add one at run time with :func:`register_frontend` (and its siblings), an entry or a reference.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping, TypeVar

from .errors import UserError
from .types import FrontendCapabilities

if TYPE_CHECKING:
    from .models.hub import WeightsSource
    from .types import Aligner, Frontend, Retrieval

Settled = Any
"""What ``build`` receives: the run's ``sl4slam.resolve.ResolvedConfig`` (``sl4slam.resolve``
imports this module, so the type is named here, not imported)."""


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
        settle_dtype: ``settle_dtype(dtype, device)``: the concrete precision mode of the ``dtype``
            setting ("auto" included) on a device, raising ``UserError`` for a mode the model or the
            device cannot run (``sl4slam.models.precision.settle_mode``); ``None``: no precision setting.
    """

    name: str
    build: Callable[[Settled], "Frontend"]
    capabilities: FrontendCapabilities
    description: str
    weights: "WeightsSource | None" = None
    licence: str = ""
    parameters: int | None = None
    settings: str = "model"
    recognizes: Callable[[Mapping[str, Any]], bool] | None = None
    convert: Callable[[str, str, str], Any] | None = None
    cpu_work: float | None = None
    settle_dtype: Callable[[str, str], str] | None = None


@dataclass(frozen=True)
class RetrievalEntry:
    """A loop-closure retrieval (``--retrieval``); ``build`` returns ``None`` for no retrieval.

    Attributes:
        uses_device: it runs a model, so the run settles a device for it (``--device``).
    """

    name: str
    build: Callable[[Settled], "Retrieval | None"]
    description: str
    uses_device: bool = False


@dataclass(frozen=True)
class AlignerEntry:
    """An alignment model (``--alignment``): what measures the link between two submaps.

    Attributes:
        name: its name on the command line ("sl4", "select", ...).
        build: makes the aligner of a resolved config.
        description: one line on what it measures.
        group: the group of its measurements ("sl4" or "sim3"); a graph must hold that group.
        projective: whether its links may be 15-DOF fits (which leave the map one common projective
            distortion: the metric upgrade is then on by default).
    """

    name: str
    build: Callable[[Settled], "Aligner"]
    description: str
    group: str
    projective: bool = False


@dataclass(frozen=True)
class GraphEntry:
    """A graph design (``--graph``) and the groups (``--backend``) whose measurements it holds;
    ``build`` returns a ``sl4slam.backend.Backend``."""

    name: str
    build: Callable[[Settled], Any]
    description: str
    groups: tuple[str, ...]


@dataclass(frozen=True)
class ObjectModelEntry:
    """A model of the object queries (``--objects``, ``sl4slam query``), for ``sl4slam models``.

    Attributes:
        name: its name ("pe-core-l14-336", "sam3").
        description: one line on what it does.
        weights: where its released weights live.
        licence: the weights' licence, in words.
        parameters: parameters of the full-size model.
        role: what the queries use it for ("image/text embedder", "text segmenter").
    """

    name: str
    description: str
    weights: "WeightsSource"
    licence: str
    parameters: int
    role: str = ""


# The catalog: a line per stage, in the order listings and the command line's choices show them.

_FRONTENDS: dict[str, FrontendEntry | str] = {
    "vggt": "sl4slam.frontend.vggt:registry_entry",
    **{f"da3-{size}": f"sl4slam.frontend.da3:registry_entry:{size}"
       for size in ("small", "base", "large", "large-1.1", "giant", "giant-1.1")},
    "pi3": "sl4slam.frontend.pi3:registry_entry:pi3",
    "pi3x": "sl4slam.frontend.pi3:registry_entry:pi3x",
    "simulated": "sl4slam.frontend.simulated:registry_entry",
}

_RETRIEVALS: dict[str, RetrievalEntry | str] = {
    "salad": "sl4slam.retrieval.salad:registry_entry",
    "orb": "sl4slam.retrieval.orb:registry_entry",
    "none": "sl4slam.retrieval:none_entry",
}

_ALIGNERS: dict[str, AlignerEntry | str] = {
    "sl4": "sl4slam.alignment.aligner:SL4Aligner.registry_entry",
    "calibration": "sl4slam.alignment.aligner:CalibrationAligner.registry_entry",
    "hybrid": "sl4slam.alignment.aligner:HybridAligner.registry_entry",
    "select": "sl4slam.alignment.aligner:SelectAligner.registry_entry",
    "sim3-points": "sl4slam.alignment.aligner:Sim3PointAligner.registry_entry",
    "sim3-cameras": "sl4slam.alignment.aligner:Sim3CameraAligner.registry_entry",
}

_GRAPHS: dict[str, GraphEntry | str] = {
    "submap": "sl4slam.backend.submap:registry_entry",
    "keyframe": "sl4slam.backend.keyframe:registry_entry",
}

_OBJECT_MODELS: dict[str, ObjectModelEntry | str] = {
    "pe-core-l14-336": "sl4slam.objects.embedder:registry_entry",
    "sam3": "sl4slam.objects.sam3:registry_entry",
}

Entry = TypeVar("Entry", FrontendEntry, RetrievalEntry, AlignerEntry, GraphEntry, ObjectModelEntry)


def load_entry(reference: str) -> Any:
    """The entry a catalog reference returns: ``"module:function"`` or ``"module:function:argument"``,
    ``function`` a dotted path inside ``module`` (``"pkg.mod:Class.registry_entry"``)."""
    module, _, function = reference.partition(":")
    function, _, argument = function.partition(":")
    factory: Any = importlib.import_module(module)
    for attribute in function.split("."):
        factory = getattr(factory, attribute)
    return factory(argument) if argument else factory()


def _entry(table: dict[str, Entry | str], name: str) -> Entry:
    """The entry of ``name`` in ``table`` (a known name), loaded and kept on first use."""
    entry = table[name]
    if isinstance(entry, str):
        entry = table[name] = load_entry(entry)
    return entry


def _register(table: dict[str, Entry | str], entry: Entry | str, name: str | None) -> None:
    key = name if isinstance(entry, str) else entry.name
    if not key:
        raise ValueError("a stage registered by reference needs its name")
    table[key] = entry


def register_frontend(entry: FrontendEntry | str, name: str | None = None) -> None:
    """Register a frontend: an entry, or (lazily) ``"module:function"`` that returns one, under ``name``."""
    _register(_FRONTENDS, entry, name)


def register_retrieval(entry: RetrievalEntry | str, name: str | None = None) -> None:
    """Register a retrieval: an entry, or (lazily) ``"module:function"`` that returns one, under ``name``."""
    _register(_RETRIEVALS, entry, name)


def register_aligner(entry: AlignerEntry | str, name: str | None = None) -> None:
    """Register an aligner: an entry, or (lazily) ``"module:function"`` that returns one, under ``name``."""
    _register(_ALIGNERS, entry, name)


def register_graph(entry: GraphEntry | str, name: str | None = None) -> None:
    """Register a graph design: an entry, or (lazily) ``"module:function"`` that returns one, under ``name``."""
    _register(_GRAPHS, entry, name)


def frontend_names() -> list[str]:
    return list(_FRONTENDS)


def retrieval_names() -> list[str]:
    return list(_RETRIEVALS)


def aligner_names() -> list[str]:
    return list(_ALIGNERS)


def graph_names() -> list[str]:
    return list(_GRAPHS)


def frontend_entry(name: str) -> FrontendEntry:
    """The entry of frontend ``name``; ``UserError`` listing the available ones otherwise."""
    if name not in _FRONTENDS:
        raise UserError(f"--frontend (config key frontend) '{name}' is an unknown model or frontend (also --model); available: "
                        f"{', '.join(_FRONTENDS)} (sl4slam models lists them), or a model's weights file or hub id")
    return _entry(_FRONTENDS, name)


def object_model_entries() -> list[ObjectModelEntry]:
    """The models of the object queries (each loaded; their code, and torch, load only when used)."""
    return [_entry(_OBJECT_MODELS, name) for name in _OBJECT_MODELS]


def frontend_entries() -> list[FrontendEntry]:
    """Every frontend in the catalog (each loaded)."""
    return [frontend_entry(name) for name in frontend_names()]


def retrieval_entry(name: str) -> RetrievalEntry:
    """The entry of retrieval ``name``; ``UserError`` listing the available ones otherwise."""
    if name not in _RETRIEVALS:
        raise UserError(f"unknown retrieval '{name}' (--retrieval); available: {', '.join(_RETRIEVALS)}")
    return _entry(_RETRIEVALS, name)


def aligner_entry(name: str) -> AlignerEntry:
    """The entry of alignment model ``name``; ``UserError`` listing the available ones otherwise."""
    if name not in _ALIGNERS:
        raise UserError(f"unknown alignment model '{name}' (--alignment); available: {', '.join(_ALIGNERS)}")
    return _entry(_ALIGNERS, name)


def graph_entry(name: str) -> GraphEntry:
    """The entry of graph design ``name``; ``UserError`` listing the available ones otherwise."""
    if name not in _GRAPHS:
        raise UserError(f"unknown graph design '{name}' (--graph); available: {', '.join(_GRAPHS)}")
    return _entry(_GRAPHS, name)
