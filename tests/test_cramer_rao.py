"""The Cramér-Rao bound of the G/I/L attitude at the simulated truth (georefine.workflows.cramer_rao).

On the README example's single-pass run (tests/conftest.py): the bound is built from the run's
matched features and the project's truth, the navigation sensors fit their weights there, the
run's stated sigma lies at or above it, and the run's error is within a window of it; the
model's optimum from the truth is where the run lands, and the G/I's bound lies above the G/I/L's.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.evaluation.trajectory_files import truth_pass_accuracy
from georefine.workflows.cramer_rao import cramer_rao_bound


@pytest.fixture(scope="module")
def single_pass_bound(gil_project, gil_single_pass):
    return cramer_rao_bound(gil_project, gil_single_pass)


@pytest.mark.slow
def test_the_bound_of_a_single_pass_at_the_truth(single_pass_bound, gil_project, gil_single_pass):
    bound = single_pass_bound
    (p,) = bound.passes  # only the strip the run used
    assert p.strip == 1 and p.epochs >= 40  # 1 s apart over the pass (1 s inset at both ends)
    metrics = json.loads((gil_single_pass / "metrics.json").read_text())
    assert bound.features_used == metrics["outer_iterations"][-1]["features_used"]
    # The simulated GNSS and IMU have the project's sensor figures: at the true trajectory (the
    # rest estimated) their observations fit the weights.
    for group in ("gnss", "imu"):
        assert 0.8 < bound.group_fit[group] < 1.25, bound.group_fit
    # The planes fit worse than their weights say (objects on inclined, faceted surfaces:
    # BENCHMARKS.md); their median-based sigma stays near 1.
    assert bound.group_fit["planes"] > 1.0
    assert np.all((0.8 < bound.plane_robust_sigma0) & (bound.plane_robust_sigma0 < 1.8)), bound.plane_robust_sigma0
    acc = truth_pass_accuracy(gil_single_pass / "gil" / "trajectory.sbet", gil_project, 1)
    # The run's stated sigma is its posterior at the solution with factors floored at 1: never
    # below the bound by more than the move of the linearisation point, and not far above it.
    ratio = acc.sigma_rms_mdeg / p.sigma_rms_mdeg
    assert np.all((0.97 < ratio) & (ratio < 1.5)), ratio
    # The error of one pass is one draw of a few slow modes: a loose window around the bound.
    assert np.all(acc.rmse_mdeg < 2.5 * p.sigma_rms_mdeg), (acc.rmse_mdeg, p.sigma_rms_mdeg)
    assert json.loads(json.dumps(bound.to_dict()))["passes"][0]["strip"] == 1


@pytest.mark.slow
def test_the_optimum_from_the_truth_and_the_gi_bound(single_pass_bound, gil_project, gil_single_pass):
    """The model's optimum from the truth is where a converged run of the same model lands on the
    same data (G/I/L 0.80/1.09/1.61 mdeg against an optimum of 0.77/1.09/1.68; G/I 2.56/3.48/9.74
    against 2.55/3.48/9.75), and the G/I's bound is the G/I/L's without the planes' information."""
    (p,) = single_pass_bound.passes
    assert p.gi is not None
    # Taking observations away never lowers a sigma; one pass's heading rests on the planes
    # (G/I 16.7 against 1.6 mdeg).
    assert np.all(p.gi.sigma_rms_mdeg >= p.gil.sigma_rms_mdeg * (1 - 1e-6)), (p.gi.sigma_rms_mdeg, p.gil.sigma_rms_mdeg)
    assert p.gi.sigma_rms_mdeg[2] > 5 * p.gil.sigma_rms_mdeg[2]
    for sol, b in (("gi", p.gi), ("gil", p.gil)):
        acc = truth_pass_accuracy(gil_single_pass / sol / "trajectory.sbet", gil_project, 1)
        # The run and the optimum: one model on one draw of the noise, so they agree to a small
        # part of the bound, much closer than either is to the truth's window (2.5x the bound).
        assert np.all(np.abs(acc.rmse_mdeg - b.optimum_rmse_mdeg) < 0.15 * b.sigma_rms_mdeg), (sol, acc.rmse_mdeg, b)
        assert np.all(np.abs(b.optimum_mean_mdeg) <= b.optimum_rmse_mdeg + 1e-9)
    d = p.to_dict()
    assert set(d["gi"]) == {"sigma_rms_mdeg", "optimum_rmse_mdeg", "optimum_mean_mdeg"}
    assert d["optimum_rmse_mdeg"]["yaw"] == pytest.approx(p.gil.optimum_rmse_mdeg[2])


def test_the_bound_needs_a_simulated_project_and_a_gil_run(gil_project, gil_single_pass, tmp_path):
    with pytest.raises(InputError, match="truth"):
        cramer_rao_bound(tmp_path, gil_single_pass)
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(gil_single_pass / "metrics.json", run / "metrics.json")
    with pytest.raises(InputError, match="features"):
        cramer_rao_bound(gil_project, run)
    shutil.copytree(gil_single_pass / "features", run / "features")
    (run / "metrics.json").write_text("{}")
    with pytest.raises(InputError, match="outer iterations"):
        cramer_rao_bound(gil_project, run)

