"""Precision modes: the mode "auto" stands for on a device, and a model's table of what each mode means.

A model's ``dtype`` setting names a mode ("auto", "fp32", "bf16", "fp16"; VGGT also "int8").
:func:`settle_mode` turns "auto" into a concrete mode once, in the resolve step (``sl4slam.resolve``):
half precision on a CUDA GPU (bf16 where the GPU runs it, else fp16), float32 elsewhere; only the
test of "runs bf16" can be a model's own (:func:`cuda_bf16_supported` or :func:`cuda_native_bf16`).
A GPU that does not run bf16, or that torch cannot describe (an unknown card, a driver too old for
it), gets fp16 for "auto" and for "bf16" too; :func:`precision_note` says so in the run's notes.
The model decides what a concrete mode means for it (a :class:`torch.dtype` to autocast to, a
storage and compute pair, ...) in a table that :func:`resolve_mode` looks the mode up in.

:func:`weight_dtype` reads the dtype that weights are stored in (loading and converting checkpoints).
"""

from __future__ import annotations

from typing import Callable, Mapping, Sequence, TypeVar

import torch

from ..errors import UserError

T = TypeVar("T")

#: Names of the weight storage dtypes (any case), as loading and converting checkpoints accept them.
WEIGHT_DTYPES: dict[str, torch.dtype] = {
    "fp32": torch.float32, "float32": torch.float32,
    "bf16": torch.bfloat16, "bfloat16": torch.bfloat16,
    "fp16": torch.float16, "float16": torch.float16,
}


class PrecisionError(UserError, ValueError):
    """An unknown precision mode, or one the device cannot run (a ``UserError`` and a ``ValueError``)."""


def weight_dtype(dtype: torch.dtype | str | None) -> torch.dtype | None:
    """The storage dtype named by ``dtype`` (:data:`WEIGHT_DTYPES`, any case); a ``torch.dtype`` or
    ``None`` (keep the checkpoint's) is returned as it is.

    Raises:
        UserError: an unknown name.
    """
    if isinstance(dtype, str):
        if dtype.lower() not in WEIGHT_DTYPES:
            raise UserError(f"unknown dtype {dtype!r}; use fp32, bf16 or fp16")
        return WEIGHT_DTYPES[dtype.lower()]
    return dtype


def cuda_bf16_supported(device: torch.device) -> bool:
    """Whether torch runs bfloat16 on the current CUDA device (natively, or emulated on GPUs older
    than compute capability 8): ``torch.cuda.is_bf16_supported()``."""
    return torch.cuda.is_bf16_supported()


def cuda_native_bf16(device: torch.device) -> bool:
    """Whether the CUDA ``device`` has native bfloat16 (compute capability 8 or more)."""
    return torch.cuda.get_device_capability(device)[0] >= 8


def runs_bf16(device: torch.device, bf16: Callable[[torch.device], bool] = cuda_bf16_supported) -> bool:
    """Whether the CUDA ``device`` runs bfloat16 by the model's test ``bf16``; a card that torch
    cannot describe (the test raises: an unknown card, a driver too old for it) does not."""
    try:
        return bool(bf16(device))
    except (RuntimeError, AssertionError, ValueError):
        return False


def auto_mode(device: torch.device, bf16: Callable[[torch.device], bool] = cuda_bf16_supported) -> str:
    """The mode "auto" stands for on ``device``: "bf16" on a CUDA device that runs it
    (:func:`runs_bf16`), "fp16" on other CUDA devices, "fp32" on every other device."""
    if device.type != "cuda":
        return "fp32"
    return "bf16" if runs_bf16(device, bf16) else "fp16"


def settle_mode(mode: str, device: str | torch.device, modes: Sequence[str], model: str,
                bf16: Callable[[torch.device], bool] = cuda_bf16_supported) -> str:
    """The concrete mode of a ``dtype`` setting on ``device``: "auto" becomes :func:`auto_mode`,
    any other mode is checked against ``modes``; "bf16" on a CUDA device that does not run it
    (:func:`runs_bf16`) becomes "fp16" (float32 for a model without fp16).

    Args:
        mode: the setting ("auto" or one of ``modes``).
        device: where the model runs ("cpu", "cuda", "cuda:N").
        modes: the model's concrete modes (e.g. ``("fp32", "bf16", "fp16")``).
        model: the model's name, for the message.
        bf16: the model's test of bf16 on a CUDA device.

    Raises:
        PrecisionError: a mode that is not "auto" and not in ``modes`` (one line naming them).
    """
    if mode == "auto":
        return auto_mode(torch.device(device), bf16)
    if mode not in modes:
        raise PrecisionError(f"unknown {model} dtype {mode!r}: use auto, " + ", ".join(modes))
    if mode in ("bf16", "bfloat16") and torch.device(device).type == "cuda" and not runs_bf16(torch.device(device), bf16):
        return "fp16" if "fp16" in modes else "fp32"
    return mode


def precision_note(requested: str, settled: str, device: str | torch.device) -> str | None:
    """The run's note on its model precision on a CUDA ``device`` (``None`` elsewhere, and where
    the mode asked for is the one used): what "auto" became, or why bf16 was not used.

    Args:
        requested: the ``dtype`` setting as given ("auto" or a mode, any case).
        settled: the concrete mode :func:`settle_mode` made of it.
        device: where the model runs.
    """
    if torch.device(device).type != "cuda":
        return None
    requested = requested.lower()
    if requested == "auto":
        why = "this GPU runs bf16" if settled == "bf16" else "this GPU does not run bf16, or torch cannot tell which card it is"
        return f"model precision: {settled} (auto on a GPU: {why})"
    if requested in ("bf16", "bfloat16") and settled != "bf16":
        return (f"model precision: {settled} instead of the bf16 asked for (this GPU does not run bf16, or torch "
                "cannot tell which card it is)")
    return None


def resolve_mode(mode: str, table: Mapping[str, T], unknown: str) -> T:
    """What the concrete ``mode`` (settled by :func:`settle_mode`) means for a model: ``table[mode]``.

    Args:
        mode: a key of ``table`` (compared as given: a model lowers the case itself if it accepts
            any case).
        table: the model's modes (e.g. ``{"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}``).
        unknown: the message for a mode that is not in ``table`` (one line naming the modes).

    Raises:
        PrecisionError: ``mode`` is not in ``table``.
    """
    if mode not in table:
        raise PrecisionError(unknown)
    return table[mode]
