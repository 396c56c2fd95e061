"""Peak-memory estimate of a π³ / Pi3X forward (efficient attention, float32 activations), and the
head chunk that fits a budget (:mod:`sl4slam.models.memory`).

The estimate adds the weights, the transformer activations (linear in the frame count: flash
attention holds no table; :data:`TOKEN_BYTES_PER_CHANNEL` bytes per token and channel), one chunk of
Pi3X's convolutional heads (:data:`CONV_HEAD_BYTES_PER_PIXEL` per output pixel of a frame) and the
outputs (:data:`OUTPUT_BYTES_PER_PIXEL` per pixel of every frame). The constants were fitted to
full-size measurements (decision: docs/decisions/memory-estimates.md).
"""

from __future__ import annotations

from .. import memory
from ..memory import GIB, MemoryPlan
from .model import Pi3Config
from .preprocess import PATCH_SIZE

TOKEN_BYTES_PER_CHANNEL = 64
CONV_HEAD_BYTES_PER_PIXEL = 1100
OUTPUT_BYTES_PER_PIXEL = 64


def estimate_peak_bytes(config: Pi3Config, frames: int, height: int, width: int, head_chunk: int,
                        weight_bytes: int) -> int:
    """Estimated peak memory of one forward (efficient attention, float32): the weights, the
    transformer activations (linear in the frame count: flash attention holds no table) and one
    chunk of the convolutional heads."""
    tokens = frames * (config.decoder_registers + (height // PATCH_SIZE) * (width // PATCH_SIZE))
    activations = tokens * max(config.decoder_dim, config.head_decoder_dim) * TOKEN_BYTES_PER_CHANNEL
    pixels = height * width
    heads = min(head_chunk, frames) * pixels * CONV_HEAD_BYTES_PER_PIXEL if config.variant == "pi3x" else 0
    return int(weight_bytes + activations + heads + frames * pixels * OUTPUT_BYTES_PER_PIXEL)


def plan_memory(config: Pi3Config, weight_bytes: int, budget_gb: float, frames: int, height: int, width: int,
                max_chunk: int = 16) -> MemoryPlan:
    """The largest head chunk (at most ``max_chunk``) whose forward of ``frames`` images ``height`` x
    ``width`` fits ``budget_gb`` GiB, with ``weight_bytes`` of weights.

    Raises:
        UserError: not even one frame at a time fits; names the largest submap that does.
    """
    def peak(n: int, head_chunk: int) -> int:
        return estimate_peak_bytes(config, n, height, width, head_chunk, weight_bytes)

    def refuse(needed: int, largest: int) -> str:
        return (f"a {config.variant} submap of {frames} frames at {width}x{height} needs about {needed / GIB:.1f} GiB, "
                f"more than the {budget_gb:g} GiB memory budget; the largest submap that fits has {largest} "
                "frames (lower the submap size or raise the budget)")

    return memory.plan_memory(peak, budget_gb, frames, max_chunk, refuse)
