"""Keyframe selection by Lucas-Kanade disparity to the last keyframe (VGGT-SLAM, paper 4.1).

Shi-Tomasi corners are detected once on each keyframe and tracked into every following frame
with pyramidal Lucas-Kanade. A frame becomes the next keyframe when the mean displacement of
the successfully tracked corners exceeds ``KeyframeConfig.tau_disparity`` pixels, or when fewer
than ``KeyframeConfig.min_tracked`` corners could be tracked (texture-less view, fast motion,
scene change: the reference is useless, so start a new one).

Threshold: the paper's 25 px by default; the authors' code and TUM script use 50 px (pass
``KeyframeConfig(tau_disparity=50)`` to match them; decision: docs/decisions/keyframe-threshold.md).

Cost: one grey conversion and one ``cv2.calcOpticalFlowPyrLK`` call per frame, plus one
``cv2.goodFeaturesToTrack`` per keyframe only. OpenCV's Python binding does not accept a prebuilt
pyramid for the previous image, so the keyframe pyramid is rebuilt per call.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from .errors import UserError
from .section import Section, setting


@dataclass
class KeyframeConfig(Section):
    """Keyframe selection by Lucas-Kanade disparity (paper 4.1)."""

    section: ClassVar[str] = "keyframes"
    builds: ClassVar[str] = "sl4slam.keyframes:KeyframeSelector"

    tau_disparity: float = setting(25.0, check=lambda v: v > 0, allowed="a positive number of pixels")
    """Mean tracked displacement (px) that makes a keyframe. Paper: 25; reference code: 50."""
    max_corners: int = setting(1000, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """Shi-Tomasi corners detected on the last keyframe (reference code)."""
    corner_quality: float = setting(0.01, advanced=True, check=lambda v: 0 < v < 1, allowed="in (0, 1)")
    """Shi-Tomasi quality level (reference code)."""
    corner_min_distance: float = setting(8.0, advanced=True, check=lambda v: v >= 0, allowed=">= 0 px")
    """Minimum distance between corners in px (reference code)."""
    lk_window: int = setting(21, advanced=True, check=lambda v: v >= 3, allowed="at least 3 px")
    """Lucas-Kanade window size in px (OpenCV default, used by the reference code)."""
    lk_levels: int = setting(3, advanced=True, check=lambda v: v >= 0, allowed=">= 0")
    """Lucas-Kanade pyramid levels above the full image (OpenCV's maxLevel; reference code: 3)."""
    min_tracked: int = setting(10, advanced=True, check=lambda v: v >= 1, allowed="at least 1")
    """A frame with fewer successfully tracked corners is always a keyframe."""


def rgb_to_grey(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB -> ``(H, W)`` uint8 grey; raises ``UserError`` on other inputs."""
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        shape = getattr(rgb, "shape", None)
        dtype = getattr(rgb, "dtype", type(rgb).__name__)
        raise UserError(f"keyframe selection needs an (H, W, 3) uint8 RGB image, got shape {shape} dtype {dtype}")
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


class KeyframeSelector:
    """Stateful keyframe decision for a stream of frames.

    Call ``is_keyframe`` once per input frame, in order. The first frame is always a keyframe;
    every keyframe becomes the reference the following frames are tracked against.

    Attributes:
        last_disparity: mean displacement (px) of the tracked corners for the latest frame;
            ``0.0`` for the first frame, ``nan`` when no corner tracked.
        last_tracked: number of corners tracked successfully into the latest frame (for the
            first frame: the number of corners detected on it).
        num_keyframes: keyframes selected so far.
        reference_corners: ``(N, 1, 2)`` float32 pixel coordinates (x, y) of the Shi-Tomasi
            corners on the current reference keyframe (``N`` may be 0).
    """

    def __init__(self, config: KeyframeConfig | None = None) -> None:
        self.config = config if config is not None else KeyframeConfig()
        if self.config.lk_window < 3 or self.config.lk_levels < 0 or self.config.max_corners < 1:
            raise UserError(
                "keyframe settings need lk_window >= 3, lk_levels >= 0 and max_corners >= 1; "
                f"got {self.config.lk_window}, {self.config.lk_levels}, {self.config.max_corners}"
            )
        self._reference_grey: np.ndarray | None = None
        self.reference_corners = np.zeros((0, 1, 2), np.float32)
        self.last_disparity = 0.0
        self.last_tracked = 0
        self.num_keyframes = 0

    def reset(self) -> None:
        """Forget the reference keyframe: the next frame is a keyframe again."""
        self._reference_grey = None
        self.reference_corners = np.zeros((0, 1, 2), np.float32)
        self.last_disparity = 0.0
        self.last_tracked = 0
        self.num_keyframes = 0

    def _set_reference(self, grey: np.ndarray) -> None:
        corners = cv2.goodFeaturesToTrack(
            grey,
            maxCorners=int(self.config.max_corners),
            qualityLevel=float(self.config.corner_quality),
            minDistance=float(self.config.corner_min_distance),
        )
        self._reference_grey = grey
        self.reference_corners = (
            np.zeros((0, 1, 2), np.float32) if corners is None else corners.astype(np.float32, copy=False)
        )
        self.num_keyframes += 1

    def track(self, grey: np.ndarray) -> tuple[float, int]:
        """Track the reference corners into ``grey`` (``(H, W)`` uint8) without changing state.

        Returns:
            ``(mean displacement in px, number of tracked corners)``; the displacement is
            ``nan`` when nothing tracked.
        """
        if self._reference_grey is None:
            raise RuntimeError("track() needs a reference keyframe; call is_keyframe() first")
        if grey.shape != self._reference_grey.shape:
            raise UserError(
                f"frame size {grey.shape[1]}x{grey.shape[0]} differs from the keyframe's "
                f"{self._reference_grey.shape[1]}x{self._reference_grey.shape[0]}; resize all frames to one size"
            )
        if len(self.reference_corners) == 0:
            return float("nan"), 0
        window = int(self.config.lk_window)
        tracked, status, _error = cv2.calcOpticalFlowPyrLK(
            self._reference_grey,
            grey,
            self.reference_corners,
            None,
            winSize=(window, window),
            # OpenCV's maxLevel: index of the coarsest level, so lk_levels + 1 images in all.
            maxLevel=int(self.config.lk_levels),
        )
        ok = status.reshape(-1).astype(bool)
        count = int(ok.sum())
        if count == 0:
            return float("nan"), 0
        displacement = np.linalg.norm((tracked - self.reference_corners).reshape(-1, 2)[ok], axis=1)
        return float(displacement.mean()), count

    def is_keyframe(self, rgb: np.ndarray) -> bool:
        """Decide whether ``rgb`` (``(H, W, 3)`` uint8 RGB) is a keyframe; if so it becomes the reference.

        A keyframe when: it is the first frame, fewer than ``min_tracked`` reference corners
        track into it, or their mean displacement exceeds ``tau_disparity`` px.
        """
        grey = rgb_to_grey(rgb)
        if self._reference_grey is None:
            self._set_reference(grey)
            self.last_disparity = 0.0
            self.last_tracked = len(self.reference_corners)
            return True
        disparity, tracked = self.track(grey)
        self.last_disparity = disparity
        self.last_tracked = tracked
        keyframe = tracked < self.config.min_tracked or disparity > self.config.tau_disparity
        if keyframe:
            self._set_reference(grey)
        return bool(keyframe)
