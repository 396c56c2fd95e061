"""Our π³ / Pi3X against the authors' code: checkpoint layout, outputs, preprocessing, weight files.

The fixtures (``tests/fixtures/pi3_tiny``, ``pi3x_tiny``, ``pi3_manifest.json``; made by
``tests/fixtures/make_pi3_fixtures.py`` with the authors' code, see ``tests/fixtures/README.md``)
hold tiny random-weight models, their inputs and every output of the authors' forward, float32 on
a CPU, and the key -> shape manifest of the full-size models.

Attention kernels: with the reference kernel (the authors' choice of backends) every output equals
theirs within float32 reordering (``reference_outputs``; the fixtures were made on another CPU). The
memory-efficient kernel (flash attention) changes the order of the softmax sums only; its outputs must
stay within ``EFFICIENT_ATOL`` + ``EFFICIENT_RTOL`` * |reference| of the reference kernel's, run here.
Measured on these fixtures (every output of every case, magnitudes ~1): max |difference| 1.7e-6 (π³)
and 9.5e-7 (Pi3X), median 6e-8; relative to max(|reference|, 1e-2 rms) max 7.5e-5, median 4e-7. At
full size (``benchmarks/results/pi3.md``, 2 frames at 574x434, random weights): max |difference|
1.5e-5 on π³ points of magnitude up to 9.7, median 3e-7; relative max 3.9e-4 (elements near zero),
median 1.1e-6 or less. Two computations made here with the same kernel (a kernel switched on a built
model, condition branches left out, weights saved and loaded) are compared bit for bit.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from reference_outputs import assert_matches_reference

from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.models.checkpoint import WeightsFileError, describe_checkpoint
from sl4slam.models.pi3 import (
    PARAMETERS,
    PI3_WEIGHTS,
    PI3X_WEIGHTS,
    WEIGHTS_LICENSE,
    Pi3Config,
    build_pi3,
    infer_config,
    load_pi3,
    parameter_count,
    preprocess_images,
    resize_lanczos,
    save_checkpoint,
    target_size,
)
from sl4slam.models.pi3.attention import KERNELS, attend, chunked_attention
from sl4slam.models.pi3.weights import convert_checkpoint, load_state_dict_into

EFFICIENT_ATOL = 1e-5
EFFICIENT_RTOL = 1e-4
FORWARD_ARGUMENT = {"imgs": "images", "mask_add_depth": "depth_mask", "mask_add_ray": "ray_mask",
                    "mask_add_pose": "pose_mask"}  # the authors' keyword -> ours


def _fixture(fixtures_dir, name):
    folder = fixtures_dir / name
    config = Pi3Config.from_dict(json.loads((folder / "config.json").read_text()))
    state_dict = load_file(str(folder / "state_dict.safetensors"))
    inputs = load_file(str(folder / "inputs.safetensors"))
    outputs = load_file(str(folder / "outputs.safetensors"))
    if name == "pi3_tiny":
        cases = {"plain": {"images": inputs["plain.imgs"]}}
    else:
        with safe_open(str(folder / "inputs.safetensors"), "pt") as handle:
            names = json.loads(handle.metadata()["cases"])
        cases = {case: {FORWARD_ARGUMENT.get(n, n): inputs[n] for n in used} for case, used in names.items()}
    expected = {case: {k.split(".", 1)[1]: v for k, v in outputs.items() if k.split(".", 1)[0] == case} for case in cases}
    return config, state_dict, cases, expected


@pytest.fixture(scope="module", params=["pi3_tiny", "pi3x_tiny"])
def tiny(request, fixtures_dir):
    return (request.param, *_fixture(fixtures_dir, request.param))


def _model(config, state_dict, kernel, head_chunk=64):
    model = build_pi3(config, kernel=kernel).eval()
    load_state_dict_into(model, state_dict)
    model.head_chunk_frames = head_chunk
    return model


def _run(model, kwargs):
    """Every output of ``model(**kwargs)``, plus the decoder's output (``"decoded"``)."""
    captured = {}
    handle = model.point_decoder.register_forward_pre_hook(lambda module, args: captured.update(decoded=args[0].clone()))
    try:
        with torch.no_grad():
            outputs = model(**kwargs)
    finally:
        handle.remove()
    return {**outputs, "decoded": captured["decoded"]}


_RUNS: dict = {}


def _runs(tiny, kernel):
    """Outputs of every case of a fixture with ``kernel`` (one model per kernel, computed once)."""
    name, config, state_dict, cases, _ = tiny
    if (name, kernel) not in _RUNS:
        model = _model(config, state_dict, kernel)
        _RUNS[name, kernel] = {case: _run(model, kwargs) for case, kwargs in cases.items()}
    return _RUNS[name, kernel]


# ---- layout ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", ["pi3", "pi3x"])
def test_full_size_layout_equals_the_authors_manifest(fixtures_dir, variant):
    manifest = json.loads((fixtures_dir / "pi3_manifest.json").read_text())[variant]
    assert len(manifest) == {"pi3": 1210, "pi3x": 1873}[variant]
    model = build_pi3(Pi3Config(variant=variant), device="meta")
    assert {k: list(v.shape) for k, v in model.state_dict().items()} == manifest
    assert all(p.is_meta for p in model.parameters())  # nothing was allocated
    assert parameter_count(Pi3Config(variant=variant)) == PARAMETERS[variant]
    assert infer_config(manifest) == Pi3Config(variant=variant)  # sizes from the shapes alone
    assert describe_checkpoint(manifest) == {"pi3": "a π³ (Pi3) checkpoint", "pi3x": "a Pi3X checkpoint"}[variant]


def test_weights_sources_and_licence():
    assert (PI3_WEIGHTS.repo_id, PI3_WEIGHTS.filename) == ("yyfz233/Pi3", "model.safetensors")
    assert (PI3X_WEIGHTS.repo_id, PI3X_WEIGHTS.filename) == ("yyfz233/Pi3X", "model.safetensors")
    assert WEIGHTS_LICENSE.startswith("CC BY-NC 4.0")
    assert PARAMETERS == {"pi3": 958_696_732, "pi3x": 1_360_032_433}


def test_tiny_config_inferred_from_shapes_but_head_counts(tiny):
    _, config, state_dict, _, _ = tiny
    inferred = infer_config(state_dict)
    # Heads without qk-norm are invisible in the shapes (64 channels per head assumed); the rest is exact.
    for field in ("encoder_heads", "head_decoder_heads", "metric_heads"):
        setattr(inferred, field, getattr(config, field))
    assert inferred == config


def test_strict_loading(tiny):
    _, config, state_dict, _, _ = tiny
    model = build_pi3(config, device="meta")
    load_state_dict_into(model, state_dict, assign=True)
    with pytest.raises(UserError, match="1 missing keys"):
        load_state_dict_into(build_pi3(config, device="meta"), {k: v for k, v in state_dict.items() if k != "register_token"})
    with pytest.raises(UserError, match="1 unexpected keys"):
        load_state_dict_into(build_pi3(config, device="meta"), {**state_dict, "extra.weight": torch.zeros(1)})
    wrong = dict(state_dict, register_token=torch.zeros(1, 1, 5, 3))
    with pytest.raises(UserError, match="shapes do not match"):
        load_state_dict_into(build_pi3(config, device="meta"), wrong, assign=True)


# ---- parity ---------------------------------------------------------------------------------------

def test_reference_kernel_matches_the_authors(tiny):
    expected = tiny[4]
    for case, outputs in _runs(tiny, "reference").items():
        reference = expected[case]
        assert set(outputs) - {"decoded"} == set(reference) - {"decoded"}, case
        for key, value in reference.items():  # "decoded" (the decoder's output) only in pi3_tiny
            assert_matches_reference(outputs[key], value, f"{tiny[0]} {case} {key}")


def test_efficient_kernel_within_tolerance(tiny):
    differences = []
    reference_kernel = _runs(tiny, "reference")
    for case, outputs in _runs(tiny, "efficient").items():
        for key, reference in reference_kernel[case].items():
            value = outputs[key]
            torch.testing.assert_close(value, reference, atol=EFFICIENT_ATOL, rtol=EFFICIENT_RTOL, msg=f"{case} {key}")
            differences.append((value - reference).abs().flatten())
    differences = torch.cat(differences)
    assert differences.max() < 5e-6 and differences.median() < 1e-6  # the figures in the module docstring


def test_head_chunking_does_not_change_outputs(fixtures_dir):
    config, state_dict, cases, _ = _fixture(fixtures_dir, "pi3x_tiny")
    outputs = _run(_model(config, state_dict, "reference", head_chunk=1), cases["intrinsics"])
    whole = _run(_model(config, state_dict, "reference"), cases["intrinsics"])
    for key, value in whole.items():
        torch.testing.assert_close(outputs[key], value, atol=1e-6, rtol=0)


def test_attention_kernels_agree():
    generator = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn((2, 3, 70, 16), generator=generator) for _ in range(3))
    mask = torch.rand((2, 1, 70, 70), generator=generator) > 0.3
    for m in (None, mask):
        reference = attend(q, k, v, "reference", m)
        torch.testing.assert_close(attend(q, k, v, "efficient", m), reference, atol=1e-6, rtol=1e-5)
        # the fallback of the efficient kernel: the exact kernel on blocks of queries
        torch.testing.assert_close(chunked_attention(q, k, v, m, chunk_bytes=2 * 3 * 70 * 4 * 9), reference,
                                   atol=1e-6, rtol=1e-5)
    assert KERNELS == ("reference", "efficient")
    with pytest.raises(ValueError, match="unknown attention kernel"):
        attend(q, k, v, "fast")


def test_kernel_is_a_setting_of_the_model(fixtures_dir):
    config, state_dict, cases, _ = _fixture(fixtures_dir, "pi3_tiny")
    expected = {"plain": _run(_model(config, state_dict, "reference"), cases["plain"])}  # made here: bit for bit
    model = build_pi3(config, kernel="efficient").eval()
    load_state_dict_into(model, state_dict)
    model.set_attention_kernel("reference")
    assert model.attention_kernel == "reference"
    assert {m.kernel for m in model.modules() if hasattr(m, "kernel") and m is not model} == {"reference"}
    with torch.no_grad():
        assert torch.equal(model(**cases["plain"])["local_points"], expected["plain"]["local_points"])


def test_condition_branches_can_be_left_out(fixtures_dir):
    config, state_dict, cases, _ = _fixture(fixtures_dir, "pi3x_tiny")
    expected = {"intrinsics": _run(_model(config, state_dict, "reference"), cases["intrinsics"])}  # all branches
    model = build_pi3(config, kernel="reference").eval()
    load_state_dict_into(model, state_dict)
    model.drop_condition_branches(keep=("intrinsics",))
    assert not hasattr(model, "depth_encoder") and not hasattr(model, "pose_inject_blk")
    with torch.no_grad():
        outputs = model(**cases["intrinsics"])
        assert torch.equal(outputs["local_points"], expected["intrinsics"]["local_points"])
        with pytest.raises(ValueError, match="depth_encoder"):
            model(**cases["masked"])


# ---- preprocessing --------------------------------------------------------------------------------

def test_preprocessing_equals_the_authors_loader(fixtures_dir):
    folder = fixtures_dir / "pi3_tiny"
    meta = json.loads((folder / "preprocess.json").read_text())
    tensors = load_file(str(folder / "preprocess.safetensors"))
    for name, sizes in meta["folders"].items():
        images = [tensors[f"{name}.input_{i}"].numpy() for i in range(len(sizes))]
        as_float, as_uint8, transforms = preprocess_images(images, budget=meta["budget"])
        expected = tensors[f"{name}.output_uint8"]
        assert np.array_equal(as_uint8, expected.numpy()), name
        assert torch.equal(as_float, expected.permute(0, 3, 1, 2).float().div(255)), name
        assert all(t.output_hw == tuple(expected.shape[1:3]) for t in transforms)
    for entry in meta["default_budget_sizes"]:
        height, width = entry["input_hw"]
        assert target_size(width, height)[::-1] == tuple(entry["output_hw"]), entry


@pytest.mark.parametrize("size, new_size", [((480, 640), (434, 588)), ((480, 640), (700, 900)), ((100, 37), (30, 200)),
                                            ((1000, 300), (200, 280)), ((64, 2000), (64, 90))])
def test_lanczos_resize_equals_pillow_13(size, new_size):
    """Our fixed-point Lanczos against the installed Pillow, bit for bit, where its pass order is
    Pillow 13's (shrinks and enlargements, tall and wide, a 22x shrink)."""
    import PIL
    from PIL import Image

    if int(PIL.__version__.split(".")[0]) < 13:
        pytest.skip(f"Pillow {PIL.__version__} runs the legacy pass order")
    image = np.random.default_rng(sum(size)).integers(0, 256, (*size, 3), dtype=np.uint8)
    (height, width) = new_size
    expected = np.asarray(Image.fromarray(image).resize((width, height), Image.LANCZOS))
    assert np.array_equal(resize_lanczos(image, width, height), expected)
    assert np.array_equal(resize_lanczos(image, width, height), expected)  # again, from the cached weights


def test_preprocessing_grid_mapping():
    image = np.zeros((30, 40, 3), np.uint8)
    _, _, (transform,) = preprocess_images([image], budget=28 * 42)
    assert transform.output_hw == (28, 42)
    corners = np.array([[-0.5, -0.5], [39.5, 29.5]])  # the image's outer corners
    np.testing.assert_allclose(transform.input_to_output(corners), [[-0.5, -0.5], [41.5, 27.5]])
    np.testing.assert_allclose(transform.output_to_input(transform.input_to_output(corners)), corners)


# ---- weight files ---------------------------------------------------------------------------------

def test_load_pi3_from_files(tmp_path, fixtures_dir):
    config, state_dict, cases, _ = _fixture(fixtures_dir, "pi3_tiny")
    expected = {"plain": _run(_model(config, state_dict, "reference"), cases["plain"])}  # from memory, made here
    for suffix in (".safetensors", ".pt"):
        path = save_checkpoint(state_dict, tmp_path / f"tiny{suffix}", config)
        model = load_pi3(str(path), "pi3", kernel="reference")
        assert all(not p.requires_grad for p in model.parameters())
        with torch.no_grad():
            assert torch.equal(model(**cases["plain"])["camera_poses"], expected["plain"]["camera_poses"])
    converted = convert_checkpoint(str(tmp_path / "tiny.pt"), tmp_path / "bf16.safetensors", "pi3", "bf16")
    assert load_pi3(str(converted), "pi3", dtype=None).register_token.dtype == torch.bfloat16


def test_another_models_checkpoint_is_named(tmp_path, fixtures_dir):
    vggt = load_file(str(fixtures_dir / "vggt_tiny_b" / "state_dict.safetensors"))
    save_file(vggt, str(tmp_path / "vggt.safetensors"))
    with pytest.raises(UserError, match="holds a VGGT checkpoint, not Pi3 weights") as err:
        load_pi3(str(tmp_path / "vggt.safetensors"), "pi3")
    assert "\n" not in str(err.value)
    pi3x = load_file(str(fixtures_dir / "pi3x_tiny" / "state_dict.safetensors"))
    save_file(pi3x, str(tmp_path / "pi3x.safetensors"))
    with pytest.raises(UserError, match="holds a Pi3X checkpoint, not Pi3 weights; use the pi3x variant") as err:
        load_pi3(str(tmp_path / "pi3x.safetensors"), "pi3")
    assert "\n" not in str(err.value)


def test_missing_and_broken_weights(tmp_path, monkeypatch, fixtures_dir):
    with pytest.raises(MissingWeightsError, match="not found"):
        load_pi3(str(tmp_path / "absent.safetensors"), "pi3x")
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes((fixtures_dir / "pi3_tiny" / "state_dict.safetensors").read_bytes()[:5000])
    with pytest.raises(WeightsFileError, match="cut short"):
        load_pi3(str(cut), "pi3")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    for variant, repo in (("pi3", "yyfz233/Pi3"), ("pi3x", "yyfz233/Pi3X")):
        with pytest.raises(MissingWeightsError, match=f"{repo}/model.safetensors") as err:
            load_pi3(None, variant, cache_dir=tmp_path / "hf")
        assert "\n" not in str(err.value)
    with pytest.raises(UserError, match="unknown π³ variant"):
        load_pi3(None, "pi4")
