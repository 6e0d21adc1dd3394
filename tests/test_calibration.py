"""Estimated IMU errors and boresight against the simulated truth (evaluation/calibration.py)."""

from __future__ import annotations

import html
import math

import numpy as np
import pytest

from georefine.evaluation.calibration import (
    BoresightFigures,
    ImuErrorFigures,
    boresight_figures,
    imu_error_figures,
    plot_imu_errors,
)
from georefine.evaluation.report import write_report
from georefine.evaluation.summary import RunEvaluation
from georefine.io.files import write_json
from georefine.io.run_metrics import AdjustmentReport, WorkflowMetrics

G0 = 9.80665
MISALIGNED = np.array([[0.0, 4e-4, -1e-4], [2e-4, 0.0, 3e-4], [-5e-4, 6e-4, 0.0]])


def _truth(tmp_path, rng):
    t = 1.4e9 + np.arange(0.0, 300.0, 0.01)
    walk = np.cumsum(rng.normal(scale=1e-3, size=(t.size, 3)), axis=0) / 100.0
    bias_acc = (np.array([300.0, -200.0, 800.0]) + walk * 50.0) * 1e-6 * G0  # m/s^2
    bias_gyro = np.radians(np.array([-5.0, 3.0, 7.0]) + walk) / 3600.0  # rad/s
    path = tmp_path / "imu_errors.npz"
    np.savez(path, time_gps=t, bias_gyro=bias_gyro, bias_acc=bias_acc, scale_gyro=np.array([1e-4, -2e-4, 3e-4]),
             scale_acc=np.array([-5e-4, 1e-4, 2e-4]), misalignment_acc=MISALIGNED, misalignment_gyro=np.zeros((3, 3)))
    return path, t, bias_acc, bias_gyro


def test_the_figures_compare_the_adjustment_with_the_truth_at_its_knots(tmp_path):
    rng = np.random.default_rng(3)
    path, t, bias_acc, bias_gyro = _truth(tmp_path, rng)
    t0 = 1.4e9 - 5.0  # the adjustment's time origin differs from the truth's first sample
    knots = np.arange(0.0, 320.0, 10.0)  # the last knots lie beyond the truth: left out
    inside = (t0 + knots >= t[0]) & (t0 + knots <= t[-1])
    acc_true = np.column_stack([np.interp(t0 + knots, t, bias_acc[:, i]) for i in range(3)]) / G0 * 1e6
    gyro_true = np.column_stack([np.interp(t0 + knots, t, bias_gyro[:, i]) for i in range(3)]) * 180 / np.pi * 3600
    acc_err = np.array([10.0, -20.0, 30.0])
    adjustment = AdjustmentReport("G/I/L", t0, imu_errors={
        "bias_knot_times_s": knots.tolist(),
        "acc_bias_ug": (acc_true + acc_err).tolist(), "acc_bias_sigma_ug": np.full((knots.size, 3), 15.0).tolist(),
        "gyro_bias_deg_per_h": (gyro_true - 0.5).tolist(),
        "gyro_bias_sigma_deg_per_h": np.full((knots.size, 3), 0.25).tolist(),
        "acc_scale_ppm": [-480.0, 110.0, 190.0], "acc_scale_sigma_ppm": [20.0, 20.0, 30.0],
        "gyro_scale_ppm": [90.0, -190.0, 310.0], "gyro_scale_sigma_ppm": [10.0, 10.0, 10.0],
        "acc_misalignment_mrad": [0.45, -0.1, 0.2, 0.3, -0.5, 0.6], "acc_misalignment_sigma_mrad": [0.05] * 6})
    f = imu_error_figures(adjustment, path)
    # The misalignment elements xy, xz, yx, yz, zx, zy of the true matrix; the gyro's was not estimated.
    np.testing.assert_allclose(f.acc_misalignment_true_mrad, [0.4, -0.1, 0.2, 0.3, -0.5, 0.6], atol=1e-12)
    assert f.gyro_misalignment_mrad is None and f.acc_misalignment_sigma_mrad == (0.05,) * 6
    np.testing.assert_allclose(f.acc_bias_rms_error_ug, np.abs(acc_err), rtol=1e-9)
    np.testing.assert_allclose(f.gyro_bias_rms_error_deg_per_h, [0.5] * 3, rtol=1e-9)
    np.testing.assert_allclose(f.acc_bias_rms_sigma_ug, [15.0] * 3)
    np.testing.assert_allclose(f.acc_scale_true_ppm, [-500.0, 100.0, 200.0])
    np.testing.assert_allclose(f.gyro_scale_true_ppm, [100.0, -200.0, 300.0])
    assert inside.sum() < knots.size  # the knots outside the truth's span were dropped, not extrapolated
    assert ImuErrorFigures.from_dict(f.to_dict()) == f
    assert imu_error_figures(AdjustmentReport("G/I/L", t0), path) is None

    # Temperature coefficients estimated: the knots hold the walk's part, the temperature part is added back at the
    # truth's temperature change before the comparison.
    temperature_c = np.linspace(0.0, 12.0, t.size)
    np.savez(tmp_path / "warm.npz", **dict(np.load(path)), temperature_c=temperature_c)
    d_t = np.interp(t0 + knots, t, temperature_c)[:, None]
    k_g, k_a = np.array([0.1, -0.2, 0.05]), np.array([10.0, 5.0, -8.0])
    warm = AdjustmentReport("G/I/L", t0, imu_errors=adjustment.imu_errors | {
        "acc_bias_ug": (acc_true + acc_err - d_t * k_a).tolist(), "gyro_bias_deg_per_h": (gyro_true - 0.5 - d_t * k_g).tolist(),
        "gyro_temperature_deg_per_h_per_c": k_g.tolist(), "acc_temperature_ug_per_c": k_a.tolist()})
    w = imu_error_figures(warm, tmp_path / "warm.npz")
    np.testing.assert_allclose(w.acc_bias_rms_error_ug, np.abs(acc_err), rtol=1e-9)
    np.testing.assert_allclose(w.gyro_bias_rms_error_deg_per_h, [0.5] * 3, rtol=1e-9)

    b = boresight_figures(AdjustmentReport("G/I/L", t0, boresight_deg=(0.062, -0.021, 0.030),
                                           boresight_sigma_mdeg=(2.0, 2.1, 9.0)),
                          [0.060, -0.020, 0.034], [0.010, -0.020, 0.034])
    np.testing.assert_allclose(b.error_mdeg, [2.0, -1.0, -4.0], atol=1e-9)
    assert BoresightFigures.from_dict(b.to_dict()) == b and boresight_figures(
        AdjustmentReport("G/I/L", t0), [0, 0, 0], [0, 0, 0]) is None

    # In the evaluation record, the report and the plot.
    run = tmp_path / "run"
    (run / "evaluation").mkdir(parents=True)
    plot_imu_errors({"G/I/L": adjustment}, path, run / "evaluation" / "imu_errors.png")
    ev = RunEvaluation("truth", imu_errors={"G/I/L": f}, imu_errors_plot="imu_errors.png", boresight=b,
                       overview_plot="overview.png")
    assert RunEvaluation.from_dict(ev.to_dict()) == ev
    write_json(run / "evaluation" / "summary.json", ev.to_dict())
    write_json(run / "metrics.json", WorkflowMetrics(t0_gps=t0, strips=(1,), strip_time_gps={1: (t[0], t[-1])}).to_dict())
    page = html.unescape(write_report(run).read_text())
    assert "against the simulated truth" in page and page.count("data:image/png;base64,") >= 1
    assert "<td>G/I/L</td><td>accelerometer bias (µg): RMS error : RMS sigma</td><td>10 : 15</td>" in page
    assert "<td>error (mdeg)</td><td>2.0</td><td>-1.0</td><td>-4.0</td>" in page
    assert ("<td>G/I/L</td><td>accelerometer misalignment (mrad)</td><td>0.450 / 0.400 ± 0.050</td>"
            "<td>-0.100 / -0.100 ± 0.050</td>") in page and "gyro misalignment" not in page
    assert math.isclose(f.gyro_scale_ppm[0], 90.0)


def test_without_imu_errors_in_the_truth_there_are_no_figures(tmp_path):
    adjustment = AdjustmentReport("G/I", 0.0, imu_errors={"bias_knot_times_s": [0.0]})
    assert imu_error_figures(adjustment, tmp_path / "none.npz") is None
    with pytest.raises(KeyError):
        ImuErrorFigures.from_dict({})
