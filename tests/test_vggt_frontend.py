"""The VGGT frontend: preprocessing, model call and outputs in the pipeline's shapes and frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from sl4slam.config import ModelConfig
from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.frontend.vggt import VGGTFrontend, resolve_compute_dtype, resolve_device
from sl4slam.io import read_tum_trajectory
from sl4slam.models.vggt.model import VGGT, VGGTModelConfig, init_random_weights
from sl4slam.models.vggt.pose_encoding import pose_encoding_to_extri_intri
from sl4slam.models.vggt.preprocess import preprocess_images, to_uint8_rgb
from sl4slam.models.vggt.weights import load_vggt, save_checkpoint
from sl4slam.types import Frame, Frontend, SubmapPrediction

# A small model for pipeline tests; img_size 518 so the position embedding is resized as in VGGT-1B.
SMALL_CONFIG = VGGTModelConfig(
    embed_dim=32, depth=4, num_heads=2, patch_embed_depth=1, patch_embed_num_heads=2,
    camera_trunk_depth=1, camera_num_heads=2, dpt_features=8, dpt_out_channels=[8, 8, 8, 8], dpt_layers=[0, 1, 2, 3],
)


def make_random_checkpoint(path: Path, config: VGGTModelConfig = SMALL_CONFIG, seed: int = 0) -> Path:
    """A random-weight VGGT checkpoint whose camera head predicts plausible cameras.

    The pose branch's last layer is shrunk and biased towards the identity rotation (w = 1) and a
    60-degree field of view, so decoded intrinsics are finite and positive as a trained model's are.
    """
    torch.manual_seed(seed)
    model = init_random_weights(VGGT(config), seed=seed)
    with torch.no_grad():
        last = model.camera_head.pose_branch.fc2
        last.weight.mul_(0.01)
        # The camera head adds its four iterations' outputs: a quarter of the target per iteration.
        last.bias.copy_(torch.tensor([0, 0, 0, 0, 0, 0, 1.0, 1.05, 1.3]) / 4)
    return save_checkpoint(model.state_dict(), path, config)


def _frames(num: int, height: int = 96, width: int = 128, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    return [Frame(index=i, timestamp=float(i), rgb=rng.integers(0, 256, (height, width, 3), dtype=np.uint8)) for i in range(num)]


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> VGGT:
    path = make_random_checkpoint(tmp_path_factory.mktemp("weights") / "small.safetensors")
    return load_vggt(str(path))


def test_reconstruct_returns_the_model_outputs_on_its_grid(tiny_model):
    frontend = VGGTFrontend(ModelConfig(dtype="fp32"), model=tiny_model, with_points=True, device="cpu")
    assert isinstance(frontend, Frontend) and frontend.name == "vggt"
    frames = _frames(3, height=48, width=128)
    prediction = frontend.reconstruct(frames, submap_id=0)
    assert isinstance(prediction, SubmapPrediction) and prediction.num_frames == 3
    grid = (196, 518)  # 48x128 -> width 518, height round(194.25 / 14) * 14
    assert prediction.depth.shape == prediction.confidence.shape == (3, *grid)
    assert prediction.depth.dtype == prediction.confidence.dtype == np.float32
    assert prediction.T_cam_submap.shape == (3, 3, 4) and prediction.T_cam_submap.dtype == np.float64
    assert prediction.K.shape == (3, 3, 3) and prediction.K.dtype == np.float64
    assert prediction.colors.shape == (3, *grid, 3) and prediction.colors.dtype == np.uint8
    assert prediction.points.shape == (3, *grid, 3) and prediction.points_confidence.shape == (3, *grid)
    assert np.all(prediction.confidence >= 1) and np.all(prediction.depth > 0)

    # Exactly what the model gives for the preprocessed images, decoded on the grid.
    images, _ = preprocess_images([f.rgb for f in frames], mode="crop")
    np.testing.assert_array_equal(prediction.colors, to_uint8_rgb(images))
    np.testing.assert_array_equal(prediction.colors[1], frontend.grid_colors(frames[1]))  # the map's colours
    with torch.inference_mode():
        raw = tiny_model(images)
    np.testing.assert_allclose(prediction.depth, raw["depth"][0, ..., 0].numpy(), rtol=1e-6, atol=0)
    np.testing.assert_allclose(prediction.points, raw["world_points"][0].numpy(), rtol=1e-6, atol=0)
    extrinsics, intrinsics = pose_encoding_to_extri_intri(raw["pose_enc"][0].double(), grid)
    np.testing.assert_allclose(prediction.T_cam_submap, extrinsics.numpy(), atol=1e-6)
    np.testing.assert_allclose(prediction.K, intrinsics.numpy(), rtol=1e-6)
    np.testing.assert_array_equal(prediction.K[:, :2, 2], np.tile([259.0, 98.0], (3, 1)))

    # The resize is recorded per frame.
    assert len(frontend.last_transforms) == 3
    transform = frontend.last_transforms[0]
    assert transform.input_hw == (48, 128) and transform.output_hw == grid
    assert transform.scale_x == pytest.approx(518 / 128) and transform.scale_y == pytest.approx(196 / 48)


def test_pad_mode_and_no_points(tiny_model):
    frontend = VGGTFrontend(ModelConfig(dtype="fp32", preprocess_mode="pad"), model=tiny_model, device="cpu")
    prediction = frontend.reconstruct(_frames(2, height=128, width=96), submap_id=3)
    assert prediction.depth.shape == (2, 518, 518) and prediction.points is None
    # Portrait 96x128 -> 392x518, centred with 63 white columns each side.
    assert frontend.last_transforms[0].valid_box == (63, 0, 455, 518)
    assert np.all(prediction.colors[:, :, :63] == 255)


def test_weights_are_loaded_from_a_file_on_first_use(tmp_path):
    path = make_random_checkpoint(tmp_path / "small.safetensors")
    frontend = VGGTFrontend(ModelConfig(dtype="fp32", weights=str(path)), device="cpu")
    assert frontend._model is None  # nothing loaded before the first submap
    prediction = frontend.reconstruct(_frames(2, height=48), submap_id=0)
    assert frontend.model.config == SMALL_CONFIG
    assert np.all(np.isfinite(prediction.K)) and np.all(prediction.K[:, 0, 0] > 0)
    # The biased camera head gives near-identity rotations and a ~60 degree field of view.
    np.testing.assert_allclose(prediction.T_cam_submap[:, :, :3], np.tile(np.eye(3), (2, 1, 1)), atol=0.2)


def test_missing_weights_fail_with_instructions(tmp_path):
    frontend = VGGTFrontend(ModelConfig(dtype="fp32", weights=str(tmp_path / "model.pt")), device="cpu")
    with pytest.raises(MissingWeightsError, match="--weights PATH"):
        frontend.reconstruct(_frames(2), submap_id=0)


def test_device_and_dtype_resolution():
    cpu = torch.device("cpu")
    assert resolve_device("cpu") == cpu
    assert resolve_compute_dtype("fp32", cpu) == torch.float32
    assert resolve_compute_dtype("bf16", cpu) == torch.bfloat16
    assert resolve_compute_dtype("fp16", torch.device("cuda")) == torch.float16
    with pytest.raises(UserError):
        resolve_compute_dtype("int4", cpu)
    with pytest.raises(UserError):
        VGGTFrontend(ModelConfig(dtype="fp32", preprocess_mode="stretch"), device="cpu")


def test_a_match_layer_the_model_lacks_is_refused_when_the_loop_check_needs_it(tiny_model):
    """The attention loop check reads global layer ``match_layer`` (21 of VGGT-1B's 24); a smaller
    model without it is refused when the weights load, before any frame, naming the fix."""
    with pytest.raises(UserError, match="--match-layer 21 does not exist: the model has 4 global attention layers"):
        VGGTFrontend(ModelConfig(dtype="fp32"), model=tiny_model, match_scores=True, device="cpu")
    VGGTFrontend(ModelConfig(dtype="fp32"), model=tiny_model, device="cpu")  # no loop check: the layer is never read
    VGGTFrontend(ModelConfig(dtype="fp32", match_layer=3), model=tiny_model, match_scores=True, device="cpu")
    if not torch.cuda.is_available():
        with pytest.raises(UserError, match="no CUDA"):
            resolve_device("cuda")


def test_cli_runs_end_to_end_with_a_random_checkpoint(tmp_path):
    synthetic = pytest.importorskip("sl4slam.synthetic")
    if not hasattr(synthetic, "write_synthetic_sequence"):
        pytest.skip("the synthetic world writer is not available")
    from sl4slam.cli import main

    weights = make_random_checkpoint(tmp_path / "vggt_small.safetensors")
    source = tmp_path / "world"
    assert main(["synth", "--out", str(source), "--frames", "30", "--width", "128", "--height", "96"]) == 0
    out = tmp_path / "run"
    code = main(["run", str(source), "--out", str(out), "--frontend", "vggt", "--weights", str(weights),
                 "--device", "cpu", "--submap-size", "4", "--match-layer", "3", "--quiet"])
    assert code == 0
    assert (out / "summary.json").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["submaps"] >= 1


def test_a_run_with_garbage_model_output_completes(tmp_path, shared_dir):
    """Random weights predict garbage (here: fields of view beyond 180 degrees, i.e. negative focal
    lengths, random poses and depths): every edge is refused or weakened, submaps start new segments,
    loops are rejected, and the run still completes with finite outputs on the real TUM excerpt."""
    from sl4slam.config import SLAMConfig
    from sl4slam.runner import run_slam

    torch.manual_seed(1)
    model = init_random_weights(VGGT(SMALL_CONFIG), seed=1)
    with torch.no_grad():  # the four camera-head iterations add up to a 4-radian field of view
        model.camera_head.pose_branch.fc2.bias[7:9] = 1.0
    weights = save_checkpoint(model.state_dict(), tmp_path / "garbage.safetensors", SMALL_CONFIG)
    config = SLAMConfig()
    config.model.weights, config.device = str(weights), "cpu"
    config.submap.size = 2
    config.retrieval.kind, config.retrieval.tau_interval = "orb", 0
    config.model.match_layer = SMALL_CONFIG.depth - 1  # the attention loop check reads the small model's last layer
    summary = run_slam(shared_dir / "data" / "tum_rgbd_fr1_xyz_first37", tmp_path / "out", config, progress=False)
    assert summary["status"] == "complete" and summary["counts"]["keyframes"] >= 4
    edges = summary["edges"]
    assert edges and all(e["kind"] != "odometry" or not e["accepted"] or e.get("fallback") or e["inlier_ratio"] >= 0.1
                         for e in edges)
    assert summary["counts"]["segments"] + sum(1 for e in edges if e["kind"] == "odometry" and e["accepted"]) \
        == summary["counts"]["submaps"]
    assert any(s["reason"] and "focal" in s["reason"] for s in summary["segments"])
    stamps, poses = read_tum_trajectory(tmp_path / "out" / "trajectory.txt")
    assert len(stamps) == summary["counts"]["keyframes"] and np.isfinite(poses).all()


def test_a_frontend_with_non_finite_output_ends_the_run_clearly(tmp_path, shared_dir):
    """Output that cannot be used at all (an infinite focal length on every submap) is a broken
    frontend, not a bad submap: the run ends with one line saying so, not a traceback."""
    from sl4slam.cli import main

    weights = save_checkpoint(init_random_weights(VGGT(SMALL_CONFIG), seed=1).state_dict(), tmp_path / "zero_fov.safetensors",
                              SMALL_CONFIG)  # the field-of-view activation is a ReLU: random weights give 0
    code = main(["run", str(shared_dir / "data" / "tum_rgbd_fr1_xyz_first37"), "--out", str(tmp_path / "out"),
                 "--weights", str(weights), "--device", "cpu", "--submap-size", "2", "--retrieval", "none", "--quiet"])
    assert code == 1
    assert not (tmp_path / "out" / "trajectory.txt").exists()
