"""The command line: generated flags, config files, and one-line errors for bad input."""

from __future__ import annotations

import json
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
