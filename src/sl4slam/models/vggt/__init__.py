"""Our implementation of VGGT (Visual Geometry Grounded Transformer), compatible with the released
``facebook/VGGT-1B`` checkpoint (tracking head excluded).

- :mod:`.model`: :class:`VGGT` and its sizes :class:`VGGTModelConfig`.
- :mod:`.aggregator`, :mod:`.camera_head`, :mod:`.dpt_head`, :mod:`.rope`: the parts.
- :mod:`.pose_encoding`, :mod:`.geometry`: camera conventions, quaternions, unprojection.
- :mod:`.preprocess`: image preprocessing (crop / pad / square).
- :mod:`.weights`: :func:`load_vggt`, :func:`convert_checkpoint`.
"""

from .geometry import closed_form_inverse_se3, unproject_depth_map_to_point_map
from .model import VGGT, VGGTModelConfig, build_vggt, init_random_weights
from .pose_encoding import extri_intri_to_pose_encoding, mat_to_quat, pose_encoding_to_extri_intri, quat_to_mat
from .preprocess import GridTransform, preprocess_images, preprocess_images_square
from .weights import convert_checkpoint, infer_config, load_vggt, read_checkpoint, resolve_weights, save_checkpoint

__all__ = [
    "VGGT",
    "VGGTModelConfig",
    "GridTransform",
    "build_vggt",
    "closed_form_inverse_se3",
    "convert_checkpoint",
    "extri_intri_to_pose_encoding",
    "infer_config",
    "init_random_weights",
    "load_vggt",
    "mat_to_quat",
    "pose_encoding_to_extri_intri",
    "preprocess_images",
    "preprocess_images_square",
    "quat_to_mat",
    "read_checkpoint",
    "resolve_weights",
    "save_checkpoint",
    "unproject_depth_map_to_point_map",
]
