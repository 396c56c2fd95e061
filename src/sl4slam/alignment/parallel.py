"""Running a link's independent fits at once (``AlignmentConfig.fit_threads``).

A link between submaps that share several frames takes several 15-DOF fits that do not depend on
each other: each shared frame's own, and the one on every frame's points together
(``sl4slam.alignment.shared``); and a submap's loop links do not depend on its odometry link, so
they are measured beside it (``sl4slam.pipeline``). Each fit draws from its own seeded generator and reads only its
own points, so running them on threads changes when they finish, never what they return; most of
their time is spent in NumPy and BLAS, which release the interpreter lock.

:func:`start` hands back a :class:`Pending` fit: running on a thread pool when ``threads > 1``,
or, with one thread, run in the caller's thread only when its result is first asked for, so that
a sequential run does exactly the work it did before (a fit whose result is never asked for is
never run). Either way :meth:`Pending.result` returns the fit's value or raises its exception, at
the point where the caller asks, so errors surface in the order the sequential code raised them.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Generic, TypeVar

T = TypeVar("T")

POOLS = ("fit", "link")
"""The two pools: ``"fit"`` runs single fits; ``"link"`` runs whole links, whose fits go to the fit
pool. A link waits for its fits, so it must never hold a fit pool's thread: with every fit thread
waiting on fits queued behind it, none would run."""

_POOLS: dict[tuple[int, str, int], ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _pool(threads: int, kind: str) -> ThreadPoolExecutor:
    """The process's pool ``kind`` of ``threads`` worker threads (one per process id: a forked
    child, whose parent's threads did not survive the fork, gets its own)."""
    key = (os.getpid(), kind, threads)
    with _POOLS_LOCK:
        pool = _POOLS.get(key)
        if pool is None:
            pool = _POOLS[key] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix=f"sl4slam-{kind}")
        return pool


class Pending(Generic[T]):
    """One fit, started or deferred (module doc); :meth:`result` gives its value or raises its error."""

    def __init__(self, work: Callable[[], T], future: Future | None = None) -> None:
        self._work: Callable[[], T] | None = None if future is not None else work
        self._future = future
        self._value: T | None = None
        self._error: BaseException | None = None

    def result(self) -> T:
        """The fit's value (waiting for it on a pool; running it now when deferred); raises what it raised."""
        if self._future is not None:
            return self._future.result()
        if self._work is not None:
            work, self._work = self._work, None
            try:
                self._value = work()
            except BaseException as exc:  # kept, and raised again at every ask, like a future's
                self._error = exc
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]


def start(work: Callable[[], T], threads: int, kind: str = "fit") -> Pending[T]:
    """``work`` as a :class:`Pending` fit: submitted to the pool ``kind`` (:data:`POOLS`) of
    ``threads`` threads when ``threads > 1``, else deferred until its result is asked for."""
    if kind not in POOLS:
        raise ValueError(f"unknown pool {kind!r}; one of {', '.join(POOLS)}")
    if threads > 1:
        return Pending(work, _pool(threads, kind).submit(work))
    return Pending(work)
