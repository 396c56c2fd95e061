"""Simulated frontend: VGGT-like submaps made from ground truth, corrupted in a controlled way.

Given RGB-D frames with ground-truth poses and intrinsics (the synthetic world, TUM RGB-D,
7-Scenes), :class:`SimulatedFrontend` returns for any list of frames what VGGT returns — depth
``(S, H, W)``, confidence ``(S, H, W)`` >= 1, camera-from-submap extrinsics ``(S, 3, 4)`` with the
submap frame being the first frame's camera, intrinsics ``(S, 3, 3)``, colours, and the principal
point each frame's intrinsics assume (the true one) — on the frames' own pixel grid. Because the
truth is known exactly, every later stage (alignment, loop closure, the SL(4) and Sim(3) graphs)
can be measured against it.

Corruption model (settings of :class:`~sl4slam.config.SimulatorConfig`, command line
``--sim-<setting>``, config file section ``[sim]``; defaults, i.e. the ``exact`` profile, in
brackets; every term is off when its magnitude is 0):

1. **True submap.** ``X`` are the true points of every frame's depth in the first camera's frame
   (metres), ``T_cam_i_cam_0`` the true relative poses, ``K_i`` each frame's intrinsics.
   Pixels without a depth measurement (0 in TUM / 7-Scenes) are filled with the depth of the
   nearest measured pixel, since VGGT predicts everywhere; they get confidence exactly 1.

2. **Per-frame cameras** (``camera_rotation_deg`` [0], ``camera_translation`` [0],
   ``focal_error`` [0], ``camera_window_frames`` [100], ``frame_consistency`` [0]). VGGT predicts
   each frame's depth in its own camera and, separately, the frame's camera; its points are that
   depth placed by that camera. So each frame ``i >= 1`` gets a wrong pose: its rotation is
   turned about the camera centre by a rotation vector ~ ``N(0, camera_rotation_deg^2)`` per
   axis and its centre moved by ``N(0, (camera_translation * d)^2)`` per axis (``d`` the submap's
   mean true point distance); the first frame keeps ``[I | 0]`` as VGGT's does. Every frame
   (the first too) gets a wrong focal length: ``fx`` and ``fy`` times ``exp(focal_error * n)``,
   scaled about the principal point, which stays where it is (VGGT assumes the image centre).
   The frame's points are its own true depth unprojected with its wrong intrinsics and pose, so
   the frames of one submap disagree the way VGGT's do, and the returned extrinsic and
   intrinsics are the wrong ones.

   *Position in the window.* The error does not grow with the frame's position: VGGT estimates
   all cameras of a window jointly, attending to every frame, so a frame's error relative to the
   first does not accumulate as odometry does. This is what makes longer submaps better: the
   link between consecutive submaps inherits the error of one frame (the shared one), so a
   trajectory of ``L`` keyframes in submaps of ``w`` collects ``L / w`` such errors and drifts like
   ``sqrt(L / w)``, i.e. by 0.71 per doubling of ``w`` — VGGT-SLAM's published TUM ATE falls by
   0.72 and 0.64 per doubling (0.115, 0.083, 0.053 m for 8, 16, 32 keyframes). An error growing
   like ``sqrt(position)`` would cancel that gain. *Window length.* Past ``camera_window_frames``
   frames all three errors grow in proportion to ``S / camera_window_frames`` (VGGT's quality
   falls as windows grow past about 100 frames; the linear growth is our assumption).
   ``focal_consistency`` [-1: as ``frame_consistency``] sets the focal error's share alone: 0 draws
   a frame's focal length afresh in every window (where a known calibration pays most).
   With ``frame_consistency = c``, a share ``c`` of the variance of a frame's focal error (and of
   its depth warp, 6.) is the frame's own, drawn from ``(seed, frame index)`` and so the same in
   every submap that contains the frame; the rest is drawn per submap.

   *Unrelated frames* (``unrelated_overlap`` [0], ``unrelated_jitter`` [0.2]). A frame that
   shares at most ``unrelated_overlap`` of its view with every other frame of the window (the
   fraction of its true points, on a coarse grid, that another frame sees in front of it and inside
   its image) is an image of another place to the model, which nonetheless places it: at the pose
   of the window frame whose image it resembles most (correlation of small grey thumbnails), turned
   and moved by ``unrelated_jitter`` (radians, and times the mean point distance). Its depth stays
   its own. This is the case of a wrong-place loop candidate: its two reconstructions (old submap,
   new submap) still agree with each other perfectly, only its place in the new one is invented.

3. **Scale normalization** (``normalize_scale`` [on]). ``kappa = 1 / mean ||X||`` over the
   measured true pixels of all frames of the submap, so a normalized submap has mean point
   distance 1 (exactly so without camera errors), as VGGT's outputs do. ``N = diag(kappa,
   kappa, kappa, 1)``.

4. **Projective distortion and scale gauge** ``H_s`` in SL(4), drawn per submap from ``(seed,
   submap_id)``. In normalized coordinates ``G_s = [[g B, 0], [p^T, 1]]`` with

   - ``p = perspective * u``, ``u`` a uniformly random unit vector (``perspective`` [0]): the
     perspective row that Sim(3) cannot model. A point at the mean distance 1 has its
     homogeneous weight ``1 + p . X`` moved by at most ``perspective``;
   - ``B`` upper triangular with det 1 (``shear`` [0]): ``B_ij ~ N(0, shear^2)`` for ``i < j``,
     ``B_ii = exp(shear * (a_i - mean(a)))`` with ``a ~ N(0, I)``: shear and anisotropic stretch;
   - ``g = exp(scale * c + log(r) * (v - 1/2))``, ``c ~ N(0, 1)`` (``scale`` [0]) and ``v ~ U(0, 1)``
     from its own stream (``gauge_scale_ratio`` r [1]). The second factor is the submap's scale
     gauge: two submaps' scales differ by a ratio within ``[1/r, r]``. A Sim(3) gauge of a VGGT
     submap is a scale only: VGGT's first camera is always ``[I | 0]``, and a rotated or shifted
     submap frame would move it; re-anchoring at the first camera removes any rotation and
     translation exactly, so only the scale is left to vary (the disagreement in rotation and
     translation between windows comes from the per-frame camera errors of 2.).

   ``H_s = G_s N`` when normalizing, else ``N^-1 G_s N`` (metric units, same distortion), and is
   then normalized to det 1. With ``distort_first_submap`` [on] switched off, submap 0 gets
   ``G_s = I`` (only the normalization): the world frame is submap 0's frame, so its distortion
   would be inherited by any backend alike, and switching it off isolates the alignment error.
   This block form is the most general distortion that keeps the first
   camera at ``[I | 0]`` (as VGGT's first extrinsic is by construction): ``[I | 0] H_s^-1 =
   [A | 0]`` with ``A`` upper triangular, which the first camera's intrinsics absorb.
   The distorted camera of frame ``i`` is ``P_i H_s^-1`` with ``P_i = K_i [T_cam_i_cam_0]`` (the
   frame's possibly wrong camera of 2.); :func:`~sl4slam.geometry.decompose_projection` splits it
   into intrinsics ``K'_i`` (with skew when the distortion needs it) and a pose
   ``T'_cam_i_submap``, and the returned depth is the z coordinate of ``H_s X`` in that camera.
   Without noise, unprojecting the returned depth with the returned cameras gives exactly
   ``H_s X`` (up to float32 rounding). If some point would cross the plane at infinity or fall
   behind a distorted camera the distortion is too strong for the scene and a ``UserError`` asks
   for a smaller ``--sim-perspective`` (naming the profile it came from).

5. **Flying pixels** (``flying_px`` [0], ``flying_jump`` [0.1]). Two adjacent pixels whose
   depths differ by more than a factor ``1 + flying_jump`` are a depth discontinuity (an
   occlusion edge; smooth surfaces stay below it even at grazing angles). Every pixel within
   ``flying_px`` of one gets the depth ``near + a (far - near)``, ``near`` / ``far`` the smallest /
   largest depth within ``flying_px + 1`` (both sides of the edge) and ``a`` uniform in (0, 1),
   smooth over about the band's width: points strung between foreground and background, as a
   regression head blurs depth edges. They get the low confidence of outlier blobs (8.); on the
   synthetic world at 320x240 that is 1-2 % of the pixels at ``flying_px`` 1.5, 2-3.5 % at 3.

6. **Depth noise and warp** (``depth_noise`` [0.002], ``depth_warp`` [0], ``depth_warp_length``
   [0.3]): every pixel's depth is multiplied by ``exp(depth_noise * n + depth_warp * f)``, ``n ~
   N(0, 1)`` i.i.d., so the error is proportional to depth, and ``f`` a zero-mean unit-variance
   smooth field whose correlation length is ``depth_warp_length`` of the image width: a
   low-frequency, non-projective bending of the frame's surfaces, the bulk of a depth network's
   error. ``frame_consistency`` (2.) makes part of ``f`` the frame's own. No published figure
   pins the warp's correlation length or its consistency across windows (our assumptions);
   they decide how much of it the SL(4) alignment of a shared frame absorbs as a projective
   error, since a depth factor ``1 / (a . X + b)`` is exactly such a map.

7. **Outlier blobs** (``outlier_fraction`` [0.02], ``outlier_blob_px`` [12],
   ``outlier_magnitude`` [0.3]): the model's errors are locally consistent, not salt-and-pepper.
   A smooth random field (white noise on a grid of cells of ``1.25 * outlier_blob_px`` px,
   Gaussian-smoothed over one cell, bicubically upsampled) is thresholded at its
   ``1 - outlier_fraction`` quantile, so that fraction of each frame's pixels lies in blobs whose
   mean equivalent radius is about ``outlier_blob_px`` (0.8x at 2 %, 1.3x at 10 %). Inside the
   blobs the depth is multiplied by ``(1 + outlier_magnitude)^s`` where ``s = tanh(2 m)`` and
   ``m`` is a second, independent unit-variance smooth field: a relative error of about
   ``outlier_magnitude`` in either direction that varies slowly across a blob.

8. **Confidence** (``confidence_scale`` [5], ``confidence_jitter`` [0.2],
   ``outlier_confidence`` [0.02]): ``1 + confidence_scale * (z_med / z) * exp(confidence_jitter
   * e)`` for clean pixels, with ``z`` the distorted noise-free depth, ``z_med`` its median over
   the submap's measured pixels and ``e ~ N(0, 1)``: high where the depth is close (its absolute
   error is small), falling with depth. Inside outlier blobs and on flying pixels the excess over
   1 is multiplied by ``outlier_confidence``; filled pixels (no measurement) get exactly 1. So the
   pipeline's percentile confidence mask (``--tau-conf``, 25 %) removes the blobs, except where at
   least that fraction of the submap's pixels had no depth measurement (the filled pixels then
   fill the dropped percentile by themselves).

9. **Randomness** (``seed`` [0]): ``H_s`` comes from ``(seed, submap_id)``, the gauge from its own
   ``(seed, submap_id)`` stream; noise, blobs and confidence of frame ``f`` in submap ``j`` come
   from ``(seed, j, f.index)``, and its camera, focal, warp and flying-pixel errors each from a
   stream of their own under ``(seed, j, f.index)`` (the frame's own share of 2. and 6. from
   ``(seed, f.index)``). Switching one term on or off therefore changes no other term's draws,
   the same frame in two submaps gets independent errors (up to ``frame_consistency``), and
   every value is repeatable whatever the other frames of the submap are (except ``kappa``,
   ``d``, ``z_med`` and the window-length growth, which are submap-wide by definition).

**Profiles** (``profile``, ``--sim-profile``, ``[sim] profile``; ``SimulatorConfig.from_profile``)
set all magnitudes at once; explicit settings override them. ``exact`` is the defaults above.
``vggt`` is calibrated to these published figures for VGGT:

- relative rotation error between the frames of one window of indoor video: median about 1-3
  degrees; on 7-Scenes pose AUC@3 about 24 and AUC@30 about 85 (Depth Anything 3 paper, Lin et
  al. 2025, its table for VGGT);
- depth AbsRel about 2-4 % indoors (NYU 3.6 %, ScanNet 2.7 %, ETH3D 3.8 %), worse at depth
  discontinuities (flying pixels) and far away;
- intrinsics: principal point at the image centre (VGGT's decoding puts it there), focal length
  off by up to about 7 %;
- scale of one window relative to the next: ratios between 0.5 and 2 are seen in practice;
- quality falls as windows grow past about 100 frames;
- VGGT-SLAM's TUM ATE falls from 0.115 to 0.083 to 0.053 m as submaps grow from 8 to 16 to 32
  keyframes (Maggio et al., 2025), and SL(4) beats Sim(3) there (0.053 against 0.074 m): real
  VGGT submaps are related by more than a similarity, so ``vggt`` keeps a moderate projective
  part (``perspective`` 0.02, ``shear`` 0.01).

Measured on windows of 17 keyframes of the synthetic world (320x240, tests/test_sim_profile.py
checks a smaller version): ``vggt`` gives a median relative rotation error of 1.6 degrees, AUC@3
23 and AUC@30 87 (the error of a pair is the larger of its rotation and translation-direction
errors), depth AbsRel 2.4 % after per-frame median scaling, focal error 2.2 % median and 5.6 % at
the 95th percentile. ``hard`` takes the upper ends of the ranges, with more flying pixels and
outliers and less consistent frames: 2.9 degrees, AbsRel 4.8 %, focal error 8.9 % at the 95th
percentile.

The distortion used for each submap is kept in :attr:`SimulatedFrontend.distortions`
(``H_submap_true``, mapping true first-camera points to the predicted submap frame) so that tests
and benchmarks can compare an estimate against it; :meth:`SimulatedFrontend.distortion` computes
it without reconstructing. With per-frame camera errors, ``H_submap_true`` maps the first frame's
true points exactly and every other frame's up to that frame's camera error.
"""

from __future__ import annotations

from typing import Callable, Sequence

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation
from scipy.special import ndtr

from .settings import SimulatorConfig
from ..errors import UserError
from ..geometry import (
    apply_transform,
    decompose_projection,
    normalize_sl4,
    se3_inverse,
    unproject_depth,
)
from ..types import Frame, FrontendCapabilities, SubmapPrediction
from .overlap import overlap_match_ratio

# Stream tags for SeedSequence spawn keys: the distortion, the gauge and the per-frame draws (noise,
# blobs, confidence; camera, focal, warp, flying pixels; each in its own stream) never share random
# numbers, so switching one term on or off leaves every other term's draws as they were.
_DISTORTION_STREAM = 0
_FRAME_STREAM = 1
_FRAME_ERROR_STREAM = 2
_GAUGE_STREAM = 3
_FRAME_OWN_STREAM = 4  # the part of a frame's errors shared by every submap it appears in
# Sub-streams of _FRAME_ERROR_STREAM.
_ROTATION, _TRANSLATION, _FOCAL, _WARP, _FLYING, _UNRELATED = range(6)

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
    # frames without depth, pose or K are skipped by the pipeline; match ratios: the true overlap
    capabilities = FrontendCapabilities(scores_pairs=True, needs_ground_truth=True, predicts_intrinsics=True)

    def __init__(self, config: SimulatorConfig | None = None):
        """``config``: the corruption settings (magnitudes left at ``None`` come from its profile),
        checked here too, so that a simulator built by hand gets the one-line errors of a run."""
        config = config if config is not None else SimulatorConfig()
        config.validate()
        self.config = config.resolved()
        self.distortions: dict[int, np.ndarray] = {}
        self.last_distortion: np.ndarray | None = None

    # ------------------------------------------------------------------ public API

    def reconstruct(self, frames: Sequence[Frame], submap_id: int,
                    match_pairs: Sequence[tuple[int, int]] = ()) -> SubmapPrediction:
        """Corrupted VGGT-like prediction of ``frames`` (the first defines the submap frame).

        Returns a :class:`SubmapPrediction` on the frames' pixel grid: depth and confidence
        ``(S, H, W)`` float32, ``T_cam_submap`` ``(S, 3, 4)`` and ``K`` ``(S, 3, 3)`` float64,
        colours = the frames' RGB, ``principal_point`` ``(S, 2)`` float64 = the true intrinsics'
        principal points. ``points`` is left ``None`` (the pipeline unprojects depth).
        ``match_pairs`` (slot pairs) get the true-overlap stand-in for VGGT's image-match ratio
        (``sl4slam.frontend.overlap``).
        """
        cfg = self.config
        truth = _TrueSubmap(frames, submap_id)
        H = self._distortion(truth, submap_id)
        K_frame, T_cam_ref, cameras_exact = self._frame_cameras(truth, frames, submap_id)
        if cfg.unrelated_overlap > 0:
            T_cam_ref, placed = self._place_unrelated(truth, frames, submap_id, K_frame, T_cam_ref)
            cameras_exact = cameras_exact and not placed

        # Distorted cameras: P_i H^-1 = lambda_i K'_i [R'_i | t'_i].
        P = np.einsum("sij,sjk->sik", K_frame, T_cam_ref[:, :3, :])
        K_pred, T_submap_cam, _ = decompose_projection(P @ np.linalg.inv(H))
        T_cam_submap = se3_inverse(T_submap_cam)

        S, height, width = truth.depth.shape
        depth_clean = np.empty((S, height, width), dtype=np.float64)
        for i in range(S):
            # The frame's own depth placed by its own (possibly wrong) camera and focal length.
            X_frame = truth.points[i] if cameras_exact else unproject_depth(
                truth.depth[i : i + 1], K_frame[i : i + 1], T_cam_ref[i : i + 1])[0]
            homogeneous_weight = X_frame.astype(np.float64) @ H[3, :3] + H[3, 3]
            X_pred = apply_transform(H, X_frame)
            depth_clean[i] = X_pred @ T_cam_submap[i, 2, :3] + T_cam_submap[i, 2, 3]
            if not (np.all(homogeneous_weight > 0) and np.all(depth_clean[i] > 0)):
                source = "" if cfg.profile == "exact" else f", {cfg.profile} profile"
                raise UserError(
                    f"the simulated distortion of submap {submap_id} is too strong for this scene (points cross "
                    f"the plane at infinity or fall behind the camera of frame {frames[i].index}); lower --sim-perspective "
                    f"(now {cfg.perspective}{source}) or --sim-shear / --sim-scale"
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
            principal_point=truth.K[:, :2, 2].copy(),
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
        log_global_scale = cfg.scale * log_scale
        if cfg.gauge_scale_ratio != 1.0:
            gauge_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(_GAUGE_STREAM, int(submap_id))))
            log_global_scale = log_global_scale + np.log(cfg.gauge_scale_ratio) * (gauge_rng.random() - 0.5)
        G = np.eye(4)
        G[:3, :3] = np.exp(log_global_scale) * B
        G[3, :3] = cfg.perspective * direction
        if submap_id == 0 and not cfg.distort_first_submap:
            G = np.eye(4)

        kappa = truth.normalizing_scale()
        N = np.diag([kappa, kappa, kappa, 1.0])
        H = G @ N if cfg.normalize_scale else np.linalg.inv(N) @ G @ N
        return normalize_sl4(H)

    def _frame_rng(self, submap_id: int, frame_index: int, term: int) -> np.random.Generator:
        """The generator of one per-frame error term (camera, focal, warp, flying pixels) in one submap."""
        key = (_FRAME_ERROR_STREAM, int(submap_id), int(frame_index), term)
        return np.random.default_rng(np.random.SeedSequence(self.config.seed, spawn_key=key))

    def _consistent_draw(
        self, draw: Callable[[np.random.Generator], np.ndarray], submap_id: int, frame_index: int, term: int
    ) -> np.ndarray:
        """A unit-variance draw of one term: ``frame_consistency`` of its variance is the frame's own (the
        same in every submap; ``focal_consistency`` for the focal error), the rest is drawn for this submap."""
        share = self.config.frame_consistency
        if term == _FOCAL and self.config.focal_consistency >= 0:
            share = self.config.focal_consistency
        submap_part = draw(self._frame_rng(submap_id, frame_index, term)) if share < 1 else 0.0
        if share == 0:
            return submap_part
        own_rng = np.random.default_rng(
            np.random.SeedSequence(self.config.seed, spawn_key=(_FRAME_OWN_STREAM, int(frame_index), term)))
        return np.sqrt(share) * draw(own_rng) + np.sqrt(1.0 - share) * submap_part

    def _frame_cameras(
        self, truth: "_TrueSubmap", frames: Sequence[Frame], submap_id: int
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """The cameras the frontend believes in: ``K (S, 3, 3)``, ``T_cam_ref (S, 4, 4)``, and whether
        they are the true ones (then the very same arrays as ``truth``'s)."""
        cfg = self.config
        if cfg.camera_rotation_deg == 0 and cfg.camera_translation == 0 and cfg.focal_error == 0:
            return truth.K, truth.T_cam_ref, True
        # Errors are the same for every position in the window; they grow with the window's length
        # past camera_window_frames (see the module docstring).
        growth = max(1.0, len(frames) / cfg.camera_window_frames)
        shift_sigma = cfg.camera_translation * growth / truth.normalizing_scale()
        rotation_sigma = np.deg2rad(cfg.camera_rotation_deg) * growth
        K = truth.K.copy()
        T_ref_cam = se3_inverse(truth.T_cam_ref)
        for i, frame in enumerate(frames):
            rotation_vector = rotation_sigma * self._frame_rng(submap_id, frame.index, _ROTATION).standard_normal(3)
            shift = shift_sigma * self._frame_rng(submap_id, frame.index, _TRANSLATION).standard_normal(3)
            log_focal = cfg.focal_error * growth * self._consistent_draw(
                lambda rng: rng.standard_normal(), submap_id, frame.index, _FOCAL)
            K[i] = scale_focal(K[i], np.exp(log_focal))
            if i > 0:  # the first camera defines the submap frame: [I | 0] exactly
                T_ref_cam[i, :3, :3] = T_ref_cam[i, :3, :3] @ Rotation.from_rotvec(rotation_vector).as_matrix()
                T_ref_cam[i, :3, 3] += shift
        return K, se3_inverse(T_ref_cam), False

    def _place_unrelated(
        self, truth: "_TrueSubmap", frames: Sequence[Frame], submap_id: int, K: np.ndarray, T_cam_ref: np.ndarray
    ) -> tuple[np.ndarray, bool]:
        """Poses ``T_cam_ref (S, 4, 4)`` with every unrelated frame placed as a model would place it
        (see the module docstring), and whether any was."""
        S, height, width = truth.depth.shape
        if S < 2:
            return T_cam_ref, False
        rows = np.linspace(0, height - 1, 12).round().astype(int)
        cols = np.linspace(0, width - 1, 16).round().astype(int)
        grid = truth.points[:, rows][:, :, cols].reshape(S, -1, 3).astype(np.float64)  # (S, n, 3) in the submap frame
        measured = truth.measured[:, rows][:, :, cols].reshape(S, -1)
        overlap = np.zeros((S, S))
        for j in range(S):  # points of every frame seen by camera j (true geometry)
            X = grid @ truth.T_cam_ref[j, :3, :3].T + truth.T_cam_ref[j, :3, 3]
            uvw = X @ truth.K[j].T
            z = uvw[..., 2]
            u, v = uvw[..., 0] / np.where(z > 0, z, 1.0), uvw[..., 1] / np.where(z > 0, z, 1.0)
            seen = measured & (z > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
            overlap[:, j] = seen.mean(axis=1)
        np.fill_diagonal(overlap, 0.0)
        unrelated = np.flatnonzero(overlap.max(axis=1) <= self.config.unrelated_overlap)
        unrelated = unrelated[unrelated > 0]  # the first frame defines the submap frame
        if len(unrelated) == 0:
            return T_cam_ref, False
        thumbnails = np.stack([_thumbnail(f.rgb) for f in frames])
        likeness = thumbnails @ thumbnails.T
        T_ref_cam = se3_inverse(T_cam_ref)
        jitter = self.config.unrelated_jitter
        for i in unrelated:
            others = np.setdiff1d(np.arange(S), unrelated)
            twin = int(others[np.argmax(likeness[i, others])])
            rng = self._frame_rng(submap_id, frames[i].index, _UNRELATED)
            placed = T_ref_cam[twin].copy()
            placed[:3, :3] = placed[:3, :3] @ Rotation.from_rotvec(jitter * rng.standard_normal(3)).as_matrix()
            placed[:3, 3] += jitter * rng.standard_normal(3) / truth.normalizing_scale()
            T_ref_cam[i] = placed
        return se3_inverse(T_ref_cam), True

    def _corrupt_frame(
        self, depth_clean: np.ndarray, measured: np.ndarray, z_median: float, submap_id: int, frame_index: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Flying pixels, noise, warp, outlier blobs and confidence of one frame: ``(H, W)`` float32
        depth, confidence."""
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
        if cfg.depth_warp > 0:
            cell = cfg.depth_warp_length * width
            warp = self._consistent_draw(lambda rng: _smooth_field(rng, height, width, cell), submap_id, frame_index, _WARP)
            log_factor = log_factor + cfg.depth_warp * warp
        low_confidence = in_blob
        depth_source = depth_clean
        if cfg.flying_px > 0:
            flying_rng = self._frame_rng(submap_id, frame_index, _FLYING)
            depth_source, flying = flying_pixels(depth_clean, cfg.flying_px, cfg.flying_jump, flying_rng)
            low_confidence = in_blob | flying
        depth = depth_source * np.exp(log_factor)

        jitter = np.exp(cfg.confidence_jitter * confidence_rng.standard_normal((height, width)))
        excess = cfg.confidence_scale * (z_median / depth_clean) * jitter
        excess = np.where(low_confidence, cfg.outlier_confidence * excess, excess)
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


def scale_focal(K: np.ndarray, factor: float) -> np.ndarray:
    """``(3, 3)`` intrinsics with the focal lengths (and skew) times ``factor``, the principal point kept."""
    about_principal_point = np.array([[factor, 0.0, (1.0 - factor) * K[0, 2]], [0.0, factor, (1.0 - factor) * K[1, 2]],
                                      [0.0, 0.0, 1.0]])
    return about_principal_point @ K


def flying_pixels(
    depth: np.ndarray, band_px: float, jump: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Depth blended across depth discontinuities, as a regression head blurs depth edges.

    Args:
        depth: ``(H, W)`` positive depth.
        band_px: half-width of the band around a discontinuity (px, >= 1).
        jump: relative depth jump between two adjacent pixels (4-neighbours) that makes both of
            them edge pixels: the larger depth exceeds ``(1 + jump)`` times the smaller.
        rng: draws the mix of each band pixel.

    Returns:
        ``(H, W)`` depth where the band (pixels within ``band_px`` of an edge pixel) is
        ``near + a (far - near)`` (``near`` / ``far`` the smallest / largest depth within
        ``band_px + 1``, so both sides of the edge; ``a`` uniform in (0, 1), smooth over about the
        band's width), and the ``(H, W)`` bool band.
    """
    edge = np.zeros(depth.shape, dtype=bool)
    for axis in (0, 1):
        first = [slice(None), slice(None)]
        second = [slice(None), slice(None)]
        first[axis], second[axis] = slice(None, -1), slice(1, None)
        a, b = depth[tuple(first)], depth[tuple(second)]
        jumps = np.maximum(a, b) > (1.0 + jump) * np.minimum(a, b)
        edge[tuple(first)] |= jumps
        edge[tuple(second)] |= jumps
    band = ndimage.binary_dilation(edge, structure=_disk(band_px))
    reach = _disk(band_px + 1.0)
    near = ndimage.minimum_filter(depth, footprint=reach, mode="nearest")
    far = ndimage.maximum_filter(depth, footprint=reach, mode="nearest")
    mix = ndtr(_smooth_field(rng, *depth.shape, band_px))  # a unit normal field mapped to uniform (0, 1)
    return np.where(band, near + mix * (far - near), depth), band


def _thumbnail(rgb: np.ndarray) -> np.ndarray:
    """Zero-mean, unit-norm grey 32x24 thumbnail ``(768,)`` of an ``(H, W, 3)`` uint8 image."""
    grey = cv2.resize(cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2GRAY), (32, 24),
                      interpolation=cv2.INTER_AREA).astype(np.float64).reshape(-1)
    grey -= grey.mean()
    norm = np.linalg.norm(grey)
    return grey / norm if norm > 0 else grey


def _disk(radius: float) -> np.ndarray:
    """Boolean ``(2r+1, 2r+1)`` footprint of the pixels within ``radius`` of the centre (``r = floor(radius)``)."""
    r = int(np.floor(radius))
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    return dx**2 + dy**2 <= radius**2


def registry_entry():
    """The simulator in the frontend registry (``sl4slam.registry``)."""
    from ..registry import FrontendEntry

    return FrontendEntry(
        name="simulated", build=lambda resolved: SimulatedFrontend(resolved.config.sim),
        capabilities=SimulatedFrontend.capabilities, settings="sim",
        description="VGGT-like submaps from an RGB-D sequence's ground truth, with controlled errors (--sim-profile)")
