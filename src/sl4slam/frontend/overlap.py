"""A stand-in for VGGT's image-match ratio, computed from ground truth (for the simulated frontend).

VGGT-SLAM 2.0 keeps a loop only if VGGT's attention says the query keyframe and the loop frame
overlap (``sl4slam.models.vggt.attention``): per token of the second image, how strongly it attends
to its best patch of the first, relative to the first image's own tokens; the score is the mean of
the top quarter of those per-token values. The simulated frontend has no attention, so it scores a
pair from what that attention responds to, the true overlap, in the same shape: per patch of the
second frame (VGGT's 14 px patches), the fraction of its pixels with a measured depth whose true
point the first frame sees (inside its image, in front of it, and within ``depth_tolerance`` of the
first frame's own measured depth there, i.e. not occluded); the score is the mean of the top quarter
of those fractions. It is 1 when at least a quarter of the second image shows surfaces the first one
shows, and falls towards 0 as the shared part shrinks; VGGT-SLAM 2.0's threshold 0.85 then keeps
pairs sharing about a fifth of the image or more.

This is a stand-in, not a model of VGGT's score: it measures the loop check's logic with perfect
overlap knowledge, so simulated runs show what the check does when the score is right, not how often
VGGT's score is wrong.
"""

from __future__ import annotations

import numpy as np

from ..geometry import se3_inverse, unproject_depth
from ..models.vggt.attention import mean_top_quarter
from ..types import Frame

PATCH_PX = 14
"""Side of the patches the per-patch overlap is taken over (VGGT's patch size)."""


def overlap_match_ratio(first: Frame, second: Frame, depth_tolerance: float = 0.1, patch: int = PATCH_PX) -> float:
    """The stand-in score of the module doc for ``(first, second)``; both need depth, pose and K.

    Raises:
        ValueError: a frame lacks ground truth.
    """
    for frame in (first, second):
        if frame.depth is None or frame.T_world_cam is None or frame.K is None:
            raise ValueError(f"frame {frame.index} has no ground-truth depth, pose and intrinsics for the overlap score")
    depth_b = np.asarray(second.depth, dtype=np.float32)
    depth_a = np.asarray(first.depth, dtype=np.float32)
    height, width = depth_b.shape
    measured = depth_b > 0
    T_a_b = se3_inverse(np.asarray(first.T_world_cam, np.float64)) @ np.asarray(second.T_world_cam, np.float64)
    X = unproject_depth(depth_b[None], np.asarray(second.K, np.float64)[None], se3_inverse(T_a_b)[None])[0]
    X = X.reshape(-1, 3).astype(np.float64)  # second frame's points in the first camera's frame
    z = X[:, 2]
    front = measured.reshape(-1) & (z > 1e-9)
    uvw = X @ np.asarray(first.K, np.float64).T
    safe = np.where(front, uvw[:, 2], 1.0)
    column, row = np.rint(uvw[:, 0] / safe).astype(np.int64), np.rint(uvw[:, 1] / safe).astype(np.int64)
    height_a, width_a = depth_a.shape
    inside = front & (column >= 0) & (column < width_a) & (row >= 0) & (row < height_a)
    seen = np.zeros(len(z), dtype=bool)
    there = depth_a[row[inside], column[inside]]
    seen[inside] = (there > 0) & (np.abs(z[inside] - there) <= depth_tolerance * there)
    rows, cols = height // patch, width // patch
    if rows == 0 or cols == 0:
        raise ValueError(f"frame {second.index} is smaller than one {patch} px patch")
    crop = (slice(0, rows * patch), slice(0, cols * patch))
    seen_patches = seen.reshape(height, width)[crop].reshape(rows, patch, cols, patch).sum(axis=(1, 3))
    measured_patches = measured[crop].reshape(rows, patch, cols, patch).sum(axis=(1, 3))
    fractions = np.where(measured_patches > 0, seen_patches / np.maximum(measured_patches, 1), 0.0)
    return mean_top_quarter(fractions)
