"""The orchestrator: frames -> keyframes -> submaps -> alignment -> factor graph -> poses and map.

It is given its stages and talks to each through its interface only (``sl4slam.types``): the
frontend (VGGT, the simulator, a replayed cache), retrieval (SALAD, ORB, none), the aligner (SL(4),
calibration-and-scale or Sim(3)), the backend (the submap graph in SL(4) or Sim(3), or the keyframe
graph) and the loop verifier. ``process_submap`` reads as the list of steps of one submap; each step
is a method below it. See docs/architecture.md.

Both graph designs get the same calls: measurements in submap coordinates, with the submap's
keyframes and extrinsics (``SubmapFrames``) and each loop's two frames, which the keyframe graph
uses to place them between keyframe nodes; both return a ``WorldEstimate`` with, for the keyframe
graph, a transform per keyframe.

Where the run ends with the metric upgrade, a link that only the shared frame's camera fixes (a
fallback on a planar frame) is completed from the new submap's cameras in the running upgrade of
the map so far before it enters the graph (``complete_link``, ``sl4slam.completion``), so the map
stays one projective frame for the final upgrade.

Nothing that goes wrong inside a submap ends a run:

- the frontend fails (an exception or non-finite output): the submap is skipped and its keyframes
  are lost; the next submap still shares a frame with the last good one. ``max_frontend_failures``
  failures in a row end the run, with what was done returned;
- the odometry fit fails or fails its checks (``sl4slam.edges``): the shared frame's camera edge
  (its two cameras and depth ratio) takes its place with an inflated sigma, listed as a fallback;
- that is unusable too (the frontend's cameras are implausible), or GTSAM cannot solve the graph
  with the new edge: the submap starts a new map segment — its node gets a weak prior at the
  previous node's estimate instead of an odometry factor, so the trajectory continues, later loops
  can join the segments, and the summary lists where each segment starts and why;
- anything goes wrong with a loop candidate (an unreadable loop frame, a failed alignment, a check
  that fails, a graph update that fails): the loop is rejected and listed with its reason.
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from .alignment import make_aligner
from .backend import Backend, BackendUpdateError, SubmapFrames, WorldEstimate, make_backend
from .backend.evidence import edge_information
from .config import SLAMConfig, attention_check, completes_links, metric_upgrade_on
from .edges import EdgeReport, camera_problem, edge_problem
from .errors import UserError
from .geometry import decompose_projection, normalize_sl4, to_4x4
from .keyframes import KeyframeSelector
from .loops import LoopEvidence, LoopVerifier, grey_for_check
from .progress import Progress, StageTimer
from .submap import StoredKeyframe, confidence_levels, confidence_mask, principal_points, submap_points
from .types import Aligner, Alignment, Frame, FrameSource, FrameView, Frontend, LoopCandidate, Retrieval, SubmapPrediction

log = logging.getLogger("sl4slam")


class FrontendFailedError(UserError):
    """The frontend failed on ``max_frontend_failures`` submaps in a row."""


@dataclass
class SubmapInput:
    """The frames of one submap and where each kind sits.

    Attributes:
        submap_id: its id.
        frames: ``[shared frame] + new keyframes + loop frames`` (no shared frame for a first submap).
        first_new: slot of the first new keyframe (0 or 1).
        num_new: number of new keyframes.
        loops: the retrieved candidates whose loop frame follows the new keyframes, in order.
    """

    submap_id: int
    frames: list[Frame]
    first_new: int
    num_new: int
    loops: list[LoopCandidate]

    @property
    def new_slots(self) -> range:
        return range(self.first_new, self.first_new + self.num_new)

    @property
    def last_slot(self) -> int:
        return self.first_new + self.num_new - 1

    def loop_slot(self, k: int) -> int:
        return self.first_new + self.num_new + k

    def slot_of(self, frame_index: int) -> int:
        return next(s for s in self.new_slots if self.frames[s].index == frame_index)


@dataclass
class DenseSubmap:
    """The frontend's prediction of a submap with what the steps derive from it once.

    Attributes:
        prediction: the frontend's output.
        mask: ``(S, H, W)`` confident pixels (``SubmapConfig.tau_conf``).
        levels: the submap's confidence quantiles (``sl4slam.submap.confidence_levels``).
        views: ``{slot: FrameView}`` for the frames that are aligned (points at full precision).
    """

    prediction: SubmapPrediction
    mask: np.ndarray
    levels: np.ndarray
    views: dict[int, FrameView]


@dataclass
class SLAMResult:
    """What a run produces (in memory); ``sl4slam.outputs`` writes it to disk.

    Attributes:
        keyframes: the stored keyframes in time order (one per keyframe, shared frames once).
        T_world_cam: ``(N, 4, 4)`` keyframe poses (world-from-camera, rigid part of the decomposed
            camera; world units are the first submap's).
        K: ``(N, 3, 3)`` keyframe intrinsics decomposed from the world camera matrices.
        H_world_submap: where each submap sits in the world (the submap graph's nodes; optimized by
            the final polish, or iSAM2's current estimate for a snapshot).
        T_world_cam_gt: ``(N, 4, 4)`` ground truth for the keyframes, or ``None``.
        edges: every odometry, loop (accepted or rejected) and segment record.
        segments: ``(N,)`` int, the map segment of each keyframe (0 unless a segment started).
        stats: counts and timings for the summary.
        colors: ``keyframe -> (H, W, 3)`` uint8 colours on the prediction grid (re-read from the source).
        H_world_keyframe: ``{frame_index: (4, 4)}`` for graphs with a node per keyframe: maps the
            keyframe's submap points into the world through its own node (use :meth:`H_world`).
    """

    keyframes: list[StoredKeyframe]
    T_world_cam: np.ndarray
    K: np.ndarray
    H_world_submap: dict[int, np.ndarray]
    T_world_cam_gt: np.ndarray | None
    edges: list[EdgeReport]
    segments: np.ndarray
    stats: dict = field(default_factory=dict)
    colors: Callable[[StoredKeyframe], np.ndarray] | None = None
    H_world_keyframe: dict[int, np.ndarray] = field(default_factory=dict)

    def H_world(self, keyframe: StoredKeyframe) -> np.ndarray:
        """``(4, 4)`` map from ``keyframe``'s submap points to the world (its own node, else its submap's)."""
        H = self.H_world_keyframe.get(keyframe.frame_index)
        return H if H is not None else self.H_world_submap[keyframe.submap_id]

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([k.timestamp for k in self.keyframes], dtype=np.float64)

    def keyframe_colors(self, keyframe: StoredKeyframe) -> np.ndarray:
        """``(H, W, 3)`` uint8 colours of ``keyframe``; mid-grey when they cannot be re-read."""
        if self.colors is not None:
            try:
                return self.colors(keyframe)
            except UserError as exc:
                log.warning("keyframe %d: colours unavailable (%s); written grey", keyframe.frame_index, exc)
        return np.full(keyframe.shape + (3,), 128, dtype=np.uint8)


class SLAMPipeline:
    """VGGT-SLAM over a frame source.

    Args:
        config: every setting; validated here, before any work.
        frontend: reconstructs a submap's frames.
        retrieval: proposes loop candidates (``None``: no loop closure).
        aligner: measures relative transforms (default: the one ``config.alignment`` names).
        backend: the factor graph (default: the one ``config.backend`` names).
        on_submap: called as ``on_submap(pipeline, submap_id)`` after every processed submap.

    Example::

        pipeline = SLAMPipeline(config, frontend=SimulatedFrontend(config.sim))
        result = pipeline.run(open_source("rgbd_dataset_freiburg1_xyz"))
    """

    def __init__(
        self,
        config: SLAMConfig,
        frontend: Frontend,
        retrieval: Retrieval | None = None,
        aligner: Aligner | None = None,
        backend: Backend | None = None,
        on_submap: Callable[["SLAMPipeline", int], None] | None = None,
    ) -> None:
        config.validate()
        self.config = config
        self.frontend = frontend
        self.retrieval = retrieval
        self.aligner = aligner if aligner is not None else make_aligner(config)
        self.backend = backend if backend is not None else make_backend(config.backend)
        if self.aligner.group == "sl4" and self.backend.kind != "sl4":
            raise UserError(f"the {self.aligner.model} aligner measures projective transforms, which a "
                            f"{self.backend.kind} graph cannot hold; use a Sim(3) alignment model")
        self.loop_verifier = LoopVerifier(config.loops, config.alignment, self.aligner, self.backend, self.edge_information,
                                          attention=attention_check(config) and scores_matches(frontend, config))
        self.selector = KeyframeSelector(config.keyframes)
        self.on_submap = on_submap
        self.keyframes: list[StoredKeyframe] = []
        self._by_frame: dict[int, StoredKeyframe] = {}
        self.edges: list[EdgeReport] = []
        self.timer = StageTimer()
        self.submap_seconds: list[dict[str, float]] = []
        self.submap_loops: list[int] = []  # loop factors added with each submap
        self.num_submaps = 0  # submap ids handed out (failed submaps included)
        self.num_frames = 0
        self.dropped: dict[str, int] = {"no ground truth": 0, "frontend failed": 0}
        self.frontend_failures: list[dict] = []
        self.stop_requested = False
        self._failures_in_a_row = 0
        self._gt: dict[int, np.ndarray] = {}
        self._prior: Frame | None = None
        self._prior_view: FrameView | None = None  # the shared frame at full precision
        self._source: FrameSource | None = None

    # ------------------------------------------------------------------ driving
    def run(self, source: FrameSource, progress: bool = True) -> SLAMResult:
        """Process every frame of ``source`` (or until :attr:`stop_requested`) and return the result."""
        self.consume(source, progress)
        return self.result()

    def consume(self, source: FrameSource, progress: bool = True) -> None:
        """Feed the frames of ``source`` through keyframe selection and submaps (no final result).

        Raises ``UserError`` for a source the frontend cannot use, and :class:`FrontendFailedError`
        when the frontend keeps failing (what was processed stays in the pipeline).
        """
        self._source = source
        total = len(source)
        if self.config.max_frames > 0:
            total = min(total, self.config.max_frames)
        if total < 2:
            raise UserError(f"{source.name}: {total} frame(s) found; SLAM needs at least 2 frames")
        if self.frontend.requires_ground_truth and not source.has_ground_truth:
            raise UserError(f"{source.name} has no depth and ground-truth poses, which the {self.frontend.name} frontend "
                            "needs (an RGB-D sequence: TUM, 7-Scenes or the synthetic world); use --frontend vggt")
        pending: list[Frame] = []
        reporter = Progress(total, enabled=progress, every=self.config.output.progress_every)
        try:
            for count, frame in enumerate(source):
                if count >= total or self.stop_requested:
                    break
                if count % self.config.stride == 0 and self._select(frame):
                    pending.append(frame)
                if len(pending) == self.config.submap.size:
                    self.process_submap(pending)
                    pending = []
                    reporter.submap(count + 1, keyframes=len(self.keyframes), submaps=self.num_submaps, loops=self.num_loops)
                reporter.frame(keyframes=len(self.keyframes) + len(pending), submaps=self.num_submaps, loops=self.num_loops)
            if pending and not self.stop_requested:
                self.process_submap(pending)
        finally:
            reporter.close()
        if len(self.keyframes) < 2 and not self.stop_requested:
            raise UserError(
                f"{source.name}: only {len(self.keyframes)} keyframe(s) selected from {self.num_frames} frames; "
                "the camera barely moves — lower --tau-disparity or use a longer sequence"
            )

    def _select(self, frame: Frame) -> bool:
        """Keyframe decision for one input frame (frames the frontend cannot use are dropped)."""
        if self.frontend.requires_ground_truth and (frame.depth is None or frame.T_world_cam is None or frame.K is None):
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
        """Reconstruct, align and optimize one submap of new keyframes."""
        timer = StageTimer()
        described = self.retrieval.describe_seconds if self.retrieval is not None else 0.0
        with timer("retrieval"):
            work = self.assemble(new_frames)
        with timer("frontend"):
            prediction = self.reconstruct(work)
        if prediction is not None:
            with timer("points"):
                dense = self.dense_submap(work, prediction)
            with timer("alignment"):
                odometry = self.align_odometry(work, dense)
            with timer("backend"):
                self.add_to_graph(work, dense, odometry)
            with timer("loops"):
                self.close_loops(work, dense)
            with timer("store"):
                self.store(work, dense)
        # descriptor extraction (a model, like the frontend) is reported apart from the search
        seconds = dict(timer.seconds)
        seconds["retrieval_describe"] = (self.retrieval.describe_seconds if self.retrieval is not None else 0.0) - described
        seconds["retrieval"] -= seconds["retrieval_describe"]
        self._account(work, seconds)

    def assemble(self, new_frames: Sequence[Frame]) -> SubmapInput:
        """The submap's frames: the shared frame, the new keyframes, and the loop frames that
        retrieval proposes (a loop frame that cannot be re-read is rejected here)."""
        submap_id = self.num_submaps
        self.num_submaps += 1
        candidates: list[LoopCandidate] = []
        if self.retrieval is not None and self.config.submap.w_loop > 0:
            proposed = self.retrieval.query(list(new_frames), submap_id, self.config.submap.w_loop)
            candidates = [c for c in proposed[: self.config.submap.w_loop] if c.match_frame in self._by_frame]
        prior = [self._prior] if self._prior is not None else []
        frames, loops = prior + list(new_frames), []
        for candidate in candidates:
            try:
                frames.append(self._source.get(candidate.match_frame))
                loops.append(candidate)
            except UserError as exc:
                self._reject_loop(candidate, submap_id, f"the loop frame cannot be read again: {exc}")
        return SubmapInput(submap_id, frames, len(prior), len(new_frames), loops)

    def reconstruct(self, work: SubmapInput) -> SubmapPrediction | None:
        """The frontend's prediction, or ``None`` when it fails on this submap (see the module doc)."""
        pairs = self._match_pairs(work)
        try:
            # only frontends asked for attention scores need to know the keyword
            prediction = self.frontend.reconstruct(work.frames, work.submap_id, **({"match_pairs": pairs} if pairs else {}))
            problem = prediction_problem(prediction, len(work.frames))
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:  # a failing model must not end the run: the submap is skipped
            problem = f"{type(exc).__name__}: {exc}"
        if problem is None:
            self._failures_in_a_row = 0
            return prediction
        self._failures_in_a_row += 1
        self.dropped["frontend failed"] += work.num_new
        self.frontend_failures.append({"submap": work.submap_id, "reason": problem,
                                       "keyframes": [f.index for f in work.frames[work.first_new:work.last_slot + 1]]})
        log.warning("submap %d: the frontend failed (%s); its %d keyframes are skipped", work.submap_id, problem, work.num_new)
        for candidate in work.loops:
            self._reject_loop(candidate, work.submap_id, "the frontend failed on this submap")
        if self._failures_in_a_row >= self.config.max_frontend_failures:
            raise FrontendFailedError(
                f"the frontend failed on {self._failures_in_a_row} submaps in a row (last: {problem}); "
                "check the model weights and the input frames")
        return None

    def dense_submap(self, work: SubmapInput, prediction: SubmapPrediction) -> DenseSubmap:
        """Confidence masks for the submap, and points for the frames that are aligned: the shared
        frame, the last new keyframe (shared with the next submap) and the loop frames. The map is
        rebuilt from stored depth, so no other frame needs points now."""
        mask = confidence_mask(prediction.confidence, prediction.depth, self.config.submap.tau_conf)
        needed = sorted({0, work.last_slot, *range(work.loop_slot(0), len(work.frames))})
        points = submap_points(prediction, self.config.submap.use_point_head, needed)
        views = {slot: FrameView(points[k], mask[slot], prediction.K[slot], to_4x4(prediction.T_cam_submap[slot]))
                 for k, slot in enumerate(needed)}
        return DenseSubmap(prediction, mask, confidence_levels(prediction.confidence, prediction.depth), views)

    def align_odometry(self, work: SubmapInput, dense: DenseSubmap) -> Alignment | str | None:
        """The measurement to the previous submap from the shared frame: the fit, else the camera
        edge (as a fallback), else the reason neither can be used. ``None`` for a first submap."""
        if self._prior_view is None:
            return None
        before, after = self._prior_view, dense.views[0]
        problem = camera_problem(before) or camera_problem(after)
        if problem:
            return problem
        try:
            alignment = self.aligner.align(before, after, seed=work.submap_id)
            problem = edge_problem(alignment, self.config.alignment)
        except ValueError as exc:
            problem = str(exc)
        if problem is None:
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

    def add_to_graph(self, work: SubmapInput, dense: DenseSubmap, odometry: Alignment | str | None) -> None:
        """Add the submap (its node, or its keyframes' nodes) with its odometry edge, or as the start
        of a new map segment."""
        submap_id = work.submap_id
        frames = self._submap_frames(work, dense)
        if odometry is None and self.backend.num_submaps == 0:
            self.backend.add_submap(submap_id, None, frames=frames)
            self.backend.update()
            return
        relative = np.eye(4)  # where a new segment starts relative to the last node, without a measurement
        if isinstance(odometry, Alignment):
            previous = self._by_frame[self._prior.index].submap_id
            odometry = self.complete_link(odometry, previous, self._prior_view, dense, slot=0)
            self.edges.append(EdgeReport.measured("odometry", previous, submap_id, self._prior.index, odometry))
            if odometry.fallback:
                log.info("submap %d->%d: %s", previous, submap_id, odometry.fallback)
            relative = self._graph_measurement(odometry.H)
            self.backend.add_submap(submap_id, relative, self.edge_information(odometry), frames=frames)
            try:
                self.backend.update()
                return
            except BackendUpdateError as exc:
                odometry = f"the graph could not be solved with this edge ({exc})"
                self.edges[-1].accepted, self.edges[-1].reason = False, odometry
        reason = odometry if isinstance(odometry, str) else "no shared frame with an earlier submap"
        self._start_segment(submap_id, reason, relative, frames)

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
            alignment = self.complete_link(decision.alignment, old.submap_id, old.view(), dense, work.loop_slot(k))
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
        """Keep the new keyframes compactly, the last one as the next submap's shared frame, and
        hand them to retrieval."""
        for slot in work.new_slots:
            frame = work.frames[slot]
            stored = StoredKeyframe.from_prediction(dense.prediction, dense.mask, dense.levels, slot, frame.index,
                                                    frame.timestamp, work.submap_id)
            self.keyframes.append(stored)
            self._by_frame[frame.index] = stored
        self._prior = work.frames[work.last_slot]
        self._prior_view = dense.views[work.last_slot]
        if self.retrieval is not None:
            self.retrieval.add(work.frames[work.first_new:work.last_slot + 1], work.submap_id)

    # ------------------------------------------------------------------ helpers of the steps
    def edge_information(self, alignment: Alignment) -> np.ndarray:
        """Information matrix of an edge measured by ``alignment`` (``sl4slam.backend.evidence``)."""
        return edge_information(alignment, self.backend.generators(), self.config.backend)

    def _submap_frames(self, work: SubmapInput, dense: DenseSubmap) -> SubmapFrames:
        """The submap's shared frame (when it has one) and new keyframes with their extrinsics."""
        slots = ([0] if work.first_new else []) + list(work.new_slots)
        T = np.stack([to_4x4(dense.prediction.T_cam_submap[slot]) for slot in slots])
        return SubmapFrames(tuple(work.frames[slot].index for slot in slots), T, shared=bool(work.first_new))

    def _match_pairs(self, work: SubmapInput) -> list[tuple[int, int]]:
        """``(query keyframe slot, loop frame slot)`` of every loop candidate, when the loop check reads
        the frontend's attention (the query first, as in VGGT-SLAM 2.0)."""
        if not self.loop_verifier.attention:
            return []
        return [(work.slot_of(c.query_frame), work.loop_slot(k)) for k, c in enumerate(work.loops)]

    def complete_link(self, alignment: Alignment, old_submap: int, old_view: FrameView, dense: DenseSubmap,
                      slot: int) -> Alignment:
        """A fallback link that only the shared frame's cameras fix, completed from the new submap's
        cameras in the running metric upgrade (``sl4slam.completion``), where the run ends with the
        upgrade; any other measurement as it is. ``slot``: the shared frame in the new submap."""
        from .completion import complete_camera_link, plane_normal, shared_camera_agreement

        if not alignment.fallback or alignment.model != "sl4" or not completes_links(self.config):
            return alignment
        new_view = dense.views[slot]
        if shared_camera_agreement(old_view.camera, new_view.camera, alignment.H) > 1e-6:
            return alignment  # a stand-in that does not keep the shared camera: nothing to complete
        running = self._running_upgrade(old_submap)
        if isinstance(running, str):
            alignment.extras["completion"] = {"applied": False, "reason": running}
            return alignment
        H_metric_world, focal = running
        prediction = dense.prediction
        others = [s for s in range(len(prediction.K)) if s != slot]
        cameras = np.stack([prediction.K[s] @ to_4x4(prediction.T_cam_submap[s])[:3] for s in others])
        points = new_view.points[new_view.mask].astype(np.float64)
        # a camera-constrained fit took the plane's tilt from its points: only the relief along the
        # normal is left free; the calibration link took nothing from them
        free = plane_normal(points) if alignment.extras.get("camera_constrained") and len(points) >= 3 else None
        H_metric_old = H_metric_world @ self.backend.H_world_submap(old_submap)
        completion = complete_camera_link(alignment.H, new_view.centre, points, cameras, principal_points(prediction)[others],
                                          H_metric_old, focal, self.config.upgrade, free)
        alignment.extras["completion"] = completion.summary()
        if not completion.applied:
            return alignment
        return dataclasses.replace(alignment, H=completion.H_a_b, extras=dict(alignment.extras), fallback=(
            f"{alignment.fallback}; completed from the new submap's cameras (constraint residual "
            f"{completion.residual_before:.2g} -> {completion.residual_after:.2g})"))

    def _running_upgrade(self, submap_id: int) -> tuple[np.ndarray, float] | str:
        """``(H_metric_world, focal px)`` of the map so far in ``submap_id``'s segment, or why there is none."""
        world = self.backend.world_estimate()
        members = self._segment_members(world).get(self.backend.segments[
            int(np.searchsorted(self.backend.segments, submap_id, side="right")) - 1], [])
        if len(members) < self.config.upgrade.min_keyframes:
            return f"too few keyframes for a running upgrade ({len(members)})"
        try:
            upgrade = self._estimate_upgrade(members, world)
        except (UserError, ValueError, np.linalg.LinAlgError) as exc:
            return f"no running upgrade: {exc}"
        if upgrade.applied:
            return upgrade.H_metric_world, upgrade.focal
        if upgrade.reason.startswith("already metric"):
            return np.eye(4), upgrade.focal
        return f"no running upgrade: {upgrade.reason}"

    def _segment_members(self, world: WorldEstimate) -> dict[int, list[StoredKeyframe]]:
        """The keyframes placed in ``world``, by the first submap of their map segment."""
        keyframes = [k for k in self.keyframes if k.submap_id in world.H_world_submap]
        starts = self.backend.segments
        segment_of = np.searchsorted(starts, [k.submap_id for k in keyframes], side="right") - 1
        members: dict[int, list[StoredKeyframe]] = {}
        for keyframe, segment in zip(keyframes, segment_of):
            members.setdefault(int(starts[segment]), []).append(keyframe)
        return members

    def _estimate_upgrade(self, members: Sequence[StoredKeyframe], world: WorldEstimate):
        """``sl4slam.upgrade.estimate_metric_upgrade`` of these keyframes' cameras in ``world``."""
        from .upgrade import estimate_metric_upgrade

        return estimate_metric_upgrade(world_cameras(members, world.H_world_submap, world.H_world_keyframe),
                                       np.stack([k.principal_point for k in members]), self.config.upgrade,
                                       image_sizes=np.array([k.shape[::-1] for k in members]))

    def _graph_measurement(self, H: np.ndarray) -> np.ndarray:
        return normalize_sl4(H) if self.backend.kind == "sl4" else H

    def _start_segment(self, submap_id: int, reason: str, relative: np.ndarray, frames: SubmapFrames) -> None:
        """Add the submap with a weak prior at ``H_world_last @ relative`` (the rejected measurement
        when it was usable, else the last submap's frame)."""
        last = self.keyframes[-1].submap_id
        self.backend.start_segment(submap_id, self.backend.H_world_submap(last) @ relative, frames=frames)
        self.backend.update()
        self.edges.append(EdgeReport(kind="segment", submap_from=last, submap_to=submap_id,
                                     frame_index=self._prior.index if self._prior is not None else -1,
                                     accepted=False, reason=reason))
        log.warning("submap %d starts a new map segment: %s", submap_id, reason)

    def _loop_evidence(self, work: SubmapInput, dense: DenseSubmap, candidate: LoopCandidate, k: int) -> LoopEvidence:
        slot, query = work.loop_slot(k), work.slot_of(candidate.query_frame)
        prediction = dense.prediction
        return LoopEvidence(
            old=self._by_frame[candidate.match_frame].view(), new=dense.views[slot],
            grey_new=grey_for_check(prediction.colors[slot]), query_depth=prediction.depth[query],
            query_mask=dense.mask[query], query_grey=grey_for_check(prediction.colors[query]),
            query_K=prediction.K[query], query_T_cam_submap=to_4x4(prediction.T_cam_submap[query]),
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

    def _account(self, work: SubmapInput, seconds: dict[str, float]) -> None:
        for key, value in seconds.items():
            self.timer.seconds[key] += value
        self.submap_seconds.append(seconds)
        self.submap_loops.append(sum(1 for e in self.edges if e.kind == "loop" and e.accepted and e.submap_to == work.submap_id))
        if self.on_submap is not None:
            self.on_submap(self, work.submap_id)

    # ------------------------------------------------------------------ results
    def result(self) -> SLAMResult:
        """Poses and intrinsics of every stored keyframe under the polished graph estimate
        (``final_estimates``: a batch polish of the whole graph, O(submaps), so call it at the end),
        upgraded to a metric frame when ``config.upgrade`` allows (``sl4slam.upgrade``)."""
        start = time.perf_counter()
        world = self.backend.world_estimate(final=True)
        optimized = time.perf_counter()
        world, upgrades = self.metric_upgrade(world)
        result = self._result(world)
        result.stats["seconds_final_optimization"] = round(optimized - start, 5)
        result.stats["metric_upgrade"] = upgrades
        return result

    def snapshot(self, metric_upgrade: bool = False) -> SLAMResult:
        """The result under iSAM2's current estimate (no polish): for checkpoints and live viewers;
        ``metric_upgrade`` also upgrades it (about 0.1 s for 500 keyframes)."""
        world = self.backend.world_estimate()
        if metric_upgrade:
            world, _ = self.metric_upgrade(world)
        return self._result(world)

    def metric_upgrade(self, world: WorldEstimate) -> tuple[WorldEstimate, list[dict]]:
        """Upgrade each map segment to a metric frame (one ``H_metric_world`` per segment, applied to
        its submaps' and keyframes' transforms: every pose and map point follows). Returns the
        upgraded estimate and one summary per segment."""
        H_world_submap, H_world_keyframe = world.H_world_submap, world.H_world_keyframe
        if not metric_upgrade_on(self.config):
            return world, []
        upgraded, summaries = WorldEstimate(dict(H_world_submap), dict(H_world_keyframe)), []
        for start, members in sorted(self._segment_members(world).items()):
            segment = self.backend.segments.index(start)
            try:
                upgrade = self._estimate_upgrade(members, world)
            except (UserError, ValueError, np.linalg.LinAlgError) as exc:
                # e.g. a camera at infinity in a broken map: the map is kept as it is, never lost
                summaries.append({"segment": int(segment), "applied": False, "reason": f"cannot be estimated: {exc}"})
                log.warning("metric upgrade of segment %d skipped: %s", segment, exc)
                continue
            summaries.append({"segment": int(segment), **upgrade.summary()})
            if upgrade.applied:
                for submap_id in {k.submap_id for k in members}:
                    upgraded.H_world_submap[submap_id] = upgrade.H_metric_world @ H_world_submap[submap_id]
                for keyframe in members:
                    if keyframe.frame_index in H_world_keyframe:
                        upgraded.H_world_keyframe[keyframe.frame_index] = (
                            upgrade.H_metric_world @ H_world_keyframe[keyframe.frame_index])
            log.info("metric upgrade of segment %d: %s", segment, upgrade.reason)
        return upgraded, summaries

    def _result(self, world: WorldEstimate) -> SLAMResult:
        H_world_submap = world.H_world_submap
        keyframes = [k for k in self.keyframes if k.submap_id in H_world_submap]
        T_world_cam, K = keyframe_cameras(keyframes, H_world_submap, world.H_world_keyframe)
        gt = None
        if keyframes and all(k.frame_index in self._gt for k in keyframes):
            gt = np.stack([self._gt[k.frame_index] for k in keyframes])
        starts = self.backend.segments
        segments = np.searchsorted(starts, [k.submap_id for k in keyframes], side="right") - 1
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
            "seconds_by_stage": dict(self.timer.seconds),
            "stored_bytes": int(sum(k.nbytes for k in keyframes)),
            "seconds_per_submap": {
                stage: round(float(np.median([s.get(stage, 0.0) for s in self.submap_seconds])), 5)
                for stage in sorted({k for s in self.submap_seconds for k in s})
            },
        }
        return SLAMResult(keyframes, T_world_cam, K, H_world_submap, gt, list(self.edges), segments, stats,
                          colors=self._colors, H_world_keyframe=dict(world.H_world_keyframe))

    def _colors(self, keyframe: StoredKeyframe) -> np.ndarray:
        if self._source is None:
            raise UserError("no frame source to read colours from")
        return self.frontend.grid_colors(self._source.get(keyframe.frame_index))


def keyframe_cameras(keyframes: Sequence[StoredKeyframe], H_world_submap: dict[int, np.ndarray],
                     H_world_keyframe: dict[int, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World poses and intrinsics of keyframes: ``P = K [R|t] H^-1``, RQ-decomposed, with ``H`` the
    keyframe's own transform in ``H_world_keyframe`` (by frame index, keyframe graph) or else its
    submap's in ``H_world_submap``.

    Returns ``T_world_cam (N, 4, 4)`` and ``K (N, 3, 3)``.
    """
    if not keyframes:
        return np.zeros((0, 4, 4)), np.zeros((0, 3, 3))
    P = world_cameras(keyframes, H_world_submap, H_world_keyframe)
    K, T_world_cam, _ = decompose_projection(P)
    return T_world_cam, K


def world_cameras(keyframes: Sequence[StoredKeyframe], H_world_submap: dict[int, np.ndarray],
                  H_world_keyframe: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """``(N, 3, 4)`` camera matrices ``K [R|t] H^-1`` of keyframes in the world frame (``H`` as in
    :func:`keyframe_cameras`)."""
    own = H_world_keyframe or {}
    H_inv = {i: np.linalg.inv(H) for i, H in H_world_submap.items()}
    return np.stack([k.K @ k.T_cam_submap[:3] @ (np.linalg.inv(own[k.frame_index]) if k.frame_index in own
                                                  else H_inv[k.submap_id]) for k in keyframes])


def scores_matches(frontend: Frontend, config: SLAMConfig) -> bool:
    """Whether ``frontend`` can give the attention loop check its image-match ratios (it takes the
    ``match_pairs`` keyword). A frontend that cannot is run without the check where the setting is
    "auto"; an explicit "on" is refused before any work."""
    try:
        parameters = inspect.signature(frontend.reconstruct).parameters
    except (TypeError, ValueError):
        parameters = {}
    able = "match_pairs" in parameters or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
    if not able and config.loops.verify_attention == "on":
        raise UserError(f"--loop-verify-attention on needs image-match ratios, which the {type(frontend).__name__} "
                        "frontend does not give; use --loop-verify-attention off or auto")
    return able


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
