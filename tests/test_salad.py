"""SALAD place recognition: DINOv2 + SALAD parity with the reference fixtures, loading, index, retrieval.

Model outputs are compared with the stored reference within float32 reordering (``reference_outputs``:
the fixtures were made on another machine); preprocessing, which is exact arithmetic on uint8 images
and tables, is compared bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import load_file

from reference_outputs import assert_matches_reference

from sl4slam.config import RetrievalConfig
from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.models import salad as salad_module
from sl4slam.models.dinov2 import DinoVisionTransformer
from sl4slam.models.salad import (
    SaladModel,
    float_images_to_uint8,
    load_salad,
    normalize_uint8_images,
    preprocess_images,
    read_state_dict,
    resize_uint8,
    sinkhorn_log_transport,
)
from sl4slam.retrieval.salad import DescriptorIndex, SaladRetrieval
from sl4slam.types import Retrieval
from sl4slam.io.memory import frames_from_images as as_frames

TINY_SIZES = dict(embed_dim=64, depth=2, num_heads=2, num_clusters=8, cluster_dim=16, token_dim=32)


# ----------------------------------------------------------------------------- helpers


@pytest.fixture(scope="module")
def tiny_dir(fixtures_dir: Path) -> Path:
    """The vendored tiny case: weights, the first image of each batch, its reference outputs."""
    return fixtures_dir / "salad_tiny"


@pytest.fixture(scope="module")
def tiny_model(tiny_dir: Path) -> SaladModel:
    model = SaladModel(**TINY_SIZES).eval()
    model.load_state_dict(load_file(str(tiny_dir / "state_dict.safetensors")), strict=True)
    return model


@pytest.fixture(scope="module")
def tiny_io(tiny_dir: Path) -> tuple[dict, dict]:
    """Inputs (float images derived from the uint8 ones, bitwise as the reference made them) and outputs."""
    inputs = load_file(str(tiny_dir / "inputs.safetensors"))
    inputs["images"] = normalize_uint8_images(inputs["images_uint8"].numpy())
    inputs["images_224"] = normalize_uint8_images(inputs["images_224_uint8"].numpy())
    return inputs, load_file(str(tiny_dir / "outputs.safetensors"))


@pytest.fixture(scope="module")
def full_tiny_io(fixtures_dir: Path, tiny_dir: Path) -> tuple[dict, dict, torch.Tensor]:
    """The reference's preprocessing examples, rebuilt bitwise from their vendored form
    (tests/fixtures/README.md): uint8 images from PNG files, float tensors from lookup tables at
    those images; of the model inputs, the first image of each batch. Also the table of
    normalized values (every value of every normalized reference tensor)."""
    folder = fixtures_dir / "salad_preprocess"
    tables = load_file(str(folder / "tables.safetensors"))
    normalize = tables["normalize"]  # (3, 256): ToTensor + Normalize of value v in channel c

    def png(name: str) -> torch.Tensor:
        return torch.from_numpy(np.array(Image.open(folder / name)))

    def normalized(hwc: torch.Tensor) -> torch.Tensor:  # (B, H, W, 3) or (H, W, 3) uint8 -> (B, 3, H, W)
        nchw = (hwc if hwc.ndim == 4 else hwc[None]).permute(0, 3, 1, 2).long()
        return normalize[torch.arange(3)[:, None, None], nchw]

    inputs = load_file(str(tiny_dir / "inputs.safetensors"))
    inputs["images"] = normalized(inputs["images_uint8"])
    inputs["images_224"] = normalized(inputs["images_224_uint8"])
    raw = inputs["preproc.raw_uint8_hwc"] = png("raw_480x400.png")
    for size in (322, 224):
        inputs[f"preproc.resized_{size}_uint8_hwc"] = png(f"resized_{size}.png")
        inputs[f"preproc.normalized_{size}"] = normalized(inputs[f"preproc.resized_{size}_uint8_hwc"])
    raw_chw = raw.permute(2, 0, 1).long()
    inputs["preproc.vggt_float01_chw"] = tables["vggt_float01"][raw_chw]
    inputs["preproc.vggt_topil_uint8_chw"] = tables["vggt_topil"][raw_chw]
    inputs["preproc.vggt_normalized_224"] = normalized(png("vggt_resized_224.png"))
    return inputs, {"preproc.descriptor_322": tables["descriptor_322"]}, normalize


def write_random_salad_checkpoint(path: Path, seed: int = 0, lightning: bool = False) -> Path:
    """A full-size (ViT-B/14, 8448-dim) SALAD checkpoint with random weights, in the layout of
    ``dino_salad.ckpt`` (or nested under ``state_dict`` as Lightning writes it)."""
    torch.manual_seed(seed)
    state_dict = SaladModel().state_dict()
    torch.save({"state_dict": state_dict, "epoch": 3} if lightning else state_dict, str(path))
    return path


def random_images(count: int, seed: int, height: int = 120, width: int = 160) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    # Smooth random images (upsampled noise) look more like photos than white noise.
    coarse = rng.integers(0, 256, size=(count, height // 8, width // 8, 3), dtype=np.uint8)
    return [np.ascontiguousarray(np.repeat(np.repeat(c, 8, axis=0), 8, axis=1)) for c in coarse]


# ----------------------------------------------------------------------------- DINOv2


def test_pos_embed_scale_factor_resize_matches_reference(fixtures_dir: Path) -> None:
    data = load_file(str(fixtures_dir / "salad_pos_embed_interp.safetensors"))
    data["interp_518"] = data["pos_embed"]  # the reference returns it unchanged (bitwise; not stored twice)
    vit = DinoVisionTransformer(embed_dim=64, depth=0, num_heads=2, interpolate_offset=0.1)
    assert vit.pos_embed_resize == "scale_factor"
    with torch.no_grad():
        vit.pos_embed.copy_(data["pos_embed"])
    for size in (322, 224, 518):
        tokens = torch.zeros(1, 1 + (size // 14) ** 2, 64)
        out = vit.interpolate_pos_encoding(tokens, size, size)
        assert_matches_reference(out, data[f"interp_{size}"], f"pos_embed {size}")
    # Resizing to the exact size instead is a different function (the reference differs by > 1).
    vit_size = DinoVisionTransformer(embed_dim=64, depth=0, num_heads=2, interpolate_offset=0.1, pos_embed_resize="size")
    with torch.no_grad():
        vit_size.pos_embed.copy_(data["pos_embed"])
    wrong = vit_size.interpolate_pos_encoding(torch.zeros(1, 530, 64), 322, 322)
    assert (wrong - data["interp_322"]).abs().max() > 0.5


def test_pos_embed_antialiased_size_resize_matches_vggt_reference(fixtures_dir: Path) -> None:
    folder = fixtures_dir / "vggt_tiny_a"  # the vendored cut of VGGT's tiny_a
    state = load_file(str(folder / "state_dict.safetensors"))
    expected = load_file(str(folder / "intermediates.safetensors"))
    prefix = "aggregator.patch_embed."
    expected["pos_embed_interp_518x518"] = state[prefix + "pos_embed"]  # returned unchanged (bitwise; not stored twice)
    vit = DinoVisionTransformer(
        embed_dim=64, depth=2, num_heads=4, num_register_tokens=4, interpolate_antialias=True, interpolate_offset=0.0
    )
    vit.load_state_dict({k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}, strict=True)
    checked = 0
    for key, value in expected.items():
        if key.startswith("pos_embed_interp_"):
            height, width = (int(v) for v in key.rsplit("_", 1)[1].split("x"))
            tokens = torch.zeros(1, 1 + (height // 14) * (width // 14), 64)
            assert_matches_reference(vit.interpolate_pos_encoding(tokens, height, width), value, key)
            checked += 1
    assert checked >= 4


# ----------------------------------------------------------------------------- Sinkhorn


def test_sinkhorn_matches_reference_cases(fixtures_dir: Path) -> None:
    data = load_file(str(fixtures_dir / "salad_sinkhorn.safetensors"))
    cases = json.loads((fixtures_dir / "salad_sinkhorn.json").read_text())
    assert len(cases) == 6
    for name, meta in cases.items():
        log_p = sinkhorn_log_transport(data[f"{name}.scores"], data[f"{name}.dustbin"][0], meta["num_iters"])
        m = meta["m"]
        assert log_p.shape == (meta["B"], m + 1, meta["n"])
        assert_matches_reference(log_p, data[f"{name}.log_P"], f"sinkhorn {name}")
        # the reference's P without the dust bin is exp of its log P (bitwise where vendored; not stored)
        reference_p = data[f"{name}.log_P"][:, :m].exp()
        torch.testing.assert_close(log_p[:, :m].exp(), reference_p, atol=1e-6, rtol=1e-5)
        # every column of P, dust bin included, sums to one after the final column update
        torch.testing.assert_close(log_p.exp().sum(dim=1), torch.ones(meta["B"], meta["n"]), atol=1e-5, rtol=0)


def test_sinkhorn_rejects_fewer_features_than_clusters() -> None:
    with pytest.raises(ValueError, match="more features than clusters"):
        sinkhorn_log_transport(torch.zeros(1, 8, 8), 1.0)


# ----------------------------------------------------------------------------- full model layout


def test_full_model_state_dict_equals_checkpoint_manifest(fixtures_dir: Path) -> None:
    manifest = json.loads((fixtures_dir / "salad_manifest_full.json").read_text())  # key -> shape, in order
    with torch.device("meta"):
        model = SaladModel()
    state = model.state_dict()
    expected = [(key, tuple(shape)) for key, shape in manifest["shapes"].items()]
    assert [(k, tuple(v.shape)) for k, v in state.items()] == expected
    assert sum(v.numel() for v in state.values()) == manifest["num_parameters_total"] == 87_991_489
    assert len(list(model.buffers())) == 0
    assert model.output_dim == 8448


# ----------------------------------------------------------------------------- tiny parity


@pytest.mark.parametrize("prefix, image_key", [("", "images"), ("s224.", "images_224")])
def test_tiny_model_matches_reference_outputs(tiny_model, tiny_io, tiny_dir, prefix, image_key) -> None:
    inputs, outputs = tiny_io
    with torch.no_grad():
        tokens = tiny_model.backbone.model.prepare_tokens(inputs[image_key])
        features, cls_token = tiny_model.backbone(inputs[image_key])
        stages = tiny_model.aggregator.forward_with_intermediates(features, cls_token)
    compared = {
        "backbone.tokens_after_prepare": tokens, "backbone.patch_features": features, "backbone.cls_token": cls_token,
        **{f"agg.{key}": stages[key] for key in ("cluster_features", "scores", "token_features", "log_assignment",
                                                  "aggregated")},
        "descriptor": stages["descriptor"],
    }
    for key, ours in compared.items():
        assert_matches_reference(ours, outputs[prefix + key], prefix + key)
    # the float64 run of the reference agrees too
    reference_f64 = load_file(str(tiny_dir / "outputs_ref_f64.safetensors"))
    torch.testing.assert_close(stages["descriptor"].double(), reference_f64[prefix + "descriptor"], atol=1e-6, rtol=0)
    # layout: [L2(token) (32) | intra-normalized clusters, channel-major (16 x 8)], all over sqrt(9)
    descriptor = stages["descriptor"]
    assert descriptor.shape[1] == 32 + 16 * 8
    torch.testing.assert_close(descriptor.norm(dim=1), torch.ones(len(descriptor)))
    torch.testing.assert_close(descriptor[:, :32].norm(dim=1), torch.full((len(descriptor),), 1 / 3))
    per_cluster = descriptor[:, 32:].reshape(-1, 16, 8).norm(dim=1)  # (B, clusters): channel-major
    torch.testing.assert_close(per_cluster, torch.full_like(per_cluster, 1 / 3))


# ----------------------------------------------------------------------------- preprocessing


def test_preprocessing_matches_reference(tiny_model, full_tiny_io) -> None:
    inputs, outputs, normalize = full_tiny_io
    assert torch.equal(normalize_uint8_images(inputs["images_uint8"].numpy()), inputs["images"])
    assert torch.equal(normalize_uint8_images(inputs["images_224_uint8"].numpy()), inputs["images_224"])
    # every value of the reference's normalized images (all of both batches), in every channel
    every_value = np.repeat(np.arange(256, dtype=np.uint8)[None, None, :, None], 3, axis=3)  # (1, 1, 256, 3)
    assert torch.equal(normalize_uint8_images(every_value), normalize[None, :, None, :])
    raw = inputs["preproc.raw_uint8_hwc"].numpy()
    for size in (322, 224):
        assert np.array_equal(resize_uint8(raw, size), inputs[f"preproc.resized_{size}_uint8_hwc"].numpy())
        assert torch.equal(preprocess_images([raw], size), inputs[f"preproc.normalized_{size}"])
    # VGGT-SLAM's frames: float [0, 1] -> truncating uint8 conversion -> 224 bilinear
    frames_uint8 = float_images_to_uint8(inputs["preproc.vggt_float01_chw"][None])
    assert np.array_equal(frames_uint8[0].transpose(2, 0, 1), inputs["preproc.vggt_topil_uint8_chw"].numpy())
    assert torch.equal(preprocess_images(list(frames_uint8), 224), inputs["preproc.vggt_normalized_224"])
    # end to end from the raw image
    descriptor = tiny_model.describe([raw], image_size=322)
    assert_matches_reference(torch.from_numpy(descriptor), outputs["preproc.descriptor_322"], "descriptor of the raw image")
    with pytest.raises(UserError, match="multiple of 14"):
        preprocess_images([raw], 300)


# ----------------------------------------------------------------------------- loading


@pytest.mark.parametrize("form", ["plain", "lightning", "safetensors"])
def test_read_state_dict_accepts_checkpoint_forms(tmp_path, tiny_dir, tiny_model, tiny_io, form) -> None:
    state = load_file(str(tiny_dir / "state_dict.safetensors"))
    if form == "safetensors":
        path = tiny_dir / "state_dict.safetensors"
    else:
        path = tmp_path / "salad.ckpt"
        torch.save({"state_dict": state, "epoch": 1, "global_step": 10} if form == "lightning" else state, str(path))
    loaded = read_state_dict(path)
    assert list(loaded) == list(state)
    model = SaladModel(**TINY_SIZES).eval()
    model.load_state_dict(loaded, strict=True)
    inputs, outputs = tiny_io
    with torch.no_grad():
        assert_matches_reference(model(inputs["images_224"]), outputs["s224.descriptor"], f"descriptor ({form})")


def test_load_salad_missing_local_file_names_the_fix(tmp_path) -> None:
    with pytest.raises(MissingWeightsError, match="not found at .*nothing.ckpt.*releases/download"):
        load_salad(tmp_path / "nothing.ckpt")


def test_load_salad_offline_download_failure_says_where_to_put_the_file(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("SL4SLAM_CACHE", str(tmp_path / "cache"))
    attempts = []

    def offline(url: str, destination: Path) -> None:
        attempts.append((url, destination))
        raise OSError("network is unreachable")

    monkeypatch.setattr(salad_module, "_download", offline)
    with pytest.raises(MissingWeightsError) as info:
        load_salad(None)
    expected_path = tmp_path / "cache" / "dino_salad.ckpt"
    assert attempts == [(salad_module.SALAD_WEIGHTS_URL, expected_path)]
    assert str(expected_path) in str(info.value) and "\n" not in str(info.value)
    assert salad_module.find_salad_weights(None) is None
    # no download allowed -> the same kind of error without trying the network
    with pytest.raises(MissingWeightsError, match="dino_salad.ckpt"):
        load_salad(None, download=False)
    assert len(attempts) == 1


def test_load_salad_rejects_a_foreign_checkpoint(tmp_path, tiny_dir) -> None:
    path = tmp_path / "tiny.ckpt"
    torch.save(load_file(str(tiny_dir / "state_dict.safetensors")), str(path))
    with pytest.raises(UserError, match="holds a SALAD checkpoint of another size, not the released SALAD .* wrong shapes"):
        load_salad(path)
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(UserError, match="not a PyTorch or safetensors checkpoint.*--salad-weights"):
        load_salad(garbage)


# ----------------------------------------------------------------------------- descriptor index


def _unit_rows(count: int, dim: int, seed: int) -> np.ndarray:
    rows = np.random.default_rng(seed).standard_normal((count, dim)).astype(np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-5), (torch.float16, 1e-3)])
def test_descriptor_index_matches_brute_force(dtype, tol) -> None:
    dim, stored_count = 256, 3000
    stored = _unit_rows(stored_count, dim, seed=1)
    # queries: noisy copies of known rows (clear nearest neighbours) plus unrelated rows
    rng = np.random.default_rng(2)
    targets = rng.choice(stored_count, size=12, replace=False)
    queries = np.concatenate([stored[targets] + 0.02 * rng.standard_normal((12, dim)), _unit_rows(4, dim, seed=3)])
    queries = queries.astype(np.float32)
    submaps = np.arange(stored_count) // 100  # 30 submaps of 100 frames
    index = DescriptorIndex(dim, dtype=dtype, initial_capacity=7)  # forces many reallocations
    for submap in range(30):
        rows = slice(submap * 100, (submap + 1) * 100)
        index.add(stored[rows], np.arange(stored_count)[rows] + 1000, submap)
    assert len(index) == stored_count
    assert index.bytes_per_descriptor == dim * (2 if dtype == torch.float16 else 4) + 20

    truth = np.linalg.norm(queries[:, None, :].astype(np.float64) - stored[None].astype(np.float64), axis=2)
    result = index.search(queries, k=5)
    expected_rows = np.argsort(truth, axis=1)[:, :5]
    np.testing.assert_array_equal(result.frame_ids[:12, 0], targets + 1000)
    np.testing.assert_allclose(result.distances, np.take_along_axis(truth, expected_rows, 1), atol=tol)
    assert np.all(np.diff(result.distances, axis=1) >= 0)

    # exclusion of recent submaps (prefix path) and the distance threshold
    limited = index.search(queries, k=1, max_submap_id=14, max_distance=0.5)
    eligible = submaps <= 14
    best = np.where(eligible[None], truth, np.inf).min(axis=1)
    for q in range(len(queries)):
        if best[q] < 0.5 - tol:
            assert limited.submap_ids[q, 0] <= 14
            assert abs(limited.distances[q, 0] - best[q]) <= tol
        elif best[q] > 0.5 + tol:
            assert limited.frame_ids[q, 0] == -1 and np.isinf(limited.distances[q, 0])
    assert np.sum(limited.frame_ids[:, 0] >= 0) == np.sum(targets < 1500)
    assert index.search(queries, max_submap_id=-1).frame_ids.max() == -1


def test_descriptor_index_unsorted_submaps_use_a_mask() -> None:
    dim = 64
    stored = _unit_rows(40, dim, seed=5)
    index = DescriptorIndex(dim, dtype=torch.float32)
    index.add(stored[:20], np.arange(20), 5)
    index.add(stored[20:], np.arange(20, 40), 1)  # older submap stored later
    result = index.search(stored[[3, 25]], k=1, max_submap_id=2)
    # frame 3 lives in submap 5 (excluded): its match must come from submap 1
    assert result.submap_ids[0, 0] == 1 and result.frame_ids[0, 0] >= 20
    assert result.frame_ids[1, 0] == 25 and result.distances[1, 0] < 1e-3
    full = index.search(stored[[3]], k=50)
    assert (full.frame_ids[0, :40] >= 0).all() and (full.frame_ids[0, 40:] == -1).all()


# ----------------------------------------------------------------------------- retrieval


def test_salad_retrieval_follows_the_query_semantics(tiny_model) -> None:
    config = RetrievalConfig(kind="salad", tau_interval=2, tau_desc=0.8, salad_image_size=224)
    retrieval = SaladRetrieval(config, model=tiny_model)
    assert isinstance(retrieval, Retrieval) and retrieval.name == "salad"
    images = random_images(12, seed=7)
    calls = []
    original_describe = retrieval.describe

    def counting_describe(batch):
        calls.append(len(batch))
        return original_describe(batch)

    retrieval.describe = counting_describe  # type: ignore[method-assign]
    for submap in range(4):  # submaps 0..3, three keyframes each
        frames = [3 * submap + i for i in range(3)]
        assert retrieval.query(as_frames(frames, [images[f] for f in frames]), submap, 1) == [] or submap >= 3
        retrieval.add(as_frames(frames, [images[f] for f in frames]), submap)
    assert calls == [3, 3, 3, 3]  # query's descriptors are reused by add
    np.testing.assert_allclose(
        retrieval.index._vectors[:12].float().numpy(), tiny_model.describe(images, 224), atol=1e-3
    )

    # a revisit of frame 4 (submap 1) from submap 4: eligible submaps are <= 4 - 1 - 2 = 1
    revisit = [images[4].copy(), images[10].copy()]
    found = retrieval.query(as_frames([100, 101], revisit), 4, max_results=5)
    assert found[0].query_frame == 100 and found[0].match_frame == 4 and found[0].match_submap == 1
    assert found[0].distance < 1e-2
    assert all(c.match_submap <= 1 and c.distance < 0.8 for c in found)
    assert [c.distance for c in found] == sorted(c.distance for c in found)
    # frame 10 sits in submap 3, excluded at submap 4, so query 101 cannot match it
    assert all(c.match_frame != 10 for c in found)
    assert len(retrieval.query(as_frames([100, 101], revisit), 4, max_results=1)) == 1
    # from submap 6, submap 3 becomes eligible and frame 10 is found
    later = retrieval.query(as_frames([100, 101], revisit), 6, max_results=2)
    assert {(c.query_frame, c.match_frame) for c in later} == {(100, 4), (101, 10)}
    # a tight threshold rejects everything but the exact revisits
    strict = SaladRetrieval(RetrievalConfig(kind="salad", tau_desc=1e-2), model=tiny_model)
    strict.index = retrieval.index
    assert {(c.query_frame, c.match_frame) for c in strict.query(as_frames([100, 101], revisit), 6, 5)} == {(100, 4), (101, 10)}
    strict.config = RetrievalConfig(kind="salad", tau_desc=0.0)
    assert strict.query(as_frames([100, 101], revisit), 6, 5) == []



def test_a_closed_salad_retrieval_frees_its_index_and_refuses_more(tiny_model) -> None:
    retrieval = SaladRetrieval(RetrievalConfig(kind="salad", tau_interval=0, salad_image_size=224), model=tiny_model)
    images = random_images(6, seed=3)
    retrieval.add(as_frames([0, 1, 2], images[:3]), 0)
    assert len(retrieval.index) == 3
    retrieval.close()
    assert len(retrieval.index) == 0 and retrieval.index._vectors.shape[0] == 1 and retrieval.model is None
    with pytest.raises(RuntimeError, match="closed"):
        retrieval.query(as_frames([9], images[3:4]), 5, max_results=1)
    with pytest.raises(RuntimeError, match="closed"):
        retrieval.add(as_frames([9], images[3:4]), 5)

# ----------------------------------------------------------------------------- full size (slow)


@pytest.mark.slow
def test_full_model_runs_on_cpu_at_322() -> None:
    torch.manual_seed(0)
    model = SaladModel().eval()
    image = random_images(1, seed=11, height=480, width=640)
    with torch.no_grad():
        batch = preprocess_images(image, 322)
        features, cls_token = model.backbone(batch)
        descriptor = model.aggregator(features, cls_token)
    assert features.shape == (1, 768, 23, 23) and cls_token.shape == (1, 768)
    assert descriptor.shape == (1, 8448)
    assert torch.isfinite(descriptor).all()
    torch.testing.assert_close(descriptor.norm(dim=1), torch.ones(1))
    torch.testing.assert_close(descriptor[:, :256].norm(dim=1), torch.full((1,), 65**-0.5))


@pytest.mark.slow
@pytest.mark.parametrize("lightning", [False, True])
def test_salad_retrieval_end_to_end_with_random_checkpoint(tmp_path, lightning) -> None:
    path = write_random_salad_checkpoint(tmp_path / "dino_salad.ckpt", seed=3, lightning=lightning)
    model = load_salad(path, "cpu")
    torch.manual_seed(3)
    reference = SaladModel().state_dict()
    assert all(torch.equal(v, reference[k]) for k, v in model.state_dict().items())

    config = RetrievalConfig(kind="salad", salad_weights=str(path), tau_interval=0)
    retrieval = SaladRetrieval(config)
    assert isinstance(retrieval, SaladRetrieval)
    images = random_images(4, seed=13)
    retrieval.add(as_frames([0, 1], images[:2]), 0)
    retrieval.add(as_frames([2, 3], images[2:]), 1)
    found = retrieval.query(as_frames([50], [images[1]]), 2, max_results=1)
    assert len(found) == 1 and found[0].match_frame == 1 and found[0].distance < 1e-2
    assert retrieval.index._vectors.shape[1] == 8448
