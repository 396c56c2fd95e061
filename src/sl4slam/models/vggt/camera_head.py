"""VGGT's camera head: iterative refinement of one pose encoding per frame.

Input: the camera token of the last aggregator output, ``(B, S, 2C)``. Each iteration embeds the
current (raw, pre-activation) pose estimate, modulates the normalised camera tokens with it
(adaptive LayerNorm: shift, scale, gate), runs a small transformer trunk that attends across the
S frames, and adds the predicted delta. The activated estimate of every iteration is returned.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..layers import Block, Mlp
from .pose_encoding import POSE_ENCODING_DIM


def activate_pose(raw: Tensor) -> Tensor:
    """Activation of a raw pose encoding ``(..., 9)``: translation and quaternion linear, FoV ReLU."""
    return torch.cat([raw[..., :7], F.relu(raw[..., 7:])], dim=-1)


class CameraHead(nn.Module):
    """Camera head.

    Args:
        dim_in: width of the aggregated tokens (2C).
        trunk_depth: transformer blocks of the trunk (VGGT-1B: 4).
        num_heads: attention heads of the trunk.
        mlp_ratio: MLP width ratio of the trunk.
        init_values: LayerScale initial value of the trunk.
        num_iterations: refinement iterations (4).
    """

    def __init__(
        self,
        dim_in: int = 2048,
        trunk_depth: int = 4,
        num_heads: int = 16,
        mlp_ratio: float = 4.0,
        init_values: float = 0.01,
        num_iterations: int = 4,
    ) -> None:
        super().__init__()
        self.num_iterations = num_iterations
        self.trunk = nn.Sequential(
            *[
                Block(dim_in, num_heads, mlp_ratio=mlp_ratio, init_values=init_values, norm_eps=1e-5)
                for _ in range(trunk_depth)
            ]
        )
        self.token_norm = nn.LayerNorm(dim_in)
        self.trunk_norm = nn.LayerNorm(dim_in)
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, POSE_ENCODING_DIM))
        self.embed_pose = nn.Linear(POSE_ENCODING_DIM, dim_in)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim_in, 3 * dim_in))
        self.adaln_norm = nn.LayerNorm(dim_in, elementwise_affine=False, eps=1e-6)
        self.pose_branch = Mlp(dim_in, dim_in // 2, out_features=POSE_ENCODING_DIM)

    def forward(self, camera_tokens: Tensor) -> list[Tensor]:
        """``camera_tokens``: ``(B, S, 2C)`` -> list of ``num_iterations`` activated encodings ``(B, S, 9)``."""
        tokens = self.token_norm(camera_tokens)
        batch, frames, _ = tokens.shape
        raw = None
        activated = []
        for _ in range(self.num_iterations):
            if raw is None:
                conditioning = self.embed_pose(self.empty_pose_tokens.expand(batch, frames, -1))
            else:
                conditioning = self.embed_pose(raw.detach())
            shift, scale, gate = self.poseLN_modulation(conditioning).chunk(3, dim=-1)
            modulated = gate * (self.adaln_norm(tokens) * (1 + scale) + shift) + tokens
            delta = self.pose_branch(self.trunk_norm(self.trunk(modulated)))
            raw = delta if raw is None else raw + delta
            activated.append(activate_pose(raw))
        return activated
