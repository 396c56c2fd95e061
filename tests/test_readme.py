"""The README's Python example, executed as written (on a synthetic RGB-D sequence in place of the
TUM folder it names), and a silent run really being silent."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sl4slam.config import SLAMConfig
from sl4slam.runner import run_slam
from sl4slam.synthetic import write_synthetic_sequence

README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("readme") / "seq", num_frames=150, width=128, height=96,
                                    seed=4)


def _library_example() -> str:
    text = README.read_text()
    section = text[text.index("## As a library"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_readme_library_example_runs(sequence: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    code = _library_example().replace('"rgbd_dataset_freiburg1_xyz"', repr(str(sequence)))
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, str(README), "exec"), namespace)
    summary, result = namespace["summary"], namespace["result"]
    assert summary["status"] == "complete" and summary["counts"]["keyframes"] >= 4
    assert summary["config"]["sim"]["focal_error"] > 0  # the profile set in Python was applied
    assert (tmp_path / "result" / "trajectory.txt").is_file()
    assert len(result.keyframes) == summary["counts"]["keyframes"]
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("simulated frontend on cpu") and printed[-1].startswith(f"({len(result.keyframes)}, 4, 4)")


def test_a_run_without_progress_prints_nothing(sequence: Path, tmp_path: Path, capsys) -> None:
    """``progress=False`` used to leave the six-line summary on stdout."""
    config = SLAMConfig(frontend="simulated")
    config.retrieval.kind = "none"
    run_slam(sequence, tmp_path / "out", config, progress=False)
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    run_slam(sequence, tmp_path / "loud", config, progress=True)
    captured = capsys.readouterr()
    assert "ATE RMSE" in captured.out and "simulated frontend" in captured.err


def test_a_run_that_fails_before_any_work_leaves_no_folder(tmp_path: Path) -> None:
    """Every bad-input try used to leave an empty --out folder behind."""
    from sl4slam.errors import UserError

    config = SLAMConfig(frontend="simulated")
    with pytest.raises(UserError, match="does not exist"):
        run_slam(tmp_path / "no-such-sequence", tmp_path / "out1", config, progress=False)
    (tmp_path / "images").mkdir()
    with pytest.raises(UserError, match="contains no images"):
        run_slam(tmp_path / "images", tmp_path / "out2", config, progress=False)
    assert not (tmp_path / "out1").exists() and not (tmp_path / "out2").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    with pytest.raises(UserError):
        run_slam(tmp_path / "images", kept, config, progress=False)
    assert kept.is_dir()  # a folder the user made is left alone
