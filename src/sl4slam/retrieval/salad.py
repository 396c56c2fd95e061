"""Loop-closure retrieval with SALAD descriptors (VGGT-SLAM, paper section 4.3).

Every keyframe gets an 8448-dim unit-norm SALAD descriptor; a new keyframe's loop candidate is
its nearest stored keyframe by L2 distance among submaps older than the latest ``tau_interval``,
accepted when the distance is below ``tau_desc`` (0.8). :class:`DescriptorIndex` stores the
descriptors compactly (float16) and answers a batch of queries with one matrix product, so a
query stays cheap as the map grows to tens of thousands of keyframes.
"""

from __future__ import annotations

import time

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .settings import RetrievalConfig
from ..registry import RetrievalEntry
from ..types import Frame, LoopCandidate


@dataclass
class SearchResult:
    """Nearest stored descriptors for each query, ascending distance.

    All arrays are ``(Q, k)``; slots without an acceptable match hold distance ``inf``,
    frame and submap id ``-1``.
    """

    distances: np.ndarray
    frame_ids: np.ndarray
    submap_ids: np.ndarray


class DescriptorIndex:
    """Exact L2 nearest-neighbour search over descriptors, stored as rows of one matrix.

    Ranking uses ``|q - e|^2 = |q|^2 + 2 (|e|^2 / 2 - q.e)``: the bracket for a batch of queries
    against all eligible rows is one fused matrix product (``addmm``) in the storage dtype
    (float16 by default: half the memory traffic of float32, which bounds the query time on
    CPU; a ranking value is rounded once, about 2.5e-4 for unit vectors). The k winners are
    then measured exactly in float32 from the stored rows and re-sorted, so reported distances
    carry only the storage rounding of the descriptors.
    Descriptors are expected to have moderate norms (SALAD's are unit vectors).

    Rows are appended in insertion order; while submap ids arrive in non-decreasing order (the
    pipeline's case) the rows eligible for ``max_submap_id`` are a prefix and are searched in
    place, otherwise a mask is applied.

    Args:
        dim: descriptor length D.
        dtype: storage (and matrix-product) dtype, ``torch.float16`` or ``torch.float32``.
        device: where the matrix lives (a GPU makes large searches faster still).
        initial_capacity: rows allocated up front; the matrix doubles when full.
    """

    def __init__(
        self,
        dim: int,
        dtype: torch.dtype = torch.float16,
        device: str | torch.device = "cpu",
        initial_capacity: int = 1024,
    ) -> None:
        self.dim = dim
        self.dtype = dtype
        self.device = torch.device(device)
        self._size = 0
        self._vectors = torch.empty((max(1, initial_capacity), dim), dtype=dtype, device=self.device)
        self._sq_norms = torch.empty(max(1, initial_capacity), dtype=torch.float32, device=self.device)
        self._frame_ids = np.empty(max(1, initial_capacity), dtype=np.int64)
        self._submap_ids = np.empty(max(1, initial_capacity), dtype=np.int64)
        self._submaps_sorted = True

    def __len__(self) -> int:
        return self._size

    @property
    def bytes_per_descriptor(self) -> int:
        """Memory per stored descriptor: the row, its float32 norm and two int64 ids."""
        return self.dim * self._vectors.element_size() + 4 + 8 + 8

    @property
    def frame_ids(self) -> np.ndarray:
        return self._frame_ids[: self._size]

    @property
    def submap_ids(self) -> np.ndarray:
        return self._submap_ids[: self._size]

    def _reserve(self, rows: int) -> None:
        capacity = self._vectors.shape[0]
        if rows <= capacity:
            return
        new_capacity = max(rows, 2 * capacity)
        vectors = torch.empty((new_capacity, self.dim), dtype=self.dtype, device=self.device)
        vectors[: self._size] = self._vectors[: self._size]
        sq_norms = torch.empty(new_capacity, dtype=torch.float32, device=self.device)
        sq_norms[: self._size] = self._sq_norms[: self._size]
        self._vectors, self._sq_norms = vectors, sq_norms
        self._frame_ids = np.resize(self._frame_ids, new_capacity)
        self._submap_ids = np.resize(self._submap_ids, new_capacity)

    def add(self, descriptors: np.ndarray | Tensor, frame_ids: Sequence[int] | np.ndarray, submap_ids: int | Sequence[int] | np.ndarray) -> None:
        """Append ``descriptors`` ``(N, D)`` with their frame ids ``(N,)`` and submap id(s) (int or ``(N,)``)."""
        vectors = torch.as_tensor(descriptors).to(device=self.device, dtype=self.dtype)
        if vectors.ndim != 2 or vectors.shape[1] != self.dim:
            raise ValueError(f"expected descriptors of shape (N, {self.dim}), got {tuple(vectors.shape)}")
        count = vectors.shape[0]
        frames = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        submaps = np.broadcast_to(np.asarray(submap_ids, dtype=np.int64), (count,))
        if frames.shape[0] != count:
            raise ValueError(f"{count} descriptors but {frames.shape[0]} frame ids")
        if count == 0:
            return
        start, stop = self._size, self._size + count
        self._reserve(stop)
        self._vectors[start:stop] = vectors
        self._sq_norms[start:stop] = vectors.float().square().sum(dim=1)
        self._frame_ids[start:stop] = frames
        self._submap_ids[start:stop] = submaps
        previous = self._submap_ids[start - 1] if start > 0 else submaps[0]
        self._submaps_sorted = self._submaps_sorted and bool(submaps[0] >= previous) and bool(np.all(np.diff(submaps) >= 0))
        self._size = stop

    def mark(self) -> tuple[int, bool]:
        """The stored count and sort flag, for :meth:`rewind`."""
        return self._size, self._submaps_sorted

    def rewind(self, mark: tuple[int, bool]) -> None:
        """Forget the descriptors added since :meth:`mark` returned ``mark`` (rows past the count
        are never read; the next add overwrites them)."""
        self._size, self._submaps_sorted = int(mark[0]), bool(mark[1])

    def search(
        self,
        queries: np.ndarray | Tensor,
        k: int = 1,
        max_submap_id: int | None = None,
        max_distance: float = float("inf"),
    ) -> SearchResult:
        """The ``k`` nearest stored descriptors of each query row.

        Args:
            queries: ``(Q, D)``.
            k: neighbours per query.
            max_submap_id: only rows with submap id ``<= max_submap_id`` are eligible (``None``: all).
            max_distance: matches must have distance strictly below this.
        """
        query = torch.as_tensor(queries).to(device=self.device, dtype=torch.float32)
        if query.ndim != 2 or query.shape[1] != self.dim:
            raise ValueError(f"expected queries of shape (Q, {self.dim}), got {tuple(query.shape)}")
        num_queries = query.shape[0]
        distances = np.full((num_queries, k), np.inf, dtype=np.float32)
        frame_ids = np.full((num_queries, k), -1, dtype=np.int64)
        submap_ids = np.full((num_queries, k), -1, dtype=np.int64)
        submaps = self.submap_ids
        mask = None
        if max_submap_id is None:
            rows = self._size
        elif self._submaps_sorted:
            rows = int(np.searchsorted(submaps, max_submap_id, side="right"))
        else:
            rows = self._size
            mask = torch.as_tensor(submaps > max_submap_id, device=self.device)
        if rows == 0 or num_queries == 0 or k <= 0 or (mask is not None and bool(mask.all())):
            return SearchResult(distances, frame_ids, submap_ids)

        # |q - e|^2 = |q|^2 + 2 (|e|^2 / 2 - q.e): rank all rows by the bracket, computed by one
        # fused matrix product in the storage dtype, then measure the k winners exactly.
        vectors = self._vectors[:rows]
        half_sq_norms = self._sq_norms[:rows].mul(0.5).to(self.dtype)
        ranking = torch.addmm(half_sq_norms.unsqueeze(0), query.to(self.dtype), vectors.T, beta=1, alpha=-1)
        if mask is not None:
            ranking.masked_fill_(mask, float("inf"))
        k_eff = min(k, rows)
        ranked_values, ranked_rows = torch.topk(ranking, k_eff, dim=1, largest=False, sorted=True)
        # Exact float32 distances of the winners only (ranking ties within the storage rounding
        # are equally good matches), re-sorted; masked rows stay excluded.
        winners = vectors[ranked_rows.reshape(-1)].float().view(num_queries, k_eff, self.dim)
        exact = torch.linalg.vector_norm(winners - query.unsqueeze(1), dim=2)
        exact.masked_fill_(torch.isinf(ranked_values), float("inf"))
        order = torch.argsort(exact, dim=1, stable=True)
        best = exact.gather(1, order).cpu().numpy()
        best_rows = ranked_rows.gather(1, order).cpu().numpy()
        accepted = best < max_distance
        distances[:, :k_eff] = np.where(accepted, best, np.inf)
        frame_ids[:, :k_eff] = np.where(accepted, self._frame_ids[best_rows], -1)
        submap_ids[:, :k_eff] = np.where(accepted, self._submap_ids[best_rows], -1)
        return SearchResult(distances, frame_ids, submap_ids)


class SaladRetrieval:
    """SALAD place recognition behind the ``Retrieval`` interface.

    ``query`` returns, for each new keyframe, its nearest stored keyframe among submaps with
    id ``<= submap_id - 1 - tau_interval`` if that distance is below ``tau_desc``; the candidates
    are sorted by distance and cut to ``max_results`` (VGGT-SLAM keeps the ``w_loop`` best).

    Args:
        config: ``kind``, ``tau_interval``, ``tau_desc``, ``salad_weights`` and
            ``salad_image_size`` are used.
        device: "cpu", "cuda" or "cuda:N" for the model and the index (settled by ``sl4slam.resolve``).
        model: a ready :class:`~sl4slam.models.salad.SaladModel` (tests, shared models);
            ``None`` loads ``config.salad_weights`` (or the cached / downloaded release file).
    """

    name = "salad"

    def __init__(self, config: RetrievalConfig, device: str | torch.device = "cpu", model: torch.nn.Module | None = None) -> None:
        from ..models.salad import load_salad

        self.config = config
        self.device = torch.device(device)
        self.model = model if model is not None else load_salad(config.salad_weights, self.device)
        self.model.to(self.device).eval()
        self.image_size = int(config.salad_image_size)
        self.batch_size = 16
        self.describe_seconds = 0.0  # time spent in the descriptor network
        self.index = DescriptorIndex(self.model.output_dim, dtype=torch.float16, device=self.device)
        # The pipeline queries and then adds the same keyframes: keep the last query's
        # descriptors so each image goes through the network once.
        self._last_query: dict[int, np.ndarray] = {}
        self.closed = False  # see close()

    def close(self) -> None:
        """Free the stored descriptors and this retrieval's hold on the network at the end of a run
        (the index alone is 17 kB a keyframe); :meth:`add` and :meth:`query` raise ``RuntimeError``
        afterwards."""
        dim = self.index.dim
        self.closed = True
        self.index = DescriptorIndex(dim, dtype=torch.float16, device=self.device, initial_capacity=1)
        self.model, self._last_query = None, {}

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError("SALAD retrieval was closed at the end of its run: it stores and answers nothing more")

    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """``(N, D)`` float32 descriptors of ``(H, W, 3)`` uint8 RGB images."""
        if len(images) == 0:
            return np.zeros((0, self.model.output_dim), dtype=np.float32)
        start = time.perf_counter()
        descriptors = self.model.describe(images, image_size=self.image_size, batch_size=self.batch_size)
        self.describe_seconds += time.perf_counter() - start
        return descriptors

    def add(self, frames: Sequence[Frame], submap_id: int) -> None:
        """Store the descriptors of the keyframes ``frames`` under ``submap_id``."""
        self._check_open()
        frame_indices, images = [f.index for f in frames], [f.rgb for f in frames]
        cached = [self._last_query.get(int(i)) for i in frame_indices]
        if all(c is not None for c in cached) and cached:
            descriptors = np.stack(cached)
        else:
            descriptors = self.describe(images)
        self._last_query = {}
        self.index.add(descriptors, frame_indices, submap_id)

    def mark(self) -> tuple:
        """What :meth:`rewind` needs to return the index to this moment."""
        return self.index.mark(), dict(self._last_query)

    def rewind(self, mark: tuple) -> None:
        """Forget the keyframes added since :meth:`mark` returned ``mark``."""
        self.index.rewind(mark[0])
        self._last_query = dict(mark[1])

    def query(self, frames: Sequence[Frame], submap_id: int, max_results: int) -> list[LoopCandidate]:
        """Loop candidates for the new keyframes ``frames`` of submap ``submap_id``, best (smallest distance) first."""
        self._check_open()
        frame_indices, images = [f.index for f in frames], [f.rgb for f in frames]
        descriptors = self.describe(images)
        self._last_query = {int(i): d for i, d in zip(frame_indices, descriptors)}
        max_submap = submap_id - 1 - self.config.tau_interval
        if max_results <= 0 or len(self.index) == 0 or len(images) == 0:
            return []
        result = self.index.search(descriptors, k=1, max_submap_id=max_submap, max_distance=self.config.tau_desc)
        found = np.flatnonzero(result.frame_ids[:, 0] >= 0)
        order = found[np.argsort(result.distances[found, 0], kind="stable")][:max_results]
        return [
            LoopCandidate(
                query_frame=int(frame_indices[q]),
                match_frame=int(result.frame_ids[q, 0]),
                match_submap=int(result.submap_ids[q, 0]),
                distance=float(result.distances[q, 0]),
            )
            for q in order
        ]


def registry_entry() -> RetrievalEntry:
    """SALAD retrieval in the catalog (``sl4slam.registry``): built from the run's ``[retrieval]`` section,
    on the run's device."""
    return RetrievalEntry("salad", lambda resolved: SaladRetrieval(resolved.config.retrieval, device=resolved.device),
                          "DINOv2 + SALAD descriptors (the paper's); needs dino_salad.ckpt", uses_device=True)
