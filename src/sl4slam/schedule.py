"""When each step of a submap runs: one after the other, or the model overlapping the graph work.

A submap goes through four steps of a :class:`SubmapSteps` (``sl4slam.pipeline.SLAMPipeline``):

- A, ``assemble``: the shared frame, the new keyframes and the loop frames retrieval proposes;
- F, ``run_frontend``: the model's forward (the expensive part; it touches no pipeline state);
- R, ``accept``: the outcome taken: the keyframes handed to retrieval and the last one made the next
  submap's shared frame, or the failure booked;
- S, ``integrate``: points, odometry, graph, loop checks and the stored keyframes.

Dependencies: A(k+1) needs R(k) (retrieval must hold submap k, and the shared frame comes from it);
F(k+1) needs A(k+1); S(k) needs R(k). Nothing else: S(k) neither reads nor changes what A(k+1) and
F(k+1) use (loop candidates come from submaps at least ``tau_interval`` >= 1 older, which S has
stored long before; rejected loop frames are booked at R). So F(k+1) can run in a worker while
S(k) runs, and the results are the same as one step after the other, byte for byte
(``tests/test_schedule.py``). The one exception is a submap that the graph cannot take at all (S
drops it): the next submap shares another frame then, so its frames are rebuilt and its forward
is run again (:meth:`OverlappedScheduler._reframe`).

The overlapped scheduler keeps a bounded queue: at most one submap waiting for the model and one
in it; keyframe selection (the caller) waits when both are taken. A forward cannot be
interrupted: on Ctrl-C the worker is left to finish in the background (a daemon thread) while the
run writes what it has.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Protocol, Sequence

from .types import Frame, SubmapPrediction
from .window import Anticipation, FrontendOutcome, SubmapInput


class SubmapSteps(Protocol):
    """What a scheduler needs of the pipeline: the steps of one submap (see the module doc)."""

    def process_submap(self, new_frames: Sequence[Frame]) -> None:
        """Every step of one submap, in order."""

    def assemble(self, new_frames: Sequence[Frame]) -> SubmapInput:
        """A: the submap's window."""

    def run_frontend(self, work: SubmapInput) -> FrontendOutcome:
        """F: the frontend's forward (touches no pipeline state)."""

    def accept(self, work: SubmapInput, outcome: FrontendOutcome) -> SubmapPrediction | None:
        """R: the outcome taken; the prediction, or ``None`` when the frontend failed."""

    def integrate(self, work: SubmapInput, prediction: SubmapPrediction) -> bool:
        """S: the graph work; ``False`` when the graph dropped the submap."""

    def reframe(self, work: SubmapInput) -> SubmapInput:
        """``work`` on the current shared frame (after the submap before it was dropped)."""


    def anticipate(self, work: SubmapInput) -> Anticipation:
        """R's hand-on (retrieval and shared frames) before F has run; see :class:`AheadScheduler`."""

    def withdraw(self, anticipation: Anticipation) -> None:
        """Undo :meth:`anticipate` (and the assembly of every window after it)."""

    def reshare(self, works: Sequence[SubmapInput]) -> list[SubmapInput]:
        """The windows handed on after a dropped submap, opened by the frames the graph holds."""

    @property
    def next_submap_id(self) -> int:
        """The id the next :meth:`assemble` gives."""


def make_scheduler(pipeline: SubmapSteps, overlap: bool, ahead: int = 1, tau_interval: int = 1) -> "SequentialScheduler":
    """The scheduler of a run: ``ahead`` > 1 windows in the model at once (:class:`AheadScheduler`,
    ``SLAMConfig.workers``), else overlapped when ``overlap`` (``SLAMConfig.overlap``, settled by
    ``sl4slam.resolve``), else sequential."""
    if ahead > 1:
        return AheadScheduler(pipeline, ahead, tau_interval)
    return OverlappedScheduler(pipeline) if overlap else SequentialScheduler(pipeline)


class SequentialScheduler:
    """Every step of a submap as soon as its keyframes are selected: A, F, R, S."""

    def __init__(self, pipeline: SubmapSteps) -> None:
        self.pipeline = pipeline

    def submit(self, new_frames: Sequence[Frame]) -> None:
        """The new keyframes of the next submap."""
        self.pipeline.process_submap(list(new_frames))

    def poll(self) -> None:
        """Do whatever can be done without waiting (nothing is ever pending here)."""

    def drain(self) -> None:
        """Finish every submap submitted."""

    def close(self) -> None:
        """Release the worker (none here)."""


class _Forward:
    """One forward in a daemon thread; its outcome is read once it is done."""

    def __init__(self, pipeline: SubmapSteps, work: SubmapInput) -> None:
        self.work = work
        self.outcome: FrontendOutcome | None = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(pipeline,), name=f"sl4slam-frontend-{work.submap_id}",
                                        daemon=True)
        self._thread.start()

    def _run(self, pipeline: SubmapSteps) -> None:
        try:
            self.outcome = pipeline.run_frontend(self.work)
        finally:
            self._done.set()

    def done(self) -> bool:
        return self._done.is_set()

    def result(self) -> FrontendOutcome:
        self._done.wait()
        if self.outcome is None:  # run_frontend catches every exception of the model; only a bug gets here
            raise RuntimeError(f"the frontend worker of submap {self.work.submap_id} ended without an outcome")
        return self.outcome


class OverlappedScheduler(SequentialScheduler):
    """The model of the next submap runs while the graph works on this one (see the module doc).

    Attributes:
        waiting: batches of new keyframes selected but not yet assembled (at most one).
        running: the forward in the worker, if any.
    """

    def __init__(self, pipeline: SubmapSteps) -> None:
        super().__init__(pipeline)
        self.waiting: deque[list[Frame]] = deque()
        self.running: _Forward | None = None

    def submit(self, new_frames: Sequence[Frame]) -> None:
        self.waiting.append(list(new_frames))
        self.poll()
        while len(self.waiting) > 1:  # the bound: keyframe selection waits for the model
            self._advance(block=True)

    def poll(self) -> None:
        while self._advance(block=False):
            pass

    def drain(self) -> None:
        while self._pending():
            self._advance(block=True)

    def _pending(self) -> bool:
        """Whether a submitted submap is not yet done."""
        return self.running is not None or bool(self.waiting)

    def close(self) -> None:
        """Forget what is left (after an error or Ctrl-C): a forward still running finishes in its
        daemon thread, unread."""
        self.running = None
        self.waiting.clear()

    def _advance(self, block: bool) -> bool:
        """One step of the schedule; whether anything happened."""
        if self.running is None:
            if not self.waiting:
                return False
            self._start(self.waiting.popleft())
            return True
        if not (block or self.running.done()):
            return False
        forward, self.running = self.running, None
        prediction = self.pipeline.accept(forward.work, forward.result())  # R(k)
        if self.waiting:
            self._start(self.waiting.popleft())  # A(k+1), F(k+1) in the worker ...
        if prediction is not None and not self.pipeline.integrate(forward.work, prediction):  # ... while S(k) runs here
            self._reframe()
        return True

    def _start(self, new_frames: list[Frame]) -> None:
        self.running = _Forward(self.pipeline, self.pipeline.assemble(new_frames))

    def _reframe(self) -> None:
        """The graph dropped the submap the running one shares a frame with: rebuild the running
        submap on the frame the graph holds and run its forward again."""
        if self.running is None:
            return
        stale = self.running
        stale.result()  # its outcome belongs to frames that are no longer the submap's
        self.running = _Forward(self.pipeline, self.pipeline.reframe(stale.work))


class _Window:
    """An assembled, handed-on window whose forward runs in a thread (that waits on a worker)."""

    def __init__(self, pipeline: SubmapSteps, work: SubmapInput, anticipation: Anticipation) -> None:
        self.work = work
        self.anticipation = anticipation
        self.forward = _Forward(pipeline, work)

    def restart(self, pipeline: SubmapSteps, work: SubmapInput) -> None:
        """Run the forward again on ``work`` (the same submap opened by other frames)."""
        self.work = work
        self.forward = _Forward(pipeline, work)


class AheadScheduler(OverlappedScheduler):
    """Up to ``ahead`` windows in the model at once (on worker processes or a Ray cluster, through
    the frontend), the graph taking them in order; the results are those of one submap after the
    other, byte for byte.

    A window's step R (the retrieval holds its keyframes, the next window shares its last one)
    depends only on its frames, as long as its forward succeeds: so it is taken as soon as the window
    is assembled (``anticipate``), and the next window can be assembled at once. A forward that
    fails is rare; then R is undone (``withdraw``: the retrieval rewinds to its mark) and the windows
    assembled after it are assembled again. A window also needs every submap that may lend it a loop
    frame to be stored: those at least ``tau_interval`` + 1 older. So at most ``tau_interval`` + 1
    windows are ever ahead of the graph, whatever ``ahead`` is. When the graph drops a submap, the
    windows after it that share its frame are opened by the frame the graph holds and their forwards
    run again (``reshare``).

    Attributes:
        waiting: batches of new keyframes selected but not yet assembled.
        flight: the assembled windows, in submap order (the first is the next the graph takes).
        settled: every submap up to this id is integrated or failed.
    """

    def __init__(self, pipeline: SubmapSteps, ahead: int, tau_interval: int) -> None:
        super().__init__(pipeline)
        self.ahead = max(1, int(ahead))
        self.tau_interval = int(tau_interval)
        self.flight: deque[_Window] = deque()
        self.settled = -1

    def _pending(self) -> bool:
        return bool(self.flight) or bool(self.waiting)

    def close(self) -> None:
        """Forget what is left: forwards still running finish in their threads, unread."""
        self.flight.clear()
        self.waiting.clear()

    def _may_assemble(self) -> bool:
        """Whether the next window may be assembled now: a worker is free, and every submap that may
        lend it a loop frame is settled."""
        following = self.pipeline.next_submap_id
        return bool(self.waiting) and len(self.flight) < self.ahead and following - 1 - self.tau_interval <= self.settled

    def _launch(self) -> None:
        work = self.pipeline.assemble(self.waiting.popleft())
        self.flight.append(_Window(self.pipeline, work, self.pipeline.anticipate(work)))

    def _advance(self, block: bool) -> bool:
        """One step of the schedule; whether anything happened."""
        if self._may_assemble():
            self._launch()
            return True
        if not self.flight or not (block or self.flight[0].forward.done()):
            return False
        head = self.flight.popleft()
        outcome = head.forward.result()
        if outcome.problem is not None:
            self._failed(head, outcome)
            return True
        prediction = self.pipeline.accept(head.work, outcome, anticipated=True)  # R(k), its ledger part
        while self._may_assemble():  # the next windows go to the model while S(k) runs
            self._launch()
        if prediction is not None and not self.pipeline.integrate(head.work, prediction):
            self._dropped()
        self.settled = head.work.submap_id
        return True

    def _failed(self, head: _Window, outcome: FrontendOutcome) -> None:
        """The forward of ``head`` failed: undo its hand-on, put the windows after it back in line
        (assembled again later, on the retrieval without it), then book the failure."""
        later, self.flight = list(self.flight), deque()
        self.pipeline.withdraw(head.anticipation)
        self.waiting.extendleft(reversed([window.work.new_frames for window in later]))
        self.settled = head.work.submap_id
        self.pipeline.accept(head.work, outcome, anticipated=True)

    def _dropped(self) -> None:
        """The graph dropped the submap just integrated: the windows after it are opened by the frames
        the graph holds (those whose frames change run their forwards again)."""
        changed = self.pipeline.reshare([window.work for window in self.flight])
        for window, work in zip(self.flight, changed):
            if work is not window.work:
                window.restart(self.pipeline, work)
