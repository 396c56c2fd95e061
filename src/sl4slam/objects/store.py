"""The keyframe embeddings of a result folder: ``objects/embeddings.npz``.

Arrays (``np.savez_compressed``):

- ``frame_index (N,)`` int64: the keyframe's source frame (the name of its ``keyframes/NNNNNN.npz``),
  strictly increasing.
- ``embeddings (N, D)`` float16: the keyframe image's embedding, L2-normalised in float32 before
  the cast (so a row's norm is 1 within float16 rounding).
- ``model`` (0-d str array): the embedder's name; a query embeds its text with the same model.
- ``format`` (0-d int): :data:`EMBEDDINGS_FORMAT`.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_npz
from ..errors import UserError

EMBEDDINGS_FILE = Path("objects") / "embeddings.npz"
"""Where the embeddings live, relative to the result folder."""
EMBEDDINGS_FORMAT = 1
"""The version of the file's layout written and read here."""
OBJECTS_OPTION = "--objects"
"""The run option that writes the embeddings (named in the error when they are absent)."""


@dataclass(frozen=True)
class KeyframeEmbeddings:
    """The embeddings of a result's keyframes.

    Attributes:
        frame_index: ``(N,)`` int64 source frame of each keyframe.
        embeddings: ``(N, D)`` float32, rows of unit norm (renormalised after reading float16).
        model: the embedder's name.
        path: the file they were read from (``None`` when made in memory).
    """

    frame_index: np.ndarray
    embeddings: np.ndarray
    model: str
    path: Path | None = None

    @property
    def dim(self) -> int:
        return int(self.embeddings.shape[1])


def _normalise(embeddings: np.ndarray) -> np.ndarray:
    """Rows of ``(N, D)`` scaled to unit L2 norm (float32; a zero row stays zero)."""
    embeddings = np.asarray(embeddings, dtype=np.float32)
    norms = np.linalg.norm(embeddings, axis=1, keepdims=True)
    return embeddings / np.where(norms > 0, norms, np.float32(1.0))


def write_embeddings(out_dir: str | Path, frame_index, embeddings, model: str) -> Path:
    """Write ``objects/embeddings.npz`` into a result folder (atomic: a reader sees the old file or
    the new one).

    Args:
        out_dir: the result folder (``--out`` of the run).
        frame_index: ``(N,)`` integer source frames of the keyframes, distinct.
        embeddings: ``(N, D)`` float embeddings, one row per keyframe (normalised here).
        model: the embedder's name.

    Returns:
        The path written.

    Raises:
        ValueError: shapes that do not go together, repeated frames or non-finite embeddings.
    """
    frame_index = np.asarray(frame_index, dtype=np.int64).reshape(-1)
    embeddings = np.asarray(embeddings)
    if embeddings.ndim != 2 or embeddings.shape[0] != frame_index.shape[0]:
        raise ValueError(f"embeddings must be ({frame_index.shape[0]}, D), got {embeddings.shape}")
    if len(np.unique(frame_index)) != len(frame_index):
        raise ValueError("frame_index repeats a frame")
    if not np.all(np.isfinite(embeddings)):
        raise ValueError("embeddings hold NaN or Inf")
    order = np.argsort(frame_index, kind="stable")
    path = Path(out_dir) / EMBEDDINGS_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_npz(path, {"frame_index": frame_index[order],
                            "embeddings": _normalise(embeddings)[order].astype(np.float16),
                            "model": np.array(str(model)), "format": np.array(EMBEDDINGS_FORMAT, dtype=np.int64)})
    return path


def read_embeddings(result_dir: str | Path) -> KeyframeEmbeddings:
    """Read the keyframe embeddings of a result folder.

    Args:
        result_dir: the result folder.

    Returns:
        The :class:`KeyframeEmbeddings` (float32, unit rows).

    Raises:
        UserError: one line when the file is absent, unreadable, of another format version, or
            malformed.
    """
    result_dir = Path(result_dir)
    path = result_dir / EMBEDDINGS_FILE
    if not path.is_file():
        raise UserError(f"{result_dir} has no keyframe embeddings: run with {OBJECTS_OPTION} to make them")
    damaged = f"the keyframe embeddings {path} are damaged"
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in ("frame_index", "embeddings", "model", "format") if k not in data.files]
            if missing:
                raise UserError(f"{damaged} (no {', '.join(missing)}): run with {OBJECTS_OPTION} again")
            version = int(data["format"])
            if version != EMBEDDINGS_FORMAT:
                raise UserError(f"{path} is in embeddings format {version}, which this sl4slam does not read "
                                f"(it reads {EMBEDDINGS_FORMAT}): run with {OBJECTS_OPTION} again")
            frame_index = np.asarray(data["frame_index"]).astype(np.int64).reshape(-1)
            embeddings = np.asarray(data["embeddings"])
            model = str(data["model"])
    except (OSError, EOFError, ValueError, TypeError, zipfile.BadZipFile) as exc:
        raise UserError(f"{damaged} ({exc}): run with {OBJECTS_OPTION} again") from None
    if embeddings.ndim != 2 or embeddings.shape[0] != frame_index.shape[0] or embeddings.shape[1] == 0:
        raise UserError(f"{damaged} (embeddings {embeddings.shape} for {frame_index.shape[0]} frames): "
                        f"run with {OBJECTS_OPTION} again")
    embeddings = embeddings.astype(np.float32)
    if not np.all(np.isfinite(embeddings)):
        raise UserError(f"{damaged} (non-finite values): run with {OBJECTS_OPTION} again")
    return KeyframeEmbeddings(frame_index=frame_index, embeddings=_normalise(embeddings), model=model, path=path)
