"""A synthetic textured indoor RGB-D world with exact ground truth.

- :func:`make_world` builds a seeded room with furniture boxes and rich procedural textures.
- :func:`camera_path` gives a looping path (last pose = first pose) with one floor-only stretch.
- :func:`render_frames` ray-casts RGB and depth images (vectorized numpy).
- :func:`write_synthetic_sequence` writes all of it as a TUM RGB-D folder, and
  :func:`write_seven_scenes_sequence` as a 7-Scenes sequence folder, that
  :func:`sl4slam.io.open_source` reads back with depth, poses and intrinsics.
- :mod:`.styles`: other rooms (office, hall, corridor), textures (low, repetitive) and motions
  (walk, orbit, rotation in place, forward), by name (``style=`` of the writers);
  :mod:`.suite`: the development suite of named sequences and its tune / validate split;
  :mod:`.properties`: a path's length, speed, rotation rate, revisits and keyframe rate.
"""

from sl4slam.synthetic.render import cast_rays, default_intrinsics, render_frames, render_pixels
from sl4slam.synthetic.sequence import read_synthetic_metadata, write_seven_scenes_sequence, write_synthetic_sequence
from sl4slam.synthetic.styles import STYLES, get_style, make_style_layout, make_style_world, style_path
from sl4slam.synthetic.suite import SUITE, split_of, suite_sequences, write_suite
from sl4slam.synthetic.world import (
    CEILING_SURFACE,
    FLOOR_SURFACE,
    World,
    camera_path,
    floor_hold_frames,
    make_layout,
    make_world,
)

__all__ = [
    "make_world",
    "make_layout",
    "camera_path",
    "floor_hold_frames",
    "render_frames",
    "render_pixels",
    "cast_rays",
    "default_intrinsics",
    "write_synthetic_sequence",
    "write_seven_scenes_sequence",
    "read_synthetic_metadata",
    "STYLES",
    "get_style",
    "make_style_layout",
    "make_style_world",
    "style_path",
    "SUITE",
    "split_of",
    "suite_sequences",
    "write_suite",
    "World",
    "FLOOR_SURFACE",
    "CEILING_SURFACE",
]
