"""Exports against exactly known cameras: COLMAP (read back by pycolmap), nerfstudio, per-submap PLY;
and the one-line errors for folders that cannot be exported."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from result_folders import run_small_world, write_known_result
from sl4slam.errors import UserError
from sl4slam.export import colmap_pose, export_colmap, export_nerfstudio, export_result, export_submap_ply, pinhole_params
from sl4slam.result.outputs import read_ply
from sl4slam.result.reading import load_result


@pytest.fixture(scope="module")
def small_run(tmp_path_factory) -> Path:
    return run_small_world(tmp_path_factory.mktemp("run"))


def _project_colmap(image, camera, xyz: np.ndarray) -> np.ndarray:
    """Project with the camera and pose as pycolmap read them (independent of our conventions)."""
    T = image.cam_from_world().matrix()
    X = xyz @ T[:, :3].T + T[:, 3]
    fx, fy, cx, cy = camera.params
    return np.stack([fx * X[:, 0] / X[:, 2] + cx, fy * X[:, 1] / X[:, 2] + cy], axis=1)


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_round_trip_through_pycolmap(tmp_path: Path, binary: bool) -> None:
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) reads the exported model back")
    truth = write_known_result(tmp_path / "run", count=5)
    report = export_colmap(load_result(tmp_path / "run"), tmp_path / "colmap", binary=binary, text=not binary)
    model = pycolmap.Reconstruction()
    (model.read_binary if binary else model.read_text)(str(tmp_path / "colmap" / "sparse" / "0"))
    assert model.num_images() == 5 and model.num_cameras() == 5
    expected_points = sum(int(m.sum()) for m in truth["masks"].values())
    assert model.num_points3D() == expected_points == report.points
    for image_id, image in model.images.items():
        frame = int(Path(image.name).stem)
        i = int(np.flatnonzero(truth["frame_indices"] == frame)[0])
        np.testing.assert_allclose(image.cam_from_world().matrix(), np.linalg.inv(truth["T_world_cam"][i])[:3], atol=1e-9)
        camera = model.cameras[image.camera_id]
        assert camera.model_name == "PINHOLE" and (camera.width, camera.height) == (48, 36)
        K = truth["K"]
        np.testing.assert_allclose(camera.params, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5], atol=1e-9)
        assert (tmp_path / "colmap" / "images" / image.name).is_file()
        # every observation is the pixel its point came from: the point projects exactly onto it
        observed = np.array([p.xy for p in image.points2D])
        xyz = np.array([model.points3D[p.point3D_id].xyz for p in image.points2D])
        np.testing.assert_allclose(_project_colmap(image, camera, xyz), observed, atol=1e-4)  # float32 points
        rows, cols = np.nonzero(truth["masks"][frame])
        np.testing.assert_allclose(observed, np.stack([cols + 0.5, rows + 0.5], 1), atol=1e-12)
    assert report.max_skew_px == 0.0 and report.mean_reprojection_px < 1e-4


def test_colmap_drops_the_skew_and_reports_what_it_costs(tmp_path: Path) -> None:
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) reads the exported model back")
    write_known_result(tmp_path / "run", count=3, skew=1.5)
    report = export_colmap(load_result(tmp_path / "run"), tmp_path / "colmap", max_points=500)
    assert report.max_skew_px == pytest.approx(1.5)
    model = pycolmap.Reconstruction(str(tmp_path / "colmap" / "sparse" / "0"))
    assert model.num_points3D() <= 500 and report.points == model.num_points3D()
    # the stored per-point error is the reprojection error pycolmap computes for the model
    assert model.compute_mean_reprojection_error() == pytest.approx(report.mean_reprojection_px, rel=1e-6)
    assert 0.05 < report.mean_reprojection_px < 1.5  # a skew of 1.5 px moves pixels by up to about that


def test_nerfstudio_transforms_against_known_poses(tmp_path: Path) -> None:
    truth = write_known_result(tmp_path / "run", count=4)
    export_nerfstudio(load_result(tmp_path / "run"), tmp_path / "ns")
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    assert meta["camera_model"] == "PINHOLE" and len(meta["frames"]) == 4
    xyz_ply, _ = read_ply(tmp_path / "ns" / meta["ply_file_path"])
    assert len(xyz_ply) == sum(int(m.sum()) for m in truth["masks"].values())
    for frame in meta["frames"]:
        index = int(Path(frame["file_path"]).stem)
        i = int(np.flatnonzero(truth["frame_indices"] == index)[0])
        c2w = np.array(frame["transform_matrix"])
        # OpenGL camera axes: x right, y up, z back (the camera looks along -z)
        np.testing.assert_allclose(c2w @ np.diag([1, -1, -1, 1]), truth["T_world_cam"][i], atol=1e-12)
        image = cv2.imread(str(tmp_path / "ns" / frame["file_path"]))
        assert image.shape[:2] == (frame["h"], frame["w"]) == (36, 48)
        # project the keyframe's points the way nerfstudio does and land on the pixel corners + 0.5
        rows, cols = np.nonzero(truth["masks"][index])
        X = truth["points"][index][rows, cols]
        X_cam = (np.linalg.inv(c2w) @ np.c_[X, np.ones(len(X))].T).T
        u = frame["fl_x"] * X_cam[:, 0] / -X_cam[:, 2] + frame["cx"]
        v = frame["fl_y"] * -X_cam[:, 1] / -X_cam[:, 2] + frame["cy"]
        np.testing.assert_allclose(np.stack([u, v], 1), np.stack([cols + 0.5, rows + 0.5], 1), atol=1e-4)


def test_submap_ply_holds_every_confident_pixel(tmp_path: Path) -> None:
    truth = write_known_result(tmp_path / "run", count=7, submap_size=3)
    export_submap_ply(load_result(tmp_path / "run"), tmp_path / "ply")
    files = sorted((tmp_path / "ply").glob("submap_*.ply"))
    assert [f.name for f in files] == ["submap_0000.ply", "submap_0001.ply", "submap_0002.ply"]
    xyz, rgb = read_ply(files[1])
    frames = truth["frame_indices"][3:6]
    expected = np.concatenate([truth["points"][int(f)][truth["masks"][int(f)]] for f in frames])
    np.testing.assert_allclose(xyz, expected, atol=1e-6)
    assert rgb.dtype == np.uint8 and not list((tmp_path / "ply").glob("*.tmp*"))


def test_pipeline_result_exports_consistently(small_run: Path, tmp_path: Path) -> None:
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) reads the exported model back")
    result = load_result(small_run)
    report = export_result(small_run, "colmap", tmp_path / "colmap", max_points=20000)
    model = pycolmap.Reconstruction(str(tmp_path / "colmap" / "sparse" / "0"))
    assert model.num_images() == len(result.keyframes) == result.summary["counts"]["keyframes"]
    centres = {int(Path(im.name).stem): im.projection_center() for im in model.images.values()}
    for record in result.keyframes:
        np.testing.assert_allclose(centres[record.frame_index], record.T_world_cam[:3, 3], atol=1e-9)
    # the map's points project near their pixels: only the dropped skew separates them
    assert report.mean_reprojection_px < 2.0
    assert model.compute_mean_reprojection_error() == pytest.approx(report.mean_reprojection_px, rel=1e-6)


def test_conventions_are_inverse_of_each_other() -> None:
    T = np.eye(4)[None].repeat(2, 0)
    T[1, :3, :3] = cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0]
    T[1, :3, 3] = [1.0, 2.0, 3.0]
    qvec, tvec = colmap_pose(T)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(np.c_[qvec[:, 1:], qvec[:, :1]]).as_matrix()
    np.testing.assert_allclose(R, np.swapaxes(T[:, :3, :3], 1, 2), atol=1e-12)
    np.testing.assert_allclose(tvec[1], -T[1, :3, :3].T @ T[1, :3, 3], atol=1e-12)
    assert (qvec[:, 0] >= 0).all()
    np.testing.assert_allclose(pinhole_params(np.array([[10.0, 0.3, 5.0], [0, 11.0, 6.0], [0, 0, 1.0]])), [10, 11, 5.5, 6.5])


def test_export_of_a_run_without_keyframe_files_names_the_option(tmp_path: Path) -> None:
    write_known_result(tmp_path / "run", keyframes=False)
    with pytest.raises(UserError, match="--keyframes compact"):
        export_result(tmp_path / "run", "colmap")
    assert not (tmp_path / "run" / "export_colmap").exists()


@pytest.mark.parametrize("make, words", [
    (lambda p: p.mkdir(), "not an sl4slam result folder"),
    (lambda p: (p.mkdir(), (p / "summary.json").write_text("{}"), (p / "trajectory.txt").write_text("0 0 0 0 0 0 0 1\n")),
     "not an sl4slam run summary"),
    (lambda p: (write_known_result(p, version=2), (p / "summary.json").write_text(json.dumps(
        {**json.loads((p / "summary.json").read_text()), "format": {"name": "sl4slam-result", "version": 9}}))),
     "version 9"),
])
def test_bad_result_folder_is_one_line(tmp_path: Path, make, words: str) -> None:
    make(tmp_path / "r")
    proc = subprocess.run([sys.executable, "-m", "sl4slam.cli", "export", str(tmp_path / "r"), "--format", "ply"],
                          capture_output=True, text=True, timeout=120)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and words in lines[0], proc.stderr


@pytest.mark.parametrize("verb", ["export", "view"])
def test_new_verbs_have_help(verb: str) -> None:
    proc = subprocess.run([sys.executable, "-m", "sl4slam.cli", verb, "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "usage" in proc.stdout and "RESULT" not in proc.stderr
    assert ("--format" in proc.stdout) == (verb == "export") and ("--host" in proc.stdout) == (verb == "view")
