"""SAM 3 (Segment Anything with Concepts, Meta 2025) as a :class:`~sl4slam.objects.interfaces.TextSegmenter`:
every instance of a short noun phrase in one image, through ``transformers``' ``Sam3Model``.

The model runs on its own inputs, prepared here as its image processor's configuration says (the
processor imports torchvision, which this package does not need): the image squashed to 1008 x 1008
with bilinear resampling, scaled to [0, 1] and normalised with mean 0.5 and standard deviation 0.5;
the text tokenized by the checkpoint's CLIP tokenizer, padded to 32 tokens. An instance's score is
the sigmoid of its query's logit times the sigmoid of the image-level presence logit; its mask, the
sigmoid of its mask logits resized bilinearly to the image, above 0.5.

The weights (``facebook/sam3``, 0.84 B parameters, under the SAM License, a gated repository: accept
its terms on the Hub and log in with ``hf auth login`` before the first download) are fetched by
``transformers.from_pretrained`` on first use. ``transformers`` is an optional dependency (the
``objects`` extra); it and torch are imported when a segmenter is made.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from ..errors import MissingWeightsError, UserError
from ..models.hub import WeightsSource, hub_offline, hub_reachable
from .interfaces import Mask2D

if TYPE_CHECKING:
    from ..registry import ObjectModelEntry

SAM3_WEIGHTS = WeightsSource("SAM 3", "facebook/sam3", "model.safetensors", folder_names=("model.safetensors",),
                             flag="--sam3-weights")
SAM3_PARAMETERS = 840_376_374
"""Parameters of ``Sam3Model`` at its default (released) configuration."""
IMAGE_SIZE = 1008
MEAN = (0.5, 0.5, 0.5)
STD = (0.5, 0.5, 0.5)
TEXT_TOKENS = 32


class Sam3Segmenter:
    """A ``Sam3Model`` and its tokenizer as a ``TextSegmenter``.

    Args:
        model: a ``transformers.Sam3Model`` in eval mode on ``device``.
        tokenize: ``tokenize(text) -> (input_ids, attention_mask)``, each ``(1, L)`` int64 tensors.
        device: where the model runs.
        image_size: the square side the model takes.
        name: the model's name.
    """

    def __init__(self, model, tokenize: Callable, device: str = "cpu", image_size: int = IMAGE_SIZE,
                 name: str = "sam3") -> None:
        self.model = model
        self.tokenize = tokenize
        self.device = device
        self.image_size = int(image_size)
        self.name = name

    def pixels(self, image: np.ndarray):
        """``(1, 3, S, S)`` float32 model input of an ``(H, W, 3)`` uint8 RGB image."""
        import torch
        from PIL import Image

        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8 RGB, got {image.shape} {image.dtype}")
        resized = np.asarray(Image.fromarray(image).resize((self.image_size, self.image_size), Image.BILINEAR),
                             dtype=np.float32) / 255.0
        normalised = (resized - np.asarray(MEAN, dtype=np.float32)) / np.asarray(STD, dtype=np.float32)
        dtype = next(self.model.parameters()).dtype  # the checkpoint's own precision
        return torch.from_numpy(normalised).permute(2, 0, 1)[None].contiguous().to(self.device, dtype=dtype)

    def segment(self, image: np.ndarray, text: str, threshold: float = 0.5) -> list[Mask2D]:
        """The instances of ``text`` in ``image`` scored at least ``threshold``, best first, each with
        an ``(H, W)`` bool mask at the image's resolution (see the module doc)."""
        import torch
        import torch.nn.functional as F

        height, width = np.asarray(image).shape[:2]
        input_ids, attention_mask = self.tokenize(text)
        with torch.inference_mode():
            out = self.model(pixel_values=self.pixels(image), input_ids=input_ids.to(self.device),
                             attention_mask=attention_mask.to(self.device))
            scores = out.pred_logits[0].float().sigmoid()
            if out.presence_logits is not None:
                scores = scores * out.presence_logits[0].float().sigmoid()
            keep = torch.nonzero(scores >= threshold).flatten()
            keep = keep[torch.argsort(scores[keep], descending=True)]
            if not len(keep):
                return []
            masks = F.interpolate(out.pred_masks[0, keep][None].float(), size=(height, width), mode="bilinear",
                                  align_corners=False)[0].sigmoid() > 0.5
        return [Mask2D(mask=m.cpu().numpy(), score=float(s)) for m, s in zip(masks, scores[keep].cpu())]


def make_segmenter(weights: str = SAM3_WEIGHTS.repo_id, device: str = "cpu", config=None,
                   random_init: bool = False) -> Sam3Segmenter:
    """A SAM 3 text segmenter.

    Args:
        weights: a hub id or a local folder in ``transformers``' layout (``config.json``,
            ``model.safetensors``, the tokenizer's files).
        device: "cpu", "cuda" or "cuda:N".
        config: a ``transformers.Sam3Config`` to build with seeded random weights instead of loading
            (``"tiny"``: :func:`tiny_config`; tests), with a byte-level tokenizer; ``weights`` unused.
        random_init: the released configuration with seeded random weights and a byte-level
            tokenizer (no download; for measuring cost).

    Returns:
        A ``TextSegmenter`` (``name``, ``segment``).

    Raises:
        UserError: ``transformers`` is not installed or lacks SAM 3; ``MissingWeightsError`` (one
            line) when the weights are neither here nor downloadable (offline, no access to the
            gated repository); a corrupt download, one line.
    """
    try:
        import torch
        from transformers import Sam3Config, Sam3Model
    except ImportError as exc:
        raise UserError(f"SAM 3 needs transformers >= 5.0 ({exc}); pip install 'sl4slam[objects]'") from None
    if config is not None or random_init:
        if isinstance(config, str):
            if config != "tiny":
                raise UserError(f"unknown SAM 3 configuration {config!r} (only 'tiny')")
            config = tiny_config()
        config = config if config is not None else Sam3Config()
        torch.manual_seed(0)
        model = Sam3Model(config).eval().to(device)
        return Sam3Segmenter(model, byte_tokenizer(config.text_config.max_position_embeddings), device,
                             image_size=config.vision_config.image_size, name="sam3-random")
    model, tokenizer = _load_pretrained(weights, device)
    image_size = int(getattr(model.config.vision_config, "image_size", IMAGE_SIZE))

    def tokenize(text: str):
        encoded = tokenizer([text], padding="max_length", max_length=TEXT_TOKENS, truncation=True, return_tensors="pt")
        return encoded["input_ids"], encoded["attention_mask"]

    return Sam3Segmenter(model, tokenize, device, image_size=image_size)


def _load_pretrained(weights: str, device: str):
    """``Sam3Model`` and tokenizer of ``weights``, from the cache first; errors in one line."""
    from transformers import AutoTokenizer, Sam3Model

    hint = (f"accept the SAM License at https://huggingface.co/{SAM3_WEIGHTS.repo_id}, log in (`hf auth login`) and "
            f"download it on a machine with internet access (`hf download {SAM3_WEIGHTS.repo_id}`), then pass the "
            "snapshot folder as the SAM 3 weights")
    what = f"SAM 3 weights {weights}"
    try:
        return _pretrained(Sam3Model, AutoTokenizer, weights, device, local_only=True)
    except (OSError, ValueError) as exc:
        local_problem = exc
    from pathlib import Path

    if Path(weights).expanduser().is_dir():
        raise UserError(f"{what} cannot be loaded ({_first_line(local_problem)}); {hint}") from None
    if hub_offline():
        raise MissingWeightsError(f"{what} are not in the Hugging Face cache and downloads are off (HF_HUB_OFFLINE); {hint}")
    if not hub_reachable():
        raise MissingWeightsError(f"{what} are not in the Hugging Face cache and huggingface.co cannot be reached; {hint}")
    try:
        return _pretrained(Sam3Model, AutoTokenizer, weights, device, local_only=False)
    except Exception as exc:  # gated repository without access, unknown repo, interrupted or corrupt download
        raise MissingWeightsError(f"{what} could not be loaded ({_first_line(exc)}); {hint}") from None


def _pretrained(model_class, tokenizer_class, weights: str, device: str, local_only: bool):
    model = model_class.from_pretrained(weights, local_files_only=local_only).eval().to(device)
    tokenizer = tokenizer_class.from_pretrained(weights, local_files_only=local_only)
    return model, tokenizer


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0].strip()}" if lines else type(exc).__name__


def byte_tokenizer(length: int) -> Callable:
    """A tokenizer of the 514-token byte vocabulary (``sl4slam.objects.pe_core.ClipTokenizer`` without
    merges) for random-weight models: ``tokenize(text) -> (input_ids, attention_mask)``, each ``(1, length)``."""
    import torch

    from .pe_core import ClipTokenizer

    words = ClipTokenizer([], length)

    def tokenize(text: str):
        ids = words([text])
        used = int((ids[0] == words.eot).nonzero()[0]) + 1
        return ids, (torch.arange(length) < used).long()[None]

    return tokenize


def tiny_config(image_size: int = 56):
    """A ``Sam3Config`` of the released shape at tiny sizes (width 32, one or two layers, 8 queries,
    the 514-token byte vocabulary): the real code path in well under a second."""
    from transformers import Sam3Config

    grid = image_size // 14
    return Sam3Config(
        vision_config=dict(backbone_config=dict(model_type="sam3_vit_model", hidden_size=32, intermediate_size=64,
                                                num_hidden_layers=2, num_attention_heads=2, image_size=image_size,
                                                patch_size=14, window_size=2, global_attn_indexes=[1],
                                                pretrain_image_size=28),
                           fpn_hidden_size=32, backbone_feature_sizes=[[4 * grid] * 2, [2 * grid] * 2, [grid] * 2]),
        text_config=dict(vocab_size=514, hidden_size=32, intermediate_size=64, projection_dim=32, num_hidden_layers=1,
                         num_attention_heads=2, max_position_embeddings=16, bos_token_id=512, eos_token_id=513,
                         pad_token_id=0),
        geometry_encoder_config=dict(hidden_size=32, num_layers=1, num_attention_heads=2, intermediate_size=64),
        detr_encoder_config=dict(hidden_size=32, num_layers=1, num_attention_heads=2, intermediate_size=64),
        detr_decoder_config=dict(hidden_size=32, num_layers=1, num_attention_heads=2, intermediate_size=64,
                                 num_queries=8),
        mask_decoder_config=dict(hidden_size=32, num_attention_heads=2, num_upsampling_stages=3),
    )


def registry_entry() -> "ObjectModelEntry":
    """SAM 3's line in ``sl4slam models``."""
    from ..registry import ObjectModelEntry

    return ObjectModelEntry(name="sam3", weights=SAM3_WEIGHTS, licence="SAM License", parameters=SAM3_PARAMETERS,
                            role="text segmenter for sl4slam query",
                            description="SAM 3: masks of every instance of a phrase in a keyframe; "
                                        "gated: accept its licence on the Hub")


__all__ = ["Sam3Segmenter", "make_segmenter", "tiny_config", "byte_tokenizer", "SAM3_WEIGHTS"]

