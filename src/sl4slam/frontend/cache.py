"""Record and replay frontend outputs (one compressed ``.npz`` per submap).

The frames a submap holds do not depend on the graph design, so a recording made with either graph
replays with the other; image-match ratios (the loop check's attention score) are recorded when the
recording run asked for them.

Recording lets the expensive model run once (e.g. on a GPU) and the backend be re-run anywhere:
``sl4slam run SRC --out A --cache-frontend`` writes ``A/frontend_cache/``; ``sl4slam run SRC --out B
--replay A/frontend_cache`` replays it. Keyframe selection and retrieval are deterministic, so the
same source and settings ask for the same submaps; a mismatch is reported, never papered over.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..atomic import atomic_write_npz
from ..errors import UserError
from ..types import Frame, Frontend, FrontendCapabilities, SubmapPrediction

_FIELDS = ("depth", "confidence", "T_cam_submap", "K", "colors", "points", "points_confidence", "principal_point",
           "match_pairs", "match_ratios", "image_to_grid")


def _path(directory: Path, submap_id: int) -> Path:
    return directory / f"submap_{submap_id:05d}.npz"


class CachingFrontend:
    """Wraps a frontend and writes each prediction to ``directory`` (atomically)."""

    def __init__(self, inner: Frontend, directory: str | os.PathLike) -> None:
        self.inner = inner
        self.name = inner.name
        self.capabilities = inner.capabilities
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def prepare(self) -> None:
        self.inner.prepare()

    def grid_colors(self, frame: Frame) -> np.ndarray:
        return self.inner.grid_colors(frame)

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, **kwargs) -> SubmapPrediction:
        prediction = self.inner.reconstruct(frames, submap_id, **kwargs)
        arrays = {k: getattr(prediction, k) for k in _FIELDS if getattr(prediction, k) is not None}
        arrays["frame_indices"] = np.array([f.index for f in frames], dtype=np.int64)
        arrays["frontend"] = np.array(self.inner.name)
        arrays["requires_ground_truth"] = np.array(self.capabilities.needs_ground_truth)
        atomic_write_npz(_path(self.directory, submap_id), arrays)
        return prediction


class ReplayFrontend:
    """Serves predictions recorded by ``CachingFrontend``."""

    name = "replay"

    def __init__(self, directory: str | os.PathLike) -> None:
        self.directory = Path(directory)
        if not self.directory.is_dir() or not any(self.directory.glob("submap_*.npz")):
            raise UserError(f"no recorded frontend outputs in {self.directory}; record them first with --cache-frontend")
        with np.load(sorted(self.directory.glob("submap_*.npz"))[0]) as first:
            recorded_by = str(first["frontend"]) if "frontend" in first.files else ""
            recorded = bool(first["requires_ground_truth"]) if "requires_ground_truth" in first.files else None
            scored = "match_ratios" in first.files
        # Replaying must skip the same frames (e.g. those without ground truth) as recording did; the
        # attention check can read only the image-match ratios the recording asked for.
        self.recorded_by = recorded_by
        self.capabilities = FrontendCapabilities(
            scores_pairs=scored, needs_ground_truth=recorded if recorded is not None else recorded_by == "simulated")
        self._color_slots: dict[int, tuple[Path, int]] | None = None

    def prepare(self) -> None:
        """Nothing to load: the recordings were checked when the cache was opened."""

    def grid_colors(self, frame: Frame) -> np.ndarray:
        """The recorded colours of ``frame`` (from the first submap that holds it)."""
        if self._color_slots is None:
            self._color_slots = {}
            for path in sorted(self.directory.glob("submap_*.npz")):
                with np.load(path) as data:
                    for slot, index in enumerate(data["frame_indices"].tolist()):
                        self._color_slots.setdefault(int(index), (path, slot))
        if frame.index not in self._color_slots:
            raise UserError(f"frame {frame.index} is not in the frontend cache {self.directory}")
        path, slot = self._color_slots[frame.index]
        with np.load(path) as data:
            return data["colors"][slot]

    def reconstruct(self, frames: Sequence[Frame], submap_id: int,
                    match_pairs: Sequence[tuple[int, int]] = ()) -> SubmapPrediction:
        """The recorded prediction; image-match ratios are the recorded ones (none if the recording
        was made without the loop check asking for them: the check is then skipped)."""
        path = _path(self.directory, submap_id)
        if not path.is_file():
            raise UserError(f"the frontend cache has no submap {submap_id} ({path.name}); re-record it with the same source and settings")
        with np.load(path) as data:
            recorded = data["frame_indices"].tolist()
            wanted = [f.index for f in frames]
            if recorded != wanted:
                raise UserError(
                    f"frontend cache mismatch at submap {submap_id}: recorded frames {recorded}, asked for {wanted}; "
                    "replay with the same source, keyframe and retrieval settings as the recording"
                )
            values = {k: data[k] for k in _FIELDS if k in data.files}
        return SubmapPrediction(**values)
