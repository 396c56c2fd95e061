"""Timing helpers shared by the whole-run benchmarks."""

from __future__ import annotations

import time


class TimedSource:
    """A frame source that records when each frame is read (``arrivals[frame index] = time``), so a
    run can report the latency from a frame's arrival to its pose."""

    def __init__(self, source, arrivals: dict[int, float]) -> None:
        self.source, self.arrivals = source, arrivals

    def __getattr__(self, name: str):
        return getattr(self.source, name)

    def __len__(self) -> int:
        return len(self.source)

    def __iter__(self):
        for frame in self.source:
            self.arrivals[frame.index] = time.perf_counter()
            yield frame
