"""The Depth Anything 3 any-view network (Lin et al., 2025): backbone, DualDPT head, cameras.

State-dict keys and shapes equal those of the released ``depth-anything/DA3-*`` checkpoints without
their ``model.`` prefix (``backbone.pretrained.*``, ``head.*``, ``cam_dec.*``, ``cam_enc.*``), except
the Giant checkpoints' Gaussian-splatting head (``gs_head.*``, novel-view rendering), which is not
built (:data:`~sl4slam.models.da3.config.GS_HEAD_PREFIXES`).

Precision: the parameters stay float32; :attr:`DepthAnything3.autocast_dtype` (``None`` = float32)
runs the backbone under autocast in bf16 / fp16, while the camera encoder, the head and the camera
decoder run in float32, as the released inference code does on CUDA.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..random_weights import init_random_weights  # noqa: F401  (part of this module's API)
from .backbone import DA3Backbone
from .camera import (
    CameraDecoder,
    CameraEncoder,
    as_homogeneous,
    decode_pose_encoding,
    invert_rigid,
)
from .config import DA3Config
from .head import DualDPT
from .rays import extrinsics_intrinsics_from_rays

#: Image normalisation the network expects (ImageNet statistics, applied by the preprocessing).
IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)
POSE_SOURCES = ("head", "rays", "none")


class _Pretrained(nn.Module):
    """Holds the ViT under ``backbone.pretrained`` (the released key layout)."""

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        self.pretrained = DA3Backbone(config)


class DepthAnything3(nn.Module):
    """Depth Anything 3 any-view network.

    ``forward(images)`` with ``images`` ``(S, 3, H, W)`` or ``(B, S, 3, H, W)`` ImageNet-normalised
    (H, W multiples of 14; :func:`~sl4slam.models.da3.preprocess.preprocess_images`) returns a dict:

    - ``depth`` ``(B, S, H, W)`` (z depth, in the units of the predicted cameras) and ``depth_conf``
      ``(B, S, H, W)`` (``1 + exp``, >= 1);
    - ``extrinsics`` ``(B, S, 3, 4)`` camera-from-world and ``intrinsics`` ``(B, S, 3, 3)`` on the
      image grid (unless ``cameras="none"``); the world is the reference view's camera
      (``reference_view`` ``(B,)``), or the normalised known cameras' frame when cameras were given;
    - ``pose_enc`` ``(B, S, 9)`` (camera decoder: c2w ``[t, q_xyzw, fov_h, fov_w]``);
    - ``ray`` ``(B, S, 8h, 8w, 6)`` and ``ray_conf`` when the ray branch ran (``cameras="rays"`` or
      ``keep_rays``).
    """

    PATCH_SIZE = 14

    def __init__(self, config: DA3Config | None = None) -> None:
        super().__init__()
        self.config = config = config or DA3Config()
        self.backbone = _Pretrained(config)
        self.head = DualDPT(config)
        self.cam_dec = CameraDecoder(config.token_dim) if config.with_camera else None
        self.cam_enc = CameraEncoder(config) if config.with_camera else None
        self.autocast_dtype: torch.dtype | None = None

    def set_head_chunk_frames(self, frames: int) -> None:
        """Frames the head decodes at once (8 by default, as the released code; bounds its memory)."""
        if frames < 1:
            raise ValueError(f"head chunk must be at least 1 frame, got {frames}")
        self.head.frames_per_chunk = int(frames)

    def encode_cameras(self, extrinsics: Tensor, intrinsics: Tensor, image_hw: tuple[int, int]) -> Tensor:
        """Camera tokens ``(B, S, C)`` of known cameras (w2c ``(B, S, 3|4, 4)``, intrinsics ``(B, S, 3, 3)``
        on the image grid), in float32. Pass :func:`~.camera.normalize_extrinsics` of the poses, as the
        released inference code does."""
        if self.cam_enc is None:
            raise ValueError("this checkpoint has no camera encoder; it cannot take known cameras")
        with torch.autocast(device_type=extrinsics.device.type, enabled=False):
            return self.cam_enc(as_homogeneous(extrinsics), intrinsics, image_hw)

    def forward(self, images: Tensor, extrinsics: Tensor | None = None, intrinsics: Tensor | None = None,
                cameras: str = "head", reference_strategy: str = "saddle_balanced", keep_rays: bool = False,
                generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """Run the network (see the class docstring).

        Args:
            images: ``(S, 3, H, W)`` or ``(B, S, 3, H, W)`` normalised images.
            extrinsics, intrinsics: known cameras (both or neither): w2c ``(B, S, 4, 4)`` as normalised
                by :func:`~.camera.normalize_extrinsics`, and intrinsics on the image grid.
            cameras: where the output cameras come from: "head" (the camera decoder; default, as the
                authors' API), "rays" (fitted to the ray maps, :mod:`.rays`) or "none".
            reference_strategy: reference-view selection when no cameras are given (:mod:`.reference_view`).
            keep_rays: also return the ray maps with the camera decoder's cameras.
            generator: random source of the ray fit (``None``: torch's global generator).
        """
        if cameras not in POSE_SOURCES:
            raise ValueError(f"cameras must be one of {POSE_SOURCES}, got {cameras!r}")
        if images.ndim == 4:
            images = images[None]
        if (extrinsics is None) != (intrinsics is None):
            raise ValueError("known cameras need both extrinsics and intrinsics")
        image_hw = (int(images.shape[-2]), int(images.shape[-1]))
        device_type = images.device.type
        camera_tokens = None
        if extrinsics is not None:
            if extrinsics.ndim == 3:
                extrinsics, intrinsics = extrinsics[None], intrinsics[None]
            camera_tokens = self.encode_cameras(extrinsics, intrinsics, image_hw)
        autocast = self.autocast_dtype
        with torch.autocast(device_type=device_type, dtype=autocast or torch.float32, enabled=autocast is not None):
            features = self.backbone.pretrained(images, camera_tokens=camera_tokens,
                                                reference_strategy=reference_strategy)
        with torch.autocast(device_type=device_type, enabled=False):
            patch_tokens = [t.float() for t in features.patch_tokens]
            run_rays = cameras == "rays" or keep_rays
            output = self.head(patch_tokens, image_hw, rays=run_rays)
            del patch_tokens
            output["reference_view"] = features.reference_view
            if cameras == "rays":
                output["extrinsics"], output["intrinsics"] = extrinsics_intrinsics_from_rays(
                    output["ray"], output["ray_conf"], image_hw, generator)
                if not keep_rays:
                    del output["ray"], output["ray_conf"]
            elif cameras == "head" and self.cam_dec is not None:
                pose_enc = self.cam_dec(features.camera_token.float())
                c2w, output["intrinsics"] = decode_pose_encoding(pose_enc, image_hw)
                output["extrinsics"] = invert_rigid(c2w)
                output["pose_enc"] = pose_enc
        return output


def build_da3(config: DA3Config | None = None, device: torch.device | str = "cpu") -> DepthAnything3:
    """Build a model; on ``device="meta"`` nothing is allocated (shapes, counts, ``load_state_dict(assign=True)``)."""
    with torch.device(device):
        return DepthAnything3(config)


def count_parameters(config: DA3Config) -> int:
    """Parameters of the network built from ``config`` (counted on the meta device; tied ones once)."""
    return sum(p.numel() for p in build_da3(config, device="meta").parameters())


