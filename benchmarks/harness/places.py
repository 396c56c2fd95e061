"""Where the benchmarks read and write: their folder, the results, scratch output and the shared data."""

from __future__ import annotations

from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1]
"""The ``benchmarks/`` folder."""
REPO = BENCHMARKS.parent
"""The repository root."""
RESULTS = BENCHMARKS / "results"
"""Where each benchmark writes its Markdown section (``collect.py`` assembles BENCHMARKS.md from it)."""
OUT = BENCHMARKS / "out"
"""Scratch output kept between runs (rendered worlds, accumulated rows); not in git."""
SHARED_DATA = REPO.parent / "shared" / "data"
"""Real sequences next to the repository (``../shared/data``)."""
SEQUENCES = {"xyz37": "tum_rgbd_fr1_xyz_first37", "desk": "tum_rgbd_fr1_desk"}
"""Short names of the real sequences the benchmarks use, and their folders in :data:`SHARED_DATA`."""


def shared_sequence(name: str) -> Path:
    """The folder of a real sequence in :data:`SHARED_DATA`.

    Args:
        name: a short name of :data:`SEQUENCES` ("xyz37", "desk") or a folder name.

    Returns:
        The path; it may not exist (callers skip the sequence then).
    """
    return SHARED_DATA / SEQUENCES.get(name, name)


def result_file(name: str) -> Path:
    """``benchmarks/results/<name>.md``, the default report of benchmark ``name``."""
    return RESULTS / f"{name}.md"
