"""π³ input preprocessing: the authors' image loader, without PIL or torchvision.

The authors' ``load_images_as_tensor`` (``pi3/utils/basic.py``) resizes every image of a set to one
size chosen from the *first* image: the largest grid of 14-pixel patches whose pixel count stays
within a budget (255 000 pixels) and whose aspect ratio is closest to the image's
(:func:`target_size`), resampled with PIL's Lanczos filter, then divided by 255. This module does
the same on uint8 arrays, bit for bit (:func:`resize_lanczos` is PIL's two-pass fixed-point
Lanczos resampler; ``tests/test_pi3_model.py`` checks both against the authors' function).

PIL's result depends on the order of its two passes (each rounds to uint8): Pillow 13 runs the
vertical pass first when the height shrinks by more than twice as many pixels as the width, and
the horizontal pass first otherwise; earlier Pillows always ran the horizontal pass first
(``pillow_order="legacy"``). The two orders differ by at most a few grey levels, and only for such
tall shrinks (never for landscape frames shrunk or enlarged in proportion).

Grid mapping (the project's pixel convention: integer coordinates at pixel centres): PIL maps
output pixel centre ``j + 0.5`` to input position ``(j + 0.5) * in / out``, so an input pixel ``x``
lands at ``(x + 0.5) * scale - 0.5`` on the grid, ``scale = out / in`` (:class:`ResizeTransform`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

PIXEL_BUDGET = 255_000
"""The authors' pixel budget per image (``PIXEL_LIMIT``)."""
PATCH_SIZE = 14
_PRECISION_BITS = 32 - 8 - 2  # PIL's fixed-point precision for 8-bit images
_LANCZOS_SUPPORT = 3.0


@dataclass(frozen=True)
class ResizeTransform:
    """How one input image maps onto the model's grid.

    Attributes:
        input_hw: ``(H, W)`` of the input image.
        output_hw: ``(H, W)`` of the grid.
        scale_x, scale_y: grid pixels per input pixel.
    """

    input_hw: tuple[int, int]
    output_hw: tuple[int, int]
    scale_x: float
    scale_y: float

    def input_to_output(self, xy: np.ndarray) -> np.ndarray:
        """``(N, 2)`` input pixel coordinates (integer = pixel centre) -> grid coordinates."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([(xy[:, 0] + 0.5) * self.scale_x - 0.5, (xy[:, 1] + 0.5) * self.scale_y - 0.5], -1)

    def output_to_input(self, xy: np.ndarray) -> np.ndarray:
        """``(N, 2)`` grid coordinates -> input pixel coordinates."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([(xy[:, 0] + 0.5) / self.scale_x - 0.5, (xy[:, 1] + 0.5) / self.scale_y - 0.5], -1)

    def intrinsics_to_output(self, K: np.ndarray) -> np.ndarray:
        """``(3, 3)`` intrinsics of the input image -> intrinsics of the grid (same convention)."""
        A = np.array([[self.scale_x, 0.0, 0.5 * self.scale_x - 0.5],
                      [0.0, self.scale_y, 0.5 * self.scale_y - 0.5],
                      [0.0, 0.0, 1.0]])
        return A @ np.asarray(K, dtype=np.float64)


def target_size(width: int, height: int, budget: int = PIXEL_BUDGET, patch: int = PATCH_SIZE) -> tuple[int, int]:
    """``(W, H)`` of the grid for a ``width`` x ``height`` image: both multiples of ``patch``, at most
    ``budget`` pixels. The scaled size is rounded to patches (Python's round), then the side that
    keeps the aspect ratio closest is reduced one patch at a time until the budget holds (the
    authors' rule, evaluated in the same order)."""
    scale = math.sqrt(budget / (width * height)) if width * height > 0 else 1
    target_w, target_h = width * scale, height * scale
    cols, rows = round(target_w / patch), round(target_h / patch)
    while (cols * patch) * (rows * patch) > budget:
        if rows > 0 and cols / rows > target_w / target_h:
            cols -= 1
        else:
            rows -= 1
    return max(1, cols) * patch, max(1, rows) * patch


def _lanczos(x: float) -> float:
    """Lanczos-3 kernel ``sinc(x) sinc(x/3)`` on [-3, 3) (PIL's definition, C double arithmetic)."""
    if -_LANCZOS_SUPPORT <= x < _LANCZOS_SUPPORT:
        return _sinc(x) * _sinc(x / 3)
    return 0.0


def _sinc(x: float) -> float:
    if x == 0.0:
        return 1.0
    x = x * math.pi
    return math.sin(x) / x


def lanczos_weights(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray]:
    """PIL's resampling weights along one axis, in its 8-bit fixed point.

    Returns:
        ``first`` ``(out,)`` int64, the first input pixel each output pixel reads, and ``weights``
        ``(out, taps)`` int64, the weights times ``2^22`` rounded half away from zero (0 beyond
        each pixel's support).
    """
    scale = in_size / out_size
    filter_scale = max(scale, 1.0)
    support = _LANCZOS_SUPPORT * filter_scale
    taps = int(math.ceil(support)) * 2 + 1
    first = np.zeros(out_size, dtype=np.int64)
    weights = np.zeros((out_size, taps), dtype=np.int64)
    inverse = 1.0 / filter_scale
    for j in range(out_size):
        center = (j + 0.5) * scale
        lo = max(int(center - support + 0.5), 0)  # C's (int) truncates toward zero
        hi = min(int(center + support + 0.5), in_size)
        values = [_lanczos((i + lo - center + 0.5) * inverse) for i in range(hi - lo)]
        total = 0.0
        for value in values:
            total += value
        if total != 0.0:
            values = [value / total for value in values]
        first[j] = lo
        for i, value in enumerate(values):
            fixed = value * (1 << _PRECISION_BITS)
            weights[j, i] = int(-0.5 + fixed) if value < 0 else int(0.5 + fixed)
    return first, weights


@functools.lru_cache(maxsize=16)
def _taps(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray]:
    """``(out, taps)`` input index of each tap (clamped: beyond the support the weight is 0) and its
    fixed-point weight, as int32 where no sum can overflow it (else int64); read-only, cached."""
    first, weights = lanczos_weights(in_size, out_size)
    index = np.minimum(first[:, None] + np.arange(weights.shape[1]), in_size - 1)
    bound = int(np.abs(weights).sum(axis=1).max()) * 255 + (1 << (_PRECISION_BITS - 1))
    weights = weights.astype(np.int32 if bound < 2**31 else np.int64)
    index.setflags(write=False)
    weights.setflags(write=False)
    return index, weights


def _resample_axis(image: np.ndarray, out_size: int, axis: int) -> np.ndarray:
    """One pass of PIL's 8-bit resampler along ``axis`` (0: rows, 1: columns) of ``(H, W, C)`` uint8
    (integer sums: exact in any order)."""
    index, weights = _taps(image.shape[axis], out_size)
    source = image.astype(weights.dtype)
    shape = image.shape[:axis] + (out_size,) + image.shape[axis + 1:]
    total = np.full(shape, 1 << (_PRECISION_BITS - 1), dtype=weights.dtype)
    term = np.empty(shape, dtype=weights.dtype)
    for tap in range(weights.shape[1]):
        np.take(source, index[:, tap], axis=axis, out=term)
        term *= weights[:, tap].reshape((-1,) + (1,) * (image.ndim - 1 - axis))
        total += term
    total >>= _PRECISION_BITS
    return np.clip(total, 0, 255).astype(np.uint8)


def horizontal_pass_first(in_w: int, in_h: int, out_w: int, out_h: int, pillow_order: str = "13") -> bool:
    """Whether PIL resamples the rows (horizontal pass) before the columns (see the module doc)."""
    if pillow_order == "legacy":
        return True
    if pillow_order != "13":
        raise ValueError(f"pillow_order must be '13' or 'legacy', got {pillow_order!r}")
    shrink_h, shrink_w = in_h - out_h, in_w - out_w
    return not (shrink_h > 0 and shrink_h > 2 * shrink_w)


def resize_lanczos(image: np.ndarray, width: int, height: int, pillow_order: str = "13") -> np.ndarray:
    """``(H, W, C)`` uint8 resized to ``(height, width, C)`` exactly as PIL's
    ``Image.resize((width, height), Image.LANCZOS)``: two passes, each rounded to uint8, in PIL's
    order (:func:`horizontal_pass_first`); an axis that keeps its size is not resampled."""
    out = np.ascontiguousarray(image)
    axes = (1, 0) if horizontal_pass_first(out.shape[1], out.shape[0], width, height, pillow_order) else (0, 1)
    for axis in axes:
        size = width if axis == 1 else height
        if out.shape[axis] != size:
            out = _resample_axis(out, size, axis=axis)
    return out


def _check_rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}")
    return image


def preprocess_images(images: Sequence[np.ndarray], budget: int = PIXEL_BUDGET, size: tuple[int, int] | None = None,
                      device: torch.device | str = "cpu") -> tuple[torch.Tensor, np.ndarray, list[ResizeTransform]]:
    """Resize images for π³ as the authors' loader does.

    Args:
        images: ``(H, W, 3)`` uint8 RGB arrays (sizes may differ; the first one sets the grid).
        budget: pixel budget of the grid.
        size: ``(W, H)`` of the grid, instead of :func:`target_size` of the first image.
        device: where the float images are made (the uint8 copied there first).

    Returns:
        ``(S, 3, H, W)`` float32 in [0, 1] (``uint8 / 255`` exactly) on ``device``, the same images
        as ``(S, H, W, 3)`` uint8, and one :class:`ResizeTransform` per image.
    """
    resized, transforms = resize_to_grid(images, budget, size)
    tensor = torch.from_numpy(resized).permute(0, 3, 1, 2).contiguous().to(device).to(torch.float32).div(255)
    return tensor, resized, transforms


def resize_to_grid(images: Sequence[np.ndarray], budget: int = PIXEL_BUDGET,
                   size: tuple[int, int] | None = None) -> tuple[np.ndarray, list[ResizeTransform]]:
    """The images resized onto π³'s grid, ``(S, H, W, 3)`` uint8, and one :class:`ResizeTransform`
    per image (arguments as :func:`preprocess_images`)."""
    if len(images) == 0:
        raise ValueError("at least one image is required")
    images = [_check_rgb(image) for image in images]
    width, height = size if size is not None else target_size(images[0].shape[1], images[0].shape[0], budget)
    resized = np.stack([resize_lanczos(image, width, height) for image in images])
    transforms = [ResizeTransform((image.shape[0], image.shape[1]), (height, width), width / image.shape[1],
                                  height / image.shape[0]) for image in images]
    return resized, transforms
