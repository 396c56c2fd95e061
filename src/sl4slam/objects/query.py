"""Open-vocabulary object queries on a finished map: a text in, the objects it names out, in 3D.

:func:`query_result` embeds the text, ranks the result's keyframes by the cosine similarity of
their stored embeddings (``objects/embeddings.npz``, :mod:`sl4slam.objects.store`), segments the
text in the ``top_k`` best keyframes, lifts each mask to the keyframe's world points
(:mod:`sl4slam.objects.lift`) and fuses the views into instances with oriented boxes
(:mod:`sl4slam.objects.fusion`). Answers are in the map's world frame (the frame of
``trajectory.txt``) and units.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..result.reading import RunResult, load_result
from .fusion import ObjectInstance, ViewDetection, fuse_views
from .interfaces import DEFAULT_MAX_TEXT_CHARS, ImageEmbedder, TextSegmenter
from .lift import grid_normals, points_under_mask, resize_mask, ring_points, trim_mask
from .store import KeyframeEmbeddings, read_embeddings

ANSWER_FORMAT = 1
"""The version of :meth:`QueryAnswer.to_json`'s layout."""


@dataclass
class KeyframeHit:
    """A keyframe searched for the query.

    Attributes:
        frame_index: its source frame. similarity: cosine similarity of its embedding with the text's.
        masks: instances the segmenter found in it. pixels: their pixels in all.
    """

    frame_index: int
    similarity: float
    masks: int = 0
    pixels: int = 0


@dataclass
class QueryAnswer:
    """The answer to a text query.

    Attributes:
        query: the text. top_k, threshold: the settings used.
        instances: the objects found, highest score first.
        keyframes: the keyframes searched, most similar first.
        embedder, segmenter: the models' names.
        result: the result folder.
        seconds: time per step ("validate", "embed_text", "rank", "load" (the keyframes' files),
            "segment", "lift", "fuse") and in all ("total").
    """

    query: str
    top_k: int
    threshold: float
    instances: list[ObjectInstance]
    keyframes: list[KeyframeHit]
    embedder: str
    segmenter: str
    result: str
    seconds: dict = field(default_factory=dict)

    def to_json(self, points: bool = False) -> dict:
        """The answer as JSON-ready data: each instance's box (``centre``, ``axes`` rows, ``extents``
        in the map's frame and units), score, best view and the keyframes that saw it with their
        scores; the keyframes searched; the query and timings. ``points``: add each instance's
        subsampled points."""
        instances = []
        for rank, inst in enumerate(self.instances):
            item = {"rank": rank, "score": round(inst.score, 6), "centre": _list(inst.centre),
                    "axes": [_list(row) for row in inst.axes], "extents": _list(inst.extents),
                    "best_view": int(inst.best_view),
                    "views": [{"frame_index": int(v.frame_index), "score": round(float(v.score), 6),
                               "similarity": round(float(v.similarity), 6), "points": int(len(v.points)),
                               "pixels": int(v.pixels)} for v in inst.views],
                    "num_points": int(len(inst.points))}
            if points:
                item["points"] = [_list(p) for p in inst.points]
            instances.append(item)
        return {"format": ANSWER_FORMAT, "query": self.query, "top_k": self.top_k, "threshold": self.threshold,
                "result": self.result, "frame": "map (the world frame of trajectory.txt)", "units": "map units",
                "embedder": self.embedder, "segmenter": self.segmenter,
                "keyframes": [{"frame_index": k.frame_index, "similarity": round(k.similarity, 6), "masks": k.masks,
                               "pixels": k.pixels} for k in self.keyframes],
                "instances": instances, "seconds": {k: round(v, 4) for k, v in self.seconds.items()}}

    def table(self) -> str:
        """A terminal table: instance, score, centre, extents, views."""
        lines = [f'"{self.query}": {len(self.instances)} instance(s) in {len(self.keyframes)} keyframe(s) searched '
                 f"({self.embedder} + {self.segmenter}; map frame and units)"]
        if not self.instances:
            return lines[0]
        lines.append(f"{'#':>3}  {'score':>6}  {'centre (x, y, z)':>26}  {'extents':>22}  views (best first)")
        for rank, inst in enumerate(self.instances):
            centre = ", ".join(f"{c:7.3f}" for c in inst.centre)
            extents = " x ".join(f"{e:.3f}" for e in inst.extents)
            views = " ".join(str(f) for f in inst.frames[:8]) + (" ..." if len(inst.views) > 8 else "")
            lines.append(f"{rank:>3}  {inst.score:6.3f}  {centre:>26}  {extents:>22}  {views}")
        return "\n".join(lines)


def _list(values) -> list[float]:
    return [round(float(v), 6) for v in np.asarray(values).reshape(-1)]


def max_text_chars(embedder: ImageEmbedder | None) -> int:
    """The longest query text the embedder takes (its ``max_text_chars``, else
    :data:`DEFAULT_MAX_TEXT_CHARS`)."""
    limit = getattr(embedder, "max_text_chars", None) if embedder is not None else None
    return int(limit) if limit else DEFAULT_MAX_TEXT_CHARS


def check_query(text, top_k: int = 5, threshold: float = 0.5, limit: int = DEFAULT_MAX_TEXT_CHARS) -> str:
    """Check a query's text and settings (one-line ``UserError`` each); returns the stripped text."""
    if not isinstance(text, str) or not text.strip():
        raise UserError("the query is empty; give the object to find, for example \"red mug\"")
    text = text.strip()
    if len(text) > limit:
        raise UserError(f"the query is {len(text)} characters long; the embedder takes at most {limit}: shorten it")
    if isinstance(top_k, bool) or not isinstance(top_k, (int, np.integer)) or top_k < 1:
        raise UserError(f"--top-k must be a whole number of at least 1, got {top_k!r}")
    if not isinstance(threshold, (int, float, np.floating)) or not 0.0 <= float(threshold) <= 1.0:
        raise UserError(f"--threshold must be between 0 and 1, got {threshold!r}")
    return text


def open_for_query(result: str | Path | RunResult) -> tuple[RunResult, KeyframeEmbeddings]:
    """Read what a query needs of a result folder: its keyframes and their embeddings.

    Raises:
        UserError: one line when the folder is not a result, is of a format ``load_result`` does not
            read, has no keyframes, or has no (or damaged) embeddings.
    """
    loaded = result if isinstance(result, RunResult) else load_result(result)
    loaded.require_keyframes("an object query")
    embeddings = read_embeddings(loaded.path)
    known = {k.frame_index for k in loaded.keyframes}
    if not any(int(f) in known for f in embeddings.frame_index):
        raise UserError(f"the keyframe embeddings of {loaded.path} name no keyframe of its keyframes/ folder; "
                        "run with --objects again")
    return loaded, embeddings


def rank_keyframes(text_embedding: np.ndarray, embeddings: KeyframeEmbeddings, frames: set[int] | None = None,
                   top_k: int = 5) -> list[KeyframeHit]:
    """The ``top_k`` keyframes most similar to a text.

    Args:
        text_embedding: ``(D,)`` unit vector. embeddings: the keyframes'.
        frames: only these frames (those with a keyframe file); ``None``: all.
        top_k: how many.

    Returns:
        Hits, highest cosine similarity first (ties: earlier frame first).
    """
    similarity = embeddings.embeddings @ np.asarray(text_embedding, np.float32).reshape(-1)
    index = embeddings.frame_index
    usable = np.array([frames is None or int(f) in frames for f in index], dtype=bool)
    order = np.lexsort((index, -similarity))
    order = order[usable[order]][:top_k]
    return [KeyframeHit(frame_index=int(index[i]), similarity=float(similarity[i])) for i in order]


def default_models(embedder_name: str, embedder: ImageEmbedder | None = None,
                   segmenter: TextSegmenter | None = None) -> tuple[ImageEmbedder, TextSegmenter]:
    """``embedder`` and ``segmenter``, each loaded when not given (downloaded on first use): the
    embedder called ``embedder_name`` (the one that made a result's keyframe embeddings) and the
    default text segmenter (SAM 3)."""
    try:
        from .embedder import make_embedder
        from .sam3 import make_segmenter
    except ImportError as exc:
        raise UserError(f"the object query models cannot be loaded ({exc}); install them: "
                        'pip install "sl4slam[objects]"') from None
    return embedder or make_embedder(embedder_name), segmenter or make_segmenter()


def query_result(result: str | Path | RunResult, text: str, embedder: ImageEmbedder, segmenter: TextSegmenter,
                 top_k: int = 5, threshold: float = 0.5, min_confidence: float = 0.0, erode_px: int = 0,
                 max_points: int = 4000, seed: int = 0, refine: bool = True, amodal: bool = True) -> QueryAnswer:
    """Find the objects a text names in a result's map.

    Args:
        result: a result folder (written with ``--objects``) or its :func:`load_result`.
        text: what to find ("red mug").
        embedder: the model that made the keyframe embeddings (its ``name`` must match theirs).
        segmenter: the text-prompted segmenter.
        top_k: keyframes segmented (the most similar to the text).
        threshold: the lowest mask score kept.
        min_confidence: keep only points at or above this confidence percentile (0..100) besides the
            run's own confidence mask.
        erode_px: grid pixels taken off each mask's rim before lifting (:func:`points_under_mask`).
        max_points: points kept per instance. seed: seed of the point subsamples.
        refine, amodal: the fusion's offset refinement and hidden-back extension (:func:`fuse_views`).

    Returns:
        The :class:`QueryAnswer` (instances in the map's world frame and units).

    Raises:
        UserError: one line, before any model runs, for an empty or too long text, ``top_k < 1``, a
            threshold outside [0, 1], a folder that is not a readable result, one without keyframes
            or without embeddings, or embeddings made by another model.
    """
    started = time.perf_counter()
    clock = started
    seconds: dict[str, float] = {}

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - clock
        clock = now

    text = check_query(text, top_k, threshold, max_text_chars(embedder))
    loaded, embeddings = open_for_query(result)
    if embedder.name != embeddings.model:
        raise UserError(f"the keyframe embeddings of {loaded.path} were made with {embeddings.model}, not "
                        f"{embedder.name}; query with {embeddings.model} (or run with --objects again)")
    if int(embedder.dim) != embeddings.dim:
        raise UserError(f"the keyframe embeddings of {loaded.path} have {embeddings.dim} dimensions, "
                        f"{embedder.name} makes {embedder.dim}; run with --objects again")
    records = {k.frame_index: k for k in loaded.keyframes}
    lap("validate")

    text_embedding = np.asarray(embedder.embed_texts([text]), np.float32).reshape(-1)
    lap("embed_text")
    hits = rank_keyframes(text_embedding, embeddings, set(records), top_k)
    lap("rank")

    detections: list[ViewDetection] = []
    for hit in hits:
        record = records[hit.frame_index]
        data = record.load()
        centre = record.T_world_cam[:3, 3]
        lap("load")
        normals = grid_normals(data.points_world, data.mask, centre)
        lap("lift")
        masks = segmenter.segment(data.colors, text, threshold)
        lap("segment")
        for found in masks:
            if float(found.score) < threshold:
                continue
            points, point_normals = points_under_mask(found.mask, data.points_world, data.mask, data.confidence,
                                                      min_confidence, erode_px=erode_px, normals=normals)
            keep = trim_mask(points, camera_centre=centre)
            points, point_normals = points[keep], point_normals[keep]
            hit.masks += 1
            hit.pixels += int(np.count_nonzero(found.mask))
            detections.append(ViewDetection(frame_index=hit.frame_index, points=points, score=float(found.score),
                                            similarity=hit.similarity, pixels=int(np.count_nonzero(found.mask)),
                                            normals=point_normals, camera_centre=centre,
                                            mask=resize_mask(found.mask, data.mask.shape),
                                            background=ring_points(found.mask, data.points_world, data.mask)))
        lap("lift")
    instances = fuse_views(detections, keyframes_searched=len(hits), max_points=max_points, seed=seed, refine=refine,
                           amodal=amodal)
    lap("fuse")
    seconds["total"] = time.perf_counter() - started
    return QueryAnswer(query=text, top_k=int(top_k), threshold=float(threshold), instances=instances, keyframes=hits,
                       embedder=str(embedder.name), segmenter=str(segmenter.name), result=str(loaded.path),
                       seconds=seconds)
