"""What a run records as it goes, for the summary: every edge (odometry, loops accepted and
rejected, map segments), the frames dropped and why, frontend failures, notes, and the counts and
wall times of frames and submaps."""

from __future__ import annotations

import logging

from .edges import EdgeReport
from .progress import StageTimer
from .types import Alignment, LoopCandidate

log = logging.getLogger("sl4slam")

DROP_REASONS = ("no ground truth", "frontend failed", "graph failed")
"""Why input frames are dropped (``RunLedger.dropped`` keys, in summary order)."""


class RunLedger:
    """The record of one run.

    Attributes:
        edges: every odometry, loop (accepted or rejected) and segment record, in the order made.
        dropped: ``{reason: frames}`` input frames or keyframes lost (:data:`DROP_REASONS`).
        frontend_failures: ``{"submap", "reason", "keyframes"}`` per submap the frontend failed on.
        notes: problems the summary reports that are not edges, one line each.
        timer: seconds by stage over the whole run.
        submap_seconds: each submap's seconds by stage, in the order the submaps were done.
        submap_loops: loop factors added with each submap, in the same order.
        frames: input frames the frontend can use (read and not dropped for lack of ground truth).
        submaps: submaps done: accepted and worked on, or failed.
        failures_in_a_row: frontend failures since the last submap it reconstructed.
    """

    def __init__(self) -> None:
        self.edges: list[EdgeReport] = []
        self.dropped: dict[str, int] = {reason: 0 for reason in DROP_REASONS}
        self.frontend_failures: list[dict] = []
        self.notes: list[str] = []
        self.timer = StageTimer()
        self.submap_seconds: list[dict[str, float]] = []
        self.submap_loops: list[int] = []
        self.frames = 0
        self.submaps = 0
        self.failures_in_a_row = 0

    # ------------------------------------------------------------------ edges
    def add(self, report: EdgeReport) -> EdgeReport:
        """Record ``report``; returns it (its outcome may still be changed)."""
        self.edges.append(report)
        return report

    def reject_loop(self, candidate: LoopCandidate, old_submap: int, submap_id: int, reason: str,
                    alignment: Alignment | None = None, checks: dict | None = None) -> None:
        """Record loop ``candidate`` between ``old_submap`` and ``submap_id`` as rejected for ``reason``
        (with its measurement and check figures when it got that far)."""
        if alignment is not None:
            report = EdgeReport.measured("loop", old_submap, submap_id, candidate.match_frame, alignment,
                                         query_frame=candidate.query_frame, accepted=False, reason=reason,
                                         checks=checks or {})
        else:
            report = EdgeReport(kind="loop", submap_from=old_submap, submap_to=submap_id,
                                frame_index=candidate.match_frame, query_frame=candidate.query_frame, accepted=False,
                                reason=reason, checks=checks or {})
        self.edges.append(report)
        log.info("loop %d->%d rejected: %s", old_submap, submap_id, reason)

    def segment(self, submap_from: int, submap_to: int, frame_index: int, reason: str) -> None:
        """Record that ``submap_to`` starts a new map segment after ``submap_from`` (or could not, as
        ``reason`` says); ``frame_index`` is its shared frame (-1 without one)."""
        self.edges.append(EdgeReport(kind="segment", submap_from=submap_from, submap_to=submap_to,
                                     frame_index=frame_index, accepted=False, reason=reason))

    @property
    def num_loops(self) -> int:
        """Loops accepted so far."""
        return sum(1 for e in self.edges if e.kind == "loop" and e.accepted)

    @property
    def loops_rejected(self) -> int:
        return sum(1 for e in self.edges if e.kind == "loop" and not e.accepted)

    @property
    def fallbacks(self) -> int:
        """Accepted odometry edges that are a fallback (the shared frame's cameras, not a fit)."""
        return sum(1 for e in self.edges if e.fallback and e.accepted and e.kind == "odometry")

    def odometry_ratios(self) -> list[float]:
        """Inlier ratios of the accepted fitted odometry edges so far."""
        return [e.inlier_ratio for e in self.edges if e.kind == "odometry" and e.accepted and not e.fallback]

    # ------------------------------------------------------------------ frames and submaps
    def frontend_failed(self, submap_id: int, reason: str, keyframes: list[int]) -> None:
        """Record that the frontend failed on ``submap_id`` (its new ``keyframes``, by frame index)."""
        self.failures_in_a_row += 1
        self.frontend_failures.append({"submap": submap_id, "reason": reason, "keyframes": keyframes})

    def submap_done(self, submap_id: int, seconds: dict[str, float]) -> None:
        """Count a submap as done, with its ``seconds`` by stage and the loops it added."""
        self.submaps += 1
        for key, value in seconds.items():
            self.timer.seconds[key] += value
        self.submap_seconds.append(seconds)
        self.submap_loops.append(sum(1 for e in self.edges if e.kind == "loop" and e.accepted and e.submap_to == submap_id))
