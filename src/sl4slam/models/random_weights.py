"""Seeded random weights for any of our models, for tests and benchmarks (a forward's cost does not
depend on the values)."""

from __future__ import annotations

import torch
from torch import nn


@torch.no_grad()
def init_random_weights(model: nn.Module, seed: int = 0, std: float = 0.02) -> nn.Module:
    """Fill every parameter of ``model`` with seeded random values: weights ~ N(0, std^2), norm
    scales 1 + N(0, std^2), LayerScales (``*.gamma``) 0.05 + |N(0, std^2)|; meta parameters are
    materialised on the CPU first. Returns ``model``."""
    if any(p.is_meta for p in model.parameters()):
        model.to_empty(device="cpu")
    generator = torch.Generator().manual_seed(seed)
    for name, param in model.named_parameters():
        noise = torch.empty(param.shape, dtype=torch.float32).normal_(0.0, std, generator=generator)
        if name.endswith(".gamma"):
            value = 0.05 + noise.abs()
        elif param.ndim == 1 and "norm" in name and name.endswith("weight"):
            value = 1.0 + noise
        else:
            value = noise
        param.copy_(value.to(param.dtype))
    return model
