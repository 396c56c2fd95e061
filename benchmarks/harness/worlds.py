"""Synthetic sequences rendered once and reused by every benchmark, and replays of a sequence.

:func:`synthetic_world` names a rendering by its parameters (size, frames, seed, layout) and keeps it
in ``benchmarks/out/worlds/``: the first benchmark that asks renders it, the others read it.
:func:`suite_sequence` does the same for a sequence of the development suite
(:mod:`sl4slam.synthetic.suite`, kept in ``benchmarks/out/suite/``) and finds its real ones in the
shared data. :class:`LapSource` replays a looping sequence lap after lap (long runs from a short
rendering).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
from pathlib import Path
from typing import Iterator

from .places import OUT, SHARED_DATA

WORLDS = OUT / "worlds"
"""Where :func:`synthetic_world` keeps its renderings."""
SUITE_OUT = OUT / "suite"
"""Where :func:`suite_sequence` keeps the suite's renderings."""
LAYOUTS = ("tum", "7scenes")


def world_name(width: int, height: int, frames: int = 600, seed: int = 0, layout: str = "tum") -> str:
    """The cache folder name of a rendering: ``synthetic_320x240``, with ``_<frames>f``, ``_seed<seed>``
    and ``_7scenes`` added where they differ from 600 frames, seed 0 and the TUM layout."""
    name = f"synthetic_{int(width)}x{int(height)}"
    if int(frames) != 600:
        name += f"_{int(frames)}f"
    if int(seed) != 0:
        name += f"_seed{int(seed)}"
    if layout != "tum":
        name += f"_{layout}"
    return name


def _matches(folder: Path, width: int, height: int, frames: int, seed: int, layout: str) -> bool:
    """Whether ``folder`` holds a complete rendering with exactly these parameters."""
    try:
        metadata = json.loads((folder / "synthetic.json").read_text())
    except (OSError, ValueError):
        return False
    wanted = {"num_frames": int(frames), "width": int(width), "height": int(height), "seed": int(seed)}
    if any(metadata.get(key) != value for key, value in wanted.items()):
        return False
    return (metadata.get("layout") == "7scenes") == (layout == "7scenes")


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """Hold an exclusive lock next to ``folder`` so that two processes do not render it at once."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(folder.parent / f".{folder.name}.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def synthetic_world(width: int = 320, height: int = 240, frames: int = 600, seed: int = 0, *, layout: str = "tum",
                    folder: str | Path | None = None) -> Path:
    """The synthetic world ``seed`` rendered along its looping path, written once and reused.

    Args:
        width, height: image size in pixels.
        frames: frames along the path (the last pose equals the first).
        seed: world and path seed.
        layout: "tum" (a TUM RGB-D folder, :func:`sl4slam.synthetic.write_synthetic_sequence`) or
            "7scenes" (a 7-Scenes sequence folder, :func:`sl4slam.synthetic.write_seven_scenes_sequence`).
        folder: where the rendering lives; default ``benchmarks/out/worlds/<world_name(...)>``.

    Returns:
        The folder. A folder whose ``synthetic.json`` records these parameters is returned as it is;
        anything else there is replaced by a fresh rendering (written aside and renamed into place).
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    folder = Path(folder) if folder is not None else WORLDS / world_name(width, height, frames, seed, layout)
    if _matches(folder, width, height, frames, seed, layout):
        return folder
    from sl4slam.synthetic import write_seven_scenes_sequence, write_synthetic_sequence

    write = write_seven_scenes_sequence if layout == "7scenes" else write_synthetic_sequence
    with _locked(folder):
        if not _matches(folder, width, height, frames, seed, layout):  # another process may have just written it
            write(folder, num_frames=frames, width=width, height=height, seed=seed, overwrite=True)
    return folder


def suite_folder_name(name: str, width: int, height: int, frames: int | None = None, default_frames: int | None = None) -> str:
    """The cache folder name of a suite sequence's rendering: its name, with ``_<frames>f`` and
    ``_<width>x<height>`` added where they differ from its own length and the suite's size."""
    from sl4slam.synthetic.suite import SUITE_HEIGHT, SUITE_WIDTH

    folder = name
    if frames is not None and int(frames) != default_frames:
        folder += f"_{int(frames)}f"
    if (int(width), int(height)) != (SUITE_WIDTH, SUITE_HEIGHT):
        folder += f"_{int(width)}x{int(height)}"
    return folder


def suite_sequence(name: str, width: int | None = None, height: int | None = None, frames: int | None = None,
                   *, root: str | Path | None = None) -> Path:
    """The folder of a sequence of the suite: a synthetic one rendered once and reused, a real one
    in the shared data (``../shared/data``).

    Args:
        name: the sequence's name in :data:`sl4slam.synthetic.suite.SUITE`.
        width, height: image size of a synthetic sequence (default: the suite's, 256x192).
        frames: a synthetic sequence's length (default: its own); a shorter rendering of the same
            style and seed, for quick runs.
        root: where renderings live (default ``benchmarks/out/suite``).

    Returns:
        The folder (a real sequence's may not exist: callers skip it then).
    """
    from sl4slam.synthetic.suite import SUITE_HEIGHT, SUITE_WIDTH, get_sequence, is_rendered

    sequence = get_sequence(name)
    if sequence.real:
        return SHARED_DATA / sequence.folder
    width, height = width or SUITE_WIDTH, height or SUITE_HEIGHT
    frames = int(frames or sequence.frames)
    folder = Path(root or SUITE_OUT) / suite_folder_name(name, width, height, frames, sequence.frames)
    if is_rendered(folder, sequence, width, height, frames):
        return folder
    from sl4slam.synthetic import write_synthetic_sequence

    with _locked(folder):
        if not is_rendered(folder, sequence, width, height, frames):
            write_synthetic_sequence(folder, num_frames=frames, width=width, height=height, seed=sequence.seed,
                                     overwrite=True, style=sequence.style)
    return folder


class LapSource:
    """A looping sequence replayed lap after lap (its path ends where it starts), as one long source.

    Args:
        base: the frame source of one lap (``sl4slam.io.open_source``).
        laps: how many laps the source holds.
        preload: decode every frame of the lap once, up front, so that a replay does not time image
            decoding.
        folder: with ``preload``, keep the decoded frames there as raw ``.npy`` arrays and read each
            back when it is asked for (from the page cache after the first lap), instead of holding
            them in the process: the replay's resident memory is then the run's alone. ``None``:
            held in RAM.

    Frame ``i`` is frame ``i % len(base)`` of the lap with index ``i`` and timestamp ``i / 30`` s.
    """

    def __init__(self, base, laps: int, preload: bool = False, folder: str | Path | None = None) -> None:
        self.base = base
        self.laps = laps
        self.name = f"{base.name} x{laps} laps"
        self.skipped: list[str] = []
        self._frames = None
        self._folder = Path(folder) if folder is not None and preload else None
        if preload:
            self._frames = [self._keep(i, base.get(i)) for i in range(len(base))]

    def _keep(self, index: int, frame):
        """The frame as the replay keeps it: itself, or (with a folder) its arrays written to files
        and replaced by their paths."""
        if self._folder is None:
            return frame
        import dataclasses

        import numpy as np

        self._folder.mkdir(parents=True, exist_ok=True)
        files = {}
        for name in ("rgb", "depth"):
            array = getattr(frame, name)
            if array is not None:
                files[name] = self._folder / f"{index:06d}_{name}.npy"
                np.save(files[name], array)
        return dataclasses.replace(frame, rgb=files["rgb"], depth=files.get("depth"))

    @property
    def has_ground_truth(self) -> bool:
        """Whether the lap has ground-truth poses."""
        return self.base.has_ground_truth

    def __len__(self) -> int:
        return len(self.base) * self.laps

    @property
    def preloaded_bytes(self) -> int:
        """Bytes of the preloaded lap's images and depth maps held in RAM (0 when not preloaded, or
        kept in files): memory of the replay itself, which a run reading its frames from a source
        does not hold."""
        if self._folder is not None:
            return 0
        frames = self._frames or []
        return sum(f.rgb.nbytes + (f.depth.nbytes if f.depth is not None else 0) for f in frames)

    def get(self, index: int):
        """Frame ``index`` of the replay (an :class:`sl4slam.types.Frame`)."""
        from sl4slam.types import Frame

        lap_index = index % len(self.base)
        frame = self._frames[lap_index] if self._frames is not None else self.base.get(lap_index)
        rgb, depth = frame.rgb, frame.depth
        if self._folder is not None:
            import numpy as np

            rgb, depth = np.load(rgb), (np.load(depth) if depth is not None else None)
        return Frame(index=index, timestamp=index / 30.0, rgb=rgb, depth=depth,
                     T_world_cam=frame.T_world_cam, K=frame.K, path=frame.path)

    def __iter__(self):
        return (self.get(i) for i in range(len(self)))


RANDOM_FRAME_HW = (480, 640)
"""Height and width of :func:`random_frames`."""


def random_frames(count: int, seed: int) -> list:
    """``count`` seeded 640x480 uint8 RGB frames of smooth ramps plus noise, shifting from frame to
    frame (some structure for a model's reference-view choice; the cost of a forward does not depend
    on the content)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    height, width = RANDOM_FRAME_HW
    ys, xs = np.mgrid[0:height, 0:width]
    frames = []
    for index in range(count):
        base = np.stack([xs // 3 + 9 * index, ys // 2, (xs + ys) // 5 + 17 * index], axis=-1) % 256
        frames.append(np.clip(base + rng.integers(-25, 26, base.shape), 0, 255).astype(np.uint8))
    return frames
