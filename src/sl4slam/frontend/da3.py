"""Depth Anything 3 frontend: one forward of DA3 (any size) over a submap's frames.

Frames are put on DA3's grid by the authors' input processing (longer side 504, sides multiples
of 14; :mod:`sl4slam.models.da3.preprocess`) and every output lives on that grid: depth, confidence
(``1 + exp``, >= 1, unchanged), the intrinsics (the model's own prediction) and the colours (the
resampled input). DA3 expresses its cameras in the frame of a reference view it picks itself; they are
re-expressed relative to the first frame (``T_cam_submap``, :mod:`sl4slam.models.da3.cameras`).

Cameras (``cameras``): "head" takes them from the camera decoder (the authors' default), "rays" fits
them to the ray maps (their ``use_ray_pose``: slower; seeded, so runs repeat exactly).

Known intrinsics (``reconstruct(..., intrinsics=K)``, ``K`` in each frame's own pixels): DA3's camera
encoder takes complete cameras (pose and calibration) only, so the window runs twice: first without
cameras, for poses; then with those poses (normalised as the authors' API does) and the known ``K``
mapped onto the grid, through the camera encoder. The second pass's outputs are returned; the cost is
two forwards.

Precision (``dtype``): "auto" is float32 on a CPU (the authors' API runs fp16 there; decision:
docs/decisions/int8-cpu.md) and, on CUDA, bf16 where supported else fp16 for the backbone, with the
camera modules and the head in float32, as the authors' API.

Memory: the head decodes up to 8 frames at a time (as the released code); with ``max_memory_gb`` the
chunk is chosen per submap from an estimate of the peak (:mod:`sl4slam.models.da3.memory`), and a
submap that cannot fit is refused with the largest size that would.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch

from ..errors import UserError
from ..models.da3.camera import as_homogeneous, normalize_extrinsics
from ..models.da3.cameras import submap_arrays
from ..models.da3.config import released
from ..models.da3.memory import GIB, largest_fitting_frames, plan_memory
from ..models.da3.model import DepthAnything3
from ..models.da3.preprocess import (
    PROCESS_RES,
    Preprocessed,
    grid_uint8,
    intrinsics_on_grid,
    preprocess_images,
)
from ..models.da3.weights import resolve_precision
from ..models.precision import settle_mode
from ..models.vggt.preprocess import GridTransform
from ..registry import FrontendEntry
from ..types import Frame, FrontendCapabilities, SubmapPrediction
from .device import resolve_device  # noqa: F401  (part of this module's API)
from .vggt import grid_affine

logger = logging.getLogger(__name__)

CAMERA_SOURCES = ("head", "rays")
#: Seed of the ray fit's random draws (every window draws the same way: runs repeat exactly).
RAY_SEED = 0


class DA3Frontend:
    """Frontend backed by our Depth Anything 3 implementation.

    Args:
        size: "small", "base", "large", "large-1.1", "giant" or "giant-1.1".
        weights: file or hub id; ``None``: the size's release (``depth-anything/DA3-<SIZE>``).
        device: "cpu", "cuda", ...
        dtype: "fp32", "bf16" or "fp16" (the backbone's compute precision).
        cameras: "head" (camera decoder) or "rays" (fitted to the ray maps).
        max_memory_gb: plan the head's chunk so a forward fits this budget (0: 8 frames at a time).
        model: an already built model (tests); ``None`` loads ``weights`` on first use.
        process_res: the longer side of the grid (504, the authors' default).
    """

    requires_ground_truth = False
    capabilities = FrontendCapabilities(scores_pairs=False, needs_ground_truth=False, predicts_intrinsics=True,
                                        accepts_intrinsics=True)

    def __init__(self, size: str = "small", weights: str | None = None, device: str = "cpu", dtype: str = "fp32",
                 cameras: str = "head", max_memory_gb: float = 0.0, model: torch.nn.Module | None = None,
                 process_res: int = PROCESS_RES) -> None:
        try:
            self.release = released(size)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        if cameras not in CAMERA_SOURCES:
            raise UserError(f"unknown Depth Anything 3 camera source {cameras!r}: use head or rays")
        if max_memory_gb < 0:
            raise UserError(f"--max-memory must be >= 0 GiB, got {max_memory_gb:g}")
        self.name = self.release.name
        self.weights = weights or self.release.repo_id
        self.device = resolve_device(device)
        self.dtype = dtype
        self.autocast_dtype = resolve_precision(dtype)
        self.cameras = cameras
        self.max_memory_gb = float(max_memory_gb)
        self.process_res = int(process_res)
        self.head_chunk_frames = 8
        self.last_transforms: list[GridTransform] = []
        self._model = self._prepare(model) if model is not None else None

    def _prepare(self, model: torch.nn.Module) -> DepthAnything3:
        model = model.eval().float().to(self.device)
        model.autocast_dtype = self.autocast_dtype
        if self.max_memory_gb > 0:
            side = self.process_res
            largest = largest_fitting_frames(model.config, int(self.max_memory_gb * GIB), side, side,
                                             self.autocast_dtype is not None, self.device.type,
                                             rays=self.cameras == "rays")
            logger.info("%s on %s: the largest submap that fits in --max-memory %g GiB is %d frames (at %dx%d)",
                        self.name, self.device.type, self.max_memory_gb, largest, side, side)
        return model

    def prepare(self) -> None:
        """Load the weights now (before any frame is read), so a missing file fails fast."""
        _ = self.model

    @property
    def model(self) -> DepthAnything3:
        """The model, loaded from ``weights`` on first use."""
        if self._model is None:
            from ..models.da3.weights import load_da3

            self._model = self._prepare(load_da3(self.weights, self.release.size, device="cpu", dtype=self.dtype))
        return self._model

    def head_chunk(self, frames: int, height: int, width: int) -> int:
        """Frames the head decodes at once for a window (``UserError`` when ``max_memory_gb`` cannot hold it)."""
        if self.max_memory_gb <= 0:
            return self.head_chunk_frames
        plan = plan_memory(self.model.config, self.max_memory_gb, frames, height, width, self.head_chunk_frames,
                           self.autocast_dtype is not None, self.device.type, rays=self.cameras == "rays")
        return plan.head_chunk_frames

    def preprocess(self, frames: Sequence[Frame]) -> Preprocessed:
        """The frames on the model's grid (images, colours and the mapping of each frame)."""
        return preprocess_images([frame.rgb for frame in frames], self.process_res, device=self.device)

    def grid_colors(self, frame: Frame) -> np.ndarray:
        """``(H, W, 3)`` uint8 colours of ``frame`` on the model's grid (the preprocessing, without the model)."""
        return grid_uint8([frame.rgb], self.process_res)[0][0]

    def _generator(self) -> torch.Generator:
        return torch.Generator(device=self.device).manual_seed(RAY_SEED)

    @torch.inference_mode()
    def predict(self, images: torch.Tensor, intrinsics: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Raw model outputs (batch of one) for normalised images ``(S, 3, H, W)`` on the grid, conditioned
        on ``intrinsics`` ``(S, 3, 3)`` on the grid when given (two passes; see the module docstring)."""
        model = self.model
        model.set_head_chunk_frames(self.head_chunk(images.shape[0], *images.shape[-2:]))
        images = images[None].to(self.device)
        outputs = model(images, cameras=self.cameras, generator=self._generator())
        if intrinsics is None:
            return outputs
        poses = normalize_extrinsics(as_homogeneous(outputs["extrinsics"]))
        known = intrinsics[None].to(device=self.device, dtype=torch.float32)
        return model(images, poses, known, cameras=self.cameras, generator=self._generator())

    def reconstruct(self, frames: Sequence[Frame], submap_id: int, match_pairs: Sequence[tuple[int, int]] = (),
                    intrinsics: np.ndarray | None = None) -> SubmapPrediction:
        """Reconstruct ``frames`` into one submap (the first frame's camera is the submap frame).

        Args:
            frames: the window, in order.
            submap_id: unused (the model is deterministic).
            match_pairs: not scored (``capabilities.scores_pairs`` is false); ignored.
            intrinsics: optional ``(S, 3, 3)`` float64 known ``K`` of each frame in its own pixels.

        Returns:
            depth / confidence ``(S, H, W)`` float32, ``T_cam_submap`` ``(S, 3, 4)`` and ``K`` ``(S, 3, 3)``
            float64, colours ``(S, H, W, 3)`` uint8 and the principal point ``(W/2, H/2)``, on the grid
            ``(H, W)``; :attr:`last_transforms` maps each frame onto it.
        """
        if len(frames) == 0:
            raise ValueError("reconstruct needs at least one frame")
        batch = self.preprocess(frames)
        self.last_transforms = batch.transforms
        known = None
        if intrinsics is not None:
            intrinsics = np.asarray(intrinsics, dtype=np.float64)
            if intrinsics.shape != (len(frames), 3, 3):
                raise ValueError(f"expected intrinsics of shape ({len(frames)}, 3, 3), got {intrinsics.shape}")
            known = torch.from_numpy(np.stack([intrinsics_on_grid(K, t) for K, t in zip(intrinsics, batch.transforms)]))
        outputs = self.predict(batch.images, known)
        arrays = submap_arrays(*(outputs[k][0].float().cpu().numpy() for k in ("depth", "depth_conf", "extrinsics",
                                                                                "intrinsics")))
        return SubmapPrediction(depth=arrays["depth"], confidence=arrays["confidence"],
                                T_cam_submap=arrays["T_cam_submap"], K=arrays["K"], colors=batch.colors,
                                principal_point=arrays["principal_point"],
                                image_to_grid=np.stack([grid_affine(t) for t in batch.transforms]))


def registry_entry(size: str):
    """One Depth Anything 3 size in the frontend registry (``sl4slam.registry``): ``da3-<size>``."""
    from ..models.da3.weights import WEIGHTS_SOURCES, parameter_counts

    release = released(size)

    def build(resolved) -> DA3Frontend:
        model = resolved.config.model
        return DA3Frontend(size=release.size, weights=model.weights,
                           device=resolved.device, dtype=model.dtype, cameras=model.cameras,
                           max_memory_gb=model.max_memory_gb)

    licence = ("Apache-2.0" if release.licence.lower().startswith("apache") else "CC BY-NC 4.0 (non-commercial)")
    return FrontendEntry(
        name=release.name, build=build, capabilities=DA3Frontend.capabilities,
        description=(f"Depth Anything 3 {release.size.upper()} (Lin et al., 2025): depth, rays and cameras of every "
                     "frame; takes a known calibration"),
        weights=WEIGHTS_SOURCES[release.size], licence=licence, parameters=parameter_counts()[release.size],
        recognizes=_recognizer(release.architecture), convert=_converter(release.size),
        cpu_work=CPU_WORK[release.architecture], settle_dtype=settle_dtype)


def settle_dtype(dtype: str, device: str) -> str:
    """The concrete precision mode of the ``dtype`` setting (any case) on ``device``."""
    from ..models.da3.weights import PRECISIONS

    return settle_mode(dtype.lower(), device, PRECISIONS, "Depth Anything 3")


CPU_WORK = {"small": 306.0, "base": 722.0, "large": 2152.0, "giant": 5601.0}
"""GFLOP-equivalents per frame on a CPU, float32 (``sl4slam.frontend.cost``; docs/decisions/cpu-estimate.md)."""


def _converter(size: str):
    def convert(src: str, dst: str, dtype: str):
        from ..models.da3.weights import convert_checkpoint

        return convert_checkpoint(src, dst, size=size, dtype=dtype)

    return convert


_SIZE_WORDS = {"small": "Small checkpoint", "base": "Base checkpoint", "large": "Large checkpoint",
               "giant": "Giant checkpoint"}


def _recognizer(architecture: str):
    """Whether a state dict (names with shapes) is a released DA3 checkpoint of ``architecture``
    (the sizes differ in width only: ``sl4slam.models.checkpoint.CHECKPOINT_KINDS``)."""
    from ..models.checkpoint import describe_checkpoint

    def recognizes(keys) -> bool:
        return _SIZE_WORDS[architecture] in describe_checkpoint(keys)

    return recognizes
