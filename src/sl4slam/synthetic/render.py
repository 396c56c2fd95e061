"""Vectorized ray casting of the synthetic world (numpy; no per-pixel Python loops).

Each pixel ``(u, v)`` (integer coordinates at pixel centres) casts the ray
``d_cam = K^-1 [u, v, 1]``, whose camera ``z`` component is exactly 1, so the ray parameter
at the hit equals the depth (distance along the optical axis) of the hit point. Rays are
intersected with the inside of the room box and the outside of every furniture box (slab test);
the nearest hit wins. Colour is the hit surface's texture, sampled bilinearly from the mip level
matching the pixel footprint (trilinear between two levels, which avoids shimmering on far
walls), times a view-independent point-light shading, so a surface point has the same colour
in every frame.
"""

from __future__ import annotations

import numpy as np

from sl4slam.synthetic.world import World

_TINY = 1e-12


def default_intrinsics(width: int, height: int) -> np.ndarray:
    """``(3, 3)`` float64 pinhole intrinsics used for the synthetic sequences.

    ``fx = fy = 0.8 * width`` (about 64 degrees horizontal field of view), principal point at
    the image centre in pixel-centre coordinates (``((W - 1) / 2, (H - 1) / 2)``).
    """
    focal = 0.8 * float(width)
    return np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def cast_rays(world: World, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest intersection of rays with the world.

    Args:
        world: the scene.
        origins: ``(N, 3)`` ray origins in the world frame (inside the room, outside all boxes).
        directions: ``(N, 3)`` ray directions in the world frame (any length; not normalized).

    Returns:
        t: ``(N,)`` ray parameter of the hit (``origin + t * direction``), float32 for float32
            inputs, float64 otherwise.
        surface: ``(N,)`` int64 id of the hit surface (numbering in ``sl4slam.synthetic.world``).
    """
    origins = np.asarray(origins)
    directions = np.asarray(directions)
    dtype = np.result_type(origins.dtype, directions.dtype, np.float32)
    # Structure of arrays: numpy reductions over a trailing axis of length 3 are slow, so every
    # min/max is an elementwise operation on three contiguous component arrays.
    o = [np.ascontiguousarray(origins[:, a], dtype) for a in range(3)]
    d = [np.ascontiguousarray(directions[:, a], dtype) for a in range(3)]
    return _cast(world, o, d)


def _cast(world: World, o: list[np.ndarray], d: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cast_rays` on component arrays ``o = [x, y, z]``, ``d = [dx, dy, dz]`` (each ``(N,)``, one dtype)."""
    dtype = d[0].dtype
    # Exact zeros would give 0 * inf = nan in the slab test; a tiny same-sign value is harmless.
    inv = [(1.0 / np.where(np.abs(c) < _TINY, np.where(c < 0, -_TINY, _TINY), c)).astype(dtype) for c in d]
    layout = world.layout

    # Leaving the room: the nearest of the three exit planes (the one ahead on each axis).
    exits = [
        (np.where(inv[a] > 0, dtype.type(layout.room_max[a]), dtype.type(layout.room_min[a])) - o[a]) * inv[a]
        for a in range(3)
    ]
    t = np.minimum(np.minimum(exits[0], exits[1]), exits[2])
    axis = np.where(exits[0] == t, 0, np.where(exits[1] == t, 1, 2))
    # Same sign convention as the exit planes above (a zero component counts as positive).
    surface = 2 * axis + (_select(axis, inv) > 0)

    # Entering a box: the farthest near plane, valid if before the nearest far plane and the current hit.
    for box, (lo, hi) in enumerate(zip(layout.boxes_min, layout.boxes_max)):
        near, far = [], []
        for a in range(3):
            t_lo = (dtype.type(lo[a]) - o[a]) * inv[a]
            t_hi = (dtype.type(hi[a]) - o[a]) * inv[a]
            near.append(np.minimum(t_lo, t_hi))
            far.append(np.maximum(t_lo, t_hi))
        t_enter = np.maximum(np.maximum(near[0], near[1]), near[2])
        t_leave = np.minimum(np.minimum(far[0], far[1]), far[2])
        hit = (t_enter <= t_leave) & (t_enter > 0) & (t_enter < t)
        hit_rows = np.flatnonzero(hit)
        if hit_rows.size == 0:
            continue
        entered = t_enter[hit_rows]
        box_axis = np.where(near[0][hit_rows] == entered, 0, np.where(near[1][hit_rows] == entered, 1, 2))
        d_hit = np.where(box_axis == 0, d[0][hit_rows], np.where(box_axis == 1, d[1][hit_rows], d[2][hit_rows]))
        # A ray travelling towards -axis enters through the face at the box's maximum.
        t[hit_rows] = entered
        surface[hit_rows] = 6 + 6 * box + 2 * box_axis + (d_hit < 0)
    return t, surface.astype(np.int64)


def _sample_atlas(world: World, level: np.ndarray, surface: np.ndarray, coord_u: np.ndarray, coord_v: np.ndarray) -> np.ndarray:
    """Bilinear texture lookups, each at its own mip level.

    Args:
        level, surface: ``(N,)`` integer mip level and surface id per lookup.
        coord_u, coord_v: ``(N,)`` float32 texture coordinates in metres from the texture origin.

    Returns:
        ``(N, 4)`` float32 RGB and the (zero) padding channel.
    """
    atlas = world.atlas
    cols = atlas.cols[level, surface]
    rows = atlas.rows[level, surface]
    # Texel centres sit at (i + 0.5) / density.
    x = coord_u * atlas.density_u[level, surface] - np.float32(0.5)
    y = coord_v * atlas.density_v[level, surface] - np.float32(0.5)
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    last_col = cols - 1
    x1c = np.clip(x0 + 1, 0, last_col)
    x0c = np.clip(x0, 0, last_col)
    y1c = np.clip(y0 + 1, 0, rows - 1)
    y0c = np.clip(y0, 0, rows - 1)
    row0 = atlas.offset[level, surface] + y0c * cols
    row1 = row0 + (y1c - y0c) * cols
    words = atlas.texels.view(np.uint32).reshape(-1)

    def fetch(index: np.ndarray) -> np.ndarray:
        return np.take(words, index).view(np.uint8).reshape(-1, 4).astype(np.float32)

    top = fetch(row0 + x0c)
    top += (fetch(row0 + x1c) - top) * fx
    bottom = fetch(row1 + x0c)
    bottom += (fetch(row1 + x1c) - bottom) * fx
    top += (bottom - top) * fy
    return top


def _select(index: np.ndarray, values: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """``values[index[i]][i]`` for three component arrays (index in 0..2)."""
    return np.where(index == 0, values[0], np.where(index == 1, values[1], values[2]))


def shade_hits(world: World, points: np.ndarray, surface: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
    """Colour of surface points.

    Args:
        points: ``(N, 3)`` world points on the surfaces.
        surface: ``(N,)`` int64 surface ids.
        footprint_m: ``(N,)`` size of one pixel on the surface (metres), picks the mip level.

    Returns:
        ``(N, 3)`` float32 RGB in [0, 255].
    """
    components = tuple(np.ascontiguousarray(points[:, a], np.float32) for a in range(3))
    return _shade(world, components, surface, np.asarray(footprint_m, np.float32))


def _shade(world: World, p: tuple[np.ndarray, np.ndarray, np.ndarray], surface: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
    """:func:`shade_hits` on component arrays ``p = (x, y, z)``, each ``(N,)`` float32."""
    origin = world.surface_origin_uv.astype(np.float32)[surface]
    sign = world.surface_uv_sign.astype(np.float32)[surface]
    coord_u = (_select(world.surface_u_axis[surface], p) - origin[:, 0]) * sign[:, 0]
    coord_v = (_select(world.surface_v_axis[surface], p) - origin[:, 1]) * sign[:, 1]
    texels_per_pixel = footprint_m * world.atlas.density_u[0, surface]
    top_level = world.atlas.offset.shape[0] - 1
    level = np.clip(np.log2(np.maximum(texels_per_pixel, np.float32(1e-6))), 0.0, top_level).astype(np.float32)
    lower = np.minimum(level.astype(np.int64), top_level - 1)
    blend = (level - lower)[:, None]
    # Trilinear: both neighbouring levels in one vectorized lookup of 2N samples.
    both = _sample_atlas(
        world,
        np.concatenate([lower, lower + 1]),
        np.concatenate([surface, surface]),
        np.concatenate([coord_u, coord_u]),
        np.concatenate([coord_v, coord_v]),
    )
    count = surface.shape[0]
    colour = both[:count, :3]
    colour += (both[count:, :3] - colour) * blend
    # View-independent point-light shading: the same surface point has the same colour in every frame.
    normal = world.surface_normal.astype(np.float32)[surface]
    lx, ly, lz = (np.float32(c) for c in world.light)
    to_light = (lx - p[0], ly - p[1], lz - p[2])
    distance = np.sqrt(to_light[0] ** 2 + to_light[1] ** 2 + to_light[2] ** 2)
    cosine = (normal[:, 0] * to_light[0] + normal[:, 1] * to_light[1] + normal[:, 2] * to_light[2]) / np.maximum(
        distance, np.float32(1e-6)
    )
    shading = np.float32(0.55) + np.float32(0.6) * np.clip(cosine, 0.0, 1.0) / (1.0 + (distance / np.float32(6.0)) ** 2)
    colour *= shading[:, None]
    return np.clip(colour, 0.0, 255.0, out=colour)


def camera_rays(K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """``(N, 3)`` float64 camera-frame rays ``K^-1 [u, v, 1]`` (``z = 1``) for ``(N, 2)`` pixels ``(u, v)``."""
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    homogeneous = np.concatenate([pixels, np.ones((pixels.shape[0], 1))], axis=1)
    return homogeneous @ np.linalg.inv(np.asarray(K, np.float64)).T


def render_pixels(
    world: World, T_world_cam: np.ndarray, K: np.ndarray, pixels: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Depth and surface id at arbitrary (sub-pixel) image positions of one camera, in float64.

    Args:
        T_world_cam: ``(4, 4)`` camera pose. K: ``(3, 3)``. pixels: ``(N, 2)`` ``(u, v)``.

    Returns:
        depth: ``(N,)`` float64 metres along the optical axis. surface: ``(N,)`` int64.
    """
    T = np.asarray(T_world_cam, np.float64)
    rays = camera_rays(K, pixels) @ T[:3, :3].T
    origins = np.broadcast_to(T[:3, 3], rays.shape).copy()
    return cast_rays(world, origins, rays)


def render_frames(
    world: World,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    chunk_frames: int = 2,
    return_surfaces: bool = False,
):
    """Render RGB and depth images.

    Args:
        world: the scene (:func:`sl4slam.synthetic.make_world`).
        T_world_cam: ``(N, 4, 4)`` (or ``(4, 4)``) camera poses, OpenCV camera axes.
        K: ``(3, 3)`` intrinsics (pixel-centre convention).
        width, height: image size in pixels.
        chunk_frames: frames ray-cast together (memory vs. numpy call overhead).
        return_surfaces: also return the ``(N, H, W)`` int16 surface id image.

    Returns:
        rgb: ``(N, H, W, 3)`` uint8. depth: ``(N, H, W)`` float32 metres (z along the optical
        axis, always > 0: the room is closed). With ``return_surfaces``, a third array.
    """
    T = np.asarray(T_world_cam, np.float64)
    if T.ndim == 2:
        T = T[None]
    count = T.shape[0]
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    rays_cam = camera_rays(K, np.stack([u.ravel(), v.ravel()], axis=1))  # (P, 3), z = 1
    rays_x, rays_y, rays_z = (rays_cam[:, a].astype(np.float32) for a in range(3))
    focal = float(np.sqrt(K[0, 0] * K[1, 1]))
    ray_length = np.linalg.norm(rays_cam, axis=1).astype(np.float32)
    pixels = rays_cam.shape[0]
    rgb = np.empty((count, height, width, 3), np.uint8)
    depth = np.empty((count, height, width), np.float32)
    surfaces = np.empty((count, height, width), np.int16) if return_surfaces else None
    for start in range(0, count, chunk_frames):
        stop = min(start + chunk_frames, count)
        poses = T[start:stop]
        n = stop - start
        rotations = poses[:, :3, :3].astype(np.float32)
        # Component arrays (x, y, z) of the world-frame rays and origins, frames stacked.
        d = tuple(
            np.concatenate([rotation[a, 0] * rays_x + rotation[a, 1] * rays_y + rotation[a, 2] * rays_z for rotation in rotations])
            for a in range(3)
        )
        o = [np.repeat(poses[:, a, 3], pixels).astype(np.float32) for a in range(3)]
        t, surface = _cast(world, o, list(d))
        points = tuple(o[a] + t * d[a] for a in range(3))
        # Footprint: pixel size at that distance over sqrt(|cos(incidence)|) (a compromise between
        # the two axes of the elongated footprint at grazing angles).
        lengths = np.tile(ray_length, n)
        normals = world.surface_normal.astype(np.float32)[surface]
        cosine = np.abs(normals[:, 0] * d[0] + normals[:, 1] * d[1] + normals[:, 2] * d[2]) / lengths
        footprint = t * lengths / np.float32(focal) / np.sqrt(np.maximum(cosine, np.float32(0.05)))
        colour = _shade(world, points, surface, footprint)
        rgb[start:stop] = (colour + 0.5).astype(np.uint8).reshape(n, height, width, 3)
        depth[start:stop] = t.reshape(n, height, width)
        if surfaces is not None:
            surfaces[start:stop] = surface.reshape(n, height, width)
    if return_surfaces:
        return rgb, depth, surfaces
    return rgb, depth


ROOM_OBJECT_ID = -1
"""The object id of a pixel that sees the room (walls, floor, ceiling) rather than a furniture box."""


def object_ids_from_surfaces(surfaces: np.ndarray) -> np.ndarray:
    """Per-pixel object ids from surface ids: furniture box ``b`` (surfaces ``6 + 6 b .. 11 + 6 b``,
    numbering in ``sl4slam.synthetic.world``) is ``b``; the room is :data:`ROOM_OBJECT_ID`.

    Args:
        surfaces: integer surface ids of any shape (``render_frames(..., return_surfaces=True)``).

    Returns:
        int16 object ids of the same shape.
    """
    surfaces = np.asarray(surfaces).astype(np.int64)
    return np.where(surfaces >= 6, (surfaces - 6) // 6, ROOM_OBJECT_ID).astype(np.int16)


def render_object_ids(world, T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Per-pixel object ids of cameras in a world: which furniture box each pixel sees.

    Only the geometry is ray-cast (no texture lookups): cheaper than :func:`render_frames`, and the
    ids equal ``object_ids_from_surfaces`` of its surfaces for the same cameras.

    Args:
        world: a :class:`World`, or its ``Layout`` (the boxes are all that is read).
        T_world_cam: ``(N, 4, 4)`` (or ``(4, 4)``) camera poses, OpenCV camera axes.
        K: ``(3, 3)`` intrinsics (pixel-centre convention). width, height: image size in pixels.

    Returns:
        ``(N, H, W)`` int16: box index ``b`` (``layout.boxes_min[b]``), or :data:`ROOM_OBJECT_ID`.
    """
    layout = getattr(world, "layout", world)
    scene = world if hasattr(world, "layout") else _LayoutOnly(layout)
    T = np.asarray(T_world_cam, np.float64)
    if T.ndim == 2:
        T = T[None]
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    rays_cam = camera_rays(K, np.stack([u.ravel(), v.ravel()], axis=1))
    out = np.empty((T.shape[0], height, width), np.int16)
    for i, pose in enumerate(T):
        rays = (rays_cam @ pose[:3, :3].T).astype(np.float32)
        o = [np.full(rays.shape[0], pose[a, 3], np.float32) for a in range(3)]
        _, surface = _cast(scene, o, [np.ascontiguousarray(rays[:, a]) for a in range(3)])
        out[i] = object_ids_from_surfaces(surface).reshape(height, width)
    return out


class _LayoutOnly:
    """A layout seen as a world by the ray caster (which reads ``world.layout`` only)."""

    def __init__(self, layout):
        self.layout = layout
