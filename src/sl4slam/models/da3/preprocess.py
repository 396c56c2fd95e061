"""Depth Anything 3's input processing, for uint8 RGB arrays, without torchvision.

Reproduces the authors' ``InputProcessor`` bit for bit (OpenCV resampling, as theirs):

1. bound resize: "upper_bound_*" scales the longer side to ``process_res`` (default 504), "lower_bound_*"
   the shorter; sizes ``max(1, round(side * scale))`` (Python's round: half to even), bicubic when
   enlarging, area averaging when shrinking; nothing when the side already matches;
2. patch multiple (14): "*_resize" resizes each side to its nearest multiple (ties up; bicubic when
   either side grows, else area), "*_crop" centre-crops each side down to a multiple (offset
   ``(side - new) // 2``);
3. images of different sizes are centre-cropped to the smallest height and width;
4. ``x / 255`` in float32, then ``(x - mean) / std`` with the ImageNet statistics as float32.

How each input maps onto the grid is returned as a
:class:`~sl4slam.models.vggt.preprocess.GridTransform` (continuous coordinates, pixel ``i`` spanning
``[i, i + 1)``: ``x_grid = x * scale + offset``); :func:`intrinsics_on_grid` carries a pinhole ``K``
whose integer coordinates are pixel centres (this project's convention) onto the grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..vggt.preprocess import GridTransform
from .model import IMAGE_MEAN, IMAGE_STD

PROCESS_RES = 504
PATCH_SIZE = 14
METHODS = ("upper_bound_resize", "upper_bound_crop", "lower_bound_resize", "lower_bound_crop")


@dataclass
class Preprocessed:
    """A batch on the model's grid.

    Attributes:
        images: ``(S, 3, H, W)`` float32, normalised (the network's input).
        colors: ``(S, H, W, 3)`` uint8: the resampled images before normalisation.
        transforms: per image, how it maps onto the grid.
    """

    images: torch.Tensor
    colors: np.ndarray
    transforms: list[GridTransform]


def _resize(image: np.ndarray, width: int, height: int, enlarge: bool) -> np.ndarray:
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_CUBIC if enlarge else cv2.INTER_AREA)


def bound_resize(image: np.ndarray, target: int, longest: bool) -> np.ndarray:
    """Step 1: scale the longer (``longest``) or shorter side of ``(H, W, 3)`` ``image`` to ``target``."""
    height, width = image.shape[:2]
    side = max(width, height) if longest else min(width, height)
    if side == target:
        return image
    scale = target / float(side)
    new_width, new_height = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
    return _resize(image, new_width, new_height, scale > 1.0)


def nearest_multiple(value: int, multiple: int) -> int:
    """The multiple of ``multiple`` nearest to ``value`` (the larger one on a tie), at least 1."""
    down = (value // multiple) * multiple
    up = down + multiple
    return max(1, up if abs(up - value) <= abs(value - down) else down)


def to_patch_multiple(image: np.ndarray, crop: bool, patch: int = PATCH_SIZE) -> tuple[np.ndarray, tuple[int, int]]:
    """Step 2; returns the image and the ``(left, top)`` pixels cropped away (0 when resized)."""
    height, width = image.shape[:2]
    if crop:
        new_width, new_height = (width // patch) * patch, (height // patch) * patch
        if (new_width, new_height) == (width, height):
            return image, (0, 0)
        left, top = (width - new_width) // 2, (height - new_height) // 2
        return image[top:top + new_height, left:left + new_width], (left, top)
    new_width, new_height = nearest_multiple(width, patch), nearest_multiple(height, patch)
    if (new_width, new_height) == (width, height):
        return image, (0, 0)
    return _resize(image, new_width, new_height, new_width > width or new_height > height), (0, 0)


def normalize_uint8(colors: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """Step 4: ``(S, H, W, 3)`` uint8 -> ``(S, 3, H, W)`` float32 ``(x / 255 - mean) / std``, computed
    on ``device`` (the uint8 copied there first)."""
    planes = torch.from_numpy(np.ascontiguousarray(colors)).permute(0, 3, 1, 2).contiguous().to(device)
    planes = planes.to(torch.float32).div(255)
    mean = torch.as_tensor(IMAGE_MEAN, dtype=torch.float32, device=device).view(1, 3, 1, 1)
    std = torch.as_tensor(IMAGE_STD, dtype=torch.float32, device=device).view(1, 3, 1, 1)
    return planes.sub_(mean).div_(std)


def _check_rgb(image: np.ndarray) -> np.ndarray:
    array = np.asarray(image)
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {array.dtype} {array.shape}")
    return np.ascontiguousarray(array)


def preprocess_images(images: Sequence[np.ndarray], process_res: int = PROCESS_RES,
                      method: str = "upper_bound_resize", device: torch.device | str = "cpu") -> Preprocessed:
    """Put ``(H, W, 3)`` uint8 RGB images on the model's grid (steps 1-4 of the module docstring).

    Args:
        images: the frames, any sizes.
        process_res: the bound of step 1 (504 in the authors' API).
        method: one of :data:`METHODS` ("upper_bound_resize" in the authors' API).
        device: where the normalised images are made (and stay).
    """
    colors, transforms = grid_uint8(images, process_res, method)
    return Preprocessed(images=normalize_uint8(colors, device), colors=colors, transforms=transforms)


def grid_uint8(images: Sequence[np.ndarray], process_res: int = PROCESS_RES,
               method: str = "upper_bound_resize") -> tuple[np.ndarray, list[GridTransform]]:
    """Steps 1-3 of the module docstring: ``(S, H, W, 3)`` uint8 colours on the model's grid and how
    each image maps onto it (arguments as :func:`preprocess_images`)."""
    if len(images) == 0:
        raise ValueError("at least one image is required")
    if method not in METHODS:
        raise ValueError(f"unknown process_res_method {method!r}: use one of {', '.join(METHODS)}")
    crop = method.endswith("crop")
    resized, placements = [], []
    for image in images:
        image = _check_rgb(image)
        in_height, in_width = image.shape[:2]
        bounded = bound_resize(image, process_res, longest=method.startswith("upper"))
        mid_height, mid_width = bounded.shape[:2]
        final, (left, top) = to_patch_multiple(bounded, crop)
        if crop:
            scale_x, scale_y = mid_width / in_width, mid_height / in_height
        else:
            scale_x, scale_y = final.shape[1] / in_width, final.shape[0] / in_height
        resized.append(final)
        placements.append(((in_height, in_width), scale_x, scale_y, -float(left), -float(top)))
    out_height = min(r.shape[0] for r in resized)
    out_width = min(r.shape[1] for r in resized)
    colors, transforms = [], []
    for image, (input_hw, scale_x, scale_y, offset_x, offset_y) in zip(resized, placements):
        top, left = max(0, (image.shape[0] - out_height) // 2), max(0, (image.shape[1] - out_width) // 2)
        colors.append(image[top:top + out_height, left:left + out_width])
        transforms.append(GridTransform(input_hw, (out_height, out_width), scale_x, scale_y, offset_x - left,
                                        offset_y - top, (0, 0, out_width, out_height)))
    return np.stack(colors), transforms


def intrinsics_on_grid(intrinsics: np.ndarray, transform: GridTransform) -> np.ndarray:
    """A pinhole ``K`` ``(3, 3)`` of an input frame (integer coordinates at pixel centres) on the grid.

    With the grid transform ``x_grid = s x + o`` between continuous (corner) coordinates, pixel-centre
    coordinates map as ``u_grid = s (u + 1/2) - 1/2 + o``: ``K_grid = [[s_x, 0, s_x/2 - 1/2 + o_x],
    [0, s_y, s_y/2 - 1/2 + o_y], [0, 0, 1]] K``. (The authors' processor scales ``cx`` by ``s`` alone,
    0.5 (1 - s) px off; DA3's camera encoder reads only the focal lengths, which agree.)
    """
    mapping = np.array([
        [transform.scale_x, 0.0, transform.scale_x / 2 - 0.5 + transform.offset_x],
        [0.0, transform.scale_y, transform.scale_y / 2 - 0.5 + transform.offset_y],
        [0.0, 0.0, 1.0],
    ])
    return mapping @ np.asarray(intrinsics, dtype=np.float64)
