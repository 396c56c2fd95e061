"""The π³ adapter against exact truth, and the π³ / Pi3X frontend end to end on the tiny models.

A hand-made pinhole scene (known K with its principal point at the grid centre, depth, cameras in an
arbitrary world frame) gives the local points and camera-to-world poses π³ would predict if it were
exact; the adapter must return the true depth, K and camera-from-first-camera extrinsics.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.frontend.pi3 import CAPABILITIES, Pi3Frontend
from sl4slam.models.pi3 import Pi3Config, build_pi3
from sl4slam.models.pi3.cameras import (
    confidence_from_logits,
    depth_from_local_points,
    extrinsics_from_poses,
    focal_from_local_points,
    grid_centre,
    intrinsics_from_local_points,
    probability_from_logits,
    to_model_intrinsics,
)
from sl4slam.models.pi3.model import Pi3X
from sl4slam.models.pi3.preprocess import ResizeTransform
from sl4slam.models.pi3.weights import load_state_dict_into
from sl4slam.types import Frame, Frontend, SubmapPrediction

HEIGHT, WIDTH, FRAMES = 42, 56, 4


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def pinhole_scene(seed: int = 0):
    """True ``K`` (S, 3, 3), depth (S, H, W), local points (S, H, W, 3) and camera-to-world poses
    (S, 4, 4) in a world frame that is none of the cameras'."""
    rng = np.random.default_rng(seed)
    centre = grid_centre(HEIGHT, WIDTH)
    K = np.tile(np.eye(3), (FRAMES, 1, 1))
    K[:, 0, 0] = rng.uniform(30, 90, FRAMES)
    K[:, 1, 1] = K[:, 0, 0] * rng.uniform(0.9, 1.1, FRAMES)
    K[:, :2, 2] = centre
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    depth = np.stack([2.0 + 0.5 * np.sin(u / 9.0 + i) + 0.3 * np.cos(v / 7.0) + 0.01 * u for i in range(FRAMES)])
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)
    rays = np.einsum("sij,hwj->shwi", np.linalg.inv(K), pixels)
    local_points = rays * depth[..., None]
    poses = np.tile(np.eye(4), (FRAMES, 1, 1))
    for i in range(FRAMES):
        poses[i, :3, :3] = _rotation(rng)
        poses[i, :3, 3] = rng.normal(size=3)
    return K, depth, local_points, poses


# ---- adapter ---------------------------------------------------------------------------------------

def test_adapter_recovers_the_true_cameras_and_depth():
    K, depth, local_points, poses = pinhole_scene()
    np.testing.assert_array_equal(depth_from_local_points(local_points), depth.astype(np.float32))
    weights = np.random.default_rng(1).uniform(0.1, 1.0, depth.shape)
    for w in (None, weights):
        np.testing.assert_allclose(intrinsics_from_local_points(local_points, w), K, rtol=1e-12, atol=1e-9)
    T_cam_submap = extrinsics_from_poses(poses)
    assert T_cam_submap.shape == (FRAMES, 3, 4) and T_cam_submap.dtype == np.float64
    np.testing.assert_allclose(T_cam_submap[0], np.eye(4)[:3], atol=1e-12)
    # truth: a point of camera 0 seen by camera i
    truth = np.linalg.inv(poses) @ poses[0]
    np.testing.assert_allclose(T_cam_submap, truth[:, :3], atol=1e-12)
    # every frame's points, moved into the submap frame, land where camera 0 sees them
    world = np.einsum("sij,shwj->shwi", poses[:, :3, :3], local_points) + poses[:, None, None, :3, 3]
    in_submap = np.einsum("ij,shwj->shwi", np.linalg.inv(poses[0])[:3, :3], world) + np.linalg.inv(poses[0])[:3, 3]
    back = np.einsum("sij,shwj->shwi", T_cam_submap[:, :, :3], in_submap) + T_cam_submap[:, None, None, :, 3]
    np.testing.assert_allclose(back, local_points, atol=1e-9)


def test_focal_fit_skips_unusable_pixels_and_says_when_undefined():
    K, _, local_points, _ = pinhole_scene()
    points = local_points[0].copy()
    points[:3, :4] = np.nan
    points[5, 5, 2] = -1.0  # behind the camera
    fx, fy = focal_from_local_points(points, K[0, :2, 2])
    np.testing.assert_allclose([fx, fy], [K[0, 0, 0], K[0, 1, 1]], rtol=1e-12)
    with pytest.raises(ValueError, match="undefined"):
        focal_from_local_points(np.full((4, 4, 3), np.nan), np.zeros(2))


def test_confidence_mapping():
    logits = np.array([-100.0, -3.0, 0.0, 2.5, 90.0, 200.0])
    confidence = confidence_from_logits(logits)
    assert confidence.dtype == np.float32 and np.all(confidence >= 1) and np.all(np.isfinite(confidence))
    assert np.all(np.diff(confidence) >= 0)  # same order as the logits
    probability = probability_from_logits(logits[1:4])
    np.testing.assert_allclose(confidence[1:4], 1.0 / (1.0 - probability), rtol=1e-6)


def test_known_intrinsics_reach_the_model_as_the_rays_of_our_pixels():
    """A K of the input frame, mapped onto the grid and into the authors' convention, gives the model
    at grid pixel (u, v) the ray of that pixel's centre under the grid's K."""
    transform = ResizeTransform((480, 640), (HEIGHT, WIDTH), WIDTH / 640, HEIGHT / 480)
    K = np.array([[520.0, 0.0, 318.0], [0.0, 515.0, 243.0], [0.0, 0.0, 1.0]])
    K_grid = transform.intrinsics_to_output(K)
    # a point seen at input pixel (u, v) is seen at the mapped grid position
    point = np.array([0.3, -0.2, 2.0])
    seen = (K @ point)[:2] / point[2]
    np.testing.assert_allclose((K_grid @ point)[:2] / point[2], transform.input_to_output(seen[None])[0])
    rays = Pi3X.rays_from_intrinsics(torch.tensor(to_model_intrinsics(K_grid)[None, None], dtype=torch.float32),
                                     HEIGHT, WIDTH)[0, 0].double().numpy()
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    expected = np.einsum("ij,hwj->hwi", np.linalg.inv(K_grid), np.stack([u, v, np.ones_like(u)], -1))[..., :2]
    np.testing.assert_allclose(rays, expected, atol=1e-5)


# ---- frontend ---------------------------------------------------------------------------------------

def _tiny_model(fixtures_dir, name):
    folder = fixtures_dir / name
    model = build_pi3(Pi3Config.from_dict(json.loads((folder / "config.json").read_text()))).eval()
    load_state_dict_into(model, load_file(str(folder / "state_dict.safetensors")))
    return model


def _frames(count=3, height=48, width=64, seed=0):
    rng = np.random.default_rng(seed)
    images = [np.clip(rng.normal(128, 60, (height, width, 3)), 0, 255).astype(np.uint8) for _ in range(count)]
    return [Frame(index=i, timestamp=float(i), rgb=image) for i, image in enumerate(images)]


@pytest.fixture(scope="module", params=["pi3", "pi3x"])
def frontend(request, fixtures_dir):
    frontend = Pi3Frontend(request.param, device="cpu", model=_tiny_model(fixtures_dir, f"{request.param}_tiny"))
    frontend.budget = 28 * 42  # a small grid keeps the test fast (the default is 255 000 pixels)
    return frontend


def test_frontend_returns_a_well_formed_submap(frontend):
    frames = _frames()
    prediction = frontend.reconstruct(frames, submap_id=0)
    assert isinstance(prediction, SubmapPrediction) and isinstance(frontend, Frontend)
    S, H, W = len(frames), 28, 42
    assert frontend.name == frontend.variant and frontend.requires_ground_truth is False
    assert prediction.depth.shape == (S, H, W) and prediction.depth.dtype == np.float32
    assert prediction.confidence.shape == (S, H, W) and prediction.confidence.dtype == np.float32
    assert np.all(prediction.confidence >= 1)
    assert prediction.T_cam_submap.shape == (S, 3, 4) and prediction.T_cam_submap.dtype == np.float64
    # the first camera relative to itself: identity up to the float32 rotation's own non-orthogonality
    np.testing.assert_allclose(prediction.T_cam_submap[0], np.eye(4)[:3], atol=1e-5)
    rotations = prediction.T_cam_submap[:, :, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.tile(np.eye(3), (S, 1, 1)), atol=1e-5)
    assert prediction.K.shape == (S, 3, 3) and prediction.K.dtype == np.float64
    np.testing.assert_allclose(prediction.K[:, :2, 2], np.tile([(W - 1) / 2, (H - 1) / 2], (S, 1)))
    np.testing.assert_allclose(prediction.principal_point, prediction.K[:, :2, 2])
    assert prediction.colors.shape == (S, H, W, 3) and prediction.colors.dtype == np.uint8
    np.testing.assert_array_equal(prediction.colors[1], frontend.grid_colors(frames[1]))
    for name in ("depth", "confidence", "T_cam_submap", "K"):
        assert np.all(np.isfinite(getattr(prediction, name))), name
    assert prediction.match_ratios is None
    assert [t.output_hw for t in frontend.last_transforms] == [(H, W)] * S


def test_known_intrinsics_condition_pi3x_only(frontend):
    frames = _frames(seed=1)
    K = np.tile(np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]]), (len(frames), 1, 1))
    plain = frontend.reconstruct(frames, 0)
    given = frontend.reconstruct(frames, 0, intrinsics=K)
    assert frontend.capabilities == CAPABILITIES[frontend.variant]
    assert frontend.capabilities.predicts_intrinsics is False
    if frontend.variant == "pi3":
        assert frontend.capabilities.accepts_intrinsics is False
        np.testing.assert_array_equal(given.depth, plain.depth)  # ignored
    else:
        assert frontend.capabilities.accepts_intrinsics is True
        assert not np.array_equal(given.depth, plain.depth)  # the model was conditioned
        with pytest.raises(ValueError, match="intrinsics must be"):
            frontend.reconstruct(frames, 0, intrinsics=K[:2])


def test_pi3x_is_given_the_grid_intrinsics_in_the_authors_convention(fixtures_dir, monkeypatch):
    frontend = Pi3Frontend("pi3x", device="cpu", model=_tiny_model(fixtures_dir, "pi3x_tiny"))
    frontend.budget = 28 * 42
    frames = _frames(count=2, height=60, width=80)
    K = np.tile(np.array([[70.0, 0.0, 39.0], [0.0, 72.0, 30.0], [0.0, 0.0, 1.0]]), (2, 1, 1))
    seen = {}
    forward = frontend.model.forward

    def spy(images, **kwargs):
        seen.update(kwargs)
        return forward(images, **kwargs)

    monkeypatch.setattr(frontend.model, "forward", spy)
    frontend.reconstruct(frames, 0, intrinsics=K)
    transform = frontend.last_transforms[0]
    expected = to_model_intrinsics(transform.intrinsics_to_output(K[0]))
    np.testing.assert_allclose(seen["intrinsics"][0, 0].numpy(), expected, rtol=1e-6)
    assert transform.output_hw == (28, 42) and transform.scale_x == 42 / 80


def test_memory_budget_refuses_what_cannot_fit(fixtures_dir):
    frontend = Pi3Frontend("pi3x", device="cpu", model=_tiny_model(fixtures_dir, "pi3x_tiny"), max_memory_gb=0.02)
    assert frontend.head_chunk(2, 28, 42) >= 1
    with pytest.raises(UserError, match="below the smallest budget any setting fits"):  # not even one frame at this size
        frontend.head_chunk(17, 434, 574)
    roomier = Pi3Frontend("pi3x", device="cpu", model=_tiny_model(fixtures_dir, "pi3x_tiny"), max_memory_gb=0.4)
    with pytest.raises(UserError, match="the largest submap that fits has"):
        roomier.head_chunk(400, 434, 574)


def test_bad_settings_and_missing_weights(tmp_path, monkeypatch):
    with pytest.raises(UserError, match="unknown π³ variant"):
        Pi3Frontend("pi4")
    with pytest.raises(UserError, match="unknown π³ dtype"):
        Pi3Frontend("pi3", device="cpu", dtype="int4")
    with pytest.raises(UserError, match="needs a Pi3X model"):
        Pi3Frontend("pi3x", device="cpu", model=build_pi3(Pi3Config(variant="pi3", encoder_depth=1, decoder_depth=2,
                                                                     head_decoder_depth=1), device="meta"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    for variant, repo in (("pi3", "yyfz233/Pi3"), ("pi3x", "yyfz233/Pi3X")):
        frontend = Pi3Frontend(variant, device="cpu")
        assert frontend.weights == repo
        with pytest.raises(MissingWeightsError, match=repo) as err:
            frontend.prepare()
        assert "\n" not in str(err.value)
