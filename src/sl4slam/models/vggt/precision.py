"""Inference precision modes of the VGGT model: where its weights live and what dtype computes.

Modes (``VGGTConfig.dtype``):

- ``fp32``: float32 weights and compute (the reference).
- ``bf16`` / ``fp16``: aggregator weights stored in that dtype (halving the largest part of the
  model) and its compute under autocast; the heads stay float32, as in the released model.
  Fast on GPUs; on CPUs without native bfloat16 instructions (AVX2-only) it is several times
  slower than float32 and only saves memory (decision: docs/decisions/int8-cpu.md).
- ``int8``: CPU only. Every ``nn.Linear`` of the aggregator (DINOv2 encoder and the 48
  frame/global blocks: about 90 % of its multiply-adds at one frame, less as global attention
  grows with the frame count) gets int8 weights, quantized per output
  channel, and dynamically quantized int8 activations (``torch.ao`` dynamic quantization, FBGEMM
  / oneDNN kernels); everything else stays float32.
"""

from __future__ import annotations

import gc
import warnings
from dataclasses import dataclass

import torch
from torch import nn

from ..precision import PrecisionError, resolve_mode

MODES = ("fp32", "bf16", "fp16", "int8")


@dataclass(frozen=True)
class Precision:
    """A resolved precision mode.

    Attributes:
        mode: one of :data:`MODES`.
        storage: dtype of the aggregator's (non-quantized) weights.
        autocast: autocast dtype of the aggregator, ``None`` for none.
    """

    mode: str
    storage: torch.dtype
    autocast: torch.dtype | None

    @property
    def activation_bytes(self) -> int:
        """Bytes per element of the aggregator's activations."""
        return 2 if self.autocast is not None else 4


#: What each of :data:`MODES` means for VGGT.
PRECISIONS: dict[str, Precision] = {
    "fp32": Precision("fp32", torch.float32, None),
    "bf16": Precision("bf16", torch.bfloat16, torch.bfloat16),
    "fp16": Precision("fp16", torch.float16, torch.float16),
    "int8": Precision("int8", torch.float32, None),
}


def resolve_precision(mode: str, device: torch.device) -> Precision:
    """``mode`` (one of :data:`MODES`; "auto" is settled before, ``sl4slam.models.precision.settle_mode``)
    on ``device`` -> :class:`Precision`.

    Raises:
        PrecisionError (a ``ValueError``): unknown mode, or int8 on a non-CPU device.
    """
    precision = resolve_mode(mode, PRECISIONS, f"unknown VGGT dtype '{mode}': use " + ", ".join(MODES))
    if precision.mode == "int8" and device.type != "cpu":
        raise PrecisionError("--dtype int8 runs on the CPU only; use bf16 on a GPU")
    return precision


def quantize_aggregator_int8(model: nn.Module) -> nn.Module:
    """Replace every ``nn.Linear`` of ``model.aggregator`` by a dynamically quantized int8 one, in place.

    Weights: int8 per output channel; activations: 8-bit, range taken per call (per tensor).
    The float32 weights of those layers are released, so the model holds each weight once.
    """
    from torch.ao.quantization import per_channel_dynamic_qconfig, quantize_dynamic

    with warnings.catch_warnings():
        # torch.ao.quantization announces its move to torchao; the eager API still works.
        warnings.simplefilter("ignore")
        quantize_dynamic(model.aggregator, {nn.Linear: per_channel_dynamic_qconfig}, inplace=True)
    # The replaced float32 layers sit in reference cycles: release their weights now.
    gc.collect()
    return model


def apply_precision(model: nn.Module, precision: Precision) -> nn.Module:
    """Put ``model``'s aggregator weights into ``precision`` (heads stay float32), in place."""
    if precision.mode == "int8":
        model.float()
        return quantize_aggregator_int8(model)
    for name, child in model.named_children():
        child.to(precision.storage if name == "aggregator" else torch.float32)
    return model


def count_quantized_linears(model: nn.Module) -> int:
    """Number of dynamically quantized linear layers in ``model``."""
    from torch.ao.nn.quantized.dynamic import Linear as DynamicLinear

    return sum(isinstance(m, DynamicLinear) for m in model.modules())


def relative_errors(test: torch.Tensor, reference: torch.Tensor, floor: float = 1e-2) -> tuple[float, float]:
    """(max, median) of ``|test - reference| / max(|reference|, floor * rms(reference))``.

    The floor keeps values that cross zero (points, translations) from dividing by ~0; for
    positive outputs far from zero (depth, confidence) it is the plain relative error.
    """
    test, reference = test.double(), reference.double()
    scale = torch.clamp(reference.abs(), min=floor * float(reference.pow(2).mean().sqrt()) + 1e-30)
    error = ((test - reference).abs() / scale).flatten()
    return float(error.max()), float(error.median())
