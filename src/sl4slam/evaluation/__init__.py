"""Benchmark evaluation with the paper's protocol: TUM RGB-D and 7-Scenes, repeated runs, sweeps.

- :mod:`.datasets`: the paper's sequences, their folder layout and ground truth.
- :mod:`.metrics`: ATE (evo, Sim(3)) and dense accuracy / completion / chamfer, plain functions.
- :mod:`.protocol`: :func:`evaluate` runs every (grid point, sequence, run) through
  :func:`sl4slam.runner.run_slam`, resumably, replaying recorded frontend outputs where it can.
- :mod:`.executors`: this process, a local process pool, or Ray, behind one interface.
- :mod:`.report`: paper-layout Markdown tables, CSV, JSON and figures.

``docs/evaluation.md`` describes the protocol and cites its sources.
"""

from .datasets import DATASETS, SEVEN_SCENES_SEQUENCES, TUM_SEQUENCES, Dataset, Sequence, get_dataset
from .executors import Executor, InProcessExecutor, LocalExecutor, RayExecutor, make_executor
from .metrics import (
    ATEResult,
    DenseResult,
    accuracy_completion,
    ate,
    dense_metrics,
    ground_truth_points,
    icp_refine,
    nearest_distances,
)
from .protocol import (
    SEEDED_SETTINGS,
    EvalOutcome,
    EvalSettings,
    GridPoint,
    evaluate,
    frontend_cache_key,
    parse_grid,
    seeded,
)

__all__ = [
    "DATASETS",
    "TUM_SEQUENCES",
    "SEVEN_SCENES_SEQUENCES",
    "Dataset",
    "Sequence",
    "get_dataset",
    "Executor",
    "InProcessExecutor",
    "LocalExecutor",
    "RayExecutor",
    "make_executor",
    "ATEResult",
    "DenseResult",
    "ate",
    "accuracy_completion",
    "dense_metrics",
    "ground_truth_points",
    "icp_refine",
    "nearest_distances",
    "SEEDED_SETTINGS",
    "EvalOutcome",
    "EvalSettings",
    "GridPoint",
    "evaluate",
    "frontend_cache_key",
    "parse_grid",
    "seeded",
]
