"""The backbone of Depth Anything 3: a DINOv2 ViT whose later blocks alternate between attention
within each frame and attention across all frames of the sequence.

Tokens are kept as ``(B, S, N, C)``: B sequences of S frames, ``N = 1 + h*w`` tokens per frame
(one class token, then the patches row-major), C channels. Block ``i``:

- attends within each frame ("local", tokens ``(B*S, N, C)``) when ``i < alt_start`` or ``i`` is
  even, across the whole sequence ("global", tokens ``(B, S*N, C)``) when ``i >= alt_start`` and
  ``i`` is odd;
- has a per-head LayerNorm on q and k from ``qknorm_start`` and 2D RoPE (base 100) from
  ``rope_start``. RoPE positions: the class / camera token sits at ``(0, 0)``; in a local block the
  patch at grid ``(r, c)`` sits at ``(r + 1, c + 1)``, in a global block every patch sits at ``(1, 1)``
  (no position difference across frames);
- at ``alt_start`` the first token of every frame is replaced by a camera token: the encoded known
  camera, or else the learned ``camera_token`` (index 0 for the reference view, 1 for the others).

Without known cameras and with at least three frames, the reference view is chosen and moved to
the front just before block ``alt_start - 1`` (:mod:`.reference_view`); outputs come back in input
order.

Output of each block in ``out_layers``: ``[local, norm(global)]`` along channels (``cat_token``),
where ``local`` is the last local block's output and ``norm`` the backbone's final LayerNorm
(eps 1e-5; the blocks use 1e-6); the patch tokens ``(B, S, h*w, 2C)`` go to the heads, the first
token ``(B, S, 2C)`` (un-normalised) to the camera decoder.

State-dict keys are those of the released checkpoints under ``backbone.pretrained.``
(``cls_token``, ``camera_token``, ``pos_embed``, ``patch_embed.proj.*``, ``blocks.N.*``,
``norm.*``; ``blocks.N.mlp.w12`` / ``w3`` for SwiGLU).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..dinov2 import PatchEmbed
from ..layers import Block
from ..vggt.rope import RotaryPositionEmbedding2D, patch_positions
from .config import DA3Config
from .reference_view import MIN_VIEWS_FOR_SELECTION, choose_reference_view, front_order, gather_views, input_order

#: DINOv2's offset added to the target grid when resizing the position embedding by a scale factor.
POS_EMBED_OFFSET = 0.1


def swiglu_hidden_features(dim: int, mlp_ratio: float) -> int:
    """Hidden width of DINOv2's SwiGLU FFN: 2/3 of the MLP width, rounded up to a multiple of 8."""
    return (int(int(dim * mlp_ratio) * 2 / 3) + 7) // 8 * 8


class SwiGLUFFN(nn.Module):
    """``w3(SiLU(a) * b)`` with ``[a, b] = w12(x)`` split in two halves along channels."""

    def __init__(self, dim: int, hidden_features: int) -> None:
        super().__init__()
        self.w12 = nn.Linear(dim, 2 * hidden_features)
        self.w3 = nn.Linear(hidden_features, dim)

    def forward(self, x: Tensor) -> Tensor:
        gate, value = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(gate) * value)


def resize_position_embedding(pos_embed: Tensor, rows: int, cols: int, dtype: torch.dtype) -> Tensor:
    """DINOv2's position embedding ``(1, 1 + G*G, C)`` for a ``rows`` x ``cols`` patch grid.

    The class entry is kept; the ``G x G`` grid is resized in float32 with bicubic interpolation by the
    scale factors ``((rows + 0.1) / G, (cols + 0.1) / G)`` (not to a size: PyTorch then maps output
    pixel ``i`` to ``(i + 0.5) G / (rows + 0.1) - 0.5``, which the weights were trained with). When the
    grid already matches (square ``rows == cols == G``) the stored embedding is returned unchanged.

    Returns:
        ``(1, 1 + rows*cols, C)`` in ``dtype``.
    """
    stored = pos_embed.shape[1] - 1
    if stored == rows * cols and rows == cols:
        return pos_embed
    side = math.isqrt(stored)
    if side * side != stored:
        raise ValueError(f"pos_embed holds {stored} patches, not a square grid")
    channels = pos_embed.shape[-1]
    table = pos_embed.float()
    grid = table[:, 1:].reshape(1, side, side, channels).permute(0, 3, 1, 2)
    scale = (float(rows + POS_EMBED_OFFSET) / side, float(cols + POS_EMBED_OFFSET) / side)
    grid = F.interpolate(grid, mode="bicubic", antialias=False, scale_factor=scale)
    if tuple(grid.shape[-2:]) != (rows, cols):
        raise RuntimeError(f"position embedding resized to {tuple(grid.shape[-2:])}, expected {(rows, cols)}")
    patches = grid.permute(0, 2, 3, 1).view(1, -1, channels)
    return torch.cat((table[:, 0].unsqueeze(0), patches), dim=1).to(dtype)


def global_positions(batch: int, frames: int, patches: int, device: torch.device | str) -> Tensor:
    """RoPE positions of a global block: ``(B, S*(1+patches), 2)`` int64, the first token of each
    frame at ``(0, 0)`` and every patch at ``(1, 1)``."""
    per_frame = torch.ones(1 + patches, 2, dtype=torch.long, device=device)
    per_frame[0] = 0
    return per_frame.repeat(frames, 1)[None].expand(batch, -1, -1)


@dataclass
class BackboneOutput:
    """What the heads read.

    Attributes:
        patch_tokens: four ``(B, S, h*w, 2C)`` tensors, one per ``out_layers`` entry.
        camera_token: ``(B, S, 2C)`` the first token of each frame at the last ``out_layers`` entry,
            un-normalised (what the camera decoder reads; a view into that layer's output).
        reference_view: ``(B,)`` the slot whose camera defines the world frame (0 when no view was
            moved, e.g. with known cameras or fewer than three frames).
    """

    patch_tokens: list[Tensor]
    camera_token: Tensor
    reference_view: Tensor


class DA3Backbone(nn.Module):
    """DINOv2 ViT with alternating local / global attention (see the module docstring).

    Registered as ``backbone.pretrained`` in :class:`~sl4slam.models.da3.model.DepthAnything3`.
    """

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        self.config = config
        dim = config.embed_dim
        grid = config.img_size // config.patch_size
        self.patch_size = config.patch_size
        self.patch_embed = PatchEmbed(config.patch_size, 3, dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.camera_token = nn.Parameter(torch.zeros(1, 2, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, dim))
        self.rope = RotaryPositionEmbedding2D(config.rope_base)
        self.blocks = nn.ModuleList(self._make_block(i) for i in range(config.depth))
        self.norm = nn.LayerNorm(dim)  # eps 1e-5, unlike the blocks' 1e-6

    def _make_block(self, index: int) -> Block:
        config = self.config
        block = Block(
            config.embed_dim,
            config.num_heads,
            mlp_ratio=config.mlp_ratio,
            init_values=1.0,
            qk_norm=index >= config.qknorm_start >= 0,
            rope=self.rope if index >= config.rope_start >= 0 else None,
            norm_eps=1e-6,
        )
        if config.ffn == "swiglu":
            block.mlp = SwiGLUFFN(config.embed_dim, swiglu_hidden_features(config.embed_dim, config.mlp_ratio))
        return block

    def is_global(self, index: int) -> bool:
        """Whether block ``index`` attends across frames."""
        start = self.config.alt_start
        return start >= 0 and index >= start and index % 2 == 1

    def embed(self, images: Tensor) -> Tensor:
        """Tokens ``(B, S, 1 + h*w, C)`` ``[class, patches]`` of normalised images ``(B, S, 3, H, W)``."""
        batch, frames, _, height, width = images.shape
        patches = self.patch_embed(images.reshape(batch * frames, *images.shape[2:]))
        cls = self.cls_token.expand(batch, frames, -1).reshape(batch * frames, -1, self.config.embed_dim)
        tokens = torch.cat((cls, patches), dim=1)
        rows, cols = height // self.patch_size, width // self.patch_size
        tokens = tokens + resize_position_embedding(self.pos_embed, rows, cols, tokens.dtype)
        return tokens.reshape(batch, frames, *tokens.shape[1:])

    def learned_camera_tokens(self, batch: int, frames: int) -> Tensor:
        """``(B, S, C)``: the reference token for slot 0, the other token for the rest."""
        reference = self.camera_token[:, :1].expand(batch, -1, -1)
        others = self.camera_token[:, 1:].expand(batch, frames - 1, -1)
        return torch.cat([reference, others], dim=1)

    def _run_block(self, index: int, tokens: Tensor, local_pos: Tensor | None, global_pos: Tensor | None) -> Tensor:
        batch, frames, num, channels = tokens.shape
        block = self.blocks[index]
        if self.is_global(index):
            out = block(tokens.reshape(batch, frames * num, channels), pos=global_pos)
        else:
            out = block(tokens.reshape(batch * frames, num, channels), pos=local_pos)
        return out.reshape(batch, frames, num, channels)

    def forward(self, images: Tensor, camera_tokens: Tensor | None = None,
                reference_strategy: str = "saddle_balanced") -> BackboneOutput:
        """Run the backbone.

        Args:
            images: ``(B, S, 3, H, W)`` ImageNet-normalised; H, W multiples of the patch size.
            camera_tokens: ``(B, S, C)`` encoded known cameras (then no reference view is chosen:
                the cameras' own world frame is kept), or ``None``.
            reference_strategy: see :mod:`.reference_view`.
        """
        config = self.config
        batch, frames, _, height, width = images.shape
        rows, cols = height // self.patch_size, width // self.patch_size
        tokens = self.embed(images)
        local_pos = patch_positions(batch * frames, rows, cols, 1, images.device)
        global_pos = global_positions(batch, frames, rows * cols, images.device)
        choose = camera_tokens is None and frames >= MIN_VIEWS_FOR_SELECTION and config.alt_start >= 1
        reference = torch.zeros(batch, dtype=torch.long, device=images.device)
        back = None
        local_tokens = tokens
        out_layers = set(config.out_layers)
        patch_outputs: list[Tensor] = []
        camera_token = None
        for index in range(config.depth):
            positioned = index >= config.rope_start >= 0
            if choose and index == config.alt_start - 1:
                reference = choose_reference_view(tokens[:, :, 0], reference_strategy)
                order = front_order(reference, frames)
                tokens = gather_views(tokens, order)
                local_tokens = gather_views(local_tokens, order)
                back = input_order(reference, frames)
            if index == config.alt_start:
                # In place, as the released model does (the last local output shares this tensor).
                if camera_tokens is None:
                    camera_tokens = self.learned_camera_tokens(batch, frames)
                tokens[:, :, 0] = camera_tokens
            tokens = self._run_block(index, tokens, local_pos if positioned else None,
                                     global_pos if positioned else None)
            if not self.is_global(index):
                local_tokens = tokens
            if index in out_layers:
                out = torch.cat([local_tokens, tokens], dim=-1) if config.cat_token else tokens
                if back is not None:
                    out = gather_views(out, back)
                camera_token = out[:, :, 0]  # only the last is read: earlier outputs are not kept alive
                patch_outputs.append(self._normalise(out)[..., 1:, :])
        return BackboneOutput(patch_tokens=patch_outputs, camera_token=camera_token, reference_view=reference)

    def _normalise(self, out: Tensor) -> Tensor:
        """The final LayerNorm on the global half of ``[local, global]`` tokens (on all of a plain output)."""
        dim = self.config.embed_dim
        if out.shape[-1] == dim:
            return self.norm(out)
        return torch.cat([out[..., :dim], self.norm(out[..., dim:])], dim=-1)
