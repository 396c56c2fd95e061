"""The object-query settings of a run (``[objects]``): whether keyframes are embedded while mapping."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..section import Section, setting

EMBEDDERS = ("pe-core-l14-336", "tiny-random")
"""The embedders a run can name (``sl4slam.objects.embedder.EMBEDDER_NAMES``; kept here so that the
settings load without the model code)."""


@dataclass
class ObjectsConfig(Section):
    """Per-keyframe image embeddings for open-vocabulary object queries (``sl4slam query``)."""

    section: ClassVar[str] = "objects"
    flag_prefix: ClassVar[str] = "objects-"
    builds: ClassVar[str] = "sl4slam.objects.embedder:build_keyframe_embedder"

    enabled: bool = setting(False, flag="--objects")
    """Embed each new keyframe's image while mapping (a submap's keyframes in one batch) and write
    ``objects/embeddings.npz`` into the result folder (at the end and with each checkpoint), which
    ``sl4slam query`` reads. Off: the run is exactly as without object queries."""
    embedder: str = setting("pe-core-l14-336", choices=EMBEDDERS, advanced=True)
    """The image embedder: "pe-core-l14-336" (Perception Encoder PE-Core-L14-336, Apache-2.0, 0.67 B
    parameters, weights downloaded on first use) or "tiny-random" (a tiny random model: for tests)."""
    weights: str = setting("", advanced=True)
    """PE-Core weights: a file, a folder or a hub id ("": facebook/PE-Core-L14-336)."""
    tokenizer: str = setting("", advanced=True)
    """CLIP byte-pair merges file ("": merges.txt of openai/clip-vit-large-patch14, fetched on first use)."""
    batch: int = setting(8, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Keyframe images per forward of the embedder."""
