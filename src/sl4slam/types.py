"""Records and stage interfaces shared by every part of the pipeline.

Shapes and frames follow docs/architecture.md: ``T_a_b`` maps points in frame ``b`` to frame ``a``;
images are ``(H, W, 3)`` uint8 RGB; geometry is float64, dense per-pixel data float32 (or
smaller when stored).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Iterator, Protocol, Sequence, runtime_checkable

import numpy as np


@dataclass
class Frame:
    """One input frame.

    Attributes:
        index: position in the source sequence (0-based, after any stride).
        timestamp: seconds (dataset time for TUM, index / fps for video, index otherwise).
        rgb: ``(H, W, 3)`` uint8 RGB.
        depth: ``(H, W)`` float32 metres, 0 where invalid; ``None`` when unknown.
        T_world_cam: ``(4, 4)`` float64 ground-truth camera pose (world-from-camera) or ``None``.
        K: ``(3, 3)`` float64 intrinsics of ``rgb`` or ``None``.
        path: where the image came from, for messages.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray | None = None
    T_world_cam: np.ndarray | None = None
    K: np.ndarray | None = None
    path: str | None = None


@runtime_checkable
class FrameSource(Protocol):
    """A finite, re-readable sequence of frames (image folder, video, TUM, 7-Scenes, in memory).

    Attributes:
        name: for messages.
        skipped: inputs that could not be read (one human-readable entry each).
        has_ground_truth: the frames come with depth, a ground-truth pose and intrinsics (RGB-D
            datasets), as the simulated frontend needs.
    """

    name: str
    skipped: list[str]
    has_ground_truth: bool

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[Frame]: ...

    def get(self, index: int) -> Frame:
        """Random access by ``Frame.index``."""
        ...

    def image_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the frames, read without decoding one (``None`` when unknown)."""
        ...

    def calibration(self) -> np.ndarray | None:
        """``(3, 3)`` intrinsics the source knows (a dataset's published calibration), or ``None``."""
        ...


@dataclass
class SubmapPrediction:
    """What a frontend returns for the S frames of one submap (VGGT's outputs, as numpy).

    All per-pixel arrays live on the prediction grid ``(H, W)``, which may differ from the
    input frames' size (VGGT resizes to 518 px wide); ``K`` refers to that grid and
    ``colors`` are the input images resampled onto it, so points and colours correspond.

    Attributes:
        depth: ``(S, H, W)`` float32, depth along the camera z axis in submap units.
        confidence: ``(S, H, W)`` float32, >= 1 (VGGT's ``1 + exp(x)`` activation).
        T_cam_submap: ``(S, 3, 4)`` float64 extrinsics, camera-from-submap; the submap frame is
            the first frame's camera, so ``T_cam_submap[0]`` is ``[I | 0]`` up to noise.
        K: ``(S, 3, 3)`` float64 intrinsics on the prediction grid.
        colors: ``(S, H, W, 3)`` uint8 RGB on the prediction grid.
        points: optional ``(S, H, W, 3)`` float32 point map in the submap frame (VGGT's point
            head); the pipeline unprojects ``depth`` unless told to use this.
        points_confidence: optional ``(S, H, W)`` float32 confidence of ``points``.
        principal_point: optional ``(S, 2)`` float64, the principal point the frontend assumes for
            each frame on the prediction grid (VGGT: the grid centre ``(W/2, H/2)``); the
            projective-to-metric upgrade constrains the cameras to it.
        match_pairs: optional ``(n, 2)`` int64 frame slots ``(first, second)`` the frontend scored,
            when asked (``Frontend.reconstruct(..., match_pairs=...)``).
        match_ratios: optional ``(n,)`` float32 their image-match ratios (VGGT's attention,
            ``sl4slam.models.vggt.attention``; the simulator's true-overlap stand-in).
        image_to_grid: optional ``(S, 3, 3)`` float64 affine map from each input frame's pixels to
            the grid's (integer coordinates at pixel centres in both), so that a known calibration
            of the input frames can be put on the grid (``sl4slam.intrinsics``); ``None``: the
            identity, which only a frontend predicting on the frames' own pixels may leave it.
    """

    depth: np.ndarray
    confidence: np.ndarray
    T_cam_submap: np.ndarray
    K: np.ndarray
    colors: np.ndarray
    points: np.ndarray | None = None
    points_confidence: np.ndarray | None = None
    principal_point: np.ndarray | None = None
    match_pairs: np.ndarray | None = None
    match_ratios: np.ndarray | None = None
    image_to_grid: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.depth.shape[0])


@dataclass(frozen=True)
class FrontendCapabilities:
    """What a frontend can do, declared by it (never guessed from its signature).

    Attributes:
        scores_pairs: it returns image-match ratios of slot pairs when asked
            (``reconstruct(..., match_pairs=...)``), which the attention loop check reads.
        needs_ground_truth: it reads depth and poses from the frames (the simulator); the pipeline
            skips frames without them and refuses sources that have none.
        predicts_intrinsics: the model itself predicts each frame's focal length (VGGT, Depth
            Anything 3); ``False`` where the adapter recovers it from the points (π³).
        accepts_intrinsics: the model can be conditioned on a known calibration
            (``reconstruct(..., intrinsics=...)``: Pi3X, Depth Anything 3).
    """

    scores_pairs: bool = False
    needs_ground_truth: bool = False
    predicts_intrinsics: bool = True
    accepts_intrinsics: bool = False


@runtime_checkable
class Frontend(Protocol):
    """Feed-forward reconstruction of a short window of frames into one submap.

    Attributes:
        name: for messages and caches.
        capabilities: what it can do (:class:`FrontendCapabilities`), declared by the class.
    """

    name: str
    capabilities: FrontendCapabilities

    def reconstruct(self, frames: Sequence[Frame], submap_id: int) -> SubmapPrediction:
        """Reconstruct ``frames`` (in order; the first defines the submap frame).

        ``submap_id`` lets stochastic frontends (the simulator) draw reproducible,
        submap-specific noise; deterministic models ignore it. Keywords a frontend takes when its
        capabilities say so: ``match_pairs`` (a list of slot pairs; ``scores_pairs``), whose
        image-match ratios it returns in ``SubmapPrediction.match_ratios``; ``intrinsics``
        (``(S, 3, 3)`` known K of the input frames in their own pixels; ``accepts_intrinsics``).
        A ``UserError`` means the settings cannot work (it ends the run); any other exception is
        a failure on these frames (the submap is skipped).
        """
        ...

    def prepare(self) -> None:
        """Load what the frontend needs (weights) before any frame is read; ``UserError`` if it
        cannot be had."""
        ...

    def grid_colors(self, frame: Frame) -> np.ndarray:
        """``(H, W, 3)`` uint8 colours of ``frame`` on the prediction grid (as in
        ``SubmapPrediction.colors``), so the map can be coloured without keeping every image."""
        ...


@dataclass(frozen=True)
class LoopCandidate:
    """A retrieved loop-closure match: ``query_frame`` (new keyframe) looks like ``match_frame``."""

    query_frame: int
    match_frame: int
    match_submap: int
    distance: float


@runtime_checkable
class Retrieval(Protocol):
    """Place recognition over stored keyframes.

    The pipeline calls ``query`` with the new keyframes of submap ``submap_id`` before the
    frontend runs, then ``add`` with the same keyframes (as :class:`Frame` records: an
    implementation uses their index and image; simulation wrappers may read their ground truth). Implementations exclude the latest
    ``tau_interval`` stored submaps (ids ``> submap_id - 1 - tau_interval``), reject matches
    whose distance is not below their threshold, and return the best candidates first.
    """

    name: str
    describe_seconds: float
    """Time spent computing descriptors (a model, like the frontend), reported apart from search."""

    def add(self, frames: Sequence[Frame], submap_id: int) -> None: ...

    def query(self, frames: Sequence[Frame], submap_id: int, max_results: int) -> list[LoopCandidate]: ...

    # Optional, for running the model's windows ahead of the graph (``sl4slam.schedule``):
    # ``mark() -> token`` and ``rewind(token)`` forget what was added and asked since the mark, so
    # that the same queries give the same answers again.
    # Optional, for the end of a run (``SLAMPipeline.release``): ``close()`` frees the stored
    # keyframes' descriptors; the retrieval takes and answers nothing more afterwards.


@dataclass
class Alignment:
    """Result of aligning two point sets: ``X_a ~ H_a_b @ X_b``.

    Attributes:
        H: ``(4, 4)`` float64; in SL(4) (det = +1) for the projective model, a similarity
            ``[sR t; 0 1]`` for the Sim(3) models (then det = s^3, not normalized).
        inliers: ``(N,)`` bool over the input correspondences.
        inlier_ratio: fraction of inliers.
        rms: root-mean-square residual of the inliers, in the units of ``X_a``.
        model: "sl4" or "sim3": the model actually fitted.
        fallback: why a constrained or weaker model replaced the requested one, or ``None``.
        extras: statistics of the estimator.
        support: an evenly strided subset of the inlier pairs ``(X_a (M, 3), X_b (M, 3))`` (of all
            pairs for a measurement not fitted to points), kept to weigh the edge by its evidence;
            ``None`` when the estimate used no points.
        support_count: how many pairs the support stands for.
    """

    H: np.ndarray
    inliers: np.ndarray
    inlier_ratio: float
    rms: float
    model: str
    fallback: str | None = None
    extras: dict = field(default_factory=dict)
    support: tuple[np.ndarray, np.ndarray] | None = None
    support_count: int = 0

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())


@dataclass
class FrameView:
    """One frame as reconstructed in one submap: what aligning two submaps needs of it.

    Attributes:
        points: ``(H, W, 3)`` float32 points in the submap frame.
        mask: ``(H, W)`` bool, the confident pixels.
        K: ``(3, 3)`` float64 intrinsics; T_cam_submap: ``(4, 4)`` float64 extrinsics.
    """

    points: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    T_cam_submap: np.ndarray

    @property
    def camera(self) -> np.ndarray:
        """``(3, 4)`` camera matrix ``K [R | t]`` in the submap frame."""
        return self.K @ np.asarray(self.T_cam_submap, dtype=np.float64)[:3]

    @property
    def centre(self) -> np.ndarray:
        """``(3,)`` the camera's centre in the submap frame."""
        T = np.asarray(self.T_cam_submap, dtype=np.float64)
        return -T[:3, :3].T @ T[:3, 3]


class Aligner(ABC):
    """Measures ``H_a_b`` between two submaps from one frame reconstructed in both.

    Attributes:
        model: what it fits ("sl4", "calibration", "hybrid", "sim3-points", "sim3-cameras").
        group: the group of its measurements ("sl4" or "sim3"), which the graph must hold.
    """

    model: str = ""
    group: str = ""

    @abstractmethod
    def align(self, view_a: FrameView, view_b: FrameView, seed: int) -> Alignment:
        """``X_a ~ H_a_b X_b`` from the frame's pixels confident in both views.

        Raises ``ValueError`` when the views share too few usable pixels or the fit degenerates.
        """

    def align_frames(self, pairs: "Sequence[tuple[FrameView, FrameView]]", seed: int) -> Alignment:
        """``X_a ~ H_a_b X_b`` from several frames the two submaps share (``pairs``: each frame's
        view in ``a`` and in ``b``). An aligner that only knows one frame uses the first."""
        return self.align(pairs[0][0], pairs[0][1], seed)

    @abstractmethod
    def camera_edge(self, view_a: FrameView, view_b: FrameView) -> Alignment:
        """The weaker measurement that needs no point fit: the frame's two cameras and the median
        ratio of its depths (used when :meth:`align` fails). Raises ``ValueError`` only when the
        cameras themselves are unusable."""
