"""Headless Chromium for the viewer's tests and benchmark: launch options, how much of the 3D view
is drawn, waiting for the first screenshot that shows it, and stopping a viewer subprocess as a
user would.

Nothing here measures how fast the machine is: waits are for a condition (a screenshot that shows
the map, the process' exit), and their bounds are only there so that a hang fails instead of
blocking the suite.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np

BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEWPORT = {"width": 1000, "height": 700}
HANG_S = 300.0
"""Bound of every wait: only a hang reaches it (software WebGL on a loaded 2-core machine draws a
100k-point page in under 10 s; benchmarks/results/viewer.md)."""
DRAWN = 0.02
"""Fraction of the canvas above which a screenshot shows something (an empty page: 0.001, the
orientation gizmo)."""


def chromium_path() -> str | None:
    """Debian's chromium (apt-get install -y chromium), or ``None``."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def launch(playwright, profile: Path, executable: str):
    """A headless Chromium context with a fresh profile folder; every wait of its pages is bounded
    by :data:`HANG_S` (a screenshot waits for the next frame, which software WebGL draws slowly)."""
    context = playwright.chromium.launch_persistent_context(str(profile), executable_path=executable, headless=True,
                                                            args=BROWSER_ARGS, viewport=VIEWPORT)
    context.set_default_timeout(HANG_S * 1000)
    return context


def drawn_fraction(png: bytes, right_margin: int = 340) -> float:
    """Fraction of the 3D canvas' pixels (below the notification area, left of the control panel)
    that are not the white background."""
    import cv2

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    canvas = image[150:, : image.shape[1] - right_margin]
    return float((np.abs(canvas.astype(int) - 255).sum(axis=2) > 60).mean())


def first_drawn(page, level: float = DRAWN, bound_s: float = HANG_S) -> bytes:
    """Screenshots of ``page`` until one shows something on the canvas (more than ``level`` of it
    drawn); that screenshot (PNG). AssertionError when none does within ``bound_s``."""
    end = time.monotonic() + bound_s
    while True:
        png = page.screenshot()
        if drawn_fraction(png) > level:
            return png
        if time.monotonic() > end:
            raise AssertionError(f"nothing drawn on the canvas within {bound_s:.0f} s")
        time.sleep(0.05)


def same_region(png_a: bytes, png_b: bytes, box: dict) -> float:
    """Fraction of the pixels of ``box`` (a Playwright bounding box: x, y, width, height in CSS px
    at scale 1) that are the same (within 8 per channel) in two screenshots."""
    import cv2

    a, b = (cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR) for png in (png_a, png_b))
    x0, y0 = int(np.ceil(box["x"])), int(np.ceil(box["y"]))
    x1, y1 = int(box["x"] + box["width"]), int(box["y"] + box["height"])
    crop_a, crop_b = a[y0:y1, x0:x1].astype(int), b[y0:y1, x0:x1].astype(int)
    return float((np.abs(crop_a - crop_b).max(axis=2) <= 8).mean())


def interrupt(proc: subprocess.Popen, bound_s: float = HANG_S) -> tuple[str, str]:
    """Ctrl-C to a viewer subprocess, as a user would, and wait until it has exited; returns what
    it wrote to stdout and stderr since last read.

    Both pipes are read while waiting (a child that fills a pipe nobody reads blocks and never
    exits). The wait is for the exit itself; ``bound_s`` only turns a hang into an AssertionError
    (the process is then killed, and the error says so), never into a return code for the caller
    to misread.
    """
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=bound_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"the viewer did not exit within {bound_s:.0f} s of Ctrl-C; stderr: {(err or '')[-2000:]}")
    return out or "", err or ""
