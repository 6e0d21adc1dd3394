"""IMU and GNSS simulators: error statistics match their specification; truth is exact."""

import numpy as np
import pytest
from pydantic import ValidationError

from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.sim.flight import FlightConfig, simulate_flight
from georefine.sim.gnss import GnssConfig, _gauss_markov, gnss_epochs, simulate_gnss
from georefine.sim.imu import (
    DEFAULT_IMU_GRADE,
    IMU_PRESETS,
    ImuGrade,
    imu_grade,
    simulate_imu,
)

P_B_A = np.array([0.3, -0.2, -1.1])


@pytest.fixture(scope="module")
def flight():
    frame = LocalFrame.from_degrees(46.7, 11.65, 600.0)
    return simulate_flight(FlightConfig(), frame, 600.0, lambda x, y: 500.0 + 0.01 * np.asarray(y))


# ---------------------------------------------------------------------------- IMU
def test_presets():
    assert set(IMU_PRESETS) == {"navigation", "tactical", "mems", "ideal", "stim300"}  # four grades, one unit
    assert DEFAULT_IMU_GRADE in IMU_PRESETS
    for name, g in IMU_PRESETS.items():
        assert g.name == name and g.source and g.rate_hz == 200.0
    ideal = imu_grade("ideal")
    assert ideal.gyro_noise_density == 0 and ideal.acc_bias_rw_density == 0 and ideal.acc_turn_on_bias == 0
    # ordering of the grades by ARW and bias
    nav, tac, mems = (imu_grade(n) for n in ("navigation", "tactical", "mems"))
    assert nav.gyro_noise_density < tac.gyro_noise_density <= mems.gyro_noise_density
    assert nav.gyro_bias_instability_deg_per_h < mems.gyro_bias_instability_deg_per_h
    # unit conversions: 0.15 deg/sqrt(h) = 0.0025 deg/sqrt(s); 50 ug = 4.9e-4 m/s^2
    assert mems.gyro_noise_density == pytest.approx(np.radians(0.0025))
    assert mems.acc_noise_density == pytest.approx(0.001)
    assert mems.acc_bias_rw_density == pytest.approx(50e-6 * 9.80665 * np.sqrt(2 / 1000))
    with pytest.raises(ValueError):
        imu_grade("consumer")
    with pytest.raises(ValidationError):
        ImuGrade(gyro_arw=0.1)


def test_ideal_imu_is_the_truth(flight):
    imu = simulate_imu(flight, imu_grade("ideal"), 5.0, 25.0, np.random.default_rng(0))
    np.testing.assert_allclose(np.diff(imu.time), 0.005, atol=1e-12)
    assert imu.time[0] == 5.0 and imu.time[-1] == pytest.approx(25.0) and len(imu.time) == 4001
    w, f = flight.imu(imu.time)
    np.testing.assert_array_equal(imu.gyro, w)
    np.testing.assert_array_equal(imu.acc, f)
    assert imu.t0_gps == flight.t0_gps


@pytest.mark.parametrize("seed", [0, 1])
def test_imu_error_statistics(flight, seed):
    grade = imu_grade("mems")
    imu = simulate_imu(flight, grade, 0.0, flight.duration_s, np.random.default_rng(seed))
    w, f = flight.imu(imu.time)
    n_g = imu.gyro - (1.0 + imu.scale_gyro) * w - imu.bias_gyro
    n_f = imu.acc - (1.0 + imu.scale_acc) * f - imu.bias_acc
    for noise, density in ((n_g, grade.gyro_noise_density), (n_f, grade.acc_noise_density)):
        sigma = density * np.sqrt(grade.rate_hz)
        np.testing.assert_allclose(noise.std(axis=0), sigma, rtol=0.03)
        assert np.abs(noise.mean(axis=0)).max() < 4 * sigma / np.sqrt(len(noise))
        # Allan-type check of white noise: averages over m samples scale as 1/sqrt(m)
        m = 200
        avg = noise[: len(noise) // m * m].reshape(-1, m, 3).mean(axis=1)
        np.testing.assert_allclose(avg.std(axis=0), sigma / np.sqrt(m), rtol=0.2)
    dt = 1.0 / grade.rate_hz
    for bias, q, on in ((imu.bias_gyro, grade.gyro_bias_rw_density, grade.gyro_turn_on_bias),
                        (imu.bias_acc, grade.acc_bias_rw_density, grade.acc_turn_on_bias)):
        np.testing.assert_allclose(np.diff(bias, axis=0).std(axis=0), q * np.sqrt(dt), rtol=0.03)
        assert np.abs(bias[0]).max() < 5 * on
    assert np.abs(imu.scale_gyro).max() < 5e-6 * grade.gyro_scale_factor_ppm
    assert np.abs(imu.scale_acc).max() < 5e-6 * grade.acc_scale_factor_ppm


def test_turn_on_bias_and_scale_factor_spread(flight):
    grade = ImuGrade(gyro_turn_on_bias_deg_per_h=10.0, acc_scale_factor_ppm=300.0)
    draws = [simulate_imu(flight, grade, 0.0, 0.1, np.random.default_rng(s)) for s in range(300)]
    b0 = np.array([d.bias_gyro[0] for d in draws])
    s_f = np.array([d.scale_acc for d in draws])
    np.testing.assert_allclose(b0.std(), grade.gyro_turn_on_bias, rtol=0.1)
    np.testing.assert_allclose(s_f.std(), 300e-6, rtol=0.1)
    d = draws[0]
    assert np.all(d.bias_gyro == d.bias_gyro[0])  # no random walk configured
    w, f = flight.imu(d.time)
    np.testing.assert_allclose(d.acc, (1.0 + d.scale_acc) * f, rtol=0, atol=1e-14)


def test_misalignment_mixes_the_axes_and_leaves_the_other_draws_alone(flight):
    """``(I + S + A) x``: each triad's misalignment drawn with its sigma (zero diagonal), the readings
    its mix of the true axes; a grade without misalignment draws the rest as before."""
    plain = imu_grade("mems")
    skew = plain.model_copy(update={"gyro_misalignment_mrad": 0.5, "acc_misalignment_mrad": 1.0})
    a = simulate_imu(flight, plain, 0.0, 20.0, np.random.default_rng(4))
    b = simulate_imu(flight, skew, 0.0, 20.0, np.random.default_rng(4))
    for name in ("bias_gyro", "bias_acc", "scale_gyro", "scale_acc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.any(a.misalignment_gyro) and not np.any(a.misalignment_acc)
    w, f = flight.imu(b.time)
    for read, plain_read, true, scale, mis in ((b.gyro, a.gyro, w, b.scale_gyro, b.misalignment_gyro),
                                                (b.acc, a.acc, f, b.scale_acc, b.misalignment_acc)):
        assert np.all(np.diag(mis) == 0) and np.all(mis[~np.eye(3, dtype=bool)] != 0)
        np.testing.assert_allclose(read - plain_read, true @ mis.T, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(read, true @ (np.eye(3) + np.diag(scale) + mis).T
                                   + (plain_read - (1.0 + scale) * true), rtol=1e-12, atol=1e-12)
    draws = np.array([simulate_imu(flight, ImuGrade(acc_misalignment_mrad=0.8), 0.0, 0.1,
                                   np.random.default_rng(s)).misalignment_acc for s in range(300)])
    off = draws[:, ~np.eye(3, dtype=bool)]
    np.testing.assert_allclose(off.std(), 0.8e-3, rtol=0.1)
    assert np.all(draws[:, np.eye(3, dtype=bool)] == 0)
    with pytest.raises(ValueError, match="zero diagonal"):
        type(a)(**{**a.__dict__, "misalignment_gyro": np.eye(3)})


# ---------------------------------------------------------------------------- GNSS
def test_ideal_gnss_is_the_true_antenna(flight):
    g = simulate_gnss(flight, P_B_A, GnssConfig(grade="ideal"), 0.0, flight.duration_s,
                      np.random.default_rng(0))
    p, R = flight.pose(g.time)
    p_e = flight.frame.to_ecef(p + np.einsum("nij,j->ni", R, P_B_A))
    np.testing.assert_allclose(earth.geodetic_to_ecef(g.lat, g.lon, g.h), p_e, rtol=0, atol=1e-6)
    assert np.all(g.error_ned == 0.0) and np.all(g.quality == 1)


def test_gnss_epochs_rate_and_outages(flight):
    cfg = GnssConfig(outages=[(100.0, 130.0)], rate_hz=2.0)
    g = simulate_gnss(flight, P_B_A, cfg, 3.3, 300.0, np.random.default_rng(1))
    t_gps = g.time + g.t0_gps
    np.testing.assert_allclose(t_gps * 2.0, np.round(t_gps * 2.0), atol=1e-6)  # whole epochs
    assert g.time[0] == pytest.approx(3.5) and g.time[-1] == pytest.approx(300.0)
    assert not np.any((g.time >= 100.0) & (g.time <= 130.0))
    assert len(g.time) == len(np.arange(3.5, 300.01, 0.5)) - 61
    # epochs for an epoch t0 that is not a whole multiple of the period
    t = gnss_epochs(1000.05, 5.0, 0.0, 1.0)
    np.testing.assert_allclose((t + 1000.05) * 5.0, np.round((t + 1000.05) * 5.0), atol=1e-9)
    assert len(t) == 5
    with pytest.raises(ValidationError):
        GnssConfig(outages=[(10.0, 5.0)])


def test_a_float_segment_is_flagged_and_offset(flight):
    """Q=2 with the float sigmas inside the segment, one offset added to the errors there; the draws of
    a configuration without float segments are as before."""
    plain = simulate_gnss(flight, P_B_A, GnssConfig(), 0.0, 300.0, np.random.default_rng(7))
    cfg = GnssConfig(float_segments=[(100.0, 160.0), (200.0, 210.0)])
    g = simulate_gnss(flight, P_B_A, cfg, 0.0, 300.0, np.random.default_rng(7))
    inside = [(g.time >= a) & (g.time <= b) for a, b in cfg.float_segments]
    either = inside[0] | inside[1]
    assert np.all(g.quality[either] == 2) and np.all(g.quality[~either] == 1)
    np.testing.assert_allclose(g.sd_neu[either], np.broadcast_to([0.05, 0.05, 0.10], (either.sum(), 3)))
    np.testing.assert_array_equal(g.sd_neu[~either], plain.sd_neu[~either])
    np.testing.assert_array_equal(g.error_ned[~either], plain.error_ned[~either])
    offsets = []
    for m in inside:
        d = g.error_ned[m] - plain.error_ned[m]
        np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), atol=1e-12)  # one offset per segment
        offsets.append(d[0])
    assert not np.allclose(offsets[0], offsets[1])
    assert np.all(np.abs(np.asarray(offsets)) < 5 * 0.3) and np.any(np.abs(np.asarray(offsets)) > 0.01)
    with pytest.raises(ValidationError):
        GnssConfig(float_segments=[(10.0, 5.0)])


def test_multipath_is_a_short_correlated_error_of_its_own(flight):
    """The multipath is a Gauss-Markov process of its sigma and correlation time, part of the total error and
    kept apart in the truth; Q and sigmas stay; the draws before it are as without it."""
    plain = simulate_gnss(flight, P_B_A, GnssConfig(), 0.0, 350.0, np.random.default_rng(8))
    cfg = GnssConfig(multipath_sigma_horizontal_m=0.02, multipath_sigma_up_m=0.04, multipath_time_constant_s=5.0)
    g = simulate_gnss(flight, P_B_A, cfg, 0.0, 350.0, np.random.default_rng(8))
    np.testing.assert_allclose(g.error_ned - g.multipath_ned, plain.error_ned, atol=1e-12)
    np.testing.assert_array_equal(g.quality, plain.quality)
    np.testing.assert_array_equal(g.sd_neu, plain.sd_neu)
    assert not np.any(plain.multipath_ned) and not np.any(plain.jump_ned) and not np.any(g.jump_ned)
    # 350 s are 70 correlation times: the sample sigma within about 12 % (1 sigma); 20 seeds pin it to 3 %.
    m = g.multipath_ned
    np.testing.assert_allclose(m.std(axis=0), [0.02, 0.02, 0.04], rtol=0.3)
    runs = np.concatenate([simulate_gnss(flight, P_B_A, cfg, 0.0, 350.0, np.random.default_rng(s)).multipath_ned
                           for s in range(20)])
    np.testing.assert_allclose(runs.std(axis=0), [0.02, 0.02, 0.04], rtol=0.08)
    for lag, rho in ((1, np.exp(-0.2 / 5.0)), (25, np.exp(-1.0)), (125, np.exp(-5.0))):  # 0.2 s, tau, 5 tau
        r = [np.mean([np.corrcoef(x[:-lag, i], x[lag:, i])[0, 1] for i in range(3)])
             for x in np.split(runs, 20)]
        assert abs(np.mean(r) - rho) < 0.06, (lag, np.mean(r), rho)
    # smooth at 5 Hz, unlike the white part: an epoch's step has sigma s sqrt(2 (1 - phi)), 0.28 s
    np.testing.assert_allclose(np.diff(runs, axis=0).std(axis=0) / [0.02, 0.02, 0.04],
                               np.sqrt(2.0 * (1.0 - np.exp(-0.2 / 5.0))), rtol=0.1)


def test_an_ambiguity_jump_is_an_offset_the_file_does_not_show(flight):
    """A wrong fix: one offset exactly over its span and none outside, Q=1 and the fixed sigmas kept; the
    draws of a configuration without jumps are as before, the offsets drawn with their sigmas."""
    plain = simulate_gnss(flight, P_B_A, GnssConfig(float_segments=[(300.0, 320.0)]), 0.0, 350.0,
                          np.random.default_rng(9))
    cfg = GnssConfig(float_segments=[(300.0, 320.0)], ambiguity_jumps=[(100.0, 160.0), (200.0, 230.0)])
    g = simulate_gnss(flight, P_B_A, cfg, 0.0, 350.0, np.random.default_rng(9))
    inside = [(g.time >= a) & (g.time <= b) for a, b in cfg.ambiguity_jumps]
    either = inside[0] | inside[1]
    np.testing.assert_array_equal(g.quality, plain.quality)  # Q=1 inside the jumps, 2 in the float segment
    assert np.all(g.quality[either] == 1) and np.all(g.sd_neu[either] == plain.sd_neu[either])
    np.testing.assert_array_equal(g.error_ned[~either], plain.error_ned[~either])
    assert not np.any(g.jump_ned[~either]) and not np.any(g.multipath_ned)
    np.testing.assert_allclose(g.error_ned - g.jump_ned, plain.error_ned, atol=1e-12)
    offsets = []
    for m in inside:
        d = g.error_ned[m] - plain.error_ned[m]
        np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), atol=1e-12)
        np.testing.assert_array_equal(g.jump_ned[m], np.broadcast_to(g.jump_ned[m][0], d.shape))
        offsets.append(d[0])
    assert not np.allclose(offsets[0], offsets[1]) and np.all(np.abs(offsets) > 0)
    draws = np.array([simulate_gnss(flight, P_B_A, GnssConfig(ambiguity_jumps=[(10.0, 11.0)]), 0.0, 12.0,
                                    np.random.default_rng(s)).jump_ned[-6] for s in range(400)])
    np.testing.assert_allclose(draws.std(axis=0), [0.08, 0.08, 0.12], rtol=0.12)
    ideal = simulate_gnss(flight, P_B_A, cfg.model_copy(update={"grade": "ideal"}), 0.0, 350.0,
                          np.random.default_rng(9))
    assert not np.any(ideal.error_ned) and not np.any(ideal.jump_ned)
    with pytest.raises(ValidationError):
        GnssConfig(ambiguity_jumps=[(10.0, 5.0)])
    with pytest.raises(ValidationError, match="overlaps"):
        GnssConfig(float_segments=[(100.0, 120.0)], ambiguity_jumps=[(110.0, 130.0)])


def test_gnss_errors_and_reported_sd(flight):
    cfg = GnssConfig(gm_sigma_horizontal_m=0.0, gm_sigma_up_m=0.0, rate_hz=10.0)
    g = simulate_gnss(flight, P_B_A, cfg, 0.0, flight.duration_s, np.random.default_rng(2))
    np.testing.assert_allclose(g.error_ned.std(axis=0), [0.01, 0.01, 0.02], rtol=0.05)
    np.testing.assert_allclose(g.sd_neu, np.broadcast_to([0.01, 0.01, 0.02], g.sd_neu.shape))
    # the error is measured - true, in NED at the true antenna
    p, R = flight.pose(g.time)
    p_e = flight.frame.to_ecef(p + np.einsum("nij,j->ni", R, P_B_A))
    lat, lon, _ = earth.ecef_to_geodetic(p_e)
    d_e = earth.geodetic_to_ecef(g.lat, g.lon, g.h) - p_e
    np.testing.assert_allclose(np.einsum("nji,nj->ni", earth.R_e_n(lat, lon), d_e), g.error_ned, atol=1e-7)
    default = GnssConfig()
    np.testing.assert_allclose(default.sigma_total_neu, np.hypot([0.01, 0.01, 0.02], [0.015, 0.015, 0.03]))


def test_gauss_markov_statistics():
    dt, tau, sigma = 0.2, 2.0, np.array([0.015, 0.015, 0.03])
    x = _gauss_markov(np.random.default_rng(3), 200_000, dt, sigma, tau)
    np.testing.assert_allclose(x.std(axis=0), sigma, rtol=0.03)
    for lag in (1, int(tau / dt)):
        rho = np.array([np.corrcoef(x[:-lag, i], x[lag:, i])[0, 1] for i in range(3)])
        np.testing.assert_allclose(rho, np.exp(-lag * dt / tau), atol=0.03)
    # stationary from the first sample: the spread across realisations at k = 0 is sigma
    x0 = np.array([_gauss_markov(np.random.default_rng(s), 2, dt, sigma, 300.0)[0] for s in range(2000)])
    np.testing.assert_allclose(x0.std(axis=0), sigma, rtol=0.08)
