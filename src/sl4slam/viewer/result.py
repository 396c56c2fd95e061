"""Viewing a finished run: a result folder read by :func:`sl4slam.result.reading.load_result`."""

from __future__ import annotations

import signal
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TextIO

import numpy as np

from ..result.reading import KEYFRAMES_OPTION, RunResult, load_result
from .scene import MapState, ViewerSettings, gt_in_estimate_frame, make_cloud, thumbnail


def summary_markdown(summary: dict, ate_rmse: float | None = None, extra: str = "") -> str:
    """The run summary as a few Markdown lines: counts, loops, fallbacks, ATE."""
    counts = summary.get("counts", {})
    lines = [f"{counts.get('frames', 0)} frames, {counts.get('keyframes', 0)} keyframes, "
             f"{counts.get('submaps', 0)} submaps  ",
             f"{counts.get('loops', 0)} loops, {counts.get('fallbacks', 0)} fallbacks  "]
    if "ate" in summary:
        lines.append(f"ATE RMSE {summary['ate']['rmse']:.4f} (Sim(3), {summary['ate'].get('poses', '?')} keyframes)  ")
    elif ate_rmse is not None:
        lines.append(f"ATE RMSE {ate_rmse:.4f} (Sim(3))  ")
    if "all_frames" in summary:
        info = summary["all_frames"]
        lines.append(f"all frames: {info.get('localized', 0)} localized, {len(info.get('failed', []))} failed  ")
    if summary.get("source"):
        lines.append(f"source: {summary['source']}  ")
    if extra:
        lines.append(extra)
    return "\n".join(lines)


def state_from_result(result: RunResult, settings: ViewerSettings, workers: int = 2) -> MapState:
    """Everything the viewer draws for a result folder, decimated to ``settings.point_budget``.

    Two passes over the keyframe files: the masks (to size the decimation), then the points of
    each submap; the arrays are read in ``workers`` threads.
    """
    state = MapState()
    records = result.keyframes
    if records:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            counts = list(pool.map(_mask_count, [r.path for r in records]))
            total = max(1, sum(counts))
            state.fraction = min(1.0, settings.point_budget / total)
            by_submap: dict[int, list] = {}
            for record in records:
                by_submap.setdefault(record.submap_id, []).append(record)
            loaded = pool.map(lambda item: _submap_cloud(item[0], item[1], state.fraction, settings),
                              sorted(by_submap.items()))
            for submap_id, (cloud, thumbs) in zip(sorted(by_submap), loaded):
                state.clouds[submap_id] = cloud
                state.thumbnails.update(thumbs)
        state.frame_indices = np.array([r.frame_index for r in records])
        state.submap_ids = np.array([r.submap_id for r in records])
        state.T_world_cam = np.stack([r.T_world_cam for r in records])
        state.K = np.stack([r.K for r in records])
        state.image_sizes = np.array([r.image_size for r in records])
        state.loop_segments = result.loop_segments()
        timestamps = np.array([r.timestamp for r in records])
    else:  # trajectory only (the run did not save keyframe files)
        state.frame_indices = np.arange(len(result.T_world_cam))
        state.T_world_cam = result.T_world_cam
        timestamps = result.timestamps
    ate_rmse = None
    if result.gt is not None:
        aligned = gt_in_estimate_frame(timestamps, state.T_world_cam, *result.gt)
        if aligned is not None:
            state.gt_positions, ate_rmse = aligned
    note = "" if records else f"no keyframes/*.npz: trajectory only (run with {KEYFRAMES_OPTION} for the map)"
    state.summary_markdown = summary_markdown(result.summary, ate_rmse, note)
    return state


def _mask_count(path: Path) -> int:
    with np.load(path) as data:
        return int(np.count_nonzero(data["mask"]))


def _submap_cloud(submap_id: int, records, fraction: float, settings: ViewerSettings):
    points, colors, confidence, thumbs = [], [], [], {}
    has_confidence = True
    for record in records:
        data = record.load()
        points.append(data.points_world[data.mask])
        colors.append(data.colors[data.mask])
        has_confidence &= data.confidence is not None
        confidence.append(data.confidence[data.mask] if data.confidence is not None else None)
        thumbs[record.frame_index] = thumbnail(data.colors, settings.thumbnail_width)
    conf = np.concatenate(confidence) if has_confidence else None
    cloud = make_cloud(submap_id, np.concatenate(points), np.concatenate(colors), conf, fraction, settings.seed)
    return cloud, thumbs


def show_state(viewer, state: MapState) -> None:
    """Send a whole state to a :class:`~sl4slam.viewer.app.MapViewer`: the view and the control
    panel's numbers and summary first, then the lines, the clouds, and the frustums last (see
    :mod:`sl4slam.viewer.app`)."""
    with viewer.lock:
        viewer.state = state
        viewer.set_up_direction()
        viewer.frame_map()
        viewer.fill_gui()
        viewer.draw_lines()
        viewer.draw_clouds()
        viewer.draw_frustums(thumbnails_for=set(state.thumbnails))


def view_result(path: str | Path, settings: ViewerSettings | None = None, block: bool = True,
                stream: TextIO = sys.stdout):
    """Serve the result folder ``path`` in the browser; blocks until Ctrl-C when ``block``.

    Returns the :class:`~sl4slam.viewer.app.MapViewer` (when not blocking).
    """
    from .app import MapViewer, require_viser

    require_viser()
    settings = settings or ViewerSettings()
    result = load_result(path)
    start = time.perf_counter()
    state = state_from_result(result, settings)
    viewer = MapViewer(settings, title=f"sl4slam: {result.path.name}", stream=stream)
    show_state(viewer, state)
    print(f"loaded {len(result.keyframes)} keyframes, {state.total_points():,} points shown in "
          f"{time.perf_counter() - start:.1f} s; Ctrl-C to stop", file=stream, flush=True)
    if not block:
        return viewer
    serve_until_stopped(viewer, stream)
    return viewer


def serve_until_stopped(viewer, stream: TextIO = sys.stdout, poll: float = 0.2) -> None:
    """Keep ``viewer`` serving until Ctrl-C (SIGINT) or SIGTERM, then stop its server and print
    "viewer stopped".

    In the main thread the two signals only set an event, which this loop checks every ``poll``
    seconds: the stop does not depend on which thread the operating system hands the signal to
    (a main thread asleep in one long ``time.sleep`` wakes only when it gets the signal itself),
    and no KeyboardInterrupt is raised inside the server's code. The previous handlers are back
    before the server stops, so a second Ctrl-C interrupts a stop that hangs. Outside the main
    thread (no handlers there), KeyboardInterrupt ends the wait.
    """
    stop = threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, lambda *_: stop.set())
    try:
        while not stop.wait(poll):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        viewer.close()
    print("viewer stopped", file=stream, flush=True)
