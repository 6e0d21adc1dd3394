"""The LiDAR time offset: its search from the strips' agreement, and the workflow that estimates it.

The observation model's Jacobians are tested in test_observation_plane.py. Here: the search on
synthetic features (two passes flown in opposite directions over tilted planes), the plan
shift, the warnings, and `georefine run` end to end on strips whose time stamps are 3 s behind.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import laspy
import numpy as np
import pytest

from georefine.evaluation.trajectory_files import truth_gnss_time_offset
from georefine.geometry.rotation import R_n_b_from_rph
from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.planes import PlanarFeatures
from georefine.lidar.tiles import StripPlan, Tile, shift_plan
from georefine.lidar.time_offset import offset_unobservable, search_time_offset
from georefine.sim.scenarios import simulate_project
from georefine.trajectory.sampled import Trajectory
from georefine.workflows.outer_checks import GNSS_PULL_RATIO, warn_plane_misfit
from georefine.workflows.time_offset import warn_time_offset
from truth_helpers import pass_rmse

SPEED = 50.0
R_W_N = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # NED -> ENU


def two_passes() -> Trajectory:
    """East along y = 0 for 40 s, a 20 s turn, back west along y = 0 for 40 s; 200 m up, gentle oscillations."""
    t = np.arange(0.0, 100.0, 0.01)
    x = np.where(t < 40, -1000 + SPEED * t, np.where(t < 60, 1000.0, 1000 - SPEED * (t - 60)))
    y = np.where((t >= 40) & (t < 60), 30.0, 0.0)
    p = np.column_stack([x, y, 200 + 0.5 * np.sin(0.3 * t)])
    heading = np.where(t < 50, np.pi / 2, -np.pi / 2)  # ENU east = NED heading 90 deg
    R_n_b = R_n_b_from_rph(np.radians(0.5 * np.sin(0.7 * t)), np.radians(0.3 * np.cos(0.5 * t)), heading)
    return Trajectory(t, p, R_W_N @ R_n_b)


def synthetic_features(rng, traj: Trajectory, offset_s: float, n_planes: int = 400) -> PlanarFeatures:
    """Roof facets and facades along the line, each seen once per pass, stamped ``offset_s`` early.

    A feature is a patch on a true plane, written into the scanner frame (= body frame here)
    with the true pose at its true time; its time stamp is that time minus ``offset_s``.
    """
    poses = PoseInterpolator(traj)
    xs = rng.uniform(-900, 900, n_planes)
    ys = rng.uniform(-60, 60, n_planes)
    zs = rng.uniform(0, 15, n_planes)
    tilt = np.where(rng.random(n_planes) < 0.5, rng.uniform(0.4, 0.8, n_planes), np.pi / 2)
    az = rng.uniform(0, 2 * np.pi, n_planes)
    normal = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    parts = []
    for strip, (t_a, direction) in enumerate([(0.0, 1.0), (60.0, -1.0)], start=1):
        t_true = t_a + (xs * direction + 1000.0) / SPEED + rng.normal(0, 0.3, n_planes)
        p, R = poses(t_true)
        centre_w = np.column_stack([xs, ys, zs])
        k1 = np.cross(normal, [0.0, 0.0, 1.0]) + np.cross(normal, [1.0, 0.0, 0.0]) * 1e-3
        k1 /= np.linalg.norm(k1, axis=1, keepdims=True)
        k2 = np.cross(normal, k1)
        to_s = lambda v: np.einsum("nji,nj->ni", R, v)  # noqa: E731
        n = n_planes
        parts.append(PlanarFeatures(
            strip=np.full(n, strip), channel=np.zeros(n), time=t_true - offset_s,
            centre_s=to_s(centre_w - p), axis1_s=to_s(k1), axis2_s=to_s(k2), normal_s=to_s(normal),
            centre_w=centre_w, normal_w=normal, n_points=np.full(n, 50), roughness_m=np.full(n, 0.01),
            extent_m=np.full(n, 2.0), sigma_d_m=np.full(n, 0.002), sigma_slope_rad=np.full(n, 1e-3),
            seed_cell=np.zeros((n, 3)),
        ))
    return PlanarFeatures.concatenate(parts)


@pytest.mark.parametrize("offset_s", [0.0, 0.05, 1.0, -3.0, 18.0])
def test_the_search_finds_the_offset_that_makes_opposite_passes_agree(offset_s):
    rng = np.random.default_rng(3)
    traj = two_passes()
    feats = synthetic_features(rng, traj, offset_s)
    poses = PoseInterpolator(traj)
    found = search_time_offset(feats, poses, poses.span, np.zeros(3), np.eye(3), speed_max_m_s=SPEED,
                               range_s=20.0)
    # The fine step is 0.4 m / (2 v) / 2 = 2 ms; the parabola places the peak well inside it.
    assert abs(found.best_s - offset_s) < 1e-3, found
    assert found.adopted == (offset_s != 0.0), found
    assert found.offset_s == (found.best_s if found.adopted else 0.0)
    if found.adopted:
        assert found.score_best > 0.9 and found.score_configured < 0.5 * found.score_best
        assert f"{offset_s:+.4f}"[:5] in found.describe()


def grid_features(rng, traj: Trajectory, spacing: float = 2.0) -> PlanarFeatures:
    """Features at the nodes of a ``spacing`` grid along the line, as the extraction seeds them:
    three rows of facades along the track (normal across it: a shift along the track stays in
    their plane), which the second pass seeds at every other node only, and a row of roofs
    sloping 15 degrees along the track (a shift moves them off their plane), seeded by both
    passes at every node. No time offset."""
    poses = PoseInterpolator(traj)
    x = np.arange(-900.0, 900.0, spacing)
    facade = np.vstack([np.column_stack([x, np.full_like(x, y), np.full_like(x, 5.0)]) for y in (20.0, 30.0, 40.0)])
    roof = np.column_stack([x, np.full_like(x, -10.0), np.full_like(x, 8.0)])
    tilt = np.radians(15.0)
    n_facade = np.tile([0.0, -1.0, 0.0], (facade.shape[0], 1))
    n_roof = np.tile([np.sin(tilt), 0.0, np.cos(tilt)], (x.size, 1))
    parts = []
    for strip, (t_a, direction) in enumerate([(0.0, 1.0), (60.0, -1.0)], start=1):
        keep = np.ones(len(facade), bool) if strip == 1 else (np.arange(len(facade)) % 2 == 0)
        centre_w = np.vstack([facade[keep], roof]) + rng.normal(0, 0.05, (keep.sum() + x.size, 3)) * [1, 0, 1]
        normal = np.vstack([n_facade[keep], n_roof])
        t_true = t_a + (centre_w[:, 0] * direction + 1000.0) / SPEED
        p, R = poses(t_true)
        k1 = np.cross(normal, [0.0, 0.0, 1.0]) + np.cross(normal, [1.0, 0.0, 0.0]) * 1e-3
        k1 /= np.linalg.norm(k1, axis=1, keepdims=True)
        k2 = np.cross(normal, k1)
        to_s = lambda v: np.einsum("nji,nj->ni", R, v)  # noqa: E731
        n = len(centre_w)
        parts.append(PlanarFeatures(
            strip=np.full(n, strip), channel=np.zeros(n), time=t_true,
            centre_s=to_s(centre_w - p), axis1_s=to_s(k1), axis2_s=to_s(k2), normal_s=to_s(normal),
            centre_w=centre_w, normal_w=normal, n_points=np.full(n, 50), roughness_m=np.full(n, 0.01),
            extent_m=np.full(n, 2.0), sigma_d_m=np.full(n, 0.002), sigma_slope_rad=np.full(n, 1e-3),
            seed_cell=np.zeros((n, 3)),
        ))
    return PlanarFeatures.concatenate(parts)


def test_counterparts_one_seed_node_away_do_not_pull_the_search_off_the_truth():
    """A feature whose node the other pass did not seed has its counterparts at the next nodes.
    Looked for within less than a node's spacing, a shift that brings them in scores better than
    the truth (on simulated corridors flown at 30 m/s the search adopted ±16 ms where the truth
    was 0); within two spacings the truth scores best."""
    traj = two_passes()
    feats = grid_features(np.random.default_rng(6), traj)
    poses = PoseInterpolator(traj)
    args = (feats, poses, poses.span, np.zeros(3), np.eye(3))
    found = search_time_offset(*args, speed_max_m_s=SPEED, range_s=2.0, feature_spacing_m=2.0)
    assert not found.adopted and abs(found.best_s) < 2e-3, found
    # The radius the fine scan had before (1.6 m, as with a 0.8 m grid) is pulled off by about
    # a node's distance over twice the speed (10 ms) and adopts it.
    narrow = search_time_offset(*args, speed_max_m_s=SPEED, range_s=2.0, feature_spacing_m=0.8)
    assert narrow.adopted and 3e-3 < abs(narrow.best_s) < 15e-3, narrow


def test_a_search_from_a_configured_offset_looks_around_it():
    rng = np.random.default_rng(4)
    traj = two_passes()
    feats = synthetic_features(rng, traj, 18.0)
    feats = PlanarFeatures(**{**feats.__dict__, "time": feats.time + 18.0})  # extracted at the configured 18 s
    poses = PoseInterpolator(traj)
    found = search_time_offset(feats, poses, poses.span, np.zeros(3), np.eye(3), speed_max_m_s=SPEED,
                               configured_s=18.0, range_s=2.0)
    assert not found.adopted and abs(found.best_s - 18.0) < 1e-3
    assert found.offset_s == 18.0 and "stays" in found.describe()


def test_passes_flown_one_way_cannot_show_an_offset():
    """Both strips from the first pass (a shift moves them alike): the configured offset stays."""
    rng = np.random.default_rng(5)
    traj = two_passes()
    feats = synthetic_features(rng, traj, 1.0)
    first = feats.select(np.flatnonzero(feats.strip == 1))
    copy = PlanarFeatures(**{**first.__dict__, "strip": np.full(len(first), 2)})
    poses = PoseInterpolator(traj)
    found = search_time_offset(PlanarFeatures.concatenate([first, copy]), poses, poses.span, np.zeros(3), np.eye(3),
                               speed_max_m_s=SPEED, range_s=3.0)
    assert not found.adopted and found.offset_s == 0.0
    assert found.candidates == 0 and "flown one way" in found.reason, found  # not searched: the adjustment's test
    # The two passes (all stamped a second early) have opposite tracks: the search runs and finds it.
    both = search_time_offset(feats, poses, poses.span, np.zeros(3), np.eye(3), speed_max_m_s=SPEED, range_s=3.0)
    assert both.adopted and both.candidates > 0 and abs(both.best_s - 1.0) < 1e-3, both
    one = search_time_offset(first, poses, poses.span, np.zeros(3), np.eye(3), speed_max_m_s=SPEED)
    assert not one.adopted and one.candidates == 0 and "one strip" in one.reason


def _track(t: np.ndarray, heading_deg) -> np.ndarray:
    """Velocity (ENU, m/s) at ``t``: 30 m/s along ``heading_deg`` (clockwise from north), ±1 m/s of noise."""
    h = np.radians(np.broadcast_to(heading_deg, t.shape))
    v = np.column_stack([30 * np.sin(h), 30 * np.cos(h), np.zeros_like(t)])
    return v + np.random.default_rng(3).normal(0, 1.0, v.shape)


@pytest.mark.parametrize("headings, observable", [
    ((90.0,), False),  # one strip
    ((90.0, 100.0), False),  # two strips flown one way, 10 degrees apart
    ((90.0, 270.0), True),  # opposite passes: twice the shift
    ((90.0, 0.0), True),  # crossing: 1.4 times
    ((90.0, 95.0, 0.0), True),
])
def test_only_strips_with_different_tracks_show_an_offset(headings, observable):
    """An offset moves each strip along its own track: strips flown one way disagree by nothing."""
    times = np.concatenate([np.linspace(100 * i, 100 * i + 40, 500) for i in range(len(headings))])
    strips = np.repeat(np.arange(1, len(headings) + 1), 500)
    heading_at = lambda t: np.asarray(headings)[np.minimum(t // 100, len(headings) - 1).astype(int)]  # noqa: E731
    reason = offset_unobservable(times, strips, lambda t: _track(t, heading_at(t)))
    assert (reason is None) == observable, reason
    if not observable:
        assert ("one strip" if len(headings) == 1 else "flown one way") in reason


def test_a_strip_that_does_not_move_shows_no_offset():
    """A hover has no track: with one moving strip beside it the offset stays held."""
    times = np.concatenate([np.linspace(0, 40, 300), np.linspace(100, 140, 300)])
    strips = np.repeat([1, 2], 300)
    velocity = lambda t: np.where((t < 50)[:, None], _track(t, 90.0), 0.1 * _track(t, 270.0))  # noqa: E731
    assert "one strip flown faster than 5 m/s only" in offset_unobservable(times, strips, velocity)


def test_a_shifted_plan_moves_every_time_and_no_record():
    tiles = (Tile(Path("s.laz"), 1, 0, 0, 10, -np.inf, 5.0, 0, 12, 1.0),
             Tile(Path("s.laz"), 1, 1, 10, 20, 5.0, np.inf, 8, 20, 1.0))
    plan = StripPlan(Path("s.laz"), 1, 20, 1.0, 9.0, True, tiles)
    moved = shift_plan(plan, 18.0)
    assert (moved.t_first, moved.t_last) == (19.0, 27.0)
    assert [(t.own_t0, t.own_t1) for t in moved.tiles] == [(-np.inf, 23.0), (23.0, np.inf)]
    assert [(t.start, t.stop, t.read_start, t.read_stop) for t in moved.tiles] == [(0, 10, 0, 12), (10, 20, 8, 20)]
    assert shift_plan(plan, 0.0) is plan


def _cfg(configured=0.0, warn_ms=0.5):
    return SimpleNamespace(scanner=SimpleNamespace(time_offset_s=configured),
                           processing=SimpleNamespace(lidar=SimpleNamespace(time_offset=SimpleNamespace(warn_ms=warn_ms))))


def test_an_estimated_offset_off_the_configuration_is_a_warning_with_its_figures(caplog):
    with caplog.at_level(logging.WARNING, logger="georefine.workflows.time_offset"):
        warn_time_offset(_cfg(), 0.0003, 0.00004)  # 0.3 ms: under the 0.5 ms threshold
        warn_time_offset(_cfg(), 0.002, 0.0008)  # 2 ms but only 2.5 sigma
        warn_time_offset(_cfg(), 0.002, None)  # no sigma
        warn_time_offset(_cfg(), -0.00064, 0.00002, 0.00071)  # corridor's clean run: GNSS errors, 0.9 sigma
        assert not caplog.records
        warn_time_offset(_cfg(18.0), 18.0021, 0.0001, 0.0002)
    assert len(caplog.records) == 1
    msg = caplog.records[0].getMessage()
    assert "+2.10 ms (± 0.22 ms: 0.10 from the adjustment, 0.20 from GNSS" in msg
    assert "scanner.time_offset_s: 18.0021" in msg


def _solve(groups):
    stats = [SimpleNamespace(name=n, rms=rms, n_downweighted=5, n_observations=100) for n, rms in groups.items()]
    return SimpleNamespace(group=lambda name: next(s for s in stats if s.name == name))


def test_planes_that_pull_the_trajectory_off_the_gnss_are_a_warning(caplog):
    gi = SimpleNamespace(solve=_solve({"gnss": 0.55}))
    fits = SimpleNamespace(result=SimpleNamespace(solve=_solve({"gnss": 0.57, "planes": 2.0})))
    pulls = SimpleNamespace(result=SimpleNamespace(solve=_solve({"gnss": 0.55 * GNSS_PULL_RATIO * 1.5, "planes": 26.0})))
    records = (SimpleNamespace(attitude_change_mdeg=66.9), SimpleNamespace(attitude_change_mdeg=17.4))
    with caplog.at_level(logging.WARNING, logger="georefine.workflows.outer_checks"):
        warn_plane_misfit(gi, fits, records)
        assert not caplog.records
        warn_plane_misfit(gi, pulls, records)
    msg = caplog.records[0].getMessage()
    assert "1.65 sigma RMS with the planes against 0.55" in msg and "66.90, 17.40 mdeg" in msg
    assert "scanner.time_offset_s" in msg


@pytest.mark.slow
def test_strips_stamped_three_seconds_late_are_found_estimated_and_written_corrected(tmp_path):
    project = tmp_path / "p"
    # Half the corridor (300 m): passes long enough to adjust, half the points of the default.
    simulate_project("corridor-tiny", project, seed=11, overrides=["scanner_time_offset_s=3.0", "scene.length_m=300"])
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "georefine", "run", str(project), "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "LiDAR time offset: the strips agree best" in proc.stderr
    assert "the LiDAR time stamps are +3" in proc.stderr  # the estimate is not in project.yaml: a warning
    assert "pull the trajectory off the GNSS" not in proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    first, last = metrics["outer_iterations"][0], metrics["outer_iterations"][-1]
    search = first["time_offset_search"]
    assert search["adopted"] and abs(search["best_s"] - 3.0) < search["step_s"]  # the fine step: 4.4 ms at 18 m/s
    report = json.loads((out / "gil" / "adjustment.json").read_text())["lidar_time_offset"]
    # The GNSS errors, correlated in time, move the passes apart along the track by a few mm, which
    # the offset cannot tell from its own (0.81 ms at 18 m/s for this seed): within 0.2 ms of that.
    implied = truth_gnss_time_offset(project)
    assert abs(report["estimate_s"] - 3.0 - implied) < 2e-4, (report, implied)
    # The adjustment estimates those GNSS errors (gnss.correlated_error), so its sigma holds that
    # share and nothing is added for it: the offset's error against the truth is within 3 sigma.
    assert report["gnss_sigma_ms"] == 0.0, report
    assert 0.1 < report["sigma_ms"] < 1.0, report
    assert abs(report["estimate_s"] - 3.0) < 3e-3 * report["sigma_ms"], (report, implied)
    assert last["time_offset_s"] == pytest.approx(report["estimate_s"], abs=1e-4)
    for strip in (1, 2):
        gi = pass_rmse(out / "gi" / "trajectory.sbet", project, strip)
        gil = pass_rmse(out / "gil" / "trajectory.sbet", project, strip)
        assert gil[2] <= 0.3 * gi[2] and np.all(gil[:2] <= 1.1 * gi[:2]), (strip, gi, gil)
    # The points carry navigation time: their stamps plus the estimate.
    src = laspy.read(project / "scans" / "strip_1.laz").gps_time[:1000]
    written = laspy.read(out / "points" / "strip_1.laz").gps_time[:1000]
    np.testing.assert_allclose(written - src, report["estimate_s"], atol=1e-6)
