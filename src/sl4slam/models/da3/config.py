"""Sizes of the Depth Anything 3 any-view network, and the released checkpoints.

One :class:`DA3Config` describes every size; :data:`RELEASED` names the released any-view
checkpoints (``depth-anything/DA3-*`` on the Hugging Face hub), each with its configuration,
licence and file. The configuration facts (transformer sizes, which layers alternate, where
qk-norm and RoPE start, which layers feed the head, the head's widths) are those of the authors'
``configs/da3-*.yaml``; the ``-1.1`` checkpoints were retrained with the same architecture.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

#: Feed-forward layers of the backbone blocks: GELU MLP (ViT-S/B/L) or SwiGLU (ViT-g).
FFN_KINDS = ("mlp", "swiglu")


@dataclass
class DA3Config:
    """Every size of the network. The defaults are DA3-Small.

    Backbone (a DINOv2 ViT whose later blocks alternate between attention within each frame and
    across all frames):

    - ``embed_dim``, ``depth``, ``num_heads``, ``mlp_ratio``, ``ffn``: the ViT; ``ffn`` is "mlp"
      (``fc2(GELU(fc1 x))``) or "swiglu" (``w3(SiLU(a) * b)`` with ``[a, b] = w12 x``, hidden width
      ``(int(2/3 * mlp_ratio * C) + 7) // 8 * 8``).
    - ``img_size``, ``patch_size``: the training grid of the position embedding
      (``img_size / patch_size`` squared patches, resized per image with DINOv2's scale factor
      ``(n + 0.1) / grid``).
    - ``alt_start``: from this block on, odd blocks attend across frames ("global"), even blocks
      within a frame ("local"); at this block the first token of every frame becomes a camera token.
    - ``qknorm_start``, ``rope_start``: blocks from which q/k get a LayerNorm and 2D RoPE.
    - ``out_layers``: the four blocks whose tokens feed the heads; ``cat_token`` concatenates the
      last local block's tokens before each of them.

    Heads: ``head_*`` is the DualDPT depth + ray head, ``cam_dec_*`` the camera decoder (an MLP on the
    camera token), ``cam_enc_*`` the camera encoder (known cameras to camera tokens).
    ``with_camera`` is false for a checkpoint without camera decoder and encoder.
    """

    embed_dim: int = 384
    depth: int = 12
    num_heads: int = 6
    mlp_ratio: float = 4.0
    ffn: str = "mlp"
    img_size: int = 518
    patch_size: int = 14
    alt_start: int = 4
    qknorm_start: int = 4
    rope_start: int = 4
    rope_base: float = 100.0
    out_layers: list[int] = field(default_factory=lambda: [5, 7, 9, 11])
    cat_token: bool = True
    head_features: int = 64
    head_out_channels: list[int] = field(default_factory=lambda: [48, 96, 192, 384])
    head_output_dim: int = 2
    head_aux_levels: int = 4
    head_aux_convs: int = 5
    with_camera: bool = True
    cam_enc_depth: int = 4
    cam_enc_heads: int = 16
    cam_enc_mlp_ratio: float = 4.0

    def __post_init__(self) -> None:
        if self.ffn not in FFN_KINDS:
            raise ValueError(f"ffn must be one of {FFN_KINDS}, got {self.ffn!r}")
        if len(self.out_layers) != 4 or len(self.head_out_channels) != 4:
            raise ValueError("DA3 reads exactly four backbone layers (out_layers) into four head stages")
        if self.embed_dim % self.num_heads:
            raise ValueError(f"embed_dim {self.embed_dim} is not divisible by num_heads {self.num_heads}")
        if not 0 <= min(self.out_layers) <= max(self.out_layers) < self.depth:
            raise ValueError(f"out_layers {self.out_layers} are not blocks of a {self.depth}-block backbone")

    @property
    def token_dim(self) -> int:
        """Width of the tokens the heads read: ``2 C`` with ``cat_token``, else ``C``."""
        return 2 * self.embed_dim if self.cat_token else self.embed_dim

    @property
    def head_dim(self) -> int:
        return self.embed_dim // self.num_heads

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_dict(cls, values: dict) -> DA3Config:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - names
        if unknown:
            raise ValueError(f"unknown DA3 config fields: {sorted(unknown)}")
        return cls(**values)


def _backbone(name: str) -> dict:
    """Transformer sizes of the DINOv2 backbones DA3 uses (``name``: vits, vitb, vitl, vitg)."""
    return {
        "vits": dict(embed_dim=384, depth=12, num_heads=6, ffn="mlp"),
        "vitb": dict(embed_dim=768, depth=12, num_heads=12, ffn="mlp"),
        "vitl": dict(embed_dim=1024, depth=24, num_heads=16, ffn="mlp"),
        "vitg": dict(embed_dim=1536, depth=40, num_heads=24, ffn="swiglu"),
    }[name]


#: The four architectures of the any-view series (``configs/da3-{small,base,large,giant}.yaml``).
ARCHITECTURES: dict[str, DA3Config] = {
    "small": DA3Config(**_backbone("vits"), out_layers=[5, 7, 9, 11], alt_start=4, qknorm_start=4, rope_start=4,
                       head_features=64, head_out_channels=[48, 96, 192, 384]),
    "base": DA3Config(**_backbone("vitb"), out_layers=[5, 7, 9, 11], alt_start=4, qknorm_start=4, rope_start=4,
                      head_features=128, head_out_channels=[96, 192, 384, 768]),
    "large": DA3Config(**_backbone("vitl"), out_layers=[11, 15, 19, 23], alt_start=8, qknorm_start=8, rope_start=8,
                       head_features=256, head_out_channels=[256, 512, 1024, 1024]),
    "giant": DA3Config(**_backbone("vitg"), out_layers=[19, 27, 33, 39], alt_start=13, qknorm_start=13,
                       rope_start=13, head_features=256, head_out_channels=[256, 512, 1024, 1024]),
}

APACHE_2 = "Apache-2.0"
CC_BY_NC_4 = "CC-BY-NC-4.0"


@dataclass(frozen=True)
class ReleasedSize:
    """One released any-view checkpoint.

    Attributes:
        size: our name ("small", "large-1.1", ...); the frontend is called ``da3-<size>``.
        architecture: key of :data:`ARCHITECTURES`.
        repo_id: its Hugging Face repository.
        licence: SPDX identifier of the weights' licence (the code is Apache-2.0 throughout).
        skipped_prefixes: checkpoint parts this implementation does not build (never used by SLAM).
    """

    size: str
    architecture: str
    repo_id: str
    licence: str
    skipped_prefixes: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return f"da3-{self.size}"

    @property
    def config(self) -> DA3Config:
        return dataclasses.replace(ARCHITECTURES[self.architecture])


#: The Gaussian-splatting head of the Giant checkpoints (novel-view rendering, not geometry).
GS_HEAD_PREFIXES = ("gs_head.", "gs_adapter.")

#: The released any-view checkpoints (README of ByteDance-Seed/Depth-Anything-3; ``-1.1``: retrained
#: after a training bug was fixed, preferred by the authors over DA3-LARGE and DA3-GIANT).
RELEASED: dict[str, ReleasedSize] = {
    r.size: r
    for r in (
        ReleasedSize("small", "small", "depth-anything/DA3-SMALL", APACHE_2),
        ReleasedSize("base", "base", "depth-anything/DA3-BASE", APACHE_2),
        ReleasedSize("large", "large", "depth-anything/DA3-LARGE", CC_BY_NC_4),
        ReleasedSize("large-1.1", "large", "depth-anything/DA3-LARGE-1.1", CC_BY_NC_4),
        ReleasedSize("giant", "giant", "depth-anything/DA3-GIANT", CC_BY_NC_4, GS_HEAD_PREFIXES),
        ReleasedSize("giant-1.1", "giant", "depth-anything/DA3-GIANT-1.1", CC_BY_NC_4, GS_HEAD_PREFIXES),
    )
}
SIZES = tuple(RELEASED)


def released(size: str) -> ReleasedSize:
    """The released checkpoint named ``size`` ("small", "da3-small", "DA3-LARGE-1.1" ...); ``ValueError``
    naming the choices for anything else."""
    key = size.lower().removeprefix("da3-").removeprefix("da3_")
    if key not in RELEASED:
        raise ValueError(f"unknown Depth Anything 3 size {size!r}: use one of {', '.join(SIZES)}")
    return RELEASED[key]
