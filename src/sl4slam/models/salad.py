"""SALAD place-recognition descriptors (Izquierdo & Civera, CVPR 2024): DINOv2 ViT-B/14 + optimal transport.

The model loads the released ``dino_salad.ckpt`` unchanged (keys ``backbone.model.*`` and
``aggregator.*``) and returns 8448-dim unit-norm descriptors: 256 global-token values followed
by 64 clusters x 128 channels stored channel-major (element ``256 + c * 64 + k``). Two images
show the same place when the L2 distance of their descriptors is small (VGGT-SLAM accepts < 0.8).

Pieces:
- :func:`sinkhorn_log_transport`: log-space Sinkhorn with a dust bin (3 iterations at inference).
- :class:`SaladAggregator`, :class:`DinoV2Backbone`, :class:`SaladModel`.
- :func:`preprocess_images`: resize (PIL bilinear, aspect ratio not kept) + ImageNet normalization.
- :func:`load_salad`: weights from a local file or the user cache, downloaded on first use.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..atomic import atomic_path
from ..paths import user_cache_dir
from ..errors import MissingWeightsError, UserError
from .checkpoint import check_weights_file, describe_checkpoint, read_checkpoint
from .dinov2 import DinoVisionTransformer

logger = logging.getLogger(__name__)

SALAD_WEIGHTS_URL = "https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt"
"""Release asset of the SALAD project holding ``dino_salad.ckpt`` (~352 MB, plain state dict)."""
SALAD_WEIGHTS_FILENAME = "dino_salad.ckpt"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# --------------------------------------------------------------------------------------------
# Optimal transport
# --------------------------------------------------------------------------------------------


def sinkhorn_log_transport(scores: Tensor, dust_bin: Tensor | float, num_iters: int = 3) -> Tensor:
    """Entropic optimal transport of ``n`` features onto ``m`` clusters plus a dust bin, in log space.

    The score matrix is augmented with a dust-bin row of constant ``dust_bin``. Row marginals are
    ``1/(n+m)`` for each cluster and ``(n-m)/(n+m)`` for the dust bin, column marginals ``1/(n+m)``;
    ``num_iters`` alternating row/column log-normalizations start from zero potentials, and the
    plan is rescaled by ``n+m`` so that every column of ``P`` sums to one.

    Args:
        scores: ``(B, m, n)`` cluster scores, ``n > m``.
        dust_bin: scalar (0-dim tensor or float).
        num_iters: Sinkhorn iterations (SALAD: 3).

    Returns:
        ``(B, m + 1, n)`` log transport plan ``log P``; the last row is the dust bin.
    """
    batch, m, n = scores.shape
    if n <= m:
        raise ValueError(f"optimal transport needs more features than clusters, got n={n} <= m={m}")
    dust_row = torch.as_tensor(dust_bin, dtype=scores.dtype, device=scores.device).reshape(1, 1, 1)
    log_plan = torch.cat((scores, dust_row.expand(batch, 1, n)), dim=1)
    # The marginals are float32 constants, as in the reference, whatever the score dtype.
    log_norm = torch.tensor(-math.log(n + m), dtype=torch.float32, device=scores.device)
    log_a = log_norm.expand(m + 1).clone()
    log_a[-1] = log_a[-1] + math.log(n - m)
    log_b = log_norm.expand(n)
    u = torch.zeros(batch, m + 1, dtype=scores.dtype, device=scores.device)
    v = torch.zeros(batch, n, dtype=scores.dtype, device=scores.device)
    for _ in range(num_iters):
        u = log_a - torch.logsumexp(log_plan + v.unsqueeze(1), dim=2)
        v = log_b - torch.logsumexp(log_plan + u.unsqueeze(2), dim=1)
    return log_plan + u.unsqueeze(2) + v.unsqueeze(1) - log_norm


# --------------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------------


class SaladAggregator(nn.Module):
    """SALAD aggregation of DINOv2 features into one descriptor.

    Parameter names equal the reference (``token_features.{0,2}``, ``cluster_features.{0,3}``,
    ``score.{0,3}``, ``dust_bin``); the hidden width of the three MLPs is 512 in the reference.

    Args:
        num_channels: backbone width C (ViT-B: 768).
        num_clusters: m (64).  cluster_dim: l (128).  token_dim: g (256).
        hidden_dim: MLP width (512).  dropout: train-time dropout of the 1x1-conv MLPs.
    """

    def __init__(
        self,
        num_channels: int = 768,
        num_clusters: int = 64,
        cluster_dim: int = 128,
        token_dim: int = 256,
        hidden_dim: int = 512,
        dropout: float = 0.3,
        sinkhorn_iters: int = 3,
    ) -> None:
        super().__init__()
        self.num_clusters = num_clusters
        self.cluster_dim = cluster_dim
        self.token_dim = token_dim
        self.sinkhorn_iters = sinkhorn_iters
        # Index layout (0, 2) / (0, 3) keeps the checkpoint's key names.
        self.token_features = nn.Sequential(
            nn.Linear(num_channels, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, token_dim)
        )
        self.cluster_features = nn.Sequential(
            nn.Conv2d(num_channels, hidden_dim, 1), nn.Dropout(dropout), nn.ReLU(), nn.Conv2d(hidden_dim, cluster_dim, 1)
        )
        self.score = nn.Sequential(
            nn.Conv2d(num_channels, hidden_dim, 1), nn.Dropout(dropout), nn.ReLU(), nn.Conv2d(hidden_dim, num_clusters, 1)
        )
        self.dust_bin = nn.Parameter(torch.tensor(1.0))

    @property
    def output_dim(self) -> int:
        return self.num_clusters * self.cluster_dim + self.token_dim

    def forward_with_intermediates(self, features: Tensor, token: Tensor) -> dict[str, Tensor]:
        """``features`` ``(B, C, h, w)``, ``token`` ``(B, C)`` -> dict of every stage.

        Keys: ``cluster_features`` ``(B, l, h, w)``, ``scores`` ``(B, m, h, w)``, ``token_features``
        ``(B, g)``, ``log_assignment`` ``(B, m+1, n)``, ``aggregated`` ``(B, l, m)`` and
        ``descriptor`` ``(B, g + l*m)``.
        """
        cluster_maps = self.cluster_features(features)
        score_maps = self.score(features)
        token_values = self.token_features(token)
        log_assignment = sinkhorn_log_transport(score_maps.flatten(2), self.dust_bin, self.sinkhorn_iters)
        assignment = log_assignment[:, :-1].exp()  # (B, m, n), dust bin dropped
        # A[b, c, k] = sum_i F[b, c, i] P[b, k, i]
        aggregated = torch.bmm(cluster_maps.flatten(2), assignment.transpose(1, 2))
        # Intra-normalization over channels per cluster; flatten(1) makes the layout channel-major.
        cluster_part = F.normalize(aggregated, p=2, dim=1).flatten(1)
        descriptor = F.normalize(torch.cat((F.normalize(token_values, p=2, dim=-1), cluster_part), dim=-1), p=2, dim=-1)
        return {
            "cluster_features": cluster_maps,
            "scores": score_maps,
            "token_features": token_values,
            "log_assignment": log_assignment,
            "aggregated": aggregated,
            "descriptor": descriptor,
        }

    def forward(self, features: Tensor, token: Tensor) -> Tensor:
        """``(B, C, h, w)``, ``(B, C)`` -> ``(B, g + l*m)`` unit-norm descriptors."""
        return self.forward_with_intermediates(features, token)["descriptor"]


class DinoV2Backbone(nn.Module):
    """DINOv2 ViT returning (patch feature map, cls token), both after the final LayerNorm.

    The ViT sits at ``.model`` so checkpoint keys read ``backbone.model.*``.
    """

    def __init__(self, embed_dim: int = 768, depth: int = 12, num_heads: int = 12, img_size: int = 518, patch_size: int = 14) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.model = DinoVisionTransformer(
            img_size=img_size,
            patch_size=patch_size,
            embed_dim=embed_dim,
            depth=depth,
            num_heads=num_heads,
            mlp_ratio=4.0,
            num_register_tokens=0,
            interpolate_antialias=False,
            interpolate_offset=0.1,
            init_values=1.0,
            pos_embed_resize="scale_factor",
        )

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, 3, H, W)`` normalized -> ``(B, C, H/14, W/14)`` patch features and ``(B, C)`` cls token."""
        batch, _, height, width = images.shape
        out = self.model.forward_features(images)
        rows, cols = height // self.patch_size, width // self.patch_size
        patches = out["x_norm_patchtokens"].reshape(batch, rows, cols, -1).permute(0, 3, 1, 2)
        return patches, out["x_norm_clstoken"]


class SaladModel(nn.Module):
    """DINOv2 backbone + SALAD aggregator. Defaults give the ``dino_salad.ckpt`` configuration
    (ViT-B/14, 64 clusters x 128 + 256 = 8448 dims, 87,991,489 parameters).

    ``forward(images)`` maps ``(B, 3, H, W)`` ImageNet-normalized images (H, W multiples of 14,
    with ``(H/14)(W/14) > num_clusters``) to ``(B, D)`` unit-norm descriptors.
    """

    def __init__(
        self,
        embed_dim: int = 768,
        depth: int = 12,
        num_heads: int = 12,
        num_clusters: int = 64,
        cluster_dim: int = 128,
        token_dim: int = 256,
        hidden_dim: int = 512,
        img_size: int = 518,
        patch_size: int = 14,
    ) -> None:
        super().__init__()
        self.backbone = DinoV2Backbone(embed_dim, depth, num_heads, img_size, patch_size)
        self.aggregator = SaladAggregator(embed_dim, num_clusters, cluster_dim, token_dim, hidden_dim)

    @property
    def output_dim(self) -> int:
        return self.aggregator.output_dim

    def forward(self, images: Tensor) -> Tensor:
        return self.aggregator(*self.backbone(images))

    @torch.inference_mode()
    def describe(
        self, images: Sequence[np.ndarray], image_size: int = 224, batch_size: int = 16
    ) -> np.ndarray:
        """Descriptors of ``(H, W, 3)`` uint8 RGB images: ``(N, D)`` float32, unit norm.

        Images are preprocessed with :func:`preprocess_images` at ``image_size`` and run in
        float32 (as VGGT-SLAM does) in batches of ``batch_size``.
        """
        param = next(self.parameters())
        out = np.empty((len(images), self.output_dim), dtype=np.float32)
        for start in range(0, len(images), batch_size):
            batch = preprocess_images(images[start : start + batch_size], image_size)
            batch = batch.to(device=param.device, dtype=param.dtype)
            out[start : start + len(batch)] = self(batch).float().cpu().numpy()
        return out


# --------------------------------------------------------------------------------------------
# Preprocessing
# --------------------------------------------------------------------------------------------


def normalize_uint8_images(images_hwc: np.ndarray | Tensor) -> Tensor:
    """``(B, H, W, 3)`` uint8 -> ``(B, 3, H, W)`` float32: ``/255`` then ImageNet mean/std.

    The same float32 operations as ToTensor + Normalize, so the result is bitwise equal to them.
    """
    tensor = torch.as_tensor(np.ascontiguousarray(images_hwc)) if isinstance(images_hwc, np.ndarray) else images_hwc
    if tensor.dtype != torch.uint8:
        raise ValueError(f"expected uint8 images, got {tensor.dtype}")
    tensor = tensor.permute(0, 3, 1, 2).contiguous().to(torch.float32).div(255)
    mean = torch.tensor(IMAGENET_MEAN, dtype=torch.float32).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=torch.float32).view(1, 3, 1, 1)
    return tensor.sub(mean).div(std)


def resize_uint8(image: np.ndarray, size: int) -> np.ndarray:
    """PIL bilinear resize of one ``(H, W, 3)`` uint8 RGB image to ``(size, size, 3)``.

    Antialiased when downscaling; the aspect ratio is not kept and nothing is cropped
    (SALAD's evaluation and VGGT-SLAM both resize this way).
    """
    from PIL import Image

    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}")
    if image.shape[:2] == (size, size):
        return image
    return np.asarray(Image.fromarray(np.ascontiguousarray(image)).resize((size, size), Image.BILINEAR))


def preprocess_images(images: Sequence[np.ndarray], image_size: int = 224) -> Tensor:
    """SALAD input for ``(H, W, 3)`` uint8 RGB images: ``(N, 3, image_size, image_size)`` float32.

    PIL bilinear resize to a square (VGGT-SLAM: 224, SALAD's evaluation: 322; a multiple of 14),
    then ToTensor + ImageNet normalization.
    """
    if image_size % 14:
        raise UserError(f"SALAD image size must be a multiple of 14 (e.g. 224 or 322), got {image_size}")
    resized = np.stack([resize_uint8(image, image_size) for image in images])
    return normalize_uint8_images(resized)


def float_images_to_uint8(images_chw: Tensor) -> np.ndarray:
    """``(B, 3, H, W)`` float in [0, 1] -> ``(B, H, W, 3)`` uint8 by truncation (``mul(255).byte()``),
    the conversion VGGT-SLAM applies to its frames before SALAD's resize."""
    return images_chw.mul(255).byte().permute(0, 2, 3, 1).contiguous().cpu().numpy()


# --------------------------------------------------------------------------------------------
# Weights
# --------------------------------------------------------------------------------------------


def salad_cache_dir() -> Path:
    """Where the SALAD checkpoint is looked for and downloaded (:func:`sl4slam.paths.user_cache_dir`)."""
    return user_cache_dir()


def find_salad_weights(weights: str | os.PathLike | None = None) -> Path | None:
    """The checkpoint that :func:`load_salad` would use without downloading, or ``None``."""
    path = Path(weights).expanduser() if weights is not None else salad_cache_dir() / SALAD_WEIGHTS_FILENAME
    return path if path.is_file() else None


def _download(url: str, destination: Path) -> None:
    """Download ``url`` to ``destination`` atomically (a partial file never takes its name)."""
    destination.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(destination) as partial:
        torch.hub.download_url_to_file(url, str(partial), progress=True)


SALAD_REFETCH = (f"delete it and download {SALAD_WEIGHTS_URL} again, then pass it with --salad-weights PATH "
                 "(or leave it in the cache folder)")


def read_state_dict(path: str | os.PathLike) -> dict[str, Tensor]:
    """Tensors of a SALAD checkpoint: a plain state dict, a Lightning checkpoint
    (``{"state_dict": ...}``) or a ``.safetensors`` file (``sl4slam.models.checkpoint``: one line
    for a cut, corrupt or unreadable file)."""
    state_dict, _ = read_checkpoint(path, "SALAD", SALAD_REFETCH)
    return state_dict


def check_salad_weights(weights: str | os.PathLike | None) -> Path | None:
    """The checkpoint a run would load, checked without loading it (a cut or corrupt file, a
    folder: one line), or ``None`` when it is neither given nor cached (it is then downloaded)."""
    path = find_salad_weights(weights)
    if weights is not None and path is None:
        given = Path(weights).expanduser()
        if given.is_dir():
            check_weights_file(given, "SALAD", SALAD_REFETCH)
        raise MissingWeightsError(f"SALAD weights not found at {given}; download {SALAD_WEIGHTS_URL} and pass its "
                                  "path with --salad-weights PATH")
    return check_weights_file(path, "SALAD", SALAD_REFETCH) if path is not None else None


def load_salad(
    weights: str | os.PathLike | None = None,
    device: str | torch.device = "cpu",
    download: bool = True,
) -> SaladModel:
    """The full SALAD model with the released weights, in eval mode on ``device``.

    Args:
        weights: path of ``dino_salad.ckpt`` (plain or Lightning form, or ``.safetensors``);
            ``None`` uses ``<cache>/dino_salad.ckpt`` (see :func:`salad_cache_dir`), downloading
            :data:`SALAD_WEIGHTS_URL` there on first use when ``download`` is true.
        device: "cpu", "cuda", "cuda:N" or a ``torch.device``.

    Raises:
        MissingWeightsError: the file is absent and cannot be downloaded (the message says where
            to put it).
        UserError: the file is not a SALAD checkpoint (keys or shapes differ).
    """
    if weights is not None:
        path = check_salad_weights(weights)
    else:
        path = salad_cache_dir() / SALAD_WEIGHTS_FILENAME
        if not path.is_file():
            if not download:
                raise MissingWeightsError(
                    f"SALAD weights not found at {path}; download {SALAD_WEIGHTS_URL} there or pass its path "
                    "with --salad-weights PATH")
            logger.info("downloading SALAD weights from %s to %s", SALAD_WEIGHTS_URL, path)
            try:
                _download(SALAD_WEIGHTS_URL, path)
            except Exception as exc:  # offline, proxy, HTTP error, disk full
                raise MissingWeightsError(
                    f"SALAD weights could not be downloaded ({type(exc).__name__}: {exc}); "
                    f"download {SALAD_WEIGHTS_URL} to {path} or pass its path with --salad-weights PATH"
                ) from None

    state_dict = read_state_dict(path)
    with torch.device("meta"):
        model = SaladModel()
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in state_dict.items()}
    if expected != found:
        missing = sorted(set(expected) - set(found))
        unexpected = sorted(set(found) - set(expected))
        wrong = sorted(k for k in set(expected) & set(found) if expected[k] != found[k])
        holds = describe_checkpoint(state_dict)
        holds = "a SALAD checkpoint of another size" if holds.startswith("a SALAD") else holds
        raise UserError(
            f"{path} holds {holds}, not the released SALAD (DINOv2 ViT-B/14) checkpoint: "
            f"{len(missing)} missing keys {missing[:3]}, "
            f"{len(unexpected)} unexpected {unexpected[:3]}, {len(wrong)} wrong shapes {wrong[:3]}"
        )
    model.load_state_dict({k: v.float() for k, v in state_dict.items()}, strict=True, assign=True)
    return model.to(torch.device(device)).eval()
