"""Each window's camera centres smoothed along the camera's path, as far as the run's measured centre
noise allows.

A feed-forward model places every frame of a window on its own, so each frame's camera centre
carries an error of its own; a keyframe outside the shared frames is in one window only, and that
error is in the trajectory as drawn, while the shared frames' errors move every later submap. The
camera itself moves smoothly between keyframes a fraction of a second apart: a track of centres
that zigzags more than its noise explains holds noise that a smoother can take out.

How much to smooth follows two things the run measures:

- **the centre noise** ``sigma`` (in units of the window's median depth, so that one value holds
  for every window and model scale): every pair of frames two consecutive windows share is placed
  by both, and the two placements of one frame relative to the other disagree by the frames' centre
  errors (:func:`replicate`). Only the part of the disagreement across the pair's baseline is used,
  since the two windows' scales differ and a scale error lies along it. The median over the run's
  links, scaled to the chi-square median, estimates ``sigma``; with few links it is shrunk towards
  zero (:data:`FEW_LINKS`), and it is taken at :data:`NOISE_MARGIN` of its value, because
  overstating the noise smooths away real motion, while understating it only smooths less;
- **the motion**: within a window the centres are fitted by the smoothest track (least squared
  acceleration, :func:`second_difference_penalty`) whose residual stays within that noise (the
  discrepancy principle: the residual sum of squares at most ``sigma^2`` times its degrees of
  freedom, :func:`smooth_track`). A window whose frames move sharply keeps its centres; one whose
  centres only jitter around a smooth path loses the jitter.

**Only where the windows carry no distortion of their own.** A projective distortion common to a
window's frames (the paper's premise) moves the two placements of a pair apart too, by an amount
that grows with the pair's baseline, and the frames' points are consistent with their distorted
cameras: moving the cameras then breaks the window. So a window is smoothed only while the last
link the graph took was read from the cameras (the ``select`` link's choice, or the calibration
link: no distortion worth a 15-DOF fit), and a replicate counts only once its window's own link
was such a link (or a fallback that decided nothing, such as a flat shared frame's, while the last
link that decided was). A run whose links are 15-DOF fits is left as it is. So is a run that shares one
frame between windows (the VGGT-SLAM 2.0 design: no replicate), and the first two windows, before
a link has been seen. Rotations, depth and intrinsics are not
touched; the frame's points follow its moved camera. The reference frame of a window (its first,
``[I | 0]``) stays where it is. Loop frames, appended to a window out of time order, are not part
of the track.

It rests on the model's centre errors being independent from frame to frame (the simulator's
``camera_translation``, drawn per frame and per window), and on the camera's path being smooth
between keyframes (decision: docs/decisions/centre-smoothing.md).

Frames: ``T_cam_submap`` maps submap points into each camera, ``X_cam = R X_sub + t``; the centre
is ``C = -R^T t``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .edges import is_camera_link
from .types import Alignment, SubmapPrediction

CHI2_2_MEDIAN = 2.0 * np.log(2.0)
"""Median of a chi-square variable with 2 degrees of freedom."""

NOISE_MARGIN = 0.8
"""The centre noise used, as a share of the measured one: overstating the noise bends real motion,
understating it only smooths less (decision: docs/decisions/centre-smoothing.md)."""

FEW_LINKS = 2.0
"""The measured noise variance is shrunk by ``n / (n + FEW_LINKS)`` over ``n`` replicates: the
median of one or two chi-square draws scatters by a factor of several."""

LOG_LAMBDA_GRID = np.arange(-9.0, 3.01, 0.25)
"""Smoothing weights tried (log10, on the window's time scaled to [0, 1])."""

MIN_TRACK = 4
"""Fewest frames in time order (the reference included) for a track worth smoothing."""


def second_difference_penalty(t: np.ndarray) -> np.ndarray:
    """``(n, n)`` positive semi-definite ``P`` with ``x^T P x`` the summed squared acceleration of a
    track ``x`` sampled at increasing times ``t`` ``(n,)``: the second divided differences
    ``2 ((x_{i+1} - x_i) / h_i - (x_i - x_{i-1}) / h_{i-1}) / (h_{i-1} + h_i)``, each weighted by the
    time it stands for, ``(h_{i-1} + h_i) / 2``. Its null space is the tracks linear in ``t``."""
    t = np.asarray(t, dtype=np.float64)
    n = len(t)
    h = np.diff(t)
    D = np.zeros((max(n - 2, 0), n))
    if n >= 3:
        rows = np.arange(n - 2)
        span = h[:-1] + h[1:]
        scale = 2.0 / span * np.sqrt(span / 2.0)
        D[rows, rows] = scale / h[:-1]
        D[rows, rows + 1] = -scale * (1.0 / h[:-1] + 1.0 / h[1:])
        D[rows, rows + 2] = scale / h[1:]
    return D.T @ D


def smooth_track(C: np.ndarray, t: np.ndarray, sigma: float) -> tuple[np.ndarray, float]:
    """The smoothest track through the centres ``C`` ``(n, 3)`` at times ``t`` ``(n,)`` (increasing)
    whose residual stays within the noise ``sigma`` (per axis, ``C``'s units), the first centre
    held where it is.

    Solves ``min |C_f - X_f|^2 + lam X^T P X`` over the free centres (all but the first), with the
    largest ``lam`` of :data:`LOG_LAMBDA_GRID` (time scaled to [0, 1]) for which the residual sum of
    squares is at most ``sigma^2 (m - trace)``: ``m`` the free coordinates, ``trace`` those the fit
    spends (the discrepancy principle).

    Returns:
        ``(X (n, 3), lam)``; ``(C, 0.0)`` when no weight keeps the residual within the noise or the
        track is shorter than :data:`MIN_TRACK`.
    """
    C = np.asarray(C, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    n = len(t)
    if n < MIN_TRACK or sigma <= 0 or not np.all(np.diff(t) > 0):
        return C, 0.0
    P = second_difference_penalty((t - t[0]) / (t[-1] - t[0]))
    P_ff, P_f0 = P[1:, 1:], P[1:, :1]
    y = C[1:]
    m = 3 * (n - 1)
    best, best_lam = C, 0.0
    identity = np.eye(n - 1)
    for log_lam in LOG_LAMBDA_GRID:
        lam = float(10.0 ** log_lam)
        M = identity + lam * P_ff
        X = np.linalg.solve(M, y - lam * P_f0 @ C[:1])
        spent = 3.0 * float(np.trace(np.linalg.inv(M)))
        if float(np.sum((y - X) ** 2)) > sigma**2 * (m - spent):
            break
        best, best_lam = np.vstack([C[:1], X]), lam
    return best, best_lam


def centres(T_cam_submap: np.ndarray) -> np.ndarray:
    """``(S, 3)`` camera centres of extrinsics ``(S, 3|4, 4)`` in the submap frame."""
    T = np.asarray(T_cam_submap, dtype=np.float64)
    return -np.einsum("sji,sj->si", T[:, :3, :3], T[:, :3, 3])


def depth_unit(depth: np.ndarray) -> float:
    """The window's length unit: the median of its positive depths ``(S, H, W)`` (every fourth pixel)."""
    sample = np.asarray(depth[:, ::4, ::4], dtype=np.float64)
    sample = sample[np.isfinite(sample) & (sample > 0)]
    return float(np.median(sample)) if len(sample) else 0.0


def is_reference(T: np.ndarray) -> bool:
    """Whether the extrinsic ``(3|4, 4)`` is its window's reference camera ``[I | 0]``."""
    return bool(np.allclose(np.asarray(T, dtype=np.float64)[:3], np.eye(4)[:3], atol=1e-9))


def replicate(old: tuple[np.ndarray, np.ndarray, float], new: tuple[np.ndarray, np.ndarray, float]) -> float | None:
    """One measurement of the centre noise variance from a pair of frames placed by two windows.

    Args:
        old, new: ``(T_first, T_second, unit)``: the two frames' extrinsics ``(3|4, 4)`` in one
            window and that window's :func:`depth_unit`.

    Returns:
        ``|d_perp|^2 / (2 k)``: the disagreement ``d`` of the second frame's centre relative to the
        first (in the first frame's camera, in units of the window's depth) between the windows,
        without its part along the pair's baseline (where the windows' scales differ); ``k`` the
        centres that carry an error (the two frames, less the windows' references). Over frames
        whose centre errors are independent, ``sigma^-2`` times it is chi-square with 2 degrees of
        freedom over 2. ``None`` when nothing is measured (no error carried, no unit, no baseline).
    """
    placed = []
    carried = 0
    for T_first, T_second, unit in (old, new):
        if unit <= 0:
            return None
        C = centres(np.stack([np.asarray(T_first)[:3], np.asarray(T_second)[:3]]))
        placed.append(np.asarray(T_first, dtype=np.float64)[:3, :3] @ (C[1] - C[0]) / unit)
        carried += (not is_reference(T_first)) + (not is_reference(T_second))
    baseline = placed[0] + placed[1]
    length = float(np.linalg.norm(baseline))
    if carried == 0 or length == 0:
        return None
    d = placed[0] - placed[1]
    along = baseline / length
    d_perp = d - (d @ along) * along
    return float(d_perp @ d_perp) / (2.0 * carried)


def link_kind(odometry: Alignment | str | None) -> str:
    """How the graph took a window, for :meth:`CentreSmoother.commit`: ``"camera"`` (a link read from
    the cameras by choice: the ``select`` link kept the camera link, or a camera aligner measured it),
    ``"fit"`` (a 15-DOF fit: a distortion common to the window) or ``"none"`` (nothing learnt: no link
    measured, or a fallback, such as a flat shared frame's cameras standing in for a fit that its
    points could not determine)."""
    if not isinstance(odometry, Alignment):
        return "none"
    chosen = odometry.extras.get("select", {}).get("chosen")
    if chosen is not None:
        return {"link": "camera", "fit": "fit"}.get(chosen, "none")
    if odometry.fallback:
        return "none"
    return "camera" if is_camera_link(odometry) else "fit"


@dataclass
class CentreNoise:
    """The run's centre noise: its replicates (:func:`replicate`) so far."""

    replicates: list[float] = field(default_factory=list)

    def sigma(self) -> float | None:
        """The noise to smooth with (units of a window's depth; module doc), ``None`` before any replicate."""
        if not self.replicates:
            return None
        n = len(self.replicates)
        variance = float(np.median(self.replicates)) / (CHI2_2_MEDIAN / 2.0) * n / (n + FEW_LINKS)
        return NOISE_MARGIN * float(np.sqrt(variance))


@dataclass
class SmoothedWindow:
    """What one window hands on once the graph took it (:meth:`CentreSmoother.commit`).

    Attributes:
        replicates: its shared frames' noise measurements.
        handed: ``frame index -> (raw extrinsic (3, 4), the window's depth unit)`` of the frames that
            open the next window, as the model placed them.
        sigma: the noise its centres were smoothed with (``None``: not smoothed); lam: the weight.
    """

    replicates: list[float]
    handed: dict[int, tuple[np.ndarray, float]]
    sigma: float | None = None
    lam: float = 0.0


class CentreSmoother:
    """The centres of each window smoothed with the run's measured noise (module doc).

    ``smooth`` a window's prediction before its points are made; ``commit`` what it measured once
    the graph took the window, with the kind of link the graph took it by (a window the graph drops
    measures nothing)."""

    def __init__(self, enabled: bool, overlap: int) -> None:
        self.enabled = bool(enabled)
        self.overlap = int(overlap)
        self.noise = CentreNoise()
        self.camera_linked = False  # the last link the graph took was read from the cameras
        self._handed: dict[int, tuple[np.ndarray, float]] = {}

    def smooth(self, frames: list, first_new: int, last_slot: int,
               prediction: SubmapPrediction) -> tuple[SubmapPrediction, SmoothedWindow | None]:
        """``prediction`` with the centres of slots ``0..last_slot`` smoothed, and what to commit.

        Args:
            frames: the window's frames (``Frame``: ``index``, ``timestamp``), by slot.
            first_new: slots before it are the shared frames; last_slot: the window's newest keyframe.
            prediction: the model's output for the window.
        """
        if not self.enabled:
            return prediction, None
        T = np.asarray(prediction.T_cam_submap, dtype=np.float64)
        unit = depth_unit(prediction.depth[: last_slot + 1])
        window = SmoothedWindow(self._replicates(frames, first_new, T, unit), {})
        for slot in range(max(0, last_slot + 1 - self.overlap), last_slot + 1):
            window.handed[int(frames[slot].index)] = (T[slot, :3].copy(), unit)
        sigma = self.noise.sigma() if self.camera_linked else None
        if sigma is None or unit <= 0:
            return prediction, window
        track = slice(0, last_slot + 1)
        times = np.array([f.timestamp for f in frames[track]], dtype=np.float64)
        if not np.all(np.diff(times) > 0):
            times = np.array([f.index for f in frames[track]], dtype=np.float64)
        smoothed, lam = smooth_track(centres(T[track]), times, sigma * unit)
        window.sigma, window.lam = sigma, lam
        if lam == 0.0:
            return prediction, window
        moved = T.copy()
        moved[track, :3, 3] = -np.einsum("sij,sj->si", T[track, :3, :3], smoothed)
        return dataclasses.replace(prediction, T_cam_submap=moved), window

    def commit(self, window: SmoothedWindow | None, link: str) -> None:
        """Keep what a window the graph took measured and hands on. ``link``: how the graph took it,
        ``"camera"`` (a link read from the cameras), ``"fit"`` (a 15-DOF fit: the windows are
        distorted) or ``"none"`` (no link measured, or a fallback that decided nothing: the window's
        replicates count only while the last link that decided was a camera link);
        :func:`link_kind` tells them apart."""
        if window is None:
            return
        if link == "camera" or (link == "none" and self.camera_linked):  # windows not distorted as far as seen
            self.noise.replicates.extend(window.replicates)
        if link != "none":
            self.camera_linked = link == "camera"
        self._handed = window.handed

    def _replicates(self, frames: list, first_new: int, T: np.ndarray, unit: float) -> list[float]:
        """The noise measurements of the window's shared frames against the window they came from."""
        shared = [int(frames[slot].index) for slot in range(first_new)]
        if len(shared) < 2 or not all(index in self._handed for index in shared):
            return []
        old_first, old_unit = self._handed[shared[0]]
        found = []
        for slot in range(1, first_new):
            old_second, _ = self._handed[shared[slot]]
            value = replicate((old_first, old_second, old_unit), (T[0], T[slot], unit))
            if value is not None:
                found.append(value)
        return found
