"""The CPU estimate a run prints before it starts (``sl4slam.frontend.cost``)."""

from __future__ import annotations

import dataclasses
import io
import re

import pytest

from sl4slam.config import SLAMConfig
from sl4slam.frontend.cost import (
    FRAMES_PER_KEYFRAME,
    estimate,
    expected_submaps,
    format_duration,
    matmul_rate,
)
from sl4slam.registry import frontend_entries, frontend_entry
from sl4slam.resolve import resolve
from sl4slam.runner import say_cpu_cost


def test_estimate_scales_work_by_frames_and_speed():
    found = estimate("big", 1000.0, window_frames=18, rate=100.0, source_frames=700, submap_size=16,
                     others=[("big", 1000.0), ("small", 50.0), ("medium", 300.0), ("close", 400.0)])
    assert found.seconds_per_submap == pytest.approx(1000.0 * 18 / 100.0)
    assert found.submaps == expected_submaps(700, 16) == 13  # 700 / 3.5 = 200 keyframes, 16 per submap
    assert found.total_seconds == pytest.approx(found.seconds_per_submap * 13)
    assert [name for name, _ in found.faster] == ["small", "medium"]  # 3x faster or more, fastest first
    assert found.faster[0][1] == pytest.approx(50.0 * 18 / 100.0)
    line = found.line()
    assert "big needs about 3 min per 18-frame submap" in line and "700 frames" in line and "--model small" in line
    assert "\n" not in line
    live = estimate("big", 1000.0, 18, 100.0, None, 16)
    assert live.total_seconds is None and live.submaps is None and "frames of this source" not in live.line()
    assert estimate("small", 50.0, 18, 100.0, 10, 16, others=[("big", 1000.0)]).faster == ()


def test_durations_read_well():
    assert [format_duration(s) for s in (12.4, 89, 95, 1043, 5399, 5400, 11520)] == [
        "12 s", "89 s", "2 min", "17 min", "90 min", "1.5 h", "3.2 h"]
    assert expected_submaps(1, 16) == 1 and FRAMES_PER_KEYFRAME > 1


def test_matmul_rate_is_a_positive_speed():
    assert 0.1 < matmul_rate(repeats=1) < 1e6


def test_every_model_states_its_work_and_the_simulator_none():
    entries = {entry.name: entry for entry in frontend_entries()}
    models = [name for name, entry in entries.items() if entry.weights is not None]
    assert {"vggt", "da3-small", "pi3x"} <= set(models)
    assert all(entries[name].cpu_work and entries[name].cpu_work > 0 for name in models)
    assert entries["simulated"].cpu_work is None
    assert entries["da3-small"].cpu_work * 10 < entries["vggt"].cpu_work  # the smallest model is far cheaper


def test_the_run_says_the_cost_of_a_model_on_the_cpu_only():
    resolved = resolve(SLAMConfig(frontend="vggt", device="cpu"))
    stream = io.StringIO()
    say_cpu_cost(resolved, 613, stream=stream)
    line = stream.getvalue()
    assert len(line.splitlines()) == 1
    assert re.search(r"vggt needs about \d+ (s|min|h) per 18-frame submap", line), line
    assert "613 frames" in line and "--model da3-small" in line and "--quiet" in line
    for other in (dataclasses.replace(resolved, device="cuda"),
                  resolve(SLAMConfig(frontend="simulated", device="cpu"))):
        quiet = io.StringIO()
        say_cpu_cost(other, 613, stream=quiet)
        assert quiet.getvalue() == ""
    assert frontend_entry("da3-small").cpu_work is not None
