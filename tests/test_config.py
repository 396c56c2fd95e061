"""The config tree: every section validates itself, with one line naming the flag and the key."""

from __future__ import annotations

import dataclasses

import pytest

from sl4slam.cli import build_parser
from sl4slam.config import AlignmentConfig, SLAMConfig, sections
from sl4slam.errors import UserError

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
    ("sim", "false_loop_rate", 2.0, "--sim-false-loop-rate"),
    ("output", "max_map_points", 0, "--max-map-points"),
    ("vggt", "device", "tpu", "--device"),
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


def test_a_projective_model_cannot_feed_a_similarity_graph() -> None:
    config = SLAMConfig()
    config.backend.kind, config.alignment.model = "sim3", "sl4"
    with pytest.raises(UserError, match="Sim\\(3\\) graph"):
        config.validate()
    config.alignment.model = "sim3-points"
    config.validate()


def test_advanced_settings_are_grouped_last_in_help() -> None:
    text = build_parser()._subparsers._group_actions[0].choices["run"].format_help()
    assert text.index("--ransac-hypothesis-batch") > text.index("--sim-perspective")  # advanced after every main group
    assert "[alignment] advanced settings" in text
    assert AlignmentConfig.advanced <= {f.name for f in dataclasses.fields(AlignmentConfig)}
