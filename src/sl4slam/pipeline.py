"""The orchestrator: frames -> keyframes -> submaps -> alignment -> factor graph -> poses and map.

It is given its stages (``sl4slam.compose.build_stages`` makes them from the resolved config) and
talks to each through its interface only (``sl4slam.types``, ``sl4slam.backend.interface``): the
frontend (a model, the simulator, a replayed cache), retrieval (SALAD, ORB, none), the aligner
(SL(4), calibration-and-scale or Sim(3)), the graph (submap or keyframe design) and the loop
verifier. ``process_submap`` reads as the list of steps of one submap; each step is a method
below it. The metric frame (completing planar links while the run goes on, the upgrade at the
end) is ``sl4slam.metric_frame``; the result and its outputs are ``sl4slam.result``. See
docs/architecture.md.

Nothing that goes wrong inside a submap ends a run:

- the frontend fails (an exception or non-finite output): the submap is skipped and its keyframes
  are lost; the next submap still shares a frame with the last good one. ``max_frontend_failures``
  failures in a row end the run, with what was done returned. A ``UserError`` from the frontend
  (a replayed cache that does not match, a submap that cannot fit the memory budget) is a problem
  of the settings, not of the frames: it ends the run at once, with its line;
- the odometry fit fails or fails its checks (``sl4slam.edges``): the shared frame's camera edge
  (its two cameras and depth ratio) takes its place with an inflated sigma, listed as a fallback;
- that is unusable too (the frontend's cameras are implausible), or GTSAM cannot solve the graph
  with the new edge: the submap starts a new map segment — its node gets a weak prior at the
  previous node's estimate instead of an odometry factor, so the trajectory continues, later loops
  can join the segments, and the summary lists where each segment starts and why; if even that
  update fails, the submap is dropped like a failed frontend's;
- anything goes wrong with a loop candidate (an unreadable loop frame, a failed alignment, a check
  that fails, a graph update that fails): the loop is rejected and listed with its reason;
- the final polish of the graph fails (a singular node): the result uses iSAM2's estimate, and the
  summary says so.
"""

from __future__ import annotations

import bisect
import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np

from .backend import Backend, BackendUpdateError, SubmapFrames, WorldEstimate
from .backend.evidence import NoiseScale, edge_information, link_scatter
from .compose import _BUILD, build_stages
from .config import SLAMConfig, SourceConfig
from .edges import EdgeReport, camera_problem, edge_problem, is_camera_link
from .errors import UserError
from .geometry import normalize_sl4, to_4x4
from .keyframes import KeyframeSelector
from .loops import LoopEvidence, LoopVerifier, grey_for_check
from .metric_frame import MetricFrame
from .progress import Progress, StageTimer
from .resolve import ResolvedConfig, resolve
from .result import SLAMResult, SourceColors, keyframe_cameras
from .source_knowledge import SourceKnowledge
from .submap import StoredKeyframe, confidence_levels, confidence_mask, submap_points
from .types import (Aligner, Alignment, Frame, FrameSource, FrameView, Frontend, FrontendCapabilities, LoopCandidate,
                    Retrieval, SubmapPrediction)

log = logging.getLogger("sl4slam")


class FrontendFailedError(UserError):
    """The frontend failed on ``max_frontend_failures`` submaps in a row."""


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

    def loop_slots(self, k: int) -> range:
        """Slots of candidate ``k``'s frames: its loop frame, then its companions."""
        start = self.first_new + self.num_new + sum(self.loop_widths[:k])
        return range(start, start + self.loop_widths[k])

    def loop_slot(self, k: int) -> int:
        """Slot of candidate ``k``'s loop frame."""
        return self.loop_slots(k).start

    def slot_of(self, frame_index: int) -> int:
        return next(s for s in self.new_slots if self.frames[s].index == frame_index)


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


def source_problem(source: FrameSource, capabilities: FrontendCapabilities, frontend_name: str,
                   settings: SourceConfig | None = None) -> str | None:
    """Why a run cannot use ``source`` with this frontend and these ``[source]`` settings (too few
    frames, no ground truth for a frontend that reads it, no depth images for the sensor's scale),
    or ``None``; checked before any frame is read."""
    if len(source) < 2:
        return f"{source.name}: {len(source)} frame(s) found; SLAM needs at least 2 frames"
    if capabilities.needs_ground_truth and not source.has_ground_truth:
        return (f"{source.name} has no depth and ground-truth poses, which the {frontend_name} frontend needs (an RGB-D "
                "sequence: TUM, 7-Scenes or the synthetic world); use a model (--model vggt)")
    if settings is not None and settings.metric_depth == "sensor" and not source.has_ground_truth:
        return (f"--metric-depth sensor needs depth images, which {source.name} has not (an RGB-D sequence: TUM, "
                "7-Scenes); use --metric-depth off")
    return None


class SLAMPipeline:
    """VGGT-SLAM over a frame source.

    Args:
        config: the run's settings (a ``SLAMConfig`` is resolved here: ``sl4slam.resolve``).
        frontend, retrieval, aligner, backend: stages that replace the ones the config names
            (``retrieval=None``: no loop closure; see ``sl4slam.compose.build_stages``).
        on_submap: called as ``on_submap(pipeline, submap_id)`` after every processed submap.

    Example::

        config = SLAMConfig(frontend="simulated")
        config.sim.profile = "vggt"
        result = SLAMPipeline(config).run(open_source("rgbd_dataset_freiburg1_xyz", config.source))
    """

    def __init__(self, config: SLAMConfig | ResolvedConfig, frontend: Frontend | None = None, retrieval: Any = _BUILD,
                 aligner: Aligner | None = None, backend: Backend | None = None,
                 on_submap: Callable[["SLAMPipeline", int], None] | None = None) -> None:
        # a frontend given here is resolved with its own capabilities (an explicit attention check it
        # cannot feed is refused, "auto" runs without it)
        self.resolved = resolve(config, capabilities=frontend.capabilities if frontend is not None else None)
        self.config = self.resolved.config
        stages = build_stages(self.resolved, frontend, retrieval, aligner, backend)
        self.frontend: Frontend = stages.frontend
        self.retrieval: Retrieval | None = stages.retrieval
        self.aligner: Aligner = stages.aligner
        self.backend: Backend = stages.backend
        if self.aligner.group == "sl4" and self.backend.kind != "sl4":
            raise UserError(f"the {self.aligner.model} aligner measures projective transforms, which a "
                            f"{self.backend.kind} graph cannot hold; use a Sim(3) alignment model")
        attention = self.resolved.attention_check and self.frontend.capabilities.scores_pairs
        self.noise_scale = NoiseScale()  # how much the edges understate their noise (several shared frames tell)
        self.loop_verifier = LoopVerifier(self.config.loops, self.config.alignment, self.aligner, self.backend,
                                          self.edge_information, attention=attention, noise_scale=self.noise_scale)
        self.metric_frame = MetricFrame(self.config.upgrade, self.backend, self.resolved.metric_upgrade,
                                        self.resolved.complete_links)
        self.selector = KeyframeSelector(self.config.keyframes)
        self.on_submap = on_submap
        self.keyframes: list[StoredKeyframe] = []
        self._by_frame: dict[int, StoredKeyframe] = {}
        self.edges: list[EdgeReport] = []
        self.timer = StageTimer()
        self.submap_seconds: list[dict[str, float]] = []
        self.submap_loops: list[int] = []  # loop factors added with each submap
        self.num_submaps = 0  # submaps done: accepted and worked on, or failed
        self._next_submap_id = 0  # submap ids handed out (one may be in the model)
        self.num_frames = 0
        self.dropped: dict[str, int] = {"no ground truth": 0, "frontend failed": 0, "graph failed": 0}
        self.frontend_failures: list[dict] = []
        self.notes: list[str] = []  # problems the summary reports that are not edges
        self.stop_requested = False
        self._failures_in_a_row = 0
        self._gt: dict[int, np.ndarray] = {}
        self._shared: list[Frame] = []  # the next submap's shared frames: the last keyframes of the last accepted submap
        self._last_stored: list[Frame] = []  # the last keyframes the graph holds
        self._shared_views: dict[int, FrameView] = {}  # ... at full precision, as their submap reconstructed them
        self._source: FrameSource | None = None
        self._frames_read = 0
        self.knowledge = SourceKnowledge(self.config, self.frontend)  # consume() makes the source's own
        self._reporter = Progress(None, enabled=False)  # consume() makes the run's own
        self.colors: SourceColors | None = None  # the keyframes' colours, re-read from the source

    # ------------------------------------------------------------------ driving
    def run(self, source: FrameSource, progress: bool = True) -> SLAMResult:
        """Process every frame of ``source`` (or until :attr:`stop_requested`) and return the result."""
        self.consume(source, progress)
        return self.result()

    def consume(self, source: FrameSource, progress: bool = True) -> None:
        """Feed the frames of ``source`` through keyframe selection and submaps (no final result).
        The source applies ``[source]`` stride and max_frames (``sl4slam.io.open_source``); the
        submaps are scheduled by ``sl4slam.schedule`` (the next submap's frontend overlapping this
        one's graph work when ``overlap`` is on, with the same results).

        Raises ``UserError`` for a source the frontend cannot use, and :class:`FrontendFailedError`
        when the frontend keeps failing (what was processed stays in the pipeline).
        """
        from .schedule import make_scheduler

        problem = source_problem(source, self.frontend.capabilities, self.frontend.name, self.config.source)
        if problem:
            raise UserError(problem)
        self.knowledge = SourceKnowledge(self.config, self.frontend, source)
        self.colors = SourceColors(source, self.frontend)
        self._source = source
        pending: list[Frame] = []
        self._reporter = Progress(len(source), enabled=progress, every=self.config.output.progress_every, per_submap=True)
        scheduler = make_scheduler(self, overlap=self.resolved.overlap)
        try:
            for frame in source:
                if self.stop_requested:
                    break
                self._frames_read += 1
                if self._select(frame):
                    pending.append(frame)
                if len(pending) == self.config.submap.size:
                    scheduler.submit(pending)
                    pending = []
                scheduler.poll()
                self._reporter.frame(self._frames_read, keyframes=len(self.keyframes) + len(pending),
                                     submaps=self.num_submaps, loops=self.num_loops)
            if pending and not self.stop_requested:
                scheduler.submit(pending)
            scheduler.drain()
        finally:
            scheduler.close()
            self._reporter.close()
        if len(self.keyframes) < 2 and not self.stop_requested:
            raise UserError(
                f"{source.name}: only {len(self.keyframes)} keyframe(s) selected from {self.num_frames} frames; "
                "the camera barely moves — lower --tau-disparity or use a longer sequence"
            )

    def _select(self, frame: Frame) -> bool:
        """Keyframe decision for one input frame (frames the frontend cannot use are dropped)."""
        if self.frontend.capabilities.needs_ground_truth and (
                frame.depth is None or frame.T_world_cam is None or frame.K is None):
            self.dropped["no ground truth"] += 1  # e.g. TUM frames without depth within 0.02 s
            return False
        self.num_frames += 1
        with self.timer("keyframes"):
            is_keyframe = self.selector.is_keyframe(frame.rgb)
        if is_keyframe and frame.T_world_cam is not None:
            self._gt[frame.index] = np.asarray(frame.T_world_cam, dtype=np.float64)
        return is_keyframe

    @property
    def num_loops(self) -> int:
        return sum(1 for e in self.edges if e.kind == "loop" and e.accepted)

    # ------------------------------------------------------------------ one submap
    def process_submap(self, new_frames: Sequence[Frame]) -> None:
        """Reconstruct, align and optimize one submap of new keyframes (the steps in order; the
        scheduler runs the same steps with the frontend of the next submap overlapping)."""
        work = self.assemble(new_frames)
        prediction = self.accept(work, self.run_frontend(work))
        if prediction is not None:
            self.finish(work, prediction)

    def assemble(self, new_frames: Sequence[Frame]) -> SubmapInput:
        """The submap's frames: the shared frame, the new keyframes, and the loop frames that
        retrieval proposes (a loop frame that cannot be re-read is rejected when the submap is
        accepted). Needs the retrieval to hold every earlier accepted submap."""
        start = time.perf_counter()
        described = self.retrieval.describe_seconds if self.retrieval is not None else 0.0
        submap_id = self._next_submap_id
        self._next_submap_id += 1
        candidates: list[LoopCandidate] = []
        if self.retrieval is not None and self.config.submap.w_loop > 0:
            proposed = self.retrieval.query(list(new_frames), submap_id, self.config.submap.w_loop)
            candidates = [c for c in proposed[: self.config.submap.w_loop] if c.match_frame in self._by_frame]
        shared = list(self._shared)
        frames, loops, unreadable, widths = shared + list(new_frames), [], [], []
        for candidate in candidates:
            try:
                loop_frames = [self._source.get(candidate.match_frame)]
            except UserError as exc:
                unreadable.append((candidate, f"the loop frame cannot be read again: {exc}"))
                continue
            present = {f.index for f in frames} | {candidate.match_frame}
            for companion in self._loop_companions(candidate.match_frame):
                if companion in present:  # already in this window: never give the model a frame twice
                    continue
                try:
                    loop_frames.append(self._source.get(companion))
                except UserError:  # the loop frame alone still measures the loop
                    continue
            frames += loop_frames
            loops.append(candidate)
            widths.append(len(loop_frames))
        work = SubmapInput(submap_id, frames, len(shared), len(new_frames), loops, unreadable, loop_widths=widths)
        self._time_retrieval(work, start, described)
        return work

    def reframe(self, work: SubmapInput) -> SubmapInput:
        """``work`` with the current shared frame (after the submap before it was dropped): the same
        new keyframes and loop frames, so that the retrieval is not asked again."""
        shared = list(self._shared)
        return SubmapInput(work.submap_id, shared + work.frames[work.first_new:], len(shared), work.num_new,
                           work.loops, work.unreadable, dict(work.seconds), list(work.loop_widths))

    def run_frontend(self, work: SubmapInput) -> FrontendOutcome:
        """The frontend's prediction of ``work`` (touches no pipeline state: it may run in a worker)."""
        keywords: dict = {}
        pairs = self._match_pairs(work)
        if pairs:  # only frontends asked for attention scores need to know the keyword
            keywords["match_pairs"] = pairs
        known_K = self.knowledge.model_intrinsics(len(work.frames))
        if known_K is not None:
            keywords["intrinsics"] = known_K
        start = time.perf_counter()
        try:
            prediction = self.frontend.reconstruct(work.frames, work.submap_id, **keywords)
            outcome = FrontendOutcome(prediction, prediction_problem(prediction, len(work.frames)))
        except UserError as exc:  # a problem of the settings (a cache that does not match, a memory budget)
            outcome = FrontendOutcome(None, str(exc), error=exc)
        except Exception as exc:  # a failing model must not end the run: the submap is skipped
            outcome = FrontendOutcome(None, f"{type(exc).__name__}: {exc}")
        outcome.seconds = time.perf_counter() - start
        return outcome

    def accept(self, work: SubmapInput, outcome: FrontendOutcome) -> SubmapPrediction | None:
        """Take the frontend's outcome: the prediction, whose keyframes the retrieval now holds and
        whose last keyframe the next submap shares; or ``None`` when it failed (see the module doc)."""
        work.seconds["frontend"] = outcome.seconds
        for candidate, reason in work.unreadable:
            self._reject_loop(candidate, work.submap_id, reason)
        if outcome.error is not None:
            raise outcome.error  # its line, at once
        if outcome.problem is None:
            self._failures_in_a_row = 0
            self._shared = [work.frames[slot] for slot in work.opening_slots(self.config.submap.overlap)]
            start = time.perf_counter()
            described = self.retrieval.describe_seconds if self.retrieval is not None else 0.0
            if self.retrieval is not None:
                self.retrieval.add(work.frames[work.first_new:work.last_slot + 1], work.submap_id)
            self._time_retrieval(work, start, described)
            return outcome.prediction
        self._failures_in_a_row += 1
        self._drop(work, "frontend failed")
        self.frontend_failures.append({"submap": work.submap_id, "reason": outcome.problem,
                                       "keyframes": [f.index for f in work.frames[work.first_new:work.last_slot + 1]]})
        log.warning("submap %d: the frontend failed (%s); its %d keyframes are skipped", work.submap_id, outcome.problem,
                    work.num_new)
        self._account(work)
        if self._failures_in_a_row >= self.config.max_frontend_failures:
            raise FrontendFailedError(
                f"the frontend failed on {self._failures_in_a_row} submaps in a row (last: {outcome.problem}); "
                "check the model weights and the input frames")
        return None

    def finish(self, work: SubmapInput, prediction: SubmapPrediction) -> bool:
        """The graph work of an accepted submap: points, odometry, graph, loops, store. ``False`` when
        the graph could not take it (it is dropped, and the next submap shares the frame before it)."""
        timer = StageTimer()
        with timer("points"):
            prediction = self.knowledge.apply(work.frames, prediction)
            dense = self.dense_submap(work, prediction)
        with timer("alignment"):
            odometry = self.align_odometry(work, dense)
        with timer("backend"):
            added = self.add_to_graph(work, dense, odometry)
        if added:
            with timer("loops"):
                self.close_loops(work, dense)
            with timer("store"):
                self.store(work, dense)
        else:
            self._shared = self._last_stored  # the next submap shares the last frame the graph holds
        work.seconds.update(timer.seconds)
        self._account(work)
        return added

    def dense_submap(self, work: SubmapInput, prediction: SubmapPrediction) -> DenseSubmap:
        """Confidence masks for the submap, and points for the frames that are aligned: the shared
        frame, the last new keyframe (shared with the next submap) and the loop frames. The map is
        rebuilt from stored depth, so no other frame needs points now."""
        mask = confidence_mask(prediction.confidence, prediction.depth, self.config.submap.tau_conf)
        T_cam_submap = to_4x4(prediction.T_cam_submap)
        needed = sorted({0, *range(work.first_new), *work.opening_slots(self.config.submap.overlap),
                         *range(work.last_slot + 1, len(work.frames))})
        points = submap_points(prediction, self.config.submap.use_point_head, needed)
        views = {slot: FrameView(points[k], mask[slot], prediction.K[slot], T_cam_submap[slot])
                 for k, slot in enumerate(needed)}
        return DenseSubmap(prediction, T_cam_submap, mask, confidence_levels(prediction.confidence, prediction.depth), views)

    def align_odometry(self, work: SubmapInput, dense: DenseSubmap) -> Alignment | str | None:
        """The measurement to the previous submap from the shared frames (all of them, robustly:
        ``Aligner.align_frames``): the fit, else the first shared frame's camera edge (as a
        fallback), else the reason neither can be used. ``None`` for a first submap."""
        if not work.first_new:
            return None
        pairs = [(self._shared_views[work.frames[slot].index], dense.views[slot]) for slot in range(work.first_new)]
        problems = [camera_problem(before) or camera_problem(after) for before, after in pairs]
        pairs = [pair for pair, problem in zip(pairs, problems) if not problem]
        if not pairs:
            return problems[0]
        before, after = pairs[0]
        try:
            alignment = self.aligner.align_frames(pairs, seed=work.submap_id)
            problem = edge_problem(alignment, self.config.alignment)
        except ValueError as exc:
            problem = str(exc)
        if problem is None:
            if len(alignment.extras.get("per_frame", ())) >= 2:
                self.noise_scale.add(link_scatter(alignment, alignment.extras["per_frame"], self.edge_information,
                                                  self.backend.generators()))
            return alignment
        try:
            edge = self.aligner.camera_edge(before, after)
        except ValueError as exc:
            return f"{problem}; the camera edge failed too: {exc}"
        weak = edge_problem(edge, self.config.alignment, fitted=False)
        if weak:
            return f"{problem}; the camera edge failed too: {weak}"
        edge.fallback = f"alignment failed ({problem}); used the shared frame's cameras and depth"
        return edge

    def add_to_graph(self, work: SubmapInput, dense: DenseSubmap, odometry: Alignment | str | None) -> bool:
        """Add the submap (its node, or its keyframes' nodes) with its odometry edge, or as the start
        of a new map segment; ``False`` when the graph cannot take it at all (the submap is dropped)."""
        submap_id = work.submap_id
        frames = self._submap_frames(work, dense)
        if odometry is None and self.backend.num_submaps == 0:
            self.backend.add_submap(submap_id, None, frames=frames)
            self.backend.update()
            return True
        relative = np.eye(4)  # where a new segment starts relative to the last node, without a measurement
        if isinstance(odometry, Alignment):
            previous = self._by_frame[work.shared.index].submap_id
            odometry = self.metric_frame.complete_link(odometry, previous, self._shared_views[work.shared.index],
                                                       dense.views[0], dense.prediction, 0, self.keyframes)
            self.edges.append(EdgeReport.measured("odometry", previous, submap_id, work.shared.index, odometry))
            if odometry.fallback:
                log.info("submap %d->%d: %s", previous, submap_id, odometry.fallback)
            relative = self._graph_measurement(odometry.H)
            if not is_camera_link(odometry) and not odometry.fallback:  # a window distortion: stiffer inside
                frames = replace(frames, fitted_link=True)
            self.backend.add_submap(submap_id, relative, self.edge_information(odometry), frames=frames)
            try:
                self.backend.update()
                return True
            except BackendUpdateError as exc:
                odometry = f"the graph could not be solved with this edge ({exc})"
                self.edges[-1].accepted, self.edges[-1].reason = False, odometry
        reason = odometry if isinstance(odometry, str) else "no shared frame with an earlier submap"
        return self._start_segment(work, reason, relative, frames)

    def close_loops(self, work: SubmapInput, dense: DenseSubmap) -> None:
        """Verify every loop candidate (``sl4slam.loops``) and add the accepted ones to the graph."""
        odometry_ratios = [e.inlier_ratio for e in self.edges if e.kind == "odometry" and e.accepted and not e.fallback]
        added: list[EdgeReport] = []
        for k, candidate in enumerate(work.loops):
            old = self._by_frame[candidate.match_frame]
            tie = (candidate.match_frame, candidate.query_frame)  # the keyframes whose nodes the loop joins
            try:
                evidence = self._loop_evidence(work, dense, candidate, k)
                decision = self.loop_verifier.verify(old.submap_id, work.submap_id, evidence, odometry_ratios,
                                                     seed=work.submap_id * 1000 + k + 1, frames=tie)
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception as exc:  # a loop never ends a run
                self._reject_loop(candidate, work.submap_id, f"{type(exc).__name__}: {exc}")
                continue
            if not decision.accepted:
                self._reject_loop(candidate, work.submap_id, decision.reason, decision.alignment, decision.checks)
                continue
            alignment = self.metric_frame.complete_link(decision.alignment, old.submap_id, evidence.old,
                                                        evidence.new, dense.prediction,
                                                        work.loop_slot(k), self.keyframes)
            report = EdgeReport.measured("loop", old.submap_id, work.submap_id, candidate.match_frame, alignment,
                                         query_frame=candidate.query_frame, checks=decision.checks)
            self.edges.append(report)
            added.append(report)
            self.backend.add_loop(old.submap_id, work.submap_id, self._graph_measurement(alignment.H),
                                  decision.information, frames=tie)
        if added:
            try:
                self.backend.update()
            except BackendUpdateError as exc:
                for report in added:
                    report.accepted, report.reason = False, f"the graph could not be solved with the loops ({exc})"
                log.info("submap %d: loops dropped: %s", work.submap_id, exc)

    def store(self, work: SubmapInput, dense: DenseSubmap) -> None:
        """Keep the new keyframes compactly, the last one's view for aligning the next submap (the
        retrieval took them when the submap was accepted)."""
        for slot in work.new_slots:
            frame = work.frames[slot]
            stored = StoredKeyframe.from_prediction(dense.prediction, dense.mask, dense.levels, slot, frame.index,
                                                    frame.timestamp, work.submap_id)
            self.keyframes.append(stored)
            self._by_frame[frame.index] = stored
        opening = work.opening_slots(self.config.submap.overlap)
        self._last_stored = [work.frames[slot] for slot in opening]
        self._shared_views = {work.frames[slot].index: dense.views[slot] for slot in opening}

    # ------------------------------------------------------------------ helpers of the steps
    def edge_information(self, alignment: Alignment) -> np.ndarray:
        """Information matrix of an edge measured by ``alignment`` (``sl4slam.backend.evidence``)."""
        return edge_information(alignment, self.backend.generators(), self.config.backend)

    def _submap_frames(self, work: SubmapInput, dense: DenseSubmap) -> SubmapFrames:
        """The submap's shared frames (when it has any) and new keyframes with their extrinsics."""
        slots = list(range(work.first_new)) + list(work.new_slots)
        return SubmapFrames(tuple(work.frames[slot].index for slot in slots), dense.T_cam_submap[slots],
                            shared=work.first_new)

    def _match_pairs(self, work: SubmapInput) -> list[tuple[int, int]]:
        """``(query keyframe slot, loop frame slot)`` of every loop candidate, when the loop check reads
        the frontend's attention (the query first, as in VGGT-SLAM 2.0)."""
        if not self.loop_verifier.attention:
            return []
        return [(work.slot_of(c.query_frame), work.loop_slot(k)) for k, c in enumerate(work.loops)]

    def _graph_measurement(self, H: np.ndarray) -> np.ndarray:
        return normalize_sl4(H) if self.backend.kind == "sl4" else H

    def _start_segment(self, work: SubmapInput, reason: str, relative: np.ndarray, frames: SubmapFrames) -> bool:
        """Add the submap with a weak prior at ``H_world_last @ relative`` (the rejected measurement
        when it was usable, else the last submap's frame); if the graph cannot take even that, the
        submap is dropped (``False``)."""
        last = self.keyframes[-1].submap_id
        shared_index = work.shared.index if work.shared is not None else -1
        try:
            self.backend.start_segment(work.submap_id, self.backend.H_world_submap(last) @ relative, frames=frames)
            self.backend.update()
        except (BackendUpdateError, ValueError) as exc:
            dropped = f"{reason}; a new map segment could not be started either ({exc}): the submap is dropped"
            self.edges.append(EdgeReport(kind="segment", submap_from=last, submap_to=work.submap_id,
                                         frame_index=shared_index, accepted=False, reason=dropped))
            self._drop(work, "graph failed")
            log.warning("submap %d: %s", work.submap_id, dropped)
            return False
        self.edges.append(EdgeReport(kind="segment", submap_from=last, submap_to=work.submap_id,
                                     frame_index=shared_index, accepted=False, reason=reason))
        log.warning("submap %d starts a new map segment: %s", work.submap_id, reason)
        return True

    def _drop(self, work: SubmapInput, why: str) -> None:
        """Count the submap's new keyframes as dropped and reject its loop candidates."""
        self.dropped[why] += work.num_new
        for candidate in work.loops:
            self._reject_loop(candidate, work.submap_id, f"the submap was dropped ({why})")

    def _loop_companions(self, frame_index: int) -> list[int]:
        """Up to ``SubmapConfig.loop_frames - 1`` keyframes stored with ``frame_index`` in its submap,
        nearest to it in the video first: with the loop frame they give the loop several frames to
        measure it on, all in the same two submaps."""
        wanted = self.config.submap.loop_frames - 1
        if wanted <= 0:
            return []
        position = bisect.bisect_left(self.keyframes, frame_index, key=lambda k: k.frame_index)
        submap = self.keyframes[position].submap_id
        lo, hi = position - 1, position + 1

        def same(p: int) -> bool:
            return 0 <= p < len(self.keyframes) and self.keyframes[p].submap_id == submap

        companions: list[int] = []
        while len(companions) < wanted and (same(lo) or same(hi)):
            gap_lo = frame_index - self.keyframes[lo].frame_index if same(lo) else np.inf
            gap_hi = self.keyframes[hi].frame_index - frame_index if same(hi) else np.inf
            if gap_hi <= gap_lo:
                companions.append(self.keyframes[hi].frame_index)
                hi += 1
            else:
                companions.append(self.keyframes[lo].frame_index)
                lo -= 1
        return companions

    def _loop_evidence(self, work: SubmapInput, dense: DenseSubmap, candidate: LoopCandidate, k: int) -> LoopEvidence:
        slot, query = work.loop_slot(k), work.slot_of(candidate.query_frame)
        prediction = dense.prediction
        pairs = [(self._by_frame[work.frames[s].index].view(), dense.views[s]) for s in work.loop_slots(k)]
        return LoopEvidence(
            pairs=pairs,
            grey_new=grey_for_check(prediction.colors[slot]), query_depth=prediction.depth[query],
            query_mask=dense.mask[query], query_grey=grey_for_check(prediction.colors[query]),
            query_K=prediction.K[query], query_T_cam_submap=dense.T_cam_submap[query],
            match_ratio=recorded_match_ratio(prediction, query, slot))

    def _reject_loop(self, candidate: LoopCandidate, submap_id: int, reason: str, alignment: Alignment | None = None,
                     checks: dict | None = None) -> None:
        old = self._by_frame[candidate.match_frame].submap_id
        if alignment is not None:
            report = EdgeReport.measured("loop", old, submap_id, candidate.match_frame, alignment,
                                         query_frame=candidate.query_frame, accepted=False, reason=reason, checks=checks or {})
        else:
            report = EdgeReport(kind="loop", submap_from=old, submap_to=submap_id, frame_index=candidate.match_frame,
                                query_frame=candidate.query_frame, accepted=False, reason=reason, checks=checks or {})
        self.edges.append(report)
        log.info("loop %d->%d rejected: %s", old, submap_id, reason)

    def _time_retrieval(self, work: SubmapInput, start: float, described: float) -> None:
        """Add the time since ``start`` to ``work``'s retrieval seconds, descriptor extraction (a
        model, like the frontend) apart from the search."""
        describe = (self.retrieval.describe_seconds if self.retrieval is not None else 0.0) - described
        work.seconds["retrieval_describe"] = work.seconds.get("retrieval_describe", 0.0) + describe
        work.seconds["retrieval"] = work.seconds.get("retrieval", 0.0) + time.perf_counter() - start - describe

    def _account(self, work: SubmapInput) -> None:
        self.num_submaps += 1
        self._reporter.submap(self._frames_read, keyframes=len(self.keyframes), submaps=self.num_submaps,
                              loops=self.num_loops)
        seconds = work.seconds
        for key, value in seconds.items():
            self.timer.seconds[key] += value
        self.submap_seconds.append(seconds)
        self.submap_loops.append(sum(1 for e in self.edges if e.kind == "loop" and e.accepted and e.submap_to == work.submap_id))
        if self.on_submap is not None:
            self.on_submap(self, work.submap_id)

    # ------------------------------------------------------------------ results
    def result(self) -> SLAMResult:
        """Poses and intrinsics of every stored keyframe under the polished graph estimate
        (a batch polish of the whole graph, O(submaps), so call it at the end), upgraded to a
        metric frame when the resolved config says so (``sl4slam.metric_frame``)."""
        start = time.perf_counter()
        world = self._final_estimate()
        optimized = time.perf_counter()
        world, upgrades = self.metric_frame.upgrade(world, self.keyframes)
        result = self._result(world)
        result.stats["seconds_final_optimization"] = round(optimized - start, 5)
        result.stats["metric_upgrade"] = upgrades
        return result

    def _final_estimate(self) -> WorldEstimate:
        """The polished estimate; iSAM2's own when the polish fails (a singular node), with a note."""
        try:
            return self.backend.world_estimate(final=True)
        except (BackendUpdateError, RuntimeError, ValueError) as exc:
            first_line = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
            note = f"the final polish of the graph failed ({first_line}); the map is iSAM2's estimate"
            log.warning(note)
            self.notes.append(note)
        try:
            return self.backend.world_estimate()
        except (RuntimeError, ValueError) as exc:
            raise UserError(f"the graph cannot be solved at the end of the run ({exc}); no trajectory can be written") from None

    def snapshot(self, metric_upgrade: bool = False) -> SLAMResult:
        """The result under iSAM2's current estimate (no polish): for checkpoints and live viewers;
        ``metric_upgrade`` also upgrades it (about 0.1 s for 500 keyframes)."""
        world = self.backend.world_estimate()
        if metric_upgrade:
            world, _ = self.metric_frame.upgrade(world, self.keyframes)
        return self._result(world)

    def _result(self, world: WorldEstimate) -> SLAMResult:
        keyframes = [k for k in self.keyframes if k.submap_id in world.H_world_submap]
        T_world_cam, K = keyframe_cameras(keyframes, world.H_world_submap, world.H_world_keyframe)
        gt = None
        if keyframes and all(k.frame_index in self._gt for k in keyframes):
            gt = np.stack([self._gt[k.frame_index] for k in keyframes])
        segments = self.backend.segments_of([k.submap_id for k in keyframes])
        stats = {
            "frames": self.num_frames,
            "keyframes": len(keyframes),
            "submaps": self.num_submaps,
            "loops": self.num_loops,
            "loops_rejected": sum(1 for e in self.edges if e.kind == "loop" and not e.accepted),
            "fallbacks": sum(1 for e in self.edges if e.fallback and e.accepted and e.kind == "odometry"),
            "segments": int(segments.max()) + 1 if len(segments) else 0,
            "dropped_frames": dict(self.dropped),
            "frontend_failures": list(self.frontend_failures),
            "notes": list(self.notes) + self.knowledge.notes(),
            **self.knowledge.summary(),
            "seconds_by_stage": dict(self.timer.seconds),
            "stored_bytes": int(sum(k.nbytes for k in keyframes)),
            "seconds_per_submap": {
                stage: round(float(np.median([s.get(stage, 0.0) for s in self.submap_seconds])), 5)
                for stage in sorted({k for s in self.submap_seconds for k in s})
            },
        }
        return SLAMResult(keyframes, T_world_cam, K, world.H_world_submap, gt, list(self.edges), segments, stats,
                          colors=self.colors, H_world_keyframe=dict(world.H_world_keyframe))


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
