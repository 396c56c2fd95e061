"""Where evaluation runs execute: this process, a local process pool, or a Ray cluster.

One small interface, :class:`Executor`: ``map_unordered(fn, tasks)`` yields ``(index, result)``
as runs finish (``result`` is the exception when the run could not be executed at all). No
scheduling of our own: :mod:`concurrent.futures` runs a bounded local process pool, Ray's task
API spreads the runs over a cluster.

Threads: each run gets ``threads`` threads for torch, OpenCV and the BLAS / OpenMP libraries
(``cores // workers`` locally), so parallel runs do not oversubscribe the cores. The BLAS and
OpenMP pools size themselves from environment variables when they load, so those are set
before a worker process starts (process pool: the parent's environment while the pool lives;
Ray: the task's ``runtime_env``); torch and OpenCV are set again in the worker.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import sys
from abc import ABC, abstractmethod
from typing import Any, Callable, Iterator, Sequence

from ..errors import UserError
from ..parallel import cpu_count

THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS")


def thread_environment(threads: int) -> dict[str, str]:
    """Environment variables that size the BLAS / OpenMP thread pools of a new process."""
    return {name: str(int(threads)) for name in THREAD_VARIABLES}


def limit_threads(threads: int) -> None:
    """Limit this process's torch and OpenCV threads (and BLAS through threadpoolctl when installed)."""
    threads = max(1, int(threads))
    os.environ.update(thread_environment(threads))  # for libraries loaded from now on
    import cv2

    cv2.setNumThreads(threads)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(threads)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return
    threadpool_limits(threads)


class Executor(ABC):
    """Runs ``fn(task)`` for every task; subclasses decide where."""

    workers: int = 1
    description: str = ""

    @abstractmethod
    def map_unordered(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        """Yield ``(index into tasks, fn(task) or the exception that prevented it)`` as runs finish."""

    def close(self) -> None:
        """Release workers (idempotent)."""

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


class InProcessExecutor(Executor):
    """One run after the other, in this process (``--workers 1``; easiest to debug)."""

    description = "in this process"

    def map_unordered(self, fn, tasks):
        for index, task in enumerate(tasks):
            try:
                yield index, fn(task)
            except Exception as exc:  # fn reports its own failures; this is a last resort
                yield index, exc


def _init_worker(threads: int, gpu_ids) -> None:
    if gpu_ids is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = str(gpu_ids.get())
    limit_threads(threads)


class LocalExecutor(Executor):
    """A bounded pool of local worker processes (``concurrent.futures``, spawn start method).

    Args:
        workers: processes.
        threads: threads per process (default ``cores // workers``).
        gpus: GPUs to spread the workers over (worker ``i`` sees GPU ``i % gpus`` only); 0 = none.
    """

    def __init__(self, workers: int, threads: int | None = None, gpus: int = 0) -> None:
        self.workers = max(1, int(workers))
        self.threads = max(1, int(threads) if threads else cpu_count() // self.workers)
        self.description = f"{self.workers} local worker processes x {self.threads} thread(s)"
        context = multiprocessing.get_context("spawn")
        gpu_ids = None
        if gpus > 0:
            gpu_ids = context.Queue()
            for worker in range(self.workers):
                gpu_ids.put(worker % gpus)
        # BLAS / OpenMP read these when a worker imports them: set while the pool lives.
        self._saved_environment = {name: os.environ.get(name) for name in THREAD_VARIABLES}
        os.environ.update(thread_environment(self.threads))
        self._pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=self.workers, mp_context=context, initializer=_init_worker, initargs=(self.threads, gpu_ids)
        )

    def map_unordered(self, fn, tasks):
        futures = {self._pool.submit(fn, task): index for index, task in enumerate(tasks)}
        try:
            for future in concurrent.futures.as_completed(futures):
                try:
                    yield futures[future], future.result()
                except Exception as exc:  # e.g. BrokenProcessPool when a worker was killed
                    yield futures[future], exc
        finally:
            for future in futures:
                future.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
            for name, value in self._saved_environment.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


class RayExecutor(Executor):
    """Runs on a Ray cluster through Ray's task API (optional extra ``sl4slam[cluster]``).

    Args:
        address: cluster address (``ray://host:10001``, ``host:6379``, ``auto``); ``None`` joins
            the cluster named by ``RAY_ADDRESS`` or else starts a local instance with
            ``workers * threads`` CPUs.
        workers: concurrent runs of a local instance (ignored when joining a cluster).
        threads: CPUs (and threads) each run asks for.
        gpus_per_task: GPUs each run asks for (1 for a run of the VGGT model on a GPU).

    Every node needs sl4slam installed and the dataset and output folders at the same paths
    (shared storage).
    """

    def __init__(self, address: str | None = None, workers: int = 1, threads: int = 1, gpus_per_task: float = 0) -> None:
        try:
            import ray
        except ImportError:
            raise UserError('--ray needs Ray: pip install "sl4slam[cluster]"') from None
        self._ray = ray
        self.threads = max(1, int(threads))
        self.gpus_per_task = gpus_per_task
        self._started = False
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"log_to_driver": False, "include_dashboard": False}
            if address is None and not os.environ.get("RAY_ADDRESS"):
                kwargs["num_cpus"] = max(1, int(workers)) * self.threads
                kwargs["num_gpus"] = 0 if not gpus_per_task else None
            try:
                ray.init(address=address, **{k: v for k, v in kwargs.items() if v is not None})
            except (ConnectionError, ValueError, RuntimeError) as exc:
                raise UserError(f"cannot start or reach Ray at {address or 'a local instance'}: {exc}") from None
            self._started = True
        resources = ray.cluster_resources()
        if gpus_per_task and not resources.get("GPU", 0):
            # a task asking for a GPU would wait forever on a CPU-only cluster; the model runs on CPUs there
            self.gpus_per_task = 0
        self.workers = max(1, int(resources.get("CPU", 1) // self.threads))
        self.description = (f"Ray ({address or 'local'}): {resources.get('CPU', 0):.0f} CPUs, "
                            f"{resources.get('GPU', 0):.0f} GPUs; {self.threads} CPU(s)"
                            + (f" and {self.gpus_per_task} GPU(s)" if self.gpus_per_task else "") + " per run")

    def map_unordered(self, fn, tasks):
        ray = self._ray
        remote = ray.remote(fn).options(
            num_cpus=self.threads, num_gpus=self.gpus_per_task,
            runtime_env={"env_vars": thread_environment(self.threads)}, max_retries=0,
        )
        pending = {remote.remote(task): index for index, task in enumerate(tasks)}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    index = pending.pop(ref)
                    try:
                        yield index, ray.get(ref)
                    except Exception as exc:  # RayTaskError, WorkerCrashedError, ...
                        yield index, exc
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False


def make_executor(
    workers: int, ray: bool = False, ray_address: str | None = None, threads: int | None = None, gpus: int = 0
) -> Executor:
    """The executor for ``workers`` parallel runs: Ray when asked, else a local pool (or this process for 1).

    Args:
        workers: parallel runs (local pool size; a local Ray instance's concurrency).
        ray: use Ray; ``ray_address`` as :class:`RayExecutor`'s ``address``.
        threads: threads per run (default: ``cores // workers``).
        gpus: GPUs the runs need: a local pool spreads its workers over them, on Ray each run asks for one.
    """
    if workers < 1:
        raise UserError(f"--workers must be at least 1, got {workers}")
    threads = threads if threads else max(1, cpu_count() // workers)
    if ray:
        return RayExecutor(ray_address, workers=workers, threads=threads, gpus_per_task=1 if gpus else 0)
    if workers == 1:
        return InProcessExecutor()
    return LocalExecutor(workers, threads, gpus=gpus)
