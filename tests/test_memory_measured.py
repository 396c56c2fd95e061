"""The VGGT memory planner against a measured peak: a small model's forward on the CPU, in a fresh
process, its resident high-water mark (``VmHWM``) beside ``estimate_peak_bytes``.

Margin: the estimate is an upper bound of the whole process's peak (it counts the interpreter and
libraries as ``CPU_RUNTIME_BYTES``), at most :data:`UPPER` times it for this small model, where the
runtime term is most of the estimate (measured 2.0x with the heads one frame at a time, 1.6x three
at a time); the estimate grows with the head chunk by at least :data:`GROWTH` of the measured growth
(measured 0.7x: the head term is set for VGGT-1B's 256 features, not this model's 48).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

UPPER = 2.5
GROWTH = 0.5
SMALL = {"embed_dim": 64, "depth": 2, "num_heads": 2, "patch_embed_depth": 1, "patch_embed_num_heads": 2,
         "camera_trunk_depth": 1, "camera_num_heads": 2, "dpt_features": 48, "dpt_out_channels": [32, 32, 64, 64],
         "dpt_layers": [0, 1, 1, 1]}
FRAMES, HEIGHT, WIDTH = 3, 392, 518

CHILD = """
import json, sys
import torch
torch.set_num_threads(2)
from sl4slam.models.vggt.memory import estimate_peak_bytes
from sl4slam.models.vggt.model import VGGT, VGGTModelConfig, init_random_weights
from sl4slam.models.vggt.precision import apply_precision, resolve_precision

def status(key):
    with open("/proc/self/status") as handle:
        return next(int(line.split()[1]) * 1024 for line in handle if line.startswith(key))

config, frames, height, width, chunk = VGGTModelConfig(**json.loads(sys.argv[1])), *map(int, sys.argv[2:6])
precision = resolve_precision("fp32", torch.device("cpu"))
model = apply_precision(init_random_weights(VGGT(config), seed=0).eval(), precision)
model.set_head_chunk_frames(chunk)
images = torch.rand(frames, 3, height, width)
with torch.inference_mode():
    model(images, heads=("camera", "depth"))
estimate = estimate_peak_bytes(config, precision, frames, height, width, chunk, "cpu", ("camera", "depth"))
print(json.dumps({"measured": status("VmHWM:"), "estimate": estimate}))
"""


def _peak(chunk: int) -> dict:
    proc = subprocess.run([sys.executable, "-c", CHILD, json.dumps(SMALL), str(FRAMES), str(HEIGHT), str(WIDTH),
                           str(chunk)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="VmHWM is read from /proc")
def test_the_vggt_estimate_bounds_the_measured_peak_of_a_forward():
    one, all_frames = _peak(1), _peak(FRAMES)
    for peak in (one, all_frames):
        assert peak["measured"] <= peak["estimate"] <= UPPER * peak["measured"], peak
    measured_growth = all_frames["measured"] - one["measured"]
    estimated_growth = all_frames["estimate"] - one["estimate"]
    assert measured_growth > 0 and estimated_growth >= GROWTH * measured_growth, (one, all_frames)


#: GPU peaks (``torch.cuda.max_memory_allocated``, GiB) of whole runs of TUM fr1/desk on an NVIDIA
#: H200 in bf16 (2026-11-28, ``benchmarks/results/gpu_run.md``), the dense heads 8 frames at a time,
#: and each model's grid for 640x480 frames (height, width); the largest window had 18 frames.
H200_PEAKS = {"vggt": (5.42, 392, 518), "da3-small": (0.95, 378, 504), "da3-large": (4.17, 378, 504)}
H200_WINDOW = 18


@pytest.mark.parametrize("model", sorted(H200_PEAKS))
def test_the_planner_bounds_the_peaks_of_whole_runs_on_a_gpu(model):
    """What ``--max-memory`` plans with is above each measured whole-run peak, by at most 30 %
    (measured 1.27x VGGT-1B, 1.13x DA3-Small, 1.17x DA3-Large), and an 8 GB budget keeps the
    default head chunk for VGGT-1B (the run within an 8 GiB cap kept it and finished)."""
    measured, height, width = H200_PEAKS[model]
    if model == "vggt":
        import torch

        from sl4slam.models.vggt.memory import estimate_peak_bytes, plan_memory
        from sl4slam.models.vggt.model import VGGTModelConfig
        from sl4slam.models.vggt.precision import resolve_precision

        precision = resolve_precision("bf16", torch.device("cuda"))
        estimate = estimate_peak_bytes(VGGTModelConfig(), precision, H200_WINDOW, height, width, 8, "cuda")
        plan = plan_memory(VGGTModelConfig(), precision, 8.0, H200_WINDOW, height, width, 8, "cuda")
        assert plan.head_chunk_frames == 8
    else:
        from sl4slam.models.da3.config import ARCHITECTURES
        from sl4slam.models.da3.memory import estimate_peak_bytes

        estimate = estimate_peak_bytes(ARCHITECTURES[model.split("-")[1]], H200_WINDOW, height, width, 8,
                                       half_precision=True, device_type="cuda")
    assert measured * 2**30 <= estimate <= 1.3 * measured * 2**30, estimate / 2**30
