"""What the source knows, applied to every submap: a known calibration and a depth sensor's scale.

- **Known intrinsics** (``--intrinsics``, ``sl4slam.intrinsics``): the source's ``K``, moved onto
  the frontend's grid by the prediction's ``image_to_grid``, replaces the model's own; each
  frame's points are then rebuilt along the known rays from the model's depth. A model that takes
  a calibration as input (``FrontendCapabilities.accepts_intrinsics``) is also given it, unless
  ``--no-intrinsics-to-model``. The model's focal over the known one is recorded per frame; a
  median outside ``FOCAL_RATIO_WARNING`` is warned about (a wrong calibration file).
- **Sensor scale** (``--metric-depth sensor``, ``sl4slam.sensor_scale``): each submap is scaled
  to metres; a submap without enough sensor depth keeps its neighbour's scale, counted.

The pipeline calls :meth:`SourceKnowledge.apply` on every accepted prediction, before its points
are made; :meth:`summary` and :meth:`notes` go into the run's summary. :func:`source_problem` says
why a run cannot use a source at all (checked before any frame is read).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Sequence

import numpy as np

from .io.settings import SourceConfig
from .errors import UserError
from .intrinsics import FOCAL_RATIO_WARNING, KnownIntrinsics, focal_ratios, from_source, on_grid
from .sensor_scale import scaled, sensor_scale
from .submap import confidence_mask
from .types import Frame, FrameSource, Frontend, FrontendCapabilities, SubmapPrediction

log = logging.getLogger("sl4slam.pipeline")


def source_problem(source: FrameSource, capabilities: FrontendCapabilities, frontend_name: str,
                   settings: SourceConfig | None = None, workers: int = 1, ray_address: str = "") -> str | None:
    """Why a run cannot use ``source`` with this frontend and these ``[source]`` settings (too few
    frames, no ground truth for a frontend that reads it, no depth images for the sensor's scale,
    model workers with a live camera), or ``None``; checked before any frame is read."""
    if getattr(source, "live", False) and (workers > 1 or ray_address):
        what = f"--workers {workers}" if workers > 1 else "--ray-address"
        return (f"{what} runs the model's windows ahead of the graph, which needs a file source; {source.name} is "
                f"a live camera (it keeps one model in this process): drop {what}, or record the stream to a file")
    if len(source) < 2:
        return f"{source.name}: {len(source)} frame(s) found; SLAM needs at least 2 frames"
    if capabilities.needs_ground_truth and not source.has_ground_truth:
        return (f"{source.name} has no depth and ground-truth poses, which the {frontend_name} frontend needs (an RGB-D "
                "sequence: TUM, 7-Scenes or the synthetic world); use a model (--model vggt)")
    if settings is not None and settings.metric_depth == "sensor" and not source.has_ground_truth:
        return (f"--metric-depth sensor needs depth images, which {source.name} has not (an RGB-D sequence: TUM, "
                "7-Scenes); use --metric-depth off")
    return None


class SourceKnowledge:
    """The known intrinsics and sensor scale of one run (see the module docstring).

    Args:
        resolved: the run's resolved config (``sl4slam.resolve.ResolvedConfig``: its intrinsics, and
            the ``source`` and ``submap`` sections).
        frontend: the run's frontend (its name and capabilities).
        source: the frame source, which says what it knows (``None``: nothing known yet).
    """

    def __init__(self, resolved, frontend: Frontend, source: FrameSource | None = None) -> None:
        self.config = resolved.config
        self.frontend = frontend
        self.intrinsics: KnownIntrinsics | None = (
            from_source(source, resolved.intrinsics, resolved.intrinsics_from_source) if source is not None else None)
        self.focal_ratios: list[float] = []  # the model's focal over the known one, per frame
        self.scales_measured: list[float] = []
        self.scales_kept = 0  # submaps that kept their neighbour's scale
        self._last_scale = 1.0

    @property
    def model_takes_intrinsics(self) -> bool:
        """The known intrinsics go to the model too (one that accepts them, unless switched off)."""
        return (self.intrinsics is not None and self.frontend.capabilities.accepts_intrinsics
                and self.config.source.intrinsics_to_model)

    def model_intrinsics(self, num_frames: int) -> np.ndarray | None:
        """``(S, 3, 3)`` known K of each input frame for a model that takes it, else ``None``."""
        return np.repeat(self.intrinsics.K[None], num_frames, axis=0) if self.model_takes_intrinsics else None

    def apply(self, frames: Sequence[Frame], prediction: SubmapPrediction) -> SubmapPrediction:
        """``prediction`` of ``frames`` with the known K in place of the model's and the sensor's scale."""
        if self.intrinsics is not None:
            prediction = self._with_known_intrinsics(frames, prediction)
        if self.config.source.metric_depth == "sensor":
            mask = confidence_mask(prediction.confidence, prediction.depth, self.config.submap.tau_conf)
            scale, _ = sensor_scale(list(frames), prediction, mask)
            if scale is None:
                self.scales_kept += 1
                scale = self._last_scale
            else:
                self.scales_measured.append(scale)
                self._last_scale = scale
            prediction = scaled(prediction, scale)
        return prediction

    def _with_known_intrinsics(self, frames: Sequence[Frame], prediction: SubmapPrediction) -> SubmapPrediction:
        if prediction.image_to_grid is None and prediction.depth.shape[1:] != frames[0].rgb.shape[:2]:
            raise UserError(f"the {self.frontend.name} frontend does not say how its grid maps the input frames; "
                            "--intrinsics cannot be used with it")
        A = prediction.image_to_grid if prediction.image_to_grid is not None else np.eye(3)[None].repeat(len(frames), 0)
        K = on_grid(self.intrinsics.K, A)
        ratios = focal_ratios(np.asarray(prediction.K, np.float64), K)
        ratios = ratios[np.isfinite(ratios)]  # a frame without a positive model focal has none to compare
        if len(ratios) and not self.focal_ratios and not FOCAL_RATIO_WARNING[0] <= float(np.median(ratios)) <= FOCAL_RATIO_WARNING[1]:
            log.warning("the model's focal length is %.2f times the given intrinsics' (%s) in the first submap: "
                        "check that they are for this camera and resolution", float(np.median(ratios)),
                        self.intrinsics.origin)
        self.focal_ratios.extend(ratios.tolist())
        return dataclasses.replace(prediction, K=K)

    def summary(self) -> dict:
        """What the known intrinsics and the sensor's scale did, for the run's summary."""
        out: dict = {}
        if self.intrinsics is not None:
            ratios = np.asarray(self.focal_ratios)
            out["intrinsics"] = {
                "K": [round(v, 4) for v in self.intrinsics.values()], "origin": self.intrinsics.origin,
                "note": self.intrinsics.note, "model_given_it": self.model_takes_intrinsics,
                "model_focal_ratio": {"median": round(float(np.median(ratios)), 4), "min": round(float(ratios.min()), 4),
                                      "max": round(float(ratios.max()), 4)} if len(ratios) else None}
        if self.config.source.metric_depth == "sensor":
            measured = self.scales_measured
            out["metric_depth"] = {"submaps_scaled": len(measured), "kept_neighbour_scale": self.scales_kept,
                                   "scale_median": round(float(np.median(measured)), 5) if measured else None}
        return out

    def notes(self) -> list[str]:
        """A warning when the model's focal disagrees wildly with the known one (a wrong file?)."""
        if self.intrinsics is None or not self.focal_ratios:
            return []
        median = float(np.median(self.focal_ratios))
        low, high = FOCAL_RATIO_WARNING
        if low <= median <= high:
            return []
        return [f"the model's focal length is {median:.2f} times the given one ({self.intrinsics.origin}); "
                "the given intrinsics were used: check that they are for this camera and resolution"]
