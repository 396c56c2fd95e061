"""Transformer blocks and decoders of π³ and Pi3X.

All blocks are pre-norm with LayerNorm eps 1e-6 and GELU MLPs (ratio 4), as in the released
models; their parameter names are those of the checkpoints:

- :func:`decoder_block`: the self-attention block (:class:`sl4slam.models.layers.Block` with a
  :class:`~.attention.KernelAttention`). The main decoder's blocks have qk-norm and LayerScale
  (0.01); the head decoders' blocks have neither. Both rotate q and k by 2D RoPE.
- :class:`TransformerDecoder`: ``projects`` (Linear in -> dim), blocks, ``linear_out``.
- :class:`PoseInjectBlock`: Pi3X's pose injection (PRoPE attention, :mod:`.prope`), which returns
  the two residual branches without the input.
- :class:`CrossOnlyBlock` and :class:`ContextDecoder`: Pi3X's metric decoder, cross-attention only.

Tokens are ``(B, N, C)``; positions ``(B, N, 2)`` integer ``(row, column)``, 0 for the special
tokens and ``1 + index`` for patches.
"""

from __future__ import annotations

from torch import Tensor, nn

from ..layers import Block, LayerScale, Mlp
from .attention import CrossAttention, KernelAttention, attend, check_kernel
from .prope import ProjectiveEncoding

NORM_EPS = 1e-6


def decoder_block(dim: int, num_heads: int, rope: nn.Module | None, qk_norm: bool, init_values: float | None,
                  kernel: str = "efficient", mlp_ratio: float = 4.0) -> Block:
    """A pre-norm self-attention block whose attention runs ``kernel`` (``Block.forward(x, pos)``)."""
    block = Block(dim, num_heads, mlp_ratio=mlp_ratio, init_values=init_values, qk_norm=qk_norm, rope=rope,
                  norm_eps=NORM_EPS)
    block.attn = KernelAttention(dim, num_heads, qk_norm=qk_norm, rope=rope, kernel=kernel)
    return block


class TransformerDecoder(nn.Module):
    """``projects`` -> ``depth`` blocks (RoPE, no qk-norm, no LayerScale) -> ``linear_out``:
    ``(B, N, in_dim)`` -> ``(B, N, out_dim)``. The attention is within each sequence of the batch
    (the heads decode frame by frame)."""

    def __init__(self, in_dim: int, dim: int, out_dim: int, depth: int, num_heads: int, rope: nn.Module,
                 kernel: str = "efficient") -> None:
        super().__init__()
        self.projects = nn.Linear(in_dim, dim)
        self.blocks = nn.ModuleList(decoder_block(dim, num_heads, rope, qk_norm=False, init_values=None, kernel=kernel)
                                    for _ in range(depth))
        self.linear_out = nn.Linear(dim, out_dim)

    def forward(self, hidden: Tensor, pos: Tensor) -> Tensor:
        hidden = self.projects(hidden)
        for block in self.blocks:
            hidden = block(hidden, pos)
        return self.linear_out(hidden)


class ProjectiveAttention(KernelAttention):
    """Self-attention over the patch tokens of all views with PRoPE (:mod:`.prope`) instead of RoPE,
    qk-norm on; parameters as :class:`KernelAttention`."""

    def __init__(self, dim: int, num_heads: int, kernel: str = "efficient") -> None:
        super().__init__(dim, num_heads, qk_norm=True, rope=None, kernel=kernel)

    def forward(self, x: Tensor, encoding: ProjectiveEncoding, mask: Tensor | None = None) -> Tensor:  # type: ignore[override]
        """``x`` ``(B, views * P, C)`` patch tokens; ``mask`` boolean ``(B, 1, L, L)`` or ``None``."""
        batch, num_tokens, channels = x.shape
        q, k, v = self.query_key_value(x)
        out = attend(encoding.queries(q), encoding.keys_values(k), encoding.keys_values(v), self.kernel, mask)
        out = encoding.outputs(out)
        return self.proj(out.transpose(1, 2).reshape(batch, num_tokens, channels))


class PoseInjectBlock(nn.Module):
    """Pi3X's pose injection: ``ls1(attn(norm1(x))) + ls2(mlp(norm2(x)))`` over the patch tokens of
    all views, the attention encoding each view's known pose by PRoPE. The input itself is not
    added: the decoder adds the result, masked per view, to its tokens."""

    def __init__(self, dim: int, num_heads: int, init_values: float = 0.01, kernel: str = "efficient") -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=NORM_EPS)
        self.attn = ProjectiveAttention(dim, num_heads, kernel=kernel)
        self.ls1 = LayerScale(dim, init_values)
        self.norm2 = nn.LayerNorm(dim, eps=NORM_EPS)
        self.mlp = Mlp(dim, 4 * dim)
        self.ls2 = LayerScale(dim, init_values)

    def forward(self, x: Tensor, extrinsics: Tensor, rows: int, cols: int, mask: Tensor | None = None) -> Tensor:
        """``x`` ``(B, views * rows * cols, C)``; ``extrinsics`` ``(B, views, 4, 4)`` camera-from-world."""
        encoding = ProjectiveEncoding(extrinsics, self.attn.head_dim, rows, cols)
        return self.ls1(self.attn(self.norm1(x), encoding, mask)) + self.ls2(self.mlp(self.norm2(x)))


class CrossOnlyBlock(nn.Module):
    """``x += cross_attn(norm2(x), norm_y(context))``; ``x += mlp(norm3(x))`` (no self-attention,
    no LayerScale: ``ls_y`` and ``ls2`` are identities in the released model)."""

    def __init__(self, dim: int, num_heads: int, rope: nn.Module, kernel: str = "efficient") -> None:
        super().__init__()
        self.norm2 = nn.LayerNorm(dim, eps=NORM_EPS)
        self.norm_y = nn.LayerNorm(dim, eps=NORM_EPS)
        self.cross_attn = CrossAttention(dim, num_heads, rope=rope, kernel=check_kernel(kernel))
        self.norm3 = nn.LayerNorm(dim, eps=NORM_EPS)
        self.mlp = Mlp(dim, 4 * dim)

    def forward(self, x: Tensor, context: Tensor, pos: Tensor, context_pos: Tensor) -> Tensor:
        context = self.norm_y(context)
        x = x + self.cross_attn(self.norm2(x), context, pos, context_pos)
        return x + self.mlp(self.norm3(x))


class ContextDecoder(nn.Module):
    """Pi3X's metric decoder: ``projects_x`` (queries) and ``projects_y`` (context), ``depth``
    :class:`CrossOnlyBlock` s, ``linear_out``. ``(B, Q, in_dim)`` queries and ``(B, M, in_dim)``
    context -> ``(B, Q, out_dim)``."""

    def __init__(self, in_dim: int, dim: int, out_dim: int, depth: int, num_heads: int, rope: nn.Module,
                 kernel: str = "efficient") -> None:
        super().__init__()
        self.projects_x = nn.Linear(in_dim, dim)
        self.projects_y = nn.Linear(in_dim, dim)
        self.blocks = nn.ModuleList(CrossOnlyBlock(dim, num_heads, rope, kernel) for _ in range(depth))
        self.linear_out = nn.Linear(dim, out_dim)

    def forward(self, queries: Tensor, context: Tensor, pos: Tensor, context_pos: Tensor) -> Tensor:
        queries, context = self.projects_x(queries), self.projects_y(context)
        for block in self.blocks:
            queries = block(queries, context, pos, context_pos)
        return self.linear_out(queries)
