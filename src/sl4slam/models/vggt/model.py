"""The VGGT model (Wang et al., CVPR 2025): aggregator plus camera, depth and point heads.

State-dict keys and shapes equal those of the released ``facebook/VGGT-1B`` checkpoint, except
that the tracking head is not implemented: its ``track_head.*`` keys are skipped when loading
(SLAM does not use tracks).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from ..random_weights import init_random_weights  # noqa: F401  (part of this module's API)
from .aggregator import Aggregator
from .camera_head import CameraHead
from .dpt_head import DPTHead

#: Prefix of the checkpoint's tracking-head keys, which this implementation does not load.
SKIPPED_PREFIXES = ("track_head.",)


@dataclass
class VGGTModelConfig:
    """Every size of the model. The defaults are VGGT-1B.

    ``patch_embed_*`` is the DINOv2 encoder, ``camera_*`` the camera head's trunk and ``dpt_*``
    the depth and point heads (which share their sizes).
    """

    img_size: int = 518
    patch_size: int = 14
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    patch_embed_depth: int = 24
    patch_embed_num_heads: int = 16
    camera_trunk_depth: int = 4
    camera_num_heads: int = 16
    camera_iterations: int = 4
    dpt_features: int = 256
    dpt_out_channels: list[int] = field(default_factory=lambda: [256, 512, 1024, 1024])
    dpt_layers: list[int] = field(default_factory=lambda: [4, 11, 17, 23])
    enable_camera: bool = True
    enable_depth: bool = True
    enable_point: bool = True

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_dict(cls, values: dict) -> "VGGTModelConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - names
        if unknown:
            raise ValueError(f"unknown VGGT config fields: {sorted(unknown)}")
        return cls(**values)

    @classmethod
    def from_reference_config(cls, config: dict) -> "VGGTModelConfig":
        """Sizes from a reference-style description (``aggregator``, ``patch_embed_vit``,
        ``camera_head``, ``depth_head`` sections, as in the test fixtures' ``config.json``)."""
        aggregator = config["aggregator"]
        vit = config.get("patch_embed_vit", {})
        camera = config.get("camera_head", {})
        dense = config.get("depth_head") or config.get("point_head") or {}
        enabled = config.get("enabled", {})
        return cls(
            img_size=aggregator["img_size"],
            patch_size=aggregator["patch_size"],
            embed_dim=aggregator["embed_dim"],
            depth=aggregator["depth"],
            num_heads=aggregator["num_heads"],
            mlp_ratio=aggregator.get("mlp_ratio", 4.0),
            num_register_tokens=aggregator.get("num_register_tokens", 4),
            patch_embed_depth=vit.get("depth", 24),
            patch_embed_num_heads=vit.get("num_heads", 16),
            camera_trunk_depth=camera.get("trunk_depth", 4),
            camera_num_heads=camera.get("num_heads", 16),
            camera_iterations=camera.get("num_iterations", 4),
            dpt_features=dense.get("features", 256),
            dpt_out_channels=list(dense.get("out_channels", [256, 512, 1024, 1024])),
            dpt_layers=list(dense.get("intermediate_layer_idx", [4, 11, 17, 23])),
            enable_camera=enabled.get("camera_head", True),
            enable_depth=enabled.get("depth_head", True),
            enable_point=enabled.get("point_head", True),
        )


class VGGT(nn.Module):
    """Visual Geometry Grounded Transformer without the tracking head.

    ``forward(images)`` with ``images`` ``(S, 3, H, W)`` or ``(B, S, 3, H, W)`` RGB in [0, 1]
    (H, W multiples of 14) returns a dict:

    - ``pose_enc`` ``(B, S, 9)`` and ``pose_enc_list`` (one per refinement iteration): see
      :mod:`.pose_encoding`; camera-from-first-frame extrinsics.
    - ``depth`` ``(B, S, H, W, 1)`` and ``depth_conf`` ``(B, S, H, W)``.
    - ``world_points`` ``(B, S, H, W, 3)`` (first camera's frame) and ``world_points_conf``.

    The heads always run in float32 (also under autocast), as in the released model; the dense
    heads decode ``frames_chunk_size`` frames at a time (:meth:`set_head_chunk_frames`).
    """

    def __init__(self, config: VGGTModelConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or VGGTModelConfig()
        self.aggregator = Aggregator(
            img_size=config.img_size,
            patch_size=config.patch_size,
            embed_dim=config.embed_dim,
            depth=config.depth,
            num_heads=config.num_heads,
            mlp_ratio=config.mlp_ratio,
            num_register_tokens=config.num_register_tokens,
            patch_embed_depth=config.patch_embed_depth,
            patch_embed_num_heads=config.patch_embed_num_heads,
        )
        dim_in = 2 * config.embed_dim
        self.camera_head = (
            CameraHead(
                dim_in,
                trunk_depth=config.camera_trunk_depth,
                num_heads=config.camera_num_heads,
                num_iterations=config.camera_iterations,
            )
            if config.enable_camera
            else None
        )

        def dense_head(output_dim: int, activation: str) -> DPTHead:
            return DPTHead(
                dim_in,
                patch_size=config.patch_size,
                output_dim=output_dim,
                activation=activation,
                conf_activation="expp1",
                features=config.dpt_features,
                out_channels=tuple(config.dpt_out_channels),
                intermediate_layer_idx=tuple(config.dpt_layers),
            )

        self.point_head = dense_head(4, "inv_log") if config.enable_point else None
        self.depth_head = dense_head(2, "exp") if config.enable_depth else None

    def set_head_chunk_frames(self, frames: int) -> None:
        """Frames the dense heads decode at once (peak memory grows with it; outputs do not change)."""
        if frames < 1:
            raise ValueError(f"head chunk must be at least 1 frame, got {frames}")
        for head in (self.depth_head, self.point_head):
            if head is not None:
                head.frames_chunk_size = frames

    def needed_layers(self, point_head: bool = True) -> set[int]:
        """Aggregator outputs read by the enabled heads (the rest need not be kept)."""
        layers = {self.config.depth - 1} if self.camera_head is not None else set()
        if self.depth_head is not None or (point_head and self.point_head is not None):
            layers |= {i % self.config.depth for i in self.config.dpt_layers}
        return layers

    def forward(self, images: Tensor, heads: tuple[str, ...] = ("camera", "depth", "point"), keep_all_layers: bool = False) -> dict:
        """Run the model (see the class docstring).

        Args:
            images: ``(S, 3, H, W)`` or ``(B, S, 3, H, W)`` in [0, 1].
            heads: which of "camera", "depth", "point" to run (when enabled).
            keep_all_layers: also return ``aggregated_tokens`` (all aggregator outputs).
        """
        if images.ndim == 4:
            images = images[None]
        run_point = "point" in heads and self.point_head is not None
        keep = None if keep_all_layers else self.needed_layers(point_head=run_point)
        tokens, patch_start_idx = self.aggregator(images, keep_layers=keep)
        image_hw = tuple(images.shape[-2:])
        predictions: dict = {}
        if keep_all_layers:
            predictions["aggregated_tokens"] = tokens
        device_type = images.device.type
        with torch.autocast(device_type=device_type, enabled=False):
            # The dense heads convert their frame chunk to float32 themselves, so half-precision
            # aggregator outputs are never held twice.
            if "camera" in heads and self.camera_head is not None:
                pose_list = self.camera_head(tokens[-1][:, :, 0].float())
                predictions["pose_enc"] = pose_list[-1]
                predictions["pose_enc_list"] = pose_list
            if "depth" in heads and self.depth_head is not None:
                depth, depth_conf = self.depth_head(tokens, image_hw, patch_start_idx)
                predictions["depth"] = depth
                predictions["depth_conf"] = depth_conf
            if run_point:
                points, points_conf = self.point_head(tokens, image_hw, patch_start_idx)
                predictions["world_points"] = points
                predictions["world_points_conf"] = points_conf
        return predictions


def build_vggt(config: VGGTModelConfig | None = None, device: torch.device | str = "cpu") -> VGGT:
    """Build a model; on ``device="meta"`` nothing is allocated (shape checks, then ``load_state_dict(assign=True)``)."""
    with torch.device(device):
        return VGGT(config)


