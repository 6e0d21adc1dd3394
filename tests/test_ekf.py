"""Initialisation filter (error-state EKF + RTS smoother) on a simulated helicopter flight.

Flight: flat terrain, 600 m corridor, one pass, figure-eight manoeuvre (~190 s; 10 s on the pad,
lift-off, heading aligned at 23.5 s). Achieved with seeds 0 and 1 and the default PPK GNSS
(white 1/1/2 cm + Gauss-Markov 1.5/1.5/3 cm, 300 s; reported sd 1.8/1.8/3.6 cm E/N/U):

======== ============== =============== ================= ==================== ===================
grade    pos RMSE cm    roll/pitch RMSE heading RMSE mdeg heading after        RMS(err/sigma) att
         E / N / U      mdeg            (whole span)      manoeuvre RMS / max  roll, pitch, hdg
======== ============== =============== ================= ==================== ===================
mems     1.7-2.0 / 1.5- 2.9-3.4 /       9.9-13.7          12-20 / 27-36 mdeg   0.73-0.92,
         2.7 / 0.8-2.2  3.9-4.9                                                0.88-1.17, 0.45
tactical 1.7-2.0 / 1.5- 3.6-4.1 /       7-30              5-45 / 13-61 mdeg    0.58-0.73,
         2.6 / 0.8-2.2  5.2-7.0                                                0.70-1.11, 0.49-1.2
======== ============== =============== ================= ==================== ===================

The position error is the GNSS Gauss-Markov error, which the filter does not model: its
position sigma (white GNSS noise assumed) gives RMS(err/sigma) of 1.6-9 with PPK and mean NIS
~1. With white GNSS errors (Gauss-Markov part off) position RMSE is 1.3-3.6 mm,
RMS(err/sigma) 0.66-1.16 and the mean NIS 2.94-2.97 (chi-square, 3 dof).
"""

import time

import numpy as np
import pytest
from pydantic import ValidationError

from georefine.config import ImuErrorSpec
from georefine.errors import InputError
from georefine.geometry import earth
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3, log_so3
from georefine.io.gnss import GnssSolution, gnss_in_w
from georefine.io.imu import ImuData
from georefine.sim.flight import FlightConfig, simulate_flight
from georefine.sim.gnss import GnssConfig, simulate_gnss
from georefine.sim.imu import imu_grade, simulate_imu
from georefine.trajectory import _ekf_kernels as kernels
from georefine.trajectory import strapdown as sd
from georefine.trajectory.ekf import FilterConfig, run_filter
from georefine.trajectory.sampled import Trajectory

P_B_A = np.array([0.3, -0.2, -1.1])
MDEG = np.degrees(1.0) * 1e3  # rad -> mdeg


@pytest.fixture(scope="module")
def frame():
    return LocalFrame.from_degrees(46.7, 11.65, 600.0)


@pytest.fixture(scope="module")
def flight(frame):
    return simulate_flight(FlightConfig(passes=1), frame, 600.0, lambda x, y: 500.0 + 0.0 * x)


def phase_end(flight, name):
    return next(b for n, _, b in flight.phases if n == name)


def gnss_w(frame, g):
    """SimulatedGnss -> (time, p_w, cov_w): ENU covariance at each fix rotated into w."""
    p_w = frame.from_geodetic(g.lat, g.lon, g.h)
    R_w_enu = frame.R_e_w.T @ earth.R_e_enu(g.lat, g.lon)
    cov_enu = np.zeros((len(g.time), 3, 3))
    cov_enu[:, [0, 1, 2], [0, 1, 2]] = g.sd_neu[:, [1, 0, 2]] ** 2
    return g.time, p_w, R_w_enu @ cov_enu @ np.swapaxes(R_w_enu, 1, 2)


def simulate(flight, grade_name, seed, gnss_cfg=None):
    rng = np.random.default_rng(seed)
    grade = imu_grade(grade_name)
    sim = simulate_imu(flight, grade, 0.0, flight.duration_s, rng)
    g = simulate_gnss(flight, P_B_A, gnss_cfg or GnssConfig(), 0.0, flight.duration_s, rng)
    spec = ImuErrorSpec(**{k: v for k, v in grade.model_dump().items() if k in ImuErrorSpec.model_fields})
    imu = ImuData(sim.time + flight.t0_gps, sim.gyro, sim.acc, grade.rate_hz)
    return sim, imu, g, spec


def run(frame, flight, imu, g, spec, cfg=None):
    return run_filter(frame, flight.t0_gps, imu, *gnss_w(frame, g), P_B_A, spec, cfg or FilterConfig())


def errors(frame, flight, res):
    """Position error (N,3) m, NED roll/pitch/heading error (N,3) rad, body attitude error (N,3)."""
    s = flight.state(res.time)
    rph = frame.rph_from_R_w_b(res.p_w_b, res.R_w_b)
    d_rph = (rph - flight.rph(res.time) + np.pi) % (2 * np.pi) - np.pi
    d_theta = log_so3(np.swapaxes(res.R_w_b, 1, 2) @ s.R_w_b)  # truth = estimate Exp(d_theta)
    return res.p_w_b - s.p_w_b, d_rph, d_theta


def rms(x, axis=0):
    return np.sqrt(np.mean(x**2, axis=axis))


def gnss_bound(g):
    """Twice the GNSS noise per w axis (E, N, U): reported sd or realised RMS, the larger."""
    realised = rms(g.error_ned[:, [1, 0, 2]])
    return 2.0 * np.maximum(GnssConfig().sigma_total_neu[[1, 0, 2]], realised)


@pytest.fixture(scope="module")
def runs(frame, flight):
    """Filter results for both grades and two seeds with the default PPK GNSS."""
    out = {}
    for grade in ("mems", "tactical"):
        for seed in (0, 1):
            sim, imu, g, spec = simulate(flight, grade, seed)
            out[grade, seed] = (sim, g, run(frame, flight, imu, g, spec))
    return out


# ---------------------------------------------------------------------------- linearisation
@pytest.mark.parametrize("seed", [0, 1])
def test_gnss_jacobian_finite_differences(seed):
    rng = np.random.default_rng(seed)
    R = exp_so3(rng.normal(size=3))
    p, v, om, w_ie = rng.normal(size=3) * 100, rng.normal(size=3) * 20, rng.normal(size=3), rng.normal(size=3) * 1e-4
    lever, d = rng.normal(size=3), rng.uniform(0.0, 0.005)
    H = np.zeros((3, 21))
    kernels._gnss_model(p, v, R, om, w_ie, lever, d, H)
    eps = 1e-6
    J = np.zeros((3, 9))
    for i in range(9):
        hs = []
        for sgn in (1.0, -1.0):
            dx = np.zeros(9)
            dx[i] = sgn * eps
            R_p = R @ exp_so3(dx[6:9])
            # omega_ib_b is a measurement: held fixed, so omega_wb_b changes only through R^T w_ie
            hs.append(kernels._gnss_model(p + dx[:3], v + dx[3:6], R_p, om, w_ie, lever, d, np.zeros((3, 21))))
        J[:, i] = (hs[0] - hs[1]) / (2 * eps)
    np.testing.assert_allclose(H[:, :9], J, rtol=0, atol=1e-6)
    assert np.all(H[:, 9:] == 0.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_transition_matches_perturbed_mechanisation(frame, flight, seed):
    """Phi accumulated over 1 s of a turn equals central differences of the mechanisation."""
    rng = np.random.default_rng(seed)
    t = 50.0 + rng.uniform(0, 40) + np.arange(201) / 200.0
    s = flight.state(t)
    w, f = flight.imu(t)
    wm, fm = sd.midpoints_from_samples(t, w), sd.midpoints_from_samples(t, f)
    Phi = np.eye(21)
    tmp = [np.zeros((3, 3)) for _ in range(4)] + [np.zeros((21, 21))]
    W_ie = np.cross(np.eye(3), frame.omega_ie_w).T  # [w_ie]x
    Gam = 9.8 / (6371e3 + 600.0) * np.diag([-1.0, -1.0, 2.0])
    for k in range(len(t) - 1):
        kernels._accumulate(Phi, t[k + 1] - t[k], s.R_w_b[k], fm[k], wm[k], W_ie, Gam, *tmp)

    def propagate(dx):
        ba, bg, sa, sg = dx[9:12], dx[12:15], dx[15:18], dx[18:21]
        r = sd.integrate(frame, t, (w - bg) / (1 + sg), (f - ba) / (1 + sa), s.p_w_b[0] + dx[:3],
                         s.v_w_b[0] + dx[3:6], s.R_w_b[0] @ exp_so3(dx[6:9]))
        return r.p_w_b[-1], r.v_w_b[-1], r.R_w_b[-1]

    ref = propagate(np.zeros(21))
    scale = np.repeat([0.1, 0.01, 1e-3, 1e-3, 1e-5, 1e-3, 1e-3], 3)
    J = np.zeros((9, 21))
    for i in range(21):
        cols = []
        for sgn in (1.0, -1.0):
            dx = np.zeros(21)
            dx[i] = sgn * scale[i]
            p, v, R = propagate(dx)
            cols.append(np.concatenate([p - ref[0], v - ref[1], log_so3(ref[2].T @ R)]))
        J[:, i] = (cols[0] - cols[1]) / (2 * scale[i])
    # semi-implicit product at 200 Hz: agreement to ~1e-3 of each block's magnitude (the
    # gravity gradient, ~1e-6 s^-2, is the spherical approximation: 1e-8 absolute)
    for r0 in (0, 3, 6):
        for c0 in range(0, 21, 3):
            blk, ref_blk = Phi[r0:r0 + 3, c0:c0 + 3], J[r0:r0 + 3, c0:c0 + 3]
            np.testing.assert_allclose(blk, ref_blk, rtol=0, atol=2e-3 * np.abs(ref_blk).max() + 1e-8)
    np.testing.assert_array_equal(Phi[9:], np.eye(21)[9:])


# ---------------------------------------------------------------------------- accuracy
@pytest.mark.parametrize("grade", ["mems", "tactical"])
@pytest.mark.parametrize("seed", [0, 1])
def test_accuracy_and_consistency(frame, flight, runs, grade, seed):
    sim, g, res = runs[grade, seed]
    dp, d_rph, d_theta = errors(frame, flight, res)
    after = res.time > phase_end(flight, "manoeuvre")
    # position: GNSS-limited (the Gauss-Markov part is not averaged out)
    assert np.all(rms(dp) < gnss_bound(g))
    # roll/pitch: mems 2.5-4.9 mdeg, tactical 2-10 mdeg achieved
    assert np.all(rms(d_rph[:, :2]) * MDEG < {"mems": 12.0, "tactical": 25.0}[grade])
    # heading after the manoeuvre: mems 12-20 mdeg RMS (max 27-36), tactical 5-45 (max 61)
    assert rms(d_rph[after, 2]) * MDEG < {"mems": 50.0, "tactical": 100.0}[grade]
    if grade == "mems":
        assert np.abs(d_rph[after, 2]).max() * MDEG < 100.0  # < 0.1 deg
    # consistency of the attitude sigma (body-frame error, as estimated)
    ratio = rms(d_theta / res.sigma[:, 6:9])
    assert np.all((ratio > 0.3) & (ratio < 3.0)), ratio
    # gyro biases converge to the truth within 3 sigma (checked at the end and on average)
    k = np.rint((res.time - sim.time[0]) * 200.0).astype(int)
    db_g = res.bias_gyro - sim.bias_gyro[k]
    assert np.all(np.abs(db_g[-1]) < 3.0 * res.sigma[-1, 12:15])
    assert np.all(rms(db_g / res.sigma[:, 12:15]) < 3.0)  # 0.4-2.8 over seeds 0-7
    if grade == "mems":  # the turn-on bias (5 deg/h) is learnt: sigma 0.8 / 0.9 / 1.7 deg/h
        assert res.sigma[-1, 12:15].max() < 0.5 * np.radians(5.0) / 3600.0
    # gyro z scale factor is observable in the figure-eight
    assert abs(res.scale_gyro[2] - sim.scale_gyro[2]) < 3.0 * res.scale_sigma[5]
    assert res.n_gnss_rejected == 0 and res.n_gnss_updates == len(res.gnss_status)


@pytest.mark.parametrize("seed", [0, 1])
def test_consistency_with_white_gnss(frame, flight, seed):
    """Without the (unmodelled) Gauss-Markov GNSS error the position sigma is consistent too."""
    _, imu, g, spec = simulate(flight, "mems", seed, GnssConfig(gm_sigma_horizontal_m=0.0, gm_sigma_up_m=0.0))
    res = run(frame, flight, imu, g, spec)
    dp, _, d_theta = errors(frame, flight, res)
    pos_ratio, att_ratio = rms(dp / res.sigma[:, :3]), rms(d_theta / res.sigma[:, 6:9])
    assert np.all((pos_ratio > 0.5) & (pos_ratio < 2.0)), pos_ratio  # achieved 0.66-1.16
    assert np.all((att_ratio > 0.3) & (att_ratio < 3.0)), att_ratio
    assert 2.5 < np.nanmean(res.gnss_nis) < 3.5  # chi-square with 3 dof
    assert np.all(rms(dp) < 0.008)  # achieved 1.3-3.6 mm


def test_outage_is_bridged(frame, flight):
    start = flight.passes[0][1] + 10.0
    outage = (start, start + 30.0)
    _, imu, g, spec = simulate(flight, "mems", 0, GnssConfig(outages=[outage]))
    res = run(frame, flight, imu, g, spec)
    dp, d_rph, _ = errors(frame, flight, res)
    inside = (res.time > outage[0]) & (res.time < outage[1])
    err = np.linalg.norm(dp[inside], axis=1)
    assert err.max() < 0.3  # smoothed across the gap: achieved 4-7 cm (mems and tactical)
    sig_h = res.sigma[:, 0]
    assert sig_h[inside].max() > 3.0 * np.median(sig_h[~inside])  # 3.6 cm vs 3 mm
    # errors within a few sigma, plus the unmodelled Gauss-Markov GNSS error
    assert np.all(np.abs(dp[inside]) < 4.0 * res.sigma[inside, :3] + 0.05)
    assert np.abs(d_rph[inside, 2]).max() * MDEG < 100.0


def test_multipath_jumps_are_rejected(frame, flight):
    _, imu, g, spec = simulate(flight, "mems", 1)
    t, p_w, cov_w = gnss_w(frame, g)
    rng = np.random.default_rng(5)
    jumps = np.searchsorted(t, [5.0, 40.0, 77.3, 120.0, 150.0, 151.0, 151.2, 180.0])
    direction = rng.normal(size=(len(jumps), 3))
    p_bad = p_w.copy()
    p_bad[jumps] += direction / np.linalg.norm(direction, axis=1, keepdims=True)  # 1 m
    res = run_filter(frame, flight.t0_gps, imu, t, p_bad, cov_w, P_B_A, spec, FilterConfig())
    assert set(np.flatnonzero(res.gnss_status == 0)) == set(jumps)
    assert res.n_gnss_rejected == len(jumps) and res.n_gnss_updates == len(t) - len(jumps)
    dp, _, _ = errors(frame, flight, res)
    assert np.all(rms(dp) < gnss_bound(g))
    # without the gate the jumps pull the trajectory
    loose = run_filter(frame, flight.t0_gps, imu, t, p_bad, cov_w, P_B_A, spec,
                       FilterConfig(gnss_gate_probability=1.0))
    assert loose.n_gnss_rejected == 0
    assert np.abs(errors(frame, flight, loose)[0]).max() > 1.5 * np.abs(dp).max()


# ---------------------------------------------------------------------------- containers, edges
def test_result_span_alignment_and_sampled(frame, flight, runs):
    _, _, res = runs["mems", 0]
    assert res.levelled
    assert 15.0 < res.alignment_time < phase_end(flight, "takeoff")  # speed > 5 m/s during take-off
    assert res.time[0] <= 0.0 + 1e-6 and res.time[-1] >= flight.duration_s - 0.2
    assert np.all(np.isfinite(res.sigma)) and np.all(res.sigma > 0)
    traj = res.to_sampled()
    assert isinstance(traj, Trajectory) and traj.t0_gps == flight.t0_gps
    p, _ = traj.interpolate(np.array([50.0, 100.0]))
    np.testing.assert_allclose(p, flight.pose(np.array([50.0, 100.0]))[0], atol=0.1)
    with pytest.raises(ValidationError):
        FilterConfig(gate_probability=0.99)
    with pytest.raises(ValidationError):
        FilterConfig(alignment_speed_mps=-1.0)


def test_start_in_a_banked_turn(frame, flight):
    """Data starting in flight (in the manoeuvre, ~20 deg bank): in-motion coarse alignment."""
    sim, imu, g, spec = simulate(flight, "mems", 0)
    sel = sim.time >= 40.0
    imu_air = ImuData(imu.time_gps[sel], imu.gyro[sel], imu.acc[sel], imu.rate_hz)
    t, p_w, cov_w = gnss_w(frame, g)
    keep = t > 40.0
    res = run_filter(frame, flight.t0_gps, imu_air, t[keep], p_w[keep], cov_w[keep], P_B_A, spec)
    assert not res.levelled and res.alignment_time < 42.0
    assert np.abs(np.degrees(flight.rph(np.array([41.0]))[0, 0])) > 15.0  # really banked
    dp, d_rph, d_theta = errors(frame, flight, res)
    assert res.n_gnss_rejected == 0
    assert np.all(rms(dp) < gnss_bound(g))
    # achieved: roll/pitch 4.5/4.2 mdeg, heading 11 mdeg RMS
    assert np.all(rms(d_rph) * MDEG < [15.0, 15.0, 50.0])
    ratio = rms(d_theta / res.sigma[:, 6:9])
    assert np.all((ratio > 0.3) & (ratio < 3.0)), ratio


def test_increment_input(frame, flight, runs):
    """IMU delivering increments (Gauss-Legendre integrals of the truth + the same errors)."""
    sim, g, res_rates = runs["mems", 0]
    t, dt = sim.time, 1.0 / 200.0
    xg, wg = np.polynomial.legendre.leggauss(5)
    tq = np.clip(t[:, None] - 0.5 * dt + 0.5 * dt * xg[None, :], 0.0, flight.duration_s)
    wq, fq = flight.imu(tq.ravel())
    w_t, f_t = flight.imu(t)
    dtheta = 0.5 * dt * np.einsum("q,nqk->nk", wg, wq.reshape(len(t), 5, 3)) + (sim.gyro - w_t) * dt
    dv = 0.5 * dt * np.einsum("q,nqk->nk", wg, fq.reshape(len(t), 5, 3)) + (sim.acc - f_t) * dt
    imu = ImuData.from_increments(t + flight.t0_gps, dtheta, dv, 200.0)
    spec = ImuErrorSpec(**{k: v for k, v in imu_grade("mems").model_dump().items() if k in ImuErrorSpec.model_fields})
    res = run(frame, flight, imu, g, spec)
    assert np.abs(res.p_w_b - res_rates.p_w_b).max() < 0.005
    assert np.linalg.norm(log_so3(np.swapaxes(res.R_w_b, 1, 2) @ res_rates.R_w_b), axis=1).max() * MDEG < 2.0


def test_ideal_imu_spec_uses_floors(frame, flight):
    _, imu, g, spec = simulate(flight, "ideal", 0)
    res = run(frame, flight, imu, g, spec)
    dp, d_rph, _ = errors(frame, flight, res)
    assert np.all(np.isfinite(res.p_w_b)) and np.all(rms(dp) < gnss_bound(g))
    assert np.all(rms(d_rph) * MDEG < 2.0)  # achieved 0.03-0.45 mdeg


def test_gnss_in_w_and_no_alignment(frame, flight):
    _, imu, g, spec = simulate(flight, "mems", 0)
    t, p_w, cov_w = gnss_w(frame, g)
    cov_enu = np.zeros((len(t), 3, 3))
    cov_enu[:, [0, 1, 2], [0, 1, 2]] = g.sd_neu[:, [1, 0, 2]] ** 2
    quality = np.where(np.arange(len(t)) % 10 == 3, 5, 1)
    sol = GnssSolution.from_geodetic(g.time + flight.t0_gps, g.lat, g.lon, g.h, cov_enu, quality,
                                     g.num_sats)
    t2, p2, c2 = gnss_in_w(frame, flight.t0_gps, sol, min_quality=2)
    keep = quality <= 2
    np.testing.assert_allclose(t2, t[keep], atol=1e-6)
    np.testing.assert_allclose(p2, p_w[keep], atol=1e-6)
    np.testing.assert_allclose(c2, cov_w[keep], atol=1e-12)
    static = t < 9.0  # only the time on the pad: the heading cannot be aligned
    with pytest.raises(InputError, match="alignment"):
        run_filter(frame, flight.t0_gps, imu, t[static], p_w[static], cov_w[static], P_B_A, spec)


def test_speed(frame, flight, runs):
    _, imu, g, spec = simulate(flight, "mems", 0)
    t0 = time.perf_counter()
    res = run(frame, flight, imu, g, spec)
    elapsed = time.perf_counter() - t0
    # ~0.3 s for 190 s at 200 Hz (10 min at 200 Hz: ~1.8 s), JIT compilation excluded
    assert elapsed < 3.0 * len(res.time) / 38_000
