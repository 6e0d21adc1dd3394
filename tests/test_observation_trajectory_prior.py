"""The delivered-trajectory prior: Jacobians against manifold finite differences, the Gauss-Markov rows."""

import numpy as np
import pytest

from georefine.adjustment.observations.bias import BiasGrid
from georefine.adjustment.observations.trajectory_prior import GaussMarkovPrior, TrajectoryPoseObservation
from georefine.adjustment.testing import check_jacobians
from georefine.geometry.rotation import exp_so3, log_so3
from georefine.trajectory.spline import KnotGrid, SplineTrajectory
from test_observations_gi import TRAJ_BLOCKS, random_knots

SEEDS = [0, 1, 2]


@pytest.mark.parametrize("seed", SEEDS)
def test_pose_observation_jacobians(seed):
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    t = np.sort(rng.uniform(0, grid.t_end, 30))
    p_ref = rng.normal(0, 1, (30, 3)) + [100, 50, 160]
    R_ref = exp_so3(rng.normal(0, 0.3, (30, 3)) + [0, 0, 1.2])
    egrid = BiasGrid.covering(0.0, grid.t_end, 0.4)
    values["sbet_position_error"] = rng.normal(0, 0.05, (egrid.n_knots, 3))
    values["sbet_attitude_error"] = rng.normal(0, 0.01, (egrid.n_knots, 3))
    group = TrajectoryPoseObservation(grid, t, p_ref, R_ref, 0.01, 1e-3, egrid)
    kinds = dict(TRAJ_BLOCKS, sbet_position_error="euclidean", sbet_attitude_error="euclidean")
    chk = check_jacobians(group, values, kinds, eps=1e-4)
    assert chk.max_rel_error < 1e-5, chk


def test_pose_observation_is_zero_on_the_reference_plus_error():
    """The spline, moved by the error at the sample times, fits the reference exactly."""
    rng = np.random.default_rng(4)
    K = 20
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    spline = SplineTrajectory(grid, *(values[k] for k in TRAJ_BLOCKS))
    t = np.linspace(0.0, grid.t_end, 57)
    p, R = spline.pose(t)
    egrid = BiasGrid.covering(0.0, grid.t_end, 0.5)
    e_p = rng.normal(0, 0.1, (egrid.n_knots, 3))
    e_t = rng.normal(0, 0.01, (egrid.n_knots, 3))
    # reference = spline minus the error: p_ref = p - e_p(t), R_ref = Exp(-e_t(t)) R
    group = TrajectoryPoseObservation(grid, t, p - egrid.evaluate(e_p, t), exp_so3(-egrid.evaluate(e_t, t)) @ R,
                                      0.01, 1e-3, egrid)
    values.update(sbet_position_error=e_p, sbet_attitude_error=e_t)
    np.testing.assert_allclose(group.residuals_unweighted(values), 0.0, atol=1e-9)
    # A heading error is a rotation about the up axis of w: the third component.
    R_ref = exp_so3(np.array([0.0, 0.0, -0.02]))[None] @ R
    g = TrajectoryPoseObservation(grid, t, p, R_ref, 0.01, 1e-3, egrid)
    values.update(sbet_position_error=np.zeros_like(e_p), sbet_attitude_error=np.zeros_like(e_t))
    np.testing.assert_allclose(g.residuals_unweighted(values)[:, 3:], np.tile([0, 0, 0.02], (t.size, 1)), atol=1e-12)
    assert np.allclose(log_so3(R @ np.swapaxes(R_ref, 1, 2)), [0, 0, 0.02])


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("tau", [30.0, (30.0, 30.0, 300.0)])
def test_gauss_markov_prior(seed, tau):
    rng = np.random.default_rng(seed)
    egrid = BiasGrid.covering(0.0, 60.0, 2.0)
    sigma = rng.uniform(0.01, 0.03, (egrid.n_knots, 3))
    group = GaussMarkovPrior("gm", "e", egrid, sigma, tau_s=tau)
    e = rng.normal(0, 0.02, (egrid.n_knots, 3))
    chk = check_jacobians(group, {"e": e}, {"e": "euclidean"}, eps=1e-6)
    assert chk.max_rel_error < 1e-7, chk
    lin = group.linearize({"e": e}, jacobians=False)
    phi = np.exp(-2.0 / np.asarray(tau))
    np.testing.assert_allclose(lin.residuals[:3], e[0] / sigma[0])
    np.testing.assert_allclose(lin.residuals[3:6], (e[1] - phi * e[0]) / (sigma[1] * np.sqrt(1 - phi**2)))


def test_gauss_markov_prior_samples_have_the_stated_statistics():
    """Samples drawn from the process whitened by the prior are standard normal (its information is right)."""
    rng = np.random.default_rng(7)
    egrid = BiasGrid.covering(0.0, 400.0, 1.0)
    tau, s = 50.0, 0.02
    phi = np.exp(-1.0 / tau)
    n = egrid.n_knots
    e = np.zeros((n, 3))
    e[0] = rng.normal(0, s, 3)
    for j in range(1, n):
        e[j] = phi * e[j - 1] + rng.normal(0, s * np.sqrt(1 - phi**2), 3)
    r = GaussMarkovPrior("gm", "e", egrid, s, tau).linearize({"e": e}, jacobians=False).residuals
    assert abs(np.std(r) - 1.0) < 0.05
    assert abs(np.corrcoef(r[3:-3:3], r[6::3])[0, 1]) < 0.1  # whitened: no correlation left
