"""VGGT frontend: one forward pass of VGGT over a submap's frames.

Frames are resized onto VGGT's grid (width 518 in "crop" mode, 518x518 in "pad" mode, sides
multiples of 14; see :mod:`sl4slam.models.vggt.preprocess`) and every output lives on that grid:
depth, confidence, the intrinsics and the colours. How each input frame maps onto the grid is
kept in :attr:`VGGTFrontend.last_transforms` (scale and offset per frame, plus the region that is
image rather than padding).

Loop check: asked for ``match_pairs``, the frontend also returns VGGT-SLAM 2.0's image-match ratio of
each pair of slots, read from the attention of global block ``VGGTConfig.match_layer`` during the same
forward pass (``sl4slam.models.vggt.attention``).

Precision: float32 on CPU; on CUDA the aggregator runs under bf16 (or fp16 where bf16 is not
supported) autocast with its weights stored in that dtype, and the heads run in float32, as in
the released model.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import torch

from ..config import VGGTConfig
from ..errors import UserError
from ..models.vggt.attention import MatchRatioProbe
from ..models.vggt.model import VGGT
from ..models.vggt.pose_encoding import pose_encoding_to_extri_intri
from ..models.vggt.preprocess import GridTransform, preprocess_images, to_uint8_rgb
from ..types import Frame, SubmapPrediction

logger = logging.getLogger(__name__)

_HALF_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def resolve_device(device: str) -> torch.device:
    """"auto" -> CUDA when available, else CPU; otherwise the named device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda was requested but no CUDA GPU is available; use --device cpu")
    return torch.device(device)


def resolve_compute_dtype(dtype: str, device: torch.device) -> torch.dtype:
    """Autocast dtype of the aggregator: float32 means no autocast."""
    if dtype not in ("auto", "fp32", "bf16", "fp16"):
        raise UserError(f"unknown VGGT dtype '{dtype}': use auto, fp32, bf16 or fp16")
    if dtype == "auto":
        if device.type != "cuda":
            return torch.float32
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    if dtype == "fp32":
        return torch.float32
    return _HALF_DTYPES[dtype]


class VGGTFrontend:
    """Frontend backed by our VGGT implementation.

    Args:
        config: device, dtype, preprocessing mode and weights (file or hub id).
        model: an already built :class:`VGGT` (e.g. with random weights in tests); when ``None``
            the weights named by ``config.weights`` are loaded on the first call.
        with_points: also return the point head's map (``SubmapPrediction.points``).
    """

    name = "vggt"
    requires_ground_truth = False

    def __init__(self, config: VGGTConfig, model: VGGT | None = None, with_points: bool = False) -> None:
        if config.preprocess_mode not in ("crop", "pad"):
            raise UserError(f"unknown VGGT preprocessing mode '{config.preprocess_mode}': use crop or pad")
        self.config = config
        self.device = resolve_device(config.device)
        self.compute_dtype = resolve_compute_dtype(config.dtype, self.device)
        self.with_points = with_points
        self.last_transforms: list[GridTransform] = []
        self._model = self._prepare(model) if model is not None else None

    def _prepare(self, model: VGGT) -> VGGT:
        model = model.to(self.device).eval()
        if self.compute_dtype != torch.float32 and self.device.type == "cuda":
            # Half-precision aggregator weights halve its memory; the heads stay float32.
            model.aggregator.to(self.compute_dtype)
        return model

    def prepare(self) -> None:
        """Load the weights now (before any frame is read), so a missing file fails fast."""
        _ = self.model

    @property
    def model(self) -> VGGT:
        """The model, loaded from ``config.weights`` on first use."""
        if self._model is None:
            from ..models.vggt.weights import load_vggt

            self._model = self._prepare(load_vggt(self.config.weights, device="cpu", dtype=torch.float32))
        return self._model

    @torch.inference_mode()
    def predict(self, images: torch.Tensor, match_pairs: Sequence[tuple[int, int]] = ()) -> dict[str, torch.Tensor]:
        """Raw model outputs for ``(S, 3, H, W)`` images in [0, 1] on the model's grid; with
        ``match_pairs`` also ``"match_ratios"`` ``(len(match_pairs),)`` (numpy) from the same pass."""
        model = self.model
        heads = ("camera", "depth", "point") if self.with_points else ("camera", "depth")
        images = images.to(self.device)
        use_autocast = self.compute_dtype != torch.float32
        probe = MatchRatioProbe(model.aggregator, match_pairs, len(images), self.config.match_layer) if match_pairs else None
        with torch.autocast(device_type=self.device.type, dtype=self.compute_dtype, enabled=use_autocast):
            if probe is None:
                return model(images, heads=heads)
            with probe:
                outputs = model(images, heads=heads)
        outputs["match_ratios"] = probe.ratios[0]
        return outputs

    def grid_colors(self, frame: Frame) -> np.ndarray:
        """``(H, W, 3)`` uint8 colours of ``frame`` on the model's grid (the preprocessing, without the model)."""
        images, _ = preprocess_images([frame.rgb], mode=self.config.preprocess_mode)
        return to_uint8_rgb(images)[0]

    def reconstruct(self, frames: Sequence[Frame], submap_id: int,
                    match_pairs: Sequence[tuple[int, int]] = ()) -> SubmapPrediction:
        """Reconstruct ``frames`` into one submap (the first frame's camera is the submap frame).

        Returns depth/confidence ``(S, H, W)`` float32, ``T_cam_submap`` ``(S, 3, 4)`` and ``K``
        ``(S, 3, 3)`` float64 and colours ``(S, H, W, 3)`` uint8, all on the model's grid
        ``(H, W)``; see :attr:`last_transforms` for the mapping from each input frame. With
        ``match_pairs`` (slot pairs), also their image-match ratios (``match_ratios``).
        """
        if len(frames) == 0:
            raise ValueError("reconstruct needs at least one frame")
        images, transforms = preprocess_images([frame.rgb for frame in frames], mode=self.config.preprocess_mode)
        self.last_transforms = transforms
        outputs = self.predict(images, match_pairs)
        height, width = images.shape[-2:]
        extrinsics, intrinsics = pose_encoding_to_extri_intri(outputs["pose_enc"][0].double().cpu(), (height, width))
        prediction = SubmapPrediction(
            depth=outputs["depth"][0, ..., 0].float().cpu().numpy(),
            confidence=outputs["depth_conf"][0].float().cpu().numpy(),
            T_cam_submap=extrinsics.numpy().astype(np.float64),
            K=intrinsics.numpy().astype(np.float64),
            colors=to_uint8_rgb(images),
            principal_point=np.tile([width / 2.0, height / 2.0], (len(frames), 1)),
        )
        if match_pairs:
            prediction.match_pairs = np.asarray(match_pairs, dtype=np.int64).reshape(-1, 2)
            prediction.match_ratios = np.asarray(outputs["match_ratios"], dtype=np.float32)
        if self.with_points:
            prediction.points = outputs["world_points"][0].float().cpu().numpy()
            prediction.points_confidence = outputs["world_points_conf"][0].float().cpu().numpy()
        return prediction
