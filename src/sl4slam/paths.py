"""Where sl4slam keeps downloaded weights and generated data on the user's machine."""

from __future__ import annotations

import os
from pathlib import Path


def user_cache_dir() -> Path:
    """``$SL4SLAM_CACHE``, else ``$XDG_CACHE_HOME/sl4slam``, else ``~/.cache/sl4slam``."""
    if os.environ.get("SL4SLAM_CACHE"):
        return Path(os.environ["SL4SLAM_CACHE"]).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "sl4slam"
