"""Views of one object into one 3D instance: association, merging, an oriented box, box overlap.

Everything here is in one frame (the map's world frame and units unless said otherwise). An
oriented box is ``(centre (3,), axes (3, 3), extents (3,))``: ``axes`` rows are unit vectors (a
right-handed orthonormal frame), ``extents`` the full side lengths along them, so its corners are
``centre + sum_i (+-extents[i] / 2) axes[i]``. Why these rules: docs/decisions/object-fusion.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

BOX_PERCENTILES = (2.0, 98.0)
"""The box spans these percentiles of the points along each of its axes (stray points cannot
stretch it)."""
TOUCH_RADIUS = 0.05
"""Two point sets touch where a point of one lies within this fraction of their joint diameter
of a point of the other (:func:`overlap`)."""
SAME_OBJECT_OVERLAP = 0.25
"""Views whose overlap (:func:`overlap`) is at least this are one instance."""
SAME_OBJECT_CENTRES = 0.5
"""...or whose centroids are closer than this fraction of the larger one's robust radius."""
ANGLE_STEPS = 18
"""Rotations tried about each principal axis (over 90 degrees) in the minimum-volume box search."""


@dataclass
class ViewDetection:
    """One instance found in one keyframe, lifted to 3D.

    Attributes:
        frame_index: the keyframe's source frame.
        points: ``(M, 3)`` float64 its trimmed world points.
        score: the segmenter's score of the mask.
        similarity: the keyframe's cosine similarity with the query text.
        pixels: mask pixels on the keyframe's grid.
        normals: ``(M, 3)`` unit surface normals of the points (zero where unknown), or ``None``.
        background: ``(K, 3)`` world points seen just outside the mask (:func:`extend_to_background`),
            or ``None``.
        camera_centre: ``(3,)`` the keyframe's camera centre, or ``None``.
        mask: ``(H, W)`` bool the mask on the keyframe's grid (for display), or ``None``.
    """

    frame_index: int
    points: np.ndarray
    score: float
    similarity: float = 0.0
    pixels: int = 0
    normals: np.ndarray | None = None
    background: np.ndarray | None = None
    camera_centre: np.ndarray | None = None
    mask: np.ndarray | None = None


@dataclass
class ObjectInstance:
    """An object found in 3D.

    Attributes:
        centre: ``(3,)`` box centre. axes: ``(3, 3)`` box axes as rows (unit vectors).
        extents: ``(3,)`` box side lengths along ``axes`` (map units).
        points: ``(P, 3)`` float32, a deterministic subsample of the merged points.
        views: the detections merged into it, best first.
        score: :func:`instance_score`.
    """

    centre: np.ndarray
    axes: np.ndarray
    extents: np.ndarray
    points: np.ndarray
    views: list[ViewDetection] = field(default_factory=list)
    score: float = 0.0

    @property
    def best_view(self) -> int:
        """The frame of the view with the highest mask score (most points on ties)."""
        return max(self.views, key=lambda v: (v.score, len(v.points))).frame_index

    @property
    def frames(self) -> list[int]:
        return [v.frame_index for v in self.views]

    def corners(self) -> np.ndarray:
        """``(8, 3)`` the box corners (:func:`box_corners`)."""
        return box_corners(self.centre, self.axes, self.extents)


def robust_radius(points: np.ndarray) -> float:
    """Median distance of ``(M, 3)`` points from their median point (0 for no points)."""
    if len(points) == 0:
        return 0.0
    return float(np.median(np.linalg.norm(points - np.median(points, axis=0), axis=1)))


def overlap(a: np.ndarray, b: np.ndarray) -> float:
    """How much two point sets cover the same surface: the fraction of the smaller set's points
    within ``TOUCH_RADIUS`` of their joint diameter (the diagonal of the box spanning both) of a
    point of the larger one. 1 for the same surface seen twice, near 0 for separate objects.

    Args:
        a, b: ``(M, 3)`` and ``(N, 3)`` points.

    Returns:
        a number in [0, 1] (0 when either is empty).
    """
    if len(a) == 0 or len(b) == 0:
        return 0.0
    small, large = (a, b) if len(a) <= len(b) else (b, a)
    both = np.concatenate([a, b])
    diameter = float(np.linalg.norm(both.max(0) - both.min(0)))
    if diameter <= 0:
        return 1.0
    distances, _ = cKDTree(large).query(small, k=1)
    return float(np.mean(distances <= TOUCH_RADIUS * diameter))


def same_object(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two point sets are views of one object: they overlap (``SAME_OBJECT_OVERLAP``) or
    their medians lie within ``SAME_OBJECT_CENTRES`` of the larger robust radius (two views of
    different faces of one object share no surface but one centre)."""
    if len(a) == 0 or len(b) == 0:
        return False
    if overlap(a, b) >= SAME_OBJECT_OVERLAP:
        return True
    gap = float(np.linalg.norm(np.median(a, axis=0) - np.median(b, axis=0)))
    return gap <= SAME_OBJECT_CENTRES * max(robust_radius(a), robust_radius(b))


def subsample(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """At most ``count`` rows of ``(M, 3)`` points, drawn without replacement with ``seed`` (kept
    in their order)."""
    return points[_subsample_index(len(points), count, seed)]


def _subsample_index(total: int, count: int, seed: int) -> np.ndarray:
    """Sorted indices of at most ``count`` of ``total`` rows (all when ``total <= count``), seeded."""
    if total <= count:
        return np.arange(total)
    return np.sort(np.random.default_rng(seed).choice(total, size=count, replace=False))


def normal_frame(normals: np.ndarray, min_normals: int = 20, seed: int = 0) -> tuple[np.ndarray, int] | None:
    """The orientation that a box-like object's faces give, from its surface normals.

    The first axis is the densest direction of the normals (the candidate among a seeded sample of
    them with the largest sum of ``max(0, n . d)^8``, then the mean of the normals within 25 degrees
    of it): the normal of the face seen most. The second is found the same way among the normals
    roughly perpendicular to the first (``|n . d1| < 0.3``), projected onto its plane, when they are
    at least ``FACE_SHARE`` of all: a second face. The third completes a right-handed frame. Faces
    of any areas give their own normals (a scatter matrix of the normals would not: two faces of
    equal area make it isotropic in their plane).

    Args:
        normals: ``(M, 3)`` unit normals (zero rows are ignored).
        min_normals: fewer non-zero normals give ``None``.
        seed: seed of the candidate sample.

    Returns:
        ``(frame (3, 3) rows, faces)``: the axes and how many of them the normals pin down (1: a
        single face seen, the rotation about its normal is free; 2: the frame is fixed), or ``None``.
    """
    normals = np.asarray(normals, np.float64).reshape(-1, 3)
    normals = normals[np.linalg.norm(normals, axis=1) > 0.5]
    if len(normals) < min_normals:
        return None
    rng = np.random.default_rng(seed)
    first = _densest_direction(normals, rng)
    across = normals[np.abs(normals @ first) < 0.3]
    if len(across) < max(min_normals, FACE_SHARE * len(normals)):
        helper = np.eye(3)[int(np.argmin(np.abs(first)))]
        second = np.cross(first, helper)
        second /= np.linalg.norm(second)
        return np.stack([first, second, np.cross(first, second)]), 1
    across = across - np.outer(across @ first, first)
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    second = _densest_direction(across, rng)
    second -= (second @ first) * first
    second /= np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)]), 2


def _densest_direction(directions: np.ndarray, rng: np.random.Generator, candidates: int = 256) -> np.ndarray:
    """The unit direction where ``(M, 3)`` unit vectors crowd most (see :func:`normal_frame`)."""
    sample = directions[rng.choice(len(directions), size=min(candidates, len(directions)), replace=False)]
    score = (np.clip(directions @ sample.T, 0.0, None) ** 8).sum(axis=0)
    best = sample[int(np.argmax(score))]
    near = directions[directions @ best > np.cos(np.deg2rad(25.0))]
    mean = near.sum(axis=0) if len(near) else best
    return mean / np.linalg.norm(mean)


FACE_SHARE = 0.1
"""A second face counts as seen when its share of the normal scatter is at least this fraction of
the first's (:func:`normal_frame`)."""


def fit_box(points: np.ndarray, percentiles: tuple[float, float] = BOX_PERCENTILES,
            angle_steps: int = ANGLE_STEPS, normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Oriented box of a point set, without assuming where "up" is.

    With surface ``normals`` of a box-like object (two faces or more seen, :func:`normal_frame`),
    the box is aligned with its faces. Otherwise the search starts from the principal axes (or,
    with one face seen, its normal): each axis (only the face's normal, when there is one) is held
    while the other two turn through 90 degrees in ``angle_steps`` steps, and the orientation whose
    percentile box has the least volume (sides floored at 1 % of the largest, so that a flat set
    still compares) wins. The box spans ``percentiles`` of the points along each axis.

    Args:
        points: ``(M, 3)`` points, ``M >= 1``.
        percentiles: the low and high percentile spanned along each axis.
        angle_steps: rotations tried per axis (0: the starting axes alone).
        normals: ``(M, 3)`` unit normals of the points (zero rows: unknown), or ``None``.

    Returns:
        centre ``(3,)``, axes ``(3, 3)`` (rows, right-handed), extents ``(3,)`` sorted largest first.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        raise ValueError("fit_box needs at least one point")
    mean = points.mean(axis=0)
    centred = points - mean
    from_normals = normal_frame(normals) if normals is not None else None
    if from_normals is not None:
        base, faces = from_normals
        turn_axes = [] if faces >= 2 else [0]
    elif len(points) >= 3:
        _, _, Vt = np.linalg.svd(centred, full_matrices=False)
        base = Vt if Vt.shape[0] == 3 else np.eye(3)
        turn_axes = [0, 1, 2]
    else:
        base, turn_axes = np.eye(3), [0, 1, 2]
    candidates = [base]
    for axis in turn_axes:
        for angle in np.arange(1, max(angle_steps, 1)) * (0.5 * np.pi / max(angle_steps, 1)):
            candidates.append(_turn(base, axis, angle))
    frames = np.stack(candidates)  # (C, 3, 3)
    coords = np.einsum("pj,cij->cpi", centred, frames)  # (C, M, 3)
    low, high = np.percentile(coords, percentiles, axis=1)  # (C, 3) each
    sides = high - low
    floored = np.maximum(sides, 0.01 * sides.max(axis=1, keepdims=True) + 1e-12)
    best = int(np.argmin(floored.prod(axis=1)))
    axes, lo, hi = frames[best], low[best], high[best]
    order = np.argsort(-(hi - lo), kind="stable")
    axes, lo, hi = axes[order], lo[order], hi[order]
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
        lo[2], hi[2] = -hi[2], -lo[2]
    centre = mean + ((lo + hi) / 2.0) @ axes
    return centre, axes, hi - lo


def _turn(frame: np.ndarray, axis: int, angle: float) -> np.ndarray:
    """``frame`` (rows) with the two rows other than ``axis`` rotated by ``angle`` about it."""
    i, j = [a for a in range(3) if a != axis]
    out = frame.copy()
    c, s = np.cos(angle), np.sin(angle)
    out[i] = c * frame[i] + s * frame[j]
    out[j] = -s * frame[i] + c * frame[j]
    return out


def instance_score(views: list[ViewDetection], keyframes_searched: int) -> float:
    """An instance's score: the sum of its views' mask scores over the keyframes searched, so an
    object found with confidence 1 in every keyframe searched scores 1, one found once 1/k."""
    return float(sum(v.score for v in views) / max(1, keyframes_searched))


def fuse_views(detections: list[ViewDetection], keyframes_searched: int | None = None, max_points: int = 4000,
               seed: int = 0, refine: bool = True, amodal: bool = True) -> list[ObjectInstance]:
    """Group detections of several keyframes into instances and fit each a box.

    Detections are taken best first (mask score times keyframe similarity); each joins the first
    instance it is the same object as (:func:`same_object` against the instance's points so far,
    after the offset refinement), else starts a new one. Two detections of one keyframe never join one instance (a segmenter's
    two masks in one image are two objects).

    Args:
        detections: the lifted masks (empty point sets are skipped).
        keyframes_searched: the number of keyframes segmented (the denominator of the score;
            default: the number of distinct frames among ``detections``).
        max_points: points kept per instance (a seeded subsample).
        seed: the subsample's seed.
        refine: move each joining view by the translation that lays its points onto the instance's
            (:func:`refine_offset`; the map's registration error between keyframes).
        amodal: extend each box behind its seen surfaces (:func:`extend_to_background`).

    Returns:
        The instances, highest score first (ties: more views, then the earlier best frame).
    """
    usable = [d for d in detections if len(d.points) > 0]
    if keyframes_searched is None:
        keyframes_searched = len({d.frame_index for d in usable})
    usable.sort(key=lambda d: (-d.score * max(d.similarity, 1e-6), -len(d.points), d.frame_index))
    groups: list[list[ViewDetection]] = []
    merged: list[np.ndarray] = []
    merged_normals: list[np.ndarray] = []
    for detection in usable:
        for g, group in enumerate(groups):
            if detection.frame_index in {v.frame_index for v in group}:
                continue
            chosen = _subsample_index(len(merged[g]), max_points, seed)
            reference, candidate = merged[g][chosen], subsample(detection.points, max_points, seed)
            shift = refine_offset(candidate, reference, merged_normals[g][chosen]) if refine else np.zeros(3)
            if same_object(reference, candidate + shift):
                detection = _shifted(detection, shift)
                group.append(detection)
                merged[g] = np.concatenate([merged[g], detection.points])
                merged_normals[g] = np.concatenate([merged_normals[g], _normals_of(detection)])
                break
        else:
            groups.append([detection])
            merged.append(detection.points)
            merged_normals.append(_normals_of(detection))
    instances = []
    for g, (group, points) in enumerate(zip(groups, merged)):
        chosen = _subsample_index(len(points), 4 * max_points, seed + g)
        centre, axes, extents = fit_box(points[chosen], normals=merged_normals[g][chosen])
        if amodal:
            centre, axes, extents = extend_to_background(centre, axes, extents, group)
        group.sort(key=lambda v: (-v.score, -len(v.points), v.frame_index))
        instances.append(ObjectInstance(centre=centre, axes=axes, extents=extents,
                                        points=subsample(points, max_points, seed + g).astype(np.float32),
                                        views=group, score=instance_score(group, keyframes_searched)))
    instances.sort(key=lambda inst: (-inst.score, -len(inst.views), inst.best_view))
    return instances


REFINE_ITERATIONS = 30
"""Iterations of :func:`refine_offset`."""
REFINE_KEEP = 0.7
"""The share of closest pairs each iteration of :func:`refine_offset` uses."""
REFINE_REACH = 0.25
"""Pairs closer than this fraction of the instance's robust radius always count in
:func:`refine_offset` (trimming by rank alone would drop the face whose offset is largest)."""
REFINE_GAIN = 0.7
""":func:`refine_offset` keeps its translation only when it brings the mean distance of the closest
pairs below this fraction of what it was."""
REFINE_MAX = 0.5
"""...and when the translation is shorter than this fraction of the instance's robust radius."""


def refine_offset(points: np.ndarray, reference: np.ndarray, reference_normals: np.ndarray | None = None,
                  iterations: int = REFINE_ITERATIONS, keep: float = REFINE_KEEP) -> np.ndarray:
    """The translation that lays a view's points onto an instance's: trimmed ICP, translation only,
    point-to-plane where the reference points have normals (a surface sliding along itself costs
    nothing, so faces pin the offset down only across themselves), point-to-point otherwise.

    A keyframe's points carry the map's registration error at that keyframe (a few percent of the
    scene), which shows as an offset between two views of one object; rotations between nearby
    keyframes are far smaller at an object's scale, so only the offset is estimated.

    Args:
        points: ``(M, 3)`` the view's points. reference: ``(N, 3)`` the instance's.
        reference_normals: ``(N, 3)`` unit normals of ``reference`` (zero rows: unknown), or ``None``.
        iterations: ICP iterations. keep: share of closest pairs used (and every pair closer than
            ``REFINE_REACH`` of the instance's robust radius).

    Returns:
        ``(3,)`` the translation to add to ``points``: zero when either is empty, or when the
        translation does not fit clearly better (``REFINE_GAIN``) or is long (``REFINE_MAX``).
    """
    shift = np.zeros(3)
    if len(points) == 0 or len(reference) == 0:
        return shift
    tree = cKDTree(reference)
    normals = None
    if reference_normals is not None:
        normals = np.asarray(reference_normals, np.float64)
        if (np.linalg.norm(normals, axis=1) > 0.5).mean() < 0.5:
            normals = None

    def misfit(offset: np.ndarray) -> float:
        distances, index = tree.query(points + offset, k=1)
        if normals is not None:
            distances = np.abs(np.sum((points + offset - reference[index]) * normals[index], axis=1))
        return float(np.mean(np.sort(distances)[: max(1, int(keep * len(distances)))]))

    reach = REFINE_REACH * robust_radius(reference)
    for _ in range(iterations):
        distances, index = tree.query(points + shift, k=1)
        closest = distances <= max(np.quantile(distances, keep), reach)
        gap = reference[index[closest]] - (points + shift)[closest]
        if normals is not None:
            n = normals[index[closest]]
            system = n.T @ n + 1e-6 * len(n) * np.eye(3)  # a small pull to zero where no face pins it
            step = np.linalg.solve(system, n.T @ np.sum(gap * n, axis=1))
        else:
            step = gap.mean(axis=0)
        shift += step
        if np.linalg.norm(step) < 1e-6 * (1.0 + np.linalg.norm(shift)):
            break
    # kept only when it fits clearly better and stays small against the object
    if misfit(shift) > REFINE_GAIN * misfit(np.zeros(3)) or np.linalg.norm(shift) > REFINE_MAX * robust_radius(reference):
        return np.zeros(3)
    return shift


def _normals_of(detection: ViewDetection) -> np.ndarray:
    """A detection's normals, zeros when it has none."""
    return detection.normals if detection.normals is not None else np.zeros_like(detection.points)


def _shifted(detection: ViewDetection, shift: np.ndarray) -> ViewDetection:
    """A copy of a detection with its points (and background points) moved by ``shift``."""
    from dataclasses import replace

    background = detection.background + shift if detection.background is not None else None
    return replace(detection, points=detection.points + shift, background=background)


AMODAL_PERCENTILE = 50.0
"""Which percentile of the background points behind an object its hidden back is extended to."""


def extend_to_background(centre: np.ndarray, axes: np.ndarray, extents: np.ndarray, views: list[ViewDetection],
                         min_points: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extend a box behind what its views saw: a camera sees an object's front, never its back.

    Along the box axis closest to the mean viewing direction (from the views' cameras to the box),
    the back face moves away from the cameras to the background seen around the object's outline
    (``AMODAL_PERCENTILE`` of the views' ``background`` points beyond the back face along that
    axis), at most until that side is as long as the box's longest one. A back already at the
    background (a side face seen) stays; without background points behind, nothing changes.

    Args:
        centre, axes, extents: the box. views: its detections (``background`` and ``camera_centre``
            used when present).
        min_points: fewer background points behind the back face leave the box as it is.

    Returns:
        The box ``(centre, axes, extents)``.
    """
    cameras = [v.camera_centre for v in views if v.camera_centre is not None]
    backgrounds = [v.background for v in views if v.background is not None and len(v.background)]
    if not cameras or not backgrounds:
        return centre, axes, extents
    centre, axes, extents = (np.asarray(x, np.float64).copy() for x in (centre, axes, extents))
    viewing = centre - np.mean(cameras, axis=0)
    if np.linalg.norm(viewing) <= 0:
        return centre, axes, extents
    alignment = axes @ (viewing / np.linalg.norm(viewing))
    a = int(np.argmax(np.abs(alignment)))
    direction = axes[a] * np.sign(alignment[a])
    back = float(centre @ direction) + extents[a] / 2.0
    front = back - extents[a]
    behind = np.concatenate(backgrounds) @ direction
    behind = behind[behind > back]
    if len(behind) < min_points:
        return centre, axes, extents
    new_back = min(float(np.percentile(behind, AMODAL_PERCENTILE)), front + float(extents.max()))
    if new_back <= back:
        return centre, axes, extents
    grow = new_back - back
    extents[a] += grow
    centre += 0.5 * grow * direction
    return centre, axes, extents


# ------------------------------------------------------------------------------------ box overlap
BOX_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1])
"""The 12 edges of a box as corner pairs (corners indexed by their sign bits, see :func:`box_corners`)."""


def box_corners(centre: np.ndarray, axes: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """``(8, 3)`` corners of an oriented box; corner ``c`` takes ``+extents[i] / 2`` along axis ``i``
    where bit ``i`` of ``c`` is set, ``-extents[i] / 2`` otherwise."""
    signs = np.array([[(c >> i) & 1 for i in range(3)] for c in range(8)], dtype=np.float64) * 2.0 - 1.0
    half = 0.5 * np.asarray(extents, np.float64)
    return np.asarray(centre, np.float64) + (signs * half) @ np.asarray(axes, np.float64)


def box_volume(extents: np.ndarray) -> float:
    return float(np.prod(np.asarray(extents, np.float64)))


def _inside(points: np.ndarray, centre: np.ndarray, axes: np.ndarray, extents: np.ndarray, tol: float) -> np.ndarray:
    local = (points - centre) @ np.asarray(axes, np.float64).T
    return np.all(np.abs(local) <= 0.5 * np.asarray(extents, np.float64) + tol, axis=1)


def _edge_face_hits(corners: np.ndarray, centre: np.ndarray, axes: np.ndarray, extents: np.ndarray, tol: float) -> np.ndarray:
    """Points where the edges of a box (``corners``) cross the faces of another, inside that box."""
    a, b = corners[BOX_EDGES[:, 0]], corners[BOX_EDGES[:, 1]]  # (12, 3)
    la, lb = (a - centre) @ axes.T, (b - centre) @ axes.T  # local coordinates (12, 3)
    hits = []
    for axis in range(3):
        for side in (-0.5, 0.5):
            plane = side * extents[axis]
            da, db = la[:, axis] - plane, lb[:, axis] - plane
            crossing = (da * db < 0)
            t = da[crossing] / (da[crossing] - db[crossing])
            hits.append(a[crossing] + t[:, None] * (b[crossing] - a[crossing]))
    points = np.concatenate(hits) if hits else np.zeros((0, 3))
    return points[_inside(points, centre, axes, extents, tol)]


def box_intersection_volume(box_a: tuple, box_b: tuple) -> float:
    """Exact volume of the intersection of two oriented boxes ``(centre, axes, extents)``.

    The intersection of two convex polytopes is the convex hull of the corners of each inside the
    other and the points where the edges of each cross the faces of the other; its volume is that
    hull's (scipy ``ConvexHull``, Qhull). Degenerate (flat or empty) intersections give 0.
    """
    ca, aa, ea = (np.asarray(x, np.float64) for x in box_a)
    cb, ab, eb = (np.asarray(x, np.float64) for x in box_b)
    scale = max(float(ea.max()), float(eb.max()), 1e-12)
    tol = 1e-9 * scale
    corners_a, corners_b = box_corners(ca, aa, ea), box_corners(cb, ab, eb)
    vertices = np.concatenate([corners_a[_inside(corners_a, cb, ab, eb, tol)],
                               corners_b[_inside(corners_b, ca, aa, ea, tol)],
                               _edge_face_hits(corners_a, cb, ab, eb, tol),
                               _edge_face_hits(corners_b, ca, aa, ea, tol)])
    if len(vertices) < 4:
        return 0.0
    try:
        return float(ConvexHull(vertices).volume)
    except (QhullError, ValueError):
        return 0.0


def box_iou(box_a: tuple, box_b: tuple) -> float:
    """Intersection over union of two oriented boxes ``(centre, axes, extents)`` (exact, through
    :func:`box_intersection_volume`)."""
    inter = box_intersection_volume(box_a, box_b)
    union = box_volume(box_a[2]) + box_volume(box_b[2]) - inter
    return float(inter / union) if union > 0 else 0.0
