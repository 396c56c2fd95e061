"""The running metric frame: estimated again only once its segment has grown by `running_refresh`."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from sl4slam.metric_frame import MetricFrame, RunningFrame
from sl4slam.upgrade import UpgradeConfig


class _Graph:
    """The few backend reads the running frame makes: submaps 0-99 are segment 0, 100 on segment 1."""

    def __init__(self) -> None:
        self.submap_ids: list[int] = []

    def segment_of(self, submap_id: int) -> int:
        return int(submap_id >= 100)

    def segments_of(self, submap_ids) -> np.ndarray:
        return (np.asarray(submap_ids) >= 100).astype(int)


def _frame(refresh: float) -> tuple[MetricFrame, _Graph, list]:
    graph = _Graph()
    frame = MetricFrame(UpgradeConfig(running_refresh=refresh), graph, upgrade_at_end=True, complete_links=True)
    estimates = []

    def estimate(members):
        estimates.append(len(members))
        return RunningFrame(np.eye(4) * len(estimates), focal=float(len(estimates)))

    frame._estimate_running = estimate
    return frame, graph, estimates


def _grow(graph: _Graph, keyframes: list, submap_id: int, count: int = 16) -> None:
    graph.submap_ids.append(submap_id)
    keyframes.extend(SimpleNamespace(submap_id=submap_id) for _ in range(count))


def test_running_frame_is_estimated_again_after_ten_percent_growth() -> None:
    frame, graph, estimates = _frame(0.1)
    keyframes: list = []
    seen = []
    for submap_id in range(40):
        _grow(graph, keyframes, submap_id)
        first = frame.running(submap_id, keyframes)
        assert frame.running(submap_id, keyframes) is first  # a second link of the same submap: no new read
        seen.append(first.focal)
    # an estimate at n keyframes serves until the segment holds 1.1 n: every submap while a submap
    # (16 keyframes) is a tenth of the segment or more, then ever more rarely
    estimated_at = [k for k in range(40) if k == 0 or seen[k] != seen[k - 1]]
    assert estimated_at[:11] == list(range(11))
    assert estimated_at[11:] == [12, 14, 16, 18, 20, 23, 26, 29, 32, 36]
    assert len(estimates) == len(estimated_at) == 21


def test_zero_refresh_estimates_for_every_link_and_segments_are_separate() -> None:
    frame, graph, estimates = _frame(0.0)
    keyframes: list = []
    _grow(graph, keyframes, 0)
    frame.running(0, keyframes)
    frame.running(0, keyframes)
    assert len(estimates) == 2
    frame, graph, estimates = _frame(0.1)
    keyframes = []
    for submap_id in (0, 1, 100):
        _grow(graph, keyframes, submap_id)
    old, new = frame.running(1, keyframes), frame.running(100, keyframes)
    assert estimates == [32, 16] and old is not new  # each segment its own frame, from its own keyframes
    _grow(graph, keyframes, 101)
    assert frame.running(100, keyframes) is not new and frame.running(1, keyframes) is old


def test_keyframe_submaps_are_read_only_where_the_list_grew() -> None:
    """The ids read for a link are the keyframes' own, whether kept from before (the run's list grew
    at its end) or read again (another list, a shorter one)."""
    frame, graph, _ = _frame(0.1)
    keyframes: list = []
    for submap_id in range(5):
        _grow(graph, keyframes, submap_id, count=3)
        np.testing.assert_array_equal(frame._keyframe_submaps(keyframes), [k.submap_id for k in keyframes])
    kept = frame._submap_ids
    keyframes[0] = SimpleNamespace(submap_id=99)  # the list's old entries are not read again ...
    assert frame._keyframe_submaps(keyframes)[0] == 0 and frame._submap_ids is kept
    other = [SimpleNamespace(submap_id=7) for _ in range(4)]  # ... but another list's are
    np.testing.assert_array_equal(frame._keyframe_submaps(other), [7, 7, 7, 7])
    np.testing.assert_array_equal(frame._keyframe_submaps(other[:2]), [7, 7])
    np.testing.assert_array_equal(frame._keyframe_submaps(keyframes), [99] + [k.submap_id for k in keyframes[1:]])
