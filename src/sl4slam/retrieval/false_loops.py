"""False loop proposals on purpose: a retrieval wrapper that measures the loop checks.

Real place recognition proposes wrong places (repeated structures, similar rooms); one false loop
that reaches the graph bends the whole map. :class:`FalseLoopRetrieval` wraps any retrieval and,
with probability ``FalseLoopConfig.rate`` per proposal (seeded), replaces the proposed
match by a *wrong place*: a stored keyframe whose true pose is at least ``min_distance``
metres or ``min_angle`` degrees (between optical axes) from the query's, and which does
not see what the query sees (at most ``max_overlap`` of its ground-truth points, on a
coarse grid, fall inside the query's view). Among those it prefers look-alikes: the one whose small
grey thumbnail correlates best with the query's. Every replacement is recorded in :attr:`injected`
so benchmarks can count how many the checks rejected.

It needs ground truth (poses, depth and intrinsics on the frames), so it is a simulation tool:
the runner refuses it on sources without ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .settings import FalseLoopConfig
from ..errors import UserError
from ..geometry import se3_inverse, unproject_depth
from ..types import Frame, LoopCandidate, Retrieval

THUMBNAIL = (32, 24)
"""Width, height of the grey thumbnails that rank look-alikes."""
GRID = (16, 12)
"""Ground-truth points per stored keyframe (columns, rows) for the overlap test."""
_STREAM = 7  # SeedSequence spawn key of the replacement draws


@dataclass
class _Stored:
    frame_index: int
    submap_id: int
    T_world_cam: np.ndarray
    points_world: np.ndarray  # (GRID cells, 3) ground-truth points seen by this keyframe
    thumbnail: np.ndarray  # (THUMBNAIL cells,) zero-mean, unit-norm grey values


def _thumbnail(rgb: np.ndarray) -> np.ndarray:
    grey = cv2.resize(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), THUMBNAIL,
                      interpolation=cv2.INTER_AREA).astype(np.float64).reshape(-1)
    grey -= grey.mean()
    norm = np.linalg.norm(grey)
    return grey / norm if norm > 0 else grey


def _grid_points(frame: Frame) -> np.ndarray:
    """``(n, 3)`` world points of the frame's ground-truth depth on a coarse grid (valid depths only)."""
    depth = np.asarray(frame.depth, dtype=np.float32)
    height, width = depth.shape
    rows = np.linspace(0, height - 1, GRID[1]).round().astype(int)
    cols = np.linspace(0, width - 1, GRID[0]).round().astype(int)
    sampled = np.zeros_like(depth)
    sampled[np.ix_(rows, cols)] = depth[np.ix_(rows, cols)]
    X = unproject_depth(sampled[None], np.asarray(frame.K)[None], se3_inverse(frame.T_world_cam)[None])[0]
    keep = sampled > 0
    return X[keep].astype(np.float64)


def overlap_fraction(points_world: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray, image_size: tuple[int, int]) -> float:
    """Fraction of ``points_world (n, 3)`` that fall inside a camera's image, in front of it."""
    if len(points_world) == 0:
        return 0.0
    T_cam_world = se3_inverse(T_world_cam)
    X = points_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = X[:, 2]
    front = z > 1e-6
    uv = (X[front] @ np.asarray(K, dtype=np.float64).T)
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    width, height = image_size
    inside = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    return float(inside.sum() / len(points_world))


class FalseLoopRetrieval:
    """A :class:`~sl4slam.types.Retrieval` that replaces some of ``inner``'s proposals by wrong places.

    Args:
        inner: the retrieval whose proposals are corrupted.
        config: the rate, the wrong places' distance, angle and overlap, and the seed.
        tau_interval: the retrieval's exclusion of recent submaps (wrong places respect it too).

    Attributes:
        injected: ``(query_frame, match_frame)`` of every replacement, in order.
        proposed: every candidate returned, in order.
    """

    def __init__(self, inner: Retrieval, config: FalseLoopConfig, tau_interval: int) -> None:
        self.inner = inner
        self.name = f"{inner.name}+false-loops"
        self.config = config
        self.tau_interval = int(tau_interval)
        self._rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(_STREAM,)))
        self._stored: list[_Stored] = []
        self.injected: list[tuple[int, int]] = []
        self.proposed: list[LoopCandidate] = []

    @property
    def describe_seconds(self) -> float:
        return self.inner.describe_seconds

    def add(self, frames: Sequence[Frame], submap_id: int) -> None:
        self.inner.add(frames, submap_id)
        for frame in frames:
            _require_ground_truth(frame)
            self._stored.append(_Stored(int(frame.index), int(submap_id), np.asarray(frame.T_world_cam, np.float64),
                                        _grid_points(frame), _thumbnail(frame.rgb)))

    def close(self) -> None:
        """``inner``'s close (when it has one), and the stored keyframes' poses, points and
        thumbnails freed; :attr:`injected` and :attr:`proposed` stay."""
        if hasattr(self.inner, "close"):
            self.inner.close()
        self._stored = []

    def spill_features(self, folder, in_ram: int) -> None:
        """``inner``'s, when it can keep older keyframes' features in a file."""
        if hasattr(self.inner, "spill_features"):
            self.inner.spill_features(folder, in_ram)

    def mark(self) -> tuple:
        """What :meth:`rewind` needs to return this wrapper and ``inner`` to this moment (``inner``
        must have ``mark``/``rewind`` too)."""
        return (self.inner.mark(), len(self._stored), self._rng.bit_generator.state, len(self.injected),
                len(self.proposed))

    def rewind(self, mark: tuple) -> None:
        """Forget what was stored, drawn and proposed since :meth:`mark` returned ``mark``."""
        inner, stored, state, injected, proposed = mark
        self.inner.rewind(inner)
        del self._stored[stored:], self.injected[injected:], self.proposed[proposed:]
        self._rng.bit_generator.state = state

    def query(self, frames: Sequence[Frame], submap_id: int, max_results: int) -> list[LoopCandidate]:
        proposals = self.inner.query(frames, submap_id, max_results)
        by_index = {int(f.index): f for f in frames}
        out = []
        for candidate in proposals:
            if self._rng.random() < self.config.rate:
                wrong = self._wrong_place(by_index[candidate.query_frame], submap_id)
                if wrong is not None:
                    candidate = LoopCandidate(candidate.query_frame, wrong.frame_index, wrong.submap_id, candidate.distance)
                    self.injected.append((candidate.query_frame, candidate.match_frame))
            out.append(candidate)
        self.proposed.extend(out)
        return out

    def _wrong_place(self, query: Frame, submap_id: int) -> _Stored | None:
        """The most query-like stored keyframe that is far enough and sees something else."""
        _require_ground_truth(query)
        cfg = self.config
        T_query = np.asarray(query.T_world_cam, np.float64)
        height, width = np.asarray(query.rgb).shape[:2]
        eligible = [s for s in self._stored if s.submap_id <= submap_id - 1 - self.tau_interval]
        if not eligible:
            return None
        positions = np.stack([s.T_world_cam[:3, 3] for s in eligible])
        axes = np.stack([s.T_world_cam[:3, 2] for s in eligible])
        distance = np.linalg.norm(positions - T_query[:3, 3], axis=1)
        angle = np.degrees(np.arccos(np.clip(axes @ T_query[:3, 2], -1.0, 1.0)))
        far = (distance >= cfg.min_distance) | (angle >= cfg.min_angle)
        elsewhere = np.array([overlap_fraction(s.points_world, T_query, query.K, (width, height)) <= cfg.max_overlap
                              for s in eligible])
        choices = np.flatnonzero(far & elsewhere)
        if len(choices) == 0:
            return None
        likeness = np.array([eligible[i].thumbnail @ _thumbnail(query.rgb) for i in choices])
        best = choices[likeness >= likeness.max() - 1e-12]
        return eligible[int(self._rng.choice(best))]


def _require_ground_truth(frame: Frame) -> None:
    if frame.T_world_cam is None or frame.depth is None or frame.K is None:
        raise UserError("--sim-false-loop-rate needs frames with ground-truth poses, depth and intrinsics "
                        "(TUM, 7-Scenes or the synthetic world)")
