"""Vision-transformer building blocks shared by the DINOv2 backbone and the VGGT aggregator.

Used by:
- :mod:`sl4slam.models.dinov2` (the DINOv2 ViT inside SALAD and inside VGGT's patch embedding):
  pre-norm blocks with LayerNorm eps 1e-6, LayerScale, no qk-norm, no RoPE.
- the VGGT aggregator's frame/global blocks: LayerNorm eps 1e-5, qk-norm and 2D RoPE on q and k.

Parameter names follow the released checkpoints (``attn.qkv``, ``attn.proj``, ``ls1.gamma``,
``mlp.fc1`` ...), so state dicts load without renaming. Tokens are ``(B, N, C)`` throughout.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class Mlp(nn.Module):
    """Two-layer perceptron ``fc2(GELU(fc1(x)))`` with exact (erf) GELU.

    Maps ``(..., in_features)`` to ``(..., out_features)`` (default ``in_features``) through
    ``hidden_features``.
    """

    def __init__(self, in_features: int, hidden_features: int, bias: bool = True, out_features: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features, bias=bias)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_features, out_features or in_features, bias=bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class LayerScale(nn.Module):
    """Per-channel scaling ``x * gamma`` with ``gamma`` of shape ``(dim,)``."""

    def __init__(self, dim: int, init_values: float = 1e-5) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init_values)))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Attention(nn.Module):
    """Multi-head self-attention with a fused qkv projection.

    The ``qkv`` output ``(B, N, 3*dim)`` is read as ``(B, N, 3, heads, head_dim)``: q, k, v in that
    order, heads as contiguous ``head_dim`` blocks. Optional per-head LayerNorm on q and k
    (``qk_norm``), then optional rotary embedding ``rope(t, pos)`` on q and k, then
    ``scaled_dot_product_attention`` with scale ``head_dim ** -0.5``.
    """

    def __init__(
        self,
        dim: int,
        num_heads: int,
        qkv_bias: bool = True,
        proj_bias: bool = True,
        qk_norm: bool = False,
        rope: Callable[[Tensor, Tensor], Tensor] | nn.Module | None = None,
    ) -> None:
        super().__init__()
        if dim % num_heads != 0:
            raise ValueError(f"dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.q_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim, bias=proj_bias)
        self.rope = rope

    def query_key_value(self, x: Tensor, pos: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """``q, k, v`` ``(B, heads, N, head_dim)`` of tokens ``x`` ``(B, N, C)``: q and k normed and
        rotated, q not yet scaled. Each token's q, k, v depend on that token (and its position) only."""
        batch, num_tokens, _ = x.shape
        # (B, N, 3, H, D) -> (3, B, H, N, D)
        qkv = self.qkv(x).reshape(batch, num_tokens, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)
        q, k = self.q_norm(q), self.k_norm(k)
        if self.rope is not None and pos is not None:
            q = self.rope(q, pos)
            k = self.rope(k, pos)
        return q, k, v

    def forward(self, x: Tensor, pos: Tensor | None = None) -> Tensor:
        """``x``: ``(B, N, C)`` tokens; ``pos``: positions handed to ``rope`` (e.g. ``(B, N, 2)``)."""
        batch, num_tokens, channels = x.shape
        q, k, v = self.query_key_value(x, pos)
        x = F.scaled_dot_product_attention(q, k, v)
        x = x.transpose(1, 2).reshape(batch, num_tokens, channels)
        return self.proj(x)


class Block(nn.Module):
    """Pre-norm transformer block.

    ``x = x + ls1(attn(norm1(x), pos))``; ``x = x + ls2(mlp(norm2(x)))``, where ``ls*`` is a
    :class:`LayerScale` (or the identity when ``init_values`` is ``None``) and the norms are
    LayerNorms with ``norm_eps`` (DINOv2: 1e-6; VGGT aggregator: 1e-5).
    """

    def __init__(
        self,
        dim: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        qkv_bias: bool = True,
        proj_bias: bool = True,
        ffn_bias: bool = True,
        init_values: float | None = None,
        qk_norm: bool = False,
        rope: Callable[[Tensor, Tensor], Tensor] | nn.Module | None = None,
        norm_eps: float = 1e-6,
    ) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qkv_bias=qkv_bias, proj_bias=proj_bias, qk_norm=qk_norm, rope=rope)
        self.ls1 = LayerScale(dim, init_values) if init_values is not None else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), bias=ffn_bias)
        self.ls2 = LayerScale(dim, init_values) if init_values is not None else nn.Identity()

    def forward(self, x: Tensor, pos: Tensor | None = None) -> Tensor:
        """``x``: ``(B, N, C)`` -> ``(B, N, C)``."""
        x = x + self.ls1(self.attn(self.norm1(x), pos))
        return x + self.ls2(self.mlp(self.norm2(x)))
