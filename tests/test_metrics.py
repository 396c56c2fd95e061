"""ATE through evo's Python API equals the evo_ape command on the same files."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sl4slam.metrics import ate


def _write_tum(path: Path, t: np.ndarray, positions: np.ndarray, quats_xyzw: np.ndarray) -> None:
    np.savetxt(path, np.c_[t, positions, quats_xyzw], fmt="%.9f")


def _poses(positions: np.ndarray, quats_xyzw: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(positions), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(quats_xyzw).as_matrix()
    T[:, :3, 3] = positions
    return T


def _trajectories(seed: int = 0):
    rng = np.random.default_rng(seed)
    n = 60
    t = 1000.0 + np.arange(n) / 30.0
    positions = np.c_[np.cos(t), np.sin(t), 0.1 * t]
    quats = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.2).as_quat()
    # the estimate: another frame, scale 2.5, plus noise
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    est_positions = 2.5 * positions @ R.T + [1.0, -2.0, 0.5] + rng.normal(size=(n, 3)) * 0.02
    return t, positions, quats, est_positions


def test_ate_recovers_known_similarity_exactly() -> None:
    t, positions, quats, _ = _trajectories()
    R = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    est = 0.5 * positions @ R.T + [3.0, 1.0, 2.0]
    result = ate(t, _poses(est, quats), t, _poses(positions, quats))
    assert result.rmse < 1e-9
    assert result.scale == pytest.approx(2.0, rel=1e-9)


def test_ate_matches_evo_ape_command(tmp_path: Path) -> None:
    evo_ape = shutil.which("evo_ape") or str(Path(sys.executable).with_name("evo_ape"))
    if not os.path.exists(evo_ape):
        pytest.skip("the evo_ape command is not installed")
    t, positions, quats, est_positions = _trajectories(1)
    _write_tum(tmp_path / "gt.txt", t, positions, quats)
    _write_tum(tmp_path / "est.txt", t, est_positions, quats)
    env = {**os.environ, "HOME": str(tmp_path)}  # evo writes its settings file under HOME
    out = subprocess.run([evo_ape, "tum", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "-as"],
                         capture_output=True, text=True, env=env, check=True).stdout
    evo_rmse = float(re.search(r"rmse\s+([0-9.eE+-]+)", out).group(1))
    ours = ate(t, _poses(est_positions, quats), t, _poses(positions, quats)).rmse
    assert ours == pytest.approx(evo_rmse, rel=1e-5, abs=1e-6)
    assert ours > 0.005  # the noise is visible: the comparison is not trivially 0 == 0
