"""The evaluation protocol: runs x sequences x grid points, resumable, with shared frontend caches.

What one evaluation does (``sl4slam eval`` / ``sl4slam sweep``, or :func:`evaluate`):

1. Finds the dataset's sequences under the root (:mod:`.datasets`) and checks every setting
   before any work.
2. Builds one run per (grid point, sequence, run ``r``); run ``r`` uses seed ``r`` for every seeded
   setting (:data:`SEEDED_SETTINGS`), so the runs differ by their random draws only.
3. Skips runs already finished with the same settings (``result.json`` in the run's folder).
4. Runs the rest through an :class:`~.executors.Executor`: each run is a full
   :func:`sl4slam.runner.run_slam` into ``OUT/runs/<point>/<sequence>/run-<r>/``, followed by
   its metrics (:func:`run_one`).
5. Writes the tables, CSV, JSON and figures (:mod:`.report`).

Frontend caches. The model's outputs depend only on which frames each submap asks for and on
the frontend's own settings; the backend never changes them. :func:`frontend_cache_key` names
exactly those settings, so a run whose key was recorded before (``--cache-frontend`` stores each
recording in ``OUT/frontend_cache/<sequence>/<key>/``, ``--replay DIR`` reads such a store)
replays it instead of running the model: a backend sweep runs the model once per sequence and
seed. Runs that would record the same key wait for the first recording.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import hashlib
import io
import json
import logging
import os
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write_text
from ..config import SLAMConfig, config_from_dict, config_to_dict
from ..errors import UserError
from .datasets import Dataset, Sequence, get_dataset
from .executors import Executor, cpu_count, limit_threads, make_executor
from .plan import SEEDED_SETTINGS, EvalOutcome, EvalSettings, GridPoint, parse_grid, seeded
from .report import one_line, write_report

log = logging.getLogger("sl4slam")

RESULT_FILE = "result.json"
CACHE_KEY_FILE = "key.json"


# --------------------------------------------------------------------------------------------
# Frontend caches
# --------------------------------------------------------------------------------------------


def frontend_cache_key(config: SLAMConfig, sequence: Sequence) -> dict:
    """The settings that decide what the frontend returns for a sequence (see the module docstring).

    Which frames a submap holds depends on the frame selection (``[source]``), the keyframe
    selector, the submap size, shared frames and loop frames, and the retrieval (with its seed, for ORB); what
    the frontend returns for them on its own settings (all of ``sim``, resolved from its profile,
    including its seed; ``[model]`` for a model, which excludes the device, so a cache recorded on
    a GPU replays on a CPU). Injected false loops (``[false_loops]``) also decide the loop frames.
    Backend, alignment, confidence and output settings are not part of it: changing them reuses
    the cache.
    """
    from ..resolve import resolve

    resolved = resolve(config, probe_device=False)
    settled = resolved.config
    retrieval: dict[str, Any] = {"kind": "none"}
    if settled.submap.w_loop > 0 and resolved.retrieval.value != "none":
        retrieval = dataclasses.asdict(settled.retrieval)
        if resolved.retrieval.value != "orb":  # only ORB's vocabulary and verification are seeded
            retrieval.pop("seed")
        if settled.false_loops.rate > 0:
            # injected wrong places change which loop frames are asked for, whatever the frontend
            retrieval["false_loops"] = dataclasses.asdict(settled.false_loops)
    if resolved.frontend.settings == "sim":
        frontend = dataclasses.asdict(settled.sim)
    else:
        frontend = {**dataclasses.asdict(settled.model), "use_point_head": settled.submap.use_point_head}
    return {
        "dataset": sequence.dataset,
        "sequence": sequence.name,
        "frames": dataclasses.asdict(settled.source),
        "keyframes": dataclasses.asdict(settled.keyframes),
        "submap": {"size": settled.submap.size, "overlap": settled.submap.overlap, "w_loop": settled.submap.w_loop,
                   # loop frames change what the model is given only where loops are proposed
                   **({"loop_frames": settled.submap.loop_frames} if retrieval["kind"] != "none" else {})},
        "retrieval": retrieval,
        "frontend": resolved.frontend.name,
        "frontend_settings": frontend,
    }


def _digest(value: Any, length: int = 16) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()[:length]


def cache_folder(store: Path, key: dict) -> Path:
    """Where the recording with ``key`` lives in a cache store."""
    return Path(store) / str(key["sequence"]).replace(os.sep, "-") / _digest(key)


def find_cache(stores: list[Path], key: dict) -> Path | None:
    """The first store folder holding a complete recording for ``key``."""
    for store in stores:
        folder = cache_folder(store, key)
        if (folder / CACHE_KEY_FILE).is_file() and any(folder.glob("submap_*.npz")):
            return folder
    return None


# --------------------------------------------------------------------------------------------
# One run
# --------------------------------------------------------------------------------------------


@dataclass
class RunTask:
    """Everything one run needs (picklable: it travels to worker processes and Ray nodes)."""

    point: str
    sequence: Sequence
    run: int
    config: dict
    run_dir: str
    settings: EvalSettings
    fingerprint: str
    replay_dir: str | None = None
    record_to: str | None = None
    threads: int = 0
    cache_key: dict = field(default_factory=dict)


def keyframe_clouds(run_dir: Path, dataset: Dataset, sequence: Sequence, config: SLAMConfig,
                    max_depth: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Estimated and ground-truth clouds of a run's keyframes (the reference dense protocol).

    For each keyframe file (``keyframes/NNNNNN.npz``, ``NNNNNN`` = the frame's position in the
    source; either layout, read through :mod:`sl4slam.result.reading`): the
    frame's ground-truth depth is resized (nearest) to the estimate's resolution and unprojected
    with the dataset's intrinsics scaled to that resolution and the ground-truth pose; depth
    0 / invalid and beyond ``max_depth`` is dropped. The estimate keeps its confident points at
    pixels where the ground truth is valid.

    Returns ``(estimate (N, 3), ground_truth (M, 3), keyframes used)``.
    """
    from ..result.reading import load_result
    from .metrics import ground_truth_points, resize_depth

    records = load_result(run_dir).keyframes
    if not records:
        raise UserError(f"{run_dir} has no keyframes/*.npz; dense metrics need output.keyframes = \"compact\" "
                        "(the default) or \"full\"")
    source = dataset.open(sequence, stride=config.source.stride, max_frames=config.source.max_frames)
    estimate, truth, used = [], [], 0
    for record in records:
        data = record.load()
        points, mask, timestamp = data.points_world, data.mask, record.timestamp
        frame = source.get(record.frame_index)
        if abs(frame.timestamp - timestamp) > 1e-6:
            raise UserError(f"{record.path} is frame {record.frame_index} at t={timestamp}, but the source has "
                            f"t={frame.timestamp} there; was the run made with other stride / max_frames settings?")
        if frame.depth is None or frame.T_world_cam is None:
            continue  # no ground truth for this keyframe (the reference skips unmatched frames too)
        height, width = points.shape[:2]
        depth = resize_depth(frame.depth, height, width)
        gt_points, valid = ground_truth_points(depth, dataset.intrinsics(width, height), frame.T_world_cam, max_depth)
        estimate.append(points[valid & mask].astype(np.float64))
        truth.append(gt_points)
        used += 1
    if not used:
        raise UserError(f"none of the {len(records)} keyframes of {run_dir} has ground-truth depth and pose")
    return np.concatenate(estimate), np.concatenate(truth), used


def _measure(task: RunTask, dataset: Dataset, config: SLAMConfig, run_dir: Path) -> tuple[dict, dict]:
    """Metrics of a finished run: ``(metrics, trajectory positions for the figure)``."""
    from ..io import read_tum_trajectory
    from .metrics import ate, dense_metrics

    t_est, T_est = read_tum_trajectory(run_dir / "trajectory.txt")
    t_gt, T_gt = dataset.ground_truth(task.sequence)
    trajectory = ate(dataset.estimate_times(t_est), T_est, t_gt, T_gt, max_time_diff=dataset.ate_max_time_diff)
    metrics: dict[str, Any] = {
        "ate_rmse": trajectory.rmse, "ate_mean": trajectory.mean, "ate_median": trajectory.median,
        "ate_max": trajectory.max, "ate_poses": trajectory.num_poses, "ate_scale": trajectory.scale,
    }
    if dataset.dense and task.settings.dense:
        estimate, truth, used = keyframe_clouds(run_dir, dataset, task.sequence, config, task.settings.max_depth)
        dense = dense_metrics(estimate, truth, trajectory.T_gt_est, voxel_size=task.settings.icp_voxel_size,
                              max_correspondence=task.settings.icp_max_correspondence,
                              max_error=task.settings.max_error, workers=max(1, task.threads or 1))
        metrics.update(accuracy=dense.accuracy, completion=dense.completion, chamfer=dense.chamfer,
                       dense_keyframes=used, dense_points_estimate=dense.num_estimate,
                       dense_points_ground_truth=dense.num_ground_truth, icp_fitness=dense.icp_fitness)
    positions = {"estimate_aligned": np.round(trajectory.positions_aligned, 5).tolist(),
                 "ground_truth": np.round(trajectory.positions_gt, 5).tolist()}
    return metrics, positions


def _store_cache(recorded: Path, target: Path, key: dict) -> str | None:
    """Move a run's fresh recording into the store (first writer wins); its path, or ``None``."""
    if not any(recorded.glob("submap_*.npz")):
        return None
    (recorded / CACHE_KEY_FILE).write_text(json.dumps(key, indent=2, default=str) + "\n")
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.rename(recorded, target)
    except OSError:  # another run stored the same recording first
        shutil.rmtree(recorded, ignore_errors=True)
    return str(target)


def _write_json(path: Path, payload: Any) -> None:
    atomic_write_text(path, json.dumps(payload, indent=2, default=str) + "\n")


def _import_pipeline() -> None:
    import evo.core.metrics  # noqa: F401
    import evo.core.sync  # noqa: F401
    import torch  # noqa: F401  (the runner asks it for the device)

    from .. import frontend, pipeline, retrieval  # noqa: F401
    from ..result import outputs  # noqa: F401
    from . import metrics  # noqa: F401


def frontend_kind(task: RunTask) -> str:
    """Where a run's frontend outputs come from, in words for its result and the report: "replay"
    (an earlier recording), "recorded" (computed now and recorded), "simulated (profile P)" (the
    simulated frontend with its error profile) or "model" (a network)."""
    if task.replay_dir:
        return "replay"
    if task.record_to:
        return "recorded"
    if task.config.get("frontend") == "simulated":
        return f"simulated (profile {task.config.get('sim', {}).get('profile', '?')})"
    return "model"


def run_one(task: RunTask) -> dict:
    """Run SLAM once and measure it; never raises (a failure is a result with its reason).

    Writes the run's outputs, ``run.log`` (what the run printed) and ``result.json`` into
    ``task.run_dir`` (emptied first, so no stale keyframe survives), moves a fresh frontend
    recording into its store, and returns the result dict (see :func:`evaluate`).
    """
    from ..runner import run_slam

    if task.threads:
        limit_threads(task.threads)
    _import_pipeline()  # so that a worker's first run is not timed with the imports
    run_dir = Path(task.run_dir)
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    result: dict[str, Any] = {
        "point": task.point, "sequence": task.sequence.name, "run": task.run, "seed": task.run,
        "status": "failed", "reason": None, "metrics": {}, "counts": {}, "seconds": {},
        "frontend": frontend_kind(task),
        "frontend_cache": task.replay_dir, "fingerprint": task.fingerprint, "run_dir": str(run_dir),
    }
    start = time.perf_counter()
    log_text = io.StringIO()
    try:
        dataset = get_dataset(task.sequence.dataset)
        config = config_from_dict(copy.deepcopy(task.config))
        config.output.cache_frontend = task.record_to is not None
        with contextlib.redirect_stdout(log_text):
            summary = run_slam(task.sequence.path, run_dir, config, replay_dir=task.replay_dir, progress=False)
        result["counts"] = summary.get("counts", {})
        result["seconds"]["slam"] = round(float(summary["seconds"]["total"]), 3)
        if task.record_to:
            result["frontend_cache"] = _store_cache(run_dir / "frontend_cache", Path(task.record_to), task.cache_key)
        t0 = time.perf_counter()
        result["metrics"], result["trajectory"] = _measure(task, dataset, config, run_dir)
        result["seconds"]["evaluation"] = round(time.perf_counter() - t0, 3)
        if not task.settings.keep_keyframe_points:
            shutil.rmtree(run_dir / "keyframes", ignore_errors=True)
        result["status"] = "ok"
    except UserError as exc:
        result["reason"] = str(exc)
    except Exception as exc:  # a bug or a library failure: keep the sweep going, keep the traceback
        result["reason"] = f"{type(exc).__name__}: {exc}".splitlines()[0]
        log_text.write(traceback.format_exc())
    result["seconds"]["total"] = round(time.perf_counter() - start, 3)
    (run_dir / "run.log").write_text(log_text.getvalue())
    _write_json(run_dir / RESULT_FILE, result)
    return result


def finished_runs(out_dir: Path) -> dict[str, dict]:
    """Results of the runs finished in ``out_dir/runs`` by fingerprint (the settings they ran with).

    A run is reused by fingerprint, not by folder: the same settings reached under another grid
    point name (a sweep that grew an axis) are not run again.
    """
    finished: dict[str, dict] = {}
    for path in sorted(Path(out_dir).glob(f"runs/*/*/run-*/{RESULT_FILE}")):
        try:
            stored = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if stored.get("status") == "ok" and stored.get("fingerprint"):
            stored["run_dir"] = str(path.parent)
            finished.setdefault(stored["fingerprint"], stored)
    return finished


def _reuse(task: RunTask, finished: dict[str, dict]) -> dict | None:
    """The finished result with this task's settings, relabelled for this task's grid point."""
    stored = finished.get(task.fingerprint)
    return None if stored is None else {**stored, "point": task.point}


# --------------------------------------------------------------------------------------------
# The whole evaluation
# --------------------------------------------------------------------------------------------



def _needs_gpu(config: SLAMConfig) -> bool:
    from ..registry import frontend_entry

    return frontend_entry(config.frontend).weights is not None and config.device != "cpu"


def _check_configs(configs: list[SLAMConfig], needs_model: bool) -> None:
    """Every grid point's settings, and the model weights when a run will need them (one line each)."""
    from ..resolve import resolve

    resolved = [resolve(config, probe_device=False) for config in configs]
    if needs_model:
        from ..models.hub import resolve_weights

        for weights, source in sorted({(r.config.model.weights, r.frontend.weights) for r in resolved
                                       if r.frontend.weights is not None}, key=lambda pair: pair[0]):
            resolve_weights(weights, source=source)


def evaluate(
    root: str | Path,
    out_dir: str | Path,
    settings: EvalSettings | None = None,
    config: SLAMConfig | None = None,
    grid: list[str] | None = None,
    sequences: list[str] | None = None,
    workers: int | None = None,
    threads: int | None = None,
    ray: bool = False,
    ray_address: str | None = None,
    replay_dir: str | Path | None = None,
    progress: bool = True,
    stream=None,
    executor: Executor | None = None,
) -> EvalOutcome:
    """Evaluate SLAM on a benchmark's sequences with the paper's protocol (module docstring).

    Args:
        root: dataset root (``rgbd_dataset_freiburg1_*`` folders, or ``<scene>/seq-01``).
        out_dir: where runs, caches and the report go; an earlier evaluation there is resumed.
        settings: dataset, runs and metric settings.
        config: the SLAM settings (a grid point overrides some; runs set the seeds).
        grid: sweep specs (``["submap.size=8,16,32", "backend.kind=sl4,sim3"]``).
        sequences: names or folders to evaluate (default: the paper's, those present).
        workers: parallel runs (default: one per core, or per GPU for model runs on GPUs).
        threads: threads per run (default: cores // workers).
        ray, ray_address: run on Ray (see :class:`~.executors.RayExecutor`).
        replay_dir: a frontend cache store of an earlier evaluation (its ``frontend_cache/``).
        progress: print one line per finished run to ``stream`` (default stderr).
        executor: run on this executor (the caller closes it) instead of one made from
            ``workers``, ``threads`` and ``ray``.

    Returns:
        :class:`EvalOutcome`. Each result dict holds ``point, sequence, run, seed, status``
        (``ok`` / ``failed``), ``reason``, ``metrics`` (``ate_rmse`` ..., and ``accuracy``,
        ``completion``, ``chamfer`` on 7-Scenes), ``counts``, ``seconds``, ``frontend``
        (``model`` / ``recorded`` / ``replay``) and ``trajectory`` (aligned positions).
    """
    start = time.perf_counter()
    stream = stream if stream is not None else sys.stderr
    settings = settings if settings is not None else EvalSettings()
    settings.validate()
    dataset = get_dataset(settings.dataset)
    base, record = _base_config(config, settings, dataset)
    points = parse_grid(grid)
    chosen, missing = dataset.resolve(root, sequences)
    out_dir = Path(out_dir).expanduser()
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} exists and is not a folder; choose another output folder")
    store = out_dir / "frontend_cache"
    stores = [store] + ([_check_replay_dir(Path(replay_dir).expanduser())] if replay_dir else [])

    point_configs = [point.apply(base) for point in points]
    tasks = _build_tasks(points, point_configs, chosen, settings, out_dir)
    finished = finished_runs(out_dir)
    results: list[dict | None] = [_reuse(task, finished) for task in tasks]
    todo = [i for i, r in enumerate(results) if r is None]
    waves = _plan_recordings(tasks, todo, stores, store if record else None)
    needs_model = any(tasks[i].replay_dir is None and tasks[i].config["frontend"] != "simulated" for i in todo)
    _check_configs(point_configs, needs_model and not ray)

    description = "nothing to run"
    if todo:
        if progress:
            replaying = sum(tasks[i].replay_dir is not None for i in todo)
            recording = sum(tasks[i].record_to is not None for i in todo)
            print(f"evaluating {len(todo)} run(s) ({len(tasks) - len(todo)} reused) of {len(chosen)} sequence(s) x "
                  f"{len(points)} setting(s) x {settings.runs} run(s) into {out_dir}: {replaying} replay a recording, "
                  f"{recording} record one, {len(waves[1])} replay those afterwards", file=stream, flush=True)
        out_dir.mkdir(parents=True, exist_ok=True)
        owned = executor is None
        if owned:
            gpus = _gpus(point_configs, needs_model, ray)
            if workers is None:
                workers = max(1, min(len(todo), cpu_count() if ray else (gpus or cpu_count())))
            executor = make_executor(workers, ray=ray, ray_address=ray_address, threads=threads, gpus=gpus)
        with executor if owned else contextlib.nullcontext(executor):
            description = executor.description
            if progress:
                print(f"running on {description}", file=stream, flush=True)
            _execute(executor, tasks, waves, results, stores, stream if progress else None)
    outcome = EvalOutcome(results=[r for r in results if r is not None], points=points, sequences=chosen,
                          missing=missing, computed=len(todo), reused=len(tasks) - len(todo), files={},
                          seconds=time.perf_counter() - start, executor=description)
    outcome.files = write_report(out_dir, outcome, settings, base)
    return outcome


def _base_config(config: SLAMConfig | None, settings: EvalSettings, dataset: Dataset) -> tuple[SLAMConfig, bool]:
    """The runs' common config, and whether frontend outputs are to be recorded."""
    base = copy.deepcopy(config) if config is not None else SLAMConfig()
    record = bool(base.output.cache_frontend)
    base.output.cache_frontend = False  # recording is decided per run (RunTask.record_to)
    if dataset.dense and settings.dense:
        from .metrics import require_open3d

        require_open3d()
        if base.output.keyframes == "none":
            base.output.keyframes = "compact"  # the same points as "full", 14x smaller
    elif not settings.keep_keyframe_points:
        base.output.keyframes = "none"  # nothing measures them
    return base, record


def _check_replay_dir(path: Path) -> Path:
    if not path.is_dir():
        raise UserError(f"--replay {path} is not a folder; pass the frontend_cache/ folder of an earlier evaluation")
    if any(path.glob("submap_*.npz")):
        raise UserError(f"--replay {path} is one run's recording; eval replays the frontend_cache/ folder of an "
                        "earlier evaluation (OUT/frontend_cache), which holds one recording per sequence and settings")
    return path


def _build_tasks(points: list[GridPoint], point_configs: list[SLAMConfig], sequences: list[Sequence],
                 settings: EvalSettings, out_dir: Path) -> list[RunTask]:
    """One run per (grid point, sequence, seed), in that order, each with its fingerprint and cache key."""
    # what a run's numbers depend on besides its config (not the number of runs)
    measurement = {k: v for k, v in dataclasses.asdict(settings).items() if k not in ("runs", "dataset")}
    tasks = []
    for point, point_config in zip(points, point_configs):
        for sequence in sequences:
            for run in range(settings.runs):
                run_config = seeded(point_config, run)
                config_dict = config_to_dict(run_config)
                fingerprint = _digest({"config": config_dict, "measure": measurement,
                                       "sequence": [sequence.dataset, sequence.name, str(sequence.path.resolve())]})
                tasks.append(RunTask(
                    point=point.label, sequence=sequence, run=run, config=config_dict,
                    run_dir=str(out_dir / "runs" / point.slug / sequence.name.replace(os.sep, "-") / f"run-{run}"),
                    settings=settings, fingerprint=fingerprint, cache_key=frontend_cache_key(run_config, sequence),
                ))
    return tasks


def _plan_recordings(tasks: list[RunTask], todo: list[int], stores: list[Path],
                     record_into: Path | None) -> tuple[list[int], list[int]]:
    """Two waves of task indices: replays, recordings and uncached runs first; runs waiting for a recording after.

    Sets ``replay_dir`` of the runs whose key is recorded, and ``record_to`` of the first run of
    each key that is not (when recording).
    """
    first, second, planned = [], [], set()
    for i in todo:
        task = tasks[i]
        found = find_cache(stores, task.cache_key)
        digest = _digest(task.cache_key)
        if found is not None:
            task.replay_dir = str(found)
            first.append(i)
        elif record_into is not None and digest in planned:
            second.append(i)
        else:
            if record_into is not None:
                task.record_to = str(cache_folder(record_into, task.cache_key))
                planned.add(digest)
            first.append(i)
    return first, second


def _gpus(configs: list[SLAMConfig], needs_model: bool, ray: bool) -> int:
    """Local: GPUs to spread the workers over; Ray: 1 when each model run asks for a GPU."""
    if not (needs_model and any(_needs_gpu(c) for c in configs)):
        return 0
    if ray:
        return 1
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


def _execute(executor: Executor, tasks: list[RunTask], waves: tuple[list[int], list[int]], results: list,
             stores: list[Path], stream) -> None:
    """Run the waves, filling ``results``; one progress line per finished run when ``stream`` is given."""
    done = sum(r is not None for r in results)
    for wave in waves:
        for i in wave:
            task = tasks[i]
            task.threads = getattr(executor, "threads", 0)
            if task.replay_dir is None and task.record_to is None:
                found = find_cache(stores, task.cache_key)  # recorded by the first wave
                task.replay_dir = str(found) if found is not None else None
        for index, returned in _run_wave(executor, [tasks[i] for i in wave]):
            i = wave[index]
            results[i] = returned if isinstance(returned, dict) else _crashed(tasks[i], returned)
            done += 1
            if stream is not None:
                print(f"[{done}/{len(tasks)}] {one_line(results[i])}", file=stream, flush=True)


def _run_wave(executor: Executor, tasks: list[RunTask]):
    if not tasks:
        return iter(())
    return executor.map_unordered(run_one, tasks)


def _crashed(task: RunTask, error: BaseException) -> dict:
    """Result of a run whose worker died (or could not be reached)."""
    reason = f"{type(error).__name__}: {error}".splitlines()[0] or type(error).__name__
    return {"point": task.point, "sequence": task.sequence.name, "run": task.run, "seed": task.run,
            "status": "failed", "reason": f"the worker running it failed ({reason})", "metrics": {}, "counts": {},
            "seconds": {}, "frontend": None, "frontend_cache": None, "fingerprint": task.fingerprint,
            "run_dir": task.run_dir}


__all__ = [
    "EvalSettings",
    "EvalOutcome",
    "GridPoint",
    "RunTask",
    "SEEDED_SETTINGS",
    "evaluate",
    "frontend_cache_key",
    "keyframe_clouds",
    "parse_grid",
    "run_one",
    "seeded",
]
