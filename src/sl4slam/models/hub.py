"""Where model weights come from: a local file or folder, or the Hugging Face hub cache.

Kept free of torch so that a missing or broken file is reported within seconds, before any model
code loads. Each model names its default file with a :class:`WeightsSource`; ``--weights`` takes a
local path, a hub id (``owner/name``, the source's default file) or ``owner/name:file``.
"""

from __future__ import annotations

import os
import re
import socket
import threading
from dataclasses import dataclass
from pathlib import Path

from ..errors import MissingWeightsError
from .checkpoint import check_weights_file, fetch_command, pass_again

_LOCAL_SUFFIXES = (".pt", ".pth", ".bin", ".ckpt", ".safetensors")


@dataclass(frozen=True)
class WeightsSource:
    """Where a model's released weights live.

    Attributes:
        what: the model's name in messages ("VGGT-1B").
        repo_id: its Hugging Face repository (the default ``--weights``).
        filename: the weights file in that repository.
        folder_names: file names looked for when ``--weights`` is a folder, in order.
        flag: the command-line flag that takes a path.
    """

    what: str
    repo_id: str
    filename: str
    folder_names: tuple[str, ...] = ("model.safetensors", "model.pt")
    flag: str = "--weights"

    def hint(self, repo_id: str | None = None, filename: str | None = None) -> str:
        """How to get the file on a machine with internet access and pass it here."""
        repo_id, filename = repo_id or self.repo_id, filename or self.filename
        return (f"download https://huggingface.co/{repo_id}/resolve/main/{filename} on a machine with internet access "
                f"(or run {fetch_command(repo_id, filename)} there) and {pass_again(self.flag)}")

    def refetch(self, repo_id: str | None = None, filename: str | None = None) -> str:
        """The fix for a broken local copy: delete it and fetch it again."""
        return (f"delete it and fetch it again ({fetch_command(repo_id or self.repo_id, filename or self.filename)}), "
                f"then {pass_again(self.flag)}")


VGGT_WEIGHTS = WeightsSource("VGGT", "facebook/VGGT-1B", "model.pt")
DEFAULT_HUB_ID = VGGT_WEIGHTS.repo_id
DEFAULT_HUB_FILENAME = VGGT_WEIGHTS.filename


def _looks_like_path(weights: str) -> bool:
    return weights.lower().endswith(_LOCAL_SUFFIXES) or weights.startswith((".", "/", "~")) or "\\" in weights


def is_hub_id(weights: str) -> bool:
    """Whether ``weights`` reads as a hub id (``owner/name`` or ``owner/name:file``) rather than a path."""
    return not _looks_like_path(weights) and re.fullmatch(r"[\w.-]+/[\w.-]+(:[\w./-]+)?", weights) is not None


def resolve_weights(weights: str, cache_dir: str | Path | None = None, local_files_only: bool | None = None,
                    source: WeightsSource = VGGT_WEIGHTS) -> Path:
    """Local path of ``weights`` (a file, a folder holding one, or a hub id fetched into / found in
    the hub cache), checked to be a complete weights file (``sl4slam.models.checkpoint``).

    Raises:
        MissingWeightsError: the file does not exist, or the hub file is neither cached nor
            downloadable (offline); the message says how to obtain it.
        WeightsFileError: the file exists but is cut short, corrupt, a folder or unreadable.
    """
    path = Path(weights).expanduser()
    if path.is_file():
        return check_weights_file(path, source.what, source.refetch())
    if path.is_dir():
        for name in source.folder_names:
            if (path / name).is_file():
                return check_weights_file(path / name, source.what, source.refetch())
        raise MissingWeightsError(f"no {' or '.join(source.folder_names)} in folder {path}; {source.hint()}")
    if not is_hub_id(weights):
        raise MissingWeightsError(f"{source.what} weights file not found: {weights}; {source.hint()}")
    repo_id, _, filename = weights.partition(":")
    filename = filename or source.filename
    path = _from_hub(repo_id, filename, cache_dir, local_files_only, source)
    return check_weights_file(path, source.what, source.refetch(repo_id, filename))


def _from_hub(repo_id: str, filename: str, cache_dir, local_files_only, source: WeightsSource) -> Path:
    from huggingface_hub import hf_hub_download

    kwargs = {"cache_dir": str(cache_dir) if cache_dir is not None else None}
    try:  # the cache first: no network at all
        return Path(hf_hub_download(repo_id, filename, local_files_only=True, **kwargs))
    except Exception:  # not cached (huggingface_hub raises its own LocalEntryNotFoundError)
        pass
    what = f"{source.what} weights {repo_id}/{filename}"
    hint = source.hint(repo_id, filename)
    if local_files_only or hub_offline():
        raise MissingWeightsError(f"{what} are not in the Hugging Face cache and downloads are off (HF_HUB_OFFLINE); {hint}")
    if not hub_reachable():
        raise MissingWeightsError(f"{what} are not in the Hugging Face cache and huggingface.co cannot be reached; {hint}")
    try:
        return Path(hf_hub_download(repo_id, filename, **kwargs))
    except Exception as exc:  # unknown repo, HTTP errors, interrupted transfer: all mean "not available here"
        raise MissingWeightsError(f"{what} could not be downloaded ({type(exc).__name__}); {hint}") from None


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


def cached_locally(weights: str, source: WeightsSource, cache_dir: str | Path | None = None) -> Path | None:
    """The local file ``weights`` would load without any network (a path, or a hub file already in
    the cache), or ``None`` (for ``sl4slam models``)."""
    path = Path(weights).expanduser()
    if path.is_file():
        return path
    if path.is_dir():
        return next((path / n for n in source.folder_names if (path / n).is_file()), None)
    if not is_hub_id(weights):
        return None
    from huggingface_hub import try_to_load_from_cache

    repo_id, _, filename = weights.partition(":")
    found = try_to_load_from_cache(repo_id, filename or source.filename,
                                   cache_dir=str(cache_dir) if cache_dir is not None else None)
    return Path(found) if isinstance(found, str) else None
