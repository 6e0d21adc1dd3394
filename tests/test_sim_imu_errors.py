"""IMU errors beyond the basic model in the simulator: gyro g-sensitivity, a temperature-driven bias, quantisation
of the output and vibration with its rectification."""

import numpy as np
import pytest

from georefine.geometry.frames import LocalFrame
from georefine.sim.flight import FlightConfig, simulate_flight
from georefine.sim.imu import G0, ImuGrade, imu_grade, quantise, simulate_imu, temperature_profile

DEG_PER_H = np.pi / 180.0 / 3600.0


@pytest.fixture(scope="module")
def flight():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    return simulate_flight(FlightConfig(), frame, 600.0, lambda x, y: 500.0 + 0.01 * np.asarray(y))


def test_g_sensitivity_adds_G_f_to_the_gyros_and_leaves_the_other_draws_alone(flight):
    plain = imu_grade("mems")
    sens = plain.model_copy(update={"gyro_g_sensitivity_deg_per_h_per_g": 2.0})
    a = simulate_imu(flight, plain, 0.0, 20.0, np.random.default_rng(4))
    b = simulate_imu(flight, sens, 0.0, 20.0, np.random.default_rng(4))
    for name in ("bias_gyro", "bias_acc", "scale_gyro", "scale_acc", "acc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.any(a.g_sensitivity) and np.all(b.g_sensitivity != 0)
    _, f = flight.imu(b.time)
    np.testing.assert_allclose(b.gyro - a.gyro, f @ b.g_sensitivity.T, rtol=1e-9, atol=1e-15)
    draws = np.array([simulate_imu(flight, ImuGrade(gyro_g_sensitivity_deg_per_h_per_g=3.0), 0.0, 0.1,
                                   np.random.default_rng(s)).g_sensitivity for s in range(200)])
    np.testing.assert_allclose(draws.std(), 3.0 * DEG_PER_H / G0, rtol=0.1)


def test_temperature_drift_follows_the_profile_in_the_true_biases(flight):
    plain = imu_grade("mems")
    warm = plain.model_copy(update={"temperature_change_c": 15.0, "temperature_time_constant_s": 150.0,
                                    "gyro_temperature_deg_per_h_per_c": 0.2, "acc_temperature_ug_per_c": 8.0})
    a = simulate_imu(flight, plain, 0.0, 350.0, np.random.default_rng(9))
    b = simulate_imu(flight, warm, 0.0, 350.0, np.random.default_rng(9))
    temp = temperature_profile(b.time, 15.0, 150.0)
    np.testing.assert_allclose(b.temperature_c, temp)
    assert temp[0] == 0.0 and 15.0 * (1 - np.exp(-2)) - 1e-9 < temp[-1] < 15.0
    for kind in ("gyro", "acc"):
        k = getattr(b, f"temperature_{kind}")
        assert np.all(k != 0)
        drift = getattr(b, f"bias_{kind}") - getattr(a, f"bias_{kind}")
        np.testing.assert_allclose(drift, temp[:, None] * k, rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(getattr(b, kind) - getattr(a, kind), drift, rtol=1e-9, atol=1e-13)
    draws = np.array([simulate_imu(flight, warm, 0.0, 0.1, np.random.default_rng(s)).temperature_acc
                      for s in range(200)])
    np.testing.assert_allclose(draws.std(), 8.0 * G0 * 1e-6, rtol=0.1)
    assert simulate_imu(flight, plain, 0.0, 1.0, np.random.default_rng(1)).temperature_c.max() == 0.0


def test_quantisation_outputs_whole_lsbs_whose_sum_follows_the_unquantised_sum(flight):
    plain = imu_grade("mems")
    lsb_g, lsb_f = 1.9e-6, 0.061e-3  # LN-200: 2^-19 rad, 2^-14 m/s
    coarse = plain.model_copy(update={"gyro_quantisation_urad": 1.9, "acc_quantisation_mm_per_s": 0.061})
    a = simulate_imu(flight, plain, 0.0, 120.0, np.random.default_rng(5))
    b = simulate_imu(flight, coarse, 0.0, 120.0, np.random.default_rng(5))
    dt = 1.0 / plain.rate_hz
    assert a.quantisation_gyro is None and a.quantisation_acc is None  # off: nothing quantised, nothing drawn
    for name in ("bias_gyro", "bias_acc", "scale_gyro", "scale_acc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for kind, lsb in (("gyro", lsb_g), ("acc", lsb_f)):
        raw, out, err = getattr(a, kind), getattr(b, kind), getattr(b, f"quantisation_{kind}")
        counts = out * dt / lsb
        np.testing.assert_allclose(counts, np.round(counts), rtol=0, atol=1e-6)  # whole LSBs per sample
        assert np.unique(np.round(counts)).size > 50  # not trivially zero: the output moves in many steps
        np.testing.assert_allclose(err, out - raw, rtol=0, atol=1e-12)
        # the remainder is carried: the running sums differ by [0, 1) LSB, never accumulating
        behind = np.cumsum(raw * dt, axis=0) - np.cumsum(out * dt, axis=0)
        assert behind.min() > -1e-6 * lsb and behind.max() < lsb * (1 + 1e-6)
        # white-ish per sample: rms LSB / (dt sqrt 6), far above what a sum-preserving error could hide
        np.testing.assert_allclose(np.sqrt(np.mean(err**2, axis=0)), lsb / dt / np.sqrt(6), rtol=0.03)
        assert np.abs(err).max() <= lsb / dt * (1 + 1e-9)
    # rounding each sample on its own (no carry) would drift: the carried sum stays, a per-sample floor does not
    alone = np.floor(a.acc * dt / lsb_f) * lsb_f / dt
    assert np.abs(np.cumsum((a.acc - alone) * dt, axis=0)).max() > 100 * lsb_f
    # deterministic, a function of the unquantised samples only
    np.testing.assert_array_equal(quantise(a.acc, dt, lsb_f), b.acc)
    # quantisation draws nothing: the generator ends where it ends without it
    r1, r2 = np.random.default_rng(5), np.random.default_rng(5)
    simulate_imu(flight, plain, 0.0, 1.0, r1)
    simulate_imu(flight, coarse, 0.0, 1.0, r2)
    assert r1.bit_generator.state == r2.bit_generator.state
    # the defaults (0) give the model as before: without noise, the samples are the old model of the truth
    quiet = plain.model_copy(update={"gyro_arw_deg_per_sqrt_h": 0.0, "acc_vrw_m_per_s_per_sqrt_h": 0.0,
                                     "gyro_misalignment_mrad": 0.3, "acc_misalignment_mrad": 0.3,
                                     "gyro_g_sensitivity_deg_per_h_per_g": 2.0, "temperature_change_c": 10.0,
                                     "acc_temperature_ug_per_c": 5.0})
    x = simulate_imu(flight, quiet, 0.0, 5.0, np.random.default_rng(2))
    assert x.vibration_acc is None and x.quantisation_gyro is None and not np.any(x.vibration_bias_acc)
    w, f = flight.imu(x.time)
    old_gyro = (1 + x.scale_gyro) * w + w @ x.misalignment_gyro.T + f @ x.g_sensitivity.T + x.bias_gyro
    old_acc = (1 + x.scale_acc) * f + f @ x.misalignment_acc.T + x.bias_acc
    np.testing.assert_allclose(x.gyro, old_gyro, rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(x.acc, old_acc, rtol=1e-14, atol=1e-15)


def test_vibration_is_zero_mean_in_the_output_and_rectifies_into_the_true_bias(flight):
    plain = imu_grade("mems")
    rms_g, freq, vre = 0.8, 23.0, 400.0  # 23 periods in 200 samples: whole periods in whole seconds
    shaken = plain.model_copy(update={"vibration_g_rms": rms_g, "vibration_frequency_hz": freq,
                                      "acc_vibration_rectification_ug_per_g2": vre})
    a = simulate_imu(flight, plain, 0.0, 60.0, np.random.default_rng(6))
    b = simulate_imu(flight, shaken, 0.0, 60.0, np.random.default_rng(6))
    whole = slice(0, 60 * 200)  # 60 s: 1380 whole vibration periods
    # the other draws and the gyro bias are untouched; the accelerometer bias moves by c rms^2 exactly
    for name in ("bias_gyro", "scale_gyro", "scale_acc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = b.vibration_rectification
    assert np.all(c != 0) and np.all(b.vibration_phase != 0)
    bias = c * (rms_g * G0) ** 2
    np.testing.assert_allclose(b.vibration_bias_acc, bias, rtol=1e-12)
    np.testing.assert_allclose(b.bias_acc - a.bias_acc, np.broadcast_to(bias, a.bias_acc.shape), rtol=1e-9,
                               atol=1e-15)
    # the vibration truth: a sinusoid of the stated rms, zero-mean over whole periods
    v = b.vibration_acc
    np.testing.assert_allclose(np.sqrt(np.mean(v[whole] ** 2, axis=0)), rms_g * G0, rtol=1e-9)
    np.testing.assert_allclose(v[whole].mean(axis=0), 0.0, atol=1e-9)
    spectrum = np.abs(np.fft.rfft(v[whole], axis=0))
    assert np.all(np.argmax(spectrum, axis=0) == round(freq * 60))  # at 23 Hz (bin of 1/60 Hz)
    # in the output: the vibration through the scale factors, plus the rectification bias
    np.testing.assert_allclose(b.acc - a.acc, (1.0 + b.scale_acc) * v + bias, rtol=1e-9, atol=1e-9)
    # against the true specific force: the mean over whole periods is the true bias, within the white noise
    _, f = flight.imu(b.time)
    mean = (b.acc - f)[whole].mean(axis=0)
    noise = plain.acc_noise_density * np.sqrt(plain.rate_hz) / np.sqrt(60 * 200)  # 13 ug per axis
    sensed = b.scale_acc * f[whole].mean(axis=0)  # the scale factors' share of the mean (|f| ~ g)
    np.testing.assert_allclose(mean - sensed, b.bias_acc[whole].mean(axis=0), rtol=0, atol=5 * noise)
    assert np.all(np.abs(bias) > 10 * noise)  # a window that a missing or wrong bias fails
    diff = (b.acc - a.acc)[whole] - bias
    np.testing.assert_allclose(np.sqrt(np.mean(diff**2, axis=0)), (1.0 + b.scale_acc) * rms_g * G0, rtol=1e-6)
    # the gyros read the vibration through their g-sensitivity only (zero-mean, no gyro rectification)
    np.testing.assert_array_equal(a.gyro, b.gyro)
    g = shaken.model_copy(update={"gyro_g_sensitivity_deg_per_h_per_g": 2.0})
    c_ = simulate_imu(flight, g, 0.0, 60.0, np.random.default_rng(6))
    d = simulate_imu(flight, g.model_copy(update={"vibration_g_rms": 0.0}), 0.0, 60.0, np.random.default_rng(6))
    np.testing.assert_allclose(c_.gyro - d.gyro, c_.vibration_acc @ c_.g_sensitivity.T, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose((c_.gyro - d.gyro)[whole].mean(axis=0), 0.0, atol=1e-12)
    # the coefficients are drawn with the stated sigma (micro-g per g^2)
    draws = np.array([simulate_imu(flight, shaken, 0.0, 0.1, np.random.default_rng(s)).vibration_rectification
                      for s in range(200)])
    np.testing.assert_allclose(draws.std(), vre * 1e-6 / G0, rtol=0.1)


def test_the_project_truth_holds_quantisation_and_vibration(flight):
    from georefine.sim.project_writer import _imu_errors

    plain = imu_grade("mems")
    both = plain.model_copy(update={"acc_quantisation_mm_per_s": 0.061, "vibration_g_rms": 0.5,
                                    "acc_vibration_rectification_ug_per_g2": 50.0})
    off, on = (_imu_errors(simulate_imu(flight, g, 0.0, 2.0, np.random.default_rng(3))) for g in (plain, both))
    imu = simulate_imu(flight, both, 0.0, 2.0, np.random.default_rng(3))
    assert set(off) == set(on)  # the same keys, zeros where an error is off
    assert not np.any(off["quantisation_acc"]) and not np.any(off["vibration_bias_acc"])
    assert on["quantisation_acc"].shape == (imu.time.size, 3) and not np.any(on["quantisation_gyro"])
    np.testing.assert_array_equal(on["quantisation_acc"], imu.quantisation_acc)
    np.testing.assert_array_equal(on["vibration_bias_acc"], imu.vibration_rectification * (0.5 * G0) ** 2)
    np.testing.assert_array_equal(on["vibration_phase"], imu.vibration_phase)


def test_the_imu_file_logs_the_temperature_where_it_changes(flight, tmp_path):
    """The written CSV carries the unit's temperature (20 deg C at the first sample plus the simulated change) where
    the grade changes it, and no such column where it does not."""
    from georefine.io.imu import read_imu_csv
    from georefine.sim.writers import write_imu

    warm = imu_grade("mems").model_copy(update={"temperature_change_c": 15.0, "gyro_temperature_deg_per_h_per_c": 0.1})
    imu = simulate_imu(flight, warm, 0.0, 2.0, np.random.default_rng(5))
    write_imu(tmp_path / "warm.csv", imu)
    back = read_imu_csv(tmp_path / "warm.csv")
    np.testing.assert_allclose(back.temperature_c, 20.0 + imu.temperature_c, atol=5e-5)
    assert back.temperature_c[0] == 20.0 and back.temperature_c[-1] > 20.0
    write_imu(tmp_path / "plain.csv", simulate_imu(flight, imu_grade("mems"), 0.0, 2.0, np.random.default_rng(5)))
    assert read_imu_csv(tmp_path / "plain.csv").temperature_c is None


def test_the_stim300_unit_is_the_mems_grade_with_every_error_its_datasheet_states(flight, tmp_path):
    """The ``stim300`` unit preset keeps the ``mems`` grade's modelled figures and adds the datasheet's misalignment,
    g-sensitivity and temperature coefficients with a warm-up; simulated, it draws each of them. ``--set imu=stim300``
    names it as it names a grade (the bench's ``imu-unit`` kind)."""
    from georefine.sim.scenarios import resolve_scenario

    mems, unit = imu_grade("mems"), imu_grade("stim300")
    extra = {"gyro_misalignment_mrad": 1.0, "acc_misalignment_mrad": 1.0, "gyro_g_sensitivity_deg_per_h_per_g": 1.0,
             "gyro_temperature_deg_per_h_per_c": 0.139, "acc_temperature_ug_per_c": 55.4, "temperature_change_c": 10.0}
    assert {k: getattr(unit, k) for k in extra} == extra
    assert all(getattr(mems, k) == 0.0 for k in extra)
    same = set(ImuGrade.model_fields) - set(extra) - {"name", "source"}
    assert {k: getattr(unit, k) for k in same} == {k: getattr(mems, k) for k in same}
    imu = simulate_imu(flight, unit, 0.0, 300.0, np.random.default_rng(11))
    off = ~np.eye(3, dtype=bool)
    for a in (imu.misalignment_gyro, imu.misalignment_acc):
        assert np.all(a[off] != 0) and np.all(np.abs(a[off]) < 5e-3) and not np.any(np.diag(a))
    assert np.all(imu.g_sensitivity != 0) and np.all(imu.temperature_gyro != 0) and np.all(imu.temperature_acc != 0)
    np.testing.assert_allclose(imu.temperature_c, temperature_profile(imu.time, 10.0, 900.0))
    cfg = resolve_scenario("corridor-tiny", seed_overrides=["imu=stim300", "imu.temperature_change_c=20"])
    assert cfg.imu.name == "stim300" and cfg.imu.temperature_change_c == 20.0 and cfg.imu.gyro_misalignment_mrad == 1.0
