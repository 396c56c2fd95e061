"""Image-match ratio of two frames from VGGT's global attention (VGGT-SLAM 2.0's loop check).

VGGT-SLAM 2.0 (Maggio and Carlone, 2026) re-runs a retrieved loop frame through VGGT next to the
query keyframe and keeps the loop only if the model's own attention says the two images overlap.
The score (their VGGT fork, ``get_similarity`` in the aggregator; restated here) is read at one
global-attention block from the queries ``q`` (scaled by ``head_dim^-1/2``) and keys ``k`` of the two
frames' tokens, laid out ``[first frame (P tokens), second frame (P tokens)]``, each frame's tokens
being ``[camera, registers, patches]``:

1. for every *patch* token ``j`` of the first frame, a softmax of the logits ``q_i . k_j`` over all
   ``2P`` query tokens ``i`` (which tokens look at patch ``j``), averaged over heads: ``a[j, i]``;
2. the second frame's part normalised by the first frame's largest: ``r[j, i] = a[j, i] /
   (max_{i' in first} a[j, i'] + 1e-8)`` for ``i`` in the second frame;
3. for every token ``i`` of the second frame, its best first-frame patch: ``m_i = max_j r[j, i]``;
4. the score is the mean of the ``m_i`` at or above their 75th percentile (linear interpolation):
   the top quarter.

A score near 1 says a quarter of the second image's tokens attend to some patch of the first as
strongly as the first image's own tokens do, which happens when the images show the same surfaces.
The reference runs the first frame = the query keyframe, the second = the retrieved frame, reads
global block 21 (the 22nd of 24) and accepts a loop at 0.85.

:class:`MatchRatioProbe` computes the score during an ordinary forward pass (no second pass): a
pre-hook on the chosen block's attention takes the tokens of the requested frame pairs, computes
their ``q`` and ``k`` with that attention's own projection, norms and rotary embedding (a token's
``q`` and ``k`` depend on that token only), and scores them. For a two-frame pass this is exactly the
reference computation (``tests/test_keyframe_graph.py`` checks it against numbers of the reference
code path); for a pair inside a longer window, the tokens carry the whole window's context. Scores
are computed in float32 whatever the model's compute dtype (the reference computes in bfloat16).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import Tensor, nn

MATCH_LAYER = 21
"""Global block whose attention VGGT-SLAM 2.0 reads (0-based, of 24 in VGGT-1B; its fork's ``target_layer``)."""
MATCH_THRESHOLD = 0.85
"""Score from which VGGT-SLAM 2.0 accepts a loop (``solver.py``)."""


def mean_top_quarter(values: np.ndarray) -> float:
    """Mean of the values at or above their 75th percentile (numpy's linear interpolation)."""
    flat = np.asarray(values, dtype=np.float64).ravel()
    return float(flat[flat >= np.percentile(flat, 75)].mean())


def match_ratio(q: Tensor, k: Tensor, tokens_per_frame: int, patch_start: int) -> np.ndarray:
    """The image-match ratio of the module doc, one per sequence.

    Args:
        q: ``(B, heads, 2P, d)`` queries of the two frames' tokens, already scaled by ``d^-1/2``.
        k: ``(B, heads, 2P, d)`` their keys.
        tokens_per_frame: ``P``.
        patch_start: index of a frame's first patch token (1 + registers; 5 in VGGT).

    Returns:
        ``(B,)`` float64 scores.
    """
    P = int(tokens_per_frame)
    if q.shape[2] != 2 * P or k.shape != q.shape:
        raise ValueError(f"expected q and k of two frames of {P} tokens, got {tuple(q.shape)} and {tuple(k.shape)}")
    q, k = q.float(), k.float()
    logits = torch.einsum("bhjd,bhid->bhji", k[:, :, patch_start:P], q)  # (B, heads, first patches, 2P)
    a = logits.softmax(dim=-1).mean(dim=1)  # over queries, then heads: (B, patches, 2P)
    best_in_first = a[..., :P].amax(dim=-1, keepdim=True)
    best_patch = (a[..., P:] / (best_in_first + 1e-8)).amax(dim=1)  # (B, P): per second-frame token
    return np.array([mean_top_quarter(row) for row in best_patch.cpu().numpy()])


def pair_query_key(attention: nn.Module, x: Tensor, pos: Tensor, first: int, second: int,
                   tokens_per_frame: int) -> tuple[Tensor, Tensor]:
    """Scaled ``q`` and ``k`` ``(B, heads, 2P, d)`` of frames ``first`` and ``second`` (in that order)
    of a global attention's input ``x`` ``(B, S*P, C)`` with positions ``pos`` ``(B, S*P, 2)``."""
    P = int(tokens_per_frame)
    pick = torch.cat([torch.arange(first * P, (first + 1) * P), torch.arange(second * P, (second + 1) * P)]).to(x.device)
    q, k, _ = attention.query_key_value(x[:, pick], pos[:, pick])
    return q * attention.head_dim**-0.5, k


class MatchRatioProbe:
    """Scores frame pairs at one global block during a forward pass of the aggregator.

    Args:
        aggregator: the model's :class:`~sl4slam.models.vggt.aggregator.Aggregator`.
        pairs: ``(first, second)`` frame slots of the sequence to score.
        num_frames: frames in the sequence (S).
        layer: the global block (0-based); :data:`MATCH_LAYER` for VGGT-1B.

    Use as a context manager around the forward pass; :attr:`ratios` is then ``(B, len(pairs))``.

    Example::

        with MatchRatioProbe(model.aggregator, [(0, 5)], num_frames=6) as probe:
            model(images)
        score = probe.ratios[0, 0]
    """

    def __init__(self, aggregator: nn.Module, pairs: Sequence[tuple[int, int]], num_frames: int,
                 layer: int = MATCH_LAYER) -> None:
        depth = len(aggregator.global_blocks)
        if not 0 <= layer < depth:
            raise ValueError(f"the model has {depth} global attention layers; layer {layer} does not exist")
        for first, second in pairs:
            if not (0 <= first < num_frames and 0 <= second < num_frames) or first == second:
                raise ValueError(f"frame pair ({first}, {second}) is not two different frames of {num_frames}")
        self.attention = aggregator.global_blocks[layer].attn
        self.pairs = [(int(a), int(b)) for a, b in pairs]
        self.num_frames = int(num_frames)
        self.patch_start = int(aggregator.patch_start_idx)
        self.ratios: np.ndarray | None = None
        self._handle = None

    def _hook(self, module: nn.Module, args: tuple) -> None:
        x, pos = args[0], args[1]
        tokens_per_frame = x.shape[1] // self.num_frames
        with torch.no_grad():
            scores = [match_ratio(*pair_query_key(module, x, pos, a, b, tokens_per_frame), tokens_per_frame,
                                  self.patch_start) for a, b in self.pairs]
        self.ratios = np.stack(scores, axis=1) if scores else np.zeros((x.shape[0], 0))

    def __enter__(self) -> "MatchRatioProbe":
        self._handle = self.attention.register_forward_pre_hook(self._hook)
        return self

    def __exit__(self, *exc) -> None:
        if self._handle is not None:
            self._handle.remove()
            self._handle = None
