"""Loading a state dict into a model and converting a checkpoint: the steps every model shares.

Each model keeps what is its own (which keys it skips or aliases, how it reads its files and infers
its sizes, how it writes them) and hands it to these functions:

- :func:`load_state_dict_into`: strict loading with one-line errors ("N missing keys", "N unexpected
  keys", "shapes do not match"); ``assign=True`` adopts the tensors of a model built on the meta
  device instead of copying them.
- :func:`convert_checkpoint`: read a checkpoint, cast its floating tensors to fp32 / bf16 / fp16,
  write it as ``.safetensors`` with its configuration embedded.
- :func:`embedded_config`, :func:`block_indices`, :func:`block_count`: reading a configuration from a
  file's metadata, and counting numbered blocks (``blocks.0.``, ``blocks.1.`` ...) in key names.
- :func:`ready_for_inference`: dtype, device, eval mode and frozen parameters of a loaded model.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Callable, Iterable, Mapping, TypeVar

import torch
from torch import nn

from ..errors import UserError
from .precision import weight_dtype

ConfigT = TypeVar("ConfigT")
ModelT = TypeVar("ModelT", bound=nn.Module)


def load_state_dict_into(model: nn.Module, state_dict: Mapping[str, torch.Tensor], what: str,
                         assign: bool = False) -> None:
    """Load ``state_dict`` into ``model`` strictly: every key of the model and no other, shapes equal.

    Args:
        model: the model (on the meta device with ``assign=True``).
        state_dict: the tensors, already filtered / completed by the model's own rules.
        what: the model's name in messages ("VGGT", "Depth Anything 3", "pi3x").
        assign: adopt the tensors as parameters instead of copying into the existing ones.

    Raises:
        UserError: the counts of missing and unexpected keys with up to five of each, or the first
            shape mismatch; one line.
    """
    expected = set(model.state_dict().keys())
    missing = sorted(expected - set(state_dict))
    unexpected = sorted(set(state_dict) - expected)
    if missing or unexpected:
        raise UserError(f"checkpoint does not match the {what} model: {len(missing)} missing keys {missing[:5]}, "
                        f"{len(unexpected)} unexpected keys {unexpected[:5]}")
    try:
        model.load_state_dict(dict(state_dict), strict=True, assign=assign)
    except RuntimeError as exc:
        raise UserError(f"checkpoint shapes do not match the {what} model: "
                        f"{str(exc).splitlines()[-1].strip()}") from None


def convert_checkpoint(read: Callable[[], tuple[Mapping[str, torch.Tensor], ConfigT]], dst: str | Path, dtype: str,
                       write: Callable[[dict[str, torch.Tensor], Path, ConfigT], Path]) -> Path:
    """Copy a checkpoint to ``dst`` ``.safetensors``, floating tensors cast to ``dtype``, every key kept.

    Args:
        read: the model's reader: ``() -> (state_dict, config)``, the file found, checked to be the
            model's and its configuration embedded or inferred (called after ``dtype`` and ``dst`` are
            checked).
        dst: the output file; must end in ``.safetensors``.
        dtype: "fp32", "bf16" or "fp16" (also "float32", "bfloat16", "float16"; any case).
        write: the model's writer: ``(state_dict, dst, config) -> path`` (config in the metadata).

    Returns:
        What ``write`` returns (the written file).

    Raises:
        UserError: unknown ``dtype``, ``dst`` not ``.safetensors``, or whatever ``read`` raises.
    """
    target = weight_dtype(dtype)
    dst = Path(dst)
    if dst.suffix != ".safetensors":
        raise UserError(f"conversion output must end in .safetensors, got {dst}")
    state_dict, config = read()
    converted = {k: v.to(target) if v.is_floating_point() else v for k, v in state_dict.items()}
    return write(converted, dst, config)


def embedded_config(metadata: Mapping, key: str) -> dict | None:
    """The configuration stored under ``key`` in a weights file's metadata (safetensors: a JSON string;
    ``.pt``: a dict), or ``None`` when there is none."""
    config = metadata.get(key)
    if isinstance(config, str):
        config = json.loads(config)
    return config


def block_indices(keys: Iterable[str], prefix: str, suffix: str = "") -> list[int]:
    """Sorted indices ``i`` of the keys that start with ``{prefix}{i}.{suffix}``."""
    pattern = re.compile(re.escape(prefix) + r"(\d+)\." + re.escape(suffix))
    return sorted({int(m.group(1)) for key in keys if (m := pattern.match(key))})


def block_count(keys: Iterable[str], prefix: str) -> int:
    """Number of numbered blocks under ``prefix`` (the largest index + 1; 0 when there is none)."""
    indices = block_indices(keys, prefix)
    return indices[-1] + 1 if indices else 0


def ready_for_inference(model: ModelT, device: torch.device | str, dtype: torch.dtype | None = None) -> ModelT:
    """``model`` cast to ``dtype`` (floating parameters and buffers; ``None``: as they are), moved to
    ``device``, in eval mode, with every parameter frozen. Returns ``model``."""
    if dtype is not None:
        model.to(dtype=dtype)
    model.to(device).eval()
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    return model
