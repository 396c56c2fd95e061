"""Our VGGT against the reference: checkpoint layout, outputs and intermediates, weight files.

Outputs and intermediates are compared with the stored reference within float32 reordering
(``reference_outputs``: the fixtures were made on another machine); two computations made here are
compared bit for bit."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle

import pytest
import torch
from safetensors.torch import load_file

from reference_outputs import assert_matches_reference

from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.models.vggt.model import SKIPPED_PREFIXES, VGGT, VGGTModelConfig, build_vggt
from sl4slam.models.vggt.rope import RotaryPositionEmbedding2D, patch_positions
from sl4slam.models.vggt.weights import (
    convert_checkpoint,
    infer_config,
    load_state_dict_into,
    load_vggt,
    read_checkpoint,
    save_checkpoint,
)

OUTPUTS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")
TRACK_HEAD_PARAMETERS = 65_941_396


@pytest.fixture(scope="module")
def manifest(fixtures_dir):
    """Key -> shape of every entry of the reference checkpoint layout (vendored, compact)."""
    return json.loads((fixtures_dir / "vggt_manifest_full.json").read_text())


def test_full_model_layout_matches_checkpoint_manifest(manifest):
    model = build_vggt(device="meta")
    ours = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    reference = {name: tuple(shape) for name, shape in manifest["shapes"].items()}
    assert len(reference) == manifest["num_state_dict_keys"] == 1797
    skipped = {k for k in reference if k.startswith(SKIPPED_PREFIXES)}
    assert len(skipped) == 394  # every track_head key, and only those, is left out
    assert ours == {k: v for k, v in reference.items() if k not in skipped}
    assert all(v.dtype == torch.float32 for v in model.state_dict().values())
    num_parameters = sum(p.numel() for p in model.parameters())
    assert num_parameters == manifest["num_parameters"] - TRACK_HEAD_PARAMETERS == 1_256_537_516 - 65_941_396
    assert all(p.is_meta for p in model.parameters())  # nothing was allocated


def test_config_inferred_from_manifest_shapes(manifest):
    state_dict = {name: torch.empty(shape, device="meta") for name, shape in manifest["shapes"].items()}
    assert infer_config(state_dict) == VGGTModelConfig()
    model = build_vggt(device="meta")
    load_state_dict_into(model, state_dict, assign=True)  # strict apart from track_head.*


def _tiny(folder):
    config = VGGTModelConfig.from_reference_config(json.loads((folder / "config.json").read_text()))
    state_dict = load_file(str(folder / "state_dict.safetensors"))
    inputs = load_file(str(folder / "inputs.safetensors"))
    outputs = load_file(str(folder / "outputs.safetensors"))
    intermediates = load_file(str(folder / "intermediates.safetensors"))
    return config, state_dict, inputs, outputs, intermediates


def _tiny_a(folder):
    """The vendored cut of the reference case tiny_a (168x518 frames, img_size 518: the position
    embedding is resized to 12x37 patches): its patch embedding and first aggregator layer, as a
    one-layer model without heads; the images regenerated from their seed and checked against the
    reference's SHA-256; the 518x518 "resized" embedding is the stored one (tests/fixtures/README.md)."""
    reference = VGGTModelConfig.from_reference_config(json.loads((folder / "config.json").read_text()))
    config = dataclasses.replace(reference, depth=1, enable_camera=False, enable_depth=False, enable_point=False)
    state_dict = load_file(str(folder / "state_dict.safetensors"))
    recipe = json.loads((folder / "inputs.json").read_text())["images"]
    images = torch.rand(recipe["shape"], generator=torch.Generator().manual_seed(recipe["seed"]))
    assert hashlib.sha256(images.numpy().tobytes()).hexdigest() == recipe["sha256"], "not the reference's images"
    intermediates = load_file(str(folder / "intermediates.safetensors"))
    intermediates["pos_embed_interp_518x518"] = state_dict["aggregator.patch_embed.pos_embed"]
    return config, state_dict, {"images": images}, None, intermediates


@pytest.fixture(scope="module", params=["tiny_a", "tiny_b"])
def tiny_run(request, fixtures_dir):
    """Both cases are vendored with the tests: tiny_b whole, tiny_a cut to its interpolation path."""
    torch.manual_seed(0)
    load = _tiny_a if request.param == "tiny_a" else _tiny
    config, state_dict, inputs, outputs, intermediates = load(fixtures_dir / f"vggt_{request.param}")
    model = VGGT(config).eval()
    load_state_dict_into(model, state_dict)
    captured = {}
    hooks = []
    if model.depth_head is not None:  # tiny_a's cut has no heads
        hooks.append(model.depth_head.scratch.output_conv1.register_forward_hook(
            lambda module, args, out: captured.setdefault("depth_head_output_conv1", []).append(out.detach().clone())
        ))
    with torch.inference_mode():
        predictions = model(inputs["images"], keep_all_layers=True)
        patch_tokens = model.aggregator.embed(inputs["images"])
    for hook in hooks:
        hook.remove()
    return request.param, model, predictions, patch_tokens, captured, outputs, intermediates, inputs


@pytest.mark.parametrize("tiny_run", ["tiny_b"], indirect=True)  # tiny_a's heads are not vendored
def test_tiny_outputs_match_reference(tiny_run):
    _, _, predictions, _, _, outputs, _, _ = tiny_run
    for key in OUTPUTS:
        assert_matches_reference(predictions[key], outputs[key], key)
    pose_list = torch.stack(predictions["pose_enc_list"])
    assert pose_list.shape == outputs["pose_enc_list"].shape  # 4 refinement iterations
    assert_matches_reference(pose_list, outputs["pose_enc_list"], "pose_enc_list")


def test_full_tiny_a_outputs_match_reference(shared_dir):
    """The dense heads on non-square frames (tiny_a's 168x518), whose 13 MB of reference weights and
    outputs are not vendored: it runs where the reference data folder is (a development checkout,
    and CI); the interpolation path of the same case runs everywhere (``tiny_run``)."""
    config, state_dict, inputs, outputs, _ = _tiny(shared_dir / "fixtures/vggt/tiny/tiny_a")
    model = VGGT(config).eval()
    load_state_dict_into(model, state_dict)
    with torch.inference_mode():
        predictions = model(inputs["images"])
    for key in OUTPUTS:
        assert_matches_reference(predictions[key], outputs[key], f"tiny_a {key}")


def test_tiny_intermediates_match_reference(tiny_run):
    name, model, predictions, patch_tokens, captured, _, intermediates, inputs = tiny_run
    batch, frames = inputs["images"].shape[:2]
    assert_matches_reference(patch_tokens.reshape(batch, frames, *patch_tokens.shape[1:]),
                             intermediates["patch_embed_tokens"], f"{name} patch_embed_tokens")
    layer_keys = [k for k in intermediates if k.startswith("aggregated_tokens_")]
    assert len(layer_keys) == (1 if name == "tiny_a" else 4)  # tiny_a: layer 0 of the vendored cut
    for key in layer_keys:
        layer = int(key.rsplit("_", 1)[1])
        assert_matches_reference(predictions["aggregated_tokens"][layer], intermediates[key], f"{name} {key}")
    for key in [k for k in intermediates if k.startswith("pos_embed_interp_")]:
        height, width = (int(v) for v in key.rsplit("_", 1)[1].split("x"))
        dummy = torch.zeros(1, 1 + (height // 14) * (width // 14), model.config.embed_dim)
        resized = model.aggregator.patch_embed.interpolate_pos_encoding(dummy, height, width)
        assert_matches_reference(resized, intermediates[key], f"{name} {key}")
    if "depth_head_output_conv1" in intermediates:
        assert_matches_reference(captured["depth_head_output_conv1"][0], intermediates["depth_head_output_conv1"],
                                 f"{name} depth_head_output_conv1")


def test_dropping_unused_layers_changes_nothing(fixtures_dir):
    config, state_dict, inputs, _, _ = _tiny(fixtures_dir / "vggt_tiny_b")
    model = VGGT(config).eval()
    load_state_dict_into(model, state_dict)
    with torch.inference_mode():
        lean = model(inputs["images"])
        full = model(inputs["images"], keep_all_layers=True)
        depth_only = model(inputs["images"][0], heads=("depth",))
    assert model.needed_layers() == {0, 1, 2, 3}
    for key in ("pose_enc", "depth", "world_points_conf"):
        assert torch.equal(lean[key], full[key])
    assert set(depth_only) == {"depth", "depth_conf"}
    # A 4-D input is one sequence; batch elements do not interact.
    assert depth_only["depth"].shape == (1, 2, 112, 112, 1)
    torch.testing.assert_close(depth_only["depth"][0], full["depth"][0], atol=1e-5, rtol=1e-5)


def test_first_frame_tokens_use_index_zero():
    config = VGGTModelConfig(embed_dim=32, depth=2, num_heads=2, patch_embed_depth=1, patch_embed_num_heads=2,
                             img_size=56, camera_trunk_depth=1, camera_num_heads=2, dpt_features=8,
                             dpt_out_channels=[8, 8, 8, 8], dpt_layers=[0, 1, 1, 1])
    model = VGGT(config)
    token = torch.arange(2 * 3 * 4, dtype=torch.float32).reshape(1, 2, 3, 4)
    expanded = model.aggregator._first_and_rest(token, batch=2, frames=3).reshape(2, 3, 3, 4)
    for b in range(2):
        assert torch.equal(expanded[b, 0], token[0, 0])
        assert torch.equal(expanded[b, 1], token[0, 1]) and torch.equal(expanded[b, 2], token[0, 1])


def test_rope_positions_and_relative_invariance():
    positions = patch_positions(1, 2, 3, num_special=5, device="cpu")
    assert positions.shape == (1, 11, 2)
    assert positions[0, :5].abs().sum() == 0
    assert positions[0, 5:].tolist() == [[1, 1], [1, 2], [1, 3], [2, 1], [2, 2], [2, 3]]
    rope = RotaryPositionEmbedding2D(100.0)
    generator = torch.Generator().manual_seed(0)
    q = torch.randn(1, 1, 1, 16, generator=generator, dtype=torch.float64)
    k = torch.randn(1, 1, 1, 16, generator=generator, dtype=torch.float64)

    def score(pos_q, pos_k):
        rq = rope(q, torch.tensor([[pos_q]]))
        rk = rope(k, torch.tensor([[pos_k]]))
        return (rq * rk).sum().item()

    # Attention scores depend only on the position difference; norms are preserved.
    assert score((3, 5), (1, 2)) == pytest.approx(score((7, 9), (5, 6)), abs=1e-6)  # float32 angles
    assert score((3, 5), (1, 2)) != pytest.approx(score((3, 5), (2, 1)), abs=1e-6)
    assert rope(q, torch.tensor([[(4, 9)]])).norm().item() == pytest.approx(q.norm().item(), abs=1e-12)
    # First half of the channels follows the row, second half the column (rotate-half layout).
    rotated = rope(q, torch.tensor([[(0, 1)]]))
    assert torch.equal(rotated[..., :8], q[..., :8]) and not torch.equal(rotated[..., 8:], q[..., 8:])
    assert rotated[0, 0, 0, 8].item() == pytest.approx(
        (q[0, 0, 0, 8] * torch.cos(torch.tensor(1.0)) - q[0, 0, 0, 12] * torch.sin(torch.tensor(1.0))).item(), abs=1e-7
    )


def test_track_head_keys_only_are_skipped(fixtures_dir):
    config, state_dict, _, _, _ = _tiny(fixtures_dir / "vggt_tiny_b")
    model = VGGT(config)
    load_state_dict_into(model, state_dict)
    broken = dict(state_dict)
    broken.pop("depth_head.scratch.output_conv2.2.weight")
    with pytest.raises(UserError, match="1 missing"):
        load_state_dict_into(VGGT(config), broken)
    extra = dict(state_dict, **{"aggregator.extra": torch.zeros(1)})
    with pytest.raises(UserError, match="1 unexpected"):
        load_state_dict_into(VGGT(config), extra)
    wrong = dict(state_dict, **{"aggregator.camera_token": torch.zeros(1, 2, 1, 8)})
    with pytest.raises(UserError, match="shapes"):
        load_state_dict_into(VGGT(config), wrong)


@pytest.fixture(scope="module")
def tiny_b_checkpoint(fixtures_dir):
    config, state_dict, inputs, outputs, _ = _tiny(fixtures_dir / "vggt_tiny_b")
    return config, state_dict, inputs, outputs


def test_safetensors_and_pt_files_load_strictly(tmp_path, tiny_b_checkpoint):
    config, state_dict, inputs, outputs = tiny_b_checkpoint
    st_path = save_checkpoint(state_dict, tmp_path / "tiny.safetensors", config)
    pt_path = save_checkpoint(state_dict, tmp_path / "tiny.pt", config)
    for path in (st_path, pt_path):
        model = load_vggt(str(path))
        assert model.config == config and not model.training
        assert all(not p.is_meta and not p.requires_grad for p in model.parameters())
        with torch.inference_mode():
            prediction = model(inputs["images"])
        assert_matches_reference(prediction["depth"], outputs["depth"], f"depth from {path.suffix}")
    # A bare state dict without a config: sizes inferred, except the DPT layers of a non-24-layer model.
    torch.save(state_dict, tmp_path / "bare.pt")
    with pytest.raises(UserError, match="cannot tell"):
        load_vggt(str(tmp_path / "bare.pt"))
    model = load_vggt(str(tmp_path / "bare.pt"), config=config)
    assert model.config.dpt_layers == [0, 1, 2, 3]


def test_convert_checkpoint_to_bf16(tmp_path, tiny_b_checkpoint):
    config, state_dict, inputs, outputs = tiny_b_checkpoint
    source = save_checkpoint(state_dict, tmp_path / "tiny.pt", config)
    target = convert_checkpoint(source, tmp_path / "tiny_bf16.safetensors", dtype="bf16")
    converted, embedded = read_checkpoint(target)
    assert VGGTModelConfig.from_dict(embedded) == config
    assert set(converted) == set(state_dict)  # every key kept, track_head included
    assert all(v.dtype == torch.bfloat16 for v in converted.values())
    model = load_vggt(str(target), dtype="fp32")
    assert all(p.dtype == torch.float32 for p in model.parameters())
    with torch.inference_mode():
        prediction = model(inputs["images"])
    torch.testing.assert_close(prediction["depth"], outputs["depth"], atol=0.1, rtol=0.1)
    exact = convert_checkpoint(source, tmp_path / "tiny_fp32.safetensors")
    assert all(torch.equal(v, state_dict[k]) for k, v in read_checkpoint(exact)[0].items())
    with pytest.raises(UserError):
        convert_checkpoint(source, tmp_path / "tiny.pt", dtype="fp32")


class _NotATensor:
    pass


def test_pickled_objects_are_refused(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"model": {"x": torch.zeros(1)}, "payload": _NotATensor()}, path)
    with pytest.raises(UserError, match="pickled objects"):
        read_checkpoint(path)
    assert issubclass(pickle.UnpicklingError, Exception)


def test_missing_weights_give_one_clear_message(tmp_path):
    with pytest.raises(MissingWeightsError, match="huggingface.co/facebook/VGGT-1B/resolve/main/model.pt"):
        load_vggt(str(tmp_path / "absent.safetensors"))
    # A hub id that is not cached, with downloads disabled: no network is touched.
    with pytest.raises(MissingWeightsError, match="--weights PATH"):
        load_vggt("facebook/VGGT-1B", cache_dir=tmp_path / "hub", local_files_only=True)


def test_rope_reads_each_positions_tensor_once_and_never_a_stale_length(monkeypatch):
    """The largest position is read once per positions tensor (each read waits for a GPU); a new
    tensor, even one at a freed tensor's address, is read again."""
    from sl4slam.models.vggt.rope import RotaryPositionEmbedding2D, patch_positions

    rope, fresh = RotaryPositionEmbedding2D(), RotaryPositionEmbedding2D
    tokens = torch.randn(1, 2, 5 + 4 * 6, 8)
    reads = []
    original = torch.Tensor.max
    monkeypatch.setattr(torch.Tensor, "max", lambda self, *a, **k: reads.append(1) or original(self, *a, **k))
    positions = patch_positions(1, 4, 6, 5, "cpu")
    first = rope(tokens, positions)
    assert torch.equal(rope(tokens, positions), first) and len(reads) == 1
    assert torch.equal(first, fresh()(tokens, positions))
    del positions
    for rows, cols in ((4, 6), (3, 8), (2, 12)):  # a new tensor may take the freed one's address
        bigger = patch_positions(1, rows, cols, 5, "cpu")
        assert torch.equal(rope(tokens, bigger), fresh()(tokens, bigger))
        del bigger
    assert len(reads) == 2 + 3 * 2  # each tensor once by ``rope``, once by its fresh module


def test_building_on_meta_to_load_weights_leaves_torch_compiler_stack_unimported() -> None:
    """Loading weights builds the model on the meta device first; drawing its tokens' random
    initial values there would import torch._dynamo (seconds on a cold start). Checked in a fresh
    process, since other tests may have imported it in this one."""
    import subprocess
    import sys

    code = ("import sys, torch\n"
            "from sl4slam.models.vggt.model import VGGT, VGGTModelConfig\n"
            "with torch.device('meta'):\n"
            "    model = VGGT(VGGTModelConfig(embed_dim=64, depth=2, num_heads=2, patch_embed_depth=2, patch_embed_num_heads=2))\n"
            "assert all(p.is_meta for p in model.parameters())\n"
            "print('torch._dynamo' in sys.modules)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "False"


def test_learned_tokens_are_drawn_as_before_off_meta() -> None:
    """Off the meta device the tokens are ``randn * 1e-6`` from the global generator, bit for bit."""
    from sl4slam.models.vggt.aggregator import _tiny_normal

    torch.manual_seed(11)
    drawn = [_tiny_normal(1, 2, 1, 64), _tiny_normal(1, 2, 4, 64)]
    torch.manual_seed(11)
    expected = [torch.randn(1, 2, 1, 64) * 1e-6, torch.randn(1, 2, 4, 64) * 1e-6]
    assert all(torch.equal(a, b) for a, b in zip(drawn, expected))
