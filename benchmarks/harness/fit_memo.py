"""A replay's link fits, recorded in one run and handed back in another: the cost floor without fits.

A run of the lap replay is deterministic: the same settings make the same fits on the same points.
:class:`FitMemo` wraps the fits of the aligners a run measures links with (the 15-DOF fit of a
frame's points with its planar fallbacks, ``SL4Aligner.fit``, and the calibration-and-scale link,
``CalibrationAligner.fit``). Recording, it keeps a copy of each result under a digest of the fit's
inputs; replaying, it returns a copy of the recorded result instead of fitting. The second run then
does every other piece of work of the first one (gathering the shared points, the held-out errors
of the ``select`` link, the loop checks, the graph, retrieval, the store) and none of the fitting,
so its per-submap cost is what the model-free work would be if the fits cost nothing.

A replayed fit costs the digest of a sample of its inputs and the copy of its result (together
about 0.1 ms); a fit that failed raises its error again. :attr:`FitMemo.misses` counts fits that
were not recorded (fitted then, as in the recording run), which a deterministic replay leaves at
zero.
"""

from __future__ import annotations

import copy
import hashlib
import pickle
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from sl4slam.alignment import aligner as aligners
from sl4slam.atomic import atomic_path

WRAPPED = (aligners.SL4Aligner, aligners.CalibrationAligner)
"""The aligner classes whose own ``fit`` is recorded or replayed."""


SAMPLE_STRIDE = 50
"""Every how many point pairs one enters a fit's key: the digest of all 30,000-60,000 pairs costs
2-3 ms a fit, which the replay would count as model-free work; a strided sample with the pair count
and the cameras tells the fits of a run apart all the same (a replay that missed would say so)."""


def fit_key(model: str, X_a: np.ndarray, X_b: np.ndarray, view_a, view_b, seed: int) -> tuple[str, int, int, str]:
    """What identifies a fit of a run: the model, the seed, the number of point pairs and a digest of
    every :data:`SAMPLE_STRIDE`-th pair and of the two cameras."""
    digest = hashlib.blake2b(digest_size=16)
    for array in (X_a[::SAMPLE_STRIDE], X_b[::SAMPLE_STRIDE], view_a.K, view_a.T_cam_submap, view_b.K,
                  view_b.T_cam_submap):
        digest.update(np.ascontiguousarray(array).tobytes())
    return model, int(seed), len(X_a), digest.hexdigest()


class FitMemo:
    """Records (``mode="record"``) or replays (``mode="replay"``) a run's fits; see the module doc.

    Args:
        mode: "record" or "replay".
        path: the file the recorded fits are written to (record) or read from (replay).
    """

    def __init__(self, mode: str, path: str | Path) -> None:
        if mode not in ("record", "replay"):
            raise ValueError(f"unknown mode {mode!r}: record or replay")
        self.mode, self.path = mode, Path(path)
        self.fits: dict[tuple[str, int, int, str], object] = {}
        if mode == "replay":
            with open(self.path, "rb") as handle:
                self.fits = pickle.load(handle)
        self.hits = self.misses = 0
        self._lock = threading.Lock()
        self._originals: dict[type, object] = {}

    def install(self) -> None:
        """Wrap the fits of :data:`WRAPPED` (each class's own ``fit``)."""
        for cls in WRAPPED:
            original = cls.__dict__["fit"]
            self._originals[cls] = original
            setattr(cls, "fit", self._wrapped(cls.model, original))

    def uninstall(self) -> None:
        """Put the original fits back."""
        for cls, original in self._originals.items():
            setattr(cls, "fit", original)
        self._originals.clear()

    @contextmanager
    def installed(self) -> Iterator["FitMemo"]:
        """The fits wrapped while the block runs (:meth:`install`, then :meth:`uninstall`)."""
        self.install()
        try:
            yield self
        finally:
            self.uninstall()

    def save(self) -> None:
        """Write the recorded fits (record mode), atomically."""
        if self.mode == "record":
            with atomic_path(self.path) as partial, open(partial, "wb") as handle:
                pickle.dump(self.fits, handle, protocol=pickle.HIGHEST_PROTOCOL)

    def _wrapped(self, model: str, original):
        memo = self

        def fit(aligner, X_a, X_b, view_a, view_b, seed):
            key = fit_key(model, X_a, X_b, view_a, view_b, seed)
            if memo.mode == "replay":
                recorded = memo.fits.get(key)
                with memo._lock:
                    memo.hits += recorded is not None
                    memo.misses += recorded is None
                if isinstance(recorded, ValueError):  # a fit that failed fails again
                    raise copy.copy(recorded)
                if recorded is not None:
                    return copy.deepcopy(recorded)
                return original(aligner, X_a, X_b, view_a, view_b, seed)
            try:
                result = original(aligner, X_a, X_b, view_a, view_b, seed)
            except ValueError as exc:
                memo.fits[key] = exc
                raise
            memo.fits[key] = copy.deepcopy(result)
            return result

        return fit
