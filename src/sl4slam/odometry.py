"""The odometry measurement between consecutive submaps, with its fallback chain: the fit on the
shared frames' points, else the first usable shared frame's camera edge (its two cameras and depth
ratio, listed as a fallback), else the reason neither can be used (the submap then starts a new map
segment: ``sl4slam.pipeline``). The checks are ``sl4slam.edges``'s."""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from .backend.evidence import NoiseScale, link_scatter
from .alignment.settings import AlignmentConfig
from .edges import camera_problem, edge_problem
from .types import Aligner, Alignment, FrameView


def measure_odometry(pairs: Sequence[tuple[FrameView, FrameView]], aligner: Aligner, settings: AlignmentConfig,
                     seed: int, information: Callable[[Alignment], np.ndarray], generators: Callable[[], np.ndarray],
                     noise_scale: NoiseScale | None = None) -> Alignment | str:
    """The measurement ``H_prev_cur`` from the shared frames, or why there is none.

    Args:
        pairs: ``(previous submap's view, current submap's view)`` of every shared frame, in slot
            order; frames with implausible cameras (``camera_problem``) are left out.
        aligner: fits the usable pairs together (``Aligner.align_frames``) and makes the camera edge.
        settings: the edge checks' thresholds (``edge_problem``).
        seed: the fit's random seed.
        information: an edge's information matrix (``sl4slam.backend.evidence.edge_information``).
        generators: the graph group's tangent basis (``Backend.generators``), asked for when needed.
        noise_scale: told the scatter of a fit over several shared frames, when given.

    Returns:
        the fit; else the first usable pair's camera edge with ``fallback`` set; else the reason.
    """
    problems = [camera_problem(before) or camera_problem(after) for before, after in pairs]
    usable = [pair for pair, problem in zip(pairs, problems) if not problem]
    if not usable:
        return problems[0]
    before, after = usable[0]
    try:
        alignment = aligner.align_frames(usable, seed=seed)
        problem = edge_problem(alignment, settings)
    except ValueError as exc:
        problem = str(exc)
    if problem is None:
        if noise_scale is not None and len(alignment.extras.get("per_frame", ())) >= 2:
            noise_scale.add(link_scatter(alignment, alignment.extras["per_frame"], information, generators()))
        return alignment
    try:
        edge = aligner.camera_edge(before, after)
    except ValueError as exc:
        return f"{problem}; the camera edge failed too: {exc}"
    weak = edge_problem(edge, settings, fitted=False)
    if weak:
        return f"{problem}; the camera edge failed too: {weak}"
    edge.fallback = f"alignment failed ({problem}); used the shared frame's cameras and depth"
    return edge
