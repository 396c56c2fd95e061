"""Instrumentation kept out of the pipeline's steps: stage timing and progress reporting.

- :class:`StageTimer`: ``with timer("alignment"): ...`` accumulates wall time per stage.
- :class:`Progress`: a progress bar on a terminal; plain lines every few submaps otherwise (a log
  file gets no carriage-return updates), and log records always on their own line.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections import defaultdict
from typing import Iterator, TextIO


class StageTimer:
    """Wall time per named stage, summed over the ``with`` blocks of that name."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextlib.contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - start


class Progress:
    """Progress of a run over ``total`` frames.

    Args:
        total: frames to process (``None`` when unknown, e.g. a live camera).
        enabled: report at all (``--quiet`` turns it off).
        every: on a non-terminal, one line every this many submaps.
        stream: where it goes (stderr by default).
    """

    def __init__(self, total: int | None, enabled: bool = True, every: int = 10, stream: TextIO | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.every = max(1, int(every))
        self.total = total
        interactive = enabled and self.stream.isatty() and sys.stdout.isatty()
        self._bar = None
        self._redirect = None
        if interactive:
            from tqdm import tqdm
            from tqdm.contrib.logging import logging_redirect_tqdm

            self._bar = tqdm(total=total, unit="frame", desc="sl4slam", leave=False, file=self.stream)
            # log records go above the bar instead of being glued to it
            self._redirect = logging_redirect_tqdm(loggers=[logging.getLogger("sl4slam")])
            self._redirect.__enter__()
        self._start = time.perf_counter()

    def frame(self, **counts: int) -> None:
        """One input frame done; ``counts`` (keyframes, submaps, loops) update the bar."""
        if self._bar is not None:
            self._bar.update(1)
            if counts:
                self._bar.set_postfix(counts, refresh=False)

    def submap(self, frames_done: int, **counts: int) -> None:
        """One submap done: on a non-terminal, a plain line every ``every`` submaps."""
        if self._bar is not None or not self.enabled:
            return
        if counts.get("submaps", 0) % self.every:
            return
        of = f"/{self.total}" if self.total else ""
        figures = ", ".join(f"{value} {name}" for name, value in counts.items())
        print(f"sl4slam: {frames_done}{of} frames, {figures}, {time.perf_counter() - self._start:.0f} s",
              file=self.stream, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        if self._redirect is not None:
            self._redirect.__exit__(None, None, None)
            self._redirect = None
