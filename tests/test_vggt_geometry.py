"""VGGT camera conventions, geometry helpers and preprocessing against the reference fixtures."""

from __future__ import annotations

import json
import lzma

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import load, load_file

from sl4slam.models.vggt.geometry import closed_form_inverse_se3, unproject_depth_map_to_point_map
from sl4slam.models.vggt.pose_encoding import (
    extri_intri_to_pose_encoding,
    mat_to_quat,
    pose_encoding_to_extri_intri,
    quat_to_mat,
)
from sl4slam.models.vggt.preprocess import (channels_last, preprocess_images, preprocess_images_square, preprocess_uint8,
                                            to_uint8_rgb)

IMAGE_HW = (294, 518)


@pytest.fixture(scope="module")
def pose_fixture(fixtures_dir):
    return load_file(str(fixtures_dir / "vggt_pose_geometry.safetensors"))


def test_pose_encoding_decodes_like_reference(pose_fixture):
    extrinsics, intrinsics = pose_encoding_to_extri_intri(pose_fixture["pose_enc"], IMAGE_HW)
    torch.testing.assert_close(extrinsics, pose_fixture["extrinsics"], atol=1e-5, rtol=0)
    torch.testing.assert_close(intrinsics, pose_fixture["intrinsics"], atol=0, rtol=1e-6)
    # Principal point exactly at (W/2, H/2), height-first FoV.
    assert torch.all(intrinsics[..., 0, 2] == IMAGE_HW[1] / 2) and torch.all(intrinsics[..., 1, 2] == IMAGE_HW[0] / 2)
    _, no_intrinsics = pose_encoding_to_extri_intri(pose_fixture["pose_enc"], IMAGE_HW, build_intrinsics=False)
    assert no_intrinsics is None


def test_pose_encoding_roundtrip_like_reference(pose_fixture):
    encoded = extri_intri_to_pose_encoding(pose_fixture["extrinsics"], pose_fixture["intrinsics"], IMAGE_HW)
    assert encoded.dtype == torch.float32
    torch.testing.assert_close(encoded, pose_fixture["pose_enc_roundtrip"], atol=1e-5, rtol=0)
    extrinsics, intrinsics = pose_encoding_to_extri_intri(encoded, IMAGE_HW)
    torch.testing.assert_close(extrinsics, pose_fixture["extrinsics_roundtrip"], atol=1e-5, rtol=0)
    torch.testing.assert_close(intrinsics, pose_fixture["intrinsics_roundtrip"], atol=0, rtol=1e-6)
    assert torch.all(encoded[..., 6] >= 0)  # scalar part last and non-negative


def test_quaternion_helpers_match_reference(pose_fixture):
    matrices = quat_to_mat(pose_fixture["quat_in"])
    torch.testing.assert_close(matrices, pose_fixture["quat_to_mat_out"], atol=1e-5, rtol=0)
    # Exact sign convention, including w = 0 (180-degree) cases.
    torch.testing.assert_close(mat_to_quat(matrices), pose_fixture["mat_to_quat_out"], atol=1e-5, rtol=0)


def test_quaternion_is_xyzw():
    angle = 0.7
    q = torch.tensor([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)], dtype=torch.float64)  # about +z
    expected = torch.tensor(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]], dtype=torch.float64
    )
    torch.testing.assert_close(quat_to_mat(q), expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(mat_to_quat(expected), q, atol=1e-12, rtol=0)


def test_se3_inverse_matches_reference(pose_fixture):
    inv34 = closed_form_inverse_se3(pose_fixture["se3_3x4"])
    assert inv34.dtype == torch.float32 and inv34.shape == (4, 4, 4)
    torch.testing.assert_close(inv34, pose_fixture["se3_3x4_inverse"], atol=1e-5, rtol=0)
    torch.testing.assert_close(closed_form_inverse_se3(pose_fixture["se3_4x4"]), pose_fixture["se3_4x4_inverse"], atol=1e-5, rtol=0)
    numpy_inverse = closed_form_inverse_se3(pose_fixture["se3_3x4"].numpy())
    assert numpy_inverse.dtype == np.float64
    np.testing.assert_allclose(numpy_inverse, pose_fixture["se3_3x4_inverse_numpy_path"].numpy(), atol=1e-5, rtol=0)


def test_unprojection_matches_reference(pose_fixture):
    args = (pose_fixture["unproject_depth"], pose_fixture["unproject_extrinsics"], pose_fixture["unproject_intrinsics"])
    points = unproject_depth_map_to_point_map(*args)
    assert points.dtype == np.float64 and points.shape == (2, 10, 16, 3)
    np.testing.assert_allclose(points, pose_fixture["unproject_world_points"].numpy(), atol=1e-5, rtol=0)
    # Same result from numpy inputs and from (S, H, W) depth.
    numpy_points = unproject_depth_map_to_point_map(args[0][..., 0].numpy(), args[1].numpy(), args[2].numpy())
    np.testing.assert_array_equal(numpy_points, points)


@pytest.fixture(scope="module")
def preprocess_fixture(fixtures_dir):
    folder = fixtures_dir / "vggt_preprocess"
    calls = json.loads((folder / "preprocess.json").read_text())
    outputs = load(lzma.decompress((folder / "outputs.safetensors.xz").read_bytes()))  # the reference's file, xz
    images = {p.name: np.asarray(Image.open(p)) for p in folder.glob("*.png")}
    return calls, outputs, images


@pytest.mark.parametrize(
    "key", ["crop__landscape", "crop__portrait", "crop__landscape_portrait", "pad__landscape_portrait", "crop__rgba", "pad__rgba"]
)
def test_preprocessing_is_exact(preprocess_fixture, key):
    calls, outputs, images = preprocess_fixture
    call = calls[key]
    batch, transforms = preprocess_images([images[name] for name in call["inputs"]], **call["kwargs"])
    expected = outputs[key].to(torch.float32) / 255
    assert batch.dtype == torch.float32 and tuple(batch.shape) == tuple(call["shape"])
    assert torch.equal(batch, expected)
    assert np.array_equal(to_uint8_rgb(batch), outputs[key].permute(0, 2, 3, 1).numpy())
    grid, grid_transforms = preprocess_uint8([images[name] for name in call["inputs"]], **call["kwargs"])
    assert grid.dtype == torch.uint8 and torch.equal(grid, outputs[key])  # white padding 255, crops the same
    assert np.array_equal(channels_last(grid), to_uint8_rgb(batch)) and grid_transforms == transforms
    assert len(transforms) == len(call["inputs"])
    for transform in transforms:
        assert transform.output_hw == tuple(call["shape"][2:])


def test_preprocessing_from_paths_and_rgba(fixtures_dir, preprocess_fixture):
    _, outputs, images = preprocess_fixture
    path = fixtures_dir / "vggt_preprocess/img_rgba_300x200.png"
    assert images["img_rgba_300x200.png"].shape[2] == 4
    batch, _ = preprocess_images([path], mode="pad")
    assert torch.equal(batch, outputs["pad__rgba"].to(torch.float32) / 255)


def test_square_preprocessing_is_exact(preprocess_fixture):
    calls, outputs, images = preprocess_fixture
    call = calls["square518__landscape_portrait"]
    batch, coords = preprocess_images_square([images[n] for n in call["inputs"]], **call["kwargs"])
    assert torch.equal(batch, outputs["square518__landscape_portrait"].to(torch.float32) / 255)
    assert torch.equal(coords, outputs["square518__landscape_portrait__original_coords"])


def test_grid_transform_records_crop_and_pad(preprocess_fixture):
    _, _, images = preprocess_fixture
    landscape, portrait = images["img_landscape_640x480.png"], images["img_portrait_480x640.png"]
    # crop, mixed shapes: the landscape image (518x392) is padded with 63 rows on top; the portrait
    # one (518x686) is cropped by 84 rows.
    _, (t_land, t_port) = preprocess_images([landscape, portrait], mode="crop")
    assert (t_land.offset_x, t_land.offset_y, t_land.valid_box) == (0.0, 63.0, (0, 63, 518, 455))
    assert (t_port.offset_y, t_port.valid_box) == (-84.0, (0, 0, 518, 518))
    assert t_land.scale_x == pytest.approx(518 / 640) and t_land.scale_y == pytest.approx(392 / 480)
    corners = np.array([[0.0, 0.0], [640.0, 480.0]])
    np.testing.assert_allclose(t_land.input_to_output(corners), [[0, 63], [518, 455]])
    np.testing.assert_allclose(t_land.output_to_input(t_land.input_to_output(corners)), corners)
    assert t_land.valid_mask().sum() == 518 * 392
    # pad: the portrait image is centred horizontally.
    _, (_, t_pad) = preprocess_images([landscape, portrait], mode="pad")
    assert (t_pad.offset_x, t_pad.offset_y, t_pad.valid_box) == (63.0, 0.0, (63, 0, 455, 518))


def test_preprocessing_rejects_bad_input():
    with pytest.raises(ValueError):
        preprocess_images([np.zeros((10, 10, 3), dtype=np.float32)])
    with pytest.raises(ValueError):
        preprocess_images([np.zeros((10, 10, 3), dtype=np.uint8)], mode="stretch")
    with pytest.raises(ValueError):
        preprocess_images([])
