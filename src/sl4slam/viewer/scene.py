"""What the viewer draws, as plain arrays (no viser here, so it is testable on its own).

A map is a set of per-submap clouds. Each cloud keeps its points in a random (seeded) order, so
thinning it to any fraction is a truncation: a cloud is decimated once when it arrives, and when
the live map outgrows the point budget every cloud is halved by truncation, without re-reading the
keyframes. Positions go to the browser as float16 offsets from the cloud's centre (the centre is
the node's position), colours as uint8.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

COLOR_MODES = ("rgb", "submap", "confidence")


@dataclass
class ViewerSettings:
    """Viewer options (the command line's ``sl4slam view`` flags).

    Attributes:
        point_budget: most points sent to the browser in all (decision:
            docs/decisions/viewer-point-budget.md).
        point_size: initial point size in world units (viser's ``point_size``: half the side of
            the square drawn); 0 derives it from the map's own point spacing
            (:func:`auto_point_size`), so that neighbouring points overlap at any map scale.
        max_frustums: keyframe frustums drawn by default (evenly spread along the trajectory,
            :func:`frustum_indices`); the viewer's "All frustums" control draws one per keyframe.
            Each carries a thumbnail ``thumbnail_width`` px wide. 24: a map of hundreds of keyframes
            stays visible behind them.
        host: interface to bind; 127.0.0.1 keeps the map on this machine.
        port: first port to try; the next free one is taken when it is in use.
        seed: seed of the per-cloud point order (and of the sample that measures the spacing).
    """

    point_budget: int = 1_000_000
    point_size: float = 0.0
    max_frustums: int = 24
    thumbnail_width: int = 96
    host: str = "127.0.0.1"
    port: int = 8080
    seed: int = 0


@dataclass
class SubmapCloud:
    """One submap's displayed points.

    Attributes:
        submap_id: graph node.
        centre: ``(3,)`` float64 world position of the cloud's node.
        offsets: ``(N, 3)`` float32 world points minus ``centre``, in random (seeded) order.
        colors: ``(N, 3)`` uint8 RGB.
        confidence: ``(N,)`` float32 (1 everywhere when the run kept only a mask).
        full_count: confident points the submap had before decimation.
    """

    submap_id: int
    centre: np.ndarray
    offsets: np.ndarray
    colors: np.ndarray
    confidence: np.ndarray
    full_count: int

    def __len__(self) -> int:
        return len(self.offsets)

    def truncate(self, fraction: float) -> None:
        """Keep the first ``fraction`` of the points (a uniform subsample, the order being random)."""
        keep = int(np.ceil(self.full_count * min(1.0, fraction)))
        if keep < len(self):
            self.offsets, self.colors, self.confidence = self.offsets[:keep], self.colors[:keep], self.confidence[:keep]


def make_cloud(submap_id: int, points: np.ndarray, colors: np.ndarray, confidence: np.ndarray | None,
               fraction: float, seed: int = 0) -> SubmapCloud:
    """A submap's cloud from its confident points ``(N, 3)``, colours ``(N, 3)`` uint8 and optional
    confidence ``(N,)``, keeping ``fraction`` of them (random order seeded by ``seed`` and the id)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    count = len(points)
    order = np.random.default_rng([seed, submap_id]).permutation(count)
    keep = order[: int(np.ceil(count * min(1.0, fraction)))]
    centre = points[keep].mean(0) if len(keep) else np.zeros(3)
    conf = np.ones(count, np.float32) if confidence is None else np.asarray(confidence, np.float32).reshape(-1)
    return SubmapCloud(submap_id, centre, (points[keep] - centre).astype(np.float32),
                       np.asarray(colors, np.uint8).reshape(-1, 3)[keep], conf[keep], count)


def confidence_threshold(clouds, percentile: float) -> float:
    """The confidence below which points are hidden: the ``percentile`` of all displayed points'
    confidence (``-inf`` at 0, so that nothing is hidden)."""
    if percentile <= 0:
        return -np.inf
    values = [c.confidence for c in clouds if len(c)]
    if not values:
        return -np.inf
    return float(np.percentile(np.concatenate(values), min(100.0, percentile)))


def submap_color(submap_id: int) -> np.ndarray:
    """A distinct colour per submap ``(3,)`` uint8 (golden-ratio hue steps)."""
    import colorsys

    hue = (submap_id * 0.618033988749895) % 1.0
    return np.round(np.array(colorsys.hsv_to_rgb(hue, 0.75, 0.95)) * 255).astype(np.uint8)


def confidence_colors(confidence: np.ndarray, low: float, high: float) -> np.ndarray:
    """Viridis colours ``(N, 3)`` uint8 of confidence values scaled from ``[low, high]``."""
    from matplotlib import colormaps

    scaled = np.clip((confidence - low) / max(high - low, 1e-12), 0.0, 1.0)
    lut = np.round(colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    return lut[np.round(scaled * 255).astype(np.int64)]


def cloud_colors(cloud: SubmapCloud, mode: str, confidence_range: tuple[float, float]) -> np.ndarray:
    """Point colours of ``cloud`` in colouring ``mode`` (one of ``COLOR_MODES``)."""
    if mode == "submap":
        return np.broadcast_to(submap_color(cloud.submap_id), cloud.colors.shape).copy()
    if mode == "confidence":
        return confidence_colors(cloud.confidence, *confidence_range)
    return cloud.colors


def visible_part(cloud: SubmapCloud, threshold: float, mode: str,
                 confidence_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Float16 offsets ``(M, 3)`` and uint8 colours ``(M, 3)`` of the points at or above ``threshold``."""
    keep = cloud.confidence >= threshold if np.isfinite(threshold) else slice(None)
    return cloud.offsets[keep].astype(np.float16), cloud_colors(cloud, mode, confidence_range)[keep]


def thumbnail(rgb: np.ndarray, width: int) -> np.ndarray:
    """``(H, W, 3)`` uint8 image downscaled to ``width`` px wide (area averaging)."""
    import cv2

    H, W = rgb.shape[:2]
    if W <= width:
        return np.ascontiguousarray(rgb)
    return cv2.resize(rgb, (width, max(1, round(H * width / W))), interpolation=cv2.INTER_AREA)


def rotation_wxyz(T_world_cam: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` poses -> ``(N, 4)`` unit quaternions ``(w, x, y, z)`` of their rotations."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(np.asarray(T_world_cam)[..., :3, :3]).as_quat()
    return np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1)


def frustum_fov(K: np.ndarray, height: int) -> float:
    """Vertical field of view (radians) of intrinsics ``K`` on an image ``height`` px tall."""
    return float(2.0 * np.arctan2(height / 2.0, K[1, 1] / K[2, 2]))


def frustum_indices(positions: np.ndarray, limit: int) -> np.ndarray:
    """Which of the keyframes at ``positions (N, 3)`` (in trajectory order) get a frustum: all when
    ``N <= limit``, otherwise at most ``limit`` (the first and the last included) evenly spread
    along the trajectory.

    "Along the trajectory" is half keyframe order, half distance travelled: the keyframe nearest
    to each of ``limit`` evenly spaced values of ``0.5 * i / (N - 1) + 0.5 * s_i / s_total`` (``s_i``
    the path length up to keyframe ``i``), so a long straight walk and a turn on the spot (no
    distance, many keyframes) both keep frustums.
    """
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    count = len(positions)
    if count <= limit:
        return np.arange(count)
    if limit <= 0:
        return np.zeros(0, np.int64)
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    order = np.arange(count) / (count - 1)
    along = 0.5 * order + (0.5 * travelled / travelled[-1] if travelled[-1] > 0 else 0.5 * order)
    targets = np.linspace(0.0, 1.0, max(limit, 2))
    picked = np.clip(np.searchsorted(along, targets), 0, count - 1)
    # searchsorted gives the first keyframe at or past each target; take the nearer of it and the one before
    before = np.clip(picked - 1, 0, count - 1)
    picked = np.where(np.abs(along[before] - targets) < np.abs(along[picked] - targets), before, picked)
    return np.unique(picked)


def frustum_scale(map_radius: float, positions: np.ndarray) -> float:
    """Size of the drawn frustums (viser's ``scale``, about the frustum's depth) in world units: 2.5 % of
    the map's radius (:func:`map_sphere`), shrunk when the drawn cameras are closer together than
    that (to the median distance between consecutive ones, at least 1 % of the radius), so that
    many frustums do not cover each other and the map."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    scale = 0.025 * map_radius
    if len(positions) > 1:
        step = float(np.median(np.linalg.norm(np.diff(positions, axis=0), axis=1)))
        scale = min(scale, max(step, 0.01 * map_radius))
    return float(scale)


POINT_SIZE_PER_SPACING = 1.5
"""viser's point size per unit of the map's median nearest-neighbour spacing (see :func:`auto_point_size`)."""


def sample_points(clouds, count: int) -> np.ndarray:
    """About ``count`` of the clouds' points ``(M, 3)`` float64 in the world, a uniform sample of
    them all (each cloud's points are in random order, so its first ones are a uniform sample)."""
    clouds = [c for c in clouds if len(c)]
    total = sum(len(c) for c in clouds)
    if not total:
        return np.zeros((0, 3))
    share = min(1.0, count / total)
    return np.concatenate([c.offsets[: max(1, round(len(c) * share))].astype(np.float64) + c.centre
                           for c in clouds])


def median_spacing(points: np.ndarray, total: int | None = None, queries: int = 5000, seed: int = 0) -> float | None:
    """Median distance from a point of the map to its nearest neighbour, in world units.

    ``points (M, 3)``: the map's points, or a uniform sample of ``total`` of them. The median is
    taken over ``queries`` points drawn at random (robust to isolated outliers, which have far
    neighbours, and to duplicates, which are skipped). When ``points`` is a sample of a larger
    map, the spacing measured in the sample is scaled by ``sqrt(M / total)``: a dense map is made
    of surfaces, where the spacing of a uniform sample grows as the square root of the thinning
    (for a surface with some thickness the true factor is smaller, so the estimate errs towards
    larger points). ``None`` when fewer than two distinct points.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 2:
        return None
    rng = np.random.default_rng(seed)
    chosen = points[rng.choice(len(points), size=min(queries, len(points)), replace=False)]
    distances, _ = cKDTree(points).query(chosen, k=min(4, len(points)))
    nearest = np.where(distances[:, 1:] > 0, distances[:, 1:], np.inf).min(axis=1)  # skip the point itself and duplicates
    nearest = nearest[np.isfinite(nearest)]
    if not len(nearest):
        return None
    spacing = float(np.median(nearest))
    if total is not None and total > len(points):
        spacing *= float(np.sqrt(len(points) / total))
    return spacing


def map_spacing(clouds, sample: int = 250_000, seed: int = 0) -> float | None:
    """:func:`median_spacing` of the displayed map (all clouds), from a uniform sample of at most
    ``sample`` points (a k-d tree of 250k points takes a few hundredths of a second)."""
    clouds = [c for c in clouds if len(c)]
    total = sum(len(c) for c in clouds)
    return median_spacing(sample_points(clouds, sample), total=total, seed=seed) if total else None


def auto_point_size(spacing: float | None, fallback: float) -> float:
    """The default point size (viser's ``point_size``, world units) for a map whose points are
    ``spacing`` apart (:func:`median_spacing`); ``fallback`` when the map has no spacing.

    viser draws a point as a square of side ``2 * point_size`` world units (its vertex shader sets
    ``gl_PointSize = point_size * H / (tan(fov / 2) * z)`` px, while a length ``L`` at depth ``z``
    spans ``L * H / (2 tan(fov / 2) z)`` px). ``point_size = 1.5 * spacing``
    (:data:`POINT_SIZE_PER_SPACING`): a square of side ``3 d`` (``d`` the median spacing) reaches
    past the centres of its nearest neighbours, so neighbouring points overlap; on a surface
    sampled at random (a decimated map has density ``ln 2 / (pi d^2)`` for that median) such
    squares cover ``1 - exp(-9 ln 2 / pi) = 86 %`` of it seen face-on, more seen at an angle
    (decision: docs/decisions/viewer-point-budget.md).
    """
    if spacing is None or not np.isfinite(spacing) or spacing <= 0:
        return float(fallback)
    return float(POINT_SIZE_PER_SPACING * spacing)


def path_segments(positions: np.ndarray) -> np.ndarray:
    """``(N, 3)`` positions -> ``(N-1, 2, 3)`` consecutive segments."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    return np.stack([positions[:-1], positions[1:]], axis=1) if len(positions) > 1 else np.zeros((0, 2, 3))


def follow_view(T_world_cam: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A viewpoint behind and above a camera: ``(position, look_at, up)`` in the world."""
    R, C = T_world_cam[:3, :3], T_world_cam[:3, 3]
    forward, up = R[:, 2], -R[:, 1]  # OpenCV axes: z forward, y down
    return C - distance * forward + 0.5 * distance * up, C + distance * forward, up


def map_sphere(state: "MapState") -> tuple[np.ndarray, float]:
    """Where the map is and how big: the median of its points (the camera centres when it has none)
    and the 90th percentile of their distances to it (at least 1e-3)."""
    samples = [c.offsets[:2000].astype(np.float64) + c.centre for c in state.clouds.values() if len(c)]
    points = np.concatenate(samples) if samples else np.asarray(state.T_world_cam)[:, :3, 3].reshape(-1, 3)
    if not len(points):
        return np.zeros(3), 1.0
    centre = np.median(points, axis=0)
    return centre, max(float(np.percentile(np.linalg.norm(points - centre, axis=1), 90)), 1e-3)


def overview(state: "MapState") -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A viewpoint that frames the map: ``(position, look_at, up)``, looking along the first
    keyframe's viewing direction from 1.6 map radii away, raised a little; ``None`` when empty."""
    if not len(state.T_world_cam):
        return None
    centre, radius = map_sphere(state)
    first = state.T_world_cam[0]
    forward, up = first[:3, 2], -first[:3, 1]
    return centre - 1.6 * radius * forward + 0.5 * radius * up, centre, up


def scene_extent(positions: np.ndarray) -> float:
    """Size of the trajectory (diagonal of its bounding box), at least 1e-3."""
    positions = np.asarray(positions).reshape(-1, 3)
    if len(positions) < 2:
        return 1.0
    return max(float(np.linalg.norm(positions.max(0) - positions.min(0))), 1e-3)


def gt_in_estimate_frame(timestamps: np.ndarray, T_world_cam: np.ndarray, gt_timestamps: np.ndarray,
                         T_gt: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Ground-truth positions ``(M, 3)`` mapped into the estimate's world by the inverse of the
    Sim(3) alignment of ``sl4slam.metrics.ate``, and the ATE RMSE; ``None`` when it cannot align."""
    from ..errors import UserError
    from ..metrics import ate

    if len(timestamps) < 3:
        return None
    try:
        result = ate(timestamps, T_world_cam, gt_timestamps, T_gt)
    except UserError:
        return None
    T_est_gt = np.linalg.inv(result.T_gt_est)
    return result.positions_gt @ T_est_gt[:3, :3].T + T_est_gt[:3, 3], result.rmse


@dataclass
class MapTotals:
    """The whole map's numbers in the control panel.

    Attributes:
        shown: points sent to the browser.
        full: confident points before decimation.
        confidence: whether the points carry a per-pixel confidence (the confidence slider works).
    """

    shown: int
    full: int
    confidence: bool


@dataclass
class MapState:
    """Everything drawn, as arrays; the viewer server mirrors it into the browser.

    ``totals``: the whole map's numbers while its clouds are still being read (the panel shows them
    before the first cloud); ``None`` counts them from the clouds (:meth:`counted_totals`).
    """

    clouds: dict[int, SubmapCloud] = field(default_factory=dict)
    fraction: float = 1.0
    frame_indices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    submap_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    T_world_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    K: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    image_sizes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    thumbnails: dict[int, np.ndarray] = field(default_factory=dict)
    loop_segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    gt_positions: np.ndarray | None = None
    summary_markdown: str = ""
    totals: MapTotals | None = None

    def total_points(self) -> int:
        return int(sum(len(c) for c in self.clouds.values()))

    def counted_totals(self) -> MapTotals:
        """The panel's numbers counted from the clouds in the state."""
        return MapTotals(self.total_points(), int(sum(c.full_count for c in self.clouds.values())),
                         self.has_confidence())

    def confidence_range(self) -> tuple[float, float]:
        values = [c.confidence for c in self.clouds.values() if len(c)]
        if not values:
            return 0.0, 1.0
        allv = np.concatenate(values)
        return float(allv.min()), float(allv.max())

    def has_confidence(self) -> bool:
        low, high = self.confidence_range()
        return high > low

