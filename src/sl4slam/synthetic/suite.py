"""The development suite: named sequences with fixed seeds, and their tune / validate split.

:data:`SUITE` lists every sequence: each style of :mod:`sl4slam.synthetic.styles` with the seeds
:data:`SUITE_SEEDS` at the style's default length, and the real sequences (TUM RGB-D) by their
folder names. :func:`write_suite` (``sl4slam synth --suite ROOT``) renders the synthetic ones as TUM
RGB-D folders ``ROOT/<name>`` at :data:`SUITE_WIDTH` x :data:`SUITE_HEIGHT`.

The split (:func:`split_of`, rule in :data:`SPLIT_RULE`) is fixed before any tuning: settings are
chosen on the ``tune`` half only, and the ``validate`` half is only reported.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from sl4slam.errors import UserError
from sl4slam.synthetic.styles import STYLES

SUITE_WIDTH, SUITE_HEIGHT = 256, 192
"""Image size of the suite's renderings: 4:3 like TUM RGB-D, small enough to render the whole suite in
about 13 minutes on two cores (27 ms per frame, PNG files included), large enough for Lucas-Kanade
keyframes and ORB retrieval."""
SUITE_SEEDS = (0, 1)
"""The seeds each style is in the suite with: one even (tune) and one odd (validate)."""
SPLITS = ("tune", "validate")
"""The two halves of the suite."""
SPLIT_RULE = ("tune: the synthetic sequences of even seed; validate: those of odd seed and every real sequence. "
              "Each style is in the suite with one seed of each parity, so both halves hold every style alike, "
              "and a sequence's half follows from the sequence alone, so adding sequences moves none.")
"""Why the split is what it is, in one line."""


@dataclass(frozen=True)
class SuiteSequence:
    """One sequence of the suite.

    Attributes:
        name: unique; ``<style>-s<seed>`` for a synthetic sequence.
        style: its style (None for a real sequence).
        seed: world and path seed (synthetic only).
        frames: its length (None for a real sequence: every frame of its folder).
        folder: a real sequence's folder name under the data root (None for a synthetic one).
        description: one line on what it is.
    """

    name: str
    style: str | None
    seed: int
    frames: int | None
    folder: str | None
    description: str

    @property
    def real(self) -> bool:
        """Whether it is a recorded sequence rather than a rendered one."""
        return self.style is None

    @property
    def split(self) -> str:
        """Its half of the suite (:func:`split_of`)."""
        return split_of(self)


def split_of(sequence: SuiteSequence) -> str:
    """The half of the suite a sequence belongs to, by :data:`SPLIT_RULE`: "tune" or "validate"."""
    if sequence.real:
        return "validate"
    return "tune" if sequence.seed % 2 == 0 else "validate"


def _synthetic(style: str, seed: int) -> SuiteSequence:
    chosen = STYLES[style]
    return SuiteSequence(f"{style}-s{seed}", style, seed, chosen.frames, None, chosen.description)


REAL_SEQUENCES = (
    SuiteSequence("tum-fr1-desk", None, 0, None, "tum_rgbd_fr1_desk",
                  "TUM RGB-D fr1/desk: handheld sweeps over an office desk (real images, motion-capture truth)"),
    SuiteSequence("tum-fr1-xyz-37", None, 0, None, "tum_rgbd_fr1_xyz_first37",
                  "TUM RGB-D fr1/xyz, its first 37 frames: small translations along the axes over a desk"),
)
"""The real sequences of the suite, by their folder names under the data root."""

SUITE = tuple(_synthetic(style, seed) for style in STYLES for seed in SUITE_SEEDS) + REAL_SEQUENCES
"""Every sequence of the suite, in table order."""


def suite_sequences(split: str | None = None, names: list[str] | None = None) -> list[SuiteSequence]:
    """The suite's sequences, in table order.

    Args:
        split: "tune", "validate" or None (both).
        names: only these (each must be in the suite).

    Raises:
        UserError: an unknown split or name (the line lists what is accepted).
    """
    if split is not None and split not in SPLITS:
        raise UserError(f"unknown split {split!r}; splits: {', '.join(SPLITS)}")
    chosen = [s for s in SUITE if split is None or s.split == split]
    if names:
        unknown = [n for n in names if n not in {s.name for s in SUITE}]
        if unknown:
            raise UserError(f"not in the suite: {', '.join(unknown)}; sequences: {', '.join(s.name for s in SUITE)}")
        chosen = [s for s in chosen if s.name in names]
    return chosen


def get_sequence(name: str) -> SuiteSequence:
    """The suite's sequence called ``name`` (raises ``UserError`` listing the names otherwise)."""
    return suite_sequences(names=[name])[0]


def is_rendered(folder: Path, sequence: SuiteSequence, width: int, height: int, frames: int | None = None) -> bool:
    """Whether ``folder`` holds a finished rendering of a synthetic sequence at this size (and length,
    default the sequence's own) along the camera path its style gives now."""
    from sl4slam.synthetic.sequence import path_digest
    from sl4slam.synthetic.styles import style_path

    try:
        metadata = json.loads((Path(folder) / "synthetic.json").read_text())
    except (OSError, ValueError):
        return False
    frames = int(frames or sequence.frames)
    wanted = {"num_frames": frames, "width": int(width), "height": int(height), "seed": int(sequence.seed)}
    style = metadata.get("style", {})
    return (all(metadata.get(key) == value for key, value in wanted.items()) and metadata.get("layout") is None
            and style.get("name") == sequence.style
            and style.get("path_sha256") == path_digest(style_path(sequence.style, frames, sequence.seed)))


def write_suite(root: str | Path, width: int = SUITE_WIDTH, height: int = SUITE_HEIGHT, split: str | None = None,
                overwrite: bool = False, report: Callable[[str], None] | None = None) -> list[Path]:
    """Render the suite's synthetic sequences as TUM RGB-D folders ``root/<name>``.

    A folder that already holds the finished rendering is kept as it is (an interrupted run resumes);
    real sequences are not written (they are read from their own folders).

    Args:
        root: the folder to write into (made if missing).
        width, height: image size (default the suite's).
        split: only this half ("tune" or "validate"); None: both.
        overwrite: replace a folder that holds something else; otherwise that is an error.
        report: called with one line per sequence (written or kept).

    Returns:
        The folders of the synthetic sequences, in table order.
    """
    from sl4slam.synthetic.sequence import write_synthetic_sequence
    from sl4slam.synthetic.styles import check_style_request

    check_style_request(2, width, height, 0)
    chosen = suite_sequences(split)
    root = Path(root)
    folders = []
    for sequence in chosen:
        if sequence.real:
            continue
        folder = root / sequence.name
        if is_rendered(folder, sequence, width, height):
            state = "kept"
        else:
            write_synthetic_sequence(folder, num_frames=sequence.frames, width=width, height=height, seed=sequence.seed,
                                     overwrite=overwrite, style=sequence.style)
            state = "wrote"
        folders.append(folder)
        if report is not None:
            report(f"{state} {sequence.name} ({sequence.split}, {sequence.frames} frames) in {folder}")
    return folders
