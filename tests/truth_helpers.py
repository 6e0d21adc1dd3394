"""Helpers the end-to-end tests share to compare a result with the simulated truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from georefine.evaluation.trajectory_files import compare_sbet_files


def pass_rmse(sbet: Path, project: Path, strip: int) -> np.ndarray:
    """Roll, pitch, yaw RMSE (mdeg) of ``sbet`` against the truth during a pass (1 s inset)."""
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    p = next(p for p in truth["passes"] if p["strip_id"] == strip)
    t0 = truth["t0_gps"]
    cmp = compare_sbet_files(sbet, project / "truth" / "trajectory.sbet",
                             time_window=(t0 + p["t_start_s"] + 1.0, t0 + p["t_end_s"] - 1.0))
    return np.array([cmp.stats[f"{a}_rmse_mdeg"] for a in ("roll", "pitch", "yaw")])
