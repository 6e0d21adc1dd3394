"""Sensor errors beyond the basic IMU model: a misaligned, non-orthogonal IMU (docs/ARCHITECTURE.md §4.3).

The simulator turns each triad by about half a milliradian (``imu.*_misalignment_mrad``); the
project states that figure, so the adjustments estimate the misalignment. The same project with the
figure removed shows what an unmodelled misalignment does. Error windows and sigma consistency
against the simulated truth; the long G/I/L run is marked slow (CI runs it).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from cli_helpers import run_georefine
from georefine.evaluation.trajectory_files import truth_pass_accuracy
from georefine.sim.scenarios import simulate_project
from georefine.workflows import run_trajectory

FAST_SCAN = ["scanner.pulse_rate_hz=2000", "scanner.line_rate_hz=100"]  # the navigation data do not depend on the scanner
MISALIGNED = ["imu.gyro_misalignment_mrad=0.5", "imu.acc_misalignment_mrad=0.5"]


def _passes(project: Path) -> list[int]:
    return [p["strip_id"] for p in yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"]]


def _unstated(project: Path, out: Path) -> Path:
    """``project`` whose ``project.yaml`` no longer states the IMU's misalignment (the data keep it)."""
    shutil.copytree(project, out, symlinks=True)
    cfg = yaml.safe_load((out / "project.yaml").read_text())
    for key in ("gyro_misalignment_mrad", "acc_misalignment_mrad"):
        cfg["imu"]["errors"].pop(key)
    (out / "project.yaml").write_text(yaml.safe_dump(cfg))
    return out


def _misalignment_z(solution: Path, project: Path) -> np.ndarray:
    """(estimate - truth) / sigma of the twelve misalignment elements (accelerometer, then gyro)."""
    e = json.loads((solution / "adjustment.json").read_text())["imu_errors"]
    truth = np.load(project / "truth" / "imu_errors.npz")
    off = ~np.eye(3, dtype=bool)
    return np.concatenate([(np.asarray(e[f"{t}_misalignment_mrad"]) - truth[f"misalignment_{t}"][off] * 1e3)
                           / np.asarray(e[f"{t}_misalignment_sigma_mrad"]) for t in ("acc", "gyro")])


@pytest.fixture(scope="module")
def misaligned_navigation(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("misaligned") / "tiny"
    simulate_project("corridor-tiny", out, seed=21, overrides=FAST_SCAN + MISALIGNED)
    return out


def test_the_gi_estimates_a_stated_misalignment_and_states_the_tilt_it_cannot_see(misaligned_navigation, tmp_path):
    """GNSS and IMU cannot tell a turn of the whole IMU from attitude: estimated with its prior, the G/I's
    stated roll and pitch sigma carry it. Unstated, the same data give errors of 4-7 stated sigma."""
    project = misaligned_navigation
    stated = run_trajectory(project, tmp_path / "stated")
    assert stated.adjustment.solve.converged
    unstated_project = _unstated(project, tmp_path / "unstated-project")
    run_trajectory(unstated_project, tmp_path / "unstated")
    for strip in _passes(project):
        ok = truth_pass_accuracy(tmp_path / "stated" / "trajectory.sbet", project, strip)
        bad = truth_pass_accuracy(tmp_path / "unstated" / "trajectory.sbet", unstated_project, strip)
        # Measured on this seed: stated roll/pitch/yaw error/sigma 1.05-1.11 / 0.30 / 0.44-0.58 (the
        # pitch's common turn happened to be small against its prior); unstated 3.5-4.0 / 6.5-6.7.
        assert np.all(ok.z_rms < 2.0) and np.all(ok.beyond_3_sigma <= 0.01), (strip, ok)
        assert bad.z_rms[1] > 3.0, (strip, bad)  # the pitch: the unmodelled misalignment's signature
        assert ok.rmse_mdeg[1] < 0.5 * bad.rmse_mdeg[1], (strip, ok, bad)
        assert np.all(ok.sigma_rms_mdeg[:2] > 2.0 * bad.sigma_rms_mdeg[:2])  # the turn's prior in roll and pitch
    z = _misalignment_z(tmp_path / "stated", project)
    assert np.sqrt(np.mean(z**2)) < 1.5 and np.max(np.abs(z)) < 3.0, z  # measured: RMS 0.83, largest 1.92
    rep = json.loads((tmp_path / "stated" / "adjustment.json").read_text())
    groups = {g["name"] for g in rep["adjustment"]["groups"]}
    assert {"gyro_misalignment_prior", "acc_misalignment_prior"} <= groups
    plain = json.loads((tmp_path / "unstated" / "adjustment.json").read_text())
    assert plain["imu_errors"]["acc_misalignment_mrad"] is None
    assert "gyro_misalignment_prior" not in {g["name"] for g in plain["adjustment"]["groups"]}


@pytest.mark.slow
def test_the_gil_observes_the_misalignment_through_the_scanner(tmp_path):
    """With the boresight held, the planes fix the scanner's attitude, and with it the IMU's turn: the
    G/I/L attitude is as good as on the clean project and its sigma honest; every misalignment element
    within about two sigma of the truth."""
    project = tmp_path / "misaligned"
    simulate_project("corridor-tiny", project, seed=21, overrides=MISALIGNED)
    proc = run_georefine("run", str(project), "--out", str(tmp_path / "run"), "--no-points", timeout=1800)
    assert proc.returncode == 0, proc.stderr
    clean = np.array([0.85, 1.03, 1.55])  # the same seed without misalignment, G/I/L roll, pitch, yaw (mdeg)
    for strip in _passes(project):
        a = truth_pass_accuracy(tmp_path / "run" / "gil" / "trajectory.sbet", project, strip)
        # Measured: 0.64-0.66 / 0.96-1.03 / 1.33-1.59 mdeg, error/sigma 0.60-1.04; unstated, the roll is 1.33-1.43.
        assert np.all(a.rmse_mdeg < 1.3 * clean), (strip, a)
        assert np.all((a.z_rms > 0.5) & (a.z_rms < 2.0)) and np.all(a.beyond_3_sigma <= 0.01), (strip, a)
    z = _misalignment_z(tmp_path / "run" / "gil", project)
    # Measured: RMS 0.86, largest 1.92 (the accelerometer's xy, which level flight hardly excites: its prior).
    assert np.sqrt(np.mean(z**2)) < 1.5 and np.max(np.abs(z)) < 2.5, z
