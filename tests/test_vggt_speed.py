"""VGGT precision modes, chunked dense heads and the --max-memory plan."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from sl4slam.config import ModelConfig, SLAMConfig
from sl4slam.errors import UserError
from sl4slam.frontend.vggt import VGGTFrontend
from sl4slam.models.vggt.memory import (
    GIB,
    estimate_peak_bytes,
    largest_fitting_frames,
    plan_memory,
    weight_bytes,
)
from sl4slam.models.vggt.model import VGGT, VGGTModelConfig
from sl4slam.models.vggt.precision import (
    apply_precision,
    count_quantized_linears,
    relative_errors,
    resolve_precision,
)
from sl4slam.models.vggt.weights import load_state_dict_into
from sl4slam.types import Frame

CPU = torch.device("cpu")
# Tolerances against float32 on the tiny fixture, (max, median) of relative_errors; measured
# int8: depth 6e-3 / 9e-4, bf16: depth 1.8e-2 / 2.2e-3 (README of benchmarks/results/vggt.md).
TOLERANCES = {
    "int8": {"depth": (3e-2, 5e-3), "depth_conf": (3e-2, 5e-3), "pose_enc": (0.3, 2e-2)},
    "bf16": {"depth": (6e-2, 1e-2), "depth_conf": (6e-2, 1e-2), "pose_enc": (0.3, 2e-2)},
}


@pytest.fixture(scope="module")
def tiny(fixtures_dir):
    folder = fixtures_dir / "vggt_tiny_b"
    config = VGGTModelConfig.from_reference_config(json.loads((folder / "config.json").read_text()))
    return config, load_file(folder / "state_dict.safetensors"), load_file(folder / "inputs.safetensors")["images"]


def _model(tiny) -> VGGT:
    config, state_dict, _ = tiny
    model = VGGT(config).eval()
    load_state_dict_into(model, state_dict)
    return model


def _run(model: VGGT, images: torch.Tensor, mode: str) -> dict:
    autocast = resolve_precision(mode, CPU).autocast
    with torch.inference_mode(), torch.autocast("cpu", dtype=autocast or torch.float32, enabled=autocast is not None):
        return model(images)


@pytest.mark.parametrize("mode", ["int8", "bf16"])
def test_reduced_precision_stays_close_to_float32(tiny, mode):
    reference = _run(_model(tiny), tiny[2], "fp32")
    model = apply_precision(_model(tiny), resolve_precision(mode, CPU))
    if mode == "int8":
        linears = sum(isinstance(m, torch.nn.Linear) for m in _model(tiny).aggregator.modules())
        assert count_quantized_linears(model) == linears > 0
        assert count_quantized_linears(model.camera_head) == 0  # the heads stay float32
    else:
        assert all(p.dtype == torch.bfloat16 for p in model.aggregator.parameters())
        assert all(p.dtype == torch.float32 for p in model.depth_head.parameters())
    outputs = _run(model, tiny[2], mode)
    for key, (max_tol, median_tol) in TOLERANCES[mode].items():
        assert outputs[key].dtype == torch.float32
        worst, median = relative_errors(outputs[key], reference[key])
        assert worst <= max_tol and median <= median_tol, (key, worst, median)
        assert worst > 0, key  # the mode really changed the arithmetic


def test_relative_errors_floor_and_values():
    reference = torch.tensor([2.0, -4.0, 0.0, 1.0])
    worst, median = relative_errors(reference * 1.01, reference)
    assert worst == pytest.approx(0.01) and median == pytest.approx(0.01)
    # A value at zero is measured against 1 % of the rms (0.0229), not divided by zero.
    worst, _ = relative_errors(reference + torch.tensor([0, 0, 1e-3, 0]), reference)
    assert worst == pytest.approx(1e-3 / (0.01 * float(reference.pow(2).mean().sqrt())))


def test_chunked_dense_heads_match_unchunked(tiny):
    model = _model(tiny)
    images = torch.cat([tiny[2], tiny[2].flip(1)], dim=1)  # B = 2, S = 4
    model.set_head_chunk_frames(4)
    whole = _run(model, images, "fp32")
    for chunk in (1, 3):
        model.set_head_chunk_frames(chunk)
        chunked = _run(model, images, "fp32")
        for key in ("depth", "depth_conf", "world_points", "world_points_conf"):
            torch.testing.assert_close(chunked[key], whole[key], atol=1e-6, rtol=1e-6, msg=key)
    with pytest.raises(ValueError, match="at least 1"):
        model.set_head_chunk_frames(0)


def test_resolve_precision():
    assert resolve_precision("fp32", CPU).mode == "fp32"
    with pytest.raises(ValueError, match="unknown"):  # "auto" is settled by sl4slam.resolve before
        resolve_precision("auto", CPU)
    assert resolve_precision("int8", CPU).autocast is None
    bf16 = resolve_precision("bf16", CPU)
    assert (bf16.storage, bf16.autocast, bf16.activation_bytes) == (torch.bfloat16, torch.bfloat16, 2)
    with pytest.raises(ValueError, match="CPU only"):
        resolve_precision("int8", torch.device("cuda"))
    with pytest.raises(ValueError, match="unknown"):
        resolve_precision("int4", CPU)


FULL = VGGTModelConfig()


def test_weight_bytes_of_the_full_model():
    fp32 = weight_bytes(FULL, resolve_precision("fp32", CPU), heads=("camera", "depth", "point"))
    with torch.device("meta"):
        params = sum(p.numel() for p in VGGT(FULL).parameters())
    assert fp32 == 4 * params
    bf16 = weight_bytes(FULL, resolve_precision("bf16", CPU))
    int8 = weight_bytes(FULL, resolve_precision("int8", CPU))
    assert int8 < bf16 < fp32 / 1.5  # the aggregator holds most of the weights


def test_memory_plan_picks_the_largest_chunk_that_fits():
    bf16 = resolve_precision("bf16", CPU)
    peaks = [estimate_peak_bytes(FULL, bf16, 16, 294, 518, chunk) for chunk in range(1, 9)]
    assert all(a < b for a, b in itertools.pairwise(peaks))  # more frames at once, more memory
    budget = (peaks[2] + peaks[3]) / 2 / GIB  # between chunk 3 and chunk 4
    plan = plan_memory(FULL, bf16, budget, 16, 294, 518)
    assert plan.head_chunk_frames == 3 and plan.estimated_peak_bytes == peaks[2]
    assert plan_memory(FULL, bf16, 1000, 16, 294, 518).head_chunk_frames == 8
    assert plan_memory(FULL, bf16, 1000, 2, 294, 518).head_chunk_frames == 2  # never more than the frames


def test_memory_plan_names_the_largest_submap_that_fits():
    bf16 = resolve_precision("bf16", CPU)
    budget = 4.0
    largest = largest_fitting_frames(FULL, bf16, int(budget * GIB), 518, 518)
    assert largest >= 1
    assert estimate_peak_bytes(FULL, bf16, largest, 518, 518, 1) <= budget * GIB
    assert estimate_peak_bytes(FULL, bf16, largest + 1, 518, 518, 1) > budget * GIB
    with pytest.raises(UserError) as error:
        plan_memory(FULL, bf16, budget, largest + 1, 518, 518)
    message = str(error.value)
    assert "\n" not in message and f"largest submap that fits is {largest} frames" in message
    assert "--max-memory" in message and "--submap-size" in message
    assert largest_fitting_frames(FULL, bf16, int(0.5 * GIB), 518, 518) == 0  # not even the weights
    # on a GPU without --max-memory the GPU's own memory is the budget, named as such
    with pytest.raises(UserError) as error:
        plan_memory(FULL, bf16, budget, largest + 1, 518, 518, budget_source="the GPU (a small one) has")
    message = str(error.value)
    assert "the GPU (a small one) has 4 GiB" in message and f"--submap-size {max(1, largest - 2)}" in message
    assert "raise --max-memory" not in message


@pytest.mark.parametrize(
    "changes, flag",
    [({"max_memory_gb": -1.0}, "--max-memory"), ({"head_chunk_frames": 0}, "--head-chunk-frames"),
     ({"dtype": "int4"}, "--dtype")],
)
def test_config_validation(changes, flag):
    with pytest.raises(UserError, match=flag):
        ModelConfig(**changes).validate()
    ModelConfig(dtype="int8", max_memory_gb=6.0, head_chunk_frames=2).validate()
    with pytest.raises(UserError, match="--dtype"):  # int8 is a CPU mode
        SLAMConfig(device="cuda", model=ModelConfig(dtype="int8")).validate()


SMALL = VGGTModelConfig(
    embed_dim=32, depth=4, num_heads=2, patch_embed_depth=1, patch_embed_num_heads=2,
    camera_trunk_depth=1, camera_num_heads=2, dpt_features=8, dpt_out_channels=[8, 8, 8, 8], dpt_layers=[0, 1, 2, 3],
)


def _frames(num: int) -> list[Frame]:
    rng = np.random.default_rng(0)
    return [Frame(index=i, timestamp=float(i), rgb=rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)) for i in range(num)]


def _small_model() -> VGGT:
    from sl4slam.models.vggt.model import init_random_weights

    return init_random_weights(VGGT(SMALL), seed=0).eval()


def test_frontend_int8_and_memory_budget():
    frames = _frames(3)
    reference = VGGTFrontend(ModelConfig(dtype="fp32"), model=_small_model(), device="cpu").reconstruct(frames, 0)
    int8 = VGGTFrontend(ModelConfig(dtype="int8"), model=_small_model(), device="cpu")
    assert count_quantized_linears(int8.model) > 0
    prediction = int8.reconstruct(frames, 0)
    worst, median = relative_errors(torch.from_numpy(prediction.depth), torch.from_numpy(reference.depth))
    assert worst > 0 and median < 1e-2
    # A budget: the chunk follows it, and a submap that cannot fit is refused before any work.
    height, width = prediction.depth.shape[1:]
    roomy = VGGTFrontend(ModelConfig(dtype="fp32", max_memory_gb=64.0), model=_small_model(), device="cpu")
    assert roomy.head_chunk(3, height, width) == 3
    tight = VGGTFrontend(ModelConfig(dtype="fp32", max_memory_gb=0.1), model=_small_model(), device="cpu")
    with pytest.raises(UserError, match="below the smallest budget any setting fits"):
        tight.reconstruct(frames, 0)
