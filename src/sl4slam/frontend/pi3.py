"""π³ / Pi3X frontend: one forward pass of π³ (``yyfz233/Pi3``) or Pi3X (``yyfz233/Pi3X``) per submap.

Frames are resized onto the model's grid as the authors' loader does (:mod:`sl4slam.models.pi3.preprocess`:
at most 255 000 pixels, sides multiples of 14, the first frame's aspect ratio, Lanczos) and every
output lives on that grid. From the model's local point maps, confidence logits and camera-to-world
poses (:mod:`sl4slam.models.pi3.cameras`):

- depth = the z of the local points; confidence = ``1 + exp(logit)`` (>= 1, VGGT's activation);
- ``T_cam_submap`` = each camera relative to the first (the model's own frame is arbitrary);
- ``K`` = principal point at the grid centre ``((W-1)/2, (H-1)/2)``, focal lengths by least squares
  from the frame's local points weighted by the confidence probability ``sigmoid(logit)``. Neither
  model predicts intrinsics (Pi3X's ray output is the direction of its local points), so ``K`` is
  recovered in both cases, also when Pi3X was given the intrinsics.

Pi3X accepts known intrinsics (``reconstruct(..., intrinsics=K)``, the frames' own pixels): they are
mapped onto the grid and given to the model as its ray condition; π³ ignores them. The loop check's
image-match ratio is not implemented for π³ (``scores_pairs`` is false): ``match_pairs`` is ignored.

Precision (``dtype``): "auto" is float32 on CPU and, as the authors run it, bf16 autocast on CUDA
(fp16 before compute capability 8) with float32 weights; the heads always run in float32.
Attention: the memory-efficient kernel (flash attention; a 17-frame submap at the native resolution
fits in a few GB on a CPU; decision: docs/decisions/memory-estimates.md). Memory: the convolutional heads of Pi3X
decode :data:`HEAD_CHUNK_FRAMES` frames at a time; with ``max_memory_gb`` the chunk is chosen per
submap from an estimate of the peak (:func:`estimate_peak_bytes`) and a submap that cannot fit is
refused with the largest size that would.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import torch

from ..errors import UserError
from ..models.pi3.cameras import (
    confidence_from_logits,
    depth_from_local_points,
    extrinsics_from_poses,
    grid_centre,
    intrinsics_from_local_points,
    probability_from_logits,
    to_model_intrinsics,
)
from ..models.pi3.memory import estimate_peak_bytes, plan_memory  # noqa: F401  (estimate_peak_bytes: API)
from ..models.pi3.model import VARIANTS, Pi3, Pi3X
from ..models.pi3.preprocess import (
    PIXEL_BUDGET,
    ResizeTransform,
    preprocess_images,
    resize_to_grid,
)
from ..models.pi3.weights import WEIGHTS_SOURCES
from ..models.precision import cuda_native_bf16, resolve_mode, settle_mode
from ..types import Frame, FrontendCapabilities, SubmapPrediction
from .device import resolve_device  # noqa: F401  (part of this module's API)

logger = logging.getLogger(__name__)

HEAD_CHUNK_FRAMES = 4
"""Frames Pi3X's convolutional heads decode at once (outputs do not depend on it)."""
CAPABILITIES = {
    "pi3": FrontendCapabilities(scores_pairs=False, needs_ground_truth=False, predicts_intrinsics=False,
                                accepts_intrinsics=False),
    "pi3x": FrontendCapabilities(scores_pairs=False, needs_ground_truth=False, predicts_intrinsics=False,
                                 accepts_intrinsics=True),
}
"""What each variant's frontend can do (the class attribute is π³'s; a Pi3X instance has its own)."""

#: Autocast dtype of the forward for each ``dtype`` (``None``: plain float32).
AUTOCAST_DTYPES: dict[str, torch.dtype | None] = {"fp32": None, "float32": None, "bf16": torch.bfloat16,
                                                  "bfloat16": torch.bfloat16, "fp16": torch.float16,
                                                  "float16": torch.float16}


def resolve_compute_dtype(dtype: str) -> torch.dtype | None:
    """Autocast dtype of the forward (``None``: plain float32) for a concrete ``dtype`` ("fp32",
    "bf16", "fp16"; "auto" is settled before: bf16 on CUDA GPUs of compute capability 8 or more, fp16
    on older ones, float32 on the CPU, :func:`settle_dtype`)."""
    return resolve_mode(dtype, AUTOCAST_DTYPES, f"unknown π³ dtype '{dtype}': use fp32, bf16 or fp16")


def settle_dtype(dtype: str, device: str) -> str:
    """The concrete mode of the ``dtype`` setting on ``device`` (``sl4slam.models.precision.settle_mode``)."""
    return settle_mode(dtype, device, tuple(AUTOCAST_DTYPES), "π³", bf16=cuda_native_bf16)


class Pi3Frontend:
    """Frontend backed by our π³ / Pi3X implementation.

    Args:
        variant: "pi3" or "pi3x" (also the frontend's ``name``).
        weights: local file / folder or hub id; ``None``: the variant's hub id
            (``yyfz233/Pi3``, ``yyfz233/Pi3X``).
        device: "cpu", "cuda", "cuda:1" ...
        dtype: "fp32", "bf16" or "fp16" (autocast dtype; weights stay float32).
        max_memory_gb: plan each submap's forward to fit (0: no planning).
        model: an already built :class:`~sl4slam.models.pi3.Pi3` / :class:`~sl4slam.models.pi3.Pi3X`
            (e.g. random weights in tests); ``None``: ``weights`` are loaded by :meth:`prepare` or
            on the first call.
    """

    requires_ground_truth = False
    capabilities = CAPABILITIES["pi3"]

    def __init__(self, variant: str = "pi3", weights: str | None = None, device: str = "cpu", dtype: str = "fp32",
                 max_memory_gb: float = 0.0, model: torch.nn.Module | None = None) -> None:
        if variant not in VARIANTS:
            raise UserError(f"unknown π³ variant '{variant}': use one of {', '.join(VARIANTS)}")
        if max_memory_gb < 0:
            raise UserError(f"max_memory_gb must be >= 0 (0: no planning), got {max_memory_gb}")
        self.name = variant
        self.variant = variant
        self.capabilities = CAPABILITIES[variant]
        self.weights = weights or WEIGHTS_SOURCES[variant].repo_id
        self.device = resolve_device(device)
        self.compute_dtype = resolve_compute_dtype(dtype)
        self.max_memory_gb = float(max_memory_gb)
        self.budget = PIXEL_BUDGET
        self.last_transforms: list[ResizeTransform] = []
        self._model = self._prepare(model) if model is not None else None

    def _prepare(self, model: torch.nn.Module) -> Pi3 | Pi3X:
        expected = Pi3X if self.variant == "pi3x" else Pi3
        if not isinstance(model, expected):
            raise UserError(f"the {self.variant} frontend needs a {expected.__name__} model, got {type(model).__name__}")
        model = model.eval().to(self.device)
        model.head_chunk_frames = HEAD_CHUNK_FRAMES
        return model

    def prepare(self) -> None:
        """Load the weights now (before any frame is read): ``MissingWeightsError`` (one line) when they
        are not available."""
        _ = self.model

    @property
    def model(self) -> Pi3 | Pi3X:
        """The model, loaded from :attr:`weights` on first use (Pi3X keeps only its intrinsics branch)."""
        if self._model is None:
            from ..models.pi3.weights import load_pi3

            conditions = ("intrinsics",) if self.variant == "pi3x" else ()
            model = load_pi3(self.weights, self.variant, device="cpu", dtype=torch.float32, kernel="efficient",
                             conditions=conditions)
            self._model = self._prepare(model)
        return self._model

    def weight_bytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.model.parameters())

    def head_chunk(self, frames: int, height: int, width: int) -> int:
        """Frames the convolutional heads decode at once for a submap of ``frames`` images on an
        ``height`` x ``width`` grid.

        Raises:
            UserError: ``max_memory_gb`` is set and the submap cannot fit (names the largest that can).
        """
        if self.max_memory_gb <= 0:
            return HEAD_CHUNK_FRAMES
        plan = plan_memory(self.model.config, self.weight_bytes(), self.max_memory_gb, frames, height, width)
        return plan.head_chunk_frames

    @torch.inference_mode()
    def predict(self, images: torch.Tensor, intrinsics: np.ndarray | None = None) -> dict[str, torch.Tensor]:
        """Raw model outputs for ``(S, 3, H, W)`` images in [0, 1] on the model's grid; ``intrinsics``
        ``(S, 3, 3)`` (Pi3X only) in the authors' pixel convention (:func:`to_model_intrinsics`)."""
        model = self.model
        model.head_chunk_frames = self.head_chunk(images.shape[0], *images.shape[-2:])
        images = images.to(self.device)
        dtype = self.compute_dtype
        with torch.autocast(device_type=self.device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            if intrinsics is not None and isinstance(model, Pi3X):
                K = torch.as_tensor(np.asarray(intrinsics), dtype=torch.float32, device=self.device)[None]
                return model(images[None], intrinsics=K)
            return model(images[None])

    def grid_colors(self, frame: Frame) -> np.ndarray:
        """``(H, W, 3)`` uint8 colours of ``frame`` on the model's grid (the preprocessing alone)."""
        return resize_to_grid([frame.rgb], self.budget)[0][0]

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, match_pairs: Sequence[tuple[int, int]] = (),
                    intrinsics: np.ndarray | None = None) -> SubmapPrediction:
        """Reconstruct ``frames`` into one submap (the first frame's camera is the submap frame).

        Args:
            frames: the submap's frames, in order.
            submap_id: unused (the model is deterministic).
            match_pairs: ignored (no image-match score; ``capabilities.scores_pairs`` is false).
            intrinsics: optional ``(S, 3, 3)`` float64 known K of each input frame in its own pixels
                (pixel centres at integers); Pi3X is conditioned on them, π³ ignores them.

        Returns:
            depth / confidence ``(S, H, W)`` float32, ``T_cam_submap`` ``(S, 3, 4)`` and ``K`` ``(S, 3, 3)``
            float64, colours ``(S, H, W, 3)`` uint8 and the principal point ``(S, 2)`` (the grid centre),
            all on the model's grid; :attr:`last_transforms` maps each input frame onto it.
        """
        if len(frames) == 0:
            raise ValueError("reconstruct needs at least one frame")
        images, colours, transforms = preprocess_images([frame.rgb for frame in frames], self.budget, device=self.device)
        self.last_transforms = transforms
        height, width = images.shape[-2:]
        model_K = None
        if intrinsics is not None and self.capabilities.accepts_intrinsics:
            K = np.asarray(intrinsics, dtype=np.float64)
            if K.shape != (len(frames), 3, 3):
                raise ValueError(f"intrinsics must be ({len(frames)}, 3, 3), got {K.shape}")
            model_K = to_model_intrinsics(np.stack([t.intrinsics_to_output(k) for t, k in zip(transforms, K)]))
        outputs = self.predict(images, model_K)
        local_points = outputs["local_points"][0].float().cpu().numpy()
        logits = outputs["conf"][0, ..., 0].float().cpu().numpy()
        poses = outputs["camera_poses"][0].double().cpu().numpy()
        return SubmapPrediction(
            depth=depth_from_local_points(local_points),
            confidence=confidence_from_logits(logits),
            T_cam_submap=extrinsics_from_poses(poses),
            K=intrinsics_from_local_points(local_points, probability_from_logits(logits)),
            colors=colours,
            principal_point=np.tile(grid_centre(height, width), (len(frames), 1)),
            image_to_grid=np.stack([t.intrinsics_to_output(np.eye(3)) for t in transforms]),
        )


def registry_entry(variant: str):
    """π³ (``pi3``) or Pi3X (``pi3x``) in the frontend registry (``sl4slam.registry``)."""
    from ..models.pi3.weights import PARAMETERS, convert_checkpoint
    from ..registry import FrontendEntry

    def build(resolved) -> Pi3Frontend:
        model = resolved.config.model
        return Pi3Frontend(variant=variant, weights=model.weights,
                           device=resolved.device, dtype=model.dtype, max_memory_gb=model.max_memory_gb)

    def convert(src: str, dst: str, dtype: str):
        return convert_checkpoint(src, dst, variant=variant, dtype=dtype)

    def recognizes(keys) -> bool:
        from ..models.checkpoint import describe_checkpoint

        word = "a Pi3X checkpoint" if variant == "pi3x" else "a π³ (Pi3) checkpoint"
        return describe_checkpoint(keys).startswith(word)

    description = ("Pi3X (Wang et al., 2025): π³'s successor; local points and cameras of every frame, takes a known "
                   "calibration" if variant == "pi3x" else
                   "π³ (Wang et al., 2025): permutation-equivariant local points and cameras of every frame")
    return FrontendEntry(name=variant, build=build, capabilities=CAPABILITIES[variant], description=description,
                         weights=WEIGHTS_SOURCES[variant], licence="CC BY-NC 4.0 (non-commercial)",
                         parameters=PARAMETERS[variant], recognizes=recognizes, convert=convert,
                         cpu_work=CPU_WORK[variant], settle_dtype=settle_dtype)


CPU_WORK = {"pi3": 4374.0, "pi3x": 4374.0}
"""GFLOP-equivalents per frame on a CPU, float32 (``sl4slam.frontend.cost``; docs/decisions/cpu-estimate.md)."""
