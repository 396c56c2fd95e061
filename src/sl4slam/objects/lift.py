"""From a 2D mask on a keyframe to the keyframe's world points under it (pure, vectorised).

Frames: a keyframe's points are in the map's world frame (``KeyframeData.points_world``, the frame
of ``trajectory.txt``), in map units; masks and grids are ``(H, W)`` images with rows first.
"""

from __future__ import annotations

import numpy as np

MAD_TO_SIGMA = 1.4826
"""The median absolute deviation of a normal distribution times this is its standard deviation."""


def resize_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of a mask onto another grid (the model's prediction grid).

    Pixel ``(r, c)`` of the output takes the input pixel whose area holds the output pixel's
    centre: row ``floor((r + 0.5) * H_in / H_out)``, likewise for columns.

    Args:
        mask: ``(H_in, W_in)`` bool (anything truthy).
        shape: ``(H_out, W_out)``.

    Returns:
        ``(H_out, W_out)`` bool (the same array's values when the shapes agree).
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be (H, W), got {mask.shape}")
    height, width = int(shape[0]), int(shape[1])
    if mask.shape == (height, width):
        return mask.copy()
    rows = np.minimum(((np.arange(height) + 0.5) * mask.shape[0] / height).astype(np.int64), mask.shape[0] - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * mask.shape[1] / width).astype(np.int64), mask.shape[1] - 1)
    return mask[rows[:, None], cols[None, :]]


def erode_mask(mask: np.ndarray, pixels: int = 1, border: bool = False) -> np.ndarray:
    """Shrink a mask by ``pixels`` (a pixel stays when its whole ``(2p+1) x (2p+1)`` square is in the
    mask).

    Args:
        mask: ``(H, W)`` bool. pixels: the erosion radius (0: unchanged).
        border: whether outside the image counts as in the mask.

    Returns:
        ``(H, W)`` bool.
    """
    mask = np.asarray(mask, dtype=bool)
    if pixels <= 0:
        return mask.copy()
    padded = np.pad(mask, pixels, constant_values=border)
    height, width = mask.shape
    out = np.ones_like(mask)
    for dr in range(2 * pixels + 1):
        for dc in range(2 * pixels + 1):
            out &= padded[dr:dr + height, dc:dc + width]
    return out


def points_under_mask(mask: np.ndarray, points_world: np.ndarray, valid: np.ndarray,
                      confidence: np.ndarray | None = None, min_confidence: float = 0.0,
                      erode_px: int = 0, min_pixels: int = 8, normals: np.ndarray | None = None):
    """The world points of a keyframe under a mask.

    Args:
        mask: ``(h, w)`` bool at any resolution (the image the segmenter saw); resized to the
            keyframe's grid by :func:`resize_mask`.
        points_world: ``(H, W, 3)`` the keyframe's world points (map frame and units).
        valid: ``(H, W)`` bool, the keyframe's mask of valid, confidence-filtered points.
        confidence: ``(H, W)`` per-pixel confidence percentile (0..100) or ``None``.
        min_confidence: keep pixels whose confidence percentile is at least this (on top of ``valid``).
        erode_px: shrink the mask by this many grid pixels first (a mask's rim is where the points
            of the surface behind bleed in; 0 by default: on low-resolution grids it costs the thin
            side faces more than it saves, see docs/decisions/object-fusion.md); skipped when it would
            leave fewer than ``min_pixels``.
        min_pixels: see ``erode_px``.
        normals: ``(H, W, 3)`` per-pixel unit normals (:func:`grid_normals`) to return beside the
            points, or ``None``.

    Returns:
        ``(M, 3)`` float64 world points (``M = 0`` when nothing valid lies under the mask); with
        ``normals``, also their ``(M, 3)`` normals (zero where a pixel had none).
    """
    points_world = np.asarray(points_world)
    grid = resize_mask(mask, points_world.shape[:2])
    keep = np.asarray(valid, dtype=bool)
    if confidence is not None and min_confidence > 0:
        keep = keep & (np.asarray(confidence) >= min_confidence)
    chosen = grid & keep
    if erode_px > 0:
        eroded = erode_mask(grid, erode_px) & keep
        if eroded.sum() >= min_pixels:
            chosen = eroded
    points = points_world[chosen].astype(np.float64)
    finite = np.isfinite(points).all(axis=1)
    if normals is None:
        return points[finite]
    return points[finite], np.asarray(normals, np.float64)[chosen][finite]


NORMAL_STEP_FRACTION = 1.0 / 48.0
"""The baseline of :func:`grid_normals` (its step in pixels) as a fraction of the grid's width: one
pixel's neighbours are too close for a model's depth noise (1 % of the depth is several pixel
spacings), a fiftieth of the image averages over enough surface."""


def grid_normals(points_world: np.ndarray, valid: np.ndarray, camera_centre: np.ndarray | None = None,
                 step: int | None = None) -> np.ndarray:
    """Surface normals of a keyframe's grid of world points, from its neighbours ``step`` pixels away.

    The normal at pixel ``(r, c)`` is the cross product of the central differences along the row
    (``(r, c + s) - (r, c - s)``) and the column, normalised and turned towards ``camera_centre``
    when given.

    Args:
        points_world: ``(H, W, 3)`` world points. valid: ``(H, W)`` bool.
        camera_centre: ``(3,)`` the keyframe's camera centre in the same frame, or ``None``.
        step: the neighbours' distance in pixels (default ``NORMAL_STEP_FRACTION`` of the width, at
            least 1).

    Returns:
        ``(H, W, 3)`` float64 unit normals; zero at pixels whose four neighbours are not all valid
        (and within ``step`` of the border).
    """
    P = np.asarray(points_world, np.float64)
    ok = np.asarray(valid, bool)
    H, W = ok.shape
    s = max(1, int(round(W * NORMAL_STEP_FRACTION))) if step is None else max(1, int(step))
    normals = np.zeros(P.shape, np.float64)
    if H <= 2 * s or W <= 2 * s:
        return normals
    inner = (slice(s, H - s), slice(s, W - s))
    right, left = (slice(s, H - s), slice(2 * s, W)), (slice(s, H - s), slice(0, W - 2 * s))
    down, up = (slice(2 * s, H), slice(s, W - s)), (slice(0, H - 2 * s), slice(s, W - s))
    n = np.cross(P[right] - P[left], P[down] - P[up])
    have = ok[right] & ok[left] & ok[down] & ok[up] & ok[inner]
    length = np.linalg.norm(n, axis=-1)
    have &= length > 0
    n = np.where(have[..., None], n / np.where(have, length, 1.0)[..., None], 0.0)
    if camera_centre is not None:
        towards = np.asarray(camera_centre, np.float64) - P[inner]
        n = np.where((np.sum(n * towards, axis=-1) < 0)[..., None], -n, n)
    normals[inner] = n
    return normals


def trim_points(points: np.ndarray, camera_centre: np.ndarray | None = None, k: float = 3.0,
                min_points: int = 8) -> np.ndarray:
    """Drop stray points of one view's object (depth-edge bleeding, points of the surface behind).

    Two robust cuts, each keeping what lies within ``k`` robust standard deviations (MAD x 1.4826)
    of the median: first the distance from ``camera_centre`` (bleeding points are strung along the
    viewing rays, so they stand out in range first), then the distance from the median point in 3D.
    A uniform spread (a long table seen end-on) keeps every point: its MAD is a quarter of its
    width, so ``k = 3`` reaches past its ends.

    Args:
        points: ``(M, 3)`` points of one view.
        camera_centre: ``(3,)`` the view's camera centre in the same frame, or ``None`` (skip the
            range cut).
        k: the cut in robust standard deviations.
        min_points: fewer points than this are returned unchanged.

    Returns:
        ``(M', 3)`` the kept points, in their order.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return points[trim_mask(points, camera_centre, k, min_points)]


def trim_mask(points: np.ndarray, camera_centre: np.ndarray | None = None, k: float = 3.0,
              min_points: int = 8) -> np.ndarray:
    """The ``(M,)`` bool of the points :func:`trim_points` keeps (to cut arrays beside them)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = np.ones(len(points), dtype=bool)
    if len(points) < min_points:
        return keep
    if camera_centre is not None:
        keep &= _within(np.linalg.norm(points - np.asarray(camera_centre, np.float64), axis=1), k)
    if keep.sum() >= min_points:
        rows = np.flatnonzero(keep)
        centre = np.median(points[rows], axis=0)
        keep[rows] = _within(np.linalg.norm(points[rows] - centre, axis=1), k)
    return keep


def _within(values: np.ndarray, k: float) -> np.ndarray:
    """``(M,)`` bool: ``values`` within ``k`` robust sigmas of their median (all when the MAD is 0)."""
    median = np.median(values)
    spread = MAD_TO_SIGMA * np.median(np.abs(values - median))
    if spread <= 0:
        return np.ones(values.shape, dtype=bool)
    return np.abs(values - median) <= k * spread


def ring_points(mask: np.ndarray, points_world: np.ndarray, valid: np.ndarray, width_px: int | None = None) -> np.ndarray:
    """The world points seen just outside a mask (what lies behind or beside the object's outline).

    Args:
        mask: ``(h, w)`` bool at any resolution (resized to the grid by :func:`resize_mask`).
        points_world: ``(H, W, 3)`` the keyframe's world points. valid: ``(H, W)`` bool.
        width_px: the ring's width in grid pixels (default 3 % of the grid's width, at least 2).

    Returns:
        ``(K, 3)`` float64 world points of valid pixels within ``width_px`` of the mask, outside it.
    """
    points_world = np.asarray(points_world)
    grid = resize_mask(mask, points_world.shape[:2])
    width_px = max(2, int(round(0.03 * grid.shape[1]))) if width_px is None else int(width_px)
    outside = ~grid
    ring = ~erode_mask(outside, width_px, border=True) & outside & np.asarray(valid, bool)
    points = points_world[ring].astype(np.float64)
    return points[np.isfinite(points).all(axis=1)]
