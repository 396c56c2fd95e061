"""The development suite: render its synthetic sequences, and measure every sequence's properties.

For each sequence of :data:`sl4slam.synthetic.suite.SUITE` (synthetic ones rendered once into
``benchmarks/out/suite/`` at 256x192, real ones read from ``../shared/data``): frames, path length,
mean speed, rotation rate, frames per keyframe (the library's keyframe selector over the frames),
revisits (:mod:`sl4slam.synthetic.properties`) and texture (kind, and the images' mean squared
gradient). Writes the properties section of ``benchmarks/results/suite.md``, with the renderer's
speed over the sequences rendered by this run.

    python benchmarks/bench_suite.py                 # the whole suite
    python benchmarks/bench_suite.py --split tune    # one half

The rows are kept in ``benchmarks/out/suite/properties.json`` (with the seconds each rendering took,
kept while the rendering is reused), which ``bench_levers.py --suite`` reads to project the time of a
full run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from harness import cpu_model, date_text, load_average, memory_gib, replace_section, result_file, table
from harness.worlds import SUITE_OUT, suite_sequence

START, END = "<!-- section:properties -->", "<!-- /section:properties -->"
TITLE = ["# Development suite", ""]


def measure(name: str) -> dict:
    """The properties of one sequence of the suite (rendered first when it is synthetic and not yet there).

    Returns:
        A row: the sequence's fields, its :class:`sl4slam.synthetic.properties.PathProperties`,
        keyframes, gradient energy, image size and the seconds its rendering took (None when reused).
    """
    from sl4slam.io import open_source
    from sl4slam.keyframes import KeyframeSelector
    from sl4slam.synthetic.properties import gradient_energy, path_properties
    from sl4slam.synthetic.suite import get_sequence

    sequence = get_sequence(name)
    rendered = None
    if not sequence.real:
        from sl4slam.synthetic.suite import SUITE_HEIGHT, SUITE_WIDTH, is_rendered

        if not is_rendered(SUITE_OUT / name, sequence, SUITE_WIDTH, SUITE_HEIGHT):
            start = time.perf_counter()
            suite_sequence(name)
            rendered = time.perf_counter() - start
    folder = suite_sequence(name)
    if not folder.is_dir():
        return {"name": name, "missing": str(folder)}
    source = open_source(str(folder))
    selector = KeyframeSelector()
    stamps, poses, energies = [], [], []
    frames = keyframes = 0
    size = None
    for frame in source:
        frames += 1
        keyframes += selector.is_keyframe(frame.rgb)
        size = frame.rgb.shape[1::-1]
        if frame.T_world_cam is not None:
            stamps.append(frame.timestamp)
            poses.append(frame.T_world_cam)
        if frames % 30 == 1:
            energies.append(gradient_energy(frame.rgb))
    props = path_properties(np.array(poses), np.array(stamps))
    return {"name": name, "split": sequence.split, "style": sequence.style, "frames": frames, "keyframes": keyframes,
            "posed": props.frames, "length": props.length_m, "speed": props.speed_m_s, "rotation": props.rotation_deg_s,
            "returns": props.returns, "revisited": props.revisited, "energy": float(np.mean(energies)),
            "size": f"{size[0]}x{size[1]}", "render_seconds": rendered, "date": date_text("%Y-%m-%d")}


def renderer_speed(frames: int = 60) -> dict[str, float]:
    """Milliseconds per frame of the renderer alone (``render_frames`` in memory, the original world
    along its lap) at 160x120, 256x192 and 320x240."""
    from sl4slam.synthetic import camera_path, default_intrinsics, make_world, render_frames

    world, poses = make_world(0), camera_path(frames, 0)
    speed = {}
    for width, height in ((160, 120), (256, 192), (320, 240)):
        start = time.perf_counter()
        render_frames(world, poses, default_intrinsics(width, height), width, height)
        speed[f"{width}x{height}"] = 1000 * (time.perf_counter() - start) / frames
    return speed


def _dates(rows: list[dict]) -> str:
    """The dates the rows were measured on ("A" or "A to B"; today for rows without one)."""
    dates = sorted({r.get("date") or date_text("%Y-%m-%d") for r in rows})
    return dates[0] if len(dates) == 1 else f"{dates[0]} to {dates[-1]}"


def report(rows: list[dict], command: str, out: Path, speed: dict[str, float]) -> None:
    from sl4slam.synthetic.properties import LEAVE_FACTOR, REVISIT_ANGLE_DEG, REVISIT_RADIUS_M
    from sl4slam.synthetic.styles import STYLES
    from sl4slam.synthetic.suite import SPLIT_RULE, SUITE_HEIGHT, SUITE_WIDTH

    body = []
    for r in rows:
        if "missing" in r:
            body.append([r["name"], "validate", "-", "-", "not here", "", "", "", "", "", "", ""])
            continue
        style = STYLES[r["style"]] if r["style"] else None
        kind = f"{style.room}, {style.motion}, {style.speed}, loops {style.loops}" if style else "real (TUM RGB-D)"
        body.append([r["name"], r["split"], kind, style.texture if style else "real", r["frames"],
                     f"{r['length']:.1f}", f"{r['speed']:.2f}", f"{r['rotation']:.1f}",
                     f"{r['frames'] / max(r['keyframes'], 1):.1f}", r["returns"], f"{100 * r['revisited']:.0f}",
                     f"{r['energy']:.0f} ({r['size']})"])
    rendered = [r for r in rows if r.get("render_seconds")]
    synthetic = [r for r in rows if r.get("style")]
    halves = {half: [r for r in synthetic if r["split"] == half] for half in ("tune", "validate")}
    lines = [START, "## Development suite: sequences, properties and the tune / validate split", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores, {memory_gib():.0f} GiB (shared with other work; "
             f"1-minute load average {load_average():.1f} at the end). Python {platform.python_version()}. "
             f"Date: {_dates(rows)}. Command: `{command}`.", "",
             f"Synthetic sequences rendered at {SUITE_WIDTH}x{SUITE_HEIGHT} (`sl4slam synth --suite ROOT` writes the "
             f"same folders), 30 frames per second; real ones at their own size. The suite is defined in "
             f"`src/sl4slam/synthetic/suite.py` (styles in `styles.py`); `sl4slam synth --list` prints it.", "",
             f"**Split**: {SPLIT_RULE} Tune: {len(halves['tune'])} synthetic sequences, "
             f"{sum(r['frames'] for r in halves['tune'])} frames; validate: {len(halves['validate'])} synthetic "
             f"({sum(r['frames'] for r in halves['validate'])} frames) and "
             f"{sum(1 for r in rows if not r.get('style'))} real.", "",
             "Columns: path length and mean speed of the camera centre; rotation: the sum of the angles between "
             "consecutive poses per second; frames / keyframe: frames over the keyframes the library's selector "
             "(Lucas-Kanade disparity, 25 px) makes of them; returns: the most times the camera comes back within "
             f"{REVISIT_RADIUS_M:g} m and {REVISIT_ANGLE_DEG:g} degrees of one earlier pose after having been "
             f"{LEAVE_FACTOR:g}x as far (anchor poses every {REVISIT_RADIUS_M / 2:g} m or {REVISIT_ANGLE_DEG / 2:g} "
             "degrees); revisited: the share of frames within that distance of an earlier pose the camera had left; "
             "gradient: the mean squared grey-level gradient per pixel (texture; it depends on the image size).", "",
             *table(["sequence", "half", "room, motion, speed, loops", "texture", "frames", "path m", "speed m/s",
                     "rotation deg/s", "frames / keyframe", "returns", "revisited %", "gradient (size)"], body), ""]
    if rendered:
        frames = sum(r["frames"] for r in rendered)
        seconds = sum(r["render_seconds"] for r in rendered)
        lines += [f"Rendering ({len(rendered)} synthetic sequences, world, textures and PNG files included, one "
                  f"process): {frames} frames in {seconds:.0f} s, {1000 * seconds / frames:.1f} ms per frame."]
    lines += ["The renderer alone (`render_frames` in memory, the original world along its lap, 60 frames): "
              + ", ".join(f"{ms:.1f} ms per frame at {size}" for size, ms in speed.items()) + ".", ""]
    lines.append(END)
    replace_section(out, START, END, lines, TITLE)


def main() -> None:
    from sl4slam.synthetic.suite import suite_sequences

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--split", choices=["tune", "validate"], help="only one half")
    parser.add_argument("--sequences", help="only these, comma-separated")
    parser.add_argument("--out", type=Path, default=result_file("suite"))
    parser.add_argument("--report", action="store_true",
                        help="only write the section from the rows kept by an earlier run (the renderer's speed is measured)")
    args = parser.parse_args()
    names = args.sequences.split(",") if args.sequences else None
    stored_file = SUITE_OUT / "properties.json"
    stored = json.loads(stored_file.read_text()) if stored_file.is_file() else {}
    rows = []
    for sequence in suite_sequences(args.split, names):
        if args.report:
            if sequence.name in stored:
                rows.append(stored[sequence.name])
            continue
        start = time.perf_counter()
        row = measure(sequence.name)
        if row.get("render_seconds") is None and stored.get(sequence.name, {}).get("render_seconds"):
            row["render_seconds"] = stored[sequence.name]["render_seconds"]  # the rendering was reused
        rows.append(row)
        stored[sequence.name] = row
        print(f"{sequence.name}: {time.perf_counter() - start:.0f} s", flush=True)

    command = "python benchmarks/bench_suite.py" + (f" --split {args.split}" if args.split else "") + \
        (f" --sequences {args.sequences}" if args.sequences else "")
    if args.report:  # the rows are the measuring run's: name its command
        command = stored.get("__command__", "python benchmarks/bench_suite.py")
    else:
        stored["__command__"] = command
        SUITE_OUT.mkdir(parents=True, exist_ok=True)
        stored_file.write_text(json.dumps(stored, indent=1) + "\n")
    report(rows, command, args.out, renderer_speed())


if __name__ == "__main__":
    main()
