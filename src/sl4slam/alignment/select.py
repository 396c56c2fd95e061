"""Choosing, per link, between the calibration-and-scale link and the 15-DOF fit by cross-validation.

Two models measure the link between consecutive submaps from their shared frames: the
calibration-and-scale link (VGGT-SLAM 2.0: the frames' cameras and one free scale) and the 15-DOF
projective fit (VGGT-SLAM: the frames' points). Which one is right depends on the error the model
made. A projective distortion of a whole window (the paper's premise) is common to every frame of
that window, and only the fit can express it. A frame's depth warp or camera error belongs to that
frame alone; the fit absorbs it as a projective error that then bends the whole next submap, where
the link, blind to it, does better. A margin on how much better the fit explains the shared frame
(the ``hybrid`` model) cannot tell the two apart: both make the fit explain its own points better.

Prediction tells them apart. With two or more shared frames, each model is measured on all of
them but one and judged on the one left out: a distortion of the window, measured on the other
frames, predicts it; another frame's warp does not. The fit is chosen only where it predicts every
left-out frame better than the link, by at least ``AlignmentConfig.select_min_gain`` times on the
geometric mean of the left-out error ratios, and, with three or more folds, by a one-sided paired
t-test over them at ``AlignmentConfig.select_confidence`` (each frame one observation: its pixels
err together). With two shared frames the two folds are one comparison seen from both sides (the
fit on the first predicting the second and the fit on the second predicting the first), so their
spread is no measure of noise: it measures how differently the two frames see the window, which
under forward motion is a lot, and a t-test with its one degree of freedom then refused a window's
distortion predicted ten times better. The gain is what separates a window's distortion (predicted
7-60x better) from per-frame errors (1.0-1.2x) (decision: docs/decisions/select-link.md).
With one shared frame nothing is left to judge on, and the link, the model that assumes less, is
kept.

Degenerate shared frames (flat, or flat against their depth errors: ``SL4Aligner``) have no 15-DOF
fit to choose: they get what the SL(4) aligner's ``planar_model`` gives them (the link, or the
camera-constrained fit where it explains nearly every point and far more than the link); a nearly
planar frame's fit must still predict the left-out frames. A flat frame can still judge as the
training frame of a fold: its camera-constrained fit (points on the plane, cameras for the rest)
predicts the other frame where the window is distorted, as the fit of any frame does. A flat frame
measured by the link itself trains no fit: its fold is a tie that does not judge, and the other
folds decide (as a held-out frame, a flat frame is judged like any other).
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

import numpy as np

from ..edges import is_camera_link
from ..types import Alignment, FrameView
from .common import FrameFitter
from .parallel import start
from .ransac import transfer_errors
from .shared import FrameMeasurements, link_from_shared_frames, mean_camera_link, measure_frames

def transfer_distances(H: np.ndarray, X_a: np.ndarray, X_b: np.ndarray) -> np.ndarray:
    """``(n,)`` ``|X_a - H X_b|`` per pair (points mapped behind the camera: infinitely far)."""
    r2, in_front = transfer_errors(np.asarray(H, dtype=np.float64)[None], X_a, X_b)
    return np.sqrt(np.where(in_front[0], r2[0], np.inf))


def fit_predicts_better(log_ratios: np.ndarray, confidence: float, min_gain: float = 1.0) -> bool:
    """Does the fit predict the held-out parts better than the link? ``log_ratios`` ``(k,)``: per
    held-out part, the log of the fit's median transfer distance over the link's (the parts whose
    training frame determined nothing beyond the link are left out by the caller). The fit must
    predict every part better (each ratio below 1), by at least ``min_gain`` times on the geometric
    mean, and, with three or more parts, pass a one-sided paired t-test at ``confidence``. The parts
    are the units: the pixels of one frame err together (a smooth warp), so they are one
    observation, not thousands. Two parts are one comparison seen from both sides (see the module
    doc): their spread measures how differently the two frames see the window, not noise, so a
    t-test on them (one degree of freedom) refuses a window's distortion whenever the two frames
    differ, as they do under forward motion."""
    log_ratios = np.asarray(log_ratios, dtype=np.float64)
    if not len(log_ratios) or not np.all(log_ratios < 0):
        return False
    mean = float(np.mean(log_ratios))
    if mean >= -np.log(max(min_gain, 1.0)):
        return False
    spread = float(np.std(log_ratios, ddof=1)) if len(log_ratios) >= 3 else 0.0
    if spread == 0.0:  # two parts face no t-test (see above)
        return True
    from scipy.stats import t

    return mean + t.ppf(confidence, len(log_ratios) - 1) * spread / np.sqrt(len(log_ratios)) < 0


def choose_link(fit_aligner: FrameFitter, link_aligner: FrameFitter,
                pairs: Sequence[tuple[FrameView, FrameView]], seed: int) -> Alignment:
    """The link of ``pairs`` (the shared frames' views in the older and newer submap) by the
    cross-validated choice of the module doc; ``extras["select"]`` records the held-out errors.
    ``fit_aligner`` measures the 15-DOF fit (an ``SL4Aligner``), ``link_aligner`` the
    calibration-and-scale link (a ``CalibrationAligner``)."""
    fits = measure_frames(fit_aligner, pairs, seed, joint=True)  # the joint fit starts beside the frames' own
    links = measure_frames(link_aligner, pairs, seed, same_points=fits)
    link = link_from_shared_frames(link_aligner, pairs, seed, links)
    fitted = link_from_shared_frames(fit_aligner, pairs, seed, fits)
    if fitted.extras.get("degenerate"):  # the SL(4) aligner's own measurement of a degenerate frame
        # a camera link: the first shared frame's own, which keeps that camera exactly, so that the
        # metric frame can complete what the plane leaves free (``sl4slam.completion``)
        chosen = fitted if not is_camera_link(fitted) else links.alignments[0] if links.frames[0] == 0 else link
        chosen.extras["select"] = {"chosen": "degenerate", "why": fitted.fallback}
        chosen.fallback = fitted.fallback
        return chosen
    common = [k for k in fits.frames if k in links.frames]
    if len(common) < 2:
        link.extras["select"] = {"chosen": "link", "why": "one shared frame: nothing held out to judge the fit on"}
        return link
    folds = _frame_folds(fit_aligner, pairs, fits, links, common, seed)
    log_ratios = np.array([np.log(max(np.median(e_fit), 1e-12) / max(np.median(e_link), 1e-12))
                           for e_fit, e_link, _ in folds])
    informative = np.array([judged for _, _, judged in folds], dtype=bool)
    better = fit_predicts_better(log_ratios[informative], fit_aligner.config.select_confidence,
                                 fit_aligner.config.select_min_gain)
    chosen = fitted if better else link
    chosen.extras["select"] = {"chosen": "fit" if better else "link", "held_out_log_ratios": log_ratios.tolist(),
                               "judged": informative.tolist()}
    return chosen


def _frame_folds(fit_aligner: FrameFitter, pairs: Sequence[tuple[FrameView, FrameView]], fits: FrameMeasurements,
                 links: FrameMeasurements, frames: list[int], seed: int) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """``(fit distances, link distances, judged)`` on each frame left out (distances ``(n,)``), both
    models measured on the others. A degenerate training frame measured by the link itself is a tie
    that does not judge (``judged`` False: it determined nothing beyond the link); measured by the
    camera-constrained fit, it votes with that fit, whose terms the plane leaves free come from the
    frame's cameras."""
    threads = int(fit_aligner.config.fit_threads)
    trained = {}  # the folds with two or more training frames: their fits, all started at once
    for held in frames:
        train = [k for k in frames if k != held]
        if len(train) > 1:
            view_a, view_b = pairs[train[0]]
            trained[held] = start(partial(fit_aligner.fit,
                                          np.concatenate([fits.points[fits.frames.index(k)][0] for k in train]),
                                          np.concatenate([fits.points[fits.frames.index(k)][1] for k in train]),
                                          view_a, view_b, seed + 100 + held), threads)
    folds = []
    for held in frames:
        X_a, X_b = fits.points[fits.frames.index(held)]
        train = [k for k in frames if k != held]
        if len(train) == 1:  # the other frame's own measurements
            fitted = fits.alignments[fits.frames.index(train[0])]
        else:
            fitted = trained[held].result()
        at = [links.frames.index(k) for k in train]
        H_link = mean_camera_link([links.alignments[i] for i in at], [pairs[k] for k in train],
                                  [links.points[i] for i in at], fit_aligner.config.inlier_threshold,
                                  fit_aligner.config.weight_reference_frame).H
        tie = bool(fitted.extras.get("degenerate")) and is_camera_link(fitted)
        H_fit = H_link if tie else fitted.H
        folds.append((transfer_distances(H_fit, X_a, X_b), transfer_distances(H_link, X_a, X_b), not tie))
    return folds
