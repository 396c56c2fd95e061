"""The source's settings (``[source]``): which frames are read and what the source's own knowledge adds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..section import Section, setting


@dataclass
class SourceConfig(Section):
    """Which input frames a run reads (stride and max_frames, applied by the source:
    ``sl4slam.io.open_source``), and what else it knows that the run can use."""

    section: ClassVar[str] = "source"

    stride: int = setting(1, common=True, check=lambda v: v >= 1, allowed="at least 1")
    """Use every n-th input frame."""
    max_frames: int = setting(0, common=True, check=lambda v: v >= 0, allowed=">= 0 (0: all)")
    """Stop after this many input frames (after the stride; 0: all)."""
    intrinsics: str = setting("", common=True, flag='--intrinsics')
    """A known calibration of the camera: "fx,fy,cx,cy" in the source's pixels, a file (TUM-style
    ``fx = .. fy = .. cx = .. cy = ..``, or a COLMAP cameras.txt), "auto" (the source's own: TUM
    RGB-D and 7-Scenes), or "" (none: the model's guess, the paper's setting). Each frame's points
    are then rebuilt along the known camera's rays from the model's depth, the links between
    submaps carry no calibration term, and the metric upgrade is skipped (``sl4slam.intrinsics``), so
    a window the model distorted projectively keeps its distortion (BENCHMARKS.md)."""
    intrinsics_to_model: bool = setting(True, flag='--intrinsics-to-model')
    """Also give the known intrinsics to a model that takes a calibration as input (Pi3X, Depth
    Anything 3); off: the points are rebuilt along the known rays only (to tell the two effects apart)."""
    metric_depth: str = setting("off", choices=("off", "sensor"), flag='--metric-depth')
    """"sensor": scale each submap (points and camera translations) by the median ratio of the
    sensor's depth to the model's over its confident pixels with a valid sensor depth (an RGB-D
    source: TUM, 7-Scenes), so that the trajectory and the map come out in metres; "off": the
    model's units (the first submap's)."""
