"""GNSS, IMU, bias and prior observation groups: Jacobians against manifold finite differences."""

import numpy as np
import pytest

from georefine.adjustment.observations.bias import BiasGrid, BiasRandomWalk
from georefine.adjustment.observations.gnss import GnssPositionObservation
from georefine.adjustment.observations.imu import (
    ImuObservation,
    discrete_gauss_rule,
    fewest_nodes,
    make_imu_windows,
    triad_matrix,
)
from georefine.adjustment.observations.prior import EuclideanPrior, RotationPrior
from georefine.adjustment.observations.trajectory_blocks import TrajectoryBlocks
from georefine.adjustment.testing import check_jacobians
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3
from georefine.trajectory.spline import KnotGrid

SEEDS = [0, 1, 2]
FRAME = LocalFrame.from_degrees(46.7, 11.65, 600.0)
B = TrajectoryBlocks()
TRAJ_BLOCKS = {B.position: "euclidean", B.velocity: "euclidean", B.acceleration: "euclidean",
               B.attitude: "so3", B.rate: "euclidean"}


def random_knots(rng, K):
    t = np.arange(K) * 0.1
    P = np.column_stack([100 + 18 * t, 50 - 3 * t, 160 + np.sin(t)]) + rng.normal(0, 0.01, (K, 3))
    V = np.column_stack([np.full(K, 18.0), np.full(K, -3.0), np.cos(t)]) + rng.normal(0, 0.1, (K, 3))
    A = rng.normal(0, 0.5, (K, 3))
    R = exp_so3(np.column_stack([0.05 * np.sin(t), 0.02 * np.cos(t), 1.2 + 0.1 * t]) + rng.normal(0, 0.01, (K, 3)))
    W = rng.normal(0, 0.2, (K, 3))
    return {B.position: P, B.velocity: V, B.acceleration: A, B.attitude: R, B.rate: W}


@pytest.mark.parametrize("seed", SEEDS)
def test_gnss_jacobians(seed):
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    t = np.sort(rng.uniform(0, grid.t_end, 20))
    A = rng.normal(size=(20, 3, 3)) * 0.01
    cov = A @ np.swapaxes(A, 1, 2) + np.eye(3) * 1e-4
    lever = np.array([-0.8, 0.1, -1.4])
    z = GnssPositionObservation(grid, t, np.zeros((20, 3)), cov, lever).predict(values) + rng.normal(0, 0.01, (20, 3))
    group = GnssPositionObservation(grid, t, z, cov, lever)
    # Step 1e-4: the residuals are whitened by sigma ~ 1 cm, so smaller steps only add roundoff.
    chk = check_jacobians(group, values, TRAJ_BLOCKS, eps=1e-4)
    assert chk.max_rel_error < 1e-5, chk


@pytest.mark.parametrize("seed", SEEDS)
def test_gnss_jacobians_with_a_correlated_error(seed):
    """The correlated GNSS error d(t) on its own knots: Jacobians, and d adds to the modelled position."""
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    egrid = BiasGrid.covering(0.0, grid.t_end, 0.35)
    values["d"] = rng.normal(0, 0.02, (egrid.n_knots, 3))
    t = np.sort(rng.uniform(0, grid.t_end, 20))
    cov = np.broadcast_to(np.diag([1e-4, 1e-4, 4e-4]), (20, 3, 3)).copy()
    lever = np.array([-0.8, 0.1, -1.4])
    plain = GnssPositionObservation(grid, t, np.zeros((20, 3)), cov, lever).predict(values)
    group = GnssPositionObservation(grid, t, plain, cov, lever, error_grid=egrid, error_block="d")
    np.testing.assert_allclose(group.predict(values) - plain, egrid.evaluate(values["d"], t), atol=1e-12)
    chk = check_jacobians(group, values, {**TRAJ_BLOCKS, "d": "euclidean"}, eps=1e-4)
    assert chk.max_rel_error < 1e-5, chk
    with pytest.raises(ValueError, match="go together"):
        GnssPositionObservation(grid, t, plain, cov, lever, error_grid=egrid)


@pytest.mark.parametrize("seed", SEEDS)
def test_gnss_jacobians_with_a_multipath_beside_the_correlated_error(seed):
    """The multipath on knots of its own adds to d(t): Jacobians of both blocks and the sum."""
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    egrid = BiasGrid.covering(0.0, grid.t_end, 0.35)
    mgrid = BiasGrid.covering(0.0, grid.t_end, 0.12)
    values["d"] = rng.normal(0, 0.02, (egrid.n_knots, 3))
    values["m"] = rng.normal(0, 0.02, (mgrid.n_knots, 3))
    t = np.sort(rng.uniform(0, grid.t_end, 20))
    cov = np.broadcast_to(np.diag([1e-4, 1e-4, 4e-4]), (20, 3, 3)).copy()
    lever = np.array([-0.8, 0.1, -1.4])
    plain = GnssPositionObservation(grid, t, np.zeros((20, 3)), cov, lever).predict(values)
    group = GnssPositionObservation(grid, t, plain, cov, lever, error_grid=egrid, error_block="d",
                                    multipath_grid=mgrid, multipath_block="m")
    np.testing.assert_allclose(group.predict(values) - plain,
                               egrid.evaluate(values["d"], t) + mgrid.evaluate(values["m"], t), atol=1e-12)
    chk = check_jacobians(group, values, {**TRAJ_BLOCKS, "d": "euclidean", "m": "euclidean"}, eps=1e-4)
    assert chk.max_rel_error < 1e-5, chk
    with pytest.raises(ValueError, match="go together"):
        GnssPositionObservation(grid, t, plain, cov, lever, multipath_block="m")


@pytest.mark.parametrize("seed", SEEDS)
def test_gnss_jacobians_with_segment_offsets(seed):
    """Epochs of a segment without a fix add its offset; the others do not."""
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    values["off"] = rng.normal(0, 0.2, (2, 3))
    t = np.sort(rng.uniform(0, grid.t_end, 20))
    segment = np.full(20, -1)
    segment[4:9], segment[13:16] = 0, 1
    cov = np.broadcast_to(np.diag([1e-4, 1e-4, 4e-4]), (20, 3, 3)).copy()
    lever = np.array([-0.8, 0.1, -1.4])
    plain = GnssPositionObservation(grid, t, np.zeros((20, 3)), cov, lever).predict(values)
    group = GnssPositionObservation(grid, t, plain, cov, lever, segment=segment, segment_block="off")
    expected = np.zeros((20, 3))
    expected[4:9], expected[13:16] = values["off"][0], values["off"][1]
    np.testing.assert_allclose(group.predict(values) - plain, expected, atol=1e-12)
    chk = check_jacobians(group, values, {**TRAJ_BLOCKS, "off": "euclidean"}, eps=1e-4)
    assert chk.max_rel_error < 1e-5, chk
    with pytest.raises(ValueError, match="go together"):
        GnssPositionObservation(grid, t, plain, cov, lever, segment=segment)


def test_non_fix_segments_from_the_quality_flags():
    from georefine.adjustment.gnss_segments import non_fix_segments
    from georefine.config import GnssFloatOffset

    t = np.arange(0.0, 100.0, 0.2)
    q = np.ones(t.size, dtype=int)
    q[50:100] = 2  # 10 s float
    q[200:210] = 2
    q[210:220] = 5  # Q 2 then 5 without a fix between: one segment, worst Q 5
    q[300:305] = 2
    q[340:345] = 2  # after 7 s of fixes: a segment of its own
    cov = np.broadcast_to(np.diag([0.05, 0.05, 0.1]) ** 2, (t.size, 3, 3)).copy()
    cov[200:220] *= 4.0
    seg = non_fix_segments(t, q, cov, GnssFloatOffset())
    assert len(seg) == 4
    np.testing.assert_array_equal(seg.epochs, [50, 20, 5, 5])
    np.testing.assert_array_equal(seg.quality, [2, 5, 2, 2])
    np.testing.assert_allclose(seg.t_start, t[[50, 200, 300, 340]])
    np.testing.assert_allclose(seg.t_end, t[[99, 219, 304, 344]])
    np.testing.assert_allclose(seg.stated_sigma_w[1], [0.1, 0.1, 0.2])
    assert np.all(seg.index[q == 1] == -1) and np.all(seg.index[200:220] == 1)
    assert non_fix_segments(t, np.ones(t.size, dtype=int), cov, GnssFloatOffset()) is None
    assert non_fix_segments(t, q, cov, None) is None
    # Non-fix epochs further apart than max_gap_s (no fix between: epochs missing) are two segments.
    q2 = np.full(6, 2)
    two = non_fix_segments(np.array([0.0, 1, 2, 30, 31, 32]), q2, cov[:6], GnssFloatOffset(max_gap_s=10.0))
    np.testing.assert_array_equal(two.index, [0, 0, 0, 1, 1, 1])


def test_white_part_of_the_gnss_covariance():
    """The .pos sigma less the correlated part per axis, floored, plus what the chord misses."""
    from georefine.adjustment.gnss_imu import white_gnss_covariance
    from georefine.config import GnssCorrelatedError

    model = GnssCorrelatedError(sigma_horizontal_m=0.015, sigma_up_m=0.03, time_constant_s=300.0)
    total = np.hypot([0.01, 0.01, 0.02], [0.015, 0.015, 0.03])
    cov = np.diag(total**2)[None].repeat(2, axis=0)
    cov[1] = np.diag([0.005, 0.005, 0.01]) ** 2  # smaller than the correlated part: the floor
    white = white_gnss_covariance(cov, model, 5.0)
    chord = np.array([0.015, 0.015, 0.03]) ** 2 * 5.0 / 900.0
    np.testing.assert_allclose(np.diag(white[0]), np.array([0.01, 0.01, 0.02]) ** 2 + chord, rtol=1e-12)
    np.testing.assert_allclose(np.diag(white[1]), (0.3 * np.array([0.005, 0.005, 0.01])) ** 2 + chord, rtol=1e-12)
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3)) * 0.01
    c = white_gnss_covariance((A @ A.T + np.eye(3) * 1e-4)[None], model, 5.0)[0]
    assert np.all(np.linalg.eigvalsh(c) > 0)  # rescaled axes keep it positive definite


def test_white_part_of_the_gnss_covariance_with_a_multipath():
    """A stated multipath's variance comes off the .pos sigma too (to the same floor), and what its knots miss
    is added."""
    from georefine.adjustment.gnss_imu import multipath_knot_interval, white_gnss_covariance
    from georefine.config import GnssCorrelatedError, GnssMultipath, TrajectoryAdjustmentConfig

    model = GnssCorrelatedError(sigma_horizontal_m=0.015, sigma_up_m=0.03, time_constant_s=300.0)
    mp = GnssMultipath(sigma_horizontal_m=0.01, sigma_up_m=0.02, time_constant_s=20.0)
    assert multipath_knot_interval(mp, TrajectoryAdjustmentConfig()) == 5.0
    assert multipath_knot_interval(mp.model_copy(update={"time_constant_s": 8.0}), TrajectoryAdjustmentConfig()) == 2.0
    white_part = np.array([0.01, 0.01, 0.02])
    total = np.sqrt(white_part**2 + np.array([0.015, 0.015, 0.03]) ** 2 + np.array([0.01, 0.01, 0.02]) ** 2)
    cov = np.diag(total**2)[None].repeat(2, axis=0)
    cov[1] = np.diag([0.005, 0.005, 0.01]) ** 2
    white = white_gnss_covariance(cov, model, 5.0, mp, 2.5)
    chord = np.array([0.015, 0.015, 0.03]) ** 2 * 5.0 / 900.0 + np.array([0.01, 0.01, 0.02]) ** 2 * 2.5 / 60.0
    np.testing.assert_allclose(np.diag(white[0]), white_part**2 + chord, rtol=1e-12)
    np.testing.assert_allclose(np.diag(white[1]), (0.3 * np.array([0.005, 0.005, 0.01])) ** 2 + chord, rtol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize(("window_samples", "kind"), [(1, "rates"), (10, "rates"), (10, "increments")])
def test_imu_jacobians(seed, window_samples, kind):
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    rate = 200.0
    t = np.arange(0.01, grid.t_end - 0.01, 1 / rate)
    wins = make_imu_windows(t, rng.normal(0, 0.1, (t.size, 3)), rng.normal(0, 1, (t.size, 3)) + [0, 0, -9.8],
                            rate, window_samples / rate, kind=kind)
    bg_a = BiasGrid(0.0, 0.5, 4)
    bg_g = BiasGrid(0.0, 0.5, 4)
    values |= {"acc_bias": rng.normal(0, 0.01, (4, 3)), "gyro_bias": rng.normal(0, 1e-4, (4, 3)),
               "acc_scale": rng.normal(0, 1e-3, (1, 3)), "gyro_scale": rng.normal(0, 1e-3, (1, 3))}
    group = ImuObservation(grid, wins, FRAME, bg_a, bg_g, sigma_acc=0.01, sigma_gyro=1e-4,
                           nodes=1 if window_samples == 1 else 3)
    blocks = dict(TRAJ_BLOCKS, acc_bias="euclidean", gyro_bias="euclidean", acc_scale="euclidean", gyro_scale="euclidean")
    chk = check_jacobians(group, values, blocks, eps=1e-4)
    assert chk.max_rel_error < 1e-6, chk


def _misaligned_setup(rng, kind: str):
    """Knots, 10-sample IMU windows at 200 Hz and a bias grid for the misalignment and temperature Jacobian tests."""
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    rate = 200.0
    t = np.arange(0.01, grid.t_end - 0.01, 1 / rate)
    wins = make_imu_windows(t, rng.normal(0, 0.1, (t.size, 3)), rng.normal(0, 1, (t.size, 3)) + [0, 0, -9.8],
                            rate, 10 / rate, kind=kind)
    return grid, values, wins, BiasGrid(0.0, 0.5, 4)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("kind", ["rates", "increments"])
def test_imu_jacobians_with_misalignment(seed, kind):
    """Both triads' misalignment blocks, and the trajectory and scale Jacobians through the full
    sensitivity matrix ``I + S + A``."""
    rng = np.random.default_rng(seed)
    grid, values, wins, bg = _misaligned_setup(rng, kind)
    values |= {"acc_bias": rng.normal(0, 0.01, (4, 3)), "gyro_bias": rng.normal(0, 1e-4, (4, 3)),
               "acc_scale": rng.normal(0, 1e-3, (1, 3)), "gyro_scale": rng.normal(0, 1e-3, (1, 3)),
               "acc_mis": rng.normal(0, 1e-3, (1, 6)), "gyro_mis": rng.normal(0, 1e-3, (1, 6))}
    group = ImuObservation(grid, wins, FRAME, bg, bg, sigma_acc=0.01, sigma_gyro=1e-4, nodes=3,
                           acc_misalignment="acc_mis", gyro_misalignment="gyro_mis")
    blocks = dict(TRAJ_BLOCKS, acc_bias="euclidean", gyro_bias="euclidean", acc_scale="euclidean",
                  gyro_scale="euclidean", acc_mis="euclidean", gyro_mis="euclidean")
    chk = check_jacobians(group, values, blocks, eps=1e-4)
    assert chk.max_rel_error < 1e-6, chk
    # The model is M x with M = I + S + A: the misaligned readings are the aligned ones' sensed axes mixed.
    plain = ImuObservation(grid, wins, FRAME, bg, bg, sigma_acc=0.01, sigma_gyro=1e-4, nodes=3)
    zero_bias = values | {"acc_bias": np.zeros((4, 3)), "gyro_bias": np.zeros((4, 3)),
                          "acc_scale": np.zeros((1, 3)), "gyro_scale": np.zeros((1, 3))}
    f0, w0 = plain.predict(zero_bias)
    f1, w1 = group.predict(zero_bias)
    m_f, m_g = triad_matrix(np.zeros(3), values["acc_mis"]), triad_matrix(np.zeros(3), values["gyro_mis"])
    np.testing.assert_allclose(f1, f0 @ m_f.T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(w1, w0 @ m_g.T, rtol=1e-12, atol=1e-15)
    assert m_f[0, 1] == values["acc_mis"][0, 0] and m_f[2, 1] == values["acc_mis"][0, 5]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("kind", ["rates", "increments"])
def test_imu_jacobians_with_temperature_coefficients(seed, kind):
    """The biases' temperature coefficients: Jacobians beside the misalignment, and ``k (T - T_ref)`` adds to each
    window's modelled mean."""
    rng = np.random.default_rng(seed)
    grid, values, wins, bg = _misaligned_setup(rng, kind)
    temperature = rng.uniform(0.0, 20.0, len(wins))
    values |= {"acc_bias": rng.normal(0, 0.01, (4, 3)), "gyro_bias": rng.normal(0, 1e-4, (4, 3)),
               "acc_scale": rng.normal(0, 1e-3, (1, 3)), "gyro_scale": rng.normal(0, 1e-3, (1, 3)),
               "acc_mis": rng.normal(0, 1e-3, (1, 6)), "gyro_mis": rng.normal(0, 1e-3, (1, 6)),
               "acc_temp": rng.normal(0, 1e-4, (1, 3)), "gyro_temp": rng.normal(0, 1e-6, (1, 3))}
    group = ImuObservation(grid, wins, FRAME, bg, bg, sigma_acc=0.01, sigma_gyro=1e-4, nodes=3,
                           acc_misalignment="acc_mis", gyro_misalignment="gyro_mis", temperature=temperature,
                           acc_temperature="acc_temp", gyro_temperature="gyro_temp")
    blocks = dict(TRAJ_BLOCKS, acc_bias="euclidean", gyro_bias="euclidean", acc_scale="euclidean",
                  gyro_scale="euclidean", acc_mis="euclidean", gyro_mis="euclidean", acc_temp="euclidean",
                  gyro_temp="euclidean")
    chk = check_jacobians(group, values, blocks, eps=1e-4)
    assert chk.max_rel_error < 1e-6, chk
    plain = ImuObservation(grid, wins, FRAME, bg, bg, sigma_acc=0.01, sigma_gyro=1e-4, nodes=3,
                           acc_misalignment="acc_mis", gyro_misalignment="gyro_mis")
    (f0, w0), (f1, w1) = plain.predict(values), group.predict(values)
    np.testing.assert_allclose(f1 - f0, temperature[:, None] * values["acc_temp"], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(w1 - w0, temperature[:, None] * values["gyro_temp"], rtol=1e-9, atol=1e-18)
    with pytest.raises(ValueError, match="go together"):
        ImuObservation(grid, wins, FRAME, bg, bg, sigma_acc=0.01, sigma_gyro=1e-4, temperature=temperature)


def _readings(grid, values, t, kind, rate):
    """Noise-free readings of the spline at ``t``: its value at each time tag (rates) or its mean
    over the interval that ends there (increments, 5-point Gauss-Legendre per interval)."""
    one = make_imu_windows(t, np.zeros((t.size, 3)), np.zeros((t.size, 3)), rate, 1 / rate, kind=kind)
    acc, gyro = ImuObservation(grid, one, FRAME, BiasGrid(0.0, 0.5, 4), BiasGrid(0.0, 0.5, 4), 1.0, 1.0,
                               nodes=5).predict(values)
    return gyro, acc


def _spline_without_imu_errors(seed, knot_interval):
    """A 12-knot random spline (:func:`random_knots`) with zero biases and scale factors."""
    grid = KnotGrid(0.0, knot_interval, 12)
    values = random_knots(np.random.default_rng(seed), 12)
    values |= {"acc_bias": np.zeros((4, 3)), "gyro_bias": np.zeros((4, 3)),
               "acc_scale": np.zeros((1, 3)), "gyro_scale": np.zeros((1, 3))}
    return grid, values


@pytest.mark.parametrize("kind", ["rates", "increments"])
def test_imu_windows_model_what_a_sample_is(kind):
    """A window's model is the mean of what its samples are: the spline's value at the time tags
    (rates, exactly) or its mean over the intervals ending there (increments). The midpoint rule of
    the continuous mean misses rates by (2 pi f dt)^2 / 24 of a line at f (the module docstring),
    half a sample's shift misses increments."""
    from dataclasses import replace

    rate = 200.0
    grid, values = _spline_without_imu_errors(7, 0.1)
    # Increments: the windows (t_first - dt, t_last] start on the knots, so that the quadrature
    # integrates within one piece of the spline (across a knot its rate has a kink).
    t = np.arange(0.02 + (1 / rate if kind == "increments" else 0.0), grid.t_end - 0.02, 1 / rate)
    gyro, acc = _readings(grid, values, t, kind, rate)
    wins = make_imu_windows(t, gyro, acc, rate, 4 / rate, kind=kind)
    bg = BiasGrid(0.0, 0.5, 4)

    def misfit(w, nodes=3):
        model_acc, model_gyro = ImuObservation(grid, w, FRAME, bg, bg, 1.0, 1.0, nodes=nodes).predict(values)
        return np.abs(model_gyro - w.gyro).max() / np.abs(w.gyro).max()

    if kind == "rates":
        assert misfit(wins, nodes=4) < 1e-12  # as many nodes as samples: the samples themselves
        # Three nodes of the discrete Gauss rule: exact for polynomials of degree 5 in time, and
        # this spline (random knots, 10 Hz of motion, windows across knots) is nearly one.
        assert misfit(wins) < 1e-9
        other = replace(wins, kind="increments")  # the earlier model: a quadrature over the same limits
    else:
        np.testing.assert_allclose(wins.t_start, t[::4] - 1 / rate, atol=1e-12)  # (t_first - dt, t_last]
        assert misfit(wins) < 1e-6
        other = make_imu_windows(t, gyro, acc, rate, 4 / rate)  # the same numbers read as rates
    assert misfit(other) > 100 * max(misfit(wins), 1e-9), (misfit(other), misfit(wins))


@pytest.mark.parametrize(("n", "m"), [(4, 3), (20, 3), (20, 2), (7, 1), (200, 4), (3, 5)])
def test_discrete_gauss_rule_gives_the_mean_at_the_samples(n, m):
    """The m-node rule over the points 0..n-1 is exact for every polynomial of degree <= 2m - 1, nodes
    inside [0, n - 1], positive weights summing to 1; with m >= n the points themselves."""
    rng = np.random.default_rng(n * 10 + m)
    x, q = discrete_gauss_rule(n, m)
    assert x.size == min(n, m) and np.all(q > 0) and q.sum() == pytest.approx(1.0, abs=1e-14)
    assert x.min() >= 0.0 and x.max() <= n - 1
    i = np.arange(n)
    for degree in range(2 * min(n, m)):
        f = np.polynomial.Polynomial(rng.normal(size=degree + 1))
        assert q @ f(x) == pytest.approx(f(i).mean(), rel=1e-12, abs=1e-12 * np.abs(f(i)).max())
    if m < n:  # one degree more is not exact in general
        f = np.polynomial.Polynomial.basis(2 * m)
        assert abs(q @ f(x) - f(i).mean()) > 1e-9 * f(i).mean()


def test_imu_windows_of_many_samples_cost_the_rule_not_the_samples():
    """Windows of 20 samples (0.1 s at 200 Hz): three nodes each, the samples' mean to 2e-6 of the
    signal on a spline with knots 0.4 s apart and random knot values (170 m/s^2 of specific force: far
    more violent than flight; on the corridor's G/I the difference is 1e-6 of a window's sigma)."""
    rate = 200.0
    grid, values = _spline_without_imu_errors(8, 0.4)
    t = np.arange(0.02, grid.t_end - 0.02, 1 / rate)
    gyro, acc = _readings(grid, values, t, "rates", rate)
    wins = make_imu_windows(t, gyro, acc, rate, 20 / rate)
    bg = BiasGrid(0.0, 2.0, 4)
    obs = ImuObservation(grid, wins, FRAME, bg, bg, 1.0, 1.0, nodes=3)
    straddling = np.floor(wins.t_start / 0.4) != np.floor(wins.t_end / 0.4)  # a knot inside: two pieces
    assert obs.n_nodes == 3 * (len(wins) + np.count_nonzero(straddling))
    model_acc, model_gyro = obs.predict(values)
    for model, data in ((model_acc, wins.acc), (model_gyro, wins.gyro)):
        assert np.abs(model - data).max() < 2e-6 * np.abs(data).max()
    exact = ImuObservation(grid, wins, FRAME, bg, bg, 1.0, 1.0, nodes=3, sample_rule=False)
    assert exact.n_nodes == wins.n_samples.sum()
    np.testing.assert_allclose(exact.predict(values)[1], wins.gyro, rtol=0, atol=1e-12 * np.abs(wins.gyro).max())


@pytest.mark.parametrize("kind", ["rates", "increments"])
def test_fewest_nodes_drops_a_node_only_within_the_tolerance(kind):
    """One node fewer per window where the window means move by at most the tolerance (in sigma)
    against the full rule, the change reported being the largest such move; else the rule kept.
    Windows short enough to be evaluated at their samples are left alone."""
    rate = 200.0
    grid, values = _spline_without_imu_errors(9, 0.4)
    t = np.arange(0.02, grid.t_end - 0.02, 1 / rate)
    gyro, acc = _readings(grid, values, t, kind, rate)
    wins = make_imu_windows(t, gyro, acc, rate, 20 / rate, kind=kind)
    bg = BiasGrid(0.0, 2.0, 4)
    obs = ImuObservation(grid, wins, FRAME, bg, bg, sigma_acc=0.05, sigma_gyro=0.001, nodes=3)
    fewer, change = fewest_nodes(obs, values, tolerance=np.inf)
    assert fewer.nodes == 2 and fewer.n_nodes < obs.n_nodes
    (a3, g3), (a2, g2) = obs.predict(values), fewer.predict(values)
    assert change == pytest.approx(max(np.abs(a2 - a3).max() / 0.05, np.abs(g2 - g3).max() / 0.001), rel=1e-12)
    assert change > 0
    kept, again = fewest_nodes(obs, values, tolerance=0.5 * change)
    assert kept is obs and again == change
    taken, _ = fewest_nodes(obs, values, tolerance=2.0 * change)
    assert taken.nodes == 2
    if kind == "rates":
        short = make_imu_windows(t, gyro, acc, rate, 2 / rate)  # two samples: evaluated at them with 2 or 3 nodes
        same = ImuObservation(grid, short, FRAME, bg, bg, 0.05, 0.001, nodes=3)
        assert fewest_nodes(same, values, tolerance=np.inf) == (same, 0.0)


def test_imu_windows_average_and_respect_gaps():
    t = np.concatenate([np.arange(0, 1, 0.005), np.arange(1.1, 2, 0.005)])
    g = np.column_stack([t, 2 * t, -t])
    w = make_imu_windows(t, g, g, 200.0, 0.05)
    assert np.all(w.n_samples <= 10)
    assert not np.any((w.t_start < 1.05) & (w.t_end > 1.05))  # no window across the gap
    k = 3
    np.testing.assert_allclose(w.gyro[k], g[10 * k:10 * k + 10].mean(axis=0))
    np.testing.assert_allclose(w.t_start[k], t[10 * k] - 0.0025)


@pytest.mark.parametrize("seed", SEEDS)
def test_bias_random_walk_and_priors(seed):
    rng = np.random.default_rng(seed)
    values = {"b": rng.normal(size=(6, 3)), "R": exp_so3(rng.normal(size=(4, 3)))}
    rw = BiasRandomWalk("rw", "b", BiasGrid(0.0, 10.0, 6), q=[1e-3, 2e-3, 3e-3])
    chk = check_jacobians(rw, values, {"b": "euclidean"})
    assert chk.max_rel_error < 1e-7
    lin = rw.linearize(values, False)
    np.testing.assert_allclose(lin.residuals[:3], (values["b"][1] - values["b"][0]) / (np.array([1, 2, 3]) * 1e-3 * np.sqrt(10)))
    prior = EuclideanPrior("p", "b", [0, 5], values["b"][[0, 5]] + 0.1, sigma=0.05)
    assert check_jacobians(prior, values, {"b": "euclidean"}).max_rel_error < 1e-7
    rp = RotationPrior("rp", "R", [1, 3], exp_so3(rng.normal(size=(2, 3)) * 0.3), sigma=[0.01, 0.02, 0.03])
    assert check_jacobians(rp, values, {"R": "so3"}).max_rel_error < 1e-5


def test_bias_grid_interpolates_linearly():
    grid = BiasGrid.covering(0.0, 25.0, 10.0)
    assert grid.n_knots == 4
    b = np.arange(12.0).reshape(4, 3)
    np.testing.assert_allclose(grid.evaluate(b, np.array([0.0, 5.0, 30.0])), [b[0], (b[0] + b[1]) / 2, b[3]])
