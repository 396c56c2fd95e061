"""Our back end against the VGGT-SLAM authors' v1 code, both fed the same recorded submaps and loops.

One row is one (world, profile, seed, our settings). Our pipeline runs with the simulated frontend and
ORB retrieval while its submaps are recorded (``sl4slam.frontend.cache.CachingFrontend``); then, on
that same recording:

- **ours**: the recorded run itself (the given settings; default: the library defaults);
- **ours sim3**: our Sim(3) submap graph (``backend.kind = "sim3"``) replayed from the recording;
- **theirs Sim(3)** and **theirs SL(4)**: the authors' ``vggt_slam.solver.Solver.add_points`` with
  ``use_sim3=True`` (a Pose3 graph over submaps rescaled by their points' norm ratio) and
  ``use_sim3=False`` (SL(4) graph, ``h_solve.ransac_projective``), given every submap our run kept,
  in the same order and with the same ids, and exactly the loops our run accepted (same submap pairs,
  same loop frames). Their graph is optimized and their submaps updated after every submap, as
  their ``main.py`` does; each keyframe's pose is read with their
  ``Submap.get_all_poses_world(ignore_loop_closure_frames=True)``.

All four trajectories are scored the same way: ATE RMSE in metres after Sim(3) alignment
(``sl4slam.metrics.ate``) against the ground truth of our run's keyframes.

Their code is never part of the product: it is loaded here, at run time, from a checkout given with
``--vggt-slam`` (a directory holding ``vggt_slam/solver.py``, branch ``version1.0`` of
MIT-SPARK/VGGT-SLAM). Modules their code imports but this machine lacks (the ``vggt`` package,
SALAD, torchvision, termcolor, ...) get stand-ins in ``sys.modules``; the two geometry functions
their solver calls from ``vggt.utils.geometry`` are written here from their documented meaning. The
solver is built without its viewer or image retrieval, and without CUDA its RANSAC's hard-coded
``device='cuda'`` tensor is made on the CPU.

Layout: our recorded submap is ``[shared frame(s)] + new keyframes + loop frames``; theirs is
``[one shared frame] + new keyframes + loop frames`` with the shared frame's camera at the origin.
:func:`their_layout` picks the slots to hand over (the last shared frame only, the accepted loops'
frames only) and :func:`reanchor` moves the submap frame onto the kept shared frame's camera.

    python benchmarks/bench_authors_v1.py --vggt-slam /path/to/VGGT-SLAM --worlds synthetic,desk --seeds 5
    python benchmarks/bench_authors_v1.py --vggt-slam /path/to/VGGT-SLAM --profile clean --worlds synthetic --seeds 1
    python benchmarks/bench_authors_v1.py --report

Rows accumulate in ``benchmarks/out/authors_v1/rows.jsonl`` (a row already there is not run again);
the report goes to ``benchmarks/results/authors_v1.md``. The ``clean`` profile (exact submaps, no
depth noise, no outliers) checks the harness: every trajectory comes out with ATE about 0, except
theirs in SL(4) mode wherever its RANSAC cannot fit a link (a shared frame that sees one plane).
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import datetime  # noqa: E402
import importlib  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Sequence  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the harness, also when loaded by path (tests)
from harness import OUT, parse_settings as _parse_settings, result_file, shared_sequence  # noqa: E402
from harness import make_frontend, run_sequence, simulated_config, synthetic_world, write_report  # noqa: E402

WORK = OUT / "authors_v1"
ROWS = WORK / "rows.jsonl"
TUM_DESK = shared_sequence("desk")
WORLDS = {"synthetic": "synthetic world (600 frames, 320x240, one lap)", "desk": "TUM fr1/desk (613 frames)"}
PROFILES = {
    # name: (sim profile, explicit magnitudes, what it is)
    "vggt": ("vggt", {}, "VGGT-like errors (per-frame cameras, focal, smooth depth warps, flying pixels)"),
    "hard": ("hard", {}, "about twice the vggt errors"),
    "exact": ("exact", {}, "one exact SL(4) transform per submap, small depth noise and outlier blobs"),
    "clean": ("exact", {"depth_noise": 0.0, "outlier_fraction": 0.0},
              "exact submaps without noise or outliers (checks the harness: ATE about 0)"),
}
METHODS = {
    # row key: column title
    "ours": "ours",
    "ours_sim3": "ours Sim(3) (replay)",
    "theirs_sim3": "theirs Sim(3)",
    "theirs_sl4": "theirs SL(4)",
}
THEIR_FILES = ("vggt_slam/solver.py", "vggt_slam/graph.py", "vggt_slam/graph_se3.py", "vggt_slam/submap.py",
               "vggt_slam/map.py", "vggt_slam/h_solve.py", "vggt_slam/loop_closure.py")
CONF_PERCENTILE = 25.0
"""``init_conf_threshold`` of their solver: the lowest 25 % of a submap's confidence is dropped
(their ``main.py`` default ``--conf_threshold 25``)."""


# ---------------------------------------------------------------------------------------------- checks
def checkout_problem(path: str | os.PathLike | None) -> str | None:
    """Why ``path`` is not a usable checkout of the authors' v1 code (one line naming the fix), or ``None``."""
    fix = ("pass --vggt-slam PATH, a checkout of branch version1.0 of MIT-SPARK/VGGT-SLAM "
           "(git clone -b version1.0 https://github.com/MIT-SPARK/VGGT-SLAM PATH)")
    if path is None:
        return f"no checkout of the authors' code given; {fix}"
    root = Path(path)
    if not root.is_dir():
        return f"--vggt-slam {path}: no such directory; {fix}"
    missing = [name for name in THEIR_FILES if not (root / name).is_file()]
    if "vggt_slam/solver.py" in missing:
        return f"--vggt-slam {path}: no vggt_slam/solver.py there; {fix}"
    if missing:
        return f"--vggt-slam {path}: not the version1.0 code (no {', '.join(missing)}); {fix}"
    if "def add_points" not in (root / "vggt_slam/solver.py").read_text(errors="replace"):
        return f"--vggt-slam {path}: its vggt_slam/solver.py has no Solver.add_points (another version); {fix}"
    try:
        import gtsam
    except ImportError:
        return "gtsam is not installed; their solver needs it (pip install gtsam, a build with SL4)"
    if not all(hasattr(gtsam, name) for name in ("SL4", "BetweenFactorSL4", "PriorFactorSL4")):
        return "this gtsam has no SL4 type; their SL(4) graph needs a gtsam built with SL4 (as this project uses)"
    return None


# ---------------------------------------------------------------------------------------------- layout
@dataclass(frozen=True)
class TheirLayout:
    """One recorded submap as the authors' solver expects it.

    Attributes:
        slots: recorded slots handed over, in order: ``[last shared frame] + new keyframes + kept loop
            frames`` (no shared frame for a first submap).
        frame_indices: the source frame index of each handed-over slot.
        last_non_loop: their ``last_non_loop_frame_index``: position of the last new keyframe.
        loop_frames: the kept loop frames' source indices, in the order of their positions
            (``last_non_loop + 1 + k``).
    """

    slots: tuple[int, ...]
    frame_indices: tuple[int, ...]
    last_non_loop: int
    loop_frames: tuple[int, ...]

    @property
    def non_loop_frames(self) -> tuple[int, ...]:
        """Frames reported from this submap's poses (``[shared] + new keyframes``)."""
        return self.frame_indices[: self.last_non_loop + 1]


def non_loop_count(frame_indices: Sequence[int]) -> int:
    """Number of leading non-loop frames of a recorded submap: its frames increase in source order
    (shared frames, then new keyframes); loop frames, older keyframes appended after them, break
    the order."""
    indices = np.asarray(frame_indices, dtype=np.int64)
    falls = np.flatnonzero(np.diff(indices) <= 0)
    return int(falls[0] + 1) if len(falls) else len(indices)


def their_layout(frame_indices: Sequence[int], previous_non_loop: Sequence[int] | None,
                 kept_loop_frames: Sequence[int] = ()) -> TheirLayout:
    """The slots of one recorded submap to hand the authors' solver.

    Args:
        frame_indices: the recorded submap's source frame indices (``[shared] + new + loop frames``).
        previous_non_loop: the previous submap's non-loop frames (``None`` for a first submap). The
            leading frames of this submap found there are the shared ones; only the last is kept,
            so that their code sees its own one-frame overlap.
        kept_loop_frames: loop frames to keep (those of accepted loops); the other loop frames are
            dropped.

    Raises:
        ValueError: the submap shares no frame with the previous one, or a loop frame to keep is not
            among its loop frames.
    """
    indices = [int(i) for i in frame_indices]
    non_loop = non_loop_count(indices)
    shared = 0
    if previous_non_loop is not None:
        before = {int(i) for i in previous_non_loop}
        while shared < non_loop and indices[shared] in before:
            shared += 1
        if shared == 0:
            raise ValueError(f"the submap with frames {indices} shares no frame with the previous submap")
        if shared == non_loop:
            raise ValueError(f"the submap with frames {indices} has no new keyframe")
    keep = {int(i) for i in kept_loop_frames}
    loop_slots = [slot for slot in range(non_loop, len(indices)) if indices[slot] in keep]
    missing = keep - {indices[slot] for slot in loop_slots}
    if missing:
        raise ValueError(f"loop frame(s) {sorted(missing)} not among the loop frames of the submap {indices}")
    first = shared - 1 if shared else 0
    slots = tuple(range(first, non_loop)) + tuple(loop_slots)
    return TheirLayout(slots=slots, frame_indices=tuple(indices[s] for s in slots),
                       last_non_loop=non_loop - 1 - first, loop_frames=tuple(indices[s] for s in loop_slots))


def reanchor(T_cam_submap: np.ndarray, slot: int) -> np.ndarray:
    """``(S, 4, 4)`` extrinsics of the same cameras in a submap frame moved onto camera ``slot``
    (which becomes the identity). Their code takes the first frame's camera as the submap frame
    (VGGT's convention); when the shared frames before it are dropped, the submap frame must follow.
    Depths are per camera and stay as they are."""
    T = np.repeat(np.eye(4)[None], len(T_cam_submap), axis=0)
    T[:, :3, :] = np.asarray(T_cam_submap, dtype=np.float64)[:, :3, :]
    T_submap_anchor = np.linalg.inv(T[slot])
    out = T @ T_submap_anchor
    out[slot] = np.eye(4)
    return out


# ---------------------------------------------------------------------------------------------- their code
def closed_form_inverse_se3(se3: np.ndarray, R: np.ndarray | None = None, T: np.ndarray | None = None) -> np.ndarray:
    """Stand-in for ``vggt.utils.geometry.closed_form_inverse_se3``: ``(N, 4, 4)`` inverses of rigid
    ``(N, 3|4, 4)`` transforms (``[R^T | -R^T t]``)."""
    se3 = np.asarray(se3)
    R = se3[:, :3, :3] if R is None else R
    T = se3[:, :3, 3:] if T is None else T
    R_t = np.swapaxes(R, 1, 2)
    out = np.repeat(np.eye(4, dtype=se3.dtype)[None], len(se3), axis=0)
    out[:, :3, :3] = R_t
    out[:, :3, 3:] = -R_t @ T
    return out


def unproject_depth_map_to_point_map(depth_map: np.ndarray, extrinsics_cam: np.ndarray,
                                     intrinsics_cam: np.ndarray) -> np.ndarray:
    """Stand-in for ``vggt.utils.geometry.unproject_depth_map_to_point_map``: ``(S, H, W, 3)`` float32
    points in the submap frame from depth ``(S, H, W[, 1])``, camera-from-submap extrinsics
    ``(S, 3, 4)`` and intrinsics ``(S, 3, 3)``; pixel ``(u, v)`` is column ``u``, row ``v`` (VGGT's
    grid). The full inverse of K is used, so a skewed camera is unprojected along its own rays."""
    depth = np.asarray(depth_map)
    depth = depth[..., 0] if depth.ndim == 4 else depth
    S, height, width = depth.shape
    T_submap_cam = closed_form_inverse_se3(np.asarray(extrinsics_cam, dtype=np.float64))
    M = T_submap_cam[:, :3, :3] @ np.linalg.inv(np.asarray(intrinsics_cam, dtype=np.float64))  # pixel -> ray
    v, u = np.mgrid[0:height, 0:width]
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3).astype(np.float32)
    points = np.einsum("nj,sij->sni", pixels, M.astype(np.float32), optimize=True)
    points *= depth.reshape(S, -1, 1).astype(np.float32, copy=False)
    points += T_submap_cam[:, None, :3, 3].astype(np.float32)
    return points.reshape(S, height, width, 3)


class _Inert:
    """Stands for anything of a module this benchmark never uses (callable, any attribute)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __call__(self, *args: Any, **kwargs: Any) -> "_Inert":
        return _Inert()

    def __getattr__(self, name: str) -> "_Inert":
        if name.startswith("__"):
            raise AttributeError(name)
        return _Inert()


class _StandIn(types.ModuleType):
    """A module registered in place of a missing one: the given attributes, anything else inert."""

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        return _Inert


def _register_stand_in(name: str, **attributes: Any) -> None:
    """Register ``name`` (and its missing parents) in ``sys.modules`` unless it can be imported."""
    try:
        importlib.import_module(name)
        return
    except ImportError:
        pass
    parts = name.split(".")
    for depth in range(1, len(parts) + 1):
        dotted = ".".join(parts[:depth])
        if dotted not in sys.modules:
            module = _StandIn(dotted)
            module.__path__ = []  # a package, so that submodules resolve
            sys.modules[dotted] = module
            if depth > 1:
                setattr(sys.modules[".".join(parts[: depth - 1])], parts[depth - 1], module)
    for key, value in attributes.items():
        setattr(sys.modules[name], key, value)


class _TorchOnCPU(types.ModuleType):
    """``torch`` as their RANSAC sees it on a machine without CUDA: ``torch.tensor(..., device='cuda')``
    (hard-coded in their ``estimate_3D_homography``) makes a CPU tensor; everything else is torch."""

    def __init__(self, torch_module: types.ModuleType) -> None:
        super().__init__("torch")
        self._torch = torch_module

    def __getattr__(self, name: str) -> Any:
        return getattr(self._torch, name)

    def tensor(self, *args: Any, device: Any = None, **kwargs: Any) -> Any:
        return self._torch.tensor(*args, **kwargs)


class _NoViewer:
    """Replaces their viser / trimesh viewers: a benchmark shows nothing."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass


class _NoRetrieval:
    """Replaces their SALAD image retrieval: the loops come from our run."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass


def load_their_modules(checkout: str | os.PathLike) -> types.SimpleNamespace:
    """Import the authors' ``vggt_slam`` modules from ``checkout``, with stand-ins for what is missing."""
    root = str(Path(checkout).resolve())
    _register_stand_in("termcolor", colored=lambda text, *args, **kwargs: text)
    _register_stand_in("vggt.utils.geometry", closed_form_inverse_se3=closed_form_inverse_se3,
                       unproject_depth_map_to_point_map=unproject_depth_map_to_point_map)
    for name in ("vggt.utils.load_fn", "vggt.utils.pose_enc", "salad.eval", "torchvision.transforms", "viser.transforms",
                 "open3d", "trimesh", "PIL.Image"):
        _register_stand_in(name)
    for name in ("matplotlib.pyplot", "mpl_toolkits.mplot3d"):
        _register_stand_in(name)
    if root not in sys.path:
        sys.path.insert(0, root)
    loaded = sys.modules.get("vggt_slam")
    if loaded is not None and not str(getattr(loaded, "__file__", "") or "").startswith(root):
        raise RuntimeError(f"another vggt_slam package is already imported ({loaded.__file__})")
    modules = types.SimpleNamespace(**{name: importlib.import_module(f"vggt_slam.{name}") for name in (
        "solver", "submap", "map", "graph", "graph_se3", "h_solve", "loop_closure")})
    import torch

    if not torch.cuda.is_available() and not isinstance(modules.h_solve.torch, _TorchOnCPU):
        modules.h_solve.torch = _TorchOnCPU(torch)
    modules.solver.Viewer = _NoViewer
    modules.solver.TrimeshViewer = _NoViewer
    modules.solver.ImageRetrieval = _NoRetrieval
    return modules


@dataclass
class Recording:
    """One recorded submap our run kept, in their layout."""

    submap_id: int
    layout: TheirLayout
    path: Path


def their_recordings(record_dir: Path, result) -> list[Recording]:
    """The recorded submaps our run kept (every submap holding a keyframe), in id order, converted to
    their layout with the loops our run accepted."""
    kept_ids = sorted({k.submap_id for k in result.keyframes})
    accepted = {}
    for edge in result.edges:
        if edge.kind == "loop" and edge.accepted:
            accepted.setdefault(edge.submap_to, []).append(int(edge.frame_index))
    recordings, previous = [], None
    for submap_id in kept_ids:
        path = record_dir / f"submap_{submap_id:05d}.npz"
        with np.load(path) as data:
            indices = data["frame_indices"].tolist()
        layout = their_layout(indices, previous, accepted.get(submap_id, ()))
        recordings.append(Recording(submap_id, layout, path))
        previous = layout.non_loop_frames
    return recordings


def their_prediction(recording: Recording, modules: types.SimpleNamespace, loops: list) -> dict:
    """The ``pred_dict`` their ``Solver.add_points`` takes, from a recorded submap (their layout)."""
    slots = list(recording.layout.slots)
    with np.load(recording.path) as data:
        T_cam_submap = reanchor(data["T_cam_submap"][slots], 0)
        colors = data["colors"][slots]
        return {
            "images": np.ascontiguousarray(colors.transpose(0, 3, 1, 2), dtype=np.float32) / 255.0,
            "extrinsic": T_cam_submap[:, :3, :],
            "intrinsic": np.asarray(data["K"][slots], dtype=np.float64),
            "depth": np.asarray(data["depth"][slots], dtype=np.float32)[..., None],
            "depth_conf": np.asarray(data["confidence"][slots], dtype=np.float32),
            "detected_loops": loops,
        }


def run_theirs(modules: types.SimpleNamespace, recordings: list[Recording], use_sim3: bool,
               seed: int) -> tuple[dict[int, np.ndarray], int]:
    """Feed the recordings to their solver (``main.py``'s loop without the model).

    Returns ``{frame_index: T_world_cam}`` for every keyframe, read once (a shared frame from the
    submap in which it was new), and how many of their RANSAC fits returned the identity (all 300
    minimal samples degenerate, e.g. a shared frame that sees a single plane)."""
    import torch

    torch.manual_seed(seed)  # their RANSAC samples with torch's global generator
    identity_fits = 0
    ransac = modules.solver.ransac_projective

    def counted_ransac(*args: Any, **kwargs: Any) -> np.ndarray:
        nonlocal identity_fits
        H = ransac(*args, **kwargs)
        identity_fits += bool(np.array_equal(H, np.eye(4)))
        return H

    modules.solver.ransac_projective = counted_ransac
    try:
        poses = _feed_their_solver(modules, recordings, use_sim3)
    finally:
        modules.solver.ransac_projective = ransac
    return poses, identity_fits


def _feed_their_solver(modules: types.SimpleNamespace, recordings: list[Recording], use_sim3: bool) -> dict[int, np.ndarray]:
    """The body of :func:`run_theirs`: every submap through ``add_points``, optimize, read the poses."""
    slot_of = {r.submap_id: {f: s for s, f in enumerate(r.layout.non_loop_frames)} for r in recordings}
    # the submap in which each keyframe was new (a shared frame belongs to the submap before)
    detected_in: dict[int, int] = {}
    for recording in recordings:
        for frame in recording.layout.non_loop_frames:
            detected_in.setdefault(frame, recording.submap_id)
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):
        solver = modules.solver.Solver(init_conf_threshold=CONF_PERCENTILE, use_sim3=use_sim3)
        for recording in recordings:
            layout = recording.layout
            submap = modules.submap.Submap(recording.submap_id)
            submap.set_last_non_loop_frame_index(layout.last_non_loop)
            loops = []
            for frame in layout.loop_frames:
                detected = detected_in[frame]
                loops.append(modules.loop_closure.LoopMatch(
                    similarity_score=0.0, query_submap_id=recording.submap_id, query_submap_frame=0,
                    detected_submap_id=detected, detected_submap_frame=slot_of[detected][frame]))
            solver.current_working_submap = submap
            solver.add_points(their_prediction(recording, modules, loops))
            solver.graph.optimize()
            solver.map.update_submap_homographies(solver.graph)
            quiet.seek(0)
            quiet.truncate()
    poses = {}
    for number, recording in enumerate(recordings):
        T = solver.map.get_submap(recording.submap_id).get_all_poses_world(ignore_loop_closure_frames=True)
        frames = recording.layout.non_loop_frames
        for slot in range(0 if number == 0 else 1, len(frames)):
            poses[frames[slot]] = T[slot]
    return poses


# ---------------------------------------------------------------------------------------------- our side
def world_path(name: str, data: Path | None = None) -> Path:
    """The sequence of a world (the synthetic world at 320x240 is the rendering bench_levers.py uses)."""
    if name == "desk":
        return data if data is not None else TUM_DESK
    return synthetic_world(320, 240)


def parse_settings(pairs: Sequence[str]) -> dict[str, Any]:
    """``["submap.overlap=2", "backend.graph=submap"]`` -> ``{"submap.overlap": 2, ...}`` (values read
    as JSON where they parse, else as text; ``ValueError`` naming ``--ours`` for a pair that is not
    ``section.name=value``)."""
    return _parse_settings(pairs, flag="--ours")


def make_config(profile: str, seed: int, settings: dict[str, Any]):
    """Our run's config: simulated frontend with ``profile``, ORB retrieval, ``settings`` on top."""
    sim_profile, magnitudes, _ = PROFILES[profile]
    return simulated_config({"sim.profile": sim_profile, "sim.seed": seed,
                             **{f"sim.{key}": value for key, value in magnitudes.items()},
                             "retrieval.kind": "orb", "retrieval.seed": seed, "alignment.seed": seed, **settings})


def _ate(poses: dict[int, np.ndarray], truth: dict[int, tuple[float, np.ndarray]]) -> float:
    """Sim(3)-aligned ATE RMSE (metres) of ``{frame_index: T_world_cam}`` against ``truth``."""
    from sl4slam.metrics import ate

    frames = sorted(poses)
    stamps = np.array([truth[f][0] for f in frames])
    estimate = np.stack([poses[f] for f in frames])
    gt = np.stack([truth[f][1] for f in frames])
    return float(ate(stamps, estimate, stamps, gt).rmse)


def one_row(world: str, profile: str, seed: int, settings: dict[str, Any], checkout: str, data: Path | None,
            keep_recording: bool = False) -> dict:
    """Run the four back ends of the module doc on one recording and return the row."""
    record_dir = WORK / "recordings" / f"{world}_{profile}_s{seed}"
    shutil.rmtree(record_dir, ignore_errors=True)
    sequence = str(world_path(world, data))
    row: dict[str, Any] = {"world": world, "profile": profile, "seed": seed, "ours_settings": settings,
                           "date": str(datetime.date.today())}
    seconds: dict[str, float] = {}

    config = make_config(profile, seed, settings)
    ours_run = run_sequence(config, sequence, frontend=make_frontend(config, cache_dir=record_dir))
    result = ours_run.result
    seconds["ours"] = ours_run.seconds
    truth = {k.frame_index: (k.timestamp, gt) for k, gt in zip(result.keyframes, result.T_world_cam_gt)}
    ours = {k.frame_index: T for k, T in zip(result.keyframes, result.T_world_cam)}
    row["ours"] = _ate(ours, truth)
    loops = [e for e in result.edges if e.kind == "loop"]
    row.update(keyframes=len(result.keyframes), submaps=len({k.submap_id for k in result.keyframes}),
               loops=sum(e.accepted for e in loops), proposed=len(loops))

    sim3_settings = {**settings, "backend.kind": "sim3"}
    sim3_config = make_config(profile, seed, sim3_settings)
    replay = run_sequence(sim3_config, sequence, frontend=make_frontend(sim3_config, replay_dir=record_dir))
    replayed = replay.result
    seconds["ours_sim3"] = replay.seconds
    row["ours_sim3"] = _ate({k.frame_index: T for k, T in zip(replayed.keyframes, replayed.T_world_cam)}, truth)
    row["ours_sim3_loops"] = sum(e.accepted for e in replayed.edges if e.kind == "loop")

    modules = load_their_modules(checkout)
    recordings = their_recordings(record_dir, result)
    for key, use_sim3 in (("theirs_sim3", True), ("theirs_sl4", False)):
        start = time.perf_counter()
        poses, row[f"{key}_identity_fits"] = run_theirs(modules, recordings, use_sim3, seed)
        seconds[key] = time.perf_counter() - start
        if set(poses) != set(truth):
            raise RuntimeError(f"{key}: poses for {len(poses)} frames, our run has {len(truth)} keyframes")
        row[key] = _ate(poses, truth)
    row["loops_fed"] = sum(len(r.layout.loop_frames) for r in recordings)
    row["seconds"] = seconds
    if not keep_recording:
        shutil.rmtree(record_dir, ignore_errors=True)
    return row


# ---------------------------------------------------------------------------------------------- driving
def row_key(world: str, profile: str, seed: int, settings: dict[str, Any]) -> str:
    return json.dumps([world, profile, seed, settings], sort_keys=True)


def load_rows() -> list[dict]:
    return [json.loads(line) for line in ROWS.read_text().splitlines() if line.strip()] if ROWS.is_file() else []


def run_rows(worlds: list[str], profile: str, seeds: list[int], settings: dict[str, Any], checkout: str,
             data: Path | None, keep_recording: bool) -> None:
    """Run every missing row, one after the other, appending each to ``rows.jsonl``."""
    WORK.mkdir(parents=True, exist_ok=True)
    done = {row_key(r["world"], r["profile"], r["seed"], r["ours_settings"]) for r in load_rows()}
    todo = [(w, s) for w in worlds for s in seeds if row_key(w, profile, s, settings) not in done]
    print(f"{len(todo)} rows to run ({len(worlds) * len(seeds) - len(todo)} cached)", flush=True)
    for world, seed in todo:
        try:
            row = one_row(world, profile, seed, settings, checkout, data, keep_recording)
        except Exception as exc:  # a row that breaks is reported, the others still run
            print(f"{world} seed {seed}: FAILED {type(exc).__name__}: {exc}", flush=True)
            continue
        with open(ROWS, "a") as log:
            log.write(json.dumps(row) + "\n")
        print(f"{world} seed {seed}: " + ", ".join(f"{METHODS[m]} {row[m]:.4f} m" for m in METHODS)
              + f"; {row['loops']}/{row['proposed']} loops, {sum(row['seconds'].values()):.0f} s", flush=True)


def _settings_text(settings: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in settings.items()) or "library defaults"


NOTES = [
    "Their `Solver.add_points` masks the shared frame's points with `prior_conf > threshold * (conf > threshold)`: "
    "by operator precedence a pixel the new submap is not confident about is kept whenever the old confidence is "
    "above 0, i.e. always (VGGT's confidence is at least 1); only pixels the new submap trusts and the old one does "
    "not are dropped, and both sides use the old submap's threshold. Loop links (SL(4) mode) use every pixel of the "
    "loop frame, unmasked.",
    "Their SL(4) link (`h_solve.ransac_projective`) returns the best 5-point minimal fit of 300, never refitted to its "
    "inliers: when all hypotheses are within the 0.01 inlier threshold (clean data) the first one wins, so a link is "
    "only as good as that threshold allows. A shared frame that sees a single plane makes every 5-point system "
    "degenerate; each hypothesis then falls back to the identity and the link becomes the identity (column "
    "\"identity fits\"). Without CUDA their `estimate_3D_homography` fails (a hard-coded `device='cuda'` tensor); "
    "here that tensor is made on the CPU. Their RANSAC draws from torch's global generator, seeded per row.",
    "Their Sim(3) mode rescales each new submap by the mean ratio of the shared frame's per-pixel distances to its "
    "camera (old over new, same mask as above), then links submaps with Pose3 (SE(3)) factors: scale is fixed once "
    "per submap and no loop can correct it; a loop's relative pose comes from the two submaps' (rescaled) cameras "
    "of the loop frame.",
]


RATIO_FLOOR = 1e-4
"""Below this ATE (metres, a tenth of a millimetre) theirs is taken as exact and no ratio is formed."""


def _metres(value: float) -> str:
    """An ATE for the tables: 4 decimals, or 1 significant digit below a tenth of a millimetre (so that
    a harness check shows how close to 0 it is)."""
    return f"{value:.4f}" if value >= RATIO_FLOOR else f"{value:.0e}"


def _ratio_text(row: dict) -> str:
    return f"{row['ours'] / row['theirs_sim3']:.2f}" if row["theirs_sim3"] > RATIO_FLOOR else "-"


def _table_command(world: str, profile: str, seeds: list[int], settings: dict[str, Any]) -> str:
    """The command that makes one table's rows."""
    count = len(seeds) if seeds == list(range(len(seeds))) else None
    text = (f"python benchmarks/bench_authors_v1.py --vggt-slam PATH --worlds {world} "
            f"--seeds {count if count else ','.join(map(str, seeds))} --profile {profile}")
    return text + ("" if not settings else " --ours " + " ".join(f"{k}={json.dumps(v)}" for k, v in settings.items()))


def report(out: Path) -> None:
    """Write the Markdown report from every row there is (one table per world, profile and settings)."""
    rows = load_rows()
    if not rows:
        print("no rows yet: run the benchmark first")
        return
    lines = ["## Our back end against the VGGT-SLAM authors' v1 code (same recorded submaps, same loops)", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; rows dated "
             f"{min(r['date'] for r in rows)} to {max(r['date'] for r in rows)}. Their code: branch version1.0 of "
             "MIT-SPARK/VGGT-SLAM, loaded from the checkout given with `--vggt-slam`.", "",
             "Our pipeline runs with the simulated frontend and ORB retrieval while its submaps are recorded; the "
             "authors' `Solver.add_points` (`use_sim3=True` and `False`) is then fed the same submaps (one shared "
             "frame each, confidence percentile 25 as in their `main.py`) and exactly the loops our run accepted, "
             "their graph optimized after every submap as their `main.py` does; our Sim(3) submap graph is replayed "
             "on the same recording. ATE RMSE in metres after Sim(3) alignment over the same keyframes; ratio: the "
             "per-seed ours / theirs Sim(3), median and range.", ""]
    groups: dict[str, list[dict]] = {}
    for row in rows:
        groups.setdefault(json.dumps([row["world"], row["profile"], row["ours_settings"]], sort_keys=True), []).append(row)
    order = {name: i for i, name in enumerate(WORLDS)}
    profile_order = {name: i for i, name in enumerate(("vggt", "hard", "exact", "clean"))}
    for key in sorted(groups, key=lambda k: (order.get(json.loads(k)[0], 99), profile_order.get(json.loads(k)[1], 99), k)):
        chosen = sorted(groups[key], key=lambda r: r["seed"])
        world, profile, settings = json.loads(key)
        lines += [f"**{WORLDS.get(world, world)}, {profile} profile** ({PROFILES.get(profile, ('', {}, ''))[2]}); "
                  f"ours: {_settings_text(settings)}. Command: `{_table_command(world, profile, [r['seed'] for r in chosen], settings)}`",
                  "",
                  "| seed | " + " | ".join(METHODS.values()) + " | ours / theirs Sim(3) | their SL(4) identity fits | "
                  "keyframes | submaps | loops fed (accepted / proposed) |",
                  "|---|" + "---|" * (len(METHODS) + 5)]
        for r in chosen:
            lines.append(f"| {r['seed']} | " + " | ".join(_metres(r[m]) for m in METHODS)
                         + f" | {_ratio_text(r)} | {r.get('theirs_sl4_identity_fits', '-')} | "
                           f"{r['keyframes']} | {r['submaps']} | {r['loops_fed']} ({r['loops']} / {r['proposed']}) |")
        medians, ranges = [], []
        for method in METHODS:
            values = np.array([r[method] for r in chosen])
            medians.append(f"**{_metres(np.median(values))}**")
            ranges.append(f"{_metres(values.min())}-{_metres(values.max())}")
        ratios = np.array([r["ours"] / r["theirs_sim3"] for r in chosen if r["theirs_sim3"] > RATIO_FLOOR])
        median_ratio = f"**{np.median(ratios):.2f}**" if len(ratios) else "-"
        ratio_range = f"{ratios.min():.2f}-{ratios.max():.2f}" if len(ratios) else "-"
        lines.append("| median | " + " | ".join(medians) + f" | {median_ratio} | | | | |")
        lines.append("| range | " + " | ".join(ranges) + f" | {ratio_range} | | | | |")
        lines.append("")
    lines += ["What their code does that the figures depend on:", ""] + [f"- {note}" for note in NOTES] + [""]
    write_report(out, lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vggt-slam", metavar="PATH", help="checkout of MIT-SPARK/VGGT-SLAM, branch version1.0")
    parser.add_argument("--worlds", default="synthetic,desk", help="comma-separated: " + ", ".join(WORLDS))
    parser.add_argument("--seeds", default="5", help="a count (seeds 0..n-1) or a list (0,3,4)")
    parser.add_argument("--profile", default="vggt", choices=sorted(PROFILES), help="simulator error profile")
    parser.add_argument("--ours", nargs="*", default=[], metavar="KEY=VALUE",
                        help="settings of our run, e.g. submap.overlap=2 backend.graph=submap (default: the library defaults)")
    parser.add_argument("--data", type=Path, help="TUM fr1/desk folder (default: ../shared/data/tum_rgbd_fr1_desk)")
    parser.add_argument("--keep-recordings", action="store_true", help="keep the recorded submaps under benchmarks/out/authors_v1/")
    parser.add_argument("--report", action="store_true", help="only write the report from the rows there are")
    parser.add_argument("--out", type=Path, default=result_file("authors_v1"))
    args = parser.parse_args(argv)
    if not args.report:
        problem = checkout_problem(args.vggt_slam)
        worlds = [w for w in args.worlds.split(",") if w]
        unknown = [w for w in worlds if w not in WORLDS]
        if problem is None and unknown:
            problem = f"--worlds: unknown world(s) {', '.join(unknown)}; choose from {', '.join(WORLDS)}"
        if problem is None and "desk" in worlds and not (args.data or TUM_DESK).is_dir():
            problem = f"--data {args.data or TUM_DESK}: no such directory; pass the TUM fr1/desk folder with --data"
        try:
            settings = parse_settings(args.ours)
            if problem is None:
                make_config(args.profile, 0, settings).validate()
        except Exception as exc:  # a bad --ours setting: its one line
            problem = problem or str(exc)
        if problem is not None:
            print(f"error: {problem}", file=sys.stderr)
            return 2
        seeds = list(range(int(args.seeds))) if "," not in args.seeds else [int(s) for s in args.seeds.split(",")]
        run_rows(worlds, args.profile, seeds, settings, args.vggt_slam, args.data, args.keep_recordings)
    report(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
