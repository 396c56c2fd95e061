"""One SLAM run from a source path to an output folder (what ``sl4slam run`` does)."""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
from pathlib import Path

from .config import SLAMConfig
from .errors import UserError

log = logging.getLogger("sl4slam")


def run_slam(source_path: str | Path, out_dir: str | Path, config: SLAMConfig, replay_dir: str | None = None,
             progress: bool = True, view=None, all_frames: bool = False, keep_viewer: bool = False) -> dict:
    """Open ``source_path``, run the pipeline, write every output into ``out_dir``; return the summary.

    ``view``: ``sl4slam.viewer.ViewerSettings`` to watch the run in the browser (kept open after
    the run until Ctrl-C when ``keep_viewer``). ``all_frames``: also localize every other frame
    (``trajectory_all.txt``, see ``sl4slam.localize``).
    """
    from .frontend import make_frontend
    from .io import open_source
    from .outputs import atomic_write_bytes, write_outputs
    from .pipeline import SLAMPipeline, check_config
    from .retrieval import make_retrieval

    check_config(config)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} exists and is not a folder; choose another output folder")
    if view is not None:
        from .viewer.app import require_viser

        require_viser()
    source = open_source(str(source_path), stride=config.stride, max_frames=config.max_frames)
    live = bool(getattr(source, "live", False))
    try:
        if all_frames and live:
            raise UserError("--all-frames needs a re-readable source (a video file or a folder): a live source keeps "
                            "only its keyframes; record the stream to a file first")
        if len(source) < 2:
            raise UserError(f"{source.name}: {len(source)} frame(s) found; SLAM needs at least 2 frames")
        cache_dir = out_dir / "frontend_cache" if config.output.cache_frontend else None
        frontend = make_frontend(config, replay_dir=replay_dir, cache_dir=cache_dir)
        retrieval = make_retrieval(config.retrieval, device=_device(config), seed=config.alignment.seed)
        # The source already applied stride and max_frames.
        run_config = dataclasses.replace(config, stride=1, max_frames=0)
        viewer = None
        if view is not None:
            from .viewer import LiveViewer

            viewer = LiveViewer(view)
        pipeline = SLAMPipeline(run_config, frontend=frontend, retrieval=retrieval,
                                on_submap=_callbacks(viewer.on_submap if viewer else None, _live_status(source) if live else None))
        if live:
            # the source keeps exactly the frames the pipeline selected as keyframes (for loop closures)
            source.keyframe_counter = lambda: pipeline.selector.num_keyframes
        result = pipeline.run(source, progress=progress and not live)
    finally:
        if live:
            source.close()  # stops the reader thread, removes the kept frames
    summary = write_outputs(result, out_dir, config, source_name=source.name, skipped=source.skipped)
    extra = {}
    if live:
        extra["live"] = {"delivered": source.delivered, "dropped": source.dropped, "fps": source.fps}
    if all_frames:
        extra["all_frames"] = _localize_all_frames(source, result, config, out_dir, progress)
    if extra:
        summary.update(extra)
        atomic_write_bytes(out_dir / "summary.json", json.dumps(summary, indent=2).encode())
    print_summary(summary, out_dir, stream=sys.stdout)
    if viewer is not None:
        viewer.finish(result, summary)
        if keep_viewer:
            print(f"viewer stays open at http://{view.host}:{viewer.viewer.port}; Ctrl-C to close", flush=True)
            _wait_for_interrupt()
        viewer.close()
    return summary


def _callbacks(*callbacks):
    """One ``on_submap`` callback calling each given one in turn (``None``s skipped)."""
    chosen = [c for c in callbacks if c is not None]
    if not chosen:
        return None

    def on_submap(pipeline, submap_id: int) -> None:
        for callback in chosen:
            callback(pipeline, submap_id)

    return on_submap


def _live_status(source):
    """A per-submap status line for live runs (the frame count is open-ended, so no progress bar)."""
    def on_submap(pipeline, submap_id: int) -> None:
        print(f"submap {submap_id}: {source.delivered} frames ({source.dropped} dropped), "
              f"{len(pipeline.keyframes)} keyframes, {pipeline.num_loops} loops", flush=True)

    return on_submap


def _localize_all_frames(source, result, config: SLAMConfig, out_dir: Path, progress: bool) -> dict:
    """Poses of every frame into ``trajectory_all.txt``; returns the summary entry."""
    from .io import write_tum_trajectory
    from .localize import grid_resampler, localize_frames, split_ate, views_from_pipeline

    views = views_from_pipeline(result.keyframes, result.H_world_submap, result.T_world_cam)
    poses = localize_frames(source, views, to_grid=grid_resampler(config), progress=progress)
    write_tum_trajectory(out_dir / "trajectory_all.txt", poses.timestamps, poses.T_world_cam)
    entry = poses.summary()
    if poses.T_world_cam_gt is not None and len(poses.timestamps) >= 3:
        split = split_ate(poses)
        entry["ate"] = {"rmse": split.all, "keyframes": split.keyframes, "non_keyframes": split.non_keyframes,
                        "metric": "one Sim(3) alignment of all posed frames, RMSE per kind"}
    return entry


def _wait_for_interrupt() -> None:
    import time

    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass


def _device(config: SLAMConfig) -> str:
    if config.vggt.device != "auto":
        return config.vggt.device
    try:
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    except ImportError:  # pragma: no cover - torch is a dependency
        return "cpu"


def print_summary(summary: dict, out_dir: Path, stream=sys.stdout) -> None:
    counts = summary["counts"]
    line = (f"{counts.get('frames', 0)} frames, {counts.get('keyframes', 0)} keyframes, {counts.get('submaps', 0)} submaps, "
            f"{counts.get('loops', 0)} loops, {counts.get('fallbacks', 0)} fallbacks; {summary['seconds']['total']:.1f} s, "
            f"peak {summary['memory']['peak_rss_mib']:.0f} MiB")
    print(line, file=stream)
    if summary.get("skipped_inputs"):
        print(f"skipped {len(summary['skipped_inputs'])} unreadable input(s); see summary.json", file=stream)
    if "ate" in summary:
        print(f"ATE RMSE {summary['ate']['rmse']:.4f} (Sim(3)-aligned, {summary['ate']['poses']} keyframes)", file=stream)
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
