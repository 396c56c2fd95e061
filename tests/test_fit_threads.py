"""A link's independent 15-DOF fits run at once (``alignment.fit_threads``): the same links, bit for
bit, as one after another, in the shared-frame fits, the cross-validated choice and a whole run;
a frame that cannot be measured still leaves the joint fit to the frames that can; the deferred
form of one thread runs nothing it is not asked for. A bad ``fit_threads`` is one of
``tests/test_bad_settings.py``'s cases, as every setting is."""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np
import pytest

from sl4slam.alignment.aligner import SelectAligner, SL4Aligner
from sl4slam.alignment.parallel import start
from sl4slam.alignment.shared import link_from_shared_frames, measure_frames
from sl4slam.config import AlignmentConfig, SimulatorConfig, SLAMConfig
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.io import open_source
from sl4slam.pipeline import SLAMPipeline
from sl4slam.submap import confidence_mask, submap_points
from sl4slam.synthetic import write_synthetic_sequence
from sl4slam.geometry import to_4x4
from sl4slam.types import FrameView


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("world") / "synthetic", num_frames=300, width=160,
                                    height=120, seed=0)


@pytest.fixture(scope="module")
def shared(world: Path) -> list[tuple[FrameView, FrameView]]:
    """Three frames shared by two simulated submaps under VGGT-like errors: their views in each."""
    source = open_source(str(world))
    frames = [source.get(i) for i in range(0, 70, 5)]
    frontend = SimulatedFrontend(SimulatorConfig(profile="vggt", seed=1))
    views = []
    for submap_id, chosen, slots in ((0, frames[:8], range(5, 8)), (1, frames[5:14], range(3))):
        prediction = frontend.reconstruct(chosen, submap_id)
        mask = confidence_mask(prediction.confidence, prediction.depth, 25.0)
        points = submap_points(prediction, slots=list(slots))
        T = to_4x4(prediction.T_cam_submap)
        views.append([FrameView(points[k], mask[s], prediction.K[s], T[s]) for k, s in enumerate(slots)])
    return list(zip(views[0], views[1]))


def same(a, b) -> None:
    """Two alignments equal bit for bit where it matters: the map, the inliers, the fallback."""
    assert a.H.tobytes() == b.H.tobytes()
    assert a.inliers.tobytes() == b.inliers.tobytes()
    assert a.fallback == b.fallback and a.rms == b.rms


def aligner(cls, threads: int):
    return cls(dataclasses.replace(AlignmentConfig(), fit_threads=threads))


@pytest.mark.parametrize("count", [2, 3])
def test_the_shared_frames_fits_are_the_same_on_threads(shared, count: int) -> None:
    pairs = shared[:count]
    links = {threads: link_from_shared_frames(aligner(SL4Aligner, threads), pairs, seed=7) for threads in (1, 2, 3)}
    for threads in (2, 3):
        same(links[threads], links[1])
        for own, own_alone in zip(links[threads].extras["per_frame"], links[1].extras["per_frame"]):
            same(own, own_alone)
    assert links[1].extras["shared_frames"] == count


@pytest.mark.parametrize("count", [2, 3])
def test_the_cross_validated_choice_is_the_same_on_threads(shared, count: int) -> None:
    """The select link: its frames' fits, the joint fit and (with three frames) the folds' fits."""
    pairs = shared[:count]
    chosen = {threads: aligner(SelectAligner, threads).align_frames(pairs, seed=3) for threads in (1, 2)}
    same(chosen[2], chosen[1])
    assert chosen[2].extras["select"] == chosen[1].extras["select"]


@pytest.mark.parametrize("fault", ["no confident pixel", "three finite points"])
def test_a_frame_that_cannot_be_measured_leaves_the_joint_fit_to_the_others(shared, fault: str) -> None:
    """A frame left out before its fit (no confident pixel) never enters the joint fit; one left out
    by its fit (too few finite points) did enter the joint fit started beside it, which is then dropped and
    made again on the frames measured. Either way: the link of one thread after another."""
    view_a, view_b = shared[1]
    if fault == "no confident pixel":
        broken = FrameView(view_b.points, np.zeros_like(view_b.mask), view_b.K, view_b.T_cam_submap)
    else:  # the frame's fit needs five; the joint fit would take them in
        points = np.full_like(view_b.points, np.nan)
        rows, cols = np.nonzero(view_b.mask)
        points[rows[:3], cols[:3]] = view_b.points[rows[:3], cols[:3]]
        broken = FrameView(points, view_b.mask, view_b.K, view_b.T_cam_submap)
    pairs = [shared[0], (view_a, broken), shared[2]]
    links = {threads: link_from_shared_frames(aligner(SL4Aligner, threads), pairs, seed=5) for threads in (1, 2)}
    same(links[2], links[1])
    assert links[2].extras["frames_used"] == [0, 2]
    assert links[2].extras["left_out"][0].startswith("frame 1: ")
    # the link of frames 0 and 2 measured alone, as a run that never saw frame 1 would
    alone = link_from_shared_frames(aligner(SL4Aligner, 1), [shared[0], shared[2]], seed=5)
    same(links[2], alone)


class CountingAligner(SL4Aligner):
    """Counts its fits, and the threads they ran on."""

    def __init__(self, config: AlignmentConfig) -> None:
        super().__init__(config)
        self.calls: list[tuple[int, str]] = []
        self.lock = threading.Lock()

    def fit(self, X_a, X_b, view_a, view_b, seed):
        with self.lock:
            self.calls.append((len(X_a), threading.current_thread().name))
        return super().fit(X_a, X_b, view_a, view_b, seed)


def test_one_thread_runs_no_fit_it_does_not_use(shared) -> None:
    """With one thread nothing runs ahead: a joint fit over a frame that fails is never made, and
    every fit runs in the caller's thread; with two, the fits run on the pool."""
    view_a, view_b = shared[1]
    unusable = np.full_like(view_b.points, np.nan)  # confident pixels, no finite point: the fit fails
    pairs = [shared[0], (view_a, FrameView(unusable, view_b.mask, view_b.K, view_b.T_cam_submap))]
    counting = CountingAligner(dataclasses.replace(AlignmentConfig(), fit_threads=1))
    measured = measure_frames(counting, pairs, seed=0, joint=True)
    assert measured.frames == [0] and measured.joint is None
    assert len(counting.calls) == 2 and {name for _, name in counting.calls} == {threading.current_thread().name}

    counting = CountingAligner(dataclasses.replace(AlignmentConfig(), fit_threads=2))
    link = link_from_shared_frames(counting, shared[:2], seed=0)
    sizes = sorted(size for size, _ in counting.calls)
    assert len(sizes) == 3 and sizes[2] == sizes[0] + sizes[1]  # each frame's fit and the joint one
    assert all(name.startswith("sl4slam-fit") for _, name in counting.calls)
    assert link.extras["shared_frames"] == 2


def test_a_pending_fit_raises_where_its_result_is_asked_for() -> None:
    def fails() -> None:
        raise ValueError("no fit")

    ran = []
    deferred = start(lambda: ran.append(1) or 5, threads=1)
    assert ran == []
    assert deferred.result() == 5 and deferred.result() == 5 and ran == [1]  # run once, on the first ask
    for threads in (1, 2):
        pending = start(fails, threads)
        for _ in range(2):
            with pytest.raises(ValueError, match="no fit"):
                pending.result()


@pytest.fixture(scope="module")
def lap(tmp_path_factory) -> Path:
    """A whole lap of the synthetic world: its end closes loops with its start."""
    return write_synthetic_sequence(tmp_path_factory.mktemp("lap") / "synthetic", num_frames=600, width=160,
                                    height=120, seed=0)


class ThreadRecordingAligner(SelectAligner):
    """The select aligner, recording the thread each link is measured on."""

    def __init__(self, config: AlignmentConfig) -> None:
        super().__init__(config)
        self.threads: list[str] = []

    def align_frames(self, pairs, seed):
        self.threads.append(threading.current_thread().name)
        return super().align_frames(pairs, seed)


def lap_run(lap: Path, threads: int, aligner=None):
    config = SLAMConfig(frontend="simulated")
    config.sim.profile = "vggt"
    config.keyframes.tau_disparity = 12.0
    config.submap.overlap = 2
    config.alignment.fit_threads = threads
    return SLAMPipeline.from_config(config, aligner=aligner).run(open_source(str(lap)), progress=False)


def test_a_whole_run_is_the_same_on_threads(lap: Path) -> None:
    """Two shared frames, the select link and loops under VGGT-like errors, the loop links measured
    beside the odometry link: the same map bit for bit."""
    recorders = {threads: ThreadRecordingAligner(dataclasses.replace(AlignmentConfig(), fit_threads=threads))
                 for threads in (1, 2)}
    one, two = (lap_run(lap, threads, recorders[threads]) for threads in (1, 2))
    assert any(e.kind == "loop" and e.accepted for e in one.edges)
    assert len(one.keyframes) == len(two.keyframes)
    assert np.asarray(one.T_world_cam).tobytes() == np.asarray(two.T_world_cam).tobytes()
    assert np.asarray(one.K).tobytes() == np.asarray(two.K).tobytes()
    assert [(e.kind, e.accepted, e.reason) for e in one.edges] == [(e.kind, e.accepted, e.reason) for e in two.edges]
    # one thread: every link in the caller's; two: each loop link on the link pool, beside the odometry
    assert set(recorders[1].threads) == {threading.current_thread().name}
    loops = sum(e.kind == "loop" for e in two.edges)
    assert sum(name.startswith("sl4slam-link") for name in recorders[2].threads) == loops


@pytest.mark.parametrize("threads", [1, 2])
def test_a_loop_whose_evidence_fails_is_rejected_with_its_error(lap: Path, threads: int, monkeypatch) -> None:
    """The evidence is read before the odometry now; its error still rejects that loop alone, with
    the same reason, and the run goes on."""
    from sl4slam.window import DenseSubmap

    read = DenseSubmap.loop_evidence
    failed = []

    def flaky(self, work, k, stored):
        if not failed:
            failed.append(work.submap_id)
            raise RuntimeError("the stored view is unreadable")
        return read(self, work, k, stored)

    monkeypatch.setattr(DenseSubmap, "loop_evidence", flaky)
    result = lap_run(lap, threads)
    rejected = [e for e in result.edges if e.kind == "loop" and not e.accepted]
    assert failed and any(e.reason == "RuntimeError: the stored view is unreadable" for e in rejected)
    # the run went on: every keyframe of the lap, and the submap of the failed loop in the graph
    assert len(result.keyframes) == len(lap_run(lap, threads).keyframes)
    assert any(e.kind == "odometry" and e.accepted and e.submap_to == failed[0] for e in result.edges)

