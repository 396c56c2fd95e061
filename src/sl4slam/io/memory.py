"""An in-memory frame source, for library users and tests."""

from __future__ import annotations

from typing import Iterator, Sequence

from sl4slam.errors import UserError
from sl4slam.types import Frame


class ListSource:
    """Wraps a list of :class:`~sl4slam.types.Frame` records (kept by reference, in order).

    ``get`` looks frames up by ``Frame.index``, which must be unique.
    """

    def __init__(self, frames: Sequence[Frame], name: str = "memory"):
        self._frames = list(frames)
        self.name = name
        self.skipped: list[str] = []
        self._by_index = {int(frame.index): frame for frame in self._frames}
        if len(self._by_index) != len(self._frames):
            raise UserError(f"frame source {name!r}: Frame.index values must be unique")

    def __len__(self) -> int:
        return len(self._frames)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self._frames)

    def get(self, index: int) -> Frame:
        try:
            return self._by_index[int(index)]
        except KeyError:
            raise UserError(f"frame index {index} is not in {self.name!r} ({len(self)} frames)") from None

    def __repr__(self) -> str:
        return f"ListSource(name={self.name!r}, frames={len(self)})"
