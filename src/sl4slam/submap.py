"""Dense submap data: confidence masks, points, and the compact per-keyframe store.

A submap's frames are ``[prior frame] + new keyframes + loop frames``. Only the new keyframes are
kept after alignment (the prior frame is kept by the submap where it was new, loop frames by
theirs), each in a compact form: float16 depth, a bit-packed confidence mask, a half-resolution
uint8 confidence rank and the frame's camera — 0.33 MB per keyframe at 518x294. Colours are not
kept: the frontend re-derives them from the source frame when the map is written
(``Frontend.grid_colors``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np

from .atomic import atomic_write_npz
from .geometry import to_4x4, unproject_depth
from .section import Section, setting
from .types import FrameView, SubmapPrediction


@dataclass
class SubmapConfig(Section):
    """Submap assembly (paper 4.1, 5.1)."""

    section: ClassVar[str] = "submap"
    flag_prefix: ClassVar[str] = "submap-"

    size: int = setting(16, common=True, check=lambda v: v >= 1, allowed="at least 1")
    """New keyframes per submap, w. Paper evaluates 8/16/32 (tables use 32); reference CLI: 16."""
    overlap: int = 2
    """Frames shared by consecutive submaps: the last ``overlap`` keyframes of a submap open the next
    one, and the link between the two uses all of them (``sl4slam.alignment.shared``). Each costs one
    more frame per forward. VGGT-SLAM: 1 (decision: docs/decisions/shared-frames.md)."""
    w_loop: int = setting(1, flag='--w-loop', check=lambda v: v >= 0, allowed=">= 0")
    """Loop candidates per submap, each appending its loop frame (paper: 1)."""
    loop_frames: int = setting(2, flag='--loop-frames',
                               check=lambda v: v >= 1, allowed="at least 1: the loop frame itself")
    """Frames of the old submap each loop candidate appends: its loop frame and the keyframes of that
    submap nearest to it. The loop is then measured like a link over several shared frames
    (``sl4slam.alignment.shared``). Each costs one more frame per forward in the submaps that
    propose a loop. VGGT-SLAM: 1 (decision: docs/decisions/shared-frames.md)."""
    tau_conf: float = setting(25.0, flag='--tau-conf')
    """Percentile of the submap's confidence below which pixels are dropped (reference code: 25)."""
    use_point_head: bool = False
    """Use the frontend's point map instead of unprojecting depth (VGGT offers both)."""
    refine_cameras: int = setting(0, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: off)")
    """Refine every frame's pose but the first against the other frames' dense points in the
    submap, by this many Gauss-Newton steps (``sl4slam.refine``); 0: the frontend's poses as they
    are (decision: docs/decisions/frame-refinement.md)."""
    feature_poses: int = setting(0, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: off)")
    """Correct every frame's camera but the first by the ORB features (this many per frame) it
    shares with the other frames of the submap (``sl4slam.feature_poses``); 0: the frontend's
    cameras as they are (decision: docs/decisions/feature-poses.md)."""
    centre_smoothing: bool = setting(True, advanced=True)
    """Smooth each window's camera centres along the camera's path, as far as the centre noise the
    run measures on its shared frames allows (``sl4slam.centres``); needs ``overlap`` >= 2 (one
    shared frame measures no noise). Rotations, depth and intrinsics are kept (decision:
    docs/decisions/centre-smoothing.md)."""
    keyframes_in_ram: int = setting(1024, advanced=True, check=lambda v: v >= 0, allowed=">= 0 (0: every keyframe)")
    """Newest keyframes whose depth, mask and confidence stay in RAM (about 0.36 MB each at
    518x294); older ones are kept in files of the run's folder (``.keyframe_store``, removed when
    the run ends; a temporary folder for a library run) and read back, the same bytes, when a
    loop check or the outputs need them. 0: every keyframe in RAM."""

    def validate(self) -> None:
        super().validate()
        # the next submap opens with this one's newest keyframes: at most all of them (a small submap
        # with the default overlap then shares every new keyframe, never an older shared frame again)
        self._require("overlap", 1 <= self.overlap <= max(self.size, 1),
                      f"at least 1 and at most the submap size ({self.size}): the shared frames are the newest keyframes "
                      "of the submap before")
        # 100 would drop every pixel (an empty map); the percentile is over the whole submap
        self._require("tau_conf", 0 <= self.tau_conf < 100, "a percentile in [0, 100)")


RANK_LEVELS = 255
"""Confidence ranks are stored as uint8: 0..255 spans the submap's 0..100th percentile."""
RANK_SAMPLES = 50_000
"""Confidence values (an evenly strided subset of the submap) that set the rank levels."""


def valid_pixels(confidence: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``(S, H, W)`` bool: finite, positive depth with a finite confidence."""
    # in place: each fresh full-size temporary costs as much as the comparison that fills it
    valid = np.isfinite(depth)
    valid &= depth > 0
    valid &= np.isfinite(confidence)
    return valid


KTH_SAMPLE = 1 << 15
"""Sample size (an evenly strided subset) that brackets the k-th smallest confidence of a submap."""


def _kth_smallest(values: np.ndarray, k: int) -> float:
    """The ``k``-th smallest (0-based) of the finite ``values`` ``(n,)``: ``np.partition(values, k)[k]``.

    A full partition of a submap's millions of confidences dominates the mask's cost. A strided
    sample brackets the k-th value between two sample values ``lo <= hi``; when the counts show it
    lies in ``[lo, hi]`` only those values (a few percent) are partitioned. The counts make the
    answer exact whatever the sample; when the bracket misses (never seen), the full partition runs.
    """
    n = len(values)
    step = n // KTH_SAMPLE
    if step < 8:  # small input: partitioning it outright is as cheap
        return np.partition(values, k)[k]
    sample = values[::step]
    m = len(sample)
    q = k / max(n - 1, 1)
    # ranks of a sample quantile scatter by ~sqrt(m q (1 - q)); a wide margin keeps misses rare
    margin = 6.0 * np.sqrt(m * q * (1.0 - q)) + 0.002 * m + 2.0
    r_lo = int(max(0, np.floor(q * (m - 1) - margin)))
    r_hi = int(min(m - 1, np.ceil(q * (m - 1) + margin)))
    bracket = np.partition(sample, [r_lo, r_hi])
    lo, hi = bracket[r_lo], bracket[r_hi]
    inside = values >= lo
    below = n - int(np.count_nonzero(inside))  # values < lo (they are finite)
    inside &= values <= hi
    kept = values[inside]
    if below <= k < below + len(kept):
        return np.partition(kept, k - below)[k - below]
    return np.partition(values, k)[k]


def _valid_values(confidence: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``confidence[valid]`` ``(n,)``; a view, not a copy, when every pixel is valid (the usual case)."""
    if valid.all():
        return confidence.reshape(-1)
    return confidence[valid]


def confidence_mask(confidence: np.ndarray, depth: np.ndarray, percentile: float) -> np.ndarray:
    """Pixels to trust in one submap: ``(S, H, W)`` bool.

    Keeps pixels whose confidence is strictly above the submap's own ``percentile`` of confidence
    (over all its frames, as in VGGT-SLAM) and whose depth is finite and positive.
    """
    return _mask_from_valid(confidence, valid_pixels(confidence, depth), percentile)


def _mask_from_valid(confidence: np.ndarray, valid: np.ndarray, percentile: float) -> np.ndarray:
    if percentile <= 0 or not valid.any():
        return valid
    values = _valid_values(confidence, valid)
    # the k-th smallest value (no interpolation), not np.percentile: see _kth_smallest
    k = min(len(values) - 1, int(round(percentile / 100.0 * (len(values) - 1))))
    threshold = _kth_smallest(values, k)
    mask = confidence > threshold
    mask &= valid
    return mask


def confidence_levels(confidence: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``(RANK_LEVELS,)`` confidence values at the submap's 1/255 .. 255/255 quantiles (of its valid
    pixels, from an evenly strided subset): ``searchsorted`` against them gives a uint8 rank."""
    return _levels_from_valid(confidence, valid_pixels(confidence, depth))


def _levels_from_valid(confidence: np.ndarray, valid: np.ndarray) -> np.ndarray:
    values = _valid_values(confidence, valid)
    if len(values) == 0:
        return np.full(RANK_LEVELS, np.inf, dtype=np.float32)
    values = values[:: max(1, len(values) // RANK_SAMPLES)]
    return np.quantile(values, np.arange(1, RANK_LEVELS + 1) / (RANK_LEVELS + 1)).astype(np.float32)


def confidence_mask_and_levels(confidence: np.ndarray, depth: np.ndarray, percentile: float) -> tuple[np.ndarray, np.ndarray]:
    """``(confidence_mask(...), confidence_levels(...))`` of one submap, the valid pixels found once."""
    valid = valid_pixels(confidence, depth)
    return _mask_from_valid(confidence, valid, percentile), _levels_from_valid(confidence, valid)


def confidence_ranks(levels: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """uint8 ranks ``np.searchsorted(levels, confidence).astype(np.uint8)`` of ``confidence`` (any shape)
    against the sorted ``levels`` ``(RANK_LEVELS,)`` of :func:`confidence_levels`.

    A binary search per pixel mispredicts a branch at every step. For float32 input each value is
    instead put into a bucket of its order-preserving integer key (``_RankTable``): a bucket that
    holds no level gives the rank by one table look-up; the few values in a bucket with a level
    (or outside the levels' range, or NaN) take ``searchsorted``. The ranks are identical.
    """
    keys = np.asarray(confidence)
    levels = np.asarray(levels)
    table = _rank_table(levels.tobytes()) if keys.dtype == np.float32 and levels.dtype == np.float32 else None
    if table is None:
        return np.searchsorted(levels, keys).astype(np.uint8)
    keys = keys + np.float32(0.0)  # a contiguous copy, with -0.0 made +0.0 (they compare equal)
    bucket = _ordered_keys(keys)
    bucket >>= table.shift
    np.clip(bucket, table.first, table.last, out=bucket)
    bucket -= table.first
    ranks = table.rank[bucket]
    slow = table.has_level[bucket]  # includes NaN and values outside the levels' buckets (clipped into the end ones)
    ranks[slow] = np.searchsorted(levels, keys[slow])
    return ranks


def to_float16(x: np.ndarray) -> np.ndarray:
    """``x.astype(np.float16)``, bit for bit, for an ``(H, W)`` array.

    NumPy converts element by element in software; OpenCV's conversion uses the CPU's float16
    instructions, several times faster, and rounds the same way (to nearest, ties to even, with
    overflow to inf). It only quiets signalling NaNs, which NumPy keeps as they are: NaN pixels
    are converted by NumPy. Falls back to NumPy where OpenCV cannot write float16.
    """
    global _CV_FLOAT16
    if _CV_FLOAT16 and x.dtype == np.float32 and x.ndim == 2:
        try:
            out = cv2.multiply(x, 1.0, dtype=cv2.CV_16F)  # x * 1.0 is x exactly
        except cv2.error:  # an OpenCV without float16 arithmetic
            _CV_FLOAT16 = False
        else:
            nan = np.isnan(x)
            if nan.any():
                out[nan] = x[nan].astype(np.float16)
            return out
    return x.astype(np.float16)


_CV_FLOAT16 = hasattr(cv2, "CV_16F")
"""Whether OpenCV may convert to float16 (cleared at its first refusal)."""


def _ordered_keys(x: np.ndarray) -> np.ndarray:
    """int32 keys of float32 ``x`` ordered as the values (non-NaN; -0.0 and +0.0 differ, so callers
    add +0.0 first): the bits of a negative float, but its magnitude bits inverted."""
    bits = x.view(np.int32)
    keys = bits >> 31  # -1 for negative values, 0 otherwise
    keys &= 0x7FFFFFFF
    keys ^= bits
    return keys


@dataclass(frozen=True)
class _RankTable:
    """Buckets of ``_ordered_keys >> shift`` over the levels' range ``first .. last``: ``rank[b]``
    levels lie in buckets before ``b`` (uint8), ``has_level[b]`` whether bucket ``b`` holds one."""

    shift: int
    first: int
    last: int
    rank: np.ndarray
    has_level: np.ndarray


TABLE_BUCKETS = 1 << 16
"""Most buckets of a rank table (the key shift is chosen so that the levels' range fits)."""


@lru_cache(maxsize=4)
def _rank_table(level_bytes: bytes) -> _RankTable | None:
    """The rank table of float32 levels (given as bytes: one table serves a submap's keyframes);
    ``None`` when the levels are not sorted or hold NaN (then ``searchsorted`` runs as is)."""
    levels = np.frombuffer(level_bytes, dtype=np.float32) + np.float32(0.0)
    if len(levels) == 0 or len(levels) > 255 or np.isnan(levels).any() or (np.diff(levels) < 0).any():
        return None
    keys = _ordered_keys(levels).astype(np.int64)
    span = int(keys[-1] - keys[0])
    shift = max(0, span.bit_length() - (TABLE_BUCKETS - 1).bit_length())
    buckets = keys >> shift
    first, last = int(buckets[0]), int(buckets[-1])
    counts = np.bincount(buckets - first, minlength=last - first + 1)
    rank = (np.cumsum(counts) - counts).astype(np.uint8)
    return _RankTable(shift, first, last, rank, counts > 0)


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

    The three image-sized arrays (``depth``, ``mask_bits``, ``confidence_rank``) can be moved to a
    file (:meth:`spill`); they are then read back from it on every access, the same bytes, and
    the keyframe keeps only its identity and camera in RAM (:attr:`ram_bytes`).
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
            depth=to_float16(prediction.depth[slot]),
            mask_bits=np.packbits(mask[slot]),
            confidence_rank=confidence_ranks(levels, prediction.confidence[slot, ::2, ::2]),
            K=np.asarray(prediction.K[slot], dtype=np.float64),
            T_cam_submap=to_4x4(prediction.T_cam_submap[slot]),
            principal_point=principal_points(prediction)[slot],
        )

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the keyframe's depth (a spilled keyframe answers without reading its file)."""
        spilled = self.__dict__.get("_spill_shape")
        return spilled if spilled is not None else self.depth.shape  # type: ignore[return-value]

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
        """This keyframe as a :class:`FrameView` of its own submap (float16-rounded depth; decision:
        docs/decisions/keyframe-format.md)."""
        return FrameView(self.points(), self.mask(), self.K, self.T_cam_submap)

    @property
    def nbytes(self) -> int:
        """Bytes of everything the keyframe stores (in RAM or in its file; a spilled keyframe answers
        without reading its file)."""
        image_sized = self.__dict__.get("_spill_nbytes")
        if image_sized is None:
            image_sized = sum(getattr(self, name).nbytes for name in _SPILLED)
        return int(image_sized + sum(a.nbytes for a in (self.K, self.T_cam_submap, self.principal_point)))

    @property
    def ram_bytes(self) -> int:
        """Bytes of the arrays the keyframe holds in RAM (the image-sized ones only until spilled)."""
        held = [self.K, self.T_cam_submap, self.principal_point]
        if not self.spilled:
            held += [self.depth, self.mask_bits, self.confidence_rank]
        return int(sum(a.nbytes for a in held))

    @property
    def spilled(self) -> bool:
        """Whether the image-sized arrays live in a file (:meth:`spill`)."""
        return "_spill_path" in self.__dict__

    def spill(self, path: str | os.PathLike, owner: object = None) -> None:
        """Move ``depth``, ``mask_bits`` and ``confidence_rank`` into the file ``path`` (``.npy``
        arrays in one uncompressed ``.npz``, written atomically) and drop them from RAM; every later
        access reads them back. ``owner``: an object that keeps the file's folder alive (a temporary
        folder), held as long as the keyframe. A keyframe spilled already is left as it is."""
        if self.spilled:
            return
        atomic_write_npz(path, {name: getattr(self, name) for name in _SPILLED}, compressed=False)
        self.__dict__["_spill_shape"] = tuple(int(n) for n in self.depth.shape)
        self.__dict__["_spill_nbytes"] = int(sum(self.__dict__[name].nbytes for name in _SPILLED))
        for name in _SPILLED:
            del self.__dict__[name]
        self.__dict__["_spill_path"] = Path(path)
        self.__dict__["_spill_owner"] = owner

    def __getattr__(self, name: str):
        # only reached for an attribute the instance lacks: a spilled array, read back from its file
        spill_path = self.__dict__.get("_spill_path")
        if name in _SPILLED and spill_path is not None:
            with np.load(spill_path) as arrays:
                return arrays[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


_SPILLED = ("depth", "mask_bits", "confidence_rank")
"""The image-sized arrays of a :class:`StoredKeyframe`, which :meth:`StoredKeyframe.spill` moves to a file."""
