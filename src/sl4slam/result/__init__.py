"""What a run produces: the in-memory result, writing it to a folder, and reading a folder back.

- :class:`SLAMResult`: keyframe poses and intrinsics, where each submap (and keyframe) sits in the
  world, edges, segments, statistics, and where the keyframes' colours come from;
- :func:`keyframe_cameras`, :func:`world_cameras`: keyframe cameras in the world, ``K [R|t] H^-1``;
- ``sl4slam.result.outputs``: the result folder (trajectory, map, keyframes, summary, plot);
- ``sl4slam.result.reading``: a result folder read back (viewer, exports, evaluation).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..errors import UserError
from ..geometry import decompose_projection
from ..submap import StoredKeyframe
from ..types import FrameSource, Frontend

log = logging.getLogger("sl4slam")


@dataclass
class SourceColors:
    """Keyframe colours re-read from a run's source onto its frontend's grid (so the map can be
    coloured without keeping every image): ``colors(keyframe) -> (H, W, 3) uint8``."""

    source: FrameSource
    frontend: Frontend

    def __call__(self, keyframe: StoredKeyframe) -> np.ndarray:
        return self.frontend.grid_colors(self.source.get(keyframe.frame_index))


@dataclass
class SLAMResult:
    """What a run produces (in memory); ``sl4slam.result.outputs`` writes it to disk.

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
        colors: ``keyframe -> (H, W, 3)`` uint8 colours on the prediction grid (e.g. :class:`SourceColors`).
        H_world_keyframe: ``{frame_index: (4, 4)}`` for graphs with a node per keyframe: maps the
            keyframe's submap points into the world through its own node (use :meth:`H_world`).
    """

    keyframes: list[StoredKeyframe]
    T_world_cam: np.ndarray
    K: np.ndarray
    H_world_submap: dict[int, np.ndarray]
    T_world_cam_gt: np.ndarray | None
    edges: list
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


__all__ = ["SLAMResult", "SourceColors", "keyframe_cameras", "world_cameras"]
