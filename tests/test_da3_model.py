"""Our Depth Anything 3 against the authors' code: checkpoint layouts, outputs, preprocessing, files.

The fixtures (``tests/fixtures/README.md``, made by ``tests/fixtures/make_da3_fixtures.py``) hold the
authors' outputs, computed at one thread in float32 on the CPU of another machine. Outputs are compared
with them within float32 reordering (``reference_outputs``: other CPUs accumulate in another order);
two computations made here are compared bit for bit.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file
from reference_outputs import FIT_ULPS, assert_matches_reference
from torch_threads import one_thread

from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.models.checkpoint import describe_checkpoint
from sl4slam.models.da3 import (
    LICENCES,
    RELEASED,
    SIZES,
    WEIGHTS_SOURCES,
    DA3Config,
    DepthAnything3,
    build_da3,
    count_parameters,
    infer_config,
    init_random_weights,
    load_da3,
    load_state_dict_into,
    parameter_counts,
    preprocess_images,
    read_checkpoint,
    save_checkpoint,
)
from sl4slam.models.da3.camera import normalize_extrinsics
from sl4slam.models.da3.config import ARCHITECTURES, GS_HEAD_PREFIXES
from sl4slam.models.da3.preprocess import METHODS

ARCHITECTURE_NAMES = ("small", "base", "large", "giant")
RAY_SEED = 5


# ------------------------------------------------------------------------------------------ helpers


def manifest(name: str, fixtures_dir) -> dict:
    return json.loads((fixtures_dir / f"da3_manifest_{name}.json").read_text())


def meta_state_dict(entry: dict) -> dict[str, torch.Tensor]:
    return {k: torch.empty(shape, device="meta") for k, shape in entry["keys"].items()}


# ------------------------------------------------------------------------------- released layouts
@pytest.mark.parametrize("name", ARCHITECTURE_NAMES)
def test_layout_equals_the_released_checkpoint(name, fixtures_dir):
    entry = manifest(name, fixtures_dir)
    model = build_da3(ARCHITECTURES[name], device="meta")
    ours = {k: list(v.shape) for k, v in model.state_dict().items()}
    stored = {k.removeprefix("model."): v for k, v in entry["keys"].items()}
    skipped = {k for k in stored if k.startswith(GS_HEAD_PREFIXES)}
    assert bool(skipped) == (name == "giant")  # only the Giant has the Gaussian-splatting head
    tied = {k for k in ours if re.fullmatch(r"head\.scratch\.output_conv2_aux\.[123]\.2\.(weight|bias)", k)}
    assert len(tied) == 6  # the ray head's one LayerNorm in levels 1-3: stored once, as level 0's
    assert {k: v for k, v in stored.items() if k not in skipped} == {k: v for k, v in ours.items() if k not in tied}
    gs_parameters = sum(int(np.prod(stored[k])) for k in skipped)
    assert count_parameters(ARCHITECTURES[name]) == entry["num_parameters"] - gs_parameters
    assert all(p.is_meta for p in model.parameters())


@pytest.mark.parametrize("name", ARCHITECTURE_NAMES)
def test_config_inferred_from_shapes_and_from_config_json(name, fixtures_dir):
    entry = manifest(name, fixtures_dir)
    state_dict = {k.removeprefix("model."): v for k, v in meta_state_dict(entry).items()}
    assert infer_config(state_dict) == ARCHITECTURES[name]  # shapes + the released table
    assert infer_config(state_dict, {"config": entry["config"]}) == ARCHITECTURES[name]  # shapes + config.json
    altered = json.loads(json.dumps(entry["config"]))
    altered["net"]["out_layers"] = [0, 1, 2, 3]
    assert infer_config(state_dict, {"config": altered}).out_layers == [0, 1, 2, 3]  # config.json wins
    model = build_da3(infer_config(state_dict), device="meta")
    load_state_dict_into(model, state_dict, assign=True)  # strict, gs_head skipped, tied aliases filled


def test_released_sizes_hub_ids_licences_and_parameter_counts():
    assert SIZES == ("small", "base", "large", "large-1.1", "giant", "giant-1.1")
    assert {s: WEIGHTS_SOURCES[s].repo_id for s in SIZES} == {
        "small": "depth-anything/DA3-SMALL", "base": "depth-anything/DA3-BASE", "large": "depth-anything/DA3-LARGE",
        "large-1.1": "depth-anything/DA3-LARGE-1.1", "giant": "depth-anything/DA3-GIANT",
        "giant-1.1": "depth-anything/DA3-GIANT-1.1"}
    assert all(WEIGHTS_SOURCES[s].filename == "model.safetensors" for s in SIZES)
    assert LICENCES == {"small": "Apache-2.0", "base": "Apache-2.0", "large": "CC-BY-NC-4.0",
                        "large-1.1": "CC-BY-NC-4.0", "giant": "CC-BY-NC-4.0", "giant-1.1": "CC-BY-NC-4.0"}
    counts = parameter_counts()
    assert counts["small"] == 34_299_463 and counts["base"] == 135_366_599
    assert counts["large"] == counts["large-1.1"] == 410_941_767
    assert counts["giant"] == counts["giant-1.1"] == 1_320_045_639  # without the 35.6 M Gaussian head
    assert RELEASED["giant-1.1"].name == "da3-giant-1.1"


@pytest.mark.parametrize("name", ARCHITECTURE_NAMES)
def test_a_checkpoint_says_which_size_it_is(name, fixtures_dir):
    entry = manifest(name, fixtures_dir)
    description = describe_checkpoint(meta_state_dict(entry))
    assert f"Depth Anything 3 {name.capitalize()}" in description and f"DA3-{name.upper()}" in description


# ------------------------------------------------------------------------------- tiny-model parity
def tiny(folder):
    meta = json.loads((folder / "config.json").read_text())
    state_dict, embedded = read_checkpoint(folder / "state_dict.safetensors")
    assert embedded is None
    model = DepthAnything3(DA3Config(**meta["config"])).eval()
    load_state_dict_into(model, state_dict)  # strict; the file stores the tied LayerNorm once
    return model, meta, load_file(str(folder / "inputs.safetensors")), load_file(str(folder / "outputs.safetensors"))


@pytest.fixture(scope="module", params=["da3_tiny", "da3_tiny_swiglu"])
def tiny_case(request, fixtures_dir):
    return tiny(fixtures_dir / request.param)


def test_tied_layer_norm_stays_one_parameter(tiny_case):
    model = tiny_case[0]
    norms = {id(level[2].weight) for level in model.head.scratch.output_conv2_aux}
    assert len(norms) == 1


@pytest.mark.parametrize("known", [False, True], ids=["no-cameras", "camera-encoder"])
def test_outputs_equal_the_reference(tiny_case, known):
    model, meta, inputs, outputs = tiny_case
    prefix = "cond_" if known else ""
    cameras = {}
    if known:
        normalised = normalize_extrinsics(inputs["extrinsics"])
        assert_matches_reference(normalised, outputs["normalised_extrinsics"], "normalised extrinsics")
        cameras = dict(extrinsics=normalised, intrinsics=inputs["intrinsics"])
    with one_thread(), torch.inference_mode():
        head = model(inputs["images"], **cameras)
        rays = model(inputs["images"], **cameras, cameras="rays", keep_rays=True,
                     generator=torch.Generator().manual_seed(RAY_SEED))
    for key in ("depth", "depth_conf", "extrinsics", "intrinsics"):
        assert_matches_reference(head[key], outputs[f"{prefix}head.{key}"], f"{prefix}head {key}")
    for key in ("ray", "ray_conf"):
        assert_matches_reference(rays[key], outputs[f"{prefix}rays.{key}"], f"{prefix}rays {key}")
    for key in ("extrinsics", "intrinsics"):  # fitted to the rays: RANSAC with the same draws
        assert_matches_reference(rays[key], outputs[f"{prefix}rays.{key}"], f"{prefix}ray-fit {key}", FIT_ULPS)
    assert torch.equal(head["depth"], rays["depth"])
    expected_view = 0 if known else meta["reference_view"]
    assert int(head["reference_view"][0]) == expected_view
    assert meta["reference_view"] != 0  # the fixture moves the reference view, so reordering is covered


def test_reference_view_strategies_and_single_frames(tiny_case):
    model, _, inputs, _ = tiny_case
    images = inputs["images"]
    with torch.inference_mode():
        first = model(images, reference_strategy="first")
        pair = model(images[:, :2])
    assert int(first["reference_view"][0]) == 0 and int(pair["reference_view"][0]) == 0
    with pytest.raises(ValueError, match="unknown reference-view strategy"):
        model(images, reference_strategy="best")


def test_head_chunking_does_not_change_depth(fixtures_dir):
    model, _, inputs, _ = tiny(fixtures_dir / "da3_tiny_swiglu")  # 9 frames: the default chunk of 8 splits them
    with one_thread(), torch.inference_mode():
        chunked = model(inputs["images"], cameras="none")
        model.set_head_chunk_frames(16)
        whole = model(inputs["images"], cameras="none")
    torch.testing.assert_close(whole["depth"], chunked["depth"], rtol=1e-5, atol=1e-6)
    assert "extrinsics" not in whole


# ---------------------------------------------------------------------------------- preprocessing
def test_preprocessing_equals_the_reference(fixtures_dir):
    folder = fixtures_dir / "da3_preprocess"
    meta = json.loads((folder / "config.json").read_text())
    reference = load_file(str(folder / "preprocess.safetensors"))
    images = [reference[f"image{i}"].numpy() for i in range(len(meta["sizes_hw"]))]
    res = meta["process_res"]
    for method in METHODS:
        for index, image in enumerate(images):
            batch = preprocess_images([image], res, method)
            assert torch.equal(batch.images, reference[f"{method}.{index}.images"]), (method, index)
            assert batch.colors.shape[1:3] == batch.images.shape[-2:]
            check_intrinsics(batch.transforms[0], meta["intrinsics"][index], reference[f"{method}.{index}.intrinsics"][0])
    mixed = preprocess_images(images[:2], res)
    assert torch.equal(mixed.images, reference["mixed.images"])
    for index in range(2):
        check_intrinsics(mixed.transforms[index], meta["intrinsics"][index], reference["mixed.intrinsics"][index])


def check_intrinsics(transform, K, theirs):
    """Focal lengths as the reference's; principal point on the grid in this project's pixel-centre
    convention, which the reference's (scaling ``c`` alone) misses by ``0.5 (1 - s)`` (plus the crop
    offset it rounds the other way for mixed batches)."""
    from sl4slam.models.da3 import intrinsics_on_grid

    ours = intrinsics_on_grid(np.asarray(K), transform)
    theirs = theirs.double().numpy()
    np.testing.assert_allclose(ours[[0, 1], [0, 1]], theirs[[0, 1], [0, 1]], rtol=1e-6)
    scales = np.array([transform.scale_x, transform.scale_y])
    centre_shift = ours[[0, 1], [2, 2]] - theirs[[0, 1], [2, 2]]
    assert np.all(np.abs(centre_shift - 0.5 * (scales - 1)) <= 1.0 + 1e-4)
    point = np.array([[3.0, 4.0]])  # the grid mapping of a pixel centre matches K_grid
    projected = ours @ np.linalg.solve(np.asarray(K), np.array([3.0, 4.0, 1.0]))
    expected = transform.input_to_output(point + 0.5)[0] - 0.5
    np.testing.assert_allclose(projected[:2] / projected[2], expected, atol=1e-9)


def test_preprocessing_refuses_what_it_cannot_read():
    with pytest.raises(ValueError, match="uint8 RGB"):
        preprocess_images([np.zeros((10, 10), np.float32)])
    with pytest.raises(ValueError, match="process_res_method"):
        preprocess_images([np.zeros((10, 10, 3), np.uint8)], method="square")


# ----------------------------------------------------------------------------------- weight files
def test_save_and_load_with_embedded_config(tmp_path, fixtures_dir):
    model, meta, inputs, outputs = tiny(fixtures_dir / "da3_tiny")
    path = save_checkpoint(model.state_dict(), tmp_path / "tiny.safetensors", model.config)
    loaded = load_da3(str(path), size="small", device="cpu")  # the embedded config, not the Small's
    assert loaded.config == model.config and loaded.autocast_dtype is None
    assert not any(p.requires_grad for p in loaded.parameters())
    with one_thread(), torch.inference_mode():
        depth = loaded(inputs["images"])["depth"]
    assert_matches_reference(depth, outputs["head.depth"], "depth after save/load")


def test_convert_embeds_the_config(tmp_path, fixtures_dir):
    from sl4slam.models.da3 import convert_checkpoint

    model = tiny(fixtures_dir / "da3_tiny")[0]
    source = save_checkpoint(model.state_dict(), tmp_path / "tiny.safetensors", model.config)
    half = convert_checkpoint(str(source), tmp_path / "half.safetensors", dtype="bf16")
    state_dict, embedded = read_checkpoint(half)
    assert embedded == model.config and state_dict["head.norm.weight"].dtype == torch.bfloat16
    assert load_da3(str(half)).head.norm.weight.dtype == torch.float32
    with pytest.raises(UserError, match="must end in .safetensors"):
        convert_checkpoint(str(source), tmp_path / "out.pt")


def test_released_file_layout_is_read(tmp_path, fixtures_dir):
    """The fixture file has the hub layout (``model.`` prefix, tied LayerNorm once); with the Small's
    shapes from the manifest, a file holding another size is refused in one line."""
    state_dict = load_file(str(fixtures_dir / "da3_tiny" / "state_dict.safetensors"))
    assert all(k.startswith("model.") for k in state_dict)
    assert "model.head.scratch.output_conv2_aux.1.2.weight" not in state_dict
    entry = manifest("base", fixtures_dir)
    fake = {k: torch.zeros(v) for k, v in entry["keys"].items() if "pretrained.blocks" not in k and "head." not in k}
    save_file(fake, str(tmp_path / "base.safetensors"))
    with pytest.raises(UserError, match=r"holds a Depth Anything 3 Base checkpoint \(DA3-BASE\), not DA3-SMALL") as err:
        load_da3(str(tmp_path / "base.safetensors"), size="small")
    assert "\n" not in str(err.value) and "choose size base" in str(err.value)


def test_another_models_checkpoint_is_named(tmp_path, fixtures_dir):
    vggt = load_file(str(fixtures_dir / "vggt_tiny_b" / "state_dict.safetensors"))
    save_file(vggt, str(tmp_path / "vggt.safetensors"))
    with pytest.raises(UserError, match="holds a VGGT checkpoint, not DA3-SMALL weights") as err:
        load_da3(str(tmp_path / "vggt.safetensors"), size="small")
    assert "\n" not in str(err.value)


def test_missing_weights_offline(tmp_path, monkeypatch):
    with pytest.raises(MissingWeightsError, match="not found"):
        load_da3(str(tmp_path / "absent.safetensors"), size="base")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    with pytest.raises(MissingWeightsError, match="depth-anything/DA3-LARGE-1.1/model.safetensors") as err:
        load_da3(size="large-1.1", cache_dir=tmp_path / "hf")
    assert "\n" not in str(err.value)


def test_unknown_size_and_precision():
    with pytest.raises(ValueError, match="unknown Depth Anything 3 size"):
        load_da3(size="huge")
    from sl4slam.models.da3.weights import resolve_precision

    assert resolve_precision("fp32") is None and resolve_precision("bf16") == torch.bfloat16
    with pytest.raises(UserError, match="unknown Depth Anything 3 dtype"):
        resolve_precision("int4")


def test_random_weights_run_end_to_end():
    config = DA3Config(embed_dim=24, depth=4, num_heads=2, img_size=56, alt_start=2, qknorm_start=2, rope_start=2,
                       out_layers=[0, 1, 2, 3], head_features=8, head_out_channels=[8, 8, 8, 8], cam_enc_depth=1,
                       cam_enc_heads=2)
    model = init_random_weights(DepthAnything3(config)).eval()
    with torch.inference_mode():
        out = model(torch.randn(3, 3, 28, 42))
    assert out["depth"].shape == (1, 3, 28, 42) and out["extrinsics"].shape == (1, 3, 3, 4)
    assert bool((out["depth_conf"] >= 1).all())


def test_memory_plan_shrinks_the_head_chunk_to_fit():
    from sl4slam.models.da3.memory import (
        GIB,
        estimate_peak_bytes,
        largest_fitting_frames,
        plan_memory,
    )

    small = ARCHITECTURES["small"]
    peaks = {chunk: estimate_peak_bytes(small, 17, 378, 504, chunk) for chunk in range(1, 9)}
    assert peaks[1] < peaks[8] and all(peaks[c] <= peaks[c + 1] for c in range(1, 8))
    assert plan_memory(small, 100.0, 17, 378, 504).head_chunk_frames == 8
    budget = peaks[5] + 1
    assert plan_memory(small, budget / GIB, 17, 378, 504).head_chunk_frames == max(c for c in peaks if peaks[c] < budget)
    largest = largest_fitting_frames(small, int(1.0 * GIB), 378, 504)
    assert 0 < largest < 17
    with pytest.raises(UserError, match=f"the largest submap that fits is {largest} frames"):
        plan_memory(small, 1.0, 17, 378, 504)
