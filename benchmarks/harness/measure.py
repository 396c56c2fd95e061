"""Timing and memory probes shared by the benchmarks."""

from __future__ import annotations

import resource
import statistics
import time
from typing import Any, Callable, Mapping


class TimedSource:
    """A frame source that records when each frame is read (``arrivals[frame index] = time``), so a
    run can report the latency from a frame's arrival to its pose.

    Args:
        source: the frame source to read.
        arrivals: filled with ``time.perf_counter()`` of each frame as it is read.
    """

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


def timed(function: Callable, *args: Any, **kwargs: Any) -> tuple[Any, float, float]:
    """``(function(*args, **kwargs), wall seconds, this process's CPU seconds)``."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = function(*args, **kwargs)
    return result, time.perf_counter() - wall, time.process_time() - cpu


def median_seconds(function: Callable[[], Any], repeats: int) -> float:
    """Median wall seconds of ``repeats`` calls of ``function``."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def interleaved_times(cases: Mapping[str, Callable[[], Any]], repeats: int) -> dict[str, list[float]]:
    """Run every case once per round, after one warm-up round, and collect the seconds of each run
    per case. Interleaving spreads the load of other processes evenly over the cases, so their
    ratios stay meaningful on a shared machine.

    Args:
        cases: name -> zero-argument callable.
        repeats: timed rounds.

    Returns:
        name -> seconds of each timed round.
    """
    for fn in cases.values():
        fn()
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return times


def cpu_seconds() -> float:
    """User + system CPU time of this process so far (all its threads)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def max_rss_bytes() -> int:
    """This process's largest resident size over its whole life (``ru_maxrss``; not reset by
    :func:`reset_peak_rss`)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _status_bytes(field: str, pid: int | str = "self") -> int | None:
    """A ``kB`` field of ``/proc/<pid>/status`` in bytes (``None`` where it cannot be read)."""
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith(f"{field}:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def peak_rss_bytes(pid: int | str = "self", fallback: bool = True) -> int:
    """Peak resident size of a process (``VmHWM``) since its start or :func:`reset_peak_rss`.

    Args:
        pid: the process (default this one).
        fallback: where ``VmHWM`` cannot be read, this process's :func:`max_rss_bytes` (else 0).
    """
    value = _status_bytes("VmHWM", pid)
    if value is not None:
        return value
    return max_rss_bytes() if fallback and pid == "self" else 0


def rss_bytes(pid: int | str = "self") -> int:
    """Current resident size of a process (``VmRSS``; 0 where it cannot be read)."""
    return _status_bytes("VmRSS", pid) or 0


def reset_peak_rss() -> bool:
    """Restart this process's peak resident size from its current one (Linux ``clear_refs``), so
    that a later peak is not an earlier step's; whether that worked."""
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
        return True
    except OSError:
        return False

