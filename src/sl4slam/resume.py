"""A run's checkpoint, so that ``sl4slam run SRC --out DIR --resume`` continues a killed run.

While a model runs, every submap's frontend output is recorded in ``DIR/frontend_cache/`` as soon as
the model returns it (``sl4slam.frontend.cache.ResumingFrontend``: one ``submap_NNNNN.npz`` each,
written atomically, with a digest of the model's inputs), beside a manifest, ``resume.json``,
written atomically before the run starts: the format version, the source's identity (its frame
count and a digest of five evenly spaced frames) and the run's settled settings.

``--resume`` checks the manifest against the run, each mismatch in one line: the format and the
settings before any frame is read, the source on its five sampled frames, before the model is
loaded. It then runs the whole pipeline again from the source's first frame: a submap whose recording
holds the same inputs is served from it, the others go to the model. Keyframe selection, retrieval,
the alignments and the graph are deterministic, so the outputs are those of a run that was never
interrupted, byte for byte; what is redone is the graph work (no model) and at most the model
forwards that were running when the run was killed.

When a run completes, its manifest is removed, and its recording too unless ``--cache-frontend``
keeps it. ``--no-resumable`` records nothing.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import re
import shutil
from pathlib import Path
from typing import Any

from .atomic import atomic_write_text
from .errors import UserError
from .frontend.cache import frame_digest, recorded_submap, recording_problem
from .paths import RUN_FILES, holds_run
from .resolve import ResolvedConfig

log = logging.getLogger("sl4slam")

RECORDING_DIR = "frontend_cache"
"""The folder of the recording inside a run's ``--out``."""

MANIFEST = "resume.json"
"""The manifest's name inside :data:`RECORDING_DIR`."""

FORMAT = {"name": "sl4slam-resume", "version": 1}

UNCHECKED_SETTINGS = ("output.", "localize.", "submap.keyframes_in_ram", "workers", "ray_address", "overlap")
"""Settings (a key, or a section's prefix) that may differ between a killed run and its resumption:
they decide what is written and how, where memory lives or where and when the model runs, never
what a submap's model is given or what the graph computes."""

_SAMPLES = 5
_TEMPORARY = re.compile(r"^\..+\.\d+\.tmp(\.[^.]+)?$")  # what sl4slam.atomic writes before its rename


def manifest_path(out: Path) -> Path:
    """The manifest of the run in ``out``."""
    return Path(out) / RECORDING_DIR / MANIFEST


def checked_settings(resolved: ResolvedConfig) -> dict[str, Any]:
    """The settled settings a resumption must share, as ``{"section.name": value}`` in the tree's
    order (JSON values), without :data:`UNCHECKED_SETTINGS`."""
    flat: dict[str, Any] = {}

    def walk(values: dict, prefix: str) -> None:
        for key, value in values.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}.")
            elif not f"{prefix}{key}".startswith(UNCHECKED_SETTINGS):
                flat[f"{prefix}{key}"] = value

    walk(json.loads(json.dumps(dataclasses.asdict(resolved.config), default=str)), "")
    return flat


def source_identity(source) -> dict[str, Any]:
    """What identifies a re-readable source: its kind, name, frame count and the SHA-256 of five evenly
    spaced frames (``sl4slam.frontend.cache.frame_digest``; a frame that cannot be read: its error).

    Reading the samples leaves ``source.skipped`` as it was."""
    count = len(source)
    positions = sorted({round(k * (count - 1) / (_SAMPLES - 1)) for k in range(_SAMPLES)}) if count else []
    skipped = list(getattr(source, "skipped", []))
    samples = {}
    for position in positions:
        try:
            samples[str(position)] = frame_digest(source.get(position))
        except UserError as exc:
            samples[str(position)] = "unreadable: " + hashlib.sha256(str(exc).encode()).hexdigest()
    if isinstance(getattr(source, "skipped", None), list):
        source.skipped[:] = skipped
    return {"kind": type(source).__name__, "name": str(source.name), "frames": count, "samples": samples}


def write_manifest(out: Path, resolved: ResolvedConfig, identity: dict[str, Any]) -> Path:
    """Write the manifest of a new run into ``out`` (atomically; the recording's folder is created).

    Args:
        out: the run's output folder.
        resolved: its settled settings.
        identity: its source's :func:`source_identity`.

    Returns:
        The recording's folder.
    """
    from . import __version__

    directory = Path(out) / RECORDING_DIR
    directory.mkdir(parents=True, exist_ok=True)
    manifest = {"format": dict(FORMAT), "sl4slam": __version__, "source": identity,
                "settings": checked_settings(resolved)}
    atomic_write_text(directory / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    return directory


def read_manifest(out: Path) -> dict[str, Any]:
    """The manifest of the killed run in ``out``.

    Raises:
        UserError: ``out`` holds no run, a finished run, no checkpoint, an unreadable manifest or one of
            another format version.
    """
    out = Path(out).expanduser()
    path = manifest_path(out)
    if not out.is_dir():
        raise UserError(f"--resume: --out {out} does not exist, so there is no run to continue; "
                        "start the run without --resume")
    if not path.is_file():
        if _finished(out):
            raise UserError(f"--resume: the run in --out {out} finished (summary.json status complete); "
                            "there is nothing to continue")
        if not holds_run(out):
            raise UserError(f"--resume: --out {out} holds no run to continue; start the run without --resume")
        raise UserError(f"--resume: no checkpoint in --out {out} (no {RECORDING_DIR}/{MANIFEST}: the run there was "
                        "started with --no-resumable, or by an earlier sl4slam); start it again with --overwrite")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
        found = manifest["format"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(f"--resume: the checkpoint {path} cannot be read ({type(exc).__name__}: {exc}); "
                        "start the run again with --overwrite") from None
    if found != FORMAT:
        name, version = (found.get("name"), found.get("version")) if isinstance(found, dict) else (found, None)
        raise UserError(f"--resume: the checkpoint {path} has format {name} version {version}; "
                        f"this sl4slam reads {FORMAT['name']} version {FORMAT['version']}: start the run again with "
                        "--overwrite")
    return manifest


def _finished(out: Path) -> bool:
    try:
        return json.loads((out / "summary.json").read_text(encoding="utf-8")).get("status") == "complete"
    except (OSError, ValueError, AttributeError):
        return False


def check_settings(manifest: dict[str, Any], resolved: ResolvedConfig, out: Path) -> None:
    """Raise a one-line ``UserError`` naming the first setting (in the tree's order) whose settled value
    differs from the killed run's (:func:`checked_settings`)."""
    recorded, current = manifest.get("settings", {}), checked_settings(resolved)
    extra = [k for k in recorded if k not in current and not k.startswith(UNCHECKED_SETTINGS)]
    for key in list(current) + extra:
        if recorded.get(key, "(absent)") != current.get(key, "(absent)"):
            section, _, name = key.rpartition(".")
            owner = getattr(resolved.config, section, None) if section else resolved.config
            flag = owner.flag(name) if hasattr(owner, name) else key
            raise UserError(f"--resume: the settings differ from those of the run in {out}: {flag} (config key {key}) "
                            f"was {recorded.get(key, '(absent)')!r}, now {current.get(key, '(absent)')!r}; resume with "
                            "the same settings, or start again with --overwrite")


def check_source(manifest: dict[str, Any], identity: dict[str, Any], out: Path) -> None:
    """Raise a one-line ``UserError`` when ``identity`` (:func:`source_identity`) is not the source the
    killed run in ``out`` read."""
    recorded = manifest.get("source", {})
    if recorded.get("frames") != identity["frames"]:
        raise UserError(f"--resume: the run in {out} read another source ({recorded.get('name')}, "
                        f"{recorded.get('frames')} frames; this is {identity['name']}, {identity['frames']} frames); "
                        "pass the same SOURCE, --stride and --max-frames, or start again with --overwrite")
    for position, digest in identity["samples"].items():
        if recorded.get("samples", {}).get(position) != digest:
            raise UserError(f"--resume: the run in {out} read another source: frame {position} of {identity['name']} "
                            "is not the one it read; pass the same SOURCE, or start again with --overwrite")


def intact_recordings(directory: Path) -> list[int]:
    """The submap ids whose recordings in ``directory`` are whole as far as their zip directory shows
    (``sl4slam.frontend.cache.recording_problem``). A cut or corrupt one is removed, with one line
    naming it (the model reconstructs that submap again); a file left by a write that was cut short
    (``sl4slam.atomic``'s temporary name) is removed."""
    intact = []
    for path in sorted(Path(directory).iterdir()) if Path(directory).is_dir() else []:
        if _TEMPORARY.match(path.name) and path.is_file():
            path.unlink()
            continue
        submap_id = recorded_submap(path)
        if submap_id is None:
            continue
        problem = recording_problem(path)
        if problem is None:
            intact.append(submap_id)
            continue
        log.warning("%s is cut or corrupt (%s): removed; submap %d is reconstructed by the model", path, problem,
                    submap_id)
        path.unlink()
    return intact


def clear_outputs(out: Path) -> None:
    """Remove what the killed run in ``out`` wrote besides its recording (the resumed run writes every
    output again), and any file a write cut short left there."""
    out = Path(out)
    for name in RUN_FILES:
        path = out / name
        if name == RECORDING_DIR:
            continue
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
    for path in out.iterdir():
        if _TEMPORARY.match(path.name) and path.is_file():
            path.unlink()


def close(out: Path, keep_recording: bool) -> None:
    """The run in ``out`` completed: remove its manifest (first, so that a half-removed recording is
    never taken for a checkpoint), then its recording unless ``keep_recording``."""
    directory = Path(out) / RECORDING_DIR
    path = directory / MANIFEST
    if path.exists():
        path.unlink()
    if not keep_recording and directory.is_dir():
        shutil.rmtree(directory)


def recording_bytes(frames: int, height: int, width: int, extra_per_pixel: int = 0) -> int:
    """Bytes of one submap's uncompressed recording of ``frames`` frames on a ``height`` x ``width``
    grid: float32 depth and confidence, uint8 RGB, float64 cameras, intrinsics, principal point and
    grid map, int64 frame indices, plus ``extra_per_pixel`` bytes per pixel (e.g. 16 for a point
    map with its confidence); the npz container's headers (about 200 bytes per array) excluded."""
    per_frame = height * width * (4 + 4 + 3 + extra_per_pixel) + 8 * (12 + 9 + 2 + 9) + 8
    return frames * per_frame


def resume_line(replayed: int, reconstructed: int, seconds: float) -> str:
    """The console line of a resumed run: what was replayed, in how long, and what the model did."""
    each = f" ({seconds / replayed:.2f} s each)" if replayed else ""
    return (f"sl4slam: resumed: {replayed} submap(s) replayed from the recording in {seconds:.1f} s{each}, "
            f"{reconstructed} reconstructed by the model")


__all__ = ["RECORDING_DIR", "MANIFEST", "FORMAT", "UNCHECKED_SETTINGS", "manifest_path", "checked_settings",
           "source_identity", "write_manifest", "read_manifest", "check_settings", "check_source",
           "intact_recordings", "clear_outputs", "close", "recording_bytes", "resume_line"]
