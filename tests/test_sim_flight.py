"""True helicopter trajectory: analytic derivatives, exact rest, corridor geometry, attitude."""

import time

import numpy as np
import pytest
from pydantic import ValidationError

from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import log_so3
from georefine.sim.flight import FlightConfig, VibrationConfig, simulate_flight

LENGTH_M = 600.0


def terrain(x, y):
    return 500.0 + 0.01 * np.asarray(y) + 0.0 * np.asarray(x)


@pytest.fixture(scope="module")
def frame():
    return LocalFrame.from_degrees(46.7, 11.65, 600.0)


@pytest.fixture(scope="module")
def flight(frame):
    return simulate_flight(FlightConfig(), frame, LENGTH_M, terrain)


@pytest.fixture(scope="module")
def shaky(frame):
    cfg = FlightConfig(vibration=VibrationConfig(enabled=True))
    return simulate_flight(cfg, frame, LENGTH_M, terrain)


def phase(traj, name, index=0):
    spans = [(a, b) for n, a, b in traj.phases if n == name]
    return spans[index]


def moving_times(traj, n=3000):
    t_static = phase(traj, "static")[1]
    return np.linspace(t_static + 0.01, traj.duration_s - 0.01, n)


def richardson(fn, t, h):
    """Central difference with one Richardson step (error O(h^4))."""
    return (4.0 * fn(t, h / 2) - fn(t, h)) / 3.0


def test_timeline(flight):
    names = [n for n, _, _ in flight.phases]
    assert names == ["static", "takeoff", "manoeuvre", "approach", "pass", "turn", "approach",
                     "pass", "end"]
    ends = np.array([(a, b) for _, a, b in flight.phases])
    np.testing.assert_allclose(ends[1:, 0], ends[:-1, 1])
    assert ends[0, 0] == 0.0 and ends[-1, 1] == pytest.approx(flight.duration_s)
    assert [p[0] for p in flight.passes] == [1, 2]
    assert 50.0 < phase(flight, "manoeuvre")[1] - phase(flight, "manoeuvre")[0] < 100.0
    assert flight.t0_gps == 1399708800.0


def test_passes_cover_corridor_along_axis(flight):
    cfg = flight.config
    (_, a1, b1), (_, a2, b2) = flight.passes
    y = lambda t: flight.pose(t)[0][1]  # noqa: E731
    assert y(a1) == pytest.approx(LENGTH_M + cfg.lead_in_m, abs=1e-6)
    assert y(b1) == pytest.approx(-cfg.lead_out_m, abs=1e-6)
    assert y(a2) == pytest.approx(-cfg.lead_in_m, abs=1e-3)
    assert y(b2) == pytest.approx(LENGTH_M + cfg.lead_out_m, abs=1e-3)
    for _, a, b in flight.passes:
        p, _ = flight.pose(np.linspace(a, b, 500))
        assert np.abs(p[:, 0]).max() < 1e-3  # on the axis x = 0


def test_body_rate_matches_finite_difference_of_attitude(flight, shaky):
    for traj, h in ((flight, 1e-3), (shaky, 2e-4)):
        t = moving_times(traj)

        def rate(t, h):
            _, Rm = traj.pose(t - h)
            _, Rp = traj.pose(t + h)
            return log_so3(np.swapaxes(Rm, 1, 2) @ Rp) / (2.0 * h)

        np.testing.assert_allclose(richardson(rate, t, h), traj.state(t).omega_wb_b, rtol=0, atol=1e-9)


def test_velocity_and_acceleration_match_finite_differences(flight, shaky):
    for traj, h, tol_a in ((flight, 1e-3, 1e-8), (shaky, 2e-4, 1e-6)):
        t = moving_times(traj)
        s = traj.state(t)
        dp = richardson(lambda t, h: (traj.state(t + h).p_w_b - traj.state(t - h).p_w_b) / (2 * h), t, h)
        dv = richardson(lambda t, h: (traj.state(t + h).v_w_b - traj.state(t - h).v_w_b) / (2 * h), t, h)
        np.testing.assert_allclose(dp, s.v_w_b, rtol=0, atol=1e-7)
        np.testing.assert_allclose(dv, s.a_w_b, rtol=0, atol=tol_a)


def test_static_period_is_exactly_at_rest(flight, frame):
    t = np.linspace(0.0, phase(flight, "static")[1], 201)
    s = flight.state(t)
    assert np.all(s.v_w_b == 0.0) and np.all(s.a_w_b == 0.0) and np.all(s.omega_wb_b == 0.0)
    assert np.all(s.p_w_b == s.p_w_b[0]) and np.all(s.R_w_b == s.R_w_b[0])
    agl = s.p_w_b[0, 2] - terrain(*s.p_w_b[0, :2])
    assert agl == pytest.approx(flight.config.ground_clearance_m, abs=1e-9)
    omega_ib, f_ib = flight.imu(t)
    lat, lon, h = frame.to_geodetic(s.p_w_b)
    np.testing.assert_allclose(np.linalg.norm(f_ib, axis=1), earth.normal_gravity(lat, h), rtol=0, atol=1e-9)
    g_b = np.einsum("nji,nj->ni", s.R_w_b, frame.gravity_w(s.p_w_b))
    np.testing.assert_allclose(f_ib, -g_b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(omega_ib, axis=1), 7.292115e-5, rtol=1e-12)
    np.testing.assert_allclose(omega_ib, np.einsum("nji,j->ni", s.R_w_b, frame.omega_ie_w), atol=1e-18)
    # the ground attitude of the configuration
    rph = np.degrees(flight.rph(t[:1]))[0]
    assert rph[0] == pytest.approx(flight.config.ground_roll_deg, abs=1e-9)
    assert rph[1] == pytest.approx(flight.config.ground_pitch_deg, abs=1e-9)


def test_take_off_is_smooth(flight):
    t_s = phase(flight, "static")[1]
    s = flight.state(np.array([t_s - 1e-6, t_s + 1e-6, t_s + 0.05]))
    assert np.abs(s.a_w_b).max() < 1e-3 and np.abs(s.omega_wb_b).max() < 1e-4


def test_passes_height_speed_crab_and_level_flight(flight):
    cfg = flight.config
    for strip, a, b in flight.passes:
        t = np.linspace(a, b, 400)
        s = flight.state(t)
        agl = s.p_w_b[:, 2] - terrain(s.p_w_b[:, 0], s.p_w_b[:, 1])
        assert np.abs(agl - cfg.altitude_agl_m).max() < 0.1
        speed_h = np.linalg.norm(s.v_w_b[:, :2], axis=1)
        np.testing.assert_allclose(speed_h, cfg.speed_mps, atol=1e-4)
        rph = flight.rph(t)
        R_n_w = np.swapaxes(flight.frame.R_w_n_at(s.p_w_b), 1, 2)
        v_n = np.einsum("nij,nj->ni", R_n_w, s.v_w_b)
        track = np.arctan2(v_n[:, 1], v_n[:, 0])
        crab = np.degrees((rph[:, 2] - track + np.pi) % (2 * np.pi) - np.pi)
        expected = cfg.crab_angle_deg if strip == 1 else -cfg.crab_angle_deg
        np.testing.assert_allclose(crab, expected, atol=1e-3)
        assert np.abs(np.degrees(rph[:, 0])).max() < 0.01
        np.testing.assert_allclose(np.degrees(rph[:, 1]), cfg.cruise_pitch_deg, atol=0.01)


def test_bank_in_turns(flight):
    cfg = flight.config
    a, b = phase(flight, "turn")
    roll = np.degrees(flight.rph(np.linspace(a, b, 2000))[:, 0])
    bank = np.degrees(np.arctan(cfg.speed_mps**2 / cfg.turn_radius_m / 9.806))
    assert roll.max() == pytest.approx(bank, abs=0.3)  # right turn away from the axis
    assert roll.min() == pytest.approx(-bank, abs=0.3)  # then the long left turn back
    a, b = phase(flight, "manoeuvre")
    roll = np.degrees(flight.rph(np.linspace(a, b, 2000))[:, 0])
    assert roll.max() > 15.0 and roll.min() < -15.0  # figure-eight: both directions
    s = flight.state(np.linspace(a, b, 2000))
    assert np.ptp(np.linalg.norm(s.v_w_b, axis=1)) > 6.0  # accelerations
    assert np.ptp(s.v_w_b[:, 2]) > 2.0  # climbs and descents


def test_pose_matches_state_and_shapes(flight):
    t = moving_times(flight, 100)
    p, R = flight.pose(t)
    s = flight.state(t)
    np.testing.assert_array_equal(p, s.p_w_b)
    np.testing.assert_allclose(R, s.R_w_b, atol=1e-15)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    p1, R1 = flight.pose(t[5])
    assert p1.shape == (3,) and R1.shape == (3, 3)
    w, f = flight.imu(t[5])
    assert w.shape == (3,) and f.shape == (3,)
    with pytest.raises(ValueError):
        flight.pose(np.array([-1.0]))
    with pytest.raises(ValueError):
        flight.pose(flight.duration_s + 1.0)


def test_pose_is_fast(flight):
    t = np.linspace(0.0, flight.duration_s, 1_000_000)
    start = time.perf_counter()
    p, R = flight.pose(t)
    assert time.perf_counter() - start < 10.0  # ~1 s on a laptop core
    assert np.isfinite(p).all() and np.isfinite(R).all()


def test_vibration_adds_high_frequency_motion(flight, shaky):
    a, b = flight.passes[0][1:]
    t = np.linspace(a, b, 20000)
    d_w = shaky.state(t).omega_wb_b - flight.state(t).omega_wb_b
    d_a = shaky.state(t).a_w_b - flight.state(t).a_w_b
    assert 1e-3 < np.abs(d_w).max() < 0.05
    assert 0.05 < np.abs(d_a).max() < 5.0


@pytest.mark.parametrize("manoeuvre", ["s_turns", "none"])
def test_single_pass_variants(frame, manoeuvre):
    cfg = FlightConfig(passes=1, manoeuvre=manoeuvre, static_duration_s=0.0, crab_angle_deg=-5.0)
    traj = simulate_flight(cfg, frame, 300.0, terrain)
    assert len(traj.passes) == 1
    _, a, b = traj.passes[0]
    p, _ = traj.pose(np.linspace(a, b, 100))
    assert np.abs(p[:, 0]).max() < 1e-3 and p[0, 1] > 300.0 and p[-1, 1] < 0.0
    s = traj.state(np.array([0.0]))
    assert np.all(s.v_w_b == 0.0)


def test_config_rejects_unknown_fields():
    with pytest.raises(ValidationError):
        FlightConfig(speed=18.0)
    with pytest.raises(ValidationError):
        VibrationConfig(frequencies_hz=(0.1,))


def test_the_papers_whole_corridor_is_an_hour_of_strips_at_its_pulse_rate():
    """``corridor-paper-full``: paper 000's 30 km corridor flown twice at 1.8 MHz (about 6 G pulses
    over 56 minutes of strips), the pulse rate overridable for benchmarks."""
    from georefine.sim.scenarios import SCENARIOS, resolve_scenario

    assert "corridor-paper-full" in SCENARIOS
    cfg = resolve_scenario("corridor-paper-full")
    assert cfg.scene.length_m == 30_000.0 and cfg.flight.passes == 2
    assert cfg.scanner.pulse_rate_hz == 1.8e6 and cfg.scanner.line_rate_hz == 400.0
    rp = cfg.reference_point
    frame = LocalFrame.from_degrees(rp.lat_deg, rp.lon_deg, rp.h_m)
    flight = simulate_flight(cfg.flight, frame, cfg.scene.length_m, lambda x, y: np.zeros(np.shape(x)))
    strips_s = sum(b - a for name, a, b in flight.phases if name == "pass")
    assert 50 * 60 < strips_s < 70 * 60, strips_s
    assert 5.0e9 < cfg.scanner.pulse_rate_hz * strips_s < 6.5e9
    assert resolve_scenario("corridor-paper-full", seed_overrides=["scanner.pulse_rate_hz=400000"]).scanner.pulse_rate_hz == 4e5
