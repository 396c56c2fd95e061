"""Depth Anything 3's cameras: the camera decoder, the camera encoder and their pose encoding.

Conventions (those of the released model):

- ``extrinsics`` are camera-from-world ``[R | t]`` (w2c, OpenCV axes: x right, y down, z forward),
  ``(..., 3, 4)`` or ``(..., 4, 4)``; the world is the reference view's camera (see
  :mod:`.reference_view`) unless known cameras were given.
- A pose encoding is ``[t (3), q (4, XYZW), fov_h, fov_w]`` of the **camera-to-world** pose
  (``R_wc``, camera centre ``t``): DA3 encodes and decodes c2w (VGGT encodes w2c). Fields of view are
  in radians, height first: ``fov_h = 2 atan((H/2) / fy)``; decoded intrinsics put the principal
  point at the grid centre ``(W/2, H/2)`` and clamp ``tan(fov/2)`` at 1e-6.

:class:`CameraDecoder` maps the last camera token ``(B, S, 2C)`` to a pose encoding
(``ReLU(Linear)`` twice, then linear translation and quaternion heads and a ReLU field-of-view
head). :class:`CameraEncoder` maps known cameras to camera tokens ``(B, S, C)``: the pose encoding
of each c2w through an MLP (9 -> C/2 -> C), a LayerNorm, a transformer over the S cameras (4 blocks,
16 heads, LayerScale 0.01, no RoPE) and a LayerNorm.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..layers import Block, Mlp
from ..vggt.pose_encoding import extri_intri_to_pose_encoding, quat_to_mat
from .config import DA3Config

#: Smallest ``tan(fov / 2)`` when decoding focal lengths.
MIN_TAN_HALF_FOV = 1e-6
#: Lower bound of the median camera distance by which known translations are divided.
MIN_MEDIAN_DISTANCE = 1e-1


def invert_rigid(transform: Tensor) -> Tensor:
    """Inverse of rigid transforms ``(..., 3, 4)`` or ``(..., 4, 4)`` (same shape): ``[R^T | -R^T t]``,
    with the bottom row ``[0 0 0 1]`` kept when present."""
    rotation = transform[..., :3, :3]
    translation = transform[..., :3, 3:]
    bottom = transform[..., 3:, :]
    inverse_rotation = rotation.mT
    return torch.cat([torch.cat([inverse_rotation, -inverse_rotation @ translation], dim=-1), bottom], dim=-2)


def decode_pose_encoding(pose_encoding: Tensor, image_hw: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Camera-to-world poses and intrinsics of pose encodings.

    Args:
        pose_encoding: ``(B, S, 9)`` ``[t, q_xyzw, fov_h, fov_w]``.
        image_hw: ``(H, W)`` of the grid the intrinsics refer to.

    Returns:
        c2w ``(B, S, 3, 4)`` and intrinsics ``(B, S, 3, 3)`` float32 ``[[fx, 0, W/2], [0, fy, H/2], [0, 0, 1]]``.
    """
    translation = pose_encoding[..., :3]
    rotation = quat_to_mat(pose_encoding[..., 3:7])
    c2w = torch.cat([rotation, translation[..., None]], dim=-1)
    height, width = image_hw
    fy = (height / 2.0) / torch.clamp(torch.tan(pose_encoding[..., 7] / 2.0), MIN_TAN_HALF_FOV)
    fx = (width / 2.0) / torch.clamp(torch.tan(pose_encoding[..., 8] / 2.0), MIN_TAN_HALF_FOV)
    intrinsics = torch.zeros(pose_encoding.shape[:2] + (3, 3), device=pose_encoding.device)
    intrinsics[..., 0, 0] = fx
    intrinsics[..., 1, 1] = fy
    intrinsics[..., 0, 2] = width / 2
    intrinsics[..., 1, 2] = height / 2
    intrinsics[..., 2, 2] = 1.0
    return c2w, intrinsics


def as_homogeneous(extrinsics: Tensor) -> Tensor:
    """``(..., 3, 4)`` -> ``(..., 4, 4)`` with the row ``[0 0 0 1]``; ``(..., 4, 4)`` unchanged."""
    if extrinsics.shape[-2:] == (4, 4):
        return extrinsics
    if extrinsics.shape[-2:] != (3, 4):
        raise ValueError(f"expected extrinsics of shape (..., 3, 4) or (..., 4, 4), got {tuple(extrinsics.shape)}")
    bottom = torch.zeros_like(extrinsics[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([extrinsics, bottom], dim=-2)


def normalize_extrinsics(extrinsics: Tensor) -> Tensor:
    """Known w2c extrinsics ``(B, S, 4, 4)`` re-expressed as the model was trained to receive them.

    The world becomes the first camera (``T_i_0 = T_i_w T_0_w^-1``) and translations are divided by
    the median distance of the camera centres from it (over all B*S cameras, the lower median for an
    even count, at least :data:`MIN_MEDIAN_DISTANCE`). Returns a new tensor.
    """
    relative = extrinsics @ invert_rigid(extrinsics[:, :1])
    centres = invert_rigid(relative)[..., :3, 3]
    median = torch.clamp(torch.median(centres.norm(dim=-1)), min=MIN_MEDIAN_DISTANCE)
    relative[..., :3, 3] = relative[..., :3, 3] / median
    return relative


class CameraDecoder(nn.Module):
    """Camera token ``(B, S, D)`` -> pose encoding ``(B, S, 9)`` (c2w; see the module docstring).

    Keys: ``backbone.0``, ``backbone.2``, ``fc_t``, ``fc_qvec``, ``fc_fov.0``.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.backbone = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.fc_t = nn.Linear(dim, 3)
        self.fc_qvec = nn.Linear(dim, 4)
        self.fc_fov = nn.Sequential(nn.Linear(dim, 2), nn.ReLU())

    def forward(self, camera_token: Tensor) -> Tensor:
        batch, frames = camera_token.shape[:2]
        features = self.backbone(camera_token.reshape(batch * frames, -1)).float()
        translation = self.fc_t(features).reshape(batch, frames, 3)
        quaternion = self.fc_qvec(features).reshape(batch, frames, 4)
        fov = self.fc_fov(features).reshape(batch, frames, 2)
        return torch.cat([translation, quaternion, fov], dim=-1)


class CameraEncoder(nn.Module):
    """Known cameras -> camera tokens ``(B, S, C)`` (see the module docstring).

    Keys: ``pose_branch.fc1/fc2``, ``token_norm``, ``trunk.N.*``, ``trunk_norm``.
    """

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        dim = config.embed_dim
        self.trunk = nn.Sequential(*(
            Block(dim, config.cam_enc_heads, mlp_ratio=config.cam_enc_mlp_ratio, init_values=0.01, norm_eps=1e-5)
            for _ in range(config.cam_enc_depth)
        ))
        self.token_norm = nn.LayerNorm(dim)
        self.trunk_norm = nn.LayerNorm(dim)
        self.pose_branch = Mlp(9, dim // 2, out_features=dim)

    def forward(self, extrinsics: Tensor, intrinsics: Tensor, image_hw: tuple[int, int]) -> Tensor:
        """Tokens of cameras ``extrinsics`` ``(B, S, 4, 4)`` w2c and ``intrinsics`` ``(B, S, 3, 3)`` on
        the ``image_hw`` grid (only the focal lengths enter, as fields of view)."""
        pose_encoding = extri_intri_to_pose_encoding(invert_rigid(extrinsics), intrinsics, image_hw)
        tokens = self.token_norm(self.pose_branch(pose_encoding))
        return self.trunk_norm(self.trunk(tokens))
