"""Viewing a finished run: a result folder read by :func:`sl4slam.result.reading.load_result`.

:func:`view_result` opens the server first (only the folder's summary and trajectory are read
before it, so a folder that is not a result is still one line and no port) and reads the map on a
background thread (:class:`ResultLoader`). A browser that opens meanwhile gets, in this order: the
control panel with a "loading" line under the title, the view from the keyframe cameras, the
trajectory, loop and ground-truth lines, the panel's point counts for the whole map (from the
keyframes' masks, before any cloud), then one cloud per submap as it is read, and last the
frustums and the view that frames the map (given to the browsers whose camera was not moved); the
"loading" line is removed. While no browser is connected no cloud is sent before the map is
complete, and the whole scene then goes out in the order of :func:`show_state`: a browser opened
later receives what it received when the map was read before the server started (see
:mod:`sl4slam.viewer.app`).
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import TextIO

import numpy as np

from ..objects.store import EMBEDDINGS_FILE
from ..result.reading import KEYFRAMES_OPTION, RunResult, load_result
from .scene import MapState, MapTotals, ViewerSettings, gt_in_estimate_frame, make_cloud, thumbnail


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
    state = cameras_state(result)
    records = result.keyframes
    if records:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            masks = list(pool.map(_mask_count, [r.path for r in records]))
            state.fraction = decimation(masks, settings)
            groups = submap_groups(records)
            loaded = pool.map(lambda item: _submap_cloud(item[0], item[1], state.fraction, settings), groups.items())
            for submap_id, (cloud, thumbs) in zip(groups, loaded):
                state.clouds[submap_id] = cloud
                state.thumbnails.update(thumbs)
    return state


def cameras_state(result: RunResult) -> MapState:
    """What a result folder shows without reading its keyframe arrays: keyframe cameras, trajectory,
    loop edges, ground truth (Sim(3)-aligned onto the estimate) and the run summary; no clouds."""
    state = MapState()
    records = result.keyframes
    if records:
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


def submap_groups(records) -> dict[int, list]:
    """The keyframe records by submap, in submap order."""
    groups: dict[int, list] = {}
    for record in records:
        groups.setdefault(record.submap_id, []).append(record)
    return dict(sorted(groups.items()))


def decimation(masks: list[tuple[int, bool]], settings: ViewerSettings) -> float:
    """The fraction of the confident points kept so that the map fits ``settings.point_budget``
    (``masks``: :func:`_mask_count` of every keyframe file)."""
    return min(1.0, settings.point_budget / max(1, sum(count for count, _ in masks)))


def expected_totals(records, masks: list[tuple[int, bool]], fraction: float) -> MapTotals:
    """The panel's numbers for the whole map before its clouds are built: each submap keeps
    ``ceil(fraction * n)`` of its ``n`` confident points (as :func:`~sl4slam.viewer.scene.make_cloud`
    does); the points carry a confidence when every keyframe file holds one."""
    per_submap: dict[int, int] = {}
    for record, (count, _) in zip(records, masks):
        per_submap[record.submap_id] = per_submap.get(record.submap_id, 0) + count
    shown = sum(int(np.ceil(n * min(1.0, fraction))) for n in per_submap.values())
    return MapTotals(shown, sum(per_submap.values()), all(saved for _, saved in masks))


def _mask_count(path: Path) -> tuple[int, bool]:
    """Confident pixels of a keyframe file, and whether the file holds a per-pixel confidence."""
    with np.load(path) as data:
        return int(np.count_nonzero(data["mask"])), "confidence" in data.files or "confidence_rank" in data.files


def mask_count(path: Path) -> tuple[int, bool]:
    """Confident pixels of a keyframe file, and whether it holds a per-pixel confidence: what
    :func:`decimation` and :func:`expected_totals` take for each keyframe."""
    return _mask_count(path)


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


class ResultLoader:
    """Reads a result folder's map into a :class:`~sl4slam.viewer.app.MapViewer` on a background
    thread, one submap at a time (the order is in the module docstring), and prints the "loaded"
    line when the map is drawn. Closing the viewer stops it.

    Attributes:
        submaps: submaps read into the viewer's state so far.
        error: what ended the reading early (a damaged keyframe file: ``UserError``), or ``None``.
        failed: an event set when the reading failed.
        complete: whether the whole map was drawn.
    """

    def __init__(self, viewer, path: str | Path, settings: ViewerSettings, stream: TextIO = sys.stdout,
                 workers: int = 2) -> None:
        self.viewer, self.path, self.settings, self.stream, self.workers = viewer, Path(path), settings, stream, workers
        self.submaps = 0
        self.error: BaseException | None = None
        self.failed = threading.Event()
        self.complete = False
        self._finished = False
        self._cond = threading.Condition()
        self._stopped: Future = Future()
        self._thread = threading.Thread(target=self._run, name="sl4slam-result-loader", daemon=True)
        viewer.on_close(self.stop)

    def start(self) -> "ResultLoader":
        """Start reading on the background thread; returns the loader."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop reading: no further submap is added to the state or drawn."""
        with self._cond:
            if not self._stopped.done():
                self._stopped.set_result(None)

    @property
    def finished(self) -> bool:
        """Whether the reading ended (the map drawn, the reading failed, or stopped)."""
        return self._finished

    def wait(self, timeout: float | None = None, submaps: int | None = None) -> bool:
        """Block until the reading ended, or with ``submaps`` until that many submaps are in the
        viewer's state (and sent, while a browser is connected).

        Returns:
            False on timeout.
        """
        with self._cond:
            return self._cond.wait_for(lambda: self._finished or (submaps is not None and self.submaps >= submaps),
                                       timeout=timeout)

    def _run(self) -> None:
        try:
            self.complete = self._load()
        except BaseException as exc:  # view_result raises it after closing the server
            self.error = exc
            self.failed.set()
        finally:
            with self._cond:
                self._finished = True
                self._cond.notify_all()

    def _load(self) -> bool:
        """Read and draw the map; False when stopped first."""
        viewer = self.viewer
        start = time.perf_counter()
        result = load_result(self.path)
        records = result.keyframes
        state = cameras_state(result)
        with viewer.lock:
            if viewer.closed:
                return False
            viewer.state = state
            if records:
                viewer.set_status("*loading the map...*")
            viewer.set_up_direction()
            viewer.frame_map()
            viewer.fill_gui()
            viewer.draw_lines()
        if records and not self._read_clouds(state, records):
            return False
        with viewer.lock:
            if viewer.closed:
                return False
            state.totals = None
            if not viewer.sent_clouds():  # no browser saw the map come in: all of it in show_state's order
                show_state(viewer, state)
            else:
                viewer.frame_map()
                viewer.fill_gui()
                # a confidence threshold or confidence colours depend on every cloud: all are sent again
                every = float(viewer.gui_confidence.value) > 0 or str(viewer.gui_color.value) == "confidence"
                viewer.draw_clouds(None if every else viewer.unsent_clouds())
                viewer.draw_frustums(thumbnails_for=set(state.thumbnails))
                viewer.reframe_unmoved()
            viewer.set_status(None)
            print(f"loaded {len(records)} keyframes, {state.total_points():,} points shown in "
                  f"{time.perf_counter() - start:.1f} s; Ctrl-C to stop", file=self.stream, flush=True)
        return True

    def _read_clouds(self, state: MapState, records) -> bool:
        """Build the submaps' clouds in ``workers`` threads and add them to the state in submap
        order, each sent at once when a browser is connected or clouds were sent already; False when
        stopped first."""
        viewer, settings = self.viewer, self.settings
        groups = submap_groups(records)
        # not joined when stopped: a submap being built is dropped, not waited for
        pool = ThreadPoolExecutor(max_workers=self.workers)
        try:
            masks = list(pool.map(_mask_count, [r.path for r in records]))
            fraction = decimation(masks, settings)
            with viewer.lock:
                if viewer.closed:
                    return False
                state.fraction = fraction
                state.totals = expected_totals(records, masks, fraction)
                viewer.fill_gui()
                viewer.set_status(f"*loading the map: 0 of {len(groups)} submaps*")
            futures = [pool.submit(_submap_cloud, submap_id, group, fraction, settings)
                       for submap_id, group in groups.items()]
            for done, (submap_id, future) in enumerate(zip(groups, futures), start=1):
                wait([future, self._stopped], return_when=FIRST_COMPLETED)
                if self._stopped.done():
                    return False
                cloud, thumbs = future.result()
                with viewer.lock:
                    if viewer.closed:
                        return False
                    state.clouds[submap_id] = cloud
                    state.thumbnails.update(thumbs)
                    if viewer.sent_clouds() or viewer.has_browsers():
                        viewer.draw_clouds(viewer.unsent_clouds())
                    viewer.set_status(f"*loading the map: {done} of {len(groups)} submaps*")
                with self._cond:
                    self.submaps = done
                    self._cond.notify_all()
        finally:
            pool.shutdown(wait=False, cancel_futures=True)
        return True


def view_result(path: str | Path, settings: ViewerSettings | None = None, block: bool = True,
                stream: TextIO = sys.stdout):
    """Serve the result folder ``path`` in the browser; blocks until Ctrl-C or SIGTERM when ``block``.

    The server opens before the map is read; the map then streams in (:class:`ResultLoader`). When
    blocking, the two signals are caught from before the server starts (:class:`StopSignals`), so a
    Ctrl-C at any moment closes the viewer cleanly.

    Returns:
        The :class:`~sl4slam.viewer.app.MapViewer`. When not blocking its map may still be loading:
        ``viewer.loader.wait()`` blocks until it is drawn.

    Raises:
        UserError: ``path`` is not a result folder (before the server opens), or a keyframe file
            cannot be read (after the server has stopped).
    """
    from .app import MapViewer, require_viser

    require_viser()
    settings = settings or ViewerSettings()
    folder = load_result(path, keyframes=False).path
    signals = StopSignals().install() if block else None
    try:
        viewer = MapViewer(settings, title=f"sl4slam: {folder.name}", stream=stream)
    except BaseException:
        if signals is not None:
            signals.restore()
        raise
    viewer.loader = ResultLoader(viewer, folder, settings, stream).start()
    if (folder / EMBEDDINGS_FILE).is_file():  # a run with --objects: the "Find object" text box
        from .objects import ObjectQueryPanel

        viewer.objects = ObjectQueryPanel(viewer, folder)
    if not block:
        return viewer
    serve_until_stopped(viewer, stream, stop=viewer.loader.failed, signals=signals)
    if viewer.loader.error is not None:
        raise viewer.loader.error
    return viewer


class StopSignals:
    """SIGINT (Ctrl-C) and SIGTERM made to set an event instead of their usual action.

    Installed only in the main thread (elsewhere :meth:`install` does nothing and ``event`` is
    never set by a signal).

    Attributes:
        event: set by either signal while installed.
    """

    def __init__(self) -> None:
        self.event = threading.Event()
        self._previous: dict = {}

    def install(self) -> "StopSignals":
        """Catch the two signals; returns this object."""
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, lambda *_: self.event.set())
        return self

    def restore(self) -> None:
        """Put the previous handlers back."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}


def serve_until_stopped(viewer, stream: TextIO = sys.stdout, poll: float = 0.2,
                        stop: threading.Event | None = None, signals: StopSignals | None = None) -> None:
    """Keep ``viewer`` serving until Ctrl-C (SIGINT) or SIGTERM, or until ``stop`` is set, then
    stop its server and print "viewer stopped".

    In the main thread the two signals only set an event (``signals``, installed by the caller, or
    installed here), which this loop checks every ``poll`` seconds: the stop does not depend on which
    thread the operating system hands the signal to (a main thread asleep in one long
    ``time.sleep`` wakes only when it gets the signal itself), and no KeyboardInterrupt is raised
    inside the server's code. The previous handlers are back before the server stops, so a second
    Ctrl-C interrupts a stop that hangs. Outside the main thread (no handlers there),
    KeyboardInterrupt ends the wait.
    """
    signals = signals if signals is not None else StopSignals().install()
    try:
        while not signals.event.wait(poll) and not (stop is not None and stop.is_set()):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        signals.restore()
        viewer.close()
    print("viewer stopped", file=stream, flush=True)
