"""Output heads of π³ and Pi3X (run in float32, outside autocast, as in the released models).

- :class:`LinearPatchHead` (π³): one linear map per patch token to ``out_dim`` values for each of
  its ``p x p`` pixels, rearranged by pixel shuffle.
- :class:`ConvHead` (Pi3X, after MoGe): three 2x upsampling stages (transposed conv + conv +
  residual conv blocks) from the patch grid, a bilinear resize to the image, then one small conv
  stack per output; at every stage two channels of normalised image-plane coordinates
  (:func:`view_plane_uv`) are appended so the head knows the aspect ratio and where it is.
- :class:`CameraHead`: residual MLPs over the patch tokens of a frame, average pooling, MLPs, then a
  translation and a 3x3 matrix projected onto SO(3) by SVD: a ``(4, 4)`` camera-to-world pose.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class LinearPatchHead(nn.Module):
    """``proj``: Linear(dim, out_dim * p^2). ``(B, N, dim)`` patch tokens of ``(H/p) x (W/p)``
    patches -> ``(B, H, W, out_dim)``."""

    def __init__(self, dim: int, out_dim: int, patch_size: int = 14) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Linear(dim, out_dim * patch_size**2)

    def forward(self, tokens: Tensor, height: int, width: int) -> Tensor:
        batch = tokens.shape[0]
        features = self.proj(tokens).transpose(-1, -2)
        features = features.view(batch, -1, height // self.patch_size, width // self.patch_size)
        return F.pixel_shuffle(features, self.patch_size).permute(0, 2, 3, 1)


def view_plane_uv(width: int, height: int, aspect_ratio: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(height, width, 2)`` pixel-centre coordinates ``(u, v)`` on a plane whose corners are
    ``(+-w, +-h) / diagonal`` for the image's ``aspect_ratio`` = w/h (MoGe's normalised view plane)."""
    span_x = aspect_ratio / (1 + aspect_ratio**2) ** 0.5
    span_y = 1 / (1 + aspect_ratio**2) ** 0.5
    edge_x = span_x * (width - 1) / width
    edge_y = span_y * (height - 1) / height
    u = torch.linspace(-edge_x, edge_x, width, dtype=dtype, device=device)
    v = torch.linspace(-edge_y, edge_y, height, dtype=dtype, device=device)
    u, v = torch.meshgrid(u, v, indexing="xy")
    return torch.stack([u, v], dim=-1)


def _with_uv(x: Tensor, aspect_ratio: float) -> Tensor:
    """``(B, C, h, w)`` -> ``(B, C + 2, h, w)``: the view-plane coordinates of the h x w grid appended."""
    uv = view_plane_uv(x.shape[-1], x.shape[-2], aspect_ratio, x.dtype, x.device)
    uv = uv.permute(2, 0, 1).unsqueeze(0).expand(x.shape[0], -1, -1, -1)
    return torch.cat([x, uv], dim=1)


def _conv3x3(in_channels: int, out_channels: int) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1, padding_mode="replicate")


class ResidualConvBlock(nn.Module):
    """``layers(x) + x``, ``layers`` = GroupNorm(1) -> ReLU -> conv3x3 -> GroupNorm(hidden/32) -> ReLU
    -> conv3x3 (replicate padding); the channels stay the same."""

    def __init__(self, channels: int, hidden: int) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.GroupNorm(1, channels), nn.ReLU(inplace=True), _conv3x3(channels, hidden),
            nn.GroupNorm(hidden // 32, hidden), nn.ReLU(inplace=True), _conv3x3(hidden, channels),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.layers(x) + x


class ConvHead(nn.Module):
    """Pi3X's convolutional head.

    Args:
        dim_in: channels of the patch tokens (the decoder's output, 1024).
        upsample_dims: channels after each 2x stage (256, 128, 64).
        out_dims: channels of each output (points: (2, 1) for xy and log-depth; confidence: (1,)).
        res_blocks: residual blocks per stage (2).
        hidden_ratio: hidden channels of a residual block / its channels (2).
        last_channels: channels of the output stacks (32).
        last_kernel: kernel of the last conv of an output stack (1).

    ``forward(tokens (B, h*w, dim_in), h, w)`` -> one ``(B, out, 14 h, 14 w)`` tensor per output.
    """

    def __init__(self, dim_in: int = 1024, upsample_dims: tuple[int, ...] = (256, 128, 64),
                 out_dims: tuple[int, ...] = (2, 1), res_blocks: int = 2, hidden_ratio: int = 2,
                 last_channels: int = 32, last_kernel: int = 1, patch_size: int = 14) -> None:
        super().__init__()
        self.patch_size = patch_size
        stages = []
        for in_ch, out_ch in zip((dim_in, *upsample_dims[:-1]), upsample_dims):
            upsampler = nn.Sequential(nn.ConvTranspose2d(in_ch + 2, out_ch, kernel_size=2, stride=2), _conv3x3(out_ch, out_ch))
            stages.append(nn.Sequential(upsampler, *(ResidualConvBlock(out_ch, hidden_ratio * out_ch) for _ in range(res_blocks))))
        self.upsample_blocks = nn.ModuleList(stages)
        self.output_block = nn.ModuleList(
            nn.Sequential(_conv3x3(upsample_dims[-1] + 2, last_channels), nn.ReLU(inplace=True),
                          nn.Conv2d(last_channels, out_dim, kernel_size=last_kernel, padding=last_kernel // 2,
                                    padding_mode="replicate"))
            for out_dim in out_dims
        )

    def forward(self, tokens: Tensor, rows: int, cols: int) -> list[Tensor]:
        height, width = rows * self.patch_size, cols * self.patch_size
        aspect_ratio = width / height
        x = tokens.permute(0, 2, 1).unflatten(2, (rows, cols)).contiguous()
        for stage in self.upsample_blocks:
            x = stage(_with_uv(x, aspect_ratio))
        x = F.interpolate(x, (height, width), mode="bilinear", align_corners=False)
        x = _with_uv(x, aspect_ratio)
        return [block(x) for block in self.output_block]


def run_in_chunks(head: ConvHead, tokens: Tensor, rows: int, cols: int, chunk_frames: int) -> list[Tensor]:
    """``head`` over ``tokens`` ``(S, N, C)`` ``chunk_frames`` frames at a time (every op of the head
    treats frames independently), outputs concatenated."""
    if tokens.shape[0] <= chunk_frames:
        return head(tokens, rows, cols)
    parts = [head(tokens[start:start + chunk_frames], rows, cols) for start in range(0, tokens.shape[0], chunk_frames)]
    return [torch.cat(outputs, dim=0) for outputs in zip(*parts)]


class ResidualMlpBlock(nn.Module):
    """``x + relu(res_conv3(relu(res_conv2(relu(res_conv1(x))))))`` on ``(..., dim)`` tokens."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.res_conv1 = nn.Linear(dim, dim)
        self.res_conv2 = nn.Linear(dim, dim)
        self.res_conv3 = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.res_conv3(F.relu(self.res_conv2(F.relu(self.res_conv1(x))))))
        return x + y


def orthogonalize(matrices: Tensor) -> Tensor:
    """Nearest rotations of ``(B, 9)`` raw 3x3 matrices (row-major): rows normalised, then the
    rotation ``V diag(1, 1, det(V U^T)) U^T`` from the SVD ``U S V^T`` of the transpose."""
    m = matrices.reshape(-1, 3, 3)
    m_t = F.normalize(m, p=2, dim=-1).transpose(-1, -2)
    u, _, vh = torch.linalg.svd(m_t, full_matrices=False)
    v = vh.mH
    det = torch.linalg.det(torch.matmul(v, u.transpose(-2, -1)))
    return torch.matmul(torch.cat([v[:, :, :-1], v[:, :, -1:] * det.view(-1, 1, 1)], dim=2), u.transpose(-2, -1))


class CameraHead(nn.Module):
    """``(B, h*w, dim)`` patch tokens of B frames -> ``(B, 4, 4)`` camera-to-world poses."""

    def __init__(self, dim: int = 512) -> None:
        super().__init__()
        self.res_conv = nn.ModuleList(ResidualMlpBlock(dim) for _ in range(2))
        self.more_mlps = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.fc_t = nn.Linear(dim, 3)
        self.fc_rot = nn.Linear(dim, 9)

    def forward(self, tokens: Tensor, rows: int, cols: int) -> Tensor:
        frames = tokens.shape[0]
        for block in self.res_conv:
            tokens = block(tokens)
        grid = tokens.permute(0, 2, 1).reshape(frames, -1, rows, cols).contiguous()
        pooled = F.adaptive_avg_pool2d(grid, 1).view(frames, -1)
        features = self.more_mlps(pooled).float()
        translation = self.fc_t(features)
        rotation = orthogonalize(self.fc_rot(features))
        pose = torch.zeros((frames, 4, 4), device=tokens.device)
        pose[:, :3, :3] = rotation
        pose[:, :3, 3] = translation
        pose[:, 3, 3] = 1.0
        return pose
