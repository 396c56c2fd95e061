"""The Depth Anything 3 frontend: the adapter against exact truth, the ray fit, and the frontend on the
tiny fixture model (``tests/fixtures/da3_tiny``: the authors' outputs of the same frames)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from reference_outputs import assert_matches_reference
from torch_threads import one_thread

from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.frontend.da3 import DA3Frontend
from sl4slam.models.da3 import (
    DA3Config,
    DepthAnything3,
    load_state_dict_into,
    read_checkpoint,
    save_checkpoint,
)
from sl4slam.models.da3.cameras import invert_rigid, relative_to_first, submap_arrays
from sl4slam.models.da3.rays import extrinsics_intrinsics_from_rays
from sl4slam.types import Frame, Frontend, FrontendCapabilities, SubmapPrediction


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


def pose(axis, angle, centre) -> np.ndarray:
    """``T_world_cam`` (4x4) with camera centre ``centre``."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rotation(axis, angle), centre
    return T


# A hand-made pinhole scene: four cameras looking at the plane z = 6 - 0.2 x (world frame).
HEIGHT, WIDTH = 42, 56
K_TRUE = np.array([[50.0, 0.0, 28.0], [0.0, 48.0, 21.0], [0.0, 0.0, 1.0]])
POSES = [pose([0, 1, 0], 0.0, [0, 0, 0]), pose([0, 1, 0.2], 0.15, [0.5, 0.1, 0.2]),
         pose([1, 0, 0.3], -0.1, [-0.4, 0.3, 0.1]), pose([0.2, 1, 0], 0.3, [1.0, -0.2, 0.4])]
PLANE = (np.array([0.2, 0.0, 1.0]), 6.0)  # n . X = d


def true_depth(T_world_cam: np.ndarray) -> np.ndarray:
    """``(H, W)`` z depth of the plane seen by the camera (pixel centres at integers)."""
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    rays_cam = np.linalg.solve(K_TRUE, np.stack([u, v, np.ones_like(u)]).reshape(3, -1))  # z = 1
    normal, offset = PLANE
    R, C = T_world_cam[:3, :3], T_world_cam[:3, 3]
    t = (offset - normal @ C) / (normal @ (R @ rays_cam))
    return t.reshape(HEIGHT, WIDTH)


def test_adapter_gives_back_the_true_cameras_and_depth():
    depth = np.stack([true_depth(T) for T in POSES]).astype(np.float32)
    reference = 2  # DA3's world: a reference view's camera, here the third frame, moved about
    T_ref_world = invert_rigid(POSES[reference])
    extrinsics = np.stack([invert_rigid(T) @ np.linalg.inv(T_ref_world) for T in POSES])[:, :3]  # T_cam_ref
    confidence = 1 + np.exp(np.random.default_rng(0).normal(size=depth.shape)).astype(np.float32)
    arrays = submap_arrays(depth, confidence, extrinsics, np.tile(K_TRUE, (4, 1, 1)))
    truth = np.stack([invert_rigid(T) @ POSES[0] for T in POSES])[:, :3]  # T_cam_first
    np.testing.assert_allclose(arrays["T_cam_submap"], truth, atol=1e-12)
    np.testing.assert_allclose(arrays["T_cam_submap"][0], np.eye(4)[:3], atol=1e-12)
    assert arrays["T_cam_submap"].dtype == np.float64 and arrays["K"].dtype == np.float64
    np.testing.assert_array_equal(arrays["K"], np.tile(K_TRUE, (4, 1, 1)))
    np.testing.assert_array_equal(arrays["depth"], depth)
    np.testing.assert_array_equal(arrays["confidence"], confidence)  # 1 + exp: passed through, >= 1
    np.testing.assert_array_equal(arrays["principal_point"], np.tile([WIDTH / 2, HEIGHT / 2], (4, 1)))
    # Every frame's points, carried into the submap frame, lie on the plane seen from the first camera.
    normal, offset = PLANE
    for index in range(4):
        v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
        cam = np.linalg.solve(K_TRUE, np.stack([u, v, np.ones_like(u)]).reshape(3, -1)) * depth[index].reshape(1, -1)
        T = np.eye(4)
        T[:3] = arrays["T_cam_submap"][index]
        submap = (np.linalg.inv(T) @ np.vstack([cam, np.ones((1, cam.shape[1]))]))[:3]
        world = POSES[0][:3, :3] @ submap + POSES[0][:3, 3:]
        np.testing.assert_allclose(normal @ world, offset, atol=1e-4)


def ray_maps(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray maps ``(S, h, w, 6)`` of the scene's cameras in the third camera's frame (DA3's layout)."""
    world_from_ref = POSES[2]
    maps, c2w = [], []
    ys = (2 * np.arange(height) + 1) / height - 1  # pixel centres, the map spanning [-1, 1]
    xs = (2 * np.arange(width) + 1) / width - 1
    grid_x, grid_y = np.meshgrid(xs, ys)
    for T_world_cam in POSES:
        T_ref_cam = np.linalg.inv(world_from_ref) @ T_world_cam
        directions = np.stack([grid_x * (WIDTH / 2) / K_TRUE[0, 0], grid_y * (HEIGHT / 2) / K_TRUE[1, 1],
                               np.ones_like(grid_x)], axis=-1) @ T_ref_cam[:3, :3].T
        origins = np.broadcast_to(T_ref_cam[:3, 3], directions.shape)
        maps.append(np.concatenate([directions, origins], axis=-1))
        c2w.append(T_ref_cam)
    return np.stack(maps), np.stack(c2w)


def test_cameras_from_rays_recover_the_true_cameras():
    rays, c2w = ray_maps(24, 32)
    confidence = torch.ones(1, 4, 24, 32)
    extrinsics, intrinsics = extrinsics_intrinsics_from_rays(torch.from_numpy(rays).float()[None], confidence,
                                                             (HEIGHT, WIDTH), torch.Generator().manual_seed(0))
    K = intrinsics[0].double().numpy()
    np.testing.assert_allclose(K[:, [0, 1], [0, 1]], np.tile([K_TRUE[0, 0], K_TRUE[1, 1]], (4, 1)), rtol=1e-3)
    np.testing.assert_allclose(K[:, [0, 1], [2, 2]], np.tile([WIDTH / 2, HEIGHT / 2], (4, 1)), atol=2e-2)
    truth = relative_to_first(np.stack([np.linalg.inv(T) for T in c2w]))
    np.testing.assert_allclose(relative_to_first(extrinsics[0].double().numpy()), truth, atol=2e-4)


# -------------------------------------------------------------------------------- the frontend
@pytest.fixture(scope="module")
def tiny(fixtures_dir):
    folder = fixtures_dir / "da3_tiny"
    meta = json.loads((folder / "config.json").read_text())
    state_dict, _ = read_checkpoint(folder / "state_dict.safetensors")
    model = DepthAnything3(DA3Config(**meta["config"])).eval()
    load_state_dict_into(model, state_dict)
    inputs = load_file(str(folder / "inputs.safetensors"))
    outputs = load_file(str(folder / "outputs.safetensors"))
    frames = [Frame(index=i, timestamp=float(i), rgb=f.numpy()) for i, f in enumerate(inputs["frames"])]
    return model, meta, inputs, outputs, frames


def frontend_of(tiny, **kwargs) -> DA3Frontend:
    model, meta = tiny[0], tiny[1]
    return DA3Frontend(model=model, device="cpu", process_res=meta["frontend_process_res"], **kwargs)


def test_reconstruct_returns_a_well_formed_submap(tiny):
    frontend = frontend_of(tiny)
    frames = tiny[4]
    assert isinstance(frontend, Frontend) and frontend.name == "da3-small" and not frontend.requires_ground_truth
    assert frontend.capabilities == FrontendCapabilities(scores_pairs=False, needs_ground_truth=False,
                                                         predicts_intrinsics=True, accepts_intrinsics=True)
    prediction = frontend.reconstruct(frames, submap_id=0)
    assert isinstance(prediction, SubmapPrediction) and prediction.num_frames == 3
    S, H, W = 3, 42, 56
    assert prediction.depth.shape == (S, H, W) and prediction.depth.dtype == np.float32
    assert prediction.confidence.shape == (S, H, W) and prediction.confidence.dtype == np.float32
    assert float(prediction.confidence.min()) >= 1.0 and np.all(prediction.depth > 0)
    assert prediction.T_cam_submap.shape == (S, 3, 4) and prediction.T_cam_submap.dtype == np.float64
    np.testing.assert_allclose(prediction.T_cam_submap[0], np.eye(4)[:3], atol=1e-6)
    for T in prediction.T_cam_submap:  # rigid
        np.testing.assert_allclose(T[:, :3] @ T[:, :3].T, np.eye(3), atol=1e-5)
    assert prediction.K.shape == (S, 3, 3) and prediction.K.dtype == np.float64
    assert np.all(prediction.K[:, [0, 1], [0, 1]] > 0)
    np.testing.assert_array_equal(prediction.principal_point, np.tile([W / 2, H / 2], (S, 1)))
    assert prediction.colors.shape == (S, H, W, 3) and prediction.colors.dtype == np.uint8
    np.testing.assert_array_equal(prediction.colors[1], frontend.grid_colors(frames[1]))
    assert frontend.last_transforms[0].scale_x == W / 64


def test_frontend_outputs_equal_the_reference(tiny):
    model, meta, inputs, outputs, frames = tiny
    frontend = frontend_of(tiny)
    batch = frontend.preprocess(frames)
    assert torch.equal(batch.images[None], outputs["frontend.images"])  # their InputProcessor, bit for bit
    with one_thread():
        raw = frontend.predict(batch.images)
    for key in ("depth", "depth_conf", "extrinsics", "intrinsics"):
        assert_matches_reference(raw[key], outputs[f"frontend.plain.{key}"], key)


def test_known_intrinsics_reach_the_model(tiny):
    model, meta, inputs, outputs, frames = tiny
    frontend = frontend_of(tiny)
    known = inputs["frame_intrinsics"].numpy()
    with one_thread():
        plain = frontend.reconstruct(frames, 0)
        conditioned = frontend.reconstruct(frames, 0, intrinsics=known)
        batch = frontend.preprocess(frames)
        from sl4slam.models.da3 import intrinsics_on_grid

        grid_K = torch.from_numpy(np.stack([intrinsics_on_grid(K, t) for K, t in zip(known, batch.transforms)]))
        raw = frontend.predict(batch.images, grid_K)
    # The camera encoder changed the outputs (most in the cameras: the random tiny model's depth
    # depends little on its camera tokens).
    assert not np.array_equal(conditioned.depth, plain.depth)
    assert np.abs(conditioned.K - plain.K).max() > 1e-2
    assert np.abs(conditioned.T_cam_submap - plain.T_cam_submap).max() > 1e-3
    torch.testing.assert_close(grid_K[:, [0, 1], [0, 1]].float(), outputs["frontend.grid_intrinsics"][:, [0, 1], [0, 1]])
    for key in ("depth", "depth_conf", "extrinsics", "intrinsics"):  # = the authors' conditioned pass
        assert_matches_reference(raw[key], outputs[f"frontend.known.{key}"], key)
    np.testing.assert_array_equal(conditioned.depth, raw["depth"][0].numpy())
    with pytest.raises(ValueError, match="intrinsics of shape"):
        frontend.reconstruct(frames, 0, intrinsics=known[:2])


def test_ray_cameras_are_deterministic(tiny):
    frontend = frontend_of(tiny, cameras="rays")
    first = frontend.reconstruct(tiny[4], 0)
    second = frontend.reconstruct(tiny[4], 1)
    np.testing.assert_array_equal(first.T_cam_submap, second.T_cam_submap)
    np.testing.assert_array_equal(first.K, second.K)


def test_weights_load_on_first_use(tmp_path, tiny):
    model = tiny[0]
    path = save_checkpoint(model.state_dict(), tmp_path / "tiny.safetensors", model.config)
    frontend = DA3Frontend(size="base", weights=str(path), device="cpu", process_res=56)
    assert frontend.name == "da3-base" and frontend._model is None
    frontend.prepare()
    assert frontend.model.config == model.config
    assert frontend.reconstruct(tiny[4][:2], 0).depth.shape == (2, 42, 56)


def test_missing_weights_fail_in_one_line(tmp_path, monkeypatch):
    with pytest.raises(MissingWeightsError, match="not found"):
        DA3Frontend(weights=str(tmp_path / "absent.safetensors"), device="cpu").prepare()
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    with pytest.raises(MissingWeightsError, match="depth-anything/DA3-SMALL") as err:
        DA3Frontend(device="cpu").prepare()
    assert "\n" not in str(err.value)


def test_bad_settings_are_refused(tiny):
    with pytest.raises(UserError, match="unknown Depth Anything 3 size"):
        DA3Frontend(size="tiny")
    with pytest.raises(UserError, match="camera source"):
        DA3Frontend(cameras="points")
    with pytest.raises(UserError, match="dtype"):
        DA3Frontend(dtype="int3", device="cpu")
    frontend = frontend_of(tiny, max_memory_gb=0.5)
    with pytest.raises(UserError, match="below the smallest budget any setting fits"):
        frontend.reconstruct(tiny[4], 0)
