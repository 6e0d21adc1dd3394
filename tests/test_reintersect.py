"""Re-intersection of the refined cloud from lidargram poses before and after the co-adjustment."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from georefine.geometry.camera import R_w_c_from_opk
from georefine.lidargrammetry.reintersect import feather_weights, reintersect


def _pose(rng, x):
    return R_w_c_from_opk(*rng.normal(0, 0.01, 3)), np.array([x, 0.0, 300.0])


def _moved(X, R0, p0, R1, p1):
    return p1 + (X - p0) @ R0 @ R1.T


def test_shown_points_follow_their_lidargrams_and_unseen_ones_are_interpolated():
    rng = np.random.default_rng(4)
    n = 20_000
    X = np.column_stack([rng.uniform(-100, 100, n), rng.uniform(-60, 60, n), rng.normal(0, 1, n)])
    strip = (np.arange(n) >= n - 2000).astype(int)  # strip 1: no lidargram shows it
    R0a, p0a = _pose(rng, -30.0)
    R0b, p0b = _pose(rng, 30.0)
    dR = Rotation.from_rotvec([0.0, 0.0, 3e-4]).as_matrix()
    R1a, p1a = dR @ R0a, p0a + [0.2, -0.1, 0.05]
    R1b, p1b = dR @ R0b, p0b + [0.25, -0.05, 0.0]
    a = np.flatnonzero((X[:, 0] < 20) & (strip == 0))[::2]
    b = np.flatnonzero((X[:, 0] > -20) & (strip == 0))[::2]
    R0, p0, R1, p1 = np.stack([R0a, R0b]), np.stack([p0a, p0b]), np.stack([R1a, R1b]), np.stack([p1a, p1b])
    out = reintersect(X, strip, [a, b], R0, p0, R1, p1)
    only_a, only_b, both = np.setdiff1d(a, b), np.setdiff1d(b, a), np.intersect1d(a, b)
    np.testing.assert_allclose(out.xyz_w[only_a], _moved(X[only_a], R0a, p0a, R1a, p1a), atol=1e-9)
    np.testing.assert_allclose(out.xyz_w[only_b], _moved(X[only_b], R0b, p0b, R1b, p1b), atol=1e-9)
    mean = 0.5 * (_moved(X[both], R0a, p0a, R1a, p1a) + _moved(X[both], R0b, p0b, R1b, p1b))
    np.testing.assert_allclose(out.xyz_w[both], mean, atol=1e-9)
    assert np.all(out.n_lidargrams[both] == 2) and np.all(out.n_lidargrams[only_a] == 1)
    # Unseen points of strip 0 (every other one) move with their neighbours; strip 1 stays.
    unseen = np.setdiff1d(np.flatnonzero(strip == 0), np.union1d(a, b))
    assert np.all(out.n_lidargrams[unseen] == 0)
    assert np.max(np.linalg.norm(out.xyz_w[unseen] - X[unseen] - [0.22, -0.07, 0.02], axis=1)) < 0.1
    np.testing.assert_array_equal(out.xyz_w[strip == 1], X[strip == 1])
    assert np.all(out.n_lidargrams[strip == 1] == -1)
    s = out.summary()
    assert s["points"] == len(X) and s["multi_ray"] == both.size and s["unchanged"] == 2000


def test_feathered_weights_blend_overlapping_lidargrams_without_a_seam():
    x = np.linspace(-50, 50, 1001)
    X = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    R = R_w_c_from_opk(0.0, 0.0, 0.0)
    p0 = np.array([[-25.0, 0.0, 300.0], [25.0, 0.0, 300.0]])
    p1 = p0 + [[0.0, 0.2, 0.0], [0.0, -0.2, 0.0]]  # the two lidargrams disagree by 0.4 m
    a, b = np.flatnonzero(x <= 25), np.flatnonzero(x >= -25)
    # Each lidargram spans 100 m across 1000 px: u = 10 px/m from its left edge.
    uv = [np.column_stack([(x[i] - p0[j, 0] + 50) * 10, np.full(i.size, 500.0)]) for j, i in enumerate((a, b))]
    w = [feather_weights(u, 1000, 1000) for u in uv]
    assert w[0].max() == 1.0 and w[0].min() >= 0.05
    hard = reintersect(X, np.zeros(len(X), int), [a, b], np.stack([R, R]), p0, np.stack([R, R]), p1)
    soft = reintersect(X, np.zeros(len(X), int), [a, b], np.stack([R, R]), p0, np.stack([R, R]), p1, weights=w)
    dy_hard, dy_soft = hard.xyz_w[:, 1], soft.xyz_w[:, 1]
    # Plain means jump by 0.2 m where the second lidargram begins; feathered ones change gradually.
    assert np.max(np.abs(np.diff(dy_hard))) > 0.19
    assert np.max(np.abs(np.diff(dy_soft))) < 0.02
    assert dy_soft[0] == 0.2 and dy_soft[-1] == -0.2 and abs(dy_soft[500]) < 1e-9
