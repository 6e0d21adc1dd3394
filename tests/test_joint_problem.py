"""Several problems merged into one (georefine.adjustment.joint, docs/ARCHITECTURE.md §4.4): the adapter's
Jacobians against finite differences, independent problems solved together as apart, shared blocks."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from georefine.adjustment.blocks import ColumnLayout
from georefine.adjustment.joint import PrefixedGroup, PrefixedValues, merge_problems
from georefine.adjustment.linalg import available_backends
from georefine.adjustment.observations.plane import PlaneObservation, plane_reference_frames
from georefine.adjustment.observations.prior import EuclideanPrior, RotationPrior
from georefine.adjustment.observations.trajectory_blocks import TrajectoryBlocks
from georefine.adjustment.problem import Problem
from georefine.adjustment.solver import SolverOptions
from georefine.adjustment.testing import check_jacobians
from georefine.geometry.rotation import exp_so3
from georefine.trajectory.spline import KnotGrid, SplineTrajectory

B = TrajectoryBlocks()
TRAJ = {B.position: "euclidean", B.velocity: "euclidean", B.acceleration: "euclidean", B.attitude: "so3",
        B.rate: "euclidean"}
TIGHT = SolverOptions(max_iterations=100, function_tolerance=1e-15, parameter_tolerance=1e-15,
                      gradient_tolerance=1e-14)


def knots(rng, K):
    t = np.arange(K) * 0.1
    P = np.column_stack([100 + 18 * t, 50 - 3 * t, 160 + np.sin(t)])
    V = np.column_stack([np.full(K, 18.0), np.full(K, -3.0), np.cos(t)])
    A = rng.normal(0, 0.5, (K, 3))
    R = exp_so3(np.column_stack([0.05 * np.sin(t), 0.02 * np.cos(t), 1.2 + 0.1 * t]))
    W = rng.normal(0, 0.2, (K, 3))
    return {B.position: P, B.velocity: V, B.acceleration: A, B.attitude: R, B.rate: W}


def planes(rng, grid, truth=None, n_features=40, n_objects=5, **named):
    """Features of ``n_objects`` planes; with ``truth`` (knot values) georeferenced consistently by it, with noise."""
    c0, k1, k2, n0 = plane_reference_frames(rng.uniform(0, 200, (n_objects, 3)), rng.normal(size=(n_objects, 3)))
    t = np.sort(rng.uniform(0.05, grid.t_end - 0.05, n_features))
    j = np.arange(n_features) % n_objects
    p_b_s, R_b_s = np.array([0.2, -0.1, 0.4]), exp_so3(np.array([0.01, -0.02, 1.5]))
    if truth is None:
        Q = exp_so3(rng.normal(size=(n_features, 3)) * 2.0)
        d = rng.normal(size=(n_features, 3))
        centre, a1, a2 = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(30, 150, (n_features, 1)), \
            Q[:, :, 0], Q[:, :, 1]
    else:
        spline = SplineTrajectory(grid, *(truth[k] for k in TRAJ))
        p, R = spline.pose(t)
        R_w_s = R @ R_b_s
        c_w = c0[j] + rng.normal(0, 3.0, (n_features, 1)) * k1[j] + rng.normal(0, 3.0, (n_features, 1)) * k2[j]
        c_w += rng.normal(0, 0.01, (n_features, 1)) * n0[j]
        centre = np.einsum("nji,nj->ni", R_w_s, c_w - p - np.einsum("nij,j->ni", R, p_b_s))
        phi = rng.uniform(0, np.pi, (n_features, 1))
        a1 = np.einsum("nji,nj->ni", R_w_s, np.cos(phi) * k1[j] + np.sin(phi) * k2[j])
        a2 = np.einsum("nji,nj->ni", R_w_s, -np.sin(phi) * k1[j] + np.cos(phi) * k2[j])
    return PlaneObservation(
        grid, t, centre, a1, a2,
        sigma_d=rng.uniform(0.005, 0.03, n_features), sigma_slope=rng.uniform(5e-4, 3e-3, n_features),
        object_index=j, c0=c0, k1=k1, k2=k2, n0=n0, p_b_s=p_b_s, R_b_s=R_b_s, **named)


def problem(seed, K=15, n_objects=5, boresight=False) -> Problem:
    """A trajectory held by priors near its knots (a stand-in for the GNSS/IMU) and plane observations."""
    rng = np.random.default_rng(seed)
    grid = KnotGrid(0.0, 0.1, K)
    truth = knots(rng, K)
    P = Problem()
    for name, manifold in TRAJ.items():
        start = truth[name]
        start = start @ exp_so3(rng.normal(0, 1e-3, (K, 3))) if manifold == "so3" else start + rng.normal(0, 0.02,
                                                                                                         start.shape)
        P.add_block(name, start, manifold=manifold)
        if manifold == "so3":
            P.add_group(RotationPrior(f"{name}_prior", name, np.arange(K), truth[name], np.full((K, 3), 2e-3)))
        else:
            P.add_group(EuclideanPrior(f"{name}_prior", name, np.arange(K), truth[name], np.full((K, 3), 0.05)))
    group = planes(rng, grid, truth, n_objects=n_objects, boresight="boresight" if boresight else None)
    P.add_block("plane_params", np.zeros((n_objects, 3)))
    if boresight:
        P.add_block("boresight", group.R_b_s[None], manifold="so3")
        P.add_group(RotationPrior("boresight_prior", "boresight", [0], group.R_b_s[None], np.radians(0.1)))
    P.add_group(group)
    return P


def test_prefixed_values_resolve_own_and_shared_names():
    values = {"f1/a": np.zeros(1), "f2/a": np.ones(1), "s": np.full(1, 2.0), "f1/b": np.zeros(2)}
    view = PrefixedValues(values, "f2/", {"s"})
    assert view["a"][0] == 1.0 and view["s"][0] == 2.0
    assert sorted(view) == ["a", "s"] and len(view) == 2
    assert "a" in view and "b" not in view
    with pytest.raises(KeyError):
        view["b"]


@pytest.mark.parametrize("seed", [0, 1])
def test_adapter_jacobians(seed):
    """The wrapped group's Jacobians under the joint names, against central differences through the retraction."""
    rng = np.random.default_rng(seed)
    grid = KnotGrid(0.0, 0.1, 12)
    group = planes(rng, grid, boresight="boresight", time_offset="tau")
    adapter = PrefixedGroup(group, "f2/", frozenset({"plane_params", "boresight", "tau"}))
    assert adapter.name == "f2/planes" and adapter.loss is group.loss and adapter.consumed_redundancy == 0.0
    own = knots(rng, 12)
    values = {f"f2/{k}": v for k, v in own.items()}
    values |= {"f1/" + B.position: own[B.position] + 5.0,  # another part's block: never read
               "plane_params": np.column_stack([rng.normal(0, 0.5, 5), rng.normal(0, 0.3, 5), rng.normal(0, 0.3, 5)]),
               "boresight": (group.R_b_s @ exp_so3(rng.normal(0, 0.01, 3)))[None],
               "tau": np.array([[0.003]])}
    lin = adapter.linearize(values)
    plain = group.linearize({**own, **{k: values[k] for k in ("plane_params", "boresight", "tau")}})
    np.testing.assert_array_equal(lin.residuals, plain.residuals)
    assert {j.block for j in lin.jacobians} == {f"f2/{k}" for k in TRAJ} | {"plane_params", "boresight", "tau"}
    linear = {f"f2/{B.position}": "euclidean", f"f2/{B.velocity}": "euclidean", f"f2/{B.acceleration}": "euclidean"}
    chk = check_jacobians(adapter, values, linear, eps=1e-3)
    assert chk.residual_mismatch == 0.0
    assert chk.max_rel_error < 1e-6, chk
    rest = {f"f2/{B.attitude}": "so3", f"f2/{B.rate}": "euclidean", "plane_params": "euclidean", "boresight": "so3"}
    chk = check_jacobians(adapter, values, rest, eps=1e-5)
    assert chk.max_rel_error < 1e-6, chk
    chk = check_jacobians(adapter, values, {"tau": "euclidean"}, eps=1e-6)
    assert chk.max_rel_error < 1e-6, chk


@pytest.mark.parametrize("backend", available_backends())
def test_independent_problems_solve_as_apart(backend):
    """Two problems that share nothing: the merged solve gives each its own solution and covariances."""
    options = replace(TIGHT, linear_solver=backend)
    apart = [problem(3), problem(4, K=21, n_objects=7)]
    merged_from = [problem(3), problem(4, K=21, n_objects=7)]
    for p in apart:
        p.solve(options)
    joint = merge_problems(merged_from, ["f1/", "f2/"])
    assert len(joint.problem.groups) == sum(len(p.groups) for p in apart)
    result = joint.problem.solve(options)
    assert result.n_unknowns == sum(ColumnLayout.build(p.blocks).n_cols for p in apart)
    for k, p in enumerate(apart):
        view = joint.part(k)
        for name in p.blocks:
            np.testing.assert_allclose(view.values(name), p.values(name), rtol=0, atol=1e-9)
        for name in ("plane_params", B.attitude):
            np.testing.assert_allclose(view.covariance(name, scale_by_variance_factor=False),
                                       p.covariance(name, scale_by_variance_factor=False), rtol=1e-7, atol=1e-16)
    joint.write_back()
    for p, q in zip(apart, merged_from):
        np.testing.assert_allclose(q.values(B.position), p.values(B.position), rtol=0, atol=1e-9)
    # The statistics per part carry the part's own group names.
    names = [g.name for g in joint.part_solve(1, result).groups]
    assert names == [g.name for g in apart[1].groups]


def test_shared_blocks_and_groups():
    """Shared planes and boresight are one block each, the boresight prior one group; a shared group that
    reads a part's own block is refused, and so is a shared block of another shape."""
    parts = [problem(5, boresight=True), problem(6, boresight=True)]
    joint = merge_problems(parts, ["f1/", "f2/"], shared={"plane_params", "boresight"},
                           shared_groups={"boresight_prior"})
    names = set(joint.problem.blocks)
    assert {"plane_params", "boresight"} <= names and "f1/plane_params" not in names
    groups = [g.name for g in joint.problem.groups]
    assert groups.count("boresight_prior") == 1 and "f1/planes" in groups and "f2/planes" in groups
    result = joint.problem.solve(TIGHT)
    assert result.termination in ("function_tolerance", "parameter_tolerance", "gradient_tolerance")
    own = sum(ColumnLayout.build(p.blocks).n_cols for p in parts)
    assert result.n_unknowns == own - 5 * 3 - 3  # one plane block and one boresight less
    # Both parts read the one boresight; its covariance is that of the joint block.
    np.testing.assert_array_equal(joint.part(0).covariance("boresight"), joint.part(1).covariance("boresight"))
    assert joint.part_groups(1)[-1] == "f2/planes" and "boresight_prior" in joint.part_groups(1)
    with pytest.raises(ValueError, match="reads blocks that are not shared"):
        merge_problems([problem(5), problem(6)], ["a/", "b/"], shared={"plane_params"},
                       shared_groups={f"{B.position}_prior"})
    with pytest.raises(ValueError, match="differs between parts"):
        merge_problems([problem(5, n_objects=5), problem(6, n_objects=6)], ["a/", "b/"], shared={"plane_params"})
    with pytest.raises(ValueError, match="distinct prefix"):
        merge_problems([problem(5), problem(6)], ["a/", "a/"])


def test_variance_component_pools_span_the_parts():
    """A part's pool of ``planes`` is the planes of every part: one component, whichever part asks."""
    joint = merge_problems([problem(7), problem(8)], ["f1/", "f2/"])
    joint.problem.solve(TIGHT)
    comps = joint.part(0).use_variance_components([["planes"]])
    pooled = [c for c in comps if "f1/planes" in c.groups]
    assert len(pooled) == 1 and set(pooled[0].groups) == {"f1/planes", "f2/planes"}
    assert joint.part(1).use_variance_components([["planes"]]) == comps
