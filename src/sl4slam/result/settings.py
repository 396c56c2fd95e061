"""The outputs' settings (``[output]``): what a run writes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..section import Section, setting


@dataclass
class OutputConfig(Section):
    """What a run writes, and how it reports."""

    section: ClassVar[str] = "output"

    voxel_size: float = setting(0.0, check=lambda v: v >= 0, allowed=">= 0 world units (0: off)")
    """Voxel downsampling of ``map.ply`` in world units (0: off)."""
    max_map_points: int = setting(2_000_000, check=lambda v: v >= 1, allowed="at least 1")
    """Cap on points written to ``map.ply`` (subsampled at random, seeded by ``seed``)."""
    seed: int = setting(0, advanced=True, flag='--map-seed', check=lambda v: v >= 0, allowed=">= 0")
    """Seed of the map's subsampling to ``max_map_points``."""
    keyframes: str = setting("compact", choices=("compact", "full", "none"))
    """What ``keyframes/NNNNNN.npz`` holds per keyframe (the exports, the viewer's map, dense
    evaluation and ``--all-frames`` from a folder read it). "compact": the run's own float16 depth
    with the keyframe's camera and projective map, mask, confidence percentile and JPEG colours,
    deflated: the same world points as "full". "full": float32 world points, uint8 colours, float16
    confidence, uncompressed, for tools that read the raw points. "none": no ``keyframes/``
    (trajectory and ``map.ply`` only). (decision: docs/decisions/keyframe-format.md)"""
    cache_frontend: bool = False
    """Store the frontend's outputs so the backend can be re-run without the model."""
    resumable: bool = True
    """Record each submap's model output in ``--out``/frontend_cache/ as soon as the model returns it,
    so that ``--resume`` continues a killed run without running the model again on those submaps
    (``sl4slam.resume``). Stored uncompressed: 11 bytes per pixel of a frame of a submap (float32
    depth and confidence, RGB), 1.6 MiB per frame at VGGT's 518x294, 32 MiB for a submap of 20
    frames. Removed when the run completes, unless ``--cache-frontend`` keeps it (compressed)."""
    checkpoint_seconds: float = setting(10.0, advanced=True, check=lambda v: v >= 0, allowed=">= 0 s")
    """``trajectory.txt`` and ``summary.json`` are rewritten from the current graph after a submap
    once this many seconds have passed since the last write (0: after every submap), so an
    interrupted run keeps its work."""
    progress_every: int = setting(10, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """When the output is not a terminal, one progress line every this many submaps."""
