"""Keyframe selection by Lucas-Kanade disparity (paper 4.1)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sl4slam.config import KeyframeConfig
from sl4slam.errors import UserError
from sl4slam.keyframes import KeyframeSelector

HEIGHT, WIDTH = 480, 640
MARGIN = 60


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """Seeded random RGB texture, larger than a frame so shifted crops are exact translations.

    Noise blurred at several scales, so that every pyramid level keeps structure to track (like
    natural images); single-scale fine noise makes coarse levels featureless and LK fails beyond
    ~20 px.
    """
    rng = np.random.default_rng(7)
    shape = (HEIGHT + 2 * MARGIN, WIDTH + 2 * MARGIN, 3)
    texture = np.zeros(shape, np.float32)
    for sigma in (1.5, 4.0, 10.0, 24.0):
        layer = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
        texture += layer / layer.std()
    return np.clip(128 + 25 * texture, 0, 255).astype(np.uint8)


def view(texture: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """The frame whose content is the reference frame's moved by (+dx, +dy) px."""
    return np.ascontiguousarray(texture[MARGIN - dy : MARGIN - dy + HEIGHT, MARGIN - dx : MARGIN - dx + WIDTH])


def test_first_frame_is_keyframe_and_corners_follow_config(texture):
    selector = KeyframeSelector(KeyframeConfig(max_corners=300))
    assert selector.is_keyframe(view(texture, 0, 0))
    assert selector.num_keyframes == 1
    assert 100 <= len(selector.reference_corners) <= 300
    assert selector.reference_corners.dtype == np.float32
    assert selector.last_tracked == len(selector.reference_corners)
    # Corners respect the minimum distance.
    corners = selector.reference_corners.reshape(-1, 2)
    gaps = np.linalg.norm(corners[:, None] - corners[None], axis=-1) + np.eye(len(corners)) * 1e9
    assert gaps.min() >= KeyframeConfig().corner_min_distance - 1e-3


@pytest.mark.parametrize(("dx", "dy"), [(12, 5), (-18, 9), (0, 20)])
def test_shift_below_threshold_is_not_keyframe(texture, dx, dy):
    selector = KeyframeSelector(KeyframeConfig(tau_disparity=25.0))
    assert selector.is_keyframe(view(texture, 0, 0))
    assert not selector.is_keyframe(view(texture, dx, dy))
    assert selector.last_disparity == pytest.approx(np.hypot(dx, dy), abs=0.5)
    assert selector.last_tracked >= 0.9 * len(selector.reference_corners)
    assert selector.num_keyframes == 1


@pytest.mark.parametrize(("dx", "dy"), [(26, 0), (-20, 20), (10, -30)])
def test_shift_above_threshold_is_keyframe(texture, dx, dy):
    selector = KeyframeSelector(KeyframeConfig(tau_disparity=25.0))
    assert selector.is_keyframe(view(texture, 0, 0))
    assert selector.is_keyframe(view(texture, dx, dy))
    assert selector.last_disparity == pytest.approx(np.hypot(dx, dy), abs=0.5)
    assert selector.num_keyframes == 2


def test_keyframe_becomes_the_reference(texture):
    selector = KeyframeSelector(KeyframeConfig(tau_disparity=25.0))
    assert selector.is_keyframe(view(texture, 0, 0))
    assert not selector.is_keyframe(view(texture, 15, 0))  # 15 px from the first keyframe
    assert selector.is_keyframe(view(texture, 30, 0))  # 30 px: new keyframe
    # 45 px from the first keyframe but 15 px from the new reference.
    assert not selector.is_keyframe(view(texture, 45, 0))
    assert selector.last_disparity == pytest.approx(15.0, abs=0.5)


def test_threshold_is_configurable(texture):
    selector = KeyframeSelector(KeyframeConfig(tau_disparity=50.0))
    assert selector.is_keyframe(view(texture, 0, 0))
    assert not selector.is_keyframe(view(texture, 30, 0))


def test_featureless_frames_are_keyframes(texture):
    blank = np.full((HEIGHT, WIDTH, 3), 128, np.uint8)
    selector = KeyframeSelector()
    assert selector.is_keyframe(blank)
    assert len(selector.reference_corners) == 0
    assert selector.is_keyframe(blank)  # nothing to track: too few tracked
    assert selector.last_tracked == 0
    assert np.isnan(selector.last_disparity)
    # A textured frame after a blank keyframe is a keyframe too, and then the reference.
    assert selector.is_keyframe(view(texture, 0, 0))
    assert not selector.is_keyframe(view(texture, 3, 0))


def test_few_corners_are_keyframe_even_without_motion():
    frame = np.full((HEIGHT, WIDTH, 3), 40, np.uint8)
    # Five bright squares: at most 4 corners each, 20 corners in all.
    for column in range(5):
        frame[200:240, 60 + 110 * column : 100 + 110 * column] = 220
    assert KeyframeSelector().is_keyframe(frame)
    selector = KeyframeSelector(KeyframeConfig(min_tracked=10))
    selector.is_keyframe(frame)
    assert 10 <= len(selector.reference_corners) <= 20
    assert not selector.is_keyframe(frame.copy())
    assert selector.last_disparity == pytest.approx(0.0, abs=0.05)
    selector = KeyframeSelector(KeyframeConfig(min_tracked=50))
    selector.is_keyframe(frame)
    assert selector.is_keyframe(frame.copy())  # every corner tracks, but fewer than 50


def test_bad_input_is_a_user_error(texture):
    selector = KeyframeSelector()
    with pytest.raises(UserError):
        selector.is_keyframe(np.zeros((HEIGHT, WIDTH), np.uint8))
    with pytest.raises(UserError):
        selector.is_keyframe(np.zeros((HEIGHT, WIDTH, 3), np.float32))
    selector.is_keyframe(view(texture, 0, 0))
    with pytest.raises(UserError):
        selector.is_keyframe(np.zeros((240, 320, 3), np.uint8))


def _tum_frames(shared_dir) -> list[np.ndarray]:
    root = shared_dir / "data/tum_rgbd_fr1_xyz_first37"
    lines = [line.split() for line in (root / "rgb.txt").read_text().splitlines()]
    paths = [root / fields[1] for fields in lines if fields and not fields[0].startswith("#")]
    return [cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB) for path in paths]


def test_tum_excerpt_keyframe_count(shared_dir):
    frames = _tum_frames(shared_dir)
    assert len(frames) == 37
    counts = {}
    for tau in (25.0, 50.0):
        selector = KeyframeSelector(KeyframeConfig(tau_disparity=tau))
        keyframes = [index for index, rgb in enumerate(frames) if selector.is_keyframe(rgb)]
        assert keyframes[0] == 0
        assert selector.num_keyframes == len(keyframes)
        counts[tau] = len(keyframes)
    # ~1.2 s of hand-held motion (0.38 m, 10 deg): a handful of keyframes, fewer at 50 px.
    assert 3 <= counts[25.0] <= 12
    assert 2 <= counts[50.0] < counts[25.0]
