"""Headless Chromium for the viewer's tests and benchmark: launch options, how much of the 3D view
is drawn, waiting for the first screenshot (or the first moment of the page) that shows it, and
stopping a viewer subprocess as a user would.

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
"""Bound of every wait: only a hang reaches it (software WebGL on a loaded 2-core machine draws the
tests' 88k-point page in under 10 s, a 1M-point one in about 20 s: benchmarks/results/viewer.md)."""
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


CANVAS_AND_TEXT = """() => {
  // the 3D view (the largest canvas: viser's WebGL one, drawn with preserveDrawingBuffer) and the
  // page's text, read in one go: JavaScript runs one task at a time, so both are of the same moment
  const gl = [...document.querySelectorAll('canvas')].reduce(
      (best, c) => (!best || c.width * c.height > best.width * best.height ? c : best), null);
  let fraction = 0;
  if (gl && gl.width > 340 && gl.height > 150) {
    const copy = document.createElement('canvas');
    copy.width = gl.width; copy.height = gl.height;
    const ctx = copy.getContext('2d');
    ctx.drawImage(gl, 0, 0);
    const x1 = Math.round(gl.width * (1 - 340 / window.innerWidth)), y0 = Math.round(gl.height * 150 / window.innerHeight);
    const data = ctx.getImageData(0, y0, x1, gl.height - y0).data;
    let drawn = 0;
    for (let i = 0; i < data.length; i += 4) {
      const a = data[i + 3] / 255;  // over the page's white, as the screen shows it
      const dark = a * ((255 - data[i]) + (255 - data[i + 1]) + (255 - data[i + 2]));
      if (dark > 60) drawn++;
    }
    fraction = drawn / (data.length / 4);
  }
  return [fraction, document.body.innerText];
}"""


def first_drawn_text(page, level: float = DRAWN, bound_s: float = HANG_S) -> tuple[float, str]:
    """The page's text at the first moment its 3D canvas shows something (more than ``level`` of it
    drawn, counted as :func:`drawn_fraction` counts a screenshot, CSS opacity aside): the canvas'
    pixels and the text are read in one JavaScript task, so the text is the one shown with that
    frame. Returns (drawn fraction, text); AssertionError when nothing is drawn within ``bound_s``."""
    end = time.monotonic() + bound_s
    while True:
        fraction, text = page.evaluate(CANVAS_AND_TEXT)
        if fraction > level:
            return fraction, text
        if time.monotonic() > end:
            raise AssertionError(f"nothing drawn on the canvas within {bound_s:.0f} s")
        time.sleep(0.02)


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
