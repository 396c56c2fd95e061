"""Properties of a camera path and its frames: length, speed, rotation rate, revisits, keyframe rate.

A **revisit** is a return of the camera to an earlier pose after leaving it: within
``REVISIT_RADIUS_M`` metres and ``REVISIT_ANGLE_DEG`` degrees of that pose, after having been more
than twice as far (``2 * REVISIT_RADIUS_M`` metres away, or ``2 * REVISIT_ANGLE_DEG`` degrees
turned). It is counted against anchor poses taken along the path (a new anchor each time the
camera has moved half the radius or turned half the angle from the last one):

- ``returns``: the most times the camera comes back to any one anchor (0: it never comes back;
  a loop closed once: 1; three laps: 3);
- ``revisited``: the share of frames that lie near an anchor the camera had left (how much of the
  sequence can close a loop).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

REVISIT_RADIUS_M = 0.5
"""Distance (m) within which a pose revisits an earlier one."""
REVISIT_ANGLE_DEG = 30.0
"""Angle (degrees) within which a pose revisits an earlier one."""
LEAVE_FACTOR = 2.0
"""The camera has left a pose when it is this many times the radius away, or the angle turned."""


@dataclass(frozen=True)
class PathProperties:
    """What a camera path is like.

    Attributes:
        frames: poses on the path.
        seconds: time from the first pose to the last.
        length_m: distance travelled by the camera centre.
        speed_m_s: ``length_m / seconds``.
        rotation_deg_s: total rotation (sum of the angles between consecutive poses) per second.
        returns: most returns to one earlier pose (see the module docstring).
        revisited: share of frames that revisit an earlier pose, in [0, 1].
    """

    frames: int
    seconds: float
    length_m: float
    speed_m_s: float
    rotation_deg_s: float
    returns: int
    revisited: float


def rotation_angles_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angles (degrees) of ``R_a^T R_b`` for ``(..., 3, 3)`` rotations (broadcast)."""
    cosine = (np.sum(R_a * R_b, axis=(-2, -1)) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def _anchors(positions: np.ndarray, rotations: np.ndarray, radius: float, angle: float) -> list[int]:
    """Indices of anchor poses: the first, then each pose half the radius or half the angle from the last anchor."""
    anchors = [0]
    for index in range(1, len(positions)):
        last = anchors[-1]
        if (np.linalg.norm(positions[index] - positions[last]) > radius / 2.0
                or rotation_angles_deg(rotations[index], rotations[last]) > angle / 2.0):
            anchors.append(index)
    return anchors


def count_revisits(T_world_cam: np.ndarray, radius_m: float = REVISIT_RADIUS_M,
                   angle_deg: float = REVISIT_ANGLE_DEG) -> tuple[int, float]:
    """Returns and revisited share of a path (see the module docstring).

    Args:
        T_world_cam: ``(N, 4, 4)`` poses in order.
        radius_m, angle_deg: how near a pose must come to revisit another.

    Returns:
        ``(returns, revisited)``.
    """
    T = np.asarray(T_world_cam, np.float64)
    count = T.shape[0]
    if count < 2:
        return 0, 0.0
    positions, rotations = T[:, :3, 3], T[:, :3, :3]
    revisiting = np.zeros(count, bool)
    returns = 0
    for anchor in _anchors(positions, rotations, radius_m, angle_deg):
        distance = np.linalg.norm(positions[anchor + 1:] - positions[anchor], axis=1)
        turned = rotation_angles_deg(rotations[anchor + 1:], rotations[anchor][None])
        near = (distance < radius_m) & (turned < angle_deg)
        far = (distance > LEAVE_FACTOR * radius_m) | (turned > LEAVE_FACTOR * angle_deg)
        if not far.any():
            continue
        first_far = int(np.argmax(far))
        revisiting[anchor + 1 + first_far:] |= near[first_far:]
        labels = np.where(near, 1, np.where(far, 2, 0))
        labels = np.concatenate([[1], labels[labels > 0]])  # the anchor itself is near
        returns = max(returns, int(np.sum((labels[1:] == 1) & (labels[:-1] == 2))))
    return returns, float(revisiting.mean())


def path_properties(T_world_cam: np.ndarray, timestamps: np.ndarray) -> PathProperties:
    """Length, speed, rotation rate and revisits of a path.

    Args:
        T_world_cam: ``(N, 4, 4)`` poses in order.
        timestamps: ``(N,)`` seconds.
    """
    T = np.asarray(T_world_cam, np.float64)
    stamps = np.asarray(timestamps, np.float64)
    seconds = float(stamps[-1] - stamps[0]) if len(stamps) > 1 else 0.0
    length = float(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum())
    rotation = float(rotation_angles_deg(T[:-1, :3, :3], T[1:, :3, :3]).sum())
    returns, revisited = count_revisits(T)
    return PathProperties(frames=int(T.shape[0]), seconds=seconds, length_m=length,
                          speed_m_s=length / seconds if seconds > 0 else 0.0,
                          rotation_deg_s=rotation / seconds if seconds > 0 else 0.0,
                          returns=returns, revisited=revisited)


def count_keyframes(images: Iterable[np.ndarray], config=None) -> tuple[int, int]:
    """Run the keyframe selector (:class:`sl4slam.keyframes.KeyframeSelector`) over frames.

    Args:
        images: ``(H, W, 3)`` uint8 RGB frames in order.
        config: a :class:`sl4slam.keyframes.KeyframeConfig` (default: the library's).

    Returns:
        ``(frames, keyframes)``.
    """
    from sl4slam.keyframes import KeyframeSelector

    selector = KeyframeSelector(config)
    frames = keyframes = 0
    for image in images:
        frames += 1
        keyframes += selector.is_keyframe(image)
    return frames, keyframes


def gradient_energy(image: np.ndarray) -> float:
    """Mean squared intensity gradient (grey levels per pixel, squared) of an ``(H, W, 3)`` uint8
    image: how much texture it shows."""
    grey = image.astype(np.float64).mean(axis=2)
    return float(np.mean(np.diff(grey, axis=0) ** 2) + np.mean(np.diff(grey, axis=1) ** 2))
