"""A known camera calibration (``--intrinsics``): reading it, checking it, and using it.

Most robots, phones and datasets come with a calibration, while a feed-forward model guesses each
frame's focal length (VGGT: errors up to about 7 %). With ``--intrinsics``:

- every frame's points are rebuilt along the known camera's rays from the model's depth (the
  prediction's ``K`` is replaced by the known one on the model's grid, before any point is made);
- so the shared frame's two cameras in consecutive submaps have the same intrinsics, and the link
  between submaps carries no calibration term (``K_prev^-1 K_cur`` is the identity);
- the metric upgrade is skipped: the cameras are metric already (``sl4slam.resolve``);
- a model that takes a calibration as input (Pi3X, Depth Anything 3) is given it as well;
- the summary says which K was used and how far the model's own focal length was from it.

A model whose focal length disagrees wildly with the given one (median ratio outside
:data:`FOCAL_RATIO_WARNING`) most likely means a wrong calibration file (another camera, another
resolution): the run warns once, with the median ratio, and goes on with the given K, which the
user asked for.

Pixel convention: ``(u, v)`` with integer values at pixel centres (OpenCV's, TUM's, COLMAP's
``PINHOLE`` uses the same up to COLMAP's half-pixel origin, which its reader here removes).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import UserError

FOCAL_RATIO_WARNING = (0.8, 1.25)
"""Median model focal / known focal outside this range is warned about: VGGT's own focal errors
reach about 7 % (``SimulatorConfig.focal_error``), a wrong calibration file (another camera or
resolution) is usually off by far more."""

_COLMAP_MODELS = {
    # model: (number of parameters, which are fx, fy, cx, cy; the rest is distortion)
    "SIMPLE_PINHOLE": (3, (0, 0, 1, 2)), "PINHOLE": (4, (0, 1, 2, 3)), "SIMPLE_RADIAL": (4, (0, 0, 1, 2)),
    "RADIAL": (5, (0, 0, 1, 2)), "OPENCV": (8, (0, 1, 2, 3)), "FULL_OPENCV": (12, (0, 1, 2, 3)),
}


@dataclass(frozen=True)
class KnownIntrinsics:
    """A calibration given for the run.

    Attributes:
        K: ``(3, 3)`` float64 in the source's pixels (integers at pixel centres).
        origin: where it came from ("given", a file path, "auto: <source>").
        note: what was left out (lens distortion), or "".
    """

    K: np.ndarray
    origin: str
    note: str = ""

    def values(self) -> list[float]:
        """``[fx, fy, cx, cy]``."""
        return [float(self.K[0, 0]), float(self.K[1, 1]), float(self.K[0, 2]), float(self.K[1, 2])]


def pinhole(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def parse_intrinsics(spec: str) -> KnownIntrinsics | None:
    """What ``--intrinsics`` names: ``""`` (none), ``"fx,fy,cx,cy"``, or a file (TUM-style
    ``fx = .. fy = .. cx = .. cy = ..`` text, or a COLMAP ``cameras.txt``); "auto" (read from the
    source) is settled by ``sl4slam.resolve`` before. Raises ``UserError`` (one line) for what cannot
    be used."""
    spec = spec.strip()
    if not spec:
        return None
    numbers = re.fullmatch(r"\s*([^,\s]+)\s*,\s*([^,\s]+)\s*,\s*([^,\s]+)\s*,\s*([^,\s]+)\s*", spec)
    if numbers is not None:
        try:
            fx, fy, cx, cy = (float(v) for v in numbers.groups())
        except ValueError:
            raise UserError(f"--intrinsics (config key source.intrinsics) {spec!r}: expected four numbers fx,fy,cx,cy in the source's pixels") from None
        return checked(KnownIntrinsics(pinhole(fx, fy, cx, cy), "given"))
    path = Path(spec).expanduser()
    if not path.is_file():
        raise UserError(f"--intrinsics (config key source.intrinsics) {spec!r} is neither fx,fy,cx,cy nor a file; give four numbers, a calibration "
                        "file (fx = .. fy = .. cx = .. cy = ..) or a COLMAP cameras.txt, or auto")
    text = path.read_text(encoding="utf-8", errors="replace")
    known = _colmap_cameras(text, path) if _looks_like_colmap(text) else _calibration_text(text, path)
    return checked(known)


def _looks_like_colmap(text: str) -> bool:
    lines = [line.split() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    return bool(lines) and len(lines[0]) >= 5 and lines[0][1].upper() in _COLMAP_MODELS


def _colmap_cameras(text: str, path: Path) -> KnownIntrinsics:
    """The first camera of a COLMAP ``cameras.txt`` (``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``)."""
    lines = [line.split() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    model = lines[0][1].upper()
    count, (fx, fy, cx, cy) = _COLMAP_MODELS[model]
    try:
        params = [float(v) for v in lines[0][4:]]
    except ValueError:
        raise UserError(f"--intrinsics {path}: the camera's parameters are not numbers ({' '.join(lines[0])})") from None
    if len(params) != count:
        raise UserError(f"--intrinsics {path}: a {model} camera has {count} parameters, the file gives {len(params)}")
    # COLMAP puts the origin at the top-left corner of the first pixel: its centre is at 0.5
    K = pinhole(params[fx], params[fy], params[cx] - 0.5, params[cy] - 0.5)
    distortion = params[max(fx, fy, cx, cy) + 1:]
    note = "lens distortion ignored (undistort the images for an exact result)" if any(distortion) else ""
    if len(lines) > 1:
        note = (note + "; " if note else "") + f"the first of {len(lines)} cameras used"
    return KnownIntrinsics(K, str(path), note)


def _calibration_text(text: str, path: Path) -> KnownIntrinsics:
    """``fx = .. fy = .. cx = .. cy = ..`` anywhere in a text (TUM's calibration notes); the first
    values found are used, and distortion coefficients written as ``d0..d4`` or ``k1`` are left out."""
    from .io.tum import parse_calibration_text

    K = parse_calibration_text(text)
    if K is None:
        raise UserError(f"--intrinsics {path}: no 'fx = .. fy = .. cx = .. cy = ..' values and not a COLMAP "
                        "cameras.txt; give the numbers as fx,fy,cx,cy")
    distorted = re.search(r"\b(d0|k1)\b", text) is not None
    return KnownIntrinsics(K, str(path), "lens distortion ignored (undistort the images for an exact result)"
                           if distorted else "")


def checked(known: KnownIntrinsics, image_size: tuple[int, int] | None = None) -> KnownIntrinsics:
    """``known`` if its focal lengths are positive and, given the image size, its principal point
    lies inside the image; else ``UserError`` (one line, before any frame is read)."""
    fx, fy, cx, cy = known.values()
    if not (np.isfinite(known.K).all() and fx > 0 and fy > 0):
        raise UserError(f"--intrinsics ({known.origin}): focal lengths must be positive, got fx={fx:g}, fy={fy:g}")
    if image_size is not None:
        width, height = image_size
        if not (0 <= cx <= width - 1 and 0 <= cy <= height - 1):
            raise UserError(f"--intrinsics ({known.origin}): the principal point ({cx:g}, {cy:g}) lies outside the "
                            f"{width}x{height} images; check that the calibration is for this camera and resolution")
    return known


def from_source(source, known: KnownIntrinsics | None, read_calibration: bool) -> KnownIntrinsics | None:
    """The run's known intrinsics, checked against the source's image size.

    Args:
        source: the opened frame source.
        known: the intrinsics the settings give (``ResolvedConfig.intrinsics``), or ``None``.
        read_calibration: read them from the source instead (``--intrinsics auto``; TUM and 7-Scenes
            know their camera).

    Raises:
        UserError: the source states no calibration, or the intrinsics do not fit its images.
    """
    if read_calibration:
        K = source.calibration()
        if K is None:
            raise UserError(f"--intrinsics auto: {source.name} states no calibration (TUM RGB-D and 7-Scenes "
                            "sequences do); give fx,fy,cx,cy or a calibration file")
        known = KnownIntrinsics(np.asarray(K, np.float64), f"auto: {source.name}")
    if known is None:
        return None
    return checked(known, source.image_size())


def on_grid(K: np.ndarray, image_to_grid: np.ndarray) -> np.ndarray:
    """``(S, 3, 3)`` the known ``K`` ``(3, 3)`` of the input frames mapped onto a frontend's grid by
    its affine ``image_to_grid`` ``(S, 3, 3)`` (``SubmapPrediction.image_to_grid``)."""
    return np.einsum("sij,jk->sik", np.asarray(image_to_grid, np.float64), np.asarray(K, np.float64))


def focal_ratios(K_model: np.ndarray, K_known: np.ndarray) -> np.ndarray:
    """``(S,)`` the model's focal over the known one, ``sqrt(fx fy)`` each (both on the grid); NaN
    where the model's focal lengths are not both positive (no focal to compare)."""
    product = K_model[:, 0, 0] * K_model[:, 1, 1]
    model = np.sqrt(np.where(product > 0, product, np.nan))
    known = np.sqrt(K_known[:, 0, 0] * K_known[:, 1, 1])
    return model / known
