"""A GPU that does not run bf16, or that torch cannot describe, gets fp16, and the run says so.

No GPU is needed: torch's CUDA queries are replaced by ones that answer as such a card would.
"""

from __future__ import annotations

import pytest
import torch

from sl4slam.config import ModelConfig, SLAMConfig
from sl4slam.models.precision import precision_note, runs_bf16, settle_mode
from sl4slam.resolve import resolve

MODES = ("fp32", "bf16", "fp16")
CUDA = torch.device("cuda")


def _no(device: torch.device) -> bool:
    return False


def _yes(device: torch.device) -> bool:
    return True


def _unknown_card(device: torch.device) -> bool:
    raise RuntimeError("CUDA driver version is insufficient for CUDA runtime version")


@pytest.mark.parametrize("test, expected", [(_yes, "bf16"), (_no, "fp16"), (_unknown_card, "fp16")])
def test_auto_and_bf16_become_fp16_where_the_gpu_does_not_run_bf16(test, expected) -> None:
    assert runs_bf16(CUDA, test) == (expected == "bf16")
    assert settle_mode("auto", "cuda", MODES, "VGGT", bf16=test) == expected
    assert settle_mode("bf16", "cuda:0", MODES, "VGGT", bf16=test) == expected
    assert settle_mode("fp32", "cuda", MODES, "VGGT", bf16=test) == "fp32"  # asked for: kept
    assert settle_mode("bf16", "cpu", MODES, "VGGT", bf16=_no) == "bf16"  # the CPU runs bf16 as asked
    assert settle_mode("auto", "cpu", MODES, "VGGT", bf16=_yes) == "fp32"
    assert settle_mode("bf16", "cuda", ("fp32", "bf16"), "a model without fp16", bf16=_no) == "fp32"


def test_the_note_says_what_auto_became_and_why_bf16_was_not_used() -> None:
    assert precision_note("auto", "bf16", "cuda") == "model precision: bf16 (auto on a GPU: this GPU runs bf16)"
    assert "fp16" in precision_note("auto", "fp16", "cuda:1") and "does not run bf16" in precision_note("auto", "fp16", "cuda")
    fallback = precision_note("BF16", "fp16", "cuda")
    assert fallback.startswith("model precision: fp16 instead of the bf16 asked for") and "\n" not in fallback
    assert precision_note("bf16", "bf16", "cuda") is None and precision_note("fp16", "fp16", "cuda") is None
    assert precision_note("auto", "fp32", "cpu") is None  # nothing to say off the GPU


@pytest.fixture
def gpu_without_bf16(monkeypatch):
    """torch answers as on a machine with one CUDA card that runs no bf16 and whose capability it
    cannot read."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: False)

    def capability(*args, **kwargs):
        raise RuntimeError("no kernel image is available for execution on the device")

    monkeypatch.setattr(torch.cuda, "get_device_capability", capability)


@pytest.mark.parametrize("frontend", ["vggt", "da3-small", "pi3x"])
def test_a_run_on_such_a_gpu_settles_fp16_and_says_so(gpu_without_bf16, frontend) -> None:
    asked = resolve(SLAMConfig(frontend=frontend, device="cuda", model=ModelConfig(dtype="bf16")))
    assert asked.device == "cuda" and asked.config.model.dtype == "fp16"
    notes = [line.strip() for line in asked.lines()[1:] if "model precision" in line]
    assert len(notes) == 1 and notes[0].startswith("model precision: fp16 instead of the bf16 asked for"), asked.lines()
    auto = resolve(SLAMConfig(frontend=frontend, device="cuda"))
    assert auto.config.model.dtype == "fp16"
    assert any("model precision: fp16 (auto on a GPU" in note for note in auto.notes)


def test_a_cpu_run_has_no_precision_note() -> None:
    resolved = resolve(SLAMConfig(frontend="vggt", device="cpu"))
    assert resolved.config.model.dtype == "fp32"
    assert not any("model precision" in note for note in resolved.notes)
