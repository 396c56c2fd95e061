"""Weights files that cannot be used: one line naming the file, what is wrong and the fix."""

from __future__ import annotations

import builtins
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.models.checkpoint import WeightsFileError, check_weights_file, describe_checkpoint, read_checkpoint
from sl4slam.models.hub import VGGT_WEIGHTS, resolve_weights
from sl4slam.models.salad import load_salad
from sl4slam.models.vggt.weights import load_vggt
from sl4slam.resolve import model_of_weights

FIX = "delete it and fetch it again"


def _one_line(exc: pytest.ExceptionInfo, path: Path) -> str:
    message = str(exc.value)
    assert "\n" not in message and str(path) in message
    return message


@pytest.fixture()
def tensors() -> dict[str, torch.Tensor]:
    return {"aggregator.camera_token": torch.arange(4096, dtype=torch.float32).reshape(1, 2, 2048),
            "other.weight": torch.ones(300, 30)}


def test_a_pt_cut_short_is_an_interrupted_download(tmp_path, tensors) -> None:
    whole = tmp_path / "whole.pt"
    torch.save(tensors, whole)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(WeightsFileError) as caught:
        load_vggt(str(cut))
    message = _one_line(caught, cut)
    assert "cut short" in message and "interrupted download" in message
    assert "`hf download facebook/VGGT-1B model.pt`" in message and "huggingface-cli" not in message
    assert read_checkpoint(whole, "VGGT", FIX)[0].keys() == tensors.keys()  # the whole file still reads


def test_a_safetensors_cut_short_says_how_much_is_missing(tmp_path, tensors) -> None:
    whole = tmp_path / "whole.safetensors"
    save_file(tensors, str(whole))
    size = whole.stat().st_size
    for keep in (5, 60, size - 100):
        cut = tmp_path / f"cut{keep}.safetensors"
        cut.write_bytes(whole.read_bytes()[:keep])
        with pytest.raises(WeightsFileError) as caught:
            resolve_weights(str(cut))
        assert "cut short" in _one_line(caught, cut)
    cut = tmp_path / f"cut{size - 100}.safetensors"
    with pytest.raises(WeightsFileError, match=f"{size - 100} of {size} bytes"):
        check_weights_file(cut, "VGGT", FIX)


def test_random_bytes_are_called_corrupt_not_unsafe(tmp_path) -> None:
    noise = tmp_path / "noise.pt"
    noise.write_bytes(bytes(range(7, 256)) * 40)
    with pytest.raises(WeightsFileError) as caught:
        load_vggt(str(noise))
    message = _one_line(caught, noise)
    assert "not a PyTorch or safetensors checkpoint" in message and "pickled" not in message
    page = tmp_path / "page.pt"
    page.write_bytes(b"<!DOCTYPE html><html>rate limited</html>")
    with pytest.raises(WeightsFileError, match="web page"):
        check_weights_file(page, "VGGT", FIX)
    empty = tmp_path / "empty.safetensors"
    empty.write_bytes(b"")
    with pytest.raises(WeightsFileError, match="is empty"):
        check_weights_file(empty, "VGGT", FIX)


def test_a_folder_without_weights_and_a_folder_as_file(tmp_path) -> None:
    folder = tmp_path / "weights.safetensors"
    folder.mkdir()
    with pytest.raises(WeightsFileError) as caught:
        check_weights_file(folder, "VGGT", FIX)
    assert "is a folder" in _one_line(caught, folder)
    with pytest.raises(MissingWeightsError, match="no model.safetensors or model.pt in folder"):
        resolve_weights(str(folder))


def test_a_file_without_read_permission(tmp_path, tensors, monkeypatch) -> None:
    path = tmp_path / "model.safetensors"
    save_file(tensors, str(path))
    real_open = builtins.open

    def refuse(file, *args, **kwargs):  # root reads any file, so the refusal is simulated
        if str(file) == str(path):
            raise PermissionError(13, "Permission denied")
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", refuse)
    with pytest.raises(WeightsFileError) as caught:
        resolve_weights(str(path))
    assert "permission denied" in _one_line(caught, path)


def test_another_models_checkpoint_says_what_it_holds(tmp_path, fixtures_dir) -> None:
    salad = fixtures_dir / "salad_tiny" / "state_dict.safetensors"
    with pytest.raises(UserError) as caught:
        load_vggt(str(salad))
    message = _one_line(caught, salad)
    assert "holds a SALAD checkpoint" in message and "not VGGT weights" in message
    vggt = fixtures_dir / "vggt_tiny_b" / "state_dict.safetensors"
    with pytest.raises(UserError) as caught:
        load_salad(vggt)
    assert "holds a VGGT checkpoint" in _one_line(caught, vggt)
    assert describe_checkpoint({"x.weight": torch.zeros(1)}).startswith("weights of an unknown model")


def test_salad_problems_name_the_salad_flag(tmp_path) -> None:
    cut = tmp_path / "dino_salad.ckpt"
    cut.write_bytes(b"PK\x03\x04" + b"\0" * 100)
    with pytest.raises(WeightsFileError) as caught:
        load_salad(cut)
    message = _one_line(caught, cut)
    assert "cut short" in message and "--salad-weights" in message
    with pytest.raises(MissingWeightsError, match="--salad-weights PATH"):
        load_salad(tmp_path / "absent.ckpt")


def test_missing_weights_suggest_the_current_hub_command(tmp_path) -> None:
    with pytest.raises(MissingWeightsError) as caught:
        resolve_weights("facebook/VGGT-1B", cache_dir=tmp_path / "hub", local_files_only=True)
    assert "`hf download facebook/VGGT-1B model.pt`" in str(caught.value)
    assert VGGT_WEIGHTS.flag in str(caught.value)


def test_a_cut_weights_file_fails_a_run_before_any_frame_is_read(tmp_path, tensors, monkeypatch) -> None:
    import cv2
    import numpy as np

    from sl4slam import io
    from sl4slam.config import SLAMConfig
    from sl4slam.runner import run_slam

    whole = tmp_path / "model.safetensors"
    save_file(tensors, str(whole))
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(whole.read_bytes()[:200])
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
    read = []
    original = io.ImageFolderSource._load
    monkeypatch.setattr(io.ImageFolderSource, "_load", lambda self, position: read.append(position) or original(self, position))
    config = SLAMConfig(device="cpu")
    config.model.weights = str(cut)
    config.retrieval.kind = "none"
    with pytest.raises(WeightsFileError) as caught:
        run_slam(folder, tmp_path / "out", config, progress=False)
    assert "cut short" in _one_line(caught, cut) and read == [] and not (tmp_path / "out").exists()


@pytest.mark.parametrize("suffix", [".pt", ".safetensors"])
def test_convert_of_a_cut_file_says_cut_short_and_how_convert_takes_it(tmp_path, tensors, capsys, suffix) -> None:
    from sl4slam.cli import main

    whole = tmp_path / f"whole{suffix}"
    torch.save(tensors, whole) if suffix == ".pt" else save_file(tensors, str(whole))
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    for model in ([], ["--model", "vggt"]):  # recognized from the file, or named
        assert main(["convert", str(cut), str(tmp_path / "out.safetensors"), *model]) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(lines) == 1 and str(cut) in lines[0], lines
        assert "cut short" in lines[0] and "known model" not in lines[0]
        assert "to sl4slam convert" in lines[0] and "--weights" not in lines[0]
    assert not (tmp_path / "out.safetensors").exists()
    with pytest.raises(WeightsFileError, match="then pass it with --weights PATH"):  # a run keeps its flag
        load_vggt(str(cut))
    with pytest.raises(WeightsFileError, match="cut short.*then pass it with --model PATH"):  # run --model FILE
        model_of_weights(str(cut))


def test_convert_of_another_models_checkpoint_names_convert_not_a_flag(tmp_path, fixtures_dir, capsys) -> None:
    from sl4slam.cli import main

    salad = fixtures_dir / "salad_tiny" / "state_dict.safetensors"
    assert main(["convert", str(salad), str(tmp_path / "out.safetensors"), "--model", "vggt"]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "holds a SALAD checkpoint" in lines[0]
    assert "pass a VGGT checkpoint to sl4slam convert" in lines[0] and "--weights" not in lines[0]
