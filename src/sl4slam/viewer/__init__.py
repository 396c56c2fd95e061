"""Browser viewer (viser, the optional extra ``sl4slam[viewer]``): a finished run or a live one.

- ``sl4slam view RESULT_DIR`` / :func:`view_result`: a result folder.
- ``sl4slam run ... --view`` / :class:`LiveViewer`: its ``on_submap`` method is the pipeline's
  per-submap callback; the scene grows with every submap and is redrawn from the optimized
  graph after a loop closure.

The array shaping lives in :mod:`sl4slam.viewer.scene` (no viser needed); viser is imported only
when a server starts, and a missing extra is one line naming the install command.
"""

from .live import LiveViewer, keyframe_colors, keyframe_confidence
from .result import state_from_result, view_result
from .scene import MapState, ViewerSettings

__all__ = ["view_result", "LiveViewer", "ViewerSettings", "MapState", "state_from_result", "keyframe_colors",
           "keyframe_confidence"]
