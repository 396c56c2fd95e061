"""The keyframe graph (VGGT-SLAM 2.0) and its parts: the calibration-and-scale link, the factors,
exact recovery, the attention loop check (against the reference code path) and its simulated stand-in."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import gtsam
import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from scipy.spatial.transform import Rotation

from sl4slam.alignment import HybridAligner
from sl4slam.alignment.sim3 import calibration_scale_link
from sl4slam.backend import BackendUpdateError, KeyframeBackend, Sim3Backend, SL4Backend, SubmapFrames, make_backend
from sl4slam.backend.pose_graph import adjoint_matrix, transport_information
from sl4slam.config import AlignmentConfig, BackendConfig, SLAMConfig
from sl4slam.resolve import AlignmentModel, GraphDesign, resolve
from sl4slam.edges import is_camera_link
from sl4slam.errors import UserError
from sl4slam.frontend.overlap import overlap_match_ratio
from sl4slam.geometry import apply_transform, decompose_projection, normalize_sl4, se3_inverse, unproject_depth
from sl4slam.io import open_source
from sl4slam.models.vggt.attention import MatchRatioProbe, mean_top_quarter
from sl4slam.models.vggt.model import VGGT, VGGTModelConfig
from sl4slam.models.vggt.weights import load_state_dict_into
from sl4slam.result.outputs import compute_ate
from sl4slam.pipeline import SLAMPipeline
from sl4slam.runner import run_slam
from sl4slam.synthetic import write_synthetic_sequence
from sl4slam.types import FrameView

GENERATORS = np.stack([np.asarray(gtsam.SL4.Hat(e)) for e in np.eye(15)])


def vee(M: np.ndarray) -> np.ndarray:
    """GTSAM's SL(4) chart at the identity: coordinates of ``M``'s traceless part (orthonormal basis)."""
    return np.einsum("mij,ij->m", GENERATORS, M)


def rigid(rng: np.random.Generator, rot: float = 0.3, trans: float = 0.5) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(scale=rot, size=3)).as_matrix()
    T[:3, 3] = rng.normal(scale=trans, size=3)
    return T


def intrinsics(f: float, cx: float = 32.0, cy: float = 24.0) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, 1.02 * f, cy], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------- the calibration-and-scale link
def shared_frame(rng: np.random.Generator, K_a: np.ndarray, K_b: np.ndarray, s: float, height: int = 48,
                 width: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame reconstructed twice: with ``K_a`` and depth ``d`` in submap ``a``, with ``K_b`` and
    ``d / s`` in submap ``b``. Returns ``depth, T_a, T_b, points_a, points_b``."""
    depth = rng.uniform(1.0, 3.0, (height, width)).astype(np.float32)
    T_a, T_b = rigid(rng), rigid(rng)
    points_a = unproject_depth(depth[None], K_a[None], T_a[None])[0]
    points_b = unproject_depth((depth / s)[None], K_b[None], T_b[None])[0]
    return depth, T_a, T_b, points_a.reshape(-1, 3).astype(np.float64), points_b.reshape(-1, 3).astype(np.float64)


def test_calibration_link_is_the_hand_computed_matrix_and_maps_pixels_onto_their_rays() -> None:
    rng = np.random.default_rng(1)
    K_a, K_b, s = intrinsics(55.0), intrinsics(48.0), 1.9
    _, T_a, T_b, X_a, X_b = shared_frame(rng, K_a, K_b, s)
    link = calibration_scale_link(K_a, T_a, K_b, T_b, X_a, X_b, inlier_threshold=1e-4)
    assert link.extras["scale"] == pytest.approx(s, rel=1e-5) and is_camera_link(link)
    L = np.eye(4)
    L[:3, :3] = s * np.linalg.inv(K_a) @ K_b  # hand-computed: diag(K_a,1)^-1 diag(K_b,1) diag(s,s,s,1)
    np.testing.assert_allclose(T_a @ link.H @ se3_inverse(T_b), L, rtol=1e-5, atol=1e-7)
    assert link.inlier_ratio == 1.0 and link.rms < 1e-5  # exact between reconstructions that differ so
    np.testing.assert_allclose(apply_transform(link.H, X_b), X_a, atol=1e-4)
    pixel = np.array([10.0, 40.0, 1.0])  # a pixel of camera b at depth 2.5 lands on the same pixel of a
    X_cam_a = (L @ np.append(2.5 * np.linalg.solve(K_b, pixel), 1.0))[:3]
    np.testing.assert_allclose(K_a @ X_cam_a / X_cam_a[2], pixel, atol=1e-12)


def test_calibration_scale_is_the_median_depth_ratio_despite_outliers() -> None:
    rng = np.random.default_rng(0)
    K_a, K_b, s = intrinsics(50.0), intrinsics(44.0), 0.62
    depth, T_a, T_b, X_a, X_b = shared_frame(rng, K_a, K_b, s)
    noisy = depth * np.exp(rng.normal(scale=0.01, size=depth.shape)).astype(np.float32)
    noisy.reshape(-1)[:450] *= rng.uniform(1.5, 3.0, 450).astype(np.float32)  # 15 % gross outliers on one side
    X_a = unproject_depth(noisy[None], K_a[None], T_a[None])[0].reshape(-1, 3).astype(np.float64)
    link = calibration_scale_link(K_a, T_a, K_b, T_b, X_a, X_b)
    assert link.extras["scale"] == pytest.approx(s, rel=0.03)
    with pytest.raises(ValueError, match="finite"):
        calibration_scale_link(K_a, T_a, K_b, T_b, np.full((3, 3), np.nan), X_b[:3])


def hybrid_views(rng: np.random.Generator, H_b_a: np.ndarray, noise: float) -> tuple[FrameView, FrameView]:
    """The frame in submap ``a`` (a bumpy surface, 48x64) and in submap ``b``, whose points are
    ``H_b_a`` of ``a``'s (with relative depth noise) and whose camera agrees with ``a``'s on the image."""
    height, width = 48, 64
    K = intrinsics(55.0)
    rows, cols = np.mgrid[0:height, 0:width]
    depth = (2.0 + 0.6 * np.sin(cols / 9.0) * np.cos(rows / 7.0)).astype(np.float32)  # well off any plane
    T_a = rigid(rng)
    points_a = unproject_depth(depth[None], K[None], T_a[None])[0]
    mask = np.ones((height, width), dtype=bool)
    P_b = K @ T_a[:3] @ np.linalg.inv(H_b_a)  # the same image seen in submap b
    K_b, T_world_cam, _ = decompose_projection(P_b)
    T_b = se3_inverse(T_world_cam)
    camera_b = apply_transform(T_b, apply_transform(H_b_a, points_a.reshape(-1, 3).astype(np.float64)))
    depth_b = (camera_b[:, 2] * np.exp(rng.normal(scale=noise, size=len(camera_b)))).reshape(height, width)
    points_b = unproject_depth(depth_b[None].astype(np.float32), K_b[None], T_b[None])[0]
    return FrameView(points_a, mask, K, T_a), FrameView(points_b, mask, K_b, T_b)


def test_hybrid_link_keeps_the_calibration_link_unless_the_points_show_a_projective_distortion() -> None:
    rng = np.random.default_rng(6)
    config = AlignmentConfig(inlier_threshold=0.02)
    similar = normalize_sl4(np.diag([1.4, 1.4, 1.4, 1.0]) @ rigid(rng, 0.1, 0.2))  # cameras and depth agree up to scale
    view_a, view_b = hybrid_views(rng, similar, noise=0.003)
    link = HybridAligner(config).align(view_a, view_b, seed=0)
    assert link.model == "sl4" and is_camera_link(link) and link.fallback is None
    assert link.extras["hybrid_ratio"] < config.hybrid_margin
    distorted = similar.copy()
    distorted[3, :3] = [0.08, -0.05, 0.06]  # a relative perspective part the cameras cannot carry
    view_a, view_b = hybrid_views(rng, normalize_sl4(distorted), noise=0.0005)
    fit = HybridAligner(config).align(view_a, view_b, seed=0)
    assert not is_camera_link(fit) and fit.extras["hybrid_ratio"] > config.hybrid_margin
    assert fit.inlier_ratio > 0.99


# ---------------------------------------------------------------------------- the graph's factors
def small_graph(rng: np.random.Generator) -> tuple[KeyframeBackend, list[SubmapFrames], np.ndarray, np.ndarray,
                                                   np.ndarray, np.ndarray]:
    """Two submaps of three keyframes sharing frame 12, and a loop from frame 10 (submap 0) to 14 (submap 1)."""
    frames_0 = SubmapFrames((10, 11, 12), np.stack([np.eye(4), rigid(rng), rigid(rng)]), shared=False)
    frames_1 = SubmapFrames((12, 13, 14), np.stack([np.eye(4), rigid(rng), rigid(rng)]), shared=True)
    H_odometry = normalize_sl4(np.diag([1.3, 1.3, 1.3, 1.0]) @ rigid(rng))
    H_loop = normalize_sl4(np.diag([0.8, 0.8, 0.8, 1.0]) @ rigid(rng))
    info_odometry = np.diag(rng.uniform(10.0, 1e4, 15))
    backend = KeyframeBackend(BackendConfig(graph="keyframe"))
    backend.add_submap(0, None, frames=frames_0)
    backend.add_submap(1, H_odometry, info_odometry, frames=frames_1)
    backend.add_loop(0, 1, H_loop, np.eye(15) * 400.0, frames=(10, 14))
    return backend, [frames_0, frames_1], H_odometry, H_loop, info_odometry, np.eye(15) * 400.0


def test_factors_match_hand_computed_residuals() -> None:
    rng = np.random.default_rng(2)
    backend, (f0, f1), H_odometry, H_loop, _, _ = small_graph(rng)
    backend.update()
    graph = backend.nodes.factor_graph()
    X = {n: normalize_sl4(np.eye(4) + 0.2 * rng.normal(size=(4, 4))) for n in range(6)}  # any node values
    values = gtsam.Values()
    for n, M in X.items():
        values.insert(backend.nodes.key(n), gtsam.SL4(M))
    T0, T1 = f0.T_cam_submap, f1.T_cam_submap

    def residual(i: int, j: int, H_i_j: np.ndarray) -> np.ndarray:
        # the factor (j, i, H_i_j^-1): Local(H_i_j^-1, X_j^-1 X_i) = vee(H_i_j X_j^-1 X_i - I)
        return vee(normalize_sl4(H_i_j) @ np.linalg.inv(X[j]) @ X[i] - np.eye(4))

    expected = [
        None,  # the prior on node 0
        residual(0, 1, T0[0] @ se3_inverse(T0[1])),  # inside submap 0: the frontend's relative poses
        residual(1, 2, T0[1] @ se3_inverse(T0[2])),
        residual(2, 3, T0[2] @ H_odometry @ se3_inverse(T1[0])),  # shared frame 12: its two nodes
        residual(3, 4, T1[0] @ se3_inverse(T1[1])),
        residual(4, 5, T1[1] @ se3_inverse(T1[2])),
        residual(0, 5, T0[0] @ H_loop @ se3_inverse(T1[2])),  # loop: frame 10 in submap 0, frame 14 in submap 1
    ]
    assert graph.size() == len(expected)
    # the prior at T_cam_submap^-1 of the first keyframe (GTSAM's prior error: -Local(X, Z))
    prior = graph.at(0)
    np.testing.assert_allclose(prior.unwhitenedError(values), -vee(np.linalg.inv(X[0]) @ se3_inverse(T0[0]) - np.eye(4)),
                               atol=1e-9)
    for index in range(1, len(expected)):
        np.testing.assert_allclose(graph.at(index).unwhitenedError(values), expected[index], atol=1e-9)


def test_moving_a_measurement_onto_the_nodes_keeps_its_chi_square() -> None:
    rng = np.random.default_rng(3)
    A, B = rigid(rng), rigid(rng)
    xi = rng.normal(size=15)
    np.testing.assert_allclose(adjoint_matrix(A, GENERATORS) @ xi,
                               vee(A @ np.einsum("m,mij->ij", xi, GENERATORS) @ np.linalg.inv(A)), atol=1e-12)
    H = normalize_sl4(np.diag([1.2, 1.2, 1.2, 1.0]) @ rigid(rng))
    root = rng.normal(size=(15, 15))
    information = root @ root.T + np.eye(15)
    moved = transport_information(information, A, GENERATORS)
    # a submap-level estimate (Y_i, Y_j) and the node-level one (X = Y T^-1) give the same whitened error
    Y_i, Y_j = normalize_sl4(np.eye(4) + 0.1 * rng.normal(size=(4, 4))), normalize_sl4(np.eye(4) + 0.1 * rng.normal(size=(4, 4)))
    e = vee(H @ np.linalg.inv(Y_j) @ Y_i - np.eye(4))
    X_i, X_j = Y_i @ np.linalg.inv(A), Y_j @ B  # A = T_cam,i ; B = T_cam,j^-1
    e_nodes = vee(normalize_sl4(A @ H @ B) @ np.linalg.inv(X_j) @ X_i - np.eye(4))
    assert e_nodes @ moved @ e_nodes == pytest.approx(e @ information @ e, rel=1e-9)


def test_loop_check_and_rollback_work_on_keyframe_nodes(monkeypatch) -> None:
    rng = np.random.default_rng(4)
    backend, _, _, H_loop, _, info = small_graph(rng)
    backend.update()
    assert backend.num_nodes == 6 and backend.num_loops == 1 and backend.segments == [0]
    # the graph has partly absorbed its loop: the loop agrees with it better than a scaled copy does
    moved = normalize_sl4(np.diag([1.5, 1.5, 1.5, 1.0]) @ H_loop)
    agreeing, disagreeing = (backend.loop_chi2(0, 1, H, info, frames=(10, 14)) for H in (H_loop, moved))
    assert 0 < agreeing < disagreeing
    with pytest.raises(ValueError, match="has no node"):
        backend.add_loop(0, 1, H_loop, info, frames=(13, 14))
    # a failed update drops the submaps it added, with their nodes
    frames_2 = SubmapFrames((14, 15), np.stack([np.eye(4), rigid(rng)]), shared=True)
    backend.add_submap(2, normalize_sl4(rigid(rng)), None, frames=frames_2)
    monkeypatch.setattr(backend.nodes, "_solve", lambda *args: (_ for _ in ()).throw(RuntimeError("indeterminate")))
    with pytest.raises(BackendUpdateError):
        backend.update()
    assert backend.submap_ids == [0, 1] and backend.num_nodes == 6
    with pytest.raises(ValueError, match="must start with keyframes of the previous submap"):
        backend.add_submap(3, np.eye(4), None, frames=SubmapFrames((99, 100), np.stack([np.eye(4)] * 2), shared=True))


def test_revisits_of_closed_places_are_priors_on_keyframe_nodes() -> None:
    """The keyframe graph holds a loop to a keyframe on an already closed cycle as a prior on the
    query keyframe's node (``BackendConfig.revisit_priors``), and ends on the same optimum."""
    rng = np.random.default_rng(8)
    frames = [SubmapFrames(tuple(range(10 + 2 * k, 13 + 2 * k)), np.stack([np.eye(4), rigid(rng, 0.1, 0.2),
                                                                         rigid(rng, 0.1, 0.2)]), shared=k > 0)
              for k in range(4)]
    odometry = [None] + [normalize_sl4(rigid(rng, 0.1, 0.2)) for _ in range(3)]
    results = {}
    for revisit_priors in (True, False):
        backend = KeyframeBackend(BackendConfig(graph="keyframe", revisit_priors=revisit_priors))
        assert backend.nodes.revisit_priors is revisit_priors
        for k in range(4):
            backend.add_submap(k, odometry[k], None, frames=frames[k])
            backend.update()
            if k >= 2:  # loops from submap k - 2's first keyframe to this submap's last, a little off the chain
                older = k - 2
                H = np.linalg.inv(backend.H_world_submap(older)) @ backend.H_world_submap(k) @ normalize_sl4(rigid(
                    np.random.default_rng(k), 0.02, 0.05))
                backend.add_loop(older, k, normalize_sl4(H), np.eye(15) * 1e3, frames=(frames[older].frame_indices[0],
                                                                                       frames[k].frame_indices[-1]))
                backend.update()
        results[revisit_priors] = (backend.nodes.num_revisit_priors, backend.world_estimate(final=True).H_world_submap)
    # the second loop's older keyframe (frame 12, in submap 1) lies on the cycle the first closed
    assert results[True][0] == 1 and results[False][0] == 0
    for k in range(4):
        np.testing.assert_allclose(results[True][1][k], results[False][1][k], atol=1e-5)


@pytest.mark.parametrize("design", ["keyframe", "submap"])
def test_an_estimate_of_some_submaps_is_the_whole_estimate_restricted_to_them(design: str) -> None:
    """``world_estimate(submaps=...)`` (what the running metric frame reads for every completed link)
    holds the very transforms of the whole estimate for those submaps and their keyframes, and no
    others, with and without a pending submap and the final polish."""
    rng = np.random.default_rng(21)
    frames = [SubmapFrames(tuple(range(10 + 2 * k, 13 + 2 * k)), np.stack([np.eye(4), rigid(rng, 0.1, 0.2),
                                                                         rigid(rng, 0.1, 0.2)]), shared=k > 0)
              for k in range(5)]
    backend = make_backend(BackendConfig(graph=design))
    for k in range(5):
        backend.add_submap(k, None if k == 0 else normalize_sl4(rigid(rng, 0.1, 0.2)), None, frames=frames[k])
        if k < 4:  # the last one pending: its initial guess
            backend.update()
    for final in (False, True):
        whole = backend.world_estimate(final=final)
        part = backend.world_estimate(final=final, submaps={1, 4})
        assert sorted(part.H_world_submap) == [1, 4]
        for s in (1, 4):
            assert np.array_equal(part.H_world_submap[s], whole.H_world_submap[s])
        if design == "keyframe":
            assert set(part.H_world_keyframe) == set(frames[1].frame_indices[1:]) | set(frames[4].frame_indices[1:])
            for f, H in part.H_world_keyframe.items():
                assert np.array_equal(H, whole.H_world_keyframe[f])


def test_graph_setting() -> None:
    """"auto" is the keyframe graph for SL(4) and the submap graph for Sim(3), settled once by
    ``resolve`` with the rules that go with it; an explicit keyframe graph with Sim(3) is refused."""
    config = SLAMConfig(frontend="simulated")
    config.retrieval.kind = "orb"
    resolved = resolve(config)
    assert config.backend.graph == "auto" and resolved.config.backend.graph == "keyframe"  # the user's tree is kept
    assert (resolved.graph, resolved.alignment) == (GraphDesign.KEYFRAME, AlignmentModel.SELECT)
    assert resolved.attention_check and resolved.metric_upgrade  # "select" may choose 15-DOF links
    backend = make_backend(resolved.config.backend)
    assert isinstance(backend, KeyframeBackend) and backend.nodes.revisit_priors
    config.upgrade.mode = "on"
    assert resolve(config).metric_upgrade
    config.upgrade.mode = "auto"
    config.backend.graph = "submap"
    resolved = resolve(config)
    assert resolved.alignment is AlignmentModel.SL4 and not resolved.attention_check and resolved.metric_upgrade
    assert resolved.complete_links and any("metric upgrade: on (auto" in note for note in resolved.notes)
    backend = make_backend(resolved.config.backend)
    assert isinstance(backend, SL4Backend) and not backend.graph.revisit_priors
    config.backend.kind, config.backend.graph = "sim3", "auto"
    resolved = resolve(config)
    assert resolved.graph is GraphDesign.SUBMAP and resolved.alignment is AlignmentModel.SIM3_CAMERAS
    assert not resolved.metric_upgrade and not resolved.complete_links
    assert isinstance(make_backend(resolved.config.backend), Sim3Backend)
    config.backend.graph = "keyframe"
    with pytest.raises(UserError, match="--graph"):
        resolve(config)
    config.backend.graph, config.alignment.model = "submap", "sl4"
    with pytest.raises(UserError, match="--alignment \\(config key alignment.model\\) sl4"):
        resolve(config)
    config.backend.kind, config.alignment.model, config.retrieval.kind = "sl4", "auto", "none"
    assert not resolve(config).attention_check  # no retrieval: no loops to check


# ---------------------------------------------------------------------------- end to end on the synthetic world
@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """A 360-frame lap at 160x120 with a floor-only stretch, returning to its start."""
    return write_synthetic_sequence(tmp_path_factory.mktemp("kf") / "world", num_frames=360, width=160, height=120,
                                    seed=1)


def world_config(graph: str, false_loop_rate: float = 0.0, **sim) -> SLAMConfig:
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 12.0
    config.retrieval.kind = "orb"
    config.backend.graph = graph
    for key, value in sim.items():
        setattr(config.sim, key, value)
    config.false_loops.rate, config.false_loops.seed = false_loop_rate, config.sim.seed
    return config


def run(world: Path, config: SLAMConfig):
    pipeline = SLAMPipeline.from_config(config)
    return pipeline, pipeline.run(open_source(str(world)), progress=False)


def test_keyframe_graph_recovers_exact_poses_without_planar_fallbacks(world: Path) -> None:
    config = world_config("keyframe")  # no distortion, perspective 0
    config.alignment.model = "calibration"  # VGGT-SLAM 2.0's link: a planar frame is no fallback for it
    _, result = run(world, config)
    assert compute_ate(result).rmse < 1e-4
    assert result.stats["fallbacks"] == 0 and result.stats["segments"] == 1
    assert result.stats["loops"] >= 1
    loops = [e for e in result.edges if e.kind == "loop" and e.accepted]
    assert all(e.model == "calibration" and e.checks["match_ratio"] >= 0.85 for e in loops)
    # every keyframe has its own transform; orientations relative to the first keyframe are exact too
    assert set(result.H_world_keyframe) == {k.frame_index for k in result.keyframes}
    R, R_gt = result.T_world_cam[:, :3, :3], result.T_world_cam_gt[:, :3, :3]
    np.testing.assert_allclose(R[0].T @ R, R_gt[0].T @ R_gt, atol=1e-5)


def test_without_loops_the_keyframe_graph_equals_the_submap_graph(world: Path) -> None:
    results = []
    for graph in ("submap", "keyframe"):
        config = world_config(graph, perspective=0.1)
        config.retrieval.kind = "none"
        config.alignment.model = "calibration"
        config.upgrade.mode = "off"  # "auto" upgrades the submap graph's map only
        config.max_frames = 200
        results.append(run(world, config)[1])
    submap, keyframe = results
    assert len(submap.keyframes) == len(keyframe.keyframes) > 20
    np.testing.assert_allclose(keyframe.T_world_cam, submap.T_world_cam, atol=1e-6)


def test_the_attention_check_rejects_false_loops(world: Path) -> None:
    pipeline, result = run(world, world_config("keyframe", false_loop_rate=1.0, seed=3))
    loops = [e for e in result.edges if e.kind == "loop"]
    injected = set(pipeline.retrieval.injected)
    assert loops and {(e.query_frame, e.frame_index) for e in loops} == injected
    assert not any(e.accepted for e in loops)
    assert all("attention" in e.reason and e.checks["match_ratio"] < 0.85 for e in loops)


def test_a_cache_recorded_with_one_graph_replays_with_the_other(world: Path, tmp_path: Path) -> None:
    recorded = world_config("submap")
    recorded.max_frames = 160
    recorded.output.cache_frontend = True
    first = run_slam(world, tmp_path / "a", recorded, progress=False)
    replay = world_config("keyframe")
    replay.max_frames = 160
    second = run_slam(world, tmp_path / "b", replay, replay_dir=str(tmp_path / "a" / "frontend_cache"), progress=False)
    direct = compute_ate(run(world, replay)[1]).rmse
    assert second["counts"]["keyframes"] == first["counts"]["keyframes"] > 10
    assert second["config"]["backend"]["graph"] == "keyframe"
    assert first["graph"] == {"group": "sl4", "design": "submap", "alignment": "sl4"}
    assert second["graph"] == {"group": "sl4", "design": "keyframe", "alignment": "select"}
    assert second["ate"]["rmse"] == pytest.approx(direct, rel=1e-6)


# ---------------------------------------------------------------------------- the attention score
MATCH_FIXTURE = Path(__file__).resolve().parent / "fixtures" / "vggt_match_ratio.json"


def tiny_model(folder: Path) -> VGGT:
    config = VGGTModelConfig.from_reference_config(json.loads((folder / "config.json").read_text()))
    model = VGGT(config).eval()
    load_state_dict_into(model, load_file(str(folder / "state_dict.safetensors")))
    return model


def reference_cases(fixture: str) -> list[dict]:
    return [c for c in json.loads(MATCH_FIXTURE.read_text())["cases"] if c["fixture"] == fixture]


def probe_scores(model: VGGT, sequence: torch.Tensor) -> dict[int, float]:
    """``{global layer: score of (frame 0, frame 1)}`` of a two-frame sequence, every layer in one pass."""
    probes = [MatchRatioProbe(model.aggregator, [(0, 1)], num_frames=2, layer=layer)
              for layer in range(len(model.aggregator.global_blocks))]
    with contextlib.ExitStack() as stack, torch.no_grad():
        for probe in probes:
            stack.enter_context(probe)
        model.aggregator(sequence)
    return {layer: float(probe.ratios[0, 0]) for layer, probe in enumerate(probes)}


def test_match_ratio_equals_the_reference_code_path_on_tiny_b(fixtures_dir: Path) -> None:
    model = tiny_model(fixtures_dir / "vggt_tiny_b")
    images = load_file(str(fixtures_dir / "vggt_tiny_b" / "inputs.safetensors"))["images"]
    cases = reference_cases("tiny_b")
    assert len(cases) == 8  # two sequences, four global layers
    scores = {b: probe_scores(model, images[b:b + 1]) for b in range(2)}
    for case in cases:
        assert scores[int(case["sequence"][-1])][case["target_layer"]] == pytest.approx(case["image_match_ratio"], abs=1e-5)


@pytest.mark.slow
def test_match_ratio_equals_the_reference_code_path_on_tiny_a(shared_dir: Path) -> None:
    folder = shared_dir / "fixtures/vggt/tiny/tiny_a"
    model = tiny_model(folder)
    images = load_file(str(folder / "inputs.safetensors"))["images"]
    cases = reference_cases("tiny_a")
    pairs = {case["sequence"] for case in cases}
    scores = {pair: probe_scores(model, images[:, [int(pair[-2]), int(pair[-1])]]) for pair in pairs}
    assert len(cases) == 24  # four frame pairs, six global layers
    for case in cases:
        assert scores[case["sequence"]][case["target_layer"]] == pytest.approx(case["image_match_ratio"], abs=1e-5)


def test_the_probe_reads_a_pair_inside_a_window_without_changing_the_outputs(fixtures_dir: Path) -> None:
    model = tiny_model(fixtures_dir / "vggt_tiny_b")
    images = load_file(str(fixtures_dir / "vggt_tiny_b" / "inputs.safetensors"))["images"][:1]
    window = torch.cat([images, images[:, :1]], dim=1)  # three frames: A, B, A again
    with torch.no_grad():
        plain = model(window)["depth"]
        with MatchRatioProbe(model.aggregator, [(0, 2), (0, 1), (1, 0)], num_frames=3, layer=3) as probe:
            probed = model(window)["depth"]
    assert torch.equal(plain, probed)
    ratios = probe.ratios[0]
    assert ratios.shape == (3,) and np.isfinite(ratios).all()
    assert ratios[1] != pytest.approx(ratios[2])  # the score is not symmetric: order matters
    with pytest.raises(ValueError, match="does not exist"):
        MatchRatioProbe(model.aggregator, [(0, 1)], num_frames=3, layer=4)


def test_mean_top_quarter() -> None:
    assert mean_top_quarter(np.arange(8.0)) == pytest.approx(6.5)  # 75th percentile 5.25: the mean of 6 and 7
    assert mean_top_quarter(np.r_[np.zeros(12), np.ones(4)]) == 1.0


def test_overlap_stand_in_follows_the_true_overlap(world: Path) -> None:
    source = open_source(str(world))
    frame = source.get(40)
    assert overlap_match_ratio(frame, frame) == pytest.approx(1.0)
    turned = source.get(220)  # the far side of the room
    assert overlap_match_ratio(frame, turned) < 0.2
    assert overlap_match_ratio(frame, source.get(44)) > 0.85  # a few frames on: mostly the same view
