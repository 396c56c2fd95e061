"""Where sl4slam keeps downloaded weights on the user's machine, and what a run writes into its folder."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

RUN_FILES = ("trajectory.txt", "trajectory_gt.txt", "trajectory_all.txt", "map.ply", "summary.json", "trajectory.png",
             "keyframes", "frontend_cache", ".keyframe_store")
"""What a run writes into its folder (``--overwrite`` removes exactly these)."""


def holds_run(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds files of an earlier run."""
    return any((Path(out_dir) / name).exists() for name in RUN_FILES)


def clear_run(out_dir: Path) -> None:
    """Remove an earlier run's files from ``out_dir`` (only the names a run writes)."""
    for name in RUN_FILES:
        path = Path(out_dir) / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def user_cache_dir() -> Path:
    """``$SL4SLAM_CACHE``, else ``$XDG_CACHE_HOME/sl4slam``, else ``~/.cache/sl4slam``."""
    if os.environ.get("SL4SLAM_CACHE"):
        return Path(os.environ["SL4SLAM_CACHE"]).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "sl4slam"
