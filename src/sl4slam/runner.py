"""One SLAM run from a source path to an output folder (what ``sl4slam run`` does).

Order of work, so that every mistake that can be found early is found before any frame is read:
settings (``SLAMConfig.validate``), the output folder (created, written to, an earlier run refused
unless ``overwrite``), the source (listed, and checked against what the frontend needs), the
frontend's weights (present, cached or downloadable; one line within seconds when offline).

During the run ``trajectory.txt`` and ``summary.json`` are rewritten from the current graph every
``OutputConfig.checkpoint_seconds``. SIGINT / SIGTERM finish the current submap, write every output
and raise :class:`RunInterrupted`; a second SIGINT stops at once, still writing what the finished
submaps hold. A frontend that keeps failing ends the run the same way, with its outputs.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from .config import SLAMConfig
from .errors import UserError

log = logging.getLogger("sl4slam")


class RunInterrupted(UserError):
    """The run stopped early (a signal, or a frontend that kept failing) after writing its partial
    results; ``exit_code`` is 130 for a signal, 1 otherwise."""

    def __init__(self, message: str, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def prepare_output(out_dir: str | Path, overwrite: bool = False, keep: str | Path | None = None) -> Path:
    """Create ``out_dir`` and prove it writable, before any work.

    A folder holding an earlier run is refused unless ``overwrite``, which removes that run's
    files first (never ``keep``, e.g. a frontend cache being replayed from inside it).
    """
    from .paths import clear_run, holds_run

    out = Path(out_dir).expanduser()
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a folder; choose another output folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the output folder --out {out}: {exc.strerror or exc}; choose another folder") from None
    if holds_run(out):
        if not overwrite:
            raise UserError(f"--out {out} holds an earlier run; pass --overwrite to replace it, or choose another folder")
        if keep is not None and Path(keep).resolve().is_relative_to(out.resolve()):
            raise UserError(f"--overwrite would delete {keep}, which this run replays; write the new run elsewhere")
        clear_run(out)
    probe = out / f".sl4slam-write-test.{threading.get_ident()}"
    try:
        probe.write_bytes(b"ok")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"cannot write into --out {out}: {exc.strerror or exc}; choose a writable folder") from None
    return out


def run_slam(source_path: str | Path, out_dir: str | Path, config: SLAMConfig, replay_dir: str | None = None,
             progress: bool = True, overwrite: bool = False,
             on_submap: Callable | None = None, view=None, all_frames: bool = False, keep_viewer: bool = False) -> dict:
    """Open ``source_path``, run the pipeline, write every output into ``out_dir``; return the summary.

    ``view``: ``sl4slam.viewer.ViewerSettings`` to watch the run in the browser (kept open after
    the run until Ctrl-C when ``keep_viewer``). ``all_frames``: also localize every other frame
    (``trajectory_all.txt``, see ``sl4slam.localize``). ``source_path`` may be a camera index or a
    stream URL (``sl4slam.io.live``).

    Raises:
        UserError: bad settings, output folder, source, or weights (before any frame is read).
        RunInterrupted: a signal stopped the run, or the frontend kept failing; the partial results
            are written first.
    """
    config.validate()  # the cheap checks first, without loading any model code
    if view is not None:
        from .viewer.app import require_viser

        require_viser()
    out = prepare_output(out_dir, overwrite, keep=replay_dir)
    from .io import open_source

    source = open_source(str(source_path), stride=config.stride, max_frames=config.max_frames)
    live = bool(getattr(source, "live", False))
    try:
        return _run(source, live, out, config, replay_dir, progress, on_submap, view, all_frames, keep_viewer)
    finally:
        if live:
            source.close()  # stops the reader thread, removes the kept frames


def _run(source, live: bool, out: Path, config: SLAMConfig, replay_dir, progress: bool, on_submap, view,
         all_frames: bool, keep_viewer: bool) -> dict:
    from .frontend import frontend_requires_ground_truth

    if all_frames and live:
        raise UserError("--all-frames needs a re-readable source (a video file or a folder): a live source keeps "
                        "only its keyframes; record the stream to a file first")
    if len(source) < 2:
        raise UserError(f"{source.name}: {len(source)} frame(s) found; SLAM needs at least 2 frames")
    if frontend_requires_ground_truth(config, replay_dir) and not source.has_ground_truth:
        raise UserError(f"{source.name} has no depth and ground-truth poses, which the {config.frontend} frontend "
                        "needs (an RGB-D sequence: TUM, 7-Scenes or the synthetic world); use --frontend vggt")
    if config.sim.false_loop_rate > 0 and not source.has_ground_truth:
        raise UserError(f"--sim-false-loop-rate needs ground-truth poses and depth, which {source.name} has not")
    if config.frontend == "vggt" and replay_dir is None:
        from .models.hub import resolve_weights

        resolve_weights(config.vggt.weights)  # missing weights: one line now, not after reading frames

    from .frontend import make_frontend
    from .outputs import atomic_write_bytes, write_checkpoint, write_outputs
    from .pipeline import FrontendFailedError, SLAMPipeline
    from .retrieval import make_retrieval

    cache_dir = out / "frontend_cache" if config.output.cache_frontend else None
    frontend = make_frontend(config, replay_dir=replay_dir, cache_dir=cache_dir)
    frontend.prepare()
    retrieval = make_retrieval(config.retrieval, device=_device(config), seed=config.alignment.seed,
                               false_loops=config.sim)
    # The source already applied stride and max_frames.
    run_config = dataclasses.replace(config, stride=1, max_frames=0)
    last_write = [time.perf_counter()]

    viewer = None
    if view is not None:
        from .viewer import LiveViewer

        viewer = LiveViewer(view)
    callbacks = [c for c in (on_submap, viewer.on_submap if viewer else None, _live_status(source) if live else None) if c]

    def checkpoint(pipeline: SLAMPipeline, submap_id: int) -> None:
        for callback in callbacks:
            callback(pipeline, submap_id)
        if time.perf_counter() - last_write[0] >= config.output.checkpoint_seconds:
            write_checkpoint(pipeline.snapshot(), out, config, {"source": source.name})
            last_write[0] = time.perf_counter()

    pipeline = SLAMPipeline(run_config, frontend=frontend, retrieval=retrieval, on_submap=checkpoint)
    if live:
        # the source keeps exactly the frames the pipeline selected as keyframes (loop closures re-read them)
        source.keyframe_counter = lambda: pipeline.selector.num_keyframes
    status, stop_reason = "complete", None
    start = time.perf_counter()
    with _stop_on_signals(pipeline):
        try:
            pipeline.consume(source, progress=progress and not live)
        except FrontendFailedError as exc:
            status, stop_reason = "failed", str(exc)
        except KeyboardInterrupt:
            pipeline.stop_requested = True
    if pipeline.stop_requested and status == "complete":
        status, stop_reason = "interrupted", f"interrupted after {pipeline.num_submaps} submaps"
    exit_code = 130 if status == "interrupted" else 1
    if not pipeline.keyframes:
        raise RunInterrupted(f"{stop_reason or 'no keyframes'}; nothing was finished, so nothing was written to {out}",
                             exit_code)
    result = pipeline.result()
    result.stats["seconds_total"] = time.perf_counter() - start
    extra = {"stop_reason": stop_reason} if stop_reason else {}
    if live:
        extra["live"] = {"delivered": source.delivered, "dropped": source.dropped, "fps": source.fps}
    summary = write_outputs(result, out, config, source_name=source.name, skipped=source.skipped, status=status,
                            extra=extra or None)
    if all_frames and status == "complete":
        summary["all_frames"] = _localize_all_frames(source, result, frontend, out, progress)
        atomic_write_bytes(out / "summary.json", json.dumps(summary, indent=2).encode())
    print_summary(summary, out, stream=sys.stdout)
    if viewer is not None:
        viewer.finish(result, summary)
        if keep_viewer:
            print(f"viewer stays open at http://{view.host}:{viewer.viewer.port}; Ctrl-C to close", flush=True)
            _wait_for_interrupt()
        viewer.close()
    if status != "complete":
        raise RunInterrupted(f"{stop_reason}; partial results written to {out}", exit_code)
    return summary


def _live_status(source):
    """A per-submap status line for live runs (the frame count is open-ended, so no progress bar)."""
    def on_submap(pipeline, submap_id: int) -> None:
        print(f"submap {submap_id}: {source.delivered} frames ({source.dropped} dropped), "
              f"{len(pipeline.keyframes)} keyframes, {pipeline.num_loops} loops", flush=True)

    return on_submap


def _localize_all_frames(source, result, frontend, out_dir: Path, progress: bool) -> dict:
    """Poses of every frame into ``trajectory_all.txt``; returns the summary entry."""
    from .io import write_tum_trajectory
    from .localize import localize_frames, split_ate, views_from_pipeline

    poses = localize_frames(source, views_from_pipeline(result), to_grid=frontend.grid_colors, progress=progress)
    write_tum_trajectory(out_dir / "trajectory_all.txt", poses.timestamps, poses.T_world_cam)
    entry = poses.summary()
    if poses.T_world_cam_gt is not None and len(poses.timestamps) >= 3:
        split = split_ate(poses)
        entry["ate"] = {"rmse": split.all, "keyframes": split.keyframes, "non_keyframes": split.non_keyframes,
                        "metric": "one Sim(3) alignment of all posed frames, RMSE per kind"}
    return entry


def _wait_for_interrupt() -> None:
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass


class _stop_on_signals:
    """SIGINT / SIGTERM set ``pipeline.stop_requested`` (the run ends after the current submap);
    a second SIGINT raises KeyboardInterrupt at once. Only in the main thread, where Python
    delivers signals; elsewhere the handlers stay as they are."""

    def __init__(self, pipeline) -> None:
        self.pipeline = pipeline
        self.previous: dict = {}

    def _handle(self, signum, frame) -> None:
        if self.pipeline.stop_requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.pipeline.stop_requested = True
        print(f"\nsl4slam: {signal.Signals(signum).name} received; finishing the current submap "
              "(Ctrl-C again to stop at once)", file=sys.stderr, flush=True)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self.previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)


def _device(config: SLAMConfig) -> str:
    if config.vggt.device != "auto":
        return config.vggt.device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def print_summary(summary: dict, out_dir: Path, stream=sys.stdout) -> None:
    counts = summary["counts"]
    line = (f"{counts.get('frames', 0)} frames, {counts.get('keyframes', 0)} keyframes, {counts.get('submaps', 0)} submaps, "
            f"{counts.get('loops', 0)} loops ({counts.get('loops_rejected', 0)} rejected), "
            f"{counts.get('fallbacks', 0)} fallbacks, {counts.get('segments', 1)} segment(s); "
            f"{summary['seconds']['total']:.1f} s, peak {summary['memory']['peak_rss_mib']:.0f} MiB")
    if "graph" in summary:
        graph = summary["graph"]
        line += f"; {graph['group']} {graph['design']} graph, {graph['alignment']} links"
    print(line, file=stream)
    dropped = {k: v for k, v in summary.get("dropped_frames", {}).items() if v}
    skipped = len(summary.get("skipped_inputs", []))
    if skipped:
        dropped["unreadable"] = skipped
    if dropped:
        print("dropped frames: " + ", ".join(f"{v} {k}" for k, v in dropped.items()) + " (see summary.json)", file=stream)
    mode = summary.get("config", {}).get("upgrade", {}).get("mode")
    if not summary.get("metric_upgrade") and (mode == "off" or (mode == "auto" and summary.get("graph", {}).get("design") != "submap")):
        print("metric upgrade: off" + (" (auto: it is for the submap graph, whose map inherits one projective distortion; "
                                       "--metric-upgrade on applies it here too)" if mode == "auto" else ""), file=stream)
    for upgrade in summary.get("metric_upgrade", []):
        state = (f"applied, focal {upgrade['focal_px']:.1f} px, constraint residual {upgrade['residual_before']:.3g} -> "
                 f"{upgrade['residual_after']:.3g}") if upgrade["applied"] else f"skipped: {upgrade['reason']}"
        print(f"metric upgrade{' of segment ' + str(upgrade['segment']) if upgrade['segment'] else ''}: {state}", file=stream)
    if "ate" in summary:
        print(f"ATE RMSE {summary['ate']['rmse']:.4f} m (Sim(3)-aligned, {summary['ate']['poses']} keyframes)", file=stream)
    if "live" in summary:
        print(f"live: {summary['live']['delivered']} frames processed, {summary['live']['dropped']} dropped", file=stream)
    if "all_frames" in summary:
        info = summary["all_frames"]
        line = (f"all frames: {info['localized']} localized ({info['ms_per_frame_median']:.1f} ms each), "
                f"{len(info['failed'])} failed (listed in summary.json); trajectory_all.txt")
        if "ate" in info:
            line += f"; ATE RMSE {info['ate']['non_keyframes']:.4f} non-keyframes, {info['ate']['keyframes']:.4f} keyframes"
        print(line, file=stream)
    print(f"outputs in {out_dir}", file=stream)
