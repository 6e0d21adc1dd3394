"""Tests of georefine.evaluation.trajectory and .plots, and ``georefine evaluate trajectory``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from georefine.cli import app
from georefine.errors import InputError
from georefine.evaluation.plots import (
    _envelope,
    plot_attitude_differences,
    plot_position_differences,
)
from georefine.evaluation.trajectory import (
    compare_trajectories,
    consistency,
)
from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.geometry.earth import (
    R_e_n,
    ecef_to_geodetic,
    geodetic_to_ecef,
    radii_of_curvature,
)
from georefine.geometry.rotation import rot_x, rot_y, wrap_angle
from georefine.io.trajectory import SbetData, write_sbet

T0 = 1_400_000_000.0  # GPS seconds (week 2314)
WEEK = 2314
MDEG = np.pi / 180e3  # one mdeg in rad
LAT0, LON0 = np.radians(47.2), np.radians(11.4)


def _truth(t: np.ndarray):
    """Smooth flight: 50 m/s north, 5 m/s east, gentle height, roll, pitch and heading changes."""
    M, N = radii_of_curvature(LAT0)
    lat = LAT0 + 50.0 * t / M
    lon = LON0 + 5.0 * t / (N * np.cos(LAT0))
    h = 650.0 + 2.0 * np.sin(0.3 * t)
    rph = np.column_stack([0.05 * np.sin(0.7 * t), 0.03 * np.cos(0.4 * t), 0.5 + 0.002 * t])
    return lat, lon, h, rph


def _sbet(t_rel, *, d_rph=None, d_ned=None, t0=T0, rph=None) -> SbetData:
    """SBET of the truth at ``t0 + t_rel``, plus attitude offsets (rad, added to the Euler angles)
    and position offsets (m, north-east-down at the true position), each (N,3) or callable of t."""
    t_rel = np.asarray(t_rel, dtype=float)
    n = t_rel.size
    lat, lon, h, rph_true = _truth(t_rel)
    if rph is not None:
        rph_true = rph
    if d_ned is not None:
        d = d_ned(t_rel) if callable(d_ned) else np.broadcast_to(d_ned, (n, 3))
        p_e = geodetic_to_ecef(lat, lon, h) + np.einsum("nij,nj->ni", R_e_n(lat, lon), d)
        lat, lon, h = ecef_to_geodetic(p_e)
    if d_rph is not None:
        rph_true = rph_true + (d_rph(t_rel) if callable(d_rph) else np.broadcast_to(d_rph, (n, 3)))
    return SbetData(
        time_gps=t0 + t_rel, lat_rad=lat, lon_rad=lon, h_m=h, velocity_wander=np.zeros((n, 3)),
        roll_rad=rph_true[:, 0], pitch_rad=rph_true[:, 1], heading_rad=rph_true[:, 2],
        wander_rad=np.zeros(n), accel_b=np.zeros((n, 3)), angular_rate_b=np.zeros((n, 3)),
    )


# ------------------------------------------------------------------------------ exact values


def test_constant_offsets_give_exact_statistics():
    t = np.arange(0.0, 20.0, 0.01)
    d_rph = np.array([5.0, -3.0, 20.0]) * MDEG
    d_ned = np.array([0.10, -0.20, 0.05])
    c = compare_trajectories(_sbet(t, d_rph=d_rph, d_ned=d_ned), _sbet(t))
    s = c.stats
    assert len(c) == t.size and c.n_interpolated == 0 and c.time_base == "reference"
    assert c.t0_gps == T0 and c.time[0] == 0.0
    for name, value in zip(("roll", "pitch", "yaw"), (5.0, -3.0, 20.0)):
        assert s[f"{name}_rmse_mdeg"] == pytest.approx(abs(value), abs=1e-9)
        assert s[f"{name}_mean_mdeg"] == pytest.approx(value, abs=1e-9)
        assert s[f"{name}_std_mdeg"] == pytest.approx(0.0, abs=1e-9)
        assert s[f"{name}_max_abs_mdeg"] == pytest.approx(abs(value), abs=1e-9)
    for name, value in zip(("north", "east", "down"), d_ned):
        assert s[f"{name}_rmse_m"] == pytest.approx(abs(value), abs=1e-7)
        assert s[f"{name}_mean_m"] == pytest.approx(value, abs=1e-7)
    assert s["horizontal_rmse_m"] == pytest.approx(np.hypot(0.1, 0.2), abs=1e-7)
    assert s["3d_rmse_m"] == pytest.approx(np.sqrt(0.01 + 0.04 + 0.0025), abs=1e-7)
    np.testing.assert_allclose(c.d_ned_m, np.broadcast_to(d_ned, (t.size, 3)), atol=1e-7)


def test_linear_offset_gives_hand_computed_rmse():
    # d_yaw(t_i) = b t_i, t_i = i dt, i = 0..N-1:
    # mean(d^2) = b^2 dt^2 (N-1)(2N-1)/6, mean(d) = b dt (N-1)/2, std^2 = b^2 dt^2 (N^2-1)/12.
    n, dt, b = 1001, 0.01, 2.0  # b in mdeg/s: 20 mdeg after 10 s
    t = np.arange(n) * dt
    c = compare_trajectories(_sbet(t, d_rph=lambda t: np.column_stack([0 * t, 0 * t, b * MDEG * t])), _sbet(t))
    assert c.stats["yaw_rmse_mdeg"] == pytest.approx(b * dt * np.sqrt((n - 1) * (2 * n - 1) / 6), rel=1e-9)
    assert c.stats["yaw_mean_mdeg"] == pytest.approx(b * dt * (n - 1) / 2, rel=1e-9)
    assert c.stats["yaw_std_mdeg"] == pytest.approx(b * dt * np.sqrt((n * n - 1) / 12), rel=1e-9)
    assert c.stats["yaw_max_abs_mdeg"] == pytest.approx(20.0, rel=1e-9)
    assert c.stats["roll_rmse_mdeg"] == pytest.approx(0.0, abs=1e-9)
    # rmse^2 = mean^2 + std^2 (population std)
    s = c.stats
    assert s["yaw_rmse_mdeg"] ** 2 == pytest.approx(s["yaw_mean_mdeg"] ** 2 + s["yaw_std_mdeg"] ** 2, rel=1e-12)


def test_rotation_vector_of_euler_offsets():
    t = np.arange(0.0, 5.0, 0.05)
    _, _, _, rph = _truth(t)
    # A roll offset is a rotation about body x: Rx(r + d) = Rx(r) Rx(d).
    c = compare_trajectories(_sbet(t, d_rph=[7 * MDEG, 0, 0]), _sbet(t))
    np.testing.assert_allclose(c.d_rotvec_rad, np.tile([7 * MDEG, 0, 0], (t.size, 1)), atol=1e-13)
    # A heading offset is a rotation about the local down axis, in body: (Ry(p) Rx(r))^T e_z d.
    c = compare_trajectories(_sbet(t, d_rph=[0, 0, 9 * MDEG]), _sbet(t))
    down_b = np.einsum("nji,j->ni", rot_y(rph[:, 1]) @ rot_x(rph[:, 0]), [0.0, 0.0, 1.0])
    np.testing.assert_allclose(c.d_rotvec_rad, 9 * MDEG * down_b, atol=1e-12)
    assert c.stats["attitude_angle_rmse_mdeg"] == pytest.approx(9.0, abs=1e-8)


# ------------------------------------------------------------------------------ time grids


@pytest.mark.parametrize("seed", [0, 1])
def test_interpolation_between_different_grids(seed):
    rng = np.random.default_rng(seed)
    t_ref = np.arange(0.0, 60.0, 0.1)  # 10 Hz
    t_est = -1.0 + rng.uniform(0, 0.005) + np.arange(0, 62.0, 0.005)  # 200 Hz, shifted
    d_rph = np.array([4.0, -2.0, 15.0]) * MDEG
    d_ned = lambda t: np.column_stack([0.01 * t, -0.02 + 0 * t, 0.03 + 0 * t])  # noqa: E731
    c = compare_trajectories(_sbet(t_est, d_rph=d_rph, d_ned=d_ned), _sbet(t_ref))
    assert c.time_base == "reference" and len(c) == t_ref.size and c.n_interpolated == t_ref.size
    # Interpolation error over 5 ms of this motion: < dt^2/8 * max|angular acc| ~ 1e-7 rad.
    np.testing.assert_allclose(c.d_rph_rad, np.tile(d_rph, (t_ref.size, 1)), atol=0.005 * MDEG)
    np.testing.assert_allclose(c.d_ned_m, d_ned(t_ref), atol=1e-5)
    # The sparser trajectory gives the time base also when it is the estimate.
    c2 = compare_trajectories(_sbet(t_ref, d_rph=d_rph, d_ned=d_ned), _sbet(t_est))
    assert c2.time_base == "estimate" and len(c2) == t_ref.size
    np.testing.assert_allclose(c2.d_rph_rad, np.tile(d_rph, (t_ref.size, 1)), atol=0.005 * MDEG)
    np.testing.assert_allclose(c2.d_ned_m, d_ned(t_ref), atol=1e-5)


def test_common_times_are_the_overlap_and_window():
    c = compare_trajectories(_sbet(np.arange(5.0, 30.0, 0.01)), _sbet(np.arange(0.0, 20.0, 0.1)))
    assert c.t0_gps == pytest.approx(T0 + 5.0) and c.time[-1] == pytest.approx(14.9, abs=1e-6)
    c = compare_trajectories(_sbet(np.arange(0.0, 30.0, 0.01)), _sbet(np.arange(0.0, 20.0, 0.1)),
                             time_window=(T0 + 2.0, T0 + 4.0))
    assert c.t0_gps == pytest.approx(T0 + 2.0) and len(c) == 21


def test_end_samples_within_max_time_offset_are_kept():
    t = np.arange(0.0, 10.0, 0.1)
    est = _sbet(t + 2e-6)  # same grid up to 2 microseconds
    c = compare_trajectories(est, _sbet(t), max_time_offset_s=1e-5)
    assert len(c) == t.size
    c = compare_trajectories(est, _sbet(t), max_time_offset_s=1e-7)
    assert len(c) == t.size - 1


def test_gaps_are_not_interpolated():
    i = np.arange(3000)
    t_est = 0.01 * i[(i < 1000) | (i > 1500)]  # 100 Hz with a gap (9.99 s, 15.01 s)
    c = compare_trajectories(_sbet(t_est), _sbet(np.arange(0.0, 30.0, 0.1)))
    assert c.n_dropped == 51 and len(c) == 300 - 51  # reference samples 10.0 .. 15.0 s
    assert not np.any((c.time_gps > T0 + 10.0 + 1e-6) & (c.time_gps < T0 + 15.0 - 1e-6))


# ------------------------------------------------------------------------------ wrap-around


def test_heading_difference_across_north():
    t_ref = np.arange(0.0, 10.0, 0.1)
    t_est = np.arange(-0.0013, 10.01, 0.005)
    heading = lambda t: -0.01 + 0.002 * t  # noqa: E731  crosses north at t = 5 s

    def rph(t):
        return np.column_stack([0.02 + 0 * t, 0.01 + 0 * t, heading(t)])

    ref = _sbet(t_ref, rph=np.column_stack([rph(t_ref)[:, :2], np.mod(heading(t_ref), 2 * np.pi)]))
    est_rph = rph(t_est) + [0, 0, 10 * MDEG]
    est_rph[:, 2] = wrap_angle(est_rph[:, 2])  # stored in (-pi, pi]: other representation
    c = compare_trajectories(_sbet(t_est, rph=est_rph), ref)
    assert c.n_interpolated == t_ref.size
    np.testing.assert_allclose(c.d_rph_rad[:, 2], 10 * MDEG, atol=1e-4 * MDEG)
    assert c.stats["yaw_max_abs_mdeg"] == pytest.approx(10.0, abs=1e-4)
    # Plain difference of the stored values would be about 360 deg before the crossing.
    assert np.ptp(ref.heading_rad) > 6.0


# ------------------------------------------------------------------------------ errors


def test_non_overlapping_spans_raise():
    with pytest.raises(InputError, match=r"do not overlap.*estimate \[.*1400000020\.000.*reference \[.*"):
        compare_trajectories(_sbet(np.arange(20.0, 30.0, 0.1)), _sbet(np.arange(0.0, 10.0, 0.1)))
    with pytest.raises(InputError, match="time window"):
        compare_trajectories(_sbet(np.arange(0.0, 30.0, 0.1)), _sbet(np.arange(0.0, 10.0, 0.1)),
                             time_window=(T0 + 50.0, T0 + 60.0))


# ------------------------------------------------------------------------------ consistency


@pytest.mark.parametrize("seed", [3, 4])
def test_consistency_of_stated_sigmas(seed):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 40.0, 0.02)
    sigma = np.array([5.0, 3.0, 12.0]) * MDEG
    c = compare_trajectories(_sbet(t, d_rph=rng.normal(size=(t.size, 3)) * sigma), _sbet(t))
    nees = consistency(c, np.tile(sigma, (t.size, 1)))
    np.testing.assert_allclose(nees, 1.0, atol=0.06)
    np.testing.assert_allclose(consistency(c, np.tile(sigma / 2, (t.size, 1))), 2 * nees, rtol=1e-12)
    # sigmas on their own time grid are interpolated to the common times
    ts = T0 + np.arange(-1.0, 41.0, 1.0)
    np.testing.assert_allclose(consistency(c, np.tile(sigma, (ts.size, 1)), ts), nees, rtol=1e-12)
    with pytest.raises(ValueError, match="positive"):
        consistency(c, np.zeros((t.size, 3)))


# ------------------------------------------------------------------------------ plots


def test_plots_are_written(tmp_path):
    t = np.arange(0.0, 30.0, 0.05)
    ref = _sbet(t)
    c1 = compare_trajectories(_sbet(t, d_rph=lambda t: np.column_stack([8 * MDEG * np.sin(t), 4 * MDEG + 0 * t,
                                                                        20 * MDEG * np.cos(0.1 * t)])), ref)
    c2 = compare_trajectories(_sbet(t[100:], d_rph=[1 * MDEG, 2 * MDEG, 2 * MDEG], d_ned=[0.02, 0, 0]), ref)
    out = plot_attitude_differences({"G/I - G/I/L": c1, "G/I/L N-S - G/I/L": c2}, tmp_path / "att.png",
                                    title="Fig. 9")
    pos = plot_position_differences({"a": c1, "b": c2}, tmp_path / "pos.png")
    for p in (out, pos):
        assert p.stat().st_size > 10_000 and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["att.png", "pos.png"]  # no temp files left
    with pytest.raises(ValueError):
        plot_attitude_differences({}, tmp_path / "none.png")


def test_envelope_keeps_extremes():
    rng = np.random.default_rng(5)
    t = np.arange(100_001, dtype=float)
    y = rng.normal(size=t.size)
    y[12_345] = 50.0
    tt, yy = _envelope(t, y, max_points=2000)
    assert tt.size <= 2100 and np.all(np.diff(tt) > 0)
    assert yy.max() == 50.0 and yy.min() == y.min()


# ------------------------------------------------------------------------------ files and CLI


def _write_pair(tmp_path, scale_est="gps", scale_ref="gps"):
    rng = np.random.default_rng(7)
    t_ref = np.arange(0.0, 30.0, 0.1)
    t_est = np.arange(-0.5, 31.0, 0.005)
    est = _sbet(t_est, d_rph=lambda t: np.column_stack([3 * MDEG + 0 * t, 2 * MDEG * np.sin(t), 0.5 * MDEG * t]),
                d_ned=rng.normal(scale=0.02, size=3))
    e = write_sbet(tmp_path / "estimate.sbet", est, scale_est)
    r = write_sbet(tmp_path / "reference.sbet", _sbet(t_ref), scale_ref)
    return e, r


def test_sbet_time_scales(tmp_path):
    e, r = _write_pair(tmp_path, "gps", "gps")
    base = compare_sbet_files(e, r)
    assert base.time_scale == "gps" and base.notes == () and base.gps_week == WEEK
    (tmp_path / "w").mkdir()
    ew, rw = _write_pair(tmp_path / "w", "week", "week")
    same = compare_sbet_files(ew, rw)
    assert same.time_scale == "seconds_of_week" and "same GPS week" in same.notes[0]
    assert same.to_dict()["t0_gps_s"] is None and same.gps_week is None
    given = compare_sbet_files(ew, rw, gps_week=WEEK)
    mixed = compare_sbet_files(ew, r)
    assert given.time_scale == mixed.time_scale == "gps" and f"GPS week {WEEK}" in mixed.notes[0]
    for c in (same, given, mixed):
        assert len(c) == len(base)
        np.testing.assert_allclose(c.d_rph_rad, base.d_rph_rad, atol=1e-3 * MDEG)
        np.testing.assert_allclose(c.d_ned_m, base.d_ned_m, atol=1e-4)
    assert given.t0_gps == pytest.approx(base.t0_gps, abs=1e-6)
    # a window in seconds of week or in GPS seconds selects the same epochs
    sow0 = T0 - WEEK * 604800.0
    for c_args in ((ew, rw, None), (e, r, None), (ew, rw, WEEK)):
        for window in ((sow0 + 5.0, sow0 + 10.0), (T0 + 5.0, T0 + 10.0)):
            c = compare_sbet_files(c_args[0], c_args[1], gps_week=c_args[2], time_window=window)
            assert len(c) == 51, (c_args, window)


def _cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_cli_end_to_end(tmp_path):
    e, r = _write_pair(tmp_path)
    out = tmp_path / "eval" / "run1"
    res = _cli("evaluate", "trajectory", e, "--reference", r, "--out", out)
    assert res.exit_code == 0, res.output
    assert "roll" in res.stdout and "yaw" in res.stdout and "3D" in res.stdout
    data = json.loads((out / "trajectory_comparison.json").read_text())
    lib = compare_sbet_files(e, r).to_dict()
    assert data == json.loads(json.dumps(lib))
    assert data["roll_rmse_mdeg"] == pytest.approx(3.0, abs=1e-3)
    for name in ("attitude_differences.png", "position_differences.png"):
        assert (out / name).stat().st_size > 0
    # without --out nothing is written; --span restricts the epochs
    res = _cli("evaluate", "trajectory", e, "--reference", r, "--span", T0 + 5.0, T0 + 10.0)
    assert res.exit_code == 0, res.output
    assert "51 epochs" in res.stdout


def test_cli_seconds_of_week_note(tmp_path):
    e, r = _write_pair(tmp_path, "week", "week")
    res = _cli("evaluate", "trajectory", e, "--reference", r, "--out", tmp_path / "o")
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "o" / "trajectory_comparison.json").read_text())
    assert data["time_scale"] == "seconds_of_week" and data["gps_week"] is None
    assert "same GPS week" in data["notes"][0] and "same GPS week" in res.stdout
    res = _cli("evaluate", "trajectory", e, "--reference", r, "--gps-week", WEEK, "--out", tmp_path / "p")
    data = json.loads((tmp_path / "p" / "trajectory_comparison.json").read_text())
    assert data["time_scale"] == "gps" and data["gps_week"] == WEEK


def test_cli_bad_input(tmp_path):
    e, r = _write_pair(tmp_path)
    bad = tmp_path / "truncated.sbet"
    bad.write_bytes(r.read_bytes()[:-50])  # size no longer a multiple of 136
    res = _cli("evaluate", "trajectory", e, "--reference", bad)
    assert res.exit_code == 2
    assert "truncated.sbet" in res.stderr and "incomplete record" in res.stderr
    # the output folder must not be an input
    res = _cli("evaluate", "trajectory", e, "--reference", r, "--out", e)
    assert res.exit_code == 2 and "input" in res.stderr
    assert e.stat().st_size % 136 == 0 and e.is_file()
    # no overlap: both spans in the message
    far = write_sbet(tmp_path / "far.sbet", _sbet(np.arange(100.0, 110.0, 0.1)), "gps")
    res = _cli("evaluate", "trajectory", e, "--reference", far)
    assert res.exit_code == 2 and "do not overlap" in res.stderr
