"""The two model interfaces of the object queries (what the query code calls, whatever answers).

- :class:`ImageEmbedder`: images and texts into one space, so that a text's cosine similarity with
  a keyframe's embedding says how much of the keyframe is about that text (Perception Encoder
  PE-Core, or the synthetic oracle of :mod:`sl4slam.objects.oracle`).
- :class:`TextSegmenter`: the masks of the instances of a text in one image (SAM 3, or the oracle).

Both are ``typing.Protocol`` classes: any object with these attributes and methods fits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

DEFAULT_MAX_TEXT_CHARS = 300
"""The longest query text accepted when the embedder does not state its own ``max_text_chars``."""


@dataclass(frozen=True)
class Mask2D:
    """One instance found in an image.

    Attributes:
        mask: ``(H, W)`` bool, true on the instance's pixels (the image's own resolution).
        score: the segmenter's confidence in the instance, in [0, 1].
    """

    mask: np.ndarray
    score: float


@runtime_checkable
class ImageEmbedder(Protocol):
    """Images and texts into a shared embedding space.

    Attributes:
        name: the model's name (recorded with the embeddings it made).
        dim: the embedding dimension ``D``.

    An embedder may also have ``max_text_chars: int``, the longest text it takes (the query checks
    it; :data:`DEFAULT_MAX_TEXT_CHARS` when absent).
    """

    name: str
    dim: int

    def embed_images(self, images: list[np.ndarray]) -> np.ndarray:
        """Embed images.

        Args:
            images: ``N`` arrays ``(H, W, 3)`` uint8 RGB (sizes may differ).

        Returns:
            ``(N, D)`` float32, each row of unit L2 norm.
        """
        ...

    def embed_texts(self, texts: list[str]) -> np.ndarray:
        """Embed texts.

        Args:
            texts: ``M`` strings.

        Returns:
            ``(M, D)`` float32, each row of unit L2 norm.
        """
        ...


@runtime_checkable
class TextSegmenter(Protocol):
    """Masks of every instance of a text in an image.

    Attributes:
        name: the model's name.
    """

    name: str

    def segment(self, image: np.ndarray, text: str, threshold: float = 0.5) -> list[Mask2D]:
        """Find the instances of ``text`` in ``image``.

        Args:
            image: ``(H, W, 3)`` uint8 RGB.
            text: what to find ("red mug").
            threshold: the lowest instance score kept, in [0, 1].

        Returns:
            The instances scored at least ``threshold``, each with an ``(H, W)`` bool mask (empty list
            when none).
        """
        ...
