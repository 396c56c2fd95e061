"""Finding objects by text in the viewer: a "Find object" folder in the panel of a result's viewer,
and of the live viewer of a run with ``--objects``.

The text box runs :func:`sl4slam.objects.query.query_result` on the viewed result and draws the
answer over the map: each instance's box as line segments (``/objects/instance_N/box``) and its
points (``/objects/instance_N/points``), the best instance in its own colour; the panel shows the
answer's table and the best view's image with the mask over it. The models load on the first query
(the keyframe embeddings name the embedder; a viewer can be given others, as the tests do).

While a run goes (:class:`LiveObjectQueryPanel`), a query is answered on the map as it is when the
query is asked: the keyframes stored so far, their embeddings so far and the graph's current
estimate (:class:`LiveMap`, taken by the live viewer on the mapping thread), seen through
:func:`live_result` as the same ``RunResult`` a finished folder gives, so the query code is shared.
The query runs on a worker thread of the viewer; the mapping thread only hands over its snapshot.
"""

from __future__ import annotations

import shutil
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import UserError
from ..result.reading import KeyframeData, KeyframeRecord, RunResult, keyframe_colors

BEST_COLOR = (255, 30, 200)
OTHER_COLOR = (40, 200, 230)
MASK_ALPHA = 0.5


def box_edges(centre: np.ndarray, axes: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """``(12, 2, 3)`` float32 the edges of an oriented box (``sl4slam.objects.fusion`` conventions)."""
    from ..objects.fusion import BOX_EDGES, box_corners

    corners = box_corners(centre, axes, extents)
    return corners[BOX_EDGES].astype(np.float32)


def mask_overlay(image: np.ndarray, mask: np.ndarray, color=BEST_COLOR, alpha: float = MASK_ALPHA) -> np.ndarray:
    """``(H, W, 3)`` uint8 ``image`` with ``mask`` (resized to it by nearest neighbour) tinted ``color``."""
    from ..objects.lift import resize_mask

    image = np.asarray(image, np.uint8)
    grid = resize_mask(mask, image.shape[:2])
    out = image.astype(np.float32)
    out[grid] = (1.0 - alpha) * out[grid] + alpha * np.asarray(color, np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def default_models(model: str):
    """The embedder called ``model`` and the text segmenter (loaded on first use)."""
    try:
        from ..objects.embedder import make_embedder
        from ..objects.sam3 import make_segmenter
    except ImportError as exc:
        raise UserError(f"the object query models cannot be loaded ({exc}); install sl4slam with its object models") from None
    return make_embedder(model), make_segmenter()


class ObjectQueryPanel:
    """The "Find object" folder of a viewer showing a result folder.

    Args:
        viewer: the :class:`~sl4slam.viewer.app.MapViewer`.
        result: the result folder (with keyframe embeddings) or its ``load_result``.
        models: ``f(embedder_name) -> (embedder, segmenter)``; default :func:`default_models`.
        top_k, threshold: the query's initial settings.

    Attributes:
        answer: the last :class:`~sl4slam.objects.query.QueryAnswer` (``None`` before one).
        message: the panel's last answer text (a table, or the one-line error).
    """

    def __init__(self, viewer, result, models: Callable | None = None, top_k: int = 5, threshold: float = 0.5):
        self.viewer = viewer
        self.result = result
        self.models = models or default_models
        self._loaded = None
        self._lock = threading.Lock()
        self._nodes: list = []
        self.answer = None
        self.message = ""
        gui = viewer.server.gui
        with gui.add_folder("Find object"):
            self.gui_text = gui.add_text("Object", initial_value="", hint='what to find, for example "red mug"')
            self.gui_top_k = gui.add_slider("Keyframes searched", min=1, max=20, step=1, initial_value=int(top_k))
            self.gui_find = gui.add_button("Find")
            self.gui_status = gui.add_markdown("")
            self.gui_answer = gui.add_markdown("")
            self.gui_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="best view", visible=False)
        self.gui_find.on_click(lambda _event: self._on_find())
        self.threshold = float(threshold)

    def _on_find(self) -> None:
        """What the Find button does: the query, here and now."""
        self.find()

    def _load_models(self):
        if self._loaded is None:
            from ..objects.query import open_for_query

            _, embeddings = open_for_query(self.result)
            self._loaded = self.models(embeddings.model)
        return self._loaded

    def find(self, text: str | None = None):
        """Run the query in the text box (or ``text``) and draw its answer; a bad query or a result
        that cannot answer shows its one line in the panel instead. Returns the answer or ``None``."""
        from ..objects.query import check_query, query_result

        text = self.gui_text.value if text is None else text
        with self._lock:
            try:
                check_query(text, int(self.gui_top_k.value), self.threshold)
                embedder, segmenter = self._load_models()
                answer = query_result(self.result, text, embedder, segmenter, top_k=int(self.gui_top_k.value),
                                      threshold=self.threshold)
            except UserError as exc:
                self._show(None, f"**{exc}**")
                return None
            self._show(answer, "```\n" + answer.table() + "\n```")
            return answer

    def _show(self, answer, message: str) -> None:
        self.answer, self.message = answer, message
        scene = self.viewer.server.scene
        with self.viewer.lock:
            if self.viewer.closed:
                return
            for node in self._nodes:
                node.remove()
            self._nodes = []
            self.gui_answer.content = message
            if answer is None or not answer.instances:
                self.gui_image.visible = False
                return
            for rank, instance in enumerate(answer.instances):
                color = BEST_COLOR if rank == 0 else OTHER_COLOR
                self._nodes.append(scene.add_line_segments(
                    f"/objects/instance_{rank}/box", points=box_edges(instance.centre, instance.axes, instance.extents),
                    colors=color, thickness=3.0 if rank == 0 else 2.0, thickness_units="screen"))
                if len(instance.points):
                    self._nodes.append(scene.add_point_cloud(
                        f"/objects/instance_{rank}/points", points=np.asarray(instance.points, np.float32), colors=color,
                        point_size=self.viewer._size(), point_shape="square", point_shading="flat"))
            best = answer.instances[0]
            view = next(v for v in best.views if v.frame_index == best.best_view)
            image = self._keyframe_image(view.frame_index)
            if image is not None and view.mask is not None:
                self.gui_image.image = mask_overlay(image, view.mask)
                self.gui_image.visible = True

    def _keyframe_image(self, frame_index: int) -> np.ndarray | None:
        from ..result.reading import RunResult, load_result

        result = self.result if isinstance(self.result, RunResult) else load_result(Path(self.result))
        record = next((k for k in result.keyframes if k.frame_index == frame_index), None)
        return record.load().colors if record is not None else None


# ------------------------------------------------------------------------------ while the run goes
@dataclass
class LiveMap:
    """What a query reads of a running map, as the mapping thread handed it over.

    Attributes:
        keyframes: the stored keyframes (``sl4slam.submap.StoredKeyframe``) whose submap the
            estimate places, in time order.
        H_world_submap, H_world_keyframe: the graph's estimate (as ``SLAMResult`` holds them).
        colors: what re-reads a keyframe's colours (``SLAMPipeline.colors``), or ``None``.
        frame_index, vectors: the keyframe embeddings so far (``KeyframeEmbedder``'s rows, in its order).
        embedder: the run's ``ImageEmbedder`` (its ``name`` names the embeddings).
        submap: the newest submap, ``None`` for the finished (polished) map.
        T_world_cam, K: the keyframe cameras when known (the finished result's), else computed.
    """

    keyframes: list
    H_world_submap: dict
    H_world_keyframe: dict
    colors: Any
    frame_index: list
    vectors: list
    embedder: Any
    submap: int | None = None
    T_world_cam: np.ndarray | None = None
    K: np.ndarray | None = None

    @property
    def model(self) -> str:
        return str(self.embedder.name)

    def describe(self) -> str:
        """A few words on which map this is: "the map at submap 4 (37 keyframes)"."""
        which = f"the map at submap {self.submap}" if self.submap is not None else "the finished map"
        return f"{which} ({len(self.keyframes)} keyframes)"


@dataclass
class LiveKeyframeRecord(KeyframeRecord):
    """A keyframe of a running map as a ``KeyframeRecord``: :meth:`load` computes its world points
    under the map's estimate and re-reads its colours, as the run writes them at the end (the full
    layout: the points where the confidence mask and the projective weight allow, zeros elsewhere).

    Attributes:
        keyframe: the ``StoredKeyframe``. H_world_local: its map into the world.
        colors: what re-reads its colours (``None``: mid-grey).
    """

    keyframe: Any = None
    H_world_local: np.ndarray | None = None
    colors: Any = None

    def image(self) -> np.ndarray:
        """``(H, W, 3)`` uint8 its colours on its grid."""
        return keyframe_colors(self.keyframe, self.colors)

    def load(self) -> KeyframeData:
        from ..result.outputs import keyframe_world_points

        X, valid = keyframe_world_points(self.keyframe, self.H_world_local)
        return KeyframeData(points_world=np.where(valid[..., None], X, np.float32(0.0)).astype(np.float32), mask=valid,
                            colors=self.image(), confidence=self.keyframe.confidence_percentile())


def live_result(live: LiveMap, folder: str | Path) -> RunResult:
    """The ``RunResult`` of a running map that :func:`~sl4slam.objects.query.query_result` takes:
    its keyframes as :class:`LiveKeyframeRecord` under the map's estimate, and its embeddings written
    to ``folder/objects/embeddings.npz`` (a scratch folder, not the run's: the run writes its own file
    at checkpoints), where the query reads them.

    Raises:
        UserError: one line when the map has no keyframe or no embedding yet.
    """
    from ..objects.store import write_embeddings
    from ..result import keyframe_cameras

    if not live.keyframes or not live.frame_index:
        raise UserError("the map has no keyframes yet; ask again when the first submap is mapped")
    folder = Path(folder)
    keyframes = list(live.keyframes)
    if live.T_world_cam is not None and live.K is not None:
        T_world_cam, K = np.asarray(live.T_world_cam), np.asarray(live.K)
    else:
        T_world_cam, K = keyframe_cameras(keyframes, live.H_world_submap, live.H_world_keyframe)
    records = [LiveKeyframeRecord(frame_index=int(k.frame_index), timestamp=float(k.timestamp), submap_id=int(k.submap_id),
                                  K=K[i], T_world_cam=T_world_cam[i], image_size=tuple(k.shape)[::-1],
                                  path=folder / "keyframes" / f"{k.frame_index:06d}.npz", layout="live", keyframe=k,
                                  H_world_local=live.H_world_keyframe.get(k.frame_index, live.H_world_submap[k.submap_id]),
                                  colors=live.colors)
               for i, k in enumerate(keyframes)]
    write_embeddings(folder, np.asarray(live.frame_index, np.int64), np.stack(live.vectors), live.model)
    return RunResult(path=folder, version=3, summary={"counts": {"keyframes": len(records)}},
                     timestamps=np.array([k.timestamp for k in keyframes], np.float64), T_world_cam=T_world_cam,
                     keyframes=records)


def run_models(embedder) -> Callable:
    """The models of a live query: the run's own embedder for the text (no second copy of it) and the
    default text segmenter on its device; another embedder name gets :func:`default_models`."""
    def models(name: str):
        if name != getattr(embedder, "name", None):
            return default_models(name)
        try:
            from ..objects.sam3 import make_segmenter
        except ImportError as exc:
            raise UserError(f"the object query models cannot be loaded ({exc}); install sl4slam with its object "
                            "models") from None
        return embedder, make_segmenter(device=getattr(embedder, "device", "cpu"))

    return models


@dataclass
class _Asked:
    """A query asked: its text and the map it is answered on."""

    text: str
    live: LiveMap | None


class LiveObjectQueryPanel(ObjectQueryPanel):
    """The "Find object" folder of the live viewer of a run with ``--objects``.

    Find answers on the map as it is when asked (``current_map()``), on a worker thread: the
    mapping goes on meanwhile; after the run, on the result folder it wrote (:meth:`finished`).
    The models load once, on the first query, with a status line; a query asked while one runs is
    refused with a line.

    Args:
        viewer: the :class:`~sl4slam.viewer.app.MapViewer`.
        current_map: returns the newest :class:`LiveMap` (``None`` before the first submap).
        models: ``f(embedder_name) -> (embedder, segmenter)``; default :func:`run_models` of the
            run's embedder.
        top_k, threshold: the query's initial settings.

    Attributes:
        answer, message: as :class:`ObjectQueryPanel`. status: the status line.
        view: the ``RunResult`` the last query read (:func:`live_result`).
    """

    def __init__(self, viewer, current_map: Callable[[], "LiveMap | None"], models: Callable | None = None,
                 top_k: int = 5, threshold: float = 0.5) -> None:
        super().__init__(viewer, None, models=models, top_k=top_k, threshold=threshold)
        self.models = models
        self.current_map = current_map
        self.status = self._progress = self._notice = ""
        self.view: RunResult | None = None
        self._running: _Asked | None = None
        self._worker: threading.Thread | None = None
        self._state = threading.Lock()
        self._scratch: Path | None = None  # where live_result writes the embeddings (made on the first query)
        self.folder: Path | None = None
        self._written: RunResult | None = None

    def finished(self, folder: str | Path) -> None:
        """The run wrote its result into ``folder``: queries on the finished map read it from there
        (its keyframes' arrays may no longer be in the run's memory), when it holds embeddings."""
        from ..objects.store import EMBEDDINGS_FILE

        if (Path(folder) / EMBEDDINGS_FILE).is_file():
            self.folder = Path(folder)

    def _on_find(self) -> None:
        self.ask()

    def set_status(self, line: str, notice: str | None = None) -> None:
        """Show ``line`` as the panel's status line, and ``notice`` (a refused query) under it until
        the running query ends (``None``: keep the notice shown)."""
        with self.viewer.lock:
            self._progress = line
            if notice is not None:
                self._notice = notice
            self.status = "  \n".join(part for part in (self._progress, self._notice) if part)
            if not self.viewer.closed:
                self.gui_status.content = self.status

    def ask(self, text: str | None = None) -> bool:
        """Start a query of the text box (or ``text``) on the map as it is now, on a worker thread;
        returns at once. ``False`` (and a status line) when a query is still running."""
        text = self.gui_text.value if text is None else text
        with self._state:
            if self._running is not None:
                self.set_status(self._progress, f'*a query is running ("{self._running.text.strip()}"); ask again '
                                "when its answer is shown*")
                return False
            self._running = asked = _Asked(text, self.current_map())
            self._worker = threading.Thread(target=self._work, args=(asked,), name="sl4slam-object-query", daemon=True)
            self._worker.start()
        return True

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the running query (if any) is answered; ``False`` on timeout."""
        worker = self._worker
        if worker is not None:
            worker.join(timeout)
            return not worker.is_alive()
        return True

    @property
    def running(self) -> bool:
        return self._running is not None

    def _work(self, asked: _Asked) -> None:
        try:
            self.find(asked.text, asked.live)
        except Exception as exc:  # a failed query leaves the run and the viewer running; its line is shown
            self._show(None, f"**the query failed: {type(exc).__name__}: {exc}**")
            self.set_status("")
        finally:
            with self._state:
                self._running = None
                self.set_status(self._progress, "")

    def find(self, text: str | None = None, live: "LiveMap | None" = None):
        """Run a query now, on this thread, on ``live`` (default: the current map) and draw its answer;
        a bad query or a map that cannot answer yet shows its one line instead. Returns the answer
        or ``None``."""
        from ..objects.query import check_query, query_result

        text = self.gui_text.value if text is None else text
        live = self.current_map() if live is None else live
        with self._lock:
            try:
                check_query(text, int(self.gui_top_k.value), self.threshold)
                if live is None:
                    raise UserError("the map has no keyframes yet; ask again when the first submap is mapped")
                embedder, segmenter = self._load_live_models(live)
                self.set_status(f"*searching {live.describe()}*")
                started = time.perf_counter()
                if live.submap is None and self.folder is not None:  # the finished map, as written
                    if self._written is None:
                        from ..result.reading import load_result

                        self._written = load_result(self.folder)
                    self.view = self._written
                else:
                    if self._scratch is None:
                        self._scratch = Path(tempfile.mkdtemp(prefix="sl4slam-live-query-"))
                    self.view = live_result(live, self._scratch)
                answer = query_result(self.view, text, embedder, segmenter, top_k=int(self.gui_top_k.value),
                                      threshold=self.threshold)
            except UserError as exc:
                self.set_status("")
                self._show(None, f"**{exc}**")
                return None
            if self.view is not self._written:
                answer.result = f"live: {live.describe()}"
            self.set_status(f"answered on {live.describe()} in {time.perf_counter() - started:.1f} s")
            self._show(answer, "```\n" + answer.table() + "\n```")
            return answer

    def _load_live_models(self, live: LiveMap):
        if self._loaded is None:
            self.set_status("*loading the object models (once) ...*")
            started = time.perf_counter()
            self._loaded = (self.models or run_models(live.embedder))(live.model)
            self.set_status(f"object models loaded in {time.perf_counter() - started:.1f} s")
        return self._loaded

    def _keyframe_image(self, frame_index: int) -> np.ndarray | None:
        view = self.view
        record = next((k for k in view.keyframes if k.frame_index == frame_index), None) if view is not None else None
        if record is None:
            return None
        return record.image() if isinstance(record, LiveKeyframeRecord) else record.load().colors

    def close(self) -> None:
        """Remove the scratch folder (a running query finishes on its own and draws nothing)."""
        if self._scratch is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)


def objects_hint(viewer):
    """The "Find object" folder of a live viewer whose run embeds no keyframes: one line on how to
    get them. Returns the markdown handle."""
    gui = viewer.server.gui
    with gui.add_folder("Find object"):
        return gui.add_markdown("Finding objects needs keyframe embeddings: run with `--objects` "
                                "(`sl4slam run SRC --out DIR --view --objects`).")
