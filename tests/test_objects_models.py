"""The models of the object queries: PE-Core (our torch code) against the reference implementation on
a tiny random configuration, its key map on the full-size layout, its tokenizer, loading through the
weights code (offline, corrupt and foreign files in one line), SAM 3 through ``transformers`` on a tiny
random configuration, the catalogue, and ``--objects`` in a run."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from sl4slam.errors import MissingWeightsError, UserError
from sl4slam.models.checkpoint import WeightsFileError
from sl4slam.objects.embedder import (PE_CORE_PARAMETERS, KeyframeEmbedder, PECoreEmbedder, load_pe_core,
                                      make_embedder)
from sl4slam.objects.interfaces import ImageEmbedder, Mask2D, TextSegmenter
from sl4slam.objects.pe_core import (CLIP_MERGES, PE_CORE_L14_336, PE_CORE_TINY, ClipTokenizer, PECore,
                                     is_pe_core_checkpoint, ours_to_published, preprocess_images, published_to_ours)

FIXTURE = Path(__file__).parent / "fixtures" / "pe_core_tiny" / "reference.safetensors"


@pytest.fixture(scope="module")
def reference() -> dict:
    from safetensors.torch import load_file

    return load_file(str(FIXTURE))


def _reference_state(reference: dict) -> dict:
    return {k[len("ref."):]: v for k, v in reference.items() if k.startswith("ref.")}


@pytest.fixture
def offline(monkeypatch, tmp_path):
    """No hub: downloads off and an empty cache."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub_cache"))
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf_home"))
    import huggingface_hub.constants as constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "hub_cache"))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)


# ------------------------------------------------------------------------------------ PE-Core parity
def test_pe_core_matches_the_reference_code_on_a_tiny_random_model(reference) -> None:
    model = PECore(PE_CORE_TINY).eval()
    model.load_state_dict(published_to_ours(_reference_state(reference)), strict=True)
    with torch.no_grad():
        images = model.encode_images(reference["images"])
        other_grid = model.encode_images(reference["images_other"])  # 5x3 patches: interpolated positions
        texts = model.encode_texts(reference["tokens"])
    torch.testing.assert_close(images, reference["image_embeddings"], atol=1e-5, rtol=0)
    torch.testing.assert_close(other_grid, reference["image_embeddings_other"], atol=1e-5, rtol=0)
    torch.testing.assert_close(texts, reference["text_embeddings"], atol=1e-5, rtol=0)
    # the embeddings are not trivially alike: the comparison can fail
    assert float((images[0] - images[1]).abs().max()) > 0.05


def test_the_key_map_is_a_bijection_onto_the_published_layout(reference) -> None:
    published = _reference_state(reference)
    assert is_pe_core_checkpoint(published)
    ours = published_to_ours(published)
    assert set(ours) == set(PECore(PE_CORE_TINY).state_dict())
    assert set(ours_to_published(ours)) == set(published)
    # "module." prefixes (a DDP save) are dropped
    assert set(published_to_ours({"module." + k: v for k, v in published.items()})) == set(ours)
    # the full-size model's keys follow the same templates, and every one maps both ways
    with torch.device("meta"):
        full = PECore(PE_CORE_L14_336)
    full_keys = set(full.state_dict())
    full_published = set(ours_to_published(dict.fromkeys(full_keys)))
    template = lambda keys: {re.sub(r"\.\d+\.", ".N.", k) for k in keys}  # noqa: E731
    assert template(full_published) == template(published)
    assert set(published_to_ours(dict.fromkeys(full_published))) == full_keys
    assert sum(1 for k in full_published if k.startswith("visual.transformer.resblocks.") and k.endswith("ln_1.weight")) == 24
    assert sum(p.numel() for p in full.parameters()) == PE_CORE_PARAMETERS
    assert full.vision.pos_embed.shape == (1 + 24 * 24, 1024) and full.text.pos_embed.shape == (32, 1024)


def test_unknown_keys_stay_unexpected_in_a_strict_load(reference, tmp_path) -> None:
    state = _reference_state(reference)
    state["visual.some_new_head.weight"] = torch.zeros(2)
    path = tmp_path / "extra.pt"
    torch.save({"state_dict": state}, path)
    with pytest.raises(UserError, match=r"1 unexpected keys \['visual.some_new_head.weight'\]"):
        load_pe_core(str(path), config=PE_CORE_TINY)


# --------------------------------------------------------------------------------- loading weights
def test_a_published_checkpoint_loads_through_the_weights_code(reference, tmp_path) -> None:
    path = tmp_path / "PE-Core-tiny.pt"
    torch.save({"weights": {"module." + k: v for k, v in _reference_state(reference).items()}}, path)
    model = load_pe_core(str(path), config=PE_CORE_TINY)
    assert not any(p.requires_grad for p in model.parameters()) and not model.training
    with torch.no_grad():
        torch.testing.assert_close(model.encode_images(reference["images"]), reference["image_embeddings"],
                                   atol=1e-5, rtol=0)


def test_bad_weights_end_in_one_line(tmp_path, offline) -> None:
    cut = tmp_path / "cut.pt"
    cut.write_bytes(b"PK\x03\x04" + b"\0" * 100)
    page = tmp_path / "page.pt"
    page.write_bytes(b"<!DOCTYPE html><html>rate limited</html>")
    cases = [(str(cut), WeightsFileError, "cut short"), (str(page), WeightsFileError, "web page"),
             (str(tmp_path / "absent.pt"), MissingWeightsError, "not found"),
             ("facebook/PE-Core-L14-336", MissingWeightsError, "HF_HUB_OFFLINE")]
    for weights, kind, words in cases:
        with pytest.raises(kind) as caught:
            make_embedder("pe-core-l14-336", weights=weights)
        message = str(caught.value)
        assert words in message and "\n" not in message, message
    with pytest.raises(MissingWeightsError, match="--objects-weights PATH"):
        make_embedder("pe-core-l14-336")
    foreign = tmp_path / "foreign.pt"
    torch.save({"model": {"aggregator.camera_token": torch.zeros(1)}}, foreign)
    with pytest.raises(UserError, match="missing keys") as caught:
        load_pe_core(str(foreign), config=PE_CORE_TINY)
    assert "\n" not in str(caught.value)


def test_the_tokenizer_merges_missing_offline_is_one_line(reference, tmp_path, offline) -> None:
    path = tmp_path / "tiny.pt"
    torch.save(_reference_state(reference), path)
    import sl4slam.objects.embedder as embedder

    with pytest.raises(MissingWeightsError, match="CLIP tokenizer merges .*--objects-tokenizer PATH") as caught:
        embedder.fetch_hub_file(*embedder.CLIP_MERGES, what="CLIP tokenizer merges", flag="--objects-tokenizer")
    assert "\n" not in str(caught.value)
    short = tmp_path / "merges.txt"
    short.write_text("#version: 0.2\nt h\nth e</w>\n")
    with pytest.raises(ValueError, match=f"2 merges, not CLIP's {CLIP_MERGES}"):
        ClipTokenizer.from_merges_file(short, 32)


# -------------------------------------------------------------------------------------- tokenizer
def test_the_byte_pair_tokenizer() -> None:
    words = ClipTokenizer([("t", "h"), ("th", "e</w>"), ("m", "u"), ("mu", "g</w>")], context_length=8)
    assert words.vocab_size == 514 + 4
    ids = words(["The MUG", "the &amp;"])[0].tolist()
    sot, eot = words.sot, words.eot
    assert ids == [sot, words.encoder["the</w>"], words.encoder["mug</w>"], eot, 0, 0, 0, 0]
    assert words.encode("the &amp;") == [words.encoder["the</w>"], words.encoder["&</w>"]]
    long = words(["a " * 20])[0].tolist()
    assert len(long) == 8 and long[0] == sot and long[-1] == eot  # cut, the end token kept last
    # the CLIP vocabulary order: printable bytes first ("!" is 0, "a</w>" is 256 + 64)
    assert words.encoder["!"] == 0 and words.encoder["a</w>"] == 320


def test_the_tokenizer_matches_the_reference_ids_when_the_clip_merges_are_here(reference) -> None:
    from huggingface_hub import try_to_load_from_cache

    from sl4slam.objects.embedder import CLIP_MERGES as SOURCE

    found = try_to_load_from_cache(*SOURCE)
    if not isinstance(found, str):
        pytest.skip("the CLIP merges are not in the Hugging Face cache")
    from safetensors import safe_open

    with safe_open(str(FIXTURE), "pt") as handle:
        texts = json.loads(handle.metadata()["texts"])
    words = ClipTokenizer.from_merges_file(found, 16)
    assert torch.equal(words(texts), reference["clip_tokens"])


# ------------------------------------------------------------------------------------ the embedder
def test_the_tiny_random_embedder() -> None:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), rng.integers(0, 256, (30, 20, 3), dtype=np.uint8),
              np.zeros((56, 56, 3), np.uint8)]
    first = make_embedder("tiny-random")
    assert isinstance(first, ImageEmbedder) and first.name == "tiny-random" and first.dim == 16
    vectors = first.embed_images(images)
    texts = first.embed_texts(["red mug", "a chair", "red mug"])
    assert vectors.shape == (3, 16) and texts.shape == (3, 16)
    assert vectors.dtype == np.float32 and texts.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(texts, axis=1), 1, atol=1e-5)
    assert np.abs(vectors[0] - vectors[1]).max() > 1e-3 and np.abs(texts[0] - texts[1]).max() > 1e-3
    np.testing.assert_array_equal(texts[0], texts[2])
    second = make_embedder("tiny-random", batch=1)  # seeded: a query embeds its text as the run did
    np.testing.assert_allclose(second.embed_images(images), vectors, atol=1e-5)
    np.testing.assert_allclose(second.embed_texts(["red mug"]), texts[:1], atol=1e-6)
    assert first.embed_texts([]).shape == (0, 16)
    with pytest.raises(UserError, match="must be one of pe-core-l14-336, tiny-random"):
        make_embedder("clip")


def test_preprocessing_squashes_to_the_square_in_minus_one_to_one() -> None:
    image = np.zeros((20, 40, 3), np.uint8)
    image[:, :20] = 255
    pixels = preprocess_images([image], 28)
    assert pixels.shape == (1, 3, 28, 28) and pixels.dtype == torch.float32
    assert float(pixels[0, :, :, :10].min()) == 1.0 and float(pixels[0, :, :, -10:].max()) == -1.0
    with pytest.raises(ValueError, match="uint8 RGB"):
        preprocess_images([np.zeros((4, 4), np.uint8)], 28)


def test_the_keyframe_embedder_collects_and_writes(tmp_path) -> None:
    from sl4slam.objects.store import read_embeddings

    collector = KeyframeEmbedder(make_embedder("tiny-random"))
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for _ in range(3)]
    collector.add([7, 3], images[:2])
    collector.add([], [])
    collector.add([3, 11], [images[1], images[2]])  # a frame again replaces its row
    assert len(collector) == 3 and collector.write(tmp_path / "empty", keep=[99]) is None
    record = collector.record(tmp_path)
    assert record["model"] == "tiny-random" and record["keyframes"] == 3 and record["dim"] == 16
    stored = read_embeddings(tmp_path)
    assert stored.frame_index.tolist() == [3, 7, 11] and stored.model == "tiny-random"
    expected = collector.embedder.embed_images(images)
    np.testing.assert_allclose(stored.embeddings, expected[[1, 0, 2]], atol=2e-3)


# ------------------------------------------------------------------------------------------ SAM 3
@pytest.fixture(scope="module")
def tiny_segmenter():
    transformers = pytest.importorskip("transformers")
    if not hasattr(transformers, "Sam3Model"):
        pytest.skip("this transformers has no Sam3Model")
    from sl4slam.objects.sam3 import make_segmenter

    return make_segmenter(config="tiny")


def test_sam3_segments_with_a_tiny_random_config(tiny_segmenter) -> None:
    assert isinstance(tiny_segmenter, TextSegmenter)
    image = np.random.default_rng(2).integers(0, 256, (64, 48, 3), dtype=np.uint8)
    found = tiny_segmenter.segment(image, "red mug", threshold=0.0)
    assert len(found) == 8  # every query of the tiny config passes threshold 0
    for instance in found:
        assert isinstance(instance, Mask2D)
        assert instance.mask.shape == (64, 48) and instance.mask.dtype == bool
        assert 0.0 <= instance.score <= 1.0
    scores = [m.score for m in found]
    assert scores == sorted(scores, reverse=True)
    assert tiny_segmenter.segment(image, "red mug", threshold=1.0) == []
    again = tiny_segmenter.segment(image, "red mug", threshold=0.0)
    assert [m.score for m in again] == scores and all(np.array_equal(a.mask, b.mask) for a, b in zip(again, found))
    pixels = tiny_segmenter.pixels(image)
    assert tuple(pixels.shape) == (1, 3, 56, 56) and -1.0 <= float(pixels.min()) and float(pixels.max()) <= 1.0


def test_sam3_weights_missing_offline_are_one_line(tiny_segmenter, offline, tmp_path) -> None:
    from sl4slam.objects.sam3 import make_segmenter

    with pytest.raises(MissingWeightsError, match="HF_HUB_OFFLINE.*SAM License") as caught:
        make_segmenter()
    assert "\n" not in str(caught.value)
    empty = tmp_path / "sam3_snapshot"
    empty.mkdir()
    with pytest.raises(UserError, match="cannot be loaded") as caught:
        make_segmenter(weights=str(empty))
    assert "\n" not in str(caught.value)


# ------------------------------------------------------------------------------ catalogue and runs
def test_sl4slam_models_lists_both_with_their_licences(capsys, monkeypatch) -> None:
    import sl4slam.registry as registry
    from sl4slam.cli import main
    from sl4slam.registry import object_model_entries

    monkeypatch.setattr(registry, "frontend_entries", lambda: [])  # the frontends' own lines: tests/test_registry.py

    entries = {e.name: e for e in object_model_entries()}
    assert entries["pe-core-l14-336"].licence == "Apache-2.0" and entries["sam3"].licence == "SAM License"
    assert entries["pe-core-l14-336"].weights.repo_id == "facebook/PE-Core-L14-336"
    assert entries["sam3"].weights.repo_id == "facebook/sam3"
    assert main(["models"]) == 0
    lines = capsys.readouterr().out.splitlines()
    pe = next(line for line in lines if line.startswith("pe-core-l14-336"))
    sam = next(line for line in lines if line.startswith("sam3"))
    assert "671.1 M" in pe and "Apache-2.0" in pe and "SAM License" in sam and "840.4 M" in sam


def test_the_objects_settings_and_flags() -> None:
    from sl4slam.cli import build_parser, config_from_args
    from sl4slam.config import SLAMConfig

    assert SLAMConfig().objects.enabled is False
    args = build_parser().parse_args(["run", "src", "--out", "o", "--objects", "--objects-embedder", "tiny-random",
                                      "--objects-batch", "2"])
    config = config_from_args(args)
    assert config.objects.enabled and config.objects.embedder == "tiny-random" and config.objects.batch == 2
    config.validate()
    config.objects.batch = 0
    with pytest.raises(UserError, match=r"--objects-batch \(config key objects.batch\) must be at least 1"):
        config.validate()
    config.objects.batch, config.objects.embedder = 1, "clip"
    with pytest.raises(UserError, match="--objects-embedder"):
        config.validate()


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    from sl4slam.synthetic import write_synthetic_sequence

    return write_synthetic_sequence(tmp_path_factory.mktemp("objects") / "world", num_frames=60, width=64, height=48,
                                    seed=2)


def _sim_config():
    from sl4slam.config import SLAMConfig

    config = SLAMConfig(frontend="simulated")
    config.keyframes.tau_disparity = 15.0
    config.submap.size = 6
    config.retrieval.kind = "none"
    return config


def test_a_run_with_objects_writes_one_embedding_per_keyframe(world, tmp_path) -> None:
    from sl4slam.objects.store import read_embeddings
    from sl4slam.runner import run_slam

    plain = run_slam(world, tmp_path / "plain", _sim_config(), progress=False)
    assert not (tmp_path / "plain" / "objects").exists() and "objects" not in plain
    config = _sim_config()
    config.objects.enabled, config.objects.embedder = True, "tiny-random"
    summary = run_slam(world, tmp_path / "objects", config, progress=False)
    stored = read_embeddings(tmp_path / "objects")
    keyframes = sorted(int(p.stem) for p in (tmp_path / "objects" / "keyframes").glob("*.npz"))
    assert stored.frame_index.tolist() == keyframes and stored.model == "tiny-random" and stored.dim == 16
    assert summary["objects"]["keyframes"] == len(keyframes) == summary["counts"]["keyframes"]
    # the map does not depend on the embeddings
    for name in ("trajectory.txt", "map.ply"):
        assert (tmp_path / "plain" / name).read_bytes() == (tmp_path / "objects" / name).read_bytes()


def test_a_library_run_takes_an_injected_embedder(world) -> None:
    from sl4slam.io import open_source
    from sl4slam.pipeline import SLAMPipeline

    class Counting:
        name, dim = "counting", 3

        def __init__(self) -> None:
            self.batches: list[int] = []

        def embed_images(self, images):
            self.batches.append(len(images))
            return np.tile(np.eye(3, dtype=np.float32)[:1], (len(images), 1))

        def embed_texts(self, texts):
            return np.zeros((len(texts), 3), np.float32)

    embedder = Counting()
    config = _sim_config()
    pipeline = SLAMPipeline.from_config(config, objects=KeyframeEmbedder(embedder))
    result = pipeline.run(open_source(str(world), config.source), progress=False)
    assert sum(embedder.batches) == len(result.keyframes) == len(pipeline.objects)
    assert len(embedder.batches) > 1  # one batch per submap


def test_embedder_types() -> None:
    assert isinstance(make_embedder("tiny-random"), PECoreEmbedder)


def test_a_run_with_objects_and_no_weights_offline_stops_in_one_line(world, tmp_path, offline) -> None:
    from sl4slam.runner import run_slam

    config = _sim_config()
    config.objects.enabled = True
    with pytest.raises(MissingWeightsError, match="PE-Core-L14-336 weights .*--objects-weights PATH") as caught:
        run_slam(world, tmp_path / "out", config, progress=False)
    assert "\n" not in str(caught.value) and not (tmp_path / "out").exists()


def test_tiny_random_models_answer_a_query_end_to_end(world, tmp_path, tiny_segmenter, monkeypatch) -> None:
    """The real code paths, offline: a run embeds its keyframes with the tiny random PE-Core, and
    ``sl4slam query`` answers with it and the tiny random SAM 3 (any answer: the weights are random)."""
    import sl4slam.cli as cli
    from sl4slam.objects.embedder import make_embedder
    from sl4slam.runner import run_slam

    config = _sim_config()
    config.objects.enabled, config.objects.embedder = True, "tiny-random"
    run_slam(world, tmp_path / "run", config, progress=False)
    monkeypatch.setattr(cli, "query_models", lambda name: (make_embedder(name), tiny_segmenter))
    answer_file = tmp_path / "answer.json"
    assert cli.main(["query", str(tmp_path / "run"), "red mug", "--top-k", "2", "--threshold", "0",
                     "--json", str(answer_file)]) == 0
    answer = json.loads(answer_file.read_text())
    keyframes = {int(p.stem) for p in (tmp_path / "run" / "keyframes").glob("*.npz")}
    assert answer["query"] == "red mug" and answer["embedder"] == "tiny-random" and len(answer["keyframes"]) == 2
    assert {k["frame_index"] for k in answer["keyframes"]} <= keyframes
    assert sum(k["masks"] for k in answer["keyframes"]) > 0  # threshold 0: the tiny SAM 3 returns masks
    for instance in answer["instances"]:
        assert np.all(np.isfinite(instance["centre"])) and np.all(np.asarray(instance["extents"]) >= 0)
        assert {v["frame_index"] for v in instance["views"]} <= keyframes
