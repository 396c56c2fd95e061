"""One SLAM run from a source path to an output folder (what ``sl4slam run`` does).

Order of work, so that every mistake that can be found early is found before any frame is read:
settings (``sl4slam.resolve.resolve``: checked once, every "auto" settled), the output folder
(created, written to, an earlier run refused unless ``overwrite``), the source (listed, and checked
against what the frontend needs), the weights (present, cached or downloadable, and not cut or
corrupt; one line within seconds when offline). A run that fails there leaves no folder behind that
it created.

During the run ``trajectory.txt`` and ``summary.json`` are rewritten from the current graph every
``OutputConfig.checkpoint_seconds``. SIGINT / SIGTERM finish the current submap, write every output
and raise :class:`RunInterrupted`; a second SIGINT stops at once, still writing what the finished
submaps hold. A frontend that keeps failing ends the run the same way, with its outputs.

Each submap's model output is recorded in ``frontend_cache/`` as the model returns it, beside a
manifest (``sl4slam.resume``), so that a run killed outright (SIGKILL, a power cut, the
out-of-memory killer) continues with ``resume=True`` (``sl4slam run ... --resume``): the source is
read again from its start, the recorded submaps are replayed without the model, and the outputs are
those of a run that was never interrupted. The recording is removed when the run completes (kept
with ``output.cache_frontend``).
"""

from __future__ import annotations

import json
import logging
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from .atomic import atomic_write_bytes
from .config import SLAMConfig
from .errors import UserError
from .intrinsics import from_source
from .resolve import ResolvedConfig, resolve
from .types import FrameSource

log = logging.getLogger("sl4slam")


class RunInterrupted(UserError):
    """The run stopped early (a signal, or a frontend that kept failing) after writing its partial
    results; ``exit_code`` is 128 + the signal's number for a signal (130 for SIGINT / Ctrl-C, 143
    for SIGTERM, :func:`signal_exit_code`), 1 otherwise."""

    def __init__(self, message: str, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def signal_exit_code(signum: int) -> int:
    """The exit status of a program ended by signal ``signum``: 128 + its number (the shell's
    convention: 130 for SIGINT, 143 for SIGTERM)."""
    return 128 + int(signum)


def prepare_output(out_dir: str | Path, overwrite: bool = False, keep: str | Path | None = None,
                   resume: bool = False) -> Path:
    """Create ``out_dir`` and prove it writable, before any work.

    A folder holding an earlier run is refused unless ``overwrite``, which removes that run's
    files first (never ``keep``, e.g. a frontend cache being replayed from inside it), or
    ``resume``, which continues it (its checkpoint is checked by ``sl4slam.resume.read_manifest``).
    """
    from .paths import clear_run, holds_run

    out = Path(out_dir).expanduser()
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a folder; choose another output folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the output folder --out {out}: {exc.strerror or exc}; choose another folder") from None
    if holds_run(out) and not resume:
        if not overwrite:
            from .resume import manifest_path

            if manifest_path(out).is_file():
                raise UserError(f"--out {out} holds a run that did not finish; pass --resume to continue it, "
                                "--overwrite to replace it, or choose another folder")
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


def run_slam(source_path: "str | Path | FrameSource", out_dir: str | Path, config: SLAMConfig, replay_dir: str | None = None,
             progress: bool = True, overwrite: bool = False,
             on_submap: Callable | None = None, view=None, all_frames: bool = False, keep_viewer: bool = False,
             resume: bool = False) -> dict:
    """Open ``source_path``, run the pipeline, write every output into ``out_dir``; return the summary.

    The way to run SLAM from Python to a result folder (``sl4slam run`` calls it)::

        from sl4slam import SLAMConfig, run_slam
        config = SLAMConfig(frontend="simulated")
        config.sim.profile = "vggt"
        summary = run_slam("rgbd_dataset_freiburg1_desk", "result/", config, progress=False)
        summary["ate"]["rmse"]

    Args:
        source_path: image folder, video, TUM / 7-Scenes sequence, camera index or stream URL, or an
            opened ``FrameSource`` (its own stride and max_frames then apply).
        out_dir: the result folder (created; an earlier run in it needs ``overwrite``).
        config: the settings (resolved here, once).
        replay_dir: replay recorded frontend outputs instead of running the frontend.
        progress: progress lines and the final summary on the console; ``False``: silent.
        view: ``sl4slam.viewer.ViewerSettings`` to watch the run in the browser (kept open after
            the run until Ctrl-C when ``keep_viewer``).
        all_frames: also localize every other frame (``trajectory_all.txt``, ``sl4slam.localize``).
        resume: continue the run in ``out_dir`` that was killed or interrupted, from the model outputs
            it recorded (``sl4slam.resume``): the same source and settings; the outputs are those of
            a run that was never interrupted.

    Raises:
        UserError: bad settings, output folder, source, or weights (before any frame is read; a
            folder this call created is removed again); for ``resume``, an ``out_dir`` without a
            checkpoint or one from another source, settings or format, ``overwrite``, a replay or a
            live source; a stage's own ``UserError`` during the run, after the finished work is
            written.
        RunInterrupted: a signal stopped the run, or the frontend kept failing; the partial results
            are written first.
    """
    from .compose import replay_capabilities

    if resume and overwrite:
        raise UserError("--resume continues the run in --out, which --overwrite would delete; pass one of them")
    resolved = resolve(config, capabilities=replay_capabilities(replay_dir) if replay_dir is not None else None)
    manifest = _resumable_run(source_path, out_dir, resolved, replay_dir) if resume else None
    if view is not None:
        from .viewer.app import require_viser

        require_viser()
    existed = Path(out_dir).expanduser().exists()
    out = prepare_output(out_dir, overwrite, keep=replay_dir, resume=resume)
    try:
        from .io import open_source

        source = source_path if _is_source(source_path) else open_source(str(source_path), resolved.config.source)
    except UserError:
        _remove_if_created(out, existed)
        raise
    live = bool(getattr(source, "live", False))
    try:
        if manifest is not None and live:
            raise UserError(_LIVE_RESUME)
        return _run(source, live, out, existed, resolved, replay_dir, progress, on_submap, view, all_frames, keep_viewer,
                    manifest)
    finally:
        if live:
            source.close()  # stops the reader thread, removes the kept frames


_LIVE_RESUME = ("--resume reads the source again from its first frame, which a live camera or stream cannot give; "
                "record the stream to a file and run on that")


def _resumable_run(source_path, out_dir, resolved: ResolvedConfig, replay_dir) -> dict:
    """The checks of ``resume`` that need no frame: no replay, no live source, a checkpoint in
    ``out_dir`` of this format and these settings. Returns its manifest."""
    from .resume import check_settings, read_manifest

    if replay_dir is not None:
        raise UserError("--resume continues a run of the model; a --replay run has no model work to keep: "
                        "run it again with --overwrite")
    if not _is_source(source_path):
        from .io.live import is_live_spec

        if is_live_spec(str(source_path)) and not Path(source_path).exists():
            raise UserError(_LIVE_RESUME)
    manifest = read_manifest(Path(out_dir))
    check_settings(manifest, resolved, Path(out_dir).expanduser())
    return manifest


def _is_source(value) -> bool:
    """Whether ``value`` is an opened frame source (``sl4slam.types.FrameSource``) rather than a path."""
    return all(hasattr(value, name) for name in ("get", "skipped", "has_ground_truth", "__iter__", "__len__"))


def _remove_if_created(out: Path, existed: bool) -> None:
    """Remove the output folder this run created, if nothing was written into it."""
    if not existed and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def check_before_frames(source, resolved: ResolvedConfig, replay_dir, all_frames: bool, live: bool) -> None:
    """Every check that can fail before a frame is read: the source against the frontend, the
    options against the source, the weights (present, cached or downloadable; one line within
    seconds when offline, and for a cut or corrupt file)."""
    from .source_knowledge import source_problem

    if all_frames and live:
        raise UserError("--all-frames needs a re-readable source (a video file or a folder): a live source keeps "
                        "only its keyframes; record the stream to a file first")
    problem = source_problem(source, resolved.capabilities, resolved.frontend.name, resolved.config.source,
                             workers=resolved.workers, ray_address=resolved.config.ray_address)
    if problem:
        raise UserError(problem)
    from_source(source, resolved.intrinsics, resolved.intrinsics_from_source)  # one that cannot be used: one line now
    if resolved.config.false_loops.rate > 0 and not source.has_ground_truth:
        raise UserError(f"--false-loop-rate needs ground-truth poses and depth, which {source.name} has not")
    if replay_dir is None and resolved.frontend.weights is not None:
        from .models.hub import resolve_weights

        resolve_weights(resolved.config.model.weights, source=resolved.frontend.weights)
    if resolved.retrieval.value == "salad":
        from .models.salad import check_salad_weights

        check_salad_weights(resolved.config.retrieval.salad_weights)


def say_cpu_cost(resolved: ResolvedConfig, source_frames: int | None, stream=None) -> None:
    """With a model on the CPU, one line with the expected seconds per submap and for the whole source,
    and the faster models (``sl4slam.frontend.cost``); nothing on a GPU or without a model."""
    if resolved.device != "cpu" or resolved.frontend.cpu_work is None:
        return
    from .frontend.cost import estimate, matmul_rate
    from .registry import frontend_entries

    submap = resolved.config.submap
    others = [(entry.name, entry.cpu_work) for entry in frontend_entries() if entry.cpu_work is not None]
    found = estimate(resolved.frontend.name, resolved.frontend.cpu_work, submap.size + submap.overlap, matmul_rate(),
                     source_frames, submap.size, others)
    print(f"sl4slam: {found.line()} (--quiet hides this line)", file=stream or sys.stderr, flush=True)


def _run(source, live: bool, out: Path, existed: bool, resolved: ResolvedConfig, replay_dir, progress: bool, on_submap,
         view, all_frames: bool, keep_viewer: bool, manifest: dict | None = None) -> dict:
    from .compose import build_stages
    from .frontend.workers import close_workers
    from .pipeline import SLAMPipeline
    from .result.outputs import write_checkpoint, write_outputs

    config = resolved.config
    recording = manifest is not None or (config.output.resumable and replay_dir is None and not live)
    try:
        if config.objects.enabled:  # the embedder's files before any frame; its model loads beside the frontend's
            from .objects.embedder import check_embedder_files

            check_embedder_files(config.objects)
        check_before_frames(source, resolved, replay_dir, all_frames, live)
        identity = None
        if recording:  # five frames read, before the model is loaded
            from .resume import check_source, source_identity

            identity = source_identity(source)
            if manifest is not None:
                check_source(manifest, identity, out)
        if progress and replay_dir is None:
            say_cpu_cost(resolved, None if live else len(source))
        cache_dir = out / "frontend_cache" if config.output.cache_frontend and not recording else None
        stages = build_stages(resolved, replay_dir=replay_dir, cache_dir=cache_dir)
        stages.frontend.prepare()
        objects = config.objects.setup(resolved.device) if config.objects.enabled else None  # its weights: before any frame
        resumer = _record_for_resume(stages, out, resolved, identity, manifest) if recording else None
    except UserError:
        _remove_if_created(out, existed)
        raise
    if progress:
        print("\n".join(resolved.lines()), file=sys.stderr, flush=True)
    last_write = [time.perf_counter()]
    replayed_until = [0.0]  # when the last submap served from the recording was finished

    viewer = None
    if view is not None:
        from .viewer import LiveViewer

        viewer = LiveViewer(view, objects=config.objects.enabled)  # with --objects: the "Find object" box
    callbacks = [c for c in (on_submap, viewer.on_submap if viewer else None,
                             _live_status(source) if live and progress else None) if c]

    def checkpoint(pipeline: SLAMPipeline, submap_id: int) -> None:
        if resumer is not None and submap_id in resumer.replayed:
            replayed_until[0] = time.perf_counter()
        for callback in callbacks:
            callback(pipeline, submap_id)
        if time.perf_counter() - last_write[0] >= config.output.checkpoint_seconds:
            write_checkpoint(pipeline.snapshot(), out, resolved, {"source": source.name})
            if pipeline.objects is not None:
                pipeline.objects.write(out)
            last_write[0] = time.perf_counter()

    keyframe_folder = out / ".keyframe_store"  # older keyframes' arrays (submap.keyframes_in_ram); removed below
    pipeline = SLAMPipeline(resolved, stages, on_submap=checkpoint, keyframe_folder=keyframe_folder, objects=objects)
    if live:
        # the source keeps exactly the frames the pipeline selected as keyframes (loop closures re-read them)
        source.keyframe_counter = lambda: pipeline.selector.num_keyframes
    status, stop_reason = "complete", None
    start = time.perf_counter()
    with _stop_on_signals(pipeline) as stopper:
        try:
            pipeline.consume(source, progress=progress and not live)
        except UserError as exc:  # a stage's own problem (a frontend that keeps failing, a cache that does not match)
            status, stop_reason = "failed", str(exc)
        except KeyboardInterrupt:
            pipeline.stop_requested = True
            stopper.signum = stopper.signum or signal.SIGINT
        finally:
            resumable = resumer is not None and resumer.recording
            if resumer is not None:
                resumer.close()  # a forward left running is not recorded: no write cut short at exit
            close_workers(stages.frontend)  # model workers (--workers, --ray-address), if any
    finished = len({k.submap_id for k in pipeline.keyframes})
    if pipeline.stop_requested and status == "complete":
        status, stop_reason = "interrupted", f"interrupted after {finished} finished submap(s)"
    exit_code = signal_exit_code(stopper.signum or signal.SIGINT) if status == "interrupted" else 1
    again = "; --resume continues it" if resumable else ""
    if not pipeline.keyframes:
        raise RunInterrupted(f"{stop_reason or 'no keyframes'}; nothing was finished, so no result was written to "
                             f"{out}{again}", exit_code)
    result = pipeline.finish(release=True)  # nothing is added after: the final polish gets the room
    result.stats["seconds_total"] = time.perf_counter() - start
    extra = {"stop_reason": stop_reason} if stop_reason else {}
    if live:
        extra["live"] = {"delivered": source.delivered, "dropped": source.dropped, "fps": source.fps}
    if pipeline.objects is not None:
        extra["objects"] = pipeline.objects.record(out)
    summary = write_outputs(result, out, resolved, source_name=source.name, skipped=source.skipped, status=status,
                            extra=extra or None)
    if all_frames and status == "complete":
        summary["all_frames"] = _localize_all_frames(source, result, stages.frontend, out, config.localize, progress)
        atomic_write_bytes(out / "summary.json", json.dumps(summary, indent=2).encode())
    shutil.rmtree(keyframe_folder, ignore_errors=True)  # every keyframe is in keyframes/ now
    if resumer is not None and status == "complete":
        from .resume import close

        close(out, keep_recording=config.output.cache_frontend)
    if progress:
        print_summary(summary, out, stream=sys.stdout)
        if manifest is not None:
            from .resume import resume_line

            print(resume_line(len(resumer.replayed), len(resumer.reconstructed), replayed_until[0] - start
                              if resumer.replayed else 0.0), file=sys.stderr, flush=True)
    if viewer is not None:
        viewer.finish(result, summary, folder=out)  # a query after the run reads the folder
        if keep_viewer:
            print(f"viewer stays open at http://{view.host}:{viewer.viewer.port}; Ctrl-C to close", flush=True)
            viewer.serve_until_stopped()
        viewer.close()
    if status != "complete":
        raise RunInterrupted(f"{stop_reason}; partial results written to {out}{again}", exit_code)
    return summary


def _record_for_resume(stages, out: Path, resolved: ResolvedConfig, identity: dict, manifest: dict | None):
    """Wrap the run's frontend so that each submap's model output is recorded as it comes
    (``sl4slam.frontend.cache.ResumingFrontend``) and, when resuming (``manifest`` given), served from
    its recording; a new run writes its manifest first, a resumed one keeps its own and clears the
    killed run's other outputs. Returns the wrapper."""
    from .frontend.cache import ResumingFrontend
    from .resume import RECORDING_DIR, clear_outputs, intact_recordings, write_manifest

    output = resolved.config.output
    directory = out / RECORDING_DIR
    try:
        if manifest is not None:
            intact_recordings(directory)
            clear_outputs(out)
        else:
            write_manifest(out, resolved, identity)
    except OSError as exc:
        raise UserError(f"cannot write the checkpoint into {directory}: {exc.strerror or exc}; free some space, "
                        "or run with --no-resumable") from None
    stages.frontend = ResumingFrontend(stages.frontend, directory, compressed=output.cache_frontend,
                                       record=output.resumable)
    return stages.frontend


def _live_status(source):
    """A per-submap status line for live runs (the frame count is open-ended, so no progress bar)."""
    def on_submap(pipeline, submap_id: int) -> None:
        print(f"submap {submap_id}: {source.delivered} frames ({source.dropped} dropped), "
              f"{len(pipeline.keyframes)} keyframes, {pipeline.num_loops} loops", flush=True)

    return on_submap


def _localize_all_frames(source, result, frontend, out_dir: Path, settings, progress: bool) -> dict:
    """Poses of every frame into ``trajectory_all.txt``; returns the summary entry."""
    from .io import write_tum_trajectory
    from .localize import localize_frames, split_ate, views_from_pipeline

    poses = localize_frames(source, views_from_pipeline(result), settings, to_grid=frontend.grid_colors, progress=progress)
    write_tum_trajectory(out_dir / "trajectory_all.txt", poses.timestamps, poses.T_world_cam)
    entry = poses.summary()
    if poses.T_world_cam_gt is not None and len(poses.timestamps) >= 3:
        split = split_ate(poses)
        entry["ate"] = {"rmse": split.all, "keyframes": split.keyframes, "non_keyframes": split.non_keyframes,
                        "metric": "one Sim(3) alignment of all posed frames, RMSE per kind"}
    return entry


class _stop_on_signals:
    """SIGINT / SIGTERM set ``pipeline.stop_requested`` (the run ends after the current submap);
    a second SIGINT raises KeyboardInterrupt at once. Only in the main thread, where Python
    delivers signals; elsewhere the handlers stay as they are. ``signum`` is the first signal
    received (``None`` while there is none)."""

    def __init__(self, pipeline) -> None:
        self.pipeline = pipeline
        self.previous: dict = {}
        self.signum: int | None = None

    def _handle(self, signum, frame) -> None:
        if self.pipeline.stop_requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.pipeline.stop_requested = True
        self.signum = self.signum or signum
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
    if not summary.get("resolved", {}).get("metric_upgrade", True):
        print("metric upgrade: off (see the settings line at the start, or summary.json \"resolved\")", file=stream)
    for upgrade in summary.get("metric_upgrade", []):
        state = (f"applied, focal {upgrade['focal_px']:.1f} px, constraint residual {upgrade['residual_before']:.3g} -> "
                 f"{upgrade['residual_after']:.3g}") if upgrade["applied"] else f"skipped: {upgrade['reason']}"
        print(f"metric upgrade{' of segment ' + str(upgrade['segment']) if upgrade['segment'] else ''}: {state}", file=stream)
    if "ate" in summary:
        print(f"ATE RMSE {format_length(summary['ate']['rmse'])} (Sim(3)-aligned, {summary['ate']['poses']} keyframes)", file=stream)
    if "live" in summary:
        print(f"live: {summary['live']['delivered']} frames processed, {summary['live']['dropped']} dropped", file=stream)
    if "all_frames" in summary:
        info = summary["all_frames"]
        line = (f"all frames: {info['localized']} localized ({info['ms_per_frame_median']:.1f} ms each), "
                f"{len(info['failed'])} failed (listed in summary.json); trajectory_all.txt")
        if "ate" in info:
            line += (f"; ATE RMSE {format_length(info['ate']['non_keyframes'])} non-keyframes, "
                     f"{format_length(info['ate']['keyframes'])} keyframes")
        print(line, file=stream)
    if "intrinsics" in summary:
        info = summary["intrinsics"]
        ratio = info["model_focal_ratio"]
        print(f"intrinsics: fx,fy,cx,cy = {','.join(f'{v:g}' for v in info['K'])} ({info['origin']})"
              + (f"; the model's focal was {ratio['median']:.3f}x (median, {ratio['min']:.3f}-{ratio['max']:.3f})" if ratio else "")
              + (f"; {info['note']}" if info["note"] else ""), file=stream)
    if "metric_depth" in summary:
        info = summary["metric_depth"]
        print(f"metric depth from the sensor: {info['submaps_scaled']} submaps scaled (median {info['scale_median']}), "
              f"{info['kept_neighbour_scale']} without enough valid sensor depth kept their neighbour's scale", file=stream)
    for note in summary.get("notes", []):
        print(f"note: {note}", file=stream)
    print(f"outputs in {out_dir}", file=stream)


def format_length(metres: float) -> str:
    """A length with the unit that shows its first digits: "0.0312 m", "4.21 mm", "9.03 µm",
    "1.4 nm"; "0 m" for zero and "< 1 nm" below a nanometre (rounding noise, not a length)."""
    size = abs(metres)
    if size == 0:
        return "0 m"
    if size >= 0.01:
        return f"{metres:.4f} m"
    if size >= 1e-5:
        return f"{metres * 1e3:.3g} mm"
    if size >= 1e-8:
        return f"{metres * 1e6:.3g} µm"
    if size >= 1e-9:
        return f"{metres * 1e9:.2g} nm"
    return "< 1 nm"
