"""Rigid-transform inverse and depth unprojection with VGGT's pixel conventions.

Pixel ``(u, v)`` is the integer column/row index (no half-pixel offset); camera coordinates are
``x = (u - cx) d / fx``, ``y = (v - cy) d / fy``, ``z = d``. Extrinsics are camera-from-world.
"""

from __future__ import annotations

import numpy as np
import torch


def closed_form_inverse_se3(se3: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Invert rigid transforms ``[R | t]`` as ``[R^T | -R^T t]``.

    Args:
        se3: ``(N, 3, 4)`` or ``(N, 4, 4)`` numpy array or torch tensor.

    Returns:
        ``(N, 4, 4)``: a tensor keeps its dtype and device; a numpy array comes back float64.
    """
    if se3.shape[-2:] not in ((3, 4), (4, 4)) or se3.ndim != 3:
        raise ValueError(f"expected (N, 3, 4) or (N, 4, 4) transforms, got {tuple(se3.shape)}")
    rotation = se3[:, :3, :3]
    translation = se3[:, :3, 3:]
    if isinstance(se3, np.ndarray):
        rotation_t = np.transpose(rotation, (0, 2, 1))
        inverse = np.tile(np.eye(4), (len(se3), 1, 1))
        inverse[:, :3, :3] = rotation_t
        inverse[:, :3, 3:] = -np.matmul(rotation_t, translation)
        return inverse
    rotation_t = rotation.transpose(1, 2)
    inverse = torch.eye(4, dtype=se3.dtype, device=se3.device).repeat(len(se3), 1, 1)
    inverse[:, :3, :3] = rotation_t
    inverse[:, :3, 3:] = -torch.bmm(rotation_t, translation)
    return inverse


def unproject_depth_map_to_point_map(
    depth: np.ndarray | torch.Tensor,
    extrinsics: np.ndarray | torch.Tensor,
    intrinsics: np.ndarray | torch.Tensor,
) -> np.ndarray:
    """World points of every pixel of a batch of depth maps.

    Zero depths are not masked: they unproject to the camera centre.

    Args:
        depth: ``(S, H, W)`` or ``(S, H, W, 1)`` depth along the camera z axis.
        extrinsics: ``(S, 3, 4)`` camera-from-world.
        intrinsics: ``(S, 3, 3)`` zero-skew pinhole intrinsics on the depth grid.

    Returns:
        ``(S, H, W, 3)`` float64 world points.
    """
    def as_numpy(array):
        return array.detach().cpu().numpy() if isinstance(array, torch.Tensor) else np.asarray(array)

    depth, extrinsics, intrinsics = as_numpy(depth), as_numpy(extrinsics), as_numpy(intrinsics)
    if depth.ndim == 4:
        depth = depth[..., 0]
    num_frames, height, width = depth.shape
    depth64 = depth.astype(np.float64)
    u = np.arange(width, dtype=np.float64)[None, None, :]
    v = np.arange(height, dtype=np.float64)[None, :, None]
    fx, fy = intrinsics[:, 0, 0, None, None], intrinsics[:, 1, 1, None, None]
    cx, cy = intrinsics[:, 0, 2, None, None], intrinsics[:, 1, 2, None, None]
    # Camera coordinates are rounded to float32 as the reference does, before the rigid motion.
    cam = np.stack(
        ((u - cx) * depth64 / fx, (v - cy) * depth64 / fy, depth64), axis=-1
    ).astype(np.float32)
    cam_to_world = closed_form_inverse_se3(extrinsics[:, :3, :4])
    rotation = cam_to_world[:, :3, :3]
    translation = cam_to_world[:, None, None, :3, 3]
    return np.einsum("shwj,sij->shwi", cam.astype(np.float64), rotation) + translation
