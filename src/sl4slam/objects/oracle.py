"""Oracle models for the synthetic world, and the ground truth to score object queries against.

The synthetic world (:mod:`sl4slam.synthetic`) knows which furniture box every pixel sees
(:func:`sl4slam.synthetic.render.render_object_ids`). The oracle models answer from that:

- an object is a furniture box ``b``; its text is ``"box b"`` (:func:`object_text`);
- :class:`OracleEmbedder`: a keyframe's embedding is the fraction of its pixels each box covers
  (one coordinate per box, and a last one for the room), normalised; a text's embedding is the
  one-hot of its box, so the cosine ranks keyframes by how much of them the box covers;
- :class:`OracleSegmenter`: the mask of a text is the box's pixels in the keyframe (score 1).

The models receive images, as the real ones do; the oracle tells which frame an image is by its
bytes (:meth:`SyntheticOracle.register`). The ground truth: :meth:`SyntheticOracle.true_box`
(axis-aligned, in the synthetic world frame, metres) and :func:`align_map_to_truth`, the Sim(3)
that takes a run's map onto that frame (a monocular map has its own frame and scale).
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..io.tum import read_tum_trajectory
from ..metrics import ate
from ..result.reading import RunResult
from ..synthetic.render import ROOM_OBJECT_ID, render_object_ids
from ..synthetic.sequence import read_synthetic_metadata
from .interfaces import Mask2D

ORACLE_EMBEDDER = "oracle-synthetic"
ORACLE_SEGMENTER = "oracle-synthetic-segmenter"
_TEXT = re.compile(r"^\s*box\s+(\d+)\s*$", re.IGNORECASE)


def object_text(box: int) -> str:
    """The query text of furniture box ``box``: ``"box 3"``."""
    return f"box {int(box)}"


def parse_object_text(text: str) -> int | None:
    """The box a text names (``"box 3"`` -> 3), or ``None``."""
    match = _TEXT.match(text or "")
    return int(match.group(1)) if match else None


def _digest(image: np.ndarray) -> str:
    image = np.ascontiguousarray(image)
    return hashlib.sha1(repr((image.shape, image.dtype.str)).encode() + image.tobytes()).hexdigest()


class SyntheticOracle:
    """What the synthetic world knows about a sequence: its boxes, cameras, and per-pixel box ids.

    Args:
        sequence_dir: a folder written by ``sl4slam synth`` / ``write_synthetic_sequence`` (its
            ``synthetic.json`` and ``groundtruth.txt``; frame ``i`` is row ``i``).
    """

    def __init__(self, sequence_dir: str | Path):
        self.sequence_dir = Path(sequence_dir)
        metadata = read_synthetic_metadata(self.sequence_dir)
        self.seed = int(metadata["seed"])
        self.width, self.height = int(metadata["width"]), int(metadata["height"])
        self.K = np.asarray(metadata["K"], np.float64)
        style = metadata.get("style")
        if style:
            from ..synthetic.styles import make_style_layout

            self.layout = make_style_layout(style["name"], self.seed).layout
        else:
            from ..synthetic.world import make_layout

            self.layout = make_layout(self.seed)
        self.timestamps, self.poses = read_tum_trajectory(self.sequence_dir / "groundtruth.txt")
        self._frames: dict[str, int] = {}
        self._ids: dict[tuple[int, int, int], np.ndarray] = {}

    @property
    def num_boxes(self) -> int:
        return int(self.layout.boxes_min.shape[0])

    def true_box(self, box: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Box ``box`` as ``(centre, axes, extents)`` in the synthetic world frame (metres, axis-aligned)."""
        lo, hi = self.layout.boxes_min[box], self.layout.boxes_max[box]
        return (lo + hi) / 2.0, np.eye(3), hi - lo

    def object_ids(self, frame_index: int, shape: tuple[int, int] | None = None) -> np.ndarray:
        """``(H, W)`` int16 box id per pixel of frame ``frame_index`` (``ROOM_OBJECT_ID`` for the room),
        on a grid of ``shape`` (default the sequence's size; another size scales the camera)."""
        height, width = shape if shape is not None else (self.height, self.width)
        key = (int(frame_index), int(height), int(width))
        if key not in self._ids:
            if not 0 <= frame_index < len(self.poses):
                raise UserError(f"frame {frame_index} is not in {self.sequence_dir} ({len(self.poses)} frames)")
            K = self.K.copy()
            if (height, width) != (self.height, self.width):
                sx, sy = width / self.width, height / self.height
                K[0] *= sx
                K[1] *= sy
                K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
                K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
            self._ids[key] = render_object_ids(self.layout, self.poses[frame_index], K, width, height)[0]
        return self._ids[key]

    def coverage(self, frame_index: int, shape: tuple[int, int] | None = None) -> np.ndarray:
        """``(B + 1,)`` fraction of the frame's pixels on each box, and last on the room."""
        ids = self.object_ids(frame_index, shape).astype(np.int64)
        ids = np.where(ids == ROOM_OBJECT_ID, self.num_boxes, ids)
        return np.bincount(ids.reshape(-1), minlength=self.num_boxes + 1) / ids.size

    def register(self, frame_index: int, image: np.ndarray) -> None:
        """Tell the oracle that ``image`` ((H, W, 3) uint8, the exact bytes a query will show it) is
        frame ``frame_index``."""
        self._frames[_digest(image)] = int(frame_index)

    def register_result(self, result: RunResult) -> None:
        """Register every keyframe image of a result (the grid colours a query reads)."""
        for record in result.require_keyframes("the synthetic oracle"):
            self.register(record.frame_index, record.load().colors)

    def frame_of(self, image: np.ndarray) -> int:
        """The frame a registered image is (``UserError`` for an image never registered)."""
        try:
            return self._frames[_digest(image)]
        except KeyError:
            raise UserError("the synthetic oracle was shown an image it does not know; register the result's "
                            "keyframes first (SyntheticOracle.register_result)") from None


class OracleEmbedder:
    """The oracle :class:`~sl4slam.objects.interfaces.ImageEmbedder` of a :class:`SyntheticOracle`."""

    name = ORACLE_EMBEDDER
    max_text_chars = 300

    def __init__(self, oracle: SyntheticOracle):
        self.oracle = oracle
        self.dim = oracle.num_boxes + 1

    @staticmethod
    def _normalise(vectors: np.ndarray) -> np.ndarray:
        vectors = np.asarray(vectors, np.float32)
        norms = np.linalg.norm(vectors, axis=1, keepdims=True)
        return vectors / np.where(norms > 0, norms, np.float32(1.0))

    def embed_frames(self, frame_indices, shape: tuple[int, int] | None = None) -> np.ndarray:
        """``(N, D)`` embeddings of frames given by index (what a run with the oracle would store)."""
        return self._normalise(np.stack([self.oracle.coverage(int(f), shape) for f in frame_indices]))

    def embed_images(self, images: list[np.ndarray]) -> np.ndarray:
        """``(N, D)`` embeddings of registered images (each the coverage of its frame, normalised)."""
        return self._normalise(np.stack([self.oracle.coverage(self.oracle.frame_of(image), image.shape[:2])
                                         for image in images]))

    def embed_texts(self, texts: list[str]) -> np.ndarray:
        """``(M, D)``: the one-hot of the box a text names; the room's coordinate for any other text."""
        out = np.zeros((len(texts), self.dim), np.float32)
        for row, text in enumerate(texts):
            box = parse_object_text(text)
            out[row, box if box is not None and 0 <= box < self.oracle.num_boxes else self.dim - 1] = 1.0
        return out


class OracleSegmenter:
    """The oracle :class:`~sl4slam.objects.interfaces.TextSegmenter` of a :class:`SyntheticOracle`."""

    name = ORACLE_SEGMENTER

    def __init__(self, oracle: SyntheticOracle, min_pixels: int = 1):
        self.oracle = oracle
        self.min_pixels = int(min_pixels)

    def segment(self, image: np.ndarray, text: str, threshold: float = 0.5) -> list[Mask2D]:
        """The named box's pixels in the image's frame (score 1), or no mask."""
        box = parse_object_text(text)
        if box is None or not 0 <= box < self.oracle.num_boxes:
            return []
        mask = self.oracle.object_ids(self.oracle.frame_of(image), image.shape[:2]) == box
        if mask.sum() < self.min_pixels or threshold > 1.0:
            return []
        return [Mask2D(mask=mask, score=1.0)]


def write_oracle_embeddings(result: RunResult, oracle: SyntheticOracle) -> Path:
    """Write ``objects/embeddings.npz`` for a result made from the oracle's sequence (as a run with
    ``--objects`` would, with the oracle embedder). Returns the path."""
    from .store import write_embeddings

    records = result.require_keyframes("the oracle's embeddings")
    frames = np.array([r.frame_index for r in records], np.int64)
    shape = (records[0].image_size[1], records[0].image_size[0])
    return write_embeddings(result.path, frames, OracleEmbedder(oracle).embed_frames(frames, shape), ORACLE_EMBEDDER)


def align_map_to_truth(result: RunResult, oracle: SyntheticOracle | None = None) -> np.ndarray:
    """The Sim(3) ``T_gt_map`` (4x4, ``[sR t; 0 1]``) that takes a result's map onto the ground-truth
    frame: Umeyama alignment of its keyframe trajectory to the ground truth of the same timestamps
    (``sl4slam.metrics.ate``, evo's ``-as``), from ``trajectory_gt.txt`` or else the oracle's
    sequence."""
    if result.gt is not None:
        gt_stamps, gt_poses = result.gt
    elif oracle is not None:
        gt_stamps, gt_poses = oracle.timestamps, oracle.poses
    else:
        raise UserError(f"{result.path} has no trajectory_gt.txt; give the synthetic sequence to align against")
    return ate(result.timestamps, result.T_world_cam, gt_stamps, gt_poses).T_gt_est


def box_to_truth(centre: np.ndarray, axes: np.ndarray, extents: np.ndarray,
                 T_gt_map: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An oriented box of the map moved by the Sim(3) ``T_gt_map`` into the ground-truth frame."""
    sR = np.asarray(T_gt_map, np.float64)[:3, :3]
    scale = float(np.cbrt(np.linalg.det(sR)))
    R = sR / scale
    return sR @ np.asarray(centre, np.float64) + T_gt_map[:3, 3], np.asarray(axes, np.float64) @ R.T, \
        scale * np.asarray(extents, np.float64)
