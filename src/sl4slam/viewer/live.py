"""The live viewer: the pipeline's ``on_submap`` callback feeds a browser view of the growing map.

``on_submap(pipeline, submap_id)`` only takes a snapshot (the keyframe list, the graph's current
estimates, the edges) and returns; a worker thread turns the latest snapshot into drawing, so a
slow browser never slows the SLAM loop (snapshots that arrive while one is drawn are merged:
the newest wins, nothing queues up).

Per snapshot the worker:

1. builds the cloud of every submap it has not seen (its keyframes' confident points through
   ``sl4slam.result.outputs.keyframe_world_points``, decimated once into a random order);
2. redraws the submaps whose graph node moved: after a loop closure the optimizer moves many
   nodes, and each such cloud is mapped by ``H_new @ H_drawn^-1`` (projective, exact), not rebuilt;
   a node counts as moved when one of 64 probe points moves more than ``redraw_tolerance`` times
   the trajectory's extent;
3. halves the density of every cloud when the map exceeds the point budget (a truncation, see
   :mod:`sl4slam.viewer.scene`), so the browser holds at most ``point_budget`` points;
4. recomputes the keyframe cameras (``P = K [R|t] H^-1`` decomposed, as the trajectory is), adds
   the new frustums and thumbnails, moves the old ones, and redraws trajectory and loop edges.

With ``objects=True`` (a run with ``--objects``) the panel has a "Find object" box
(:class:`sl4slam.viewer.objects.LiveObjectQueryPanel`): ``on_submap`` also keeps the keyframe
embeddings so far (copies of the lists of ``pipeline.objects``, no array copied), and a query is
answered on its own worker thread on the newest snapshot when it is asked. With ``objects=False``
the folder holds one line on how to get embeddings.
"""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass, field
from typing import Callable, TextIO

import numpy as np

from ..result.reading import GraphEdge, keyframe_colors, loop_segments
from ..submap import StoredKeyframe
from .result import summary_markdown
from .scene import MapState, SubmapCloud, ViewerSettings, gt_in_estimate_frame, make_cloud, scene_extent, thumbnail

PROBE_POINTS = 64


def keyframe_confidence(keyframe: StoredKeyframe) -> np.ndarray:
    """``(H, W)`` float32 per-pixel confidence of a stored keyframe (its percentile in its submap)."""
    return np.asarray(keyframe.confidence_percentile(), np.float32)


def apply_projective(H: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``X (N, 3)`` through the projective ``H (4, 4)``: points ``(N, 3)`` float32 and ``(N,)`` bool
    validity (finite, positive homogeneous weight)."""
    X = np.asarray(X, np.float64)
    w = X @ H[3, :3] + H[3, 3]
    valid = w > 1e-12
    out = (X @ H[:3, :3].T + H[:3, 3]) / np.where(valid, w, 1.0)[:, None]
    valid &= np.isfinite(out).all(axis=1)
    return out.astype(np.float32), valid


@dataclass
class _Snapshot:
    keyframes: list
    estimates: dict[int, np.ndarray]
    edges: list
    frames: int
    colors: object = None  # what re-reads keyframe colours (see sl4slam.result.reading.keyframe_colors)
    T_world_cam: np.ndarray | None = None  # final poses and intrinsics (from the result) when known
    K: np.ndarray | None = None
    gt: np.ndarray | None = None
    summary: dict | None = None
    keyframe_estimates: dict[int, np.ndarray] = field(default_factory=dict)  # per keyframe (keyframe graph)
    embeddings: tuple | None = None  # (frame indices, vectors, embedder) of the keyframes embedded so far
    submap: int | None = None  # the newest submap (None: the finished map)


class LiveViewer:
    """Browser view of a running pipeline; pass ``on_submap`` (or the object) as the pipeline's callback.

    Example::

        viewer = LiveViewer(ViewerSettings(port=8080))
        pipeline = SLAMPipeline.from_config(config, frontend, retrieval, on_submap=viewer.on_submap)
        result = pipeline.run(source)
        viewer.finish(result)

    ``objects``: ``True`` for a pipeline that embeds its keyframes (``--objects``): the panel gets
    the "Find object" box (:attr:`objects`, a ``LiveObjectQueryPanel``; ``query_models``: its
    ``f(embedder_name) -> (embedder, segmenter)``, default the run's embedder and SAM 3); ``False``:
    a line saying to run with ``--objects``; ``None``: neither.
    """

    def __init__(self, settings: ViewerSettings | None = None, title: str = "sl4slam (live)",
                 redraw_tolerance: float = 1e-3, stream: TextIO = sys.stdout, viewer=None, objects: bool | None = None,
                 query_models: Callable | None = None) -> None:
        from .app import MapViewer

        self.viewer = viewer if viewer is not None else MapViewer(settings, title=title, stream=stream)
        self.settings = self.viewer.settings
        self.redraw_tolerance = float(redraw_tolerance)
        self.state: MapState = self.viewer.state
        self._drawn_H: dict[int, np.ndarray] = {}
        self._thumbs_done: set[int] = set()
        self._pending: _Snapshot | None = None
        self._busy = False
        self._closed = False
        self._cond = threading.Condition()
        self.updates = 0
        self.redrawn: list[list[int]] = []  # per update: submaps redrawn because their node moved
        self.error: BaseException | None = None
        self._latest: _Snapshot | None = None  # what a query reads: the newest snapshot
        self.objects = self.objects_hint = None
        if objects:
            from .objects import LiveObjectQueryPanel

            self.objects = LiveObjectQueryPanel(self.viewer, self.current_map, models=query_models)
        elif objects is not None:
            from .objects import objects_hint

            self.objects_hint = objects_hint(self.viewer)
        self._worker = threading.Thread(target=self._run, name="sl4slam-live-viewer", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ pipeline side
    def on_submap(self, pipeline, submap_id: int) -> None:
        """The pipeline's per-submap callback: snapshot and return at once."""
        world = pipeline.backend.world_estimate()
        snapshot = _Snapshot(keyframes=list(pipeline.keyframes),
                             estimates={k: np.array(v, np.float64) for k, v in world.H_world_submap.items()},
                             edges=list(pipeline.edges), frames=int(pipeline.num_frames), colors=pipeline.colors,
                             keyframe_estimates=dict(world.H_world_keyframe), submap=int(submap_id))
        embedder = getattr(pipeline, "objects", None) if self.objects is not None else None
        if embedder is not None:  # the lists as they are now (add() appends or replaces rows, never edits one)
            snapshot.embeddings = (list(embedder.frame_index), list(embedder.vectors), embedder.embedder)
        self._submit(snapshot)

    __call__ = on_submap

    def current_map(self):
        """The newest snapshot as a ``sl4slam.viewer.objects.LiveMap`` for a query (``None`` before the
        first submap, or without embeddings)."""
        from .objects import LiveMap

        with self._cond:
            snap = self._latest
        if snap is None or snap.embeddings is None:
            return None
        frame_index, vectors, embedder = snap.embeddings
        keyframes = [k for k in snap.keyframes if k.submap_id in snap.estimates]
        known = snap.T_world_cam is not None and len(snap.T_world_cam) == len(keyframes)
        cameras = {"T_world_cam": snap.T_world_cam, "K": snap.K} if known else {}
        return LiveMap(keyframes=keyframes, H_world_submap=snap.estimates, H_world_keyframe=snap.keyframe_estimates,
                       colors=snap.colors, frame_index=frame_index, vectors=vectors, embedder=embedder,
                       submap=snap.submap, **cameras)

    def finish(self, result, summary: dict | None = None, timeout: float = 60.0, folder=None) -> None:
        """Draw the final (polished) result, with ground truth and the run summary; wait until drawn.
        ``folder``: the result folder the run wrote, which object queries then read."""
        if folder is not None and self.objects is not None:
            self.objects.finished(folder)
        snapshot = _Snapshot(keyframes=list(result.keyframes), estimates=dict(result.H_world_submap),
                             edges=list(result.edges), frames=int(result.stats.get("frames", 0)),
                             T_world_cam=result.T_world_cam, K=result.K, gt=result.T_world_cam_gt, summary=summary,
                             colors=result.keyframe_colors, keyframe_estimates=dict(result.H_world_keyframe))
        self._submit(snapshot)
        self.wait(timeout)

    def _submit(self, snapshot: _Snapshot) -> None:
        with self._cond:
            if snapshot.embeddings is None and self._latest is not None:
                snapshot.embeddings = self._latest.embeddings  # the finished map: the last submap's embeddings
            self._latest = snapshot
            self._pending = snapshot  # the newest wins: older snapshots are subsumed by it
            self._cond.notify_all()

    def wait(self, timeout: float = 60.0) -> bool:
        """Block until every submitted snapshot is drawn; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending is None and not self._busy, timeout=timeout)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self.viewer.close()
        if self.objects is not None:
            self.objects.close()

    def serve_until_stopped(self, stream: TextIO = sys.stdout) -> None:
        """Keep the map served after the run until Ctrl-C or SIGTERM, then close (see
        :func:`sl4slam.viewer.result.serve_until_stopped`: the stop does not depend on which thread
        gets the signal)."""
        from .result import serve_until_stopped

        try:
            serve_until_stopped(self.viewer, stream)
        finally:
            self.close()

    # ------------------------------------------------------------------ worker side
    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closed)
                if self._closed:
                    return
                snapshot, self._pending, self._busy = self._pending, None, True
            try:
                self.apply(snapshot)
            except Exception as exc:  # a drawing failure must not stop the run; it is reported once
                if self.error is None:
                    self.error = exc
                    print(f"sl4slam: viewer update failed: {exc}", file=sys.stderr)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def apply(self, snap: _Snapshot) -> None:
        """Turn one snapshot into drawing (runs on the worker thread; callable directly in tests)."""
        from ..result import keyframe_cameras

        viewer, state = self.viewer, self.state
        keyframes = [k for k in snap.keyframes if k.submap_id in snap.estimates]
        if snap.T_world_cam is not None:
            T_world_cam, K = np.asarray(snap.T_world_cam), np.asarray(snap.K)
        else:
            T_world_cam, K = keyframe_cameras(keyframes, snap.estimates, snap.keyframe_estimates)
        extent = scene_extent(T_world_cam[:, :3, 3]) if len(T_world_cam) else 1.0
        with viewer.lock:
            by_submap: dict[int, list] = {}
            for keyframe in keyframes:
                by_submap.setdefault(keyframe.submap_id, []).append(keyframe)
            new = [s for s in sorted(by_submap) if s not in state.clouds]
            moved = [s for s in state.clouds if s in snap.estimates and self._moved(s, snap.estimates[s], extent)]
            own = snap.keyframe_estimates  # a node per keyframe: a moved submap may have bent, so it is rebuilt
            for s in new + (moved if own else []):
                state.clouds[s] = self._build_cloud(s, by_submap[s], snap.estimates[s], snap.colors, own)
                self._drawn_H[s] = snap.estimates[s]
            for s in ([] if own else moved):
                self._move_cloud(state.clouds[s], snap.estimates[s] @ np.linalg.inv(self._drawn_H[s]))
                self._drawn_H[s] = snap.estimates[s]
            resized = self._fit_budget()
            state.frame_indices = np.array([k.frame_index for k in keyframes], dtype=np.int64)
            state.submap_ids = np.array([k.submap_id for k in keyframes], dtype=np.int64)
            state.T_world_cam, state.K = T_world_cam, K
            state.image_sizes = np.array([tuple(k.shape)[::-1] for k in keyframes], dtype=np.int64).reshape(-1, 2)
            fresh = [k for k in keyframes if k.frame_index not in self._thumbs_done]
            for keyframe in fresh:
                state.thumbnails[keyframe.frame_index] = thumbnail(keyframe_colors(keyframe, snap.colors),
                                                                   self.settings.thumbnail_width)
                self._thumbs_done.add(keyframe.frame_index)
            loops = [GraphEdge("loop", (e.submap_from, e.submap_to), e.frame_index, e.query_frame)
                     for e in snap.edges if e.kind == "loop" and e.accepted]
            state.loop_segments = loop_segments(state.frame_indices, state.submap_ids, T_world_cam[:, :3, 3], loops) \
                if len(T_world_cam) else np.zeros((0, 2, 3))
            ate_rmse = None
            if snap.gt is not None and len(keyframes) >= 3:
                timestamps = np.array([k.timestamp for k in keyframes])
                aligned = gt_in_estimate_frame(timestamps, T_world_cam, timestamps, snap.gt)
                if aligned is not None:
                    state.gt_positions, ate_rmse = aligned
            counts = {"frames": snap.frames, "keyframes": len(keyframes), "submaps": len(snap.estimates),
                      "loops": len(loops), "fallbacks": sum(1 for e in snap.edges if e.fallback)}
            summary = snap.summary if snap.summary is not None else {"counts": counts}
            if len(new) == len(state.clouds) and new:
                viewer.set_up_direction()
            if new:
                viewer.frame_map()  # where a browser opened from now on starts (open ones keep their view)
            # the panel first, then the lines, the clouds, the frustums last (see sl4slam.viewer.app)
            viewer.set_summary(summary_markdown(summary, ate_rmse, "" if snap.summary else "*running*"))
            viewer.draw_lines()
            viewer.draw_clouds(None if resized else new + moved)
            viewer.draw_frustums(thumbnails_for={k.frame_index for k in fresh})
            viewer.apply_follow(newest=True)
        self.updates += 1
        self.redrawn.append(sorted(moved))

    def _build_cloud(self, submap_id: int, keyframes: list, H_world_submap: np.ndarray, owner=None,
                     H_world_keyframe: dict | None = None) -> SubmapCloud:
        from ..result.outputs import keyframe_world_points

        points, colors, confidence = [], [], []
        own = H_world_keyframe or {}
        for keyframe in keyframes:
            X, valid = keyframe_world_points(keyframe, own.get(keyframe.frame_index, H_world_submap))
            points.append(X[valid])
            colors.append(keyframe_colors(keyframe, owner)[valid])
            conf = keyframe_confidence(keyframe)
            confidence.append(np.ones(int(valid.sum()), np.float32) if conf is None else conf[valid])
        return make_cloud(submap_id, np.concatenate(points), np.concatenate(colors), np.concatenate(confidence),
                          self.state.fraction, self.settings.seed)

    def _moved(self, submap_id: int, H_new: np.ndarray, extent: float) -> bool:
        cloud = self.state.clouds[submap_id]
        if np.array_equal(H_new, self._drawn_H[submap_id]) or not len(cloud):
            return False
        probe = cloud.offsets[:PROBE_POINTS].astype(np.float64) + cloud.centre
        moved, valid = apply_projective(H_new @ np.linalg.inv(self._drawn_H[submap_id]), probe)
        if not valid.all():
            return True
        return float(np.abs(moved - probe).max()) > self.redraw_tolerance * extent

    @staticmethod
    def _move_cloud(cloud: SubmapCloud, H_new_old: np.ndarray) -> None:
        moved, valid = apply_projective(H_new_old, cloud.offsets.astype(np.float64) + cloud.centre)
        moved, cloud.colors, cloud.confidence = moved[valid], cloud.colors[valid], cloud.confidence[valid]
        cloud.centre = moved.mean(0).astype(np.float64) if len(moved) else cloud.centre
        cloud.offsets = (moved - cloud.centre).astype(np.float32)

    def _fit_budget(self) -> bool:
        """Halve every cloud's density until the map fits the point budget; True when it did."""
        state, resized = self.state, False
        while state.total_points() > self.settings.point_budget and state.fraction > 1e-6:
            state.fraction /= 2.0
            for cloud in state.clouds.values():
                cloud.truncate(state.fraction)
            resized = True
        return resized
