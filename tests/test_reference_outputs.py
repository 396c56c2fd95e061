"""The float32 bound used against stored reference outputs (``reference_outputs``): it accepts the same
computation rounded differently, and rejects a wrong one by a wide margin."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch
from reference_outputs import REFERENCE_ULPS, assert_matches_reference, spacings_apart
from safetensors.torch import load_file

from sl4slam.models.vggt.model import VGGT, VGGTModelConfig
from sl4slam.models.vggt.weights import load_state_dict_into

OUTPUTS = ("pose_enc", "depth", "world_points")


@pytest.fixture(scope="module")
def tiny_b(fixtures_dir):
    folder = fixtures_dir / "vggt_tiny_b"
    config = VGGTModelConfig.from_reference_config(json.loads((folder / "config.json").read_text()))
    state_dict = load_file(str(folder / "state_dict.safetensors"))
    inputs = load_file(str(folder / "inputs.safetensors"))
    outputs = load_file(str(folder / "outputs.safetensors"))
    return config, state_dict, inputs, outputs


def _forward(config, state_dict, images):
    model = VGGT(config).eval()
    load_state_dict_into(model, state_dict)
    with torch.inference_mode():
        predictions = model(images)
    return {key: predictions[key] for key in OUTPUTS}


PLAIN_KERNELS = {"ATEN_CPU_CAPABILITY": "default", "ONEDNN_MAX_CPU_ISA": "SSE41", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2"}
"""Environment that makes torch, oneDNN and MKL take their plain (non-AVX) kernels: another CPU's order."""


def test_the_bound_accepts_another_kernel_path(tiny_b, fixtures_dir, tmp_path):
    """The same forward in a process forced onto the plain kernels (another accumulation order than
    this machine's and the fixtures') stays within the bound."""
    script = f"""
import json, sys, torch
from safetensors.torch import load_file, save_file
from sl4slam.models.vggt.model import VGGT, VGGTModelConfig
from sl4slam.models.vggt.weights import load_state_dict_into
folder = sys.argv[1]
config = VGGTModelConfig.from_reference_config(json.load(open(folder + "/config.json")))
model = VGGT(config).eval()
load_state_dict_into(model, load_file(folder + "/state_dict.safetensors"))
with torch.inference_mode():
    predictions = model(load_file(folder + "/inputs.safetensors")["images"])
save_file({{k: predictions[k].contiguous() for k in {OUTPUTS!r}}}, sys.argv[2])
print(torch.backends.cpu.get_cpu_capability())
"""
    target = tmp_path / "plain.safetensors"
    done = subprocess.run([sys.executable, "-c", script, str(fixtures_dir / "vggt_tiny_b"), str(target)],
                          env={**os.environ, **PLAIN_KERNELS}, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-1] == "DEFAULT"  # the forced path was taken
    plain = load_file(str(target))
    outputs = tiny_b[3]
    for key in OUTPUTS:
        assert_matches_reference(plain[key], outputs[key], f"plain kernels {key}")


def test_the_bound_rejects_a_wrong_computation(tiny_b):
    """One bias of one attention projection dropped moves the outputs by more than 10x the bound."""
    config, state_dict, inputs, outputs = tiny_b
    name = "aggregator.frame_blocks.0.attn.proj.bias"
    assert name in state_dict
    wrong = _forward(config, {**state_dict, name: torch.zeros_like(state_dict[name])}, inputs["images"])
    for key in OUTPUTS:
        assert spacings_apart(wrong[key], outputs[key]) > 10 * REFERENCE_ULPS, key
        with pytest.raises(AssertionError, match="float32 spacings from the reference"):
            assert_matches_reference(wrong[key], outputs[key], key)


def test_discrete_and_special_values():
    reference = torch.tensor([1.0, float("nan"), float("inf"), 0.0])
    assert spacings_apart(reference.clone(), reference) == 0.0
    assert_matches_reference(reference + torch.tensor([2**-23, 0.0, 0.0, 0.0]), reference, "one spacing")
    with pytest.raises(AssertionError, match="NaN in different places"):
        assert_matches_reference(torch.tensor([1.0, 0.0, float("inf"), 0.0]), reference, "nan moved")
    with pytest.raises(AssertionError, match="discrete outputs differ"):
        assert_matches_reference(torch.tensor([1, 2]), torch.tensor([1, 3]), "indices")
    with pytest.raises(AssertionError, match="dtype"):
        assert_matches_reference(torch.zeros(2, dtype=torch.float64), torch.zeros(2), "dtype")
    with pytest.raises(AssertionError, match="shape"):
        assert_matches_reference(torch.zeros(3), torch.zeros(2), "shape")
