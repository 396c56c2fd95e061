"""The model of the next submap overlapping the graph work of this one (``sl4slam.schedule``): the
same outputs as one submap after the other, byte for byte, whatever fails; a worker that really
runs ahead; Ctrl-C and failures as in a sequential run."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from sl4slam.backend import SL4PoseGraph, SubmapBackend
from sl4slam.config import SLAMConfig
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.io import open_source
from sl4slam.pipeline import SLAMPipeline
from sl4slam.result.outputs import write_outputs
from sl4slam.runner import RunInterrupted, run_slam
from sl4slam.synthetic import write_synthetic_sequence
from sl4slam.types import FrontendCapabilities


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """A 360-frame lap at 160x120 that returns to its start."""
    return write_synthetic_sequence(tmp_path_factory.mktemp("schedule") / "world", num_frames=360, width=160, height=120,
                                    seed=1)


def lap_config(overlap: bool, **changes) -> SLAMConfig:
    config = SLAMConfig(frontend="simulated", overlap=overlap)
    config.keyframes.tau_disparity = 12.0
    config.retrieval.kind = "orb"
    config.sim.profile = "vggt"
    for key, value in changes.items():
        section, _, name = key.rpartition(".")
        setattr(getattr(config, section) if section else config, name, value)
    return config


class FailingFrontend(SimulatedFrontend):
    """Raises on the chosen submaps (like a model running out of memory)."""

    capabilities = FrontendCapabilities(needs_ground_truth=True, scores_pairs=True)

    def __init__(self, config, failing: set[int]):
        super().__init__(config)
        self.failing = failing

    def reconstruct(self, frames, submap_id, **kwargs):
        if submap_id in self.failing:
            raise RuntimeError("CUDA out of memory (simulated)")
        return super().reconstruct(frames, submap_id, **kwargs)


class DroppingGraph(SL4PoseGraph):
    """GTSAM fails on every update that holds the chosen node (the graph drops that submap)."""

    def __init__(self, config, node: int):
        super().__init__(config)
        self.node = node

    def _solve(self, factors, values, loop_keys):
        if self.node in self._pending_ids:
            raise RuntimeError("IndeterminateSystemException (simulated)")
        return super()._solve(factors, values, loop_keys)


def _outputs(world: Path, out: Path, config: SLAMConfig, frontend=None, backend=None) -> tuple[SLAMPipeline, dict]:
    pipeline = SLAMPipeline.from_config(config, frontend, backend=backend)
    result = pipeline.run(open_source(str(world)), progress=False)
    summary = write_outputs(result, out, pipeline.resolved, source_name="world")
    return pipeline, summary


def _same_outputs(a: Path, b: Path, summary_a: dict, summary_b: dict) -> None:
    for name in ("trajectory.txt", "trajectory_gt.txt", "map.ply"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    keyframes = sorted(p.name for p in (a / "keyframes").iterdir())
    assert keyframes == sorted(p.name for p in (b / "keyframes").iterdir())
    for name in keyframes:
        assert (a / "keyframes" / name).read_bytes() == (b / "keyframes" / name).read_bytes(), name
    assert _untimed(summary_a) == _untimed(summary_b)


def _untimed(value):
    """A summary without wall times, memory and the settings (which differ in ``overlap`` only)."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if k not in ("seconds", "memory", "config", "resolved")}
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


@pytest.mark.parametrize("graph, false_loops", [("keyframe", 0.0), ("submap", 1.0)])
def test_overlapped_and_sequential_runs_are_byte_identical(world: Path, tmp_path: Path, graph: str,
                                                          false_loops: float) -> None:
    runs = {}
    for overlap in (False, True):
        config = lap_config(overlap, **{"backend.graph": graph, "false_loops.rate": false_loops})
        frontend = FailingFrontend(config.sim, {4})  # a failure inside the worker, handled as today
        runs[overlap] = _outputs(world, tmp_path / str(overlap), config, frontend)
    (sequential, summary_s), (overlapped, summary_o) = runs[False], runs[True]
    assert sequential.resolved.overlap is False and overlapped.resolved.overlap is True
    # true loops accepted, or wrong places rejected
    assert summary_o["counts"]["loops" if false_loops == 0 else "loops_rejected"] >= 1
    assert [f["submap"] for f in summary_o["frontend_failures"]] == [4]
    _same_outputs(tmp_path / "False", tmp_path / "True", summary_s, summary_o)


def test_a_submap_the_graph_drops_is_redone_identically(world: Path, tmp_path: Path) -> None:
    """The next submap was assembled on the dropped one's last keyframe while it was being worked
    on: it is rebuilt on the frame the graph holds and run again, as a sequential run assembles it."""
    runs = {}
    for overlap in (False, True):
        config = lap_config(overlap, **{"backend.graph": "submap"})
        backend = SubmapBackend(DroppingGraph(config.backend, node=3))
        runs[overlap] = _outputs(world, tmp_path / str(overlap), config, backend=backend)
    summary = runs[True][1]
    assert summary["dropped_frames"]["graph failed"] > 0
    assert any("could not be started either" in s["reason"] for s in summary["segments"])
    _same_outputs(tmp_path / "False", tmp_path / "True", runs[False][1], summary)


def test_the_next_forward_runs_while_the_graph_works(world: Path, monkeypatch) -> None:
    """The frontend of submap k+1 starts before the graph work of submap k ends (an ordering, not a
    timing: the graph work of submap 1 waits for the forward of submap 2 to have begun). As with a
    real model, the forward is slower than keyframe selection: the forward of submap 1 returns once
    the keyframes of submap 2 are selected."""
    from sl4slam import schedule

    config = lap_config(True)
    started: dict[int, threading.Event] = {}
    submitted: list[threading.Event] = [threading.Event() for _ in range(64)]  # one per batch of keyframes
    submit = schedule.OverlappedScheduler.submit

    def counting_submit(self, new_frames):
        submitted[sum(e.is_set() for e in submitted)].set()
        submit(self, new_frames)

    monkeypatch.setattr(schedule.OverlappedScheduler, "submit", counting_submit)

    class SlowModel(SimulatedFrontend):
        def reconstruct(self, frames, submap_id, **kwargs):
            started.setdefault(submap_id, threading.Event()).set()
            if submap_id == 1:
                submitted[2].wait(timeout=120)  # the keyframes of submap 2 are selected meanwhile
            return super().reconstruct(frames, submap_id, **kwargs)

    pipeline = SLAMPipeline.from_config(config, SlowModel(config.sim))
    integrate = pipeline.integrate
    overlapped = []

    def waiting_integrate(work, prediction):
        if work.submap_id == 1:
            overlapped.append(started.setdefault(2, threading.Event()).wait(timeout=120))
        return integrate(work, prediction)

    pipeline.integrate = waiting_integrate
    pipeline.run(open_source(str(world)), progress=False)
    assert overlapped == [True]


def test_ctrl_c_during_an_overlapped_run_leaves_valid_outputs(world: Path, tmp_path: Path) -> None:
    config = lap_config(True)

    def stop_after_three(pipeline, submap_id: int) -> None:
        if submap_id == 2:
            pipeline.stop_requested = True  # what the SIGINT handler does

    with pytest.raises(RunInterrupted, match="interrupted after") as caught:
        run_slam(world, tmp_path / "out", config, progress=False, on_submap=stop_after_three)
    assert caught.value.exit_code == 130
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    finished = {e["submaps"][1] for e in summary["edges"] if e["kind"] == "odometry"} | {0}
    assert summary["status"] == "interrupted" and summary["counts"]["keyframes"] > 0
    assert f"after {len(finished)} finished submap" in summary["stop_reason"]
    stamps = np.loadtxt(tmp_path / "out" / "trajectory.txt")
    assert len(stamps) == summary["counts"]["keyframes"] and np.isfinite(stamps).all()
    # a second Ctrl-C stops at once, in the middle of the schedule: still valid outputs
    def abort(pipeline, submap_id: int) -> None:
        if submap_id == 3:
            raise KeyboardInterrupt

    with pytest.raises(RunInterrupted) as caught:
        run_slam(world, tmp_path / "aborted", config, progress=False, on_submap=abort)
    assert caught.value.exit_code == 130
    summary = json.loads((tmp_path / "aborted" / "summary.json").read_text())
    assert summary["status"] == "interrupted" and np.isfinite(np.loadtxt(tmp_path / "aborted" / "trajectory.txt")).all()


def test_overlap_needs_older_loop_frames() -> None:
    from sl4slam.resolve import resolve

    config = lap_config(True, **{"retrieval.tau_interval": 0})
    resolved = resolve(config)
    assert not resolved.overlap and any("overlap: off" in note for note in resolved.notes)
