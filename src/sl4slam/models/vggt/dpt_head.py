"""DPT dense-prediction head of VGGT (depth map and point map).

Four aggregator outputs are turned into a feature pyramid (strides 4, 8, 16, 32 relative to the
patch grid scale: x4, x2, x1, x0.5), fused coarse-to-fine with RefineNet-style blocks, upsampled
to the image size and decoded to ``output_dim`` channels, the last of which is a confidence.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# Bilinear resizes larger than this many output elements are done in batch chunks (the CUDA
# kernel indexes with 32-bit integers).
_MAX_INTERPOLATE_ELEMENTS = 1_610_612_736


def interpolate_bilinear(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Bilinear resize of ``(N, C, h, w)`` to ``size`` with ``align_corners=True``, chunked when huge."""
    elements = size[0] * size[1] * x.shape[0] * x.shape[1]
    if elements <= _MAX_INTERPOLATE_ELEMENTS:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=True)
    chunks = x.chunk(elements // _MAX_INTERPOLATE_ELEMENTS + 1, dim=0)
    return torch.cat([F.interpolate(c, size=size, mode="bilinear", align_corners=True) for c in chunks], 0)


def uv_position_embedding(height: int, width: int, channels: int, aspect_ratio: float, device) -> Tensor:
    """Sinusoidal embedding ``(channels, height, width)`` float32 of a normalised UV grid.

    The grid spans ``±span_x (w-1)/w`` and ``±span_y (h-1)/h`` with ``span = (ar, 1)/sqrt(ar^2+1)``
    (``ar`` = image width / height); channels are ``[sin(x w_k), cos(x w_k), sin(y w_k), cos(y w_k)]``
    with ``w_k = 100^(-k / (channels/4))``, evaluated in float64.
    """
    diagonal = math.sqrt(aspect_ratio**2 + 1.0)
    span_x, span_y = aspect_ratio / diagonal, 1.0 / diagonal
    # The coordinates are made in float32 (as the released model does), then promoted.
    xs = torch.linspace(-span_x * (width - 1) / width, span_x * (width - 1) / width, width, device=device)
    ys = torch.linspace(-span_y * (height - 1) / height, span_y * (height - 1) / height, height, device=device)
    quarter = channels // 4
    omega = 1.0 / 100.0 ** (torch.arange(quarter, dtype=torch.float64, device=device) / quarter)
    angle_x = xs.double()[:, None] * omega[None]  # (w, q)
    angle_y = ys.double()[:, None] * omega[None]  # (h, q)
    emb_x = torch.cat([angle_x.sin(), angle_x.cos()], -1).float()  # (w, 2q)
    emb_y = torch.cat([angle_y.sin(), angle_y.cos()], -1).float()  # (h, 2q)
    embedding = torch.cat(
        [emb_x[None, :, :].expand(height, width, -1), emb_y[:, None, :].expand(height, width, -1)], -1
    )
    return embedding.permute(2, 0, 1)


class ResidualConvUnit(nn.Module):
    """``conv2(relu(conv1(relu(x)))) + relu(x)``.

    The released model applies an in-place ReLU to the input, so its skip connection carries
    ``relu(x)``, not ``x``; the weights were trained that way and it is reproduced here.
    """

    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, kernel_size=3, padding=1)
        self.conv2 = nn.Conv2d(features, features, kernel_size=3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        x = F.relu(x)
        return self.conv2(F.relu(self.conv1(x))) + x


class FeatureFusionBlock(nn.Module):
    """``out_conv(upsample(RCU2(x0 + RCU1(x1))))``; the coarsest block has no ``x1`` input."""

    def __init__(self, features: int, has_residual: bool = True) -> None:
        super().__init__()
        if has_residual:
            self.resConfUnit1 = ResidualConvUnit(features)
        self.has_residual = has_residual
        self.resConfUnit2 = ResidualConvUnit(features)
        self.out_conv = nn.Conv2d(features, features, kernel_size=1)

    def forward(self, x: Tensor, skip: Tensor | None = None, size: tuple[int, int] | None = None) -> Tensor:
        if self.has_residual:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        size = size if size is not None else (int(x.shape[-2] * 2), int(x.shape[-1] * 2))
        return self.out_conv(interpolate_bilinear(x, size))


class Scratch(nn.Module):
    """Container matching the released key names (``scratch.layerN_rn``, ``scratch.refinenetN``, ...)."""

    def __init__(self, in_channels: list[int], features: int, feature_only: bool, output_dim: int) -> None:
        super().__init__()
        for index, channels in enumerate(in_channels, start=1):
            setattr(self, f"layer{index}_rn", nn.Conv2d(channels, features, kernel_size=3, padding=1, bias=False))
        self.refinenet1 = FeatureFusionBlock(features)
        self.refinenet2 = FeatureFusionBlock(features)
        self.refinenet3 = FeatureFusionBlock(features)
        self.refinenet4 = FeatureFusionBlock(features, has_residual=False)
        hidden = features if feature_only else features // 2
        self.output_conv1 = nn.Conv2d(features, hidden, kernel_size=3, padding=1)
        if not feature_only:
            self.output_conv2 = nn.Sequential(
                nn.Conv2d(hidden, 32, kernel_size=3, padding=1),
                nn.ReLU(),
                nn.Conv2d(32, output_dim, kernel_size=1),
            )


def activate_dense(out: Tensor, activation: str, conf_activation: str = "expp1") -> tuple[Tensor, Tensor]:
    """Split ``(N, C, H, W)`` head output into values ``(N, H, W, C-1)`` and confidence ``(N, H, W)``.

    activation: "exp" (depth) or "inv_log" (points: ``sign(v)(exp|v| - 1)``) or "linear";
    conf_activation: "expp1" (``1 + exp``), "expp0" or "sigmoid".
    """
    out = out.permute(0, 2, 3, 1)
    values, conf = out[..., :-1], out[..., -1]
    if activation == "exp":
        values = torch.exp(values)
    elif activation == "inv_log":
        values = torch.sign(values) * torch.expm1(values.abs())
    elif activation != "linear":
        raise ValueError(f"unknown activation {activation!r}")
    if conf_activation == "expp1":
        conf = 1 + conf.exp()
    elif conf_activation == "expp0":
        conf = conf.exp()
    elif conf_activation == "sigmoid":
        conf = torch.sigmoid(conf)
    else:
        raise ValueError(f"unknown confidence activation {conf_activation!r}")
    return values, conf


class DPTHead(nn.Module):
    """DPT head.

    Args:
        dim_in: width of the aggregated tokens (2C).
        patch_size: ViT patch size in pixels.
        output_dim: output channels including the confidence (depth 2, points 4).
        activation, conf_activation: see :func:`activate_dense`.
        features: fusion width (VGGT-1B: 256).
        out_channels: widths of the four projected token maps (VGGT-1B: 256, 512, 1024, 1024).
        intermediate_layer_idx: aggregator outputs used (VGGT-1B: 4, 11, 17, 23).
        pos_embed: add the UV sinusoidal embedding (x0.1) after projection and after upsampling.
        feature_only: stop after upsampling and return ``features``-channel maps.
        down_ratio: output resolution divisor.
        frames_chunk_size: frames decoded at once (memory bound; results do not depend on it).
    """

    def __init__(
        self,
        dim_in: int,
        patch_size: int = 14,
        output_dim: int = 4,
        activation: str = "inv_log",
        conf_activation: str = "expp1",
        features: int = 256,
        out_channels: tuple[int, ...] = (256, 512, 1024, 1024),
        intermediate_layer_idx: tuple[int, ...] = (4, 11, 17, 23),
        pos_embed: bool = True,
        feature_only: bool = False,
        down_ratio: int = 1,
        frames_chunk_size: int = 8,
    ) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.activation = activation
        self.conf_activation = conf_activation
        self.pos_embed = pos_embed
        self.feature_only = feature_only
        self.down_ratio = down_ratio
        self.intermediate_layer_idx = tuple(intermediate_layer_idx)
        self.frames_chunk_size = frames_chunk_size
        out_channels = list(out_channels)
        self.norm = nn.LayerNorm(dim_in)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, c, kernel_size=1) for c in out_channels)
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(out_channels[0], out_channels[0], kernel_size=4, stride=4),
                nn.ConvTranspose2d(out_channels[1], out_channels[1], kernel_size=2, stride=2),
                nn.Identity(),
                nn.Conv2d(out_channels[3], out_channels[3], kernel_size=3, stride=2, padding=1),
            ]
        )
        self.scratch = Scratch(out_channels, features, feature_only, output_dim)

    def forward(
        self, aggregated_tokens: list[Tensor | None], image_hw: tuple[int, int], patch_start_idx: int
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Decode dense maps.

        Args:
            aggregated_tokens: aggregator outputs ``(B, S, P, 2C)`` (only the used layers are read).
            image_hw: ``(H, W)`` of the input images.
            patch_start_idx: index of the first patch token.

        Returns:
            ``(values (B, S, H', W', output_dim-1), conf (B, S, H', W'))`` or, with
            ``feature_only``, features ``(B, S, features, H', W')``; ``H' = H / down_ratio``.
        """
        frames = next(t for t in aggregated_tokens if t is not None).shape[1]
        chunk = self.frames_chunk_size if self.frames_chunk_size else frames
        results = [
            self._decode(aggregated_tokens, image_hw, patch_start_idx, start, min(start + chunk, frames))
            for start in range(0, frames, chunk)
        ]
        if self.feature_only:
            return torch.cat(results, dim=1)
        return torch.cat([r[0] for r in results], dim=1), torch.cat([r[1] for r in results], dim=1)

    def _decode(self, aggregated_tokens, image_hw, patch_start_idx, start, stop):
        height, width = image_hw
        rows, cols = height // self.patch_size, width // self.patch_size
        pyramid = []
        for level, layer in enumerate(self.intermediate_layer_idx):
            tokens = aggregated_tokens[layer]
            if tokens is None:
                raise ValueError(f"aggregator output {layer} was not kept but the DPT head needs it")
            tokens = tokens[:, start:stop, patch_start_idx:].float()
            batch, frames = tokens.shape[:2]
            x = self.norm(tokens.reshape(batch * frames, rows * cols, tokens.shape[-1]))
            x = x.permute(0, 2, 1).reshape(batch * frames, -1, rows, cols)
            x = self.projects[level](x)
            if self.pos_embed:
                x = x + 0.1 * uv_position_embedding(rows, cols, x.shape[1], width / height, x.device).to(x.dtype)
            pyramid.append(self.resize_layers[level](x))

        scratch = self.scratch
        layer1, layer2, layer3, layer4 = (getattr(scratch, f"layer{i}_rn")(pyramid[i - 1]) for i in range(1, 5))
        fused = scratch.refinenet4(layer4, size=layer3.shape[2:])
        fused = scratch.refinenet3(fused, layer3, size=layer2.shape[2:])
        fused = scratch.refinenet2(fused, layer2, size=layer1.shape[2:])
        fused = scratch.refinenet1(fused, layer1)
        fused = scratch.output_conv1(fused)

        out_size = (int(rows * self.patch_size / self.down_ratio), int(cols * self.patch_size / self.down_ratio))
        fused = interpolate_bilinear(fused, out_size)
        if self.pos_embed:
            fused = fused + 0.1 * uv_position_embedding(*out_size, fused.shape[1], width / height, fused.device).to(
                fused.dtype
            )
        if self.feature_only:
            return fused.reshape(batch, frames, *fused.shape[1:])
        values, conf = activate_dense(scratch.output_conv2(fused), self.activation, self.conf_activation)
        return values.reshape(batch, frames, *values.shape[1:]), conf.reshape(batch, frames, *conf.shape[1:])
