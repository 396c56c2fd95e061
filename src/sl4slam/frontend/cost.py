"""What a model's submaps will cost on this CPU, said before the run starts.

A model's work per frame is stored in its registry entry (``FrontendEntry.cpu_work``) as the float32
matrix-multiply work that takes the same time: GFLOP-equivalents per frame of a window, measured once
per model. This machine's float32 matmul speed, measured in under a
second (``matmul_rate``), turns it into seconds here. ``docs/decisions/cpu-estimate.md`` gives the
measurements and how close the estimate comes.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

FRAMES_PER_KEYFRAME = 3.5
"""Input frames per keyframe assumed for a whole source (TUM fr1/desk's rate at the default disparity
threshold): the keyframe count is known only once the run has seen the frames."""

PROBE_SIZE = 2048
"""Side of the square float32 matrices whose product measures the machine's speed."""

PROBE_WARMUP_SECONDS = 0.3
"""Products run before timing: a fresh process's first products run at a fraction of the speed
(threads starting, caches and clocks cold), which would make every estimate pessimistic."""


def matmul_rate(threads: int | None = None, repeats: int = 5) -> float:
    """This machine's float32 matrix-multiply speed, GFLOP/s: the fastest of ``repeats`` products of
    two ``PROBE_SIZE`` squares after ``PROBE_WARMUP_SECONDS`` of warm-up (about 0.7 s in all; the
    fastest, since other work on the machine only ever slows a product down).

    Args:
        threads: torch threads to measure with (default: torch's current setting, as the run uses).
        repeats: timed products.
    """
    import torch

    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        generator = torch.Generator().manual_seed(0)
        a = torch.rand(PROBE_SIZE, PROBE_SIZE, generator=generator)
        b = torch.rand(PROBE_SIZE, PROBE_SIZE, generator=generator)
        start = time.perf_counter()
        while time.perf_counter() - start < PROBE_WARMUP_SECONDS:
            torch.mm(a, b)
        times = []
        for _ in range(repeats):
            begin = time.perf_counter()
            torch.mm(a, b)
            times.append(time.perf_counter() - begin)
    finally:
        torch.set_num_threads(previous)
    return 2 * PROBE_SIZE**3 / max(min(times), 1e-9) / 1e9


@dataclass(frozen=True)
class CpuEstimate:
    """The expected cost of a run's model work on this CPU.

    Attributes:
        model: the frontend's name.
        window_frames: frames in one submap's window (shared frames included).
        seconds_per_submap: expected seconds of one window's ``reconstruct``.
        source_frames: input frames of the source (``None``: unknown, e.g. a camera).
        submaps: expected submaps for the whole source (``None`` when the frame count is unknown).
        total_seconds: expected seconds of model work for the whole source (``None`` likewise).
        faster: ``(name, seconds_per_submap)`` of models at least 3x faster, fastest first.
        rate: the measured matmul speed, GFLOP/s.
    """

    model: str
    window_frames: int
    seconds_per_submap: float
    source_frames: int | None
    submaps: int | None
    total_seconds: float | None
    faster: tuple[tuple[str, float], ...]
    rate: float

    def line(self) -> str:
        """One line for the console."""
        text = (f"on this CPU (float32 matmul {self.rate:.0f} GFLOP/s) {self.model} needs about "
                f"{format_duration(self.seconds_per_submap)} per {self.window_frames}-frame submap")
        if self.total_seconds is not None:
            text += (f", about {format_duration(self.total_seconds)} for the {self.source_frames} frames of this "
                     f"source (~{self.submaps} submap(s) at one keyframe in {FRAMES_PER_KEYFRAME:g} frames)")
        if self.faster:
            options = ", ".join(f"--model {name} ~{format_duration(seconds)} per submap" for name, seconds in self.faster)
            text += f"; faster: {options}"
        return text + "; a GPU (--device cuda) is far faster"


def format_duration(seconds: float) -> str:
    """``"47 s"``, ``"17 min"``, ``"3.2 h"``: the unit that shows its first digits."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def expected_submaps(source_frames: int, submap_size: int) -> int:
    """Submaps for a source of ``source_frames`` input frames (after the stride), at
    ``FRAMES_PER_KEYFRAME`` and ``submap_size`` new keyframes per submap."""
    keyframes = max(1, round(source_frames / FRAMES_PER_KEYFRAME))
    return max(1, math.ceil(keyframes / submap_size))


def estimate(model: str, cpu_work: float, window_frames: int, rate: float, source_frames: int | None,
             submap_size: int, others: Sequence[tuple[str, float]] = ()) -> CpuEstimate:
    """The expected cost of a run's model work.

    Args:
        model: the frontend's name.
        cpu_work: its GFLOP-equivalents per frame (``FrontendEntry.cpu_work``).
        window_frames: frames per window (new keyframes plus shared frames).
        rate: this machine's matmul speed, GFLOP/s (``matmul_rate``).
        source_frames: input frames of the source, or ``None`` when unknown.
        submap_size: new keyframes per submap.
        others: ``(name, cpu_work)`` of the other models, to name the faster ones.

    Returns:
        The estimate; ``faster`` holds up to two models at least 3x faster, fastest first.
    """
    per_submap = cpu_work * window_frames / rate
    submaps = expected_submaps(source_frames, submap_size) if source_frames else None
    faster = sorted((work * window_frames / rate, name) for name, work in others
                    if name != model and work * 3 <= cpu_work)
    return CpuEstimate(model=model, window_frames=window_frames, seconds_per_submap=per_submap,
                       source_frames=source_frames or None, submaps=submaps,
                       total_seconds=per_submap * submaps if submaps else None,
                       faster=tuple((name, seconds) for seconds, name in faster[:2]), rate=rate)
