"""The feature-pose correction (``sl4slam.feature_poses``) inside one window, against the simulator's
error terms: how much of each frame's rotation and centre error it removes, and which term stops it.

Windows of 17 frames (every keyframe-spaced frame from frame 40) of three sequences of the suite's
tune half and of TUM fr1/desk (every 4th frame), the simulated frontend with its ``vggt`` profile
and single terms switched off, no per-submap distortion and the submap in metres (so that poses
compare with the truth directly); seeds 0 and 1. Reported: the median over frames 1-16 of the
rotation error (degrees) and the centre error (mm) against the true relative poses, before and
after the correction with 1000 ORB features per frame, and the model and measurement spreads the
correction estimated from the window.

    python benchmarks/bench_feature_poses.py
"""

from __future__ import annotations

import numpy as np

from harness import date_text, result_file, shared_sequence, write_report
from harness.worlds import suite_sequence

WINDOWS = [("office-walk-slow-s0", 9), ("lap-s0", 8), ("hall-walk-slow-s0", 10)]
CASES = [
    ("vggt", {}),
    ("vggt without focal errors", {"focal_error": 0.0}),
    ("vggt without depth warps", {"depth_warp": 0.0}),
    ("vggt without focal errors and depth warps", {"focal_error": 0.0, "depth_warp": 0.0}),
    ("per-frame cameras only", {"focal_error": 0.0, "depth_warp": 0.0, "depth_noise": 0.0, "flying_px": 0.0,
                                "outlier_fraction": 0.0, "unrelated_overlap": 0.0}),
]
REAL_CASES = [("exact (no simulated error)", {"profile": "exact"}), ("vggt", {})]


def true_poses(frames: list) -> np.ndarray:
    """``(S, 4, 4)`` true camera-from-first-camera poses of ``frames``."""
    T_world_cam = np.stack([np.asarray(f.T_world_cam, dtype=np.float64) for f in frames])
    return np.linalg.inv(T_world_cam) @ T_world_cam[0]


def errors(T_cam_submap: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Median rotation error (degrees) and centre error (mm) of frames 1.."""
    T = np.asarray(T_cam_submap, dtype=np.float64)
    turned = np.einsum("sij,skj->sik", T[:, :3, :3], truth[:, :3, :3])
    angles = np.degrees(np.arccos(np.clip((np.trace(turned, axis1=1, axis2=2) - 1) / 2, -1, 1)))[1:]
    centre = lambda P: -np.einsum("sji,sj->si", P[:, :3, :3], P[:, :3, 3])  # noqa: E731
    shifts = np.linalg.norm(centre(T) - centre(truth), axis=1)[1:]
    return float(np.median(angles)), 1000.0 * float(np.median(shifts))


def main() -> None:
    from sl4slam.feature_poses import corrected_poses, measure_pairs
    from sl4slam.frontend.settings import SimulatorConfig
    from sl4slam.frontend.simulated import SimulatedFrontend
    from sl4slam.io import open_source
    from sl4slam.submap import SubmapConfig, confidence_mask

    tau_conf = SubmapConfig().tau_conf
    windows = [(name, [f for f in open_source(str(suite_sequence(name)))][40::step][:17], CASES)
               for name, step in WINDOWS]
    desk = shared_sequence("tum_rgbd_fr1_desk")
    if desk.is_dir():
        frames = [f for _, f in zip(range(200), iter(open_source(str(desk)))) if f.depth is not None]
        windows.append(("TUM fr1/desk", frames[::4][:17], REAL_CASES))
    rows = ["| window | simulator | seed | pairs used | rotation error before / after (deg) | centre error before / "
            "after (mm) | model spread: rotation deg, centre mm | measurement spread: rotation deg, centre mm |",
            "|---|---|---|---|---|---|---|---|"]
    for name, frames, cases in windows:
        truth = true_poses(frames)
        for label, terms in cases:
            for seed in (0, 1):
                config = SimulatorConfig(**{"profile": "vggt", "perspective": 0.0, "shear": 0.0, "scale": 0.0,
                                            "gauge_scale_ratio": 1.0, "normalize_scale": False, "seed": seed,
                                            **terms})
                prediction = SimulatedFrontend(config).reconstruct(frames, 1)
                mask = confidence_mask(prediction.confidence, prediction.depth, tau_conf)
                pairs = measure_pairs(prediction, mask, 1000)
                corrected, found = corrected_poses(prediction.T_cam_submap, pairs)
                (rot_b, cen_b), (rot_a, cen_a) = errors(prediction.T_cam_submap, truth), errors(corrected, truth)
                rows.append(f"| {name} | {label} | {seed} | {found.pairs_used} of {len(pairs)} | {rot_b:.3f} / "
                            f"{rot_a:.3f} | {cen_b:.1f} / {cen_a:.1f} | {np.degrees(found.model_spread[0]):.2f}, "
                            f"{1000 * found.model_spread[1]:.1f} | {np.degrees(found.measurement_spread[0]):.2f}, "
                            f"{1000 * found.measurement_spread[1]:.1f} |")
                print(rows[-1], flush=True)
    write_report(result_file("feature_poses"), [
        "## Feature-pose correction inside one window, by simulator term", "",
        f"Date: {date_text()}. Command: `python benchmarks/bench_feature_poses.py`. Windows of 17 frames, "
        "simulated frontend without per-submap distortion, submaps in metres; medians over frames 1-16 against "
        "the true relative poses (TUM: the motion-capture poses); 1000 ORB features per frame, pairs up to 4 "
        "frames apart. Spreads: per axis, as the correction estimated them.", "", *rows, ""])


if __name__ == "__main__":
    main()
