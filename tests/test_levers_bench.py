"""The levers benchmark's suite report: a variant held against the better of the two graph designs."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def levers():
    """``benchmarks/bench_levers.py`` loaded as a module by its path (its ``harness`` beside it); the
    environment it sets defaults in is put back afterwards."""
    environment = dict(os.environ)
    sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location("bench_levers_under_test", BENCHMARKS / "bench_levers.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)
        sys.path.remove(str(BENCHMARKS))
        os.environ.clear()
        os.environ.update(environment)


def _row(sequence: str, variant: str, seed: int, ate: float | None, split: str = "tune") -> dict:
    return {"sequence": sequence, "length": 600, "split": split, "profile": "strong", "variant": variant, "seed": seed,
            "ate": ate}


def test_each_seed_is_held_against_the_lower_of_the_two_designs(levers):
    runs = [_row("a", "baseline", 0, 0.050), _row("a", "submap", 0, 0.002), _row("a", "defaults", 0, 0.003),
            _row("a", "baseline", 1, 0.004), _row("a", "submap", 1, 0.008), _row("a", "defaults", 1, 0.002),
            _row("a", "submap", 2, 0.001), _row("a", "defaults", 2, 0.004),  # no baseline run: the submap graph
            _row("a", "defaults", 3, 0.001),  # no design run on this seed: left out
            _row("a", "defaults", 4, None), _row("a", "submap", 4, 0.001),  # a failed run: left out
            _row("a", "defaults", 0, 0.001) | {"profile": "vggt"}]  # another profile
    ratios = levers.better_graph_ratios(runs, "strong", "defaults")
    assert list(ratios) == [("a", 600)]
    assert ratios[("a", 600)] == pytest.approx([1.5, 0.5, 4.0])


def test_errors_below_a_micrometre_count_as_equal(levers):
    runs = [_row("one-submap", "submap", 0, 2e-14), _row("one-submap", "defaults", 0, 7e-14),
            _row("one-submap", "submap", 1, 2e-14), _row("one-submap", "defaults", 1, 3e-6)]
    assert levers.better_graph_ratios(runs, "strong", "defaults")[("one-submap", 600)] == pytest.approx([1.0, 1.5e8])


def test_the_table_counts_the_sequences_within_one_and_a_half_times(levers):
    runs = []
    for sequence, ratio, split in (("a", 1.2, "tune"), ("b", 1.6, "tune"), ("c", 0.5, "tune"), ("d", 3.0, "validate")):
        for seed in (0, 1):
            runs += [_row(sequence, "submap", seed, 0.01, split), _row(sequence, "defaults", seed, 0.01 * ratio, split)]
    lines = levers._better_graph_table(runs, "strong", [("a", 600), ("b", 600), ("c", 600), ("d", 600)])
    text = "\n".join(lines)
    assert "| a | tune | 600 | 1.20 (2) |" in text and "| b | tune | 600 | 1.60 (2) |" in text
    assert "| **tune: within 1.5x** | tune |  | 2/3 |" in text
    assert "| **tune: worst** | tune |  | 1.60 |" in text and "| **tune: median** | tune |  | 1.20 |" in text
    assert "| **validate: within 1.5x** | validate |  | 0/1 |" in text
    assert levers._better_graph_table([r for r in runs if r["variant"] != "submap"], "strong", [("a", 600)]) == []
