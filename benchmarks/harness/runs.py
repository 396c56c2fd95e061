"""One SLAM run on a sequence, and what the benchmarks read from it: ATE, loop counts, failures.

:func:`run_sequence` builds a :class:`sl4slam.pipeline.SLAMPipeline` from a config (:func:`make_pipeline`),
runs it over a sequence folder and returns a :class:`Run`; :func:`attempt` does the same but turns an exception into
a :class:`Failure` (a run that aborts is a finding of a benchmark, not the end of it).
"""

from __future__ import annotations

import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable


def count_model_frames(pipeline) -> Callable[[], int]:
    """Count the frames the pipeline's frontend is given from now on (the model's cost).

    Args:
        pipeline: a :class:`sl4slam.pipeline.SLAMPipeline`, before it runs.

    Returns:
        A function returning the frames counted so far.
    """
    counted = [0]
    reconstruct = pipeline.frontend.reconstruct

    def counting(frames, submap_id, **kwargs):
        counted[0] += len(frames)
        return reconstruct(frames, submap_id, **kwargs)

    pipeline.frontend.reconstruct = counting
    return lambda: counted[0]


def loop_counts(edges, retrieval=None) -> dict[str, int]:
    """Loop proposals of a run by outcome, with the false ones (injected by the false-loop wrapper)
    apart from the true ones.

    Args:
        edges: the run's edge records (``result.edges`` or ``pipeline.edges``).
        retrieval: the pipeline's retrieval stage; its ``injected`` pairs (query frame, stored frame)
            are the false proposals (none when it injects nothing).

    Returns:
        ``proposed``, ``accepted``, ``rejected``; ``false`` (injected proposals), ``false_accepted``,
        ``false_rejected``, ``false_by_attention`` (rejected by the attention check); ``true``,
        ``true_accepted``, ``true_rejected``, ``true_by_attention``.
    """
    injected = set(getattr(retrieval, "injected", []))
    loops = [e for e in edges if e.kind == "loop"]
    false = [e for e in loops if (e.query_frame, e.frame_index) in injected]
    true = [e for e in loops if (e.query_frame, e.frame_index) not in injected]

    def by_attention(group) -> int:
        return sum(bool(e.reason and "attention" in e.reason) for e in group)

    return {"proposed": len(loops), "accepted": sum(e.accepted for e in loops),
            "rejected": sum(not e.accepted for e in loops),
            "false": len(false), "false_accepted": sum(e.accepted for e in false),
            "false_rejected": sum(not e.accepted for e in false), "false_by_attention": by_attention(false),
            "true": len(true), "true_accepted": sum(e.accepted for e in true),
            "true_rejected": sum(not e.accepted for e in true), "true_by_attention": by_attention(true)}


def result_ate(result, correct_scale: bool = True):
    """The keyframe trajectory's ATE of a :class:`sl4slam.pipeline.SLAMResult` against its ground
    truth (:class:`sl4slam.metrics.ATEResult`).

    Args:
        result: the run's result.
        correct_scale: align with a similarity (``evo_ape -as``, the default) or a rigid motion.

    Raises:
        ValueError: the result has no ground truth or fewer than three keyframes.
    """
    from sl4slam.metrics import ate

    if result.T_world_cam_gt is None or len(result.keyframes) < 3:
        raise ValueError(f"no ATE: {len(result.keyframes)} keyframes, ground truth "
                         f"{'missing' if result.T_world_cam_gt is None else 'present'}")
    return ate(result.timestamps, result.T_world_cam, result.timestamps, result.T_world_cam_gt,
               correct_scale=correct_scale)


@dataclass
class Run:
    """A finished run: the pipeline after it, its result, wall seconds (building the pipeline
    included) and the frames its frontend was given."""

    pipeline: Any
    result: Any
    seconds: float
    model_frames: int
    _ates: dict = field(default_factory=dict, repr=False)

    @property
    def stats(self) -> dict:
        """The result's statistics (``submaps``, ``loops``, ``fallbacks``, ``segments`` ...)."""
        return self.result.stats

    def ate_result(self, correct_scale: bool = True):
        """:func:`result_ate` of this run's result (computed once per ``correct_scale``)."""
        if correct_scale not in self._ates:
            self._ates[correct_scale] = result_ate(self.result, correct_scale)
        return self._ates[correct_scale]

    def ate(self, correct_scale: bool = True) -> float:
        """The ATE RMSE in metres (see :meth:`ate_result`)."""
        return float(self.ate_result(correct_scale).rmse)

    def loops(self) -> dict[str, int]:
        """:func:`loop_counts` of this run."""
        return loop_counts(self.result.edges, self.pipeline.retrieval)


def failing_step(exc: BaseException) -> str:
    """``module.function`` of the deepest sl4slam frame in the exception's traceback ("?" if none)."""
    frames = [f for f in traceback.extract_tb(exc.__traceback__) if f"{os.sep}sl4slam{os.sep}" in f.filename]
    if not frames:
        return "?"
    last = frames[-1]
    return f"{Path(last.filename).stem}.{last.name}"


@dataclass
class Failure:
    """A run that raised: the exception's type name and message, the step that raised it
    (:func:`failing_step`) and the seconds until then."""

    kind: str
    message: str
    step: str
    seconds: float

    def __str__(self) -> str:
        return f"{self.kind}: {self.message}"

    def line(self, limit: int = 160) -> str:
        """One line for a table: ``Type in module.function: message`` (white space folded, cut at ``limit``)."""
        return f"{self.kind} in {self.step}: {' '.join(self.message.split())[:limit]}"


def make_pipeline(config, **stages):
    """A :class:`sl4slam.pipeline.SLAMPipeline` for the settings ``config``, resolved there.

    Args:
        config: a :class:`sl4slam.config.SLAMConfig`.
        stages: stages that replace the config's (``frontend=``, ``retrieval=None``, ``on_submap=``).

    Returns:
        The pipeline (``SLAMPipeline.from_config``: the settings resolved, the stages built).
    """
    from sl4slam.pipeline import SLAMPipeline

    return SLAMPipeline.from_config(config, **stages)


def make_frontend(config, **options):
    """The frontend ``config`` names, as a run builds it (``sl4slam.compose.make_frontend``).

    Args:
        config: a :class:`sl4slam.config.SLAMConfig`.
        options: ``cache_dir=`` (record every submap there) or ``replay_dir=`` (replay a recording).
    """
    from sl4slam.compose import make_frontend as build

    return build(config, **options)


def run_sequence(config, sequence: str | Path | None = None, *, source=None, **stages) -> Run:
    """Run SLAM with ``config`` over a sequence.

    Args:
        config: a :class:`sl4slam.config.SLAMConfig` (resolved by the pipeline).
        sequence: a sequence folder, opened with the config's ``[source]`` settings.
        source: a frame source to run instead of opening ``sequence``.
        stages: stages that replace the config's (``frontend=``, ``retrieval=None``, ``on_submap=``),
            passed to :func:`make_pipeline`.

    Returns:
        The :class:`Run`.
    """
    from sl4slam.io import open_source

    start = time.perf_counter()
    pipeline = make_pipeline(config, **stages)
    frames = count_model_frames(pipeline)
    if source is None:
        source = open_source(str(sequence), pipeline.config.source)
    result = pipeline.run(source, progress=False)
    return Run(pipeline, result, time.perf_counter() - start, frames())


def attempt(config, sequence: str | Path | None = None, *, ate: bool = False, **kwargs) -> Run | Failure:
    """:func:`run_sequence`, with an exception returned as a :class:`Failure`.

    Args:
        ate: also measure the ATE inside the attempt, so that a run without one is a failure too.
        kwargs: as :func:`run_sequence`.
    """
    start = time.perf_counter()
    try:
        run = run_sequence(config, sequence, **kwargs)
        if ate:
            run.ate()
        return run
    except Exception as exc:  # reported by the caller: which step failed and why
        return Failure(type(exc).__name__, str(exc), failing_step(exc), time.perf_counter() - start)
