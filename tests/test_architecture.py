"""The package's layering (pyproject.toml, ``[tool.importlinter]``): no import circles, each layer
importing only those below it, and a catalog that imports no stage."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

lint = pytest.importorskip("importlinter.cli", reason="the contracts need import-linter (the test extra)")

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def test_the_import_contracts_hold() -> None:
    """In a process of its own: import-linter configures logging with ``disable_existing_loggers``,
    which would silence the package's logger for every later test."""
    code = ("import sys, importlinter.cli as lint\n"
            f"sys.exit(lint.lint_imports(config_filename={str(PYPROJECT)!r}, no_cache=True))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert done.returncode == lint.EXIT_STATUS_SUCCESS, done.stdout[-4000:] + done.stderr[-2000:]


def test_the_catalog_imports_no_stage_until_one_is_asked_for() -> None:
    """Importing the catalog and the settings loads no stage module (only the stage packages' own
    settings, which live beside them); asking for an entry loads its own."""
    code = ("import sys, sl4slam.config, sl4slam.resolve\n"
            "stages = ('sl4slam.frontend', 'sl4slam.retrieval', 'sl4slam.alignment', 'sl4slam.backend')\n"
            "settings = {name + suffix for name in stages for suffix in ('', '.settings')}\n"
            "assert not [m for m in sys.modules if m.startswith(stages) and m not in settings], sorted(sys.modules)\n"
            "assert 'torch' not in sys.modules and 'gtsam' not in sys.modules\n"
            "from sl4slam.registry import aligner_entry\n"
            "assert aligner_entry('select').group == 'sl4' and 'sl4slam.alignment.aligner' in sys.modules\n"
            "assert not [m for m in sys.modules if m.startswith(('sl4slam.frontend', 'sl4slam.backend')) and m not in settings]\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_the_documented_aligner_is_a_catalog_entry_that_aligns() -> None:
    """The example of docs/architecture.md ("Add an aligner"), executed as written: its class makes
    its own catalog entry, and the entry's aligner measures a known offset."""
    import re

    import numpy as np

    from sl4slam.config import SLAMConfig
    from sl4slam.types import FrameView

    text = (Path(__file__).resolve().parents[1] / "docs" / "architecture.md").read_text()
    section = text[text.index("## Add an aligner"):]
    namespace: dict = {}
    exec(compile(re.search(r"```python\n(.*?)```", section, re.S).group(1), "architecture.md", "exec"), namespace)
    entry = namespace["MedianShiftAligner"].registry_entry()
    assert (entry.name, entry.group, entry.projective) == ("median-shift", "sim3", False)
    aligner = entry.build(SimpleNamespace(config=SLAMConfig()))
    points = np.random.default_rng(0).normal(size=(48, 64, 3)).astype(np.float32)
    mask, K, T = np.ones((48, 64), dtype=bool), np.eye(3), np.eye(4)[:3]
    alignment = aligner.align(FrameView(points + np.float32(0.5), mask, K, T), FrameView(points, mask, K, T), seed=0)
    assert np.allclose(alignment.H[:3, 3], 0.5, atol=1e-5) and alignment.inlier_ratio == 1.0
