"""Finding, reading, loading and converting VGGT checkpoints.

Sources: a local ``.pt`` / ``.pth`` / ``.safetensors`` file, or a Hugging Face hub id (default
``facebook/VGGT-1B``, file ``model.pt``; ``owner/name:file`` picks another file) resolved through
huggingface_hub's cache. ``.pt`` files are read with ``weights_only=True``: tensors and plain
containers only, never arbitrary pickled objects.

Model sizes: a ``.safetensors`` file written by :func:`convert_checkpoint` (or
:func:`save_checkpoint`) carries its :class:`VGGTModelConfig` as JSON in the metadata entry
``vggt_config``; a ``.pt`` file may hold ``{"model": state_dict, "vggt_config": {...}}``. Without
it the sizes are inferred from the tensor shapes; the only size that shapes cannot tell, the
aggregator layers read by the dense heads, defaults to VGGT-1B's ``[4, 11, 17, 23]`` when the
aggregator has 24 layers (any other depth needs the embedded config).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import torch

from ...errors import UserError
from .. import loading
from ..checkpoint import describe_checkpoint, pass_again, write_checkpoint
from ..checkpoint import read_checkpoint as read_weights_file
from ..hub import DEFAULT_HUB_ID, VGGT_WEIGHTS, resolve_weights
from ..loading import block_count, embedded_config, ready_for_inference
from ..precision import weight_dtype
from .model import SKIPPED_PREFIXES, VGGT, VGGTModelConfig

logger = logging.getLogger(__name__)

CONFIG_METADATA_KEY = "vggt_config"


def read_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict | None]:
    """State dict and embedded config (or ``None``) of a ``.safetensors`` or ``.pt`` file, on CPU
    (``sl4slam.models.checkpoint.read_checkpoint``: one line for a cut, corrupt or unsafe file).

    ``.pt`` files are memory-mapped when possible, so loading them with ``assign=True`` keeps a
    single copy of the weights.
    """
    state_dict, metadata = read_weights_file(path, VGGT_WEIGHTS.what, VGGT_WEIGHTS.refetch())
    return state_dict, embedded_config(metadata, CONFIG_METADATA_KEY)


def require_vggt(state_dict: dict, path: str | Path) -> None:
    """``UserError`` (one line naming the file and what it holds) unless ``state_dict`` is VGGT's."""
    if "aggregator.camera_token" not in state_dict:
        raise UserError(f"{path} holds {describe_checkpoint(state_dict)}, not VGGT weights; "
                        f"{pass_again(it='a VGGT checkpoint', value='', default=DEFAULT_HUB_ID)}")


def infer_config(state_dict: dict[str, torch.Tensor]) -> VGGTModelConfig:
    """Model sizes from checkpoint shapes (see the module docstring for the one assumption)."""
    try:
        embed_dim = state_dict["aggregator.camera_token"].shape[-1]
        num_register_tokens = state_dict["aggregator.register_token"].shape[2]
        depth = block_count(state_dict, "aggregator.frame_blocks.")
        head_dim = state_dict["aggregator.frame_blocks.0.attn.q_norm.weight"].shape[0]
        patch_size = state_dict["aggregator.patch_embed.patch_embed.proj.weight"].shape[-1]
        grid = math.isqrt(state_dict["aggregator.patch_embed.pos_embed"].shape[1] - 1)
        mlp_hidden = state_dict["aggregator.frame_blocks.0.mlp.fc1.weight"].shape[0]
    except KeyError:
        raise UserError(f"the weights hold {describe_checkpoint(state_dict)}, not VGGT's; "
                        f"{pass_again(it='a VGGT checkpoint', value='', default=DEFAULT_HUB_ID)}") from None
    num_heads = embed_dim // head_dim
    dense_prefix = "depth_head." if "depth_head.norm.weight" in state_dict else "point_head."
    has_dense = f"{dense_prefix}norm.weight" in state_dict
    if has_dense and depth != 24:
        raise UserError(
            "cannot tell which aggregator layers the dense heads read for a checkpoint with "
            f"{depth} layers; save it with its config (convert_checkpoint(..., config=...))"
        )
    defaults = VGGTModelConfig()
    return VGGTModelConfig(
        img_size=grid * patch_size,
        patch_size=patch_size,
        embed_dim=embed_dim,
        depth=depth,
        num_heads=num_heads,
        mlp_ratio=mlp_hidden / embed_dim,
        num_register_tokens=num_register_tokens,
        patch_embed_depth=block_count(state_dict, "aggregator.patch_embed.blocks."),
        # Head counts are not visible in the shapes; VGGT uses the aggregator's for all transformers.
        patch_embed_num_heads=num_heads,
        camera_trunk_depth=block_count(state_dict, "camera_head.trunk."),
        camera_num_heads=num_heads,
        dpt_features=state_dict[f"{dense_prefix}scratch.layer1_rn.weight"].shape[0] if has_dense else defaults.dpt_features,
        dpt_out_channels=[state_dict[f"{dense_prefix}projects.{i}.weight"].shape[0] for i in range(4)]
        if has_dense
        else defaults.dpt_out_channels,
        dpt_layers=defaults.dpt_layers,
        enable_camera="camera_head.token_norm.weight" in state_dict,
        enable_depth="depth_head.norm.weight" in state_dict,
        enable_point="point_head.norm.weight" in state_dict,
    )


def load_state_dict_into(model: VGGT, state_dict: dict[str, torch.Tensor], assign: bool = False) -> None:
    """Load strictly, except for the ``track_head.*`` keys (not implemented), which are ignored.

    Raises:
        UserError: listing missing or unexpected keys (or shape mismatches).
    """
    kept = {k: v for k, v in state_dict.items() if not k.startswith(SKIPPED_PREFIXES)}
    loading.load_state_dict_into(model, kept, "VGGT", assign=assign)


def load_vggt(
    weights: str = DEFAULT_HUB_ID,
    device: torch.device | str = "cpu",
    dtype: torch.dtype | str | None = torch.float32,
    config: VGGTModelConfig | None = None,
    cache_dir: str | Path | None = None,
    local_files_only: bool | None = None,
) -> VGGT:
    """Build a VGGT model from a checkpoint, in eval mode, holding one copy of the weights.

    Args:
        weights: local file or hub id (see :func:`resolve_weights`).
        device: where the model lives.
        dtype: parameter dtype (``None`` keeps the checkpoint's); "fp32"/"bf16"/"fp16" accepted.
        config: model sizes; default: embedded in the checkpoint, else inferred from shapes.
        cache_dir, local_files_only: passed to huggingface_hub for hub ids.

    Raises:
        MissingWeightsError: weights not available (message says how to get them).
        UserError: not a compatible checkpoint.
    """
    path = resolve_weights(weights, cache_dir=cache_dir, local_files_only=local_files_only)
    state_dict, embedded = read_checkpoint(path)
    require_vggt(state_dict, path)
    if config is None:
        config = VGGTModelConfig.from_dict(embedded) if embedded else infer_config(state_dict)
    with torch.device("meta"):
        model = VGGT(config)
    # assign=True adopts the checkpoint's tensors as parameters instead of copying into new ones.
    load_state_dict_into(model, state_dict, assign=True)
    del state_dict
    ready_for_inference(model, device, weight_dtype(dtype))
    logger.info("loaded VGGT weights from %s", path)
    return model


def save_checkpoint(state_dict: dict[str, torch.Tensor], path: str | Path, config: VGGTModelConfig | None = None) -> Path:
    """Write a state dict as ``.safetensors`` (config embedded when given) or ``.pt`` (by suffix)."""
    return write_checkpoint(state_dict, path, CONFIG_METADATA_KEY, config.to_json() if config is not None else None)


def convert_checkpoint(src: str | Path, dst: str | Path, dtype: str = "fp32") -> Path:
    """Copy a VGGT checkpoint (file or hub id) to ``dst`` ``.safetensors``, optionally in bf16/fp16.

    Every key is kept (including ``track_head.*``); floating tensors are cast to ``dtype``; the
    model config (embedded or inferred) is written into the metadata.
    """
    def read() -> tuple[dict[str, torch.Tensor], VGGTModelConfig]:
        path = resolve_weights(str(src))
        state_dict, embedded = read_checkpoint(path)
        require_vggt(state_dict, path)
        return state_dict, VGGTModelConfig.from_dict(embedded) if embedded else infer_config(state_dict)

    return loading.convert_checkpoint(read, dst, dtype, save_checkpoint)
