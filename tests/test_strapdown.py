"""Strapdown mechanisation in w: njit Earth model equals the numpy one; accuracy on the truth."""

import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3, exp_so3_into, log_so3, right_jacobian_inv
from georefine.sim.flight import FlightConfig, simulate_flight
from georefine.trajectory import strapdown as sd

RATE_HZ = 200.0


@pytest.fixture(scope="module")
def frame():
    return LocalFrame.from_degrees(46.7, 11.65, 600.0)


@pytest.fixture(scope="module")
def flight(frame):
    return simulate_flight(FlightConfig(), frame, 600.0, lambda x, y: 500.0 + 0.01 * np.asarray(y))


def truth_window(flight, t0, duration=60.0):
    t = t0 + np.arange(int(round(duration * RATE_HZ)) + 1) / RATE_HZ
    return t, flight.state(t), flight.imu(t)


def errors(result, state):
    dp = np.linalg.norm(result.p_w_b - state.p_w_b, axis=1).max()
    dR = log_so3(np.swapaxes(state.R_w_b, 1, 2) @ result.R_w_b)
    return dp, np.degrees(np.linalg.norm(dR, axis=1).max()) * 1e3  # m, mdeg


# ---------------------------------------------------------------------------- njit helpers
@pytest.mark.parametrize("seed", [0, 1])
def test_njit_earth_model_equals_numpy(frame, seed):
    rng = np.random.default_rng(seed)
    p_w = rng.uniform([-3e4, -3e4, -500.0], [3e4, 3e4, 5000.0], (200, 3))
    p_e = frame.to_ecef(p_w)
    lat, lon, h = earth.ecef_to_geodetic(p_e)
    R_e_w, p_e_w, _ = sd.frame_arrays(frame)
    g_ref = frame.gravity_w(p_w)
    out = np.empty(3)
    for i in range(len(p_w)):
        la, lo, hh = sd._ecef_to_geodetic(*p_e[i])
        assert (la, lo) == pytest.approx((lat[i], lon[i]), abs=1e-15)
        assert hh == pytest.approx(h[i], abs=1e-8)
        gamma = earth.normal_gravity(lat[i], h[i])
        assert sd._normal_gravity(lat[i], h[i]) == pytest.approx(gamma, abs=1e-14)
        sd._gravity_w(p_w[i], R_e_w, p_e_w, out)
        np.testing.assert_allclose(out, g_ref[i], rtol=0, atol=1e-13)


@pytest.mark.parametrize("scale", [1e-7, 1e-3, 0.5, 2.5])
def test_njit_so3_helpers(scale):
    rng = np.random.default_rng(4)
    for phi, v in zip(rng.normal(size=(20, 3)) * scale, rng.normal(size=(20, 3))):
        E = np.empty((3, 3))
        exp_so3_into(phi, E)  # the kernel the integration calls (exp_so3 runs it element by element)
        np.testing.assert_allclose(E, Rotation.from_rotvec(phi).as_matrix(), rtol=0, atol=1e-15)
        np.testing.assert_allclose(E, exp_so3(phi), rtol=0, atol=1e-15)
        out = np.empty(3)
        sd._jr_inv_apply(phi, v, out)
        np.testing.assert_allclose(out, right_jacobian_inv(phi) @ v, rtol=0, atol=1e-13)


# ---------------------------------------------------------------------------- accuracy
def test_acceptance_60_s_of_flight_with_ideal_imu(frame, flight):
    """Manoeuvre end, approach and the start of the first pass: within 5 cm and 1 mdeg."""
    manoeuvre = [(a, b) for n, a, b in flight.phases if n == "manoeuvre"][0]
    t, s, (w, f) = truth_window(flight, manoeuvre[1] - 35.0)
    assert t[-1] > flight.passes[0][1]  # includes straight flight on the pass
    result = sd.integrate(frame, t, w, f, s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])
    dp, da = errors(result, s)
    assert dp < 0.05 and da < 1.0  # acceptance test of the project
    assert dp < 1e-4 and da < 1e-3  # achieved: ~1e-8 m, ~1e-6 mdeg
    np.testing.assert_allclose(result.v_w_b, s.v_w_b, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(result.time, t)


def test_increments_mode(frame, flight):
    t, s, _ = truth_window(flight, 50.0)
    # exact increments over (t_k-1, t_k] by 5-point Gauss-Legendre quadrature of the truth
    xg, wg = np.polynomial.legendre.leggauss(5)
    dt = 1.0 / RATE_HZ
    tq = (t[:, None] - 0.5 * dt) + 0.5 * dt * xg[None, :]
    wq, fq = flight.imu(tq.ravel())
    dtheta = 0.5 * dt * np.einsum("q,nqk->nk", wg, wq.reshape(len(t), 5, 3))
    dv = 0.5 * dt * np.einsum("q,nqk->nk", wg, fq.reshape(len(t), 5, 3))
    result = sd.integrate(frame, t, dtheta, dv, s.p_w_b[0], s.v_w_b[0], s.R_w_b[0], increments=True)
    dp, da = errors(result, s)
    assert dp < 1e-4 and da < 1e-3


def test_stationary_stays_put(frame, flight):
    t_static = [b for n, a, b in flight.phases if n == "static"][0]
    t, s, (w, f) = truth_window(flight, 0.0, t_static)
    result = sd.integrate(frame, t, w, f, s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])
    dp, da = errors(result, s)
    assert dp < 1e-9 and da < 1e-9
    # ten minutes of constant at-rest samples
    n = int(600 * RATE_HZ)
    tt = np.arange(n) / RATE_HZ
    result = sd.integrate(frame, tt, np.tile(w[0], (n, 1)), np.tile(f[0], (n, 1)),
                          s.p_w_b[0], np.zeros(3), s.R_w_b[0])
    assert np.abs(result.p_w_b - s.p_w_b[0]).max() < 1e-6
    assert np.abs(result.v_w_b).max() < 1e-8
    assert np.degrees(np.linalg.norm(log_so3(s.R_w_b[0].T @ result.R_w_b[-1]))) < 1e-8


def test_step_function_equals_batch(frame, flight):
    t, s, (w, f) = truth_window(flight, 100.0, 1.0)
    result = sd.integrate(frame, t, w, f, s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])
    wm, fm = sd.midpoints_from_samples(t, w), sd.midpoints_from_samples(t, f)
    state = sd.StrapdownState(s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])
    for k in range(len(t) - 1):
        state = sd.strapdown_step(frame, state, w[k], f[k], w[k + 1], f[k + 1], t[k + 1] - t[k], wm[k], fm[k])
    np.testing.assert_allclose(state.p_w_b, result.p_w_b[-1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(state.R_w_b, result.R_w_b[-1], rtol=0, atol=1e-12)
    # without mid values the step is second order: still close over one second
    state2 = sd.StrapdownState(s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])
    for k in range(len(t) - 1):
        state2 = sd.strapdown_step(frame, state2, w[k], f[k], w[k + 1], f[k + 1], t[k + 1] - t[k])
    assert np.linalg.norm(state2.p_w_b - s.p_w_b[-1]) < 1e-4


def test_jittered_sample_times(frame, flight):
    rng = np.random.default_rng(5)
    t = 60.0 + np.arange(4001) / RATE_HZ + rng.uniform(-1e-4, 1e-4, 4001)
    s = flight.state(t)
    w, f = flight.imu(t)
    result = sd.integrate(frame, t, w, f, s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])
    dp, da = errors(result, s)
    assert dp < 1e-4 and da < 1e-3


def test_speed(frame, flight):
    t, s, (w, f) = truth_window(flight, 150.0)
    sd.integrate(frame, t[:10], w[:10], f[:10], s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])  # compiled
    start = time.perf_counter()
    sd.integrate(frame, t, w, f, s.p_w_b[0], s.v_w_b[0], s.R_w_b[0])
    assert time.perf_counter() - start < 1.0  # ~0.05 s


def test_input_validation(frame):
    t = np.arange(5) / RATE_HZ
    z = np.zeros((5, 3))
    with pytest.raises(ValueError):
        sd.integrate(frame, t, z[:4], z, np.zeros(3), np.zeros(3), np.eye(3))
    with pytest.raises(ValueError):
        sd.integrate(frame, t[::-1], z, z, np.zeros(3), np.zeros(3), np.eye(3))
    with pytest.raises(ValueError):
        sd.integrate(frame, t[:1], z[:1], z[:1], np.zeros(3), np.zeros(3), np.eye(3))
