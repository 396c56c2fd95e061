"""Write a synthetic world's rendered sequence as a TUM RGB-D folder or a 7-Scenes sequence folder."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from sl4slam.errors import UserError
from sl4slam.io.seven_scenes import SEVEN_SCENES_INVALID_DEPTH, seven_scenes_intrinsics
from sl4slam.io.tum import TUM_DEPTH_SCALE, write_tum_trajectory
from sl4slam.synthetic.render import default_intrinsics, render_frames
from sl4slam.synthetic.styles import check_style_request, get_style, make_style_layout, make_style_world, style_path
from sl4slam.synthetic.world import (
    FLOOR_HOLD,
    FLOOR_SURFACE,
    _path_from_layout,
    make_world,
    path_parameters,
)

logger = logging.getLogger("sl4slam")

SYNTHETIC_FPS = 30.0
METADATA_FILE = "synthetic.json"
CALIBRATION_FILE = "calibration.txt"
CONTACT_SHEET_FILE = "contact_sheet.png"


def _timestamps(num_frames: int) -> np.ndarray:
    """``(N,)`` 30 Hz timestamps rounded to the microseconds written in the file lists."""
    return np.round(np.arange(num_frames) / SYNTHETIC_FPS, 6)


def contact_sheet(rgb: np.ndarray, labels: list[str], columns: int = 6) -> np.ndarray:
    """Tile ``(M, H, W, 3)`` uint8 images into one ``(rows * H, columns * W, 3)`` image with a label on each."""
    count, height, width = rgb.shape[:3]
    rows = -(-count // columns)
    sheet = np.full((rows * height, columns * width, 3), 255, np.uint8)
    for i in range(count):
        tile = np.ascontiguousarray(rgb[i])
        cv2.putText(tile, labels[i], (5, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(tile, labels[i], (5, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        r, c = divmod(i, columns)
        sheet[r * height : (r + 1) * height, c * width : (c + 1) * width] = tile
    return sheet


def _longest_run(flags: np.ndarray) -> tuple[int, int]:
    """Half-open ``(start, stop)`` of the longest run of True in ``flags`` (``(0, 0)`` if none)."""
    best = (0, 0)
    padded = np.concatenate([[False], flags, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    for start, stop in zip(edges[0::2], edges[1::2]):
        if stop - start > best[1] - best[0]:
            best = (int(start), int(stop))
    return best


def _check_request(out_dir: Path, num_frames: int, width: int, height: int, overwrite: bool, seed: int = 0,
                   style: str | None = None) -> None:
    if style is not None:
        get_style(style)
        check_style_request(num_frames, width, height, seed)
    if int(num_frames) < 2:
        raise UserError(f"--frames must be at least 2, got {num_frames}")
    if int(width) < 16 or int(height) < 16:
        raise UserError(f"image size must be at least 16x16 px, got {width}x{height}")
    if int(seed) < 0:
        raise UserError(f"--seed must be 0 or more, got {seed}")
    if out_dir.exists() and not (out_dir.is_dir() and not any(out_dir.iterdir())) and not overwrite:
        raise UserError(f"output folder {out_dir} already exists and is not empty; choose another folder or overwrite it")


def _write_image(path: Path, image: np.ndarray) -> None:
    """Write an 8-bit RGB (converted to OpenCV's BGR) or a 16-bit single-channel PNG."""
    data = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    if not cv2.imwrite(str(path), data):
        raise UserError(f"cannot write {path}; check free disk space and permissions")


@contextlib.contextmanager
def _staged(out_dir: Path) -> Iterator[Path]:
    """A temporary sibling folder that replaces ``out_dir`` when the block succeeds (removed otherwise)."""
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = out_dir.with_name(f".{out_dir.name}.{os.getpid()}.tmp")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    try:
        yield staging
        if out_dir.exists():
            shutil.rmtree(out_dir)
        os.replace(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)


def _world_and_path(style: str | None, seed: int, num_frames: int):
    """The world and ``(N, 4, 4)`` camera path of a sequence: the original world along its lap, or a style's."""
    if style is None:
        world = make_world(seed)
        return world, _path_from_layout(world.layout, path_parameters(num_frames))
    layout = make_style_layout(style, seed)
    return make_style_world(style, seed, layout), style_path(style, num_frames, seed, layout)


def path_digest(poses: np.ndarray) -> str:
    """SHA-256 of a camera path's float64 bytes: tells whether a rendering followed the path a style gives now."""
    return hashlib.sha256(np.ascontiguousarray(poses, np.float64).tobytes()).hexdigest()


def _style_metadata(style: str | None, poses: np.ndarray) -> dict:
    """``synthetic.json`` entries naming a sequence's style and its path's digest (none for the
    original world without a style)."""
    if style is None:
        return {}
    chosen = get_style(style)
    return {"style": {"name": chosen.name, "room": chosen.room, "texture": chosen.texture, "motion": chosen.motion,
                      "speed": chosen.speed, "loops": chosen.loops, "description": chosen.description,
                      "path_sha256": path_digest(poses)}}


def _metadata(world, seed: int, num_frames: int, width: int, height: int, K: np.ndarray, depth_scale: float,
              depth_range: tuple[float, float], **extra) -> str:
    """``synthetic.json``: what was rendered, with which camera, and the depth range met."""
    metadata = {
        "generator": "sl4slam.synthetic", "seed": int(seed), "num_frames": num_frames, "width": width, "height": height,
        "fps": SYNTHETIC_FPS, "depth_scale": depth_scale, "K": K.tolist(), **extra,
        "depth_range_m": list(depth_range), "room_size_m": world.layout.room_max.tolist(), "num_boxes": world.num_boxes,
    }
    return json.dumps(metadata, indent=2) + "\n"


def write_synthetic_sequence(
    out_dir: str | Path,
    num_frames: int = 600,
    width: int = 320,
    height: int = 240,
    seed: int = 0,
    overwrite: bool = False,
    sheet_frames: int = 24,
    block_frames: int = 32,
    style: str | None = None,
) -> Path:
    """Render the synthetic world ``seed`` along its looping path (or a style's world along its path)
    and write a TUM RGB-D folder.

    Output (written to a temporary sibling folder, then renamed into place):

    - ``rgb/<timestamp>.png`` (8-bit RGB) and ``depth/<timestamp>.png`` (16-bit, 5000 per metre),
    - ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (camera-to-world, TUM format), 30 Hz,
    - ``calibration.txt`` (``fx = .. fy = .. cx = .. cy = ..``, read by :class:`sl4slam.io.TumSource`),
    - ``synthetic.json``: seed, size, ``K``, the floor-only frame range (measured on the renders:
      frames where every pixel shows the floor), loop information, depth range and the style,
    - ``contact_sheet.png``: ``sheet_frames`` evenly sampled frames with their indices.

    Args:
        out_dir: the folder to create.
        num_frames: frames to render (>= 2); the last pose equals the first.
        width, height: image size in pixels (>= 16).
        seed: world and path seed.
        overwrite: replace an existing ``out_dir``; otherwise an existing non-empty folder is an error.
        sheet_frames: frames shown on the contact sheet.
        block_frames: frames rendered per block (bounds memory).
        style: a style of :mod:`sl4slam.synthetic.styles` (its room, textures and camera path with
            this seed); None: the original world and its lap.

    Returns:
        ``out_dir`` as a Path.
    """
    out_dir = Path(out_dir)
    _check_request(out_dir, num_frames, width, height, overwrite, seed, style)
    num_frames, width, height = int(num_frames), int(width), int(height)

    world, poses = _world_and_path(style, seed, num_frames)
    K = default_intrinsics(width, height)
    stamps = _timestamps(num_frames)
    names = [f"{stamp:.6f}.png" for stamp in stamps]

    with _staged(out_dir) as staging:
        (staging / "rgb").mkdir()
        (staging / "depth").mkdir()
        floor_only = np.zeros(num_frames, bool)
        depth_min, depth_max = np.inf, 0.0
        sheet_indices = np.unique(np.linspace(0, num_frames - 1, min(sheet_frames, num_frames)).round().astype(int))
        sheet_images = {}
        for start in range(0, num_frames, block_frames):
            stop = min(start + block_frames, num_frames)
            rgb, depth, surfaces = render_frames(world, poses[start:stop], K, width, height, return_surfaces=True)
            floor_only[start:stop] = np.all(surfaces.reshape(stop - start, -1) == FLOOR_SURFACE, axis=1)
            depth_min = min(depth_min, float(depth.min()))
            depth_max = max(depth_max, float(depth.max()))
            raw_depth = np.clip(np.round(depth * TUM_DEPTH_SCALE), 1, 65535).astype(np.uint16)
            for offset, index in enumerate(range(start, stop)):
                _write_image(staging / "rgb" / names[index], rgb[offset])
                _write_image(staging / "depth" / names[index], raw_depth[offset])
                if index in sheet_indices:
                    sheet_images[index] = rgb[offset].copy()

        header = "# {kind}\n# file: 'sl4slam synthetic world, seed {seed}'\n# timestamp filename\n"
        for kind, folder in (("color images", "rgb"), ("depth maps", "depth")):
            lines = [f"{stamp:.6f} {folder}/{name}" for stamp, name in zip(stamps, names)]
            (staging / f"{folder}.txt").write_text(header.format(kind=kind, seed=seed) + "\n".join(lines) + "\n")
        write_tum_trajectory(staging / "groundtruth.txt", stamps, poses)
        (staging / CALIBRATION_FILE).write_text(
            "sl4slam synthetic world -- pinhole camera, no distortion\n"
            f"Image size: {width} x {height}\n"
            f"fx = {float(K[0, 0])!r}  fy = {float(K[1, 1])!r}  cx = {float(K[0, 2])!r}  cy = {float(K[1, 2])!r}\n"
            "Pixel centres at integer coordinates. Depth PNGs: 16-bit, value / 5000 = metres (z along the optical axis).\n"
            "groundtruth.txt: camera-to-world poses, OpenCV camera axes (x right, y down, z forward), world z up.\n"
        )
        labels = [f"#{i}" + (" floor" if floor_only[i] else "") for i in sheet_indices]
        sheet = contact_sheet(np.stack([sheet_images[i] for i in sheet_indices]), labels)
        cv2.imwrite(str(staging / CONTACT_SHEET_FILE), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))

        floor_start, floor_stop = _longest_run(floor_only)
        floor = {
            "start": floor_start,
            "stop": floor_stop,
            "count": int(floor_only.sum()),
            "description": "frames [start, stop) see nothing but the floor (planar, degenerate case)",
        }
        if style is None or get_style(style).motion == "lap":
            floor["designed_path_interval"] = list(FLOOR_HOLD)
            loop = {"first_frame": 0, "last_frame": num_frames - 1,
                    "description": "the last pose equals the first; the path circles the room once"}
        else:
            loop = {"structure": get_style(style).loops, "description": f"loop structure {get_style(style).loops!r} "
                    "(sl4slam.synthetic.styles: none 0.7 of a lap, one 1.2 laps, many 3.2 or more)"}
        (staging / METADATA_FILE).write_text(_metadata(
            world, seed, num_frames, width, height, K, TUM_DEPTH_SCALE, (depth_min, depth_max),
            floor_only=floor, loop=loop, **_style_metadata(style, poses),
        ))
    logger.info(
        "wrote %d synthetic frames to %s (floor-only frames %d..%d)", num_frames, out_dir, floor_start, floor_stop - 1
    )
    return out_dir


def write_seven_scenes_sequence(
    out_dir: str | Path,
    num_frames: int = 600,
    width: int = 320,
    height: int = 240,
    seed: int = 0,
    overwrite: bool = False,
    block_frames: int = 32,
    style: str | None = None,
) -> Path:
    """Render the synthetic world ``seed`` (or a style's world and path) and write it as a 7-Scenes
    sequence folder (``seq-XX``).

    The layout of the dataset's archives: ``frame-XXXXXX.color.png`` (8-bit RGB),
    ``frame-XXXXXX.depth.png`` (16-bit millimetres, 65535 = invalid; every rendered pixel is
    valid) and ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world matrix), plus ``synthetic.json``
    (seed, size, ``K``). The camera is the published 7-Scenes one (fx = fy = 585, cx = 320,
    cy = 240 at 640x480) scaled to ``width`` x ``height``, which is what
    :class:`sl4slam.io.SevenScenesSource` and the dense evaluation assume for this layout; 4:3
    sizes keep square pixels.

    For an evaluation root, write it as ``ROOT/<scene>/seq-01``. Written to a temporary sibling
    folder, then renamed into place. Arguments as :func:`write_synthetic_sequence`; the style is
    recorded in ``synthetic.json``.
    """
    out_dir = Path(out_dir)
    _check_request(out_dir, num_frames, width, height, overwrite, seed, style)
    num_frames, width, height = int(num_frames), int(width), int(height)

    world, poses = _world_and_path(style, seed, num_frames)
    K = seven_scenes_intrinsics(width, height)
    with _staged(out_dir) as staging:
        depth_min, depth_max = np.inf, 0.0
        for start in range(0, num_frames, block_frames):
            stop = min(start + block_frames, num_frames)
            rgb, depth = render_frames(world, poses[start:stop], K, width, height)
            depth_min = min(depth_min, float(depth.min()))
            depth_max = max(depth_max, float(depth.max()))
            # millimetres; 65535 is reserved for "no measurement"
            raw_depth = np.clip(np.round(depth * 1000.0), 1, SEVEN_SCENES_INVALID_DEPTH - 1).astype(np.uint16)
            for offset, index in enumerate(range(start, stop)):
                stem = staging / f"frame-{index:06d}"
                _write_image(stem.with_name(stem.name + ".color.png"), rgb[offset])
                _write_image(stem.with_name(stem.name + ".depth.png"), raw_depth[offset])
                np.savetxt(stem.with_name(stem.name + ".pose.txt"), poses[index], fmt="%.10e", delimiter="\t")
        (staging / METADATA_FILE).write_text(_metadata(world, seed, num_frames, width, height, K, 1000.0,
                                                       (depth_min, depth_max), layout="7scenes",
                                                       **_style_metadata(style, poses)))
    logger.info("wrote %d synthetic frames in the 7-Scenes layout to %s", num_frames, out_dir)
    return out_dir


def read_synthetic_metadata(folder: str | Path) -> dict:
    """The ``synthetic.json`` of a folder written by :func:`write_synthetic_sequence`."""
    path = Path(folder) / METADATA_FILE
    if not path.is_file():
        raise UserError(f"{folder} has no {METADATA_FILE}; it was not written by write_synthetic_sequence")
    return json.loads(path.read_text())
