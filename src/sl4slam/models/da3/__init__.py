"""Our implementation of the Depth Anything 3 any-view network (Lin et al., 2025), compatible with the
released ``depth-anything/DA3-{SMALL,BASE,LARGE,GIANT}`` and ``-1.1`` checkpoints (the Giant's
Gaussian-splatting head excluded).

- :mod:`.config`: :class:`DA3Config`, the released sizes (:data:`RELEASED`: hub ids, licences).
- :mod:`.model`: :class:`DepthAnything3`; :mod:`.backbone`, :mod:`.head`, :mod:`.camera`,
  :mod:`.reference_view`, :mod:`.rays`: its parts.
- :mod:`.preprocess`: the authors' input processing (uint8 RGB in).
- :mod:`.cameras`: outputs to the SLAM frontend's arrays.
- :mod:`.weights`: :func:`load_da3`, :func:`convert_checkpoint`, :data:`WEIGHTS_SOURCES`, :data:`LICENCES`,
  :func:`parameter_counts`.
"""

from .cameras import relative_to_first, submap_arrays
from .config import RELEASED, SIZES, DA3Config, ReleasedSize, released
from .model import DepthAnything3, build_da3, count_parameters, init_random_weights
from .preprocess import Preprocessed, intrinsics_on_grid, preprocess_images
from .weights import (
    LICENCES,
    WEIGHTS_SOURCES,
    convert_checkpoint,
    infer_config,
    load_da3,
    load_state_dict_into,
    parameter_counts,
    read_checkpoint,
    save_checkpoint,
    weights_source,
)

__all__ = [
    "DA3Config",
    "DepthAnything3",
    "LICENCES",
    "Preprocessed",
    "RELEASED",
    "ReleasedSize",
    "SIZES",
    "WEIGHTS_SOURCES",
    "build_da3",
    "convert_checkpoint",
    "count_parameters",
    "infer_config",
    "init_random_weights",
    "intrinsics_on_grid",
    "load_da3",
    "load_state_dict_into",
    "parameter_counts",
    "preprocess_images",
    "read_checkpoint",
    "relative_to_first",
    "released",
    "save_checkpoint",
    "submap_arrays",
    "weights_source",
]
