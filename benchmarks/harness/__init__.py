"""The benchmarks' shared harness: settings, synthetic worlds, runs, parallel execution, reports.

A benchmark script is its grid and its tables; everything else comes from here:

- :mod:`.settings`: dotted setting overrides (``{"alignment.model": "select"}``) applied to a
  config, and grids of them (:func:`grid`);
- :mod:`.worlds`: :func:`synthetic_world`, rendered once per parameters and reused by every
  benchmark, :class:`LapSource` for replays lap after lap, :func:`random_frames` for model inputs;
- :mod:`.runs`: :func:`run_sequence` / :func:`attempt` (one pipeline run and its ATE, loop counts,
  failures);
- :mod:`.parallel`: :func:`run_all` on :mod:`sl4slam.evaluation.executors` (this process, a local
  pool or Ray);
- :mod:`.report`: :func:`write_report` and the pieces of a report's text;
- :mod:`.measure`: timing and memory probes;
- :mod:`.places`: the folders the benchmarks read and write.

Scripts run from ``benchmarks/`` (``python benchmarks/bench_x.py``): their folder is on the import
path, so ``import harness`` finds this package.
"""

from .measure import (
    TimedSource,
    cpu_seconds,
    interleaved_times,
    max_rss_bytes,
    median_seconds,
    peak_rss_bytes,
    reset_peak_rss,
    rss_bytes,
    timed,
)
from .parallel import add_parallel_arguments, parallel_options, run_all
from .places import BENCHMARKS, OUT, REPO, RESULTS, SHARED_DATA, result_file, shared_sequence
from .report import (
    cpu_model,
    date_text,
    fraction,
    load_average,
    markdown_row,
    memory_gib,
    replace_heading,
    replace_section,
    table,
    torch_machine,
    write_report,
)
from .runs import (
    Failure,
    Run,
    attempt,
    count_model_frames,
    failing_step,
    loop_counts,
    make_frontend,
    make_pipeline,
    result_ate,
    run_sequence,
)
from .settings import describe, grid, nested, parse_settings, seed_settings, simulated_config, with_settings
from .worlds import LapSource, random_frames, synthetic_world, world_name

__all__ = [
    "BENCHMARKS", "OUT", "REPO", "RESULTS", "SHARED_DATA", "result_file", "shared_sequence",
    "describe", "grid", "nested", "parse_settings", "seed_settings", "simulated_config", "with_settings",
    "LapSource", "random_frames", "synthetic_world", "world_name",
    "Failure", "Run", "attempt", "count_model_frames", "failing_step", "loop_counts", "make_frontend",
    "make_pipeline", "result_ate", "run_sequence",
    "add_parallel_arguments", "parallel_options", "run_all",
    "cpu_model", "date_text", "fraction", "load_average", "markdown_row", "memory_gib", "replace_heading",
    "replace_section", "table", "torch_machine", "write_report",
    "TimedSource", "cpu_seconds", "interleaved_times", "max_rss_bytes", "median_seconds", "peak_rss_bytes",
    "reset_peak_rss", "rss_bytes", "timed",
]
