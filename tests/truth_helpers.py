"""Helpers the end-to-end tests share to compare a result with the simulated truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from georefine.evaluation.trajectory_files import truth_pass_rmse


def pass_rmse(sbet: Path, project: Path, strip: int) -> np.ndarray:
    """Roll, pitch, yaw RMSE (mdeg) of ``sbet`` against the truth during a pass (1 s inset)."""
    return truth_pass_rmse(sbet, project, strip)
