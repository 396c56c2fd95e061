"""Styles of synthetic sequence and the development suite: determinism, what each style claims,
the suite's split, and the one-line errors of ``sl4slam synth``."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from sl4slam.cli import main
from sl4slam.io import open_source
from sl4slam.synthetic import default_intrinsics, render_frames, render_pixels, write_synthetic_sequence
from sl4slam.synthetic import suite as suite_module
from sl4slam.synthetic.properties import count_revisits, gradient_energy, path_properties, rotation_angles_deg
from sl4slam.synthetic.styles import STYLES, SPEEDS, make_style_layout, make_style_world, style_path
from sl4slam.synthetic.suite import SUITE, SuiteSequence, split_of, suite_sequences
from sl4slam.synthetic.textures import MOTIF_M

W, H = 64, 48


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for array in arrays:
        h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()


@pytest.mark.parametrize("name", list(STYLES))
def test_every_style_path_and_layout_are_seeded(name: str) -> None:
    frames = min(STYLES[name].frames, 600)
    a, b = make_style_layout(name, 3), make_style_layout(name, 3)
    assert _digest(a.layout.room_max, a.layout.boxes_min, a.layout.boxes_max) == \
        _digest(b.layout.room_max, b.layout.boxes_min, b.layout.boxes_max)
    path = style_path(name, frames, 3)
    np.testing.assert_array_equal(path, style_path(name, frames, 3, b))
    assert not np.array_equal(path, style_path(name, frames, 4))
    R = path[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    # Inside the room, outside every box, by a margin (the renderer's rays start there).
    positions = path[:, :3, 3]
    layout = a.layout
    assert np.all((positions > layout.room_min + 0.3) & (positions < layout.room_max - 0.3))
    for lo, hi in zip(layout.boxes_min, layout.boxes_max):
        assert not np.any(np.all((positions > lo - 0.2) & (positions < hi + 0.2), axis=1))


@pytest.mark.parametrize("name", ["office-walk-slow", "office-lowtex-walk", "room-repeat-walk", "corridor-repeat-fast"])
def test_style_renders_the_same_bytes_from_the_same_seed(name: str) -> None:
    K = default_intrinsics(W, H)
    images = []
    for _ in range(2):
        world = make_style_world(name, 1)
        path = style_path(name, 40, 1)
        images.append(render_frames(world, path[::13], K, W, H))
    np.testing.assert_array_equal(images[0][0], images[1][0])
    np.testing.assert_array_equal(images[0][1], images[1][1])
    other = render_frames(make_style_world(name, 2), style_path(name, 40, 2)[::13], K, W, H)[0]
    assert not np.array_equal(images[0][0], other)


def test_written_style_sequence_is_byte_identical_and_reads_back(tmp_path: Path) -> None:
    folders = [write_synthetic_sequence(tmp_path / f"run{i}", num_frames=6, width=32, height=24, seed=2,
                                        style="office-rotate") for i in range(2)]
    files = [sorted(p.relative_to(f) for p in f.rglob("*") if p.is_file()) for f in folders]
    assert files[0] == files[1]
    for relative in files[0]:
        assert (folders[0] / relative).read_bytes() == (folders[1] / relative).read_bytes()
    frames = list(open_source(folders[0]))
    expected = style_path("office-rotate", 6, 2)
    assert len(frames) == 6
    for frame in frames:
        np.testing.assert_allclose(frame.T_world_cam, expected[frame.index], atol=2e-8)
        np.testing.assert_allclose(frame.K, default_intrinsics(32, 24))


def test_lap_style_is_the_original_world(tmp_path: Path) -> None:
    plain = write_synthetic_sequence(tmp_path / "plain", num_frames=5, width=32, height=24, seed=1)
    styled = write_synthetic_sequence(tmp_path / "styled", num_frames=5, width=32, height=24, seed=1, style="lap")
    for name in sorted(p.name for p in (plain / "rgb").iterdir()):
        assert (plain / "rgb" / name).read_bytes() == (styled / "rgb" / name).read_bytes()
    assert (plain / "groundtruth.txt").read_text() == (styled / "groundtruth.txt").read_text()


@pytest.mark.parametrize("name", [n for n, s in STYLES.items() if s.motion == "orbit"])
def test_orbit_keeps_the_object_centred(name: str) -> None:
    layout = make_style_layout(name, 0)
    path = style_path(name, 300, 0, layout)
    K = default_intrinsics(W, H)
    T_cam_world = np.linalg.inv(path)
    target = T_cam_world[:, :3, :3] @ layout.target + T_cam_world[:, :3, 3]
    pixels = (target @ K.T)[:, :2] / target[:, 2:3]
    assert np.all(target[:, 2] > 0)
    assert np.abs(pixels - K[:2, 2]).max() < 0.06 * W  # within a few degrees of the image centre
    # The ray through the image centre hits one of the object's boxes (surfaces 6.. are box faces).
    _, surface = render_pixels(make_style_world(name, 0, layout), path[0], K, K[None, :2, 2])
    assert surface[0] >= 6


@pytest.mark.parametrize("name", [n for n, s in STYLES.items() if s.motion == "rotate"])
def test_rotation_in_place_turns_about_an_axis_just_behind_the_camera(name: str) -> None:
    layout = make_style_layout(name, 0)
    path = style_path(name, STYLES[name].frames, 0, layout)
    centres = path[:, :3, 3]
    axis = layout.plan.position
    radius = np.hypot(*(centres[:, :2] - axis[:2]).T)
    np.testing.assert_allclose(radius, 0.25, atol=1e-9)  # the centre circles the axis at arm's length
    assert np.ptp(centres[:, 2]) < 1e-9
    outward = (centres[:, :2] - axis[:2]) / radius[:, None]
    viewing = path[:, :2, 2] / np.linalg.norm(path[:, :2, 2], axis=1, keepdims=True)
    assert np.all(np.sum(outward * viewing, axis=1) > 0.97)  # looking away from the axis
    props = path_properties(path, np.arange(len(path)) / 30.0)
    # Mostly rotation: under 2 cm of travel per 10 degrees turned.
    assert props.rotation_deg_s > 15.0 and props.speed_m_s / props.rotation_deg_s < 0.005


def test_forward_walks_along_the_corridor() -> None:
    path = style_path("corridor-forward-slow", 600, 0)
    assert np.all(np.diff(path[:, 0, 3]) > 0)  # always further along x
    assert np.all(path[:, 0, 2] > 0.95)  # looking along it
    assert path[-1, 0, 3] - path[0, 0, 3] > 5.0


def test_low_texture_has_less_gradient_energy_and_repetitive_surfaces_repeat() -> None:
    K = default_intrinsics(128, 96)
    energy = {}
    for name in ("office-walk-slow", "office-lowtex-walk"):
        rgb, _ = render_frames(make_style_world(name, 0), style_path(name, 600, 0)[::150], K, 128, 96)
        energy[name] = np.mean([gradient_energy(image) for image in rgb])
    assert energy["office-lowtex-walk"] < 0.3 * energy["office-walk-slow"]

    world = make_style_world("room-repeat-walk", 0)
    atlas = world.atlas

    def texture(surface: int) -> np.ndarray:
        rows, cols = atlas.rows[0, surface], atlas.cols[0, surface]
        start = atlas.offset[0, surface]
        return atlas.texels[start:start + rows * cols].reshape(rows, cols, 4)

    period = int(np.ceil(MOTIF_M["wall"] / 0.01))
    wall, other_wall = texture(0), texture(2)
    np.testing.assert_array_equal(wall[:, :period], wall[:, period:2 * period])
    np.testing.assert_array_equal(wall[:period, :period], other_wall[:period, :period])  # every wall alike
    normal = make_style_world("room-walk-open", 0).atlas
    start, cols = normal.offset[0, 0], normal.cols[0, 0]
    rows = normal.rows[0, 0]
    plain = normal.texels[start:start + rows * cols].reshape(rows, cols, 4)
    assert not np.array_equal(plain[:, :period], plain[:, period:2 * period])


@pytest.mark.parametrize("name", list(STYLES))
def test_loop_structure_and_speed_are_what_the_style_says(name: str) -> None:
    style = STYLES[name]
    path = style_path(name, style.frames, 0)
    props = path_properties(path, np.arange(style.frames) / 30.0)
    expected = {"none": (0, 0), "one": (1, 1), "many": (3, 99)}[style.loops]
    assert expected[0] <= props.returns <= expected[1], props
    if style.motion in ("walk", "orbit", "forward"):
        nominal = SPEEDS[style.speed][0]
        assert 0.9 * nominal < props.speed_m_s < 1.5 * nominal, props


def test_speed_classes_differ_and_revisits_are_counted() -> None:
    slow = path_properties(style_path("office-walk-slow", 600, 0), np.arange(600) / 30.0)
    fast = path_properties(style_path("office-walk-fast", 600, 0), np.arange(600) / 30.0)
    assert fast.speed_m_s > 2.0 * slow.speed_m_s and fast.rotation_deg_s > slow.rotation_deg_s
    # A hand-made path: out 3 m along x and back twice, facing +x: its middle is passed four times.
    x = np.concatenate([np.linspace(0, 3, 50), np.linspace(3, 0, 50), np.linspace(0, 3, 50), np.linspace(3, 0, 50)])
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, 0, 3] = x
    returns, revisited = count_revisits(T)
    assert returns == 3 and 0.5 < revisited < 0.9
    T[100:, :3, :3] = np.diag([-1.0, -1.0, 1.0])  # the second time turned round: not a revisit of the first pass
    assert count_revisits(T)[0] == 1
    assert rotation_angles_deg(np.eye(3), np.diag([-1.0, -1.0, 1.0])) == pytest.approx(180.0)


def test_suite_is_broad_named_and_split_by_a_fixed_rule() -> None:
    synthetic = [s for s in SUITE if not s.real]
    assert len(synthetic) >= 24
    assert len({s.name for s in SUITE}) == len(SUITE)
    assert all(300 <= s.frames <= 3000 for s in synthetic)
    assert min(s.frames for s in synthetic) == 300 and max(s.frames for s in synthetic) == 3000
    for dimension in ("room", "texture", "motion", "speed", "loops"):
        assert len({getattr(STYLES[s.style], dimension) for s in synthetic}) >= 3 or dimension == "speed"
    # Balanced: every style has as many sequences in each half, and so as many frames.
    for style in STYLES:
        halves = [split_of(s) for s in synthetic if s.style == style]
        assert halves.count("tune") == halves.count("validate") >= 1
    assert all(s.split == "validate" for s in SUITE if s.real)
    assert {s.folder for s in SUITE if s.real} >= {"tum_rgbd_fr1_desk"}
    # Fixed: the tune half as it was decided; a sequence's half depends on nothing but itself.
    assert [s.name for s in suite_sequences("tune")] == [f"{style}-s0" for style in STYLES]
    newcomer = SuiteSequence("extra-s7", "office-walk-slow", 7, 300, None, "")
    assert split_of(newcomer) == "validate" and split_of(newcomer) == split_of(newcomer)
    assert [s.split for s in SUITE] == [split_of(s) for s in SUITE]


def test_suite_command_writes_every_sequence_and_resumes(tmp_path: Path, monkeypatch, capsys) -> None:
    tiny = (SuiteSequence("office-rotate-s0", "office-rotate", 0, 4, None, ""),
            SuiteSequence("room-walk-open-s1", "room-walk-open", 1, 3, None, ""),
            SuiteSequence("tum-fr1-desk", None, 0, None, "tum_rgbd_fr1_desk", ""))
    monkeypatch.setattr(suite_module, "SUITE", tiny)
    assert main(["synth", "--suite", str(tmp_path), "--width", "32", "--height", "24"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["office-rotate-s0", "room-walk-open-s1"]
    assert len(open_source(tmp_path / "room-walk-open-s1")) == 3
    capsys.readouterr()
    assert main(["synth", "--suite", str(tmp_path), "--width", "32", "--height", "24", "--split", "tune"]) == 0
    out = capsys.readouterr().out
    assert "kept office-rotate-s0" in out and "room-walk-open-s1" not in out


@pytest.mark.parametrize("argv, words", [
    (["--style", "nope", "--out", "X"], ["unknown style 'nope'", "office-walk-slow", "corridor-forward-slow"]),
    (["--style", "office-rotate", "--frames", "0", "--out", "X"], ["--frames", "from 2 to 20000", "got 0"]),
    (["--style", "office-rotate", "--frames", "50000", "--out", "X"], ["--frames", "got 50000"]),
    (["--style", "office-rotate", "--seed", "-1", "--out", "X"], ["--seed", "0 or more", "got -1"]),
    (["--style", "office-rotate", "--width", "8", "--out", "X"], ["16x16", "got 8x240"]),
    (["--suite", "X", "--split", "half"], ["unknown split 'half'", "tune, validate"]),
    (["--suite", "X", "--style", "lap"], ["--suite", "drop --style"]),
    (["--style", "lap"], ["--out", "--suite"]),
])
def test_bad_synth_input_is_one_line(tmp_path: Path, capsys, argv: list[str], words: list[str]) -> None:
    argv = [str(tmp_path / "o") if a == "X" else a for a in argv]
    assert main(["synth", *argv]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("sl4slam: error: "), err
    for word in words:
        assert word in err[0], err
    assert not (tmp_path / "o").exists()
