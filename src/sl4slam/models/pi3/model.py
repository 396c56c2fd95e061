"""The π³ and Pi3X models (Wang et al., 2025: "π³: Permutation-Equivariant Visual Geometry Learning").

Both read a set of S images and predict, per image, a point map in the image's own camera frame
(``local_points``), a confidence logit per pixel and a camera-to-world pose in one frame shared by
the set; ``points`` are the local points moved by the poses. No image is special (no reference
frame: the shared frame is the model's choice) and no intrinsics are predicted.

Architecture (sizes of the released checkpoints; :class:`Pi3Config` holds them):

1. DINOv2 ViT-L/14 with 4 registers encodes each image (ImageNet-normalised) into patch tokens.
2. 5 learned register tokens are prepended to each frame; 36 blocks (width 1024, 16 heads,
   qk-norm, 2D RoPE base 100, LayerScale) alternate attention within a frame (even blocks) and
   across all frames (odd blocks). The last two blocks' outputs are concatenated (width 2048).
3. Three (π³) or four (Pi3X) head decoders (5 blocks, frame-wise attention) read them:
   points, confidence, camera (and Pi3X's metric scale, cross-attention from one learned token).
4. π³: a linear head per patch gives ``(x/z, y/z, log z)`` and a confidence logit per pixel.
   Pi3X: convolutional heads (:class:`~.heads.ConvHead`), ``z = exp(min(log z, 15))``, and all
   geometry is multiplied by the predicted metric scale. Camera head: SVD-orthogonalised rotation.

Pi3X can also be given, per frame, known intrinsics (or the rays they define), camera poses and
depth maps (:meth:`Pi3X.forward`); each enters only where it is given (per-frame masks).

State-dict keys and shapes equal the released checkpoints (``yyfz233/Pi3``, ``yyfz233/Pi3X``).
The heads run in float32 outside autocast, as the authors' code does; under CUDA autocast
(bf16, how the authors run the model) the rest follows the same casts as theirs.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..dinov2 import PatchEmbed
from ..vggt.rope import RotaryPositionEmbedding2D, patch_positions
from .attention import check_kernel, set_attention_kernel
from .blocks import ContextDecoder, PoseInjectBlock, TransformerDecoder, decoder_block
from .encoder import Pi3Encoder
from .heads import CameraHead, ConvHead, LinearPatchHead, run_in_chunks

VARIANTS = ("pi3", "pi3x")
IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)
MAX_LOG_DEPTH = 15.0
"""Pi3X clamps its log-depth here before the exponential."""
STATIC_TRANSLATION = 2e-2
"""Pi3X: a set of known poses whose translations (after depth normalisation) all stay below this is static."""


@dataclass
class Pi3Config:
    """Every size of π³ / Pi3X; the defaults are the released models'.

    Attributes:
        variant: "pi3" or "pi3x".
        img_size, patch_size: the encoder's training size (position-embedding grid) and patch.
        encoder_dim, encoder_depth, encoder_heads, encoder_registers: DINOv2 ViT-L/14-reg.
        decoder_dim, decoder_depth, decoder_heads, decoder_registers: the alternating decoder.
        head_decoder_dim, head_decoder_depth, head_decoder_heads: each head decoder (points,
            confidence, camera).
        point_features: output width of the point and confidence decoders.
        camera_features: output width of the camera decoder = the camera head's width.
        conv_upsample_dims, conv_res_blocks, conv_hidden_ratio, conv_last_channels, conv_last_kernel:
            Pi3X's convolutional heads.
        metric_dim, metric_depth, metric_heads, metric_features: Pi3X's metric decoder.
        depth_condition, ray_condition: Pi3X holds the depth encoder / the ray embedding.
        pose_inject_blocks: Pi3X's pose-injection blocks (0: none).
        pose_inject_layers: decoder blocks after which they run, in order.
        rope_base: 2D RoPE base frequency.
    """

    variant: str = "pi3"
    img_size: int = 518
    patch_size: int = 14
    encoder_dim: int = 1024
    encoder_depth: int = 24
    encoder_heads: int = 16
    encoder_registers: int = 4
    decoder_dim: int = 1024
    decoder_depth: int = 36
    decoder_heads: int = 16
    decoder_registers: int = 5
    head_decoder_dim: int = 1024
    head_decoder_depth: int = 5
    head_decoder_heads: int = 16
    point_features: int = 1024
    camera_features: int = 512
    conv_upsample_dims: list[int] = field(default_factory=lambda: [256, 128, 64])
    conv_res_blocks: int = 2
    conv_hidden_ratio: int = 2
    conv_last_channels: int = 32
    conv_last_kernel: int = 1
    metric_dim: int = 512
    metric_depth: int = 5
    metric_heads: int = 8
    metric_features: int = 512
    depth_condition: bool = True
    ray_condition: bool = True
    pose_inject_blocks: int = 5
    pose_inject_layers: list[int] = field(default_factory=lambda: [1, 9, 17, 25, 33])
    rope_base: float = 100.0

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown π³ variant {self.variant!r}: use one of {', '.join(VARIANTS)}")

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_dict(cls, values: dict) -> "Pi3Config":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - names
        if unknown:
            raise ValueError(f"unknown π³ config fields: {sorted(unknown)}")
        return cls(**values)


def invert_rigid(transforms: Tensor) -> Tensor:
    """Inverse of ``(..., 4, 4)`` rigid transforms: ``[R^T | -R^T t; 0 0 0 1]``."""
    rotation_t = transforms[..., :3, :3].transpose(-2, -1)
    translation = -torch.matmul(rotation_t, transforms[..., :3, 3].unsqueeze(-1))
    bottom = torch.tensor([0, 0, 0, 1], device=transforms.device, dtype=transforms.dtype).repeat(*transforms.shape[:-2], 1, 1)
    return torch.cat([torch.cat([rotation_t, translation], dim=-1), bottom], dim=-2)


def homogeneous(points: Tensor) -> Tensor:
    """``(..., 3)`` -> ``(..., 4)`` with a trailing 1."""
    return torch.cat([points, torch.ones_like(points[..., :1])], dim=-1)


def move_points(camera_to_world: Tensor, local_points: Tensor) -> Tensor:
    """``(B, S, 4, 4)`` poses applied to ``(B, S, H, W, 3)`` local points -> points in the shared frame."""
    return torch.einsum("bnij, bnhwj -> bnhwi", camera_to_world, homogeneous(local_points))[..., :3]


class _Pi3Base(nn.Module):
    """What π³ and Pi3X share: encoder, alternating decoder, head decoders, camera head."""

    def __init__(self, config: Pi3Config, kernel: str = "efficient") -> None:
        super().__init__()
        self.config = config
        self.kernel = check_kernel(kernel)
        self.head_chunk_frames = 64  # frames a convolutional head decodes at once (the authors' 64)
        self.patch_size = config.patch_size
        self.patch_start = config.decoder_registers
        self.encoder = Pi3Encoder(config.img_size, config.patch_size, config.encoder_dim, config.encoder_depth,
                                  config.encoder_heads, config.encoder_registers, kernel=kernel)
        self.rope = RotaryPositionEmbedding2D(config.rope_base)
        self.decoder = nn.ModuleList(
            decoder_block(config.decoder_dim, config.decoder_heads, self.rope, qk_norm=True, init_values=0.01, kernel=kernel)
            for _ in range(config.decoder_depth))
        self.register_token = nn.Parameter(torch.zeros(1, 1, config.decoder_registers, config.decoder_dim))
        self.register_buffer("image_mean", torch.tensor(IMAGE_MEAN).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor(IMAGE_STD).view(1, 3, 1, 1))
        width = 2 * config.decoder_dim

        def head_decoder(out_dim: int) -> TransformerDecoder:
            return TransformerDecoder(width, config.head_decoder_dim, out_dim, config.head_decoder_depth,
                                      config.head_decoder_heads, self.rope, kernel)

        self.point_decoder = head_decoder(config.point_features)
        self.conf_decoder = head_decoder(config.point_features)
        self.camera_decoder = head_decoder(config.camera_features)
        self.camera_head = CameraHead(config.camera_features)

    @property
    def attention_kernel(self) -> str:
        """The attention kernel every attention of the model runs (:data:`~.attention.KERNELS`)."""
        return self.kernel

    def set_attention_kernel(self, kernel: str) -> None:
        """Switch every attention to ``kernel`` ("reference": the authors' kernels, bitwise equal to
        their outputs; "efficient": flash attention, bounded memory)."""
        set_attention_kernel(self, kernel)
        self.kernel = kernel

    @staticmethod
    def _as_batch(images: Tensor) -> Tensor:
        if images.ndim == 4:
            images = images[None]
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"expected images (B, S, 3, H, W) or (S, 3, H, W), got {tuple(images.shape)}")
        return images

    def _grid(self, height: int, width: int) -> tuple[int, int]:
        if height % self.patch_size or width % self.patch_size:
            raise ValueError(f"image size {height}x{width} is not a multiple of the patch size {self.patch_size}")
        return height // self.patch_size, width // self.patch_size

    def encode_images(self, images: Tensor) -> Tensor:
        """``(B, S, 3, H, W)`` RGB in [0, 1] -> patch tokens ``(B*S, h*w, C)``."""
        batch, frames, channels, height, width = images.shape
        normalized = (images - self.image_mean) / self.image_std
        return self.encoder.patch_tokens(normalized.reshape(batch * frames, channels, height, width))

    def decode(self, tokens: Tensor, frames: int, rows: int, cols: int,
               inject: Callable[[int, Tensor], Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """The alternating decoder.

        Args:
            tokens: ``(B*S, rows*cols, C)`` patch tokens of S frames per sequence.
            inject: ``inject(index, hidden) -> hidden`` called with every block's output
                (``(B*S, n, C)`` after a frame block, ``(B, S*n, C)`` after a global one): Pi3X's
                pose injection, or ``None``.

        Returns:
            ``(B*S, n, 2C)``: the outputs of the last two blocks concatenated, with ``n = R + rows*cols``
            (registers first), and their positions ``(B*S, n, 2)``.
        """
        batch = tokens.shape[0] // frames
        registers = self.register_token.repeat(batch, frames, 1, 1).reshape(batch * frames, self.patch_start, -1)
        hidden = torch.cat([registers, tokens], dim=1)
        num_tokens = hidden.shape[1]
        frame_pos = patch_positions(batch * frames, rows, cols, self.patch_start, hidden.device)
        global_pos = frame_pos.reshape(batch, frames * num_tokens, 2)
        penultimate = hidden
        last = len(self.decoder) - 1
        for index, block in enumerate(self.decoder):
            if index % 2 == 0:  # within each frame
                hidden = block(hidden.reshape(batch * frames, num_tokens, -1), frame_pos)
            else:  # across all frames of a sequence
                hidden = block(hidden.reshape(batch, frames * num_tokens, -1), global_pos)
            if inject is not None:
                hidden = inject(index, hidden)
            if index == last - 1:
                penultimate = hidden.reshape(batch * frames, num_tokens, -1)
        both = torch.cat([penultimate, hidden.reshape(batch * frames, num_tokens, -1)], dim=-1)
        return both, frame_pos.reshape(batch * frames, num_tokens, 2)

    def camera_poses(self, hidden: Tensor, pos: Tensor, rows: int, cols: int) -> Tensor:
        """``(B*S, 4, 4)`` camera-to-world poses from the decoder output."""
        tokens = self.camera_decoder(hidden, pos)
        with torch.autocast(device_type=hidden.device.type, enabled=False):
            return self.camera_head(tokens[:, self.patch_start:].float(), rows, cols)


class Pi3(_Pi3Base):
    """π³ (``yyfz233/Pi3``).

    ``forward(images)``, ``images`` ``(B, S, 3, H, W)`` (or ``(S, 3, H, W)``) RGB in [0, 1], H and W
    multiples of 14, returns a dict of float32 tensors:

    - ``local_points`` ``(B, S, H, W, 3)``: each pixel's point in its camera frame (OpenCV axes:
      x right, y down, z forward), in the model's (arbitrary) units;
    - ``conf`` ``(B, S, H, W, 1)``: confidence logits (``sigmoid`` gives a probability);
    - ``camera_poses`` ``(B, S, 4, 4)``: camera-to-world in the shared frame;
    - ``points`` ``(B, S, H, W, 3)``: the local points in the shared frame.
    """

    def __init__(self, config: Pi3Config | None = None, kernel: str = "efficient") -> None:
        config = config or Pi3Config()
        if config.variant != "pi3":
            raise ValueError(f"Pi3 needs a 'pi3' config, got {config.variant!r}")
        super().__init__(config, kernel)
        self.point_head = LinearPatchHead(config.point_features, 3, config.patch_size)
        self.conf_head = LinearPatchHead(config.point_features, 1, config.patch_size)

    def forward(self, images: Tensor) -> dict[str, Tensor]:
        images = self._as_batch(images)
        batch, frames, _, height, width = images.shape
        rows, cols = self._grid(height, width)
        hidden, pos = self.decode(self.encode_images(images), frames, rows, cols)
        point_tokens = self.point_decoder(hidden, pos)
        conf_tokens = self.conf_decoder(hidden, pos)
        poses = self.camera_poses(hidden, pos, rows, cols).reshape(batch, frames, 4, 4)
        with torch.autocast(device_type=images.device.type, enabled=False):
            raw = self.point_head(point_tokens.float()[:, self.patch_start:], height, width)
            xy, log_z = raw.reshape(batch, frames, height, width, -1).split([2, 1], dim=-1)
            z = torch.exp(log_z)
            local_points = torch.cat([xy * z, z], dim=-1)
            conf = self.conf_head(conf_tokens.float()[:, self.patch_start:], height, width)
            conf = conf.reshape(batch, frames, height, width, -1)
            points = move_points(poses, local_points)
        return {"points": points, "local_points": local_points, "conf": conf, "camera_poses": poses}


class Pi3X(_Pi3Base):
    """Pi3X (``yyfz233/Pi3X``): π³ with convolutional heads, a metric scale and optional known
    intrinsics, poses and depth (see :meth:`forward`).

    The condition branches can be left out to save memory (:meth:`drop_condition_branches`, or a
    checkpoint without them); a condition whose branch is absent cannot be given.
    """

    def __init__(self, config: Pi3Config | None = None, kernel: str = "efficient") -> None:
        config = config or Pi3Config(variant="pi3x")
        if config.variant != "pi3x":
            raise ValueError(f"Pi3X needs a 'pi3x' config, got {config.variant!r}")
        super().__init__(config, kernel)
        dim = config.decoder_dim
        if config.depth_condition:
            self.depth_encoder = Pi3Encoder(config.img_size, config.patch_size, config.encoder_dim,
                                            config.encoder_depth, config.encoder_heads, config.encoder_registers,
                                            in_chans=2, kernel=kernel)
            self.depth_emb = nn.Parameter(torch.zeros(1, 1, config.encoder_dim))
        if config.ray_condition:
            self.ray_embed = PatchEmbed(config.patch_size, 2, config.encoder_dim)
        if config.pose_inject_blocks:
            self.pose_inject_blk = nn.ModuleList(PoseInjectBlock(dim, config.decoder_heads, kernel=kernel)
                                                 for _ in range(config.pose_inject_blocks))

        def conv_head(out_dims: tuple[int, ...]) -> ConvHead:
            return ConvHead(config.point_features, tuple(config.conv_upsample_dims), out_dims, config.conv_res_blocks,
                            config.conv_hidden_ratio, config.conv_last_channels, config.conv_last_kernel, config.patch_size)

        self.point_head = conv_head((2, 1))
        self.conf_head = conv_head((1,))
        self.metric_token = nn.Parameter(torch.zeros(1, 1, 2 * dim))
        self.metric_decoder = ContextDecoder(2 * dim, config.metric_dim, config.metric_features, config.metric_depth,
                                             config.metric_heads, self.rope, kernel)
        self.metric_head = nn.Linear(config.metric_features, 1)

    def drop_condition_branches(self, keep: tuple[str, ...] = ()) -> None:
        """Release the condition branches not named in ``keep`` (of "depths", "intrinsics", "poses")."""
        for name, attribute, flag in (("depths", ("depth_encoder", "depth_emb"), "depth_condition"),
                                      ("intrinsics", ("ray_embed",), "ray_condition"),
                                      ("poses", ("pose_inject_blk",), "pose_inject_blocks")):
            if name not in keep:
                for attr in attribute:
                    if hasattr(self, attr):
                        delattr(self, attr)
                setattr(self.config, flag, False if flag != "pose_inject_blocks" else 0)

    # ---- conditions ---------------------------------------------------------------------------

    @staticmethod
    def _default_mask(mask: Tensor | None, given: bool, use_priors: bool, batch: int, frames: int,
                      device: torch.device) -> Tensor:
        """The per-frame mask of one condition: as given, else every frame when the condition is
        given and ``use_priors``, else none. (The authors draw ``rand <= p`` with p = 1 or 0,
        which is the same except with probability 2^-24 per frame when p = 0.)"""
        if mask is not None:
            mask = torch.as_tensor(mask, device=device, dtype=torch.bool)
            if mask.shape != (batch, frames):
                raise ValueError(f"a condition mask must be (B, S) = ({batch}, {frames}), got {tuple(mask.shape)}")
            return mask.clone()
        return torch.full((batch, frames), bool(given and use_priors), device=device)

    @staticmethod
    def _normalize_depths(depths: Tensor) -> tuple[Tensor, Tensor]:
        """Depths ``(B, S, H, W)`` divided by each sequence's mean valid (> 0) depth (1 when none),
        and those means ``(B,)``."""
        batch = depths.shape[0]
        valid = torch.where(depths > 0, depths, float("nan"))
        means = torch.nan_to_num(torch.nanmean(valid.view(batch, -1), dim=1), nan=1.0)
        return depths / (means.view(batch, 1, 1, 1) + 1e-8), means.reshape(-1)

    @staticmethod
    def rays_from_intrinsics(intrinsics: Tensor, height: int, width: int) -> Tensor:
        """``(B, S, H, W, 2)`` ``x/z, y/z`` of the ray through each pixel, for ``(B, S, 3, 3)``
        intrinsics in the authors' pixel convention (pixel ``(u, v)`` is centred at ``(u + 0.5, v + 0.5)``)."""
        batch = intrinsics.shape[0]
        u = torch.arange(width, device=intrinsics.device).repeat(height) + 0.5
        v = torch.arange(height, device=intrinsics.device).repeat_interleave(width) + 0.5
        pixels = torch.stack([u, v, torch.ones_like(u)], dim=-1).float().reshape(height, width, 3)
        pixels = pixels[None].repeat(batch, 1, 1, 1)
        return torch.einsum("bnij, bhwj -> bnhwi", torch.inverse(intrinsics), pixels)[..., :2]

    def _conditions(self, images: Tensor, depths, intrinsics, rays, poses, use_priors, depth_mask, ray_mask, pose_mask):
        """Inputs of the condition branches (float32, outside autocast): the normalised depths and
        their validity ``(B*S, 1, H, W)``, the rays ``(B, S, H, W, 2)``, the known poses relative to
        the first frame ``(B, S, 4, 4)`` and the three per-frame masks ``(B, S)``."""
        batch, frames, _, height, width = images.shape
        device = images.device
        depth_mask = self._default_mask(depth_mask, depths is not None, use_priors, batch, frames, device)
        ray_mask = self._default_mask(ray_mask, rays is not None or intrinsics is not None, use_priors, batch, frames, device)
        pose_mask = self._default_mask(pose_mask, poses is not None, use_priors, batch, frames, device)
        pose_mask[pose_mask.sum(dim=1) == 1] = False  # a single known pose says nothing relative
        for mask, branch, what in ((depth_mask, "depth_encoder", "depth maps"), (ray_mask, "ray_embed", "intrinsics or rays"),
                                   (pose_mask, "pose_inject_blk", "poses")):
            if mask.any() and not hasattr(self, branch):
                raise ValueError(f"this Pi3X was built without its {branch} branch: {what} cannot be used")
        if depths is None:
            depths = torch.zeros((batch, frames, height, width), device=device)
        if rays is not None:
            rays = rays[..., :2] / (rays[..., 2:3] + 1e-6)
        elif intrinsics is not None:
            rays = self.rays_from_intrinsics(intrinsics.float(), height, width)
        else:
            rays = torch.zeros((batch, frames, height, width, 2), device=device)
        if poses is None:
            poses = torch.eye(4, device=device)[None, None].repeat(batch, frames, 1, 1)
        depths, depth_scale = self._normalize_depths(depths.float())
        validity = (depths > 0).float().reshape(batch * frames, 1, height, width)
        relative = torch.einsum("bij, bnjk -> bnik", invert_rigid(poses[:, 0].float()), poses.float())
        relative[..., :3, 3] /= depth_scale.view(batch, 1, 1)
        without_depth = ~(depth_mask.sum(dim=1) > 0)
        if without_depth.sum() > 0 and frames > 1:
            # Without depth, the mean translation sets the scale (a static set keeps its own).
            scale = relative[..., 1:, :3, 3].norm(dim=-1)
            static = scale.max(dim=1)[0] < STATIC_TRANSLATION
            scale = scale.mean(dim=1)
            moving = torch.logical_and(without_depth, ~static)
            relative[moving, ..., :3, 3] /= scale.view(batch, 1, 1)[moving] + 1e-8
            depths[moving] /= scale.view(batch, 1, 1, 1)[moving] + 1e-8
        depths = depths.reshape(batch * frames, 1, height, width)
        return depths, validity, rays, relative, depth_mask, ray_mask, pose_mask

    def forward(self, images: Tensor, depths: Tensor | None = None, intrinsics: Tensor | None = None,
                rays: Tensor | None = None, poses: Tensor | None = None, use_priors: bool = True,
                depth_mask: Tensor | None = None, ray_mask: Tensor | None = None,
                pose_mask: Tensor | None = None) -> dict[str, Tensor]:
        """Run Pi3X, optionally conditioned.

        Args:
            images: ``(B, S, 3, H, W)`` (or ``(S, 3, H, W)``) RGB in [0, 1]; H, W multiples of 14.
            depths: ``(B, S, H, W)`` known depth, 0 where unknown (any scale: normalised by its mean).
            intrinsics: ``(B, S, 3, 3)`` known pinhole intrinsics in pixels of the model's grid, in the
                authors' convention: pixel ``(u, v)`` is centred at ``(u + 0.5, v + 0.5)`` (the
                project's integer-centred K plus 0.5 on ``c_x`` and ``c_y``).
            rays: ``(B, S, H, W, 3)`` known ray directions instead of intrinsics.
            poses: ``(B, S, 4, 4)`` known camera-to-world poses (OpenCV axes); at least two frames
                need one (the authors pair them with intrinsics or rays).
            use_priors: when ``False``, conditions enter only where a mask says so.
            depth_mask, ray_mask, pose_mask: ``(B, S)`` bool, the frames whose condition is used
                (default: every frame whose condition is given).

        Returns:
            The outputs of :class:`Pi3` (``local_points``, ``points`` and the translations of
            ``camera_poses`` scaled to approximately metric units) plus ``rays`` ``(B, S, H, W, 3)``
            (unit ray of each pixel, the direction of ``local_points``) and ``metric`` ``(B,)``.
        """
        images = self._as_batch(images)
        batch, frames, _, height, width = images.shape
        rows, cols = self._grid(height, width)
        tokens = self.encode_images(images)
        inject = None
        if any(x is not None for x in (depths, intrinsics, rays, poses)) or any(
                m is not None for m in (depth_mask, ray_mask, pose_mask)):
            with torch.autocast(device_type=images.device.type, enabled=False):
                depth_input, validity, ray_input, relative, depth_mask, ray_mask, pose_mask = self._conditions(
                    images, depths, intrinsics, rays, poses, use_priors, depth_mask, ray_mask, pose_mask)
            if ray_mask.sum() > 0:
                ray_tokens = self.ray_embed(ray_input.reshape(batch * frames, height, width, 2).permute(0, 3, 1, 2))
                tokens = tokens + ray_tokens * ray_mask.reshape(batch * frames, 1, 1)
            if depth_mask.sum() > 0:
                depth_tokens = self.depth_encoder.patch_tokens(torch.cat([depth_input, validity], dim=1)) + self.depth_emb
                tokens = tokens + depth_tokens * depth_mask.reshape(batch * frames, 1, 1)
            if pose_mask.sum() > 0:
                inject = self._pose_injection(relative, pose_mask, frames, rows, cols)
        hidden, pos = self.decode(tokens, frames, rows, cols, inject)
        return self._heads(hidden, pos, batch, frames, rows, cols)

    def _pose_injection(self, relative_poses: Tensor, pose_mask: Tensor, frames: int, rows: int,
                        cols: int) -> Callable[[int, Tensor], Tensor]:
        """The decoder hook that adds the pose-injection blocks' output to the patch tokens of the
        frames with a known pose, after the blocks of ``config.pose_inject_layers``."""
        batch = pose_mask.shape[0]
        extrinsics = invert_rigid(relative_poses)
        patches = rows * cols
        mask = None
        if pose_mask.sum() != pose_mask.numel():
            pairs = pose_mask.unsqueeze(2) & pose_mask.unsqueeze(1)  # (B, S, S): both views posed
            mask = pairs.repeat_interleave(patches, dim=1).repeat_interleave(patches, dim=2)[:, None]
        layers = {layer: k for k, layer in enumerate(self.config.pose_inject_layers[:len(self.pose_inject_blk)])}
        start = self.patch_start

        def inject(index: int, hidden: Tensor) -> Tensor:
            if index not in layers:
                return hidden
            hidden = hidden.reshape(batch, frames, start + patches, -1)
            tokens = hidden[..., start:, :].reshape(batch, frames * patches, -1)
            update = self.pose_inject_blk[layers[index]](tokens, extrinsics, rows, cols, mask)
            hidden[..., start:, :] += update.reshape(batch, frames, patches, -1) * pose_mask.view(batch, frames, 1, 1)
            return hidden.reshape(batch, frames * (start + patches), -1)

        return inject

    def _heads(self, hidden: Tensor, pos: Tensor, batch: int, frames: int, rows: int, cols: int) -> dict[str, Tensor]:
        height, width = rows * self.patch_size, cols * self.patch_size
        num_tokens = hidden.shape[1]
        start = self.patch_start
        device_type = hidden.device.type
        point_tokens = self.point_decoder(hidden, pos)
        with torch.autocast(device_type=device_type, enabled=False):
            xy, log_z = run_in_chunks(self.point_head, point_tokens[:, start:].float(), rows, cols, self.head_chunk_frames)
            del point_tokens
            xy = xy.permute(0, 2, 3, 1).reshape(batch, frames, height, width, -1)
            z = torch.exp(log_z.permute(0, 2, 3, 1).reshape(batch, frames, height, width, -1).clamp(max=MAX_LOG_DEPTH))
            local_points = torch.cat([xy * z, z], dim=-1)
            rays = F.normalize(torch.cat([xy, torch.ones_like(z)], dim=-1), dim=-1)
            del xy, z
        poses = self.camera_poses(hidden, pos, rows, cols).reshape(batch, frames, 4, 4)
        global_pos = pos.reshape(batch, frames * num_tokens, -1)
        metric_tokens = self.metric_decoder(self.metric_token.repeat(batch, 1, 1),
                                            hidden.reshape(batch, frames * num_tokens, -1), global_pos[:, 0:1], global_pos)
        conf_tokens = self.conf_decoder(hidden, pos)
        with torch.autocast(device_type=device_type, enabled=False):
            metric = self.metric_head(metric_tokens.float()).reshape(batch).exp()
            conf = run_in_chunks(self.conf_head, conf_tokens[:, start:].float(), rows, cols, self.head_chunk_frames)[0]
            conf = conf.permute(0, 2, 3, 1).reshape(batch, frames, height, width, -1)
            scale = metric.view(batch, 1, 1, 1, 1)
            points = move_points(poses, local_points) * scale
            poses[..., :3, 3] = poses[..., :3, 3] * metric.view(batch, 1, 1)
            local_points = local_points * scale
        return {"points": points, "local_points": local_points, "rays": rays, "conf": conf,
                "camera_poses": poses, "metric": metric}


def build_pi3(config: Pi3Config | None = None, device: torch.device | str = "cpu", kernel: str = "efficient") -> nn.Module:
    """A :class:`Pi3` or :class:`Pi3X` (by ``config.variant``); on ``device="meta"`` nothing is
    allocated (for shapes, parameter counts and ``load_state_dict(assign=True)``)."""
    config = config or Pi3Config()
    with torch.device(device):
        return (Pi3X if config.variant == "pi3x" else Pi3)(config, kernel)


def parameter_count(config: Pi3Config) -> int:
    """Parameters of the model ``config`` describes (built on the meta device: nothing allocated)."""
    model = build_pi3(config, device="meta")
    return sum(p.numel() for p in model.parameters())
