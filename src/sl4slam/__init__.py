"""sl4slam: dense SLAM from an uncalibrated monocular camera on the SL(4) manifold (VGGT-SLAM).

The library's front door (each name is imported on first use, so ``import sl4slam`` stays cheap):

- :class:`SLAMConfig` (``sl4slam.config``): every setting; ``sl4slam.resolve.resolve`` settles it;
- :func:`run_slam` (``sl4slam.runner``): a source to a result folder, as ``sl4slam run`` does;
- :class:`SLAMPipeline` (``sl4slam.pipeline``): the same in memory, over a frame source from
  :func:`open_source` (``sl4slam.io``);
- :func:`load_result` (``sl4slam.result.reading``): a result folder read back.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_PUBLIC = {
    "SLAMConfig": "sl4slam.config",
    "SimulatorConfig": "sl4slam.config",
    "run_slam": "sl4slam.runner",
    "SLAMPipeline": "sl4slam.pipeline",
    "open_source": "sl4slam.io",
    "load_result": "sl4slam.result.reading",
    "UserError": "sl4slam.errors",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'sl4slam' has no attribute {name!r}")
