"""Seeded procedural textures: rich, multi-scale and non-repeating, different for every surface.

A texture is built in metric units (``texel_m`` metres per texel) from

- coloured value noise at several octaves (each octave has its own random colour direction),
- a few random-phase oriented sinusoidal gratings,
- random shapes (ellipses, rectangles, polygons, strokes, short text) drawn with OpenCV,
  sized in metres so the same style looks alike on any surface size,

so that Lucas-Kanade finds corners at every viewing distance and no two places look the same.
Per-style parameters pick the palette and the shape mix (floor: terrazzo chips and rugs; walls:
posters and blobs; ceiling: pale with panels; furniture: saturated, patterned).
"""

from __future__ import annotations

import math
import string

import cv2
import numpy as np

_STYLES = {
    # value: (base brightness, saturation of the base, noise amplitude, shapes per m^2,
    #         shape size range in metres, small chips per m^2, posters per m^2; tint: RGB offset of the base)
    "floor": dict(tint=(0.10, 0.02, -0.10), base=0.50, saturation=0.25, noise=0.30, shapes=10.0, size=(0.04, 0.30), chips=220.0, posters=0.08),
    "wall": dict(tint=(0.0, 0.0, 0.0), base=0.62, saturation=0.25, noise=0.22, shapes=18.0, size=(0.03, 0.35), chips=25.0, posters=0.20),
    "ceiling": dict(tint=(0.02, 0.02, 0.0), base=0.78, saturation=0.10, noise=0.15, shapes=6.0, size=(0.05, 0.40), chips=10.0, posters=0.10),
    "furniture": dict(tint=(0.0, 0.0, 0.0), base=0.50, saturation=0.50, noise=0.25, shapes=35.0, size=(0.02, 0.20), chips=60.0, posters=0.0),
}

TEXTURE_STYLES = tuple(_STYLES)

_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_TRIPLEX)


def _random_colours(rng: np.random.Generator, brightness, saturation, count: int) -> np.ndarray:
    """``(count, 3)`` RGB colours in [0, 1] with roughly the given brightness and saturation (scalars or ``(count,)``)."""
    hue_direction = rng.normal(size=(count, 3))
    hue_direction -= hue_direction.mean(axis=1, keepdims=True)
    hue_direction /= np.linalg.norm(hue_direction, axis=1, keepdims=True) + 1e-9
    brightness = np.broadcast_to(np.asarray(brightness, np.float64), (count,))[:, None]
    saturation = np.broadcast_to(np.asarray(saturation, np.float64), (count,))[:, None]
    return np.clip(brightness + saturation * 0.5 * hue_direction, 0.0, 1.0)


def _random_colour(rng: np.random.Generator, brightness: float, saturation: float) -> np.ndarray:
    """One ``(3,)`` RGB colour (see :func:`_random_colours`)."""
    return _random_colours(rng, brightness, saturation, 1)[0]


def _value_noise(rng: np.random.Generator, rows: int, cols: int, cells_r: int, cells_c: int) -> np.ndarray:
    """``(rows, cols)`` float32 smooth noise in about [-1, 1]: a random grid upsampled bicubically."""
    grid = rng.uniform(-1.0, 1.0, size=(cells_r + 3, cells_c + 3)).astype(np.float32)
    big = cv2.resize(grid, (cols + 2 * max(1, cols // (cells_c + 1)), rows + 2 * max(1, rows // (cells_r + 1))),
                     interpolation=cv2.INTER_CUBIC)
    # Crop the interior so the outermost (unsupported) cubic cells do not show.
    r0 = (big.shape[0] - rows) // 2
    c0 = (big.shape[1] - cols) // 2
    return big[r0:r0 + rows, c0:c0 + cols]


def _draw_text(rng: np.random.Generator, canvas: np.ndarray, centre, size_px: float, colour) -> None:
    """Stamp a short random string onto ``canvas`` (float32, in place) via a small uint8 coverage mask."""
    text = "".join(rng.choice(list(string.ascii_uppercase + string.digits), size=int(rng.integers(2, 6))))
    scale = max(size_px / 30.0, 0.3)
    thickness = max(1, int(round(scale * 2)))
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    (width, height), baseline = cv2.getTextSize(text, font, scale, thickness)
    mask = np.zeros((height + baseline + 2 * thickness, width + 2 * thickness), np.uint8)
    cv2.putText(mask, text, (thickness, height + thickness), font, scale, 255, thickness, cv2.LINE_AA)
    r0, c0 = int(centre[1]) - mask.shape[0] // 2, int(centre[0]) - mask.shape[1] // 2
    rows, cols = canvas.shape[:2]
    rr0, cc0 = max(r0, 0), max(c0, 0)
    rr1, cc1 = min(r0 + mask.shape[0], rows), min(c0 + mask.shape[1], cols)
    if rr1 <= rr0 or cc1 <= cc0:
        return
    alpha = mask[rr0 - r0:rr1 - r0, cc0 - c0:cc1 - c0, None].astype(np.float32) / 255.0
    region = canvas[rr0:rr1, cc0:cc1]
    region *= 1.0 - alpha
    region += alpha * np.asarray(colour, np.float32)


def _draw_shapes(rng: np.random.Generator, canvas: np.ndarray, count: int, size_range_px: tuple[float, float],
                 brightness: float, saturation: float, kinds: tuple[str, ...]) -> None:
    """Draw ``count`` random filled/outlined shapes onto ``canvas`` ((rows, cols, 3) float32, in place).

    All random parameters are drawn up front in arrays; the loop only issues the drawing calls.
    """
    if count <= 0:
        return
    rows, cols = canvas.shape[:2]
    lo, hi = max(size_range_px[0], 1.0), max(size_range_px[1], size_range_px[0] + 1.0, 2.0)
    kind_index = rng.integers(len(kinds), size=count)
    # Log-uniform sizes: many small shapes, a few big ones (multi-scale).
    sizes = np.exp(rng.uniform(math.log(lo), math.log(hi), size=count))
    centres = rng.uniform((0.0, 0.0), (cols, rows), size=(count, 2))
    colours = _random_colours(rng, rng.uniform(0.15, 0.9, count), saturation * rng.uniform(0.3, 1.2, count), count)
    filled = rng.uniform(size=count) < 0.7
    line_width = np.maximum(1, (sizes * rng.uniform(0.05, 0.2, count)).astype(int))
    aspect = rng.uniform(0.3, 1.0, count)
    stretch = rng.uniform(0.5, 2.0, size=(count, 2))
    angles = rng.uniform(0.0, 180.0, count)
    for i in range(count):
        kind = kinds[kind_index[i]]
        size = float(sizes[i])
        colour = (float(colours[i, 0]), float(colours[i, 1]), float(colours[i, 2]))
        thickness = -1 if filled[i] else int(line_width[i])
        cx, cy = float(centres[i, 0]), float(centres[i, 1])
        if kind == "ellipse":
            axes = (max(1, int(size)), max(1, int(size * aspect[i])))
            cv2.ellipse(canvas, (int(cx), int(cy)), axes, float(angles[i]), 0, 360, colour, thickness, cv2.LINE_AA)
        elif kind == "rectangle":
            box = cv2.boxPoints(((cx, cy), (size * stretch[i, 0], size * stretch[i, 1]), float(angles[i]) / 2.0))
            pts = np.round(box).astype(np.int32).reshape(-1, 1, 2)
            if thickness < 0:
                cv2.fillPoly(canvas, [pts], colour, cv2.LINE_AA)
            else:
                cv2.polylines(canvas, [pts], True, colour, thickness, cv2.LINE_AA)
        elif kind == "polygon":
            n = int(rng.integers(3, 7))
            theta = np.sort(rng.uniform(0, 2 * np.pi, n))
            radii = size * rng.uniform(0.4, 1.0, n)
            pts = np.stack([cx + radii * np.cos(theta), cy + radii * np.sin(theta)], 1)
            cv2.fillPoly(canvas, [np.round(pts).astype(np.int32).reshape(-1, 1, 2)], colour, cv2.LINE_AA)
        elif kind == "stroke":
            n = int(rng.integers(2, 5))
            pts = np.cumsum(np.vstack([(cx, cy), rng.normal(scale=size, size=(n, 2))]), axis=0)
            cv2.polylines(canvas, [np.round(pts).astype(np.int32).reshape(-1, 1, 2)], False, colour,
                          max(1, int(size * 0.12)), cv2.LINE_AA)
        else:  # text
            _draw_text(rng, canvas, (cx, cy), size, colour)


def _poster(rng: np.random.Generator, rows: int, cols: int, texel_m: float) -> np.ndarray:
    """A framed rectangular picture with its own palette and pattern, ``(rows, cols, 3)`` float32."""
    palette_brightness = rng.uniform(0.3, 0.8)
    image = np.empty((rows, cols, 3), np.float32)
    image[:] = _random_colour(rng, palette_brightness, 0.8)
    for octave, cells in enumerate((2, 5, 11)):
        noise = _value_noise(rng, rows, cols, cells, max(1, int(cells * cols / max(rows, 1))))
        image += noise[:, :, None] * _random_colour(rng, 0.0, 1.2)[None, None, :] * (0.35 / (octave + 1))
    count = int(rows * cols * texel_m * texel_m * 120) + 5
    _draw_shapes(rng, image, count, (2.0 / texel_m * 0.01, min(rows, cols) / 3.0), 0.5, 0.9,
                 ("ellipse", "rectangle", "polygon", "stroke", "text"))
    frame = max(2, int(0.02 / texel_m))
    cv2.rectangle(image, (0, 0), (cols - 1, rows - 1), tuple(float(c) for c in _random_colour(rng, 0.15, 0.2)), frame)
    return image


def make_texture(rng: np.random.Generator, width_m: float, height_m: float, texel_m: float, style: str) -> np.ndarray:
    """Generate one surface texture.

    Args:
        rng: seeded generator (consumed).
        width_m, height_m: surface extent in metres along its texture u (columns) and v (rows).
        texel_m: metres per texel.
        style: one of ``TEXTURE_STYLES``.

    Returns:
        ``(rows, cols, 3)`` uint8 RGB with ``rows = ceil(height_m / texel_m)``, ``cols = ceil(width_m / texel_m)``.
    """
    params = _STYLES[style]
    rows = max(2, int(math.ceil(height_m / texel_m)))
    cols = max(2, int(math.ceil(width_m / texel_m)))
    area = width_m * height_m
    image = np.empty((rows, cols, 3), np.float32)
    image[:] = np.clip(_random_colour(rng, params["base"] * rng.uniform(0.8, 1.15), params["saturation"])
                       + np.asarray(params["tint"]), 0.0, 1.0)

    # Coloured value noise, octaves from ~1.5 m down to ~3 cm; amplitude falls slowly with scale
    # so fine detail stays visible (LK needs gradients at the pixel scale).
    for octave, scale_m in enumerate((1.5, 0.6, 0.25, 0.1, 0.05, 0.03)):
        noise = _value_noise(rng, rows, cols, max(1, int(height_m / scale_m)), max(1, int(width_m / scale_m)))
        direction = _random_colour(rng, rng.uniform(-0.4, 0.4), 0.8)
        image += noise[:, :, None] * direction[None, None, :] * params["noise"] * (0.8 ** octave)

    # Random-phase oriented gratings (wood-grain / fabric-like streaks), modulated by noise so they never repeat.
    v = (np.arange(rows, dtype=np.float32) * np.float32(texel_m))[:, None]
    u = (np.arange(cols, dtype=np.float32) * np.float32(texel_m))[None, :]
    for _ in range(3):
        angle = rng.uniform(0, np.pi)
        wavelength = rng.uniform(0.04, 0.4)
        phase = rng.uniform(0, 2 * np.pi)
        envelope = 0.5 + 0.5 * _value_noise(rng, rows, cols, max(1, int(height_m / 0.8)), max(1, int(width_m / 0.8)))
        frequency = np.float32(2 * np.pi / wavelength)
        grating = np.sin((np.float32(np.cos(angle)) * u + np.float32(np.sin(angle)) * v) * frequency + np.float32(phase))
        grating *= envelope
        image += grating[:, :, None] * _random_colour(rng, 0.0, 1.0)[None, None, :] * 0.08

    px_per_m = 1.0 / texel_m
    # Small chips (terrazzo on the floor, speckle elsewhere): dense, tiny, high contrast corners.
    _draw_shapes(rng, image, int(params["chips"] * area), (0.008 * px_per_m, 0.03 * px_per_m),
                 params["base"], 1.0, ("ellipse", "polygon", "rectangle"))
    # Posters / rugs / panels: large distinctive landmarks for place recognition.
    for _ in range(rng.poisson(params["posters"] * area) if params["posters"] > 0 else 0):
        ph = int(rng.uniform(0.3, 1.0) * px_per_m)
        pw = int(rng.uniform(0.3, 1.2) * px_per_m)
        if ph >= rows or pw >= cols or ph < 4 or pw < 4:
            continue
        r0 = int(rng.integers(0, rows - ph))
        c0 = int(rng.integers(0, cols - pw))
        image[r0:r0 + ph, c0:c0 + pw] = _poster(rng, ph, pw, texel_m)
    # Mid-size shapes on top.
    lo, hi = params["size"]
    _draw_shapes(rng, image, int(params["shapes"] * area), (lo * px_per_m, hi * px_per_m),
                 params["base"], params["saturation"] + 0.3, ("ellipse", "rectangle", "polygon", "stroke", "text"))
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Texture kinds: normal, low-texture, repetitive
# --------------------------------------------------------------------------------------------

TEXTURE_KINDS = ("normal", "low", "repetitive")
"""The kinds of surface texture a world can have (:func:`texture_maker`)."""

_LOW_NOISE_SHARE = 0.25
"""Low-texture surfaces: amplitude of their value noise, as a share of the normal texture's."""
_LOW_MARKS_PER_M2 = 1.5
"""Low-texture surfaces: small faint marks per square metre (stains, switches, screws)."""
_LOW_MARK_CONTRAST = 0.5
"""Low-texture surfaces: how much of a mark's colour shows over the base (0: invisible, 1: opaque)."""
MOTIF_M = {"floor": 0.40, "wall": 0.30, "ceiling": 0.60, "furniture": 0.15}
"""Repetitive surfaces: side in metres of the square motif each style repeats (tiles, wallpaper, panels)."""


def _texture_size(width_m: float, height_m: float, texel_m: float) -> tuple[int, int]:
    """``(rows, cols)`` of a surface texture (at least 2 x 2 texels)."""
    return max(2, int(math.ceil(height_m / texel_m))), max(2, int(math.ceil(width_m / texel_m)))


def make_low_texture(rng: np.random.Generator, width_m: float, height_m: float, texel_m: float, style: str) -> np.ndarray:
    """A low-texture surface: the style's base colour, faint large-scale shading and a few faint marks.

    Painted walls, a plain floor, bare furniture: Lucas-Kanade finds few corners away from the
    edges between surfaces.

    Args:
        rng: seeded generator (consumed).
        width_m, height_m: surface extent in metres along its texture u (columns) and v (rows).
        texel_m: metres per texel.
        style: one of ``TEXTURE_STYLES``.

    Returns:
        ``(rows, cols, 3)`` uint8 RGB, sized as :func:`make_texture`'s.
    """
    params = _STYLES[style]
    rows, cols = _texture_size(width_m, height_m, texel_m)
    image = np.empty((rows, cols, 3), np.float32)
    image[:] = np.clip(_random_colour(rng, params["base"] * rng.uniform(0.8, 1.15), params["saturation"])
                       + np.asarray(params["tint"]), 0.0, 1.0)
    for scale_m in (1.5, 0.6):
        noise = _value_noise(rng, rows, cols, max(1, int(height_m / scale_m)), max(1, int(width_m / scale_m)))
        image += noise[:, :, None] * np.float32(params["noise"] * _LOW_NOISE_SHARE)
    marks = image.copy()
    px_per_m = 1.0 / texel_m
    _draw_shapes(rng, marks, int(_LOW_MARKS_PER_M2 * width_m * height_m), (0.02 * px_per_m, 0.08 * px_per_m),
                 params["base"], params["saturation"], ("ellipse", "rectangle", "stroke"))
    image += (marks - image) * np.float32(_LOW_MARK_CONTRAST)
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)


def make_motif(rng: np.random.Generator, size_m: float, texel_m: float, style: str) -> np.ndarray:
    """One square motif of a repetitive surface: a small :func:`make_texture` patch with a few bold
    shapes and a dark grout line along two edges (so that the repeats form a grid).

    Returns:
        ``(n, n, 3)`` uint8 RGB, ``n = ceil(size_m / texel_m)``.
    """
    patch = make_texture(rng, size_m, size_m, texel_m, style).astype(np.float32) / 255.0
    side = patch.shape[0]
    _draw_shapes(rng, patch, 4, (0.1 * side, 0.3 * side), 0.5, 0.8, ("ellipse", "rectangle", "polygon"))
    grout = max(1, int(round(0.01 / texel_m)))
    patch[:grout] *= 0.35
    patch[:, :grout] *= 0.35
    return np.clip(patch * 255.0 + 0.5, 0, 255).astype(np.uint8)


def texture_maker(kind: str, rng: np.random.Generator):
    """The texture function of a kind of surface, for :func:`sl4slam.synthetic.world.build_world`.

    Args:
        kind: one of ``TEXTURE_KINDS``: "normal" (:func:`make_texture`: rich and never repeating),
            "low" (:func:`make_low_texture`) or "repetitive" (each style's one motif, :data:`MOTIF_M`
            metres square, repeated over every surface of that style: all walls alike, all floor
            tiles alike).
        rng: seeded generator; "repetitive" draws its motifs' seed from it (once, here).

    Returns:
        ``f(rng, width_m, height_m, texel_m, style) -> (rows, cols, 3) uint8``.
    """
    if kind == "normal":
        return make_texture
    if kind == "low":
        return make_low_texture
    if kind != "repetitive":
        raise ValueError(f"texture kind must be one of {', '.join(TEXTURE_KINDS)}, got {kind!r}")
    motif_seed = int(rng.integers(2**63))
    motifs: dict[tuple[str, float], np.ndarray] = {}

    def make_repetitive(_rng: np.random.Generator, width_m: float, height_m: float, texel_m: float, style: str) -> np.ndarray:
        key = (style, float(texel_m))
        if key not in motifs:
            style_rng = np.random.default_rng(np.random.SeedSequence([motif_seed, TEXTURE_STYLES.index(style)]))
            motifs[key] = make_motif(style_rng, MOTIF_M[style], texel_m, style)
        motif = motifs[key]
        rows, cols = _texture_size(width_m, height_m, texel_m)
        reps = (-(-rows // motif.shape[0]), -(-cols // motif.shape[1]), 1)
        return np.ascontiguousarray(np.tile(motif, reps)[:rows, :cols])

    return make_repetitive
