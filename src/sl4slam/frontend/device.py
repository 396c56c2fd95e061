"""The torch device a frontend runs on."""

from __future__ import annotations

import torch

from ..errors import UserError


def resolve_device(device: str) -> torch.device:
    """The named device ("cpu", "cuda", "cuda:N"; "auto" is settled by ``sl4slam.resolve``); ``cuda``
    without a GPU: one line."""
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("--device cuda was requested but no CUDA GPU is available; use --device cpu")
    return torch.device(device)
