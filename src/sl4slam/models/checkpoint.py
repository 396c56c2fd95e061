"""Reading weights files: every model's checkpoints go through here.

A weights file that cannot be used ends in one line that names the file, what is wrong with it and
the fix, before any frame is read (:func:`check_weights_file` needs no torch and reads at most the
file's header and its last bytes):

- a folder, a file that cannot be opened (permission), an empty file;
- a download cut short: a ``.safetensors`` file shorter than its header says, or a ``.pt`` zip
  archive without its central directory (it sits at the end of the file);
- bytes that are neither a safetensors header, a zip archive nor a pickle (a corrupt file, or an
  HTML error page saved under the weights' name);
- a checkpoint of another model or size (:func:`describe_checkpoint`, from its key names).

``.pt`` files are read with ``torch.load(weights_only=True)``: tensors and plain containers only,
never code; a file that holds other pickled objects is refused with the way to convert it.

The fix in a message ends in how to hand a good copy back: ``pass it with --weights PATH`` for a
run, or what the command that reads the file sets with :func:`weights_passed_as` (``sl4slam
convert`` takes the path as an argument, not a flag).
"""

from __future__ import annotations

import json
import os
import pickle
import struct
import zipfile
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

from ..errors import UserError

SAFETENSORS_SUFFIX = ".safetensors"
# the first bytes of a torch.save file: a zip archive (torch >= 1.6) or a pickle (the legacy format)
_ZIP_MAGIC = b"PK\x03\x04"
_PICKLE_PROTOCOL = 0x80


class WeightsFileError(UserError):
    """A weights file exists but cannot be used (truncated, corrupt, another model's, unreadable)."""


_PASSED_AS: ContextVar[str | None] = ContextVar("sl4slam_weights_passed_as", default=None)


def pass_again(flag: str = "--weights", it: str = "it", value: str = "PATH", default: str | None = None) -> str:
    """How the user hands weights to the command that needs them, for the end of a fix: "pass
    {it} with {flag} {value}" ("pass it with --weights PATH"), or the words set by the enclosing
    :func:`weights_passed_as` with ``it`` filled in. ``default``, the model's hub id, is named as
    the flag's default, or as what can be passed instead."""
    how = _PASSED_AS.get()
    if how is None:
        return f"pass {it} with {flag} {value}".rstrip() + (f" (default {default})" if default else "")
    return how.format(it=it) + (f" (or its hub id, {default})" if default else "")


@contextmanager
def weights_passed_as(how: str) -> Iterator[None]:
    """Within the block, weights messages end their fix with ``how``, its ``{it}`` filled in (e.g.
    "pass {it} to sl4slam convert"), in place of a flag: for a command that takes weights another way."""
    token = _PASSED_AS.set(how)
    try:
        yield
    finally:
        _PASSED_AS.reset(token)


def fetch_command(repo_id: str, filename: str) -> str:
    """The command that downloads one file of a Hugging Face repository (``hf``, which current
    ``huggingface_hub`` installs; the older ``huggingface-cli`` is gone)."""
    return f"`hf download {repo_id} {filename}`"


def _readable(path: Path, what: str, fix: str) -> int:
    """The size of ``path`` in bytes, after checking that it is a file that can be opened."""
    if path.is_dir():
        raise WeightsFileError(f"{what} weights {path} is a folder, not a weights file; pass the file itself "
                               f"(e.g. {path / 'model.safetensors'}) or {fix}")
    try:
        with open(path, "rb"):
            pass
    except PermissionError:
        raise WeightsFileError(f"{what} weights {path} cannot be read (permission denied); make it readable "
                               f"(chmod u+r) or copy it somewhere you can read") from None
    except OSError as exc:
        raise WeightsFileError(f"{what} weights {path} cannot be opened ({exc.strerror or exc}); {fix}") from None
    return path.stat().st_size


def check_weights_file(path: str | os.PathLike, what: str, fix: str) -> Path:
    """``path`` if it looks like a complete weights file, else :class:`WeightsFileError` (one line).

    Reads the safetensors header (to compare the length it promises with the file's) or the zip
    archive's directory, not the tensors: milliseconds for a multi-gigabyte file.

    Args:
        path: the file.
        what: the model's name, for the message ("VGGT", "SALAD").
        fix: how to get a good copy, appended to every message (e.g. "delete it and fetch it again
            with `hf download facebook/VGGT-1B model.pt`").
    """
    path = Path(path).expanduser()
    size = _readable(path, what, fix)
    if size == 0:
        raise WeightsFileError(f"{what} weights {path} is empty (an interrupted download?); {fix}")
    with open(path, "rb") as handle:
        head = handle.read(8)
    if path.suffix.lower() == SAFETENSORS_SUFFIX:
        _check_safetensors(path, size, what, fix)
    elif head.startswith(_ZIP_MAGIC):
        if not zipfile.is_zipfile(path):
            raise WeightsFileError(f"{what} weights {path} is cut short ({size} bytes, its zip directory is missing): "
                                   f"an interrupted download; {fix}")
    elif head[:1] != bytes([_PICKLE_PROTOCOL]):
        kind = "a web page" if head.lstrip().lower().startswith((b"<", b"<!doc")) else "unknown bytes"
        raise WeightsFileError(f"{what} weights {path} is not a PyTorch or safetensors checkpoint (it starts with "
                               f"{kind}: a corrupt file or a failed download); {fix}")
    return path


def _check_safetensors(path: Path, size: int, what: str, fix: str) -> None:
    """Header length, JSON header and data length of a ``.safetensors`` file against its size."""
    cut = f"{what} weights {path} is cut short"
    if size < 8:
        raise WeightsFileError(f"{cut} ({size} bytes, not even a header): an interrupted download; {fix}")
    with open(path, "rb") as handle:
        (header_length,) = struct.unpack("<Q", handle.read(8))
        if header_length > 100_000_000:  # the format caps its header at 100 MB
            raise WeightsFileError(f"{what} weights {path} is not a safetensors file (corrupt header); {fix}")
        if 8 + header_length > size:
            raise WeightsFileError(f"{cut} ({size} bytes, its header alone needs {8 + header_length}): "
                                   f"an interrupted download; {fix}")
        try:
            header = json.loads(handle.read(header_length))
        except (ValueError, UnicodeDecodeError):
            raise WeightsFileError(f"{what} weights {path} is not a safetensors file (corrupt header); {fix}") from None
    if not isinstance(header, dict):
        raise WeightsFileError(f"{what} weights {path} is not a safetensors file (corrupt header); {fix}")
    ends = [entry["data_offsets"][1] for key, entry in header.items()
            if key != "__metadata__" and isinstance(entry, dict) and "data_offsets" in entry]
    expected = 8 + header_length + (max(ends) if ends else 0)
    if size < expected:
        raise WeightsFileError(f"{cut} ({size} of {expected} bytes): an interrupted download; {fix}")


def read_checkpoint(path: str | os.PathLike, what: str, fix: str) -> tuple[dict[str, Any], dict]:
    """Tensors and metadata of a ``.safetensors`` or ``.pt`` / ``.pth`` / ``.ckpt`` file, on the CPU.

    Returns ``(state_dict, metadata)``: the tensors (a ``.pt`` payload's ``"model"`` or
    ``"state_dict"`` or ``"weights"`` entry when it has one: VGGT's, Lightning's and PE's forms), and the safetensors
    metadata (strings) or the ``.pt`` payload's other top-level entries. ``.pt`` files are
    memory-mapped where torch can.

    Raises:
        WeightsFileError: see :func:`check_weights_file`; also a file torch cannot read, pickled
            objects other than tensors, or no tensors at all.
    """
    import torch

    path = check_weights_file(path, what, fix)
    if path.suffix.lower() == SAFETENSORS_SUFFIX:
        from safetensors import SafetensorError, safe_open
        from safetensors.torch import load_file

        try:
            with safe_open(str(path), framework="pt") as handle:
                metadata = dict(handle.metadata() or {})
            return load_file(str(path), device="cpu"), metadata
        except (SafetensorError, OSError, ValueError) as exc:
            raise WeightsFileError(f"{what} weights {path} cannot be read ({_first_line(exc)}); {fix}") from None
    try:
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError as exc:
            if "mmap" not in str(exc).lower():
                raise
            payload = torch.load(path, map_location="cpu", weights_only=True)  # legacy format: no mmap
    except pickle.UnpicklingError as exc:
        raise WeightsFileError(
            f"{what} weights {path} hold pickled objects other than tensors, which are not loaded for safety "
            f"({_first_line(exc)}); load a trusted copy with torch and save its state_dict() alone, or to "
            ".safetensors") from None
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise WeightsFileError(f"{what} weights {path} cannot be read, a corrupt or cut file "
                               f"({_first_line(exc)}); {fix}") from None
    if not isinstance(payload, dict):
        raise WeightsFileError(f"{what} weights {path} do not hold a state dict (found {type(payload).__name__}); {fix}")
    tensors: Mapping = payload
    for key in ("model", "state_dict", "weights"):  # "weights": the Perception Encoder releases
        if isinstance(payload.get(key), dict):
            tensors = payload[key]
            break
    state_dict = {k: v for k, v in tensors.items() if isinstance(v, torch.Tensor)}
    if not state_dict:
        raise WeightsFileError(f"{what} weights {path} hold no tensors; {fix}")
    metadata = {k: v for k, v in payload.items() if v is not tensors and not isinstance(v, torch.Tensor)}
    return state_dict, metadata


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0].strip()}" if text else type(exc).__name__


# What a state dict holds, told from its key names: ``(description, test)`` in order, the most
# specific first. Each model adds its line here.
CHECKPOINT_KINDS: list[tuple[str, Callable[[Mapping[str, Any]], bool]]] = [
    # Depth Anything 3 (keys "model.backbone.pretrained.*"; the any-view sizes by their width)
    ("a Depth Anything 3 nested checkpoint (DA3NESTED: any-view + metric)",
     lambda keys: any(k.startswith("model.da3_metric.") for k in keys)),
    ("a Depth Anything 3 monocular or metric checkpoint (DA3MONO / DA3METRIC: single view, no cameras)",
     lambda keys: "model.backbone.pretrained.cls_token" in keys and "model.backbone.pretrained.camera_token" not in keys),
    ("a Depth Anything 3 Small checkpoint (DA3-SMALL)",
     lambda keys: keys["model.backbone.pretrained.camera_token"].shape[-1] == 384),
    ("a Depth Anything 3 Base checkpoint (DA3-BASE)",
     lambda keys: keys["model.backbone.pretrained.camera_token"].shape[-1] == 768),
    ("a Depth Anything 3 Large checkpoint (DA3-LARGE or DA3-LARGE-1.1)",
     lambda keys: keys["model.backbone.pretrained.camera_token"].shape[-1] == 1024),
    ("a Depth Anything 3 Giant checkpoint (DA3-GIANT or DA3-GIANT-1.1)",
     lambda keys: keys["model.backbone.pretrained.camera_token"].shape[-1] == 1536),
    ("a Depth Anything 3 any-view checkpoint of an unreleased size",
     lambda keys: "model.backbone.pretrained.camera_token" in keys),
    ("a Pi3X checkpoint", lambda keys: "metric_token" in keys and "camera_decoder.projects.weight" in keys),
    ("a π³ (Pi3) checkpoint", lambda keys: "register_token" in keys and "camera_decoder.projects.weight" in keys),
    ("a VGGT checkpoint", lambda keys: "aggregator.camera_token" in keys),
    ("a SALAD checkpoint (DINOv2 + SALAD aggregator)",
     lambda keys: any(k.startswith("aggregator.") for k in keys) and any(k.startswith("backbone.") for k in keys)),
]


def describe_checkpoint(state_dict: Mapping[str, Any]) -> str:
    """What ``state_dict`` holds, in words ("a VGGT checkpoint"), from its key names; "weights of
    an unknown model" when no known layout matches."""
    for description, test in CHECKPOINT_KINDS:
        try:
            if test(state_dict):
                return description
        except (KeyError, AttributeError, IndexError):
            continue
    sample = ", ".join(sorted(state_dict)[:3])
    return f"weights of an unknown model (keys like {sample})"


def write_checkpoint(state_dict: Mapping[str, Any], path: str | os.PathLike, config_key: str,
                     config_json: str | None = None) -> Path:
    """Write a torch state dict to ``path``: ``.safetensors`` with the model's config (JSON) in the
    metadata under ``config_key``, or a ``.pt`` holding ``{"model": tensors, config_key: config}``
    (by suffix). Tensors that share storage get their own copy (safetensors refuses shared memory)."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors: dict = {}
    seen: set[int] = set()
    for key, value in state_dict.items():
        value = value.detach().cpu().contiguous()
        pointer = value.untyped_storage().data_ptr()
        tensors[key] = value.clone() if pointer in seen else value
        seen.add(pointer)
    if path.suffix == ".safetensors":
        from safetensors.torch import save_file

        metadata = {"format": "pt"}
        if config_json is not None:
            metadata[config_key] = config_json
        save_file(tensors, str(path), metadata=metadata)
    else:
        payload: dict = {"model": tensors}
        if config_json is not None:
            payload[config_key] = json.loads(config_json)
        torch.save(payload, path)
    return path
