"""From Depth Anything 3's outputs to what the SLAM frontend returns (pure functions, numpy).

DA3 gives, per frame of a window, on its grid ``(H, W)``:

- ``depth``: z depth, ``exp`` of the head's logit, in the units of its cameras;
- ``depth_conf``: ``1 + exp(logit)``, already >= 1, which is what ``SubmapPrediction.confidence``
  holds (VGGT's activation too): it is passed through unchanged;
- ``extrinsics``: camera-from-world ``[R | t]`` where the world is the *reference view's* camera
  (chosen by the model among the frames, not necessarily the first) or the frame of the known
  cameras it was given. The submap frame of this project is the first frame's camera, so the
  extrinsics are re-expressed as ``T_cam_submap = T_cam_world T_world_first`` (rigid: depth and units
  are unchanged, and ``T_cam_submap[0]`` is the identity up to rounding);
- ``intrinsics``: pinhole ``K`` on the grid (camera decoder: principal point at ``(W/2, H/2)``; ray
  fit: fitted principal point).
"""

from __future__ import annotations

import numpy as np


def to_homogeneous(extrinsics: np.ndarray) -> np.ndarray:
    """``(S, 3, 4)`` or ``(S, 4, 4)`` -> ``(S, 4, 4)`` float64."""
    extrinsics = np.asarray(extrinsics, dtype=np.float64)
    if extrinsics.shape[-2:] == (4, 4):
        return extrinsics.copy()
    out = np.zeros(extrinsics.shape[:-2] + (4, 4))
    out[..., :3, :] = extrinsics
    out[..., 3, 3] = 1.0
    return out


def invert_rigid(transform: np.ndarray) -> np.ndarray:
    """Inverse of rigid ``(..., 4, 4)`` transforms: ``[R^T | -R^T t]``."""
    rotation = transform[..., :3, :3]
    inverse = np.zeros_like(transform)
    inverse[..., :3, :3] = np.swapaxes(rotation, -1, -2)
    inverse[..., :3, 3] = -np.einsum("...ji,...j->...i", rotation, transform[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def relative_to_first(extrinsics: np.ndarray) -> np.ndarray:
    """``T_cam_submap`` ``(S, 3, 4)`` float64 of camera-from-world extrinsics ``(S, 3|4, 4)``: each camera
    seen from the first camera's frame (``T_i_w T_0_w^-1``)."""
    T_cam_world = to_homogeneous(extrinsics)
    T_world_first = invert_rigid(T_cam_world[0])
    return (T_cam_world @ T_world_first)[:, :3, :]


def grid_principal_points(frames: int, height: int, width: int) -> np.ndarray:
    """``(S, 2)`` float64 ``(W/2, H/2)``: the principal point DA3's camera decoder assumes on its grid."""
    return np.tile([width / 2.0, height / 2.0], (frames, 1))


def submap_arrays(depth: np.ndarray, depth_conf: np.ndarray, extrinsics: np.ndarray,
                  intrinsics: np.ndarray) -> dict[str, np.ndarray]:
    """The frontend's arrays of one window from the model's (batch-free) outputs.

    Args:
        depth, depth_conf: ``(S, H, W)``.
        extrinsics: ``(S, 3|4, 4)`` camera-from-world (any world frame).
        intrinsics: ``(S, 3, 3)`` on the grid.

    Returns:
        ``depth`` ``(S, H, W)`` float32, ``confidence`` ``(S, H, W)`` float32 (>= 1, unchanged),
        ``T_cam_submap`` ``(S, 3, 4)`` float64 camera-from-first-frame, ``K`` ``(S, 3, 3)`` float64 and
        ``principal_point`` ``(S, 2)`` float64 (the grid centre).
    """
    depth = np.asarray(depth, dtype=np.float32)
    frames, height, width = depth.shape
    return {
        "depth": depth,
        "confidence": np.asarray(depth_conf, dtype=np.float32),
        "T_cam_submap": relative_to_first(extrinsics),
        "K": np.asarray(intrinsics, dtype=np.float64).copy(),
        "principal_point": grid_principal_points(frames, height, width),
    }
