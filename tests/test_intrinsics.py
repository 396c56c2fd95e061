"""A known calibration (``--intrinsics``): reading it, one-line errors before any frame, points
rebuilt along the true rays whatever focal the model guessed, the grid mapping of a resizing
model, and the summary's report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sl4slam.config import SLAMConfig, SimulatorConfig
from sl4slam.errors import UserError
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.geometry import unproject_depth
from sl4slam.intrinsics import checked, from_source, on_grid, parse_intrinsics
from sl4slam.io import open_source
from sl4slam.metrics import ate
from sl4slam.runner import run_slam
from sl4slam.synthetic import write_synthetic_sequence

TUM_TEXT = """RGB camera, calibrated by TUM for fr1 (pinhole + radial-tangential, OpenCV order):
  fx = 517.3  fy = 516.5  cx = 318.6  cy = 255.3
  d0..d4 (k1 k2 p1 p2 k3) = 0.2624  -0.9531  -0.0054  0.0026  1.1633
"""


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("intrinsics") / "world", num_frames=240, width=160,
                                    height=120, seed=5)


def test_the_three_ways_to_give_a_calibration(tmp_path: Path) -> None:
    given = parse_intrinsics("517.3, 516.5,318.6,255.3")
    np.testing.assert_array_equal(given.K, [[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]])
    (tmp_path / "calibration.txt").write_text(TUM_TEXT)
    tum = parse_intrinsics(str(tmp_path / "calibration.txt"))
    np.testing.assert_array_equal(tum.K, given.K)
    assert "distortion ignored" in tum.note
    # COLMAP counts pixels from the first one's corner: its principal point is half a pixel further
    (tmp_path / "cameras.txt").write_text("# Camera list\n1 PINHOLE 640 480 517.3 516.5 319.1 255.8\n")
    np.testing.assert_allclose(parse_intrinsics(str(tmp_path / "cameras.txt")).K, given.K)
    (tmp_path / "opencv.txt").write_text("1 OPENCV 640 480 517.3 516.5 319.1 255.8 0.26 -0.95 -0.005 0.003\n")
    assert "distortion ignored" in parse_intrinsics(str(tmp_path / "opencv.txt")).note
    assert parse_intrinsics("") is None  # "auto" (the source says) is settled by resolve, not parsed


@pytest.mark.parametrize("spec, words", [
    ("500,500,320", "neither fx,fy,cx,cy nor a file"),
    ("-500,500,320,240", "focal lengths must be positive"),
    ("500,0,320,240", "focal lengths must be positive"),
    ("500,abc,320,240", "four numbers"),
])
def test_a_calibration_that_cannot_be_used_is_one_line(spec: str, words: str) -> None:
    with pytest.raises(UserError, match=words) as caught:
        parse_intrinsics(spec)
    assert "\n" not in str(caught.value)


def test_bad_calibrations_end_a_run_before_any_frame_is_read(world: Path, tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "notes.txt").write_text("no numbers here\n")
    read = []
    import sl4slam.io.tum as tum

    original = tum.TumSource._load
    monkeypatch.setattr(tum.TumSource, "_load", lambda self, position: read.append(position) or original(self, position))
    images = tmp_path / "images"
    images.mkdir()
    import cv2

    for i in range(3):
        cv2.imwrite(str(images / f"{i:04d}.png"), np.full((72, 96, 3), 60 * i, np.uint8))
    cases = [
        (world, "100,100,400,60", "principal point (400, 60) lies outside the 160x120 images"),
        (world, str(tmp_path / "notes.txt"), "no 'fx = .. fy = .. cx = .. cy = ..' values"),
        (images, "auto", "states no calibration"),
    ]
    for source, spec, words in cases:
        config = SLAMConfig(frontend="simulated" if source == world else "vggt", device="cpu")
        config.retrieval.kind = "none"
        config.source.intrinsics = spec
        with pytest.raises(UserError, match=words.replace("(", r"\(").replace(")", r"\)")) as caught:
            run_slam(source, tmp_path / "out", config, progress=False)
        assert "\n" not in str(caught.value) and read == []
    assert not (tmp_path / "out").exists()


def test_points_are_rebuilt_along_the_true_rays_whatever_focal_the_model_guessed(world: Path) -> None:
    """The simulated model gets each frame's focal length wrong by ~10 %; with the known K its depth
    placed along the known camera's rays gives back the true points exactly (no other error here)."""
    source = open_source(str(world))
    frames = [source.get(i) for i in (0, 6, 12, 18, 24)]
    config = SimulatorConfig(focal_error=0.1, depth_noise=0.0, outlier_fraction=0.0, normalize_scale=False, seed=3)
    prediction = SimulatedFrontend(config).reconstruct(frames, 0)
    known = from_source(source, None, read_calibration=True)
    K_grid = on_grid(known.K, np.eye(3)[None].repeat(len(frames), 0))
    assert np.abs(prediction.K[:, 0, 0] / K_grid[:, 0, 0] - 1).max() > 0.02  # the model's focal is off
    T_world_cam = np.stack([f.T_world_cam for f in frames])
    T_cam_first = np.linalg.inv(T_world_cam) @ T_world_cam[0]
    truth = unproject_depth(np.stack([f.depth for f in frames]), K_grid, T_cam_first)
    rebuilt = unproject_depth(prediction.depth, K_grid, prediction.T_cam_submap)
    guessed = unproject_depth(prediction.depth, prediction.K, prediction.T_cam_submap)
    valid = np.stack([f.depth for f in frames]) > 0
    assert np.abs(rebuilt - truth)[valid].max() < 1e-4  # float32 unprojection
    assert np.abs(guessed - truth)[valid].max() > 0.05


def test_a_resizing_models_grid_gets_the_known_camera(tmp_path: Path) -> None:
    """VGGT resizes and crops: a point projected by the known K into the input image and carried by
    the preprocessing's transform lands where the K put on the grid projects it."""
    torch = pytest.importorskip("torch")  # noqa: F841 (the preprocessing is torch's)
    from sl4slam.frontend.vggt import grid_affine
    from sl4slam.models.vggt.preprocess import preprocess_images

    K = np.array([[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]])
    for mode in ("crop", "pad"):
        _, (transform,) = preprocess_images([np.zeros((480, 640, 3), np.uint8)], mode=mode)
        K_grid = on_grid(K, grid_affine(transform)[None])[0]
        X = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 3.0], [0.0, 0.0, 1.5]])
        uv_input = (X @ K.T)[:, :2] / X[:, 2:]
        carried = transform.input_to_output(uv_input + 0.5) - 0.5  # integer pixel centres on both sides
        np.testing.assert_allclose((X @ K_grid.T)[:, :2] / X[:, 2:], carried, atol=1e-9)


def test_a_run_with_known_intrinsics_reports_them_and_skips_the_upgrade(world: Path, tmp_path: Path) -> None:
    config = SLAMConfig(frontend="simulated")
    config.sim.focal_error, config.sim.seed = 0.05, 1
    config.keyframes.tau_disparity = 10.0
    config.retrieval.kind = "none"
    config.backend.graph, config.upgrade.mode = "submap", "auto"  # whose upgrade would run
    plain = run_slam(world, tmp_path / "plain", config, progress=False)
    config.source.intrinsics = "auto"
    known = run_slam(world, tmp_path / "known", config, progress=False)
    report = known["intrinsics"]
    assert report["K"] == [76.8 * 160 / 96, 76.8 * 160 / 96, 79.5, 59.5] and report["origin"].startswith("auto")
    assert 0.9 < report["model_focal_ratio"]["median"] < 1.1 and report["model_focal_ratio"]["max"] > 1.02
    assert not known["resolved"]["metric_upgrade"] and not known["metric_upgrade"]
    assert any("known intrinsics" in note for note in known["resolved"]["notes"])
    assert known["ate"]["rmse"] < plain["ate"]["rmse"]


def test_a_wildly_wrong_calibration_is_warned_about(world: Path, tmp_path: Path, caplog) -> None:
    config = SLAMConfig(frontend="simulated")
    config.retrieval.kind = "none"
    config.source.intrinsics = "400,400,79.5,59.5"  # the simulator's frames have a focal of 128 px
    summary = run_slam(world, tmp_path / "out", config, progress=False)
    assert summary["intrinsics"]["model_focal_ratio"]["median"] == pytest.approx(128 / 400, rel=1e-6)
    assert any("0.32 times the given" in note for note in summary["notes"])
    assert sum("times the given intrinsics" in r.getMessage() for r in caplog.records) == 1


def test_checked_accepts_a_calibration_for_the_images() -> None:
    known = parse_intrinsics("100,100,79.5,59.5")
    assert checked(known, (160, 120)) is known


# ------------------------------------------------------------------------- metric scale from the sensor
def test_the_sensors_depth_puts_the_map_in_metres(world: Path, tmp_path: Path) -> None:
    """The simulated model gives every submap its own scale (the window normalization and a gauge
    ratio of up to 2); the sensor's depth brings each back to metres, so the trajectory needs no
    scale to match the ground truth: its SE(3)-aligned ATE is about its Sim(3)-aligned one."""
    from sl4slam.io import read_tum_trajectory

    config = SLAMConfig(frontend="simulated")
    config.sim.profile, config.sim.seed = "vggt", 2
    config.keyframes.tau_disparity = 10.0
    config.retrieval.kind = "none"
    config.source.metric_depth = "sensor"
    summary = run_slam(world, tmp_path / "out", config, progress=False)
    t, T = read_tum_trajectory(tmp_path / "out" / "trajectory.txt")
    t_gt, T_gt = read_tum_trajectory(tmp_path / "out" / "trajectory_gt.txt")
    se3 = ate(t, T, t_gt, T_gt, correct_scale=False)
    sim3 = ate(t, T, t_gt, T_gt, correct_scale=True)
    assert summary["metric_depth"]["submaps_scaled"] == summary["counts"]["submaps"]
    assert abs(sim3.scale - 1) < 0.03 and se3.rmse < 1.5 * sim3.rmse + 0.01
    config.source.metric_depth = "off"
    unscaled = run_slam(world, tmp_path / "off", config, progress=False)
    assert abs(unscaled["ate"]["scale"] - 1) > 0.1  # without it the map is in the model's units


def test_frames_without_sensor_depth_keep_the_neighbours_scale(world: Path, tmp_path: Path) -> None:
    from sl4slam.io import ListSource
    from sl4slam.pipeline import SLAMPipeline

    frames = list(open_source(str(world)))
    holes = [f if not 100 <= f.index < 160 else type(f)(f.index, f.timestamp, f.rgb, np.zeros_like(f.depth),
                                                          f.T_world_cam, f.K, f.path) for f in frames]
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 10.0
    config.retrieval.kind = "none"
    config.submap.size = 4
    config.source.metric_depth = "sensor"
    originals = {f.index: f for f in frames}

    class SensorHoles(SimulatedFrontend):  # the model sees the scene; the sensor has holes
        def reconstruct(self, batch, submap_id, **kwargs):
            return super().reconstruct([originals[f.index] for f in batch], submap_id, **kwargs)

    result = SLAMPipeline.from_config(config, SensorHoles(config.sim)).run(ListSource(holes), progress=False)
    report = result.stats["metric_depth"]
    assert report["kept_neighbour_scale"] >= 1 and report["submaps_scaled"] >= 1
    assert np.isfinite(result.T_world_cam).all()


def test_the_sensors_scale_needs_depth_images(tmp_path: Path) -> None:
    import cv2

    images = tmp_path / "images"
    images.mkdir()
    for i in range(3):
        cv2.imwrite(str(images / f"{i:04d}.png"), np.full((72, 96, 3), 60 * i, np.uint8))
    config = SLAMConfig(device="cpu")
    config.retrieval.kind = "none"
    config.source.metric_depth = "sensor"
    with pytest.raises(UserError, match="--metric-depth sensor needs depth images"):
        run_slam(images, tmp_path / "out", config, progress=False)
