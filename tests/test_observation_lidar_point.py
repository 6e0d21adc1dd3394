"""LiDAR returns observing tie points through the trajectory (docs/ARCHITECTURE.md §4.3): Jacobians,
weights, and a mounting calibration solved from returns and control points."""

import numpy as np
import pytest

from georefine.adjustment.observations.lidar_point import LidarPointObservation, beam_whitening
from georefine.adjustment.problem import Problem
from georefine.adjustment.solver import SolverOptions
from georefine.adjustment.testing import check_jacobians
from georefine.geometry.rotation import exp_so3, log_so3
from georefine.trajectory.spline import KnotGrid, eval_orientation, eval_position
from test_observation_plane import DURATION_S, RADIUS_M, TRAJ_BLOCKS, B, random_knots, true_trajectory

SEEDS = [0, 1, 2]
MDEG = np.radians(1e-3)
R_B_S = exp_so3(np.array([0.01, -0.02, np.pi / 2]))
P_B_S = np.array([0.3, -0.1, 0.5])


def _unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def random_group(rng, grid, n=30, m=8, **calibration):
    x_s = _unit(rng.normal(size=(n, 3))) * rng.uniform(30, 150, (n, 1))
    return LidarPointObservation(
        grid, np.sort(rng.uniform(0.05, grid.t_end - 0.05, n)), x_s, rng.integers(0, m, n),
        beam_w=_unit(rng.normal(size=(n, 3))), sigma_range=rng.uniform(0.005, 0.02, n),
        sigma_across=rng.uniform(0.01, 0.05, n), p_b_s=P_B_S, R_b_s=R_B_S, offset_w=rng.normal(0.0, 0.1, (n, 3)),
        **calibration)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("calibration", [False, True])
def test_lidar_point_jacobians(seed, calibration):
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    extra = {"boresight": "R_b_s", "lever_arm": "p_b_s", "time_offset": "tau"} if calibration else {}
    group = random_group(rng, grid, **extra)
    values["points"] = rng.uniform(0, 200, (8, 3))
    blocks = dict(TRAJ_BLOCKS, points="euclidean")
    if calibration:
        values |= {"R_b_s": (R_B_S @ exp_so3(rng.normal(0, 0.01, 3)))[None],
                   "p_b_s": (P_B_S + rng.normal(0, 0.05, 3))[None], "tau": np.array([[rng.uniform(-0.02, 0.02)]])}
        blocks |= {"R_b_s": "so3", "p_b_s": "euclidean"}
        # The time moves returns at 18 m/s and turns their ~150 m vectors: a small step.
        chk = check_jacobians(group, values, {"tau": "euclidean"}, eps=1e-6)
        assert chk.max_rel_error < 1e-6, chk
    # Linear in the position states, the lever arm and the points: a large step; rotations act
    # on lever arms of ~150 m: a small one.
    linear = {B.position, B.velocity, B.acceleration, "p_b_s", "points"}
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k in linear}, eps=1e-3)
    assert chk.residual_mismatch == 0.0
    assert chk.max_rel_error < 1e-6, chk
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k not in linear}, eps=1e-5)
    assert chk.max_rel_error < 1e-6, chk


def test_the_offset_moves_the_observed_point_and_nothing_else():
    rng = np.random.default_rng(4)
    grid = KnotGrid(0.0, 0.1, 12)
    values = random_knots(rng, 12) | {"points": rng.uniform(0, 200, (8, 3))}
    with_offset = random_group(np.random.default_rng(5), grid)
    without = random_group(np.random.default_rng(5), grid)
    without.offset_w = np.zeros_like(with_offset.offset_w)
    np.testing.assert_allclose(with_offset.georeference(values) - without.georeference(values), with_offset.offset_w,
                               atol=1e-9)
    a, b = with_offset.linearize(values), without.linearize(values)
    for ja, jb in zip(a.jacobians, b.jacobians):
        np.testing.assert_array_equal(ja.values, jb.values)


def test_whitening_is_the_inverse_square_root_of_the_beam_covariance():
    rng = np.random.default_rng(3)
    u = _unit(rng.normal(size=(20, 3)))
    s_r, s_a = rng.uniform(0.005, 0.02, 20), rng.uniform(0.01, 0.05, 20)
    L = beam_whitening(u, s_r, s_a)
    cov = s_a[:, None, None] ** 2 * np.eye(3) + (s_r**2 - s_a**2)[:, None, None] * u[:, :, None] * u[:, None, :]
    np.testing.assert_allclose(np.swapaxes(L, 1, 2) @ L @ cov, np.broadcast_to(np.eye(3), cov.shape), atol=1e-12)
    # Along the beam the range sigma, across it the other.
    np.testing.assert_allclose(np.linalg.norm(np.einsum("nij,nj->ni", L, u), axis=1), 1 / s_r)


def test_validation():
    grid = KnotGrid(0.0, 0.1, 12)
    rng = np.random.default_rng(0)
    ok = dict(time=[0.5], x_s=[[0, 0, 100.0]], point_index=[0], beam_w=[[0, 0, 1.0]], sigma_range=0.01,
              sigma_across=0.02, p_b_s=P_B_S, R_b_s=R_B_S)
    LidarPointObservation(grid, **ok)
    for change, message in [({"time": [5.0]}, "leave the trajectory's span"),
                            ({"beam_w": [[0, 0, 2.0]]}, "unit vectors"),
                            ({"sigma_range": 0.0}, "must be positive"),
                            ({"point_index": [-1]}, "non-negative integers"),
                            ({"x_s": [[0, np.nan, 1.0]]}, "NaN"),
                            ({"offset_w": [[0.0, 0.1]]}, "offset_w must have shape"),
                            ({"R_b_s": np.diag([1.0, 1.0, -1.0])}, "not a rotation")]:
        with pytest.raises(ValueError, match=message):
            LidarPointObservation(grid, **(ok | change))
    group = LidarPointObservation(grid, **(ok | {"point_index": [3]}))
    values = random_knots(rng, 12) | {"points": np.zeros((2, 3))}
    with pytest.raises(ValueError, match="does not hold the points"):
        group.linearize(values)


# ------------------------------------------------------------------- end to end (simulated)


def simulate(rng, n_points=60, per_point=4, sigma_range=0.01, sigma_across=0.02):
    """Ground tie points around the U-turn of tests/test_observation_plane.py, each hit by
    ``per_point`` returns at random times, written into ``s`` with the true trajectory and
    calibration; each return's position in ``w`` is off by a draw of its beam covariance."""
    grid, traj = true_trajectory()
    th, off = rng.uniform(0, np.pi, n_points), rng.uniform(-45, 50, n_points)
    X = np.column_stack([(RADIUS_M + off) * np.sin(th), RADIUS_M - (RADIUS_M + off) * np.cos(th),
                         rng.uniform(-1, 12, n_points)])
    N = n_points * per_point
    idx = np.repeat(np.arange(n_points), per_point)
    time = rng.uniform(0.1, DURATION_S - 0.1, N)
    P, V, A, R, W = B.knots(traj)
    R_w_b = eval_orientation(grid, R, W, time, rate=False).R_w_b
    origin = eval_position(grid, P, V, A, time) + R_w_b @ P_B_S
    beam = _unit(X[idx] - origin)
    s_r, s_a = sigma_range * rng.uniform(0.5, 1.5, N), sigma_across * rng.uniform(0.5, 1.5, N)
    L = beam_whitening(beam, s_r, s_a)
    seen = X[idx] + np.linalg.solve(L, rng.standard_normal((N, 3))[:, :, None])[:, :, 0]
    x_s = np.einsum("ji,nj->ni", R_B_S, np.einsum("nji,nj->ni", R_w_b, seen - origin))
    return {"grid": grid, "traj": traj, "time": time, "x_s": x_s, "point_index": idx, "beam_w": beam,
            "sigma_range": s_r, "sigma_across": s_a, "X": X}


@pytest.mark.parametrize("seed", SEEDS)
def test_recovers_boresight_and_lever_arm_from_returns_and_control_points(seed):
    """Trajectory held at the truth, a fifth of the tie points are control (held), the rest free;
    boresight off by 0.05 deg per axis and lever arm by 5 cm: both come back within their posterior
    covariance, and the free points within theirs."""
    rng = np.random.default_rng(seed)
    sim = simulate(rng)
    group = LidarPointObservation(**{k: sim[k] for k in ("grid", "time", "x_s", "point_index", "beam_w",
                                                         "sigma_range", "sigma_across")},
                                  p_b_s=P_B_S, R_b_s=R_B_S, boresight="R_b_s", lever_arm="p_b_s")
    M = sim["X"].shape[0]
    control = np.zeros(M, dtype=bool)
    control[rng.choice(M, M // 5, replace=False)] = True
    problem = Problem()
    for name, v in sim["traj"].items():
        problem.add_block(name, v, "so3" if name == B.attitude else "euclidean", constant=True)
    start = np.where(control[:, None], sim["X"], sim["X"] + rng.normal(0, 0.5, (M, 3)))
    problem.add_block("points", start, constant=control)
    problem.add_block("R_b_s", (R_B_S @ exp_so3(np.radians(0.05) * rng.choice([-1.0, 1.0], 3)))[None], "so3")
    problem.add_block("p_b_s", (P_B_S + 0.05 * rng.choice([-1.0, 1.0], 3))[None])
    problem.add_group(group)
    result = problem.solve(SolverOptions(max_iterations=50))
    assert result.converged, result.summary()
    # Redundancy 240 x 3 - 48 x 3 - 6 = 570: sigma0^2 within 4.5 of its sd 0.06 of 1.
    assert 0.75 < result.variance_factor < 1.25, result.variance_factor
    bs_err = log_so3(R_B_S.T @ problem.values("R_b_s")[0])
    la_err = problem.values("p_b_s")[0] - P_B_S
    # Observed over seeds 0-9: |boresight error| 0.6-4.5 mdeg, lever arm 0.8-4.9 mm, sigma0^2
    # 0.92-1.09, the points' normalised error squared 0.72-1.21 per axis.
    assert np.linalg.norm(bs_err) < 8 * MDEG and np.linalg.norm(la_err) < 0.01, (bs_err, la_err)
    # Errors against the posterior covariance: chi2 with 3 dof below p = 0.001 (16.27) each.
    for err, cov in ((bs_err, problem.covariance("R_b_s")[0]), (la_err, problem.covariance("p_b_s")[0])):
        assert err @ np.linalg.solve(cov, err) < 16.27
    free = np.flatnonzero(~control)
    pt_err = problem.values("points")[free] - sim["X"][free]
    pt_cov = problem.covariance("points")[free]
    nees = np.einsum("ni,ni->n", pt_err, np.linalg.solve(pt_cov, pt_err[:, :, None])[:, :, 0])
    assert 0.6 < nees.mean() / 3 < 1.5, nees.mean() / 3  # normalised error squared, 48 points
