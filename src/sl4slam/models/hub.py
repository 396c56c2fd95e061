"""Where VGGT weights come from: a local file or folder, or the Hugging Face hub cache.

Kept free of torch so that a missing file is reported within seconds, before any model code loads.
"""

from __future__ import annotations

import os
import re
import socket
import threading
from pathlib import Path

from ..errors import MissingWeightsError

DEFAULT_HUB_ID = "facebook/VGGT-1B"
DEFAULT_HUB_FILENAME = "model.pt"
_LOCAL_SUFFIXES = (".pt", ".pth", ".bin", ".safetensors")


def _download_hint(repo_id: str, filename: str) -> str:
    return (
        f"download https://huggingface.co/{repo_id}/resolve/main/{filename} on a machine with internet access "
        f"(or run `huggingface-cli download {repo_id} {filename}` there) and pass the file with --weights PATH"
    )


def _looks_like_path(weights: str) -> bool:
    return weights.lower().endswith(_LOCAL_SUFFIXES) or weights.startswith((".", "/", "~")) or "\\" in weights


def resolve_weights(weights: str, cache_dir: str | Path | None = None, local_files_only: bool | None = None) -> Path:
    """Local path of ``weights`` (a file, or a hub id fetched into / found in the hub cache).

    Raises:
        MissingWeightsError: the file does not exist, or the hub file is neither cached nor
            downloadable (offline); the message says how to obtain it.
    """
    path = Path(weights).expanduser()
    if path.is_file():
        return path
    if path.is_dir():
        for name in ("model.safetensors", DEFAULT_HUB_FILENAME):
            if (path / name).is_file():
                return path / name
        raise MissingWeightsError(f"no model.safetensors or model.pt in folder {path}; {_download_hint(DEFAULT_HUB_ID, DEFAULT_HUB_FILENAME)}")
    if _looks_like_path(weights) or not re.fullmatch(r"[\w.-]+/[\w.-]+(:[\w./-]+)?", weights):
        raise MissingWeightsError(
            f"VGGT weights file not found: {weights}; {_download_hint(DEFAULT_HUB_ID, DEFAULT_HUB_FILENAME)}"
        )
    repo_id, _, filename = weights.partition(":")
    filename = filename or DEFAULT_HUB_FILENAME
    from huggingface_hub import hf_hub_download

    kwargs = {"cache_dir": str(cache_dir) if cache_dir is not None else None}
    try:  # the cache first: no network at all
        return Path(hf_hub_download(repo_id, filename, local_files_only=True, **kwargs))
    except Exception:  # not cached (huggingface_hub raises its own LocalEntryNotFoundError)
        pass
    if local_files_only or hub_offline():
        raise MissingWeightsError(
            f"VGGT weights {repo_id}/{filename} are not in the Hugging Face cache and downloads are off "
            f"(HF_HUB_OFFLINE); {_download_hint(repo_id, filename)}")
    if not hub_reachable():
        raise MissingWeightsError(
            f"VGGT weights {repo_id}/{filename} are not in the Hugging Face cache and huggingface.co cannot be "
            f"reached; {_download_hint(repo_id, filename)}")
    try:
        return Path(hf_hub_download(repo_id, filename, **kwargs))
    except Exception as exc:  # unknown repo, HTTP errors, interrupted transfer: all mean "not available here"
        raise MissingWeightsError(
            f"VGGT weights {repo_id}/{filename} could not be downloaded ({type(exc).__name__}); "
            f"{_download_hint(repo_id, filename)}"
        ) from None


def hub_offline() -> bool:
    """Whether the Hugging Face hub is switched off (``HF_HUB_OFFLINE`` / ``TRANSFORMERS_OFFLINE``)."""
    return any(os.environ.get(name, "").strip().lower() in ("1", "true", "yes", "on")
               for name in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"))


def hub_reachable(host: str = "huggingface.co", timeout: float = 2.0) -> bool:
    """Whether one TCP connection to the hub succeeds within ``timeout`` seconds (name lookup
    included, which a socket timeout alone does not bound), instead of a download's retries."""
    result: list[bool] = []

    def connect() -> None:
        try:
            with socket.create_connection((host, 443), timeout=timeout):
                result.append(True)
        except OSError:
            result.append(False)

    attempt = threading.Thread(target=connect, daemon=True)
    attempt.start()
    attempt.join(timeout)
    return bool(result and result[0])


