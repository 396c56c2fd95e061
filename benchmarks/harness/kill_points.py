"""A child process for the resume tests and benchmark: ``sl4slam`` that dies (SIGKILL) at a chosen point.

    python kill_points.py POINT LOG sl4slam-arguments...

POINT: "model:K" (in submap K's forward), "graph:K" (in the graph update that holds submap K),
"recording:K" (half-way through writing submap K's recording), "outputs:N" (half-way through the
N-th keyframe file of the outputs), or "" (never). Every submap given to the model is appended to
LOG. The kill is deterministic: the function where it happens is patched, no timer is involved.
"""

import io, os, signal, sys
import numpy as np

point, log = sys.argv[1], sys.argv[2]
kind, _, at = point.partition(":")
at = int(at) if at else -1


def die():
    os.kill(os.getpid(), signal.SIGKILL)


def half_written(path, arrays, compressed):
    # what a kill in the middle of an atomic write leaves: half of the temporary file, no rename
    data = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(data, **arrays)
    path = os.fspath(path)
    head, name = os.path.split(path)
    stem, suffix = os.path.splitext(name)
    with open(os.path.join(head, f".{stem}.{os.getpid()}.tmp{suffix}"), "wb") as tmp:
        tmp.write(data.getvalue()[: len(data.getvalue()) // 2])
    die()


from sl4slam.frontend.simulated import SimulatedFrontend

model = SimulatedFrontend.reconstruct


def reconstruct(self, frames, submap_id, **keywords):
    with open(log, "a") as calls:
        calls.write(f"{submap_id}\n")
    if kind == "model" and submap_id == at:
        die()
    return model(self, frames, submap_id, **keywords)


SimulatedFrontend.reconstruct = reconstruct

if kind == "graph":  # inside the graph update that holds submap `at`
    from sl4slam.backend.keyframe import KeyframeBackend
    from sl4slam.backend.submap import SubmapBackend

    for cls in (KeyframeBackend, SubmapBackend):
        def patch(cls=cls, update=cls.update):
            def killing(self):
                if self.num_submaps == at + 1:
                    die()
                return update(self)
            cls.update = killing
        patch()

if kind == "outputs":  # the at-th keyframe file of the outputs, half written
    import sl4slam.result.outputs as outputs

    written, write = [0], outputs.atomic_write_npz

    def outputs_write(path, arrays, compressed=True):
        written[0] += 1
        if written[0] == at:
            half_written(path, arrays, compressed)
        write(path, arrays, compressed)

    outputs.atomic_write_npz = outputs_write

if kind == "recording":  # submap `at`'s recording, half written
    import sl4slam.frontend.cache as cache

    record = cache.atomic_write_npz

    def recording_write(path, arrays, compressed=True):
        if os.path.basename(os.fspath(path)) == f"submap_{at:05d}.npz":
            half_written(path, arrays, compressed)
        record(path, arrays, compressed)

    cache.atomic_write_npz = recording_write

from sl4slam.cli import main

sys.exit(main(sys.argv[3:]))
