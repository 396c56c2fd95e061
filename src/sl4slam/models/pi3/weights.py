"""Finding, reading and loading π³ / Pi3X checkpoints.

Sources (``sl4slam.models.hub.resolve_weights``): a local ``.safetensors`` / ``.pt`` file, a folder
holding ``model.safetensors``, or a Hugging Face hub id: ``yyfz233/Pi3`` and ``yyfz233/Pi3X``, file
``model.safetensors`` (the authors' README). ``.pt`` files are read with ``weights_only=True``.

The released weights are licensed CC BY-NC 4.0 (non-commercial use only; the authors' code is
BSD-3-Clause): :data:`WEIGHTS_LICENSE`.

Model sizes: a checkpoint written by :func:`save_checkpoint` carries its :class:`Pi3Config` as JSON
(safetensors metadata ``pi3_config``; a ``.pt`` payload's ``"pi3_config"`` entry). Without it the
sizes come from the tensor shapes (:func:`infer_config`). The one thing shapes cannot show is the
head count of the attentions without qk-norm (the encoder, the head decoders, the metric decoder):
every attention of the released models has 64 channels per head, so that is assumed.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Mapping

import torch

from ...errors import UserError
from .. import loading
from ..checkpoint import describe_checkpoint, pass_again, write_checkpoint
from ..checkpoint import read_checkpoint as read_weights_file
from ..hub import WeightsSource, resolve_weights
from ..loading import block_count, embedded_config, ready_for_inference
from ..precision import weight_dtype
from .model import VARIANTS, Pi3, Pi3Config, Pi3X, build_pi3, parameter_count

logger = logging.getLogger(__name__)

PI3_WEIGHTS = WeightsSource("Pi3", "yyfz233/Pi3", "model.safetensors")
PI3X_WEIGHTS = WeightsSource("Pi3X", "yyfz233/Pi3X", "model.safetensors")
WEIGHTS_SOURCES = {"pi3": PI3_WEIGHTS, "pi3x": PI3X_WEIGHTS}
WEIGHTS_LICENSE = "CC BY-NC 4.0 (non-commercial use only)"
"""Licence of both released checkpoints (the authors' README; their code is BSD-3-Clause)."""
PARAMETERS = {"pi3": 958_696_732, "pi3x": 1_360_032_433}
"""Parameters at full size (:func:`sl4slam.models.pi3.model.parameter_count` of the default
configs, a meta-device build; ``tests/test_pi3_model.py`` recomputes them). Pi3X's include its
condition branches (depth encoder 304 M, pose injection 63 M, ray embedding 6 k)."""
CONFIG_METADATA_KEY = "pi3_config"
HEAD_DIM = 64
"""Channels per attention head of every attention of the released models."""


def checkpoint_variant(state_dict: Mapping) -> str | None:
    """"pi3" or "pi3x" when ``state_dict`` (or a key -> shape map) has that model's keys, else ``None``."""
    if "camera_decoder.projects.weight" not in state_dict or "register_token" not in state_dict:
        return None
    return "pi3x" if "metric_token" in state_dict else "pi3"


def require_variant(state_dict: Mapping, variant: str, path: str | Path) -> None:
    """``UserError`` (one line naming the file and what it holds) unless it is ``variant``'s."""
    found = checkpoint_variant(state_dict)
    if found == variant:
        return
    source = WEIGHTS_SOURCES[variant]
    if found is not None:
        raise UserError(f"{path} holds {describe_checkpoint(state_dict)}, not {source.what} weights; "
                        f"use the {found} variant, or "
                        f"{pass_again(source.flag, f'{source.what} weights', '', source.repo_id)}")
    raise UserError(f"{path} holds {describe_checkpoint(state_dict)}, not {source.what} weights; "
                    f"{pass_again(source.flag, f'a {source.what} checkpoint', '', source.repo_id)}")


def read_checkpoint(path: str | Path, variant: str = "pi3") -> tuple[dict[str, torch.Tensor], dict | None]:
    """State dict and embedded config (or ``None``) of a ``.safetensors`` or ``.pt`` file, on the CPU
    (``sl4slam.models.checkpoint.read_checkpoint``: one line for a cut, corrupt or unsafe file)."""
    source = WEIGHTS_SOURCES[_check_variant(variant)]
    state_dict, metadata = read_weights_file(path, source.what, source.refetch())
    return state_dict, embedded_config(metadata, CONFIG_METADATA_KEY)


def _check_variant(variant: str) -> str:
    if variant not in VARIANTS:
        raise UserError(f"unknown π³ variant '{variant}': use one of {', '.join(VARIANTS)}")
    return variant


def infer_config(shapes: Mapping[str, torch.Tensor | tuple | list]) -> Pi3Config:
    """Model sizes from a state dict's shapes (tensors, or a key -> shape map such as the vendored
    manifest); see the module docstring for the head-count assumption.

    Raises:
        UserError: not a π³ / Pi3X checkpoint, or a layout this implementation does not have.
    """
    variant = checkpoint_variant(shapes)
    if variant is None:
        raise UserError(f"the weights hold {describe_checkpoint(shapes)}, not π³ or Pi3X weights")

    def shape(key: str) -> tuple[int, ...]:
        value = shapes[key]
        return tuple(value.shape) if hasattr(value, "shape") else tuple(value)

    keys = list(shapes)
    try:
        patch = shape("encoder.patch_embed.proj.weight")[-1]
        encoder_dim = shape("encoder.cls_token")[-1]
        decoder_dim = shape("register_token")[-1]
        head_dim = shape("point_decoder.projects.weight")[0]
        config = Pi3Config(
            variant=variant,
            img_size=math.isqrt(shape("encoder.pos_embed")[1] - 1) * patch,
            patch_size=patch,
            encoder_dim=encoder_dim,
            encoder_depth=block_count(keys, "encoder.blocks."),
            encoder_heads=max(1, encoder_dim // HEAD_DIM),
            encoder_registers=shape("encoder.register_tokens")[1],
            decoder_dim=decoder_dim,
            decoder_depth=block_count(keys, "decoder."),
            decoder_heads=decoder_dim // shape("decoder.0.attn.q_norm.weight")[0],
            decoder_registers=shape("register_token")[2],
            head_decoder_dim=head_dim,
            head_decoder_depth=block_count(keys, "point_decoder.blocks."),
            head_decoder_heads=max(1, head_dim // HEAD_DIM),
            point_features=shape("point_decoder.linear_out.weight")[0],
            camera_features=shape("camera_decoder.linear_out.weight")[0],
        )
        if variant == "pi3x":
            _infer_pi3x(config, shape, keys)
    except KeyError as exc:
        raise UserError(f"the weights lack {exc.args[0]}: not a complete {variant} checkpoint") from None
    return config


def _infer_pi3x(config: Pi3Config, shape, keys) -> None:
    stages = block_count(keys, "point_head.upsample_blocks.")
    config.conv_upsample_dims = [shape(f"point_head.upsample_blocks.{i}.0.0.weight")[1] for i in range(stages)]
    config.conv_res_blocks = block_count(keys, "point_head.upsample_blocks.0.") - 1
    if config.conv_res_blocks:
        config.conv_hidden_ratio = shape("point_head.upsample_blocks.0.1.layers.2.weight")[0] // config.conv_upsample_dims[0]
    if "point_head.output_block.0.2.weight" not in keys:
        raise UserError("this Pi3X checkpoint's output blocks have residual blocks, which this implementation lacks")
    config.conv_last_channels = shape("point_head.output_block.0.0.weight")[0]
    config.conv_last_kernel = shape("point_head.output_block.0.2.weight")[-1]
    config.metric_dim = shape("metric_decoder.projects_x.weight")[0]
    config.metric_depth = block_count(keys, "metric_decoder.blocks.")
    config.metric_heads = max(1, config.metric_dim // HEAD_DIM)
    config.metric_features = shape("metric_decoder.linear_out.weight")[0]
    config.depth_condition = "depth_emb" in keys
    config.ray_condition = "ray_embed.proj.weight" in keys
    config.pose_inject_blocks = block_count(keys, "pose_inject_blk.")


def load_state_dict_into(model: torch.nn.Module, state_dict: Mapping[str, torch.Tensor], assign: bool = False) -> None:
    """Load strictly: every key of the model and no other, shapes equal.

    Raises:
        UserError: listing missing or unexpected keys, or the first shape mismatch.
    """
    loading.load_state_dict_into(model, state_dict, model.config.variant, assign=assign)


#: The weight dtype of ``load_pi3``'s ``dtype`` (:func:`sl4slam.models.precision.weight_dtype`).
resolve_dtype = weight_dtype


def load_pi3(
    weights: str | None = None,
    variant: str = "pi3",
    device: torch.device | str = "cpu",
    dtype: torch.dtype | str | None = torch.float32,
    kernel: str = "efficient",
    config: Pi3Config | None = None,
    conditions: tuple[str, ...] = ("depths", "intrinsics", "poses"),
    cache_dir: str | Path | None = None,
    local_files_only: bool | None = None,
) -> Pi3 | Pi3X:
    """Build π³ or Pi3X from a checkpoint, in eval mode, holding one copy of the weights.

    Args:
        weights: local file / folder or hub id; ``None``: the variant's hub id.
        variant: "pi3" or "pi3x" (the checkpoint must be that model's).
        device: where the model lives.
        dtype: parameter dtype (``None`` keeps the checkpoint's); "fp32" / "bf16" / "fp16" accepted.
            The authors keep float32 weights and run bf16 autocast on CUDA (what the frontend does).
        kernel: attention kernel, "efficient" (default) or "reference" (the authors').
        config: model sizes; default: embedded in the checkpoint, else inferred from the shapes.
        conditions: Pi3X condition branches to keep ("depths", "intrinsics", "poses"); the others
            are released after loading (the checkpoint is still checked whole).
        cache_dir, local_files_only: passed to huggingface_hub for hub ids.

    Raises:
        MissingWeightsError: weights not available (the message says how to get them).
        WeightsFileError: a cut, corrupt or unreadable file.
        UserError: not this variant's checkpoint, or mismatched keys or shapes.
    """
    source = WEIGHTS_SOURCES[_check_variant(variant)]
    path = resolve_weights(weights or source.repo_id, cache_dir=cache_dir, local_files_only=local_files_only,
                           source=source)
    state_dict, embedded = read_checkpoint(path, variant)
    require_variant(state_dict, variant, path)
    if config is None:
        config = Pi3Config.from_dict(embedded) if embedded else infer_config(state_dict)
    model = build_pi3(config, device="meta", kernel=kernel)
    # assign=True adopts the checkpoint's tensors (memory-mapped or loaded once) as parameters.
    load_state_dict_into(model, state_dict, assign=True)
    del state_dict
    if isinstance(model, Pi3X):
        model.drop_condition_branches(keep=conditions)
    ready_for_inference(model, device, weight_dtype(dtype))
    logger.info("loaded %s weights from %s", source.what, path)
    return model


def save_checkpoint(state_dict: Mapping[str, torch.Tensor], path: str | Path, config: Pi3Config | None = None) -> Path:
    """Write a state dict as ``.safetensors`` (config in the metadata when given) or ``.pt``."""
    return write_checkpoint(state_dict, path, CONFIG_METADATA_KEY, config.to_json() if config is not None else None)


def convert_checkpoint(src: str, dst: str | Path, variant: str = "pi3", dtype: str = "fp32") -> Path:
    """Copy a π³ / Pi3X checkpoint (file or hub id) to ``dst`` ``.safetensors``, floating tensors cast
    to ``dtype``, with its config (embedded or inferred) in the metadata."""
    def read() -> tuple[dict[str, torch.Tensor], Pi3Config]:
        source = WEIGHTS_SOURCES[_check_variant(variant)]
        path = resolve_weights(src, source=source)
        state_dict, embedded = read_checkpoint(path, variant)
        require_variant(state_dict, variant, path)
        return state_dict, Pi3Config.from_dict(embedded) if embedded else infer_config(state_dict)

    return loading.convert_checkpoint(read, dst, dtype, save_checkpoint)


def full_size_parameters(variant: str) -> int:
    """Parameters of the released ``variant`` (computed from a meta-device build)."""
    return parameter_count(Pi3Config(variant=_check_variant(variant)))
