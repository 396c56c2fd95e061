"""Projective positional encoding (PRoPE, Li et al. 2025) of Pi3X's pose-injection attention.

Pi3X injects known camera poses by an attention over the patch tokens of all views in which each
head's channels are split in three blocks (``d`` = head dimension):

- the first ``d/2`` channels, read as ``d/8`` 4-vectors, are moved by the token's camera: queries
  by ``P^T``, keys and values by ``P^-1``, the output by ``P``, where ``P`` is the view's
  camera-from-world matrix (its 4x4 extrinsics; Pi3X passes no intrinsics, the "GTA" form). So
  ``q . k`` sees the relative pose of the two views;
- the next ``d/4`` channels are rotated by the patch column, the last ``d/4`` by the patch row
  (1D RoPE, base 100, "split" layout: first half against second half of the block); the output
  is rotated back.

Tokens are ``(B, heads, views * rows * cols, d)``, views outer, patches row-major inside a view.
"""

from __future__ import annotations

import torch
from torch import Tensor

ROPE_BASE = 100.0


def rigid_inverse(transforms: Tensor) -> Tensor:
    """Inverse of ``(..., 4, 4)`` rigid transforms, ``[R^T | -R^T t]`` (PRoPE's own formula)."""
    rotation_t = transforms[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(transforms)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -torch.einsum("...ij,...j->...i", rotation_t, transforms[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def rope_coefficients(positions: Tensor, feat_dim: int, base: float = ROPE_BASE) -> tuple[Tensor, Tensor]:
    """``(cos, sin)``, each ``(1, 1, L, feat_dim/2)``, of integer ``positions`` ``(L,)``: angle
    ``position * base^(-i / (feat_dim/2))`` for frequency ``i``."""
    num_freqs = feat_dim // 2
    exponents = -torch.arange(num_freqs, device=positions.device)[None, None, None, :] / num_freqs
    angles = positions[None, None, :, None] * (1.0 * (base ** exponents))
    return torch.cos(angles), torch.sin(angles)


def rotate(features: Tensor, coefficients: tuple[Tensor, Tensor], inverse: bool = False) -> Tensor:
    """Rotate ``(B, heads, L, f)`` features: pairs ``(x_i, y_i)`` = channel ``i`` of the first and of
    the second half; ``inverse`` rotates the other way. Coefficients of one view are tiled over
    all views."""
    cos, sin = coefficients
    if cos.shape[2] != features.shape[2]:
        repeats = features.shape[2] // cos.shape[2]
        cos, sin = cos.repeat(1, 1, repeats, 1), sin.repeat(1, 1, repeats, 1)
    half = features.shape[-1] // 2
    x, y = features[..., :half], features[..., half:]
    if inverse:
        return torch.cat([cos * x - sin * y, sin * x + cos * y], dim=-1)
    return torch.cat([cos * x + sin * y, -sin * x + cos * y], dim=-1)


def transform_by_camera(features: Tensor, matrices: Tensor) -> Tensor:
    """Multiply each 4-vector of ``(B, heads, views * P, f)`` features (f divisible by 4) by its
    view's ``(B, views, 4, 4)`` matrix."""
    batch, heads, _, feat_dim = features.shape
    views = matrices.shape[1]
    blocks = features.reshape(batch, heads, views, -1, feat_dim // 4, 4)
    return torch.einsum("bvij,bhvpkj->bhvpki", matrices, blocks).reshape(features.shape)


class ProjectiveEncoding:
    """The three block-diagonal maps of PRoPE for one set of views (see the module docstring).

    Args:
        extrinsics: ``(B, views, 4, 4)`` camera-from-world transforms.
        head_dim: ``d`` (divisible by 8).
        rows, cols: the patch grid of one view.
    """

    def __init__(self, extrinsics: Tensor, head_dim: int, rows: int, cols: int) -> None:
        if head_dim % 8:
            raise ValueError(f"PRoPE needs a head dimension divisible by 8, got {head_dim}")
        device = extrinsics.device
        views = extrinsics.shape[1]
        self.sizes = [head_dim // 2, head_dim // 4, head_dim // 4]
        self.camera = extrinsics
        self.camera_t = extrinsics.transpose(-1, -2)
        self.camera_inv = rigid_inverse(extrinsics)
        column_of_patch = torch.tile(torch.arange(cols, device=device), (rows * views,))
        row_of_patch = torch.tile(torch.repeat_interleave(torch.arange(rows, device=device), cols), (views,))
        self.columns = rope_coefficients(column_of_patch, head_dim // 4)
        self.rows = rope_coefficients(row_of_patch, head_dim // 4)

    def _apply(self, features: Tensor, matrices: Tensor, inverse: bool) -> Tensor:
        camera_part, column_part, row_part = torch.split(features, self.sizes, dim=-1)
        return torch.cat([transform_by_camera(camera_part, matrices),
                          rotate(column_part, self.columns, inverse),
                          rotate(row_part, self.rows, inverse)], dim=-1)

    def queries(self, q: Tensor) -> Tensor:
        return self._apply(q, self.camera_t, inverse=False)

    def keys_values(self, kv: Tensor) -> Tensor:
        return self._apply(kv, self.camera_inv, inverse=False)

    def outputs(self, o: Tensor) -> Tensor:
        return self._apply(o, self.camera, inverse=True)
