"""Styles of synthetic sequence: the room, its surfaces' texture, and how the camera moves.

A style (:data:`STYLES`, :func:`get_style`) names a room kind (:data:`ROOMS`: a small office, a
furnished room, a large hall, a long corridor), a texture kind (``normal``, ``low``, ``repetitive``:
:func:`sl4slam.synthetic.textures.texture_maker`), a motion (:data:`MOTIONS`: a handheld walk, an
orbit around an object, a rotation in place, a walk forward along a corridor, or the original
world's lap), a speed (:data:`SPEEDS`: slow, fast) and a loop structure (:data:`LAPS`: none, one,
many), and a default length. With a seed it gives a world (:func:`make_style_world`) and, for any
number of frames, a camera path (:func:`style_path`). Every random choice is drawn from
``(seed, style name)``: the same style and seed give the same world and path, byte for byte.

How frames, speed and loops fit together: the loop structure fixes the laps the camera makes
(``none``: 0.7 of a lap, so it never comes back; ``one``: 1.2 laps; ``many``: at least 3.2), the
speed fixes the distance covered (speed x duration at 30 frames per second), and the path's size
follows (distance / laps), within what the room holds. Where the room cannot hold that size the
speed gives way, except that ``many`` makes more laps at the nominal speed when the path would be
too large. A rotation in place has no size: its turns are its laps, and its angular speed follows
from the frames (``many``: more turns at the nominal angular speed when the frames allow); it turns
about a vertical axis 0.25 m behind the camera, as a person turning on the spot holds it. The
corridor's ``none`` is a straight walk (distance at most the corridor's length); its loops are
out-and-back laps of a stadium-shaped path.

The style ``lap`` is the original world (:func:`sl4slam.synthetic.make_world`,
:func:`sl4slam.synthetic.camera_path`): same seed, same frames as without a style.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from sl4slam.errors import UserError
from sl4slam.synthetic.textures import TEXTURE_KINDS, texture_maker
from sl4slam.synthetic.world import Layout, World, build_world, camera_path, make_layout, make_world

FPS = 30.0
"""Frames per second of every synthetic sequence."""
MAX_FRAMES = 20000
"""The most frames a styled sequence may have."""
MOTIONS = ("lap", "walk", "orbit", "rotate", "forward")
"""Camera motions: the original world's lap, a handheld walk along a closed curve, an orbit around
an object looking at it, a rotation in place, a walk forward along a corridor."""
LOOPS = ("none", "one", "many")
"""Loop structures: never back to an earlier place, back once, back many times."""
LAPS = {"none": 0.7, "one": 1.2, "many": 3.2}
"""Laps of each loop structure (``many``: at least this many)."""
SPEEDS = {"slow": (0.3, 20.0), "fast": (0.9, 60.0)}
"""Nominal speed of each speed class: metres per second, and degrees per second for a rotation in place."""


@dataclass(frozen=True)
class RoomKind:
    """What a kind of room looks like; every length in metres.

    Attributes:
        size_min, size_max: ``(x, y, z)`` range of the room's size (drawn per seed).
        boxes: ``(min, max)`` furniture boxes wanted.
        box_width, box_depth: ranges of a wall-side box's length along its wall and depth from it.
        low_height, tall_height: height ranges of low furniture (tables, chests) and tall furniture
            (wardrobes, shelves).
        free_share: share of boxes standing free in the room (islands; pillars in a hall).
        pillars: free-standing boxes are pillars from floor to ceiling.
        lamps: share of boxes hanging from the ceiling (lamps, ducts) anywhere above head height.
        wall_margin: the walk's distance from the walls at its largest.
        orbit_margin: the orbit's distance from the nearest wall at its largest.
        clearance: least horizontal distance from the camera path to a box (boxes above the camera
            by 0.4 m or more excepted).
        object_scale: size of the object an orbit circles (1: a table with things on it).
        camera_height: range of the camera's height above the floor.
        floor_texel, surface_texel: metres per texel of the floor and of every other surface.
        mip_levels: texture pyramid levels (more for far walls).
    """

    size_min: tuple[float, float, float]
    size_max: tuple[float, float, float]
    boxes: tuple[int, int]
    box_width: tuple[float, float]
    box_depth: tuple[float, float]
    low_height: tuple[float, float]
    tall_height: tuple[float, float]
    free_share: float
    pillars: bool
    lamps: float
    wall_margin: float
    orbit_margin: float
    clearance: float
    object_scale: float
    camera_height: tuple[float, float]
    floor_texel: float
    surface_texel: float
    mip_levels: int


ROOMS = {
    "office": RoomKind((3.8, 3.3, 2.5), (4.6, 4.0, 2.8), (5, 8), (0.4, 1.2), (0.3, 0.6), (0.4, 0.8), (1.4, 2.1),
                       0.0, False, 0.0, 1.0, 0.8, 0.4, 0.8, (1.3, 1.5), 0.005, 0.01, 4),
    "room": RoomKind((7.5, 5.6, 2.7), (9.0, 6.6, 3.1), (8, 12), (0.5, 1.6), (0.35, 0.9), (0.35, 1.1), (1.6, 2.3),
                     0.1, False, 0.0, 1.5, 1.0, 0.6, 1.0, (1.3, 1.5), 0.005, 0.01, 5),
    "hall": RoomKind((16.0, 12.0, 4.5), (22.0, 16.0, 6.0), (16, 24), (0.6, 2.5), (0.4, 1.5), (0.4, 1.2), (1.8, 3.0),
                     0.35, True, 0.0, 3.0, 2.5, 0.8, 1.6, (1.4, 1.6), 0.01, 0.02, 6),
    "corridor": RoomKind((30.0, 2.3, 2.6), (38.0, 2.8, 3.0), (16, 24), (0.3, 1.5), (0.1, 0.3), (0.4, 1.0),
                         (1.6, 2.2), 0.0, False, 0.3, 0.0, 0.0, 0.3, 0.5, (1.5, 1.65), 0.008, 0.01, 6),
}
"""The kinds of room: a small office, a furnished room (the original world's size), a large hall
with pillars, a long narrow corridor with shallow boxes along its walls and lamps under its ceiling."""


@dataclass(frozen=True)
class Style:
    """One style of sequence (see the module docstring).

    Attributes:
        name: what ``sl4slam synth --style`` takes.
        room: a :data:`ROOMS` key.
        texture: a texture kind (``TEXTURE_KINDS``).
        motion: a :data:`MOTIONS` name.
        speed: a :data:`SPEEDS` key ("-" for ``lap``, whose speed follows from its frames).
        loops: a :data:`LOOPS` name.
        frames: the default number of frames.
        description: one line on what it is.
    """

    name: str
    room: str
    texture: str
    motion: str
    speed: str
    loops: str
    frames: int
    description: str


STYLES = {style.name: style for style in (
    Style("lap", "room", "normal", "lap", "-", "one", 600,
          "the original world: one lap of a furnished room, looking outwards, with a floor-only stretch"),
    Style("office-walk-slow", "office", "normal", "walk", "slow", "one", 600, "slow handheld walk once round an office"),
    Style("office-walk-fast", "office", "normal", "walk", "fast", "many", 900, "fast handheld walk round an office, many laps"),
    Style("office-lowtex-walk", "office", "low", "walk", "slow", "one", 600,
          "slow handheld walk once round a low-texture office (painted walls, plain floor)"),
    Style("office-rotate", "office", "normal", "rotate", "slow", "one", 600,
          "slow rotation in place in an office, 1.2 turns, the camera 0.25 m from the axis"),
    Style("room-orbit-slow", "room", "normal", "orbit", "slow", "one", 900, "slow orbit once round an object on a table"),
    Style("room-orbit-fast", "room", "normal", "orbit", "fast", "many", 1200, "fast orbits round an object on a table"),
    Style("room-repeat-walk", "room", "repetitive", "walk", "slow", "many", 2000,
          "slow walk, many laps, in a room of repeated tiles and wallpaper"),
    Style("room-walk-open", "room", "normal", "walk", "fast", "none", 300, "fast walk through a room, never back"),
    Style("hall-walk-slow", "hall", "normal", "walk", "slow", "one", 3000, "slow walk once round a large hall with pillars"),
    Style("hall-lowtex-orbit", "hall", "low", "orbit", "slow", "one", 1500, "slow orbit round a plinth in a low-texture hall"),
    Style("hall-rotate-fast", "hall", "normal", "rotate", "fast", "many", 450,
          "fast rotation in place in a hall, many turns, the camera 0.25 m from the axis"),
    Style("corridor-forward-slow", "corridor", "normal", "forward", "slow", "none", 600, "slow walk forward along a corridor"),
    Style("corridor-repeat-fast", "corridor", "repetitive", "forward", "fast", "one", 1200,
          "fast walk down a repetitive corridor and back to the start"),
)}
"""Every style by name."""


def get_style(name: str) -> Style:
    """The style called ``name``.

    Raises:
        UserError: no such style (the line lists them).
    """
    try:
        return STYLES[name]
    except KeyError:
        raise UserError(f"unknown style {name!r}; styles: {', '.join(STYLES)}") from None


def check_style_request(num_frames: int, width: int, height: int, seed: int) -> None:
    """Check a styled sequence's frames, image size and seed.

    Raises:
        UserError: one line naming the accepted range of the first value out of it.
    """
    if not 2 <= int(num_frames) <= MAX_FRAMES:
        raise UserError(f"--frames must be from 2 to {MAX_FRAMES}, got {num_frames}")
    if not (16 <= int(width) <= 4096 and 16 <= int(height) <= 4096):
        raise UserError(f"image size must be from 16x16 to 4096x4096 px, got {width}x{height}")
    if int(seed) < 0:
        raise UserError(f"--seed must be 0 or more, got {seed}")


def _seeds(style: Style, seed: int, stream: int) -> np.random.Generator:
    """A generator for one purpose (1: layout, 2: textures, 3: the path's wobble) of a style and seed."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(style.name.encode()), stream]))


# --------------------------------------------------------------------------------------------
# Poses
# --------------------------------------------------------------------------------------------


def poses_from_angles(position: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray | None = None) -> np.ndarray:
    """``(N, 4, 4)`` ``T_world_cam`` (OpenCV camera axes, world ``z`` up) from a position and angles.

    Args:
        position: ``(N, 3)`` camera centres.
        yaw: ``(N,)`` radians, heading in the xy plane from the ``x`` axis.
        pitch: ``(N,)`` radians above the horizon (negative: looking down).
        roll: ``(N,)`` radians about the viewing direction (default 0).
    """
    yaw, pitch = np.asarray(yaw, np.float64), np.asarray(pitch, np.float64)
    roll = np.zeros_like(yaw) if roll is None else np.asarray(roll, np.float64)
    forward = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1)
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)
    down = np.cross(forward, right)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    T = np.tile(np.eye(4), (yaw.shape[0], 1, 1))
    T[:, :3, 0] = c * right + s * down
    T[:, :3, 1] = -s * right + c * down
    T[:, :3, 2] = forward
    T[:, :3, 3] = position
    return T


def _wobble(rng: np.random.Generator, t: np.ndarray, amplitude: float, channels: int = 3, terms: int = 3) -> np.ndarray:
    """``(N, channels)`` smooth handheld wobble: per channel a weighted sum of ``terms`` sinusoids of
    0.2-1.5 Hz with seeded phases, peak about ``amplitude``. Draws a fixed number of values, so the
    same generator state gives the same wobble for any ``t``."""
    frequency = rng.uniform(0.2, 1.5, (channels, terms))
    phase = rng.uniform(0.0, 2.0 * np.pi, (channels, terms))
    weight = rng.uniform(0.5, 1.0, (channels, terms))
    weight /= weight.sum(axis=1, keepdims=True)
    waves = np.sin(2.0 * np.pi * frequency[None] * t[:, None, None] + phase[None])
    return amplitude * (waves * weight[None]).sum(axis=2)


def _schedule(style: Style, num_frames: int, size_min: float, size_max: float, lap_length: Callable[[float], float]):
    """The path's size and laps for ``num_frames`` at the style's speed (see the module docstring).

    Args:
        size_min, size_max: the sizes the room holds (a scale, a radius, a straight's length).
        lap_length: the length of one lap at a size.

    Returns:
        ``(size, laps)``.
    """
    duration = max(num_frames - 1, 1) / FPS
    distance = SPEEDS[style.speed][0] * duration
    laps = LAPS[style.loops]
    # The lap length grows with the size; find the size whose laps cover the distance (bisection).
    lo, hi = size_min, max(size_max, size_min)
    if lap_length(hi) * laps <= distance:
        size = hi
        if style.loops == "many":
            laps = distance / lap_length(hi)
        return size, laps
    if lap_length(lo) * laps >= distance:
        return lo, laps
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if lap_length(mid) * laps < distance else (lo, mid)
    return 0.5 * (lo + hi), laps


# --------------------------------------------------------------------------------------------
# Motions: each a plan drawn with the layout, and its poses for any number of frames
# --------------------------------------------------------------------------------------------


@dataclass
class _Walk:
    """A handheld walk along a closed, slightly irregular oval, scaled about the room's centre."""

    centre: np.ndarray
    radii: np.ndarray
    shape: np.ndarray  # a2, phase2, a3, phase3
    direction: float
    start: float
    height: float
    s_min: float = 0.35
    drift: float = 0.1

    def unit(self, theta: np.ndarray) -> np.ndarray:
        """``(N, 2)`` the oval at scale 1, relative to the centre, at angles ``theta``."""
        a2, p2, a3, p3 = self.shape
        r = 1.0 + a2 * np.cos(2.0 * theta + p2) + a3 * np.cos(3.0 * theta + p3)
        grid = np.linspace(0.0, 2.0 * np.pi, 2049)
        rg = 1.0 + a2 * np.cos(2.0 * grid + p2) + a3 * np.cos(3.0 * grid + p3)
        extent = np.array([np.abs(rg * np.cos(grid)).max(), np.abs(rg * np.sin(grid)).max()])
        return np.stack([r * np.cos(theta), r * np.sin(theta)], axis=-1) / extent * self.radii

    def _arc(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Angles, their arc-length fractions and the oval's length at scale 1."""
        theta = np.linspace(0.0, 2.0 * np.pi, 4097)
        steps = np.linalg.norm(np.diff(self.unit(theta), axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(steps)])
        return theta, arc / arc[-1], float(arc[-1])

    def keep_out(self, clearance: float) -> np.ndarray:
        """``(M, 2)`` floor points the furniture keeps ``clearance`` from (every size the path may take)."""
        theta = np.linspace(0.0, 2.0 * np.pi, 361)
        scales = np.linspace(self.s_min, 1.0, max(2, int(np.ceil((1.0 - self.s_min) * self.radii.max() / 0.25)) + 1))
        return np.concatenate([self.centre + s * self.unit(theta) for s in scales])

    def poses(self, style: Style, num_frames: int, rng: np.random.Generator) -> np.ndarray:
        """``(N, 4, 4)`` ``T_world_cam`` of ``num_frames`` frames at the style's speed and loops; the
        handheld wobble and the swings' phases drawn from ``rng``."""
        theta_grid, arc, length = self._arc()
        scale, laps = _schedule(style, num_frames, self.s_min, 1.0, lambda s: s * length)
        fast = style.speed == "fast"
        swing = np.deg2rad(35.0 if fast else 25.0)
        phases = rng.uniform(0.0, 2.0 * np.pi, 4)
        t = np.arange(num_frames) / FPS
        progress = laps * np.arange(num_frames) / max(num_frames - 1, 1)  # laps done
        fraction = self.start + self.direction * progress

        def at(f: np.ndarray) -> np.ndarray:
            """``(N, 2)`` points at lap fractions ``f``."""
            theta = np.interp(np.mod(f, 1.0), arc, theta_grid)
            return self.centre + scale * self.unit(theta)

        xy = at(fraction)
        tangent = (at(fraction + 1e-4 * self.direction) - at(fraction - 1e-4 * self.direction))
        heading = np.arctan2(tangent[:, 1], tangent[:, 0])
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
        xy = xy + normal * (self.drift * np.sin(2.0 * np.pi * progress / 2.7 + phases[0]))[:, None]
        lap_phase = 2.0 * np.pi * np.mod(fraction, 1.0)
        yaw = heading + swing * np.sin(2.0 * lap_phase + phases[1])
        pitch = np.deg2rad(-12.0) + np.deg2rad(6.0) * np.sin(3.0 * lap_phase + phases[2])
        z = self.height + 0.02 * np.sin(2.0 * np.pi * 1.8 * t + phases[3])
        shake = _wobble(rng, t, np.deg2rad(1.2 if fast else 0.6))
        sway = _wobble(rng, t, 0.01)
        position = np.concatenate([xy, z[:, None]], axis=1) + sway
        return poses_from_angles(position, yaw + shake[:, 0], pitch + shake[:, 1], shake[:, 2])


@dataclass
class _Orbit:
    """An orbit round an object, looking at its centre."""

    target: np.ndarray
    r_min: float
    r_max: float
    direction: float
    start: float
    rise: float

    def keep_out(self, clearance: float) -> np.ndarray:
        """``(M, 2)`` floor points the furniture keeps ``clearance`` from (every size the path may take)."""
        theta = np.linspace(0.0, 2.0 * np.pi, 361)
        radii = np.linspace(self.r_min, self.r_max, max(2, int(np.ceil((self.r_max - self.r_min) / 0.25)) + 1))
        ring = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
        return np.concatenate([self.target[:2] + r * ring for r in radii])

    def poses(self, style: Style, num_frames: int, rng: np.random.Generator) -> np.ndarray:
        """``(N, 4, 4)`` ``T_world_cam`` of ``num_frames`` frames at the style's speed and loops; the
        handheld wobble and the swings' phases drawn from ``rng``."""
        radius, laps = _schedule(style, num_frames, self.r_min, self.r_max, lambda r: 2.0 * np.pi * r)
        phase = rng.uniform(0.0, 2.0 * np.pi)
        t = np.arange(num_frames) / FPS
        progress = laps * np.arange(num_frames) / max(num_frames - 1, 1)
        angle = 2.0 * np.pi * (self.start + self.direction * progress)
        position = np.stack([self.target[0] + radius * np.cos(angle), self.target[1] + radius * np.sin(angle),
                             self.target[2] + self.rise + 0.1 * np.sin(2.0 * angle + phase)], axis=-1)
        position = position + _wobble(rng, t, 0.01)
        look = self.target - position
        yaw = np.arctan2(look[:, 1], look[:, 0])
        pitch = np.arctan2(look[:, 2], np.hypot(look[:, 0], look[:, 1]))
        shake = _wobble(rng, t, np.deg2rad(1.0 if style.speed == "fast" else 0.5))
        return poses_from_angles(position, yaw + shake[:, 0], pitch + shake[:, 1], shake[:, 2])


@dataclass
class _Rotate:
    """A rotation in place, as a person turning on the spot holds a camera: it turns about a vertical
    axis ``arm`` metres behind it (its centre circles that axis; with no arm at all the ground
    truth would have no extent, and a trajectory error aligned on positions no meaning)."""

    position: np.ndarray
    yaw: float
    direction: float
    arm: float = 0.25

    def keep_out(self, clearance: float) -> np.ndarray:
        """``(M, 2)`` floor points the furniture keeps ``clearance`` from (every size the path may take)."""
        theta = np.linspace(0.0, 2.0 * np.pi, 73)
        return self.position[:2] + (self.arm + 0.2) * np.stack([np.cos(theta), np.sin(theta)], axis=-1)

    def poses(self, style: Style, num_frames: int, rng: np.random.Generator) -> np.ndarray:
        """``(N, 4, 4)`` ``T_world_cam`` of ``num_frames`` frames at the style's speed and loops; the
        handheld wobble and the swings' phases drawn from ``rng``."""
        turns = LAPS[style.loops]
        duration = max(num_frames - 1, 1) / FPS
        if style.loops == "many":
            turns = max(turns, SPEEDS[style.speed][1] * duration / 360.0)
        phase = rng.uniform(0.0, 2.0 * np.pi)
        t = np.arange(num_frames) / FPS
        turned = 2.0 * np.pi * turns * np.arange(num_frames) / max(num_frames - 1, 1)
        yaw = self.yaw + self.direction * turned
        pitch = np.deg2rad(-8.0) + np.deg2rad(8.0) * np.sin(2.0 * turned + phase)
        shake = _wobble(rng, t, np.deg2rad(0.8 if style.speed == "fast" else 0.4))
        position = self.position + self.arm * np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=-1)
        return poses_from_angles(position, yaw + shake[:, 0], pitch + shake[:, 1], shake[:, 2])


@dataclass
class _Forward:
    """A walk forward along a corridor (``x``): straight for ``none``, out and back round a stadium
    (two straights ``2 * half_gap`` apart joined by half circles) for loops."""

    x_start: float
    x_end: float
    centre_y: float
    height: float
    half_gap: float = 0.45
    sway: float = 0.1
    straight_min: float = 3.0

    def keep_out(self, clearance: float) -> np.ndarray:
        """``(M, 2)`` floor points the furniture keeps ``clearance`` from (every size the path may take)."""
        x = np.arange(self.x_start - self.half_gap, self.x_end + self.half_gap + 0.01, 0.2)
        band = self.half_gap + self.sway
        return np.concatenate([np.stack([x, np.full_like(x, self.centre_y + y)], axis=-1)
                               for y in np.linspace(-band, band, 5)])

    def poses(self, style: Style, num_frames: int, rng: np.random.Generator) -> np.ndarray:
        """``(N, 4, 4)`` ``T_world_cam`` of ``num_frames`` frames at the style's speed and loops; the
        handheld wobble and the swings' phases drawn from ``rng``."""
        phases = rng.uniform(0.0, 2.0 * np.pi, 4)
        t = np.arange(num_frames) / FPS
        share = np.arange(num_frames) / max(num_frames - 1, 1)
        if style.loops == "none":
            duration = max(num_frames - 1, 1) / FPS
            distance = min(SPEEDS[style.speed][0] * duration, self.x_end - self.x_start)
            xy = np.stack([self.x_start + distance * share,
                           self.centre_y + self.sway * np.sin(2.0 * np.pi * 0.25 * t + phases[0])], axis=-1)
            heading = np.zeros(num_frames)
            yaw = heading + np.deg2rad(6.0) * np.sin(2.0 * np.pi * 0.2 * t + phases[1])
        else:
            rho = self.half_gap
            straight_max = self.x_end - self.x_start - 2.0 * rho
            straight, laps = _schedule(style, num_frames, self.straight_min, straight_max,
                                       lambda s: 2.0 * s + 2.0 * np.pi * rho)
            lap_length = 2.0 * straight + 2.0 * np.pi * rho
            along = np.mod(laps * share, 1.0) * lap_length
            x0 = self.x_start + rho
            xy, heading = np.zeros((num_frames, 2)), np.zeros(num_frames)
            ends = np.cumsum([straight, np.pi * rho, straight, np.pi * rho])
            out, turn1, back = along < ends[0], (along >= ends[0]) & (along < ends[1]), (along >= ends[1]) & (along < ends[2])
            turn2 = along >= ends[2]
            xy[out] = np.stack([x0 + along[out], np.full(out.sum(), self.centre_y - rho)], axis=-1)
            a = (along[turn1] - ends[0]) / rho - np.pi / 2.0
            xy[turn1] = np.stack([x0 + straight + rho * np.cos(a), self.centre_y + rho * np.sin(a)], axis=-1)
            heading[turn1] = a + np.pi / 2.0
            xy[back] = np.stack([x0 + straight - (along[back] - ends[1]), np.full(back.sum(), self.centre_y + rho)], axis=-1)
            heading[back] = np.pi
            a = (along[turn2] - ends[2]) / rho + np.pi / 2.0
            xy[turn2] = np.stack([x0 + rho * np.cos(a), self.centre_y + rho * np.sin(a)], axis=-1)
            heading[turn2] = a + np.pi / 2.0
            yaw = heading + np.deg2rad(6.0) * np.sin(2.0 * np.pi * 4.0 * np.mod(laps * share, 1.0) + phases[1])
        pitch = np.deg2rad(-5.0) + np.deg2rad(3.0) * np.sin(2.0 * np.pi * 0.15 * t + phases[2])
        z = self.height + 0.02 * np.sin(2.0 * np.pi * 1.8 * t + phases[3])
        shake = _wobble(rng, t, np.deg2rad(1.2 if style.speed == "fast" else 0.6))
        position = np.concatenate([xy, z[:, None]], axis=1) + _wobble(rng, t, 0.01)
        return poses_from_angles(position, yaw + shake[:, 0], pitch + shake[:, 1], shake[:, 2])


# --------------------------------------------------------------------------------------------
# Layouts
# --------------------------------------------------------------------------------------------


@dataclass
class StyleLayout:
    """A style's room and furniture (:class:`sl4slam.synthetic.world.Layout`) with its camera plan.

    Attributes:
        style: the style.
        seed: the seed.
        layout: room and boxes.
        plan: the motion's parameters; ``plan.poses(style, frames, rng)`` gives the path.
        target: ``(3,)`` the orbited object's centre (None for other motions).
    """

    style: Style
    seed: int
    layout: Layout
    plan: object
    target: np.ndarray | None = None


def _conflicts(lo: np.ndarray, hi: np.ndarray, keep_xy: np.ndarray, camera_top: float, clearance: float) -> bool:
    """Whether a box comes within ``clearance`` (horizontally) of a path point, unless it hangs 0.4 m
    or more above the camera."""
    if lo[2] >= camera_top + 0.4:
        return False
    dx = np.maximum(np.maximum(lo[0] - keep_xy[:, 0], keep_xy[:, 0] - hi[0]), 0.0)
    dy = np.maximum(np.maximum(lo[1] - keep_xy[:, 1], keep_xy[:, 1] - hi[1]), 0.0)
    return bool(np.hypot(dx, dy).min() < clearance)


def _furnish(rng: np.random.Generator, room: RoomKind, size: np.ndarray, keep_xy: np.ndarray, camera_top: float,
             boxes_min: list, boxes_max: list) -> None:
    """Add seeded furniture boxes to ``boxes_min`` / ``boxes_max`` (in place), clear of the path."""
    wanted = len(boxes_min) + int(rng.integers(room.boxes[0], room.boxes[1] + 1))
    for _attempt in range(60 * wanted):
        if len(boxes_min) >= wanted:
            break
        kind = rng.uniform()
        lo, hi = np.zeros(3), np.zeros(3)
        if kind < room.lamps:  # hanging from the ceiling
            length, width = rng.uniform(0.6, 1.4), rng.uniform(0.2, 0.4)
            along = int(rng.integers(2))
            extent = np.array([length, width]) if along == 0 else np.array([width, length])
            corner = rng.uniform([0.0, 0.0], size[:2] - extent)
            lo[:2], hi[:2] = corner, corner + extent
            lo[2], hi[2] = size[2] - rng.uniform(0.05, 0.12), size[2]
        elif kind < room.lamps + room.free_share:  # standing free: an island, or a pillar in a hall
            if room.pillars:
                side = rng.uniform(0.4, 0.8)
                extent = np.array([side, side])
                top = size[2]
            else:
                extent = np.array([rng.uniform(*room.box_width), rng.uniform(*room.box_depth)])
                top = rng.uniform(*room.low_height)
            corner = rng.uniform([0.3, 0.3], size[:2] - extent - 0.3)
            lo[:2], hi[:2] = corner, corner + extent
            lo[2], hi[2] = 0.0, top
        else:  # against a wall: a wall cabinet, a tall wardrobe or a low table / chest
            width, depth = rng.uniform(*room.box_width), rng.uniform(*room.box_depth)
            form = rng.uniform()
            if form < 0.15:
                bottom, height = rng.uniform(1.2, 1.8), rng.uniform(0.3, 0.7)
                depth = min(depth, 0.45)
            elif form < 0.4:
                bottom, height = 0.0, rng.uniform(*room.tall_height)
            else:
                bottom, height = 0.0, rng.uniform(*room.low_height)
            wall = int(rng.integers(4))
            along_axis = 0 if wall < 2 else 1
            across_axis = 1 - along_axis
            width = min(width, size[along_axis] - 0.3)
            start = rng.uniform(0.1, size[along_axis] - width - 0.1)
            lo[along_axis], hi[along_axis] = start, start + width
            gap = rng.uniform(0.0, 0.1) if bottom == 0.0 else 0.0
            if wall % 2 == 0:
                lo[across_axis], hi[across_axis] = gap, gap + depth
            else:
                lo[across_axis], hi[across_axis] = size[across_axis] - gap - depth, size[across_axis] - gap
            lo[2], hi[2] = bottom, bottom + height
        hi[2] = min(hi[2], size[2] - 0.02)
        if _conflicts(lo, hi, keep_xy, camera_top, room.clearance):
            continue
        if any(np.all(lo < b_hi + 0.05) and np.all(hi > b_lo - 0.05) for b_lo, b_hi in zip(boxes_min, boxes_max)):
            continue
        boxes_min.append(lo)
        boxes_max.append(hi)


def _orbit_object(rng: np.random.Generator, centre_xy: np.ndarray, scale: float) -> tuple[list, list, np.ndarray]:
    """A table (a plinth when large) with two or three things stacked on it, centred at ``centre_xy``.

    Returns:
        The boxes' minimum and maximum corners, and the ``(3,)`` centre the camera looks at.
    """
    table = np.array([rng.uniform(0.9, 1.3), rng.uniform(0.6, 0.9)]) * scale
    table_height = rng.uniform(0.72, 0.8) if scale <= 1.0 else rng.uniform(0.5, 0.9)
    boxes_min = [np.array([*(centre_xy - table / 2), 0.0])]
    boxes_max = [np.array([*(centre_xy + table / 2), table_height])]
    top = table_height
    footprint = table * rng.uniform(0.4, 0.6)
    for _ in range(int(rng.integers(2, 4))):
        height = rng.uniform(0.15, 0.4) * scale
        offset = rng.uniform(-0.1, 0.1, 2) * footprint
        boxes_min.append(np.array([*(centre_xy + offset - footprint / 2), top]))
        boxes_max.append(np.array([*(centre_xy + offset + footprint / 2), top + height]))
        top += height
        footprint = footprint * rng.uniform(0.6, 0.85)
    target = np.array([centre_xy[0], centre_xy[1], 0.5 * (table_height + top)])
    return boxes_min, boxes_max, target


def make_style_layout(style: Style | str, seed: int = 0) -> StyleLayout:
    """The room, furniture and camera plan of a style and seed (no textures; cheap).

    Args:
        style: a :class:`Style` or its name.
        seed: a non-negative integer.

    Returns:
        The :class:`StyleLayout`. For ``lap``, the original world's layout (:func:`make_layout`).
    """
    style = get_style(style) if isinstance(style, str) else style
    if style.motion == "lap":
        return StyleLayout(style, int(seed), make_layout(seed), None)
    room = ROOMS[style.room]
    rng = _seeds(style, seed, 1)
    size = rng.uniform(room.size_min, room.size_max)
    height = float(rng.uniform(*room.camera_height))
    centre = size[:2] / 2.0
    direction = float(rng.choice([-1.0, 1.0]))
    boxes_min: list = []
    boxes_max: list = []
    target = None
    camera_top = height + 0.15
    if style.motion == "walk":
        radii = centre - room.wall_margin
        shape = np.array([rng.uniform(0.0, 0.12), rng.uniform(0.0, 2 * np.pi), rng.uniform(0.0, 0.08),
                          rng.uniform(0.0, 2 * np.pi)])
        plan = _Walk(centre, radii, shape, direction, float(rng.uniform()), height)
    elif style.motion == "orbit":
        object_centre = centre + rng.uniform(-0.2, 0.2, 2)
        boxes_min, boxes_max, target = _orbit_object(rng, object_centre, room.object_scale)
        reach = max(np.hypot(*(b_hi[:2] - b_lo[:2])) / 2 for b_lo, b_hi in zip(boxes_min, boxes_max))
        r_min = reach + room.clearance + 0.4
        r_max = max(r_min, float(min(object_centre.min(), (size[:2] - object_centre).min())) - room.orbit_margin)
        rise = float(rng.uniform(0.3, 0.6))
        camera_top = target[2] + rise + 0.25
        plan = _Orbit(target, r_min, r_max, direction, float(rng.uniform()), rise)
    elif style.motion == "rotate":
        axis = np.array([*(centre + rng.uniform(-0.3, 0.3, 2)), height])
        plan = _Rotate(axis, float(rng.uniform(0.0, 2.0 * np.pi)), direction)
    elif style.motion == "forward":
        plan = _Forward(1.2, float(size[0] - 1.2), float(centre[1]), height)
    else:
        raise ValueError(f"motion must be one of {', '.join(MOTIONS)}, got {style.motion!r}")
    _furnish(rng, room, size, plan.keep_out(room.clearance), camera_top, boxes_min, boxes_max)
    layout = Layout(room_min=np.zeros(3), room_max=size,
                    boxes_min=np.array(boxes_min, np.float64).reshape(-1, 3),
                    boxes_max=np.array(boxes_max, np.float64).reshape(-1, 3))
    return StyleLayout(style, int(seed), layout, plan, target)


def make_style_world(style: Style | str, seed: int = 0, layout: StyleLayout | None = None) -> World:
    """The textured world of a style and seed (the original world for ``lap``).

    Args:
        style: a :class:`Style` or its name.
        seed: a non-negative integer.
        layout: its :func:`make_style_layout`, when already made.
    """
    style = get_style(style) if isinstance(style, str) else style
    if style.motion == "lap":
        return make_world(seed)
    layout = layout or make_style_layout(style, seed)
    room = ROOMS[style.room]
    if style.texture not in TEXTURE_KINDS:
        raise ValueError(f"texture kind must be one of {', '.join(TEXTURE_KINDS)}, got {style.texture!r}")
    texture_rng = _seeds(style, seed, 2)
    return build_world(layout.layout, texture_rng, seed, texture_maker(style.texture, texture_rng),
                       floor_texel_m=room.floor_texel, surface_texel_m=room.surface_texel, mip_levels=room.mip_levels)


def style_path(style: Style | str, num_frames: int, seed: int = 0, layout: StyleLayout | None = None) -> np.ndarray:
    """The camera path of a style and seed over ``num_frames`` frames (30 per second).

    Args:
        style: a :class:`Style` or its name.
        num_frames: at least 2.
        seed: a non-negative integer.
        layout: its :func:`make_style_layout`, when already made.

    Returns:
        ``(N, 4, 4)`` float64 ``T_world_cam`` (OpenCV camera axes, world ``z`` up).
    """
    style = get_style(style) if isinstance(style, str) else style
    if style.motion == "lap":
        return camera_path(int(num_frames), seed)
    layout = layout or make_style_layout(style, seed)
    return layout.plan.poses(style, int(num_frames), _seeds(style, seed, 3))


def style_summary(style: Style) -> str:
    """One line: ``name: room, texture, motion, speed, loops, frames - description``."""
    return (f"{style.name}: {style.room}, {style.texture} texture, {style.motion}, {style.speed}, "
            f"loops {style.loops}, {style.frames} frames - {style.description}")


__all__ = ["Style", "RoomKind", "StyleLayout", "STYLES", "ROOMS", "MOTIONS", "LOOPS", "LAPS", "SPEEDS", "FPS",
           "MAX_FRAMES", "get_style", "check_style_request", "make_style_layout", "make_style_world", "style_path",
           "poses_from_angles", "style_summary"]
