"""From the settings a user gave to the settings a run uses: every "auto" settled, in one place.

:func:`resolve` checks the config tree once (each section's ``validate``), looks the frontend up
in the registry (a model's name, or its weights: a hub id or a file whose keys it recognizes) and
settles every "auto" by the rules below, each with the reason it gives the user. Everything
downstream (the composition root, the pipeline, the outputs) reads the :class:`ResolvedConfig` and
never applies a rule again; the runner prints :meth:`ResolvedConfig.lines`, the summary records
:meth:`ResolvedConfig.choices`.

The rules (each setting's docstring in ``sl4slam.config`` names the page of ``docs/decisions/``
that gives its reasons):

- graph design: "keyframe" (VGGT-SLAM 2.0) for the SL(4) group, "submap" for Sim(3);
- alignment model: "select" for the keyframe graph (the calibration link or the 15-DOF fit, chosen
  per link; with known intrinsics the calibration link, a similarity then), "sl4" for the SL(4)
  submap graph, "sim3-cameras" for Sim(3); a projective model on a Sim(3) graph is refused;
- metric upgrade: on where links may be 15-DOF (the SL(4) submap graph; the keyframe graph with
  "select", "sl4" or "hybrid" links), and never with known intrinsics (the cameras are metric
  already); links are completed from the cameras only where it runs, on SL(4) links;
- attention loop check: never without retrieval; on with the keyframe graph when the frontend
  scores pairs; "on" with a frontend that cannot is refused;
- retrieval: SALAD when its weights are found locally, else ORB;
- device: CUDA when available (only looked up when a model runs); ``cuda`` without a GPU is refused;
- model weights: the model's released weights;
- model precision: half precision on a CUDA GPU (bf16 where it runs, else fp16), float32 elsewhere
  (``sl4slam.models.precision.settle_mode``; settled with the device); bf16 asked for on a GPU
  that does not run it becomes fp16; on a GPU a note says what was chosen and why;
- overlap of the model and the graph work: only with ``tau_interval`` >= 1;
- simulator: every error magnitude not set explicitly from its profile.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import struct
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from .config import SLAMConfig
from .errors import UserError
from .intrinsics import KnownIntrinsics, parse_intrinsics
from .registry import (FrontendEntry, aligner_entry, aligner_names, frontend_entries, frontend_entry, frontend_names,
                       graph_entry, graph_names, retrieval_entry, retrieval_names)
from .types import FrontendCapabilities


class Group(str, Enum):
    """The group of the graph's transforms."""

    SL4 = "sl4"
    SIM3 = "sim3"


def _members(names: list[str]) -> list[tuple[str, str]]:
    """Enum members of catalog names: ``"sim3-points"`` is ``SIM3_POINTS``."""
    return [(name.upper().replace("-", "_").replace(".", "_"), name) for name in names]


class _Aligners(str, Enum):
    """The base of :data:`AlignmentModel` (members come from the catalog)."""

    @property
    def group(self) -> Group:
        """The group of its measurements."""
        return Group(aligner_entry(self.value).group)


GraphDesign = Enum("GraphDesign", _members(graph_names()), type=str, module=__name__)
GraphDesign.__doc__ = """A graph design of the catalog (``sl4slam.registry``): ``SUBMAP`` (VGGT-SLAM, a node per
submap), ``KEYFRAME`` (VGGT-SLAM 2.0, a node per keyframe)."""
AlignmentModel = _Aligners("AlignmentModel", _members(aligner_names()), module=__name__)
AlignmentModel.__doc__ = """What measures the link between two submaps (``AlignmentConfig.model``): an alignment
model of the catalog (``SL4``, ``CALIBRATION``, ``HYBRID``, ``SELECT``, ``SIM3_POINTS``, ``SIM3_CAMERAS``)."""
RetrievalKind = Enum("RetrievalKind", _members(retrieval_names()), type=str, module=__name__)
RetrievalKind.__doc__ = """A retrieval of the catalog (``SALAD``, ``ORB``, ``NONE``)."""

_GROUP_WORDS = {"sl4": "an SL(4)", "sim3": "a Sim(3)"}


@dataclass(frozen=True)
class ResolvedConfig:
    """The settings of one run, every "auto" settled and checked.

    Attributes:
        config: the settled tree: the user's settings with each "auto" replaced by what it became
            (``backend.graph``, ``alignment.model``, ``upgrade.mode``, ``loops.verify_attention``,
            ``retrieval.kind``, ``model.weights``, ``device``, the simulator's magnitudes).
        frontend: the registry entry of the frontend.
        capabilities: what the frontend can do (a replayed cache: what the recording holds).
        group, graph, alignment, retrieval: the settled choices, typed.
        metric_upgrade: whether the run ends with the metric upgrade.
        complete_links: whether fallback links on planar frames are completed from the cameras.
        attention_check: whether loops pass the attention check.
        device: where the models run ("cpu", "cuda", "cuda:N").
        overlap: whether the next submap's model runs while the graph works on this one.
        workers: windows the model may work on at once (``SLAMConfig.workers``).
        notes: why each "auto" became what it is, one line each.
        intrinsics: the known intrinsics the settings give (numbers or a file), ``None`` otherwise.
        intrinsics_from_source: the source's own calibration is the known intrinsics
            (``--intrinsics auto``; read when the source is opened, ``sl4slam.intrinsics.from_source``).
    """

    config: SLAMConfig
    frontend: FrontendEntry
    capabilities: FrontendCapabilities
    group: Group
    graph: GraphDesign
    alignment: AlignmentModel
    retrieval: RetrievalKind
    metric_upgrade: bool
    complete_links: bool
    attention_check: bool
    device: str
    overlap: bool = False
    notes: tuple[str, ...] = ()
    intrinsics: KnownIntrinsics | None = None
    intrinsics_from_source: bool = False
    workers: int = 1

    @property
    def needs_ground_truth(self) -> bool:
        return self.capabilities.needs_ground_truth

    def choices(self) -> dict[str, Any]:
        """The settled choices as plain values (``summary.json["resolved"]``)."""
        return {"frontend": self.frontend.name, "group": self.group.value, "graph": self.graph.value,
                "alignment": self.alignment.value, "retrieval": self.retrieval.value,
                "metric_upgrade": self.metric_upgrade, "complete_links": self.complete_links,
                "attention_check": self.attention_check, "device": self.device, "overlap": self.overlap,
                "notes": list(self.notes)}

    def lines(self) -> list[str]:
        """What the run uses, for the console: one line, then the reasons of the "auto" choices."""
        group = {"sl4": "SL(4)", "sim3": "Sim(3)"}[self.group.value]
        head = (f"{self.frontend.name} frontend on {self.device}; {group} {self.graph.value} graph, "
                f"{self.alignment.value} links; retrieval {self.retrieval.value}; "
                f"metric upgrade {'on' if self.metric_upgrade else 'off'}")
        return [head] + [f"  {note}" for note in self.notes]


def resolve(config: SLAMConfig, capabilities: FrontendCapabilities | None = None,
            probe_device: bool = True) -> ResolvedConfig:
    """Check ``config`` and settle every "auto" (see the module doc), once per run, at its entry point.

    Args:
        config: the user's settings (not changed).
        capabilities: what the frontend can do when that is not the registered model's (a replayed
            cache holds only what its recording asked for).
        probe_device: settle the device on this machine (``False`` where the run happens elsewhere,
            e.g. an evaluation planned here for a cluster: the device stays as given).

    Raises:
        UserError: a bad setting, an unknown frontend, or choices that cannot go together.
        TypeError: ``config`` is not a ``SLAMConfig`` (a ``ResolvedConfig`` is settled already).
    """
    if not isinstance(config, SLAMConfig):
        raise TypeError(f"resolve() takes a SLAMConfig, got {type(config).__name__}")
    config.validate()
    settled = copy.deepcopy(config)
    notes: list[str] = []
    entry = _frontend(settled, notes)
    capabilities = capabilities or entry.capabilities
    group = Group(settled.backend.kind)
    graph = _graph(settled, group, notes)
    alignment = _alignment(settled, group, graph, notes)
    metric_upgrade = _metric_upgrade(settled, group, graph, alignment, notes)
    spec = settled.source.intrinsics.strip()
    intrinsics_from_source = spec == "auto"
    known = None if intrinsics_from_source else parse_intrinsics(spec)  # a bad spec is one line now
    if spec:
        if metric_upgrade:
            notes.append("metric upgrade: off (known intrinsics: the cameras are metric already)")
        metric_upgrade, settled.upgrade.mode = False, "off"
    complete_links = settled.upgrade.complete_links and group is Group.SL4 and metric_upgrade
    retrieval = _retrieval(settled, notes)
    attention = _attention(settled, graph, retrieval, capabilities, notes)
    device = _device(settled, entry, retrieval) if probe_device else settled.device
    if probe_device and entry.settle_dtype is not None:
        from .models.precision import precision_note

        requested = settled.model.dtype
        settled.model.dtype = entry.settle_dtype(requested, device)
        note = precision_note(requested, settled.model.dtype, device)
        if note:
            notes.append(note)
    settled.sim = settled.sim.resolved()
    overlap = settled.overlap and (retrieval is RetrievalKind.NONE or settled.retrieval.tau_interval >= 1)
    if settled.overlap and not overlap:
        notes.append("overlap: off (--tau-interval 0 lets a loop frame come from the submap still being worked on)")
    settled.overlap = overlap
    workers = _workers(settled, overlap, retrieval, notes)
    if settled.false_loops.rate > 0 and retrieval is RetrievalKind.NONE:
        notes.append("false loops: none are injected (there is no retrieval to propose loops)")
    return ResolvedConfig(settled, entry, capabilities, group, graph, alignment, retrieval, metric_upgrade,
                          complete_links, attention, device, overlap, tuple(notes), known, intrinsics_from_source,
                          workers)


def _workers(settled: SLAMConfig, overlap: bool, retrieval: RetrievalKind, notes: list[str]) -> int:
    """Windows the model may work on at once (``workers``); refuses settings that need the model in
    the run's own process, one after the other."""
    workers = settled.workers
    if workers == 1 and not settled.ray_address:
        return 1
    what = f"--workers {workers}" if workers > 1 else "--ray-address"
    if not overlap:
        why = ("--tau-interval 0 lets a loop frame come from the submap still being worked on"
               if retrieval is not RetrievalKind.NONE and settled.retrieval.tau_interval == 0
               else "--no-overlap forbids (it runs one submap after the other)")
        raise UserError(f"{what} runs windows ahead of the graph, which {why}; drop {what} or "
                        "use --tau-interval 1 or more with the overlap on")
    if retrieval is not RetrievalKind.NONE and workers > settled.retrieval.tau_interval + 1:
        notes.append(f"workers: at most {settled.retrieval.tau_interval + 1} windows can be ahead of the graph "
                     f"(--tau-interval {settled.retrieval.tau_interval} + 1); the other workers wait")
    return workers


def _frontend(settled: SLAMConfig, notes: list[str]) -> FrontendEntry:
    """The frontend's entry; ``--model`` given as weights (a hub id or a file) names its model."""
    name = settled.frontend
    if name not in frontend_names():
        found = model_of_weights(name)
        if found is None:
            frontend_entry(name)  # raises the one line listing the names
        notes.append(f"model: {found.name} (recognized from {name})")
        settled.frontend, settled.model.weights, name = found.name, name, found.name
    entry = frontend_entry(name)
    if entry.weights is not None and settled.model.weights == "auto":
        settled.model.weights = entry.weights.repo_id
    return entry


def model_of_weights(weights: str) -> FrontendEntry | None:
    """The registered model whose weights ``weights`` are: a hub id one of them names (its own or a
    file in it), or a local file whose tensor names one of them recognizes; ``None`` otherwise.

    Raises:
        WeightsFileError: a local file that cannot be read (cut short, corrupt, unreadable): the
            one line a run gives for it, not "unknown model".
    """
    from .models.hub import is_hub_id

    if is_hub_id(weights):
        repo = weights.partition(":")[0].lower()
        return next((e for e in frontend_entries() if e.weights is not None and e.weights.repo_id.lower() == repo), None)
    path = Path(weights).expanduser()
    if not path.is_file():
        return None
    keys = _tensor_names(path)
    return next((e for e in frontend_entries() if e.recognizes is not None and e.recognizes(keys)), None)


def _tensor_names(path: Path) -> dict[str, SimpleNamespace]:
    """Tensor names of a weights file with their shapes (``.shape``: models of one family differ in
    widths only); a safetensors header is read without loading anything. A file that is cut short,
    corrupt or unreadable raises :class:`~sl4slam.models.checkpoint.WeightsFileError`."""
    from .models.checkpoint import check_weights_file, pass_again, read_checkpoint

    fix = f"delete it and fetch it again, then {pass_again('--model')}"
    check_weights_file(path, "model", fix)
    if path.suffix.lower() == ".safetensors":
        try:
            with open(path, "rb") as handle:
                (length,) = struct.unpack("<Q", handle.read(8))
                header = json.loads(handle.read(length))
            return {k: SimpleNamespace(shape=tuple(v.get("shape", ()))) for k, v in header.items() if k != "__metadata__"}
        except (OSError, ValueError, struct.error, AttributeError):
            return {}
    state_dict, _ = read_checkpoint(path, "model", fix)
    return {k: SimpleNamespace(shape=tuple(getattr(v, "shape", ()))) for k, v in state_dict.items()}


def _graph(settled: SLAMConfig, group: Group, notes: list[str]) -> GraphDesign:
    if settled.backend.graph == "auto":
        settled.backend.graph = "keyframe" if group is Group.SL4 else "submap"
        notes.append(f"graph: {settled.backend.graph} (auto: the {'SL(4)' if group is Group.SL4 else 'Sim(3)'} default)")
    graph = GraphDesign(settled.backend.graph)
    holds = graph_entry(graph.value).groups
    if group.value not in holds:
        others = [name for name in graph_names() if group.value in graph_entry(name).groups]
        raise UserError(f"--graph (config key backend.graph) {graph.value} needs --backend {' or '.join(holds)} (the {graph.value} graph is "
                        f"{' or '.join(_GROUP_WORDS[g] for g in holds)} graph); "
                        f"use --graph {' or '.join(others)} or auto with --backend {group.value}")
    return graph


def _alignment(settled: SLAMConfig, group: Group, graph: GraphDesign, notes: list[str]) -> AlignmentModel:
    if settled.alignment.model == "auto":
        known_k = bool(settled.source.intrinsics.strip())
        model = ("sim3-cameras" if group is Group.SIM3 else
                 "calibration" if graph is GraphDesign.KEYFRAME and known_k else
                 "select" if graph is GraphDesign.KEYFRAME else "sl4")
        settled.alignment.model = model
        notes.append("links: calibration (auto: with known intrinsics the shared frames' link is a similarity; a "
                     "15-DOF fit would add a projective drift that no metric upgrade removes)" if model == "calibration"
                     else f"links: {model} (auto: the {graph.value} graph's in {group.value})")
    alignment = AlignmentModel(settled.alignment.model)
    if group is Group.SIM3 and alignment.group is Group.SL4:
        raise UserError(f"--alignment (config key alignment.model) {alignment.value} measures projective transforms, which a Sim(3) graph cannot "
                        "hold; use --alignment sim3-points or sim3-cameras with --backend sim3")
    return alignment


def _metric_upgrade(settled: SLAMConfig, group: Group, graph: GraphDesign, alignment: AlignmentModel,
                    notes: list[str]) -> bool:
    if settled.upgrade.mode == "auto":
        projective = aligner_entry(alignment.value).projective
        on = group is Group.SL4 and (graph is GraphDesign.SUBMAP or projective)
        settled.upgrade.mode = "on" if on else "off"
        notes.append(f"metric upgrade: on (auto: {alignment.value} links may be 15-DOF, so the map inherits one projective "
                     "distortion)" if on else
                     f"metric upgrade: off (auto: {alignment.value} links carry no common projective distortion; "
                     "--metric-upgrade on applies it all the same)")
    return settled.upgrade.mode == "on"


def _retrieval(settled: SLAMConfig, notes: list[str]) -> RetrievalKind:
    if settled.retrieval.kind == "auto":
        from .models.salad import find_salad_weights, salad_cache_dir

        if settled.retrieval.salad_weights is not None or find_salad_weights() is not None:
            settled.retrieval.kind = "salad"
            notes.append("retrieval: salad (auto: its weights were found)")
        else:
            settled.retrieval.kind = "orb"
            notes.append(f"retrieval: orb (auto: SALAD weights not found; pass --salad-weights or put dino_salad.ckpt "
                         f"in {salad_cache_dir()})")
    return RetrievalKind(settled.retrieval.kind)


def _attention(settled: SLAMConfig, graph: GraphDesign, retrieval: RetrievalKind,
               capabilities: FrontendCapabilities, notes: list[str]) -> bool:
    setting = settled.loops.verify_attention
    if setting == "on" and not capabilities.scores_pairs:
        raise UserError(f"--loop-verify-attention (config key loops.verify_attention) on needs image-match ratios, which the {settled.frontend} frontend "
                        "does not give; use --loop-verify-attention off or auto")
    if retrieval is RetrievalKind.NONE:
        on = False
    elif setting == "auto":
        on = graph is GraphDesign.KEYFRAME and capabilities.scores_pairs
        if graph is GraphDesign.KEYFRAME and not on:
            notes.append(f"attention loop check: off (auto: the {settled.frontend} frontend gives no image-match "
                         "ratios; loops pass the view and graph checks)")
    else:
        on = setting == "on"
    settled.loops.verify_attention = "on" if on else "off"
    return on


def _device(settled: SLAMConfig, entry: FrontendEntry, retrieval: RetrievalKind) -> str:
    """The models' device; torch is imported only when a model runs."""
    uses_models = (entry.weights is not None or retrieval_entry(retrieval.value).uses_device
                   or settled.objects.enabled)  # --objects runs an image embedder
    if not uses_models:
        settled.device = "cpu" if settled.device == "auto" else settled.device
        return settled.device
    import torch

    if settled.device == "auto":
        settled.device = "cuda" if torch.cuda.is_available() else "cpu"
    elif settled.device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UserError(f"--device {settled.device} was requested but no CUDA GPU is available; use --device cpu "
                            "or auto")
        index = int(settled.device[5:] or 0) if settled.device.startswith("cuda:") else 0
        if index >= torch.cuda.device_count():
            raise UserError(f"--device {settled.device}: this machine has {torch.cuda.device_count()} GPU(s) "
                            f"(cuda:0 to cuda:{torch.cuda.device_count() - 1})")
    return settled.device


def settled_dict(resolved: ResolvedConfig) -> dict:
    """The settled tree as a plain dict (what a run records as its settings)."""
    return dataclasses.asdict(resolved.config)
