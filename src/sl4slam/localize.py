"""Poses for every frame, not only keyframes: each other frame is localized against a keyframe.

Method (per non-keyframe):

1. The nearest keyframe in time is the reference (the second nearest is tried when it fails).
2. Shi-Tomasi corners on the reference keyframe's image (inside its confidence mask) are tracked
   into the frame with pyramidal Lucas-Kanade, and back; a track is kept when the round trip
   returns within ``max_round_trip_px``.
3. Each kept track takes its 3D point from the keyframe's dense points at the corner's pixel, in
   the keyframe's *submap* frame, where the frontend's reconstruction is Euclidean and the
   keyframe's own ``K`` describes the camera.
4. PnP in RANSAC (OpenCV, on normalized coordinates so a skewed ``K`` is exact), refined by
   Levenberg-Marquardt on the inliers, gives the frame's ``T_cam_submap``.
5. The world may be slightly projective (an SL(4) graph): the frame's camera in the world is
   ``P = K [R | t] H_world_submap^-1``, decomposed (RQ) exactly as the keyframes' poses are, so a
   non-keyframe's pose is consistent with its keyframe's whatever the world's distortion.

A frame is reported as failed (listed with its reason, never invented) when neither keyframe gives
``min_inliers`` PnP inliers making up ``min_inlier_ratio`` of the tracks. Keyframes keep their own
poses. From a result folder written with the compact keyframe layout (the default), each keyframe
file holds its depth, camera and projective map in its submap frame, so the localization is the
run's own. From a full-layout folder (no graph nodes saved), the keyframes' world points,
decomposed ``K`` and pose stand in for the submap frame (``H = I``): exact when the world is
Euclidean, first-order otherwise.

Frames are resampled onto the keyframes' grid (the grid ``K`` refers to) by ``to_grid``: the
frontend's own ``grid_colors`` (VGGT's preprocessing; nothing for the simulator).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable, ClassVar, Iterable, Iterator, Sequence

import cv2
import numpy as np


from .errors import UserError
from .geometry import decompose_projection, se3_inverse, to_4x4
from .progress import Progress
from .section import Section, setting
from .types import Frame


@dataclass
class LocalizationConfig(Section):
    """Poses of every frame (``--all-frames``, ``sl4slam.localize``): tracking into the nearest keyframe
    and PnP against its points (defaults: OpenCV's, or ours: docs/decisions/localization.md)."""

    section: ClassVar[str] = "localize"
    flag_prefix: ClassVar[str] = "localize-"

    max_corners: int = setting(500, advanced=True, check=lambda v: v >= 4, allowed="at least 4")
    """Shi-Tomasi corners per keyframe; tracking cost grows linearly with the corners
    (decision: docs/decisions/localization.md)."""
    corner_quality: float = setting(0.01, advanced=True, check=lambda v: 0 < v < 1, allowed="in (0, 1)")
    """Shi-Tomasi quality level (as the keyframe selector)."""
    corner_min_distance: float = setting(5.0, advanced=True, check=lambda v: v >= 0, allowed=">= 0 px")
    """Minimum spacing of corners, px on the keyframe grid."""
    lk_window: int = setting(15, advanced=True, check=lambda v: v >= 3, allowed="at least 3 px")
    """Lucas-Kanade window, px (decision: docs/decisions/localization.md)."""
    lk_levels: int = setting(3, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Lucas-Kanade pyramid levels above the full image (as the keyframe selector)."""
    max_round_trip_px: float = setting(1.0, advanced=True,
                                       check=lambda v: v > 0, allowed="a positive distance in px")
    """Forward-backward tracking error above which a track is dropped."""
    ransac_threshold_px: float = setting(2.0, advanced=True,
                                         check=lambda v: v > 0, allowed="a positive distance in px")
    """PnP RANSAC inlier threshold, px."""
    ransac_iterations: int = setting(200, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """PnP RANSAC hypotheses at most."""
    min_inliers: int = setting(15, advanced=True, check=lambda v: v >= 4, allowed="at least 4")
    """Fewer PnP inliers than this is a failed localization."""
    min_inlier_ratio: float = setting(0.3, advanced=True, check=lambda v: 0 <= v <= 1, allowed="in [0, 1]")
    """A pose whose inliers are fewer than this fraction of the tracks is a failed localization."""
    seed: int = setting(0, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Seed of OpenCV's RANSAC (combined with the frame index)."""


@dataclass
class KeyframeView:
    """What localization needs of one keyframe.

    Attributes:
        frame_index, timestamp: the keyframe's source frame.
        image: ``(H, W, 3)`` uint8 RGB on the reconstruction grid.
        mask: ``(H, W)`` bool confident pixels.
        K: ``(3, 3)`` intrinsics of the keyframe in its local frame (on the grid).
        T_cam_local: ``(4, 4)`` camera-from-local rigid transform.
        H_world_local: ``(4, 4)`` projective map from the local frame to the world.
        T_world_cam: ``(4, 4)`` the keyframe's reported pose (kept as is in the output).
        points: callable giving ``(H, W, 3)`` float32 points in the local frame (computed on demand).
    """

    frame_index: int
    timestamp: float
    image: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    T_cam_local: np.ndarray
    H_world_local: np.ndarray
    T_world_cam: np.ndarray
    points: Callable[[], np.ndarray]


@dataclass
class FramePose:
    """A localized frame: world pose and intrinsics (decomposed), and what supported it."""

    frame_index: int
    timestamp: float
    T_world_cam: np.ndarray
    K: np.ndarray
    keyframe: int
    tracks: int
    inliers: int


@dataclass
class AllFramePoses:
    """Poses of every frame of a source.

    Attributes:
        timestamps, T_world_cam: ``(N,)``, ``(N, 4, 4)`` in time order: keyframes (their own poses)
            and localized frames.
        is_keyframe: ``(N,)`` bool.
        frame_indices: ``(N,)``.
        failed: ``[(frame_index, reason)]`` frames without a pose.
        seconds_per_frame: median localization time of a non-keyframe.
        T_world_cam_gt: ``(N, 4, 4)`` ground truth of the posed frames when every one has it.
    """

    timestamps: np.ndarray
    T_world_cam: np.ndarray
    is_keyframe: np.ndarray
    frame_indices: np.ndarray
    failed: list[tuple[int, str]] = field(default_factory=list)
    seconds_per_frame: float = 0.0
    T_world_cam_gt: np.ndarray | None = None

    def summary(self) -> dict:
        return {"frames": int(len(self.frame_indices) + len(self.failed)), "keyframes": int(self.is_keyframe.sum()),
                "localized": int((~self.is_keyframe).sum()), "failed": [{"frame": f, "reason": r} for f, r in self.failed],
                "ms_per_frame_median": round(1000 * self.seconds_per_frame, 3)}


# ------------------------------------------------------------------------- keyframe views
class _LRU:
    """A tiny cache of the last few keyframes' dense points (frames come in order)."""

    def __init__(self, size: int = 3) -> None:
        self.size, self.items = size, OrderedDict()

    def get(self, key, make):
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        value = self.items[key] = make()
        if len(self.items) > self.size:
            self.items.popitem(last=False)
        return value


def views_from_pipeline(result) -> list[KeyframeView]:
    """Keyframe views from a run in memory (``SLAMResult``: its stored keyframes in their submap
    frames, the graph nodes, the reported poses; exact in a projective world)."""
    from .result.reading import keyframe_colors

    return [KeyframeView(frame_index=k.frame_index, timestamp=k.timestamp, image=keyframe_colors(k, result.keyframe_colors), mask=k.mask(),
                         K=k.K, T_cam_local=to_4x4(k.T_cam_submap),
                         H_world_local=np.asarray(result.H_world_submap[k.submap_id]), T_world_cam=np.asarray(T),
                         points=k.points)
            for k, T in zip(result.keyframes, result.T_world_cam)]


def views_from_result(result) -> list[KeyframeView]:
    """Keyframe views from a result folder: in each keyframe's submap frame when its file is
    compact (exact, as :func:`views_from_pipeline`), else in the world frame with ``H = I`` (see
    the module docstring)."""
    views = []
    for record in result.require_keyframes("all-frame localization"):
        data = record.load()
        if data.depth is not None:  # compact: the keyframe's own submap frame
            views.append(KeyframeView(frame_index=record.frame_index, timestamp=record.timestamp, image=data.colors,
                                      mask=data.mask, K=data.K_local, T_cam_local=to_4x4(data.T_cam_local),
                                      H_world_local=data.H_world_local, T_world_cam=record.T_world_cam,
                                      points=lambda record=record: record.load().points_local()))
            continue
        views.append(KeyframeView(frame_index=record.frame_index, timestamp=record.timestamp, image=data.colors,
                                  mask=data.mask, K=record.K, T_cam_local=se3_inverse(record.T_world_cam),
                                  H_world_local=np.eye(4), T_world_cam=record.T_world_cam,
                                  points=lambda record=record: record.load().points_world))
    return views


# ------------------------------------------------------------------------- localization
class FrameLocalizer:
    """Localizes frames against a fixed set of keyframes (see the module docstring)."""

    def __init__(self, keyframes: Sequence[KeyframeView], config: LocalizationConfig | None = None,
                 to_grid: Callable[[Frame], np.ndarray] | None = None) -> None:
        self.config = config or LocalizationConfig()
        if not keyframes:
            raise UserError("all-frame localization needs at least one keyframe")
        self.keyframes = sorted(keyframes, key=lambda k: k.frame_index)
        self._indices = np.array([k.frame_index for k in self.keyframes])
        self.to_grid = to_grid or (lambda frame: frame.rgb)
        self._points = _LRU(4)
        self._corners = _LRU(4)

    def _grey(self, view: KeyframeView) -> np.ndarray:
        return cv2.cvtColor(view.image, cv2.COLOR_RGB2GRAY)

    def _keyframe_corners(self, position: int) -> tuple[np.ndarray, np.ndarray]:
        view = self.keyframes[position]

        def make():
            grey = self._grey(view)
            corners = cv2.goodFeaturesToTrack(grey, maxCorners=self.config.max_corners, qualityLevel=self.config.corner_quality,
                                              minDistance=self.config.corner_min_distance, mask=view.mask.astype(np.uint8))
            return grey, np.zeros((0, 1, 2), np.float32) if corners is None else corners.astype(np.float32)

        return self._corners.get(position, make)

    def candidates(self, frame_index: int) -> list[int]:
        """Positions of the two keyframes nearest in time to ``frame_index``, nearest first."""
        order = np.argsort(np.abs(self._indices - frame_index), kind="stable")
        return order[:2].tolist()

    def localize(self, frame: Frame) -> FramePose | str:
        """The frame's pose, or the reason it could not be localized."""
        grey = cv2.cvtColor(np.ascontiguousarray(self.to_grid(frame)), cv2.COLOR_RGB2GRAY)
        reasons = []
        for position in self.candidates(frame.index):
            outcome = self._against(position, grey, frame)
            if isinstance(outcome, FramePose):
                return outcome
            reasons.append(f"keyframe {self.keyframes[position].frame_index}: {outcome}")
        return "; ".join(reasons)

    def _against(self, position: int, grey: np.ndarray, frame: Frame) -> FramePose | str:
        cfg, view = self.config, self.keyframes[position]
        key_grey, corners = self._keyframe_corners(position)
        if grey.shape != key_grey.shape:
            raise UserError(f"frame {frame.index} is {grey.shape[1]}x{grey.shape[0]} on the grid but keyframe "
                            f"{view.frame_index} is {key_grey.shape[1]}x{key_grey.shape[0]}; the frames must share one size")
        if len(corners) < cfg.min_inliers:
            return f"only {len(corners)} corners on the keyframe"
        lk = dict(winSize=(cfg.lk_window, cfg.lk_window), maxLevel=cfg.lk_levels)
        tracked, status, _ = cv2.calcOpticalFlowPyrLK(key_grey, grey, corners, None, **lk)
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(grey, key_grey, tracked, None, **lk)
        ok = (status.ravel() == 1) & (status_back.ravel() == 1)
        ok &= np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < cfg.max_round_trip_px
        if ok.sum() < cfg.min_inliers:
            return f"{int(ok.sum())} corners tracked"
        source = np.round(corners.reshape(-1, 2)[ok]).astype(np.int64)
        target = tracked.reshape(-1, 2)[ok].astype(np.float64)
        height, width = view.mask.shape
        source[:, 0] = np.clip(source[:, 0], 0, width - 1)
        source[:, 1] = np.clip(source[:, 1], 0, height - 1)
        inside = view.mask[source[:, 1], source[:, 0]]
        points = self._points.get(position, view.points)
        X = points[source[inside, 1], source[inside, 0]].astype(np.float64)
        uv = target[inside]
        if len(X) < cfg.min_inliers:
            return f"{len(X)} tracks on confident pixels"
        # normalized image coordinates: a skewed K is handled exactly, PnP then runs with K = I
        K = view.K / view.K[2, 2]
        normalized = (np.linalg.solve(K, np.c_[uv, np.ones(len(uv))].T).T)[:, :2]
        focal = 0.5 * (K[0, 0] + K[1, 1])
        T_guess = view.T_cam_local
        rvec0, _ = cv2.Rodrigues(T_guess[:3, :3])
        cv2.setRNGSeed(int(cfg.seed) * 1_000_003 + int(frame.index))
        ok_pnp, rvec, tvec, inliers = cv2.solvePnPRansac(
            X, normalized, np.eye(3), None, rvec=rvec0.copy(), tvec=T_guess[:3, 3].reshape(3, 1).copy(),
            useExtrinsicGuess=True, iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.ransac_threshold_px / focal, confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
        count = 0 if inliers is None else len(inliers)
        if not ok_pnp or count < cfg.min_inliers or count < cfg.min_inlier_ratio * len(X):
            return f"PnP kept {count} of {len(X)} tracks"
        inliers = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(X[inliers], normalized[inliers], np.eye(3), None, rvec, tvec)
        T_cam_local = np.eye(4)
        T_cam_local[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_cam_local[:3, 3] = tvec.ravel()
        P = view.K @ T_cam_local[:3] @ np.linalg.inv(view.H_world_local)
        K_world, T_world_cam, _ = decompose_projection(P)
        if not np.isfinite(T_world_cam).all():
            return "degenerate camera"
        return FramePose(frame.index, float(frame.timestamp), T_world_cam, K_world, view.frame_index, len(X), count)


def _reported(frames: Iterable[Frame], reporter: Progress) -> Iterator[Frame]:
    """``frames``, reporting each one done to ``reporter`` (closed at the end)."""
    try:
        for frame in frames:
            yield frame
            reporter.frame()
    finally:
        reporter.close()


def localize_frames(frames: Iterable[Frame], keyframes: Sequence[KeyframeView], config: LocalizationConfig | None = None,
                    to_grid: Callable[[Frame], np.ndarray] | None = None, progress: bool = False) -> AllFramePoses:
    """Poses of every frame of ``frames`` (keyframes keep theirs; see the module docstring)."""
    localizer = FrameLocalizer(keyframes, config, to_grid)
    by_index = {k.frame_index: k for k in keyframes}
    stamps, poses, is_key, indices, gts, failed, seconds = [], [], [], [], [], [], []
    total = len(frames) if hasattr(frames, "__len__") else None
    reporter = Progress(total, enabled=progress, description="all frames")
    for frame in _reported(frames, reporter):
        if frame.index in by_index:
            view = by_index[frame.index]
            stamps.append(view.timestamp)
            poses.append(view.T_world_cam)
            is_key.append(True)
        else:
            start = time.perf_counter()
            outcome = localizer.localize(frame)
            seconds.append(time.perf_counter() - start)
            if isinstance(outcome, str):
                failed.append((int(frame.index), outcome))
                continue
            stamps.append(outcome.timestamp)
            poses.append(outcome.T_world_cam)
            is_key.append(False)
        indices.append(int(frame.index))
        gts.append(frame.T_world_cam)
    order = np.argsort(np.array(stamps), kind="stable")
    result = AllFramePoses(
        timestamps=np.array(stamps, np.float64)[order], T_world_cam=np.array(poses, np.float64).reshape(-1, 4, 4)[order],
        is_keyframe=np.array(is_key, bool)[order], frame_indices=np.array(indices, np.int64)[order], failed=failed,
        seconds_per_frame=float(np.median(seconds)) if seconds else 0.0)
    if gts and all(g is not None for g in gts):
        result.T_world_cam_gt = np.array(gts, np.float64)[order]
    return result


@dataclass
class SplitATE:
    """ATE of an all-frame trajectory under one Sim(3) alignment, split by frame kind."""

    all: float
    keyframes: float
    non_keyframes: float
    count_keyframes: int
    count_non_keyframes: int


def split_ate(poses: AllFramePoses) -> SplitATE:
    """RMSE translation error of keyframes and of the other frames after one Sim(3) alignment of the
    whole trajectory onto its ground truth (``sl4slam.metrics.ate``)."""
    from .metrics import ate

    if poses.T_world_cam_gt is None:
        raise UserError("the frames carry no ground truth; all-frame ATE needs a sequence with ground-truth poses")
    # align on frame indices as time stamps: keeps every pair, whatever the frame rate
    stamps = poses.frame_indices.astype(np.float64)
    result = ate(stamps, poses.T_world_cam, stamps, poses.T_world_cam_gt, max_time_diff=0.1)
    errors = np.linalg.norm(result.positions_aligned - result.positions_gt, axis=1)

    def rmse(values: np.ndarray) -> float:
        return float(np.sqrt(np.mean(values**2))) if len(values) else float("nan")

    return SplitATE(rmse(errors), rmse(errors[poses.is_keyframe]), rmse(errors[~poses.is_keyframe]),
                    int(poses.is_keyframe.sum()), int((~poses.is_keyframe).sum()))
