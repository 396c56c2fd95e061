"""Weights-free loop-closure retrieval: ORB features, binary bag of words, epipolar verification.

A CPU-only stand-in for SALAD (paper 4.3) that needs no download. Per stored keyframe we keep
its ORB keypoints and descriptors and a sparse bag of binary words; a query

1. ranks the stored keyframes of eligible submaps (ids ``<= submap_id - 1 - tau_interval``) by
   tf-idf cosine similarity of their word histograms (sparse products through an inverted
   file, so ranking stays vectorized as the database grows),
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

Memory per stored keyframe (1000 features): descriptors 32 kB uint8, keypoints 8 kB float32,
words <= 32 kB (int32 ids + float32 term frequencies); no images are kept.
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

        # Database: one entry per stored keyframe.
        self._frame_indices: list[int] = []
        self._submap_ids = np.zeros(0, np.int64)
        self._keypoints: list[np.ndarray | None] = []  # None: spilled to the features file
        self._descriptors: list[np.ndarray | None] = []
        self._spill: _FeatureFile | None = None  # see spill_features
        self._features_in_ram = 0  # keep this many newest keyframes' features in RAM (0: all)
        self._spilled = 0  # positions below this are in the file
        self._document_frequency = np.zeros(self.vocabulary_size, np.int32)
        # Term-frequency matrix (stored keyframes x words) as growable CSR buffers.
        self._tf_indptr = np.zeros(1, np.int64)
        self._tf_indices = np.zeros(0, np.int32)
        self._tf_data = np.zeros(0, np.float32)
        self._tf_nnz = 0
        # Inverted file (words x keyframes) over the first keyframes; see _inverted_file().
        self._inverted: scipy.sparse.csr_matrix | None = None
        self._idf: np.ndarray | None = None  # cached, see _idf_and_norms
        self._global = np.zeros((0, GLOBAL_DIM), np.float32)  # hashed tf rows, grown geometrically
        self.describe_seconds = 0.0  # time spent extracting features (the "descriptor model")
        self._stored_norm = np.zeros(0, np.float32)
        # vocabulary-sized scratch of _dot_rows (allocated at its first call, all False / -1 between calls)
        self._word_present: np.ndarray | None = None
        self._word_lookup: np.ndarray | None = None
        # Features of the latest query batch, keyed by frame index, reused by the following add().
        self._pending: dict[int, tuple[np.ndarray, OrbFeatures]] = {}

    def __len__(self) -> int:
        """Number of stored keyframes."""
        return len(self._frame_indices)

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
        keypoints = self._keypoints[position]
        if keypoints is not None:
            return keypoints, self._descriptors[position]
        return self._spill.read(position)

    def _spill_oldest(self) -> None:
        """Move the features of keyframes beyond the newest ``_features_in_ram`` to the file."""
        if self._spill is None:
            return
        while len(self) - self._spilled > self._features_in_ram:
            position = self._spilled
            self._spill.write(position, self._keypoints[position], self._descriptors[position])
            self._keypoints[position] = self._descriptors[position] = None
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
        frame_indices, images = [f.index for f in frames], [f.rgb for f in frames]
        batch = [self._features(index, image) for index, image in zip(frame_indices, images)]
        self._pending.clear()
        for index, features in zip(frame_indices, batch):
            self._frame_indices.append(int(index))
            self._keypoints.append(features.keypoints)
            self._descriptors.append(features.descriptors)
            self._append_tf_row(features.word_ids, features.word_tf)
            self._document_frequency[features.word_ids] += 1
            self._append_global_row(_global_vector(features))
        self._submap_ids = np.concatenate([self._submap_ids, np.full(len(batch), int(submap_id), np.int64)])
        self._spill_oldest()

    def mark(self) -> dict:
        """What :meth:`rewind` needs to return the database to this moment: the stored count, the
        buffers' fill and the cached idf, norms and inverted file (replaced, never changed in place,
        so references are enough). Cost independent of the database's size."""
        return {"count": len(self), "nnz": self._tf_nnz, "indptr": self._tf_indptr, "submap_ids": self._submap_ids,
                "idf": self._idf, "stored_norm": self._stored_norm, "inverted": self._inverted,
                "pending": dict(self._pending)}

    def rewind(self, mark: dict) -> None:
        """Forget every keyframe added since :meth:`mark` returned ``mark``: the database, its caches
        and the latest query's features are as they were then (queries give the same answers)."""
        count = int(mark["count"])
        if count < self._spilled:  # only the newest keyframes are ever withdrawn, and they are in RAM
            raise ValueError(f"cannot rewind to {count} keyframes: the first {self._spilled} were spilled")
        if len(self) > count:
            start = int(self._tf_indptr[count])
            np.subtract.at(self._document_frequency, self._tf_indices[start: self._tf_nnz], 1)
            del self._frame_indices[count:], self._keypoints[count:], self._descriptors[count:]
        self._tf_nnz = int(mark["nnz"])
        self._tf_indptr, self._submap_ids = mark["indptr"], mark["submap_ids"]
        self._idf, self._stored_norm, self._inverted = mark["idf"], mark["stored_norm"], mark["inverted"]
        self._pending = dict(mark["pending"])

    def _append_global_row(self, row: np.ndarray) -> None:
        count = len(self._frame_indices) - 1  # the row's position (frame index already appended)
        if count >= len(self._global):
            grown = np.zeros((max(64, len(self._global) + len(self._global) // 4), GLOBAL_DIM), np.float32)
            grown[: len(self._global)] = self._global
            self._global = grown
        self._global[count] = row

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

    def _append_tf_row(self, word_ids: np.ndarray, word_tf: np.ndarray) -> None:
        needed = self._tf_nnz + len(word_ids)
        if needed > len(self._tf_indices):  # grow geometrically: amortized O(1) per entry
            capacity = max(needed, len(self._tf_indices) + len(self._tf_indices) // 4, 4096)  # 1.25x: less slack
            grown_indices = np.zeros(capacity, np.int32)
            grown_data = np.zeros(capacity, np.float32)
            grown_indices[: self._tf_nnz] = self._tf_indices[: self._tf_nnz]
            grown_data[: self._tf_nnz] = self._tf_data[: self._tf_nnz]
            self._tf_indices, self._tf_data = grown_indices, grown_data
        self._tf_indices[self._tf_nnz : needed] = word_ids
        self._tf_data[self._tf_nnz : needed] = word_tf
        self._tf_nnz = needed
        self._tf_indptr = np.append(self._tf_indptr, needed)

    def _rows_csr(self, first_row: int, values: np.ndarray | None = None) -> scipy.sparse.csr_matrix:
        """Stored rows ``first_row:`` of the term-frequency matrix as ``(rows, V)`` CSR (views of
        the buffers, no copy); ``values`` replaces the term frequencies of those rows."""
        start, stop = int(self._tf_indptr[first_row]), self._tf_nnz
        data = self._tf_data[start:stop] if values is None else values
        return scipy.sparse.csr_matrix(
            (data, self._tf_indices[start:stop], self._tf_indptr[first_row:] - start),
            shape=(len(self) - first_row, self.vocabulary_size),
        )

    def _idf_and_norms(self) -> tuple[np.ndarray, np.ndarray]:
        """Inverse document frequencies ``(V,)`` and stored tf-idf norms ``(num_stored,)``.

        Both depend on the whole database, so they are recomputed only when it has grown by a
        quarter since the last time (amortized O(1) per stored entry, like the inverted file);
        keyframes added since are normed with the cached idf, which then describes at least
        80 % of the database.
        """
        num_stored = len(self)
        cached = 0 if self._idf is None else len(self._stored_norm)
        if self._idf is None or num_stored - cached > max(64, cached // 4):
            self._idf = np.log1p(num_stored / np.maximum(self._document_frequency, 1)).astype(np.float32)
            term_frequency = self._tf_data[: self._tf_nnz]
            self._stored_norm = np.sqrt(self._rows_csr(0, term_frequency * term_frequency) @ (self._idf**2))
        elif cached < num_stored:
            start = int(self._tf_indptr[cached])
            term_frequency = self._tf_data[start : self._tf_nnz]
            new_norms = np.sqrt(self._rows_csr(cached, term_frequency * term_frequency) @ (self._idf**2))
            self._stored_norm = np.concatenate([self._stored_norm, new_norms])
        return self._idf, self._stored_norm

    def _dot_rows(self, rows: np.ndarray, weighted: scipy.sparse.csr_matrix) -> np.ndarray:
        """``(len(rows), num_queries)`` dot products of stored rows with the query rows ``weighted``.

        Only the words the queries contain matter, so the stored entries are remapped onto that
        compact vocabulary and multiplied with a small dense matrix (a sparse-times-sparse product
        over the full 2^18-word vocabulary costs several times more). The vocabulary-sized mask and
        look-up table persist between calls (only the entries a call set are reset), and the compact
        matrix is built from int32 index arrays, which SciPy takes without converting them.
        """
        data, indices, indptr = self._selected_entries(rows)
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

    def _selected_entries(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stored rows ``rows`` of the term-frequency matrix as CSR arrays ``(data, indices, indptr)``
        (float32, int32, int64), gathered straight from the buffers (cost follows those rows'
        entries, not the database's)."""
        rows = np.asarray(rows, dtype=np.int64)
        starts, stops = self._tf_indptr[rows], self._tf_indptr[rows + 1]
        lengths = stops - starts
        indptr = np.concatenate([[0], np.cumsum(lengths)])
        # positions starts[i] .. stops[i]-1 for every selected row, without a Python loop
        positions = np.repeat(starts - indptr[:-1], lengths) + np.arange(indptr[-1])
        return self._tf_data[positions], self._tf_indices[positions], indptr

    def _selected_rows_csr(self, rows: np.ndarray) -> scipy.sparse.csr_matrix:
        """Stored rows ``rows`` of the term-frequency matrix as ``(len(rows), V)`` CSR."""
        data, indices, indptr = self._selected_entries(rows)
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
        frame_indices, images = [f.index for f in frames], [f.rgb for f in frames]
        batch = [self._features(index, image) for index, image in zip(frame_indices, images)]
        # Keep only this batch for the add() that follows, so repeated queries do not accumulate.
        self._pending = {int(index): self._pending[int(index)] for index in frame_indices}
        if max_results <= 0 or len(self) == 0:
            return []
        eligible = np.flatnonzero(self._submap_ids <= int(submap_id) - 1 - int(self.config.tau_interval))
        if len(eligible) == 0:
            return []
        if len(eligible) > COARSE_CANDIDATES:
            # coarse: one dense product over the database; fine: exact tf-idf on the best rows
            queries = np.stack([_global_vector(f) for f in batch])
            # eligible rows are a prefix while submap ids arrive in order: no copy then
            prefix = eligible[-1] == len(eligible) - 1
            stored = self._global[: len(eligible)] if prefix else self._global[eligible]
            coarse = stored @ queries.T  # (num_eligible, num_queries)
            best = np.argpartition(-coarse, COARSE_CANDIDATES - 1, axis=0)[:COARSE_CANDIDATES]
            eligible = eligible[np.unique(best)]
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
                match_frame=self._frame_indices[position],
                match_submap=int(self._submap_ids[position]),
                distance=float(max(0.0, 1.0 - inliers / budget)),
            )
            for column, (inliers, position) in best.items()
        ]
        candidates.sort(key=lambda c: (c.distance, c.query_frame, c.match_frame))
        return candidates[:max_results]


class _FeatureFile:
    """Keypoints and descriptors of stored keyframes in one append-only file, read back by position.

    Each record is the keypoints' float32 bytes then the descriptors' uint8 bytes; the offsets and
    counts stay in RAM (16 bytes a keyframe). The file is started empty; ``path`` ``None``: an
    anonymous temporary file."""

    def __init__(self, path: Path | None) -> None:
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._file = open(path, "w+b") if path is not None else tempfile.TemporaryFile()
        self._records: dict[int, tuple[int, int]] = {}  # position -> (offset, count)
        self._end = 0
        self._unflushed = False

    def write(self, position: int, keypoints: np.ndarray, descriptors: np.ndarray) -> None:
        data = np.ascontiguousarray(keypoints, np.float32).tobytes() + np.ascontiguousarray(descriptors, np.uint8).tobytes()
        self._file.seek(self._end)
        self._file.write(data)
        self._records[position] = (self._end, len(keypoints))
        self._end += len(data)
        self._unflushed = True

    def read(self, position: int) -> tuple[np.ndarray, np.ndarray]:
        offset, count = self._records[position]
        if self._unflushed:  # reads see the writes after a flush of the buffer
            self._file.flush()
            self._unflushed = False
        self._file.seek(offset)
        data = self._file.read(count * (8 + 32))
        keypoints = np.frombuffer(data, np.float32, count * 2).reshape(count, 2)
        descriptors = np.frombuffer(data, np.uint8, count * 32, offset=count * 8).reshape(count, 32)
        return keypoints, descriptors


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
