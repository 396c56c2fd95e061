"""VGGT's camera parameterisation: quaternions and the "absT_quaR_FoV" pose encoding.

Conventions (those of the released VGGT model):

- Extrinsics are camera-from-world ``[R | t]`` (``T_cam_world``, 3x4) in the OpenCV camera frame
  (x right, y down, z forward).
- Quaternions are **XYZW** (scalar last).
- A pose encoding is ``[t (3), q (4), fov_h, fov_w]``: ``t`` is the translation column of the
  extrinsic matrix, ``q`` the rotation ``R``, and the fields of view are in radians, **height
  first**: ``fov_h = 2 atan((H/2) / fy)``, ``fov_w = 2 atan((W/2) / fx)``.
- Decoded intrinsics put the principal point exactly at ``(W/2, H/2)``.
"""

from __future__ import annotations

import torch

POSE_ENCODING_DIM = 9


def quat_to_mat(quaternions: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of XYZW quaternions.

    Args:
        quaternions: ``(..., 4)`` XYZW; need not be unit length (the formula divides by ``|q|^2``).

    Returns:
        ``(..., 3, 3)`` rotation matrices, same dtype.
    """
    x, y, z, w = torch.unbind(quaternions, -1)
    two_s = 2.0 / (quaternions * quaternions).sum(-1)
    entries = (
        1 - two_s * (y * y + z * z),
        two_s * (x * y - z * w),
        two_s * (x * z + y * w),
        two_s * (x * y + z * w),
        1 - two_s * (x * x + z * z),
        two_s * (y * z - x * w),
        two_s * (x * z - y * w),
        two_s * (y * z + x * w),
        1 - two_s * (x * x + y * y),
    )
    return torch.stack(entries, -1).reshape(quaternions.shape[:-1] + (3, 3))


def standardize_quaternion(quaternions: torch.Tensor) -> torch.Tensor:
    """Flip XYZW quaternions whose scalar part is negative (``q`` and ``-q`` are one rotation)."""
    return torch.where(quaternions[..., 3:4] < 0, -quaternions, quaternions)


def mat_to_quat(matrix: torch.Tensor) -> torch.Tensor:
    """XYZW quaternions of rotation matrices, with a non-negative scalar part.

    Four algebraically equivalent candidates are formed, one per quaternion component, and the
    one dividing by the largest ``|component|`` is kept, so the result is well conditioned for
    every rotation (including 180-degree turns). When the scalar part is exactly zero the sign is
    the one of the chosen candidate.

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 4)`` XYZW unit quaternions.
    """
    if matrix.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotation matrices of shape (..., 3, 3), got {tuple(matrix.shape)}")
    batch_shape = matrix.shape[:-2]
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = torch.unbind(matrix.reshape(batch_shape + (9,)), -1)

    # 4 * component^2 for the components (w, x, y, z), clamped at zero before the square root.
    four_sq = torch.stack(
        [1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1
    )
    abs_twice = torch.where(four_sq > 0, torch.sqrt(four_sq.clamp(min=0)), torch.zeros_like(four_sq))

    # Row i holds (w, x, y, z) multiplied by 2 * |component i| * 2.
    scaled = torch.stack(
        [
            torch.stack([abs_twice[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, abs_twice[..., 1] ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, abs_twice[..., 2] ** 2, m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, abs_twice[..., 3] ** 2], -1),
        ],
        -2,
    )
    # The floor only guards the division of candidates that are never selected.
    floor = torch.tensor(0.1, dtype=abs_twice.dtype, device=abs_twice.device)
    candidates = scaled / (2.0 * torch.maximum(abs_twice, floor)[..., None])
    best = abs_twice.argmax(-1)
    wxyz = torch.gather(candidates, -2, best[..., None, None].expand(batch_shape + (1, 4))).squeeze(-2)
    xyzw = wxyz[..., [1, 2, 3, 0]]
    return standardize_quaternion(xyzw)


def pose_encoding_to_extri_intri(
    pose_encoding: torch.Tensor, image_size_hw: tuple[int, int], build_intrinsics: bool = True
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Decode VGGT pose encodings into extrinsics and intrinsics.

    Args:
        pose_encoding: ``(..., 9)`` ``[t, q_xyzw, fov_h, fov_w]``.
        image_size_hw: ``(H, W)`` of the image grid the intrinsics refer to (pixels).
        build_intrinsics: return ``None`` for the intrinsics when false.

    Returns:
        extrinsics ``(..., 3, 4)`` camera-from-world ``[R | t]``; intrinsics ``(..., 3, 3)``
        ``[[fx, 0, W/2], [0, fy, H/2], [0, 0, 1]]`` (same dtype as the encoding) or ``None``.
    """
    translation = pose_encoding[..., :3]
    rotation = quat_to_mat(pose_encoding[..., 3:7])
    extrinsics = torch.cat([rotation, translation[..., None]], dim=-1)
    if not build_intrinsics:
        return extrinsics, None
    height, width = image_size_hw
    fy = (height / 2.0) / torch.tan(pose_encoding[..., 7] / 2.0)
    fx = (width / 2.0) / torch.tan(pose_encoding[..., 8] / 2.0)
    intrinsics = torch.zeros(pose_encoding.shape[:-1] + (3, 3), dtype=pose_encoding.dtype, device=pose_encoding.device)
    intrinsics[..., 0, 0] = fx
    intrinsics[..., 1, 1] = fy
    intrinsics[..., 0, 2] = width / 2
    intrinsics[..., 1, 2] = height / 2
    intrinsics[..., 2, 2] = 1.0
    return extrinsics, intrinsics


def extri_intri_to_pose_encoding(
    extrinsics: torch.Tensor, intrinsics: torch.Tensor, image_size_hw: tuple[int, int]
) -> torch.Tensor:
    """Encode camera-from-world extrinsics and pinhole intrinsics as VGGT pose encodings.

    Args:
        extrinsics: ``(..., 3, 4)`` (or ``(..., 4, 4)``) camera-from-world.
        intrinsics: ``(..., 3, 3)`` pixels; only ``fx`` and ``fy`` are used.
        image_size_hw: ``(H, W)`` of the image grid in pixels.

    Returns:
        ``(..., 9)`` float32 ``[t, q_xyzw (w >= 0), fov_h, fov_w]``.
    """
    rotation = extrinsics[..., :3, :3]
    translation = extrinsics[..., :3, 3]
    quaternion = mat_to_quat(rotation)
    height, width = image_size_hw
    fov_h = 2 * torch.atan((height / 2) / intrinsics[..., 1, 1])
    fov_w = 2 * torch.atan((width / 2) / intrinsics[..., 0, 0])
    return torch.cat([translation, quaternion, fov_h[..., None], fov_w[..., None]], dim=-1).float()
