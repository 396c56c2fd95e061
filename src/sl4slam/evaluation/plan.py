"""What an evaluation measures and sweeps, and what it did: the plain data the protocol
(:mod:`.protocol`) and the report (:mod:`.report`) share.

- :data:`SEEDED_SETTINGS`: every setting that seeds a random choice (run ``r`` sets each to ``r``);
- :class:`EvalSettings`: how results are measured;
- :class:`GridPoint` and :func:`parse_grid`: the combinations of settings a sweep runs;
- :func:`seeded`: a config with every seeded setting set to one run's seed;
- :class:`EvalOutcome`: what :func:`~.protocol.evaluate` did.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import SLAMConfig
from ..errors import UserError
from .datasets import Sequence, get_dataset

SEEDED_SETTINGS = ("sim.seed", "alignment.seed", "retrieval.seed", "false_loops.seed", "output.seed")
"""Every setting that seeds a random choice; run ``r`` sets each of them to ``r``."""
DEFAULT_POINT = "default"


@dataclass
class EvalSettings:
    """How results are measured (not how SLAM runs: that is :class:`sl4slam.config.SLAMConfig`)."""

    dataset: str = "tum"
    """"tum" or "7scenes"."""
    runs: int = 5
    """Runs per sequence and grid point; run r uses seed r (paper: 5 runs, reference evals/eval_*.sh)."""
    dense: bool = True
    """7-Scenes: dense accuracy / completion / chamfer besides the ATE (paper's 7-Scenes tables)."""
    max_depth: float = 4.5
    """Ground-truth depth beyond this (m) is dropped (reference dense evaluation: Kinect range)."""
    max_error: float = 0.5
    """Nearest-neighbour distances are clipped here (m) (reference dense evaluation)."""
    icp_voxel_size: float = 0.05
    """Voxel size (m) of the copies ICP runs on (reference dense evaluation)."""
    icp_max_correspondence: float = 0.1
    """ICP's maximum correspondence distance (m) (reference dense evaluation)."""
    keep_keyframe_points: bool = False
    """Keep each run's ``keyframes/`` (dense data per keyframe, 0.2-0.3 MB each at VGGT's 518x392 in
    the compact layout: GBs for a full evaluation). Off: TUM runs do not write them, and 7-Scenes
    runs remove them once the dense metrics are measured."""

    def validate(self) -> None:
        get_dataset(self.dataset)
        if int(self.runs) < 1:
            raise UserError(f"--runs must be at least 1, got {self.runs}")
        for name in ("max_depth", "max_error", "icp_voxel_size", "icp_max_correspondence"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise UserError(f"evaluation setting {name} must be a positive number, got {value}")


# --------------------------------------------------------------------------------------------
# Grid of settings
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GridPoint:
    """One combination of settings of a sweep: ``(("submap.size", 16), ("backend.kind", "sl4"))``."""

    overrides: tuple[tuple[str, Any], ...] = ()

    @property
    def label(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.overrides) or DEFAULT_POINT

    @property
    def slug(self) -> str:
        """Folder name of the point's runs."""
        return "_".join(f"{k}={v}" for k, v in self.overrides).replace(os.sep, "-") or DEFAULT_POINT

    def apply(self, config: SLAMConfig) -> SLAMConfig:
        """A copy of ``config`` with this point's settings."""
        config = copy.deepcopy(config)
        for path, value in self.overrides:
            _set(config, path, value)
        return config


def _resolve(config: SLAMConfig, path: str) -> tuple[Any, str]:
    """The object holding setting ``path`` ("submap.size", "frontend") and the field name."""
    parts = path.split(".")
    target: Any = config
    for depth, part in enumerate(parts):
        names = {f.name for f in dataclasses.fields(target)}
        if part not in names:
            where = ".".join(parts[:depth]) or "the top level"
            raise UserError(f"unknown setting '{path}' in --grid; settings of {where}: {', '.join(sorted(names))}")
        if depth == len(parts) - 1:
            break
        target = getattr(target, part)
        if not dataclasses.is_dataclass(target):
            raise UserError(f"'{'.'.join(parts[:depth + 1])}' is a setting, not a section; write --grid {'.'.join(parts[:depth + 1])}=...")
    if dataclasses.is_dataclass(getattr(target, parts[-1])):
        raise UserError(f"'{path}' is a section; name one of its settings, e.g. --grid {path}.{dataclasses.fields(getattr(target, parts[-1]))[0].name}=...")
    return target, parts[-1]


def _set(config: SLAMConfig, path: str, value: Any) -> None:
    target, name = _resolve(config, path)
    setattr(target, name, value)


def _parse_value(text: str, current: Any, path: str) -> Any:
    text = text.strip()
    try:
        if isinstance(current, bool):
            lowered = text.lower()
            if lowered not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                raise ValueError
            return lowered in ("true", "1", "yes", "on")
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float):
            value = float(text)
            if not np.isfinite(value):
                raise ValueError
            return value
    except ValueError:
        raise UserError(f"--grid {path}: '{text}' is not a valid {type(current).__name__}") from None
    if not text:
        raise UserError(f"--grid {path}: empty value")
    return None if current is None and text.lower() == "none" else text


def parse_grid(specs: list[str] | None) -> list[GridPoint]:
    """Grid points from ``["submap.size=8,16,32", "backend.kind=sl4,sim3"]`` (their product).

    Each spec is ``SETTING=V1,V2,...`` with ``SETTING`` a config path as in a config file
    (``section.name``, or a top-level name such as ``frontend``). Values are parsed as the
    setting's type. The seeded settings cannot be swept: runs set them.
    """
    if not specs:
        return [GridPoint()]
    reference = SLAMConfig()
    axes: list[list[tuple[str, Any]]] = []
    seen: set[str] = set()
    for spec in specs:
        path, sep, values = spec.partition("=")
        path = path.strip()
        if not sep or not path or not values.strip():
            raise UserError(f"--grid '{spec}': write SETTING=V1,V2,... (e.g. submap.size=8,16,32)")
        if path in SEEDED_SETTINGS:
            raise UserError(f"--grid {path}: seeds are set by the runs (run r uses seed r); use --runs instead")
        if path in seen:
            raise UserError(f"--grid names {path} twice; give all its values in one SETTING=V1,V2 list")
        seen.add(path)
        target, name = _resolve(reference, path)
        parsed = [_parse_value(v, getattr(target, name), path) for v in values.split(",")]
        if len(set(map(str, parsed))) != len(parsed):
            raise UserError(f"--grid {path}: a value is repeated")
        axes.append([(path, v) for v in parsed])
    return [GridPoint(tuple(combination)) for combination in itertools.product(*axes)]


def seeded(config: SLAMConfig, run: int) -> SLAMConfig:
    """A copy of ``config`` whose seeded settings (:data:`SEEDED_SETTINGS`) are all ``run``."""
    config = copy.deepcopy(config)
    for path in SEEDED_SETTINGS:
        _set(config, path, int(run))
    return config


@dataclass
class EvalOutcome:
    """What :func:`evaluate` did.

    Attributes:
        results: one result dict per (point, sequence, run), in that order.
        points, sequences, missing: the grid points, the evaluated sequences, the paper's
            sequences absent from the root.
        computed, reused: runs executed now / taken from an earlier evaluation.
        files: the report files written.
        seconds: wall time of the evaluation; executor: where the runs ran.
    """

    results: list[dict]
    points: list[GridPoint]
    sequences: list[Sequence]
    missing: list[str]
    computed: int
    reused: int
    files: dict[str, Any]
    seconds: float
    executor: str
