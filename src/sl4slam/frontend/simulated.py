"""Simulated frontend: VGGT-like submaps made from ground truth, corrupted in a controlled way.

Given RGB-D frames with ground-truth poses and intrinsics (the synthetic world, TUM RGB-D,
7-Scenes), :class:`SimulatedFrontend` returns for any list of frames what VGGT returns — depth
``(S, H, W)``, confidence ``(S, H, W)`` >= 1, camera-from-submap extrinsics ``(S, 3, 4)`` with the
submap frame being the first frame's camera, intrinsics ``(S, 3, 3)`` and colours — on the frames'
own pixel grid. Because the truth is known exactly, every later stage (alignment, loop closure,
the SL(4) and Sim(3) graphs) can be measured against it.

Corruption model (settings of :class:`~sl4slam.config.SimulatorConfig`, command line
``--sim-<setting>``, config file section ``[sim]``; defaults in brackets):

1. **True submap.** ``X`` are the true points of every frame's depth in the first camera's frame
   (metres), ``T_cam_i_cam_0`` the true relative poses, ``K_i`` each frame's intrinsics.
   Pixels without a depth measurement (0 in TUM / 7-Scenes) are filled with the depth of the
   nearest measured pixel, since VGGT predicts everywhere; they get confidence exactly 1.

2. **Scale normalization** (``normalize_scale`` [on]). ``kappa = 1 / mean ||X||`` over the
   measured pixels of all frames of the submap, so a normalized submap has mean point distance 1,
   as VGGT's outputs do. ``N = diag(kappa, kappa, kappa, 1)``.

3. **Projective distortion** ``H_s`` in SL(4), drawn per submap from ``(seed, submap_id)``. In
   normalized coordinates ``G_s = [[g B, 0], [p^T, 1]]`` with

   - ``p = perspective * u``, ``u`` a uniformly random unit vector (``perspective`` [0]): the
     perspective row that Sim(3) cannot model. A point at the mean distance 1 has its
     homogeneous weight ``1 + p . X`` moved by at most ``perspective``;
   - ``B`` upper triangular with det 1 (``shear`` [0]): ``B_ij ~ N(0, shear^2)`` for ``i < j``,
     ``B_ii = exp(shear * (a_i - mean(a)))`` with ``a ~ N(0, I)``: shear and anisotropic stretch;
   - ``g = exp(scale * c)``, ``c ~ N(0, 1)`` (``scale`` [0]): the global scale.

   ``H_s = G_s N`` when normalizing, else ``N^-1 G_s N`` (metric units, same distortion), and is
   then normalized to det 1. With ``distort_first_submap`` [on] switched off, submap 0 gets
   ``G_s = I`` (only the normalization): the world frame is submap 0's frame, so its distortion
   would be inherited by any backend alike, and switching it off isolates the alignment error.
   This block form is the most general distortion that keeps the first
   camera at ``[I | 0]`` (as VGGT's first extrinsic is by construction): ``[I | 0] H_s^-1 =
   [A | 0]`` with ``A`` upper triangular, which the first camera's intrinsics absorb.
   The distorted camera of frame ``i`` is ``P_i H_s^-1`` with ``P_i = K_i [T_cam_i_cam_0]``;
   :func:`~sl4slam.geometry.decompose_projection` splits it into intrinsics ``K'_i`` (with skew
   when the distortion needs it) and a pose ``T'_cam_i_submap``, and the returned depth is the
   z coordinate of ``H_s X`` in that camera. Without noise, unprojecting the returned depth with
   the returned cameras gives exactly ``H_s X`` (up to float32 rounding). If some point would
   cross the plane at infinity or fall behind a distorted camera the distortion is too strong
   for the scene and a ``UserError`` asks for a smaller ``--sim-perspective``.

4. **Depth noise** (``depth_noise`` [0.002]): every pixel's depth is multiplied by
   ``exp(depth_noise * n)``, ``n ~ N(0, 1)`` i.i.d., so the error is proportional to depth.

5. **Outlier blobs** (``outlier_fraction`` [0.02], ``outlier_blob_px`` [12],
   ``outlier_magnitude`` [0.3]): the model's errors are locally consistent, not salt-and-pepper.
   A smooth random field (white noise on a grid of cells of ``1.25 * outlier_blob_px`` px,
   Gaussian-smoothed over one cell, bicubically upsampled) is thresholded at its
   ``1 - outlier_fraction`` quantile, so that fraction of each frame's pixels lies in blobs whose
   mean equivalent radius is about ``outlier_blob_px`` (0.8x at 2 %, 1.3x at 10 %). Inside the
   blobs the depth is multiplied by ``(1 + outlier_magnitude)^s`` where ``s = tanh(2 m)`` and
   ``m`` is a second, independent unit-variance smooth field: a relative error of about
   ``outlier_magnitude`` in either direction that varies slowly across a blob.

6. **Confidence** (``confidence_scale`` [5], ``confidence_jitter`` [0.2],
   ``outlier_confidence`` [0.02]): ``1 + confidence_scale * (z_med / z) * exp(confidence_jitter
   * e)`` for clean pixels, with ``z`` the distorted noise-free depth, ``z_med`` its median over
   the submap's measured pixels and ``e ~ N(0, 1)``: high where the depth is close (its absolute
   error is small), falling with depth. Inside outlier blobs the excess over 1 is multiplied by
   ``outlier_confidence``; filled pixels (no measurement) get exactly 1. So the pipeline's
   percentile confidence mask (``--tau-conf``, 25 %) removes the blobs, except where at least that
   fraction of the submap's pixels had no depth measurement (the filled pixels then fill the
   dropped percentile by themselves).

7. **Randomness** (``seed`` [0]): ``H_s`` comes from ``(seed, submap_id)``; noise, blobs and
   confidence of frame ``f`` in submap ``j`` come from ``(seed, j, f.index)``, each from its own
   stream. The same frame in two submaps therefore gets independent noise, and every value is
   repeatable whatever the other frames of the submap are (except ``kappa`` and ``z_med``, which
   are submap-wide by definition).

The distortion used for each submap is kept in :attr:`SimulatedFrontend.distortions`
(``H_submap_true``, mapping true first-camera points to the predicted submap frame) so that tests
and benchmarks can compare an estimate against it; :meth:`SimulatedFrontend.distortion` computes
it without reconstructing.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
from scipy import ndimage

from ..config import SimulatorConfig
from ..errors import UserError
from ..geometry import apply_transform, decompose_projection, normalize_sl4, se3_inverse, unproject_depth
from ..types import Frame, SubmapPrediction
from .overlap import overlap_match_ratio

# Stream tags for SeedSequence spawn keys: the distortion and the per-frame draws (noise, blobs,
# confidence; each spawned into its own stream) never share random numbers.
_DISTORTION_STREAM = 0
_FRAME_STREAM = 1

# Cell size of the blob field relative to outlier_blob_px (calibrated so the blobs' mean
# equivalent radius is about outlier_blob_px at the default fraction and above).
_BLOB_CELL_PER_PX = 1.25


class SimulatedFrontend:
    """A :class:`~sl4slam.types.Frontend` that corrupts ground truth (see the module docstring).

    Args:
        config: the corruption settings.

    Attributes:
        distortions: ``{submap_id: (4, 4) H_submap_true}`` for every reconstructed submap.
        last_distortion: ``H_submap_true`` of the latest reconstructed submap (``None`` before).
    """

    name = "simulated"
    requires_ground_truth = True  # frames without depth, pose or K are skipped by the pipeline

    def __init__(self, config: SimulatorConfig | None = None):
        self.config = config if config is not None else SimulatorConfig()
        _validate(self.config)
        self.distortions: dict[int, np.ndarray] = {}
        self.last_distortion: np.ndarray | None = None

    # ------------------------------------------------------------------ public API

    def reconstruct(self, frames: Sequence[Frame], submap_id: int,
                    match_pairs: Sequence[tuple[int, int]] = ()) -> SubmapPrediction:
        """Corrupted VGGT-like prediction of ``frames`` (the first defines the submap frame).

        Returns a :class:`SubmapPrediction` on the frames' pixel grid: depth and confidence
        ``(S, H, W)`` float32, ``T_cam_submap`` ``(S, 3, 4)`` and ``K`` ``(S, 3, 3)`` float64,
        colours = the frames' RGB. ``points`` is left ``None`` (the pipeline unprojects depth).
        ``match_pairs`` (slot pairs) get the true-overlap stand-in for VGGT's image-match ratio
        (``sl4slam.frontend.overlap``).
        """
        cfg = self.config
        truth = _TrueSubmap(frames, submap_id)
        H = self._distortion(truth, submap_id)

        # Distorted cameras: P_i H^-1 = lambda_i K'_i [R'_i | t'_i].
        P = np.einsum("sij,sjk->sik", truth.K, truth.T_cam_ref[:, :3, :])
        K_pred, T_submap_cam, _ = decompose_projection(P @ np.linalg.inv(H))
        T_cam_submap = se3_inverse(T_submap_cam)

        S, height, width = truth.depth.shape
        depth_clean = np.empty((S, height, width), dtype=np.float64)
        for i in range(S):
            X_true = truth.points[i]
            homogeneous_weight = X_true.astype(np.float64) @ H[3, :3] + H[3, 3]
            X_pred = apply_transform(H, X_true)
            depth_clean[i] = X_pred @ T_cam_submap[i, 2, :3] + T_cam_submap[i, 2, 3]
            if not (np.all(homogeneous_weight > 0) and np.all(depth_clean[i] > 0)):
                raise UserError(
                    f"the simulated distortion of submap {submap_id} is too strong for this scene (points cross "
                    f"the plane at infinity or fall behind the camera of frame {frames[i].index}); lower --sim-perspective "
                    f"(now {cfg.perspective}) or --sim-shear / --sim-scale"
                )

        z_median = float(np.median(depth_clean[truth.measured]))
        depth = np.empty((S, height, width), dtype=np.float32)
        confidence = np.empty((S, height, width), dtype=np.float32)
        for i, frame in enumerate(frames):
            depth[i], confidence[i] = self._corrupt_frame(
                depth_clean[i], truth.measured[i], z_median, submap_id, frame.index
            )

        self.distortions[int(submap_id)] = H
        self.last_distortion = H
        prediction = SubmapPrediction(
            depth=depth,
            confidence=confidence,
            T_cam_submap=T_cam_submap[:, :3, :],
            K=K_pred,
            colors=np.stack([np.asarray(f.rgb, dtype=np.uint8) for f in frames]),
        )
        if match_pairs:
            prediction.match_pairs = np.asarray(match_pairs, dtype=np.int64).reshape(-1, 2)
            prediction.match_ratios = np.array([overlap_match_ratio(frames[a], frames[b]) for a, b in match_pairs],
                                               dtype=np.float32)
        return prediction

    def prepare(self) -> None:
        """Nothing to load: the simulator needs no weights."""

    def grid_colors(self, frame: Frame) -> np.ndarray:
        """The frame's own RGB: the simulator predicts on the input grid."""
        return np.asarray(frame.rgb, dtype=np.uint8)

    def distortion(self, frames: Sequence[Frame], submap_id: int) -> np.ndarray:
        """``H_submap_true`` ``(4, 4)`` in SL(4) that :meth:`reconstruct` applies to these frames.

        Maps true points in the first frame's camera (metres) to the predicted submap frame:
        ``X_pred = H X_true`` (homogeneous).
        """
        return self._distortion(_TrueSubmap(frames, submap_id), submap_id)

    # ------------------------------------------------------------------ internals

    def _distortion(self, truth: "_TrueSubmap", submap_id: int) -> np.ndarray:
        cfg = self.config
        rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(_DISTORTION_STREAM, int(submap_id))))
        # Fixed draw order, whatever the magnitudes, so each part is reproducible on its own.
        direction = rng.standard_normal(3)
        direction /= np.linalg.norm(direction)
        log_stretch = rng.standard_normal(3)
        off_diagonal = rng.standard_normal(3)
        log_scale = rng.standard_normal()

        B = np.diag(np.exp(cfg.shear * (log_stretch - log_stretch.mean())))
        B[np.triu_indices(3, k=1)] = cfg.shear * off_diagonal
        G = np.eye(4)
        G[:3, :3] = np.exp(cfg.scale * log_scale) * B
        G[3, :3] = cfg.perspective * direction
        if submap_id == 0 and not cfg.distort_first_submap:
            G = np.eye(4)

        kappa = truth.normalizing_scale()
        N = np.diag([kappa, kappa, kappa, 1.0])
        H = G @ N if cfg.normalize_scale else np.linalg.inv(N) @ G @ N
        return normalize_sl4(H)

    def _corrupt_frame(
        self, depth_clean: np.ndarray, measured: np.ndarray, z_median: float, submap_id: int, frame_index: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noise, outlier blobs and confidence of one frame: ``(H, W)`` float32 depth, confidence."""
        cfg = self.config
        height, width = depth_clean.shape
        root = np.random.SeedSequence(cfg.seed, spawn_key=(_FRAME_STREAM, int(submap_id), int(frame_index)))
        noise_rng, blob_rng, confidence_rng = (np.random.default_rng(s) for s in root.spawn(3))

        log_factor = cfg.depth_noise * noise_rng.standard_normal((height, width))
        in_blob = np.zeros((height, width), dtype=bool)
        if cfg.outlier_fraction > 0:
            cell = _BLOB_CELL_PER_PX * cfg.outlier_blob_px
            blob_field = _smooth_field(blob_rng, height, width, cell)
            in_blob = blob_field > np.quantile(blob_field, 1.0 - cfg.outlier_fraction)
            error_sign = np.tanh(2.0 * _smooth_field(blob_rng, height, width, cell))
            log_factor = log_factor + in_blob * (np.log1p(cfg.outlier_magnitude) * error_sign)
        depth = depth_clean * np.exp(log_factor)

        jitter = np.exp(cfg.confidence_jitter * confidence_rng.standard_normal((height, width)))
        excess = cfg.confidence_scale * (z_median / depth_clean) * jitter
        excess = np.where(in_blob, cfg.outlier_confidence * excess, excess)
        confidence = np.where(measured, 1.0 + excess, 1.0)
        return depth.astype(np.float32), confidence.astype(np.float32)


class _TrueSubmap:
    """Ground truth of a list of frames, checked, in the first frame's camera.

    Attributes:
        depth: ``(S, H, W)`` float32 metres, holes filled from the nearest measured pixel.
        measured: ``(S, H, W)`` bool, where the depth was measured.
        K: ``(S, 3, 3)`` float64 intrinsics.
        T_cam_ref: ``(S, 4, 4)`` float64 true ``T_cam_i_cam_0``.
    """

    def __init__(self, frames: Sequence[Frame], submap_id: int):
        if len(frames) == 0:
            raise UserError(f"submap {submap_id} has no frames; the simulated frontend needs at least one")
        shape = None
        depths, measured, Ks, poses = [], [], [], []
        for frame in frames:
            where = f"frame {frame.index}" + (f" ({frame.path})" if frame.path else "")
            missing = [name for name in ("depth", "T_world_cam", "K") if getattr(frame, name) is None]
            if missing:
                raise UserError(
                    f"{where} has no {', '.join(missing)}: the simulated frontend needs an RGB-D sequence with "
                    "ground-truth poses and intrinsics (TUM, 7-Scenes or the synthetic world); use --frontend vggt "
                    "for plain images"
                )
            depth = np.asarray(frame.depth, dtype=np.float32)
            rgb = np.asarray(frame.rgb)
            if depth.ndim != 2 or rgb.shape[:2] != depth.shape:
                raise UserError(
                    f"{where}: depth {depth.shape} does not match the RGB image {rgb.shape}; "
                    "the simulated frontend needs depth registered to the RGB frame"
                )
            if shape is None:
                shape = depth.shape
            elif depth.shape != shape:
                raise UserError(
                    f"{where} is {depth.shape[1]}x{depth.shape[0]} but the submap's first frame is "
                    f"{shape[1]}x{shape[0]}; all frames of a sequence must have the same size"
                )
            K = np.asarray(frame.K, dtype=np.float64)
            T = np.asarray(frame.T_world_cam, dtype=np.float64)
            if K.shape != (3, 3) or T.shape != (4, 4) or not (np.all(np.isfinite(K)) and np.all(np.isfinite(T))):
                raise UserError(f"{where}: intrinsics must be a finite 3x3 and the pose a finite 4x4 matrix")
            valid = np.isfinite(depth) & (depth > 0)
            if not valid.any():
                raise UserError(f"{where} has no valid depth pixel; the simulated frontend cannot reconstruct it")
            depths.append(_fill_holes(depth, valid))
            measured.append(valid)
            Ks.append(K)
            poses.append(T)
        self.depth = np.stack(depths)
        self.measured = np.stack(measured)
        self.K = np.stack(Ks)
        T_world_cam = np.stack(poses)
        self.T_cam_ref = se3_inverse(T_world_cam) @ T_world_cam[0]
        self._points: np.ndarray | None = None

    @property
    def points(self) -> np.ndarray:
        """``(S, H, W, 3)`` float32 true points in the first camera (holes filled), computed once."""
        if self._points is None:
            # Frame by frame: unprojection works in float64, which for a whole submap would be large.
            self._points = np.empty(self.depth.shape + (3,), dtype=np.float32)
            for i in range(len(self.depth)):
                self._points[i] = unproject_depth(self.depth[i : i + 1], self.K[i : i + 1], self.T_cam_ref[i : i + 1])[0]
        return self._points

    def normalizing_scale(self) -> float:
        """``1 / mean ||X||`` over the measured pixels of all frames (X in the first camera)."""
        distances = np.linalg.norm(self.points[self.measured].astype(np.float64), axis=-1)
        mean_distance = float(distances.mean())
        if not mean_distance > 0:
            raise UserError("the submap's points all sit at the first camera's centre; check the depth and poses")
        return 1.0 / mean_distance


def _fill_holes(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(H, W)`` depth with every invalid pixel set to the depth of its nearest valid pixel."""
    if valid.all():
        return depth
    nearest = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return depth[nearest[0], nearest[1]]


def _smooth_field(rng: np.random.Generator, height: int, width: int, cell: float) -> np.ndarray:
    """Zero-mean, unit-variance random field ``(height, width)`` with correlation length ~``cell`` px.

    White noise on a grid of ``cell``-px cells (with a margin so the crop has no border effects),
    smoothed over one cell and bicubically upsampled.
    """
    cell = max(float(cell), 1.0)
    rows, cols = int(np.ceil(height / cell)) + 3, int(np.ceil(width / cell)) + 3
    coarse = ndimage.gaussian_filter(rng.standard_normal((rows, cols)), 1.0, mode="wrap")
    fine = cv2.resize(coarse, (int(round(cols * cell)), int(round(rows * cell))), interpolation=cv2.INTER_CUBIC)
    margin = int(cell)
    field = fine[margin : margin + height, margin : margin + width]
    return (field - field.mean()) / max(float(field.std()), 1e-12)


def _validate(cfg: SimulatorConfig) -> None:
    """One-line errors for settings outside their meaningful range."""
    checks = [
        ("perspective", cfg.perspective >= 0, ">= 0"),
        ("shear", cfg.shear >= 0, ">= 0"),
        ("scale", cfg.scale >= 0, ">= 0"),
        ("depth-noise", cfg.depth_noise >= 0, ">= 0"),
        ("outlier-fraction", 0 <= cfg.outlier_fraction < 1, "in [0, 1)"),
        ("outlier-blob-px", cfg.outlier_blob_px > 0, "> 0"),
        ("outlier-magnitude", cfg.outlier_magnitude >= 0, ">= 0"),
        ("confidence-scale", cfg.confidence_scale > 0, "> 0"),
        ("confidence-jitter", cfg.confidence_jitter >= 0, ">= 0"),
        ("outlier-confidence", 0 <= cfg.outlier_confidence <= 1, "in [0, 1]"),
        ("seed", cfg.seed >= 0, ">= 0"),
    ]
    for flag, ok, allowed in checks:
        value = getattr(cfg, flag.replace("-", "_"))
        if not (ok and np.isfinite(value)):
            raise UserError(f"--sim-{flag} must be {allowed}, got {value}")
