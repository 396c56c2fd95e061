"""Assemble BENCHMARKS.md from the sections the benchmark scripts write to benchmarks/results/.

    python benchmarks/collect.py
"""

from __future__ import annotations

from harness import REPO, RESULTS
ORDER = ["robustness", "robustness_defaults", "submap_size", "submap_size_submap", "accuracy", "upgrade_pipeline", "upgrade", "failfast", "pipeline", "pipeline_3000_progress", "pipeline_shortcuts", "ransac", "backend", "evaluation",
         "keyframe_graph", "levers", "refine", "suite", "authors_v1", "render", "retrieval_orb", "salad", "vggt", "pi3", "da3", "models", "cpu_estimate", "overlap", "workers", "resume", "gpu_run", "localize", "export",
         "keyframe_format", "viewer", "viewer_open", "objects", "objects_models", "test_suite"]
HEADER = """# Benchmarks

Every figure below was measured by a script in `benchmarks/` (the command is given with each
section) on the project's reference machine: 2 CPU cores, 24 GiB, no GPU. Timings are medians of
repeated runs; comparisons are ratios measured side by side in one process. Regenerate this file
with `python benchmarks/collect.py` after running the scripts.

"""


def main() -> None:
    sections = []
    for name in ORDER:
        path = RESULTS / f"{name}.md"
        if path.is_file():
            text = path.read_text().strip()
            # demote the sections' own top-level titles under this file's title
            text = "\n".join("#" + line if line.startswith("#") else line for line in text.splitlines())
            sections.append(text)
    (REPO / "BENCHMARKS.md").write_text(HEADER + "\n\n".join(sections) + "\n")


if __name__ == "__main__":
    main()
