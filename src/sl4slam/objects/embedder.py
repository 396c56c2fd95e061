"""Image and text embeddings for object queries: Perception Encoder PE-Core-L14-336 (``sl4slam.objects.pe_core``)
behind the :class:`~sl4slam.objects.interfaces.ImageEmbedder` interface, and the run-time collector that
embeds each new keyframe while mapping (``--objects``) and writes ``objects/embeddings.npz``.

Names :func:`make_embedder` takes (the name is stored with the embeddings, and a query embeds its
text with the embedder of that name):

- ``pe-core-l14-336``: the published weights (``facebook/PE-Core-L14-336``, Apache-2.0), downloaded on
  first use; the tokenizer's byte-pair merges come from ``openai/clip-vit-large-patch14``
  (``merges.txt``, the CLIP vocabulary PE uses).
- ``tiny-random``: a tiny PE-Core of seeded random weights with the 514-token byte vocabulary: the
  same code path, offline and fast, for tests (its embeddings mean nothing).

torch is imported when an embedder is made, not when this module is imported.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..errors import MissingWeightsError
from ..models.hub import WeightsSource, hub_offline, hub_reachable

if TYPE_CHECKING:
    from ..registry import ObjectModelEntry
    from .interfaces import ImageEmbedder

PE_CORE_NAME = "pe-core-l14-336"
TINY_RANDOM_NAME = "tiny-random"
EMBEDDER_NAMES = (PE_CORE_NAME, TINY_RANDOM_NAME)
PE_CORE_WEIGHTS = WeightsSource("PE-Core-L14-336", "facebook/PE-Core-L14-336", "PE-Core-L14-336.pt",
                                folder_names=("PE-Core-L14-336.pt", "model.safetensors", "model.pt"),
                                flag="--objects-weights")
CLIP_MERGES = ("openai/clip-vit-large-patch14", "merges.txt")
"""Where the CLIP byte-pair merges are fetched from (hub repository, file)."""
PE_CORE_PARAMETERS = 671_137_793
"""Parameters of PE-Core-L14-336, both towers (counted from the model built here)."""


class PECoreEmbedder:
    """A PE-Core model and its tokenizer as an ``ImageEmbedder``.

    Args:
        model: a ``sl4slam.objects.pe_core.PECore`` in eval mode on ``device``.
        tokenizer: its ``ClipTokenizer``.
        name: the name stored with the embeddings.
        device: where the model runs.
        batch: images per forward.
    """

    def __init__(self, model, tokenizer, name: str, device: str = "cpu", batch: int = 8) -> None:
        self.model = model
        self.tokenizer = tokenizer
        self.name = name
        self.device = device
        self.batch = max(1, int(batch))
        self.dim = int(model.config.dim)
        self.image_size = int(model.config.vision.image_size)

    def embed_images(self, images: list[np.ndarray]) -> np.ndarray:
        """``(N, D)`` float32 unit embeddings of ``N`` ``(H, W, 3)`` uint8 RGB images."""
        import torch

        from .pe_core import preprocess_images

        out = np.zeros((len(images), self.dim), dtype=np.float32)
        for start in range(0, len(images), self.batch):
            pixels = preprocess_images(images[start:start + self.batch], self.image_size).to(self.device)
            with torch.inference_mode():
                out[start:start + len(pixels)] = self.model.encode_images(pixels).cpu().numpy()
        return out

    def embed_texts(self, texts: list[str]) -> np.ndarray:
        """``(M, D)`` float32 unit embeddings of ``M`` texts (cut to the model's 32 tokens)."""
        import torch

        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        with torch.inference_mode():
            return self.model.encode_texts(self.tokenizer(list(texts)).to(self.device)).cpu().numpy().astype(np.float32)


def make_embedder(name: str = PE_CORE_NAME, device: str = "cpu", weights: str | None = None,
                  random_init: bool = False, tokenizer: str | None = None, batch: int = 8) -> "ImageEmbedder":
    """An image-and-text embedder by name.

    Args:
        name: ``pe-core-l14-336`` or ``tiny-random`` (see the module doc).
        device: "cpu", "cuda" or "cuda:N".
        weights: PE-Core weights: a file, a folder holding one, or a hub id (``owner/name`` or
            ``owner/name:file``); ``None``: ``facebook/PE-Core-L14-336``. Ignored by ``tiny-random``.
        random_init: the full-size model with seeded random weights and the byte vocabulary (no
            download at all: for measuring cost).
        tokenizer: a CLIP ``merges.txt`` or ``bpe_simple_vocab_16e6.txt.gz`` to use instead of the
            hub's ``merges.txt``.
        batch: images per forward.

    Returns:
        An ``ImageEmbedder`` (``name``, ``dim``, ``embed_images``, ``embed_texts``).

    Raises:
        UserError: an unknown name; ``MissingWeightsError`` (one line, with how to get them) when the
            weights or the merges are neither here nor downloadable; ``WeightsFileError`` for a
            corrupt, cut or foreign weights file.
    """
    from ..errors import UserError

    if name not in EMBEDDER_NAMES:
        raise UserError(f"--objects-embedder (config key objects.embedder) must be one of {', '.join(EMBEDDER_NAMES)}, "
                        f"got {name!r}")
    import torch

    from ..models.random_weights import init_random_weights
    from .pe_core import PE_CORE_L14_336, PE_CORE_TINY, ClipTokenizer, PECore

    if name == TINY_RANDOM_NAME or random_init:
        config = PE_CORE_TINY if name == TINY_RANDOM_NAME else PE_CORE_L14_336
        with torch.device("meta"):
            model = PECore(config)
        init_random_weights(model, seed=0)
        words = ClipTokenizer([], config.text.context_length)
        return PECoreEmbedder(model.to(device).eval(), words, name, device, batch)
    model = load_pe_core(weights or PE_CORE_WEIGHTS.repo_id, device)
    merges = Path(tokenizer) if tokenizer else fetch_hub_file(*CLIP_MERGES, what="CLIP tokenizer merges",
                                                                flag="--objects-tokenizer")
    try:
        words = ClipTokenizer.from_merges_file(merges, PE_CORE_L14_336.text.context_length)
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise UserError(f"CLIP tokenizer merges {merges} cannot be read ({exc}); delete the file and fetch it again "
                        f"(`hf download {CLIP_MERGES[0]} {CLIP_MERGES[1]}`)") from None
    return PECoreEmbedder(model, words, name, device, batch)


def load_pe_core(weights: str, device: str = "cpu", config=None):
    """The PE-Core model of ``weights`` (see :func:`make_embedder`), eval mode, fp32, on ``device``.

    Args:
        weights: a file, a folder holding one, or a hub id, in the published layout.
        device: where the model runs.
        config: its ``sl4slam.objects.pe_core.PECoreConfig`` (``None``: PE-Core-L14-336).

    Raises:
        MissingWeightsError, WeightsFileError, UserError: see :func:`make_embedder` (a checkpoint of
            another model: its key counts, one line).
    """
    import torch

    from ..models.checkpoint import read_checkpoint
    from ..models.hub import resolve_weights
    from ..models.loading import load_state_dict_into, ready_for_inference
    from .pe_core import PE_CORE_L14_336, PECore, published_to_ours

    path = resolve_weights(weights, source=PE_CORE_WEIGHTS)
    state_dict, _ = read_checkpoint(path, PE_CORE_WEIGHTS.what, PE_CORE_WEIGHTS.refetch())
    with torch.device("meta"):
        model = PECore(config or PE_CORE_L14_336)
    load_state_dict_into(model, published_to_ours(state_dict), PE_CORE_WEIGHTS.what, assign=True)
    return ready_for_inference(model.float(), device)


def fetch_hub_file(repo_id: str, filename: str, what: str, flag: str) -> Path:
    """A small hub file, from the cache or downloaded; one-line ``MissingWeightsError`` when it is
    neither cached nor downloadable (``HF_HUB_OFFLINE``, no network, unknown file)."""
    from huggingface_hub import hf_hub_download

    try:
        return Path(hf_hub_download(repo_id, filename, local_files_only=True))
    except Exception:  # not cached
        pass
    hint = (f"download https://huggingface.co/{repo_id}/resolve/main/{filename} on a machine with internet access "
            f"(or run `hf download {repo_id} {filename}` there) and pass it with {flag} PATH")
    if hub_offline():
        raise MissingWeightsError(f"{what} {repo_id}/{filename} are not in the Hugging Face cache and downloads are off "
                                  f"(HF_HUB_OFFLINE); {hint}")
    if not hub_reachable():
        raise MissingWeightsError(f"{what} {repo_id}/{filename} are not in the Hugging Face cache and huggingface.co "
                                  f"cannot be reached; {hint}")
    try:
        return Path(hf_hub_download(repo_id, filename))
    except Exception as exc:
        raise MissingWeightsError(f"{what} {repo_id}/{filename} could not be downloaded ({type(exc).__name__}); {hint}") from None


def check_embedder_files(settings) -> None:
    """Find (or download) the files the ``[objects]`` settings' embedder needs, without loading it:
    a run calls this before reading any frame. Raises what :func:`make_embedder` raises for them."""
    from ..errors import UserError
    from ..models.hub import resolve_weights

    if not settings.enabled or settings.embedder != PE_CORE_NAME:
        return
    resolve_weights(settings.weights or PE_CORE_WEIGHTS.repo_id, source=PE_CORE_WEIGHTS)
    if settings.tokenizer:
        if not Path(settings.tokenizer).expanduser().is_file():
            raise UserError(f"--objects-tokenizer (config key objects.tokenizer) file not found: {settings.tokenizer}")
    else:
        fetch_hub_file(*CLIP_MERGES, what="CLIP tokenizer merges", flag="--objects-tokenizer")


class KeyframeEmbedder:
    """Embeds the keyframes a run stores, a submap's new keyframes in one call, and writes them.

    Args:
        embedder: any ``ImageEmbedder``.
    """

    def __init__(self, embedder: "ImageEmbedder") -> None:
        self.embedder = embedder
        self.frame_index: list[int] = []
        self.vectors: list[np.ndarray] = []
        self._row: dict[int, int] = {}  # frame index -> its row
        self.seconds = 0.0

    def __len__(self) -> int:
        return len(self.frame_index)

    def add(self, frame_indices: Sequence[int], images: Sequence[np.ndarray]) -> None:
        """Embed ``images`` (``(H, W, 3)`` uint8 RGB) of the keyframes ``frame_indices`` (a keyframe
        embedded before is embedded again and replaces its row)."""
        if not len(frame_indices):
            return
        start = time.perf_counter()
        vectors = np.asarray(self.embedder.embed_images([np.asarray(image) for image in images]), dtype=np.float32)
        self.seconds += time.perf_counter() - start
        for index, vector in zip(frame_indices, vectors):
            index = int(index)
            if index in self._row:
                self.vectors[self._row[index]] = vector
            else:
                self._row[index] = len(self.frame_index)
                self.frame_index.append(index)
                self.vectors.append(vector)

    def write(self, out_dir: str | Path, keep: Sequence[int] | None = None) -> Path | None:
        """Write ``objects/embeddings.npz`` into the result folder ``out_dir`` (``keep``: only these
        frames, the keyframes of the result). Returns the path, ``None`` when there is nothing to write."""
        from .store import write_embeddings

        kept = None if keep is None else {int(k) for k in keep}
        rows = [i for i, index in enumerate(self.frame_index) if kept is None or index in kept]
        if not rows:
            return None
        try:
            return write_embeddings(out_dir, np.array([self.frame_index[i] for i in rows], dtype=np.int64),
                                    np.stack([self.vectors[i] for i in rows]), self.embedder.name)
        except OSError as exc:
            from ..errors import UserError

            raise UserError(f"cannot write the keyframe embeddings into {out_dir}: {exc.strerror or exc}") from None

    def record(self, out_dir: str | Path) -> dict:
        """Write the embeddings (:meth:`write`) and return what the run's summary records of them:
        the model, the dimension, the keyframes embedded, the seconds spent and the file."""
        path = self.write(out_dir)
        return {"model": self.embedder.name, "dim": int(self.embedder.dim), "keyframes": len(self),
                "seconds": round(self.seconds, 3), "file": str(path.relative_to(out_dir)) if path else None}


def build_keyframe_embedder(settings, device: str = "cpu") -> KeyframeEmbedder:
    """The collector of a run's ``[objects]`` settings (``sl4slam.objects.settings.ObjectsConfig``)."""
    embedder = make_embedder(settings.embedder, device=device, weights=settings.weights or None,
                             tokenizer=settings.tokenizer or None, batch=settings.batch)
    return KeyframeEmbedder(embedder)


def registry_entry() -> "ObjectModelEntry":
    """PE-Core-L14-336's line in ``sl4slam models``."""
    from ..registry import ObjectModelEntry

    return ObjectModelEntry(name=PE_CORE_NAME, weights=PE_CORE_WEIGHTS, licence="Apache-2.0",
                            parameters=PE_CORE_PARAMETERS, role="image/text embedder for --objects",
                            description="Perception Encoder PE-Core-L14-336: keyframe and phrase embeddings "
                                        "for object queries")
