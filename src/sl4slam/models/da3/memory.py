"""Peak-memory estimate of a Depth Anything 3 forward, and the head chunk that fits a budget.

The estimate adds the tensors alive at the peak, each counted from its shape (S frames of
``N = 1 + h*w`` tokens of width C at ``H x W`` pixels):

* the weights (float32: the parameters stay float32 in every precision mode);
* the backbone's kept outputs: four ``2C`` outputs per token and the last one's raw ``[local,
  global]`` tokens, float32 (:data:`KEPT_WIDTHS` widths of C);
* the larger of two phases: a backbone block at work (residual stream, norms, qkv, rotated q / k,
  attention output, the MLP's hidden layer before and after its activation: :data:`BACKBONE_WIDTHS`
  widths of C per token, at the compute precision), or the head decoding a chunk of frames
  (:data:`HEAD_IMAGE_MAPS` maps of ``features / 2`` channels at the image size and
  :data:`HEAD_FINE_MAPS` maps of ``features`` channels at 8x the patch grid per frame, float32;
  the ray branch, when it runs, doubles the fine maps);
* the depth and confidence of every frame, and on a CPU the interpreter and libraries
  (:data:`CPU_RUNTIME_BYTES`).

The multipliers were set from measured peaks and rounded up, so the estimate lies above them
(decision: docs/decisions/memory-estimates.md).
"""

from __future__ import annotations

import functools
import json

from .. import memory
from ..memory import GIB, MemoryPlan, PeakEstimate, submap_too_large  # noqa: F401  (GIB: part of this module's API)
from .config import DA3Config

KEPT_WIDTHS = 10.0
BACKBONE_WIDTHS = 16.0
HEAD_IMAGE_MAPS = 1.5
HEAD_FINE_MAPS = 3.3
CPU_RUNTIME_BYTES = 512 * 2**20


@functools.lru_cache(maxsize=16)
def _parameter_bytes(config_json: str) -> int:
    from .model import count_parameters

    return 4 * count_parameters(DA3Config.from_dict(json.loads(config_json)))


def estimate_peak_bytes(config: DA3Config, frames: int, height: int, width: int, head_chunk: int = 8,
                        half_precision: bool = False, device_type: str = "cpu", rays: bool = False) -> int:
    """Upper estimate of one forward's peak for ``frames`` images ``height`` x ``width`` (CPU: resident
    set size; CUDA: allocated memory, weights included); ``rays``: the ray branch runs too."""
    patch = config.patch_size
    rows, cols = height // patch, width // patch
    token_width = frames * (1 + rows * cols) * config.embed_dim
    kept = 4 * KEPT_WIDTHS * token_width
    backbone = (2 if half_precision else 4) * BACKBONE_WIDTHS * config.mlp_ratio / 4.0 * token_width
    chunk = min(max(int(head_chunk), 1), frames)
    fine_maps = HEAD_FINE_MAPS * (2 if rays else 1)
    per_frame_head = 4 * (HEAD_IMAGE_MAPS * config.head_features / 2 * height * width
                          + fine_maps * config.head_features * (8 * rows) * (8 * cols))
    outputs = frames * height * width * 4 * 2
    runtime = CPU_RUNTIME_BYTES if device_type == "cpu" else 0
    return int(runtime + _parameter_bytes(config.to_json()) + kept + max(backbone, chunk * per_frame_head) + outputs)


def largest_fitting_frames(config: DA3Config, budget_bytes: int, height: int, width: int,
                           half_precision: bool = False, device_type: str = "cpu", limit: int = 4096,
                           rays: bool = False) -> int:
    """Largest frame count whose forward (head one frame at a time) fits ``budget_bytes`` (0: none)."""
    return memory.largest_fitting_frames(_peak(config, height, width, half_precision, device_type, rays),
                                         budget_bytes, limit)


def plan_memory(config: DA3Config, budget_gb: float, frames: int, height: int, width: int, max_chunk: int = 8,
                half_precision: bool = False, device_type: str = "cpu", rays: bool = False) -> MemoryPlan:
    """The largest head chunk (at most ``max_chunk``) whose forward fits ``budget_gb`` GiB.

    Raises:
        UserError: not even one frame at a time fits; names the largest submap that does.
    """
    def refuse(needed: int, largest: int) -> str:
        return submap_too_large(frames, height, width, needed, largest, needs="with Depth Anything 3",
                                budget=f"--max-memory is {budget_gb:g}",
                                advice="lower --submap-size, raise --max-memory, or use a smaller model size")

    return memory.plan_memory(_peak(config, height, width, half_precision, device_type, rays), budget_gb, frames,
                              max_chunk, refuse)


def _peak(config: DA3Config, height: int, width: int, half_precision: bool, device_type: str,
          rays: bool) -> PeakEstimate:
    def peak(frames: int, head_chunk: int) -> int:
        return estimate_peak_bytes(config, frames, height, width, head_chunk, half_precision, device_type, rays)

    return peak
