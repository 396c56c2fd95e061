"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

# The project's reference data (model fixtures, a real TUM excerpt) sits beside the repository.
SHARED_DIR = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The ``shared/`` folder next to the repository; skips the test when it is absent."""
    if not SHARED_DIR.is_dir():
        pytest.skip(f"reference data folder {SHARED_DIR} is absent (only a development checkout has it)")
    return SHARED_DIR


FIXTURES_DIR = Path(__file__).resolve().parent / "fixtures"


@pytest.fixture(scope="session")
def fixtures_dir() -> Path:
    """The compact model fixtures vendored with the tests (``tests/fixtures/README.md``; ``subset.py``
    there makes the VGGT and SALAD ones from the full reference fixtures): always present, so the
    model parity tests never need ``shared/``."""
    return FIXTURES_DIR
