"""The benchmarks' fit memo (``benchmarks/harness/fit_memo.py``): a run whose link fits are handed
back from a recording run makes the same map bit for bit and fits nothing, so its per-submap cost
is the model-free work without the fits."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from sl4slam.alignment.aligner import CalibrationAligner, SL4Aligner
from sl4slam.config import SLAMConfig
from sl4slam.io import open_source
from sl4slam.pipeline import SLAMPipeline
from sl4slam.synthetic import write_synthetic_sequence

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture()
def fit_memo(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    monkeypatch.delitem(sys.modules, "harness", raising=False)
    monkeypatch.delitem(sys.modules, "harness.fit_memo", raising=False)
    from harness import fit_memo

    return fit_memo


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("world") / "synthetic", num_frames=120, width=160,
                                    height=120, seed=0)


def _run(world: Path):
    config = SLAMConfig(frontend="simulated")
    config.sim.profile = "vggt"
    config.keyframes.tau_disparity = 12.0
    config.submap.overlap = 2
    return SLAMPipeline.from_config(config).run(open_source(str(world)), progress=False)


def test_replayed_fits_make_the_same_map_and_fit_nothing(fit_memo, world: Path, tmp_path: Path, monkeypatch) -> None:
    originals = {cls: cls.__dict__["fit"] for cls in (SL4Aligner, CalibrationAligner)}
    with fit_memo.FitMemo("record", tmp_path / "fits.pkl").installed() as recorder:
        recorded = _run(world)
    recorder.save()
    assert {cls: cls.__dict__["fit"] for cls in originals} == originals  # put back
    kinds = {key[0] for key in recorder.fits}
    assert kinds == {"sl4", "calibration"} and len(recorder.fits) > 10

    fitted = []
    for cls, original in originals.items():  # any fit the replay makes itself is counted
        monkeypatch.setattr(cls, "fit", lambda self, *args, _original=original: fitted.append(1) or _original(self, *args))
    with fit_memo.FitMemo("replay", tmp_path / "fits.pkl").installed() as replayer:
        replayed = _run(world)
    assert fitted == [] and replayer.misses == 0 and replayer.hits >= len(recorder.fits)
    assert np.asarray(replayed.T_world_cam).tobytes() == np.asarray(recorded.T_world_cam).tobytes()
    assert [(e.kind, e.accepted, e.reason) for e in replayed.edges] == [(e.kind, e.accepted, e.reason)
                                                                        for e in recorded.edges]


def test_a_fit_that_was_not_recorded_is_fitted_and_counted(fit_memo, world: Path, tmp_path: Path) -> None:
    import pickle

    with open(tmp_path / "empty.pkl", "wb") as handle:
        pickle.dump({}, handle)
    with fit_memo.FitMemo("replay", tmp_path / "empty.pkl").installed() as replayer:
        _run(world)
    assert replayer.hits == 0 and replayer.misses > 0
    with pytest.raises(ValueError, match="record or replay"):
        fit_memo.FitMemo("both", tmp_path / "empty.pkl")
