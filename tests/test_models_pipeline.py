"""Every feed-forward model through the whole pipeline, and the model verbs of the command line.

The models here are the tiny random-weight fixtures (``tests/fixtures``): their geometry is garbage,
which is the point of running them end to end: whatever a model predicts, a run completes with
finite outputs, reports every keyframe once, and uses a known calibration where given.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sl4slam.cli import main
from sl4slam.config import SLAMConfig
from sl4slam.io import open_source
from sl4slam.pipeline import SLAMPipeline
from sl4slam.registry import frontend_entry, frontend_names
from sl4slam.synthetic import write_synthetic_sequence

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("world") / "synthetic", num_frames=160, width=160,
                                    height=120, seed=0)


def tiny_da3(fixtures_dir: Path):
    from sl4slam.frontend.da3 import DA3Frontend
    from sl4slam.models.da3 import DA3Config, DepthAnything3, load_state_dict_into, read_checkpoint

    folder = fixtures_dir / "da3_tiny"
    meta = json.loads((folder / "config.json").read_text())
    state_dict, _ = read_checkpoint(folder / "state_dict.safetensors")
    model = DepthAnything3(DA3Config(**meta["config"])).eval()
    load_state_dict_into(model, state_dict)
    return DA3Frontend(model=model, device="cpu", process_res=meta["frontend_process_res"])


def tiny_pi3(variant: str):
    def build(fixtures_dir: Path):
        from sl4slam.frontend.pi3 import Pi3Frontend
        from safetensors.torch import load_file

        from sl4slam.models.pi3 import Pi3Config, build_pi3
        from sl4slam.models.pi3.weights import load_state_dict_into

        folder = fixtures_dir / f"{variant}_tiny"
        model = build_pi3(Pi3Config.from_dict(json.loads((folder / "config.json").read_text()))).eval()
        load_state_dict_into(model, load_file(str(folder / "state_dict.safetensors")))
        frontend = Pi3Frontend(variant, device="cpu", model=model)
        frontend.budget = 224 * 168  # 1.4x the 160x120 frames in whole patches (the 255 000-pixel grid: slow)
        return frontend

    return build


MODELS = {"da3": tiny_da3, "pi3": tiny_pi3("pi3"), "pi3x": tiny_pi3("pi3x")}


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("intrinsics", ["", "auto"])
def test_each_model_runs_the_whole_pipeline(world: Path, fixtures_dir: Path, name: str, intrinsics: str) -> None:
    torch.manual_seed(0)
    frontend = MODELS[name](fixtures_dir)
    config = SLAMConfig()
    config.keyframes.tau_disparity = 12.0
    config.submap.size, config.submap.overlap = 4, 2
    config.retrieval.kind = "none"
    config.source.intrinsics = intrinsics
    with torch.no_grad():
        result = SLAMPipeline.from_config(config, frontend=frontend).run(open_source(str(world)), progress=False)
    assert len(result.keyframes) >= 4
    assert len(set(result.timestamps)) == len(result.timestamps)
    assert np.isfinite(result.T_world_cam).all() and np.isfinite(result.K).all()
    if intrinsics:
        known = result.stats["intrinsics"]
        assert known["model_given_it"] is frontend.capabilities.accepts_intrinsics
        assert known["model_focal_ratio"] is None or np.isfinite(known["model_focal_ratio"]["median"])
        # the keyframes' intrinsics are the known ones, moved onto the model's grid
        assert np.allclose(result.K[:, 0, 0] / result.K[:, 1, 1], 1.0, atol=0.05)


def test_models_lists_every_model_with_its_licence(capsys) -> None:
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    for name in frontend_names():
        entry = frontend_entry(name)
        assert name in out
        if entry.weights is not None:
            assert entry.weights.repo_id in out and entry.licence.split(" (")[0] in out
    assert "da3-small" in out and "Apache-2.0" in out and "CC BY-NC 4.0" in out


def test_convert_writes_a_checkpoint_that_loads_back(tmp_path: Path, fixtures_dir: Path, capsys) -> None:
    from sl4slam.models.da3 import read_checkpoint, save_checkpoint

    frontend = tiny_da3(fixtures_dir)
    source = save_checkpoint(frontend.model.state_dict(), tmp_path / "source.safetensors", frontend.model.config)
    # the tiny model's width is no released size: its model must be named
    assert main(["convert", str(source), str(tmp_path / "x.safetensors")]) == 2
    assert "name it with --model" in capsys.readouterr().err
    assert main(["convert", str(source), str(tmp_path / "tiny.safetensors"), "--model", "da3-small", "--dtype", "bf16"]) == 0
    converted, _ = read_checkpoint(tmp_path / "tiny.safetensors")
    original, _ = read_checkpoint(source)
    assert converted.keys() == original.keys()
    assert all(converted[k].dtype == torch.bfloat16 for k in converted if original[k].is_floating_point())


def test_a_model_named_on_the_command_line_runs_with_every_graph_cache_replay_and_all_frames(
        world: Path, fixtures_dir: Path, tmp_path: Path) -> None:
    """``--model da3-small --weights FILE`` (the tiny model saved with its config) through the runner:
    both graph designs, the frontend recorded and replayed to the same trajectory, every frame
    localized, and the loop check without attention (DA3 scores no pairs: view and graph checks)."""
    from sl4slam.io import read_tum_trajectory
    from sl4slam.models.da3 import save_checkpoint

    model = tiny_da3(fixtures_dir).model
    weights = save_checkpoint(model.state_dict(), tmp_path / "tiny.safetensors", model.config)
    common = ["--model", "da3-small", "--weights", str(weights), "--device", "cpu", "--submap-size", "4",
              "--tau-disparity", "12", "--max-frames", "60", "--quiet"]
    for graph in ("keyframe", "submap"):
        out = tmp_path / graph
        assert main(["run", str(world), "--out", str(out), "--graph", graph, "--cache-frontend", "--all-frames",
                     *common]) == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["resolved"]["frontend"] == "da3-small" and summary["counts"]["keyframes"] >= 4
        assert summary["resolved"]["attention_check"] is False
        stamps, poses = read_tum_trajectory(out / "trajectory_all.txt")
        assert len(stamps) == 60 and np.isfinite(poses).all()
        replayed = tmp_path / f"{graph}_replay"
        assert main(["run", str(world), "--out", str(replayed), "--graph", graph, "--replay",
                     str(out / "frontend_cache"), *common]) == 0
        np.testing.assert_array_equal(read_tum_trajectory(replayed / "trajectory.txt")[1],
                                      read_tum_trajectory(out / "trajectory.txt")[1])


def test_a_model_on_the_cpu_says_its_cost_before_the_first_frame_unless_quiet(
        world: Path, fixtures_dir: Path, tmp_path: Path, capfd) -> None:
    from sl4slam.models.da3 import save_checkpoint

    model = tiny_da3(fixtures_dir).model
    weights = save_checkpoint(model.state_dict(), tmp_path / "tiny.safetensors", model.config)
    common = ["--model", "da3-small", "--weights", str(weights), "--device", "cpu", "--submap-size", "4",
              "--tau-disparity", "12", "--max-frames", "24", "--retrieval", "none"]
    assert main(["run", str(world), "--out", str(tmp_path / "loud"), *common]) == 0
    err = capfd.readouterr().err.splitlines()
    lines = [line for line in err if "on this CPU" in line]
    assert len(lines) == 1 and "da3-small needs about" in lines[0] and "24 frames of this source" in lines[0]
    assert main(["run", str(world), "--out", str(tmp_path / "quiet"), *common, "--quiet"]) == 0
    assert "on this CPU" not in capfd.readouterr().err
