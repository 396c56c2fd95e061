"""π³'s image encoder (and Pi3X's depth encoder): DINOv2 ViT-L/14 with 4 registers.

:class:`sl4slam.models.dinov2.DinoVisionTransformer` as VGGT uses it (position embedding resized to
the exact patch grid with antialiased bicubic, LayerScale, LayerNorm eps 1e-6), with three
differences that the checkpoints and the authors' code need:

- no ``mask_token`` (the authors delete it, so the checkpoints do not have it);
- the patch embedding may take another number of channels (Pi3X's depth encoder: depth and
  validity, 2 channels);
- every attention is a :class:`~.attention.KernelAttention` (reference or memory-efficient kernel),
  and the first tokens are assembled as the authors' code does under autocast: the class token
  and the position embedding stay float32, so half-precision patch embeddings are promoted.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..dinov2 import DinoVisionTransformer, PatchEmbed
from .attention import KernelAttention


class Pi3Encoder(DinoVisionTransformer):
    """DINOv2 encoder of π³: ``(B, in_chans, H, W)`` -> patch tokens ``(B, (H/14)(W/14), C)``
    (``forward_features(x)["x_norm_patchtokens"]``).

    Args:
        img_size: training size; the position embedding covers ``(img_size/patch)^2`` patches (518).
        embed_dim, depth, num_heads: ViT-L: 1024, 24, 16.
        num_register_tokens: 4.
        in_chans: 3 for RGB (ImageNet-normalised), 2 for Pi3X's depth encoder.
        kernel: attention kernel (:data:`~.attention.KERNELS`).
    """

    def __init__(self, img_size: int = 518, patch_size: int = 14, embed_dim: int = 1024, depth: int = 24,
                 num_heads: int = 16, num_register_tokens: int = 4, in_chans: int = 3, kernel: str = "efficient") -> None:
        super().__init__(img_size=img_size, patch_size=patch_size, embed_dim=embed_dim, depth=depth, num_heads=num_heads,
                         mlp_ratio=4.0, num_register_tokens=num_register_tokens, interpolate_antialias=True,
                         interpolate_offset=0.0, init_values=1.0, pos_embed_resize="size")
        del self.mask_token
        if in_chans != 3:
            self.patch_embed = PatchEmbed(patch_size, in_chans, embed_dim)
        for block in self.blocks:
            block.attn = KernelAttention(embed_dim, num_heads, kernel=kernel)

    def prepare_tokens(self, x: Tensor) -> Tensor:
        """``(B, C_in, H, W)`` -> ``(B, 1 + R + N, C)`` tokens ``[cls, registers, patches]``."""
        batch, _, height, width = x.shape
        tokens = self.patch_embed(x)
        # No cast of the float32 class token: under autocast the concatenation promotes (as the
        # authors' code does); in float32 it changes nothing.
        tokens = torch.cat((self.cls_token.expand(batch, -1, -1), tokens), dim=1)
        tokens = tokens + self.interpolate_pos_encoding(tokens, height, width)
        registers = self.register_tokens.expand(batch, -1, -1)
        return torch.cat((tokens[:, :1], registers, tokens[:, 1:]), dim=1)

    def patch_tokens(self, x: Tensor) -> Tensor:
        """The normalised patch tokens ``(B, N, C)`` of ``x`` (the only output π³ reads)."""
        return self.forward_features(x)["x_norm_patchtokens"]
