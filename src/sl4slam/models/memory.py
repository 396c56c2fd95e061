"""Planning a forward to fit a memory budget, from a model's own estimate of its peak.

A model supplies a :data:`PeakEstimate`: the peak bytes of one forward of ``frames`` images whose
heads decode ``head_chunk`` frames at a time, at a fixed image size and precision. From it:

- :func:`plan_memory`: the largest head chunk that fits a budget, or one line saying the submap does
  not fit and the largest one that would (the model words it; :func:`submap_too_large` is the
  common sentence);
- :func:`largest_fitting_frames`: the largest frame count that fits with one frame at a time.

Each estimate must grow with the frame count (the search bisects it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from ..errors import UserError

GIB = 2**30

#: ``(frames, head_chunk) -> bytes``: a model's estimate of the peak of one forward.
PeakEstimate = Callable[[int, int], int]


@dataclass(frozen=True)
class MemoryPlan:
    """Chunk size chosen for a budget.

    Attributes:
        head_chunk_frames: frames the heads decode at once.
        estimated_peak_bytes: the model's estimate of the peak with that chunk.
    """

    head_chunk_frames: int
    estimated_peak_bytes: int


def largest_fitting_frames(peak: PeakEstimate, budget_bytes: int, limit: int = 4096) -> int:
    """Largest frame count (at most ``limit``) whose forward, heads one frame at a time, fits
    ``budget_bytes`` (0: not even one frame)."""
    def fits(frames: int) -> bool:
        return peak(frames, 1) <= budget_bytes

    if not fits(1):
        return 0
    low, high = 1, limit
    while low < high:  # the estimate grows with the frame count: bisect
        middle = (low + high + 1) // 2
        low, high = (middle, high) if fits(middle) else (low, middle - 1)
    return low


def plan_memory(peak: PeakEstimate, budget_gb: float, frames: int, max_chunk: int,
                refuse: Callable[[int, int], str]) -> MemoryPlan:
    """The largest head chunk (at most ``max_chunk`` frames, at most ``frames``) whose forward of
    ``frames`` images fits ``budget_gb`` GiB.

    Args:
        peak: the model's estimate.
        budget_gb: the budget in GiB.
        frames: the submap's frame count.
        max_chunk: the largest chunk to consider.
        refuse: ``(needed_bytes, largest_frames) -> message`` for a submap that does not fit even one
            frame at a time: the bytes it needs that way, and the largest frame count that fits.

    Raises:
        UserError: not even one frame at a time fits (``refuse``'s message), or not even a one-frame
            window fits (the smallest budget that does).
    """
    budget = int(budget_gb * GIB)
    for chunk in range(min(max_chunk, frames), 0, -1):
        estimate = peak(frames, chunk)
        if estimate <= budget:
            return MemoryPlan(chunk, estimate)
    largest = largest_fitting_frames(peak, budget)
    if largest == 0:
        raise UserError(below_smallest_budget(budget_gb, peak(1, 1)))
    raise UserError(refuse(peak(frames, 1), largest))


def below_smallest_budget(budget_gb: float, smallest_bytes: int) -> str:
    """The one line for a budget that no setting fits: even a one-frame window decoded one frame at a
    time needs ``smallest_bytes``."""
    smallest = math.ceil(smallest_bytes / GIB * 10) / 10
    return (f"--max-memory is {budget_gb:g} GiB, below the smallest budget any setting fits: {smallest:.1f} GiB "
            f"(one frame per window, decoded one at a time); give --max-memory {smallest:.1f} or more")


def submap_too_large(frames: int, height: int, width: int, needed_bytes: int, largest: int, needs: str,
                     budget: str, advice: str, fitting: str = "") -> str:
    """The one line for a submap that does not fit: "a submap of {frames} frames at {width}x{height}
    needs about {GiB} GiB {needs} but {budget} GiB; the largest submap that fits is {largest}
    frames{fitting}: {advice}".

    Args:
        frames, height, width: the submap and its image size in pixels.
        needed_bytes: its estimated peak with one frame at a time.
        largest: the largest frame count that fits.
        needs: what it was estimated for ("in bf16", "with Depth Anything 3").
        budget: the budget and where it comes from ("--max-memory is 4").
        advice: what to change.
        fitting: words after the largest frame count (e.g. the setting that gives it).
    """
    return (f"a submap of {frames} frames at {width}x{height} needs about {needed_bytes / GIB:.1f} GiB {needs} "
            f"but {budget} GiB; the largest submap that fits is {largest} frames{fitting}: {advice}")
