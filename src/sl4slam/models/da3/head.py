"""DualDPT: Depth Anything 3's dense head, a depth branch and a ray branch over one feature pyramid.

Per frame, the four backbone outputs ``(h*w, 2C)`` are LayerNorm-ed, projected by 1x1 convolutions
to ``head_out_channels``, given a sinusoidal UV embedding (x0.1) and resized to strides
x4, x2, x1, x1/2 of the patch grid; 3x3 convolutions bring them to ``head_features`` channels.
Two independent RefineNet chains fuse the pyramid coarse to fine (each ends at twice the finest
level, i.e. 8x the patch grid):

- depth branch: 3x3 conv to ``features / 2``, bilinear resize to the image (align_corners), UV
  embedding again, 3x3 conv + ReLU + 1x1 conv to ``[log depth, confidence logit]``;
  ``depth = exp``, ``confidence = 1 + exp`` (>= 1).
- ray branch (at 8x the patch grid, not resized): a five-convolution neck, UV embedding, 3x3 conv,
  LayerNorm over channels, ReLU, 1x1 conv to 7 channels: a ray per pixel ``(direction (3), origin
  (3))`` in the world frame of the reference view, linear, and a confidence ``1 + exp``.

The released checkpoints hold a neck and output block for each of the ray branch's four pyramid
levels, but only the finest level's is ever used; the others are kept so the checkpoint loads
strictly, and never run. The four output blocks share one LayerNorm (a tied parameter: the
checkpoint stores it once, as level 0's).

Frames are decoded ``frames_per_chunk`` at a time (8, as the released code), which bounds memory;
state-dict keys are those of the released checkpoints under ``head.``.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import DA3Config

#: Bilinear resizes with more output elements than this are done in batch chunks (32-bit indexing).
_MAX_INTERPOLATE_ELEMENTS = 1_610_612_736
#: UV embedding: added with this weight, frequencies ``100^(-k / (channels/4))``.
UV_EMBED_WEIGHT = 0.1
UV_EMBED_OMEGA = 100


def interpolate_bilinear(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Bilinear resize ``(N, C, h, w)`` -> ``size`` with ``align_corners=True``, in batch chunks when huge."""
    size = (int(size[0]), int(size[1]))
    elements = size[0] * size[1] * x.shape[0] * x.shape[1]
    if elements <= _MAX_INTERPOLATE_ELEMENTS:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=True)
    chunks = torch.chunk(x, chunks=elements // _MAX_INTERPOLATE_ELEMENTS + 1, dim=0)
    return torch.cat([F.interpolate(c, size=size, mode="bilinear", align_corners=True) for c in chunks]).contiguous()


def _sincos(coordinates: Tensor, channels: int) -> Tensor:
    """``(M,)`` float32 coordinates -> ``(M, channels)`` ``[sin(x w_k), cos(x w_k)]``,
    ``w_k = 100^(-k / (channels/2))``."""
    omega = torch.arange(channels // 2, dtype=torch.float32, device=coordinates.device)
    omega /= channels / 2.0
    omega = 1.0 / UV_EMBED_OMEGA**omega
    angles = torch.einsum("m,d->md", coordinates.reshape(-1), omega)
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=1).float()


@functools.lru_cache(maxsize=64)
def uv_embedding(height: int, width: int, channels: int, aspect_ratio: float, dtype: torch.dtype,
                 device: torch.device) -> Tensor:
    """UV embedding ``(channels, height, width)`` of a ``height`` x ``width`` map, evaluated in float32.

    The UV grid spans ``x in ±span_x (w-1)/w`` and ``y in ±span_y (h-1)/h`` (``linspace``, in ``dtype``)
    with ``(span_x, span_y) = (ar, 1) / sqrt(ar^2 + 1)``, ``ar`` the *image's* width / height. Channels:
    ``[sin(x w), cos(x w), sin(y w), cos(y w)]``, a quarter each (:func:`_sincos` on every pixel, so the
    values are those of the released model bit for bit). Cached: the same map serves every frame.
    """
    diagonal = (aspect_ratio**2 + 1.0) ** 0.5
    span_x, span_y = aspect_ratio / diagonal, 1.0 / diagonal
    xs = torch.linspace(-span_x * (width - 1) / width, span_x * (width - 1) / width, steps=width, dtype=dtype,
                        device=device)
    ys = torch.linspace(-span_y * (height - 1) / height, span_y * (height - 1) / height, steps=height,
                        dtype=dtype, device=device)
    grid_x, grid_y = torch.meshgrid(xs, ys, indexing="xy")  # (height, width) each
    flat = torch.stack((grid_x, grid_y), dim=-1).reshape(-1, 2)
    embedding = torch.cat([_sincos(flat[:, 0], channels // 2), _sincos(flat[:, 1], channels // 2)], dim=-1)
    return embedding.view(height, width, channels).permute(2, 0, 1)


def add_uv_embedding(x: Tensor, image_hw: tuple[int, int]) -> Tensor:
    """``x + 0.1 * uv_embedding`` for feature maps ``x`` ``(N, C, h, w)`` of an image ``image_hw``."""
    height, width = image_hw
    embedding = uv_embedding(x.shape[-2], x.shape[-1], x.shape[1], width / height, x.dtype, x.device)
    return x + (embedding * UV_EMBED_WEIGHT)[None].expand(x.shape[0], -1, -1, -1)


class ResidualConvUnit(nn.Module):
    """``x + conv2(relu(conv1(relu(x))))`` (the skip carries ``x`` itself: DA3's ReLUs are not in place)."""

    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, 1, 1)
        self.conv2 = nn.Conv2d(features, features, 3, 1, 1)

    def forward(self, x: Tensor) -> Tensor:
        return torch.add(self.conv2(F.relu(self.conv1(F.relu(x)))), x)


class FusionBlock(nn.Module):
    """``out_conv(resize(RCU2(x + RCU1(skip))))``: one RefineNet step (the coarsest has no skip).

    Resizes to ``size``, or to twice the input when ``size`` is ``None``.
    """

    def __init__(self, features: int, has_residual: bool = True) -> None:
        super().__init__()
        self.has_residual = has_residual
        self.resConfUnit1 = ResidualConvUnit(features) if has_residual else None
        self.resConfUnit2 = ResidualConvUnit(features)
        self.out_conv = nn.Conv2d(features, features, 1, 1, 0)

    def forward(self, x: Tensor, skip: Tensor | None = None, size: tuple[int, int] | None = None) -> Tensor:
        if self.resConfUnit1 is not None and skip is not None:
            x = torch.add(x, self.resConfUnit1(skip))
        x = self.resConfUnit2(x)
        if size is None:
            size = (int(x.shape[-2] * 2), int(x.shape[-1] * 2))
        return self.out_conv(interpolate_bilinear(x, size))


class Permute(nn.Module):
    """``x.permute(*dims)`` as a module (keeps the checkpoint's ``nn.Sequential`` indices)."""

    def __init__(self, dims: tuple[int, ...]) -> None:
        super().__init__()
        self.dims = dims

    def forward(self, x: Tensor) -> Tensor:
        return x.permute(*self.dims)


def ray_neck(channels: int, convs: int) -> nn.Sequential:
    """The ray branch's neck: ``convs`` (5, 3 or 1) 3x3 convolutions alternating ``C -> C/2 -> C``,
    ending at ``C/2``."""
    if convs not in (1, 3, 5):
        raise ValueError(f"the ray neck has 1, 3 or 5 convolutions, not {convs}")
    widths = [channels] + [channels // 2 if i % 2 == 0 else channels for i in range(convs)]
    return nn.Sequential(*(nn.Conv2d(widths[i], widths[i + 1], 3, 1, 1) for i in range(convs)))


class Scratch(nn.Module):
    """Container with the released key names (``layerN_rn``, ``refinenetN[_aux]``, ``output_conv*``)."""

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        features, half = config.head_features, config.head_features // 2
        for index, channels in enumerate(config.head_out_channels, start=1):
            setattr(self, f"layer{index}_rn", nn.Conv2d(channels, features, 3, 1, 1, bias=False))
        for suffix in ("", "_aux"):
            for level in (1, 2, 3, 4):
                setattr(self, f"refinenet{level}{suffix}", FusionBlock(features, has_residual=level != 4))
        self.output_conv1 = nn.Conv2d(features, half, 3, 1, 1)
        self.output_conv2 = nn.Sequential(
            nn.Conv2d(half, 32, 3, 1, 1), nn.ReLU(inplace=True), nn.Conv2d(32, config.head_output_dim, 1, 1, 0)
        )
        self.output_conv1_aux = nn.ModuleList(ray_neck(features, config.head_aux_convs)
                                              for _ in range(config.head_aux_levels))
        shared_norm = nn.LayerNorm(32)  # one module in every level: a tied parameter
        self.output_conv2_aux = nn.ModuleList(
            nn.Sequential(nn.Conv2d(half, 32, 3, 1, 1), Permute((0, 2, 3, 1)), shared_norm, Permute((0, 3, 1, 2)),
                          nn.ReLU(inplace=True), nn.Conv2d(32, 7, 1, 1, 0))
            for _ in range(config.head_aux_levels)
        )


def tied_norm_keys(levels: int) -> list[tuple[str, list[str]]]:
    """Checkpoint keys of the ray head's tied LayerNorm, ``(stored key, aliases)`` relative to ``head.scratch.``."""
    return [(f"output_conv2_aux.0.2.{p}", [f"output_conv2_aux.{level}.2.{p}" for level in range(1, levels)])
            for p in ("weight", "bias")]


class DualDPT(nn.Module):
    """The depth + ray head (see the module docstring).

    Args:
        config: sizes (``token_dim`` input width, ``head_*``, ``patch_size``).
    """

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        channels = list(config.head_out_channels)
        self.patch_size = config.patch_size
        self.frames_per_chunk = 8
        self.norm = nn.LayerNorm(config.token_dim)
        self.projects = nn.ModuleList(nn.Conv2d(config.token_dim, c, 1, 1, 0) for c in channels)
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(channels[0], channels[0], kernel_size=4, stride=4, padding=0),
            nn.ConvTranspose2d(channels[1], channels[1], kernel_size=2, stride=2, padding=0),
            nn.Identity(),
            nn.Conv2d(channels[3], channels[3], kernel_size=3, stride=2, padding=1),
        ])
        self.scratch = Scratch(config)

    def forward(self, patch_tokens: list[Tensor], image_hw: tuple[int, int], rays: bool = True) -> dict[str, Tensor]:
        """Decode the dense maps.

        Args:
            patch_tokens: four ``(B, S, h*w, 2C)`` backbone outputs.
            image_hw: ``(H, W)`` of the input images.
            rays: also run the ray branch.

        Returns:
            ``depth`` ``(B, S, H, W)``, ``depth_conf`` ``(B, S, H, W)``; with ``rays`` also ``ray``
            ``(B, S, 8h, 8w, 6)`` and ``ray_conf`` ``(B, S, 8h, 8w)``.
        """
        batch, frames, num, channels = patch_tokens[0].shape
        flat = [t.reshape(batch * frames, num, channels) for t in patch_tokens]
        total = batch * frames
        chunk = self.frames_per_chunk
        if not chunk or chunk >= frames:
            parts = [self._decode(flat, image_hw, rays)]
        else:
            parts = [self._decode([t[start:start + chunk] for t in flat], image_hw, rays)
                     for start in range(0, total, chunk)]
        merged = parts[0] if len(parts) == 1 else {key: torch.cat([p[key] for p in parts], dim=0) for key in parts[0]}
        return {key: value.reshape(batch, frames, *value.shape[1:]) for key, value in merged.items()}

    def _pyramid(self, tokens: list[Tensor], image_hw: tuple[int, int]) -> list[Tensor]:
        """Four feature maps at strides x4, x2, x1, x1/2 of the patch grid, ``head_features`` wide."""
        height, width = image_hw
        rows, cols = height // self.patch_size, width // self.patch_size
        levels = []
        for level, x in enumerate(tokens):
            x = self.norm(x)
            x = x.permute(0, 2, 1).reshape(x.shape[0], x.shape[-1], rows, cols)
            x = self.projects[level](x)
            x = add_uv_embedding(x, image_hw)
            levels.append(self.resize_layers[level](x))
        scratch = self.scratch
        return [getattr(scratch, f"layer{i}_rn")(levels[i - 1]) for i in range(1, 5)]

    def _fuse(self, pyramid: list[Tensor], suffix: str) -> Tensor:
        """One RefineNet chain (``suffix`` "" for depth, "_aux" for rays), coarse to fine."""
        scratch = self.scratch
        fine, middle, coarse, coarsest = pyramid
        x = getattr(scratch, f"refinenet4{suffix}")(coarsest, size=coarse.shape[2:])
        x = getattr(scratch, f"refinenet3{suffix}")(x, coarse, size=middle.shape[2:])
        x = getattr(scratch, f"refinenet2{suffix}")(x, middle, size=fine.shape[2:])
        return getattr(scratch, f"refinenet1{suffix}")(x, fine)

    def _decode(self, tokens: list[Tensor], image_hw: tuple[int, int], rays: bool) -> dict[str, Tensor]:
        pyramid = self._pyramid(tokens, image_hw)
        scratch = self.scratch
        rows, cols = image_hw[0] // self.patch_size, image_hw[1] // self.patch_size
        depth_features = scratch.output_conv1(self._fuse(pyramid, ""))
        depth_features = interpolate_bilinear(depth_features, (rows * self.patch_size, cols * self.patch_size))
        depth_features = add_uv_embedding(depth_features, image_hw)
        logits = scratch.output_conv2(depth_features).permute(0, 2, 3, 1)
        out = {"depth": torch.exp(logits[..., :-1]).squeeze(-1), "depth_conf": torch.exp(logits[..., -1]) + 1}
        if rays:
            ray_features = scratch.output_conv1_aux[-1](self._fuse(pyramid, "_aux"))
            ray_features = add_uv_embedding(ray_features, image_hw)
            ray_logits = scratch.output_conv2_aux[-1](ray_features).permute(0, 2, 3, 1)
            out["ray"] = ray_logits[..., :-1]
            out["ray_conf"] = torch.exp(ray_logits[..., -1]) + 1
        return out
