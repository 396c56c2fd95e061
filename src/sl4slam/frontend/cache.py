"""Record and replay frontend outputs (one compressed ``.npz`` per submap).

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

from ..errors import UserError
from ..types import Frame, Frontend, SubmapPrediction

_FIELDS = ("depth", "confidence", "T_cam_submap", "K", "colors", "points", "points_confidence", "principal_point")


def _path(directory: Path, submap_id: int) -> Path:
    return directory / f"submap_{submap_id:05d}.npz"


class CachingFrontend:
    """Wraps a frontend and writes each prediction to ``directory`` (atomically)."""

    def __init__(self, inner: Frontend, directory: str | os.PathLike) -> None:
        self.inner = inner
        self.name = inner.name
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def reconstruct(self, frames: Sequence[Frame], submap_id: int) -> SubmapPrediction:
        prediction = self.inner.reconstruct(frames, submap_id)
        arrays = {k: getattr(prediction, k) for k in _FIELDS if getattr(prediction, k) is not None}
        arrays["frame_indices"] = np.array([f.index for f in frames], dtype=np.int64)
        arrays["frontend"] = np.array(self.inner.name)
        target = _path(self.directory, submap_id)
        tmp = target.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, target)
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
        # Replaying the simulator must skip the same frames (those without ground truth) as recording did.
        self.requires_ground_truth = recorded_by == "simulated"

    def reconstruct(self, frames: Sequence[Frame], submap_id: int) -> SubmapPrediction:
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
