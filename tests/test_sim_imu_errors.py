"""IMU errors beyond the basic model in the simulator: gyro g-sensitivity and a temperature-driven bias."""

import numpy as np
import pytest

from georefine.geometry.frames import LocalFrame
from georefine.sim.flight import FlightConfig, simulate_flight
from georefine.sim.imu import G0, ImuGrade, imu_grade, simulate_imu, temperature_profile

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
