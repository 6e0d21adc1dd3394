"""IMU up-sampling: high-frequency motion rebuilt from the raw IMU (docs/ARCHITECTURE.md §4.6).

Unit checks of the high-pass and the reconstruction against a simulated vibrating flight, and
the GNSS/IMU adjustment end to end on a vibrating corridor, with and without up-sampling.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from georefine.evaluation.trajectory import consistency
from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import log_so3
from georefine.io.trajectory import read_sbet
from georefine.io.trajectory_csv import read_trajectory_csv
from georefine.sim.flight import FlightConfig, VibrationConfig, simulate_flight
from georefine.sim.scenarios import simulate_project
from georefine.trajectory.highrate import high_pass, reconstruct_high_rate, significant_content
from georefine.trajectory.sampled import trajectory_from_sbet
from georefine.trajectory.spline import KnotGrid
from georefine.trajectory.spline_fit import fit_spline
from georefine.workflows import load_navigation, run_trajectory

FAST_SCAN = ["scanner.pulse_rate_hz=2000", "scanner.line_rate_hz=100"]  # navigation only


def test_high_pass_removes_what_a_spline_on_the_knots_holds_and_keeps_faster_motion():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 20.0, 0.005)
    c = rng.normal(size=(4, 3))
    slow = c[0] + np.outer(t, c[1]) + np.outer(t**2, c[2]) * 0.1 + np.outer(t**3, c[3]) * 0.01
    assert np.abs(high_pass(t, slow, 0.1)).max() < 1e-8 * np.abs(slow).max()
    fast = np.sin(2 * np.pi * 26.0 * t)[:, None] * np.ones(3)
    kept = high_pass(t, slow + fast, 0.1)
    inner = (t > 1) & (t < 19)
    assert np.sqrt(np.mean((kept - fast)[inner] ** 2)) < 0.03  # 26 Hz passes a 0.1 s spline almost untouched
    assert np.all(high_pass(t[:30], fast[:30], 0.1) == 0.0)  # shorter than four knot intervals: all slow



def test_high_pass_is_the_least_squares_spline_residual_of_scipy():
    """The banded normal equations give scipy's least-squares spline (irregular sampling, (N, 3, 3) values)."""
    from scipy.interpolate import make_lsq_spline

    rng = np.random.default_rng(8)
    t = np.cumsum(rng.uniform(0.003, 0.007, 3000))
    y = rng.normal(size=(t.size, 3, 3)) + np.sin(t)[:, None, None]
    out = high_pass(t, y, 0.25)
    inner = t[0] + 0.25 * np.arange(1, int(np.floor((t[-1] - t[0]) / 0.25)))
    if t[-1] - inner[-1] < 0.125:
        inner = inner[:-1]
    knots = np.concatenate([np.full(4, t[0]), inner, np.full(4, t[-1])])
    ref = y - make_lsq_spline(t, y.reshape(t.size, -1), knots, k=3)(t).reshape(y.shape)
    assert out.shape == y.shape
    np.testing.assert_allclose(out, ref, atol=1e-10)

@pytest.fixture(scope="module")
def vibrating_flight():
    frame = LocalFrame.from_degrees(48.0, 11.0, 500.0)

    def terrain(x, y):
        return 500.0 + 0.01 * np.asarray(y)

    vib = simulate_flight(FlightConfig(vibration=VibrationConfig(enabled=True)), frame, 600.0, terrain)
    smooth = simulate_flight(FlightConfig(), frame, 600.0, terrain)
    t = np.arange(20.0, 60.0, 1 / 200)
    s = smooth.state(t)
    spline = fit_spline(KnotGrid(20.0, 0.1, 401), t, s.p_w_b, s.R_w_b, s.v_w_b, s.omega_wb_b)
    return frame, vib, smooth, spline, t


def test_integration_of_the_readings_follows_a_rotor_harmonic():
    """The rebuild integrates the samples' interpolating cubic spline: a 26 Hz line sampled at
    200 Hz comes out within 0.1 % of its amplitude, where the trapezoid rule misses 4-6 %."""
    from scipy.integrate import cumulative_trapezoid

    from georefine.trajectory.highrate import _integral

    t = np.arange(0.0, 30.0, 1 / 200)
    for f in (6.5, 13.0, 26.0):
        w = 2 * np.pi * f
        rate = np.column_stack([np.cos(w * t), np.sin(w * t)])
        exact = np.column_stack([np.sin(w * t), 1.0 - np.cos(w * t)]) / w
        inner = (t > 1) & (t < 29)

        def rel(x):
            e = x - exact
            return np.sqrt(np.mean((e - e[inner].mean(axis=0))[inner] ** 2)) / np.sqrt(np.mean(exact[inner] ** 2))

        ours = rel(_integral(t, rate))
        assert ours < 1e-3, (f, ours)  # measured 0.0002 % / 0.003 % / 0.055 % at 6.5 / 13 / 26 Hz
        assert rel(cumulative_trapezoid(rate, t, axis=0, initial=0.0)) > 20 * ours  # the rule it replaced: 0.25-4 %


def test_significant_content_keeps_vibration_lines_and_leaves_white_noise():
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 60.0, 1 / 200)
    lines = 0.5 * np.sin(2 * np.pi * 13.0 * t) + 0.2 * np.sin(2 * np.pi * 26.0 * t + 1.0)
    noise = rng.normal(scale=0.05, size=(t.size, 2))
    x = np.column_stack([lines, np.zeros_like(t)]) + noise
    kept = significant_content(x)
    assert np.sqrt(np.mean((kept[:, 0] - lines) ** 2)) < 0.1 * np.sqrt(np.mean(lines**2))
    # Of pure noise hardly anything is taken: the windows keep the noise their weights assume.
    assert np.sqrt(np.mean(kept[:, 1] ** 2)) < 0.05 * 0.05
    assert np.all(significant_content(x[:40]) == 0.0)


def test_the_redundancy_the_cleaning_consumes_is_what_it_takes_out_of_the_windows_noise():
    """The cleaning subtracts from the readings a filter fitted to themselves (the lines' bins of
    the high-passed corrections, all of them near the ends). Over draws of the sensor noise, the
    windows' whitened sum of squares of cleaned noise is smaller than that of the raw noise by
    what :meth:`HighRateMotion.removed_noise` predicts from one draw of unit noise
    (:func:`georefine.adjustment.gnss_imu.cleaning_redundancy`)."""
    from georefine.adjustment.observations.imu import make_imu_windows
    from georefine.trajectory.highrate import HighRateMotion

    rate, knot, window = 200.0, 0.1, 0.02
    t = np.arange(0.0, 60.0, 1 / rate)
    lines = np.column_stack([np.sin(2 * np.pi * f * t + k) for k, f in enumerate((6.5, 13.0, 26.0, 6.5, 13.0, 26.0))])
    zeros = np.zeros((t.size, 3))
    hf = HighRateMotion(t, zeros, zeros, zeros, zeros, zeros, knot)

    def windows_ss(x):
        w = make_imu_windows(t, x[:, :3], x[:, 3:], rate, window)
        return float(np.sum(w.gyro**2) + np.sum(w.acc**2)) * round(window * rate)  # unit sample noise

    rng = np.random.default_rng(21)
    drops, predicted = [], []
    for _ in range(6):
        noise = rng.normal(size=(t.size, 6))
        corrections = high_pass(t, lines + noise, knot)
        d_omega, d_f, unit = hf.removed_noise(corrections[:, :3], corrections[:, 3:], rate, seed=int(rng.integers(1 << 30)))
        cleaned = noise - np.hstack([d_omega, d_f]) + high_pass(t, lines, knot)  # the lines go whole
        drops.append(windows_ss(noise) - windows_ss(cleaned))
        predicted.append(windows_ss(unit))
    rows = 6 * t.size / round(window * rate)
    drop, pred = np.mean(drops), np.mean(predicted)
    assert 0.03 * rows < pred < 0.5 * rows, (pred, rows)  # the lines' bins and the ends: a share, not all
    assert abs(drop - pred) < 0.1 * pred, (drop, pred)
    # Without lines the test keeps hardly any bin: only the ends are spent.
    _, _, unit = hf.removed_noise(*np.hsplit(high_pass(t, rng.normal(size=(t.size, 6)), knot), 2), rate)
    ends = hf.edges(rate).mean() * rows
    assert windows_ss(unit) < 1.2 * ends, (windows_ss(unit), ends)


def test_reconstruction_restores_the_vibration_that_the_spline_lacks(vibrating_flight):
    frame, vib, smooth, spline, t = vibrating_flight
    gyro, acc = vib.imu(t)
    hf = reconstruct_high_rate(frame, spline, t, gyro, acc, 200.0)
    p_true, R_true = vib.pose(t)
    m = (t > 21) & (t < 59)

    def att_rms(R):
        return np.sqrt(np.mean(np.sum(log_so3(np.swapaxes(R, 1, 2) @ R_true)[m] ** 2, axis=1)))

    traj = hf.trajectory(spline)
    spline_alone = att_rms(spline.pose(t)[1])
    assert spline_alone > np.radians(0.005)  # the vibration is there and the spline misses it
    assert att_rms(traj.R_w_b) < spline_alone / 8
    # What the motion adds to the readings is what the vibration adds (iteration input).
    d_omega, d_f = hf.reading_corrections(frame, spline)
    g_smooth, f_smooth = smooth.imu(t)
    for got, want in ((d_omega, gyro - g_smooth), (d_f, acc - f_smooth)):
        assert np.sqrt(np.mean((got - want)[m] ** 2)) < 0.05 * np.sqrt(np.mean(want[m] ** 2))
    # Within half a Fourier block of the ends all of the corrections are taken out of the windows
    # (there the test cannot tell the lines from the noise), elsewhere what stands out of the noise.
    sig_omega, sig_f = hf.significant_corrections(frame, spline, 200.0)
    edges = hf.edges(200.0)
    assert edges[0] and edges[-1] and not edges[t.size // 2]
    assert np.count_nonzero(edges) == 2 * (2048 // 2)
    np.testing.assert_array_equal(sig_omega[edges], d_omega[edges])
    np.testing.assert_array_equal(sig_f[edges], d_f[edges])
    assert np.abs(sig_omega[~edges] - d_omega[~edges]).max() > 0.0
    # Inputs outside the spline are dropped; none of the inputs is modified.
    t_out = np.concatenate([[10.0], t])
    hf2 = reconstruct_high_rate(frame, spline, t_out, np.vstack([gyro[:1], gyro]), np.vstack([acc[:1], acc]), 200.0)
    assert np.array_equal(hf2.time, t)


def _high_frequency_attitude_error(project: Path, sbet: Path) -> float:
    """RMS (mdeg) of the attitude error faster than 1 s during the passes."""
    nav = load_navigation(project)
    week = int(nav.t0_gps // 604800)
    est = trajectory_from_sbet(read_sbet(sbet, gps_week=week), nav.frame, nav.t0_gps)
    truth = trajectory_from_sbet(read_sbet(project / "truth" / "trajectory.sbet", gps_week=week), nav.frame, nav.t0_gps)
    out = []
    for p in yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"]:
        t = est.time[(est.time > p["t_start_s"] + 1) & (est.time < p["t_end_s"] - 1)]
        e = log_so3(np.swapaxes(truth.interpolate(t)[1], 1, 2) @ est.interpolate(t)[1])
        out.append(high_pass(t, e, 1.0))
    e = np.concatenate(out)
    return float(np.degrees(np.sqrt(np.mean(np.sum(e**2, axis=1)))) * 1e3)


def test_gnss_imu_adjustment_on_a_vibrating_platform_with_and_without_upsampling(tmp_path, caplog):
    project = tmp_path / "vib"
    simulate_project("corridor-tiny", project, seed=5, overrides=FAST_SCAN + ["flight.vibration.enabled=true"])
    up = run_trajectory(project, tmp_path / "up")
    cfg = yaml.safe_load((project / "project.yaml").read_text())
    cfg.setdefault("processing", {}).setdefault("trajectory", {})["upsampling"] = False
    (project / "project.yaml").write_text(yaml.safe_dump(cfg))
    with caplog.at_level("WARNING", logger="georefine.workflows.navigation"):
        down = run_trajectory(project, tmp_path / "down")
    # Without up-sampling the windows carry the vibration as noise: not silently.
    assert any("times worse than the IMU noise model" in r.getMessage() for r in caplog.records)
    assert up.adjustment.high_rate is not None and down.adjustment.high_rate is None
    # The G/I/L then runs every outer iteration on the configured knots (no coarse first one, which
    # would alias the vibration into the trajectory: georefine.workflows.run_parts.outer_knot_interval).
    from georefine.adjustment.upsampling import high_rate_share
    from georefine.workflows.opened import load_navigation
    from georefine.workflows.run_parts import VIBRATION_SHARE

    assert high_rate_share(load_navigation(project).gnss, up.adjustment) > VIBRATION_SHARE

    hf_up = _high_frequency_attitude_error(project, tmp_path / "up" / "trajectory.sbet")
    hf_down = _high_frequency_attitude_error(project, tmp_path / "down" / "trajectory.sbet")
    assert hf_up < 0.4 * hf_down, (hf_up, hf_down)  # measured 1.4 against 5.9 mdeg (BENCHMARKS.md)
    assert hf_up < 2.5

    s_up = compare_sbet_files(tmp_path / "up" / "trajectory.sbet", project / "truth" / "trajectory.sbet")
    s_down = compare_sbet_files(tmp_path / "down" / "trajectory.sbet", project / "truth" / "trajectory.sbet")
    for angle in ("roll", "pitch"):
        assert s_up.stats[f"{angle}_rmse_mdeg"] < 0.9 * s_down.stats[f"{angle}_rmse_mdeg"], angle
    # Yaw, the weak angle of straight flight, rests on the same GNSS information either way: the two
    # solutions differ by a fraction of its sigma (measured 28.2 against 24.2 mdeg, sigma 29 mdeg).
    table = read_trajectory_csv(tmp_path / "up" / "trajectory.csv")
    yaw_sigma = 1e3 * np.degrees(np.sqrt(np.mean(table.sigma_rpy_rad[:, 2] ** 2)))
    assert abs(s_up.stats["yaw_rmse_mdeg"] - s_down.stats["yaw_rmse_mdeg"]) < 0.5 * yaw_sigma, yaw_sigma
    # Consistency: with the vibration out of the windows and the noise left in, the variance
    # factor is that of a smooth platform again and the posterior sigma describe the errors.
    assert 0.8 < up.adjustment.solve.variance_factor < 1.5, up.adjustment.solve.variance_factor
    assert down.adjustment.solve.variance_factor > 100
    ratio = consistency(s_up, table.sigma_rpy_rad, table.time_gps)
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio


def test_navigation_grade_imu_on_a_vibrating_platform_states_honest_sigmas(tmp_path):
    """A navigation-grade gyro's noise is 1/1700 of a 5 mdeg rotor line at 13 Hz, so the windows
    show any misfit of the line's removal. Two were found: the windows' model took the samples as the
    midpoint rule of a continuous mean ((2 pi f dt)^2 / 24 of a line at f), and the significance test
    kept only part of each line within half a Fourier block of the ends. The G/I's variance factor
    was 246 and every sigma 16x too large (RMS of error/sigma 0.05-0.09); then 2.6 and 0.44-0.89.
    With the redundancy the cleaning spends counted and a second cleaning (the first keeps part of
    the aliased vibration): 1.78, the windows at 0.47 per row, roll and pitch at 0.79-0.85."""
    project = tmp_path / "vib"
    simulate_project("corridor-tiny", project, seed=5, imu_grade="navigation",
                     overrides=FAST_SCAN + ["flight.vibration.enabled=true"])
    run = run_trajectory(project, tmp_path / "gi")
    solve = run.adjustment.solve
    imu = next(g for g in solve.groups if g.name == "imu")
    assert solve.variance_factor < 5.0 and imu.variance_factor < 2.0, (solve.variance_factor, imu.variance_factor)
    from georefine.evaluation.trajectory_files import truth_pass_accuracy

    for strip in (1, 2):
        acc = truth_pass_accuracy(tmp_path / "gi" / "trajectory.sbet", project, strip)
        assert np.all(acc.rmse_mdeg[:2] < 0.4), acc.rmse_mdeg  # measured 0.18-0.29 mdeg (0.21-0.31 before)
        assert np.all((acc.z_rms[:2] > 0.5) & (acc.z_rms[:2] < 2.0)), acc.z_rms
        assert acc.z_rms[2] > 0.3, acc.z_rms  # yaw: one sample of a slow error per pass
        assert np.all(acc.beyond_3_sigma <= 0.01), acc.beyond_3_sigma


@pytest.mark.parametrize("n", [2, 3, 4, 5, 9, 1000])
def test_cubic_integral_is_scipys_not_a_knot_antiderivative(n):
    """The integral of the samples' not-a-knot cubic spline, solved and summed here, equals
    SciPy's ``CubicSpline(t, y).antiderivative()(t)`` on irregular spacing, one or many columns."""
    from scipy.interpolate import CubicSpline

    from georefine.trajectory.highrate import _integral

    rng = np.random.default_rng(n)
    t = np.cumsum(rng.uniform(0.5, 1.5, n)) * 5e-3
    for y in (rng.normal(size=n).cumsum(), rng.normal(size=(n, 3)).cumsum(axis=0)):
        ref = CubicSpline(t, y, axis=0).antiderivative()(t)
        got = _integral(t, y)
        assert got.shape == y.shape
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * max(1.0, np.abs(ref).max()))


def test_significant_content_block_by_block_equals_the_whole_series(monkeypatch):
    """Stretches of a few STFT hops with a window's margin either side give the whole series'
    result exactly (every block's bins and noise are its own), with ``also`` too, whatever the
    series' length against the stretch."""
    import georefine.trajectory.highrate as highrate

    rng = np.random.default_rng(31)
    n = 12_345
    t = np.arange(n) / 200.0
    x = rng.normal(size=(n, 3)) + 0.4 * np.sin(2 * np.pi * 13.0 * t)[:, None]
    u = rng.normal(size=(n, 3))
    monkeypatch.setattr(highrate, "STFT_CHUNK_BLOCKS", 10**6)
    whole, whole_u = significant_content(x, block=256, also=u)
    assert np.abs(whole).max() > 0.1  # the 13 Hz line passes
    monkeypatch.setattr(highrate, "STFT_CHUNK_BLOCKS", 4)
    parts, parts_u = significant_content(x, block=256, also=u)
    np.testing.assert_allclose(parts, whole, rtol=0, atol=1e-12)
    np.testing.assert_allclose(parts_u, whole_u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(significant_content(x, block=256), whole, rtol=0, atol=1e-12)
