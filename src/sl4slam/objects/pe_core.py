"""Perception Encoder PE-Core (Bolya et al., 2025): a CLIP-style image and text encoder pair.

The image tower is a ViT (patch 14, 336 px for PE-Core-L14-336) with a class token, learned absolute
position embeddings plus 2D rotary position embeddings (RoPE) inside every attention, optional layer
scale (PE-Core has none), a final LayerNorm, an attention-pooling head (one learned probe attending to
every token, then an MLP with a residual) and a linear projection. The text tower is a causal
transformer over 32 tokens of the CLIP byte-pair vocabulary, pooled at the end-of-text token and
projected into the same space. Images and texts are compared by the cosine of their embeddings.

The published checkpoint (``facebook/PE-Core-L14-336``, ``PE-Core-L14-336.pt``) is read through
:func:`published_to_ours`, which renames its state-dict keys to this module's; :func:`ours_to_published`
is its inverse. Preprocessing follows the reference: the image squashed to ``image_size`` squared
(bilinear), scaled to [-1, 1]. Texts are lower-cased, HTML entities undone and white space collapsed
before byte-pair encoding (the reference also runs ``ftfy``, which only changes mis-decoded text).
"""

from __future__ import annotations

import gzip
import html
import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

SOT_TEXT = "<start_of_text>"
EOT_TEXT = "<end_of_text>"
CLIP_MERGES = 48894
"""Byte-pair merges of the CLIP vocabulary (256 bytes, 256 word-final bytes, the merges and the two
special tokens make its 49408 tokens)."""


@dataclass(frozen=True)
class PEVisionConfig:
    """The image tower's sizes.

    Attributes:
        image_size: the square input side in pixels (the pre-training size of the position table).
        patch_size: the patch side in pixels.
        width: the token width.
        layers: transformer blocks.
        heads: attention heads per block.
        mlp_ratio: MLP hidden width over ``width``.
        output_dim: the embedding dimension after the projection.
        pool_heads: attention heads of the pooling head.
        layer_scale: initial value of per-block layer scales; ``None``: no layer scale (PE-Core).
        rope_theta: the RoPE frequency base.
    """

    image_size: int = 336
    patch_size: int = 14
    width: int = 1024
    layers: int = 24
    heads: int = 16
    mlp_ratio: float = 4.0
    output_dim: int = 1024
    pool_heads: int = 8
    layer_scale: float | None = None
    rope_theta: float = 10000.0


@dataclass(frozen=True)
class PETextConfig:
    """The text tower's sizes.

    Attributes:
        context_length: tokens per text, start and end tokens included.
        vocab_size: the byte-pair vocabulary's size.
        width, layers, heads, mlp_ratio: the transformer.
        output_dim: the embedding dimension after the projection.
    """

    context_length: int = 32
    vocab_size: int = 49408
    width: int = 1024
    layers: int = 24
    heads: int = 16
    mlp_ratio: float = 4.0
    output_dim: int = 1024


@dataclass(frozen=True)
class PECoreConfig:
    """An image tower and a text tower that embed into one space of ``vision.output_dim`` dimensions."""

    vision: PEVisionConfig = field(default_factory=PEVisionConfig)
    text: PETextConfig = field(default_factory=PETextConfig)

    @property
    def dim(self) -> int:
        return self.vision.output_dim


PE_CORE_L14_336 = PECoreConfig()
"""PE-Core-L14-336: ViT-L/14 at 336 px (317 M parameters with its pooling head and projection) and a
24-layer text transformer (354 M): 671 M in all."""

PE_CORE_TINY = PECoreConfig(
    vision=PEVisionConfig(image_size=56, patch_size=14, width=32, layers=2, heads=2, output_dim=16, pool_heads=2),
    text=PETextConfig(context_length=16, vocab_size=514, width=32, layers=2, heads=2, output_dim=16))
"""A tiny configuration of the same shape, for tests (its vocabulary is the 514 byte tokens, no merges)."""


# ---------------------------------------------------------------------------------------------- model
class _RotaryGrid:
    """2D rotary angles of a patch grid with a class token in front: the class token at angle 0,
    patch (row r, column c) rotated by columns c + 1 in the first half of each head's channels and
    rows r + 1 in the second half; channel pairs (2i, 2i+1) share one frequency."""

    def __init__(self, head_dim: int, theta: float) -> None:
        quarter = head_dim // 4
        steps = torch.arange(0, 2 * quarter, 2, dtype=torch.float32, device="cpu")
        self.freqs = 1.0 / theta ** (steps / (2 * quarter))
        self._cache: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def cos_sin(self, grid_h: int, grid_w: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """``cos`` and ``sin`` of the angles, each ``(1 + grid_h * grid_w, head_dim)`` float32."""
        key = (grid_h, grid_w, str(device))
        if key not in self._cache:
            rows = torch.arange(grid_h, dtype=torch.float32, device="cpu") + 1
            cols = torch.arange(grid_w, dtype=torch.float32, device="cpu") + 1
            per_axis = lambda pos: torch.repeat_interleave(pos[:, None] * self.freqs[None, :], 2, dim=1)  # noqa: E731
            angle_x = per_axis(cols)[None, :, :].expand(grid_h, grid_w, -1)
            angle_y = per_axis(rows)[:, None, :].expand(grid_h, grid_w, -1)
            angles = torch.cat([angle_x, angle_y], dim=-1).reshape(grid_h * grid_w, -1)
            angles = torch.cat([torch.zeros(1, angles.shape[1], device="cpu"), angles], dim=0).to(device)
            self._cache[key] = (angles.cos(), angles.sin())
        return self._cache[key]


def _rotate(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """``x`` (..., N, D) rotated pairwise: (a, b) -> (a cos - b sin, b cos + a sin) per channel pair."""
    pairs = x.float().unflatten(-1, (-1, 2))
    turned = torch.stack([-pairs[..., 1], pairs[..., 0]], dim=-1).flatten(-2)
    return (x.float() * cos + turned * sin).to(x.dtype)


class _Attention(nn.Module):
    """Multi-head self-attention with one fused ``qkv`` projection (queries, keys, values in that order)."""

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor] | None = None,
                causal: bool = False) -> torch.Tensor:
        batch, tokens, width = x.shape
        q, k, v = self.qkv(x).reshape(batch, tokens, 3, self.heads, width // self.heads).permute(2, 0, 3, 1, 4)
        if rope is not None:
            q, k = _rotate(q, *rope), _rotate(k, *rope)
        out = F.scaled_dot_product_attention(q, k, v, is_causal=causal)
        return self.proj(out.transpose(1, 2).reshape(batch, tokens, width))


class _MLP(nn.Module):
    def __init__(self, width: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(width, hidden)
        self.fc2 = nn.Linear(hidden, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class _Block(nn.Module):
    """Pre-norm transformer block: attention and MLP residuals, each with an optional layer scale."""

    def __init__(self, width: int, heads: int, mlp_ratio: float, layer_scale: float | None) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(width, eps=1e-5)
        self.attn = _Attention(width, heads)
        self.norm2 = nn.LayerNorm(width, eps=1e-5)
        self.mlp = _MLP(width, int(width * mlp_ratio))
        if layer_scale is not None:
            self.ls1 = nn.Parameter(torch.full((width,), float(layer_scale)))
            self.ls2 = nn.Parameter(torch.full((width,), float(layer_scale)))
        else:
            self.ls1 = self.ls2 = None

    def forward(self, x: torch.Tensor, rope=None, causal: bool = False) -> torch.Tensor:
        a = self.attn(self.norm1(x), rope, causal)
        x = x + (a * self.ls1 if self.ls1 is not None else a)
        m = self.mlp(self.norm2(x))
        return x + (m * self.ls2 if self.ls2 is not None else m)


class _AttentionPool(nn.Module):
    """One learned probe attends to every token; an MLP with a residual refines the result."""

    def __init__(self, width: int, heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.heads = heads
        self.probe = nn.Parameter(torch.zeros(1, 1, width))
        self.attn = _Attention(width, heads)
        self.norm = nn.LayerNorm(width, eps=1e-5)
        self.mlp = _MLP(width, int(width * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, tokens, width = x.shape
        w_q, w_k, w_v = self.attn.qkv.weight.chunk(3)
        b_q, b_k, b_v = self.attn.qkv.bias.chunk(3)
        split = lambda t, n: t.reshape(batch, n, self.heads, width // self.heads).transpose(1, 2)  # noqa: E731
        q = split(F.linear(self.probe.expand(batch, -1, -1).to(x.dtype), w_q, b_q), 1)
        k, v = split(F.linear(x, w_k, b_k), tokens), split(F.linear(x, w_v, b_v), tokens)
        pooled = self.attn.proj(F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(batch, 1, width))
        return (pooled + self.mlp(self.norm(pooled)))[:, 0]


class PEVision(nn.Module):
    """The image tower: ``(B, 3, H, W)`` in [-1, 1] (sides multiples of the patch) to ``(B, output_dim)``."""

    def __init__(self, config: PEVisionConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.grid = c.image_size // c.patch_size
        self.patch_embed = nn.Conv2d(3, c.width, c.patch_size, c.patch_size, bias=False)
        self.cls_token = nn.Parameter(torch.zeros(c.width))
        self.pos_embed = nn.Parameter(torch.zeros(1 + self.grid ** 2, c.width))
        self.norm_pre = nn.LayerNorm(c.width, eps=1e-5)
        self.blocks = nn.ModuleList(_Block(c.width, c.heads, c.mlp_ratio, c.layer_scale) for _ in range(c.layers))
        self.norm_post = nn.LayerNorm(c.width, eps=1e-5)
        self.pool = _AttentionPool(c.width, c.pool_heads)
        self.proj = nn.Parameter(torch.zeros(c.width, c.output_dim))
        self.rope = _RotaryGrid(c.width // c.heads, c.rope_theta)

    def _positions(self, grid_h: int, grid_w: int) -> torch.Tensor:
        if (grid_h, grid_w) == (self.grid, self.grid):
            return self.pos_embed
        cls, table = self.pos_embed[:1], self.pos_embed[1:]
        table = table.reshape(1, self.grid, self.grid, -1).permute(0, 3, 1, 2)
        table = F.interpolate(table, size=(grid_h, grid_w), mode="bilinear", align_corners=False)
        return torch.cat([cls, table.permute(0, 2, 3, 1).reshape(grid_h * grid_w, -1)], dim=0)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        batch = images.shape[0]
        grid_h, grid_w = images.shape[2] // self.config.patch_size, images.shape[3] // self.config.patch_size
        x = self.patch_embed(images).flatten(2).transpose(1, 2)
        x = torch.cat([self.cls_token.view(1, 1, -1).expand(batch, -1, -1).to(x.dtype), x], dim=1)
        x = self.norm_pre(x + self._positions(grid_h, grid_w).to(x.dtype))
        rope = self.rope.cos_sin(grid_h, grid_w, x.device)
        for block in self.blocks:
            x = block(x, rope)
        return self.pool(self.norm_post(x)) @ self.proj


class PEText(nn.Module):
    """The text tower: ``(B, context_length)`` token ids to ``(B, output_dim)``, pooled at each text's
    end token (its largest id)."""

    def __init__(self, config: PETextConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.token_embed = nn.Parameter(torch.zeros(c.vocab_size, c.width))  # the token table
        self.pos_embed = nn.Parameter(torch.zeros(c.context_length, c.width))
        self.blocks = nn.ModuleList(_Block(c.width, c.heads, c.mlp_ratio, None) for _ in range(c.layers))
        self.norm = nn.LayerNorm(c.width, eps=1e-5)
        self.proj = nn.Parameter(torch.zeros(c.width, c.output_dim))

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        x = F.embedding(tokens, self.token_embed) + self.pos_embed[: tokens.shape[1]]
        for block in self.blocks:
            x = block(x, causal=True)
        x = self.norm(x)
        return x[torch.arange(x.shape[0], device=x.device), tokens.argmax(dim=-1)] @ self.proj


class PECore(nn.Module):
    """The pair of towers; :meth:`encode_images` and :meth:`encode_texts` return unit vectors."""

    def __init__(self, config: PECoreConfig = PE_CORE_L14_336) -> None:
        super().__init__()
        self.config = config
        self.vision = PEVision(config.vision)
        self.text = PEText(config.text)
        self.logit_scale = nn.Parameter(torch.tensor(math.log(1 / 0.07)))

    def encode_images(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, 3, S, S)`` preprocessed images to ``(B, D)`` unit embeddings."""
        return F.normalize(self.vision(images).float(), dim=-1)

    def encode_texts(self, tokens: torch.Tensor) -> torch.Tensor:
        """``(B, context_length)`` token ids to ``(B, D)`` unit embeddings."""
        return F.normalize(self.text(tokens).float(), dim=-1)


# ------------------------------------------------------------------------------------ the key map
_BLOCK_RENAMES = (("attn.in_proj_weight", "attn.qkv.weight"), ("attn.in_proj_bias", "attn.qkv.bias"),
                  ("attn.out_proj.", "attn.proj."), ("ln_1.", "norm1."), ("ln_2.", "norm2."),
                  ("mlp.c_fc.", "mlp.fc1."), ("mlp.c_proj.", "mlp.fc2."), ("ls_1.gamma", "ls1"), ("ls_2.gamma", "ls2"))
_POOL_RENAMES = (("attn.in_proj_weight", "attn.qkv.weight"), ("attn.in_proj_bias", "attn.qkv.bias"),
                 ("attn.out_proj.", "attn.proj."), ("layernorm.", "norm."), ("probe", "probe"),
                 ("mlp.c_fc.", "mlp.fc1."), ("mlp.c_proj.", "mlp.fc2."))
_PLAIN = (("visual.conv1.weight", "vision.patch_embed.weight"), ("visual.class_embedding", "vision.cls_token"),
          ("visual.positional_embedding", "vision.pos_embed"), ("visual.ln_pre.", "vision.norm_pre."),
          ("visual.ln_post.", "vision.norm_post."), ("visual.proj", "vision.proj"),
          ("token_embedding.weight", "text.token_embed"), ("positional_embedding", "text.pos_embed"),
          ("ln_final.", "text.norm."), ("text_projection", "text.proj"), ("logit_scale", "logit_scale"))
_PREFIXES = (("visual.transformer.resblocks.", "vision.blocks.", _BLOCK_RENAMES),
             ("transformer.resblocks.", "text.blocks.", _BLOCK_RENAMES),
             ("visual.attn_pool.", "vision.pool.", _POOL_RENAMES))


def _rename(key: str, forward: bool) -> str | None:
    """The key's name in the other layout (``forward``: published -> ours), ``None`` if unknown."""
    for theirs, ours, inner in _PREFIXES:
        src, dst = (theirs, ours) if forward else (ours, theirs)
        if key.startswith(src):
            rest = key[len(src):]
            numbered = src.endswith("blocks.")
            number, dot, tail = rest.partition(".") if numbered else ("", "", rest)
            if numbered and not (number.isdigit() and dot):
                return None
            for a, b in inner:
                a, b = (a, b) if forward else (b, a)
                if tail == a or (a.endswith(".") and tail.startswith(a)):
                    return dst + (number + "." if number else "") + b + tail[len(a):]
            return None
    for theirs, ours in _PLAIN:
        src, dst = (theirs, ours) if forward else (ours, theirs)
        if key == src or (src.endswith(".") and key.startswith(src)):
            return dst + key[len(src):]
    return None


def published_to_ours(state_dict: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The published PE-Core CLIP state dict (keys ``visual.*``, ``transformer.*``, ``token_embedding``,
    ...; a ``module.`` prefix is dropped) under this module's key names. Keys of no known part keep
    their name, so that a strict load reports them as unexpected."""
    renamed = {}
    for key, value in state_dict.items():
        key = key[len("module."):] if key.startswith("module.") else key
        renamed[_rename(key, True) or key] = value
    return renamed


def ours_to_published(state_dict: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The inverse of :func:`published_to_ours` (for writing a checkpoint in the published layout)."""
    return {(_rename(key, False) or key): value for key, value in state_dict.items()}


def is_pe_core_checkpoint(keys: Iterable[str]) -> bool:
    """Whether state-dict keys are a published PE-Core CLIP checkpoint's (image and text towers)."""
    keys = {k[len("module."):] if k.startswith("module.") else k for k in keys}
    return "visual.attn_pool.probe" in keys and "text_projection" in keys


# ------------------------------------------------------------------------------------- tokenizer
@lru_cache(maxsize=1)
def _byte_symbols() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The printable stand-in character of each byte 0..255 as CLIP's vocabulary spells it (printable
    Latin-1 bytes stand for themselves, the others for the characters from U+0100 on), and the same
    characters in the vocabulary's order (the printable ones first)."""
    kept = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    order = kept + [b for b in range(256) if b not in kept]
    symbol = {b: chr(b) for b in kept}
    symbol.update({b: chr(256 + n) for n, b in enumerate(order[len(kept):])})
    return tuple(symbol[b] for b in range(256)), tuple(symbol[b] for b in order)


def _word_pattern():
    """The pre-tokenizer: contractions, runs of letters, single digits, runs of other non-space characters."""
    try:
        import regex

        return regex.compile(r"""<start_of_text>|<end_of_text>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+""",
                             regex.IGNORECASE)
    except ImportError:  # the standard library's classes: letters are word characters that are not digits or "_"
        return re.compile(r"""<start_of_text>|<end_of_text>|'s|'t|'re|'ve|'m|'ll|'d|[^\W\d_]+|\d|(?:[^\s\w]|_)+""",
                          re.IGNORECASE)


class ClipTokenizer:
    """CLIP's byte-pair tokenizer: lower-cased text, ``<start_of_text>`` ... ``<end_of_text>``, padded
    with 0 (or cut, the end token kept last) to ``context_length``.

    Args:
        merges: the byte-pair merges in priority order (CLIP's 48894; none gives the 514 byte tokens).
        context_length: tokens per text.
    """

    def __init__(self, merges: Sequence[tuple[str, str]], context_length: int) -> None:
        _, symbols = _byte_symbols()
        vocab = list(symbols) + [s + "</w>" for s in symbols] + ["".join(m) for m in merges] + [SOT_TEXT, EOT_TEXT]
        self.encoder = {token: i for i, token in enumerate(vocab)}
        self.ranks = {tuple(m): i for i, m in enumerate(merges)}
        self.sot, self.eot = self.encoder[SOT_TEXT], self.encoder[EOT_TEXT]
        self.vocab_size = len(vocab)
        self.context_length = context_length
        self.pattern = _word_pattern()
        self._cache: dict[str, list[str]] = {}

    @classmethod
    def from_merges_file(cls, path: str | Path, context_length: int) -> "ClipTokenizer":
        """Read the merges from a CLIP ``merges.txt`` or ``bpe_simple_vocab_16e6.txt.gz`` (first line a header)."""
        path = Path(path)
        raw = gzip.open(path).read() if path.suffix == ".gz" else path.read_bytes()
        lines = raw.decode("utf-8").split("\n")[1: CLIP_MERGES + 1]
        merges = [tuple(line.split()) for line in lines if len(line.split()) == 2]
        if len(merges) != CLIP_MERGES:
            raise ValueError(f"{path} holds {len(merges)} merges, not CLIP's {CLIP_MERGES}")
        return cls(merges, context_length)

    def _bpe(self, word: str) -> list[str]:
        if word in self._cache:
            return self._cache[word]
        parts = list(word[:-1]) + [word[-1] + "</w>"]
        while len(parts) > 1:
            rank, best = min((self.ranks.get(pair, math.inf), i) for i, pair in enumerate(zip(parts, parts[1:])))
            if rank == math.inf:
                break
            first, second = parts[best], parts[best + 1]
            merged, i = [], 0
            while i < len(parts):
                if i + 1 < len(parts) and parts[i] == first and parts[i + 1] == second:
                    merged.append(first + second)
                    i += 2
                else:
                    merged.append(parts[i])
                    i += 1
            parts = merged
        self._cache[word] = parts
        return parts

    def encode(self, text: str) -> list[int]:
        """The token ids of ``text``, without start and end tokens."""
        text = re.sub(r"\s+", " ", html.unescape(html.unescape(text))).strip().lower()
        symbols, _ = _byte_symbols()
        ids: list[int] = []
        for word in self.pattern.findall(text):
            if word in (SOT_TEXT, EOT_TEXT):
                ids.append(self.encoder[word])
                continue
            ids.extend(self.encoder[p] for p in self._bpe("".join(symbols[b] for b in word.encode("utf-8"))))
        return ids

    def __call__(self, texts: Sequence[str]) -> torch.Tensor:
        """``(len(texts), context_length)`` int64 token ids."""
        out = torch.zeros(len(texts), self.context_length, dtype=torch.long)
        for row, text in enumerate(texts):
            ids = [self.sot] + self.encode(text) + [self.eot]
            if len(ids) > self.context_length:
                ids = ids[: self.context_length - 1] + [self.eot]
            out[row, : len(ids)] = torch.tensor(ids)
        return out


# ---------------------------------------------------------------------------------- preprocessing
def preprocess_images(images: Sequence[np.ndarray], size: int) -> torch.Tensor:
    """``(N, 3, size, size)`` float32 in [-1, 1]: each ``(H, W, 3)`` uint8 RGB image squashed to
    ``size`` squared with bilinear resampling (antialiased when shrinking, as PIL does)."""
    from PIL import Image

    batch = np.empty((len(images), size, size, 3), dtype=np.float32)
    for i, image in enumerate(images):
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"images must be (H, W, 3) uint8 RGB, got {image.shape} {image.dtype}")
        resized = Image.fromarray(image).resize((size, size), Image.BILINEAR)
        batch[i] = np.asarray(resized, dtype=np.float32)
    return torch.from_numpy(batch / 127.5 - 1.0).permute(0, 3, 1, 2).contiguous()
