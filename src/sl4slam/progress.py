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
    """Progress over ``total`` frames: a bar on a terminal; on anything else (a log file) plain
    lines, never carriage returns: every ``every`` submaps for a run, every tenth of the frames
    otherwise, and a last line at :meth:`close` so that a log ends with the final figures.

    Args:
        total: frames to process (``None`` when unknown, e.g. a live camera).
        enabled: report at all (``--quiet`` turns it off).
        every: on a non-terminal, one line every this many submaps.
        stream: where it goes (stderr by default).
        description: what is counted ("sl4slam" for a run, "all frames" for the localization).
        per_submap: plain lines come from :meth:`submap` (a run), not from tenths of the frames.
    """

    def __init__(self, total: int | None, enabled: bool = True, every: int = 10, stream: TextIO | None = None,
                 description: str = "sl4slam", per_submap: bool = False) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.every = max(1, int(every))
        self.total = total
        self.description = description
        interactive = enabled and self.stream.isatty() and sys.stdout.isatty()
        self._bar = None
        self._redirect = None
        if interactive:
            from tqdm import tqdm
            from tqdm.contrib.logging import logging_redirect_tqdm

            self._bar = tqdm(total=total, unit="frame", desc=description, leave=False, file=self.stream)
            # log records go above the bar instead of being glued to it
            self._redirect = logging_redirect_tqdm(loggers=[logging.getLogger("sl4slam")])
            self._redirect.__enter__()
        self._start = time.perf_counter()
        self._done = 0
        self._bar_done = 0  # frames the bar has been told of
        self._counts: dict[str, int] = {}
        self._printed = -1  # frames done at the last plain line
        self._printed_counts: dict[str, int] = {}  # ... and the counts it showed
        self._by_submap = per_submap

    def frame(self, done: int | None = None, **counts: int) -> None:
        """One input frame done (``done``: the frames done so far, when the caller counts them);
        ``counts`` (keyframes, submaps, loops) update the bar."""
        step = 1 if done is None else done - self._bar_done
        self._done = self._done + 1 if done is None else done
        self._bar_done += step
        self._counts.update(counts)
        if self._bar is not None:
            self._bar.update(step)
            if counts:
                self._bar.set_postfix(counts, refresh=False)
        elif self.enabled and not self._by_submap and self.total and self._done * 10 // self.total > self._printed * 10 // self.total:
            self._line()

    def submap(self, frames_done: int, **counts: int) -> None:
        """One submap done (``frames_done`` input frames read by then): on a non-terminal, a plain
        line every ``every`` submaps."""
        self._done = max(self._done, frames_done)
        self._counts.update(counts)
        if self._bar is not None or not self.enabled:
            return
        if counts.get("submaps", 0) % self.every:
            return
        self._line()

    def _line(self) -> None:
        of = f"/{self.total}" if self.total and self.total < 1 << 40 else ""
        figures = "".join(f", {value} {name}" for name, value in self._counts.items())
        print(f"{self.description}: {self._done}{of} frames{figures}, {time.perf_counter() - self._start:.0f} s",
              file=self.stream, flush=True)
        self._printed, self._printed_counts = self._done, dict(self._counts)

    def close(self) -> None:
        """End the bar, or print the final line where the last one is stale."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self.enabled and self._done and (self._done != self._printed or self._counts != self._printed_counts):
            self._line()  # the last line is stale: frames or counts (a last submap) changed since
        if self._redirect is not None:
            self._redirect.__exit__(None, None, None)
            self._redirect = None
