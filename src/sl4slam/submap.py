"""Dense submap data: confidence masks, points, and the compact per-keyframe store.

A submap's frames are ``[prior frame] + new keyframes + loop frames``. Only the new keyframes are
kept after alignment (the prior frame is kept by the submap where it was new, loop frames by
theirs), each in a compact form: float16 depth, uint8 colour, a bit-packed confidence mask and the
frame's camera — about 0.8 MB per keyframe at 518x294.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import to_4x4, unproject_depth
from .types import SubmapPrediction


def confidence_mask(confidence: np.ndarray, depth: np.ndarray, percentile: float) -> np.ndarray:
    """Pixels to trust in one submap: ``(S, H, W)`` bool.

    Keeps pixels whose confidence is strictly above the submap's own ``percentile`` of confidence
    (over all its frames, as in VGGT-SLAM) and whose depth is finite and positive.
    """
    valid = np.isfinite(depth) & (depth > 0) & np.isfinite(confidence)
    if not valid.any() or percentile <= 0:
        return valid
    values = confidence[valid]
    # the k-th smallest value (no interpolation): a partition is several times faster than
    # np.percentile on the millions of pixels of a submap
    k = min(len(values) - 1, int(round(percentile / 100.0 * (len(values) - 1))))
    threshold = np.partition(values, k)[k]
    return valid & (confidence > threshold)


def submap_points(prediction: SubmapPrediction, use_point_head: bool = False, slots=None) -> np.ndarray:
    """Dense points ``(S', H, W, 3)`` float32 in the submap frame (first camera).

    ``slots`` selects frames (all by default): the pipeline only needs the frames it aligns.
    """
    slots = slice(None) if slots is None else list(slots)
    if use_point_head and prediction.points is not None:
        return prediction.points[slots].astype(np.float32, copy=False)
    return unproject_depth(prediction.depth[slots], prediction.K[slots], prediction.T_cam_submap[slots])


@dataclass
class StoredKeyframe:
    """One keyframe as kept for the final map and trajectory (compact).

    Attributes:
        frame_index, timestamp: identity of the source frame.
        submap_id: the submap in which this frame was a new keyframe.
        slot: its position in that submap's frame list.
        depth: ``(H, W)`` float16 depth in submap units.
        colors: ``(H, W, 3)`` uint8.
        mask_bits: bit-packed ``(H, W)`` confidence mask.
        K: ``(3, 3)`` float64 intrinsics; T_cam_submap: ``(4, 4)`` float64 extrinsics.
    """

    frame_index: int
    timestamp: float
    submap_id: int
    slot: int
    depth: np.ndarray
    colors: np.ndarray
    mask_bits: np.ndarray
    K: np.ndarray
    T_cam_submap: np.ndarray

    @classmethod
    def from_prediction(
        cls, prediction: SubmapPrediction, mask: np.ndarray, slot: int, frame_index: int, timestamp: float, submap_id: int
    ) -> "StoredKeyframe":
        return cls(
            frame_index=int(frame_index),
            timestamp=float(timestamp),
            submap_id=int(submap_id),
            slot=int(slot),
            depth=prediction.depth[slot].astype(np.float16),
            colors=np.ascontiguousarray(prediction.colors[slot], dtype=np.uint8),
            mask_bits=np.packbits(mask[slot]),
            K=np.asarray(prediction.K[slot], dtype=np.float64),
            T_cam_submap=to_4x4(prediction.T_cam_submap[slot]),
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape  # type: ignore[return-value]

    def mask(self) -> np.ndarray:
        """``(H, W)`` bool confidence mask."""
        H, W = self.shape
        return np.unpackbits(self.mask_bits, count=H * W).reshape(H, W).astype(bool)

    def points(self) -> np.ndarray:
        """``(H, W, 3)`` float32 points in the submap frame."""
        return unproject_depth(self.depth[None].astype(np.float32), self.K[None], self.T_cam_submap[None])[0]

    @property
    def nbytes(self) -> int:
        return int(self.depth.nbytes + self.colors.nbytes + self.mask_bits.nbytes + self.K.nbytes + self.T_cam_submap.nbytes)
