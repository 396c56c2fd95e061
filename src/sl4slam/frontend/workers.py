"""The model's forwards on other processes: local worker processes or the actors of a Ray cluster.

A :class:`WorkerFrontend` is a frontend (``sl4slam.types.Frontend``) whose ``reconstruct`` sends the
window to a worker that holds its own copy of the model and waits for the prediction. The run's
scheduler (``sl4slam.schedule.AheadScheduler``) calls it from several threads at once, so several
windows are in the model at the same time while the graph takes them in order.

- :class:`ProcessWorkers`: ``N`` local processes (started with ``spawn``: each imports the library
  and builds the frontend once). A process that dies (killed, out of memory) breaks the pool; the
  pool is started again and the window redone, up to ``retries`` times per window.
- :class:`RayWorkers`: ``N`` actors on an existing Ray cluster, one GPU each where the cluster has
  GPUs. An actor that dies is replaced and its window redone, up to ``retries`` times.

Each worker builds its frontend from the run's settled config with ``factory(index)``
(``sl4slam.compose.frontend_for_worker``); on a machine with several GPUs, worker ``i`` uses GPU
``i mod count``. Predictions come back as they left the model, so the run is the same as with the
model in the run's own process (byte for byte on the same device and number of threads).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Sequence

from ..errors import UserError
from ..types import Frame, Frontend, SubmapPrediction

log = logging.getLogger("sl4slam")

Factory = Callable[[int], Frontend]
"""``factory(worker_index) -> Frontend``: the frontend a worker builds (picklable: a module-level
function, possibly in a ``functools.partial``)."""


class WorkerLostError(RuntimeError):
    """A window's worker died more often than the retries allow."""


# ------------------------------------------------------------------------------ worker processes

_WORKER: dict[str, Any] = {}
"""The frontend of this worker process (``"frontend"``), built once by :func:`_start_worker`."""


def _start_worker(factory: Factory, counter: Any, threads: int) -> None:
    """Initializer of a worker process: its index, its CPU threads, its frontend (prepared)."""
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:  # a frontend without torch (the simulator)
        pass
    frontend = factory(index)
    frontend.prepare()
    _WORKER["frontend"] = frontend


def _reconstruct(frames: Sequence[Frame], submap_id: int, keywords: dict) -> SubmapPrediction:
    """A window's forward in a worker process."""
    return _WORKER["frontend"].reconstruct(frames, submap_id, **keywords)


class ProcessWorkers:
    """``workers`` local processes, each with the frontend ``factory`` builds.

    Args:
        factory: builds a worker's frontend (see :data:`Factory`).
        workers: number of processes (at least 1).
        threads: CPU threads each process's model may use (default: the CPUs shared among them).
        retries: times a window is redone on a new pool after its worker died.
    """

    def __init__(self, factory: Factory, workers: int, threads: int | None = None, retries: int = 2) -> None:
        if workers < 1:
            raise UserError(f"--workers must be at least 1, got {workers}")
        self.factory = factory
        self.workers = int(workers)
        self.threads = int(threads) if threads else max(1, (os.cpu_count() or 1) // self.workers)
        self.retries = int(retries)
        self.restarts = 0
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()
        self.description = f"{self.workers} local worker process(es), {self.threads} thread(s) each"

    def start(self) -> None:
        """Start the processes (each builds and prepares its frontend when it takes its first window)."""
        with self._lock:
            if self._pool is None:
                self._pool = self._new_pool()

    def _new_pool(self) -> ProcessPoolExecutor:
        context = multiprocessing.get_context("spawn")
        counter = context.Value("i", 0)
        return ProcessPoolExecutor(max_workers=self.workers, mp_context=context, initializer=_start_worker,
                                   initargs=(self.factory, counter, self.threads))

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, keywords: dict) -> SubmapPrediction:
        """The prediction of one window from a worker; redone on a new pool if its worker died."""
        for attempt in range(self.retries + 1):
            with self._lock:
                if self._pool is None:
                    self._pool = self._new_pool()
                pool = self._pool
            future = pool.submit(_reconstruct, list(frames), submap_id, keywords)
            try:
                return future.result()
            except BrokenProcessPool:
                with self._lock:
                    if self._pool is pool:  # the first window to notice starts the new pool
                        pool.shutdown(wait=False, cancel_futures=True)
                        self._pool = None
                        self.restarts += 1
                log.warning("submap %d: a worker process died; its window is redone (%d of %d)", submap_id,
                            attempt + 1, self.retries)
        raise WorkerLostError(f"the worker processes died {self.retries + 1} time(s) running submap {submap_id}")

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)


# ------------------------------------------------------------------------------------ Ray actors

class _RayActor:
    """A Ray actor holding one frontend (its class is wrapped by ``ray.remote`` when used)."""

    def __init__(self, factory: Factory, index: int) -> None:
        self.frontend = factory(index)
        self.frontend.prepare()

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, keywords: dict) -> SubmapPrediction:
        return self.frontend.reconstruct(frames, submap_id, **keywords)


class RayWorkers:
    """``workers`` actors on the Ray cluster at ``address``, one GPU each where the cluster has GPUs.

    The cluster is reached (or refused, in one line) when the object is made, before any frame is
    read. Every node needs sl4slam and the model weights (or the network to fetch them).
    """

    def __init__(self, factory: Factory, workers: int, address: str, retries: int = 2) -> None:
        problem = unreachable(address)
        if problem:
            raise UserError(f"cannot reach the Ray cluster at {address}: {problem}; check --ray-address "
                            "(host:6379, ray://host:10001 or auto)")
        try:
            import ray
        except ImportError:
            raise UserError('--ray-address needs Ray: pip install "sl4slam[cluster]"') from None
        self._ray = ray
        self.factory = factory
        self.workers = int(workers)
        self.retries = int(retries)
        self.restarts = 0
        self._started = False
        if not ray.is_initialized():
            try:
                ray.init(address=address, log_to_driver=False, include_dashboard=False)
            except Exception as exc:  # ConnectionError, ValueError, RuntimeError, timeouts
                raise UserError(f"cannot reach the Ray cluster at {address}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}; "
                                "check --ray-address (host:6379, ray://host:10001 or auto)") from None
            self._started = True
        gpus = ray.cluster_resources().get("GPU", 0)
        self.gpus_per_actor = 1 if gpus >= 1 else 0
        self._remote = ray.remote(num_gpus=self.gpus_per_actor, max_restarts=0)(_RayActor)
        self._free: queue.Queue = queue.Queue()
        self._next_index = 0
        self._lock = threading.Lock()
        for _ in range(self.workers):
            self._free.put(self._new_actor())
        self.description = (f"{self.workers} Ray actor(s) at {address}"
                            + (", one GPU each" if self.gpus_per_actor else " (no GPU in the cluster)"))

    def _new_actor(self) -> Any:
        with self._lock:
            index, self._next_index = self._next_index, self._next_index + 1
        return self._remote.remote(self.factory, index)

    def start(self) -> None:
        """Nothing to do: the actors were created with the object."""

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, keywords: dict) -> SubmapPrediction:
        """The prediction of one window from a free actor; redone on a new actor if it died."""
        from ray.exceptions import RayActorError

        for attempt in range(self.retries + 1):
            actor = self._free.get()
            try:
                prediction = self._ray.get(actor.reconstruct.remote(list(frames), submap_id, keywords))
            except RayActorError:
                self.restarts += 1
                self._free.put(self._new_actor())
                log.warning("submap %d: a Ray actor died; its window is redone (%d of %d)", submap_id, attempt + 1,
                            self.retries)
                continue
            self._free.put(actor)
            return prediction
        raise WorkerLostError(f"the Ray actors died {self.retries + 1} time(s) running submap {submap_id}")

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False


def unreachable(address: str, seconds: float = 5.0) -> str | None:
    """Why nothing answers at a Ray address's host and port (a TCP connection refused or timed out
    within ``seconds``), or ``None``; "auto" and addresses without a port are left to Ray."""
    import socket

    target = address.split("://", 1)[-1]
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit():
        return None
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=seconds):
            return None
    except OSError as exc:
        return exc.strerror or type(exc).__name__


class WorkerFrontend:
    """A frontend whose forwards run on ``workers`` (:class:`ProcessWorkers` or :class:`RayWorkers`).

    Args:
        local: the same frontend built in this process, unprepared (its name, capabilities and the
            colours of the prediction grid; its model is never loaded here).
        workers: where the forwards run.
    """

    def __init__(self, local: Frontend, workers: ProcessWorkers | RayWorkers) -> None:
        self.local = local
        self.workers = workers
        self.name = local.name
        self.capabilities = local.capabilities

    def prepare(self) -> None:
        self.workers.start()

    def grid_colors(self, frame: Frame):
        return self.local.grid_colors(frame)

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, **keywords) -> SubmapPrediction:
        return self.workers.reconstruct(frames, submap_id, keywords)

    def close(self) -> None:
        self.workers.close()


def close_workers(frontend: Any) -> None:
    """Stop the workers of ``frontend`` or of the frontend it wraps (``inner``), if it has any."""
    seen = 0
    while frontend is not None and seen < 8:
        if isinstance(frontend, WorkerFrontend):
            frontend.close()
            return
        frontend, seen = getattr(frontend, "inner", None), seen + 1
