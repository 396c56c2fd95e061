"""The config tree: every section validates itself, with one line naming the flag and the key."""

from __future__ import annotations

import dataclasses

import pytest

from sl4slam.cli import build_parser, config_from_args
from sl4slam.config import AlignmentConfig, SLAMConfig, config_from_dict, sections
from sl4slam.errors import UserError
from sl4slam.resolve import resolve

BAD_VALUES = [
    ("submap", "tau_conf", 150.0, "--tau-conf"),
    ("submap", "tau_conf", -5.0, "--tau-conf"),
    ("output", "voxel_size", -1.0, "--voxel-size"),
    ("keyframes", "tau_disparity", -1.0, "--tau-disparity"),
    ("alignment", "min_inliers", 0, "--ransac-min-inliers"),
    ("alignment", "max_points", 0, "--ransac-max-points"),
    ("alignment", "inlier_threshold", float("nan"), "--ransac-inlier-threshold"),
    ("alignment", "model", "affine", "--alignment"),
    ("backend", "effective_points", 0.0, "--backend-effective-points"),
    ("backend", "loop_kernel", "tukey", "--backend-loop-kernel"),
    ("retrieval", "orb_ratio", 1.5, "--orb-ratio"),
    ("loops", "consistency_quantile", 1.0, "--loop-consistency-quantile"),
    ("false_loops", "rate", 2.0, "--false-loop-rate"),
    ("output", "max_map_points", 0, "--max-map-points"),
    ("model", "head_chunk_frames", 0, "--head-chunk-frames"),
    ("localize", "min_inliers", 2, "--localize-min-inliers"),
    ("source", "stride", 0, "--stride"),
]


@pytest.mark.parametrize("section, name, value, flag", BAD_VALUES)
def test_a_value_out_of_range_names_its_flag_and_key(section: str, name: str, value, flag: str) -> None:
    config = SLAMConfig()
    setattr(getattr(config, section), name, value)
    with pytest.raises(UserError) as caught:
        config.validate()
    message = str(caught.value)
    assert flag in message and f"{section}.{name}" in message and "\n" not in message


def test_defaults_are_valid_and_every_field_has_a_flag() -> None:
    config = SLAMConfig()
    config.validate()
    parser_flags = {option for action in build_parser()._subparsers._group_actions[0].choices["run"]._actions
                    for option in action.option_strings}
    for section in sections(config):
        for f in dataclasses.fields(section):
            assert section.flag(f.name) in parser_flags, (section.section, f.name)


def test_a_top_level_value_out_of_range_names_its_flag() -> None:
    with pytest.raises(UserError, match="--device \\(config key device\\)"):
        SLAMConfig(device="tpu").validate()


def test_a_projective_model_cannot_feed_a_similarity_graph() -> None:
    config = SLAMConfig(frontend="simulated")
    config.retrieval.kind = "none"
    config.backend.kind, config.alignment.model = "sim3", "sl4"
    with pytest.raises(UserError, match="Sim\\(3\\) graph"):
        resolve(config)
    config.alignment.model = "sim3-points"
    resolve(config)


def test_settings_of_earlier_releases_are_read_under_their_current_names() -> None:
    config = config_from_dict({"stride": 3, "max_frames": 50, "vggt": {"weights": "w.pt", "device": "cpu", "dtype": "bf16"},
                               "sim": {"false_loop_rate": 0.3, "seed": 2}})
    assert (config.source.stride, config.source.max_frames) == (3, 50)
    assert (config.model.weights, config.model.dtype, config.device) == ("w.pt", "bf16", "cpu")
    assert config.false_loops.rate == 0.3 and config.sim.seed == 2
    # the current key wins when both are given
    assert config_from_dict({"stride": 3, "source": {"stride": 5}}).source.stride == 5


def test_every_section_is_reachable_from_a_file_and_the_command_line(tmp_path) -> None:
    """The all-frame localization's settings were outside the tree: ``--all-frames`` always ran with
    its defaults."""
    (tmp_path / "c.toml").write_text("[localize]\nmin_inliers = 30\n[false_loops]\nrate = 0.2\n")
    args = build_parser().parse_args(["run", "src", "--out", "o", "--config", str(tmp_path / "c.toml"),
                                      "--localize-max-corners", "250", "--model", "pi3", "--sim-false-loop-rate", "0.4"])
    config = config_from_args(args)
    assert config.localize.min_inliers == 30 and config.localize.max_corners == 250
    assert config.frontend == "pi3" and config.false_loops.rate == 0.4


def test_advanced_settings_are_grouped_last_in_help() -> None:
    text = build_parser()._subparsers._group_actions[0].choices["run"].format_help()
    assert text.index("--ransac-hypothesis-batch") > text.index("--sim-perspective")  # advanced after every main group
    assert "[alignment] advanced settings" in text
    assert AlignmentConfig.advanced <= {f.name for f in dataclasses.fields(AlignmentConfig)}


def test_resolve_settles_every_auto_a_stage_would_read_and_takes_only_the_users_config() -> None:
    """The resolved tree holds no "auto" that a stage reads: the device, a model's precision and
    weights, the graph, the links, the upgrade, the retrieval and the attention check are settled;
    "auto" intrinsics become a flag to read the source's calibration. A resolved config is not
    resolved again."""
    config = SLAMConfig(frontend="da3-small", device="cpu")
    config.source.intrinsics = "auto"
    resolved = resolve(config)
    settled = resolved.config
    assert settled.model.dtype == "fp32" and settled.model.weights.startswith("depth-anything/")
    assert (settled.backend.graph, settled.alignment.model, settled.upgrade.mode) == ("keyframe", "calibration", "off")
    assert settled.retrieval.kind in ("orb", "salad") and settled.loops.verify_attention == "off"
    assert resolved.intrinsics is None and resolved.intrinsics_from_source
    given = SLAMConfig(frontend="simulated")
    given.source.intrinsics = "500,500,320,240"
    known = resolve(given)
    assert known.intrinsics.values() == [500.0, 500.0, 320.0, 240.0] and not known.intrinsics_from_source
    assert config.model.dtype == "auto" and config.source.intrinsics == "auto"  # the user's tree is not changed
    with pytest.raises(TypeError, match="takes a SLAMConfig"):
        resolve(resolved)


def test_field_declarations_are_the_one_home_of_their_flags_and_ranges() -> None:
    """A section's flag overrides, choices, help groups and single-field ranges come from its fields'
    ``setting(...)`` declarations; a field's own range is checked by the base section."""
    fields = {f.name: f for f in dataclasses.fields(AlignmentConfig)}
    assert AlignmentConfig.flag("model") == "--alignment" and fields["model"].metadata["flag"] == "--alignment"
    assert "planar_model" in AlignmentConfig.advanced and AlignmentConfig.choices["planar_model"][0] == "by-support"
    assert {name for name, f in fields.items() if f.metadata.get("advanced")} == AlignmentConfig.advanced
    bad = AlignmentConfig(inlier_threshold=-1.0)
    with pytest.raises(UserError, match="--ransac-inlier-threshold \\(config key alignment.inlier_threshold\\)"):
        bad.validate()
