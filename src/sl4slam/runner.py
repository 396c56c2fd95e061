"""One SLAM run from a source path to an output folder (what ``sl4slam run`` does)."""

from __future__ import annotations

import dataclasses
import logging
import sys
from pathlib import Path

from .config import SLAMConfig
from .errors import UserError

log = logging.getLogger("sl4slam")


def run_slam(source_path: str | Path, out_dir: str | Path, config: SLAMConfig, replay_dir: str | None = None,
             progress: bool = True) -> dict:
    """Open ``source_path``, run the pipeline, write every output into ``out_dir``; return the summary."""
    from .frontend import make_frontend
    from .io import open_source
    from .outputs import write_outputs
    from .pipeline import SLAMPipeline, check_config
    from .retrieval import make_retrieval

    check_config(config)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} exists and is not a folder; choose another output folder")
    source = open_source(str(source_path), stride=config.stride, max_frames=config.max_frames)
    if len(source) < 2:
        raise UserError(f"{source.name}: {len(source)} frame(s) found; SLAM needs at least 2 frames")
    cache_dir = out_dir / "frontend_cache" if config.output.cache_frontend else None
    frontend = make_frontend(config, replay_dir=replay_dir, cache_dir=cache_dir)
    retrieval = make_retrieval(config.retrieval, device=_device(config), seed=config.alignment.seed)
    # The source already applied stride and max_frames.
    run_config = dataclasses.replace(config, stride=1, max_frames=0)
    pipeline = SLAMPipeline(run_config, frontend=frontend, retrieval=retrieval)
    result = pipeline.run(source, progress=progress)
    summary = write_outputs(result, out_dir, config, source_name=source.name, skipped=source.skipped)
    print_summary(summary, out_dir, stream=sys.stdout)
    return summary


def _device(config: SLAMConfig) -> str:
    if config.vggt.device != "auto":
        return config.vggt.device
    try:
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    except ImportError:  # pragma: no cover - torch is a dependency
        return "cpu"


def print_summary(summary: dict, out_dir: Path, stream=sys.stdout) -> None:
    counts = summary["counts"]
    line = (f"{counts.get('frames', 0)} frames, {counts.get('keyframes', 0)} keyframes, {counts.get('submaps', 0)} submaps, "
            f"{counts.get('loops', 0)} loops, {counts.get('fallbacks', 0)} fallbacks; {summary['seconds']['total']:.1f} s, "
            f"peak {summary['memory']['peak_rss_mib']:.0f} MiB")
    print(line, file=stream)
    if summary.get("skipped_inputs"):
        print(f"skipped {len(summary['skipped_inputs'])} unreadable input(s); see summary.json", file=stream)
    if "ate" in summary:
        print(f"ATE RMSE {summary['ate']['rmse']:.4f} (Sim(3)-aligned, {summary['ate']['poses']} keyframes)", file=stream)
    print(f"outputs in {out_dir}", file=stream)
