"""Variance components in the posterior: redundancy per group, one factor per group, honest sigmas."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from georefine.adjustment import linalg
from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.linalg import NotPositiveDefiniteError, available_backends, cholesky
from georefine.adjustment.problem import Problem
from georefine.adjustment.solver import SolverOptions
from georefine.adjustment.variance_components import group_traces, traces_needed, variance_components


class Linear:
    """r = (A x - b) / sigma for element 0 of block ``x``."""

    consumed_redundancy = 0.0

    def __init__(self, name, A, b, sigma):
        self.name, self.A, self.b, self.sigma, self.loss = name, np.asarray(A, float), np.asarray(b, float), sigma, None

    def linearize(self, values, jacobians=True):
        r = (self.A @ values["x"][0] - self.b) / self.sigma
        jac = []
        if jacobians:
            m = r.size
            jac = [JacobianBlock("x", np.arange(m)[:, None], np.zeros(m, int), (self.A / self.sigma)[:, None, :])]
        return Linearization(r, jac, np.arange(r.size))


def test_group_traces_are_the_hat_matrix_traces_exact_or_within_their_stated_deviation():
    rng = np.random.default_rng(3)
    n, counts = 40, [12, 300, 1500]
    J = sp.random(sum(counts), n, density=0.15, random_state=rng, format="csr") + sp.eye(sum(counts), n, format="csr")
    J = sp.csr_matrix(J)
    N = (J.T @ J).toarray()
    Ninv = np.linalg.inv(N)
    factor = cholesky(sp.csr_matrix(N))
    traces, sds = group_traces(J, counts, factor, probes=32, seed=1)
    starts = np.cumsum([0, *counts])
    exact = np.array([np.trace(J[a:b].toarray() @ Ninv @ J[a:b].toarray().T) for a, b in zip(starts[:-1], starts[1:])])
    assert exact.sum() == pytest.approx(n, rel=1e-9)  # sum of the hat matrix's traces = unknowns
    assert traces[0] == pytest.approx(exact[0], rel=1e-9) and sds[0] == 0.0  # 12 rows <= 32 probes: exact
    for g in (1, 2):
        assert 0 < sds[g] <= np.sqrt(2 * exact[g] / 32) * 1.5  # the bound sqrt(2 tr / K), with sampling slack
        assert abs(traces[g] - exact[g]) < 4 * sds[g]
    again, _ = group_traces(J, counts, factor, probes=32, seed=1)
    np.testing.assert_array_equal(traces, again)  # seeded
    with pytest.raises(ValueError, match="row counts"):
        group_traces(J, [12, 300], factor)


def test_small_groups_are_pooled_and_factors_are_floored_at_one():
    comps = variance_components(["imu", "gnss", "prior_a", "prior_b"], [1000, 200, 3, 4], [2500.0, 90.0, 1.0, 20.0],
                                np.array([500.0, 50.0, 1.0, 0.5]), np.zeros(4), 655.5, min_redundancy=30)
    by = {c.groups: c for c in comps}
    assert by[("imu",)].factor == pytest.approx(5.0) and by[("imu",)].scale == pytest.approx(5.0)
    assert by[("gnss",)].factor == pytest.approx(0.6) and by[("gnss",)].scale == 1.0
    pool = by[("prior_a", "prior_b")]  # pooled: redundancy 5.5 < 30
    assert pool.redundancy == pytest.approx(5.5) and pool.scale == pytest.approx(21 / 5.5)
    none = variance_components(["imu", "prior"], [1000, 1], [2500.0, 4.0], np.array([500.0, 0.9]), np.zeros(2), 500.1)
    assert none[1].redundancy == pytest.approx(0.1) and none[1].scale == 1.0  # nothing measures its fit
    # Pools: the named groups one component, the rest another, whose redundancy is the total less the pools'.
    pooled = variance_components(["imu", "gnss", "planes"], [1000, 200, 5000], [2500.0, 90.0, 3000.0],
                                 np.array([np.nan, np.nan, 600.0]), np.array([np.nan, np.nan, 5.0]), 5000.0,
                                 pools=[("planes", "absent")])
    assert [c.groups for c in pooled] == [("planes",), ("imu", "gnss")]
    assert pooled[0].redundancy == pytest.approx(4400) and pooled[0].scale == 1.0  # 0.68 floored
    assert pooled[1].redundancy == pytest.approx(600) and pooled[1].redundancy_sd == pytest.approx(5.0)
    assert pooled[1].scale == pytest.approx(2590 / 600)
    assert traces_needed(["imu", "gnss", "planes"], [1000, 200, 0], [("planes",)]) == [False, False, False]
    with pytest.raises(ValueError, match="more than one component"):
        variance_components(["imu", "gnss"], [10, 10], [1.0, 1.0], np.full(2, np.nan), np.zeros(2), 5.0, pools=[("imu",)])
    assert traces_needed(["imu", "gnss", "planes"], [1000, 200, 0], None) == [True, True, False]


def _two_group_problem(rng, x_true, m, sigma_a_true, sigma_b_true):
    """Group ``a`` sees all three unknowns (sigma 1 assumed), ``b`` only the last two (sigma 1 assumed)."""
    A = rng.normal(size=(m, 3))
    B = np.c_[np.zeros(m), rng.normal(size=(m, 2))]
    problem = Problem()
    problem.add_block("x", np.zeros((1, 3)))
    problem.add_group(Linear("a", A, A @ x_true + sigma_a_true * rng.normal(size=m), 1.0))
    problem.add_group(Linear("b", B, B @ x_true + sigma_b_true * rng.normal(size=m), 1.0))
    problem.add_group(Linear("prior", np.eye(3)[:1], x_true[:1] + 10 * rng.normal(size=1), 10.0))
    return problem, A, B


def test_the_components_weight_the_posterior_group_by_group():
    rng = np.random.default_rng(7)
    x_true = np.array([0.3, -1.0, 2.0])
    problem, A, B = _two_group_problem(rng, x_true, 3000, 3.0, 1.0)
    problem.solve()
    comps = {c.groups: c for c in problem.use_variance_components()}
    assert problem.use_variance_components() == tuple(comps.values())  # the same, asked twice
    assert comps[("a",)].factor == pytest.approx(9.0, rel=0.1)
    assert comps[("b",)].factor == pytest.approx(1.0, rel=0.1)
    assert comps[("prior",)].redundancy_sd == 0.0 and comps[("prior",)].scale == 1.0  # 1 row: exact; fits
    s_a, s_b, s_p = (comps[k].scale for k in (("a",), ("b",), ("prior",)))
    P = np.eye(3)[:1] / 10.0
    expected = np.linalg.inv(A.T @ A / s_a + B.T @ B / s_b + P.T @ P / s_p)
    np.testing.assert_allclose(problem.covariance("x", scale_by_variance_factor=False)[0], expected, rtol=1e-8)
    with pytest.raises(ValueError, match="components scale it already"):
        problem.covariance("x")


def test_a_solve_result_reads_back_from_its_json_form_to_the_same_text(tmp_path):
    """``SolveResult.from_dict`` (the co-adjustment's metrics.json read back) gives what ``to_dict``
    wrote, variance components and non-finite figures (null) included."""
    import json

    from georefine.adjustment.statistics import SolveResult
    from georefine.io.files import write_json

    rng = np.random.default_rng(7)
    problem, _, _ = _two_group_problem(rng, np.array([0.3, -1.0, 2.0]), 300, 3.0, 1.0)
    result = problem.solve()
    result = replace(result, variance_components=problem.use_variance_components())
    write_json(tmp_path / "a.json", result.to_dict())
    d = json.loads((tmp_path / "a.json").read_text())
    back = SolveResult.from_dict(d)
    assert back.to_dict() == d and len(back.variance_components) == 3 and back.groups == result.groups
    write_json(tmp_path / "b.json", back.to_dict())
    assert (tmp_path / "b.json").read_text() == (tmp_path / "a.json").read_text()
    assert back.variance_components == result.variance_components and back.timings == result.timings


def test_the_weighted_posterior_reuses_the_solves_analysis():
    """The component-weighted normal matrix is filled in the solve's pattern: its factorisation
    needs no second symbolic analysis, and gives the dense inverse's blocks. ``x_0`` and ``x_3``
    meet only through the zeros the groups' blocks hold, which SciPy's product had dropped (a
    pattern of its own, analysed again)."""
    rng = np.random.default_rng(8)
    m = 3000
    x_true = np.array([0.3, -1.0, 2.0, 0.5])
    A = np.c_[rng.normal(size=(m, 3)), np.zeros(m)]
    B = np.c_[np.zeros(m), rng.normal(size=(m, 3))]
    problem = Problem()
    problem.add_block("x", np.zeros((1, 4)))
    problem.add_group(Linear("a", A, A @ x_true + 3.0 * rng.normal(size=m), 1.0))
    problem.add_group(Linear("b", B, B @ x_true + 1.0 * rng.normal(size=m), 1.0))
    problem.add_group(Linear("prior", np.eye(4)[:1], x_true[:1] + 10 * rng.normal(size=1), 10.0))
    problem.solve(SolverOptions(linear_solver="qdldl"))
    comps = {c.groups: c for c in problem.use_variance_components()}
    assert comps[("a",)].scale > 2.0 and comps[("b",)].scale == 1.0  # the weighted path
    factorizer = problem._posterior.factorizer
    analyses = factorizer.analyses
    cov = problem.covariance("x", scale_by_variance_factor=False)[0]
    assert factorizer.analyses == analyses
    P = np.eye(4)[:1] / 10.0
    expected = np.linalg.inv(A.T @ A / comps[("a",)].scale + B.T @ B + P.T @ P)
    np.testing.assert_allclose(cov, expected, rtol=1e-8)


def test_pools_take_the_rest_from_the_exact_redundancy():
    rng = np.random.default_rng(9)
    problem, A, B = _two_group_problem(rng, np.array([0.3, -1.0, 2.0]), 2000, 3.0, 1.0)
    result = problem.solve()
    a, rest = problem.use_variance_components([("a",)])
    assert a.groups == ("a",) and rest.groups == ("b", "prior")
    assert a.redundancy + rest.redundancy == pytest.approx(result.redundancy)
    assert a.factor == pytest.approx(9.0, rel=0.1) and rest.factor == pytest.approx(1.0, rel=0.1)
    P = np.eye(3)[:1] / 10.0
    expected = np.linalg.inv(A.T @ A / a.scale + (B.T @ B + P.T @ P) / rest.scale)
    np.testing.assert_allclose(problem.covariance("x", scale_by_variance_factor=False)[0], expected, rtol=1e-8)
    # One pool holding every group: the single factor, floored at 1, with no trace estimated.
    problem2, _, _ = _two_group_problem(rng, np.zeros(3), 200, 3.0, 3.0)
    result2 = problem2.solve()
    (only,) = problem2.use_variance_components([])
    assert only.redundancy == result2.redundancy and only.scale == pytest.approx(result2.variance_factor)
    np.testing.assert_allclose(problem2.covariance("x", scale_by_variance_factor=False),
                               _fresh_covariance(problem2, result2.variance_factor), rtol=1e-10)


def test_redundancy_spent_before_the_adjustment_is_taken_off_its_group():
    """Observations of which a share of the noise was taken out before the adjustment (the IMU
    windows cleaned of a vibration fitted to the same readings) fit better than their sigma by
    the degrees of freedom spent; with ``consumed_redundancy`` counted, the solve's redundancy and
    the group's component take them off and the factor is that of the noise again."""
    rng = np.random.default_rng(12)
    m, spent = 3000, 900
    factors = []
    for counted in (False, True):
        A = rng.normal(size=(m, 3))
        noise = rng.normal(scale=2.0, size=m)
        noise[:spent] = 0.0  # what the cleaning took: these rows' noise
        a = Linear("a", A, A @ np.array([1.0, 2.0, 3.0]) + noise, 2.0)
        if counted:
            a.consumed_redundancy = float(spent)
        B = rng.normal(size=(400, 3))
        b = Linear("b", B, B @ np.array([1.0, 2.0, 3.0]) + rng.normal(scale=0.5, size=400), 0.5)
        problem = Problem()
        problem.add_block("x", np.zeros((1, 3)))
        problem.add_group(a)
        problem.add_group(b)
        result = problem.solve()
        assert result.redundancy == m + 400 - 3 - (spent if counted else 0)
        comp_a = next(c for c in problem.use_variance_components([("a",)]) if c.groups == ("a",))
        factors.append(comp_a.factor)
    assert factors[0] == pytest.approx((m - spent) / m, rel=0.1)  # uncounted: 0.7, the sigma too small
    assert factors[1] == pytest.approx(1.0, rel=0.1)


@pytest.mark.parametrize("backend", available_backends())
def test_where_every_scale_is_one_the_posterior_is_the_unscaled_one(backend, monkeypatch):
    rng = np.random.default_rng(10)
    problem, A, B = _two_group_problem(rng, np.zeros(3), 500, 0.5, 0.5)  # both fit better than assumed
    problem.solve(SolverOptions(linear_solver=backend))
    comps = problem.use_variance_components([("a",)])
    assert [c.scale for c in comps] == [1.0, 1.0] and all(c.factor < 0.5 for c in comps)
    # The factor of the traces serves the covariance, inverted on its pattern or solved with as
    # selected_inverse chooses: the queries factorise nothing more.
    post = problem._posterior
    assert (post.inverse is not None) or (post.factor is not None)
    if backend == "qdldl":  # its factor always goes to the recursion (selected_inverse)
        assert post.inverse is not None
    factorisations = []
    factorize = linalg.SparseCholesky.factorize
    monkeypatch.setattr(linalg.SparseCholesky, "factorize",
                        lambda self, *a, **k: factorisations.append(1) or factorize(self, *a, **k))
    P = np.eye(3)[:1] / 10.0
    np.testing.assert_allclose(problem.covariance("x", scale_by_variance_factor=False)[0],
                               np.linalg.inv(A.T @ A + B.T @ B + P.T @ P), rtol=1e-8)
    assert factorisations == []


def _fresh_covariance(problem, scale):
    """The single-factor posterior of the same problem, solved again."""
    twin = Problem()
    twin.add_block("x", problem.values("x"))
    for g in problem.groups:
        twin.add_group(g)
    twin.solve()
    return twin.covariance("x", scale_by_variance_factor=False) * scale


@pytest.mark.parametrize("backend", available_backends())
def test_a_singular_normal_matrix_is_reported_before_any_trace(backend):
    rng = np.random.default_rng(12)
    B = np.c_[np.zeros(200), rng.normal(size=(200, 2))]  # nothing observes x[0]
    problem = Problem()
    problem.add_block("x", np.zeros((1, 3)))
    problem.add_group(Linear("b", B, rng.normal(size=200), 1.0))
    problem.solve(SolverOptions(linear_solver=backend))
    with pytest.raises(NotPositiveDefiniteError):
        problem.use_variance_components()


def test_use_variance_components_needs_a_fresh_solve():
    rng = np.random.default_rng(8)
    problem, _, _ = _two_group_problem(rng, np.zeros(3), 100, 1.0, 1.0)
    with pytest.raises(RuntimeError, match="solve"):
        problem.use_variance_components()
    problem.solve()
    problem.covariance("x")
    with pytest.raises(RuntimeError, match="before the first covariance query"):
        problem.use_variance_components()


def test_a_direction_one_noisier_group_determines_gets_an_honest_sigma_over_draws():
    """Monte Carlo: x[0] rests on group ``a`` alone, 3x noisier than assumed; ``b`` fits and sets the
    single variance factor near 5, so one factor gives x[0] a sigma 1.34x too small."""
    rng = np.random.default_rng(11)
    x_true = np.array([0.3, -1.0, 2.0])
    z_components, z_single = [], []
    for _ in range(150):
        problem, _, _ = _two_group_problem(rng, x_true, 300, 3.0, 1.0)
        result = problem.solve()
        err = problem.values("x")[0, 0] - x_true[0]
        single = problem.covariance("x", elements=[0])[0, 0, 0]  # sigma0^2 N^-1, before the components
        z_single.append(err / np.sqrt(single))
        problem2, _, _ = _two_group_problem(np.random.default_rng(rng.integers(1 << 32)), x_true, 300, 3.0, 1.0)
        problem2.solve()
        problem2.use_variance_components()
        err2 = problem2.values("x")[0, 0] - x_true[0]
        z_components.append(err2 / np.sqrt(problem2.covariance("x", scale_by_variance_factor=False)[0, 0, 0]))
        assert result.variance_factor < 6.0
    rms = lambda z: float(np.sqrt(np.mean(np.square(z))))  # noqa: E731
    assert 0.85 < rms(z_components) < 1.15
    assert rms(z_single) > 1.2
