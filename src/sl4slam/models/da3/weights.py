"""Finding, reading and loading Depth Anything 3 checkpoints.

Sources: a local ``.safetensors`` / ``.pt`` file (or a folder holding ``model.safetensors``), or a
Hugging Face hub id, by default the size's release (``depth-anything/DA3-SMALL``, file
``model.safetensors``; ``owner/name:file`` picks another file), resolved through
:func:`sl4slam.models.hub.resolve_weights` and read by :func:`sl4slam.models.checkpoint.read_checkpoint`
(one line for a cut, corrupt or unsafe file; ``.pt`` with ``weights_only``).

Configuration, in order of precedence:

1. a :class:`DA3Config` embedded in a ``.safetensors`` file's metadata (``da3_config``), as
   :func:`save_checkpoint` writes it;
2. the shapes of the tensors (widths, depths, heads, FFN kind, where qk-norm starts, head widths,
   whether there are camera modules), completed by the release's ``config.json`` when it sits next
   to the weights or in the hub cache (``config.net``: ``out_layers``, ``alt_start``, ``rope_start``),
   else by the released architecture with the same backbone (the one thing shapes cannot tell is
   which blocks alternate and which feed the heads).

Loading is strict: every tensor of the model must be in the file and every tensor of the file in the
model, except the Giant checkpoints' Gaussian-splatting head (``gs_head.*``, not built: SLAM renders
nothing) and the ray head's tied LayerNorm, which the files store once (level 0) for four aliases.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import torch

from ...errors import UserError
from .. import loading
from ..checkpoint import describe_checkpoint, pass_again
from ..checkpoint import read_checkpoint as read_weights_file
from ..hub import WeightsSource, hub_offline, hub_reachable, is_hub_id, resolve_weights
from ..loading import block_count, block_indices, embedded_config, ready_for_inference
from ..precision import resolve_mode
from .backbone import swiglu_hidden_features
from .config import ARCHITECTURES, GS_HEAD_PREFIXES, RELEASED, SIZES, DA3Config, ReleasedSize, released
from .head import tied_norm_keys
from .model import DepthAnything3, build_da3, count_parameters

logger = logging.getLogger(__name__)

CONFIG_METADATA_KEY = "da3_config"
CHECKPOINT_PREFIX = "model."
CONFIG_FILENAME = "config.json"
WEIGHTS_FILENAME = "model.safetensors"
PRECISIONS = ("fp32", "bf16", "fp16")
#: Autocast dtype of the backbone for each mode (``None``: float32, no autocast).
AUTOCAST_DTYPES: dict[str, torch.dtype | None] = {"fp32": None, "float32": None, "bf16": torch.bfloat16,
                                                  "fp16": torch.float16}


def weights_source(size: str) -> WeightsSource:
    """Where the released weights of ``size`` live (``WeightsSource("DA3-SMALL", "depth-anything/DA3-SMALL", ...)``)."""
    release = released(size)
    return WeightsSource(release.repo_id.split("/")[1], release.repo_id, WEIGHTS_FILENAME,
                         folder_names=(WEIGHTS_FILENAME, "model.pt"))


#: ``WeightsSource`` of every released size, by our size name.
WEIGHTS_SOURCES: dict[str, WeightsSource] = {size: weights_source(size) for size in SIZES}
#: Licence of every released size's weights (SPDX).
LICENCES: dict[str, str] = {size: RELEASED[size].licence for size in SIZES}


def parameter_counts() -> dict[str, int]:
    """Parameters of each released size as built from its configuration (meta device, no memory),
    without the Giant's Gaussian-splatting head."""
    return {size: count_parameters(RELEASED[size].config) for size in SIZES}


def strip_prefix(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The released files prefix every key with ``model.`` (the API wrapper's attribute): drop it."""
    if any(k.startswith(CHECKPOINT_PREFIX) for k in state_dict) and all(
            k.startswith(CHECKPOINT_PREFIX) for k in state_dict):
        return {k[len(CHECKPOINT_PREFIX):]: v for k, v in state_dict.items()}
    return dict(state_dict)


def _width(state_dict: dict) -> int | None:
    token = state_dict.get("backbone.pretrained.cls_token")
    return int(token.shape[-1]) if token is not None else None


def architecture_of(state_dict: dict) -> str | None:
    """Which released architecture (small, base, large, giant) a prefix-free state dict has, by width."""
    width = _width(state_dict)
    return next((name for name, config in ARCHITECTURES.items() if config.embed_dim == width), None)


def require_da3(state_dict: dict, path: str | Path, release: ReleasedSize | None = None) -> None:
    """``UserError`` (one line naming the file and what it holds) unless ``state_dict`` (prefix-free) is
    a Depth Anything 3 any-view checkpoint, of ``release``'s architecture when given."""
    wanted = f"{release.repo_id.split('/')[1]} weights" if release else "Depth Anything 3 any-view weights"
    if release is not None:
        hint = pass_again(it=f"the {release.name} checkpoint", value="", default=release.repo_id)
    else:
        hint = pass_again(it="a DA3-SMALL/BASE/LARGE/GIANT checkpoint", value="")
    holds = describe(state_dict)
    if "backbone.pretrained.camera_token" not in state_dict:
        raise UserError(f"{path} holds {holds}, not {wanted}; {hint}")
    if release is not None and state_dict.get("backbone.pretrained.cls_token") is not None:
        found = architecture_of(state_dict)
        if found is not None and found != release.architecture:
            others = " or ".join(s for s in SIZES if RELEASED[s].architecture == found)
            raise UserError(f"{path} holds {holds}, not {wanted}; {hint}, or choose size {others} for this file")


def describe(state_dict: dict) -> str:
    """What a prefix-free state dict holds, in words (:func:`sl4slam.models.checkpoint.describe_checkpoint`)."""
    holds = describe_checkpoint({CHECKPOINT_PREFIX + k: v for k, v in state_dict.items()})
    return describe_checkpoint(state_dict) if holds.startswith("weights of an unknown model") else holds


def _reference_net(reference: dict | None) -> dict:
    """The ``net`` section of a release's ``config.json`` (``{"config": {"net": ...}}`` or top level)."""
    if not reference:
        return {}
    config = reference.get("config", reference)
    if "anyview" in config:
        raise UserError("this is a nested Depth Anything 3 checkpoint (any-view + metric, DA3NESTED-*); "
                        "use the any-view release of the same size (e.g. depth-anything/DA3-GIANT-1.1)")
    return dict(config.get("net", {}))


def infer_config(state_dict: dict[str, torch.Tensor], reference: dict | None = None) -> DA3Config:
    """Sizes of a (prefix-free) checkpoint from its shapes, completed by ``reference`` (a release's
    ``config.json`` content) or the released architecture of the same width and depth.

    Raises:
        UserError: not a DA3 any-view checkpoint, or a layout whose alternation / output layers cannot
            be told (no config.json and no released architecture of that backbone).
    """
    try:
        embed_dim = int(state_dict["backbone.pretrained.cls_token"].shape[-1])
        patch_size = int(state_dict["backbone.pretrained.patch_embed.proj.weight"].shape[-1])
        grid = math.isqrt(state_dict["backbone.pretrained.pos_embed"].shape[1] - 1)
        token_dim = int(state_dict["head.norm.weight"].shape[0])
        head_features = int(state_dict["head.scratch.layer1_rn.weight"].shape[0])
        out_channels = [int(state_dict[f"head.projects.{i}.weight"].shape[0]) for i in range(4)]
        output_dim = int(state_dict["head.scratch.output_conv2.2.weight"].shape[0])
    except KeyError:
        raise UserError(f"the weights hold {describe(state_dict)}, "
                        "not a Depth Anything 3 any-view checkpoint") from None
    prefix = "backbone.pretrained.blocks."
    depth = block_count(state_dict, prefix)
    normed = block_indices(state_dict, prefix, "attn.q_norm.weight")
    swiglu = f"{prefix}0.mlp.w12.weight" in state_dict
    if swiglu:
        hidden = int(state_dict[f"{prefix}0.mlp.w12.weight"].shape[0]) // 2
        mlp_ratio = 4.0
        if swiglu_hidden_features(embed_dim, mlp_ratio) != hidden:
            raise UserError(f"unsupported SwiGLU width {hidden} for a {embed_dim}-wide backbone")
    else:
        mlp_ratio = int(state_dict[f"{prefix}0.mlp.fc1.weight"].shape[0]) / embed_dim
    net = _reference_net(reference)
    known = next((c for c in ARCHITECTURES.values() if (c.embed_dim, c.depth, c.ffn) ==
                  (embed_dim, depth, "swiglu" if swiglu else "mlp")), None)
    if normed:
        num_heads = embed_dim // int(state_dict[f"{prefix}{normed[0]}.attn.q_norm.weight"].shape[0])
    elif known is not None:
        num_heads = known.num_heads
    else:
        raise UserError(f"cannot tell the attention heads of a {embed_dim}-wide backbone without qk-norm")
    qknorm_start = normed[0] if normed else -1
    if "qknorm_start" in net and int(net["qknorm_start"]) != qknorm_start:
        raise UserError(f"config.json says qk-norm starts at block {net['qknorm_start']} but the weights have it "
                        f"from block {qknorm_start}")
    if {"out_layers", "alt_start", "rope_start"} <= set(net):
        layout = dict(out_layers=[int(i) for i in net["out_layers"]], alt_start=int(net["alt_start"]),
                      rope_start=int(net["rope_start"]))
    elif known is not None:
        layout = dict(out_layers=list(known.out_layers), alt_start=known.alt_start, rope_start=known.rope_start)
    else:
        raise UserError(f"cannot tell which blocks of this {depth}-block, {embed_dim}-wide backbone alternate and feed "
                        "the heads: put the release's config.json next to the weights, or save the checkpoint with "
                        "its config (save_checkpoint(..., config=...))")
    with_camera = "cam_dec.fc_t.weight" in state_dict
    return DA3Config(
        embed_dim=embed_dim, depth=depth, num_heads=num_heads, mlp_ratio=mlp_ratio, ffn="swiglu" if swiglu else "mlp",
        img_size=grid * patch_size, patch_size=patch_size, qknorm_start=qknorm_start,
        cat_token=token_dim == 2 * embed_dim, head_features=head_features, head_out_channels=out_channels,
        head_output_dim=output_dim, head_aux_levels=block_count(state_dict, "head.scratch.output_conv1_aux."),
        head_aux_convs=block_count(state_dict, "head.scratch.output_conv1_aux.0."),
        with_camera=with_camera, cam_enc_depth=block_count(state_dict, "cam_enc.trunk.") if with_camera else 4,
        **layout,
    )


def read_checkpoint(path: str | Path, what: str = "Depth Anything 3", fix: str | None = None
                    ) -> tuple[dict[str, torch.Tensor], DA3Config | None]:
    """Prefix-free state dict and embedded :class:`DA3Config` (or ``None``) of a weights file, on CPU."""
    fix = fix or f"delete it and fetch it again, then {pass_again()}"
    state_dict, metadata = read_weights_file(path, what, fix)
    embedded = embedded_config(metadata, CONFIG_METADATA_KEY)
    return strip_prefix(state_dict), DA3Config.from_dict(embedded) if embedded else None


def find_reference_config(weights: str, path: Path) -> dict | None:
    """The release's ``config.json``: next to the weights file, else (for a hub id) in the hub cache or,
    when online, downloaded. ``None`` when there is none; never raises."""
    beside = path.with_name(CONFIG_FILENAME)
    try:
        if beside.is_file():
            return json.loads(beside.read_text())
        if not is_hub_id(weights):
            return None
        from huggingface_hub import hf_hub_download

        repo_id = weights.partition(":")[0]
        try:
            found = hf_hub_download(repo_id, CONFIG_FILENAME, local_files_only=True)
        except Exception:
            if hub_offline() or not hub_reachable():
                return None
            found = hf_hub_download(repo_id, CONFIG_FILENAME)
        return json.loads(Path(found).read_text())
    except Exception as exc:  # a missing or unreadable config.json only means: infer from the shapes
        logger.debug("no usable %s for %s (%s)", CONFIG_FILENAME, weights, exc)
        return None


def load_state_dict_into(model: DepthAnything3, state_dict: dict[str, torch.Tensor], assign: bool = False,
                         skipped_prefixes: tuple[str, ...] = GS_HEAD_PREFIXES) -> None:
    """Load a prefix-free state dict strictly (see the module docstring for the two exceptions).

    Raises:
        UserError: missing or unexpected keys, or shape mismatches, listed.
    """
    kept = {k: v for k, v in state_dict.items() if not k.startswith(skipped_prefixes)}
    levels = model.config.head_aux_levels
    for stored, aliases in tied_norm_keys(levels):
        stored = "head.scratch." + stored
        for alias in aliases:
            alias = "head.scratch." + alias
            if stored in kept and alias not in kept:
                kept[alias] = kept[stored]
    loading.load_state_dict_into(model, kept, "Depth Anything 3", assign=assign)


def resolve_precision(dtype: str | torch.dtype | None) -> torch.dtype | None:
    """Autocast dtype of the backbone for ``dtype`` ("fp32", "bf16", "fp16"; ``None``: float32);
    ``None`` for float32. "auto" is settled before (``sl4slam.models.precision.settle_mode``)."""
    if isinstance(dtype, torch.dtype):
        return None if dtype == torch.float32 else dtype
    return resolve_mode((dtype or "fp32").lower(), AUTOCAST_DTYPES,
                        f"unknown Depth Anything 3 dtype {dtype!r}: use {', '.join(PRECISIONS)}")


def load_da3(weights: str | None = None, size: str = "small", device: torch.device | str = "cpu",
             dtype: str | torch.dtype | None = "fp32", config: DA3Config | None = None,
             cache_dir: str | Path | None = None, local_files_only: bool | None = None) -> DepthAnything3:
    """Build a Depth Anything 3 model from a checkpoint, in eval mode, with one copy of the weights.

    Args:
        weights: local file / folder or hub id; ``None``: the size's release (``depth-anything/DA3-*``).
        size: one of :data:`~sl4slam.models.da3.config.SIZES` ("small", "base", "large", "large-1.1",
            "giant", "giant-1.1"): the default weights and the architecture the file must have.
        device: where the model lives.
        dtype: compute precision of the backbone (:func:`resolve_precision`); weights stay float32.
        config: sizes; default: embedded in the file, else :func:`infer_config`.
        cache_dir, local_files_only: passed to huggingface_hub for hub ids.

    Raises:
        MissingWeightsError: the weights are not available (the message says how to get them).
        WeightsFileError: the file is cut short, corrupt or unreadable.
        UserError: the file holds another model or another DA3 size (one line saying what it holds).
    """
    release = released(size)
    source = WEIGHTS_SOURCES[release.size]
    weights = weights or release.repo_id
    path = resolve_weights(weights, cache_dir=cache_dir, local_files_only=local_files_only, source=source)
    state_dict, embedded = read_checkpoint(path, source.what, source.refetch())
    require_da3(state_dict, path, release if embedded is None and config is None else None)
    if config is None:
        config = embedded or infer_config(state_dict, find_reference_config(weights, path))
    model = build_da3(config, device="meta")
    # assign=True adopts the file's tensors as parameters instead of copying them into new ones.
    load_state_dict_into(model, state_dict, assign=True, skipped_prefixes=GS_HEAD_PREFIXES)
    del state_dict
    device = torch.device(device)
    ready_for_inference(model, device, torch.float32)
    model.autocast_dtype = resolve_precision(dtype)
    logger.info("loaded %s weights from %s", source.what, path)
    return model


def convert_checkpoint(src: str | Path | None, dst: str | Path, size: str = "small", dtype: str = "fp32") -> Path:
    """Copy a DA3 checkpoint (file or hub id; ``None``: the size's release) to ``dst`` ``.safetensors`` with
    its configuration embedded (no config.json needed afterwards), optionally in bf16 / fp16 (halves the
    file; :func:`load_da3` computes in float32 all the same). Every key is kept, ``gs_head.*`` included."""
    def read() -> tuple[dict[str, torch.Tensor], DA3Config]:
        release = released(size)
        source = WEIGHTS_SOURCES[release.size]
        weights = str(src) if src is not None else release.repo_id
        path = resolve_weights(weights, source=source)
        state_dict, embedded = read_checkpoint(path, source.what, source.refetch())
        require_da3(state_dict, path, None if embedded else release)
        return state_dict, embedded or infer_config(state_dict, find_reference_config(weights, path))

    return loading.convert_checkpoint(read, dst, dtype, save_checkpoint)


def save_checkpoint(state_dict: dict[str, torch.Tensor], path: str | Path, config: DA3Config | None = None,
                    prefix: str = CHECKPOINT_PREFIX) -> Path:
    """Write a state dict as ``.safetensors`` with the released ``model.`` prefix (tied tensors stored once,
    as the released files) and, when given, the config in the metadata (``da3_config``)."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors: dict[str, torch.Tensor] = {}
    seen: set[int] = set()
    for key in sorted(state_dict):  # level 0 of the tied LayerNorm sorts first
        value = state_dict[key].detach().cpu()
        if value.data_ptr() in seen:
            continue  # an alias of a tied parameter
        seen.add(value.data_ptr())
        tensors[prefix + key] = value.contiguous().clone()
    metadata = {"format": "pt"}
    if config is not None:
        metadata[CONFIG_METADATA_KEY] = config.to_json()
    save_file(tensors, str(path), metadata=metadata)
    return path
