"""One link between two submaps from every frame they share (``SubmapConfig.overlap``).

Consecutive submaps may share several frames, each reconstructed in both. Each frame alone gives a
measurement of ``H_a_b`` (``Aligner.align``); together they give one link, robust to one frame whose
depth is bad in one of its reconstructions:

- a model fitted to points (15-DOF SL(4), Sim(3) points) is fitted once to every shared frame's
  points together, in RANSAC: each frame's cameras and depth constrain the one fit, one frame's
  depth errors average out, and a frame whose points disagree with the others' is outvoted as
  outliers (with two frames, RANSAC keeps the one more of whose points agree);
- a link read from the cameras (calibration-and-scale, shared-frame Sim(3)) is the mean, in the
  group's tangent, of the frames' own links, so per-frame camera errors average out; the scale,
  the one thing such a link reads from the depth, is the median depth ratio of every frame's
  pixels pooled, so a frame with wrongly scaled depth is outvoted by the others' pixels.

The combined ``Alignment`` covers every usable frame's points; ``extras["shared_frames"]`` says how
many frames it stands on, which the edge's evidence (``sl4slam.backend.evidence``) counts as
independent witnesses, and ``extras["left_out"]`` why a frame could not be used (too few
confident pixels, unusable cameras).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Callable, Sequence

import numpy as np

from ..geometry import matrix_exp, matrix_log
from ..types import Alignment, FrameView
from .common import FrameFitter, make_alignment
from .parallel import Pending, start
from .ransac import transfer_errors

def tangent_mean(H: Sequence[np.ndarray], reference: np.ndarray, weights: Sequence[float] | None = None) -> np.ndarray:
    """The (weighted) mean of 4x4 transforms ``H`` in the tangent at ``reference``:
    ``reference exp(sum_k w_k log(reference^-1 H_k) / sum_k w_k)`` (Sim(3) stays Sim(3), SL(4) stays SL(4)).

    Args:
        H: transforms of one group, close to each other (measurements of one link).
        reference: ``(4, 4)`` one of them (the consensus winner).
        weights: ``(len(H),)`` positive weights (``None``: equal).
    """
    inverse = np.linalg.inv(reference)
    steps = matrix_log(inverse @ np.asarray(H, dtype=np.float64))
    return reference @ matrix_exp(np.average(steps, axis=0, weights=weights))


def is_reference_view(view: FrameView) -> bool:
    """Whether the frame is its submap's reference: its camera is the submap frame (``[I | 0]``,
    VGGT's first camera by construction), so its pose there carries no error of its own."""
    return bool(np.allclose(np.asarray(view.T_cam_submap, dtype=np.float64)[:3], np.eye(4)[:3], atol=1e-9))


def pose_error_weights(pairs: Sequence[tuple[FrameView, FrameView]]) -> np.ndarray:
    """``(N,)`` inverse-variance weights of the shared frames' camera links: a frame's link carries
    the pose error the model made for it in each submap, none where it is that submap's reference
    (:func:`is_reference_view`). With errors of one size per frame and submap, independent between
    frames (``sl4slam.frontend.simulated`` argues this for VGGT), a link's variance counts the
    submaps in which its frame is not the reference; a frame that is the reference in both is exact
    in pose, and the others get no weight beside it."""
    counts = np.array([(not is_reference_view(a)) + (not is_reference_view(b)) for a, b in pairs], dtype=np.float64)
    if (counts == 0).any():
        return (counts == 0).astype(np.float64)
    return 1.0 / counts


@dataclass
class FrameMeasurements:
    """Each shared frame measured alone.

    Attributes:
        frames: positions (in the caller's ``pairs``) of the frames that could be measured.
        alignments: their own measurements; points: their ``(X_a, X_b)`` shared confident points.
        problems: why the other frames could not be measured.
        joint: the fit on every measured frame's points together, started beside the frames' own
            fits (``measure_frames(..., joint=True)``; ``sl4slam.alignment.parallel``); None when not
            asked for, or when a frame whose points were gathered could not be measured.
    """

    frames: list[int]
    alignments: list[Alignment]
    points: list[tuple[np.ndarray, np.ndarray]]
    problems: list[str]
    joint: Pending[Alignment] | None = None


def measure_frames(aligner: FrameFitter, pairs: Sequence[tuple[FrameView, FrameView]], seed: int,
                   same_points: FrameMeasurements | None = None, joint: bool = False) -> FrameMeasurements:
    """Every shared frame measured alone by ``aligner`` (frame ``k`` with seed ``seed + k``);
    ``same_points``: another aligner's measurements of the same frames with the same pixel
    selection, whose points are taken as they are instead of being gathered again.

    The frames' fits run at once on ``aligner.config.fit_threads`` threads (the same results as one
    after another: ``sl4slam.alignment.parallel``). With ``joint`` (and a model fitted to points,
    two or more frames), the fit of every frame's points together that :func:`link_from_shared_frames`
    makes of them is started beside them (``FrameMeasurements.joint``).
    """
    measured = FrameMeasurements([], [], [], [])
    known = {} if same_points is None else dict(zip(same_points.frames, same_points.points))
    threads = int(aligner.config.fit_threads)
    gathered: list[tuple[np.ndarray, np.ndarray] | ValueError] = []
    for k, (view_a, view_b) in enumerate(pairs):
        try:
            gathered.append(known[k] if k in known else aligner.pairs(view_a, view_b))
        except ValueError as exc:
            gathered.append(exc)
    usable = [k for k, points in enumerate(gathered) if not isinstance(points, ValueError)]
    together = None
    if joint and aligner.fits_points and len(usable) > 1:  # the longest fit, so started first
        together = start(_fit_together(aligner, pairs, usable, [gathered[k] for k in usable], seed), threads)
    own = {k: start(partial(aligner.fit, *gathered[k], *pairs[k], seed + k), threads) for k in usable}
    for k, points in enumerate(gathered):
        problem = points if isinstance(points, ValueError) else None
        if problem is None:
            try:
                alignment = own[k].result()
            except ValueError as exc:
                problem = exc
        if problem is not None:
            measured.problems.append(f"frame {k}: {problem}")
            continue
        measured.frames.append(k)
        measured.alignments.append(alignment)
        measured.points.append(points)
    if not measured.frames:
        raise ValueError("no shared frame can be aligned (" + "; ".join(measured.problems) + ")")
    if measured.frames == usable:  # else the joint fit stood on a frame left out
        measured.joint = together
    return measured


def _fit_together(aligner: FrameFitter, pairs: Sequence[tuple[FrameView, FrameView]], frames: list[int],
                  points: list[tuple[np.ndarray, np.ndarray]], seed: int) -> Callable[[], Alignment]:
    """The fit of the ``frames``' ``points`` together (the first frame's views give the cameras), not
    yet run."""
    first = pairs[frames[0]]
    return partial(aligner.fit, np.concatenate([p[0] for p in points]), np.concatenate([p[1] for p in points]),
                   first[0], first[1], seed)


def link_from_shared_frames(aligner: FrameFitter, pairs: Sequence[tuple[FrameView, FrameView]], seed: int,
                            measured: FrameMeasurements | None = None) -> Alignment:
    """The link ``X_a ~ H X_b`` from every shared frame (module doc).

    Args:
        aligner: the run's aligner (its model measures each frame, and fits the points together
            when it fits points).
        pairs: ``(view in a, view in b)`` of each shared frame, oldest first.
        seed: seed of the fits (frame ``k`` uses ``seed + k``, the joint fit ``seed``).
        measured: the frames already measured by this aligner (:func:`measure_frames`).

    Raises:
        ValueError: no shared frame can be aligned (each frame's reason, joined).
    """
    if len(pairs) == 1 and measured is None:
        return aligner.align(pairs[0][0], pairs[0][1], seed)
    measured = measured or measure_frames(aligner, pairs, seed, joint=True)
    own, points = measured.alignments, measured.points
    if len(own) == 1:
        link = own[0]
    elif aligner.fits_points and measured.joint is not None:  # started beside the frames' own fits
        link = measured.joint.result()
    elif aligner.fits_points:
        link = _fit_together(aligner, pairs, measured.frames, points, seed)()
    else:
        link = mean_camera_link(own, [pairs[k] for k in measured.frames], points, aligner.config.inlier_threshold,
                                aligner.config.weight_reference_frame)
    link.extras["shared_frames"] = len(own)
    link.extras["frames_used"] = list(measured.frames)
    link.extras["per_frame"] = list(own)  # each frame's own link: their scatter calibrates the loop gate
    if measured.problems:
        link.extras["left_out"] = list(measured.problems)
    return link


def pooled_scale(views_a: Sequence[FrameView], views_b: Sequence[FrameView],
                 points: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    """Median ratio ``z_a / z_b`` of every frame's point depths (each in its own camera in each
    submap), all frames' pixels pooled."""
    ratios = []
    for view_a, view_b, (X_a, X_b) in zip(views_a, views_b, points):
        z_a = X_a @ view_a.T_cam_submap[2, :3] + view_a.T_cam_submap[2, 3]
        z_b = X_b @ view_b.T_cam_submap[2, :3] + view_b.T_cam_submap[2, 3]
        usable = (z_a > 0) & (z_b > 0)
        ratios.append(z_a[usable] / z_b[usable])
    return float(np.median(np.concatenate(ratios)))


def rescaled_link(link: Alignment, view_a: FrameView, scale: float) -> np.ndarray:
    """A camera link ``T_a_cam [[s A, 0], [0, 1]] T_cam_b`` with its scale ``s`` replaced by ``scale``."""
    T = np.asarray(view_a.T_cam_submap, dtype=np.float64)
    T = np.vstack([T[:3], [0.0, 0.0, 0.0, 1.0]])
    S = np.diag([scale / link.extras["scale"]] * 3 + [1.0])
    return np.linalg.inv(T) @ S @ T @ link.H


def mean_camera_link(links: Sequence[Alignment], pairs: Sequence[tuple[FrameView, FrameView]],
                     points: Sequence[tuple[np.ndarray, np.ndarray]], threshold: float,
                     weighted: bool = True) -> Alignment:
    """The camera links of several frames as one: each with the pooled scale (:func:`pooled_scale`),
    then their tangent mean, weighted by how many pose errors each carries (:func:`pose_error_weights`:
    the new submap's reference frame counts twice); scored (not fitted) on every frame's points.

    Args:
        links: each frame's own camera link (``extras["scale"]`` its scale).
        pairs: the frames' ``(view in a, view in b)``; points: their ``(X_a, X_b)`` shared points.
        threshold: inlier distance for the reported inlier ratio.
        weighted: weigh the links by :func:`pose_error_weights` (else equally).
    """
    scale = pooled_scale([a for a, _ in pairs], [b for _, b in pairs], points)
    H = tangent_mean([rescaled_link(link, view_a, scale) for link, (view_a, _) in zip(links, pairs)], links[0].H,
                     pose_error_weights(pairs) if weighted else None)
    X_a = np.concatenate([p[0] for p in points])
    X_b = np.concatenate([p[1] for p in points])
    r2, in_front = transfer_errors(H[None], X_a, X_b)
    fallbacks = [a.fallback for a in links if a.fallback]
    return make_alignment(H, X_a, X_b, np.ones(len(X_a), dtype=bool), (r2[0] < threshold**2) & in_front[0], r2[0],
                          links[0].model, fallback=fallbacks[0] if fallbacks else None,
                          extras=dict(links[0].extras, scale=scale), fitted=False)
