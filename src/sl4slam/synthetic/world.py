"""The synthetic indoor world: a textured room with furniture boxes and a looping camera path.

World frame: metres, ``z`` up, the room is the axis-aligned box ``[room_min, room_max]`` with the
floor at ``z = 0``. Cameras use the OpenCV convention (``x`` right, ``y`` down, ``z`` forward);
poses are ``T_world_cam`` (world-from-camera).

Surfaces are numbered: room faces ``0..5`` as ``2 * axis + side`` (side 0 = the face at the
minimum coordinate, 1 = at the maximum; so the floor is 4 and the ceiling 5), then box ``b``'s
faces ``6 + 6 * b + 2 * axis + side``.

The camera path (:func:`camera_path`) circles the room once on an ellipse around its centre,
looking outwards and a little ahead, and ends exactly at its start pose (a loop to close).
Between path parameters ``FLOOR_RAMP_DOWN`` and ``FLOOR_RAMP_UP`` the camera pitches down to
look straight at the floor and holds there over ``FLOOR_HOLD`` (the planar, degenerate case).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from sl4slam.synthetic.textures import make_texture

FLOOR_SURFACE = 4
CEILING_SURFACE = 5

FLOOR_RAMP_DOWN = (0.40, 0.50)
"""Path-parameter interval over which the camera pitches from its cruise pitch to straight down."""
FLOOR_HOLD = (0.50, 0.60)
"""Path-parameter interval during which the camera looks straight down (sees only the floor)."""
FLOOR_RAMP_UP = (0.60, 0.70)
"""Path-parameter interval over which the camera pitches back up."""

FLOOR_TEXEL_M = 0.005
SURFACE_TEXEL_M = 0.01
MIP_LEVELS = 4


@dataclass
class Layout:
    """Seeded geometry of a world: room box, camera-path parameters, furniture boxes.

    The path parameters are those of the looping path of :func:`camera_path`; worlds made for
    other camera paths (:mod:`sl4slam.synthetic.styles`) leave them at zero.

    Attributes:
        room_min, room_max: ``(3,)`` float64 room corners (metres, ``room_min = 0``).
        path_centre: ``(2,)`` float64 ellipse centre (x, y).
        path_radii: ``(2,)`` float64 ellipse radii (x, y).
        path_height: camera height (m) at the start.
        height_wobble: amplitude (m) of the height variation along the loop.
        yaw_offset: mean radians between the outward direction and the viewing direction.
        yaw_swing: amplitude (radians) of the periodic swing of that angle along the loop.
        swing_phase: phase (radians) of the swing.
        cruise_pitch: radians (negative = looking down) outside the floor segment.
        start_angle: radians, the ellipse angle of the first pose.
        boxes_min, boxes_max: ``(B, 3)`` float64 box corners.
    """

    room_min: np.ndarray
    room_max: np.ndarray
    path_centre: np.ndarray = field(default_factory=lambda: np.zeros(2))
    path_radii: np.ndarray = field(default_factory=lambda: np.zeros(2))
    path_height: float = 0.0
    height_wobble: float = 0.0
    yaw_offset: float = 0.0
    yaw_swing: float = 0.0
    swing_phase: float = 0.0
    cruise_pitch: float = 0.0
    start_angle: float = 0.0
    boxes_min: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    boxes_max: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass
class TextureAtlas:
    """Every surface texture at every mip level, flattened into one array.

    Level ``l`` halves the resolution of level ``l - 1`` (area averaging).

    Attributes:
        texels: ``(T, 4)`` uint8 RGB plus a zero padding byte (one texel = one 32-bit word, so
            lookups gather words rather than rows); the texture of (level ``l``, surface ``s``) is
            ``texels[offset[l, s] : offset[l, s] + rows[l, s] * cols[l, s]]`` raveled row-major.
        offset, rows, cols: ``(L, S)`` int64.
        density_u, density_v: ``(L, S)`` float32 texels per metre along u (columns) and v (rows).
    """

    texels: np.ndarray
    offset: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    density_u: np.ndarray
    density_v: np.ndarray


@dataclass
class World:
    """A renderable world (see the module docstring for frames and surface numbering).

    Attributes:
        layout: the geometry.
        surface_axis: ``(S,)`` int64 axis (0 x, 1 y, 2 z) the surface is perpendicular to.
        surface_u_axis, surface_v_axis: ``(S,)`` int64 world axes along texture columns / rows.
        surface_uv_sign: ``(S, 2)`` float64 +-1: texture column / row coordinates grow along
            ``sign * world axis`` (chosen so that text reads unmirrored and upright on walls).
        surface_origin_uv: ``(S, 2)`` float64 world coordinates (u, v) of the texture's first texel corner.
        surface_normal: ``(S, 3)`` float64 unit normal facing the visible side.
        surface_style: texture style name per surface.
        atlas: all textures and their mip pyramids.
        light: ``(3,)`` float64 point light position (view-independent shading).
        seed: the seed the world was made from.
    """

    layout: Layout
    surface_axis: np.ndarray
    surface_u_axis: np.ndarray
    surface_v_axis: np.ndarray
    surface_uv_sign: np.ndarray
    surface_origin_uv: np.ndarray
    surface_normal: np.ndarray
    surface_style: list[str]
    atlas: TextureAtlas
    light: np.ndarray
    seed: int

    @property
    def num_surfaces(self) -> int:
        return int(self.surface_axis.shape[0])

    @property
    def num_boxes(self) -> int:
        return int(self.layout.boxes_min.shape[0])


# --------------------------------------------------------------------------------------------
# Layout and camera path
# --------------------------------------------------------------------------------------------


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """C1 ease from 0 to 1 over x in [0, 1] (cosine), clamped outside."""
    x = np.clip(x, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def floor_weight(s: np.ndarray) -> np.ndarray:
    """``(N,)`` in [0, 1]: how far the camera has pitched towards straight down at path parameter ``s``."""
    s = np.asarray(s, np.float64)
    down = _smoothstep((s - FLOOR_RAMP_DOWN[0]) / (FLOOR_RAMP_DOWN[1] - FLOOR_RAMP_DOWN[0]))
    up = _smoothstep((s - FLOOR_RAMP_UP[0]) / (FLOOR_RAMP_UP[1] - FLOOR_RAMP_UP[0]))
    return down * (1.0 - up)


def _path_from_layout(layout: Layout, s: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` camera poses at path parameters ``s`` (``s = 0`` and ``s = 1`` give the same pose)."""
    s = np.asarray(s, np.float64)
    angle = layout.start_angle + 2.0 * np.pi * s
    x = layout.path_centre[0] + layout.path_radii[0] * np.cos(angle)
    y = layout.path_centre[1] + layout.path_radii[1] * np.sin(angle)
    z = layout.path_height + layout.height_wobble * np.sin(2.0 * np.pi * s) * np.cos(4.0 * np.pi * s)
    # The viewing direction swings between outwards-ahead (near walls and furniture) and
    # inwards-ahead (across the room, far depths); the swing is periodic so the loop still closes.
    yaw = angle + layout.yaw_offset + layout.yaw_swing * np.sin(2.0 * np.pi * s + layout.swing_phase)
    pitch = layout.cruise_pitch + (-0.5 * np.pi - layout.cruise_pitch) * floor_weight(s)
    forward = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1)
    # "right" stays horizontal and follows the yaw, so looking straight down is not singular.
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)
    down = np.cross(forward, right)
    T = np.tile(np.eye(4), (s.shape[0], 1, 1))
    T[:, :3, 0] = right
    T[:, :3, 1] = down
    T[:, :3, 2] = forward
    T[:, :3, 3] = np.stack([x, y, z], axis=-1)
    return T


def _footprint_xy(T_world_cam: np.ndarray, half_fov_tan: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned xy bounds of the floor area seen by downward-looking cameras (generous)."""
    heights = T_world_cam[:, 2, 3]
    reach = heights * half_fov_tan * np.sqrt(2.0) + 0.3
    xy = T_world_cam[:, :2, 3]
    return (xy - reach[:, None]).min(0), (xy + reach[:, None]).max(0)


def make_layout(seed: int) -> Layout:
    """Seeded room size, path parameters and furniture boxes (no textures; cheap)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    size = np.array([rng.uniform(7.5, 9.0), rng.uniform(5.6, 6.6), rng.uniform(2.7, 3.1)])
    layout = Layout(
        room_min=np.zeros(3),
        room_max=size,
        path_centre=size[:2] / 2.0,
        path_radii=np.array([size[0] * rng.uniform(0.20, 0.24), size[1] * rng.uniform(0.18, 0.22)]),
        path_height=float(rng.uniform(1.3, 1.5)),
        height_wobble=float(rng.uniform(0.08, 0.15)),
        yaw_offset=float(np.deg2rad(rng.uniform(80.0, 90.0))),
        yaw_swing=float(np.deg2rad(rng.uniform(40.0, 50.0))),
        swing_phase=float(rng.uniform(0.0, 2.0 * np.pi)),
        cruise_pitch=float(np.deg2rad(-rng.uniform(10.0, 16.0))),
        start_angle=float(rng.uniform(0.0, 2.0 * np.pi)),
    )

    # Keep-out zones for furniture: a tube around the camera path, and the floor seen while
    # looking down (it must show nothing but floor).
    s_dense = np.linspace(0.0, 1.0, 721)
    poses = _path_from_layout(layout, s_dense)
    path_xy = poses[:, :2, 3]
    hold = (s_dense >= FLOOR_HOLD[0] - 0.01) & (s_dense <= FLOOR_HOLD[1] + 0.01)
    floor_lo, floor_hi = _footprint_xy(poses[hold])

    boxes_min, boxes_max = [], []
    wanted = int(rng.integers(8, 12))
    for _attempt in range(400):
        if len(boxes_min) >= wanted:
            break
        kind = rng.uniform()
        width = rng.uniform(0.5, 1.6)
        depth = rng.uniform(0.35, 0.9)
        if kind < 0.15:  # wall cabinet / shelf hanging above the floor
            bottom = rng.uniform(1.2, 1.8)
            height = rng.uniform(0.3, 0.7)
            depth = rng.uniform(0.25, 0.45)
        elif kind < 0.35:  # tall wardrobe
            bottom, height = 0.0, rng.uniform(1.6, 2.3)
        else:  # tables, chests, crates
            bottom, height = 0.0, rng.uniform(0.35, 1.1)
        wall = int(rng.integers(4))
        along_axis = 0 if wall < 2 else 1
        across_axis = 1 - along_axis
        lo = np.zeros(3)
        hi = np.zeros(3)
        start = rng.uniform(0.1, size[along_axis] - width - 0.1)
        lo[along_axis], hi[along_axis] = start, start + width
        gap = rng.uniform(0.0, 0.25) if bottom == 0.0 else 0.0
        if wall % 2 == 0:
            lo[across_axis], hi[across_axis] = gap, gap + depth
        else:
            lo[across_axis], hi[across_axis] = size[across_axis] - gap - depth, size[across_axis] - gap
        lo[2], hi[2] = bottom, min(bottom + height, size[2] - 0.2)
        # Horizontal distance from the camera path to the box rectangle must exceed 0.7 m.
        dx = np.maximum(np.maximum(lo[0] - path_xy[:, 0], path_xy[:, 0] - hi[0]), 0.0)
        dy = np.maximum(np.maximum(lo[1] - path_xy[:, 1], path_xy[:, 1] - hi[1]), 0.0)
        if np.hypot(dx, dy).min() < 0.7:
            continue
        overlaps_floor_view = np.all(lo[:2] < floor_hi) and np.all(hi[:2] > floor_lo)
        if overlaps_floor_view:
            continue
        if any(np.all(lo < b_hi + 0.05) and np.all(hi > b_lo - 0.05) for b_lo, b_hi in zip(boxes_min, boxes_max)):
            continue
        boxes_min.append(lo)
        boxes_max.append(hi)
    layout.boxes_min = np.array(boxes_min, np.float64).reshape(-1, 3)
    layout.boxes_max = np.array(boxes_max, np.float64).reshape(-1, 3)
    return layout


def path_parameters(num_frames: int) -> np.ndarray:
    """``(N,)`` path parameter of each frame: ``i / (N - 1)``, so the last pose equals the first."""
    if num_frames < 2:
        return np.zeros(max(int(num_frames), 0))
    return np.arange(num_frames, dtype=np.float64) / (num_frames - 1)


def camera_path(num_frames: int, seed: int = 0) -> np.ndarray:
    """The looping camera path of world ``seed``.

    Args:
        num_frames: number of poses ``N``.
        seed: world seed (the path adapts to the seeded room size).

    Returns:
        ``(N, 4, 4)`` float64 ``T_world_cam``; the last pose equals the first; poses with path
        parameter inside ``FLOOR_HOLD`` look straight down.
    """
    return _path_from_layout(make_layout(seed), path_parameters(num_frames))


def floor_hold_frames(num_frames: int) -> np.ndarray:
    """``(N,)`` bool: frames whose designed pitch is straight down (path parameter in ``FLOOR_HOLD``).

    Furniture is kept out of the floor area these frames see with fields of view up to about
    75 degrees (the default intrinsics have 64); a written sequence records the floor-only range
    measured on its renders in ``synthetic.json``.
    """
    return floor_weight(path_parameters(num_frames)) >= 1.0 - 1e-12


# --------------------------------------------------------------------------------------------
# Surfaces and textures
# --------------------------------------------------------------------------------------------


def _mip_pyramid(texture: np.ndarray, levels: int) -> list[np.ndarray]:
    """Level 0 is ``texture``; each next level halves both sizes (area averaging)."""
    pyramid = [texture]
    for _ in range(1, levels):
        prev = pyramid[-1]
        rows, cols = max(1, (prev.shape[0] + 1) // 2), max(1, (prev.shape[1] + 1) // 2)
        pyramid.append(cv2.resize(prev, (cols, rows), interpolation=cv2.INTER_AREA).reshape(rows, cols, 3))
    return pyramid


def make_world(seed: int = 0) -> World:
    """Build the textured world for ``seed`` (room, 8-11 furniture boxes, textures, light).

    Same seed, same world (geometry and every texel). Takes about 2-4 s (texture synthesis).
    """
    layout = make_layout(seed)
    texture_rng = np.random.default_rng(np.random.SeedSequence([int(seed), 2]))
    return build_world(layout, texture_rng, seed)


def build_world(
    layout: Layout,
    texture_rng: np.random.Generator,
    seed: int,
    texture_maker: Callable[[np.random.Generator, float, float, float, str], np.ndarray] = make_texture,
    floor_texel_m: float = FLOOR_TEXEL_M,
    surface_texel_m: float = SURFACE_TEXEL_M,
    mip_levels: int = MIP_LEVELS,
    light: np.ndarray | None = None,
) -> World:
    """Texture a layout's surfaces and assemble the renderable world.

    Args:
        layout: the room and its boxes.
        texture_rng: seeded generator; each surface's texture gets its own generator drawn from it,
            in surface order (room faces, then each box's six faces).
        seed: recorded in the world.
        texture_maker: ``f(rng, width_m, height_m, texel_m, style) -> (rows, cols, 3) uint8`` for
            the styles "wall", "floor", "ceiling" and "furniture" (default :func:`make_texture`).
        floor_texel_m, surface_texel_m: metres per texel of the floor and of every other surface.
        mip_levels: levels of each texture's mip pyramid (more for far surfaces of large rooms).
        light: ``(3,)`` point light position; default 0.4 m below the ceiling above the lap's
            path centre (the room centre for layouts without one).

    Returns:
        The :class:`World`.
    """
    axes, u_axes, v_axes, signs, origins, normals, styles, textures, extents = [], [], [], [], [], [], [], [], []

    def add_surface(axis: int, side: int, lo: np.ndarray, hi: np.ndarray, inward: bool, style: str, texel: float):
        u_axis, v_axis = ((1, 2), (0, 2), (0, 1))[axis]
        normal = np.zeros(3)
        # Room faces are seen from inside, box faces from outside.
        normal[axis] = (1.0 if side == 0 else -1.0) * (1.0 if inward else -1.0)
        # Texture rows run downwards on vertical faces (v = -z); columns are then signed so that
        # column x row points into the surface, as image right x image down does for a viewer.
        sign_v = -1.0 if axis < 2 else 1.0
        column_dir = np.zeros(3)
        column_dir[u_axis] = 1.0
        row_dir = np.zeros(3)
        row_dir[v_axis] = sign_v
        sign_u = 1.0 if np.dot(np.cross(column_dir, row_dir), normal) < 0 else -1.0
        width_m, height_m = hi[u_axis] - lo[u_axis], hi[v_axis] - lo[v_axis]
        axes.append(axis)
        u_axes.append(u_axis)
        v_axes.append(v_axis)
        signs.append((sign_u, sign_v))
        origins.append((lo[u_axis] if sign_u > 0 else hi[u_axis], lo[v_axis] if sign_v > 0 else hi[v_axis]))
        normals.append(normal)
        styles.append(style)
        extents.append((width_m, height_m))
        textures.append(texture_maker(np.random.default_rng(texture_rng.integers(2**63)), width_m, height_m, texel, style))

    for axis in range(3):
        for side in range(2):
            style = "wall" if axis < 2 else ("floor" if side == 0 else "ceiling")
            texel = floor_texel_m if style == "floor" else surface_texel_m
            add_surface(axis, side, layout.room_min, layout.room_max, True, style, texel)
    for lo, hi in zip(layout.boxes_min, layout.boxes_max):
        for axis in range(3):
            for side in range(2):
                add_surface(axis, side, lo, hi, False, "furniture", surface_texel_m)

    pyramids = [_mip_pyramid(t, mip_levels) for t in textures]
    extents_arr = np.array(extents, np.float64)
    rows = np.array([[p[level].shape[0] for p in pyramids] for level in range(mip_levels)], np.int64)
    cols = np.array([[p[level].shape[1] for p in pyramids] for level in range(mip_levels)], np.int64)
    sizes = (rows * cols).ravel()
    offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).reshape(rows.shape).astype(np.int64)
    atlas = TextureAtlas(
        texels=np.concatenate(
            [np.pad(pyramids[s][level].reshape(-1, 3), ((0, 0), (0, 1))) for level in range(mip_levels) for s in range(len(pyramids))]
        ),
        offset=offset,
        rows=rows,
        cols=cols,
        density_u=(cols / np.maximum(extents_arr[None, :, 0], 1e-9)).astype(np.float32),
        density_v=(rows / np.maximum(extents_arr[None, :, 1], 1e-9)).astype(np.float32),
    )
    if light is None:
        centre = layout.path_centre if np.any(layout.path_centre) else (layout.room_min[:2] + layout.room_max[:2]) / 2.0
        light = np.array([centre[0], centre[1], layout.room_max[2] - 0.4])
    return World(
        layout=layout,
        surface_axis=np.array(axes, np.int64),
        surface_u_axis=np.array(u_axes, np.int64),
        surface_v_axis=np.array(v_axes, np.int64),
        surface_uv_sign=np.array(signs, np.float64),
        surface_origin_uv=np.array(origins, np.float64),
        surface_normal=np.array(normals, np.float64),
        surface_style=styles,
        atlas=atlas,
        light=light,
        seed=int(seed),
    )
