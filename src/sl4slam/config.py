"""The run's tree of settings: every stage's section, composed.

Each section lives beside the stage that reads it (``sl4slam.keyframes.KeyframeConfig``,
``sl4slam.alignment.settings.AlignmentConfig``, ...) and is re-exported here. Defaults cite VGGT-SLAM (Maggio, Lim, Carlone, NeurIPS 2025), section 5.1 ("paper"), or the authors'
code ("reference code"); a default of ours names the page of ``docs/decisions/`` that gives its
reasons ("decision: ..."). The command line is generated from this tree (``sl4slam.cli``) and the same tree can be read from a
TOML or JSON file. Each section checks its own values in ``validate()``; ``sl4slam.resolve.resolve``
calls it once per run, before any frame is read, and settles every "auto" (the rules live there,
not here); a bad value is one line that names the flag, the config-file key and the allowed range.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .alignment.settings import AlignmentConfig
from .backend.settings import BackendConfig
from .errors import UserError
from .frontend.settings import (SIM_EXACT, SIM_PROFILE_VALUES, SIM_PROFILES, ModelConfig, SimulatorConfig,
                                apply_sim_profile, profile_values)
from .io.settings import SourceConfig
from .keyframes import KeyframeConfig
from .localize import LocalizationConfig
from .loops import LoopConfig
from .objects.settings import ObjectsConfig
from .result.settings import OutputConfig
from .retrieval.settings import FalseLoopConfig, RetrievalConfig
from .section import Section, setting
from .submap import SubmapConfig
from .upgrade import UpgradeConfig

__all__ = ["SLAMConfig", "Section", "setting", "sections", "config_to_dict", "config_from_dict", "load_config",
           "read_config_file", "AlignmentConfig", "BackendConfig", "FalseLoopConfig", "KeyframeConfig",
           "LocalizationConfig", "LoopConfig", "ModelConfig", "ObjectsConfig", "OutputConfig", "RetrievalConfig",
           "SimulatorConfig", "SourceConfig", "SubmapConfig", "UpgradeConfig", "SIM_EXACT", "SIM_PROFILES", "SIM_PROFILE_VALUES",
           "apply_sim_profile", "profile_values"]


@dataclass
class SLAMConfig(Section):
    """Everything a run needs. ``sl4slam.resolve.resolve`` checks it once and settles every "auto"."""

    frontend: str = setting("vggt", common=True, flag='--frontend', aliases=('--model',),
                            check=lambda v: bool(v.strip()),
                            allowed="a model name, simulated, or a model's weights")
    """The frontend that reconstructs each submap: a model ("vggt", "pi3", "pi3x", "da3-small",
    "da3-base", "da3-large", "da3-giant"; ``sl4slam models`` lists them with their weights and
    licences), "simulated" (VGGT-like submaps from an RGB-D sequence's ground truth), or a model's
    weights (a hub id or a file), whose model is recognized. VGGT-1B is the paper's."""
    device: str = setting("auto", common=True)
    """Where the models run (the frontend's and SALAD's): "auto" (CUDA when available), "cpu",
    "cuda" or "cuda:N"."""
    max_frontend_failures: int = setting(3, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """A submap on which the frontend fails (an exception, or non-finite output) is skipped; this
    many failures in a row end the run (with its outputs written): the frontend is broken, not the
    frames."""
    overlap: bool = setting(True, advanced=True)
    """Run the model on the next submap while the graph, the loop checks and the outputs work on
    this one (one worker, at most one submap waiting; ``sl4slam.schedule``). The results are the same
    as one submap after the other, byte for byte; it needs ``--tau-interval`` >= 1 (the default, 2),
    so that a loop frame never comes from the submap still being worked on."""
    workers: int = setting(1, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Model copies that reconstruct windows ahead of the graph, on local worker processes (or as
    actors on the Ray cluster of ``ray_address``); the graph takes the windows in order, and the
    trajectory and map are the same as with one, byte for byte (``sl4slam.schedule.AheadScheduler``).
    At most ``tau_interval`` + 1 windows can be ahead (a loop frame must be stored before its window
    is assembled). File sources only: a live camera keeps one model in the run's own process. A
    frontend handed to the library directly (``SLAMPipeline.from_config(config, frontend=...)``) is
    called from that many threads at once instead."""
    ray_address: str = setting("", advanced=True)
    """Run the model's windows as ``workers`` actors on this existing Ray cluster (``host:6379``,
    ``ray://host:10001`` or ``auto``; one GPU per actor where the cluster has GPUs); "" runs them
    locally. Needs ``sl4slam[cluster]``; every node needs sl4slam and the model weights."""
    source: SourceConfig = setting(factory=SourceConfig)
    keyframes: KeyframeConfig = setting(factory=KeyframeConfig)
    submap: SubmapConfig = setting(factory=SubmapConfig)
    alignment: AlignmentConfig = setting(factory=AlignmentConfig)
    backend: BackendConfig = setting(factory=BackendConfig)
    retrieval: RetrievalConfig = setting(factory=RetrievalConfig)
    loops: LoopConfig = setting(factory=LoopConfig)
    false_loops: FalseLoopConfig = setting(factory=FalseLoopConfig)
    sim: SimulatorConfig = setting(factory=SimulatorConfig)
    model: ModelConfig = setting(factory=ModelConfig)
    output: OutputConfig = setting(factory=OutputConfig)
    upgrade: UpgradeConfig = setting(factory=UpgradeConfig)
    localize: LocalizationConfig = setting(factory=LocalizationConfig)
    objects: ObjectsConfig = setting(factory=ObjectsConfig)

    def validate(self) -> None:
        """Check every section, then the settings that depend on each other (the frontend's name
        and the "auto" rules are checked by ``sl4slam.resolve.resolve``)."""
        super().validate()
        device_ok = self.device in ("auto", "cpu", "cuda") or (self.device.startswith("cuda:") and self.device[5:].isdigit())
        self._require("device", device_ok, "auto, cpu, cuda or cuda:N")
        for section in sections(self):
            section.validate()
        if self.model.dtype == "int8" and self.device.startswith("cuda"):
            raise UserError("--dtype (config key model.dtype) must be auto, fp32, bf16 or fp16 on a GPU "
                            "(int8 runs on the CPU only), got 'int8'")


def sections(config: SLAMConfig) -> list[Section]:
    """The sections of ``config`` in tree order."""
    return [getattr(config, f.name) for f in dataclasses.fields(config) if isinstance(getattr(config, f.name), Section)]


def config_to_dict(config: Any) -> dict:
    """A plain, JSON-serialisable dict of a config tree."""
    return dataclasses.asdict(config)


def _apply(target: Any, values: dict, where: str) -> None:
    names = {f.name: f for f in dataclasses.fields(target)}
    for key, value in values.items():
        if key not in names:
            raise UserError(f"unknown setting '{where}{key}' in config file; valid: {', '.join(sorted(names))}")
        current = getattr(target, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise UserError(f"setting '{where}{key}' must be a table/object of settings")
            _apply(current, value, f"{where}{key}.")
        else:
            expected = current if current is not None else type(target).field_default(key)
            if expected is not None and value is not None and not isinstance(value, type(expected)):
                if isinstance(expected, float) and isinstance(value, int) and not isinstance(value, bool):
                    value = float(value)
                else:
                    raise UserError(
                        f"setting '{where}{key}' must be {type(expected).__name__}, got {value!r}"
                    )
            setattr(target, key, value)


# Settings that moved: (old table, old key) -> (new table, new key); "" is the top level.
_MOVED = {
    ("", "stride"): ("source", "stride"), ("", "max_frames"): ("source", "max_frames"),
    ("vggt", "device"): ("", "device"),
    **{("vggt", key): ("model", key) for key in ("weights", "dtype", "preprocess_mode", "max_memory_gb",
                                                 "head_chunk_frames", "match_layer")},
    **{("sim", f"false_loop_{key}"): ("false_loops", key) for key in ("rate", "min_distance", "min_angle", "max_overlap")},
    ("output", "save_keyframe_points"): ("output", "keyframes"),
}
_MOVED_VALUES = {("output", "save_keyframe_points"): {True: "compact", False: "none"}}
"""Moved settings whose values changed too: (old table, old key) -> {old value: new value}."""
_RENAMED_VALUES = {("alignment", "planar_model"): {"auto": "by-support"}, ("backend", "weighting"): {"auto": "by-link"}}
"""Values of earlier releases under their current names: (table, key) -> {old value: new value}."""


def _move_renamed(values: dict) -> dict:
    """``values`` with settings of earlier releases (``[vggt] weights``, top-level ``stride``,
    ``[sim] false_loop_rate`` ...) under their current keys, with their values translated where
    those changed too (``[output] save_keyframe_points = true / false`` is ``keyframes = "compact" /
    "none"``; ``[backend] weighting = "auto"`` is "by-link"); the current key wins if both are given."""
    moved = {key: dict(value) if isinstance(value, dict) else value for key, value in values.items()}
    for (old_table, old_key), (new_table, new_key) in _MOVED.items():
        old = moved if not old_table else moved.get(old_table)
        if not isinstance(old, dict) or old_key not in old:
            continue
        value = old.pop(old_key)
        mapping = _MOVED_VALUES.get((old_table, old_key))
        if mapping is not None and isinstance(value, bool):
            value = mapping[value]
        new = moved if not new_table else moved.setdefault(new_table, {})
        if isinstance(new, dict):
            new.setdefault(new_key, value)
    if isinstance(moved.get("vggt"), dict) and not moved["vggt"]:
        del moved["vggt"]
    for (table, key), mapping in _RENAMED_VALUES.items():
        section = moved.get(table)
        if isinstance(section, dict) and isinstance(section.get(key), str) and section[key] in mapping:
            section[key] = mapping[section[key]]
    return moved


def config_from_dict(values: dict, base: SLAMConfig | None = None) -> SLAMConfig:
    """Overlay ``values`` (nested dict) on ``base`` (default: the defaults); keys of earlier
    releases are read under their current names."""
    config = base if base is not None else SLAMConfig()
    _apply(config, _move_renamed(values), "")
    return config


def load_config(path: str | Path, base: SLAMConfig | None = None) -> SLAMConfig:
    """Read a TOML (``.toml``) or JSON file of settings over the defaults."""
    return config_from_dict(read_config_file(path), base)


def read_config_file(path: str | Path) -> dict:
    """The nested dict of settings in a TOML (``.toml``) or JSON file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"config file not found: {path}")
    try:
        if path.suffix.lower() == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib  # type: ignore[no-redef]
            values = tomllib.loads(path.read_text())
        else:
            values = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot parse config file {path}: {exc}") from None
    if not isinstance(values, dict):
        raise UserError(f"config file {path} must hold a table/object of settings")
    return values
