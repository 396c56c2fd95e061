"""Benchmark runs spread over processes (or a Ray cluster) through :mod:`sl4slam.evaluation.executors`.

:func:`run_all` calls ``fn(*args)`` for every task and returns the results in task order: one task
after the other in this process for ``jobs=1``, a local pool of ``jobs`` worker processes (spawned,
each with ``cores // jobs`` threads) otherwise, or Ray's task API with ``ray=True``. ``fn`` must be a
module-level function (it travels to the workers by name, or by value to Ray).
"""

from __future__ import annotations

import argparse
import os
from typing import Any, Callable, Sequence

from .places import BENCHMARKS


def _call(task: tuple[Callable, tuple]) -> Any:
    fn, args = task
    return fn(*args)


def run_all(fn: Callable, tasks: Sequence[tuple], jobs: int = 1, *, ray: bool = False, ray_address: str | None = None,
            threads: int | None = None, on_result: Callable[[int, Any], None] | None = None,
            raise_errors: bool = True) -> list:
    """``[fn(*args) for args in tasks]``, computed on ``jobs`` workers.

    Args:
        fn: a module-level function.
        tasks: the argument tuples.
        jobs: parallel runs (1: in this process).
        ray, ray_address: run on Ray (:class:`sl4slam.evaluation.RayExecutor`); a local instance
            with ``jobs`` workers unless an address (or ``RAY_ADDRESS``) names a cluster.
        threads: threads per run (default: cores // jobs).
        on_result: called as ``on_result(index, value)`` as each task finishes, in the order they
            finish (``value`` is the exception when the task raised).
        raise_errors: raise the first task's exception once every task has finished; otherwise the
            exception stands in the returned list in place of that task's result.

    Returns:
        The results in the order of ``tasks``.
    """
    from sl4slam.evaluation.executors import make_executor

    if ray:  # Ray's workers import the harness by name: put benchmarks/ on their path
        os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(BENCHMARKS), os.environ.get("PYTHONPATH", "")) if p)
    results: list = [None] * len(tasks)
    errors: list[BaseException] = []
    with make_executor(max(1, int(jobs)), ray=ray, ray_address=ray_address, threads=threads) as executor:
        for index, value in executor.map_unordered(_call, [(fn, tuple(args)) for args in tasks]):
            results[index] = value
            if isinstance(value, BaseException):
                errors.append(value)
            if on_result is not None:
                on_result(index, value)
    if errors and raise_errors:
        raise errors[0]
    return results


def add_parallel_arguments(parser: argparse.ArgumentParser, flag: str = "--jobs", default: int = 2) -> None:
    """Add the options of :func:`run_all` to a benchmark's command line: ``flag`` (parallel runs),
    ``--ray`` and ``--ray-address``."""
    parser.add_argument(flag, type=int, default=default,
                        help="runs in parallel (1: one after the other, in this process)")
    parser.add_argument("--ray", action="store_true", help="run on Ray (a local instance unless --ray-address)")
    parser.add_argument("--ray-address", default=None, help="a Ray cluster's address (ray://host:10001, auto)")


def parallel_options(args: argparse.Namespace, flag: str = "--jobs") -> dict:
    """The keyword arguments of :func:`run_all` from options added by :func:`add_parallel_arguments`."""
    return {"jobs": getattr(args, flag.lstrip("-").replace("-", "_")), "ray": args.ray, "ray_address": args.ray_address}
