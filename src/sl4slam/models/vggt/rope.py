"""2D rotary position embedding of the VGGT aggregator.

Each head's channels are split in two halves: the first half is rotated by the token's row
(y) and the second by its column (x). Within a half of size ``d``, frequencies are
``base^(-2k/d)`` for ``k < d/2`` and rotation uses the "rotate-half" layout:
``out = t cos(a) + rotate_half(t) sin(a)``, ``rotate_half(t) = [-t[d/2:], t[:d/2]]``, with the
angles ``a = pos * inv_freq`` duplicated as ``[a, a]``.
"""

from __future__ import annotations

import weakref

import torch
from torch import Tensor, nn


def patch_positions(batch: int, rows: int, cols: int, num_special: int, device: torch.device | str) -> Tensor:
    """Positions of VGGT's tokens: ``(batch, num_special + rows*cols, 2)`` int64 ``(y, x)``.

    Special (camera and register) tokens get ``(0, 0)``; patch ``(r, c)`` (row-major) gets
    ``(r + 1, c + 1)`` so no patch shares the special tokens' position.
    """
    ys = torch.arange(rows, device=device).repeat_interleave(cols)
    xs = torch.arange(cols, device=device).repeat(rows)
    patches = torch.stack([ys, xs], -1) + 1
    special = torch.zeros(num_special, 2, dtype=patches.dtype, device=device)
    return torch.cat([special, patches], 0)[None].expand(batch, -1, -1)


class RotaryPositionEmbedding2D(nn.Module):
    """Apply 2D RoPE to per-head features.

    Call with ``tokens`` ``(B, heads, N, D)`` (D divisible by 4) and ``positions`` ``(B, N, 2)``
    integer ``(y, x)``; returns a tensor like ``tokens``. No parameters (nothing in the state dict).
    """

    def __init__(self, base: float = 100.0) -> None:
        super().__init__()
        self.base = float(base)
        self._cache: dict[tuple, tuple[Tensor, Tensor]] = {}
        self._lengths: dict[int, tuple[weakref.ref, int]] = {}

    def _length(self, positions: Tensor) -> int:
        """1 + the largest entry of ``positions``, read once per positions tensor: on a GPU each read
        waits for all queued work, and every block of a forward is handed the same tensor."""
        hit = self._lengths.get(id(positions))
        if hit is not None and hit[0]() is positions:
            return hit[1]
        length = int(positions.max()) + 1
        self._lengths = {key: value for key, value in self._lengths.items() if value[0]() is not None}
        self._lengths[id(positions)] = (weakref.ref(positions), length)
        return length

    def _tables(self, half_dim: int, length: int, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """cos/sin tables ``(length, half_dim)`` for positions ``0..length-1``."""
        key = (half_dim, length, device, dtype)
        if key not in self._cache:
            inv_freq = 1.0 / (self.base ** (torch.arange(0, half_dim, 2, device=device).float() / half_dim))
            angles = torch.arange(length, device=device, dtype=torch.float32)[:, None] * inv_freq[None, :]
            # Angles are rounded to the token dtype before cos/sin, as the released model does.
            angles = angles.to(dtype)
            angles = torch.cat([angles, angles], -1)
            self._cache[key] = (angles.cos().to(dtype), angles.sin().to(dtype))
        return self._cache[key]

    @staticmethod
    def _rotate_half(x: Tensor) -> Tensor:
        half = x.shape[-1] // 2
        return torch.cat([-x[..., half:], x[..., :half]], -1)

    def _rotate(self, features: Tensor, positions: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
        cos_p = cos[positions][:, None]  # (B, 1, N, d)
        sin_p = sin[positions][:, None]
        return features * cos_p + self._rotate_half(features) * sin_p

    def forward(self, tokens: Tensor, positions: Tensor) -> Tensor:
        if tokens.shape[-1] % 4 != 0:
            raise ValueError(f"RoPE 2D needs a head dimension divisible by 4, got {tokens.shape[-1]}")
        half_dim = tokens.shape[-1] // 2
        cos, sin = self._tables(half_dim, self._length(positions), tokens.device, tokens.dtype)
        rows_part, cols_part = tokens.chunk(2, dim=-1)
        return torch.cat(
            [self._rotate(rows_part, positions[..., 0], cos, sin), self._rotate(cols_part, positions[..., 1], cos, sin)],
            -1,
        )
