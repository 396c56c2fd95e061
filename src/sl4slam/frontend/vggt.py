"""VGGT frontend: one forward pass of VGGT over a submap's frames.

Frames are resized onto VGGT's grid (width 518 in "crop" mode, 518x518 in "pad" mode, sides
multiples of 14; see :mod:`sl4slam.models.vggt.preprocess`) and every output lives on that grid:
depth, confidence, the intrinsics and the colours. How each input frame maps onto the grid is
kept in :attr:`VGGTFrontend.last_transforms` (scale and offset per frame, plus the region that is
image rather than padding).

Loop check: asked for ``match_pairs``, the frontend also returns VGGT-SLAM 2.0's image-match ratio of
each pair of slots, read from the attention of global block ``VGGTConfig.match_layer`` during the same
forward pass (``sl4slam.models.vggt.attention``).

Precision (``--dtype``, :mod:`sl4slam.models.vggt.precision`): "auto" is float32 on CPU and bf16
(fp16 where bf16 is not supported) on CUDA; half precision stores the aggregator's weights in that
dtype and runs it under autocast; "int8" (CPU) quantizes the aggregator's linear layers. The heads
always run in float32, as in the released model.

Memory: the dense heads decode ``head_chunk_frames`` frames at a time; with ``--max-memory GB`` the
chunk is chosen per submap from an estimate of the peak (:mod:`sl4slam.models.vggt.memory`), and a
submap that cannot fit is refused with the largest size that would.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import torch

from .settings import ModelConfig
from ..errors import UserError
from ..models.vggt.attention import MatchRatioProbe
from ..models.vggt.memory import (
    GIB,
    estimate_peak_bytes,
    largest_fitting_frames,
    plan_memory,
)
from ..models.vggt.model import VGGT
from ..models.vggt.pose_encoding import pose_encoding_to_extri_intri
from ..models.precision import settle_mode
from ..models.vggt.precision import MODES, Precision, apply_precision, resolve_precision
from ..models.vggt.preprocess import GridTransform, channels_last, preprocess_uint8
from ..registry import FrontendEntry
from ..types import Frame, FrontendCapabilities, SubmapPrediction
from .device import resolve_device  # noqa: F401  (part of this module's API)

logger = logging.getLogger(__name__)

# Largest image side on VGGT's grid (both preprocessing modes): the worst case for memory.
_GRID_SIDE = 518


def resolve_mode(dtype: str, device: torch.device) -> Precision:
    """The precision of the concrete mode ``dtype`` on ``device`` (one line on bad input)."""
    try:
        return resolve_precision(dtype, device)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def resolve_compute_dtype(dtype: str, device: torch.device) -> torch.dtype:
    """Autocast dtype of the aggregator: float32 means no autocast (also for int8 linears)."""
    precision = resolve_mode(dtype, device)
    return precision.autocast or torch.float32


def grid_affine(transform: GridTransform) -> np.ndarray:
    """``(3, 3)`` affine from input pixels to grid pixels, integer coordinates at pixel centres in
    both (the transform's continuous coordinates put pixel ``i``'s centre at ``i + 0.5``)."""
    A = np.eye(3)
    A[0, 0], A[1, 1] = transform.scale_x, transform.scale_y
    A[0, 2] = 0.5 * transform.scale_x + transform.offset_x - 0.5
    A[1, 2] = 0.5 * transform.scale_y + transform.offset_y - 0.5
    return A


class VGGTFrontend:
    """Frontend backed by our VGGT implementation.

    Args:
        config: the settled ``[model]`` section: dtype (a concrete mode), preprocessing mode, memory
            budget and weights (file or hub id).
        model: an already built :class:`VGGT` (e.g. with random weights in tests); when ``None``
            the weights named by ``config.weights`` are loaded on the first call.
        with_points: also return the point head's map (``SubmapPrediction.points``).
        match_scores: the loop check will ask for image-match ratios (``config.match_layer`` must
            then exist in the model, checked when the weights load).
        device: "cpu", "cuda" or "cuda:N".
        submap_frames: the most frames a submap holds (new keyframes, the shared and the loop
            frames); on a GPU without ``--max-memory``, a submap that cannot fit the GPU's memory is
            refused when the weights load, before any frame is read.
    """

    name = "vggt"
    capabilities = FrontendCapabilities(scores_pairs=True, predicts_intrinsics=True)

    def __init__(self, config: ModelConfig, model: VGGT | None = None, with_points: bool = False,
                 match_scores: bool = False, device: str = "cpu", submap_frames: int = 0) -> None:
        if config.preprocess_mode not in ("crop", "pad"):
            raise UserError(f"unknown VGGT preprocessing mode '{config.preprocess_mode}': use crop or pad")
        self.config = config
        self.device = resolve_device(device)
        self.precision = resolve_mode(config.dtype, self.device)
        self.compute_dtype = self.precision.autocast or torch.float32
        self.with_points = with_points
        self.heads = ("camera", "depth", "point") if with_points else ("camera", "depth")
        self.last_transforms: list[GridTransform] = []
        self.match_scores = match_scores
        self.submap_frames = int(submap_frames)
        self._model = self._prepare(model) if model is not None else None

    def _prepare(self, model: VGGT) -> VGGT:
        layers = len(model.aggregator.global_blocks)
        if self.match_scores and not 0 <= self.config.match_layer < layers:
            raise UserError(f"--match-layer {self.config.match_layer} does not exist: the model has {layers} "
                            f"global attention layers (0-{layers - 1}); pick one of them, or switch the attention "
                            "loop check off with --loop-verify-attention off")
        # Weights are converted on the CPU, one copy each, before they move to the device.
        model = apply_precision(model.eval(), self.precision).to(self.device)
        if self.device.type == "cuda" and self.config.max_memory_gb <= 0 and self.submap_frames:
            # no budget given: the GPU's memory is the budget; a submap that cannot fit is refused now
            free, _ = torch.cuda.mem_get_info(self.device)
            budget = (free + torch.cuda.memory_allocated(self.device)) / GIB
            plan_memory(model.config, self.precision, budget, self.submap_frames, _GRID_SIDE, _GRID_SIDE,
                        self.config.head_chunk_frames, "cuda", self.heads,
                        budget_source=f"the GPU ({torch.cuda.get_device_name(self.device)}) has")
        if self.config.max_memory_gb > 0:
            largest = largest_fitting_frames(
                model.config, self.precision, int(self.config.max_memory_gb * GIB), _GRID_SIDE, _GRID_SIDE,
                self.device.type, self.heads)
            logger.info("VGGT %s on %s: the largest submap that fits in --max-memory %g GiB is %d frames (at %dx%d)",
                        self.precision.mode, self.device.type, self.config.max_memory_gb, largest, _GRID_SIDE, _GRID_SIDE)
        return model

    def prepare(self) -> None:
        """Load the weights now (before any frame is read), so a missing file fails fast."""
        _ = self.model

    @property
    def model(self) -> VGGT:
        """The model, loaded from ``config.weights`` on first use."""
        if self._model is None:
            from ..models.vggt.weights import load_vggt

            # The checkpoint's own dtype (memory-mapped): each weight is converted once, in _prepare.
            model = load_vggt(self.config.weights, device="cpu", dtype=None)
            if not self.with_points:
                model.point_head = None  # its weights are never read
            self._model = self._prepare(model)
        return self._model

    def head_chunk(self, frames: int, height: int, width: int) -> int:
        """Frames the dense heads decode at once for a submap of ``frames`` images ``height`` x ``width``.

        Raises:
            UserError: ``--max-memory`` is set and the submap cannot fit (names the largest that can).
        """
        if self.config.max_memory_gb <= 0:
            return self.config.head_chunk_frames
        plan = plan_memory(self.model.config, self.precision, self.config.max_memory_gb, frames, height, width,
                           self.config.head_chunk_frames, self.device.type, self.heads)
        return plan.head_chunk_frames

    def estimated_peak_bytes(self, frames: int, height: int, width: int) -> int:
        """Estimated peak memory of one forward (see :mod:`sl4slam.models.vggt.memory`)."""
        chunk = self.head_chunk(frames, height, width)
        return estimate_peak_bytes(self.model.config, self.precision, frames, height, width, chunk,
                                   self.device.type, self.heads)

    @torch.inference_mode()
    def predict(self, images: torch.Tensor, match_pairs: Sequence[tuple[int, int]] = ()) -> dict[str, torch.Tensor]:
        """Raw model outputs for ``(S, 3, H, W)`` images in [0, 1] on the model's grid; with
        ``match_pairs`` also ``"match_ratios"`` ``(len(match_pairs),)`` (numpy) from the same pass."""
        model = self.model
        model.set_head_chunk_frames(self.head_chunk(images.shape[0], *images.shape[-2:]))
        images = images.to(self.device)
        autocast = self.precision.autocast
        probe = MatchRatioProbe(model.aggregator, match_pairs, len(images), self.config.match_layer) if match_pairs else None
        with torch.autocast(device_type=self.device.type, dtype=autocast or torch.float32, enabled=autocast is not None):
            if probe is None:
                return model(images, heads=self.heads)
            with probe:
                outputs = model(images, heads=self.heads)
        outputs["match_ratios"] = probe.ratios[0]
        return outputs

    def grid_colors(self, frame: Frame) -> np.ndarray:
        """``(H, W, 3)`` uint8 colours of ``frame`` on the model's grid (the preprocessing, without the model)."""
        grid, _ = preprocess_uint8([frame.rgb], mode=self.config.preprocess_mode)
        return channels_last(grid)[0]

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
        grid, transforms = preprocess_uint8([frame.rgb for frame in frames], mode=self.config.preprocess_mode)
        self.last_transforms = transforms
        # uint8 to the device, then / 255 there (a quarter of the bytes to copy, no host float pass)
        images = grid.to(self.device).to(torch.float32).div(255)
        outputs = self.predict(images, match_pairs)
        height, width = images.shape[-2:]
        extrinsics, intrinsics = pose_encoding_to_extri_intri(outputs["pose_enc"][0].double().cpu(), (height, width))
        prediction = SubmapPrediction(
            depth=outputs["depth"][0, ..., 0].float().cpu().numpy(),
            confidence=outputs["depth_conf"][0].float().cpu().numpy(),
            T_cam_submap=extrinsics.numpy().astype(np.float64),
            K=intrinsics.numpy().astype(np.float64),
            colors=channels_last(grid),
            principal_point=np.tile([width / 2.0, height / 2.0], (len(frames), 1)),
            image_to_grid=np.stack([grid_affine(t) for t in transforms]),
        )
        if match_pairs:
            prediction.match_pairs = np.asarray(match_pairs, dtype=np.int64).reshape(-1, 2)
            prediction.match_ratios = np.asarray(outputs["match_ratios"], dtype=np.float32)
        if self.with_points:
            prediction.points = outputs["world_points"][0].float().cpu().numpy()
            prediction.points_confidence = outputs["world_points_conf"][0].float().cpu().numpy()
        return prediction


def settle_dtype(dtype: str, device: str) -> str:
    """The concrete precision mode of the ``dtype`` setting on ``device`` ("int8": the CPU only)."""
    mode = settle_mode(dtype, device, MODES, "VGGT")
    if mode == "int8" and torch.device(device).type != "cpu":
        raise UserError("--dtype int8 runs on the CPU only; use bf16 on a GPU")
    return mode


def registry_entry() -> FrontendEntry:
    """VGGT-1B in the frontend registry (``sl4slam.registry``)."""
    from ..models.hub import VGGT_WEIGHTS

    def build(resolved) -> VGGTFrontend:
        submap = resolved.config.submap
        return VGGTFrontend(resolved.config.model, with_points=submap.use_point_head,
                            match_scores=resolved.attention_check, device=resolved.device,
                            submap_frames=submap.size + submap.overlap + submap.w_loop * submap.loop_frames)

    return FrontendEntry(
        name="vggt", build=build, capabilities=VGGTFrontend.capabilities,
        description="VGGT-1B (Wang et al., CVPR 2025): cameras, depth and points of every frame; the paper's model",
        weights=VGGT_WEIGHTS,
        licence="CC BY-NC 4.0 (facebook/VGGT-1B; facebook/VGGT-1B-Commercial is under the VGGT License, commercial use allowed)",
        parameters=VGGT_PARAMETERS, recognizes=lambda keys: "aggregator.camera_token" in keys,
        convert=_convert, cpu_work=CPU_WORK, settle_dtype=settle_dtype)


def _convert(src: str, dst: str, dtype: str):
    from ..models.vggt.weights import convert_checkpoint

    return convert_checkpoint(src, dst, dtype=dtype)


VGGT_PARAMETERS = 1_190_596_120

CPU_WORK = 6800.0
"""GFLOP-equivalents per frame on a CPU, float32 (``sl4slam.frontend.cost``; docs/decisions/cpu-estimate.md)."""
"""Parameters of the VGGT-1B we build: the checkpoint's 1,256,537,516 without the tracking head's
65,941,396 (``tests/test_vggt_model.py`` counts them)."""
