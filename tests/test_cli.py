"""The command line: generated flags, config files, and one-line errors for bad input."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sl4slam.cli import build_parser, config_from_args, main


def _run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sl4slam.cli", *args], capture_output=True, text=True, timeout=120)


def _assert_one_line_error(proc: subprocess.CompletedProcess, *words: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    for word in words:
        assert word in lines[0]


def test_flags_are_generated_from_the_config_tree() -> None:
    args = build_parser().parse_args([
        "run", "src", "--out", "o", "--submap-size", "32", "--tau-disparity", "50", "--backend", "sim3",
        "--retrieval", "none", "--sim-perspective", "0.1", "--tau-conf", "10", "--ransac-iterations", "500",
        "--keyframes", "none", "--salad-weights", "w.ckpt",
    ])
    config = config_from_args(args)
    assert config.submap.size == 32
    assert config.keyframes.tau_disparity == 50.0
    assert config.backend.kind == "sim3"
    assert config.retrieval.kind == "none"
    assert config.sim.perspective == 0.1
    assert config.submap.tau_conf == 10.0
    assert config.alignment.ransac_iterations == 500
    assert config.output.keyframes == "none"
    assert config.retrieval.salad_weights == "w.ckpt"


def test_config_file_then_flags(tmp_path: Path) -> None:
    (tmp_path / "c.toml").write_text("frontend = 'simulated'\n[submap]\nsize = 8\n[sim]\nperspective = 0.05\n")
    config = config_from_args(build_parser().parse_args(
        ["run", "src", "--out", "o", "--config", str(tmp_path / "c.toml"), "--sim-perspective", "0.2"]))
    assert config.frontend == "simulated" and config.submap.size == 8
    assert config.sim.perspective == 0.2  # the flag wins over the file
    (tmp_path / "c.json").write_text(json.dumps({"backend": {"sigma": 0.1}}))
    config = config_from_args(build_parser().parse_args(["run", "src", "--out", "o", "--config", str(tmp_path / "c.json")]))
    assert config.backend.sigma == 0.1


def test_unknown_config_key_is_a_one_line_error(tmp_path: Path, capsys) -> None:
    (tmp_path / "bad.toml").write_text("[submap]\nsiz = 8\n")
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--config", str(tmp_path / "bad.toml")]) == 2
    err = capsys.readouterr().err
    assert "siz" in err and "submap" in err


def test_nonexistent_source_is_a_one_line_error(tmp_path: Path) -> None:
    proc = _run_cli("run", str(tmp_path / "missing"), "--out", str(tmp_path / "out"), "--frontend", "simulated")
    _assert_one_line_error(proc, "missing")


def test_single_frame_is_a_one_line_error(tmp_path: Path) -> None:
    folder = tmp_path / "one"
    folder.mkdir()
    cv2.imwrite(str(folder / "000001.png"), np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8))
    proc = _run_cli("run", str(folder), "--out", str(tmp_path / "out"), "--frontend", "simulated", "--quiet")
    _assert_one_line_error(proc, "frame")
    assert not (tmp_path / "out" / "trajectory.txt").exists()


@pytest.mark.parametrize("flag, value", [("--ransac-confidence", "1.5"), ("--ransac-iterations", "0"),
                                         ("--backend-sigma", "0"), ("--submap-size", "0")])
def test_bad_setting_is_a_one_line_error_before_any_work(tmp_path: Path, capsys, flag: str, value: str) -> None:
    missing = tmp_path / "missing"  # the setting is checked before the source is even opened
    assert main(["run", str(missing), "--out", str(tmp_path / "o"), "--frontend", "simulated", flag, value]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and flag.lstrip("-").split("-")[-1] in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("verb", ["run", "demo", "synth", "convert", "ate"])
def test_every_verb_has_help(verb: str) -> None:
    proc = _run_cli(verb, "--help")
    assert proc.returncode == 0 and "usage" in proc.stdout


def test_ate_prints_metres_and_labels_the_scale(tmp_path: Path, capsys) -> None:
    times = np.arange(6) * 0.1
    positions = np.stack([times, np.sin(times), 0.5 * times], axis=1)
    for name, scale in (("gt.txt", 1.0), ("est.txt", 0.5)):  # the estimate at half the size
        (tmp_path / name).write_text("".join(f"{t:.3f} {' '.join(f'{v:.6f}' for v in scale * p)} 0 0 0 1\n"
                                             for t, p in zip(times, positions)))
    assert main(["ate", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt")]) == 0
    line = capsys.readouterr().out.strip()
    for figure in ("rmse", "mean", "median", "max"):
        assert re.search(rf"\b{figure} \d+\.\d+ m\b", line), line
    assert re.search(r"Sim\(3\) scale factor 2\.0000", line), line
    assert main(["ate", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--no-scale"]) == 0
    line = capsys.readouterr().out.strip()
    assert re.search(r"\brmse \d+\.\d+ m\b", line) and "scale not corrected" in line, line


# ------------------------------------------------------------------------------------- help texts
def test_run_help_is_short_and_shows_the_settings_most_runs_touch(capsys) -> None:
    from sl4slam.cli_help import RUN_OPTIONS, common_destinations

    with pytest.raises(SystemExit) as stop:
        main(["run", "--help"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    assert len(text.splitlines()) < 80
    for flag in (*RUN_OPTIONS, "--frontend", "--weights", "--device", "--intrinsics", "--graph", "--submap-size",
                 "--retrieval", "--sim-profile"):
        assert re.search(rf"^\s+{re.escape(flag)}\b", text, re.M), flag
    assert len(common_destinations()) >= 10
    assert "--help-all" in text and "--ransac-iterations" not in text  # the rest is one flag away


def test_help_all_lists_every_setting_and_searches(capsys) -> None:
    parser = build_parser()
    run = next(a for a in parser._actions if isinstance(a, __import__("argparse")._SubParsersAction)).choices["run"]
    every_flag = {flag for action in run._actions for flag in action.option_strings}
    with pytest.raises(SystemExit):
        main(["run", "--help-all"])
    text = capsys.readouterr().out
    assert all(flag in text for flag in every_flag)
    with pytest.raises(SystemExit) as stop:
        main(["run", "--help-all", "RANSAC-SEED"])  # case-insensitive
    assert stop.value.code == 0
    found = capsys.readouterr().out
    assert "--ransac-seed" in found and "--submap-size" not in found and len(found.splitlines()) < 10


def test_help_all_with_a_word_that_matches_nothing_is_one_line() -> None:
    proc = _run_cli("run", "--help-all", "zzqx")
    _assert_one_line_error(proc, "zzqx", "--help-all")
    assert proc.stdout == ""


def test_a_mistyped_flag_gets_runs_usage_and_the_closest_names(tmp_path: Path) -> None:
    proc = _run_cli("run", str(tmp_path), "--out", str(tmp_path / "o"), "--submap-sise", "8")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines[0].startswith("usage: sl4slam run SOURCE")  # run's usage, not the top level's
    assert "--submap-sise" in lines[-1] and "did you mean --submap-size" in lines[-1]
    proc = _run_cli("run", str(tmp_path), "--out", str(tmp_path / "o"), "--qqqqqqq")
    assert "no flag of that name" in proc.stderr and "sl4slam run --help" in proc.stderr
    proc = _run_cli("export", str(tmp_path), "--formt", "ply")
    assert "usage: sl4slam export" in proc.stderr and "did you mean --format" in proc.stderr
