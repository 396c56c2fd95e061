"""The evaluation's report: paper-layout Markdown tables, per-run CSV, JSON, and figures.

Files in the output folder:

- ``tables.md``: per grid point, one table laid out as the paper's (a column per sequence and
  the average, a row per metric; mean ± sample standard deviation over the runs), and for a
  sweep one comparison table per metric with a row per grid point;
- ``runs.csv``: one row per (grid point, sequence, run);
- ``results.json``: every number, the settings, and where each run's outputs are;
- ``figures/<point>/<sequence>.png``: the runs' trajectories against the ground truth, and the
  ATE of each run.

A sequence with failed runs shows how many runs succeeded, and a footnote gives each reason.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_path, atomic_write_text
from ..config import SLAMConfig, config_to_dict
from .datasets import get_dataset
from .plan import SEEDED_SETTINGS, EvalOutcome, EvalSettings

TRAJECTORY_METRICS = [("ate_rmse", "ATE RMSE [m]")]
DENSE_METRICS = [("accuracy", "Accuracy [m]"), ("completion", "Completion [m]"), ("chamfer", "Chamfer [m]")]
TIME_ROW = ("seconds_slam", "SLAM time per run [s]")
"""The pipeline's own time (summary.json ``seconds.total``: no process start-up, output writing or metrics)."""
CSV_COLUMNS = ["point", "sequence", "run", "seed", "status", "ate_rmse", "accuracy", "completion", "chamfer",
               "keyframes", "seconds_slam", "seconds_total", "frontend", "reason"]


def metrics_of(dataset: str, dense: bool) -> list[tuple[str, str]]:
    """``(key, label)`` of the metrics reported for a dataset."""
    return TRAJECTORY_METRICS + (DENSE_METRICS if get_dataset(dataset).dense and dense else [])


def _value(result: dict, key: str) -> float | None:
    if key == "seconds_slam":
        return result.get("seconds", {}).get("slam")
    return result.get("metrics", {}).get(key)


def one_line(result: dict) -> str:
    """A progress line for a finished run."""
    where = f"{result['sequence']} run {result['run']}" + (f" [{result['point']}]" if result["point"] != "default" else "")
    if result["status"] != "ok":
        return f"{where}: FAILED: {result['reason']}"
    metrics = result["metrics"]
    text = f"{where}: ATE {metrics['ate_rmse']:.4f} m"
    if "chamfer" in metrics:
        text += f", accuracy {metrics['accuracy']:.4f} m, completion {metrics['completion']:.4f} m"
    seconds = result.get("seconds", {}).get("total")
    return text + (f" ({seconds:.1f} s, frontend {result.get('frontend')})" if seconds is not None else "")


def _stats(values: list[float]) -> dict:
    array = np.asarray(values, np.float64)
    return {"mean": float(array.mean()) if len(array) else None,
            "std": float(array.std(ddof=1)) if len(array) > 1 else None,
            "values": [float(v) for v in array]}


def summarize(results: list[dict], points: list[str], sequences: list[str], metrics: list[tuple[str, str]]) -> dict:
    """Per grid point and sequence: mean and sample std over successful runs; and the average.

    The average of a metric is the mean of the sequences' means (the paper's "Avg" column); its
    std is the sample std over runs of the per-run mean across sequences, over the runs that
    succeeded on every sequence.
    """
    keys = [k for k, _ in metrics] + [TIME_ROW[0]]
    summary: dict[str, Any] = {}
    for point in points:
        per_sequence: dict[str, Any] = {}
        for sequence in sequences:
            runs = [r for r in results if r["point"] == point and r["sequence"] == sequence]
            ok = [r for r in runs if r["status"] == "ok"]
            entry: dict[str, Any] = {
                "runs_ok": len(ok), "runs": len(runs),
                "failures": [{"run": r["run"], "reason": r["reason"]} for r in runs if r["status"] != "ok"],
            }
            for key in keys:
                entry[key] = _stats([v for v in (_value(r, key) for r in ok) if v is not None])
            per_sequence[sequence] = entry
        average: dict[str, Any] = {}
        complete = [s for s in sequences if per_sequence[s]["runs_ok"] > 0]
        for key in keys:
            means = [per_sequence[s][key]["mean"] for s in complete if per_sequence[s][key]["mean"] is not None]
            by_run: dict[int, list[float]] = {}
            for r in results:
                if r["point"] == point and r["status"] == "ok" and _value(r, key) is not None:
                    by_run.setdefault(r["run"], []).append(float(_value(r, key)))
            run_means = [float(np.mean(v)) for v in by_run.values() if len(v) == len(sequences)]
            average[key] = {"mean": float(np.mean(means)) if means else None,
                            "std": float(np.std(run_means, ddof=1)) if len(run_means) > 1 else None,
                            "sequences": len(means), "of": len(sequences)}
        summary[point] = {"sequences": per_sequence, "average": average}
    return summary


def _cell(stats: dict, digits: int) -> str:
    if stats["mean"] is None:
        return "—"
    text = f"{stats['mean']:.{digits}f}"
    return text + (f" ± {stats['std']:.{digits}f}" if stats.get("std") is not None else "")


def _digits(key: str) -> int:
    return 2 if key == TIME_ROW[0] else 4


def point_table(summary: dict, point: str, sequences: list[str], metrics: list[tuple[str, str]]) -> str:
    """The paper-layout table of one grid point (Markdown), with footnotes for failed runs."""
    entry = summary[point]
    rows = metrics + [TIME_ROW]
    lines = ["| | " + " | ".join(sequences) + " | Avg |", "|:--|" + "--:|" * (len(sequences) + 1)]
    notes: list[str] = []
    marks: dict[str, str] = {}
    for sequence in sequences:
        s = entry["sequences"][sequence]
        if s["failures"]:
            marks[sequence] = f"<sup>{len(notes) + 1}</sup>"
            by_reason: dict[str, list[str]] = {}
            for failure in s["failures"]:
                by_reason.setdefault(failure["reason"], []).append(str(failure["run"]))
            reasons = "; ".join(f"run{'s' if len(runs) > 1 else ''} {', '.join(runs)}: {reason}"
                                for reason, runs in by_reason.items())
            notes.append(f"{len(notes) + 1}. {sequence}: {s['runs_ok']}/{s['runs']} runs succeeded — {reasons}")
    for key, label in rows:
        cells = []
        for sequence in sequences:
            s = entry["sequences"][sequence]
            if s["runs_ok"] == 0:
                cells.append(f"failed{marks.get(sequence, '')}")
                continue
            partial = f" ({s['runs_ok']}/{s['runs']})" if s["failures"] else ""
            cells.append(_cell(s[key], _digits(key)) + partial + marks.get(sequence, ""))
        average = entry["average"][key]
        average_cell = _cell(average, _digits(key))
        if average["mean"] is not None and average["sequences"] < average["of"]:
            average_cell += f" ({average['sequences']}/{average['of']} sequences)"
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {average_cell} |")
    return "\n".join(lines + ([""] + notes if notes else []))


def comparison_table(summary: dict, points: list[str], sequences: list[str], key: str, label: str) -> str:
    """A row per grid point (as the paper's rows per method), means over runs."""
    lines = [f"| {label} | " + " | ".join(sequences) + " | Avg |", "|:--|" + "--:|" * (len(sequences) + 1)]
    for point in points:
        entry = summary[point]
        cells = [("failed" if entry["sequences"][s]["runs_ok"] == 0 else f"{entry['sequences'][s][key]['mean']:.{_digits(key)}f}")
                 for s in sequences]
        average = entry["average"][key]["mean"]
        lines.append(f"| {point} | " + " | ".join(cells) + f" | {'—' if average is None else f'{average:.{_digits(key)}f}'} |")
    return "\n".join(lines)


def changed_settings(config: SLAMConfig) -> dict:
    """Settings of ``config`` that differ from the defaults, as ``{"section.name": value}``."""
    def flatten(values: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in values.items():
            out.update(flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    defaults, current = flatten(config_to_dict(SLAMConfig())), flatten(config_to_dict(config))
    decided_by_the_evaluation = (*SEEDED_SETTINGS, "output.keyframes", "output.cache_frontend")
    return {k: v for k, v in current.items() if defaults.get(k) != v and k not in decided_by_the_evaluation}


def markdown(outcome: EvalOutcome, settings: EvalSettings, config: SLAMConfig, summary: dict) -> str:
    dataset = get_dataset(settings.dataset)
    metrics = metrics_of(settings.dataset, settings.dense)
    sequences = [s.name for s in outcome.sequences]
    points = [p.label for p in outcome.points]
    changed = changed_settings(config)
    head = [
        f"# {dataset.title}: {len(sequences)} sequence(s), {settings.runs} run(s) each (run r uses seed r)",
        "",
        "Keyframe ATE RMSE after a Umeyama Sim(3) alignment (evo_ape -as)"
        + ("; dense accuracy / completion / chamfer after the trajectory's Sim(3) and ICP, distances clipped at "
           f"{settings.max_error} m" if dataset.dense and settings.dense else "")
        + ". Cells: mean ± sample standard deviation over the runs; Avg: mean over sequences.",
        "",
        "Settings changed from the defaults: " + (", ".join(f"`{k}={v}`" for k, v in changed.items()) or "none") + ".",
    ]
    if outcome.missing:
        head += ["", f"Not found under the root (left out): {', '.join(outcome.missing)}."]
    parts = ["\n".join(head)]
    for point in points:
        title = f"## {point}" if len(points) > 1 else "## Results"
        parts.append(f"{title}\n\n" + point_table(summary, point, sequences, metrics))
    if len(points) > 1:
        for key, label in metrics:
            parts.append(f"## Comparison: {label}\n\n" + comparison_table(summary, points, sequences, key, label))
    return "\n\n".join(parts) + "\n"


def write_runs_csv(path: Path, results: list[dict]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for r in results:
        metrics, seconds = r.get("metrics", {}), r.get("seconds", {})
        writer.writerow({
            "point": r["point"], "sequence": r["sequence"], "run": r["run"], "seed": r["seed"], "status": r["status"],
            **{k: metrics.get(k, "") for k in ("ate_rmse", "accuracy", "completion", "chamfer")},
            "keyframes": r.get("counts", {}).get("keyframes", ""), "seconds_slam": seconds.get("slam", ""),
            "seconds_total": seconds.get("total", ""), "frontend": r.get("frontend") or "", "reason": r.get("reason") or "",
        })
    atomic_write_text(path, buffer.getvalue())


def plot_sequence(path: Path, title: str, runs: list[dict]) -> bool:
    """Trajectories of the runs against the ground truth (top view) and the ATE of each run.

    The top view is the ground truth's principal plane (its two main directions), whatever the
    dataset's world axes. Returns False when no run has a trajectory to draw.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drawn = [r for r in runs if r["status"] == "ok" and r.get("trajectory")]
    if not drawn:
        return False
    ground_truth = np.asarray(max(drawn, key=lambda r: len(r["trajectory"]["ground_truth"]))["trajectory"]["ground_truth"])
    centre = ground_truth.mean(0)
    _, _, Vt = np.linalg.svd(ground_truth - centre, full_matrices=False)
    fig, (top, bars) = plt.subplots(1, 2, figsize=(11, 4.8), gridspec_kw={"width_ratios": [1.2, 1]})
    p = (ground_truth - centre) @ Vt[:2].T
    top.plot(p[:, 0], p[:, 1], "k--", lw=1.6, label="ground truth")
    for r in drawn:
        q = (np.asarray(r["trajectory"]["estimate_aligned"]) - centre) @ Vt[:2].T
        top.plot(q[:, 0], q[:, 1], "-", lw=1.0, alpha=0.8, label=f"run {r['run']} (ATE {r['metrics']['ate_rmse']:.3f} m)")
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("first principal axis of the ground truth [m]")
    top.set_ylabel("second principal axis [m]")
    top.set_title("keyframe trajectories, Sim(3)-aligned (top view)")
    top.legend(loc="best", fontsize=7)
    top.grid(alpha=0.3)

    ok = [r for r in runs if r["status"] == "ok"]
    failed = [r for r in runs if r["status"] != "ok"]
    values = [r["metrics"]["ate_rmse"] for r in ok]
    bars.bar([r["run"] for r in ok], values, color="tab:blue", label="ATE RMSE")
    if failed:
        bars.bar([r["run"] for r in failed], [0] * len(failed), color="tab:red")
        for r in failed:
            bars.annotate("failed", (r["run"], 0), ha="center", va="bottom", color="tab:red", fontsize=8)
    if values:
        bars.axhline(float(np.mean(values)), color="k", lw=1, ls=":", label=f"mean {np.mean(values):.4f} m")
    bars.set_xticks(sorted(r["run"] for r in runs))
    bars.set_xlabel("run (= seed)")
    bars.set_ylabel("ATE RMSE [m]")
    bars.set_title("ATE over runs")
    bars.legend(loc="best", fontsize=8)
    bars.grid(alpha=0.3, axis="y")
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return True


def write_report(out_dir: Path, outcome: EvalOutcome, settings: EvalSettings, config: SLAMConfig) -> dict[str, Any]:
    """Write ``tables.md``, ``runs.csv``, ``results.json`` and the figures; return their paths."""
    import dataclasses

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics = metrics_of(settings.dataset, settings.dense)
    sequences = [s.name for s in outcome.sequences]
    points = [p.label for p in outcome.points]
    summary = summarize(outcome.results, points, sequences, metrics)
    files: dict[str, Any] = {"tables": str(out_dir / "tables.md"), "runs": str(out_dir / "runs.csv"), "json": str(out_dir / "results.json")}
    atomic_write_text(out_dir / "tables.md", markdown(outcome, settings, config, summary))
    write_runs_csv(out_dir / "runs.csv", outcome.results)
    figures = []
    for point in outcome.points:
        for sequence in sequences:
            runs = [r for r in outcome.results if r["point"] == point.label and r["sequence"] == sequence]
            path = out_dir / "figures" / point.slug / f"{sequence.replace(os.sep, '-')}.png"
            title = f"{get_dataset(settings.dataset).title} {sequence}" + ("" if point.label == "default" else f" — {point.label}")
            if plot_sequence(path, title, runs):
                figures.append(str(path))
    files["figures"] = figures
    payload = {
        "dataset": settings.dataset,
        "settings": dataclasses.asdict(settings),
        "config": config_to_dict(config),
        "seeded_settings": "run r sets " + " = ".join(SEEDED_SETTINGS) + " = r",
        "grid": [{"label": p.label, "folder": p.slug, "overrides": dict(p.overrides)} for p in outcome.points],
        "sequences": {s.name: str(s.path) for s in outcome.sequences},
        "missing_sequences": outcome.missing,
        "executor": outcome.executor,
        "runs_computed": outcome.computed,
        "runs_reused": outcome.reused,
        "seconds": round(outcome.seconds, 3),
        "summary": summary,
        "runs": [{k: v for k, v in r.items() if k != "trajectory"} for r in outcome.results],
    }
    atomic_write_text(out_dir / "results.json", json.dumps(payload, indent=2, default=str) + "\n")
    return files
