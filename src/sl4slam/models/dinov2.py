"""DINOv2 vision transformer (Oquab et al., 2023) with DINOv2's own parameter names.

Used by:
- SALAD place recognition (:mod:`sl4slam.models.salad`): ViT-B/14, no registers, position
  embedding resized by a *scale factor* ``(h + 0.1) / 37`` with plain bicubic (A = -0.75).
- VGGT's patch embedding: ViT-L/14 with 4 register tokens, position embedding resized to an
  explicit *size* with antialiased bicubic (PyTorch's antialias kernel uses a = -0.5).

Both behaviours follow from the constructor (``interpolate_offset``, ``interpolate_antialias``,
``pos_embed_resize``). The state dict keys equal those of the released DINOv2 weights
(``cls_token``, ``pos_embed``, ``register_tokens``, ``mask_token``, ``patch_embed.proj.*``,
``blocks.N.*``, ``norm.*``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .layers import Block


class PatchEmbed(nn.Module):
    """Non-overlapping ``patch_size`` convolution: ``(B, 3, H, W)`` -> ``(B, (H/p)(W/p), C)``, row-major."""

    def __init__(self, patch_size: int = 14, in_chans: int = 3, embed_dim: int = 768) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: Tensor) -> Tensor:
        height, width = x.shape[-2:]
        if height % self.patch_size or width % self.patch_size:
            raise ValueError(f"image size {height}x{width} is not a multiple of the patch size {self.patch_size}")
        return self.proj(x).flatten(2).transpose(1, 2)


class DinoVisionTransformer(nn.Module):
    """DINOv2 ViT without the classification head.

    Args:
        img_size: training image size; ``pos_embed`` covers an ``(img_size/patch_size)^2`` grid.
        patch_size, embed_dim, depth, num_heads, mlp_ratio: the usual ViT sizes
            (ViT-B/14: 14, 768, 12, 12, 4; ViT-L/14: 14, 1024, 24, 16, 4).
        num_register_tokens: extra learned tokens inserted after cls (no position embedding).
        interpolate_antialias: antialiased bicubic when resizing the position embedding.
        interpolate_offset: DINOv2's offset added to the target grid size when resizing by scale factor.
        init_values: LayerScale initial value (``None``: no LayerScale).
        pos_embed_resize: ``"scale_factor"`` (resize with ``scale = (h0 + offset) / M``, as DINOv2
            does whenever ``interpolate_offset`` is non-zero: SALAD), ``"size"`` (resize to the
            exact grid: VGGT, offset 0) or ``"auto"`` (DINOv2's rule: scale factor iff the offset
            is non-zero).
    """

    def __init__(
        self,
        img_size: int = 518,
        patch_size: int = 14,
        embed_dim: int = 768,
        depth: int = 12,
        num_heads: int = 12,
        mlp_ratio: float = 4.0,
        num_register_tokens: int = 0,
        interpolate_antialias: bool = False,
        interpolate_offset: float = 0.1,
        init_values: float | None = 1.0,
        pos_embed_resize: str = "auto",
        qkv_bias: bool = True,
        proj_bias: bool = True,
        ffn_bias: bool = True,
    ) -> None:
        super().__init__()
        if pos_embed_resize not in ("auto", "scale_factor", "size"):
            raise ValueError(f"pos_embed_resize must be 'auto', 'scale_factor' or 'size', got {pos_embed_resize!r}")
        if pos_embed_resize == "auto":
            pos_embed_resize = "scale_factor" if interpolate_offset else "size"
        self.patch_size = patch_size
        self.embed_dim = embed_dim
        self.num_register_tokens = num_register_tokens
        self.interpolate_antialias = interpolate_antialias
        self.interpolate_offset = interpolate_offset
        self.pos_embed_resize = pos_embed_resize

        grid = img_size // patch_size
        self.patch_embed = PatchEmbed(patch_size, 3, embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, embed_dim))
        self.register_tokens = (
            nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim)) if num_register_tokens > 0 else None
        )
        self.blocks = nn.ModuleList(
            Block(
                embed_dim,
                num_heads,
                mlp_ratio=mlp_ratio,
                qkv_bias=qkv_bias,
                proj_bias=proj_bias,
                ffn_bias=ffn_bias,
                init_values=init_values,
                norm_eps=1e-6,
            )
            for _ in range(depth)
        )
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))  # used only in masked training
        self._init_tokens()

    def _init_tokens(self) -> None:
        # DINOv2's initialisation of the learned tokens (global torch RNG: seed it for reproducibility).
        if self.cls_token.is_meta:  # built to be assigned loaded weights: nothing to fill (and normal_ on
            return  # meta would import torch's compiler stack, seconds on a cold start)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        if self.register_tokens is not None:
            nn.init.normal_(self.register_tokens, std=1e-6)

    def interpolate_pos_encoding(self, x: Tensor, w: int, h: int) -> Tensor:
        """Position embedding for tokens ``x`` ``(B, 1 + N, C)`` of an image with ``w`` = rows (height)
        and ``h`` = columns (width) in pixels (DINOv2's own, swapped, naming: it is called with
        ``x.shape[-2], x.shape[-1]``).

        Returns ``(1, 1 + (w/p)(h/p), C)`` in ``x``'s dtype. The cls entry is never resized; the
        patch grid is resized in float32 with bicubic interpolation (see the class docstring).
        """
        previous_dtype = x.dtype
        num_patches = x.shape[1] - 1
        num_stored = self.pos_embed.shape[1] - 1
        if num_patches == num_stored and w == h:
            return self.pos_embed
        pos_embed = self.pos_embed.float()
        class_pos_embed = pos_embed[:, :1]
        dim = x.shape[-1]
        rows, cols = w // self.patch_size, h // self.patch_size
        side = int(math.sqrt(num_stored))
        if side * side != num_stored:
            raise ValueError(f"pos_embed holds {num_stored} patches, not a square grid")
        grid = pos_embed[:, 1:].reshape(1, side, side, dim).permute(0, 3, 1, 2)
        if self.pos_embed_resize == "scale_factor":
            # A scale factor (not the size) makes PyTorch map coordinates with this scale,
            # src = (i + 0.5) * side / (rows + offset) - 0.5; the checkpoint was trained this way.
            scale = (float(rows + self.interpolate_offset) / side, float(cols + self.interpolate_offset) / side)
            grid = F.interpolate(grid, mode="bicubic", antialias=self.interpolate_antialias, scale_factor=scale)
        else:
            grid = F.interpolate(grid, mode="bicubic", antialias=self.interpolate_antialias, size=(rows, cols))
        if tuple(grid.shape[-2:]) != (rows, cols):
            raise RuntimeError(f"position embedding resized to {tuple(grid.shape[-2:])}, expected {(rows, cols)}")
        patch_pos_embed = grid.permute(0, 2, 3, 1).reshape(1, rows * cols, dim)
        return torch.cat((class_pos_embed, patch_pos_embed), dim=1).to(previous_dtype)

    def prepare_tokens(self, x: Tensor) -> Tensor:
        """``(B, 3, H, W)`` normalized images -> ``(B, 1 + R + N, C)`` tokens ``[cls, registers, patches]``."""
        batch, _, height, width = x.shape
        tokens = self.patch_embed(x)
        tokens = torch.cat((self.cls_token.expand(batch, -1, -1).to(tokens.dtype), tokens), dim=1)
        tokens = tokens + self.interpolate_pos_encoding(tokens, height, width)
        if self.register_tokens is not None:
            tokens = torch.cat(
                (tokens[:, :1], self.register_tokens.expand(batch, -1, -1).to(tokens.dtype), tokens[:, 1:]), dim=1
            )
        return tokens

    def forward_features(self, x: Tensor) -> dict[str, Tensor]:
        """Run the ViT on ``(B, 3, H, W)`` normalized images (H, W multiples of the patch size).

        Returns a dict with ``x_norm_clstoken`` ``(B, C)``, ``x_norm_regtokens`` ``(B, R, C)``,
        ``x_norm_patchtokens`` ``(B, N, C)`` (row-major patches, after the final LayerNorm) and
        ``x_prenorm`` ``(B, 1 + R + N, C)``.
        """
        tokens = self.prepare_tokens(x)
        for block in self.blocks:
            tokens = block(tokens)
        normed = self.norm(tokens)
        first_patch = 1 + self.num_register_tokens
        return {
            "x_norm_clstoken": normed[:, 0],
            "x_norm_regtokens": normed[:, 1:first_patch],
            "x_norm_patchtokens": normed[:, first_patch:],
            "x_prenorm": tokens,
        }

    def forward(self, x: Tensor) -> Tensor:
        """The normalized cls token ``(B, C)`` (DINOv2's forward without a head)."""
        return self.forward_features(x)["x_norm_clstoken"]
