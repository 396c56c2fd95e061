"""Choosing the reference view of a multi-view forward, and moving it to the front.

Depth Anything 3 expresses its cameras in the frame of one *reference view*. Without known cameras,
and with at least :data:`MIN_VIEWS_FOR_SELECTION` views, the backbone picks that view from the
frames' class tokens just before its first camera-aware block, moves it to the front for the rest of
the backbone (the first slot gets the reference camera token), and puts the outputs back in input
order. Strategies (the authors' names):

- ``"first"`` / ``"middle"``: slot 0 / slot ``S // 2``;
- ``"saddle_balanced"`` (their default): per view, three statistics of its class token ``c``:
  the mean cosine similarity to the other views, ``|c|``, and the variance of ``c / |c|`` over
  channels; each min-max scaled to [0, 1] over the views (``(v - min) / (max - min + 1e-8)``);
  the view whose three scaled values are closest to 0.5 (sum of ``|v - 0.5|``) wins;
- ``"saddle_sim_range"``: the view with the largest range (max - min) of cosine similarity to the
  others (the diagonal counted as ``1 - 1 = 0``).

Ties go to the lowest slot (``argmin`` / ``argmax``).
"""

from __future__ import annotations

import torch
from torch import Tensor

STRATEGIES = ("first", "middle", "saddle_balanced", "saddle_sim_range")
MIN_VIEWS_FOR_SELECTION = 3
"""Fewer views keep their order (the authors' ``THRESH_FOR_REF_SELECTION``)."""


def _scale_to_unit_range(values: Tensor) -> Tensor:
    """``(B, S)`` -> ``(v - min) / (max - min + 1e-8)`` over S."""
    low = values.min(dim=1, keepdim=True).values
    high = values.max(dim=1, keepdim=True).values
    return (values - low) / (high - low + 1e-8)


def _similarity_without_self(unit_tokens: Tensor) -> Tensor:
    """``(B, S, S)`` cosine similarities of unit tokens ``(B, S, C)``, the diagonal lowered by 1."""
    views = unit_tokens.shape[1]
    similarity = torch.matmul(unit_tokens, unit_tokens.transpose(1, 2))
    return similarity - torch.eye(views, device=similarity.device).unsqueeze(0)


def choose_reference_view(class_tokens: Tensor, strategy: str = "saddle_balanced") -> Tensor:
    """Reference slot of each sequence.

    Args:
        class_tokens: ``(B, S, C)`` the views' class tokens (may be a strided view).
        strategy: one of :data:`STRATEGIES` (see the module docstring).

    Returns:
        ``(B,)`` int64 slot indices.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown reference-view strategy {strategy!r}: use one of {', '.join(STRATEGIES)}")
    batch, views = class_tokens.shape[:2]
    device = class_tokens.device
    if views <= 1 or strategy == "first":
        return torch.zeros(batch, dtype=torch.long, device=device)
    if strategy == "middle":
        return torch.full((batch,), views // 2, dtype=torch.long, device=device)
    unit = class_tokens / class_tokens.norm(dim=-1, keepdim=True)
    similarity = _similarity_without_self(unit)
    if strategy == "saddle_sim_range":
        spread = similarity.max(dim=-1).values - similarity.min(dim=-1).values
        return spread.argmax(dim=1)
    mean_similarity = similarity.sum(dim=-1) / (views - 1)
    length = class_tokens.norm(dim=-1)
    channel_variance = unit.var(dim=-1)
    distance_from_middle = (
        (_scale_to_unit_range(mean_similarity) - 0.5).abs()
        + (_scale_to_unit_range(length) - 0.5).abs()
        + (_scale_to_unit_range(channel_variance) - 0.5).abs()
    )
    return distance_from_middle.argmin(dim=1)


def front_order(reference: Tensor, views: int) -> Tensor:
    """``(B, S)`` input slots in the order ``[reference, the others in input order]``."""
    slots = torch.arange(views, device=reference.device).unsqueeze(0).expand(reference.shape[0], -1)
    shifted = torch.where((slots > 0) & (slots <= reference[:, None]), slots - 1, slots)
    shifted[:, 0] = reference
    return shifted


def input_order(reference: Tensor, views: int) -> Tensor:
    """``(B, S)``: for each input slot, where it sits in :func:`front_order` (its inverse)."""
    slots = torch.arange(views, device=reference.device).unsqueeze(0).expand(reference.shape[0], -1)
    back = torch.where(slots < reference[:, None], slots + 1, slots)
    return back.scatter(1, reference[:, None], torch.zeros_like(reference[:, None]))


def gather_views(tensor: Tensor, order: Tensor) -> Tensor:
    """``tensor`` ``(B, S, ...)`` with its views taken in ``order`` ``(B, S)`` (a new tensor)."""
    if tensor.shape[1] <= 1:
        return tensor
    batch_index = torch.arange(tensor.shape[0], device=tensor.device).unsqueeze(1)
    return tensor[batch_index, order]
