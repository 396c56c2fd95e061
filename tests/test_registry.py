"""The registry of frontends and the composition root: names, capabilities, models named by their
weights, and the documented way to add a model (docs/architecture.md), run end to end."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sl4slam import registry
from sl4slam.compose import build_stages
from sl4slam.config import SLAMConfig
from sl4slam.errors import UserError
from sl4slam.registry import frontend_entry, frontend_names
from sl4slam.resolve import resolve
from sl4slam.runner import run_slam
from sl4slam.synthetic import write_synthetic_sequence

DOCS = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("registry") / "world", num_frames=150, width=128, height=96,
                                    seed=2)


def test_the_built_in_frontends_are_registered_with_their_capabilities() -> None:
    assert {"vggt", "simulated"} <= set(frontend_names())
    vggt, simulated = frontend_entry("vggt"), frontend_entry("simulated")
    assert vggt.capabilities.scores_pairs and vggt.capabilities.predicts_intrinsics and vggt.weights is not None
    assert simulated.capabilities.needs_ground_truth and simulated.weights is None and simulated.settings == "sim"
    assert vggt.parameters and vggt.licence


def test_an_unknown_model_is_one_line_listing_the_available_ones() -> None:
    with pytest.raises(UserError) as caught:
        resolve(SLAMConfig(frontend="vggt2"))
    message = str(caught.value)
    assert "\n" not in message and "'vggt2'" in message and all(name in message for name in ("vggt", "simulated"))


def test_a_model_is_recognized_from_its_hub_id_or_its_weights_file(fixtures_dir: Path) -> None:
    config = SLAMConfig(frontend="facebook/VGGT-1B", device="cpu")
    config.retrieval.kind = "none"
    resolved = resolve(config)
    assert resolved.frontend.name == "vggt" and resolved.config.model.weights == "facebook/VGGT-1B"
    weights = fixtures_dir / "vggt_tiny_b" / "state_dict.safetensors"
    config.frontend = str(weights)
    resolved = resolve(config)
    assert resolved.frontend.name == "vggt" and resolved.config.model.weights == str(weights)
    assert any("recognized" in note for note in resolved.notes)
    config.frontend = str(fixtures_dir / "salad_tiny" / "state_dict.safetensors")  # weights of no frontend
    with pytest.raises(UserError, match="is an unknown model or frontend"):
        resolve(config)


def test_the_composition_root_builds_every_stage_from_the_resolved_config() -> None:
    config = SLAMConfig(frontend="simulated")
    config.retrieval.kind = "orb"
    config.false_loops.rate = 0.3
    stages = build_stages(resolve(config))
    assert stages.frontend.name == "simulated" and stages.backend.design == "keyframe"
    assert stages.aligner.model == "select" and stages.retrieval.name == "orb+false-loops"
    config.retrieval.kind = "none"
    assert build_stages(resolve(config)).retrieval is None


def _documented_example() -> str:
    text = DOCS.read_text()
    section = text[text.index("## How to add a model"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_documented_way_to_add_a_model_runs_the_whole_pipeline(world: Path, tmp_path: Path, monkeypatch) -> None:
    """The example of docs/architecture.md, executed as written: a model registered from user code
    is named in the config like a built-in one and runs the whole pipeline (keyframes, alignment,
    loops, graph, outputs) through the same composition root."""
    monkeypatch.setattr(registry, "_FRONTENDS", dict(registry._FRONTENDS))  # registered for this test only
    exec(compile(_documented_example(), str(DOCS), "exec"), {})
    assert "oracle" in frontend_names()
    config = SLAMConfig(frontend="oracle")
    config.retrieval.kind = "orb"
    config.keyframes.tau_disparity = 10.0
    summary = run_slam(world, tmp_path / "out", config, progress=False)
    assert summary["status"] == "complete" and summary["resolved"]["frontend"] == "oracle"
    assert summary["counts"]["submaps"] >= 2 and summary["ate"]["rmse"] < 1e-3  # exact depth and cameras
    assert not summary["resolved"]["attention_check"]  # the oracle declares no image-match scores
