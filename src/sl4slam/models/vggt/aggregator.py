"""VGGT's aggregator: DINOv2 patch embedding, then alternating frame / global attention.

Token layout per frame: ``[camera (1), registers (R), patches (h*w, row-major)]``, so patch
tokens start at ``1 + R`` (5 in VGGT-1B). The learned camera and register tokens come in two
versions: index 0 for the first frame of every sequence (the frame that defines the world
frame), index 1 for all other frames.
"""

from __future__ import annotations

from typing import Iterable

import torch
from torch import Tensor, nn

from ..dinov2 import DinoVisionTransformer
from ..layers import Block
from .rope import RotaryPositionEmbedding2D, patch_positions

# ImageNet statistics: the model normalises [0, 1] RGB itself.
IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)



def _tiny_normal(*shape: int) -> Tensor:
    """A learned token's initial value, ``N(0, 1e-12)`` from torch's global generator (``randn * 1e-6``,
    bit for bit); left empty under a ``torch.device("meta")`` context, where the weights are assigned
    later (drawing there would import torch's compiler stack: seconds on a cold start)."""
    token = torch.empty(*shape)
    return token if token.is_meta else token.normal_() * 1e-6

class Aggregator(nn.Module):
    """Alternating-attention transformer over S frames.

    Args:
        img_size: training image size of the DINOv2 patch embedding (position-embedding grid).
        patch_size: ViT patch size in pixels.
        embed_dim: token width C.
        depth: number of frame blocks (= number of global blocks = number of outputs).
        num_heads: attention heads of the frame/global blocks.
        mlp_ratio: MLP hidden width / C.
        num_register_tokens: register tokens of both the DINOv2 encoder and the aggregator.
        patch_embed_depth, patch_embed_num_heads: DINOv2 encoder size (VGGT-1B: ViT-L, 24 / 16).
        rope_base: RoPE base frequency (100).
        init_values: LayerScale initial value of the frame/global blocks.
    """

    def __init__(
        self,
        img_size: int = 518,
        patch_size: int = 14,
        embed_dim: int = 1024,
        depth: int = 24,
        num_heads: int = 16,
        mlp_ratio: float = 4.0,
        num_register_tokens: int = 4,
        patch_embed_depth: int = 24,
        patch_embed_num_heads: int = 16,
        rope_base: float = 100.0,
        init_values: float = 0.01,
    ) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.depth = depth
        self.patch_embed = DinoVisionTransformer(
            img_size=img_size,
            patch_size=patch_size,
            embed_dim=embed_dim,
            depth=patch_embed_depth,
            num_heads=patch_embed_num_heads,
            mlp_ratio=4.0,
            num_register_tokens=num_register_tokens,
            interpolate_antialias=True,
            interpolate_offset=0.0,
            init_values=1.0,
            pos_embed_resize="size",
        )
        self.rope = RotaryPositionEmbedding2D(rope_base)

        def make_block() -> Block:
            return Block(
                embed_dim,
                num_heads,
                mlp_ratio=mlp_ratio,
                qkv_bias=True,
                proj_bias=True,
                ffn_bias=True,
                init_values=init_values,
                qk_norm=True,
                rope=self.rope,
                norm_eps=1e-5,
            )

        self.frame_blocks = nn.ModuleList(make_block() for _ in range(depth))
        self.global_blocks = nn.ModuleList(make_block() for _ in range(depth))
        self.camera_token = nn.Parameter(_tiny_normal(1, 2, 1, embed_dim))
        self.register_token = nn.Parameter(_tiny_normal(1, 2, num_register_tokens, embed_dim))
        self.patch_start_idx = 1 + num_register_tokens

    @staticmethod
    def _first_and_rest(token: Tensor, batch: int, frames: int) -> Tensor:
        """``(1, 2, X, C)`` learned tokens -> ``(batch*frames, X, C)``: index 0 for frame 0, 1 otherwise."""
        first = token[:, :1].expand(batch, 1, *token.shape[2:])
        rest = token[:, 1:].expand(batch, frames - 1, *token.shape[2:])
        return torch.cat([first, rest], 1).reshape(batch * frames, *token.shape[2:])

    def embed(self, images: Tensor) -> Tensor:
        """DINOv2 patch tokens ``(B*S, h*w, C)`` of ``(B, S, 3, H, W)`` images in [0, 1]."""
        batch, frames, channels, height, width = images.shape
        if channels != 3:
            raise ValueError(f"expected 3 colour channels, got {channels}")
        mean = torch.tensor(IMAGE_MEAN, dtype=images.dtype, device=images.device).view(1, 1, 3, 1, 1)
        std = torch.tensor(IMAGE_STD, dtype=images.dtype, device=images.device).view(1, 1, 3, 1, 1)
        normalized = ((images - mean) / std).reshape(batch * frames, channels, height, width)
        return self.patch_embed.forward_features(normalized)["x_norm_patchtokens"]

    def forward(self, images: Tensor, keep_layers: Iterable[int] | None = None) -> tuple[list[Tensor | None], int]:
        """Aggregate a batch of sequences.

        Args:
            images: ``(B, S, 3, H, W)`` RGB in [0, 1]; H and W multiples of the patch size.
            keep_layers: indices of the outputs to keep (others are ``None``) to save memory;
                ``None`` keeps all ``depth`` outputs.

        Returns:
            A list of ``depth`` tensors ``(B, S, P, 2C)``: output ``i`` is frame block ``i``'s
            tokens concatenated with global block ``i``'s along channels (``P = 1 + R + h*w``);
            and the index of the first patch token.
        """
        batch, frames, _, height, width = images.shape
        if height % self.patch_size or width % self.patch_size:
            raise ValueError(f"image size {height}x{width} is not a multiple of the patch size {self.patch_size}")
        keep = set(range(self.depth)) if keep_layers is None else {i % self.depth for i in keep_layers}
        patch_tokens = self.embed(images)
        tokens = torch.cat(
            [
                self._first_and_rest(self.camera_token, batch, frames).to(patch_tokens.dtype),
                self._first_and_rest(self.register_token, batch, frames).to(patch_tokens.dtype),
                patch_tokens,
            ],
            dim=1,
        )
        num_tokens, channels = tokens.shape[1], tokens.shape[2]
        positions = patch_positions(
            batch * frames, height // self.patch_size, width // self.patch_size, self.patch_start_idx, images.device
        )
        global_positions = positions.reshape(batch, frames * num_tokens, 2)

        outputs: list[Tensor | None] = []
        for frame_block, global_block in zip(self.frame_blocks, self.global_blocks):
            # Frame attention: each frame's tokens attend among themselves.
            tokens = frame_block(tokens.reshape(batch * frames, num_tokens, channels), pos=positions)
            frame_out = tokens
            # Global attention: all tokens of a sequence attend to each other.
            tokens = global_block(tokens.reshape(batch, frames * num_tokens, channels), pos=global_positions)
            if len(outputs) in keep:
                outputs.append(
                    torch.cat(
                        [
                            frame_out.reshape(batch, frames, num_tokens, channels),
                            tokens.reshape(batch, frames, num_tokens, channels),
                        ],
                        dim=-1,
                    )
                )
            else:
                outputs.append(None)
        return outputs, self.patch_start_idx
