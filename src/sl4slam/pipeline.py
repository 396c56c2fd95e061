"""The orchestrator: frames -> keyframes -> submaps -> alignment -> factor graph -> poses and map.

It is given its stages (``sl4slam.compose.build_stages`` makes them from the resolved config) and
talks to each through its interface only (``sl4slam.types``, ``sl4slam.backend.interface``): the
frontend (a model, the simulator, a replayed cache), retrieval (SALAD, ORB, none), the aligner
(SL(4), calibration-and-scale or Sim(3)), the graph (submap or keyframe design) and the loop
verifier. ``process_submap`` reads as the list of steps of one submap; each step is a method
below it. What the steps work on lives in modules of their own: the window of a submap
(``sl4slam.window``), the stored keyframes (``sl4slam.keyframe_store``), the run's record of
edges, drops and notes (``sl4slam.ledger``), the odometry measurement with its fallbacks
(``sl4slam.odometry``), the metric frame (``sl4slam.metric_frame``), the result
(``sl4slam.result.assemble``). When each step runs is ``sl4slam.schedule``'s. See
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

import logging
import os
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np

from .alignment.parallel import Pending
from .backend import Backend, BackendUpdateError, SubmapFrames, WorldEstimate
from .backend.evidence import NoiseScale, edge_information
from .compose import _BUILD, Stages, build_stages
from .config import SLAMConfig
from .edges import EdgeReport, is_camera_link
from .errors import UserError
from .geometry import normalize_sl4
from .heap import return_freed_memory
from .keyframe_store import KeyframeStore
from .ledger import RunLedger
from .loops import LoopEvidence
from .odometry import measure_odometry
from .progress import Progress, StageTimer
from .resolve import ResolvedConfig, resolve
from .result import SLAMResult, SourceColors, keyframe_cameras
from .result.assemble import assemble_result, final_estimate
from .schedule import SequentialScheduler, make_scheduler
from .source_knowledge import SourceKnowledge, source_problem
from .refine import refine_prediction
from .centres import CentreSmoother, link_kind
from .feature_poses import correct_prediction
from .submap import StoredKeyframe, confidence_mask
from .types import Aligner, Alignment, Frame, FrameSource, Frontend, LoopCandidate, Retrieval, SubmapPrediction
from .window import (Anticipation, DenseSubmap, FrontendOutcome, SharedFrames, SubmapInput, prediction_problem,
                     recorded_match_ratio)

log = logging.getLogger("sl4slam")

__all__ = ["SLAMPipeline", "FrontendFailedError",
           # defined elsewhere, importable from here too
           "source_problem", "SubmapInput", "DenseSubmap", "FrontendOutcome", "prediction_problem", "recorded_match_ratio",
           "keyframe_cameras"]


class FrontendFailedError(UserError):
    """The frontend failed on ``max_frontend_failures`` submaps in a row."""


@dataclass
class _Input:
    """The frames being fed (between :meth:`SLAMPipeline.start` and the end of input)."""

    source: FrameSource
    scheduler: SequentialScheduler
    reporter: Progress
    pending: list[Frame] = field(default_factory=list)  # keyframes selected for the next submap
    frames_read: int = 0
    loops: int = 0  # loops accepted when the last submap was done (counting them walks every edge)


class SLAMPipeline:
    """VGGT-SLAM over a frame source.

    Args:
        resolved: the run's settings, resolved once at the entry point (``sl4slam.resolve.resolve``).
        stages: the run's stages (``sl4slam.compose.build_stages``).
        on_submap: called as ``on_submap(pipeline, submap_id)`` after every processed submap.
        keyframe_folder: where keyframes beyond ``submap.keyframes_in_ram`` keep their arrays
            (``sl4slam.keyframe_store``); ``None``: a temporary folder.
        objects: what embeds each stored keyframe's image for object queries
            (``sl4slam.objects.embedder.KeyframeEmbedder``); by default made from the ``[objects]``
            settings when ``--objects`` is on; ``None``: no embeddings.

    Example (:meth:`from_config` resolves the settings and builds the stages)::

        config = SLAMConfig(frontend="simulated")
        config.sim.profile = "vggt"
        result = SLAMPipeline.from_config(config).run(open_source("rgbd_dataset_freiburg1_xyz", config.source))

    or frame by frame: ``start(source)``, ``feed(frame)`` for each frame, ``finish()``.
    """

    def __init__(self, resolved: ResolvedConfig, stages: Stages,
                 on_submap: Callable[["SLAMPipeline", int], None] | None = None,
                 keyframe_folder: str | os.PathLike | None = None, objects: Any = _BUILD) -> None:
        self.resolved = resolved
        self.config = resolved.config
        self.frontend: Frontend = stages.frontend
        self.retrieval: Retrieval | None = stages.retrieval
        self.aligner: Aligner = stages.aligner
        self.backend: Backend = stages.backend
        attention = self.resolved.attention_check and self.frontend.capabilities.scores_pairs
        self.loop_verifier = self.config.loops.setup(self.config.alignment, self.aligner, self.backend,
                                                     self.edge_information, attention=attention,
                                                     noise_scale=NoiseScale())  # how much edges understate their noise
        self.metric_frame = self.config.upgrade.setup(self.backend, self.resolved.metric_upgrade,
                                                      self.resolved.complete_links)
        self.selector = self.config.keyframes.setup()
        self.on_submap = on_submap
        self.keyframe_store = KeyframeStore(self.config.submap.keyframes_in_ram, keyframe_folder)
        if hasattr(self.retrieval, "spill_features"):  # the retrieval's per-keyframe features likewise
            self.retrieval.spill_features(os.path.join(keyframe_folder, "retrieval") if keyframe_folder is not None
                                          else None, self.config.submap.keyframes_in_ram)
        self.ledger = RunLedger()
        self.shared = SharedFrames()
        self.centres = CentreSmoother(self.config.submap.centre_smoothing, self.config.submap.overlap)
        self.stop_requested = False
        self.knowledge = SourceKnowledge(self.resolved, self.frontend)  # start() makes the source's own
        self.colors: SourceColors | None = None  # the keyframes' colours, re-read from the source
        self._next_submap_id = 0  # submap ids handed out (one may be in the model)
        self._input: _Input | None = None
        self._released = False  # see release()
        if objects is _BUILD:
            objects = self.config.objects.setup(resolved.device) if self.config.objects.enabled else None
        self.objects = objects

    @classmethod
    def from_config(cls, config: SLAMConfig, frontend: Frontend | None = None, retrieval: Any = _BUILD,
                    aligner: Aligner | None = None, backend: Backend | None = None,
                    on_submap: Callable[["SLAMPipeline", int], None] | None = None,
                    objects: Any = _BUILD) -> "SLAMPipeline":
        """The pipeline of the user's settings (resolved here: the entry point of a library run).

        Args:
            config: the user's settings.
            frontend, retrieval, aligner, backend: stages that replace the ones the config names
                (``retrieval=None``: no loop closure; ``sl4slam.compose.build_stages``). A frontend
                given here is resolved with its own capabilities.
            on_submap, objects: see the class.
        """
        resolved = resolve(config, capabilities=frontend.capabilities if frontend is not None else None)
        return cls(resolved, build_stages(resolved, frontend, retrieval, aligner, backend), on_submap, objects=objects)

    # ------------------------------------------------------------------ what the run holds
    @property
    def keyframes(self) -> list[StoredKeyframe]:
        """The stored keyframes in time order (the store's own list)."""
        return self.keyframe_store.keyframes

    @property
    def edges(self) -> list[EdgeReport]:
        """Every odometry, loop and segment record so far (the ledger's own list)."""
        return self.ledger.edges

    @property
    def num_frames(self) -> int:
        """Input frames the frontend can use, so far."""
        return self.ledger.frames

    @property
    def num_submaps(self) -> int:
        """Submaps done so far: accepted and worked on, or failed."""
        return self.ledger.submaps

    @property
    def num_loops(self) -> int:
        """Loops accepted so far."""
        return self.ledger.num_loops

    # ------------------------------------------------------------------ driving
    def run(self, source: FrameSource, progress: bool = True, release: bool = False) -> SLAMResult:
        """Process every frame of ``source`` (or until :attr:`stop_requested`) and return the result
        (``release``: see :meth:`finish`)."""
        self.consume(source, progress)
        return self.finish(release)

    def consume(self, source: FrameSource, progress: bool = True) -> None:
        """Feed the frames of ``source`` (:meth:`start`, :meth:`feed`, :meth:`flush`; no final result)
        until they end or :attr:`stop_requested`. The source applies ``[source]`` stride and
        max_frames (``sl4slam.io.open_source``).

        Raises ``UserError`` for a source the frontend cannot use or with too few keyframes, and
        :class:`FrontendFailedError` when the frontend keeps failing (what was processed stays in
        the pipeline).
        """
        self.start(source, progress)
        try:
            for frame in source:
                if self.stop_requested:
                    break
                self.feed(frame)
        except BaseException:
            self._close_input()
            raise
        self.flush()

    def start(self, source: FrameSource, progress: bool = True) -> None:
        """Take ``source`` as the run's input: :meth:`feed` gets its frames, and loop frames are read
        again from it. The submaps are scheduled by ``sl4slam.schedule`` (the next submap's frontend
        overlapping this one's graph work when ``overlap`` is on, with the same results).

        Raises ``UserError`` for a source the frontend cannot use (checked before any frame is read).
        """
        if self._released:
            raise RuntimeError("SLAMPipeline.start after release(): the pipeline freed its running state at the end "
                               "of its run; make a new pipeline")
        problem = source_problem(source, self.frontend.capabilities, self.frontend.name, self.config.source,
                                 workers=self.resolved.workers, ray_address=self.config.ray_address)
        if problem:
            raise UserError(problem)
        if self.resolved.workers > 1 and self.retrieval is not None and not hasattr(self.retrieval, "rewind"):
            raise UserError(f"--workers {self.resolved.workers} hands windows on before their forwards, which needs a "
                            f"retrieval that can rewind (mark/rewind); {self.retrieval.name} cannot: use --workers 1")
        self.knowledge = SourceKnowledge(self.resolved, self.frontend, source)
        self.colors = SourceColors(source, self.frontend)
        reporter = Progress(len(source), enabled=progress, every=self.config.output.progress_every, per_submap=True)
        self._input = _Input(source, make_scheduler(self, overlap=self.resolved.overlap, ahead=self.resolved.workers,
                                                    tau_interval=self.config.retrieval.tau_interval), reporter,
                             loops=self.num_loops)

    def feed(self, frame: Frame) -> bool:
        """Take the next frame of the source given to :meth:`start`: keyframe selection, and once
        ``submap.size`` keyframes wait, their submap (which may still run when this returns). Returns
        whether ``frame`` became a keyframe. Raises what the submaps raise (see :meth:`consume`)."""
        fed = self._started()
        fed.frames_read += 1
        is_keyframe = self._select(frame)
        if is_keyframe:
            fed.pending.append(frame)
        if len(fed.pending) == self.config.submap.size:
            fed.scheduler.submit(fed.pending)
            fed.pending = []
        fed.scheduler.poll()
        fed.reporter.frame(fed.frames_read, keyframes=len(self.keyframes) + len(fed.pending),
                           submaps=self.num_submaps, loops=fed.loops)
        return is_keyframe

    def flush(self) -> None:
        """End of input: the keyframes still waiting become a last, shorter submap (unless a stop was
        requested), every submap is finished, and the input is closed. Nothing to do when it is closed.

        Raises ``UserError`` when fewer than 2 keyframes were selected.
        """
        if self._input is None:
            return
        fed = self._input
        try:
            if fed.pending and not self.stop_requested:
                fed.scheduler.submit(fed.pending)
            fed.scheduler.drain()
        finally:
            self._close_input()
        if len(self.keyframes) < 2 and not self.stop_requested:
            raise UserError(
                f"{fed.source.name}: only {len(self.keyframes)} keyframe(s) selected from {self.num_frames} frames; "
                "the camera barely moves — lower --tau-disparity or use a longer sequence"
            )

    def finish(self, release: bool = False) -> SLAMResult:
        """:meth:`flush` (when the input is still open), then :meth:`result`.

        Args:
            release: the run ends here: :meth:`release` before the final polish, which lowers the
                peak memory of a long run's end by what only a growing map needs; the pipeline
                takes no more frames afterwards. The result is the same either way.
        """
        self.flush()
        if release:
            self.release()
        return self.result()

    def release(self) -> None:
        """Free what only a growing map needs, once the input is closed: the retrieval's stored
        descriptors (its ``close``, where it has one) and the graph's incremental solver
        (``Backend.freeze``), together about 40 kB a keyframe with ORB retrieval, and, on a run long
        enough that the keyframe store spills already, the newest keyframes' arrays (to the store's
        files, about 0.36 MB a keyframe); then returns the freed memory to the system
        (``sl4slam.heap``), so that the final polish does not add its own to it. :meth:`result` and
        :meth:`snapshot` give what they gave before; :meth:`start` refuses afterwards."""
        if self._input is not None:
            raise RuntimeError("SLAMPipeline.release needs the input closed first (flush or finish)")
        if self.retrieval is not None and hasattr(self.retrieval, "close"):
            self.retrieval.close()
        self.backend.freeze()
        if self.keyframe_store.spilled:
            self.keyframe_store.spill_all()
        return_freed_memory()
        self._released = True

    def _started(self) -> _Input:
        if self._input is None:
            raise RuntimeError("SLAMPipeline.feed needs start(source) first")
        return self._input

    def _close_input(self) -> None:
        """Forget the input (a forward still running finishes unread) and close the progress line."""
        fed, self._input = self._input, None
        if fed is not None:
            fed.scheduler.close()
            fed.reporter.close()

    def _select(self, frame: Frame) -> bool:
        """Keyframe decision for one input frame (frames the frontend cannot use are dropped)."""
        if self.frontend.capabilities.needs_ground_truth and (
                frame.depth is None or frame.T_world_cam is None or frame.K is None):
            self.ledger.dropped["no ground truth"] += 1  # e.g. TUM frames without depth within 0.02 s
            return False
        self.ledger.frames += 1
        with self.ledger.timer("keyframes"):
            is_keyframe = self.selector.is_keyframe(frame.rgb)
        if is_keyframe:
            self.keyframe_store.note_ground_truth(frame)
        return is_keyframe

    # ------------------------------------------------------------------ one submap
    def process_submap(self, new_frames: Sequence[Frame]) -> None:
        """Reconstruct, align and optimize one submap of new keyframes (the steps in order; the
        scheduler runs the same steps with the frontend of the next submap overlapping)."""
        work = self.assemble(new_frames)
        prediction = self.accept(work, self.run_frontend(work))
        if prediction is not None:
            self.integrate(work, prediction)

    def assemble(self, new_frames: Sequence[Frame]) -> SubmapInput:
        """The submap's frames: the shared frame, the new keyframes, and the loop frames that
        retrieval proposes (a loop frame that cannot be re-read is rejected when the submap is
        accepted). Needs the retrieval to hold every earlier accepted submap."""
        start = time.perf_counter()
        described = self._described()
        submap_id = self._next_submap_id
        self._next_submap_id += 1
        candidates: list[LoopCandidate] = []
        if self.retrieval is not None and self.config.submap.w_loop > 0:
            proposed = self.retrieval.query(list(new_frames), submap_id, self.config.submap.w_loop)
            candidates = [c for c in proposed[: self.config.submap.w_loop] if c.match_frame in self.keyframe_store]
        source = self._input.source if self._input is not None else None
        shared = list(self.shared.next)
        frames, loops, unreadable, widths = shared + list(new_frames), [], [], []
        for candidate in candidates:
            try:
                loop_frames = [source.get(candidate.match_frame)]
            except UserError as exc:
                unreadable.append((candidate, f"the loop frame cannot be read again: {exc}"))
                continue
            present = {f.index for f in frames} | {candidate.match_frame}
            for companion in self.keyframe_store.companions(candidate.match_frame, self.config.submap.loop_frames - 1):
                if companion in present:  # already in this window: never give the model a frame twice
                    continue
                try:
                    loop_frames.append(source.get(companion))
                except UserError:  # the loop frame alone still measures the loop
                    continue
            frames += loop_frames
            loops.append(candidate)
            widths.append(len(loop_frames))
        work = SubmapInput(submap_id, frames, len(shared), len(new_frames), loops, unreadable, loop_widths=widths)
        work.add_retrieval_seconds(start, self._described() - described)
        return work

    def reframe(self, work: SubmapInput) -> SubmapInput:
        """``work`` with the current shared frame (after the submap before it was dropped): the same
        new keyframes and loop frames, so that the retrieval is not asked again."""
        return work.with_shared(self.shared.next)

    def run_frontend(self, work: SubmapInput) -> FrontendOutcome:
        """The frontend's prediction of ``work`` (touches no pipeline state: it may run in a worker)."""
        keywords: dict = {}
        if self.loop_verifier.attention and work.loops:  # only frontends asked for attention scores get the keyword
            keywords["match_pairs"] = work.match_pairs()
        known_K = self.knowledge.model_intrinsics(len(work.frames))
        if known_K is not None:
            keywords["intrinsics"] = known_K
        start = time.perf_counter()
        try:
            prediction = self.frontend.reconstruct(work.frames, work.submap_id, **keywords)
            problem = prediction_problem(prediction, len(work.frames))
            steps = self.config.submap.refine_cameras
            if steps and problem is None:  # a lever, off by default: each frame's pose against the others' points
                mask = confidence_mask(prediction.confidence, prediction.depth, self.config.submap.tau_conf)
                prediction = refine_prediction(prediction, mask, steps)
            features = self.config.submap.feature_poses
            if features and problem is None:
                mask = confidence_mask(prediction.confidence, prediction.depth, self.config.submap.tau_conf)
                prediction = correct_prediction(prediction, mask, features)
            outcome = FrontendOutcome(prediction, problem)
        except UserError as exc:  # a problem of the settings (a cache that does not match, a memory budget)
            outcome = FrontendOutcome(None, str(exc), error=exc)
        except Exception as exc:  # a failing model must not end the run: the submap is skipped
            outcome = FrontendOutcome(None, f"{type(exc).__name__}: {exc}")
        outcome.seconds = time.perf_counter() - start
        return outcome

    def _hand_on(self, work: SubmapInput) -> None:
        """What an accepted submap hands on to the next ones: the retrieval holds its keyframes, and
        the next window shares its opening frames."""
        self.shared.next = [work.frames[slot] for slot in work.opening_slots(self.config.submap.overlap)]
        start = time.perf_counter()
        described = self._described()
        if self.retrieval is not None:
            self.retrieval.add(work.new_frames, work.submap_id)
        work.add_retrieval_seconds(start, self._described() - described)

    def anticipate(self, work: SubmapInput) -> Anticipation:
        """Hand ``work`` on as if its forward will succeed, before it has run, so that the windows
        after it can be assembled while the model works (``sl4slam.schedule.AheadScheduler``); then
        :meth:`accept` it with ``anticipated=True``. Returns what :meth:`withdraw` needs to undo it
        (and every window assembled after it) should the forward fail. Needs a retrieval with
        ``mark``/``rewind`` (``sl4slam.types.Retrieval``)."""
        mark = self.retrieval.mark() if self.retrieval is not None else None
        anticipation = Anticipation(work.submap_id, mark, list(self.shared.next))
        self._hand_on(work)
        return anticipation

    def reshare(self, works: Sequence[SubmapInput]) -> list[SubmapInput]:
        """After the graph dropped a submap: ``works``, the windows handed on after it in order, each
        opened by the frames the one before hands on, the first by the frames the graph holds
        (:attr:`shared` ``.next``, set by :meth:`integrate`). A window whose frames stay the same is
        returned as it is (and so is every one after it); the next window shares the last one's
        opening frames again."""
        shared, out = list(self.shared.next), list(works)
        overlap = self.config.submap.overlap
        for position, work in enumerate(works):
            if [f.index for f in work.frames[: work.first_new]] == [f.index for f in shared]:
                break
            out[position] = work.with_shared(shared)
            shared = [out[position].frames[slot] for slot in out[position].opening_slots(overlap)]
        if out:
            last = out[-1]
            self.shared.next = [last.frames[slot] for slot in last.opening_slots(overlap)]
        return out

    @property
    def next_submap_id(self) -> int:
        """The id the next :meth:`assemble` gives."""
        return self._next_submap_id

    def withdraw(self, anticipation: Anticipation) -> None:
        """Undo :meth:`anticipate` of a submap whose forward failed, and the assembly of every window
        after it: the retrieval, the shared frames and the next submap id are as they were before
        it was handed on (its own window stays assembled)."""
        if self.retrieval is not None:
            self.retrieval.rewind(anticipation.retrieval)
        self.shared.next = anticipation.shared
        self._next_submap_id = anticipation.submap_id + 1

    def accept(self, work: SubmapInput, outcome: FrontendOutcome, anticipated: bool = False) -> SubmapPrediction | None:
        """Take the frontend's outcome: the prediction, whose keyframes the retrieval now holds and
        whose last keyframe the next submap shares; or ``None`` when it failed (see the module doc).
        ``anticipated``: :meth:`anticipate` handed it on already (and :meth:`withdraw` undid that if
        the forward failed)."""
        work.seconds["frontend"] = outcome.seconds
        for candidate, reason in work.unreadable:
            self._reject_loop(candidate, work.submap_id, reason)
        if outcome.error is not None:
            raise outcome.error  # its line, at once
        if outcome.problem is None:
            self.ledger.failures_in_a_row = 0
            if not anticipated:
                self._hand_on(work)
            return outcome.prediction
        self._drop(work, "frontend failed")
        self.ledger.frontend_failed(work.submap_id, outcome.problem, [f.index for f in work.new_frames])
        log.warning("submap %d: the frontend failed (%s); its %d keyframes are skipped", work.submap_id, outcome.problem,
                    work.num_new)
        self._account(work)
        if self.ledger.failures_in_a_row >= self.config.max_frontend_failures:
            raise FrontendFailedError(
                f"the frontend failed on {self.ledger.failures_in_a_row} submaps in a row (last: {outcome.problem}); "
                "check the model weights and the input frames")
        return None

    def integrate(self, work: SubmapInput, prediction: SubmapPrediction) -> bool:
        """The graph work of an accepted submap: points, odometry, graph, loops, store. ``False`` when
        the graph could not take it (it is dropped, and the next submap shares the frame before it)."""
        timer = StageTimer()
        with timer("points"):
            prediction = self.knowledge.apply(work.frames, prediction)
            prediction, centres = self.centres.smooth(work.frames, work.first_new, work.last_slot, prediction)
            dense = DenseSubmap.of(work, prediction, self.config.submap)
        with timer("loops"):
            loops = self.start_loops(work, dense)
        with timer("alignment"):
            odometry = self.align_odometry(work, dense)
        with timer("backend"):
            added = self.add_to_graph(work, dense, odometry)
        if added:
            self.centres.commit(centres, link_kind(odometry))
            with timer("loops"):
                self.close_loops(work, loops, dense)
            with timer("store"):
                self.store(work, dense)
            if self.objects is not None:
                with timer("objects"):
                    self.objects.add([work.frames[s].index for s in work.new_slots],
                                     [work.frames[s].rgb for s in work.new_slots])
        else:
            self.shared.next = self.shared.held  # the next submap shares the last frame the graph holds
        work.seconds.update(timer.seconds)
        self._account(work)
        return added

    def align_odometry(self, work: SubmapInput, dense: DenseSubmap) -> Alignment | str | None:
        """The measurement to the previous submap from the shared frames (``sl4slam.odometry``): the
        fit, else the first shared frame's camera edge (as a fallback), else the reason neither can be
        used. ``None`` for a first submap."""
        if not work.first_new:
            return None
        pairs = [(self.shared.views[work.frames[slot].index], dense.views[slot]) for slot in range(work.first_new)]
        return measure_odometry(pairs, self.aligner, self.config.alignment, work.submap_id, self.edge_information,
                                self.backend.generators, self.loop_verifier.noise_scale)

    def add_to_graph(self, work: SubmapInput, dense: DenseSubmap, odometry: Alignment | str | None) -> bool:
        """Add the submap (its node, or its keyframes' nodes) with its odometry edge, or as the start
        of a new map segment; ``False`` when the graph cannot take it at all (the submap is dropped)."""
        submap_id = work.submap_id
        frames = dense.submap_frames(work, agreement=self.config.backend.window_agreement_factor > 0
                                     and self.backend.design == "keyframe")
        if odometry is None and self.backend.num_submaps == 0:
            self.backend.add_submap(submap_id, None, frames=frames)
            self.backend.update()
            return True
        relative = np.eye(4)  # where a new segment starts relative to the last node, without a measurement
        if isinstance(odometry, Alignment):
            previous = self.keyframe_store.get(work.shared.index).submap_id
            odometry = self.metric_frame.complete_link(odometry, previous, self.shared.views[work.shared.index],
                                                       dense.views[0], dense.prediction, 0, self.keyframes)
            report = self.ledger.add(EdgeReport.measured("odometry", previous, submap_id, work.shared.index, odometry))
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
                report.accepted, report.reason = False, odometry
        reason = odometry if isinstance(odometry, str) else "no shared frame with an earlier submap"
        return self._start_segment(work, reason, relative, frames)

    def start_loops(self, work: SubmapInput, dense: DenseSubmap) -> list[tuple[LoopEvidence | Exception, Pending | None]]:
        """Each loop candidate's evidence and its link, started now (``LoopVerifier.start_alignment``):
        a loop's link does not depend on the odometry link, so the two are measured at once. A
        candidate whose evidence cannot be read keeps the error, for :meth:`close_loops` to report."""
        started = []
        for k in range(len(work.loops)):
            try:
                evidence = dense.loop_evidence(work, k, lambda index: self.keyframe_store.get(index).view())
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception as exc:  # a loop never ends a run
                started.append((exc, None))
                continue
            started.append((evidence, self.loop_verifier.start_alignment(evidence, self._loop_seed(work, k))))
        return started

    @staticmethod
    def _loop_seed(work: SubmapInput, k: int) -> int:
        return work.submap_id * 1000 + k + 1

    def close_loops(self, work: SubmapInput, started: list[tuple[LoopEvidence | Exception, Pending | None]],
                    dense: DenseSubmap) -> None:
        """Verify every loop candidate (``sl4slam.loops``) on its evidence and link as
        :meth:`start_loops` started them, and add the accepted ones to the graph."""
        odometry_ratios = self.ledger.odometry_ratios()
        added: list[EdgeReport] = []
        for k, (candidate, (evidence, alignment)) in enumerate(zip(work.loops, started)):
            old = self.keyframe_store.get(candidate.match_frame)
            tie = (candidate.match_frame, candidate.query_frame)  # the keyframes whose nodes the loop joins
            try:
                if isinstance(evidence, Exception):
                    raise evidence
                decision = self.loop_verifier.verify(old.submap_id, work.submap_id, evidence, odometry_ratios,
                                                     seed=self._loop_seed(work, k), frames=tie, alignment=alignment)
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
            added.append(self.ledger.add(EdgeReport.measured("loop", old.submap_id, work.submap_id,
                                                             candidate.match_frame, alignment,
                                                             query_frame=candidate.query_frame,
                                                             checks=decision.checks)))
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
            self.keyframe_store.add(StoredKeyframe.from_prediction(dense.prediction, dense.mask, dense.levels, slot,
                                                                   frame.index, frame.timestamp, work.submap_id))
        opening = work.opening_slots(self.config.submap.overlap)
        self.shared.held = [work.frames[slot] for slot in opening]
        self.shared.views = {work.frames[slot].index: dense.views[slot] for slot in opening}

    # ------------------------------------------------------------------ helpers of the steps
    def edge_information(self, alignment: Alignment) -> np.ndarray:
        """Information matrix of an edge measured by ``alignment`` (``sl4slam.backend.evidence``)."""
        return edge_information(alignment, self.backend.generators(), self.config.backend)

    def _graph_measurement(self, H: np.ndarray) -> np.ndarray:
        return normalize_sl4(H) if self.backend.kind == "sl4" else H

    def _described(self) -> float:
        """Seconds the retrieval has spent extracting descriptors so far."""
        return self.retrieval.describe_seconds if self.retrieval is not None else 0.0

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
            self.ledger.segment(last, work.submap_id, shared_index, dropped)
            self._drop(work, "graph failed")
            log.warning("submap %d: %s", work.submap_id, dropped)
            return False
        self.ledger.segment(last, work.submap_id, shared_index, reason)
        log.warning("submap %d starts a new map segment: %s", work.submap_id, reason)
        return True

    def _drop(self, work: SubmapInput, why: str) -> None:
        """Count the submap's new keyframes as dropped and reject its loop candidates."""
        self.ledger.dropped[why] += work.num_new
        for candidate in work.loops:
            self._reject_loop(candidate, work.submap_id, f"the submap was dropped ({why})")

    def _reject_loop(self, candidate: LoopCandidate, submap_id: int, reason: str, alignment: Alignment | None = None,
                     checks: dict | None = None) -> None:
        old = self.keyframe_store.get(candidate.match_frame).submap_id
        self.ledger.reject_loop(candidate, old, submap_id, reason, alignment, checks)

    def _account(self, work: SubmapInput) -> None:
        self.ledger.submap_done(work.submap_id, work.seconds)
        if self._input is not None:
            self._input.loops = self.num_loops
            self._input.reporter.submap(self._input.frames_read, keyframes=len(self.keyframes),
                                        submaps=self.num_submaps, loops=self._input.loops)
        if self.on_submap is not None:
            self.on_submap(self, work.submap_id)

    # ------------------------------------------------------------------ results
    def result(self) -> SLAMResult:
        """Poses and intrinsics of every stored keyframe under the polished graph estimate
        (a batch polish of the whole graph, O(submaps), so call it at the end), upgraded to a
        metric frame when the resolved config says so (``sl4slam.metric_frame``)."""
        start = time.perf_counter()
        world = final_estimate(self.backend, self.ledger)
        optimized = time.perf_counter()
        world, upgrades = self.metric_frame.upgrade(world, self.keyframes)
        result = self.result_for(world)
        result.stats["seconds_final_optimization"] = round(optimized - start, 5)
        result.stats["metric_upgrade"] = upgrades
        return result

    def snapshot(self, metric_upgrade: bool = False) -> SLAMResult:
        """The result under iSAM2's current estimate (no polish): for checkpoints and live viewers;
        ``metric_upgrade`` also upgrades it (about 0.1 s for 500 keyframes)."""
        world = self.backend.world_estimate()
        if metric_upgrade:
            world, _ = self.metric_frame.upgrade(world, self.keyframes)
        return self.result_for(world)

    def result_for(self, world: WorldEstimate) -> SLAMResult:
        """The result under the graph estimate ``world`` as given (``Backend.world_estimate``; no
        polish or upgrade here): ``sl4slam.result.assemble``."""
        return assemble_result(world, self.keyframe_store, self.ledger, self.backend, self.knowledge, self.colors)
