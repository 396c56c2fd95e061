"""Records and stage interfaces shared by every part of the pipeline.

Shapes and frames follow DESIGN.md: ``T_a_b`` maps points in frame ``b`` to frame ``a``;
images are ``(H, W, 3)`` uint8 RGB; geometry is float64, dense per-pixel data float32 (or
smaller when stored).
"""

from __future__ import annotations

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

    ``skipped`` lists inputs that could not be read (one human-readable entry each).
    """

    name: str
    skipped: list[str]

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[Frame]: ...

    def get(self, index: int) -> Frame:
        """Random access by ``Frame.index``."""
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
        principal_point: optional ``(S, 2)`` float64, the principal point the frontend assumes
            for each frame, on the prediction grid (VGGT: the grid centre ``(W/2, H/2)``).
    """

    depth: np.ndarray
    confidence: np.ndarray
    T_cam_submap: np.ndarray
    K: np.ndarray
    colors: np.ndarray
    points: np.ndarray | None = None
    points_confidence: np.ndarray | None = None
    principal_point: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.depth.shape[0])


@runtime_checkable
class Frontend(Protocol):
    """Feed-forward reconstruction of a short window of frames into one submap."""

    name: str

    def reconstruct(self, frames: Sequence[Frame], submap_id: int) -> SubmapPrediction:
        """Reconstruct ``frames`` (in order; the first defines the submap frame).

        ``submap_id`` lets stochastic frontends (the simulator) draw reproducible,
        submap-specific noise; deterministic models ignore it.
        """
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
    frontend runs, then ``add`` with the same keyframes. Implementations exclude the latest
    ``tau_interval`` stored submaps (ids ``> submap_id - 1 - tau_interval``), reject matches
    whose distance is not below their threshold, and return the best candidates first.
    """

    name: str

    def add(self, frame_indices: Sequence[int], images: Sequence[np.ndarray], submap_id: int) -> None: ...

    def query(
        self, frame_indices: Sequence[int], images: Sequence[np.ndarray], submap_id: int, max_results: int
    ) -> list[LoopCandidate]: ...


@dataclass
class Alignment:
    """Result of aligning two point sets: ``X_a ~ H_a_b @ X_b``.

    Attributes:
        H: ``(4, 4)`` float64; in SL(4) (det = +1) for the projective model, a similarity
            ``[sR t; 0 1]`` for the Sim(3) model (then det = s^3, not normalized).
        inliers: ``(N,)`` bool over the input correspondences.
        inlier_ratio: fraction of inliers.
        rms: root-mean-square residual of the inliers, in the units of ``X_a``.
        model: "sl4" or "sim3": the model actually fitted.
        fallback: why a constrained model replaced the requested one, or ``None``.
    """

    H: np.ndarray
    inliers: np.ndarray
    inlier_ratio: float
    rms: float
    model: str
    fallback: str | None = None
    extras: dict = field(default_factory=dict)
