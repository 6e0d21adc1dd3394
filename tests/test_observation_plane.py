"""Plane correspondences (docs/ARCHITECTURE.md §4.3, paper 000 Eq. 5): Jacobians, model and an end-to-end boresight solve."""

import numpy as np
import pytest

from georefine.adjustment.observations.plane import (
    PlaneObservation,
    object_planes,
    plane_parameters,
    plane_reference_frames,
)
from georefine.adjustment.observations.trajectory_blocks import TrajectoryBlocks
from georefine.adjustment.problem import Problem
from georefine.adjustment.robust import CauchyLoss
from georefine.adjustment.solver import SolverOptions
from georefine.adjustment.testing import check_jacobians
from georefine.errors import InputError
from georefine.geometry.rotation import R_n_b_from_rph, exp_so3, log_so3
from georefine.trajectory.spline import KnotGrid, eval_orientation, eval_position, locate_near

SEEDS = [0, 1, 2]
B = TrajectoryBlocks()
TRAJ_BLOCKS = {B.position: "euclidean", B.velocity: "euclidean", B.acceleration: "euclidean",
               B.attitude: "so3", B.rate: "euclidean"}
R_W_N = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # NED -> ENU
MDEG = np.radians(1e-3)


# ----------------------------------------------------------------------------- random groups


def random_knots(rng, K):
    t = np.arange(K) * 0.1
    P = np.column_stack([100 + 18 * t, 50 - 3 * t, 160 + np.sin(t)]) + rng.normal(0, 0.01, (K, 3))
    V = np.column_stack([np.full(K, 18.0), np.full(K, -3.0), np.cos(t)]) + rng.normal(0, 0.1, (K, 3))
    A = rng.normal(0, 0.5, (K, 3))
    R = exp_so3(np.column_stack([0.05 * np.sin(t), 0.02 * np.cos(t), 1.2 + 0.1 * t]) + rng.normal(0, 0.01, (K, 3)))
    W = rng.normal(0, 0.2, (K, 3))
    return {B.position: P, B.velocity: V, B.acceleration: A, B.attitude: R, B.rate: W}


def random_axes(rng, n):
    """Orthonormal in-plane axes k1, k2 (n, 3) each (columns of random rotations)."""
    Q = exp_so3(rng.normal(size=(n, 3)) * 2.0)
    return Q[:, :, 0], Q[:, :, 1]


def random_group(rng, grid, n_features=25, n_objects=4, boresight=None, lever_arm=None, **timing):
    c0, k1, k2, n0 = plane_reference_frames(rng.uniform(0, 200, (n_objects, 3)), rng.normal(size=(n_objects, 3)))
    a1, a2 = random_axes(rng, n_features)
    direction = rng.normal(size=(n_features, 3))
    centre_s = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(30, 150, (n_features, 1))
    return PlaneObservation(
        grid, np.sort(rng.uniform(0.05, grid.t_end - 0.05, n_features)), centre_s, a1, a2,
        sigma_d=rng.uniform(0.005, 0.03, n_features), sigma_slope=rng.uniform(5e-4, 3e-3, n_features),
        object_index=rng.integers(0, n_objects, n_features), c0=c0, k1=k1, k2=k2, n0=n0,
        p_b_s=np.array([0.2, -0.1, 0.4]), R_b_s=exp_so3(np.array([0.01, -0.02, 1.5])),
        boresight=boresight, lever_arm=lever_arm, **timing,
    )


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("calibration", [False, True])
def test_plane_jacobians(seed, calibration):
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    group = random_group(rng, grid, boresight="R_b_s" if calibration else None,
                         lever_arm="p_b_s" if calibration else None)
    # (d, alpha, beta) away from zero: the normalisation of n matters.
    values["plane_params"] = np.column_stack([rng.normal(0, 0.5, 4), rng.normal(0, 0.3, 4), rng.normal(0, 0.3, 4)])
    blocks = dict(TRAJ_BLOCKS, plane_params="euclidean")
    if calibration:
        values["R_b_s"] = (group.R_b_s @ exp_so3(rng.normal(0, 0.01, 3)))[None]
        values["p_b_s"] = (group.p_b_s + rng.normal(0, 0.05, 3))[None]
        blocks |= {"R_b_s": "so3", "p_b_s": "euclidean"}
    # The residuals are linear in the position states and the lever arm: a large step keeps the
    # round-off of residuals ~1e4 (random planes 100 m away, sigma ~1 cm) small. Rotations act on
    # lever arms of ~150 m (curvature ~1e4): small step.
    linear = {B.position, B.velocity, B.acceleration, "p_b_s"}
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k in linear}, eps=1e-3)
    assert chk.residual_mismatch == 0.0
    assert chk.max_rel_error < 1e-6, chk
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k not in linear}, eps=1e-5)
    assert chk.max_rel_error < 1e-6, chk


@pytest.mark.parametrize("seed", SEEDS)
def test_time_offset_and_drift_jacobians(seed):
    """The LiDAR time offset and drift: their columns and the knots' columns at the shifted times."""
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    group = random_group(rng, grid, boresight="R_b_s", lever_arm="p_b_s", time_offset="tau", time_drift="kappa")
    values["plane_params"] = np.column_stack([rng.normal(0, 0.5, 4), rng.normal(0, 0.3, 4), rng.normal(0, 0.3, 4)])
    values |= {"R_b_s": group.R_b_s[None], "p_b_s": group.p_b_s[None],
               "tau": np.array([[rng.uniform(-0.02, 0.02)]]), "kappa": np.array([[rng.uniform(-1e-3, 1e-3)]])}
    blocks = dict(TRAJ_BLOCKS, plane_params="euclidean", R_b_s="so3", p_b_s="euclidean")
    # The times move the features along 18 m/s and rotate them at ~0.2 rad/s: a step of 1e-6 s
    # keeps the curvature error of the central difference far below the tolerance.
    chk = check_jacobians(group, values, {"tau": "euclidean", "kappa": "euclidean"}, eps=1e-6)
    assert chk.residual_mismatch == 0.0
    assert chk.max_rel_error < 1e-6, chk
    linear = {B.position, B.velocity, B.acceleration, "p_b_s"}
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k in linear}, eps=1e-3)
    assert chk.max_rel_error < 1e-6, chk
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k not in linear}, eps=1e-5)
    assert chk.max_rel_error < 1e-6, chk
    # Zero offset and drift are the group without time parameters.
    plain = random_group(np.random.default_rng(seed), grid)
    zero = values | {"tau": np.zeros((1, 1)), "kappa": np.zeros((1, 1))}
    timed = random_group(np.random.default_rng(seed), grid, time_offset="tau", time_drift="kappa")
    np.testing.assert_allclose(timed.linearize(zero, False).residuals, plain.linearize(zero, False).residuals,
                               rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_range_calibration_jacobians(seed):
    """The range offset and scale: their column, and the others through the corrected centres; zero
    offset and scale are the group without them, and a centre read 3 cm + 100 ppm long is put back."""
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    group = random_group(rng, grid, boresight="R_b_s", lever_arm="p_b_s", range_calibration="range")
    values["plane_params"] = np.column_stack([rng.normal(0, 0.5, 4), rng.normal(0, 0.3, 4), rng.normal(0, 0.3, 4)])
    values |= {"R_b_s": group.R_b_s[None], "p_b_s": group.p_b_s[None],
               "range": np.array([[rng.normal(0, 0.03), rng.normal(0, 2e-4)]])}
    blocks = dict(TRAJ_BLOCKS, plane_params="euclidean", R_b_s="so3", p_b_s="euclidean")
    chk = check_jacobians(group, values, {"range": "euclidean"}, eps=1e-6)
    assert chk.residual_mismatch == 0.0
    assert chk.max_rel_error < 1e-6, chk
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k in {"R_b_s", B.attitude}}, eps=1e-5)
    assert chk.max_rel_error < 1e-6, chk
    plain = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s")
    ranged = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s",
                          range_calibration="range")
    zero = values | {"range": np.zeros((1, 2))}
    np.testing.assert_allclose(ranged.linearize(zero, False).residuals, plain.linearize(zero, False).residuals,
                               rtol=0, atol=1e-9)
    long = group.centre_s * (1.0 + 1e-4) + 0.03 * group.centre_s / np.linalg.norm(group.centre_s, axis=1)[:, None]
    read_long = random_group(np.random.default_rng(seed), grid, range_calibration="range")
    read_long.centre_s = long
    read_long.__post_init__()
    np.testing.assert_allclose(read_long.centres_s({"range": np.array([[0.03, 1e-4]])}), group.centre_s, atol=1e-9)


def _calibrated_group_values(seed):
    """``(rng, grid, values, channel)`` of the scanner-calibration Jacobian tests: knots, object planes, a range
    calibration ``range`` and channel angles ``ch`` drawn from ``rng`` (seeded), and 25 features' channels."""
    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    channel = np.random.default_rng(seed + 100).integers(-1, 3, 25)
    values["plane_params"] = np.column_stack([rng.normal(0, 0.5, 4), rng.normal(0, 0.3, 4), rng.normal(0, 0.3, 4)])
    values |= {"range": np.array([[rng.normal(0, 0.03), rng.normal(0, 2e-4)]]), "ch": rng.normal(0, 1e-3, (3, 2))}
    return rng, grid, values, channel


@pytest.mark.parametrize("seed", SEEDS)
def test_range_incidence_jacobians(seed):
    """The incidence-dependent range bias: its column (alone, with the range calibration, and with the channel
    angles), the others through the corrected centres; zero is the group without it, and a centre read
    b (1 / cos(phi) - 1) long is put back."""
    from georefine.adjustment.observations.plane import incidence_term

    rng, grid, values, channel = _calibrated_group_values(seed)
    values["inc"] = np.array([[rng.normal(0, 0.05)]])
    for extra in ({}, {"range_calibration": "range"},
                  {"range_calibration": "range", "channel": channel, "channel_angles": "ch"}):
        group = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s",
                             range_incidence="inc", **extra)
        values |= {"R_b_s": group.R_b_s[None], "p_b_s": group.p_b_s[None]}
        assert np.ptp(group._incidence_g) > 0.01  # features seen under several incidences
        chk = check_jacobians(group, values, {"inc": "euclidean"} | {extra[k]: "euclidean" for k in extra
                                                                      if k != "channel"}, eps=1e-7)
        assert chk.residual_mismatch == 0.0
        assert chk.max_rel_error < 1e-6, chk
        chk = check_jacobians(group, values, {"R_b_s": "so3", B.attitude: "so3"}, eps=1e-5)
        assert chk.max_rel_error < 1e-6, chk
    plain = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s")
    biased = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s",
                          range_incidence="inc")
    zero = values | {"inc": np.zeros((1, 1))}
    np.testing.assert_allclose(biased.linearize(zero, False).residuals, plain.linearize(zero, False).residuals,
                               rtol=0, atol=1e-9)
    true = plain.centre_s
    beam = true / np.linalg.norm(true, axis=1)[:, None]
    g = incidence_term(beam, np.cross(plain.axis1_s, plain.axis2_s))
    read = random_group(np.random.default_rng(seed), grid, range_incidence="inc")
    read.centre_s = true + (0.04 * g)[:, None] * beam
    read.__post_init__()
    np.testing.assert_allclose(read.centres_s({"inc": np.array([[0.04]])}), true, atol=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_channel_angle_jacobians(seed):
    """Each channel's tilt and scan-angle error: their columns (with the range calibration too; -1 a reference
    channel without them), and the others through the corrected centres; zero angles are the group without
    them, and a centre recorded along a beam tens of mdeg off is turned back onto its true beam."""
    from georefine.lidar.georeference import calibrated_channels

    rng = np.random.default_rng(seed)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    channel = np.random.default_rng(seed + 100).integers(-1, 3, 25)  # -1: the reference channel
    group = random_group(rng, grid, boresight="R_b_s", lever_arm="p_b_s", range_calibration="range",
                         channel=channel, channel_angles="ch")
    values["plane_params"] = np.column_stack([rng.normal(0, 0.5, 4), rng.normal(0, 0.3, 4), rng.normal(0, 0.3, 4)])
    values |= {"R_b_s": group.R_b_s[None], "p_b_s": group.p_b_s[None],
               "range": np.array([[rng.normal(0, 0.03), rng.normal(0, 2e-4)]]), "ch": rng.normal(0, 1e-3, (3, 2))}
    blocks = dict(TRAJ_BLOCKS, plane_params="euclidean", R_b_s="so3", p_b_s="euclidean")
    chk = check_jacobians(group, values, {"ch": "euclidean", "range": "euclidean"}, eps=1e-7)
    assert chk.residual_mismatch == 0.0
    assert chk.max_rel_error < 1e-6, chk
    chk = check_jacobians(group, values, {k: v for k, v in blocks.items() if k in {"R_b_s", B.attitude}}, eps=1e-5)
    assert chk.max_rel_error < 1e-6, chk
    plain = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s")
    angled = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s",
                          range_calibration="range", channel=channel, channel_angles="ch")
    zero = values | {"range": np.zeros((1, 2)), "ch": np.zeros((3, 2))}
    np.testing.assert_allclose(angled.linearize(zero, False).residuals, plain.linearize(zero, False).residuals,
                               rtol=0, atol=1e-9)
    errors = np.radians(np.array([[40.0, -25.0], [-10.0, 15.0], [5.0, 30.0]]) * 1e-3)
    true = group.centre_s
    errors[0] = 0.0
    recorded = calibrated_channels(true, np.maximum(channel, 0), -errors)  # turned the other way: as recorded
    channel_as_block = np.where(channel > 0, channel - 1, -1)
    read = random_group(np.random.default_rng(seed), grid, channel=channel_as_block, channel_angles="ch")
    read.centre_s = recorded
    read.__post_init__()
    np.testing.assert_allclose(read.centres_s({"ch": errors[1:]}), true, atol=1e-9)
    with pytest.raises(ValueError, match="channel of each"):
        random_group(np.random.default_rng(seed), grid, channel_angles="ch")


def test_calibration_blocks_default_to_fixed_values():
    rng = np.random.default_rng(4)
    grid = KnotGrid(0.0, 0.1, 12)
    values = random_knots(rng, 12) | {"plane_params": rng.normal(0, 0.1, (4, 3))}
    fixed = random_group(np.random.default_rng(5), grid)
    named = random_group(np.random.default_rng(5), grid, boresight="bs", lever_arm="la")
    values |= {"bs": fixed.R_b_s[None], "la": fixed.p_b_s[None]}
    np.testing.assert_array_equal(fixed.linearize(values, False).residuals, named.linearize(values, False).residuals)
    lin = named.linearize(values)
    assert lin.residuals.shape == (3 * fixed.n_features,)
    np.testing.assert_array_equal(lin.observation, np.repeat(np.arange(fixed.n_features), 3))
    with pytest.raises(ValueError, match="shape"):
        named.linearize(values | {"bs": np.stack([fixed.R_b_s] * 2)}, False)


def test_plane_parametrisation_round_trip():
    rng = np.random.default_rng(7)
    c0, k1, k2, n0 = plane_reference_frames(rng.normal(size=(50, 3)) * 100, rng.normal(size=(50, 3)))
    frame = np.stack([k1, k2, n0], axis=2)
    np.testing.assert_allclose(frame @ np.swapaxes(frame, 1, 2), np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frame), 1.0)
    params = rng.normal(0, 0.3, (50, 3))
    c, n = object_planes(c0, k1, k2, n0, params)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    np.testing.assert_allclose(c, c0 + params[:, :1] * n0)
    # Any point of the plane and either sign of the normal give the same parameters.
    a1, a2 = np.cross(n, k1), np.cross(n, k2)
    point = c + rng.normal(size=(50, 1)) * a1 + rng.normal(size=(50, 1)) * a2
    np.testing.assert_allclose(plane_parameters(c0, k1, k2, n0, point, -3.0 * n), params, atol=1e-12)
    # Horizontal and vertical planes get a horizontal first axis.
    _, k1h, _, _ = plane_reference_frames(np.zeros((2, 3)), [[0, 0, 2.0], [0.6, 0.8, 0]])
    np.testing.assert_allclose(k1h[:, 2], 0.0, atol=1e-15)
    with pytest.raises(ValueError, match="perpendicular"):
        plane_parameters(c0[:1], k1[:1], k2[:1], n0[:1], c0[:1], k1[:1])


def test_validation():
    rng = np.random.default_rng(3)
    grid = KnotGrid(0.0, 0.1, 12)
    g = random_group(rng, grid)
    kw = {"grid": grid, "time": g.time, "centre_s": g.centre_s, "axis1_s": g.axis1_s, "axis2_s": g.axis2_s,
          "sigma_d": 0.01, "sigma_slope": 1e-3, "object_index": g.object_index, "c0": g.c0, "k1": g.k1, "k2": g.k2,
          "n0": g.n0, "p_b_s": g.p_b_s, "R_b_s": g.R_b_s}
    PlaneObservation(**kw)
    with pytest.raises(ValueError, match="object_index"):
        PlaneObservation(**kw | {"object_index": g.object_index + 4})
    with pytest.raises(ValueError, match="not orthonormal"):
        PlaneObservation(**kw | {"axis2_s": g.axis1_s})
    with pytest.raises(ValueError, match="not orthonormal"):
        PlaneObservation(**kw | {"k1": g.n0})
    with pytest.raises(ValueError, match="positive"):
        PlaneObservation(**kw | {"sigma_d": 0.0})
    with pytest.raises(ValueError, match="rotation"):
        PlaneObservation(**kw | {"R_b_s": 2 * np.eye(3)})
    with pytest.raises(InputError, match="outside the spline span"):
        PlaneObservation(**kw | {"time": g.time + 5.0})
    empty = PlaneObservation(**kw | {k: v[:0] for k, v in kw.items() if k in ("time", "centre_s", "axis1_s", "axis2_s", "object_index")})
    lin = empty.linearize(random_knots(rng, 12) | {"plane_params": np.zeros((4, 3))})
    assert lin.residuals.size == 0 and lin.jacobians == []


# ------------------------------------------------------------------- end to end (simulated)

RADIUS_M, DURATION_S = 60.0, 10.0


def motion(t):
    """A U-turn at 100 m above ground: heading through 180 deg, 20 deg bank, small oscillations."""
    th, thd = np.pi * t / DURATION_S, np.pi / DURATION_S
    p = np.column_stack([RADIUS_M * np.sin(th), RADIUS_M * (1 - np.cos(th)), 100 + 2 * np.sin(0.6 * t)])
    v = np.column_stack([RADIUS_M * thd * np.cos(th), RADIUS_M * thd * np.sin(th), 1.2 * np.cos(0.6 * t)])
    a = np.column_stack([-RADIUS_M * thd**2 * np.sin(th), RADIUS_M * thd**2 * np.cos(th), -0.72 * np.sin(0.6 * t)])
    R_n_b = R_n_b_from_rph(np.radians(20 + 3 * np.sin(1.3 * t)), np.radians(2 * np.sin(0.9 * t)), np.pi / 2 - th)
    return p, v, a, R_W_N @ R_n_b


def true_trajectory():
    grid = KnotGrid(0.0, 0.25, 41)
    t = grid.knot_times
    P, V, A, R = motion(t)
    h = 1e-4
    W = log_so3(np.swapaxes(motion(t - h)[3], 1, 2) @ motion(t + h)[3]) / (2 * h)
    return grid, {B.position: P, B.velocity: V, B.acceleration: A, B.attitude: R, B.rate: W}


def simulate(rng, noise, n_objects=40, per_object=10, sigma_d=5e-4, sigma_slope=2e-4):
    """Ground patches, roofs and facades around the U-turn, each seen by features at random times.

    Features are 8 m x 8 m patches on the true planes, written into ``s`` with the true
    trajectory, boresight and lever arm; with ``noise`` their centres move along the normal by
    ``sigma_d`` and their axes tilt by ``sigma_slope`` (0.5-1.5 x the nominal values, per feature).
    Reference frames come from planes off by 5 cm and 0.5 deg, so the true (d, alpha, beta) are
    not zero.
    """
    grid, traj = true_trajectory()
    R_b_s = exp_so3(np.array([0.01, -0.02, np.pi / 2]))
    p_b_s = np.array([0.3, -0.1, 0.5])
    kind = rng.integers(0, 3, n_objects)  # ground, roof, facade
    th, off = rng.uniform(0, np.pi, n_objects), rng.uniform(-45, 50, n_objects)
    centre = np.column_stack([(RADIUS_M + off) * np.sin(th), RADIUS_M - (RADIUS_M + off) * np.cos(th),
                              np.choose(kind, [0.0, 10.0, 5.0])])
    tilt = np.choose(kind, [rng.uniform(0, 0.05, n_objects), rng.uniform(0.35, 0.7, n_objects), np.full(n_objects, np.pi / 2)])
    az = rng.uniform(0, 2 * np.pi, n_objects)
    normal = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    _, u1, u2, _ = plane_reference_frames(centre, normal)

    F = n_objects * per_object
    obj = np.repeat(np.arange(n_objects), per_object)
    time = rng.uniform(0.1, DURATION_S - 0.1, F)
    uv = rng.uniform(-4, 4, (F, 2))
    x_w = centre[obj] + uv[:, :1] * u1[obj] + uv[:, 1:] * u2[obj]
    gamma = rng.uniform(0, 2 * np.pi, F)
    a1 = np.cos(gamma)[:, None] * u1[obj] + np.sin(gamma)[:, None] * u2[obj]
    a2 = np.cross(normal[obj], a1)
    sd, ss = sigma_d * rng.uniform(0.5, 1.5, F), sigma_slope * rng.uniform(0.5, 1.5, F)
    if noise:
        x_w = x_w + (sd * rng.standard_normal(F))[:, None] * normal[obj]
        frame = np.stack([a1, a2, normal[obj]], axis=2) @ exp_so3(
            np.column_stack([ss * rng.standard_normal(F), ss * rng.standard_normal(F), np.zeros(F)]))
        a1, a2 = frame[:, :, 0], frame[:, :, 1]
    P, V, A, R, W = B.knots(traj)
    R_w_b = eval_orientation(grid, R, W, time, rate=False).R_w_b
    R_s_w = np.swapaxes(R_w_b @ R_b_s, 1, 2)
    p_w_s = eval_position(grid, P, V, A, time) + R_w_b @ p_b_s

    def to_s(x_w):
        return np.einsum("nij,nj->ni", R_s_w, x_w)

    tilt_err = exp_so3(rng.normal(0, np.radians(0.5), (n_objects, 3)))
    c0, k1, k2, n0 = plane_reference_frames(centre + rng.normal(0, 0.05, (n_objects, 3)),
                                            np.einsum("nij,nj->ni", tilt_err, normal))
    return {"grid": grid, "traj": traj, "time": time, "centre_s": to_s(x_w - p_w_s), "axis1_s": to_s(a1),
            "axis2_s": to_s(a2), "sigma_d": sd, "sigma_slope": ss, "object_index": obj, "c0": c0, "k1": k1, "k2": k2,
            "n0": n0, "p_b_s": p_b_s, "R_b_s": R_b_s, "params_true": plane_parameters(c0, k1, k2, n0, centre, normal)}


def adjust(sim, rng, object_index=None, loss=None, perturb_deg=0.05):
    """Trajectory constant; boresight off by perturb_deg about each axis; objects start at (0, 0, 0)."""
    fields = ("grid", "time", "centre_s", "axis1_s", "axis2_s", "sigma_d", "sigma_slope", "object_index",
              "c0", "k1", "k2", "n0", "p_b_s", "R_b_s")
    kw = {k: sim[k] for k in fields}
    if object_index is not None:
        kw["object_index"] = object_index
    group = PlaneObservation(**kw, boresight="R_b_s", loss=loss)
    problem = Problem()
    for name, v in sim["traj"].items():
        problem.add_block(name, v, "so3" if name == B.attitude else "euclidean", constant=True)
    problem.add_block("plane_params", np.zeros((sim["c0"].shape[0], 3)))
    problem.add_block("R_b_s", (sim["R_b_s"] @ exp_so3(np.radians(perturb_deg) * rng.choice([-1.0, 1.0], 3)))[None], "so3")
    problem.add_group(group)
    result = problem.solve(SolverOptions(max_iterations=100))
    boresight_error = log_so3(sim["R_b_s"].T @ problem.values("R_b_s")[0])
    c, n = object_planes(sim["c0"], sim["k1"], sim["k2"], sim["n0"], problem.values("plane_params"))
    c_true, n_true = object_planes(sim["c0"], sim["k1"], sim["k2"], sim["n0"], sim["params_true"])
    offset_error = np.abs(np.einsum("oi,oi->o", n, c_true - c))  # distance at the true plane's point c
    tilt_error = np.linalg.norm(np.cross(n, n_true), axis=1)
    return result, problem, group, boresight_error, offset_error, tilt_error


@pytest.mark.parametrize("seed", SEEDS)
def test_simulated_planes_are_consistent_with_the_model(seed):
    sim = simulate(np.random.default_rng(seed), noise=False)
    group = PlaneObservation(**{k: sim[k] for k in ("grid", "time", "centre_s", "axis1_s", "axis2_s", "sigma_d",
                                                    "sigma_slope", "object_index", "c0", "k1", "k2", "n0", "p_b_s", "R_b_s")})
    values = sim["traj"] | {"plane_params": sim["params_true"]}
    assert np.abs(group.linearize(values, False).residuals).max() < 1e-6
    frames = group.feature_frames(values)
    c, n = group.object_planes(values)
    np.testing.assert_allclose(np.einsum("ni,ni->n", n[sim["object_index"]], frames.centre_w - c[sim["object_index"]]),
                               0.0, atol=1e-8)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", n[sim["object_index"]], frames.normal_w)), 1.0)
    # Moving every object by 1 mm along its reference normal changes r1 by -(n.n0) 1 mm / sigma_d.
    moved = values | {"plane_params": sim["params_true"] + [1e-3, 0.0, 0.0]}
    r1 = group.linearize(moved, False).residuals[0::3]
    j = sim["object_index"]
    np.testing.assert_allclose(r1, -np.einsum("ni,ni->n", n[j], sim["n0"][j]) * 1e-3 / sim["sigma_d"], atol=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("noise", [False, True])
def test_recovers_boresight_and_planes(seed, noise):
    rng = np.random.default_rng(seed)
    sim = simulate(rng, noise=noise)
    result, problem, _, bs_err, off_err, tilt_err = adjust(sim, rng)
    assert result.converged, result.summary()
    if not noise:  # exact data: exact recovery of the 0.05 deg boresight error and the planes
        assert np.linalg.norm(bs_err) < 1e-3 * MDEG
        assert off_err.max() < 1e-6 and tilt_err.max() < 1e-8
        return
    # Noise 0.5 mm / 0.2 mrad (x 0.5-1.5): observed |boresight error| <= 0.25 mdeg, offsets <= 0.46 mm,
    # tilts <= 0.16 mrad over seeds 0-9.
    assert np.linalg.norm(bs_err) < MDEG
    assert off_err.max() < 1e-3
    assert tilt_err.max() < 4e-4
    # The a-priori sigmas are right, so sigma0^2 ~ 1 (redundancy ~1080: sd 0.04) and the boresight
    # error is consistent with its posterior covariance (chi2, 3 dof, p = 0.001).
    assert 0.85 < result.variance_factor < 1.15
    cov = problem.covariance("R_b_s")[0]
    assert bs_err @ np.linalg.solve(cov, bs_err) < 16.27


@pytest.mark.parametrize("seed", SEEDS)
def test_cauchy_loss_rejects_wrong_assignments(seed):
    rng = np.random.default_rng(seed)
    sim = simulate(rng, noise=True)
    obj = sim["object_index"].copy()
    F, O = obj.size, sim["c0"].shape[0]
    wrong = rng.choice(F, F // 10, replace=False)
    obj[wrong] = (obj[wrong] + rng.integers(1, O, wrong.size)) % O
    state = rng.bit_generator.state
    result, problem, group, bs_err, off_err, _ = adjust(sim, rng, object_index=obj, loss=CauchyLoss())
    assert result.converged, result.summary()
    # Observed over seeds 0-9: |boresight error| <= 0.27 mdeg, offsets <= 0.56 mm; all wrong
    # assignments end with a whitened norm > 10, no correct one does.
    assert np.linalg.norm(bs_err) < MDEG
    assert off_err.max() < 1e-3
    norms = group.residual_norms({name: b.values for name, b in problem.blocks.items()})
    good = np.setdiff1d(np.arange(F), wrong)
    assert np.median(norms[wrong]) > 100 * np.median(norms[good])
    assert np.mean(norms[wrong] > 10) > 0.9 and np.mean(norms[good] > 10) < 0.01
    # Plain least squares on the same data is ruined (observed 46-930 mdeg).
    rng.bit_generator.state = state
    _, _, _, bs_err_ls, _, _ = adjust(sim, rng, object_index=obj, loss=None)
    assert np.linalg.norm(bs_err_ls) > 20 * MDEG


def test_a_moving_time_offset_keeps_the_jacobian_structure():
    """An offset change of a few ms moves features across knots; they stay in their stamps'
    intervals (the polynomial continued: locate_near), so the Jacobian's elements do not change and
    the solver keeps its analysis. Beyond half an interval they move to the next interval."""
    rng = np.random.default_rng(5)
    K = 12
    grid = KnotGrid(0.0, 0.1, K)
    values = random_knots(rng, K)
    group = random_group(rng, grid, time_offset="tau")
    values["plane_params"] = np.column_stack([rng.normal(0, 0.5, 4), rng.normal(0, 0.3, 4), rng.normal(0, 0.3, 4)])

    def elements(tau):
        lin = group.linearize(values | {"tau": np.array([[tau]])}, True)
        return [jb.elements.copy() for jb in lin.jacobians]

    k_stamp, _ = grid.locate(group.time)
    crossing = grid.locate(np.clip(group.time + 0.03, grid.t_start, grid.t_end))[0] != k_stamp
    assert crossing.any()  # some features change interval at +30 ms
    for a, b in zip(elements(0.0), elements(0.03)):
        np.testing.assert_array_equal(a, b)
    moved = elements(0.07)  # more than half an interval: relocated
    assert any(not np.array_equal(a, b) for a, b in zip(elements(0.0), moved))


def test_locate_near_continues_the_interval_within_half_of_it():
    grid = KnotGrid(1.0, 0.1, 6)
    t = np.array([1.02, 1.19, 1.31, 1.45])
    k0, _ = grid.locate(t)
    k, u = locate_near(grid, t + 0.04, k0)
    np.testing.assert_array_equal(k, k0)  # 1.23 stays in [1.1, 1.2) continued: u = 1.3
    np.testing.assert_allclose(u, (t + 0.04 - (1.0 + 0.1 * k0)) / 0.1)
    k, u = locate_near(grid, t + 0.09, k0)  # 1.28 is 0.8 of an interval past 1.2: relocated
    assert k[1] == k0[1] + 1 and 0.0 <= u[1] <= 1.0


@pytest.mark.parametrize("seed", SEEDS)
def test_encoder_error_jacobians(seed):
    """The encoder error's four columns (alone, and with the range calibration and the channel angles), the
    others through the corrected centres; zero is the group without it, and a centre whose beam left at
    ``alpha + e(alpha)`` is put back on it."""
    from georefine.adjustment.observations.plane import ENCODER_TERMS, encoder_basis
    from georefine.lidar.georeference import beam_angles, beam_direction

    rng, grid, values, channel = _calibrated_group_values(seed)
    values["enc"] = rng.normal(0, 5e-4, (1, ENCODER_TERMS))
    for extra in ({}, {"range_calibration": "range", "channel": channel, "channel_angles": "ch"}):
        group = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s",
                             encoder="enc", **extra)
        values |= {"R_b_s": group.R_b_s[None], "p_b_s": group.p_b_s[None]}
        chk = check_jacobians(group, values, {"enc": "euclidean"} | {extra[k]: "euclidean" for k in extra
                                                                      if k != "channel"}, eps=1e-7)
        assert chk.residual_mismatch == 0.0
        assert chk.max_rel_error < 1e-6, chk
        chk = check_jacobians(group, values, {"R_b_s": "so3", B.attitude: "so3"}, eps=1e-5)
        assert chk.max_rel_error < 1e-6, chk
    plain = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s")
    with_encoder = random_group(np.random.default_rng(seed), grid, boresight="R_b_s", lever_arm="p_b_s", encoder="enc")
    zero = values | {"enc": np.zeros((1, ENCODER_TERMS))}
    np.testing.assert_allclose(with_encoder.linearize(zero, False).residuals, plain.linearize(zero, False).residuals,
                               rtol=0, atol=1e-9)
    e = values["enc"][0]
    r, tau, alpha = beam_angles(plain.centre_s)
    read = random_group(np.random.default_rng(seed), grid, encoder="enc")
    true = r[:, None] * beam_direction(tau, alpha + encoder_basis(alpha) @ e)
    np.testing.assert_allclose(read.centres_s(values), true, atol=1e-9)


def test_encoder_basis_is_orthogonal_over_the_field_of_view():
    """The four terms have zero mean and are orthogonal over +-A (the mean is the boresight's roll)."""
    from georefine.adjustment.observations.plane import ENCODER_HALF_WIDTH_DEG, encoder_basis

    alpha = np.radians(np.linspace(-ENCODER_HALF_WIDTH_DEG, ENCODER_HALF_WIDTH_DEG, 20001))
    basis = encoder_basis(alpha)
    np.testing.assert_allclose(basis.mean(axis=0), 0.0, atol=1e-4)
    gram = basis.T @ basis / alpha.size
    np.testing.assert_allclose(gram - np.diag(np.diag(gram)), 0.0, atol=1e-4)
    np.testing.assert_allclose(np.diag(gram), 1.0 / (2 * np.arange(1, 5) + 1), rtol=1e-3)
