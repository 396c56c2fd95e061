"""The keyframe store keeps RAM bounded: beyond the newest ``submap.keyframes_in_ram`` keyframes the
image-sized arrays live in files and are read back as the same bytes, so a run's outputs do not
change."""

from __future__ import annotations

import gc
import pickle
from pathlib import Path

import numpy as np
import pytest

from sl4slam.config import SLAMConfig
from sl4slam.io import open_source
from sl4slam.keyframe_store import KeyframeStore
from sl4slam.pipeline import SLAMPipeline
from sl4slam.result.outputs import write_outputs
from sl4slam.submap import StoredKeyframe
from sl4slam.synthetic import write_synthetic_sequence


def _keyframe(index: int, rng: np.random.Generator) -> StoredKeyframe:
    depth = rng.uniform(0.5, 4.0, (12, 16)).astype(np.float16)
    mask = rng.random((12, 16)) > 0.2
    return StoredKeyframe(frame_index=index, timestamp=index / 30, submap_id=index // 4, slot=index % 4, depth=depth,
                          mask_bits=np.packbits(mask), confidence_rank=rng.integers(0, 256, (6, 8), dtype=np.uint8),
                          K=np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), T_cam_submap=np.eye(4),
                          principal_point=np.array([8.0, 6.0]))


def test_the_store_keeps_only_the_newest_keyframes_arrays_in_ram(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    kept = [_keyframe(i, rng) for i in range(10)]
    copies = [pickle.loads(pickle.dumps(k)) for k in kept]  # the arrays before any spill
    store = KeyframeStore(in_ram=3, folder=tmp_path / "store")
    for k, keyframe in enumerate(kept):
        store.add(keyframe)
        assert sum(not kf.spilled for kf in store.keyframes) == min(k + 1, 3)
    assert store.spilled == 7 and len(list((tmp_path / "store").glob("*.npz"))) == 7
    assert [k.spilled for k in store.keyframes] == [True] * 7 + [False] * 3
    for keyframe, before in zip(store.keyframes, copies):
        for name in ("depth", "mask_bits", "confidence_rank"):
            again = getattr(keyframe, name)
            assert again.dtype == getattr(before, name).dtype and again.tobytes() == getattr(before, name).tobytes()
        assert np.array_equal(keyframe.mask(), before.mask()) and np.array_equal(keyframe.points(), before.points())
        assert keyframe.nbytes == before.nbytes
    spilled, held = store.keyframes[0], store.keyframes[-1]
    arrays = held.depth.nbytes + held.mask_bits.nbytes + held.confidence_rank.nbytes
    assert spilled.ram_bytes == held.ram_bytes - arrays  # only the camera stays in RAM
    assert store.get(3) is store.keyframes[3]
    with pytest.raises(AttributeError):
        spilled.no_such_array


def test_a_spilled_keyframe_answers_its_shape_and_size_without_its_file(tmp_path: Path) -> None:
    # the end of a long run reads every keyframe's shape (the metric upgrade) and size (the summary):
    # tens of thousands of file reads if a spilled keyframe had to load its arrays for them
    keyframe = _keyframe(0, np.random.default_rng(2))
    shape, nbytes = keyframe.shape, keyframe.nbytes
    keyframe.spill(tmp_path / "k.npz")
    (tmp_path / "k.npz").unlink()
    assert keyframe.shape == shape == (12, 16) and keyframe.nbytes == nbytes
    with pytest.raises(FileNotFoundError):
        keyframe.depth


def test_a_temporary_folder_lives_as_long_as_its_keyframes() -> None:
    rng = np.random.default_rng(1)
    store = KeyframeStore(in_ram=1)
    for i in range(3):
        store.add(_keyframe(i, rng))
    keyframes, folder = store.keyframes, store.folder
    del store
    gc.collect()
    assert folder.is_dir() and keyframes[0].depth.shape == (12, 16)  # still readable
    del keyframes
    gc.collect()
    assert not folder.exists()


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("world") / "synthetic", num_frames=300, width=160,
                                    height=120, seed=0)


def _run(world: Path, in_ram: int, out: Path):
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 12.0
    config.sim.profile = "vggt"
    config.submap.size = 6
    config.submap.keyframes_in_ram = in_ram
    config.retrieval.kind = "orb"  # its keypoints and descriptors are spilled likewise
    pipeline = SLAMPipeline.from_config(config)
    result = pipeline.run(open_source(str(world)), progress=False)
    write_outputs(result, out, pipeline.resolved, source_name="world")
    return pipeline


def test_a_run_that_spills_keyframes_writes_the_same_outputs(world: Path, tmp_path: Path) -> None:
    everything = _run(world, 0, tmp_path / "all")
    bounded = _run(world, 4, tmp_path / "bounded")
    assert everything.keyframe_store.spilled == 0
    assert bounded.keyframe_store.spilled == len(bounded.keyframes) - 4 > 10
    assert sum(not k.spilled for k in bounded.keyframes) == 4
    assert everything.retrieval.features_in_ram() == len(everything.retrieval)
    assert bounded.retrieval.features_in_ram() == 4 < len(bounded.retrieval)
    assert bounded.ledger.edges == everything.ledger.edges and bounded.num_loops >= 1  # verified on spilled features
    for name in ["trajectory.txt", "map.ply", *sorted(p.name for p in (tmp_path / "all" / "keyframes").iterdir())]:
        folder = "keyframes/" if name.endswith(".npz") else ""
        assert (tmp_path / "all" / folder / name).read_bytes() == (tmp_path / "bounded" / folder / name).read_bytes(), name
