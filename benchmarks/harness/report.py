"""Writing a benchmark's Markdown into ``benchmarks/results/``, and the pieces its text is made of."""

from __future__ import annotations

import os
import platform
import re
import subprocess
from pathlib import Path
from typing import Any, Iterable, Sequence


def write_report(path: str | Path, lines: Sequence[str]) -> None:
    """Write ``lines`` to ``path`` atomically (a half-written report never replaces a whole one)
    and print them.

    Args:
        path: the Markdown file (its folder is made).
        lines: the file's lines, without line ends.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)
    print("\n".join(lines))


def replace_section(path: str | Path, start: str, end: str, block: Sequence[str], first: Sequence[str]) -> None:
    """Replace the block from the line ``start`` to the line ``end`` of ``path`` by ``block`` (which
    holds both lines), or append it; the rest of the file is kept.

    Args:
        path: the results file.
        start, end: the lines that open and close the section (``<!-- section:timing -->`` ...).
        block: the section's lines, ``start`` and ``end`` included.
        first: the lines a new file starts with (its title).
    """
    path = Path(path)
    text = path.read_text() if path.exists() else "\n".join(first) + "\n"
    pattern = re.compile(re.escape(start) + ".*?" + re.escape(end), re.S)
    joined = "\n".join(block)
    text = pattern.sub(lambda _: joined, text) if pattern.search(text) else text.rstrip("\n") + "\n\n" + joined
    write_report(path, text.rstrip("\n").splitlines())


def replace_heading(path: str | Path, heading: str, lines: Sequence[str], first: Sequence[str]) -> None:
    """Replace the section under the Markdown ``heading`` (``## ...``, up to the next ``## ``) of
    ``path`` by ``heading`` and ``lines``, or append it; the other sections are kept.

    Args:
        path: the results file.
        heading: the section's heading line.
        lines: the section's lines after the heading (a blank line is put between).
        first: the lines a new file starts with (its title).
    """
    path = Path(path)
    existing = path.read_text() if path.is_file() else "\n".join(first) + "\n"
    if heading in existing:
        before, _, rest = existing.partition(heading)
        after = rest[rest.find("\n## ") + 1:] if "\n## " in rest else ""
        existing = before.rstrip() + "\n\n" + after
    write_report(path, (existing.rstrip() + "\n\n" + "\n".join([heading, "", *lines])).splitlines())


def markdown_row(cells: Sequence[Any]) -> str:
    """One line of a Markdown table (cells as ``str``): ``| a | b |``."""
    return "| " + " | ".join(str(cell) for cell in cells) + " |"


def table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """A Markdown table: the header, its rule and one :func:`markdown_row` per row."""
    return [markdown_row(header), "|" + "---|" * len(header), *(markdown_row(row) for row in rows)]


def fraction(part: int, whole: int) -> str:
    """``"3/5"``, or ``"-"`` when ``whole`` is 0."""
    return f"{part}/{whole}" if whole else "-"


def load_average() -> float:
    """The 1-minute load average."""
    return os.getloadavg()[0]


def date_text(form: str | None = None) -> str:
    """What ``date`` prints (with ``+FORM`` when ``form`` is given)."""
    return subprocess.run(["date", *([f"+{form}"] if form else [])], capture_output=True, text=True).stdout.strip()


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else ``lscpu``; "unknown CPU" if neither says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return platform.processor() or "unknown CPU"
    match = re.search(r"Model name:\s*(.+)", out)
    return match.group(1).strip() if match else "unknown CPU"


def memory_gib() -> float:
    """The machine's physical memory in GiB."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30


def torch_machine() -> str:
    """The machine in one line for the model benchmarks: CPU model, cores, memory, kernel, torch and
    its CPU capability, Python."""
    import torch

    return (f"{cpu_model()}, {os.cpu_count()} cores, {memory_gib():.0f} GiB, Linux {platform.release()}; "
            f"torch {torch.__version__} ({torch.backends.cpu.get_cpu_capability()}), "
            f"Python {platform.python_version()}")
