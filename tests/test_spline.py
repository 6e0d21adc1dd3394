"""Continuous-time spline (docs/ARCHITECTURE.md §4.2): interpolation, derivatives, Jacobians, fit."""

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.geometry.rotation import (
    R_n_b_from_rph,
    exp_so3,
    log_so3,
    omega_nb_b_from_rph_rates,
)
from georefine.trajectory.sampled import Trajectory
from georefine.trajectory.spline import (
    KnotGrid,
    SplineTrajectory,
    eval_orientation,
    eval_position,
    position_basis,
)
from georefine.trajectory.spline_fit import fit_spline

SEEDS = [0, 1, 2]


def random_knots(rng, n_knots, rate_scale=0.5, angle_step=0.05):
    """Knot states of a plausible random trajectory (angles in rad, rates in rad/s)."""
    grid = KnotGrid(rng.uniform(-5, 5), rng.uniform(0.05, 0.2), n_knots)
    P = np.cumsum(rng.normal(0, 5, (n_knots, 3)), axis=0)
    V = rng.normal(0, 30, (n_knots, 3))
    A = rng.normal(0, 2, (n_knots, 3))
    R = exp_so3(rng.normal(0, 1, 3)) @ exp_so3(np.cumsum(rng.normal(0, angle_step, (n_knots, 3)), axis=0))
    W = rng.normal(0, rate_scale, (n_knots, 3))
    return grid, P, V, A, R, W


def _times_in_even_intervals(rng, grid, n_times):
    """Times in intervals 0, 2, 4, ... so that each knot is used by one time only as k or k+1."""
    k = 2 * np.arange(n_times)
    u = rng.uniform(0, 1, n_times)
    u[:3] = [0.0, 1e-7, 1.0 - 1e-7]  # at and near both ends (u = 1 is the next interval's 0)
    return grid.t_start + (k + u) * grid.dt


def angle(R_a, R_b):
    return np.linalg.norm(log_so3(np.swapaxes(R_a, -1, -2) @ R_b), axis=-1)


# ------------------------------------------------------------------------------ knot grid


def test_grid_locate_and_span():
    grid = KnotGrid(10.0, 0.1, 11)
    assert grid.t_end == pytest.approx(11.0)
    np.testing.assert_allclose(grid.knot_times, 10.0 + 0.1 * np.arange(11))
    k, u = grid.locate(np.array([10.0, 10.05, 10.1, 10.999, 11.0]))
    np.testing.assert_array_equal(k, [0, 0, 1, 9, 9])  # the last interval is closed on the right
    np.testing.assert_allclose(u, [0.0, 0.5, 0.0, 0.99, 1.0], atol=1e-9)
    for bad in ([9.999], [11.001], [10.5, np.nan]):
        with pytest.raises(InputError, match="outside the spline span"):
            grid.locate(np.array(bad))
    with pytest.raises(ValueError):  # InputError is a ValueError
        grid.locate(12.0)


@pytest.mark.parametrize("seed", SEEDS)
def test_grid_covering(seed):
    rng = np.random.default_rng(seed)
    t_first = rng.uniform(-100, 100)
    dt = rng.uniform(0.01, 0.5)
    for span in (dt * rng.integers(1, 1000), rng.uniform(0.01, 100.0)):
        grid = KnotGrid.covering(t_first, t_first + span, dt)
        assert grid.t_start == t_first and grid.t_end >= t_first + span - 1e-9
        assert grid.t_end - dt < t_first + span  # shortest such grid
        grid.locate(np.array([t_first, t_first + span]))  # both ends evaluable


@pytest.mark.parametrize("seed", SEEDS)
def test_grid_spanning(seed):
    rng = np.random.default_rng(seed)
    t_first, span = rng.uniform(-100, 100), rng.uniform(1.0, 100.0)
    for dt in (0.1, 0.25, rng.uniform(0.01, 0.5), 2 * span):
        grid = KnotGrid.spanning(t_first, t_first + span, dt)
        assert grid.t_start == t_first and grid.t_end == pytest.approx(t_first + span, abs=1e-9)
        assert abs(grid.dt - dt) <= 0.5 * grid.dt ** 2 / span * 1.000001 or grid.n_knots == 2  # nearest whole number
    fine = KnotGrid(t_first, 0.1, 361)
    again = KnotGrid.spanning(fine.t_start, fine.t_end, 0.1)  # a grid spans its own span with its own knots
    assert again.n_knots == fine.n_knots
    np.testing.assert_allclose(again.knot_times, fine.knot_times, rtol=0, atol=1e-9)
    with pytest.raises(ValueError):
        KnotGrid.spanning(1.0, 1.0, 0.1)
    with pytest.raises(ValueError):
        KnotGrid.spanning(0.0, 1.0, 0.0)


@pytest.mark.parametrize("seed", SEEDS)
def test_resampled_keeps_the_curve_at_the_new_knots(seed):
    rng = np.random.default_rng(seed)
    grid, P, V, A, R, W = random_knots(rng, 40)
    spline = SplineTrajectory(grid, P, V, A, R, W, t0_gps=1.4e9)
    for dt in (grid.dt / 3.0, 2.5 * grid.dt):
        other = KnotGrid.spanning(grid.t_start, grid.t_end, dt)
        moved = spline.resampled(other)
        assert moved.grid == other and moved.t0_gps == spline.t0_gps
        t = other.knot_times
        np.testing.assert_allclose(moved.p_w_b, spline.position(t), rtol=0, atol=1e-9)
        np.testing.assert_allclose(moved.v_w_b, spline.velocity(t), rtol=0, atol=1e-9)
        np.testing.assert_allclose(moved.a_w_b, spline.acceleration(t), rtol=0, atol=1e-9)
        assert angle(moved.R_w_b, spline.orientation(t).R_w_b).max() < 1e-12
        np.testing.assert_allclose(moved.omega_wb_b, spline.body_rate(t), rtol=0, atol=1e-9)
    # on a grid three times finer the states at the old knots are the old ones
    finer = spline.resampled(KnotGrid.spanning(grid.t_start, grid.t_end, grid.dt / 3.0))
    np.testing.assert_allclose(finer.p_w_b[::3], P, rtol=0, atol=1e-8)
    assert angle(finer.R_w_b[::3], R).max() < 1e-10
    with pytest.raises(InputError):
        spline.resampled(KnotGrid(grid.t_start, grid.dt, grid.n_knots + 1))


def test_grid_rejects_bad_parameters():
    for args in [(0.0, 0.0, 5), (0.0, -0.1, 5), (0.0, 0.1, 1), (0.0, 0.1, 2.5), (np.nan, 0.1, 5)]:
        with pytest.raises(ValueError):
            KnotGrid(*args)


# ------------------------------------------------------------------------------- position


@pytest.mark.parametrize("seed", SEEDS)
def test_position_interpolates_knot_states(seed):
    rng = np.random.default_rng(seed)
    grid, P, V, A, _, _ = random_knots(rng, 8)
    t = grid.knot_times
    for order, X in enumerate((P, V, A)):
        np.testing.assert_allclose(eval_position(grid, P, V, A, t, order), X, atol=1e-9, rtol=1e-12)
        # C²: at u = 1 (left limit at knot k+1) and u = 0 the basis selects that knot's state,
        # so both sides of every knot agree.
        w = position_basis(np.array([0.0, 1.0]), grid.dt, order)
        np.testing.assert_allclose(w, np.eye(6)[[order, 3 + order]], atol=1e-12 / grid.dt**order)


@pytest.mark.parametrize("seed", SEEDS)
def test_position_derivatives_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    grid, P, V, A, _, _ = random_knots(rng, 8)
    h = 1e-5
    t = rng.uniform(grid.t_start + h, grid.t_end - h, 200)
    for order in (1, 2):
        fd = (eval_position(grid, P, V, A, t + h, order - 1) - eval_position(grid, P, V, A, t - h, order - 1)) / (2 * h)
        scale = np.abs(fd).max()
        np.testing.assert_allclose(eval_position(grid, P, V, A, t, order), fd, atol=1e-6 * scale)


@pytest.mark.parametrize("seed", SEEDS)
def test_position_basis_is_the_jacobian(seed):
    rng = np.random.default_rng(seed)
    n_times = 10
    grid, P, V, A, _, _ = random_knots(rng, 2 * n_times + 1)
    t = _times_in_even_intervals(rng, grid, n_times)
    k, u = grid.locate(t)
    h = 1e-3
    for order in (0, 1, 2):
        w = position_basis(u, grid.dt, order)
        assert w.shape == (n_times, 6)
        for j in range(6):
            which, knots = j % 3, k + j // 3  # state p, v or a of knot k or k+1
            for axis in range(3):
                plus, minus = [X.copy() for X in (P, V, A)], [X.copy() for X in (P, V, A)]
                plus[which][knots, axis] += h
                minus[which][knots, axis] -= h
                fd = (eval_position(grid, *plus, t, order) - eval_position(grid, *minus, t, order)) / (2 * h)
                expected = np.zeros((n_times, 3))
                expected[:, axis] = w[:, j]
                np.testing.assert_allclose(fd, expected, atol=1e-9 * max(1.0, np.abs(w[:, j]).max()))


def test_position_reproduces_quintic_polynomials():
    # A quintic in t is in the spline space: knot states from the polynomial reproduce it.
    rng = np.random.default_rng(7)
    c = rng.normal(size=(6, 3))
    poly = np.polynomial.polynomial
    grid = KnotGrid(0.0, 0.25, 9)
    tk = grid.knot_times
    P, V, A = (poly.polyval(tk, poly.polyder(c, m)).T for m in range(3))
    t = rng.uniform(0, grid.t_end, 100)
    for order in range(3):
        expected = poly.polyval(t, poly.polyder(c, order)).T
        np.testing.assert_allclose(eval_position(grid, P, V, A, t, order), expected, rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------------------- orientation

SCENARIOS = {
    "moderate": dict(rate_scale=0.3, angle_step=0.05),
    "large_rates": dict(rate_scale=1.0, angle_step=0.2),
    "near_zero_rates": dict(rate_scale=1e-9, angle_step=1e-9),
    "zero": dict(rate_scale=0.0, angle_step=0.0),
}


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_orientation_interpolates_knot_states(seed, scenario):
    rng = np.random.default_rng(seed)
    grid, _, _, _, R, W = random_knots(rng, 7, **SCENARIOS[scenario])
    R_t, omega_t, jac = eval_orientation(grid, R, W, grid.knot_times)
    assert jac is None
    assert angle(R_t, R).max() < 1e-12
    np.testing.assert_allclose(omega_t, W, atol=1e-12)
    np.testing.assert_allclose(R_t @ np.swapaxes(R_t, 1, 2), np.broadcast_to(np.eye(3), R_t.shape), atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_orientation_constant_rate_is_exact(seed):
    # A constant body rate is a one-parameter subgroup: R(t) = R_0 Exp(omega (t - t_0)).
    rng = np.random.default_rng(seed)
    omega = rng.normal(0, 0.7, 3)
    grid = KnotGrid(0.0, 0.1, 12)
    R0 = exp_so3(rng.normal(size=3))
    R = R0 @ exp_so3(grid.knot_times[:, None] * omega)
    t = rng.uniform(0, grid.t_end, 100)
    R_t, omega_t, _ = eval_orientation(grid, R, np.tile(omega, (12, 1)), t)
    assert angle(R_t, R0 @ exp_so3(t[:, None] * omega)).max() < 1e-12
    np.testing.assert_allclose(omega_t, np.broadcast_to(omega, t.shape + (3,)), atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_body_rate_matches_finite_differences(seed, scenario):
    rng = np.random.default_rng(seed)
    grid, _, _, _, R, W = random_knots(rng, 7, **SCENARIOS[scenario])
    h = 1e-6
    t = np.concatenate([rng.uniform(grid.t_start + h, grid.t_end - h, 100), grid.knot_times[1:-1] + 2 * h])
    R_plus = eval_orientation(grid, R, W, t + h, rate=False).R_w_b
    R_minus = eval_orientation(grid, R, W, t - h, rate=False).R_w_b
    fd = log_so3(np.swapaxes(R_minus, 1, 2) @ R_plus) / (2 * h)
    np.testing.assert_allclose(eval_orientation(grid, R, W, t).omega_wb_b, fd, atol=1e-8)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_orientation_jacobians_match_manifold_finite_differences(seed, scenario):
    rng = np.random.default_rng(seed)
    n_times = 12
    grid, _, _, _, R, W = random_knots(rng, 2 * n_times + 1, **SCENARIOS[scenario])
    t = _times_in_even_intervals(rng, grid, n_times)
    R_t, omega_t, jac = eval_orientation(grid, R, W, t, jacobians=True)
    assert jac.dR.shape == jac.domega.shape == (n_times, 3, 12)
    np.testing.assert_array_equal(jac.k, 2 * np.arange(n_times))
    h = 1e-6
    blocks = {
        "dtheta_k": (0, "R"), "domega_k": (0, "W"), "dtheta_k1": (1, "R"), "domega_k1": (1, "W"),
    }
    for name, (offset, kind) in blocks.items():
        knots = jac.k + offset
        fd_R = np.zeros((n_times, 3, 3))
        fd_w = np.zeros((n_times, 3, 3))
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            evals = []
            for sign in (1.0, -1.0):
                R2, W2 = R.copy(), W.copy()
                if kind == "R":
                    R2[knots] = R2[knots] @ exp_so3(sign * e)  # through the retraction
                else:
                    W2[knots] += sign * e
                evals.append(eval_orientation(grid, R2, W2, t))
            fd_R[:, :, i] = log_so3(np.swapaxes(evals[1].R_w_b, 1, 2) @ evals[0].R_w_b) / (2 * h)
            fd_w[:, :, i] = (evals[0].omega_wb_b - evals[1].omega_wb_b) / (2 * h)
        np.testing.assert_allclose(getattr(jac, "dR_" + name), fd_R, atol=2e-8, err_msg=f"dR_{name}")
        np.testing.assert_allclose(getattr(jac, "domega_" + name), fd_w, atol=2e-7, err_msg=f"domega_{name}")


@pytest.mark.parametrize("seed", SEEDS)
def test_vectorised_paths_agree(seed):
    # Many times (per-interval terms) and few times (per-time terms) agree.
    rng = np.random.default_rng(seed)
    grid, _, _, _, R, W = random_knots(rng, 40, rate_scale=1.0, angle_step=0.2)
    t = np.sort(rng.uniform(grid.t_start, grid.t_end, 20000))
    many = eval_orientation(grid, R, W, t, jacobians=True)
    sel = rng.choice(t.size, 10, replace=False)
    few = eval_orientation(grid, R, W, t[sel], jacobians=True)
    np.testing.assert_allclose(many.R_w_b[sel], few.R_w_b, atol=1e-14)
    np.testing.assert_allclose(many.omega_wb_b[sel], few.omega_wb_b, atol=1e-13)
    np.testing.assert_allclose(many.jacobians.dR[sel], few.jacobians.dR, atol=1e-13)
    np.testing.assert_allclose(many.jacobians.domega[sel], few.jacobians.domega, atol=1e-12)
    no_rate = eval_orientation(grid, R, W, t, rate=False, jacobians=True)
    assert no_rate.omega_wb_b is None and no_rate.jacobians.domega is None
    np.testing.assert_array_equal(no_rate.jacobians.dR, many.jacobians.dR)


@pytest.mark.parametrize("seed", SEEDS)
def test_orientation_continued_beyond_the_interval_stays_a_rotation(seed):
    """A normalised time a little outside [0, 1] (``locate_near``) makes some beta_i negative: the
    sin/cos factors are even functions and must take their closed forms for |beta theta| >= 0.01
    either side of zero (the series there once left R 7e-6 from orthonormal); the rate still matches
    finite differences of the continued polynomial."""
    rng = np.random.default_rng(seed)
    grid, _, _, _, R, W = random_knots(rng, 12, rate_scale=1.0, angle_step=0.2)
    k = rng.integers(1, grid.n_intervals - 1, 200)
    u = rng.uniform(-0.5, 1.5, 200)
    t = grid.t_start + (k + u) * grid.dt
    ev = eval_orientation(grid, R, W, t, located=(k, u))
    np.testing.assert_allclose(ev.R_w_b @ np.swapaxes(ev.R_w_b, 1, 2), np.broadcast_to(np.eye(3), ev.R_w_b.shape),
                               atol=1e-13)
    h = 1e-6
    plus = eval_orientation(grid, R, W, t + h, rate=False, located=(k, u + h / grid.dt)).R_w_b
    minus = eval_orientation(grid, R, W, t - h, rate=False, located=(k, u - h / grid.dt)).R_w_b
    np.testing.assert_allclose(ev.omega_wb_b, log_so3(np.swapaxes(minus, 1, 2) @ plus) / (2 * h), atol=1e-7)


# ------------------------------------------------------------------------------ container


@pytest.mark.parametrize("seed", SEEDS)
def test_spline_trajectory_methods(seed):
    rng = np.random.default_rng(seed)
    grid, P, V, A, R, W = random_knots(rng, 10)
    spline = SplineTrajectory(grid, P, V, A, R, W, t0_gps=1.4e9)
    t = np.sort(rng.uniform(grid.t_start, grid.t_end, 30))
    p, R_t = spline.pose(t)
    np.testing.assert_array_equal(p, eval_position(grid, P, V, A, t))
    np.testing.assert_array_equal(R_t, eval_orientation(grid, R, W, t).R_w_b)
    np.testing.assert_array_equal(spline.velocity(t), eval_position(grid, P, V, A, t, 1))
    np.testing.assert_array_equal(spline.acceleration(t), eval_position(grid, P, V, A, t, 2))
    np.testing.assert_array_equal(spline.body_rate(t), eval_orientation(grid, R, W, t).omega_wb_b)
    sampled = spline.to_sampled(t)
    assert isinstance(sampled, Trajectory) and sampled.t0_gps == 1.4e9
    np.testing.assert_array_equal(sampled.v_w_b, spline.velocity(t))
    with pytest.raises(InputError):
        spline.pose(np.array([grid.t_end + 0.01]))
    with pytest.raises(ValueError, match="knot array"):
        SplineTrajectory(grid, P[:-1], V, A, R, W)


# ------------------------------------------------------------------------------------ fit


def aircraft_motion(rng, t):
    """Smooth analytic flight: position, velocity (m, m/s), attitude and body rate."""
    a = rng.uniform(5, 20, 3)
    f = rng.uniform(0.1, 0.5, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    speed = rng.uniform(30, 70)
    arg = f[:2] * t[:, None] + ph[:2]
    p = np.column_stack([speed * t, a[0] * np.sin(arg[:, 0]), 300 + a[1] * np.sin(arg[:, 1])])
    v = np.column_stack([np.full_like(t, speed), a[0] * f[0] * np.cos(arg[:, 0]), a[1] * f[1] * np.cos(arg[:, 1])])
    amp = np.array([rng.uniform(0.05, 0.3), rng.uniform(0.02, 0.1), rng.uniform(0.05, 0.5)])
    g = rng.uniform(0.2, 0.8, 3)
    rph = amp * np.sin(g * t[:, None] + ph) + np.array([0.0, 0.0, rng.uniform(0, 2 * np.pi)])
    rph_dot = amp * g * np.cos(g * t[:, None] + ph)
    return p, v, R_n_b_from_rph(*rph.T), omega_nb_b_from_rph_rates(rph, rph_dot)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("with_rates", [False, True])
def test_fit_recovers_smooth_motion(seed, with_rates):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 20.0, 0.005)  # 200 Hz
    state = rng.bit_generator.state
    p, v, R, omega = aircraft_motion(rng, t)
    grid = KnotGrid.covering(t[0], t[-1], 0.1)
    spline = fit_spline(grid, t, p, R, v if with_rates else None, omega if with_rates else None)
    t_mid = t[:-1] + rng.uniform(0.0, 0.005, t.size - 1)  # between the samples
    rng.bit_generator.state = state
    p_true, v_true, R_true, omega_true = aircraft_motion(rng, t_mid)
    p_fit, R_fit = spline.pose(t_mid)
    assert np.abs(p_fit - p_true).max() < 1e-4
    assert angle(R_fit, R_true).max() < 1e-6
    # Derivatives are recovered too (looser: the ends are only constrained from one side).
    assert np.abs(spline.velocity(t_mid) - v_true).max() < 1e-2
    assert np.abs(spline.body_rate(t_mid) - omega_true).max() < 1e-4


def test_fit_bridges_a_data_gap():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 10.0, 0.005)
    p, _, R, _ = aircraft_motion(rng, t)
    keep = (t < 4.0) | (t > 4.6)  # 0.6 s (6 knot intervals) without samples
    grid = KnotGrid.covering(t[0], t[-1], 0.1)
    spline = fit_spline(grid, t[keep], p[keep], R[keep])
    p_fit, R_fit = spline.pose(t)
    assert np.all(np.isfinite(p_fit)) and np.all(np.isfinite(R_fit))
    assert np.abs(p_fit - p)[keep].max() < 1e-4
    assert np.abs(p_fit - p).max() < 1e-3  # minimum-jerk bridge
    assert angle(R_fit, R)[keep].max() < 1e-6
    # Attitude knots without data keep their start values, the geodesic bridge of the gap.
    _, R_geodesic = Trajectory(t[keep], p[keep], R[keep]).interpolate(t)
    assert angle(R_fit, R).max() < 1.05 * angle(R_geodesic, R).max()


def test_fit_rejects_bad_input():
    t = np.arange(0.0, 2.0, 0.01)
    p, _, R, _ = aircraft_motion(np.random.default_rng(0), t)
    with pytest.raises(InputError):  # samples outside the knot span
        fit_spline(KnotGrid(0.0, 0.1, 10), t, p, R)
    grid = KnotGrid.covering(t[0], t[-1], 0.1)
    with pytest.raises(ValueError, match="strictly increasing"):
        fit_spline(grid, t[::-1], p, R)
    with pytest.raises(ValueError, match="R_w_b"):
        fit_spline(grid, t, p, R[:-1])
