"""Open-vocabulary 3D object queries: the embeddings file, lifting masks, fusing views into boxes,
box overlap, the query's one-line errors, the synthetic oracle end to end and the ``query`` verb."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.errors import UserError
from sl4slam.objects.fusion import (ViewDetection, box_corners, box_iou, extend_to_background, fit_box, fuse_views,
                                    refine_offset)
from sl4slam.objects.interfaces import ImageEmbedder, Mask2D, TextSegmenter
from sl4slam.objects.lift import grid_normals, points_under_mask, resize_mask, ring_points, trim_points
from sl4slam.objects.query import check_query, query_result
from sl4slam.objects.store import EMBEDDINGS_FILE, read_embeddings, write_embeddings

sys.path.insert(0, str(Path(__file__).resolve().parent))
from result_folders import run_small_world, write_known_result  # noqa: E402


# ------------------------------------------------------------------------------ embeddings file
def test_embeddings_round_trip_normalised_float16(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    raw = rng.normal(size=(4, 6)) * 3.0
    path = write_embeddings(tmp_path, [9, 3, 6, 0], raw, "pe-core-test")
    with np.load(path) as data:
        assert data["embeddings"].dtype == np.float16 and data["frame_index"].dtype == np.int64
        assert str(data["model"]) == "pe-core-test" and int(data["format"]) == 1
    read = read_embeddings(tmp_path)
    assert read.frame_index.tolist() == [0, 3, 6, 9]  # sorted by frame, rows follow
    expected = raw[[3, 1, 2, 0]] / np.linalg.norm(raw[[3, 1, 2, 0]], axis=1, keepdims=True)
    assert np.allclose(read.embeddings, expected, atol=2e-3)
    assert np.allclose(np.linalg.norm(read.embeddings, axis=1), 1.0, atol=1e-6)
    assert read.model == "pe-core-test" and read.dim == 6
    with pytest.raises(ValueError):
        write_embeddings(tmp_path, [1, 1], np.ones((2, 3)), "m")
    with pytest.raises(ValueError):
        write_embeddings(tmp_path, [1, 2, 3], np.ones((2, 3)), "m")


def test_missing_or_damaged_embeddings_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(UserError) as absent:
        read_embeddings(tmp_path)
    assert str(absent.value) == f"{tmp_path} has no keyframe embeddings: run with --objects to make them"
    (tmp_path / EMBEDDINGS_FILE).parent.mkdir()
    np.savez(tmp_path / EMBEDDINGS_FILE, frame_index=np.arange(2), model=np.array("m"), format=np.array(1))
    with pytest.raises(UserError, match="damaged .*no embeddings") as damaged:
        read_embeddings(tmp_path)
    assert "\n" not in str(damaged.value)
    (tmp_path / EMBEDDINGS_FILE).write_bytes(b"not a zip")
    with pytest.raises(UserError, match="damaged"):
        read_embeddings(tmp_path)
    np.savez(tmp_path / EMBEDDINGS_FILE, frame_index=np.arange(2), embeddings=np.ones((2, 3), np.float16),
             model=np.array("m"), format=np.array(7))
    with pytest.raises(UserError, match="format 7"):
        read_embeddings(tmp_path)


# ------------------------------------------------------------------------------ lifting
def test_resize_mask_is_nearest_neighbour() -> None:
    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:4] = True
    up = resize_mask(mask, (8, 12))
    assert up.shape == (8, 12) and up.sum() == 4 * mask.sum()
    assert np.array_equal(up[::2, ::2], mask) and np.array_equal(up[1::2, 1::2], mask)
    assert np.array_equal(resize_mask(up, (4, 6)), mask)
    assert np.array_equal(resize_mask(mask, (4, 6)), mask)


def _plane_grid(height: int = 30, width: int = 40, depth: float = 2.0) -> np.ndarray:
    """World points of a camera at the origin looking along +z at a wall ``depth`` away (f = 40 px)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([(u - width / 2) / 40.0 * depth, (v - height / 2) / 40.0 * depth, np.full(u.shape, depth)], -1)


def test_points_under_mask_keep_valid_confident_pixels_and_trim_bleeding() -> None:
    points = _plane_grid()
    points[10:20, 10:20, 2] = 1.0  # an object 1 m in front of the wall
    points[10:20, 10:20, :2] *= 0.5
    valid = np.ones((30, 40), bool)
    valid[12, 12] = False
    confidence = np.full((30, 40), 80.0)
    confidence[13, 13] = 5.0
    mask = np.zeros((60, 80), bool)  # at twice the grid's resolution
    mask[20:40, 20:40] = True
    lifted = points_under_mask(mask, points, valid, confidence, min_confidence=10.0)
    assert lifted.shape == (100 - 2, 3) and np.allclose(lifted[:, 2], 1.0)
    # a mask that bleeds one pixel over the object's edge picks up wall points: the range cut drops them
    bled = np.zeros((30, 40), bool)
    bled[10:21, 10:20] = True
    raw = points_under_mask(bled, points, np.ones((30, 40), bool))
    assert (raw[:, 2] > 1.5).sum() == 10
    kept = trim_points(raw, camera_centre=np.zeros(3))
    assert len(kept) == 100 and np.allclose(kept[:, 2], 1.0)
    # a uniform spread (a table seen end-on) keeps every point
    line = np.stack([np.linspace(0, 3, 200), np.zeros(200), np.linspace(1, 4, 200)], -1)
    assert len(trim_points(line, camera_centre=np.array([0.0, 0.0, -1.0]))) == 200


def test_grid_normals_and_ring() -> None:
    points = _plane_grid()
    normals = grid_normals(points, np.ones((30, 40), bool), camera_centre=np.zeros(3))
    assert np.allclose(normals[1:-1, 1:-1], [0.0, 0.0, -1.0], atol=1e-9)  # towards the camera
    assert not normals[0].any() and not normals[:, -1].any()
    mask = np.zeros((30, 40), bool)
    mask[10:20, 10:20] = True
    ring = ring_points(mask, points, np.ones((30, 40), bool), width_px=2)
    assert len(ring) == 14 * 14 - 100


# ------------------------------------------------------------------------------ boxes
def test_box_iou_exact_cases() -> None:
    I = np.eye(3)
    unit = (np.zeros(3), I, np.ones(3))
    assert box_iou(unit, unit) == pytest.approx(1.0)
    assert box_iou(unit, (np.array([0.5, 0, 0]), I, np.ones(3))) == pytest.approx(1 / 3)
    assert box_iou(unit, (np.array([0.5, 0.5, 0.5]), I, np.ones(3))) == pytest.approx(0.125 / 1.875)
    assert box_iou(unit, (np.array([3.0, 0, 0]), I, np.ones(3))) == 0.0
    turned = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    octagon = 2 * (np.sqrt(2) - 1)  # the square and itself turned by 45 degrees share a regular octagon
    assert box_iou(unit, (np.zeros(3), turned.T, np.ones(3))) == pytest.approx(octagon / (2 - octagon), rel=1e-9)
    inner = (np.zeros(3), Rotation.random(random_state=3).as_matrix(), np.full(3, 0.3))
    assert box_iou(unit, inner) == pytest.approx(0.027, rel=1e-9)  # wholly inside


def _box_surface(centre, R, size, faces, per_face: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward normals on the given faces ``(axis, side)`` of a box."""
    points, normals = [], []
    for axis, side in faces:
        local = rng.uniform(-0.5, 0.5, (per_face, 3)) * size
        local[:, axis] = side * size[axis] / 2
        normal = np.zeros(3)
        normal[axis] = side
        points.append(local @ R.T + centre)
        normals.append(np.tile(R @ normal, (per_face, 1)))
    return np.concatenate(points), np.concatenate(normals)


def test_fit_box_from_two_seen_faces_and_from_all_six() -> None:
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=2).as_matrix()
    centre, size = np.array([1.0, -2.0, 0.5]), np.array([1.2, 0.6, 0.4])
    every = [(a, s) for a in range(3) for s in (-1, 1)]
    points, _ = _box_surface(centre, R, size, every, 500, rng)
    c, axes, extents = fit_box(points)
    assert np.allclose(axes @ axes.T, np.eye(3), atol=1e-9) and np.linalg.det(axes) > 0
    assert box_iou((c, axes, extents), (centre, R.T, size)) > 0.85
    points, normals = _box_surface(centre, R, size, [(0, 1), (2, 1)], 800, rng)
    _, axes, _ = fit_box(points + rng.normal(0, 0.005, points.shape), normals=normals)
    assert np.allclose(np.abs(axes @ R).max(axis=1), 1.0, atol=1e-3)  # the box's own axes
    corners = box_corners(c, axes, extents)
    assert corners.shape == (8, 3) and np.allclose(corners.mean(0), c)


def test_fusion_merges_views_of_one_object_and_keeps_another_apart() -> None:
    rng = np.random.default_rng(4)
    size = np.array([1.0, 0.8, 0.6])
    front, front_n = _box_surface(np.zeros(3), np.eye(3), size, [(0, -1), (2, 1)], 600, rng)
    side, side_n = _box_surface(np.zeros(3), np.eye(3), size, [(1, -1), (2, 1)], 600, rng)
    other, other_n = _box_surface(np.array([4.0, 0, 0]), np.eye(3), size, [(0, -1), (2, 1)], 600, rng)
    detections = [ViewDetection(3, front, 0.9, 0.8, normals=front_n), ViewDetection(5, side, 0.8, 0.7, normals=side_n),
                  ViewDetection(5, other, 0.6, 0.7, normals=other_n), ViewDetection(7, np.zeros((0, 3)), 0.9, 0.9)]
    instances = fuse_views(detections, keyframes_searched=4, refine=False, amodal=False)
    assert [sorted(i.frames) for i in instances] == [[3, 5], [5]]
    assert instances[0].score == pytest.approx((0.9 + 0.8) / 4) and instances[1].score == pytest.approx(0.6 / 4)
    assert instances[0].best_view == 3
    assert box_iou((instances[0].centre, instances[0].axes, instances[0].extents), (np.zeros(3), np.eye(3), size)) > 0.8
    # a view carried 8 cm off by the map's registration error is laid back onto the first; one that
    # shares only the top face with it is not moved along that face (nothing pins it there)
    corner = [(0, -1), (1, -1), (2, 1)]  # three faces: every direction of the offset is pinned down
    seen, seen_n = _box_surface(np.zeros(3), np.eye(3), size, corner, 600, rng)
    again, _ = _box_surface(np.zeros(3), np.eye(3), size, corner, 600, rng)
    assert np.allclose(refine_offset(again + [0.08, -0.05, 0.03], seen, seen_n), [-0.08, 0.05, -0.03], atol=0.005)
    slid = refine_offset(side + [0.08, -0.05, 0.0], front, front_n)
    assert abs(slid[0]) < 0.02 and abs(slid[2]) < 0.005


def test_hidden_back_extends_to_the_background_at_most_to_the_longest_side() -> None:
    rng = np.random.default_rng(5)
    # a box's front face seen from a camera at x = -3 looking along +x, a wall behind it at x = 1.5
    face = np.column_stack([np.zeros(400), rng.uniform(-0.5, 0.5, 400), rng.uniform(0, 1.0, 400)])
    wall = np.column_stack([np.full(200, 1.5), rng.uniform(-1, 1, 200), rng.uniform(0, 1.5, 200)])
    view = ViewDetection(1, face, 1.0, 1.0, background=wall, camera_centre=np.array([-3.0, 0.0, 0.5]))
    centre, axes, extents = fit_box(face)
    c, a, e = extend_to_background(centre, axes, extents, [view])
    assert np.allclose(a, axes)
    thin = int(np.argmax(np.abs(a[:, 0])))
    assert e[thin] == pytest.approx(max(e))  # capped: the wall is farther than the longest side
    near_wall = ViewDetection(1, face, 1.0, 1.0, background=wall - [1.1, 0, 0], camera_centre=view.camera_centre)
    c, a, e = extend_to_background(centre, axes, extents, [near_wall])
    assert c @ a[thin] * np.sign(a[thin, 0]) + e[thin] / 2 == pytest.approx(0.4, abs=1e-9)  # the back at the wall
    assert extend_to_background(centre, axes, extents, [ViewDetection(1, face, 1.0)])[2] is extents


# ------------------------------------------------------------------------------ the query
class _Untouchable:
    """An embedder and segmenter that fail if a query uses them."""

    name = "untouchable"
    dim = 3

    def embed_images(self, images):
        raise AssertionError("model work before the checks")

    embed_texts = embed_images

    def segment(self, image, text, threshold=0.5):
        raise AssertionError("model work before the checks")


def test_interfaces_are_protocols() -> None:
    assert isinstance(_Untouchable(), ImageEmbedder) and isinstance(_Untouchable(), TextSegmenter)
    assert Mask2D(np.zeros((2, 2), bool), 0.7).score == 0.7


@pytest.mark.parametrize("text, top_k, threshold, words", [
    ("", 5, 0.5, "empty"), ("   ", 5, 0.5, "empty"), ("a" * 301, 5, 0.5, "301 characters"),
    ("mug", 0, 0.5, "--top-k"), ("mug", 5, 1.5, "--threshold")])
def test_bad_queries_are_one_line_before_any_model_work(tmp_path: Path, text, top_k, threshold, words) -> None:
    with pytest.raises(UserError) as error:
        query_result(tmp_path, text, _Untouchable(), _Untouchable(), top_k=top_k, threshold=threshold)
    assert words in str(error.value) and "\n" not in str(error.value)
    assert check_query("a" * 300) == "a" * 300
    limited = _Untouchable()
    limited.max_text_chars = 10
    with pytest.raises(UserError, match="at most 10"):
        query_result(tmp_path, "a long description", limited, limited)


def test_results_without_keyframes_or_embeddings_are_one_line(tmp_path: Path) -> None:
    write_known_result(tmp_path / "old", keyframes=False)  # format 1, no keyframes folder
    with pytest.raises(UserError, match="no keyframes") as error:
        query_result(tmp_path / "old", "mug", _Untouchable(), _Untouchable())
    assert "\n" not in str(error.value)
    write_known_result(tmp_path / "plain", version=3)
    with pytest.raises(UserError) as error:
        query_result(tmp_path / "plain", "mug", _Untouchable(), _Untouchable())
    assert str(error.value) == f"{tmp_path / 'plain'} has no keyframe embeddings: run with --objects to make them"
    (tmp_path / "new").mkdir()
    (tmp_path / "new" / "summary.json").write_text(json.dumps({"counts": {}, "format": {"name": "sl4slam-result", "version": 99}}))
    (tmp_path / "new" / "trajectory.txt").write_text("0 0 0 0 0 0 0 1\n")
    with pytest.raises(UserError, match="format version 99"):
        query_result(tmp_path / "new", "mug", _Untouchable(), _Untouchable())
    write_embeddings(tmp_path / "plain", [0, 3], np.eye(2, 3), "another-model")
    with pytest.raises(UserError, match="made with another-model"):
        query_result(tmp_path / "plain", "mug", _Untouchable(), _Untouchable())


# ------------------------------------------------------------------------------ oracle end to end
@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """A run of the simulated frontend on the synthetic world (120 frames at 96x72, about 10 s) with
    the oracle's embeddings written into it."""
    from sl4slam.objects.oracle import SyntheticOracle, write_oracle_embeddings
    from sl4slam.result.reading import load_result

    root = tmp_path_factory.mktemp("objects")
    result = load_result(run_small_world(root, frames=120))
    oracle = SyntheticOracle(root / "world")
    oracle.register_result(result)
    write_oracle_embeddings(result, oracle)
    return result, oracle


CLEARLY_SEEN = 2
"""The box of the small run's world covering most of a keyframe (36 % of one, seen by 18 of 75)."""
FUSED_IOU_BOUND = 0.5
"""The fused box's IoU with the true one for :data:`CLEARLY_SEEN` is 0.74 on the development
machine; without the hidden-back extension (its back is against the wall, never seen) it is 0.36,
and with the lifting, the fusion or the map alignment broken it falls near 0. A box 5 cm (the run's
ATE) too long at both ends of each of its three sides would still score 0.77, so 0.5 leaves room
for another machine's float rounding while failing when any step breaks."""


def test_oracle_query_finds_a_clearly_seen_box(small_run) -> None:
    from sl4slam.objects.oracle import (OracleEmbedder, OracleSegmenter, align_map_to_truth, box_to_truth,
                                        object_text)

    result, oracle = small_run
    embedder, segmenter = OracleEmbedder(oracle), OracleSegmenter(oracle)
    answer = result.query(object_text(CLEARLY_SEEN), embedder, segmenter, top_k=5)
    assert len(answer.keyframes) == 5 and answer.keyframes[0].similarity >= answer.keyframes[-1].similarity
    assert len(answer.instances) == 1 and len(answer.instances[0].views) == 5
    best = answer.instances[0]
    T_gt_map = align_map_to_truth(result, oracle)
    iou = box_iou(box_to_truth(best.centre, best.axes, best.extents, T_gt_map), oracle.true_box(CLEARLY_SEEN))
    assert iou > FUSED_IOU_BOUND
    # the best keyframe is the one the box covers most
    shape = (result.keyframes[0].image_size[1], result.keyframes[0].image_size[0])
    cover = {k.frame_index: oracle.coverage(k.frame_index, shape)[CLEARLY_SEEN] for k in result.keyframes}
    assert cover[answer.keyframes[0].frame_index] >= np.quantile(list(cover.values()), 0.9)
    data = answer.to_json()
    assert data["query"] == "box 2" and data["instances"][0]["best_view"] in [k["frame_index"] for k in data["keyframes"]]
    assert np.allclose(data["instances"][0]["centre"], best.centre, atol=1e-5)
    assert np.allclose(np.array(data["instances"][0]["axes"]) @ np.array(data["instances"][0]["axes"]).T, np.eye(3), atol=1e-5)
    assert set(data["seconds"]) >= {"embed_text", "segment", "lift", "fuse", "total"}
    # a text naming nothing in the map finds nothing
    assert query_result(result, "a red mug", embedder, segmenter).instances == []
    # deterministic
    again = query_result(result.path, object_text(CLEARLY_SEEN), embedder, segmenter, top_k=5)
    assert np.array_equal(again.instances[0].centre, best.centre)


def test_object_ids_match_the_ray_caster() -> None:
    from types import SimpleNamespace

    from sl4slam.synthetic import camera_path, cast_rays, default_intrinsics, make_layout
    from sl4slam.synthetic.render import camera_rays, object_ids_from_surfaces, render_object_ids

    layout = make_layout(0)  # geometry only: no textures to synthesise
    poses, K = camera_path(40, 0)[::13], default_intrinsics(48, 36)
    ids = render_object_ids(layout, poses, K, 48, 36)
    v, u = np.mgrid[0:36, 0:48]
    rays = camera_rays(K, np.stack([u.ravel(), v.ravel()], axis=1))
    for pose, frame_ids in zip(poses, ids):
        _, surfaces = cast_rays(SimpleNamespace(layout=layout), np.tile(pose[:3, 3], (len(rays), 1)), rays @ pose[:3, :3].T)
        assert np.array_equal(frame_ids.ravel(), object_ids_from_surfaces(surfaces))
    assert (ids >= 0).any() and (ids == -1).any()
    assert object_ids_from_surfaces(np.array([0, 5, 6, 11, 12, 6 + 6 * 7 + 5])).tolist() == [-1, -1, 0, 0, 1, 7]


# ------------------------------------------------------------------------------ the query verb
def test_query_verb_prints_a_table_and_writes_json(small_run, tmp_path: Path, monkeypatch, capsys) -> None:
    import sl4slam.cli as cli
    from sl4slam.objects.oracle import ORACLE_EMBEDDER, OracleEmbedder, OracleSegmenter

    result, oracle = small_run
    asked = []

    def oracle_models(model):
        asked.append(model)
        return OracleEmbedder(oracle), OracleSegmenter(oracle)

    monkeypatch.setattr(cli, "query_models", oracle_models)
    out = tmp_path / "answer.json"
    assert cli.main(["query", str(result.path), "box 2", "--top-k", "3", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert asked == [ORACLE_EMBEDDER] and '"box 2": 1 instance(s) in 3 keyframe(s)' in printed
    data = json.loads(out.read_text())
    assert data["top_k"] == 3 and len(data["instances"]) == 1 and len(data["instances"][0]["extents"]) == 3
    for argv, words in ((["query", str(result.path), ""], "empty"),
                        (["query", str(result.path), "box 2", "--top-k", "0"], "--top-k"),
                        (["query", str(tmp_path), "box 2"], "not an sl4slam result")):
        asked.clear()
        assert cli.main(argv) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(lines) == 1 and words in lines[0] and not asked


# ------------------------------------------------------------------------------ the viewer's text box
def test_viewer_text_box_draws_the_answer(small_run) -> None:
    pytest.importorskip("viser")
    import io
    import socket

    from sl4slam.objects.oracle import OracleEmbedder, OracleSegmenter
    from sl4slam.viewer.app import MapViewer
    from sl4slam.viewer.objects import ObjectQueryPanel, box_edges, mask_overlay
    from sl4slam.viewer.scene import ViewerSettings

    edges = box_edges(np.zeros(3), np.eye(3), np.array([2.0, 1.0, 0.5]))
    assert edges.shape == (12, 2, 3)
    assert np.allclose(np.sort(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1)), [0.5] * 4 + [1.0] * 4 + [2.0] * 4)
    tinted = mask_overlay(np.full((4, 4, 3), 100, np.uint8), np.eye(2, dtype=bool), color=(200, 0, 0), alpha=0.5)
    assert tinted[0, 0].tolist() == [150, 50, 50] and tinted[0, 3].tolist() == [100, 100, 100]

    result, oracle = small_run
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    viewer = MapViewer(ViewerSettings(port=port), stream=io.StringIO())
    try:
        panel = ObjectQueryPanel(viewer, result, models=lambda name: (OracleEmbedder(oracle), OracleSegmenter(oracle)))
        answer = panel.find("box 2")
        assert answer is not None and len(answer.instances) == 1
        assert len(panel._nodes) == 2 and panel.gui_image.visible and "box 2" in panel.gui_answer.content
        assert panel.find("   ") is None and "empty" in panel.gui_answer.content
        assert not panel._nodes and not panel.gui_image.visible
    finally:
        viewer.close()
