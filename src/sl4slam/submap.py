"""Dense submap data: confidence masks, points, and the compact per-keyframe store.

A submap's frames are ``[prior frame] + new keyframes + loop frames``. Only the new keyframes are
kept after alignment (the prior frame is kept by the submap where it was new, loop frames by
theirs), each in a compact form: float16 depth, a bit-packed confidence mask, a half-resolution
uint8 confidence rank and the frame's camera — 0.33 MB per keyframe at 518x294. Colours are not
kept: the frontend re-derives them from the source frame when the map is written
(``Frontend.grid_colors``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import to_4x4, unproject_depth
from .types import FrameView, SubmapPrediction

RANK_LEVELS = 255
"""Confidence ranks are stored as uint8: 0..255 spans the submap's 0..100th percentile."""
RANK_SAMPLES = 50_000
"""Confidence values (an evenly strided subset of the submap) that set the rank levels."""


def valid_pixels(confidence: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``(S, H, W)`` bool: finite, positive depth with a finite confidence."""
    return np.isfinite(depth) & (depth > 0) & np.isfinite(confidence)


def confidence_mask(confidence: np.ndarray, depth: np.ndarray, percentile: float) -> np.ndarray:
    """Pixels to trust in one submap: ``(S, H, W)`` bool.

    Keeps pixels whose confidence is strictly above the submap's own ``percentile`` of confidence
    (over all its frames, as in VGGT-SLAM) and whose depth is finite and positive.
    """
    valid = valid_pixels(confidence, depth)
    if not valid.any() or percentile <= 0:
        return valid
    values = confidence[valid]
    # the k-th smallest value (no interpolation): a partition is several times faster than
    # np.percentile on the millions of pixels of a submap
    k = min(len(values) - 1, int(round(percentile / 100.0 * (len(values) - 1))))
    threshold = np.partition(values, k)[k]
    return valid & (confidence > threshold)


def confidence_levels(confidence: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``(RANK_LEVELS,)`` confidence values at the submap's 1/255 .. 255/255 quantiles (of its valid
    pixels, from an evenly strided subset): ``searchsorted`` against them gives a uint8 rank."""
    values = confidence[valid_pixels(confidence, depth)]
    if len(values) == 0:
        return np.full(RANK_LEVELS, np.inf, dtype=np.float32)
    values = values[:: max(1, len(values) // RANK_SAMPLES)]
    return np.quantile(values, np.arange(1, RANK_LEVELS + 1) / (RANK_LEVELS + 1)).astype(np.float32)


def submap_points(prediction: SubmapPrediction, use_point_head: bool = False, slots=None) -> np.ndarray:
    """Dense points ``(S', H, W, 3)`` float32 in the submap frame (first camera).

    ``slots`` selects frames (all by default): the pipeline only needs the frames it aligns.
    """
    slots = slice(None) if slots is None else list(slots)
    if use_point_head and prediction.points is not None:
        return prediction.points[slots].astype(np.float32, copy=False)
    return unproject_depth(prediction.depth[slots], prediction.K[slots], prediction.T_cam_submap[slots])


def principal_points(prediction: SubmapPrediction) -> np.ndarray:
    """``(S, 2)`` float64 the principal point the frontend assumes for each frame (pixels): its own,
    else VGGT's convention, the centre of the prediction grid."""
    if prediction.principal_point is not None:
        return np.asarray(prediction.principal_point, dtype=np.float64)
    height, width = prediction.depth.shape[1:3]
    return np.tile([width / 2.0, height / 2.0], (len(prediction.depth), 1))


@dataclass
class StoredKeyframe:
    """One keyframe as kept for the final map and trajectory (compact).

    Attributes:
        frame_index, timestamp: identity of the source frame.
        submap_id: the submap in which this frame was a new keyframe.
        slot: its position in that submap's frame list.
        depth: ``(H, W)`` float16 depth in submap units.
        mask_bits: bit-packed ``(H, W)`` confidence mask.
        confidence_rank: ``(ceil(H / 2), ceil(W / 2))`` uint8 percentile of each pixel's confidence
            in its submap (0..255 for 0..100 %), every second pixel in each direction.
        K: ``(3, 3)`` float64 intrinsics; T_cam_submap: ``(4, 4)`` float64 extrinsics.
        principal_point: ``(2,)`` float64 the principal point the frontend assumes (pixels).
    """

    frame_index: int
    timestamp: float
    submap_id: int
    slot: int
    depth: np.ndarray
    mask_bits: np.ndarray
    confidence_rank: np.ndarray
    K: np.ndarray
    T_cam_submap: np.ndarray
    principal_point: np.ndarray

    @classmethod
    def from_prediction(
        cls, prediction: SubmapPrediction, mask: np.ndarray, levels: np.ndarray, slot: int, frame_index: int,
        timestamp: float, submap_id: int,
    ) -> "StoredKeyframe":
        """Keep frame ``slot`` of a submap; ``mask`` ``(S, H, W)`` and ``levels`` from
        :func:`confidence_mask` and :func:`confidence_levels` of the same submap."""
        return cls(
            frame_index=int(frame_index),
            timestamp=float(timestamp),
            submap_id=int(submap_id),
            slot=int(slot),
            depth=prediction.depth[slot].astype(np.float16),
            mask_bits=np.packbits(mask[slot]),
            confidence_rank=np.searchsorted(levels, prediction.confidence[slot, ::2, ::2]).astype(np.uint8),
            K=np.asarray(prediction.K[slot], dtype=np.float64),
            T_cam_submap=to_4x4(prediction.T_cam_submap[slot]),
            principal_point=principal_points(prediction)[slot],
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape  # type: ignore[return-value]

    def mask(self) -> np.ndarray:
        """``(H, W)`` bool confidence mask."""
        H, W = self.shape
        return np.unpackbits(self.mask_bits, count=H * W).reshape(H, W).astype(bool)

    def confidence_percentile(self) -> np.ndarray:
        """``(H, W)`` float32 percentile (0..100) of each pixel's confidence in its submap
        (nearest of the stored half-resolution ranks)."""
        H, W = self.shape
        full = np.repeat(np.repeat(self.confidence_rank, 2, axis=0), 2, axis=1)[:H, :W]
        return full.astype(np.float32) * (100.0 / RANK_LEVELS)

    def points(self) -> np.ndarray:
        """``(H, W, 3)`` float32 points in the submap frame."""
        return unproject_depth(self.depth[None].astype(np.float32), self.K[None], self.T_cam_submap[None])[0]

    def view(self) -> FrameView:
        """This keyframe as a :class:`FrameView` of its own submap (float16-rounded depth; see
        ``benchmarks/bench_robustness.py`` for why that precision suffices for loop alignment)."""
        return FrameView(self.points(), self.mask(), self.K, self.T_cam_submap)

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.depth, self.mask_bits, self.confidence_rank, self.K, self.T_cam_submap,
                                          self.principal_point)))
