"""VGGT input preprocessing: resize RGB images onto a grid whose sides are multiples of 14.

Reproduces the released model's ``load_and_preprocess_images`` (modes "crop" and "pad") and
``load_and_preprocess_images_square`` bit for bit (PIL bicubic resampling, ``/ 255`` in float32),
but takes in-memory uint8 images as well as paths, and also returns how every input pixel maps
onto the output grid so predictions can be related back to the input frames.

Grid mapping: an input pixel centre ``(x, y)`` (continuous pixel coordinates, pixel ``i`` spans
``[i, i+1)``) lands at ``(x * scale_x + offset_x, y * scale_y + offset_y)`` on the output grid.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from PIL import Image

logger = logging.getLogger(__name__)

TARGET_SIZE = 518
PATCH_SIZE = 14


@dataclass(frozen=True)
class GridTransform:
    """How one input image was placed on the model's grid (see the module docstring).

    Attributes:
        input_hw: ``(H, W)`` of the input image.
        output_hw: ``(H, W)`` of the output grid (after cropping/padding to the batch shape).
        scale_x, scale_y: output pixels per input pixel.
        offset_x, offset_y: output position of the input's top-left corner (negative when cropped).
        valid_box: ``(x0, y0, x1, y1)`` output pixels covered by the image (the rest is padding).
    """

    input_hw: tuple[int, int]
    output_hw: tuple[int, int]
    scale_x: float
    scale_y: float
    offset_x: float
    offset_y: float
    valid_box: tuple[int, int, int, int]

    def input_to_output(self, xy: np.ndarray) -> np.ndarray:
        """Map ``(N, 2)`` continuous input pixel coordinates to output grid coordinates."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([xy[:, 0] * self.scale_x + self.offset_x, xy[:, 1] * self.scale_y + self.offset_y], -1)

    def output_to_input(self, xy: np.ndarray) -> np.ndarray:
        """Map ``(N, 2)`` continuous output grid coordinates back to input pixel coordinates."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([(xy[:, 0] - self.offset_x) / self.scale_x, (xy[:, 1] - self.offset_y) / self.scale_y], -1)

    def valid_mask(self) -> np.ndarray:
        """``(H, W)`` bool over the output grid: true where the pixel comes from the image."""
        mask = np.zeros(self.output_hw, dtype=bool)
        x0, y0, x1, y1 = self.valid_box
        mask[y0:y1, x0:x1] = True
        return mask


def _to_pil_rgb(image: np.ndarray | str | Path | Image.Image) -> Image.Image:
    """Open/wrap an image; RGBA is composited over opaque white, everything else converted to RGB."""
    if isinstance(image, (str, Path)):
        pil = Image.open(image)
    elif isinstance(image, Image.Image):
        pil = image
    else:
        array = np.asarray(image)
        if array.dtype != np.uint8 or array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] not in (3, 4)):
            raise ValueError(
                f"expected an (H, W, 3) RGB or (H, W, 4) RGBA uint8 image, got {array.dtype} {array.shape}"
            )
        pil = Image.fromarray(array)
    if pil.mode == "RGBA":
        white = Image.new("RGBA", pil.size, (255, 255, 255, 255))
        pil = Image.alpha_composite(white, pil)
    return pil.convert("RGB")


def _resized_size(width: int, height: int, mode: str) -> tuple[int, int]:
    """``(new_w, new_h)`` of the bicubic resize; Python's round (half to even), evaluated in this order."""
    if mode == "crop" or width >= height:
        new_w = TARGET_SIZE
        new_h = round(height * (new_w / width) / PATCH_SIZE) * PATCH_SIZE
    else:
        new_h = TARGET_SIZE
        new_w = round(width * (new_h / height) / PATCH_SIZE) * PATCH_SIZE
    return new_w, new_h


def preprocess_images(
    images: Sequence[np.ndarray | str | Path | Image.Image], mode: str = "crop"
) -> tuple[torch.Tensor, list[GridTransform]]:
    """Resize images for VGGT: :func:`preprocess_uint8`, then ``/ 255`` in float32.

    Args:
        images: ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA uint8 arrays, PIL images or file paths.
        mode: "crop" or "pad".

    Returns:
        ``(N, 3, H', W')`` float32 in [0, 1] (``uint8 / 255`` exactly) and one
        :class:`GridTransform` per image.
    """
    batch, transforms = preprocess_uint8(images, mode)
    return batch.to(torch.float32).div(255), transforms


def preprocess_uint8(
    images: Sequence[np.ndarray | str | Path | Image.Image], mode: str = "crop"
) -> tuple[torch.Tensor, list[GridTransform]]:
    """Resize images onto VGGT's grid, in uint8 (the model's input is this ``/ 255``).

    - "crop": width becomes 518, height keeps the aspect ratio rounded to a multiple of 14, and
      rows beyond 518 are centre-cropped.
    - "pad": the longer side becomes 518, the other keeps the aspect ratio (multiple of 14), and the
      image is centred on a 518x518 canvas of 1.0 (white).
    When the results differ in shape, every image is centred on white padding to the largest height
    and width.

    Args:
        images: ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA uint8 arrays, PIL images or file paths.
        mode: "crop" or "pad".

    Returns:
        ``(N, 3, H', W')`` uint8 (padding 255) and one :class:`GridTransform` per image.
    """
    if len(images) == 0:
        raise ValueError("at least one image is required")
    if mode not in ("crop", "pad"):
        raise ValueError(f"mode must be 'crop' or 'pad', got {mode!r}")

    planes: list[torch.Tensor] = []
    placements: list[tuple[int, int, float, float, float, float]] = []  # (in_h, in_w, sx, sy, ox, oy)
    for image in images:
        pil = _to_pil_rgb(image)
        width, height = pil.size
        new_w, new_h = _resized_size(width, height, mode)
        resized = np.asarray(pil.resize((new_w, new_h), Image.Resampling.BICUBIC))
        plane = torch.from_numpy(resized.copy()).permute(2, 0, 1)
        offset_x, offset_y = 0.0, 0.0
        if mode == "crop" and new_h > TARGET_SIZE:
            top = (new_h - TARGET_SIZE) // 2
            plane = plane[:, top : top + TARGET_SIZE, :]
            offset_y = -float(top)
        if mode == "pad":
            plane, (pad_left, pad_top) = _pad_white(plane, TARGET_SIZE, TARGET_SIZE)
            offset_x, offset_y = float(pad_left), float(pad_top)
        planes.append(plane)
        placements.append((height, width, new_w / width, new_h / height, offset_x, offset_y))

    shapes = {tuple(p.shape[1:]) for p in planes}
    if len(shapes) > 1:
        logger.warning("images of different shapes %s are padded with white to a common shape", sorted(shapes))
        max_h = max(s[0] for s in shapes)
        max_w = max(s[1] for s in shapes)
        for index, plane in enumerate(planes):
            planes[index], (pad_left, pad_top) = _pad_white(plane, max_h, max_w)
            h, w, sx, sy, ox, oy = placements[index]
            placements[index] = (h, w, sx, sy, ox + pad_left, oy + pad_top)

    batch = torch.stack(planes)
    out_h, out_w = batch.shape[-2:]
    transforms = []
    for in_h, in_w, sx, sy, ox, oy in placements:
        x0, y0 = max(0, int(round(ox))), max(0, int(round(oy)))
        x1 = min(out_w, int(round(ox + in_w * sx)))
        y1 = min(out_h, int(round(oy + in_h * sy)))
        transforms.append(GridTransform((in_h, in_w), (out_h, out_w), sx, sy, ox, oy, (x0, y0, x1, y1)))
    return batch, transforms


def _pad_white(plane: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Centre a ``(3, h, w)`` plane on a white ``(3, height, width)`` canvas (255 for uint8, else 1.0);
    returns it and (left, top)."""
    pad_h = height - plane.shape[1]
    pad_w = width - plane.shape[2]
    if pad_h <= 0 and pad_w <= 0:
        return plane, (0, 0)
    top, left = pad_h // 2, pad_w // 2
    padded = torch.nn.functional.pad(plane, (left, pad_w - left, top, pad_h - top), mode="constant",
                                     value=255 if plane.dtype == torch.uint8 else 1.0)
    return padded, (left, top)


def preprocess_images_square(
    images: Sequence[np.ndarray | str | Path | Image.Image], target_size: int = 1024
) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre each image on a black square, then resize it to ``target_size``.

    Args:
        images: RGB/RGBA uint8 arrays, PIL images or paths.
        target_size: side of the output square in pixels.

    Returns:
        ``(N, 3, T, T)`` float32 in [0, 1] and ``(N, 6)`` float32
        ``[x1, y1, x2, y2, width, height]``: the image's box on the output square and its
        original size.
    """
    if len(images) == 0:
        raise ValueError("at least one image is required")
    planes = []
    coords = []
    for image in images:
        pil = _to_pil_rgb(image)
        width, height = pil.size
        side = max(width, height)
        left, top = (side - width) // 2, (side - height) // 2
        scale = target_size / side
        coords.append([left * scale, top * scale, (left + width) * scale, (top + height) * scale, width, height])
        square = Image.new("RGB", (side, side), (0, 0, 0))
        square.paste(pil, (left, top))
        resized = np.asarray(square.resize((target_size, target_size), Image.Resampling.BICUBIC))
        planes.append(torch.from_numpy(resized.copy()).permute(2, 0, 1).to(torch.float32).div(255))
    return torch.stack(planes), torch.from_numpy(np.array(coords, dtype=np.float64)).float()


def channels_last(images: torch.Tensor) -> np.ndarray:
    """``(N, 3, H, W)`` uint8 (as :func:`preprocess_uint8` makes them) to ``(N, H, W, 3)`` uint8 RGB."""
    return np.ascontiguousarray(images.permute(0, 2, 3, 1).numpy())


def to_uint8_rgb(images: torch.Tensor) -> np.ndarray:
    """``(N, 3, H, W)`` floats in [0, 1] (as made above) to ``(N, H, W, 3)`` uint8 RGB (exact inverse)."""
    return (images.permute(0, 2, 3, 1).clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
