"""evo and trajectopy run on Georefine's trajectory exports, for the tests that compare their figures.

* evo: ``evo_ape`` found on the PATH (``shutil.which``).
* trajectopy: the Python interpreter named by the environment variable
  ``GEOREFINE_TRAJECTOPY_PYTHON`` (e.g. a virtual environment with ``pip install trajectopy``),
  or this interpreter if it imports ``trajectopy``.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from cli_helpers import run_georefine


def georefine_figures(estimate: Path, reference: Path, out: Path) -> dict:
    """``georefine evaluate trajectory``'s JSON (3-D RMSE in m, attitude angle RMSE in mdeg, ...)."""
    run = run_georefine("evaluate", "trajectory", str(estimate), "--reference", str(reference), "--out", str(out))
    assert run.returncode == 0, run.stderr
    return json.loads((out / "trajectory_comparison.json").read_text())


def export_pair(estimate: Path, reference: Path, folder: Path, fmt: str) -> tuple[Path, Path]:
    """``georefine export trajectory`` of both files into ``folder`` (``estimate.EXT``, ``reference.EXT``)."""
    ext = {"tum": "tum", "trajectopy": "traj"}[fmt]
    paths = (folder / f"estimate.{ext}", folder / f"reference.{ext}")
    for source, path in zip((estimate, reference), paths):
        run = run_georefine("export", "trajectory", str(source), "--format", fmt, "--out", str(path))
        assert run.returncode == 0, run.stderr
    return paths


def evo_ape_rmse(reference: Path, estimate: Path, relation: str, folder: Path) -> float:
    """RMSE of ``evo_ape tum REFERENCE ESTIMATE -r RELATION`` (no alignment), from its saved stats."""
    result = folder / f"ape_{relation}.zip"
    proc = subprocess.run([shutil.which("evo_ape"), "tum", str(reference), str(estimate), "-r", relation,
                           "--save_results", str(result), "--no_warnings"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with zipfile.ZipFile(result) as z:
        return float(json.loads(z.read("stats.json"))["rmse"])


_TRAJECTOPY_ATE = """
import json, sys
import trajectopy as tpy
est = tpy.Trajectory.from_file(sys.argv[1])
ref = tpy.Trajectory.from_file(sys.argv[2])
ate = tpy.ate(est, ref, align=False)
print(json.dumps({"pos_rms_m": float(ate.pos_dev_rms), "rot_rms_rad": float(ate.rot_dev_rms), "n": len(ate.pos_dev_comb),
                  "epsg": int(est.positions.epsg)}))
"""


def trajectopy_python() -> str | None:
    """An interpreter with trajectopy: $GEOREFINE_TRAJECTOPY_PYTHON, else this one if it has it."""
    named = os.environ.get("GEOREFINE_TRAJECTOPY_PYTHON")
    if named:
        return named
    return sys.executable if importlib.util.find_spec("trajectopy") is not None else None


def trajectopy_ate(estimate: Path, reference: Path) -> dict:
    """trajectopy's ATE without alignment: position and rotation-angle RMS, pose count, EPSG of the estimate."""
    python = trajectopy_python()
    proc = subprocess.run([python, "-c", _TRAJECTOPY_ATE, str(estimate), str(reference)], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def assert_same_figures(ours: dict, position_m: float, angle_mdeg: float, what: str) -> None:
    """Within 1 % of Georefine's 3-D position RMSE and attitude angle RMSE (|Log(R_ref^T R_est)|)."""
    assert position_m == pytest.approx(ours["3d_rmse_m"], rel=0.01), (what, position_m, ours["3d_rmse_m"])
    assert angle_mdeg == pytest.approx(ours["attitude_angle_rmse_mdeg"], rel=0.01), (
        what, angle_mdeg, ours["attitude_angle_rmse_mdeg"])
