"""An in-memory frame source, for library users and tests."""

from __future__ import annotations

from typing import Iterator, Sequence

import numpy as np

from sl4slam.errors import UserError
from sl4slam.types import Frame


def frames_from_images(indices: Sequence[int], images: Sequence[np.ndarray]) -> list[Frame]:
    """Plain :class:`Frame` records (timestamp = index) for ``(H, W, 3)`` uint8 images."""
    if len(indices) != len(images):
        raise UserError(f"got {len(indices)} frame indices but {len(images)} images; pass one image per index")
    return [Frame(index=int(i), timestamp=float(i), rgb=np.asarray(image)) for i, image in zip(indices, images)]


class ListSource:
    """Wraps a list of :class:`~sl4slam.types.Frame` records (kept by reference, in order).

    ``get`` looks frames up by ``Frame.index``, which must be unique.
    """

    def __init__(self, frames: Sequence[Frame], name: str = "memory"):
        self._frames = list(frames)
        self.name = name
        self.skipped: list[str] = []
        self.has_ground_truth = bool(self._frames) and all(
            f.depth is not None and f.T_world_cam is not None and f.K is not None for f in self._frames)
        self._by_index = {int(frame.index): frame for frame in self._frames}
        if len(self._by_index) != len(self._frames):
            raise UserError(f"frame source {name!r}: Frame.index values must be unique")

    def __len__(self) -> int:
        return len(self._frames)

    def image_size(self) -> tuple[int, int] | None:
        return (self._frames[0].rgb.shape[1], self._frames[0].rgb.shape[0]) if self._frames else None

    def calibration(self) -> np.ndarray | None:
        """The frames' intrinsics when every frame has the same, else ``None``."""
        Ks = [f.K for f in self._frames]
        if not Ks or any(K is None for K in Ks) or any(not np.allclose(K, Ks[0]) for K in Ks):
            return None
        return np.asarray(Ks[0], np.float64).copy()

    def __iter__(self) -> Iterator[Frame]:
        return iter(self._frames)

    def get(self, index: int) -> Frame:
        try:
            return self._by_index[int(index)]
        except KeyError:
            raise UserError(f"frame index {index} is not in {self.name!r} ({len(self)} frames)") from None

    def __repr__(self) -> str:
        return f"ListSource(name={self.name!r}, frames={len(self)})"
