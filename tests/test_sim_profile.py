"""Error profiles of the simulated frontend: the profile tables, how config files and flags apply
them, the statistics each profile produces on the synthetic world against the published VGGT
figures, and bad input."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.cli import build_parser, config_from_args, main
from sl4slam.config import (
    SIM_PROFILE_VALUES,
    SIM_PROFILES,
    SimulatorConfig,
    apply_sim_profile,
    config_from_dict,
    config_to_dict,
)
from sl4slam.errors import UserError
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.geometry import se3_inverse, to_4x4
from sl4slam.synthetic import camera_path, default_intrinsics, make_world, render_frames
from sl4slam.types import Frame

WIDTH, HEIGHT = 128, 96
KEYFRAME_STEP = 7  # about the keyframe spacing of the 600-frame lap (89 keyframes at tau_disparity 25 px)
WINDOWS = ((40, 9), (180, 9), (430, 9), (520, 9))  # (first frame, keyframes) around the lap


@pytest.fixture(scope="module")
def windows() -> list[list[Frame]]:
    """Two windows of keyframes of the synthetic world's lap, rendered small."""
    world = make_world(0)
    poses = camera_path(600, seed=0)
    K = default_intrinsics(WIDTH, HEIGHT)
    out = []
    for start, count in WINDOWS:
        indices = [start + KEYFRAME_STEP * k for k in range(count)]
        rgb, depth = render_frames(world, poses[indices], K, WIDTH, HEIGHT)
        out.append([Frame(index=i, timestamp=i / 30.0, rgb=rgb[k], depth=depth[k], T_world_cam=poses[i], K=K)
                    for k, i in enumerate(indices)])
    return out


def profile_statistics(config: SimulatorConfig, windows: list[list[Frame]]) -> dict[str, float]:
    """Median relative rotation error between the frames of a window (degrees), depth AbsRel after
    per-frame median scaling, and per-frame focal errors ``|sqrt(fx fy) / sqrt(fx fy)_true - 1|``."""
    frontend = SimulatedFrontend(config)
    rotation_errors, absrel, focal = [], [], []
    for submap_id, frames in enumerate(windows):
        prediction = frontend.reconstruct(frames, submap_id)
        T_world_cam = np.stack([f.T_world_cam for f in frames])
        R_true = (se3_inverse(T_world_cam) @ T_world_cam[0])[:, :3, :3]  # camera-from-first-camera
        R_pred = to_4x4(prediction.T_cam_submap)[:, :3, :3]
        a, b = np.triu_indices(len(frames), k=1)
        relative_true = R_true[b] @ np.swapaxes(R_true[a], 1, 2)
        relative_pred = R_pred[b] @ np.swapaxes(R_pred[a], 1, 2)
        rotation_errors += list(np.degrees(Rotation.from_matrix(relative_pred @ np.swapaxes(relative_true, 1, 2)).magnitude()))
        for i, frame in enumerate(frames):
            truth = frame.depth.astype(np.float64)
            estimate = prediction.depth[i].astype(np.float64)
            estimate *= np.median(truth / estimate)
            absrel.append(np.mean(np.abs(estimate - truth) / truth))
            focal.append(abs(np.sqrt(np.prod(np.diagonal(prediction.K[i])[:2]) / np.prod(np.diagonal(frame.K)[:2])) - 1))
    return {"rotation_deg": float(np.median(rotation_errors)), "absrel": float(np.mean(absrel)),
            "focal_median": float(np.median(focal)), "focal_within_7": float(np.mean(np.array(focal) <= 0.07))}


def test_profile_statistics_match_the_published_vggt_figures(windows):
    exact = profile_statistics(SimulatorConfig.from_profile("exact"), windows)
    vggt = profile_statistics(SimulatorConfig.from_profile("vggt"), windows)
    hard = profile_statistics(SimulatorConfig.from_profile("hard"), windows)

    assert exact["rotation_deg"] < 1e-6 and exact["focal_median"] < 1e-9 and exact["absrel"] < 0.01
    # VGGT indoors: median relative rotation error 1-3 degrees, depth AbsRel 2-4 %, focal off by up to ~7 %.
    assert 1.0 <= vggt["rotation_deg"] <= 3.0, vggt
    assert 0.02 <= vggt["absrel"] <= 0.04, vggt
    assert 0.005 <= vggt["focal_median"] <= 0.04 and vggt["focal_within_7"] >= 0.9, vggt
    # hard: the upper ends of the ranges and beyond.
    assert hard["rotation_deg"] >= 2.5 and hard["rotation_deg"] > 1.5 * vggt["rotation_deg"], hard
    assert hard["absrel"] >= 0.035 and hard["absrel"] > 1.5 * vggt["absrel"], hard
    assert hard["focal_median"] > vggt["focal_median"], hard


def test_vggt_profile_scale_gauge_ratio_between_windows(windows):
    frontend = SimulatedFrontend(SimulatorConfig.from_profile("vggt", perspective=0.0, shear=0.0, normalize_scale=False))
    scales = [np.cbrt(np.linalg.det(H[:3, :3])) / H[3, 3] for H in (frontend.distortion(windows[0], j) for j in range(40))]
    ratios = np.array(scales[1:]) / np.array(scales[:-1])
    assert ratios.min() >= 0.5 and ratios.max() <= 2.0  # consecutive windows: 0.5 to 2, as seen in practice
    assert ratios.min() < 0.7 and ratios.max() > 1.4


def test_exact_profile_is_the_defaults_and_profiles_are_complete():
    assert SimulatorConfig.from_profile("exact").resolved() == SimulatorConfig().resolved()
    assert set(SIM_PROFILES) == set(SIM_PROFILE_VALUES)
    names = {f.name for f in dataclasses.fields(SimulatorConfig)}
    for profile, values in SIM_PROFILE_VALUES.items():
        assert set(values) <= names - {"profile", "seed", "normalize_scale", "distort_first_submap"}, profile
        config = SimulatorConfig.from_profile(profile, seed=5)
        assert config.profile == profile and config.seed == 5
        SimulatedFrontend(config)  # every profile passes its own validation


def test_a_profile_fills_every_magnitude_not_set_explicitly_whatever_the_order():
    """Setting ``profile`` on a config (the Python way, ``config.sim.profile = "vggt"``) applies it:
    earlier it was recorded but ignored, and a run gave the exact profile's errors."""
    config = SimulatorConfig(depth_noise=0.3, seed=7, distort_first_submap=False)
    config.profile = "vggt"
    resolved = config.resolved()
    assert resolved.depth_noise == 0.3  # explicit, set before the profile: it still wins
    assert resolved.camera_rotation_deg == SIM_PROFILE_VALUES["vggt"]["camera_rotation_deg"] > 0
    assert resolved.focal_error == SIM_PROFILE_VALUES["vggt"]["focal_error"]
    assert resolved.seed == 7 and resolved.distort_first_submap is False
    assert SimulatedFrontend(config).config == resolved  # what the simulator runs with
    apply_sim_profile(config, "exact")  # switching profile forgets the explicit magnitudes
    assert dataclasses.replace(config.resolved(), seed=0, distort_first_submap=True) == SimulatorConfig().resolved()
    with pytest.raises(UserError, match="unknown simulator profile 'vgg'"):
        apply_sim_profile(config, "vgg")
    config.profile = "vgg"
    with pytest.raises(UserError, match="--sim-profile"):
        config.validate()
    with pytest.raises(UserError, match="unknown simulator setting"):
        SimulatorConfig.from_profile("vggt", depth_nois=0.1)


def test_a_run_records_the_magnitudes_it_used(tmp_path: Path, windows) -> None:
    """The settled config (``sl4slam.resolve``), which summary.json records, holds the profile's
    values, not ``None`` and not the defaults."""
    from sl4slam.config import SLAMConfig
    from sl4slam.resolve import resolve

    config = SLAMConfig(frontend="simulated")
    config.retrieval.kind = "none"
    config.sim.profile = "vggt"
    settled = config_to_dict(resolve(config).config)["sim"]
    assert settled["profile"] == "vggt" and settled["focal_error"] == SIM_PROFILE_VALUES["vggt"]["focal_error"]
    assert config.sim.focal_error is None  # the user's tree is left as given


def test_config_file_profile_and_its_other_keys_in_any_order():
    # The explicit key is written first, yet it overrides the profile.
    config = config_from_dict({"sim": {"depth_noise": 0.1, "profile": "hard", "seed": 3}})
    resolved = config.sim.resolved()
    assert config.sim.profile == "hard" and resolved.depth_noise == 0.1 and resolved.seed == 3
    assert resolved.camera_rotation_deg == SIM_PROFILE_VALUES["hard"]["camera_rotation_deg"]
    assert config_to_dict(config)["sim"]["profile"] == "hard"
    with pytest.raises(UserError, match="profile"):
        config_from_dict({"sim": {"profile": "nope"}}).validate()


def test_sim_profile_flag_and_explicit_settings(tmp_path: Path):
    parse = build_parser().parse_args
    config = config_from_args(parse(["run", "src", "--out", "o", "--sim-depth-warp", "0.2", "--sim-profile", "vggt"]))
    resolved = config.sim.resolved()
    assert config.sim.profile == "vggt" and resolved.depth_warp == 0.2
    assert resolved.focal_error == SIM_PROFILE_VALUES["vggt"]["focal_error"]

    # The flag replaces the file's profile; the file's explicit settings and the flags still win over it.
    (tmp_path / "c.toml").write_text("[sim]\nperspective = 0.3\nprofile = 'vggt'\nseed = 2\n")
    config = config_from_args(parse(["run", "src", "--out", "o", "--config", str(tmp_path / "c.toml"),
                                     "--sim-shear", "0.0", "--sim-profile", "hard"]))
    resolved = config.sim.resolved()
    assert config.sim.profile == "hard" and resolved.perspective == 0.3 and resolved.seed == 2
    assert resolved.shear == 0.0 and resolved.depth_warp == SIM_PROFILE_VALUES["hard"]["depth_warp"]
    (tmp_path / "c.json").write_text(json.dumps({"sim": {"profile": "vggt"}}))
    config = config_from_args(parse(["run", "src", "--out", "o", "--config", str(tmp_path / "c.json")]))
    assert config.sim.profile == "vggt" and config.sim.resolved().depth_warp == SIM_PROFILE_VALUES["vggt"]["depth_warp"]
    with pytest.raises(SystemExit):
        parse(["run", "src", "--out", "o", "--sim-profile", "vgg"])


def test_bad_simulator_setting_is_one_line_before_any_frame_is_read(tmp_path: Path, capsys):
    import cv2

    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.zeros((24, 32, 3), np.uint8))
    code = main(["run", str(folder), "--out", str(tmp_path / "o"), "--frontend", "simulated", "--sim-profile", "vggt",
                 "--sim-focal-error", "0.9", "--quiet"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and "--sim-focal-error" in err[0] and "0.9" in err[0]
    assert not (tmp_path / "o" / "summary.json").exists()


def test_a_profile_too_strong_for_the_scene_names_the_setting_to_lower(windows):
    config = SimulatorConfig.from_profile("vggt", perspective=1.5)
    with pytest.raises(UserError, match=r"lower --sim-perspective \(now 1.5, vggt profile\)") as error:
        SimulatedFrontend(config).reconstruct(windows[0], 4)  # this submap's perspective row faces the scene
    assert "\n" not in str(error.value)
