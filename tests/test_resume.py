"""``sl4slam run ... --resume``: a run killed outright (SIGKILL) inside the model, inside the graph
update, while writing its recording or its outputs continues from its recording, and its outputs
are byte-identical to those of a run that was never interrupted, for both graph designs; the model
runs again only on the submaps it had not returned; every bad resumption is one line, before any
frame is read.

The kills are deterministic: the CLI runs in a child process (``python -c``) that patches the
function where it dies, so no test depends on timing or machine load."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sl4slam.io as io
from sl4slam.cli import main
from sl4slam.config import SLAMConfig
from sl4slam.errors import UserError
from sl4slam.frontend.cache import ResumingFrontend, input_digest, recording_path
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.io import open_source
from sl4slam.resume import MANIFEST, RECORDING_DIR, recording_bytes
from sl4slam.runner import RunInterrupted, run_slam
from sl4slam.synthetic import write_synthetic_sequence

# A lap at 160x120 that returns to its start: 12 submaps of 8 keyframes, one loop closed.
ARGS = ["--frontend", "simulated", "--tau-disparity", "12", "--submap-size", "8", "--retrieval", "orb"]
GRAPH = {"keyframe": [], "submap": ["--graph", "submap"]}  # the keyframe graph is the default

KILL_POINTS = Path(__file__).resolve().parents[1] / "benchmarks" / "harness" / "kill_points.py"
"""The child that dies at a chosen point (shared with ``benchmarks/bench_resume.py``)."""


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("resume") / "world", num_frames=360, width=160, height=120,
                                    seed=1)


@pytest.fixture(scope="module")
def reference(world: Path, tmp_path_factory) -> dict[str, Path]:
    """An uninterrupted run per graph design (the same command, never killed)."""
    runs = {}
    for graph in ("keyframe", "submap"):
        out = tmp_path_factory.mktemp("reference") / graph
        assert main(["run", str(world), "--out", str(out), *ARGS, *GRAPH[graph], "--quiet"]) == 0
        runs[graph] = out
    return runs


def run_child(world: Path, out: Path, point: str, log: Path, *extra: str) -> subprocess.CompletedProcess:
    """``sl4slam run world --out out`` in a child that dies at ``point`` ("model:K": in submap K's
    forward; "graph:K": in the graph update of submap K; "recording:K": half-way through writing
    submap K's recording; "outputs:N": half-way through the N-th keyframe file; "": never), logging
    the submaps it gives the model to ``log``."""
    return subprocess.run([sys.executable, str(KILL_POINTS), point, str(log), "run", str(world), "--out", str(out), *ARGS,
                           *extra], capture_output=True, text=True, timeout=600)


def model_calls(log: Path) -> list[int]:
    return [int(line) for line in log.read_text().split()] if log.exists() else []


def untimed(value):
    """A summary without wall times and memory."""
    if isinstance(value, dict):
        return {k: untimed(v) for k, v in value.items() if k not in ("seconds", "memory")}
    if isinstance(value, list):
        return [untimed(v) for v in value]
    return value


def assert_same_outputs(expected: Path, out: Path, **written_settings) -> None:
    """The outputs of ``out`` are those of ``expected``, byte for byte (``summary.json`` but its times,
    and for its settings ``written_settings``: ``[output]`` settings that differ on purpose)."""
    for name in ("trajectory.txt", "trajectory_gt.txt", "map.ply"):
        assert (expected / name).read_bytes() == (out / name).read_bytes(), name
    names = sorted(p.name for p in (expected / "keyframes").iterdir())
    assert names and names == sorted(p.name for p in (out / "keyframes").iterdir())
    for name in names:
        assert (expected / "keyframes" / name).read_bytes() == (out / "keyframes" / name).read_bytes(), name
    summary = json.loads((out / "summary.json").read_text())
    reference = json.loads((expected / "summary.json").read_text())
    reference["config"]["output"].update(written_settings)
    assert untimed(reference) == untimed(summary)
    assert summary["status"] == "complete"
    assert not (out / RECORDING_DIR).exists()  # removed once the run completed
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


# every kill point and both graphs in the fast set; the other graph at the same points is marked slow
@pytest.mark.parametrize("graph, point", [("keyframe", "model:5"),
                                          pytest.param("submap", "model:5", marks=pytest.mark.slow),
                                          pytest.param("keyframe", "graph:6", marks=pytest.mark.slow),
                                          ("submap", "graph:6"), ("submap", "outputs:20"),
                                          ("keyframe", "recording:4")])
def test_a_killed_run_resumes_to_the_same_bytes(world: Path, reference: dict, tmp_path: Path, graph: str,
                                                point: str) -> None:
    out, killed_log, resumed_log = tmp_path / "out", tmp_path / "killed.log", tmp_path / "resumed.log"
    killed = run_child(world, out, point, killed_log, *GRAPH[graph], "--quiet")
    assert killed.returncode == -9, killed.stderr[-2000:]
    assert (out / RECORDING_DIR / MANIFEST).is_file()
    resumed = run_child(world, out, "", resumed_log, *GRAPH[graph], "--resume")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert_same_outputs(reference[graph], out)
    submaps = json.loads((out / "summary.json").read_text())["counts"]["submaps"]
    again = model_calls(resumed_log)
    kind, at = point.split(":")
    at = int(at)
    if kind == "model":  # the forward being killed is the only one redone
        assert again == list(range(at, submaps))
    elif kind == "recording":  # so is the one whose recording was cut short (its temporary file is gone)
        assert again == list(range(at, submaps))
    elif kind == "graph":  # submap `at` was recorded before its graph work; the next forward may have been too
        assert set(range(at + 2, submaps)) <= set(again) <= set(range(at + 1, submaps))
    else:  # every forward was recorded before the outputs were written
        assert again == []
    assert f"resumed: {submaps - len(again)} submap(s) replayed from the recording" in resumed.stderr


def test_a_run_killed_twice_resumes_twice(world: Path, reference: dict, tmp_path: Path) -> None:
    out = tmp_path / "out"
    logs = [tmp_path / f"{k}.log" for k in range(3)]
    assert run_child(world, out, "model:3", logs[0], "--quiet").returncode == -9
    assert run_child(world, out, "model:8", logs[1], "--quiet", "--resume").returncode == -9
    # settings that decide only what is written (or when) may change on resumption
    done = run_child(world, out, "", logs[2], "--quiet", "--resume", "--checkpoint-seconds", "0")
    assert done.returncode == 0, done.stderr[-2000:]
    assert model_calls(logs[1]) == [3, 4, 5, 6, 7, 8]
    assert model_calls(logs[2])[0] == 8
    assert_same_outputs(reference["keyframe"], out, checkpoint_seconds=0.0)


def test_a_cut_or_corrupt_recording_is_named_and_only_its_submap_redone(world: Path, reference: dict,
                                                                       tmp_path: Path) -> None:
    """A recording cut short is found (and named) before any frame is read; one with a flipped byte
    when it is replayed (its checksum). Only those submaps go to the model again: each later
    recording is checked on its own, and holds the digest of the inputs it was made from."""
    out = tmp_path / "out"
    assert run_child(world, out, "model:7", tmp_path / "killed.log", "--quiet").returncode == -9
    cut, flipped = recording_path(out / RECORDING_DIR, 2), recording_path(out / RECORDING_DIR, 4)
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    data = bytearray(flipped.read_bytes())
    data[len(data) // 2] ^= 0xFF
    flipped.write_bytes(bytes(data))
    resumed = run_child(world, out, "", tmp_path / "resumed.log", "--quiet", "--resume")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    named = [line for line in resumed.stderr.splitlines() if "submap_0000" in line]
    assert len(named) == 2 and "submap_00002.npz is cut or corrupt" in named[0] and "submap 2" in named[0]
    assert "submap_00004.npz cannot be read" in named[1] and "CRC" in named[1]
    submaps = json.loads((out / "summary.json").read_text())["counts"]["submaps"]
    assert model_calls(tmp_path / "resumed.log") == [2, 4, *range(7, submaps)]
    assert_same_outputs(reference["keyframe"], out)


# ---------------------------------------------------------------------- the recording itself
def test_a_replayed_recording_is_the_models_output_byte_for_byte(world: Path, tmp_path: Path) -> None:
    config = SLAMConfig(frontend="simulated")
    config.sim.profile = "vggt"
    from sl4slam.resolve import resolve

    sim = resolve(config).config.sim
    source = open_source(str(world))
    frames = [source.get(i) for i in (0, 7, 14, 21)]
    keywords = {"match_pairs": [(0, 3), (1, 3)]}
    recorder = ResumingFrontend(SimulatedFrontend(sim), tmp_path)
    made = recorder.reconstruct(frames, 3, **keywords)
    assert recorder.reconstructed == [3] and recorder.replayed == []

    class NoModel(SimulatedFrontend):
        def reconstruct(self, *args, **kwargs):
            raise AssertionError("the model ran although the recording holds these inputs")

    replayer = ResumingFrontend(NoModel(sim), tmp_path, record=False)
    replayed = replayer.reconstruct(frames, 3, **keywords)
    assert replayer.replayed == [3]
    for name, value in vars(made).items():
        again = getattr(replayed, name)
        if value is None:
            assert again is None, name
        else:
            value = np.asarray(value)
            assert (again.dtype, again.shape) == (value.dtype, value.shape), name
            assert again.tobytes() == value.tobytes(), name
    # other inputs (another frame, other pairs): the model runs, and the recording is not replaced
    with pytest.raises(AssertionError, match="the model ran"):
        replayer.reconstruct(frames[:3] + [source.get(22)], 3, **keywords)
    with pytest.raises(AssertionError, match="the model ran"):
        replayer.reconstruct(frames, 3, match_pairs=[(0, 3)])
    assert input_digest(frames, keywords) != input_digest(frames, {"match_pairs": [(0, 2), (1, 3)]})
    # the uncompressed recording's size, as documented per pixel
    S, H, W = made.depth.shape
    size = recording_path(tmp_path, 3).stat().st_size
    assert abs(size - recording_bytes(S, H, W)) <= 4096


def sim_config(**changes) -> SLAMConfig:
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 12.0
    config.submap.size = 8
    config.retrieval.kind = "orb"
    for key, value in changes.items():
        section, _, name = key.rpartition(".")
        setattr(getattr(config, section) if section else config, name, value)
    return config


def stop_at(submap: int):
    def stop(pipeline, submap_id: int) -> None:
        if submap_id == submap:
            pipeline.stop_requested = True  # what SIGINT does

    return stop


@pytest.fixture(scope="module")
def interrupted(world: Path, tmp_path_factory) -> Path:
    """A run stopped after its third submap (as by Ctrl-C): its checkpoint stays."""
    out = tmp_path_factory.mktemp("interrupted") / "out"
    with pytest.raises(RunInterrupted, match="--resume continues it"):
        run_slam(world, out, sim_config(), progress=False, on_submap=stop_at(2))
    assert (out / RECORDING_DIR / MANIFEST).is_file()
    return out


def test_the_recording_is_removed_kept_or_never_made_as_asked(world: Path, tmp_path: Path) -> None:
    run_slam(world, tmp_path / "plain", sim_config(**{"source.max_frames": 120}), progress=False)
    assert not (tmp_path / "plain" / RECORDING_DIR).exists()
    run_slam(world, tmp_path / "kept", sim_config(**{"source.max_frames": 120, "output.cache_frontend": True}),
             progress=False)
    kept = sorted((tmp_path / "kept" / RECORDING_DIR).iterdir())
    assert kept and all(p.name.startswith("submap_") for p in kept)  # no manifest: nothing to resume
    with pytest.raises(RunInterrupted):
        run_slam(world, tmp_path / "none", sim_config(**{"output.resumable": False}), progress=False,
                 on_submap=stop_at(1))
    assert not (tmp_path / "none" / RECORDING_DIR).exists()
    with pytest.raises(UserError, match="no checkpoint in --out .* --no-resumable"):
        run_slam(world, tmp_path / "none", sim_config(**{"output.resumable": False}), progress=False, resume=True)
    with pytest.raises(UserError, match="finished .*nothing to continue"):
        run_slam(world, tmp_path / "plain", sim_config(**{"source.max_frames": 120}), progress=False, resume=True)


# ---------------------------------------------------------------------- bad resumptions: one line each
@pytest.fixture
def no_frame_reads(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a frame source was opened before the resumption was checked")

    monkeypatch.setattr(io, "open_source", refuse)


def one_line(capsys, argv: list[str]) -> str:
    """The CLI's error line (exit status 2)."""
    assert main(argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("sl4slam: error: --resume"), lines
    return lines[0]


def test_resume_without_a_checkpoint_is_one_line(tmp_path: Path, capsys, no_frame_reads) -> None:
    line = one_line(capsys, ["run", "anything", "--out", str(tmp_path / "absent"), *ARGS, "--resume"])
    assert "does not exist" in line and not (tmp_path / "absent").exists()
    (tmp_path / "empty").mkdir()
    assert "holds no run" in one_line(capsys, ["run", "anything", "--out", str(tmp_path / "empty"), *ARGS, "--resume"])


def test_resume_with_overwrite_replay_or_a_live_camera_is_refused(interrupted: Path, capsys, no_frame_reads) -> None:
    assert "--overwrite would delete" in one_line(
        capsys, ["run", "anything", "--out", str(interrupted), *ARGS, "--resume", "--overwrite"])
    assert "--replay run has no model work" in one_line(
        capsys, ["run", "anything", "--out", str(interrupted), *ARGS, "--resume", "--replay",
                 str(interrupted / RECORDING_DIR)])
    assert "live camera or stream" in one_line(capsys, ["run", "0", "--out", str(interrupted), *ARGS, "--resume"])
    assert (interrupted / RECORDING_DIR / MANIFEST).is_file()
    # without --resume, the unfinished run is pointed out
    assert main(["run", "anything", "--out", str(interrupted), *ARGS]) == 2
    assert "did not finish; pass --resume to continue it, --overwrite to replace it" in capsys.readouterr().err


def test_resume_with_other_settings_names_the_first_one(interrupted: Path, capsys, no_frame_reads) -> None:
    line = one_line(capsys, ["run", "anything", "--out", str(interrupted), *ARGS, "--submap-size", "6", "--resume"])
    assert "--submap-size (config key submap.size) was 8, now 6" in line
    line = one_line(capsys, ["run", "anything", "--out", str(interrupted), *ARGS, "--device", "cuda", "--resume"])
    assert "--device (config key device) was 'cpu', now 'cuda'" in line


def test_resume_from_another_source_is_one_line(world: Path, interrupted: Path, tmp_path: Path, capsys) -> None:
    shorter = ["run", str(world), "--out", str(interrupted), *ARGS, "--max-frames", "300", "--resume"]
    assert "--max-frames (config key source.max_frames)" in one_line(capsys, shorter)
    other = write_synthetic_sequence(tmp_path / "other", num_frames=300, width=160, height=120, seed=5)
    line = one_line(capsys, ["run", str(other), "--out", str(interrupted), *ARGS, "--resume"])
    assert "read another source" in line and "360 frames" in line and "300 frames" in line
    edited = tmp_path / "edited"
    shutil.copytree(world, edited)
    listed = [line.split()[1] for line in (edited / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    shutil.copyfile(edited / listed[181], edited / listed[180])  # the same names, one frame's pixels changed
    line = one_line(capsys, ["run", str(edited), "--out", str(interrupted), *ARGS, "--resume"])
    assert "frame 180 of" in line and "is not the one it read" in line
    assert (interrupted / RECORDING_DIR / MANIFEST).is_file()


def test_resume_from_another_format_version_is_one_line(interrupted: Path, tmp_path: Path, capsys,
                                                        no_frame_reads) -> None:
    out = tmp_path / "out"
    shutil.copytree(interrupted, out)
    manifest = out / RECORDING_DIR / MANIFEST
    content = json.loads(manifest.read_text())
    content["format"]["version"] = 99
    manifest.write_text(json.dumps(content))
    line = one_line(capsys, ["run", "anything", "--out", str(out), *ARGS, "--resume"])
    assert "version 99" in line and "reads sl4slam-resume version 1" in line
    manifest.write_text("{cut")
    assert "cannot be read" in one_line(capsys, ["run", "anything", "--out", str(out), *ARGS, "--resume"])


def test_an_interrupted_run_resumes_in_process(world: Path, reference: dict, interrupted: Path, tmp_path: Path,
                                               monkeypatch) -> None:
    """A run stopped by Ctrl-C (its outputs written, status "interrupted") resumes through the
    library call too; the model starts after the submaps it had finished."""
    out = tmp_path / "out"
    shutil.copytree(interrupted, out)
    calls: list[int] = []
    original = SimulatedFrontend.reconstruct

    def counting(self, frames, submap_id, **keywords):
        calls.append(submap_id)
        return original(self, frames, submap_id, **keywords)

    monkeypatch.setattr(SimulatedFrontend, "reconstruct", counting)
    summary = run_slam(world, out, sim_config(), progress=False, resume=True)
    assert summary["status"] == "complete" and calls and calls[0] >= 3
    assert_same_outputs(reference["keyframe"], out)


def test_a_recording_that_cannot_be_written_is_one_line_and_the_run_goes_on(world: Path, tmp_path: Path,
                                                                           monkeypatch, caplog) -> None:
    import sl4slam.frontend.cache as cache

    def full(path, arrays, compressed=True):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cache, "atomic_write_npz", full)
    config = sim_config(**{"source.max_frames": 120})
    summary = run_slam(world, tmp_path / "out", config, progress=False)
    assert summary["status"] == "complete" and summary["counts"]["submaps"] >= 2
    assert summary["frontend_failures"] == []  # the model's outputs were used all the same
    warned = [r.getMessage() for r in caplog.records if "cannot record" in r.getMessage()]
    assert len(warned) == 1 and "No space left on device" in warned[0]
