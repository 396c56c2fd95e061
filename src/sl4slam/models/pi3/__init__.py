"""Our implementation of π³ (Wang et al., 2025) and its successor Pi3X, compatible with the released
checkpoints ``yyfz233/Pi3`` and ``yyfz233/Pi3X`` (weights CC BY-NC 4.0).

- :mod:`.model`: :class:`Pi3`, :class:`Pi3X` and their sizes :class:`Pi3Config`.
- :mod:`.attention`: the attention kernels ("reference": bitwise the authors'; "efficient": flash).
- :mod:`.encoder`, :mod:`.blocks`, :mod:`.heads`, :mod:`.prope`: the parts.
- :mod:`.preprocess`: the authors' image resizing (pixel budget, Lanczos), without PIL.
- :mod:`.cameras`: outputs -> depth, confidence, extrinsics and recovered intrinsics.
- :mod:`.memory`: the peak-memory estimate of a forward and the head chunk that fits a budget.
- :mod:`.weights`: :func:`load_pi3`, :data:`PI3_WEIGHTS`, :data:`PI3X_WEIGHTS`, the licence.
"""

from .attention import KERNELS
from .cameras import (
    confidence_from_logits,
    depth_from_local_points,
    extrinsics_from_poses,
    focal_from_local_points,
    intrinsics_from_local_points,
    to_model_intrinsics,
)
from .model import VARIANTS, Pi3, Pi3Config, Pi3X, build_pi3, parameter_count
from .preprocess import PIXEL_BUDGET, ResizeTransform, preprocess_images, resize_lanczos, target_size
from .weights import (
    PARAMETERS,
    PI3_WEIGHTS,
    PI3X_WEIGHTS,
    WEIGHTS_LICENSE,
    WEIGHTS_SOURCES,
    convert_checkpoint,
    infer_config,
    load_pi3,
    read_checkpoint,
    save_checkpoint,
)

__all__ = [
    "KERNELS",
    "PARAMETERS",
    "PI3X_WEIGHTS",
    "PI3_WEIGHTS",
    "PIXEL_BUDGET",
    "Pi3",
    "Pi3Config",
    "Pi3X",
    "ResizeTransform",
    "VARIANTS",
    "WEIGHTS_LICENSE",
    "WEIGHTS_SOURCES",
    "build_pi3",
    "confidence_from_logits",
    "convert_checkpoint",
    "depth_from_local_points",
    "extrinsics_from_poses",
    "focal_from_local_points",
    "infer_config",
    "intrinsics_from_local_points",
    "load_pi3",
    "parameter_count",
    "preprocess_images",
    "read_checkpoint",
    "resize_lanczos",
    "save_checkpoint",
    "target_size",
    "to_model_intrinsics",
]
