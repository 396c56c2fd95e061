"""The keyframes a run keeps: each stored compactly (``sl4slam.submap.StoredKeyframe``) in time
order, found by frame index, with the ground-truth poses the source gave for them.

RAM stays bounded on long runs: beyond the newest ``in_ram`` keyframes, a keyframe's image-sized
arrays (depth, mask, confidence: about 0.36 MB at 518x294) move to a file of the store's folder
and are read back, the same bytes, whenever a loop check, the map or the outputs need them. What
the graph and retrieval use (identity, camera) stays in RAM.
"""

from __future__ import annotations

import bisect
import os
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from .submap import StoredKeyframe
from .types import Frame


class KeyframeStore:
    """The stored keyframes of a run, in the order they were stored (time order).

    Args:
        in_ram: how many of the newest keyframes keep their image-sized arrays in RAM; older ones
            are spilled to files (``0``: every keyframe stays in RAM).
        folder: where spilled keyframes go (created when the first one is spilled); ``None``: a
            temporary folder, removed with the store.

    Attributes:
        keyframes: the stored keyframes (the list itself: readers may hold it while the run grows).
    """

    def __init__(self, in_ram: int = 0, folder: str | os.PathLike | None = None) -> None:
        self.keyframes: list[StoredKeyframe] = []
        self._by_frame: dict[int, StoredKeyframe] = {}
        self._ground_truth: dict[int, np.ndarray] = {}
        self.in_ram = int(in_ram)
        self._folder = Path(folder) if folder is not None else None
        self._temporary: tempfile.TemporaryDirectory | None = None
        self._spilled = 0  # keyframes[:_spilled] are spilled

    def __len__(self) -> int:
        return len(self.keyframes)

    def __contains__(self, frame_index: int) -> bool:
        return frame_index in self._by_frame

    def add(self, keyframe: StoredKeyframe) -> None:
        """Keep ``keyframe`` (after every keyframe stored so far in time); spill the oldest one kept
        in RAM when more than ``in_ram`` are."""
        self.keyframes.append(keyframe)
        self._by_frame[keyframe.frame_index] = keyframe
        if self.in_ram > 0:
            while len(self.keyframes) - self._spilled > self.in_ram:
                self._spill_oldest_in_ram()

    def _spill_oldest_in_ram(self) -> None:
        keyframe = self.keyframes[self._spilled]
        keyframe.spill(self.folder / f"{keyframe.frame_index:06d}.npz", owner=self._temporary)
        self._spilled += 1

    def spill_all(self) -> int:
        """Spill every keyframe still in RAM (when the store spills at all, ``in_ram > 0``), e.g.
        once the run takes no more frames, so that what comes after (the final polish) has that
        room; the arrays are read back, the same bytes, when the outputs need them. Returns how many
        keyframes were spilled now."""
        if self.in_ram <= 0:
            return 0
        before = self._spilled
        while self._spilled < len(self.keyframes):
            self._spill_oldest_in_ram()
        return self._spilled - before

    @property
    def folder(self) -> Path:
        """The folder of the spilled keyframes (made on first use)."""
        if self._folder is None:
            self._temporary = tempfile.TemporaryDirectory(prefix="sl4slam-keyframes-")
            self._folder = Path(self._temporary.name)
        self._folder.mkdir(parents=True, exist_ok=True)
        return self._folder

    @property
    def spilled(self) -> int:
        """How many keyframes have their image-sized arrays in files."""
        return self._spilled

    def ram_bytes(self) -> int:
        """Bytes of keyframe arrays held in RAM."""
        return int(sum(k.ram_bytes for k in self.keyframes))

    def get(self, frame_index: int) -> StoredKeyframe:
        """The stored keyframe of input frame ``frame_index`` (``KeyError`` when none is stored)."""
        return self._by_frame[frame_index]

    def note_ground_truth(self, frame: Frame) -> None:
        """Remember ``frame``'s ground-truth pose ``T_world_cam`` (when the source gave one)."""
        if frame.T_world_cam is not None:
            self._ground_truth[frame.index] = np.asarray(frame.T_world_cam, dtype=np.float64)

    def ground_truth(self, keyframes: Sequence[StoredKeyframe]) -> np.ndarray | None:
        """``(N, 4, 4)`` float64 ground-truth ``T_world_cam`` of ``keyframes``, or ``None`` unless
        every one has it (and there is at least one)."""
        if keyframes and all(k.frame_index in self._ground_truth for k in keyframes):
            return np.stack([self._ground_truth[k.frame_index] for k in keyframes])
        return None

    def companions(self, frame_index: int, wanted: int) -> list[int]:
        """Frame indices of up to ``wanted`` keyframes stored with ``frame_index`` in its submap,
        nearest to it in the video first (ties: the later one): with a loop frame they give the loop
        several frames to measure it on, all in the same two submaps."""
        if wanted <= 0:
            return []
        keyframes = self.keyframes
        position = bisect.bisect_left(keyframes, frame_index, key=lambda k: k.frame_index)
        submap = keyframes[position].submap_id
        lo, hi = position - 1, position + 1

        def same(p: int) -> bool:
            return 0 <= p < len(keyframes) and keyframes[p].submap_id == submap

        found: list[int] = []
        while len(found) < wanted and (same(lo) or same(hi)):
            gap_lo = frame_index - keyframes[lo].frame_index if same(lo) else np.inf
            gap_hi = keyframes[hi].frame_index - frame_index if same(hi) else np.inf
            if gap_hi <= gap_lo:
                found.append(keyframes[hi].frame_index)
                hi += 1
            else:
                found.append(keyframes[lo].frame_index)
                lo -= 1
        return found
