"""The end of a run frees what only a growing map needs (``SLAMPipeline.release``: retrieval's
stored descriptors, the graph's incremental solver) before the final polish, and gives the same
result as a run that keeps them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sl4slam.config import SLAMConfig
from sl4slam.io import open_source
from sl4slam.pipeline import SLAMPipeline
from sl4slam.synthetic import write_synthetic_sequence


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("world") / "synthetic", num_frames=300, width=160,
                                    height=120, seed=0)


def _pipeline(graph: str, false_loop_rate: float) -> SLAMPipeline:
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 12.0
    config.sim.profile = "vggt"
    config.submap.size = 6
    config.retrieval.kind = "orb"
    config.backend.graph = graph
    config.false_loops.rate = false_loop_rate
    return SLAMPipeline.from_config(config)


@pytest.mark.parametrize("graph, false_loop_rate", [("keyframe", 0.0), ("submap", 0.0), ("keyframe", 0.5)])
def test_a_released_run_gives_the_same_result(world: Path, graph: str, false_loop_rate: float) -> None:
    kept, released = _pipeline(graph, false_loop_rate), _pipeline(graph, false_loop_rate)
    a = kept.run(open_source(str(world)), progress=False)
    b = released.run(open_source(str(world)), progress=False, release=True)
    assert b.stats["loops"] == a.stats["loops"] >= (0 if false_loop_rate else 1)
    np.testing.assert_array_equal(b.T_world_cam, a.T_world_cam)
    np.testing.assert_array_equal(b.K, a.K)
    assert b.H_world_submap.keys() == a.H_world_submap.keys()
    for s in a.H_world_submap:
        np.testing.assert_array_equal(b.H_world_submap[s], a.H_world_submap[s])
    np.testing.assert_array_equal(released.snapshot().T_world_cam, kept.snapshot().T_world_cam)
    # what was freed: iSAM2, and the retrieval's database (the wrapper's stored places too)
    orb = getattr(released.retrieval, "inner", released.retrieval)
    assert released.backend.freeze()  # already frozen
    assert orb.closed and len(orb._global) == 0 and orb._in_ram == [] and len(orb) == len(getattr(kept.retrieval, "inner", kept.retrieval))
    if false_loop_rate:
        assert released.retrieval._stored == [] and released.retrieval.injected == kept.retrieval.injected != []
    frame = open_source(str(world)).get(0)
    with pytest.raises(RuntimeError, match="closed"):
        released.retrieval.query([frame], 1000, 1)
    with pytest.raises(RuntimeError, match="make a new pipeline"):
        released.start(open_source(str(world)))


def test_release_waits_for_the_input_to_close(world: Path) -> None:
    pipeline = _pipeline("keyframe", 0.0)
    pipeline.start(open_source(str(world)), progress=False)
    with pytest.raises(RuntimeError, match="input closed"):
        pipeline.release()


def test_release_returns_the_freed_memory_to_the_system(world: Path, monkeypatch) -> None:
    # freed after the graph and retrieval were dropped, not before: the polish then starts from less
    import sl4slam.pipeline as pipeline_module

    asked = []
    monkeypatch.setattr(pipeline_module, "return_freed_memory",
                        lambda: asked.append(pipeline.backend.freeze() and pipeline.retrieval.closed) or True)
    pipeline = _pipeline("keyframe", 0.0)
    pipeline.run(open_source(str(world)), progress=False, release=True)
    assert asked == [True]


def test_freed_memory_goes_back_where_the_c_library_is_glibc() -> None:
    import platform

    from sl4slam.heap import return_freed_memory

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("malloc_trim is glibc's; elsewhere the freed memory is only reused by the process")
    assert return_freed_memory() is True


def test_a_spilling_run_spills_every_keyframe_before_the_polish(world: Path) -> None:
    # a run long enough that its store spills keeps no keyframe's arrays in RAM once released; the
    # result and the arrays read back are the same as a run that keeps them
    kept, released = _pipeline("keyframe", 0.0), _pipeline("keyframe", 0.0)
    for pipeline in (kept, released):
        pipeline.keyframe_store.in_ram = 4
    a = kept.run(open_source(str(world)), progress=False)
    assert 0 < kept.keyframe_store.spilled < len(kept.keyframe_store)  # the newest four stay in RAM
    b = released.run(open_source(str(world)), progress=False, release=True)
    store = released.keyframe_store
    assert store.spilled == len(store) and store.ram_bytes() == sum(
        k.K.nbytes + k.T_cam_submap.nbytes + k.principal_point.nbytes for k in store.keyframes)
    np.testing.assert_array_equal(b.T_world_cam, a.T_world_cam)
    for x, y in zip(kept.keyframe_store.keyframes[-4:], store.keyframes[-4:]):
        np.testing.assert_array_equal(y.depth, x.depth)
        np.testing.assert_array_equal(y.mask_bits, x.mask_bits)
        np.testing.assert_array_equal(y.confidence_rank, x.confidence_rank)


def test_a_run_that_never_spilled_keeps_its_keyframes_in_ram(world: Path) -> None:
    pipeline = _pipeline("keyframe", 0.0)
    pipeline.run(open_source(str(world)), progress=False, release=True)
    assert len(pipeline.keyframe_store) < pipeline.keyframe_store.in_ram and pipeline.keyframe_store.spilled == 0
