"""Headless Chromium for the viewer's tests and benchmark: launch options, how much of the 3D view
is drawn, and stopping a viewer subprocess as a user would."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np

BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEWPORT = {"width": 1000, "height": 700}


def chromium_path() -> str | None:
    """Debian's chromium (apt-get install -y chromium), or ``None``."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def launch(playwright, profile: Path, executable: str):
    """A headless Chromium context with a fresh profile folder."""
    return playwright.chromium.launch_persistent_context(str(profile), executable_path=executable, headless=True,
                                                         args=BROWSER_ARGS, viewport=VIEWPORT)


def drawn_fraction(png: bytes, right_margin: int = 340) -> float:
    """Fraction of the 3D canvas' pixels (below the notification area, left of the control panel)
    that are not the white background."""
    import cv2

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    canvas = image[150:, : image.shape[1] - right_margin]
    return float((np.abs(canvas.astype(int) - 255).sum(axis=2) > 60).mean())


def interrupt(proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Ctrl-C to a viewer subprocess; killed if it does not stop in time."""
    proc.send_signal(2)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
