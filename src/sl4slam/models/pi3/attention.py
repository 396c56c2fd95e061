"""Attention of the π³ / Pi3X transformers, with a choice of kernel.

Every attention of the two models (DINOv2 encoder, alternating decoder, head decoders, metric
cross-attention, pose injection) ends in one call, :func:`attend`, which runs one of two kernels:

- ``"reference"``: what the authors' code runs. ``scaled_dot_product_attention`` restricted to
  PyTorch's math and memory-efficient backends in float32 and float16, and to the flash backend in
  bfloat16 when there is no mask. On a CPU in float32 this is the math backend, which holds the
  whole ``(heads, N, N)`` attention table: about 30 GB for the global attention of 17 frames at
  the native resolution. With this kernel our outputs are bitwise equal to the authors'
  (``tests/test_pi3_model.py``).
- ``"efficient"`` (the default): the flash (or memory-efficient) backend, which never holds the
  table (PyTorch's CPU flash kernel works on blocks of queries and keys, with masks too); where
  neither applies, the exact math kernel on blocks of :data:`QUERY_CHUNK_BYTES` of table at a time.
  Its outputs differ from the reference kernel's by float rounding only (the summation order of
  the softmax); ``tests/test_pi3_model.py`` states the tolerance (decision:
  docs/decisions/memory-estimates.md).

Tensors are ``(B, heads, N, head_dim)``; masks are boolean, broadcastable to ``(B, heads, N, M)``,
``True`` where a query may attend to a key.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from ..layers import Attention

KERNELS = ("reference", "efficient")
"""The attention kernels a π³ model can run (see the module docstring)."""
QUERY_CHUNK_BYTES = 256 * 1024**2
"""Largest block of attention table the chunked fallback of the efficient kernel holds."""

_REFERENCE_FULL = [SDPBackend.MATH, SDPBackend.EFFICIENT_ATTENTION]
_REFERENCE_BF16 = [SDPBackend.FLASH_ATTENTION]
_EFFICIENT = [SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION]


def check_kernel(kernel: str) -> str:
    """``kernel`` if it is one of :data:`KERNELS`, else ``ValueError``."""
    if kernel not in KERNELS:
        raise ValueError(f"unknown attention kernel {kernel!r}: use one of {', '.join(KERNELS)}")
    return kernel


def reference_backends(dtype: torch.dtype, masked: bool) -> list[SDPBackend]:
    """The backends the authors' code allows: flash alone for unmasked bfloat16, else math and
    memory-efficient."""
    return _REFERENCE_BF16 if dtype == torch.bfloat16 and not masked else _REFERENCE_FULL


def attend(q: Tensor, k: Tensor, v: Tensor, kernel: str, mask: Tensor | None = None) -> Tensor:
    """Softmax attention ``softmax(q k^T / sqrt(d)) v`` with the chosen kernel.

    Args:
        q: ``(B, heads, N, d)`` queries (not scaled).
        k, v: ``(B, heads, M, d)`` keys and values.
        kernel: ``"reference"`` or ``"efficient"`` (module docstring).
        mask: optional boolean mask broadcastable to ``(B, heads, N, M)``.

    Returns:
        ``(B, heads, N, d)``.
    """
    if kernel == "reference":
        with sdpa_kernel(reference_backends(q.dtype, mask is not None)):
            return F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    if kernel != "efficient":
        check_kernel(kernel)
    try:
        with sdpa_kernel(_EFFICIENT):
            return F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    except RuntimeError as exc:  # no flash / memory-efficient kernel for these inputs
        if "kernel" not in str(exc).lower():
            raise
    return chunked_attention(q, k, v, mask)


def chunked_attention(q: Tensor, k: Tensor, v: Tensor, mask: Tensor | None = None,
                      chunk_bytes: int = QUERY_CHUNK_BYTES) -> Tensor:
    """The math kernel on blocks of queries, so that at most ``chunk_bytes`` of attention table
    exist at a time (each query's softmax is over all keys, so the blocks are exact)."""
    batch, heads, num_queries, _ = q.shape
    table_row = batch * heads * k.shape[2] * q.element_size()
    step = max(1, min(num_queries, chunk_bytes // max(table_row, 1)))
    parts = []
    with sdpa_kernel([SDPBackend.MATH]):
        for start in range(0, num_queries, step):
            block_mask = None
            if mask is not None:
                block_mask = mask[..., start:start + step, :] if mask.shape[-2] > 1 else mask
            parts.append(F.scaled_dot_product_attention(q[:, :, start:start + step], k, v, attn_mask=block_mask))
    return torch.cat(parts, dim=2)


class KernelAttention(Attention):
    """Multi-head self-attention with a fused qkv projection, optional qk-norm and 2D RoPE, and a
    choice of kernel (:attr:`kernel`, one of :data:`KERNELS`).

    Parameter names and layout are those of :class:`sl4slam.models.layers.Attention` (``qkv``,
    ``q_norm``, ``k_norm``, ``proj``). As in the authors' code, q and k are cast back to v's dtype
    after their LayerNorms (under autocast a LayerNorm returns float32), then rotated.
    """

    def __init__(self, dim: int, num_heads: int, qk_norm: bool = False,
                 rope: Callable[[Tensor, Tensor], Tensor] | nn.Module | None = None, kernel: str = "efficient") -> None:
        super().__init__(dim, num_heads, qkv_bias=True, proj_bias=True, qk_norm=qk_norm, rope=rope)
        self.kernel = check_kernel(kernel)

    def query_key_value(self, x: Tensor, pos: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """``q, k, v`` ``(B, heads, N, head_dim)`` of ``x`` ``(B, N, C)``: q, k normed, cast, rotated."""
        batch, num_tokens, _ = x.shape
        # (B, N, 3, heads, d) -> (3, B, heads, N, d): q, k, v are strided views of the projection.
        q, k, v = self.qkv(x).reshape(batch, num_tokens, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k = self.q_norm(q).to(v.dtype), self.k_norm(k).to(v.dtype)
        if self.rope is not None and pos is not None:
            q, k = self.rope(q, pos), self.rope(k, pos)
        return q, k, v

    def forward(self, x: Tensor, pos: Tensor | None = None) -> Tensor:
        """``x`` ``(B, N, C)``, ``pos`` ``(B, N, 2)`` integer ``(row, column)`` or ``None`` -> ``(B, N, C)``."""
        batch, num_tokens, channels = x.shape
        q, k, v = self.query_key_value(x, pos)
        out = attend(q, k, v, self.kernel)
        return self.proj(out.transpose(1, 2).reshape(batch, num_tokens, channels))


class CrossAttention(nn.Module):
    """Multi-head cross-attention with separate ``q_proj``, ``k_proj``, ``v_proj`` (no qk-norm) and
    2D RoPE on queries and keys, each with its own positions (Pi3X's metric decoder).

    ``forward(query (B, N, C), context (B, M, C), query_pos (B, N, 2), context_pos (B, M, 2))`` ->
    ``(B, N, C)``; the context serves as keys and values.
    """

    def __init__(self, dim: int, num_heads: int, rope: Callable[[Tensor, Tensor], Tensor] | nn.Module | None = None,
                 kernel: str = "efficient") -> None:
        super().__init__()
        if dim % num_heads != 0:
            raise ValueError(f"dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.q_proj = nn.Linear(dim, dim)
        self.k_proj = nn.Linear(dim, dim)
        self.v_proj = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope
        self.kernel = check_kernel(kernel)

    def _heads(self, projected: Tensor) -> Tensor:
        batch, length, _ = projected.shape
        return projected.reshape(batch, length, self.num_heads, self.head_dim).permute(0, 2, 1, 3)

    def forward(self, query: Tensor, context: Tensor, query_pos: Tensor | None = None,
                context_pos: Tensor | None = None) -> Tensor:
        batch, num_queries, channels = query.shape
        q, k, v = self._heads(self.q_proj(query)), self._heads(self.k_proj(context)), self._heads(self.v_proj(context))
        if self.rope is not None:
            q, k = self.rope(q, query_pos), self.rope(k, context_pos)
        out = attend(q, k, v, self.kernel)
        return self.proj(out.transpose(1, 2).reshape(batch, num_queries, channels))


def set_attention_kernel(module: nn.Module, kernel: str) -> None:
    """Make every attention inside ``module`` run ``kernel``."""
    check_kernel(kernel)
    for child in module.modules():
        if isinstance(getattr(child, "kernel", None), str):
            child.kernel = kernel
