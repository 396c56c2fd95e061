"""The window of one submap: its frames and slots (:class:`SubmapInput`), what the frontend made of
it (:class:`FrontendOutcome`), what the steps derive from the prediction once (:class:`DenseSubmap`),
and the frames consecutive windows share (:class:`SharedFrames`).

A window holds ``shared frames + new keyframes + loop frames``; a slot is a frame's position in it
(and in the frontend's prediction of it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .backend import SubmapFrames

from .errors import UserError
from .geometry import to_4x4
from .loops import LoopEvidence, grey_for_check
from .refine import window_disagreement
from .submap import SubmapConfig, confidence_mask_and_levels, submap_points
from .types import Frame, FrameView, LoopCandidate, SubmapPrediction


@dataclass
class SubmapInput:
    """The frames of one submap and where each kind sits.

    Attributes:
        submap_id: its id.
        frames: ``shared frames + new keyframes + loop frames`` (no shared frame for a first submap).
        first_new: slot of the first new keyframe (the number of shared frames).
        num_new: number of new keyframes.
        loops: the retrieved candidates whose loop frames follow the new keyframes, in order.
        unreadable: candidates whose loop frame could not be read again, with the reason (rejected
            when the submap is accepted, so that the edges keep their order however submaps overlap).
        seconds: wall time of its stages.
        loop_widths: how many frames each candidate appended (its loop frame first, then keyframes
            of the same old submap: ``SubmapConfig.loop_frames``).
    """

    submap_id: int
    frames: list[Frame]
    first_new: int
    num_new: int
    loops: list[LoopCandidate]
    unreadable: list[tuple[LoopCandidate, str]] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    loop_widths: list[int] = field(default_factory=list)

    @property
    def shared(self) -> Frame | None:
        """The first frame shared with the previous submap (``None`` for a first submap)."""
        return self.frames[0] if self.first_new else None

    def opening_slots(self, overlap: int) -> range:
        """Slots of the frames that open the next submap: the last ``overlap`` of its keyframes."""
        return range(max(0, self.last_slot + 1 - overlap), self.last_slot + 1)

    @property
    def new_slots(self) -> range:
        return range(self.first_new, self.first_new + self.num_new)

    @property
    def last_slot(self) -> int:
        return self.first_new + self.num_new - 1

    @property
    def new_frames(self) -> list[Frame]:
        """The new keyframes, in order."""
        return self.frames[self.first_new:self.last_slot + 1]

    def loop_slots(self, k: int) -> range:
        """Slots of candidate ``k``'s frames: its loop frame, then its companions."""
        start = self.first_new + self.num_new + sum(self.loop_widths[:k])
        return range(start, start + self.loop_widths[k])

    def loop_slot(self, k: int) -> int:
        """Slot of candidate ``k``'s loop frame."""
        return self.loop_slots(k).start

    def slot_of(self, frame_index: int) -> int:
        return next(s for s in self.new_slots if self.frames[s].index == frame_index)

    def match_pairs(self) -> list[tuple[int, int]]:
        """``(query keyframe slot, loop frame slot)`` of every loop candidate (the query first, as in
        VGGT-SLAM 2.0's attention check)."""
        return [(self.slot_of(c.query_frame), self.loop_slot(k)) for k, c in enumerate(self.loops)]

    def add_retrieval_seconds(self, start: float, describe: float) -> None:
        """Add the wall time since ``start`` (``time.perf_counter``) to the retrieval's seconds,
        ``describe`` seconds of it (descriptor extraction, a model like the frontend) apart from
        the search."""
        self.seconds["retrieval_describe"] = self.seconds.get("retrieval_describe", 0.0) + describe
        self.seconds["retrieval"] = self.seconds.get("retrieval", 0.0) + time.perf_counter() - start - describe

    def with_shared(self, shared: list[Frame]) -> SubmapInput:
        """The same window opened by ``shared`` instead: the same new keyframes and loop frames."""
        return SubmapInput(self.submap_id, list(shared) + self.frames[self.first_new:], len(shared), self.num_new,
                           self.loops, self.unreadable, dict(self.seconds), list(self.loop_widths))


@dataclass
class Anticipation:
    """What handing a window on before its forward ran changed (``SLAMPipeline.anticipate``), to undo it.

    Attributes:
        submap_id: the window's submap id.
        retrieval: the retrieval's mark before the window's keyframes were added (``None``: no retrieval).
        shared: the shared frames the next window had before.
    """

    submap_id: int
    retrieval: Any
    shared: list[Frame]


@dataclass
class FrontendOutcome:
    """What the frontend made of one submap: its prediction, or why it failed.

    Attributes:
        prediction: the prediction (``None`` when it failed).
        problem: why it cannot be used (an exception, wrong frame count, non-finite values).
        error: a ``UserError`` it raised (a problem of the settings: it ends the run).
        seconds: wall time of the forward.
    """

    prediction: SubmapPrediction | None
    problem: str | None = None
    error: UserError | None = None
    seconds: float = 0.0


@dataclass
class DenseSubmap:
    """The frontend's prediction of a submap with what the steps derive from it once.

    Attributes:
        prediction: the frontend's output.
        T_cam_submap: ``(S, 4, 4)`` float64 its extrinsics.
        mask: ``(S, H, W)`` confident pixels (``SubmapConfig.tau_conf``).
        levels: the submap's confidence quantiles (``sl4slam.submap.confidence_levels``).
        views: ``{slot: FrameView}`` for the frames that are aligned (points at full precision): the
            shared frames, the frames that open the next submap and the loop frames.
    """

    prediction: SubmapPrediction
    T_cam_submap: np.ndarray
    mask: np.ndarray
    levels: np.ndarray
    views: dict[int, FrameView]

    @classmethod
    def of(cls, work: SubmapInput, prediction: SubmapPrediction, settings: SubmapConfig) -> DenseSubmap:
        """Confidence masks for the window, and points for the frames that are aligned: the shared
        frames, the frames that open the next submap and the loop frames (the map is rebuilt from
        stored depth, so no other frame needs points now)."""
        mask, levels = confidence_mask_and_levels(prediction.confidence, prediction.depth, settings.tau_conf)
        T_cam_submap = to_4x4(prediction.T_cam_submap)
        needed = sorted({0, *range(work.first_new), *work.opening_slots(settings.overlap),
                         *range(work.last_slot + 1, len(work.frames))})
        points = submap_points(prediction, settings.use_point_head, needed)
        views = {slot: FrameView(points[k], mask[slot], prediction.K[slot], T_cam_submap[slot])
                 for k, slot in enumerate(needed)}
        return cls(prediction, T_cam_submap, mask, levels, views)

    def submap_frames(self, work: SubmapInput, agreement: bool = False) -> SubmapFrames:
        """The window's shared frames (when it has any) and new keyframes with their extrinsics, as
        the graph takes them; with ``agreement``, how far those frames disagree about their surfaces
        (:func:`sl4slam.refine.window_disagreement` over the confident pixels)."""
        slots = list(range(work.first_new)) + list(work.new_slots)
        disagreement = None
        if agreement:
            prediction = self.prediction
            # the leading frames as views where they are (no copy of the window's depth maps)
            frames = slice(0, len(slots)) if slots == list(range(len(slots))) else slots
            disagreement = window_disagreement(prediction.depth[frames], prediction.K[frames],
                                               self.T_cam_submap[frames], self.mask[frames])
        return SubmapFrames(tuple(work.frames[slot].index for slot in slots), self.T_cam_submap[slots],
                            shared=work.first_new, disagreement=disagreement)

    def loop_evidence(self, work: SubmapInput, k: int, stored: Callable[[int], FrameView]) -> LoopEvidence:
        """What the window says about loop candidate ``k``; ``stored(frame_index)`` is a frame's view
        as stored in its old submap."""
        candidate = work.loops[k]
        slot, query = work.loop_slot(k), work.slot_of(candidate.query_frame)
        prediction = self.prediction
        pairs = [(stored(work.frames[s].index), self.views[s]) for s in work.loop_slots(k)]
        return LoopEvidence(
            pairs=pairs,
            grey_new=grey_for_check(prediction.colors[slot]), query_depth=prediction.depth[query],
            query_mask=self.mask[query], query_grey=grey_for_check(prediction.colors[query]),
            query_K=prediction.K[query], query_T_cam_submap=self.T_cam_submap[query],
            match_ratio=recorded_match_ratio(prediction, query, slot))


@dataclass
class SharedFrames:
    """The frames consecutive windows share.

    Attributes:
        next: the next window's shared frames: the opening frames of the last accepted submap.
        held: the opening frames of the last submap the graph holds (the next window shares these
            instead when the graph drops a submap).
        views: ``{frame index: FrameView}`` of ``held`` at full precision, as their submap
            reconstructed them.
    """

    next: list[Frame] = field(default_factory=list)
    held: list[Frame] = field(default_factory=list)
    views: dict[int, FrameView] = field(default_factory=dict)


def recorded_match_ratio(prediction: SubmapPrediction, first: int, second: int) -> float | None:
    """The frontend's image-match ratio of slots ``(first, second)``, or ``None`` when it gave none."""
    if prediction.match_pairs is None or prediction.match_ratios is None:
        return None
    hits = np.flatnonzero((np.asarray(prediction.match_pairs) == (first, second)).all(axis=1))
    return float(prediction.match_ratios[hits[0]]) if len(hits) else None


def prediction_problem(prediction: SubmapPrediction, num_frames: int) -> str | None:
    """Why a frontend's output cannot be used (wrong frame count, non-finite values), or ``None``."""
    S = prediction.depth.shape[0]
    if S != num_frames:
        return f"it returned {S} frames for a submap of {num_frames}"
    for name in ("depth", "confidence", "T_cam_submap", "K"):
        if not np.all(np.isfinite(getattr(prediction, name))):
            return f"it returned non-finite {name}"
    return None
