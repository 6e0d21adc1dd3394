"""IMU sampling gaps: found, bridged with the interpolation error measured on the data, or refused."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.adjustment.observations.imu import make_imu_windows
from georefine.io.imu import ImuData
from georefine.io.imu_gaps import bridge_imu_gaps, find_imu_gaps, interpolation_sigma

RATE = 200.0


def _imu(seed: int = 0, seconds: float = 60.0, noise: float = 0.002) -> ImuData:
    """Smooth motion (0.2-2 Hz) with a 12 Hz vibration and white noise: a helicopter-like record."""
    rng = np.random.default_rng(seed)
    t = 1000.0 + np.arange(int(seconds * RATE)) / RATE
    phases = rng.uniform(0, 2 * np.pi, (4, 3))
    motion = (0.05 * np.sin(2 * np.pi * 0.2 * t[:, None] + phases[0]) + 0.02 * np.sin(2 * np.pi * 2.0 * t[:, None] + phases[1])
              + 0.01 * np.sin(2 * np.pi * 12.0 * t[:, None] + phases[2]))
    gyro = motion + rng.normal(0, noise, motion.shape)
    acc = 5 * motion + [0, 0, -9.81] + rng.normal(0, 10 * noise, motion.shape)
    return ImuData(t, gyro, acc, RATE)


def _drop(imu: ImuData, keep: np.ndarray) -> ImuData:
    return ImuData(imu.time_gps[keep], imu.gyro[keep], imu.acc[keep], imu.rate_hz)


def test_interpolation_sigma_is_zero_on_a_line_and_the_noise_on_white_noise():
    x = np.linspace(0, 1, 500)[:, None] * [1.0, -2.0, 3.0]
    assert interpolation_sigma(x, 7) == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(3)
    noise = rng.normal(0, 1.0, (20000, 3))
    # one hidden sample midway: its error is n_j - (n_l + n_r) / 2, variance 1 + 1/2
    assert interpolation_sigma(noise, 1, max_starts=20000) == pytest.approx(np.sqrt(1.5), rel=0.03)
    assert np.isnan(interpolation_sigma(x[:5], 7))


def test_gaps_are_bridged_on_the_nominal_grid_with_linear_readings():
    full = _imu()
    keep = np.ones(len(full), bool)
    keep[2000::2000] = False  # one dropped sample every 10 s
    keep[5000:5100] = False  # a 0.5 s run
    imu = _drop(full, keep)
    gaps = find_imu_gaps(imu)
    assert len(gaps) == 6 and sorted(g.missing for g in gaps) == [1, 1, 1, 1, 1, 100]
    bridged, too_long = bridge_imu_gaps(imu, max_gap_s=1.0)
    assert too_long is None and bridged.n_bridged == int((~keep).sum())
    np.testing.assert_allclose(bridged.data.time_gps, full.time_gps, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(bridged.data.gyro[keep], full.gyro[keep])  # measured samples untouched
    assert np.all(bridged.gyro_sigma[keep] == 0) and np.all(bridged.gyro_sigma[~keep] > 0)
    # the 0.5 s run is a straight line between its neighbours
    run = bridged.data.gyro[4999:5101]
    np.testing.assert_allclose(run, np.linspace(run[0], run[-1], run.shape[0]), atol=1e-12)
    text = bridged.describe()
    assert "6 IMU sampling gaps bridged (105 samples interpolated), the longest 0.505 s" in text
    longest_sigma = bridged.gyro_sigma[5000]  # the first bridged sample of the 0.5 s run (two gaps before it)
    assert longest_sigma > 0 and f"gyro sigma {np.degrees(longest_sigma):.3g} deg/s" in text


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_widened_sigma_matches_the_actual_interpolation_error(seed):
    """The sigma of the bridged samples is the error they really make (within 30-40 %)."""
    full = _imu(seed)
    rng = np.random.default_rng(seed)
    ratios = {}
    for missing in (1, 20, 100):
        starts = rng.choice(np.arange(3000, len(full) - 3000 - missing), 40, replace=False)
        errs, sig_g, sig_a = [], [], []
        for s in starts:
            keep = np.ones(len(full), bool)
            keep[s:s + missing] = False
            b, _ = bridge_imu_gaps(_drop(full, keep), max_gap_s=1.0)
            errs.append((b.data.gyro[~keep] - full.gyro[~keep]).ravel())
            sig_g.append(b.gyro_sigma[~keep][0])
            sig_a.append(b.acc_sigma[~keep][0])
        actual = np.sqrt(np.mean(np.concatenate(errs) ** 2))
        ratios[missing] = actual / np.mean(sig_g)
        assert np.all(np.asarray(sig_a) > np.asarray(sig_g))  # the accelerometer moves 5x, its noise 10x
    assert all(0.7 < r < 1.4 for r in ratios.values()), ratios  # measured 0.88-1.01


def test_a_gap_longer_than_the_limit_is_returned_and_nothing_bridged():
    full = _imu(seconds=20)
    keep = np.ones(len(full), bool)
    keep[100] = False
    keep[2000:2400] = False  # 2 s
    imu = _drop(full, keep)
    bridged, too_long = bridge_imu_gaps(imu, max_gap_s=1.0)
    assert too_long is not None and too_long.missing == 400 and too_long.index == 1998
    assert bridged.data is imu and not bridged.gaps
    ok, none = bridge_imu_gaps(imu, max_gap_s=3.0)
    assert none is None and len(ok.gaps) == 2
    clean, none = bridge_imu_gaps(full, max_gap_s=1.0)
    assert none is None and clean.data is full and clean.describe() == "no IMU sampling gaps"


def test_windows_carry_the_bridged_sigma_of_their_samples():
    full = _imu(seconds=2)
    sigma = np.zeros(len(full))
    sigma[10:13] = 0.3  # 3 bridged samples in the window of samples 8..11 and 12..15 (4 per window)
    w = make_imu_windows(full.time_gps, full.gyro, full.acc, RATE, 0.02, gyro_sigma=sigma, acc_sigma=2 * sigma)
    assert w.n_samples[0] == 4
    np.testing.assert_allclose(w.gyro_bridged_sigma[2:4], [0.3 * 2 / 4, 0.3 / 4])
    np.testing.assert_allclose(w.acc_bridged_sigma[2:4], [0.6 * 2 / 4, 0.6 / 4])
    assert np.all(w.gyro_bridged_sigma[[0, 1, 4]] == 0)
    plain = make_imu_windows(full.time_gps, full.gyro, full.acc, RATE, 0.02, gyro_sigma=np.zeros(len(full)))
    assert plain.gyro_bridged_sigma is None and plain.acc_bridged_sigma is None
