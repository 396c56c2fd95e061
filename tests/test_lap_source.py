"""The benchmarks' lap replay (``benchmarks/harness/worlds.py``): the lap held in RAM and the lap
read back from files give the same frames."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from sl4slam.io import open_source
from sl4slam.synthetic import write_synthetic_sequence

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture()
def harness(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    monkeypatch.delitem(sys.modules, "harness", raising=False)
    import harness

    return harness


def test_a_lap_kept_in_files_replays_the_same_frames(harness, tmp_path: Path) -> None:
    world = write_synthetic_sequence(tmp_path / "world", num_frames=6, width=32, height=24, seed=0)
    in_ram = harness.LapSource(open_source(str(world)), laps=3, preload=True)
    in_files = harness.LapSource(open_source(str(world)), laps=3, preload=True, folder=tmp_path / "lap")
    assert len(in_files) == len(in_ram) == 18
    assert in_ram.preloaded_bytes > 0 and in_files.preloaded_bytes == 0
    assert len(list((tmp_path / "lap").glob("*.npy"))) == 12  # each frame's image and depth, once
    for index in (0, 5, 6, 17):
        a, b = in_ram.get(index), in_files.get(index)
        assert (a.index, a.timestamp) == (b.index, b.timestamp) == (index, index / 30.0)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
        np.testing.assert_array_equal(a.K, b.K)
