"""The per-frame pose refinement (``sl4slam.refine``) against the simulator's error terms: which
of them it corrects and which it absorbs into the poses.

One window of 17 frames (every 6th frame of the synthetic world at 320x240; every 4th frame with
depth of TUM fr1/desk), the simulated frontend with its ``vggt`` profile and single terms switched
off (no per-submap projective distortion, so that the poses compare with the truth directly), and
the median rotation error of frames 1-16 against the true relative poses, before and after three
refinement steps over the confident pixels (``SubmapConfig.tau_conf``).

    python benchmarks/bench_refine.py
"""

from __future__ import annotations

import numpy as np

from harness import date_text, result_file, synthetic_world, write_report

CASES = [
    ("exact (no error at all)", {"profile": "exact"}),
    ("vggt", {}),
    ("vggt without focal errors", {"focal_error": 0.0}),
    ("vggt without depth warps", {"depth_warp": 0.0}),
    ("vggt without focal errors and depth warps", {"focal_error": 0.0, "depth_warp": 0.0}),
    ("per-frame poses only", {"focal_error": 0.0, "depth_warp": 0.0, "depth_noise": 0.0, "flying_px": 0.0,
                              "outlier_fraction": 0.0, "unrelated_overlap": 0.0}),
]


def window(path: str, step: int) -> list:
    """17 frames with depth: every ``step``-th of the first 200 of ``path``."""
    from sl4slam.io import open_source

    frames = [f for _, f in zip(range(200), iter(open_source(path))) if f.depth is not None]
    return frames[::step][:17]


def rotation_errors(T_cam_submap: np.ndarray, frames: list) -> np.ndarray:
    """Degrees between each frame's rotation and the true one relative to the first frame (frames 1..)."""
    T_world_cam = np.stack([np.asarray(f.T_world_cam, dtype=np.float64) for f in frames])
    true = np.linalg.inv(T_world_cam) @ T_world_cam[0]  # T_cam_i_cam_0
    turned = np.einsum("sji,sjk->sik", T_cam_submap[:, :, :3], true[:, :3, :3])
    return np.degrees(np.arccos(np.clip((np.trace(turned, axis1=1, axis2=2) - 1) / 2, -1, 1)))[1:]


def main() -> None:
    from sl4slam.frontend.settings import SimulatorConfig
    from sl4slam.frontend.simulated import SimulatedFrontend
    from sl4slam.refine import refine_prediction
    from sl4slam.submap import SubmapConfig, confidence_mask

    tau_conf = SubmapConfig().tau_conf
    rows = ["| sequence | simulator | rotation error before (median deg) | after 3 steps | after / before |",
            "|---|---|---|---|---|"]
    sequences = [("synthetic world", str(synthetic_world(320, 240)), 6)]
    from harness import REPO

    desk = REPO.parent / "shared" / "data" / "tum_rgbd_fr1_desk"
    if desk.is_dir():
        sequences.append(("TUM fr1/desk", str(desk), 4))
    for name, path, step in sequences:
        frames = window(path, step)
        for label, terms in CASES:
            if name != "synthetic world" and label not in ("exact (no error at all)", "vggt", "per-frame poses only"):
                continue
            config = SimulatorConfig(**{"profile": "vggt", "perspective": 0.0, "shear": 0.0, "seed": 0, **terms})
            prediction = SimulatedFrontend(config).reconstruct(frames, 1)
            refined = refine_prediction(prediction, confidence_mask(prediction.confidence, prediction.depth, tau_conf), 3)
            before = float(np.median(rotation_errors(prediction.T_cam_submap, frames)))
            after = float(np.median(rotation_errors(refined.T_cam_submap, frames)))
            ratio = f"{after / before:.2f}" if before > 1e-3 else "-"
            rows.append(f"| {name} | {label} | {before:.3f} | {after:.3f} | {ratio} |")
            print(rows[-1], flush=True)
    write_report(result_file("refine"), [
        "## Per-frame pose refinement against the simulator's terms", "",
        f"Date: {date_text()}. Command: `python benchmarks/bench_refine.py`. One window of 17 frames, simulated "
        "frontend, seed 0, no per-submap projective distortion; rotation error of frames 1-16 against the true "
        "relative poses (TUM: the motion-capture poses).", "", *rows, ""])


if __name__ == "__main__":
    main()
