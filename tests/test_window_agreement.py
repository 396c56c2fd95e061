"""How well the frames of one window agree (``sl4slam.refine.window_disagreement``) and the
stiffness the keyframe graph sets inside a submap by it (``BackendConfig.window_agreement_factor``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.backend import KeyframeBackend, SubmapFrames
from sl4slam.config import BackendConfig, SimulatorConfig, SLAMConfig
from sl4slam.frontend.settings import SIM_EXACT
from sl4slam.frontend.simulated import SimulatedFrontend
from sl4slam.io import open_source
from sl4slam.pipeline import SLAMPipeline
from sl4slam.refine import window_disagreement
from sl4slam.submap import confidence_mask
from sl4slam.synthetic import write_synthetic_sequence
from test_refine import K, room

STRONG = dict(profile="exact", perspective=0.2, shear=0.05, scale=0.1)
"""One projective distortion per window and nothing else (the levers benchmark's ``strong``)."""


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("world") / "synthetic", num_frames=600, width=160,
                                    height=120, seed=0)


def measured(frames: list, **sim) -> float:
    """The disagreement of one simulated window over its confident pixels."""
    prediction = SimulatedFrontend(SimulatorConfig(**sim)).reconstruct(frames, 1)
    mask = confidence_mask(prediction.confidence, prediction.depth, 25.0)
    return window_disagreement(prediction.depth, prediction.K, prediction.T_cam_submap, mask)


def test_exact_frames_agree_and_a_turned_frame_does_not():
    truth, depth, valid, _ = room()
    Ks = np.repeat(K[None], len(truth), axis=0)
    assert window_disagreement(depth, Ks, truth, valid, stride=4) < 1e-6
    turned = truth.copy()
    one_degree = Rotation.from_rotvec([0.0, np.radians(1.0), 0.0]).as_matrix()
    for s in range(1, len(truth), 2):  # every other frame off by one degree
        turned[s, :, :3] = one_degree @ truth[s, :, :3]
    small = window_disagreement(depth, Ks, turned, valid, stride=4)
    for s in range(1, len(truth), 2):
        turned[s, :, :3] = one_degree @ turned[s, :, :3]
    large = window_disagreement(depth, Ks, turned, valid, stride=4)
    assert 0.003 < small < large, (small, large)
    assert window_disagreement(depth[:1], Ks[:1], truth[:1], valid[:1]) is None
    assert window_disagreement(depth[:2], Ks[:2], truth[:2], np.zeros_like(valid[:2])) is None


def test_a_distortion_of_the_whole_window_keeps_it_consistent(world: Path):
    """The window's projective distortion (which the measure does not model: it decomposes into
    skewed intrinsics and moved cameras) leaves its frames agreeing to well below the depth maps'
    pixel noise, which the blocks average out; per-frame camera errors and depth warps (the vggt
    profile) make them disagree by their size, several times the noise."""
    source = open_source(str(world))
    frames = [source.get(i) for i in range(0, 100, 6)]
    noise = SIM_EXACT["depth_noise"]
    exact = measured(frames, profile="exact", seed=0)
    strong = measured(frames, **STRONG, seed=0)
    vggt = measured(frames, profile="vggt", seed=0)
    assert exact < 0.5 * noise and strong < 0.5 * noise, (exact, strong, noise)
    assert vggt > 5 * noise and vggt > 20 * strong, (vggt, strong)
    assert measured(frames, **STRONG, depth_noise=0.0, seed=0) < 0.1 * noise


def frames_of(n: int, disagreement: float | None) -> SubmapFrames:
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 2, 3] = np.arange(n) * 0.1
    return SubmapFrames(tuple(range(n)), T, shared=0, disagreement=disagreement)


@pytest.mark.parametrize("factor, disagreement, expected", [
    (0.0, 0.002, 0.05),  # not used
    (2.0, None, 0.05),  # not measured
    (2.0, 0.002, 0.004),
    (2.0, 0.04, 0.05),  # at most frame_sigma
    (2.0, 1e-5, 1e-3),  # at least min_sigma
])
def test_chain_sigma_follows_the_window_agreement(factor, disagreement, expected):
    backend = KeyframeBackend(BackendConfig(window_agreement_factor=factor))
    assert backend.chain_sigma(frames_of(4, disagreement)) == pytest.approx(expected)


ADD_SUBMAP = KeyframeBackend.add_submap


def chain_sigmas(world: Path, monkeypatch, factor: float, **sim) -> list[float]:
    """Run the defaults with ``window_agreement_factor = factor`` on the lap: every submap's chain sigma."""
    seen: list[float] = []
    add_submap = ADD_SUBMAP

    def spy(self, submap_id, H_prev_cur, information=None, frames=None):
        add_submap(self, submap_id, H_prev_cur, information, frames)
        seen.append(self.chain_sigma(frames))

    monkeypatch.setattr(KeyframeBackend, "add_submap", spy)
    config = SLAMConfig(frontend="simulated")
    config.retrieval.kind = "none"
    config.backend.window_agreement_factor = factor
    for key, value in sim.items():
        setattr(config.sim, key, value)
    SLAMPipeline.from_config(config).run(open_source(str(world)), progress=False)
    return seen


def test_the_pipeline_stiffens_consistent_windows_only(world: Path, monkeypatch):
    """With the factor on, every submap under a strong per-window distortion gets links well below
    frame_sigma (camera-linked ones included); under the vggt profile's per-frame errors they stay
    several times looser."""
    frame_sigma = BackendConfig().frame_sigma
    strong = chain_sigmas(world, monkeypatch, 2.0, **STRONG, seed=2)
    assert len(strong) >= 3 and max(strong) < 0.2 * frame_sigma, strong
    vggt = chain_sigmas(world, monkeypatch, 2.0, profile="vggt", seed=2)
    assert len(vggt) >= 3 and min(vggt) > 4 * max(strong), (vggt, strong)
    off = chain_sigmas(world, monkeypatch, 0.0, **STRONG, seed=2)
    assert off[0] == frame_sigma and strong[0] < 0.2 * frame_sigma, (off, strong)  # the first submap has no fitted link


def test_the_flat_depth_reader_reads_what_the_two_dimensional_one_does():
    from sl4slam.refine import _bilinear_depth, _bilinear_depth_flat

    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 4.0, size=(30, 40)).astype(np.float32)
    valid = rng.random((30, 40)) > 0.2
    depth[~valid & (rng.random((30, 40)) > 0.5)] = 0.0  # some invalid pixels hold no depth at all
    u, v = rng.uniform(0, 38.999, size=500), rng.uniform(0, 28.999, size=500)
    col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inverse = 1.0 / np.where(valid, depth, 1.0).astype(np.float64)
    expected, expected_known = _bilinear_depth(inverse, valid, row, col, u - col, v - row)
    got, known = _bilinear_depth_flat(depth, valid, row, col, u - col, v - row)
    assert 0 < known.sum() < len(known)
    np.testing.assert_array_equal(known, expected_known)
    np.testing.assert_array_equal(got[known], expected[known])
