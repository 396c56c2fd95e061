"""Keyframe files: the compact layout (the default) against the full one, written from the same run.

The compact file holds the run's own float16 depth in the keyframe's submap frame with that frame's
camera and projective map into the world, so its world points are the run's (bounded by
``COMPACT_POINT_TOLERANCE`` = 1e-6 of the depth; 0 measured here); the mask is the same; colours
are JPEG (quality 85, 4:4:4: on the 128x96 synthetic frames a mean absolute error of 4.4 levels of
255, 99th percentile 19); the confidence is the run's uint8 percentile, which the full file rounds
to float16 (at most 0.031 percentile points apart). Measured at 128x96: 10.7x fewer bytes per
keyframe (the 518x392 figures are in ``benchmarks/results/keyframe_format.md``). Checked in an SL(4)
keyframe graph and in a projective world (the submap graph with a 0.1 perspective distortion per
submap, no metric upgrade), through every reader: exports, ``--all-frames`` from a folder, the
viewer, the dense evaluation.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from result_folders import small_world_config, write_known_result
from sl4slam.cli import build_parser, config_from_args
from sl4slam.config import SLAMConfig, config_from_dict, load_config
from sl4slam.errors import UserError
from sl4slam.export import export_colmap, export_nerfstudio, export_result
from sl4slam.geometry import se3_inverse
from sl4slam.io import open_source
from sl4slam.localize import localize_frames, views_from_pipeline, views_from_result
from sl4slam.pipeline import SLAMPipeline
from sl4slam.resolve import resolve
from sl4slam.result import SLAMResult, keyframe_cameras
from sl4slam.parallel import ordered_map
from sl4slam.result.outputs import keyframe_world_points, read_ply, write_map_and_keyframes, write_outputs
from sl4slam.result.reading import COMPACT_POINT_TOLERANCE, decode_depth, encode_depth, load_result
from sl4slam.runner import run_slam
from sl4slam.submap import StoredKeyframe
from sl4slam.synthetic import write_seven_scenes_sequence, write_synthetic_sequence

WIDTH, HEIGHT = 128, 96
COLOUR_MEAN, COLOUR_P99 = 5.0, 22.0
"""JPEG error bounds in levels of 255 (measured 4.4 and 19 on these frames)."""
CONFIDENCE_STEP = 0.0313
"""Half the float16 spacing of percentiles in [64, 100]: how far the full file's float16 confidence
may lie from the run's own percentile."""
MIN_RATIO = 10.0


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_synthetic_sequence(tmp_path_factory.mktemp("world") / "w", num_frames=120, width=WIDTH,
                                    height=HEIGHT, seed=0)


def _assert_layout(folder: Path, layout: str) -> None:
    """Every keyframe file of ``folder`` is in ``layout`` (by its arrays, not through the reader)."""
    files = sorted((folder / "keyframes").glob("*.npz"))
    assert files, f"{folder} has no keyframe files"
    for path in files:
        with np.load(path) as data:
            compact = "depth_bytes" in data.files and "points_world" not in data.files
            assert compact == (layout == "compact"), (path, data.files)


def _config(graph: str) -> SLAMConfig:
    config = small_world_config(perspective=0.1)
    config.keyframes.tau_disparity = 10.0  # px at 128 px wide
    config.backend.graph = graph
    config.upgrade.mode = "off"  # keep the submap graph's world projective
    return config


@pytest.fixture(scope="module", params=["keyframe", "submap"])
def run(request, world, tmp_path_factory) -> SimpleNamespace:
    """One pipeline run, its outputs written three times: ``full/``, ``compact/``, ``none/``."""
    config = _config(request.param)
    result = SLAMPipeline.from_config(config, retrieval=None).run(open_source(str(world)), progress=False)
    root = tmp_path_factory.mktemp(f"run_{request.param}")
    for layout in ("full", "compact", "none"):
        written = copy.deepcopy(config)
        written.output.keyframes = layout
        write_outputs(result, root / layout, resolve(written), source_name="world")
    _assert_layout(root / "full", "full")
    _assert_layout(root / "compact", "compact")
    return SimpleNamespace(root=root, result=result, graph=request.param, world=world)


def _depth_along_axis(points: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    T_cam_world = se3_inverse(T_world_cam)
    return points.astype(np.float64) @ T_cam_world[2, :3] + T_cam_world[2, 3]


def test_compact_reads_back_the_full_points_mask_colours_and_confidence(run) -> None:
    full, compact = load_result(run.root / "full"), load_result(run.root / "compact")
    assert {r.layout for r in full.keyframes} == {"full"} and {r.layout for r in compact.keyframes} == {"compact"}
    assert len(compact.keyframes) == len(full.keyframes) == len(run.result.keyframes) > 20
    worst, colour_errors, perspective = 0.0, [], 0.0
    for a, b, keyframe in zip(full.keyframes, compact.keyframes, run.result.keyframes):
        assert (a.frame_index, a.submap_id, a.timestamp, a.image_size) == (b.frame_index, b.submap_id, b.timestamp,
                                                                            b.image_size)
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
        A, B = a.load(), b.load()
        np.testing.assert_array_equal(A.mask, B.mask)
        assert B.mask.sum() > 0.1 * B.mask.size  # not vacuous (a frame facing a far wall keeps fewer)
        assert not B.points_world[~B.mask].any() and not B.depth[~B.mask].any()
        # the world points: the full file's, and the run's own, within the stated tolerance of the depth
        depth = np.abs(_depth_along_axis(A.points_world[A.mask], a.T_world_cam))
        distance = np.linalg.norm(A.points_world[A.mask].astype(np.float64) - B.points_world[B.mask], axis=1)
        worst = max(worst, float((distance / depth).max()))
        X_run, valid_run = keyframe_world_points(keyframe, run.result.H_world(keyframe))
        np.testing.assert_array_equal(valid_run, B.mask)
        np.testing.assert_allclose(B.points_world[B.mask], X_run[valid_run], rtol=0, atol=COMPACT_POINT_TOLERANCE * depth.max())
        # ... which lie on the rays of the keyframe's world camera K [R|t], whatever the projective map
        X_cam = B.points_world[B.mask].astype(np.float64) @ se3_inverse(b.T_world_cam)[:3, :3].T + se3_inverse(b.T_world_cam)[:3, 3]
        uvw = X_cam @ b.K.T
        rows, cols = np.nonzero(B.mask)
        np.testing.assert_allclose(uvw[:, :2] / uvw[:, 2:], np.stack([cols, rows], axis=1), atol=1e-3)
        # colours within JPEG error; confidence the run's percentile (the full file's float16 of it)
        colour_errors.append(np.abs(A.colors.astype(np.int16) - B.colors).ravel())
        np.testing.assert_array_equal(B.confidence, keyframe.confidence_percentile())
        np.testing.assert_allclose(B.confidence, A.confidence, rtol=0, atol=CONFIDENCE_STEP)
        perspective = max(perspective, float(np.abs(B.H_world_local[3, :3]).max()))
    assert worst <= COMPACT_POINT_TOLERANCE, worst
    errors = np.concatenate(colour_errors)
    assert errors.mean() < COLOUR_MEAN and np.percentile(errors, 99) < COLOUR_P99, (errors.mean(), np.percentile(errors, 99))
    if run.graph == "submap":  # the world map really is projective: w varies over every keyframe
        assert perspective > 0.05, perspective


@pytest.mark.parametrize("layout", ["compact", "full"])
def test_the_map_and_keyframe_files_do_not_depend_on_the_worker_count(run, layout, tmp_path) -> None:
    """Keyframes are processed in threads; the random subsample is drawn in keyframe order, so one
    thread and three write the same bytes (the map subsampled: the draws are exercised)."""
    written = {}
    for workers in (1, 3):
        folder = tmp_path / str(workers)
        folder.mkdir()
        count = write_map_and_keyframes(run.result, folder, max_points=5000, seed=4, keyframe_dir=folder / "keyframes",
                                        layout=layout, workers=workers)
        assert 0 < count <= 5000
        written[workers] = {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
    assert len(written[1]) == len(run.result.keyframes) + 1
    assert written[1] == written[3]


def test_ordered_map_keeps_order_bounds_what_is_in_flight_and_raises_in_turn() -> None:
    import threading

    lock, state = threading.Lock(), {"running": 0, "most": 0, "started": 0}

    def slow_first(i: int) -> int:
        with lock:
            state["running"] += 1
            state["started"] += 1
            state["most"] = max(state["most"], state["running"])
        if i == 0:
            threading.Event().wait(0.05)  # the first item finishes last: order must still hold
        with lock:
            state["running"] -= 1
        if i == 7:
            raise ValueError("item 7")
        return i * i

    got = []
    with pytest.raises(ValueError, match="item 7"):
        for value in ordered_map(slow_first, range(40), workers=2):
            got.append(value)
    assert got == [i * i for i in range(7)]
    assert state["most"] <= 2
    assert state["started"] <= 7 + 1 + 2 * 2  # nothing runs far ahead of what is consumed
    assert list(ordered_map(lambda i: -i, range(5), workers=1)) == [0, -1, -2, -3, -4]


def test_compact_is_at_least_ten_times_smaller(run) -> None:
    sizes = {layout: [r.path.stat().st_size for r in load_result(run.root / layout).keyframes]
             for layout in ("full", "compact")}
    ratio = np.mean(sizes["full"]) / np.mean(sizes["compact"])
    assert ratio >= MIN_RATIO, f"compact files are only {ratio:.2f}x smaller ({np.mean(sizes['compact']):.0f} bytes)"
    summary = json.loads((run.root / "compact" / "summary.json").read_text())
    assert summary["config"]["output"]["keyframes"] == "compact"


def test_exports_of_the_compact_layout_match_the_full_one(run, tmp_path) -> None:
    full, compact = load_result(run.root / "full"), load_result(run.root / "compact")
    reports = {name: (export_colmap(result, tmp_path / f"colmap_{name}"), export_nerfstudio(result, tmp_path / f"ns_{name}"))
               for name, result in (("full", full), ("compact", compact))}
    for a, b in zip(reports["full"], reports["compact"]):
        assert (a.images, a.points) == (b.images, b.points) and a.points > 1000
        assert b.mean_reprojection_px == pytest.approx(a.mean_reprojection_px, abs=1e-4)
        assert b.max_skew_px == a.max_skew_px
    xyz_full, _ = read_ply(tmp_path / "ns_full" / "sparse_pc.ply")
    xyz_compact, _ = read_ply(tmp_path / "ns_compact" / "sparse_pc.ply")
    np.testing.assert_allclose(xyz_compact, xyz_full, rtol=COMPACT_POINT_TOLERANCE, atol=1e-6)
    assert json.loads((tmp_path / "ns_full" / "transforms.json").read_text()) == \
        json.loads((tmp_path / "ns_compact" / "transforms.json").read_text())
    export_result(run.root / "compact", "ply", tmp_path / "ply_compact")
    export_result(run.root / "full", "ply", tmp_path / "ply_full")
    for path in sorted((tmp_path / "ply_full").glob("submap_*.ply")):
        xyz_a, rgb_a = read_ply(path)
        xyz_b, rgb_b = read_ply(tmp_path / "ply_compact" / path.name)
        np.testing.assert_allclose(xyz_b, xyz_a, rtol=COMPACT_POINT_TOLERANCE, atol=1e-6)
        assert np.abs(rgb_a.astype(np.int16) - rgb_b).mean() < COLOUR_MEAN


def test_all_frames_from_a_compact_folder_are_the_runs_own(run) -> None:
    """The compact file holds the submap frame, so the folder localizes frames as the run does in
    memory; the full file's world points stand in for it only to first order in a projective world."""
    source = open_source(str(run.world))
    in_memory = localize_frames(source, views_from_pipeline(run.result))
    from_compact = localize_frames(source, views_from_result(load_result(run.root / "compact")))
    from_full = localize_frames(source, views_from_result(load_result(run.root / "full")))
    assert from_compact.failed == [] and (~from_compact.is_keyframe).sum() >= 20
    np.testing.assert_array_equal(from_compact.frame_indices, in_memory.frame_indices)
    np.testing.assert_array_equal(from_compact.T_world_cam[from_compact.is_keyframe], run.result.T_world_cam)
    others = ~in_memory.is_keyframe
    centres = in_memory.T_world_cam[others, :3, 3]
    extent = np.linalg.norm(np.ptp(in_memory.T_world_cam[:, :3, 3], axis=0))
    compact_difference = np.linalg.norm(from_compact.T_world_cam[others, :3, 3] - centres, axis=1) / extent
    full_difference = np.linalg.norm(from_full.T_world_cam[others, :3, 3] - centres, axis=1) / extent
    # the only difference left: corners found on the JPEG colours instead of the source's (median
    # 4e-4 of the path's extent measured, both graphs); in the projective world the full layout's
    # first-order stand-in is 6x further off (2.8e-3)
    assert np.median(compact_difference) < 1e-3, np.median(compact_difference)
    if run.graph == "submap":
        assert np.median(compact_difference) < 0.5 * np.median(full_difference)


def test_the_viewer_reads_the_compact_layout(run) -> None:
    from sl4slam.viewer.result import state_from_result
    from sl4slam.viewer.scene import ViewerSettings

    states = {layout: state_from_result(load_result(run.root / layout), ViewerSettings(point_budget=10**6))
              for layout in ("full", "compact")}
    full, compact = states["full"], states["compact"]
    assert sorted(full.clouds) == sorted(compact.clouds) and len(compact.clouds) >= 5
    for submap_id, cloud in full.clouds.items():
        other = compact.clouds[submap_id]
        assert other.full_count == cloud.full_count
        np.testing.assert_allclose(other.centre + other.offsets, cloud.centre + cloud.offsets, atol=1e-5)
        np.testing.assert_allclose(other.confidence, cloud.confidence, atol=CONFIDENCE_STEP)
    np.testing.assert_array_equal(compact.T_world_cam, full.T_world_cam)
    assert set(compact.thumbnails) == set(full.thumbnails)


def test_keyframes_none_writes_no_folder_and_the_tools_name_the_option(world, tmp_path) -> None:
    args = build_parser().parse_args(["run", str(world), "--out", str(tmp_path / "r"), "--frontend", "simulated",
                                      "--keyframes", "none", "--retrieval", "none", "--tau-disparity", "10"])
    config = config_from_args(args)
    assert config.output.keyframes == "none"
    run_slam(world, tmp_path / "r", config, progress=False)
    assert not (tmp_path / "r" / "keyframes").exists() and (tmp_path / "r" / "map.ply").is_file()
    for fmt in ("colmap", "nerfstudio", "ply"):
        with pytest.raises(UserError, match="--keyframes compact") as error:
            export_result(tmp_path / "r", fmt)
        assert len(str(error.value).splitlines()) == 1
    with pytest.raises(UserError, match="--keyframes compact"):
        views_from_result(load_result(tmp_path / "r"))


def test_a_full_layout_folder_of_earlier_releases_still_reads(tmp_path) -> None:
    for version in (1, 2):
        truth = write_known_result(tmp_path / f"v{version}", version=version, confidence=True)
        result = load_result(tmp_path / f"v{version}")
        assert result.version == version and [r.layout for r in result.keyframes] == ["full"] * len(result.keyframes)
        for record in result.keyframes:
            data = record.load()
            assert data.depth is None and data.points_local() is None and data.confidence is not None
            np.testing.assert_allclose(data.points_world, truth["points"][record.frame_index], atol=1e-6)
            np.testing.assert_array_equal(data.mask, truth["masks"][record.frame_index])


def test_invalid_pixels_and_the_plane_at_infinity(tmp_path) -> None:
    """Pixels that leave the mask (low confidence, float16 overflow, beyond the plane at infinity of
    the projective world map, w <= 0) are invalid and zero in both layouts; the rest agree."""
    rng = np.random.default_rng(3)
    height, width = 24, 32
    depth = rng.uniform(1.0, 5.0, (height, width))
    depth[2, 3:6] = np.inf  # as a float16 overflow leaves it
    mask = rng.random((height, width)) > 0.2
    mask[5] = False  # a row without any valid pixel
    mask[6, :7] = False  # a row whose first pixels are invalid
    mask[2, 3:6] = True
    K = np.array([[30.0, 0.2, 15.5], [0.0, 31.0, 11.5], [0.0, 0.0, 1.0]])
    T_cam_submap = np.eye(4)
    T_cam_submap[:3, 3] = [0.1, -0.2, 0.3]
    keyframe = StoredKeyframe(frame_index=7, timestamp=0.25, submap_id=0, slot=1, depth=depth.astype(np.float16),
                              mask_bits=np.packbits(mask), confidence_rank=rng.integers(0, 256, (12, 16)).astype(np.uint8),
                              K=K, T_cam_submap=T_cam_submap, principal_point=np.array([15.5, 11.5]))
    H = np.eye(4)
    H[3, 2] = -0.25  # w = 1 - 0.25 z_submap: points beyond 4 units fall behind the plane at infinity
    H[0, 1] = 0.1
    T_world_cam, K_world = keyframe_cameras([keyframe], {0: H})
    result = SLAMResult(keyframes=[keyframe], T_world_cam=T_world_cam, K=K_world, H_world_submap={0: H},
                        T_world_cam_gt=None, edges=[], segments=np.zeros(1, np.int64))
    loaded = {}
    for layout in ("full", "compact"):
        config = SLAMConfig()
        config.output.keyframes = layout
        write_outputs(result, tmp_path / layout, resolve(config))
        (record,) = load_result(tmp_path / layout).keyframes
        loaded[layout] = record.load()
    full, compact = loaded["full"], loaded["compact"]
    X_run, valid = keyframe_world_points(keyframe, H)
    with np.errstate(invalid="ignore"):
        w = keyframe.points().astype(np.float64) @ H[3, :3] + H[3, 3]
    assert (mask & (w <= 0)).any() and not valid[mask & (w <= 0)].any()  # some pixels do fall behind
    assert not valid[2, 3:6].any() and not valid[5].any()
    for data in (full, compact):
        np.testing.assert_array_equal(data.mask, valid)
        assert not data.points_world[~valid].any()
        np.testing.assert_array_equal(data.points_world[valid], X_run[valid])
    np.testing.assert_array_equal(compact.depth[valid], depth.astype(np.float16).astype(np.float32)[valid])
    assert np.isfinite(compact.points_local()[valid]).all()


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_depth_coding_is_lossless_where_the_mask_is_set(dtype) -> None:
    rng = np.random.default_rng(0)
    depth = rng.lognormal(0.5, 1.0, (37, 53)).astype(dtype)
    depth[0, 0], depth[1, 1], depth[2, 2], depth[3, 3] = np.inf, -2.5, 0.0, np.finfo(dtype).tiny / 4  # subnormal
    depth[4, 4] = np.nan
    mask = rng.random(depth.shape) > 0.3
    mask[10] = False
    mask[11, :20] = False
    mask[:4, :5] = True
    for given in (None, mask):
        planes = encode_depth(depth, given)
        assert planes.dtype == np.uint8 and planes.shape == (np.dtype(dtype).itemsize,) + depth.shape
        decoded = decode_depth(planes)
        assert decoded.dtype == dtype
        where = np.ones(depth.shape, bool) if given is None else mask
        np.testing.assert_array_equal(decoded.view(np.uint8).reshape(depth.shape + (-1,))[where],
                                      depth.view(np.uint8).reshape(depth.shape + (-1,))[where])


def test_the_setting_of_earlier_releases_is_read(tmp_path) -> None:
    assert SLAMConfig().output.keyframes == "compact"
    assert config_from_dict({"output": {"save_keyframe_points": True}}).output.keyframes == "compact"
    assert config_from_dict({"output": {"save_keyframe_points": False}}).output.keyframes == "none"
    both = {"output": {"save_keyframe_points": False, "keyframes": "full"}}
    assert config_from_dict(both).output.keyframes == "full"  # the current key wins
    (tmp_path / "old.toml").write_text("[output]\nsave_keyframe_points = false\nmax_map_points = 1000\n")
    config = load_config(tmp_path / "old.toml")
    assert config.output.keyframes == "none" and config.output.max_map_points == 1000
    config.output.keyframes = "raw"
    with pytest.raises(UserError, match="--keyframes .*output.keyframes.*compact, full, none"):
        config.output.validate()


def test_dense_evaluation_reads_the_compact_layout(tmp_path) -> None:
    from sl4slam.evaluation import get_dataset
    from sl4slam.evaluation.protocol import keyframe_clouds

    write_seven_scenes_sequence(tmp_path / "7s" / "chess" / "seq-01", num_frames=48, width=96, height=72, seed=2)
    dataset = get_dataset("7scenes")
    (sequence,), _ = dataset.resolve(tmp_path / "7s", ["chess"])
    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 4.0
    config.submap.size = 8
    config.retrieval.kind = "none"
    result = SLAMPipeline.from_config(config, retrieval=None).run(dataset.open(sequence), progress=False)
    clouds = {}
    for layout in ("full", "compact"):
        written = copy.deepcopy(config)
        written.output.keyframes = layout
        write_outputs(result, tmp_path / layout, resolve(written))
        _assert_layout(tmp_path / layout, layout)
        clouds[layout] = keyframe_clouds(tmp_path / layout, dataset, sequence, written, max_depth=10.0)
    (estimate_full, truth_full, used_full), (estimate, truth, used) = clouds["full"], clouds["compact"]
    assert used == used_full == len(result.keyframes)
    np.testing.assert_array_equal(truth, truth_full)
    np.testing.assert_allclose(estimate, estimate_full, rtol=COMPACT_POINT_TOLERANCE, atol=1e-6)


def test_a_damaged_keyframe_file_is_one_line(run, tmp_path) -> None:
    import shutil

    shutil.copytree(run.root / "compact", tmp_path / "r")
    record = load_result(tmp_path / "r").keyframes[0]
    record.path.write_bytes(record.path.read_bytes()[:4000])  # cut short, as by a full disk
    with pytest.raises(UserError, match="cannot be read.*damaged") as error:
        record.load()
    assert len(str(error.value).splitlines()) == 1
