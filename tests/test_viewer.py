"""The viewer: reading result folders (both formats), the live viewer's redraw logic against exact
world points, the point budget, the server's port and host handling, and the page in a real
headless browser."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from browser import DRAWN, HANG_S, chromium_path, drawn_fraction, first_drawn, first_drawn_text, interrupt, launch
from result_folders import write_known_result
from sl4slam.backend import WorldEstimate
from sl4slam.errors import UserError
from sl4slam.result.outputs import keyframe_world_points
from sl4slam.result.reading import load_result
from sl4slam.submap import StoredKeyframe
from sl4slam.viewer.scene import (
    MapState,
    ViewerSettings,
    auto_point_size,
    confidence_threshold,
    frustum_indices,
    frustum_scale,
    make_cloud,
    map_spacing,
    median_spacing,
)

# ----------------------------------------------------------------------------- result folders
def test_version_1_folder_loops_come_from_the_summary(tmp_path: Path) -> None:
    truth = write_known_result(tmp_path / "r", count=9, submap_size=3, loops=[{"submaps": [0, 2], "frame": 3}])
    result = load_result(tmp_path / "r")
    assert result.version == 1 and result.gt is None and len(result.keyframes) == 9
    assert [(e.kind, e.submaps, e.frame) for e in result.edges] == [("loop", (0, 2), 3)]
    segments = result.loop_segments()
    assert segments.shape == (1, 2, 3)
    # one end is frame 3's keyframe in submap 0, the other the nearest keyframe of submap 2
    np.testing.assert_allclose(segments[0, 0], truth["T_world_cam"][1, :3, 3])
    centres = truth["T_world_cam"][6:9, :3, 3]
    nearest = centres[np.argmin(np.linalg.norm(centres - segments[0, 0], axis=1))]
    np.testing.assert_allclose(segments[0, 1], nearest)


def test_version_2_folder_has_edges_and_ground_truth(tmp_path: Path) -> None:
    truth = write_known_result(tmp_path / "r", count=6, version=2, confidence=True, loops=[{"submaps": [0, 1], "frame": 0}])
    result = load_result(tmp_path / "r")
    assert result.version == 2 and result.gt is not None
    np.testing.assert_allclose(result.gt[1], truth["T_world_cam"], atol=1e-8)
    assert result.keyframes[0].load().confidence.dtype == np.float32


def test_not_a_result_folder_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "x").mkdir()
    with pytest.raises(UserError, match="not an sl4slam result folder"):
        load_result(tmp_path / "x")
    write_known_result(tmp_path / "y")
    summary = json.loads((tmp_path / "y" / "summary.json").read_text())
    (tmp_path / "y" / "summary.json").write_text(json.dumps({**summary, "format": {"name": "other", "version": 1}}))
    with pytest.raises(UserError, match="not an sl4slam result"):
        load_result(tmp_path / "y")


# ----------------------------------------------------------------------------- scene shaping
def test_cloud_decimation_is_a_uniform_truncation() -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(10000, 3))
    cloud = make_cloud(3, points, rng.integers(0, 255, (10000, 3), dtype=np.uint8), None, fraction=0.5, seed=1)
    assert len(cloud) == 5000 and cloud.full_count == 10000
    kept = cloud.offsets.astype(np.float64) + cloud.centre
    from scipy.spatial import cKDTree

    distance, nearest = cKDTree(points).query(kept)
    assert distance.max() < 1e-5 and len(np.unique(nearest)) == 5000  # a subset, no point twice
    cloud.truncate(0.25)
    assert len(cloud) == 2500
    np.testing.assert_allclose(cloud.offsets.mean(0) + cloud.centre, points.mean(0), atol=0.1)  # still spread out


def test_confidence_threshold_is_a_percentile_of_the_shown_points() -> None:
    clouds = [make_cloud(i, np.zeros((100, 3)), np.zeros((100, 3), np.uint8), np.arange(100) + 100 * i, 1.0)
              for i in range(2)]
    assert confidence_threshold(clouds, 0) == -np.inf
    assert confidence_threshold(clouds, 50) == pytest.approx(99.5)
    assert sum(int((c.confidence >= confidence_threshold(clouds, 25)).sum()) for c in clouds) == 150


def _plane(step: float, n: int, seed: int = 0) -> np.ndarray:
    """An ``n x n`` grid ``step`` apart on a tilted plane, in random order."""
    u, v = np.meshgrid(np.arange(n) * step, np.arange(n) * step)
    R = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))[0]
    return (np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], axis=1) @ R.T)[np.random.default_rng(seed).permutation(n * n)]


def test_point_spacing_is_the_median_nearest_neighbour_distance() -> None:
    grid = _plane(0.01, 200)
    assert median_spacing(grid) == pytest.approx(0.01, rel=1e-6)
    # isolated outliers (flying pixels) and duplicated points do not move it
    rng = np.random.default_rng(1)
    noisy = np.concatenate([grid, rng.uniform(-50, 50, (400, 3)), grid[:2000]])
    assert median_spacing(noisy) == pytest.approx(0.01, rel=1e-6)
    assert median_spacing(np.zeros((5, 3))) is None and median_spacing(np.zeros((1, 3))) is None
    # a surface sampled at random (a decimated map): the median of the Poisson process, sqrt(ln 2 / (pi rho))
    points = np.c_[rng.uniform(0, 4, (400_000, 2)), np.zeros(400_000)]
    expected = np.sqrt(np.log(2) / (np.pi * 400_000 / 16))
    assert median_spacing(points) == pytest.approx(expected, rel=0.05)
    # measured on a uniform sample of the map and scaled back (surfaces: sqrt of the thinning)
    clouds = [make_cloud(i, points[i::4], np.zeros((100_000, 3), np.uint8), None, 1.0, seed=2) for i in range(4)]
    assert map_spacing(clouds, sample=40_000) == pytest.approx(expected, rel=0.05)
    assert map_spacing([]) is None


def test_default_point_size_follows_the_map_spacing() -> None:
    """viser draws a square of side 2 * point_size: 1.5 spacings makes neighbouring squares overlap."""
    assert auto_point_size(0.02, fallback=1.0) == pytest.approx(0.03)
    assert auto_point_size(None, fallback=0.5) == 0.5 and auto_point_size(0.0, fallback=0.5) == 0.5
    # scale-free: the same map in millimetres gets 1000x larger points
    grid = _plane(0.01, 100)
    in_mm = auto_point_size(median_spacing(grid * 1000), 1.0)
    assert in_mm == pytest.approx(1000 * auto_point_size(median_spacing(grid), 1.0))


def test_frustums_are_spread_along_the_trajectory() -> None:
    line = np.c_[np.linspace(0, 17.2, 173), np.zeros(173), np.zeros(173)]
    picked = frustum_indices(line, 24)
    assert len(picked) == 24 and picked[0] == 0 and picked[-1] == 172 and np.all(np.diff(picked) > 0)
    assert np.ptp(np.diff(picked)) <= 1  # evenly spread: steps of 7 or 8 keyframes
    np.testing.assert_array_equal(frustum_indices(line[:10], 24), np.arange(10))
    # 100 keyframes turning on the spot, then 73 along 10 m: both parts keep frustums
    still = np.r_[np.zeros((100, 3)), np.c_[np.linspace(0.1, 10, 73), np.zeros(73), np.zeros(73)]]
    picked = frustum_indices(still, 24)
    assert 4 <= np.count_nonzero(picked < 100) <= 20 and picked[0] == 0 and picked[-1] == 172


def test_frustums_are_sized_to_the_map() -> None:
    far_apart = np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]
    assert frustum_scale(4.0, far_apart) == pytest.approx(0.1)  # 2.5 % of the map's radius
    close = far_apart * 0.05  # cameras 5 cm apart: as small as their spacing ...
    assert frustum_scale(4.0, close) == pytest.approx(0.05)
    assert frustum_scale(4.0, close * 0.01) == pytest.approx(0.04)  # ... but not below 1 % of the radius
    assert frustum_scale(4.0, far_apart[:1]) == pytest.approx(0.1)


def test_viewer_defaults_follow_the_map(tmp_path: Path) -> None:
    """A served result: the point size comes from the map's spacing, at most ``max_frustums``
    frustums unless "All frustums" is ticked."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import io

    from sl4slam.viewer import view_result

    write_known_result(tmp_path / "room", count=30, width=32, height=24, submap_size=8, scene="room")
    viewer = view_result(tmp_path / "room", ViewerSettings(port=_free_port(), max_frustums=12), block=False,
                         stream=io.StringIO())
    try:
        assert viewer.loader.wait(HANG_S) and viewer.loader.complete  # the bound only catches a hang
        spacing = map_spacing(viewer.state.clouds.values())
        assert spacing is not None and viewer._size() == pytest.approx(auto_point_size(spacing, 1.0))
        assert all(h.point_size == pytest.approx(viewer._size()) for h in viewer._clouds.values())
        assert len(viewer._frustums) == 12
        viewer.gui_all_frustums.value = True
        viewer.draw_frustums()
        assert len(viewer._frustums) == 30
        viewer.gui_size.value = 2.0
        viewer._apply_point_size()
        assert all(h.point_size == pytest.approx(2 * auto_point_size(spacing, 1.0)) for h in viewer._clouds.values())
    finally:
        viewer.close()


# ----------------------------------------------------------------------------- live viewer logic
class FakeMapViewer:
    """Stands in for the viser server: records what would be sent."""

    def __init__(self, settings: ViewerSettings) -> None:
        import threading

        self.settings, self.state, self.lock = settings, MapState(), threading.RLock()
        self.cloud_draws: list = []
        self.port = 0

    def draw_clouds(self, submap_ids=None):
        self.cloud_draws.append(None if submap_ids is None else sorted(submap_ids))

    def draw_lines(self):
        pass

    def draw_frustums(self, thumbnails_for=()):
        pass

    def set_summary(self, markdown):
        self.summary = markdown

    def apply_follow(self, newest=False):
        pass

    def set_up_direction(self):
        pass

    def frame_map(self):
        pass

    def close(self):
        pass


def _keyframes(count_per_submap: int = 2, submaps: int = 3, size=(24, 32)):
    rng = np.random.default_rng(0)
    keyframes = []
    K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    for s in range(submaps):
        for j in range(count_per_submap):
            T = np.eye(4)
            T[:3, 3] = [0.1 * j, 0.0, 0.0]
            mask = rng.random(size) > 0.3
            keyframes.append(StoredKeyframe(frame_index=10 * s + j, timestamp=float(10 * s + j), submap_id=s, slot=j + 1,
                                            depth=rng.uniform(1, 2, size).astype(np.float16), mask_bits=np.packbits(mask),
                                            confidence_rank=rng.integers(0, 255, (12, 16), dtype=np.uint8), K=K,
                                            T_cam_submap=T, principal_point=K[:2, 2].copy()))
    return keyframes


def _pipeline(keyframes, estimates, edges=()):
    """What the live viewer reads of a running pipeline (colours are re-read through ``colors``)."""
    backend = SimpleNamespace(estimates=lambda: estimates, world_estimate=lambda: WorldEstimate(dict(estimates)))
    return SimpleNamespace(keyframes=keyframes, backend=backend, edges=list(edges),
                           num_frames=100, colors=lambda k: np.full(k.shape + (3,), k.frame_index, np.uint8))


def _world_points(keyframes, submap_id, H):
    chunks = [keyframe_world_points(k, H) for k in keyframes if k.submap_id == submap_id]
    return np.concatenate([X[valid] for X, valid in chunks])


def test_live_viewer_redraws_only_the_submaps_a_loop_closure_moved() -> None:
    from sl4slam.viewer.live import LiveViewer

    keyframes = _keyframes()
    similarity = np.diag([1.1, 1.1, 1.1, 1.0])
    similarity[:3, 3] = [0.5, 0, 0]
    estimates = {0: np.eye(4), 1: similarity, 2: similarity @ similarity}
    fake = FakeMapViewer(ViewerSettings(point_budget=10**6))
    viewer = LiveViewer(viewer=fake)
    try:
        viewer.apply(viewer_snapshot(viewer, _pipeline(keyframes[:4], {0: estimates[0], 1: estimates[1]})))
        viewer.apply(viewer_snapshot(viewer, _pipeline(keyframes, estimates)))
        assert fake.cloud_draws == [[0, 1], [2]]  # each submap drawn once, when it arrived
        for s in range(3):
            cloud = fake.state.clouds[s]
            expected = _world_points(keyframes, s, estimates[s])
            assert len(cloud) == len(expected)
            np.testing.assert_allclose(np.sort(cloud.offsets + cloud.centre, axis=0), np.sort(expected, axis=0), atol=1e-4)
            assert set(np.unique(cloud.colors).tolist()) == {k.frame_index for k in keyframes if k.submap_id == s}
            assert fake.state.has_confidence()  # the keyframes' confidence percentiles drive the slider
        # a loop closure moves submap 2 by a projective correction and leaves 0 and 1 in place
        correction = np.eye(4)
        correction[3, :3] = [0.02, -0.01, 0.03]
        correction[:3, 3] = [0.0, 0.2, 0.0]
        moved = {**estimates, 2: correction @ estimates[2]}
        before = fake.state.clouds[1].offsets.copy()
        viewer.apply(viewer_snapshot(viewer, _pipeline(keyframes, moved)))
        assert viewer.redrawn[-1] == [2] and fake.cloud_draws[-1] == [2]
        np.testing.assert_array_equal(fake.state.clouds[1].offsets, before)
        cloud = fake.state.clouds[2]
        expected = _world_points(keyframes, 2, moved[2])
        np.testing.assert_allclose(np.sort(cloud.offsets + cloud.centre, axis=0), np.sort(expected, axis=0), atol=1e-4)
        # a change below the tolerance is not a redraw
        nudged = {**moved, 0: moved[0] + 1e-9}
        viewer.apply(viewer_snapshot(viewer, _pipeline(keyframes, nudged)))
        assert viewer.redrawn[-1] == []
    finally:
        viewer.close()


def viewer_snapshot(viewer, pipeline):
    """What ``on_submap`` would hand to the worker, built synchronously for the test."""
    from sl4slam.viewer.live import _Snapshot

    return _Snapshot(keyframes=list(pipeline.keyframes), estimates=dict(pipeline.backend.world_estimate().H_world_submap),
                     edges=list(pipeline.edges), frames=pipeline.num_frames, colors=pipeline.colors)


def test_live_viewer_keeps_the_map_within_the_point_budget() -> None:
    from sl4slam.viewer.live import LiveViewer

    keyframes = _keyframes(count_per_submap=3, submaps=6)
    estimates = {s: np.eye(4) for s in range(6)}
    budget = 1500
    fake = FakeMapViewer(ViewerSettings(point_budget=budget))
    viewer = LiveViewer(viewer=fake)
    try:
        for s in range(6):
            viewer.on_submap(_pipeline([k for k in keyframes if k.submap_id <= s], {i: estimates[i] for i in range(s + 1)}), s)
            assert viewer.wait(HANG_S)  # drawn (the bound only catches a hang)
            assert fake.state.total_points() <= budget
        assert fake.state.fraction < 1.0 and viewer.updates >= 1
        full = sum(c.full_count for c in fake.state.clouds.values())
        assert fake.state.total_points() > budget / 2 - len(fake.state.clouds)  # halved no more than needed
        assert full > budget
    finally:
        viewer.close()


# ----------------------------------------------------------------------------- the server
def test_missing_viser_is_one_line(tmp_path: Path) -> None:
    write_known_result(tmp_path / "r")
    code = ("import sys; sys.modules['viser'] = None\nfrom sl4slam.cli import main\n"
            f"sys.exit(main(['view', {str(tmp_path / 'r')!r}]))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=HANG_S)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and 'pip install "sl4slam[viewer]"' in lines[0], proc.stderr


def test_port_in_use_takes_the_next_free_one_and_says_so(tmp_path: Path) -> None:
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import io

    from sl4slam.viewer.app import MapViewer, is_loopback

    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        taken = blocker.getsockname()[1]
        out = io.StringIO()
        viewer = MapViewer(ViewerSettings(port=taken), stream=out)
        try:
            assert viewer.port != taken
            lines = out.getvalue().splitlines()
            assert lines == [f"port {taken} is in use; using {viewer.port}", f"viewer at http://127.0.0.1:{viewer.port}"]
        finally:
            viewer.close()
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.2")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _browser_socket(viewer):
    """A websocket client that the viser server takes for a browser: it connects with viser's
    protocol and reports a camera (the server counts a client from its first camera message).
    Returns the open connection once the viewer's connect callbacks have run."""
    import threading

    import msgspec
    import viser
    from viser import _messages
    from websockets.sync.client import connect

    connected = threading.Event()
    viewer.server.on_client_connect(lambda _: connected.set())  # runs after the viewer's own callback
    socket_ = connect(f"ws://127.0.0.1:{viewer.port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
    camera = _messages.ViewerCameraMessage(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -1.0), fov=1.0, near=0.01,
                                           far=100.0, image_height=480, image_width=640, look_at=(0.0, 0.0, 0.0),
                                           up_direction=(0.0, -1.0, 0.0))
    socket_.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
    assert connected.wait(HANG_S)
    return socket_


def test_result_viewer_serves_before_its_map_is_read(tmp_path: Path, monkeypatch) -> None:
    """`view_result` opens its port before any keyframe array is read, then streams the map in.

    The cloud building is held at each submap (an event per submap): while none is built, the page
    answers over HTTP and the panel already holds the whole map's point counts, the summary and a
    "loading" line. Without a browser a built cloud is not sent (a browser opened later gets the
    scene in the usual order); with one connected, the clouds built so far go out at the next
    submap, and each further one as it is built. The complete map is the one
    :func:`~sl4slam.viewer.result.state_from_result` reads, the "loading" line is gone, and the
    browser whose camera was not moved is given the view that frames the map."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import io
    import threading
    import urllib.request

    from sl4slam.viewer import result as result_module
    from sl4slam.viewer import view_result
    from sl4slam.viewer.scene import overview

    truth = write_known_result(tmp_path / "r", count=12, width=32, height=24, submap_size=4, version=2,
                               confidence=True, scene="room")
    points = sum(int(mask.sum()) for mask in truth["masks"].values())
    gates = {submap_id: threading.Event() for submap_id in range(3)}
    held = threading.Event()
    build = result_module._submap_cloud

    def held_build(submap_id, *args):
        held.set()
        assert gates[submap_id].wait(HANG_S)
        return build(submap_id, *args)

    monkeypatch.setattr(result_module, "_submap_cloud", held_build)
    out = io.StringIO()
    viewer = view_result(tmp_path / "r", ViewerSettings(port=_free_port()), block=False, stream=out)
    browser = None
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}/", timeout=HANG_S) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        assert held.wait(HANG_S)  # the loader waits for the first cloud
        assert not viewer.loader.finished and viewer.state.clouds == {} and viewer.sent_clouds() == []
        assert viewer._status.content == "*loading the map: 0 of 3 submaps*"
        assert viewer.gui_points.content == f"points: {points:,} shown of {points:,}"
        assert "12 keyframes, 3 submaps" in viewer.gui_summary.content and len(viewer.state.T_world_cam) == 12
        gates[0].set()
        assert viewer.loader.wait(HANG_S, submaps=1)
        assert list(viewer.state.clouds) == [0] and viewer.sent_clouds() == []  # nobody watches: kept back
        browser = _browser_socket(viewer)
        gates[1].set()
        assert viewer.loader.wait(HANG_S, submaps=2)
        assert viewer.sent_clouds() == [0, 1] and 2 not in viewer.state.clouds
        assert viewer._status.content == "*loading the map: 2 of 3 submaps*" and viewer._frustums == {}
        gates[2].set()
        assert viewer.loader.wait(HANG_S) and viewer.loader.complete and viewer.loader.error is None
        assert viewer.sent_clouds() == [0, 1, 2] and viewer._status is None and len(viewer._frustums) == 12
        printed = out.getvalue().splitlines()
        assert f"viewer at http://127.0.0.1:{viewer.port}" in printed
        assert printed[-1].startswith(f"loaded 12 keyframes, {points:,} points shown")
        expected = result_module.state_from_result(load_result(tmp_path / "r"), ViewerSettings())
        assert list(viewer.state.clouds) == list(expected.clouds)
        for submap_id, cloud in expected.clouds.items():
            np.testing.assert_array_equal(viewer.state.clouds[submap_id].offsets, cloud.offsets)
            np.testing.assert_array_equal(viewer.state.clouds[submap_id].colors, cloud.colors)
        assert viewer.gui_points.content == f"points: {points:,} shown of {points:,}"
        client = next(iter(viewer.server.get_clients().values()))
        np.testing.assert_allclose(client.camera.position, overview(viewer.state)[0])
    finally:
        for gate in gates.values():
            gate.set()
        if browser is not None:
            browser.close()
        viewer.close()


def test_closing_the_viewer_while_its_map_loads_stops_the_loader(tmp_path: Path, monkeypatch) -> None:
    """Closing the viewer while a submap is being built ends the reading at once: nothing more is
    added or drawn, and no "loaded" line is printed."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import io
    import threading

    from sl4slam.viewer import result as result_module
    from sl4slam.viewer import view_result

    write_known_result(tmp_path / "r", count=8, width=32, height=24, submap_size=4)
    gate, held = threading.Event(), threading.Event()
    build = result_module._submap_cloud

    def held_build(*args):
        held.set()
        assert gate.wait(HANG_S)
        return build(*args)

    monkeypatch.setattr(result_module, "_submap_cloud", held_build)
    out = io.StringIO()
    viewer = view_result(tmp_path / "r", ViewerSettings(port=_free_port()), block=False, stream=out)
    try:
        assert held.wait(HANG_S)
        viewer.close()
        assert viewer.loader.wait(HANG_S) and not viewer.loader.complete and viewer.loader.error is None
        assert viewer.state.clouds == {} and "loaded" not in out.getvalue()
    finally:
        gate.set()
        viewer.close()


def test_a_browser_connecting_while_the_map_loads_is_framed_under_the_viewer_lock(tmp_path: Path) -> None:
    """The map loader adds clouds to the state under the viewer's lock; a browser that connects
    meanwhile is framed from the state under the same lock (reading it while a cloud is added raised
    "dictionary changed size during iteration" in viser's callback thread, and the browser kept
    viser's default camera): while another thread holds the lock the connect callback waits, and once
    it is released the browser gets the view that frames the map."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import contextlib
    import threading

    from sl4slam.viewer import view_result
    from sl4slam.viewer.scene import overview

    write_known_result(tmp_path / "r", count=8, width=32, height=24, submap_size=4)
    viewer = view_result(tmp_path / "r", ViewerSettings(port=_free_port()), block=False)
    try:
        assert viewer.loader.wait(HANG_S) and viewer.loader.complete
        client = SimpleNamespace(client_id=7, camera=SimpleNamespace(position=None, look_at=None, up_direction=None),
                                 atomic=contextlib.nullcontext)
        framed = threading.Thread(target=viewer._view_client, args=(client,))
        with viewer.lock:
            framed.start()
            framed.join(0.2)
            assert framed.is_alive() and client.camera.position is None and 7 not in viewer._given_views
        framed.join(HANG_S)
        assert not framed.is_alive()
        np.testing.assert_array_equal(client.camera.position, overview(viewer.state)[0])
        np.testing.assert_array_equal(viewer._given_views[7][0], client.camera.position)
    finally:
        viewer.close()


def test_view_serves_at_once_and_sigterm_stops_it_while_the_map_loads(tmp_path: Path) -> None:
    """`sl4slam view` with the cloud building held until the viewer closes: the URL answers while
    no cloud is built, and SIGTERM stops the viewer cleanly (exit 0, "viewer stopped", no map)."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import queue
    import signal
    import threading
    import urllib.request

    write_known_result(tmp_path / "r", count=8, width=32, height=24, submap_size=4)
    port = _free_port()
    code = ("import sys, threading\n"
            "from sl4slam.viewer import app, result\n"
            "from sl4slam.cli import main\n"
            "closed = threading.Event()\n"
            "close, build = app.MapViewer.close, result._submap_cloud\n"
            "def close_first(self):\n    closed.set()\n    close(self)\n"
            "def held_build(*args):\n    print('building', flush=True)\n    closed.wait()\n    return build(*args)\n"
            "app.MapViewer.close, result._submap_cloud = close_first, held_build\n"
            f"sys.exit(main(['view', {str(tmp_path / 'r')!r}, '--port', '{port}']))\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout] + [lines.put("")], daemon=True).start()
    seen = []
    try:
        while not (any(line.startswith("building") for line in seen)  # two workers may print on one line
                   and any(line.startswith("viewer at") for line in seen)):
            seen.append(lines.get(timeout=HANG_S).strip())  # a viewer that serves only after the map: no URL
            assert seen[-1] or proc.poll() is None, f"viewer exited: {proc.stderr.read()}"
        url = next(line for line in seen if line.startswith("viewer at")).split()[-1]
        with urllib.request.urlopen(url, timeout=HANG_S) as page:
            assert page.status == 200
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=HANG_S)
        while (line := lines.get(timeout=HANG_S)):
            seen.append(line.strip())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and "viewer stopped" in seen and not any(line.startswith("loaded") for line in seen), \
        proc.stderr.read()


def _browser(playwright, profile: Path):
    chromium = chromium_path()
    if chromium is None:
        pytest.skip("headless Chromium is not installed (apt-get install -y chromium)")
    return launch(playwright, profile, chromium)


def _wait_until_drawn(page) -> float:
    """Screenshots until the canvas shows something; the drawn fraction of that screenshot."""
    return drawn_fraction(first_drawn(page))


def _wait_for_line(proc, prefix: str) -> str:
    """Read the viewer's stdout up to the line that starts with ``prefix`` (or its exit)."""
    while True:
        line = proc.stdout.readline()
        if line.startswith(prefix):
            return line.strip()
        if not line and proc.poll() is not None:
            raise AssertionError(f"viewer exited before '{prefix}': {proc.stderr.read()}")


MAP_VISIBLE = 0.40
"""Fraction of the canvas the room of :func:`test_view_in_a_real_browser` covers in the first
screenshot that shows it, at least (measured: 0.30 before the defaults followed the map, 0.48 after)."""


def test_view_in_a_real_browser(tmp_path: Path) -> None:
    """`sl4slam view` in headless Chromium, default settings, no interaction: the first screenshot
    that shows anything on the canvas shows the map, the control panel holds every control, the
    counts and the run summary from the first frame that draws the map, and Ctrl-C stops the
    viewer (exit 0).

    The result is a room with a desk as a run writes it: 16 keyframes at 96x72 of dense surface
    points, 88,381 shown (``write_known_result(scene="room")``). Fraction of the canvas drawn in that
    first screenshot (software WebGL, 1000x700 page, :func:`browser.drawn_fraction`): 0.30 with the
    previous defaults (point size the trajectory's extent / 500: the map a dotted haze; 16 frustums
    of 4 % of that extent; viser's environment map fading the canvas in from 5 % opacity: under
    load the first screenshot caught the fade, 0.14), 0.48 with the current ones (point size from
    the map's point spacing, frustums of 2.5 % of the map's radius, no environment map). The
    threshold :data:`MAP_VISIBLE` = 0.40 lies between.

    The panel is checked on the page's text read in the same JavaScript task as the canvas' pixels
    (:func:`browser.first_drawn_text`), at the first moment the canvas shows something: a
    screenshot and a separate read of the page are two moments, and under load viser's panel may
    still be sliding open in a screenshot whose page already holds everything.
    """
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    truth = write_known_result(tmp_path / "room", count=16, width=96, height=72, submap_size=4, version=2,
                               confidence=True, scene="room", loops=[{"submaps": [0, 2], "frame": 0}])
    points = sum(int(mask.sum()) for mask in truth["masks"].values())
    expected = ("Point size", "Min confidence %", "Colour", "Cameras", "All frustums", "Trajectory", "Loop edges",
                "Ground truth", "Follow camera", "Keyframe", f"points: {points:,} shown of {points:,}",
                "16 keyframes, 4 submaps", "ATE RMSE")
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "sl4slam.cli", "view", str(tmp_path / "room"), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ})
    try:
        url = _wait_for_line(proc, "viewer at").split()[-1]
        assert url == f"http://127.0.0.1:{port}"
        _wait_for_line(proc, "loaded")
        with sync_api.sync_playwright() as playwright:
            browser = _browser(playwright, tmp_path / "profile")
            page = browser.new_page()
            page.goto(url)
            _, text = first_drawn_text(page)
            first = first_drawn(page)
            (tmp_path / "first.png").write_bytes(first)
            page.get_by_text("ATE RMSE", exact=False).first.wait_for()
            settled = page.screenshot()
            browser.close()
        missing = [item for item in expected if item not in text]
        assert not missing, f"not in the page when the canvas first showed the map: {missing}"
        fraction = drawn_fraction(first)
        assert fraction > MAP_VISIBLE, f"the first view shows {fraction:.3f} of the canvas drawn (see first.png)"
        assert drawn_fraction(settled) > MAP_VISIBLE
    finally:
        out, err = interrupt(proc)
    assert proc.returncode == 0 and "viewer stopped" in out, err


def test_a_damaged_keyframe_file_closes_the_viewer_with_one_line(tmp_path: Path) -> None:
    """The map is read after the port opens: a keyframe file that cannot be read stops the server,
    and the error is one line (exit 2), as when the map was read first."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    write_known_result(tmp_path / "r", count=6, submap_size=3)
    damaged = sorted((tmp_path / "r" / "keyframes").glob("*.npz"))[-1]
    with np.load(damaged) as data:
        arrays = {name: data[name] for name in data.files if name != "points_world"}
    np.savez(damaged, **arrays)
    proc = subprocess.run([sys.executable, "-m", "sl4slam.cli", "view", str(tmp_path / "r"), "--port",
                           str(_free_port())], capture_output=True, text=True, timeout=HANG_S)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and "viewer stopped" in proc.stdout and "loaded" not in proc.stdout, proc.stderr
    assert len(lines) == 1 and lines[0].startswith(f"sl4slam: error: keyframe file {damaged}"), proc.stderr


def test_view_streams_the_map_into_an_open_browser(tmp_path: Path) -> None:
    """`sl4slam view` in headless Chromium opened before the map is read: the page shows the control
    panel with the whole map's counts, the run summary and a "loading" line while the cloud building
    is held (until the test writes to a FIFO); once released the map is drawn, the "loading" line
    goes, the view frames the map as it does for a browser opened afterwards, and Ctrl-C stops the
    viewer (exit 0)."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    truth = write_known_result(tmp_path / "room", count=16, width=96, height=72, submap_size=4, version=2,
                               confidence=True, scene="room")
    points = sum(int(mask.sum()) for mask in truth["masks"].values())
    release = tmp_path / "release"
    os.mkfifo(release)
    code = ("import sys, threading\n"
            "from sl4slam.viewer import result\n"
            "from sl4slam.cli import main\n"
            "lock, released, build = threading.Lock(), threading.Event(), result._submap_cloud\n"
            "def held_build(*args):\n"
            "    with lock:\n"
            "        if not released.is_set():\n"
            f"            open({str(release)!r}).read()\n"
            "            released.set()\n"
            "    return build(*args)\n"
            "result._submap_cloud = held_build\n"
            f"sys.exit(main(['view', {str(tmp_path / 'room')!r}, '--port', '{_free_port()}']))\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    released = False
    try:
        url = _wait_for_line(proc, "viewer at").split()[-1]
        with sync_api.sync_playwright() as playwright:
            browser = _browser(playwright, tmp_path / "profile")
            page = browser.new_page()
            page.goto(url)
            page.get_by_text("loading the map: 0 of 4 submaps", exact=False).first.wait_for()
            text = page.evaluate("() => document.body.innerText")
            for item in ("Point size", "Min confidence %", "Colour", "Follow camera",
                         f"points: {points:,} shown of {points:,}", "16 keyframes, 4 submaps"):
                assert item in text, f"{item!r} not in the page while the map loads"
            with open(release, "w") as fifo:
                fifo.write("go")
            released = True
            _wait_for_line(proc, "loaded")
            page.get_by_text("loading the map", exact=False).first.wait_for(state="detached")
            assert _wait_until_drawn(page) > DRAWN
            settled = page.screenshot()  # the view framing the whole map, given at the end of the loading
            (tmp_path / "settled.png").write_bytes(settled)
            browser.close()
        assert drawn_fraction(settled) > MAP_VISIBLE
    finally:
        if not released:
            proc.kill()  # its cloud building waits on the FIFO
        out, err = interrupt(proc)
    assert proc.returncode == 0 and "viewer stopped" in out, err


def test_live_viewer_follows_a_real_run(tmp_path: Path) -> None:
    """The pipeline's callback feeds a real viser server; the final scene is the polished result."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import io

    from result_folders import small_world_config
    from sl4slam.io import open_source
    from sl4slam.pipeline import SLAMPipeline
    from sl4slam.synthetic import write_synthetic_sequence
    from sl4slam.viewer import LiveViewer

    world = write_synthetic_sequence(tmp_path / "w", num_frames=60, width=96, height=72, seed=0)
    config = small_world_config()
    viewer = LiveViewer(ViewerSettings(port=_free_port(), point_budget=50_000), stream=io.StringIO())
    calls = []
    try:
        pipeline = SLAMPipeline.from_config(config,
                                on_submap=lambda p, s: (calls.append(s), viewer.on_submap(p, s)))
        result = pipeline.run(open_source(str(world)), progress=False)
        viewer.finish(result, {"counts": result.stats, "ate": {"rmse": 0.01, "poses": len(result.keyframes)}})
        assert viewer.wait(HANG_S)  # the final state is drawn (the bound only catches a hang)
        state = viewer.state
        assert calls == list(range(result.stats["submaps"])) and viewer.updates >= 2 and viewer.error is None
        assert sorted(state.clouds) == sorted(result.H_world_submap)
        assert 0 < state.total_points() <= 50_000
        np.testing.assert_allclose(state.T_world_cam, result.T_world_cam)
        assert state.gt_positions is not None and len(state.gt_positions) == len(result.keyframes)
        assert "ATE RMSE 0.0100" in viewer.viewer.gui_summary.content
        # every cloud sits where the polished graph puts its submap (redrawn after the final polish)
        for submap_id, cloud in state.clouds.items():
            expected = _world_points([k for k in result.keyframes if k.submap_id == submap_id], submap_id,
                                     result.H_world_submap[submap_id])
            centre = expected.mean(0)
            assert np.linalg.norm(cloud.offsets.mean(0) + cloud.centre - centre) < 0.02 * np.ptp(expected, axis=0).max()
    finally:
        viewer.close()


@pytest.mark.slow
def test_run_with_view_in_a_real_browser(tmp_path: Path) -> None:
    """`sl4slam run --view`: the page shows the map while and after the run; Ctrl-C closes it."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    from sl4slam.synthetic import write_synthetic_sequence

    world = write_synthetic_sequence(tmp_path / "w", num_frames=120, width=96, height=72, seed=0)
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "sl4slam.cli", "run", str(world), "--out", str(tmp_path / "o"),
                             "--frontend", "simulated", "--tau-disparity", "7.5", "--submap-size", "8", "--retrieval",
                             "none", "--view", "--port", str(port), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = _wait_for_line(proc, "viewer at").split()[-1]
        _wait_for_line(proc, "viewer stays open")
        assert (tmp_path / "o" / "summary.json").is_file()
        with sync_api.sync_playwright() as playwright:
            browser = _browser(playwright, tmp_path / "profile")
            page = browser.new_page()
            page.goto(url)
            assert _wait_until_drawn(page) > 0.02
            page.get_by_text("ATE RMSE", exact=False).first.wait_for()
            browser.close()
    finally:
        _, err = interrupt(proc)
    assert proc.returncode == 0, err


def test_a_run_without_keyframe_files_shows_its_trajectory(tmp_path: Path) -> None:
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    import io

    from sl4slam.viewer import view_result

    write_known_result(tmp_path / "r", count=5, keyframes=False)
    out = io.StringIO()
    viewer = view_result(tmp_path / "r", ViewerSettings(port=_free_port()), block=False, stream=out)
    try:
        assert viewer.loader.wait(HANG_S) and viewer.loader.complete
        assert len(viewer.state.T_world_cam) == 5 and viewer.state.total_points() == 0
        assert "--keyframes compact" in viewer.gui_summary.content
    finally:
        viewer.close()
