"""Writing a benchmark's Markdown section into benchmarks/results/ (shared by the scripts)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence


def write_report(path: str | Path, lines: Sequence[str]) -> None:
    """Write ``lines`` to ``path`` atomically (a half-written report never replaces a whole one)
    and print them."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)
    print("\n".join(lines))
