"""The orchestrator: frames -> keyframes -> submaps -> alignment -> factor graph -> poses and map.

It talks to every stage through its interface only (``Frontend``, ``Retrieval``, the backend and
the alignment functions), so each can be swapped: VGGT or the simulator, SALAD or ORB retrieval,
the SL(4) or the Sim(3) graph.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from .alignment import camera_constrained_sl4, estimate_sl4, sim3_from_shared_frame
from .backend import make_backend, validate_backend_config
from .config import SLAMConfig
from .errors import UserError
from .geometry import decompose_projection, normalize_sl4, to_4x4
from .keyframes import KeyframeSelector
from .submap import StoredKeyframe, confidence_mask, submap_points
from .types import Alignment, Frame, FrameSource, Frontend, LoopCandidate, Retrieval, SubmapPrediction

log = logging.getLogger("sl4slam")

MIN_ALIGNMENT_POINTS = 5


@dataclass
class EdgeReport:
    """One relative measurement added to the graph."""

    kind: str  # "odometry" or "loop"
    submap_from: int
    submap_to: int
    frame_index: int
    model: str
    inlier_ratio: float
    rms: float
    num_points: int
    fallback: str | None = None


@dataclass
class SLAMResult:
    """What a run produces (in memory); ``sl4slam.outputs`` writes it to disk.

    Attributes:
        keyframes: the stored keyframes in time order (one per keyframe, shared frames once).
        T_world_cam: ``(N, 4, 4)`` keyframe poses (world-from-camera, rigid part of the decomposed
            camera; world units are the first submap's).
        K: ``(N, 3, 3)`` keyframe intrinsics decomposed from the world camera matrices.
        H_world_submap: optimized graph nodes.
        T_world_cam_gt: ``(N, 4, 4)`` ground truth for the keyframes, or ``None``.
        edges: every odometry and loop measurement with its quality.
        stats: counts and timings for the summary.
    """

    keyframes: list[StoredKeyframe]
    T_world_cam: np.ndarray
    K: np.ndarray
    H_world_submap: dict[int, np.ndarray]
    T_world_cam_gt: np.ndarray | None
    edges: list[EdgeReport]
    stats: dict = field(default_factory=dict)

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([k.timestamp for k in self.keyframes], dtype=np.float64)


class SLAMPipeline:
    """VGGT-SLAM over a frame source.

    Example::

        pipeline = SLAMPipeline(config, frontend=SimulatedFrontend(config.sim))
        result = pipeline.run(open_source("rgbd_dataset_freiburg1_xyz"))
    """

    def __init__(
        self,
        config: SLAMConfig,
        frontend: Frontend,
        retrieval: Retrieval | None = None,
        on_submap: Callable[["SLAMPipeline", int], None] | None = None,
    ) -> None:
        check_config(config)
        self.config = config
        self.frontend = frontend
        self.retrieval = retrieval
        self.backend = make_backend(config.backend)
        self.selector = KeyframeSelector(config.keyframes)
        self.on_submap = on_submap
        self.keyframes: list[StoredKeyframe] = []
        self._by_frame: dict[int, StoredKeyframe] = {}
        self.edges: list[EdgeReport] = []
        self.timings: dict[str, float] = defaultdict(float)
        self.submap_seconds: list[dict[str, float]] = []
        self.submap_loops: list[int] = []  # loop factors added with each submap
        self.num_submaps = 0
        self.num_frames = 0
        self._gt: dict[int, np.ndarray] = {}
        self._prior: Frame | None = None
        self._prior_points: np.ndarray | None = None  # (H, W, 3) float32, full precision
        self._prior_mask: np.ndarray | None = None
        self._source: FrameSource | None = None
        self._needs_ground_truth = bool(getattr(frontend, "requires_ground_truth", False))
        self.frames_without_ground_truth = 0

    # ------------------------------------------------------------------ driving
    def run(self, source: FrameSource, progress: bool = True) -> SLAMResult:
        """Process every frame of ``source`` and return the optimized result."""
        from tqdm import tqdm

        self._source = source
        total = len(source)
        if self.config.max_frames > 0:
            total = min(total, self.config.max_frames)
        if total < 2:
            raise UserError(f"{source.name}: {total} frame(s) found; SLAM needs at least 2 frames")
        pending: list[Frame] = []
        bar = tqdm(total=total, unit="frame", disable=not progress, desc="sl4slam", leave=False)
        start = time.perf_counter()
        for count, frame in enumerate(source):
            if count >= total:
                break
            if count % max(1, self.config.stride):
                bar.update(1)
                continue
            if self._needs_ground_truth and (frame.depth is None or frame.T_world_cam is None or frame.K is None):
                # e.g. TUM frames whose depth image is not within 0.02 s: the simulator cannot use them
                self.frames_without_ground_truth += 1
                bar.update(1)
                continue
            self.num_frames += 1
            t0 = time.perf_counter()
            is_keyframe = self.selector.is_keyframe(frame.rgb)
            self.timings["keyframes"] += time.perf_counter() - t0
            if is_keyframe:
                pending.append(frame)
                if frame.T_world_cam is not None:
                    self._gt[frame.index] = np.asarray(frame.T_world_cam, dtype=np.float64)
            if len(pending) == self.config.submap.size:
                self.process_submap(pending)
                pending = []
            bar.update(1)
            bar.set_postfix(keyframes=len(self.keyframes) + len(pending), submaps=self.num_submaps,
                            loops=self.num_loops)
        bar.close()
        if pending:
            self.process_submap(pending)
        if not self.keyframes or len(self.keyframes) < 2:
            raise UserError(
                f"{source.name}: only {len(self.keyframes)} keyframe(s) selected from {self.num_frames} frames; "
                "the camera barely moves — lower --tau-disparity or use a longer sequence"
            )
        result = self.result()
        result.stats["seconds_total"] = time.perf_counter() - start
        return result

    @property
    def num_loops(self) -> int:
        return sum(1 for e in self.edges if e.kind == "loop")

    # ------------------------------------------------------------------ one submap
    def process_submap(self, new_frames: Sequence[Frame]) -> None:
        """Reconstruct, align and optimize one submap of new keyframes."""
        submap_id = self.num_submaps
        seconds: dict[str, float] = {}
        cfg = self.config

        loops_before = self.num_loops
        t0 = time.perf_counter()
        described = getattr(self.retrieval, "describe_seconds", 0.0)
        loops: list[LoopCandidate] = []
        if self.retrieval is not None and cfg.submap.w_loop > 0:
            loops = self.retrieval.query(
                [f.index for f in new_frames], [f.rgb for f in new_frames], submap_id, cfg.submap.w_loop
            )[: cfg.submap.w_loop]
            loops = [c for c in loops if c.match_frame in self._by_frame]
        # descriptor extraction (a model, like the frontend) is reported apart from the search
        seconds["retrieval_describe"] = getattr(self.retrieval, "describe_seconds", 0.0) - described
        seconds["retrieval"] = time.perf_counter() - t0 - seconds["retrieval_describe"]

        frames: list[Frame] = ([self._prior] if self._prior is not None else []) + list(new_frames)
        first_new = len(frames) - len(new_frames)
        loop_frames = [self._source.get(c.match_frame) if self._source is not None else None for c in loops]
        frames += [f for f in loop_frames if f is not None]

        t0 = time.perf_counter()
        prediction = self.frontend.reconstruct(frames, submap_id)
        seconds["frontend"] = time.perf_counter() - t0
        _check_prediction(prediction, len(frames))

        t0 = time.perf_counter()
        mask = confidence_mask(prediction.confidence, prediction.depth, cfg.submap.tau_conf)
        # Points are needed now only for the frames that are aligned (the shared frame, the last
        # new keyframe for the next submap, loop frames); the map is rebuilt from stored depth.
        last = first_new + len(new_frames) - 1
        needed = sorted({0, last, *range(first_new + len(new_frames), len(frames))})
        points = dict(zip(needed, submap_points(prediction, cfg.submap.use_point_head, needed)))
        seconds["points"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        if submap_id == 0:
            self.backend.add_submap(0, None)
            seconds["alignment"] = 0.0
        else:
            shared = frames[0]
            prev = self._by_frame[shared.index]
            alignment = self._align_odometry(
                self._prior_points, self._prior_mask, points[0], mask[0],
                (prev.K, prev.T_cam_submap), (prediction.K[0], prediction.T_cam_submap[0]), seed=submap_id,
            )
            self._record_edge("odometry", prev.submap_id, submap_id, shared.index, alignment)
            seconds["alignment"] = time.perf_counter() - t0
            t1 = time.perf_counter()
            self.backend.add_submap(submap_id, self._as_node_measurement(alignment.H),
                                    sigma_scale=cfg.backend.fallback_sigma_scale if alignment.fallback else 1.0)
            seconds["backend"] = time.perf_counter() - t1
        t0 = time.perf_counter()
        for offset, candidate in enumerate(c for c, f in zip(loops, loop_frames) if f is not None):
            slot = len(new_frames) + first_new + offset
            old = self._by_frame[candidate.match_frame]
            try:
                alignment = self._align(
                    old.points(), old.mask(), points[slot], mask[slot], (old.K, old.T_cam_submap),
                    (prediction.K[slot], prediction.T_cam_submap[slot]), seed=submap_id * 1000 + offset + 1,
                )
            except ValueError as exc:
                log.info("loop %d->%d rejected: %s", old.submap_id, submap_id, exc)
                continue
            if alignment.inlier_ratio < self._loop_inlier_gate() or alignment.fallback:
                log.info("loop %d->%d rejected: inlier ratio %.2f", old.submap_id, submap_id, alignment.inlier_ratio)
                continue
            self._record_edge("loop", old.submap_id, submap_id, candidate.match_frame, alignment)
            self.backend.add_loop(old.submap_id, submap_id, self._as_node_measurement(alignment.H))
        seconds["loops"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.backend.update()
        seconds["backend"] = seconds.get("backend", 0.0) + time.perf_counter() - t0

        t0 = time.perf_counter()
        for slot in range(first_new, first_new + len(new_frames)):
            frame = frames[slot]
            stored = StoredKeyframe.from_prediction(prediction, mask, slot, frame.index, frame.timestamp, submap_id)
            self.keyframes.append(stored)
            self._by_frame[frame.index] = stored
        self._prior = frames[last]
        self._prior_points = points[last]
        self._prior_mask = mask[last]
        if self.retrieval is not None:
            self.retrieval.add([f.index for f in new_frames], [f.rgb for f in new_frames], submap_id)
        seconds["store"] = time.perf_counter() - t0

        for key, value in seconds.items():
            self.timings[key] += value
        self.submap_seconds.append(seconds)
        self.submap_loops.append(self.num_loops - loops_before)
        self.num_submaps += 1
        if self.on_submap is not None:
            self.on_submap(self, submap_id)

    def _align(self, X_a_map, mask_a, X_b_map, mask_b, camera_a, camera_b, seed: int) -> Alignment:
        """``H_a_b`` from one frame's pixels seen in submaps a and b (confident in both).

        ``camera_a`` / ``camera_b`` are that frame's ``(K, T_cam_submap)`` in each submap.
        """
        both = np.flatnonzero(mask_a & mask_b)
        limit = self.config.alignment.max_correspondences
        if limit > 0 and len(both) > limit:
            both = both[:: -(-len(both) // limit)]  # evenly strided over the frame
        X_a = X_a_map.reshape(-1, 3)[both].astype(np.float64)
        X_b = X_b_map.reshape(-1, 3)[both].astype(np.float64)
        if len(X_a) < MIN_ALIGNMENT_POINTS:
            raise UserError(
                f"only {len(X_a)} confident pixels shared between submaps; the frontend's confidence is too "
                "low everywhere — lower --tau-conf or check the input images"
            )
        (K_a, T_cam_a), (K_b, T_cam_b) = camera_a, camera_b
        if self.config.backend.kind == "sim3":
            return sim3_from_shared_frame(T_cam_a, T_cam_b, X_a, X_b, self.config.alignment.inlier_threshold)
        # the alignment combines config.alignment.seed with this per-edge seed
        alignment = estimate_sl4(X_a, X_b, self.config.alignment, seed=seed)
        if alignment.fallback is None:
            return alignment
        # Degenerate 15-DOF fit (e.g. a planar shared frame): the frame's two cameras supply the
        # constraints the points lack; keep it when it explains at least as many points.
        constrained = camera_constrained_sl4(
            X_a, X_b, K_a @ to_4x4(T_cam_a)[:3], K_b @ to_4x4(T_cam_b)[:3], alignment.H, self.config.alignment)
        if constrained is not None and constrained.inlier_ratio >= alignment.inlier_ratio:
            constrained.fallback = f"{alignment.fallback}; used the camera-constrained projective fit"
            return constrained
        return alignment

    def _align_odometry(self, *args, **kwargs) -> Alignment:
        try:
            return self._align(*args, **kwargs)
        except ValueError as exc:
            raise UserError(f"cannot align consecutive submaps: {exc}") from None

    def _loop_inlier_gate(self) -> float:
        """Inlier ratio a loop alignment must reach: ``min_loop_inlier_ratio``, or half the median
        ratio of the odometry so far when the model fits consecutive submaps worse than that
        (Sim(3) under a projective distortion): a loop must fit about as well as odometry does."""
        odometry = [e.inlier_ratio for e in self.edges if e.kind == "odometry" and not e.fallback]
        gate = self.config.retrieval.min_loop_inlier_ratio
        return min(gate, 0.5 * float(np.median(odometry))) if odometry else gate

    def _as_node_measurement(self, H: np.ndarray) -> np.ndarray:
        if self.config.backend.kind == "sl4":
            return normalize_sl4(H)
        return H

    def _record_edge(self, kind: str, a: int, b: int, frame_index: int, alignment: Alignment) -> None:
        self.edges.append(EdgeReport(
            kind=kind, submap_from=a, submap_to=b, frame_index=frame_index, model=alignment.model,
            inlier_ratio=float(alignment.inlier_ratio), rms=float(alignment.rms),
            num_points=int(alignment.inliers.size), fallback=alignment.fallback,
        ))
        if alignment.fallback:
            log.info("submap %d->%d: %s", a, b, alignment.fallback)

    # ------------------------------------------------------------------ results
    def result(self) -> SLAMResult:
        """Poses and intrinsics of every stored keyframe under the polished graph estimate
        (``final_estimates``: a batch polish of the whole graph, O(submaps), so call it at the end)."""
        start = time.perf_counter()
        H_world_submap = self.backend.final_estimates()  # batch polish of the whole graph, once per result
        final_seconds = time.perf_counter() - start
        T_world_cam, K = keyframe_cameras(self.keyframes, H_world_submap)
        gt = None
        if self.keyframes and all(k.frame_index in self._gt for k in self.keyframes):
            gt = np.stack([self._gt[k.frame_index] for k in self.keyframes])
        fallbacks = [e for e in self.edges if e.fallback]
        stats = {
            "frames": self.num_frames,
            "keyframes": len(self.keyframes),
            "submaps": self.num_submaps,
            "loops": self.num_loops,
            "fallbacks": len(fallbacks),
            "frames_without_ground_truth": self.frames_without_ground_truth,
            "seconds_by_stage": dict(self.timings),
            "seconds_final_optimization": round(final_seconds, 5),
            "stored_bytes": int(sum(k.nbytes for k in self.keyframes)),
            "seconds_per_submap": {
                stage: round(float(np.median([s.get(stage, 0.0) for s in self.submap_seconds])), 5)
                for stage in sorted({k for s in self.submap_seconds for k in s})
            },
        }
        return SLAMResult(self.keyframes, T_world_cam, K, H_world_submap, gt, list(self.edges), stats)


def keyframe_cameras(keyframes: Sequence[StoredKeyframe], H_world_submap: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """World poses and intrinsics of keyframes: ``P = K [R|t] H_world_submap^-1``, RQ-decomposed.

    Returns ``T_world_cam (N, 4, 4)`` and ``K (N, 3, 3)``.
    """
    if not keyframes:
        return np.zeros((0, 4, 4)), np.zeros((0, 3, 3))
    H_inv = {i: np.linalg.inv(H) for i, H in H_world_submap.items()}
    P = np.stack([k.K @ to_4x4(k.T_cam_submap)[:3] @ H_inv[k.submap_id] for k in keyframes])
    K, T_world_cam, _ = decompose_projection(P)
    return T_world_cam, K


def check_config(config: SLAMConfig) -> None:
    """Raise ``UserError`` for settings the pipeline cannot run with (cheap: call it before loading models)."""
    if config.submap.size < 1:
        raise UserError("--submap-size must be at least 1")
    if config.backend.kind not in ("sl4", "sim3"):
        raise UserError(f"unknown backend '{config.backend.kind}': use --backend sl4 or --backend sim3")
    validate_backend_config(config.backend)
    alignment = config.alignment
    if alignment.ransac_iterations < 1:
        raise UserError(f"--ransac-iterations must be at least 1, got {alignment.ransac_iterations}")
    if not 0.0 < alignment.ransac_confidence < 1.0:
        raise UserError(f"--ransac-confidence must be between 0 and 1 (exclusive), got {alignment.ransac_confidence}")
    if not (np.isfinite(alignment.inlier_threshold) and alignment.inlier_threshold > 0):
        raise UserError(f"--ransac-inlier-threshold must be a positive number, got {alignment.inlier_threshold}")


def _check_prediction(prediction: SubmapPrediction, num_frames: int) -> None:
    S = prediction.depth.shape[0]
    if S != num_frames:
        raise UserError(f"frontend returned {S} frames for a submap of {num_frames}; the frontend is misconfigured")
    for name in ("depth", "confidence", "T_cam_submap", "K"):
        if not np.all(np.isfinite(getattr(prediction, name))):
            raise UserError(f"frontend returned non-finite {name}; check the model weights and input images")
