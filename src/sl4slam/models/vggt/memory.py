"""Peak-memory model of a VGGT forward, and the dense-head chunk size that fits a memory budget.

The estimate adds up the tensors that are alive at the peak, each counted from its shape:

* weights: the parameters in their storage dtype (int8 linears: ``INT8_WEIGHT_BYTES`` per weight);
* the aggregator: ``S`` frames of ``P = 1 + R + h*w`` tokens of width ``C``; inside a block the
  residual stream, its norm, q/k/v (and their rotated copies), the attention output and the MLP's
  hidden layer (``mlp_ratio * C``, before and after GELU) coexist: about ``AGGREGATOR_WIDTHS``
  token widths of ``C`` per token; plus the kept aggregator outputs (``2C`` per token each, only
  the layers the heads read);
* the dense head, per frame of a chunk: the float32 maps at image size (``features / 2`` channels
  after upsampling, the positional embedding added to them, and the 32-channel output trunk),
  about ``HEAD_MAPS`` such maps; the chunk's float32 copy of its kept tokens;
* on CPU the interpreter and libraries (``CPU_RUNTIME_BYTES``).

The multipliers and the runtime are set from measured peaks and rounded up, so the estimate lies
above them (decision: docs/decisions/memory-estimates.md).
"""

from __future__ import annotations

import functools
import json

import torch

from .. import memory
from ..memory import GIB, MemoryPlan, PeakEstimate, submap_too_large  # noqa: F401  (GIB: part of this module's API)
from .model import VGGT, VGGTModelConfig
from .precision import Precision

#: Token widths (of C) of the aggregator alive at its peak, per token (measured, rounded up).
AGGREGATOR_WIDTHS = 16.0
#: Float32 image-size maps of ``features / 2`` channels alive at the dense head's peak (measured, rounded up).
HEAD_MAPS = 4.0
#: Resident size of the interpreter, torch and this package on CPU before any weight (measured).
CPU_RUNTIME_BYTES = 700 * 2**20
#: Bytes per int8 linear weight as held by the quantized kernels (packed copy, offsets; measured).
INT8_WEIGHT_BYTES = 1.25


def weight_bytes(model_config: VGGTModelConfig, precision: Precision, heads: tuple[str, ...] = ("camera", "depth")) -> int:
    """Bytes of the parameters held for ``heads`` under ``precision`` (counted on the meta device)."""
    return _weight_bytes(model_config.to_json(), precision.mode, precision.storage, tuple(heads))


@functools.lru_cache(maxsize=32)
def _weight_bytes(config_json: str, mode: str, storage: torch.dtype, heads: tuple[str, ...]) -> int:
    with torch.device("meta"):
        model = VGGT(VGGTModelConfig.from_dict(json.loads(config_json)))
    storage_bytes = torch.empty(0, dtype=storage).element_size()
    total = 0
    for name, param in model.named_parameters():
        part = name.split(".", 1)[0]
        if part == "aggregator":
            quantized = mode == "int8" and param.ndim == 2 and name.endswith(".weight")
            total += int(param.numel() * (INT8_WEIGHT_BYTES if quantized else storage_bytes))
        elif part.removesuffix("_head") in heads:
            total += param.numel() * 4
    return total


def estimate_peak_bytes(
    model_config: VGGTModelConfig,
    precision: Precision,
    frames: int,
    height: int,
    width: int,
    head_chunk: int,
    device_type: str = "cpu",
    heads: tuple[str, ...] = ("camera", "depth"),
) -> int:
    """Upper estimate of the peak memory of one forward of ``frames`` images ``height`` x ``width``.

    CPU: resident set size of the process; CUDA: ``torch.cuda.max_memory_allocated`` (weights included).
    """
    patch = model_config.patch_size
    tokens = 1 + model_config.num_register_tokens + (height // patch) * (width // patch)
    act = precision.activation_bytes
    width_c = model_config.embed_dim
    dense = [h for h in heads if h in ("depth", "point")]
    kept = len({i % model_config.depth for i in model_config.dpt_layers} | {model_config.depth - 1})
    per_frame_aggregator = tokens * width_c * act * (AGGREGATOR_WIDTHS * model_config.mlp_ratio / 4.0 + 2 * kept)
    chunk = min(max(head_chunk, 1), frames)
    per_frame_head = (
        height * width * 4 * (HEAD_MAPS * model_config.dpt_features / 2 + 2)
        + tokens * 2 * width_c * 4 * len(model_config.dpt_layers)
    )
    outputs = frames * height * width * 4 * (2 * len(dense) + 2)
    runtime = CPU_RUNTIME_BYTES if device_type == "cpu" else 0
    head_peak = chunk * per_frame_head if dense else 0
    return int(runtime + weight_bytes(model_config, precision, heads) + frames * per_frame_aggregator + head_peak + outputs)


def largest_fitting_frames(
    model_config: VGGTModelConfig, precision: Precision, budget_bytes: int, height: int, width: int,
    device_type: str = "cpu", heads: tuple[str, ...] = ("camera", "depth"), limit: int = 4096,
) -> int:
    """Largest frame count whose forward (dense heads one frame at a time) fits ``budget_bytes`` (0: none)."""
    return memory.largest_fitting_frames(
        _peak(model_config, precision, height, width, device_type, heads), budget_bytes, limit)


def plan_memory(
    model_config: VGGTModelConfig,
    precision: Precision,
    budget_gb: float,
    frames: int,
    height: int,
    width: int,
    max_chunk: int = 8,
    device_type: str = "cpu",
    heads: tuple[str, ...] = ("camera", "depth"),
    budget_source: str = "",
) -> MemoryPlan:
    """The largest dense-head chunk (at most ``max_chunk`` frames) whose forward fits ``budget_gb`` GiB.

    ``budget_source``: where the budget comes from, for the message ("" : ``--max-memory``).

    Raises:
        UserError: not even one frame at a time fits; names the largest submap that does.
    """
    def refuse(needed: int, largest: int) -> str:
        return submap_too_large(
            frames, height, width, needed, largest, needs=f"in {precision.mode}",
            budget=f"{budget_source or '--max-memory is'} {budget_gb:.3g}",
            fitting=f" (--submap-size {max(1, largest - 2)} with the shared and a loop frame)",
            advice=f"lower --submap-size, {'raise --max-memory, ' if not budget_source else ''}"
                   "or use a smaller --dtype (bf16, int8 on CPU)")

    return memory.plan_memory(_peak(model_config, precision, height, width, device_type, heads),
                              budget_gb, frames, max_chunk, refuse)


def _peak(model_config: VGGTModelConfig, precision: Precision, height: int, width: int, device_type: str,
          heads: tuple[str, ...]) -> PeakEstimate:
    def peak(frames: int, head_chunk: int) -> int:
        return estimate_peak_bytes(model_config, precision, frames, height, width, head_chunk, device_type, heads)

    return peak
