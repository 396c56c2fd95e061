"""The model's windows ahead of the graph (``--workers N``; ``sl4slam.schedule.AheadScheduler`` and
``sl4slam.frontend.workers``): byte-identical to one submap after the other whatever fails, is
dropped or dies; one line for settings and sources that cannot have them."""

from __future__ import annotations

import os
import socket
import sys
import threading
from functools import partial
from pathlib import Path

import pytest

from sl4slam.backend import SubmapBackend
from sl4slam.compose import frontend_for_worker
from sl4slam.config import SLAMConfig
from sl4slam.errors import UserError
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.frontend.workers import ProcessWorkers, RayWorkers, WorkerFrontend
from sl4slam.io import open_source
from sl4slam.pipeline import SLAMPipeline
from sl4slam.resolve import resolve
from sl4slam.result.outputs import write_outputs
from sl4slam.schedule import AheadScheduler
from sl4slam.source_knowledge import source_problem
from sl4slam.types import FrontendCapabilities

from sl4slam.synthetic import write_synthetic_sequence

from test_schedule import DroppingGraph, FailingFrontend, _outputs, _same_outputs, lap_config


class SerialFrontend(FailingFrontend):
    """The failing simulator, one forward at a time: several windows are in flight, but the model
    itself is not asked to be thread-safe."""

    def __init__(self, config, failing: set[int]):
        super().__init__(config, failing)
        self._lock = threading.Lock()

    def reconstruct(self, frames, submap_id, **kwargs):
        with self._lock:
            return super().reconstruct(frames, submap_id, **kwargs)


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """A 360-frame lap at 160x120 that returns to its start."""
    return write_synthetic_sequence(tmp_path_factory.mktemp("workers") / "world", num_frames=360, width=160,
                                    height=120, seed=1)


@pytest.mark.parametrize("graph, false_loops", [("keyframe", 0.0), pytest.param("submap", 1.0, marks=pytest.mark.slow)])
def test_windows_ahead_are_byte_identical_with_a_failing_forward(world: Path, tmp_path: Path, graph: str,
                                                                 false_loops: float) -> None:
    """Submap 4's forward fails after the windows after it were handed on: the retrieval rewinds and
    they are assembled again, as one submap after the other would assemble them."""
    runs = {}
    for workers in (1, 3):
        config = lap_config(workers > 1, **{"backend.graph": graph, "false_loops.rate": false_loops})
        config.workers = workers
        frontend = SerialFrontend(config.sim, {4})
        runs[workers] = _outputs(world, tmp_path / str(workers), config, frontend)
    (_, summary_1), (ahead, summary_3) = runs[1], runs[3]
    assert ahead.resolved.workers == 3
    assert summary_3["counts"]["loops" if false_loops == 0 else "loops_rejected"] >= 1
    assert [f["submap"] for f in summary_3["frontend_failures"]] == [4]
    _same_outputs(tmp_path / "1", tmp_path / "3", summary_1, summary_3)


def test_windows_after_a_dropped_submap_are_reopened_identically(world: Path, tmp_path: Path) -> None:
    runs = {}
    for workers in (1, 3):
        config = lap_config(workers > 1, **{"backend.graph": "submap"})
        config.workers = workers
        backend = SubmapBackend(DroppingGraph(config.backend, node=3))
        runs[workers] = _outputs(world, tmp_path / str(workers), config, SerialFrontend(config.sim, set()), backend)
    summary = runs[3][1]
    assert summary["dropped_frames"]["graph failed"] > 0
    _same_outputs(tmp_path / "1", tmp_path / "3", runs[1][1], summary)


class _Steps:
    """The steps of a pipeline, with forwards that wait until the test lets them finish."""

    def __init__(self) -> None:
        self.next_submap_id = 0
        self.released: dict[int, threading.Event] = {}
        self.integrated: list[int] = []
        self.shared = type("Shared", (), {"next": []})()

    def assemble(self, new_frames):
        work = type("Work", (), {"submap_id": self.next_submap_id, "new_frames": new_frames})()
        self.released[work.submap_id] = threading.Event()
        self.next_submap_id += 1
        return work

    def anticipate(self, work):
        return work.submap_id

    def run_frontend(self, work):
        self.released[work.submap_id].wait(30)
        return type("Outcome", (), {"problem": None})()

    def accept(self, work, outcome, anticipated=False):
        return "prediction"

    def integrate(self, work, prediction):
        self.integrated.append(work.submap_id)
        return True


def test_no_window_is_assembled_before_its_loop_frames_are_stored() -> None:
    """A window may take loop frames from submaps ``tau_interval`` + 1 older, so it is assembled only
    once they are integrated: with ``tau_interval`` 1, two windows are in the model together and
    never more, however many workers there are."""
    steps = _Steps()
    scheduler = AheadScheduler(steps, ahead=4, tau_interval=1)
    for batch in range(3):
        scheduler.submit([batch])
    assert [w.work.submap_id for w in scheduler.flight] == [0, 1] and len(scheduler.waiting) == 1
    steps.released[1].set()  # the second forward ends first: the graph still waits for the first
    scheduler.flight[1].forward.result()
    scheduler.poll()
    assert steps.integrated == [] and len(scheduler.flight) == 2
    steps.released[0].set()
    scheduler.flight[0].forward.result()
    scheduler.poll()  # submaps 0 and 1 integrated in order; window 2 assembled after submap 0 was
    assert steps.integrated == [0, 1] and [w.work.submap_id for w in scheduler.flight] == [2]
    steps.released[2].set()
    scheduler.drain()
    assert steps.integrated == [0, 1, 2] and not scheduler.flight and not scheduler.waiting


class DyingFrontend(SimulatedFrontend):
    """The simulator in a worker process that dies (``os._exit``) the first time it gets submap 2."""

    capabilities = FrontendCapabilities(needs_ground_truth=True, scores_pairs=True)

    def __init__(self, config, marker: str):
        super().__init__(config)
        self.marker = marker

    def reconstruct(self, frames, submap_id, **kwargs):
        if submap_id == 2 and not os.path.exists(self.marker):
            Path(self.marker).write_text("died once")
            os._exit(1)
        return super().reconstruct(frames, submap_id, **kwargs)


def dying_frontend(config: SLAMConfig, marker: str, index: int) -> DyingFrontend:
    """A worker's frontend (built in the worker process)."""
    return DyingFrontend(config.sim, marker)


def _short_run(world: Path, out: Path, config: SLAMConfig, frontend=None):
    """A run of the first ``source.max_frames`` frames, written to ``out``."""
    pipeline = SLAMPipeline.from_config(config, frontend)
    result = pipeline.run(open_source(str(world), config.source), progress=False)
    return pipeline, write_outputs(result, out, pipeline.resolved, source_name="world")


def test_worker_processes_give_the_same_run_and_redo_a_lost_window(world: Path, tmp_path: Path) -> None:
    config = lap_config(False, **{"source.max_frames": 200})
    _, summary_1 = _short_run(world, tmp_path / "1", config)
    ahead = lap_config(True, **{"source.max_frames": 200})
    ahead.workers = 2
    marker = tmp_path / "died"
    workers = ProcessWorkers(partial(dying_frontend, ahead, str(marker)), 2, threads=1)
    frontend = WorkerFrontend(SimulatedFrontend(ahead.sim), workers)
    try:
        pipeline, summary_2 = _short_run(world, tmp_path / "2", ahead, frontend)
    finally:
        workers.close()
    assert marker.read_text() == "died once" and workers.restarts == 1
    assert summary_2["frontend_failures"] == []
    _same_outputs(tmp_path / "1", tmp_path / "2", summary_1, summary_2)


def test_a_worker_that_keeps_dying_is_a_frontend_failure(tmp_path: Path) -> None:
    workers = ProcessWorkers(partial(_always_dying, str(tmp_path)), 1, threads=1, retries=0)
    try:
        with pytest.raises(RuntimeError, match=r"died 1 time\(s\) running submap 0"):
            workers.reconstruct([], 0, {})
    finally:
        workers.close()


def _always_dying(folder: str, index: int):
    os._exit(3)


def test_the_worker_factory_builds_the_settled_frontend() -> None:
    config = resolve(lap_config(True)).config
    frontend = frontend_for_worker(config, 5)
    assert isinstance(frontend, SimulatedFrontend) and frontend.name == "simulated"


def test_settings_that_cannot_run_windows_ahead_say_so_in_one_line() -> None:
    config = lap_config(True, **{"retrieval.tau_interval": 0})
    config.workers = 2
    with pytest.raises(UserError, match=r"^--workers 2 runs windows ahead .*--tau-interval 0"):
        resolve(config)
    config = lap_config(False)
    config.workers = 2
    with pytest.raises(UserError, match="--no-overlap"):
        resolve(config)
    config = lap_config(True)
    config.workers = 8
    resolved = resolve(config)
    assert resolved.workers == 8 and any("at most 3 windows" in note for note in resolved.notes)
    with pytest.raises(UserError, match="--workers"):
        SLAMConfig(workers=0).validate()


def test_a_live_camera_keeps_the_model_in_the_run(tmp_path: Path) -> None:
    class Camera:
        live = True
        name = "camera 0"
        has_ground_truth = False

        def __len__(self) -> int:
            return 10**9

    capabilities = FrontendCapabilities()
    problem = source_problem(Camera(), capabilities, "vggt", workers=2)
    assert problem is not None and problem.startswith("--workers 2 runs the model's windows ahead")
    assert "camera 0 is a live camera" in problem
    assert source_problem(Camera(), capabilities, "vggt", workers=1) is None


def test_ray_missing_or_unreachable_is_one_line(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(UserError, match=r'^--ray-address needs Ray: pip install "sl4slam\[cluster\]"$'):
        RayWorkers(partial(frontend_for_worker, SLAMConfig()), 1, "auto")
    with socket.socket() as closed:  # a port nothing listens on: bound, never listening
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
        with pytest.raises(UserError, match=rf"^cannot reach the Ray cluster at 127.0.0.1:{port}: .*; check --ray-address"):
            RayWorkers(partial(frontend_for_worker, SLAMConfig()), 1, f"127.0.0.1:{port}")


def test_a_run_may_resume_with_other_workers(tmp_path: Path) -> None:
    """Where the model runs changes no output, so a killed run may continue with other ``--workers``
    (any other setting that differs is still named)."""
    from sl4slam.resume import check_settings, checked_settings

    one = resolve(lap_config(True))
    manifest = {"settings": checked_settings(one)}
    three = lap_config(True)
    three.workers = 3
    check_settings(manifest, resolve(three), tmp_path)
    other = lap_config(True, **{"submap.size": 12})
    other.workers = 3
    with pytest.raises(UserError, match="--submap-size"):
        check_settings(manifest, resolve(other), tmp_path)


def test_a_rewound_orb_database_answers_as_if_it_never_held_the_withdrawn_keyframes(world: Path) -> None:
    from sl4slam.retrieval.orb import OrbRetrieval

    frames = list(open_source(str(world)))[:96:4]
    held, withdrawn = frames[:16], frames[16:]
    config = lap_config(True).retrieval
    rewound, fresh = OrbRetrieval(config), OrbRetrieval(config)
    for retrieval in (rewound, fresh):
        retrieval.add(held[:8], 0)
        retrieval.add(held[8:], 1)
    mark = rewound.mark()
    rewound.query(withdrawn, 2, 1)
    rewound.add(withdrawn, 2)
    features = [rewound.extract(f.rgb) for f in withdrawn]
    assert rewound.similarity(features).shape == (24, len(withdrawn))  # its caches now include them
    rewound.rewind(mark)
    assert len(rewound) == len(fresh) == 16
    assert rewound.similarity(features).tobytes() == fresh.similarity(features).tobytes()
    for retrieval in (rewound, fresh):
        retrieval.add(withdrawn, 2)
    assert rewound.similarity(features).tobytes() == fresh.similarity(features).tobytes()
    assert rewound.query(frames[:4], 5, 2) == fresh.query(frames[:4], 5, 2)


def test_a_rewound_descriptor_index_forgets_the_withdrawn_rows() -> None:
    import numpy as np

    from sl4slam.retrieval.salad import DescriptorIndex

    rng = np.random.default_rng(0)
    index = DescriptorIndex(8, initial_capacity=2)
    index.add(rng.normal(size=(3, 8)), [0, 1, 2], 0)
    mark = index.mark()
    index.add(rng.normal(size=(5, 8)), [3, 4, 5, 6, 7], 1)
    index.rewind(mark)
    assert len(index) == 3 and index.frame_ids.tolist() == [0, 1, 2] and index.submap_ids.tolist() == [0, 0, 0]
