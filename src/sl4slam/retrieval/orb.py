"""Weights-free loop-closure retrieval: ORB features, binary bag of words, epipolar verification.

A CPU-only stand-in for SALAD (paper 4.3) that needs no download. Per stored keyframe we keep
its ORB keypoints and descriptors and a sparse bag of binary words; a query

1. ranks the stored keyframes of eligible submaps (ids ``<= submap_id - 1 - tau_interval``) by
   tf-idf cosine similarity of their word histograms (sparse products through an inverted
   file, so ranking stays vectorized as the database grows), after a coarse ranking by their
   words hashed into a short dense row has picked the few worth scoring; past
   ``RetrievalConfig.orb_coarse_flat_rows`` keyframes that coarse ranking first picks groups of
   consecutive keyframes (:meth:`OrbRetrieval.coarse_rows`), so its cost grows 16 times slower
   than the map,
2. geometrically verifies the best ``RetrievalConfig.orb_candidates``: one-to-one nearest-neighbour
   Hamming matching with Lowe's ratio test, then a fundamental-matrix RANSAC
   (``cv2.findFundamentalMat``, seeded with ``cv2.setRNGSeed``),
3. accepts a match when at least ``RetrievalConfig.orb_min_inliers`` matches are epipolar
   inliers.

Precision comes before recall (one false loop bends the whole map): unrelated images (random
textures, other scenes) do not even reach 40 one-to-one ratio-test matches, let alone epipolar
inliers, while frames of the TUM fr1_xyz excerpt up to 1.2 s apart verify 100-600 inliers.

Binary words. Each word table hashes a descriptor to the integer formed by ``WORD_BITS`` of its
256 bits, chosen once from the seed (bit-sampling locality-sensitive hashing for Hamming space):
two descriptors of the same point (Hamming distance ~20-40) share a table's word with
probability 0.05-0.25, two unrelated ones (~128) with 2**-16. ``WORD_TABLES`` tables give a vocabulary
of ``WORD_TABLES * 2**WORD_BITS`` words that needs no training, does not change as the database
grows, and is the same for every run with the same seed. Inverse document frequencies come from
the stored keyframes at query time.

Distance. ``LoopCandidate.distance = 1 - inliers / orb_features``: one minus the share of the
feature budget that was geometrically verified; in ``[0, 1)``, smaller = more similar, and
monotone in the inlier count, so candidates of different queries compare by their evidence.
It is not on SALAD's scale: ``RetrievalConfig.tau_desc`` does not apply, the acceptance test is
``orb_min_inliers`` (distance ``< 1 - orb_min_inliers / orb_features``, 0.96 by default).

Memory per stored keyframe (1000 features): descriptors 32 kB uint8, keypoints 8 kB float32 (both
may be spilled to a file, :meth:`OrbRetrieval.spill_features`), words about 5 kB (one byte per
descriptor and table, see ``OrbRetrieval._append_tf_row``), the hashed global row 4 kB float32
(and a 16th of a group's summed row, 256 bytes); no images are kept.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import scipy.sparse

from .settings import RetrievalConfig
from ..errors import UserError
from ..registry import RetrievalEntry
from ..types import Frame, LoopCandidate

WORD_BITS = 16
"""Descriptor bits per binary word (2**16 words per table). Fewer bits make words so common
that unrelated images score almost like revisits (10 bits: 0.54 versus 0.66 on the TUM excerpt);
more bits make a true revisit share too few words."""
WORD_TABLES = 4
"""Independent bit-sampling tables; the vocabulary has WORD_TABLES * 2**WORD_BITS words."""
DESCRIPTOR_BITS = 256
"""ORB descriptors are 32 bytes."""
MIN_FUNDAMENTAL_MATCHES = 8
"""RANSAC on the fundamental matrix needs at least 8 correspondences."""
_HIGH_DTYPE = np.uint8 if WORD_BITS <= 16 else np.uint32
"""High bits (above the low byte) of a stored word step that does not fit in a byte."""
NORM_ROWS = 256
"""Stored keyframes whose tf-idf norms are computed at a time (bounds the temporary arrays)."""


@dataclass
class OrbFeatures:
    """ORB features of one image at the working resolution.

    Attributes:
        keypoints: ``(N, 2)`` float32 pixel coordinates (x, y) at the working resolution.
        descriptors: ``(N, 32)`` uint8 ORB descriptors.
        word_ids: ``(M,)`` int32 distinct binary words of the image, ascending.
        word_tf: ``(M,)`` float32 term frequencies of ``word_ids`` (sum to 1 when ``M > 0``).
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    word_ids: np.ndarray
    word_tf: np.ndarray

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def match_descriptors(
    descriptors_query: np.ndarray, descriptors_stored: np.ndarray, ratio: float, max_hamming: float
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour matches that pass Lowe's ratio test, an absolute bound, and are one-to-one.

    Brute-force Hamming search (``cv2.batchDistance``, two nearest neighbours per query
    descriptor, returned as arrays). A stored descriptor claimed by several query descriptors is
    ambiguous and dropped: a cheap stand-in for a mutual-nearest-neighbour check, which would
    need a second full search.

    Args:
        descriptors_query: ``(N, 32)`` uint8 ORB descriptors.
        descriptors_stored: ``(M, 32)`` uint8 ORB descriptors, ``M >= 2``.
        ratio: keep a match when nearest < ratio * second nearest distance.
        max_hamming: keep a match when its Hamming distance (of 256 bits) is at most this.

    Returns:
        ``(query_idx, stored_idx)``: ``(K,)`` int64 indices of the kept matches, by query index.
    """
    distances, neighbours = cv2.batchDistance(
        descriptors_query, descriptors_stored, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2
    )
    nearest = neighbours[:, 0].astype(np.int64)
    keep = (distances[:, 0] < ratio * distances[:, 1]) & (distances[:, 0] <= max_hamming) & (nearest >= 0)
    claims = np.bincount(nearest[keep], minlength=len(descriptors_stored))
    keep &= claims[np.maximum(nearest, 0)] == 1
    query_idx = np.flatnonzero(keep)
    return query_idx, nearest[query_idx]



# Coarse ranking: each keyframe's term frequencies hashed into a short dense vector, so that a
# query batch is ranked against the whole database by one matrix product; only the best
# COARSE_CANDIDATES rows per query are then scored exactly (tf-idf through the sparse rows).
GLOBAL_DIM = 1024
COARSE_CANDIDATES = 8
# Beyond RetrievalConfig.orb_coarse_flat_rows eligible keyframes the coarse ranking has two levels:
# groups of GROUP_ROWS consecutive stored keyframes (a submap's worth) are ranked by the sum of their
# hashed rows (their mean similarity to the query), and only the rows of each query's best
# RetrievalConfig.orb_coarse_groups groups (plus an unfinished last group) are ranked one by one.
GROUP_ROWS = 16

class OrbRetrieval:
    """Place recognition with ORB features (implements ``sl4slam.types.Retrieval``, name "orb").

    Deterministic: the vocabulary and the RANSAC sampling depend only on ``seed``.

    Args:
        config: ``RetrievalConfig``; uses ``tau_interval`` and the ``orb_*`` settings (features,
            candidates, minimum inliers, ratio test, Hamming bound, epipolar threshold, image size).
        seed: seed of the word tables and of the RANSAC sampler (default: ``config.seed``).
    """

    name = "orb"

    def __init__(self, config: RetrievalConfig | None = None, seed: int | None = None) -> None:
        self.config = config if config is not None else RetrievalConfig()
        self.config.validate()  # a retrieval built by hand gets the one-line errors of a run
        self.seed = int(self.config.seed if seed is None else seed)
        self.max_image_side = int(self.config.orb_max_image_side)
        self.ratio = float(self.config.orb_ratio)
        self.max_hamming = float(self.config.orb_max_hamming)
        self.epipolar_threshold_px = float(self.config.orb_epipolar_threshold_px)
        self.vocabulary_size = WORD_TABLES << WORD_BITS

        rng = np.random.default_rng(self.seed)
        # (WORD_TABLES, WORD_BITS) descriptor bit positions: distinct within a table.
        self._word_bit_positions = np.stack(
            [rng.choice(DESCRIPTOR_BITS, size=WORD_BITS, replace=False) for _ in range(WORD_TABLES)]
        )
        self._orb = cv2.ORB_create(nfeatures=int(self.config.orb_features))

        # Database: one entry per stored keyframe, rows [0, _count) of growable buffers.
        self._count = 0
        self._frame_indices = np.zeros(0, np.int64)
        self._submap_ids = np.zeros(0, np.int64)
        # (keypoints, descriptors) of positions _spilled.. in order; older ones are in the features file
        self._in_ram: list[tuple[np.ndarray, np.ndarray]] = []
        self._spill: _FeatureFile | None = None  # see spill_features
        self._features_in_ram = 0  # keep this many newest keyframes' features in RAM (0: all)
        self._spilled = 0  # positions below this are in the file
        self._document_frequency = np.zeros(self.vocabulary_size, np.int32)
        # Term-frequency matrix (stored keyframes x words), encoded in growable buffers: each
        # keyframe's words, one per descriptor and table, sorted, as byte steps with the rare larger
        # steps' high bits aside (see _append_tf_row); _tf_indptr[r]:_tf_indptr[r + 1] are row r's
        # steps. The CSR rows (word ids, term frequencies) are rebuilt where they are used (_entries).
        self._tf_indptr = np.zeros(1, np.int64)
        self._tf_steps = np.zeros(0, np.uint8)
        self._tf_nnz = 0
        # the steps of 256 or more: row r's are _tf_high_indptr[r]:_tf_high_indptr[r + 1] of their
        # positions within the row (ascending) and their high bits
        self._tf_high_indptr = np.zeros(1, np.int64)
        self._tf_high_offsets = np.zeros(0, np.uint16)  # widened to uint32 for a row of 2**16 steps or more
        self._tf_high = np.zeros(0, _HIGH_DTYPE)
        # Inverted file (words x keyframes) over the first keyframes; see _inverted_file().
        self._inverted: scipy.sparse.csr_matrix | None = None
        self._idf: np.ndarray | None = None  # cached, see _idf_and_norms
        self._idf_count = 0  # keyframes stored when the cached idf was computed
        self._global = np.zeros((0, GLOBAL_DIM), np.float32)  # hashed tf rows, grown geometrically
        # row g: the sum of hashed rows g * GROUP_ROWS .. (g + 1) * GROUP_ROWS - 1, written when the
        # group's last row is (again after a rewind); the groups of the first n rows are n // GROUP_ROWS
        self._group_sums = np.zeros((0, GLOBAL_DIM), np.float32)
        self.describe_seconds = 0.0  # time spent extracting features (the "descriptor model")
        self._stored_norm = np.zeros(0, np.float32)
        # vocabulary-sized scratch of _dot_rows (allocated at its first call, all False / -1 between calls)
        self._word_present: np.ndarray | None = None
        self._word_lookup: np.ndarray | None = None
        # Features of the latest query batch, keyed by frame index, reused by the following add().
        self._pending: dict[int, tuple[np.ndarray, OrbFeatures]] = {}
        self.closed = False  # see close()

    def __len__(self) -> int:
        """Number of stored keyframes."""
        return self._count

    def close(self) -> None:
        """Free the database at the end of a run: every stored keyframe's words, hashed row and
        features (in RAM, and the features file), about 17 kB a keyframe in RAM. ``len`` still
        counts what was stored; :meth:`add` and :meth:`query` raise ``RuntimeError`` afterwards."""
        self.closed = True
        if self._spill is not None:
            self._spill.close()
        self._spill, self._in_ram, self._pending = None, [], {}
        self._tf_indptr, self._tf_steps = np.zeros(1, np.int64), np.zeros(0, np.uint8)
        self._tf_high_indptr, self._tf_high_offsets = np.zeros(1, np.int64), np.zeros(0, np.uint16)
        self._tf_high = np.zeros(0, _HIGH_DTYPE)
        self._global, self._stored_norm = np.zeros((0, GLOBAL_DIM), np.float32), np.zeros(0, np.float32)
        self._group_sums = np.zeros((0, GLOBAL_DIM), np.float32)
        self._inverted = self._idf = self._word_present = self._word_lookup = None

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError("ORB retrieval was closed at the end of its run: it stores and answers nothing more")

    def spill_features(self, folder: str | os.PathLike | None, in_ram: int) -> None:
        """Keep only the ``in_ram`` newest keyframes' keypoints and descriptors in RAM (about 38 kB
        a keyframe); older ones go to one append-only file in ``folder`` (``None``: a temporary
        file) and are read back (the same bytes) when a query verifies against them, at most
        ``orb_candidates`` per submap. ``in_ram`` 0 keeps all. Call before the first :meth:`add`."""
        self._features_in_ram = max(0, int(in_ram))
        path = Path(folder) / "orb_features.bin" if folder is not None else None
        self._spill = _FeatureFile(path) if self._features_in_ram else None

    def features_in_ram(self) -> int:
        """Stored keyframes whose keypoints and descriptors are in RAM."""
        return len(self) - self._spilled

    def _stored_features(self, position: int) -> tuple[np.ndarray, np.ndarray]:
        """``(keypoints (n, 2) float32, descriptors (n, 32) uint8)`` of the stored keyframe at ``position``."""
        if not 0 <= position < len(self):
            raise IndexError(f"no stored keyframe at position {position} (stored: {len(self)})")
        if position >= self._spilled:
            return self._in_ram[position - self._spilled]
        return self._spill.read(position)

    def _spill_oldest(self) -> None:
        """Move the features of keyframes beyond the newest ``_features_in_ram`` to the file."""
        if self._spill is None:
            return
        while len(self._in_ram) > self._features_in_ram:
            keypoints, descriptors = self._in_ram.pop(0)
            self._spill.write(self._spilled, keypoints, descriptors)
            self._spilled += 1

    def forget_query_features(self) -> None:
        """Drop the features kept from the latest query, so that the next query or add extracts its
        frames' features again (e.g. to time a query with its feature extraction, as the pipeline pays it)."""
        self._pending.clear()

    # ----------------------------------------------------------------------------------- features

    def extract(self, image: np.ndarray) -> OrbFeatures:
        """ORB features and binary words of ``image``: ``(H, W, 3)`` uint8 RGB or ``(H, W)`` uint8 grey."""
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3) or (
            image.ndim == 3 and image.shape[2] != 3
        ):
            shape = getattr(image, "shape", None)
            dtype = getattr(image, "dtype", type(image).__name__)
            raise UserError(f"ORB retrieval needs (H, W, 3) uint8 RGB images, got shape {shape} dtype {dtype}")
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        longer_side = max(grey.shape)
        if longer_side > self.max_image_side:
            scale = self.max_image_side / longer_side
            size = (max(1, round(grey.shape[1] * scale)), max(1, round(grey.shape[0] * scale)))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        keypoints, descriptors = self._orb.detectAndCompute(grey, None)
        if descriptors is None or len(keypoints) == 0:
            no_points, no_descriptors = np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
            return OrbFeatures(no_points, no_descriptors, np.zeros(0, np.int32), np.zeros(0, np.float32))
        points = cv2.KeyPoint_convert(keypoints).astype(np.float32).reshape(-1, 2)
        word_ids, word_tf = self._words(descriptors)
        return OrbFeatures(points, np.ascontiguousarray(descriptors, np.uint8), word_ids, word_tf)

    def _words(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distinct word ids ``(M,)`` int32 and their term frequencies ``(M,)`` float32."""
        bits = np.unpackbits(descriptors, axis=1).astype(np.int64)  # (N, 256)
        place_values = np.int64(1) << np.arange(WORD_BITS, dtype=np.int64)
        table_offsets = np.arange(WORD_TABLES, dtype=np.int64) << WORD_BITS
        # (N, WORD_TABLES) word of each descriptor in each table, offset into one vocabulary.
        words = bits[:, self._word_bit_positions] @ place_values + table_offsets
        word_ids, counts = np.unique(words.reshape(-1), return_counts=True)
        return word_ids.astype(np.int32), (counts / counts.sum()).astype(np.float32)

    def _features(self, frame_index: int, image: np.ndarray) -> OrbFeatures:
        """Features of ``image``, reusing the latest query's extraction of the same image.

        The query keeps a copy of each image and reuses its features only for an equal image
        (a byte comparison costs a few hundredths of a millisecond, far less than hashing).
        """
        cached = self._pending.get(int(frame_index))
        if cached is not None and _same_image(cached[0], image):
            return cached[1]
        start = time.perf_counter()
        features = self.extract(image)
        self.describe_seconds += time.perf_counter() - start
        self._pending[int(frame_index)] = (np.array(image, copy=True), features)
        return features

    # ----------------------------------------------------------------------------------- database

    def add(self, frames: Sequence[Frame], submap_id: int) -> None:
        """Store the keyframes ``frames`` (their ``(H, W, 3)`` uint8 RGB images) of submap ``submap_id``."""
        self._check_open()
        frame_indices, images = [f.index for f in frames], [f.rgb for f in frames]
        batch = [self._features(index, image) for index, image in zip(frame_indices, images)]
        self._pending.clear()
        for index, features in zip(frame_indices, batch):
            position = self._count
            self._append_tf_row(position, features)  # checks the features before anything is stored
            self._frame_indices = _room(self._frame_indices, position + 1, position)
            self._frame_indices[position] = int(index)
            self._in_ram.append((features.keypoints, features.descriptors))
            self._document_frequency[features.word_ids] += 1
            self._append_global_row(position, _global_vector(features))
            self._count = position + 1
        self._submap_ids = np.concatenate([self._submap_ids, np.full(len(batch), int(submap_id), np.int64)])
        self._spill_oldest()

    def mark(self) -> dict:
        """What :meth:`rewind` needs to return the database to this moment: the stored count, the
        buffers' fill and the cached idf, norms and inverted file (replaced, never changed in place,
        so references are enough). Cost independent of the database's size."""
        return {"count": len(self), "nnz": self._tf_nnz, "indptr": self._tf_indptr, "submap_ids": self._submap_ids,
                "idf": self._idf, "idf_count": self._idf_count, "stored_norm": self._stored_norm,
                "inverted": self._inverted, "pending": dict(self._pending)}

    def rewind(self, mark: dict) -> None:
        """Forget every keyframe added since :meth:`mark` returned ``mark``: the database, its caches
        and the latest query's features are as they were then (queries give the same answers)."""
        count = int(mark["count"])
        if count < self._spilled:  # only the newest keyframes are ever withdrawn, and they are in RAM
            raise ValueError(f"cannot rewind to {count} keyframes: the first {self._spilled} were spilled")
        if len(self) > count:
            withdrawn = self._entries(np.arange(count, len(self)))[1]
            np.subtract.at(self._document_frequency, withdrawn, 1)
            del self._in_ram[count - self._spilled:]
            self._count = count  # rows from here on are written again by the next add
        self._tf_nnz = int(mark["nnz"])
        self._tf_indptr, self._submap_ids = mark["indptr"], mark["submap_ids"]
        self._idf, self._stored_norm, self._inverted = mark["idf"], mark["stored_norm"], mark["inverted"]
        self._idf_count = int(mark["idf_count"])
        self._pending = dict(mark["pending"])

    def _append_global_row(self, position: int, row: np.ndarray) -> None:
        self._global = _room(self._global, position + 1, position)
        self._global[position] = row
        if (position + 1) % GROUP_ROWS == 0:  # a group is complete: its sum for the grouped ranking
            group = position // GROUP_ROWS
            self._group_sums = _room(self._group_sums, group + 1, group)
            self._group_sums[group] = self._global[position + 1 - GROUP_ROWS:position + 1].sum(axis=0, dtype=np.float64)

    def coarse_rows(self, queries: np.ndarray, eligible: np.ndarray) -> np.ndarray:
        """The stored rows the exact tf-idf scores: each query's ``COARSE_CANDIDATES`` best of
        ``eligible`` (ascending positions) by hashed-row similarity, ascending, without repeats.

        Up to ``orb_coarse_flat_rows`` eligible rows (or when they are not the first stored ones),
        every eligible row is scored; beyond, the rows of each query's ``orb_coarse_groups`` best
        groups of ``GROUP_ROWS`` consecutive keyframes (ranked by the sum of their rows, i.e. their
        mean similarity) and the rows of an unfinished last group.

        Args:
            queries: ``(num_queries, GLOBAL_DIM)`` float32 hashed rows of the query keyframes.
            eligible: ``(n,)`` stored positions the queries may match, ``n > COARSE_CANDIDATES``.
        """
        count = len(eligible)
        prefix = eligible[-1] == count - 1  # the first stored rows, as while submap ids arrive in order
        if not prefix:
            rows, stored = eligible, self._global[eligible]
        elif count <= int(self.config.orb_coarse_flat_rows):
            rows, stored = eligible, self._global[:count]  # a view: no copy
        else:
            groups = count // GROUP_ROWS
            keep = min(int(self.config.orb_coarse_groups), groups)
            if keep < groups:
                scores = self._group_sums[:groups] @ queries.T  # (groups, num_queries)
                chosen = np.unique(np.argpartition(-scores, keep - 1, axis=0)[:keep])
            else:
                chosen = np.arange(groups)
            rows = np.concatenate([(chosen[:, None] * GROUP_ROWS + np.arange(GROUP_ROWS)).reshape(-1),
                                   np.arange(groups * GROUP_ROWS, count)])
            stored = self._global[rows]
        coarse = stored @ queries.T  # (len(rows), num_queries)
        best = np.argpartition(-coarse, COARSE_CANDIDATES - 1, axis=0)[:COARSE_CANDIDATES]
        return rows[np.unique(best)]

    def _query_weights(self, query_features: Sequence[OrbFeatures], idf: np.ndarray) -> tuple[scipy.sparse.csr_matrix, np.ndarray]:
        """Queries as ``(num_queries, V)`` CSR rows ``tf_q * idf^2`` (with the raw stored tf this gives
        the tf-idf dot product) and their tf-idf norms ``(num_queries,)``."""
        query_rows = np.concatenate([[0], np.cumsum([len(f.word_ids) for f in query_features])])
        query_words = np.concatenate([f.word_ids for f in query_features])
        query_tf_idf = np.concatenate([f.word_tf for f in query_features]) * idf[query_words]
        query_norm = np.zeros(len(query_features), np.float32)
        nonempty = np.diff(query_rows) > 0
        if nonempty.any():
            query_norm[nonempty] = np.sqrt(np.add.reduceat(query_tf_idf * query_tf_idf, query_rows[:-1][nonempty]))
        weighted = scipy.sparse.csr_matrix(
            (query_tf_idf * idf[query_words], query_words, query_rows),
            shape=(len(query_features), self.vocabulary_size),
        )
        return weighted, query_norm

    def similarity_rows(self, query_features: Sequence[OrbFeatures], rows: np.ndarray) -> np.ndarray:
        """tf-idf cosine similarity ``(len(rows), num_queries)`` of the stored keyframes ``rows`` only
        (same values as the matching rows of :meth:`similarity`)."""
        idf, stored_norm = self._idf_and_norms()
        weighted, query_norm = self._query_weights(query_features, idf)
        dots = self._dot_rows(rows, weighted)
        denominator = np.maximum(stored_norm[rows][:, None] * query_norm[None, :], 1e-12)
        return (dots / denominator).astype(np.float32)

    def _append_tf_row(self, position: int, features: OrbFeatures) -> None:
        """Store the words of ``features`` as row ``position`` of the term-frequency matrix.

        The term frequencies are ``count / (WORD_TABLES * descriptors)`` (see :meth:`_words`): the
        row is stored as the sorted words of every descriptor in every table (a word as often as
        its count), table after table, each as its step from the previous word of its table (from
        0 for a table's first) in one byte; a step of 256 or more (a table's first word, a gap in a
        sparse table: a few percent) also has its high bits kept aside. The counts are recovered
        from the term frequencies exactly, and checked to give back the same float32 values.
        """
        word_ids = np.asarray(features.word_ids)
        word_tf = np.asarray(features.word_tf, np.float32)
        descriptors = len(features.descriptors)
        total = WORD_TABLES * descriptors
        counts = np.rint(word_tf.astype(np.float64) * total).astype(np.int64)
        if len(word_ids) and not (
            counts.min() > 0 and np.array_equal((counts / total).astype(np.float32), word_tf)
            and np.array_equal(np.bincount(word_ids >> WORD_BITS, counts, WORD_TABLES), np.full(WORD_TABLES, descriptors))
        ):
            raise ValueError("ORB term frequencies must be word counts over WORD_TABLES * descriptors, as extract() gives")
        words = np.repeat(word_ids & ((1 << WORD_BITS) - 1), counts)  # (total,) table after table
        steps = np.diff(words, prepend=0).astype(np.int64)
        steps[::max(descriptors, 1)] = words[::max(descriptors, 1)]  # each table starts from 0
        high = np.flatnonzero(steps >> 8)
        if len(words) > np.iinfo(self._tf_high_offsets.dtype).max + 1:
            self._tf_high_offsets = self._tf_high_offsets.astype(np.uint32)
        needed = self._tf_nnz + len(words)
        # grow by a quarter at a time: amortized O(1) per entry, at most 25 % slack
        self._tf_steps = _room(self._tf_steps, needed, self._tf_nnz, minimum=4096)
        self._tf_steps[self._tf_nnz : needed] = steps & 0xFF
        first = int(self._tf_high_indptr[position])
        highs = first + len(high)
        self._tf_high_offsets = _room(self._tf_high_offsets, highs, first, minimum=4096)
        self._tf_high = _room(self._tf_high, highs, first, minimum=4096)
        self._tf_high_offsets[first:highs] = high
        self._tf_high[first:highs] = steps[high] >> 8
        self._tf_high_indptr = _room(self._tf_high_indptr, position + 2, position + 1)
        self._tf_high_indptr[position + 1] = highs
        self._tf_nnz = needed
        self._tf_indptr = np.append(self._tf_indptr, needed)

    def _entries(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stored rows ``rows`` (in any order) of the term-frequency matrix as CSR arrays ``(data,
        indices, indptr)``: float32 term frequencies (computed as in :meth:`_words`: the same
        values), int32 word ids ascending within a row, int64; decoded from the buffers, at a cost
        that follows those rows' entries, not the database's."""
        rows = np.asarray(rows, dtype=np.int64)
        starts, stops = self._tf_indptr[rows], self._tf_indptr[rows + 1]
        lengths = stops - starts
        offsets = np.concatenate([[0], np.cumsum(lengths)])  # of each row's steps in the gathered ones
        if len(rows) and rows[-1] - rows[0] == len(rows) - 1 and np.all(np.diff(rows) == 1):
            positions = slice(int(starts[0]), int(stops[-1]))  # consecutive rows: one slice, no gather
        else:
            # positions starts[i] .. stops[i]-1 for every selected row, without a Python loop
            positions = np.repeat(starts - offsets[:-1], lengths) + np.arange(offsets[-1])
        steps = self._tf_steps[positions].astype(np.int64)
        # the high bits of the rows' large steps
        first, last = self._tf_high_indptr[rows], self._tf_high_indptr[rows + 1]
        in_row = last - first
        kept = np.repeat(first - np.cumsum(in_row) + in_row, in_row) + np.arange(in_row.sum())
        within = self._tf_high_offsets[kept].astype(np.int64)
        steps[within + np.repeat(offsets[:-1], in_row)] += self._tf_high[kept].astype(np.int64) << 8
        # words: running sums of the steps within each table of each row
        table_lengths = np.repeat(lengths // WORD_TABLES, WORD_TABLES)
        table_starts = np.repeat(offsets[:-1], WORD_TABLES) + np.tile(np.arange(WORD_TABLES), len(rows)) * table_lengths
        running = np.concatenate([[0], np.cumsum(steps)])
        words = running[1:] - np.repeat(running[table_starts], table_lengths)
        words += np.repeat(np.tile(np.arange(WORD_TABLES, dtype=np.int64) << WORD_BITS, len(rows)), table_lengths)
        # distinct words (a zero step repeats the word, except at a table's start) and their counts
        distinct = steps != 0
        distinct[table_starts[table_lengths > 0]] = True
        firsts = np.flatnonzero(distinct)
        counts = np.diff(np.append(firsts, len(steps)))
        indptr = np.concatenate([[0], np.cumsum(distinct)])[offsets]
        totals = np.repeat(lengths.astype(np.float64), np.diff(indptr))
        data = (counts.astype(np.float64) / totals).astype(np.float32)
        return data, words[firsts].astype(np.int32), indptr

    def _rows_csr(self, first_row: int) -> scipy.sparse.csr_matrix:
        """Stored rows ``first_row:`` of the term-frequency matrix as ``(rows, V)`` CSR."""
        data, indices, indptr = self._entries(np.arange(first_row, len(self)))
        return scipy.sparse.csr_matrix((data, indices, indptr), shape=(len(self) - first_row, self.vocabulary_size))

    def _norms(self, first_row: int, idf: np.ndarray) -> np.ndarray:
        """tf-idf norms ``(rows,)`` float32 of the stored rows ``first_row:`` under ``idf``, a
        block of NORM_ROWS rows at a time (each row's norm depends on that row only)."""
        idf_squared = idf**2
        norms = np.zeros(len(self) - first_row, np.float32)
        for start in range(first_row, len(self), NORM_ROWS):
            stop = min(start + NORM_ROWS, len(self))
            data, indices, indptr = self._entries(np.arange(start, stop))
            squares = scipy.sparse.csr_matrix((data * data, indices, indptr), shape=(stop - start, self.vocabulary_size))
            norms[start - first_row : stop - first_row] = np.sqrt(squares @ idf_squared)
        return norms

    def _idf_and_norms(self) -> tuple[np.ndarray, np.ndarray]:
        """Inverse document frequencies ``(V,)`` and stored tf-idf norms ``(num_stored,)``.

        Both depend on the whole database, so they are recomputed only when it has grown by a
        quarter since the last time (amortized O(1) per stored entry, like the inverted file);
        keyframes added since are normed with the cached idf, which then describes at least
        80 % of the database.
        """
        num_stored = len(self)
        cached = 0 if self._idf is None else len(self._stored_norm)
        if self._idf is None or num_stored - self._idf_count > max(64, self._idf_count // 4):
            self._idf = np.log1p(num_stored / np.maximum(self._document_frequency, 1)).astype(np.float32)
            self._stored_norm = self._norms(0, self._idf)
            self._idf_count = num_stored
        elif cached < num_stored:
            self._stored_norm = np.concatenate([self._stored_norm, self._norms(cached, self._idf)])
        return self._idf, self._stored_norm

    def _dot_rows(self, rows: np.ndarray, weighted: scipy.sparse.csr_matrix) -> np.ndarray:
        """``(len(rows), num_queries)`` dot products of stored rows with the query rows ``weighted``.

        Only the words the queries contain matter, so the stored entries are remapped onto that
        compact vocabulary and multiplied with a small dense matrix (a sparse-times-sparse product
        over the full 2^18-word vocabulary costs several times more). The vocabulary-sized mask and
        look-up table persist between calls (only the entries a call set are reset), and the compact
        matrix is built from int32 index arrays, which SciPy takes without converting them.
        """
        data, indices, indptr = self._entries(rows)
        if self._word_lookup is None:
            self._word_present = np.zeros(self.vocabulary_size, dtype=bool)
            self._word_lookup = np.full(self.vocabulary_size, -1, np.int32)
        present, lookup = self._word_present, self._word_lookup
        present[weighted.indices] = True  # a mask over the vocabulary is several times cheaper than np.unique
        query_words = np.flatnonzero(present)
        present[query_words] = False
        lookup[query_words] = np.arange(len(query_words), dtype=np.int32)
        try:
            compact_query = np.zeros((len(query_words), weighted.shape[0]), np.float32)
            query_of_entry = np.repeat(np.arange(weighted.shape[0]), np.diff(weighted.indptr))
            # a query's words are distinct, so every (word, query) entry is written once
            compact_query[lookup[weighted.indices], query_of_entry] = weighted.data
            columns = lookup[indices]
        finally:
            lookup[query_words] = -1
        shared = columns >= 0
        # entries kept before each row boundary: the compact rows' pointers
        kept_before = np.zeros(len(shared) + 1, np.int32)
        np.cumsum(shared, out=kept_before[1:])
        compact_rows = scipy.sparse.csr_matrix(
            (data[shared], columns[shared], kept_before[indptr]), shape=(len(rows), len(query_words)))
        return compact_rows @ compact_query

    def _selected_rows_csr(self, rows: np.ndarray) -> scipy.sparse.csr_matrix:
        """Stored rows ``rows`` of the term-frequency matrix as ``(len(rows), V)`` CSR."""
        data, indices, indptr = self._entries(rows)
        return scipy.sparse.csr_matrix((data, indices, indptr), shape=(len(rows), self.vocabulary_size))

    def _inverted_file(self) -> tuple[scipy.sparse.csr_matrix | None, int]:
        """Inverted file ``(V, rows)`` CSR of the first ``rows`` stored keyframes' term frequencies.

        Transposing the whole database costs O(nnz), so it is redone only when the keyframes
        added since the last build exceed a quarter of those covered (amortized O(1) per
        stored entry); newer keyframes are scored row-wise.
        """
        covered = 0 if self._inverted is None else self._inverted.shape[1]
        if len(self) - covered > max(64, covered // 4):
            self._inverted = self._rows_csr(0).T.tocsr()
            covered = len(self)
        return self._inverted, covered

    def similarity(self, query_features: Sequence[OrbFeatures]) -> np.ndarray:
        """tf-idf cosine similarity ``(num_stored, num_queries)`` float32 of every stored keyframe to each query.

        Inverse document frequency ``log(1 + n / max(n_w, 1))`` over the ``n`` stored keyframes,
        ``n_w`` of which contain word ``w``: positive even for a word in every keyframe (a
        database of one keyframe still ranks). The idf weights go on the query side, so most
        of the database is scored through an inverted file in one sparse product whose cost
        follows the words the query shares with it; the stored vectors' norms take one sparse
        matrix-vector product.
        """
        num_stored = len(self)
        if num_stored == 0 or len(query_features) == 0:
            return np.zeros((num_stored, len(query_features)), np.float32)
        idf, stored_norm = self._idf_and_norms()
        weighted, query_norm = self._query_weights(query_features, idf)
        inverted, covered = self._inverted_file()
        dots = np.zeros((num_stored, len(query_features)), np.float32)
        if covered:
            dots[:covered] = (weighted @ inverted).toarray().T
        if covered < num_stored:
            dots[covered:] = (self._rows_csr(covered) @ weighted.T).toarray()
        denominator = np.maximum(stored_norm[:, None] * query_norm[None, :], 1e-12)
        return (dots / denominator).astype(np.float32)

    # -------------------------------------------------------------------------------------- query

    def verify(self, query: OrbFeatures, stored_position: int) -> int:
        """Epipolar inliers between ``query`` and the stored keyframe at ``stored_position``.

        Returns 0 when there are too few tentative matches to reach ``orb_min_inliers``.
        """
        stored_keypoints, stored_descriptors = self._stored_features(stored_position)
        needed = max(MIN_FUNDAMENTAL_MATCHES, int(self.config.orb_min_inliers))
        if len(query) < needed or len(stored_descriptors) < needed:
            return 0
        query_idx, stored_idx = match_descriptors(query.descriptors, stored_descriptors, self.ratio, self.max_hamming)
        if len(query_idx) < needed:
            return 0
        points_query = query.keypoints[query_idx].astype(np.float64)
        points_stored = stored_keypoints[stored_idx].astype(np.float64)
        cv2.setRNGSeed(self.seed)  # RANSAC sampling: the same result for the same pair, whatever came before
        fundamental, mask = cv2.findFundamentalMat(
            points_query, points_stored, cv2.FM_RANSAC, self.epipolar_threshold_px, 0.999, 2000
        )
        if fundamental is None or mask is None:
            return 0
        return int(np.count_nonzero(mask))

    def query(self, frames: Sequence[Frame], submap_id: int, max_results: int) -> list[LoopCandidate]:
        """Loop candidates for the new keyframes ``frames`` of submap ``submap_id``, best first.

        Only stored keyframes of submaps with id ``<= submap_id - 1 - tau_interval`` are
        considered. The ``orb_candidates`` most similar (query, stored) pairs of the whole batch
        (bag of words) are verified geometrically in order of similarity — a fixed budget per
        submap, so the cost does not grow with the number of query keyframes — and for each query
        keyframe the verified match with most epipolar inliers is kept if it has at least
        ``orb_min_inliers``. Verification stops as soon as ``max_results`` query keyframes have a
        match (the pipeline asks for ``w_loop = 1``: the most similar pair that verifies wins, and
        a revisit costs one verification instead of five). The kept candidates are sorted by
        distance (ties: query frame, then match frame) and the first ``max_results`` returned.
        """
        self._check_open()
        frame_indices, images = [f.index for f in frames], [f.rgb for f in frames]
        batch = [self._features(index, image) for index, image in zip(frame_indices, images)]
        # Keep only this batch for the add() that follows, so repeated queries do not accumulate.
        self._pending = {int(index): self._pending[int(index)] for index in frame_indices}
        if max_results <= 0 or len(self) == 0:
            return []
        eligible = np.flatnonzero(self._submap_ids <= int(submap_id) - 1 - int(self.config.tau_interval))
        if len(eligible) == 0:
            return []
        if len(eligible) > COARSE_CANDIDATES:  # coarse: hashed rows; fine: exact tf-idf on the best rows
            eligible = self.coarse_rows(np.stack([_global_vector(f) for f in batch]), eligible)
        scores = self.similarity_rows(batch, eligible)  # (num_candidates, num_queries)
        budget = float(self.config.orb_features)
        flat = np.argsort(-scores, axis=None, kind="stable")[: int(self.config.orb_candidates)]
        best: dict[int, tuple[int, int]] = {}  # query column -> (inliers, stored position)
        for row, column in zip(*np.unravel_index(flat, scores.shape)):
            if len(best) >= max_results:
                break  # enough query keyframes matched: the rest of the budget is not spent
            if scores[row, column] <= 0:
                continue
            position = int(eligible[row])
            inliers = self.verify(batch[column], position)
            if inliers >= self.config.orb_min_inliers and inliers > best.get(int(column), (0, -1))[0]:
                best[int(column)] = (inliers, position)
        candidates = [
            LoopCandidate(
                query_frame=int(frame_indices[column]),
                match_frame=int(self._frame_indices[position]),
                match_submap=int(self._submap_ids[position]),
                distance=float(max(0.0, 1.0 - inliers / budget)),
            )
            for column, (inliers, position) in best.items()
        ]
        candidates.sort(key=lambda c: (c.distance, c.query_frame, c.match_frame))
        return candidates[:max_results]


class _FeatureFile:
    """Keypoints and descriptors of stored keyframes in one append-only file, read back by position.

    Each record is the keypoints' float32 bytes then the descriptors' uint8 bytes; records are
    written in position order, and their bounds stay in RAM (8 bytes a keyframe). The file is
    started empty; ``path`` ``None``: an anonymous temporary file."""

    def __init__(self, path: Path | None) -> None:
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._file = open(path, "w+b") if path is not None else tempfile.TemporaryFile()
        self._bounds = np.zeros(1, np.int64)  # record p is bytes _bounds[p]:_bounds[p + 1]
        self._written = 0
        self._end = 0
        self._unflushed = False

    def close(self) -> None:
        """Close the file (an anonymous one is removed)."""
        self._file.close()

    def write(self, position: int, keypoints: np.ndarray, descriptors: np.ndarray) -> None:
        """Append the record of ``position``, the next one in order."""
        if position != self._written:
            raise ValueError(f"feature records are written in order: expected position {self._written}, got {position}")
        data = np.ascontiguousarray(keypoints, np.float32).tobytes() + np.ascontiguousarray(descriptors, np.uint8).tobytes()
        self._file.seek(self._end)
        self._file.write(data)
        self._end += len(data)
        self._bounds = _room(self._bounds, position + 2, position + 1)
        self._bounds[position + 1] = self._end
        self._written += 1
        self._unflushed = True

    def read(self, position: int) -> tuple[np.ndarray, np.ndarray]:
        if not 0 <= position < self._written:
            raise KeyError(position)
        offset = int(self._bounds[position])
        count = (int(self._bounds[position + 1]) - offset) // (8 + 32)
        if self._unflushed:  # reads see the writes after a flush of the buffer
            self._file.flush()
            self._unflushed = False
        self._file.seek(offset)
        data = self._file.read(count * (8 + 32))
        keypoints = np.frombuffer(data, np.float32, count * 2).reshape(count, 2)
        descriptors = np.frombuffer(data, np.uint8, count * 32, offset=count * 8).reshape(count, 32)
        return keypoints, descriptors


def _room(buffer: np.ndarray, needed: int, used: int, minimum: int = 64) -> np.ndarray:
    """``buffer`` when it has ``needed`` rows, else a copy of its first ``used`` rows in a buffer a
    quarter larger (at least ``needed`` and ``minimum`` rows): amortized O(1) per row, at most 25 %
    slack."""
    if needed <= len(buffer):
        return buffer
    grown = np.zeros((max(needed, len(buffer) + len(buffer) // 4, minimum),) + buffer.shape[1:], buffer.dtype)
    grown[:used] = buffer[:used]
    return grown


def _same_image(kept: np.ndarray, image: np.ndarray) -> bool:
    """Whether ``image`` equals the copy ``kept`` (same shape, dtype and pixels)."""
    image = np.asarray(image)
    return kept.shape == image.shape and kept.dtype == image.dtype and np.array_equal(kept, image)


def _global_vector(features: OrbFeatures) -> np.ndarray:
    """Term frequencies hashed into ``GLOBAL_DIM`` buckets, L2-normalized: ``(GLOBAL_DIM,)`` float32."""
    vector = np.bincount(features.word_ids % GLOBAL_DIM, weights=features.word_tf, minlength=GLOBAL_DIM)
    norm = np.linalg.norm(vector)
    return (vector / norm if norm > 0 else vector).astype(np.float32)


def registry_entry() -> RetrievalEntry:
    """ORB retrieval in the catalog (``sl4slam.registry``): built from the run's ``[retrieval]`` section."""
    return RetrievalEntry("orb", lambda resolved: OrbRetrieval(resolved.config.retrieval),
                          "ORB features, bag of words and geometric verification; no weights")
