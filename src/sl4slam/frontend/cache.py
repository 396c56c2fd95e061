"""Record and replay frontend outputs (one ``.npz`` per submap).

The frames a submap holds do not depend on the graph design, so a recording made with either graph
replays with the other; image-match ratios (the loop check's attention score) are recorded when the
recording run asked for them.

Recording lets the expensive model run once (e.g. on a GPU) and the backend be re-run anywhere:
``sl4slam run SRC --out A --cache-frontend`` writes ``A/frontend_cache/``; ``sl4slam run SRC --out B
--replay A/frontend_cache`` replays it. Keyframe selection and retrieval are deterministic, so the
same source and settings ask for the same submaps; a mismatch is reported, never papered over.

A recording ``submap_NNNNN.npz`` holds every field of the :class:`~sl4slam.types.SubmapPrediction`
the frontend returned (its arrays as they were, so a replay gives the same bytes), the input frames'
indices (``frame_indices``), the frontend's name, whether it needs ground truth, and ``inputs``: a
digest of what the model was given (:func:`input_digest`), which :class:`ResumingFrontend` compares
before it serves a recording instead of running the model (``sl4slam run ... --resume``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import threading
import time
import zipfile
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..atomic import atomic_write_npz
from ..errors import UserError
from ..types import Frame, Frontend, FrontendCapabilities, SubmapPrediction

log = logging.getLogger("sl4slam")

_FIELDS = tuple(f.name for f in dataclasses.fields(SubmapPrediction))
"""Every field of a prediction: a recording holds each one that is set."""

_REQUIRED = ("depth", "confidence", "T_cam_submap", "K", "colors", "frame_indices")
"""The arrays without which a recording cannot be replayed."""


def recording_path(directory: str | os.PathLike, submap_id: int) -> Path:
    """The file of submap ``submap_id``'s recording in ``directory``."""
    return Path(directory) / f"submap_{submap_id:05d}.npz"


def recorded_submap(path: str | os.PathLike) -> int | None:
    """The submap id of a recording's file name (``submap_00012.npz`` -> 12); ``None`` for another name."""
    name = Path(path).name
    if not (name.startswith("submap_") and name.endswith(".npz")) or not name[7:-4].isdigit():
        return None
    return int(name[7:-4])


def _update(digest: Any, value: Any) -> None:
    """Feed ``value`` (``None``, a number, a string, a sequence or an array) into the hash ``digest``,
    with its type, shape and dtype, so that different values never feed the same bytes."""
    if value is None:
        digest.update(b"none;")
        return
    array = np.ascontiguousarray(np.asarray(value))
    digest.update(f"{array.dtype.str}{array.shape};".encode())
    digest.update(array.tobytes() if array.dtype != object else repr(array.tolist()).encode())


def frame_digest(frame: Frame) -> str:
    """SHA-256 (hex) of what a frontend can read of ``frame``: its index, RGB, depth, ground-truth
    pose and intrinsics."""
    digest = hashlib.sha256()
    for value in (frame.index, frame.rgb, frame.depth, frame.T_world_cam, frame.K):
        _update(digest, value)
    return digest.hexdigest()


def input_digest(frames: Sequence[Frame], keywords: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of a frontend call's inputs: each frame (:func:`frame_digest`) and the keyword
    arguments (``match_pairs``, ``intrinsics``), by name."""
    digest = hashlib.sha256()
    for frame in frames:
        digest.update(frame_digest(frame).encode())
    for name in sorted(keywords):
        digest.update(f"|{name}=".encode())
        _update(digest, keywords[name])
    return digest.hexdigest()


def recording_problem(path: str | os.PathLike) -> str | None:
    """What is wrong with the recording ``path`` as far as its zip directory shows (cut short, not a
    zip, an array missing, an entry reaching past the file's end), or ``None``. The arrays' checksums
    are verified when they are read (a replay reads them all)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with zipfile.ZipFile(path) as archive:
            entries = archive.infolist()
    except (OSError, zipfile.BadZipFile, ValueError, EOFError) as exc:
        return f"{type(exc).__name__}: {exc}"
    names = {entry.filename for entry in entries}
    missing = [name for name in (*_REQUIRED, "inputs") if f"{name}.npy" not in names]
    if missing:
        return f"no {', '.join(missing)} recorded"
    for entry in entries:
        if entry.header_offset + entry.compress_size > size:
            return f"{entry.filename} reaches past the end of the file"
    return None


class CachingFrontend:
    """Wraps a frontend and writes each prediction to ``directory`` (atomically) as soon as the model
    returns it.

    Args:
        inner: the frontend that reconstructs.
        directory: where ``submap_NNNNN.npz`` go (created).
        compressed: deflate the arrays (smaller files, much slower to write: a model's float32 outputs
            compress little); ``False``: stored as they are.

    A recording that cannot be written (a full disk) is reported once, in one line; the run goes on
    without recording the later submaps. :meth:`close` ends the recording: a forward that finishes
    later (in a worker the run no longer waits for) is not recorded, so no write is cut short when
    the process exits.
    """

    def __init__(self, inner: Frontend, directory: str | os.PathLike, compressed: bool = True) -> None:
        self.inner = inner
        self.name = inner.name
        self.capabilities = inner.capabilities
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.compressed = compressed
        self.recording = True
        self._writing = threading.Lock()

    def prepare(self) -> None:
        self.inner.prepare()

    def grid_colors(self, frame: Frame) -> np.ndarray:
        return self.inner.grid_colors(frame)

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, **kwargs) -> SubmapPrediction:
        prediction = self.inner.reconstruct(frames, submap_id, **kwargs)
        self.record(frames, submap_id, prediction, input_digest(frames, kwargs))
        return prediction

    def record(self, frames: Sequence[Frame], submap_id: int, prediction: SubmapPrediction, inputs: str) -> None:
        """Write ``prediction`` of ``frames`` (the model's inputs digested as ``inputs``) as submap
        ``submap_id``'s recording, unless recording has stopped."""
        arrays = {k: getattr(prediction, k) for k in _FIELDS if getattr(prediction, k) is not None}
        arrays["frame_indices"] = np.array([f.index for f in frames], dtype=np.int64)
        arrays["frontend"] = np.array(self.inner.name)
        arrays["requires_ground_truth"] = np.array(self.capabilities.needs_ground_truth)
        arrays["inputs"] = np.array(inputs)
        path = recording_path(self.directory, submap_id)
        with self._writing:
            if not self.recording:
                return
            try:
                atomic_write_npz(path, arrays, compressed=self.compressed)
            except OSError as exc:
                self.recording = False
                log.warning("cannot record the frontend's output of submap %d into %s (%s); the run goes on without "
                            "recording the later submaps", submap_id, self.directory, exc.strerror or exc)

    def close(self) -> None:
        """Stop recording, once a write under way (if any) has ended."""
        with self._writing:
            self.recording = False


class ResumingFrontend(CachingFrontend):
    """A :class:`CachingFrontend` that serves a submap's recording instead of running the model when
    the recording holds the same inputs (:func:`input_digest`: the same frames, pixel for pixel, and
    the same keyword arguments); other submaps are reconstructed and recorded. What ``--resume``
    runs: the recorded submaps of a killed run cost a file read, the rest the model.

    Args:
        inner, directory, compressed: as :class:`CachingFrontend`.
        record: record the submaps the model reconstructs (``False``: only replay what is there).

    Attributes:
        replayed: the submap ids served from their recordings, in order.
        reconstructed: the submap ids the model reconstructed, in order.
        first_model_call: ``time.perf_counter()`` when the model was first called (``None``: never).
    """

    def __init__(self, inner: Frontend, directory: str | os.PathLike, compressed: bool = False,
                 record: bool = True) -> None:
        super().__init__(inner, directory, compressed)
        self.recording = record
        self.replayed: list[int] = []
        self.reconstructed: list[int] = []
        self.first_model_call: float | None = None

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, **kwargs) -> SubmapPrediction:
        inputs = input_digest(frames, kwargs)
        recorded = self.replay(submap_id, inputs)
        if recorded is not None:
            self.replayed.append(submap_id)
            return recorded
        if self.first_model_call is None:
            self.first_model_call = time.perf_counter()
        prediction = self.inner.reconstruct(frames, submap_id, **kwargs)
        self.reconstructed.append(submap_id)
        self.record(frames, submap_id, prediction, inputs)
        return prediction

    def replay(self, submap_id: int, inputs: str) -> SubmapPrediction | None:
        """Submap ``submap_id``'s recording when it holds the inputs digested as ``inputs``; ``None``
        when there is none, it was made from other inputs, or it cannot be read (said in one line)."""
        path = recording_path(self.directory, submap_id)
        if not path.is_file():
            return None
        try:
            with np.load(path) as data:
                if "inputs" not in data.files or str(data["inputs"]) != inputs:
                    log.info("submap %d: its recording %s was made from other inputs; reconstructed again",
                             submap_id, path)
                    return None
                values = {k: data[k] for k in _FIELDS if k in data.files}
        except Exception as exc:  # a cut or corrupt file: the model reconstructs the submap again
            log.warning("%s cannot be read (%s: %s); submap %d is reconstructed again", path, type(exc).__name__,
                        exc, submap_id)
            return None
        return SubmapPrediction(**values)


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
        if self._color_slots is None:  # built whole before it is shared (the map is written in threads)
            slots: dict[int, tuple[Path, int]] = {}
            for path in sorted(self.directory.glob("submap_*.npz")):
                with np.load(path) as data:
                    for slot, index in enumerate(data["frame_indices"].tolist()):
                        slots.setdefault(int(index), (path, slot))
            self._color_slots = slots
        if frame.index not in self._color_slots:
            raise UserError(f"frame {frame.index} is not in the frontend cache {self.directory}")
        path, slot = self._color_slots[frame.index]
        with np.load(path) as data:
            return data["colors"][slot]

    def reconstruct(self, frames: Sequence[Frame], submap_id: int,
                    match_pairs: Sequence[tuple[int, int]] = ()) -> SubmapPrediction:
        """The recorded prediction; image-match ratios are the recorded ones (none if the recording
        was made without the loop check asking for them: the check is then skipped)."""
        path = recording_path(self.directory, submap_id)
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
