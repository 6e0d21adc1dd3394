"""GNSS/IMU/LiDAR workflow variants on simulated truth: boresight recovery, robustness to wrong
matches, a local cluster against one process, a coarse first outer iteration.

The project of the README's smallest example, simulated and run once for this file,
tests/test_workflow_gil.py and tests/test_readme_tiny.py (tests/conftest.py: whichever worker
needs it first builds it); every run here starts from that run's G/I adjustment.
The runs are marked slow (CI runs them).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml

from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.io.run_metrics import WorkflowMetrics
from georefine.io.trajectory import read_sbet
from georefine.lidar.correspondences import (
    inject_wrong_matches,
    match_features,
)
from georefine.tasks import TaskRunner
from georefine.trajectory.sampled import trajectory_from_sbet
from georefine.workflows import (
    load_navigation,
)
from georefine.workflows.cache import StepCache, StepRunner
from georefine.workflows.lidar import (
    read_strips,
    run_workflow,
    step_adjust_gil,
    step_features,
)
from georefine.workflows.navigation import imu_rate_trajectory
from georefine.workflows.run_parts import stage_gnss_imu
from truth_helpers import pass_rmse


@pytest.fixture(scope="module")
def project(gil_project) -> Path:
    """The README example's project (corridor-tiny, seed 4, the corridor's scanner): shared (read only)."""
    return gil_project


@pytest.fixture(scope="module")
def gi_cache(gil_gi_cache) -> Path:
    """A step cache holding the project's G/I adjustment (steps 1-2) only: read only."""
    return gil_gi_cache


def _cache(gi_cache: Path, dest: Path) -> Path:
    """A new step cache starting with the G/I adjustment (a copy: the runs add their own steps)."""
    shutil.copytree(gi_cache, dest)
    return dest


@pytest.mark.slow
def test_boresight_error_of_005_deg_is_recovered_from_both_passes(project, gi_cache, tmp_path, caplog):
    wrong = tmp_path / "wrong"
    shutil.copytree(project, wrong)
    cfg = yaml.safe_load((wrong / "project.yaml").read_text())
    true_bs = np.array(cfg["scanner"]["boresight_deg"], dtype=float)
    cfg["scanner"]["boresight_deg"] = (true_bs + [0.05, 0.0, 0.0]).tolist()  # a 0.05 deg roll error
    # No time offset search: the boresight is what this test is about (test_time_offset.py covers it).
    cfg["processing"] = {"lidar": {"estimate_boresight": True, "time_offset": {"search": False}}}
    (wrong / "project.yaml").write_text(yaml.safe_dump(cfg))
    with caplog.at_level("WARNING", logger="georefine.workflows.outer_checks"):
        res = run_workflow(wrong, tmp_path / "out", points=False, cache_dir=_cache(gi_cache, tmp_path / "cache"))
    err_mdeg = (res.gil.boresight_deg - true_bs) * 1e3
    sigma = res.gil.boresight_sigma_mdeg
    assert abs(err_mdeg[0]) < 5.0, (err_mdeg, sigma)
    # All three angles are estimated. A boresight yaw is nearly a heading offset (about the same
    # vertical axis); on this 600 m corridor it is known to a few mdeg only: consistent with sigma.
    assert np.all(np.abs(err_mdeg) < 3.0 * sigma), (err_mdeg, sigma)
    assert sigma[0] < 3.0 and sigma[1] < 3.0, sigma  # roll and pitch: a 5 mdeg bound is about 2 sigma
    # Two passes along one line know the boresight's roll only beside each pass's roll (2.74 mdeg, 0.74 of the
    # G/I/L's roll sigma, 0.66 of the G/I's): the run says so with the figures. The scanner is mounted level, so
    # its sigma about the body's axes is its own.
    np.testing.assert_allclose(res.gil.boresight_body_sigma_mdeg, sigma, rtol=0.01)
    found = [r.getMessage() for r in caplog.records if "do not separate the boresight" in r.getMessage()]
    assert len(found) == 1 and f"roll ± {sigma[0]:.2f} mdeg" in found[0], found


@pytest.mark.slow
def test_ten_percent_wrong_matches_change_yaw_by_less_than_20_percent(project, gi_cache):
    nav = load_navigation(project)
    gi, _ = stage_gnss_imu(StepRunner(StepCache(gi_cache)), nav)  # resumed from the cache
    features, _ = step_features(nav, imu_rate_trajectory(nav, gi), read_strips(nav))
    objects = match_features(features, nav.config.processing.matching)
    sb = read_sbet(project / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800))
    truth = trajectory_from_sbet(sb, nav.frame, nav.t0_gps)
    passes = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"]

    def yaw_rmse(spline):
        d = []
        for p in passes:
            t = np.arange(p["t_start_s"] + 1.0, p["t_end_s"] - 1.0, 0.05)
            pt, Rt = truth.interpolate(t)
            pe, Re = spline.pose(t)
            d.append(nav.frame.rph_from_R_w_b(pe, Re)[:, 2] - nav.frame.rph_from_R_w_b(pt, Rt)[:, 2])
        d = (np.concatenate(d) + np.pi) % (2 * np.pi) - np.pi
        return np.degrees(np.sqrt(np.mean(d**2))) * 1e3

    clean = yaw_rmse(step_adjust_gil(nav, gi, features, objects, covariance=False).result.spline)
    bad_objects, changed = inject_wrong_matches(objects, features, 0.10, np.random.default_rng(3))
    assert changed.size == round(0.10 * np.count_nonzero(objects.feature_object >= 0))
    bad = yaw_rmse(step_adjust_gil(nav, gi, features, bad_objects, covariance=False).result.spline)
    assert yaw_rmse(gi.spline) > 3 * clean  # the LiDAR data matter here
    assert abs(bad - clean) < 0.2 * clean, (clean, bad)


@pytest.mark.slow
def test_a_local_cluster_writes_the_same_trajectory_and_points_as_one_process(project, gi_cache, tmp_path):
    """The whole run on a two-process LocalCluster against the in-process (sync) run.

    One outer iteration and one strip keep it short; its tiles go through the cluster like both
    strips' would (test_tiles.py compares both strips' features and points on a cluster).
    """
    one = tmp_path / "p"
    shutil.copytree(project, one)
    cfg = yaml.safe_load((one / "project.yaml").read_text())
    cfg["processing"] = {"lidar": {"outer_iterations": 1}}
    (one / "project.yaml").write_text(yaml.safe_dump(cfg))
    a = run_workflow(one, tmp_path / "sync", scheduler="sync", cache_dir=_cache(gi_cache, tmp_path / "cache_a"),
                     strips=[1])
    (tmp_path / "cache_b").mkdir()
    for f in (tmp_path / "cache_a").glob("gi-*.pkl"):  # the same G/I, so that only steps 3-6 are compared
        shutil.copy(f, tmp_path / "cache_b" / f.name)
    with TaskRunner("processes", workers=2) as cluster:
        b = run_workflow(one, tmp_path / "cluster", scheduler=cluster, cache_dir=tmp_path / "cache_b", strips=[1])
    assert a.metrics.resumed == b.metrics.resumed == ("gi",) and a.metrics.outer_iterations == b.metrics.outer_iterations
    sa = read_sbet(a.out / "gil" / "trajectory.sbet")  # seconds of week; the week from trajectory.sbet.json
    sb = read_sbet(b.out / "gil" / "trajectory.sbet")
    for k in ("roll_rad", "pitch_rad", "heading_rad"):
        assert np.degrees(np.abs(getattr(sa, k) - getattr(sb, k))).max() <= 1e-6, k
    assert np.abs(sa.h_m - sb.h_m).max() <= 1e-6 and np.abs(sa.lat_rad - sb.lat_rad).max() * 6.4e6 <= 1e-6
    for f in ("strip_1.laz",):
        pa, pb = laspy.read(a.out / "points" / f), laspy.read(b.out / "points" / f)
        assert len(pa.points) == len(pb.points) > 0
        for dim in ("X", "Y", "Z", "gps_time"):
            assert np.array_equal(pa[dim], pb[dim]), (f, dim)


@pytest.mark.slow
def test_a_coarse_first_outer_iteration_ends_where_fine_ones_do(project, gi_cache, gil_single_pass, tmp_path):
    """Outer iterations that start on 0.25 s knots give the trajectory of outer iterations on 0.1 s
    knots alone: the same accuracy against the truth, and the two within the churn of re-matching.
    One pass keeps it short (test_run_both_passes_fixes_heading_and_the_point_cloud runs both
    with the coarse start). The coarse start is the default: the README's single-pass run."""
    fine = tmp_path / "p"
    shutil.copytree(project, fine)
    cfg = yaml.safe_load((fine / "project.yaml").read_text())
    cfg.setdefault("processing", {}).setdefault("lidar", {})["first_knot_interval_s"] = None
    (fine / "project.yaml").write_text(yaml.safe_dump(cfg))
    a_out = gil_single_pass
    a = WorkflowMetrics.read(a_out / "metrics.json")
    b = run_workflow(fine, tmp_path / "fine", strips=[1], points=False, cache_dir=_cache(gi_cache, tmp_path / "cache"))
    assert b.metrics.resumed == ("gi",) and a.strips == b.metrics.strips == (1,)
    # The same G/I start: the single pass computed its own, the fine run resumed the run of both passes'.
    assert (a_out / "gi" / "trajectory.sbet").read_bytes() == (b.out / "gi" / "trajectory.sbet").read_bytes()
    assert [it.knot_interval_s for it in a.outer_iterations][0] == pytest.approx(0.25, rel=1e-3)
    assert {round(it.knot_interval_s, 6) for it in b.metrics.outer_iterations} == {0.1}
    ra = pass_rmse(a_out / "gil" / "trajectory.sbet", project, 1)
    rb = pass_rmse(b.out / "gil" / "trajectory.sbet", project, 1)
    assert np.all(ra <= 1.15 * rb + 0.1), (ra, rb)  # mdeg
    between = compare_sbet_files(a_out / "gil" / "trajectory.sbet", b.out / "gil" / "trajectory.sbet").stats
    assert between["attitude_angle_rmse_mdeg"] < 1.5, between  # processing.lidar.convergence_attitude_mdeg


@pytest.mark.slow
def test_ground_tiles_give_the_whole_flights_objects_and_trajectory(project, gi_cache, gil_full_run, tmp_path):
    """The run (features matched in ground tiles of 200 m, the default) against the whole flight's
    features matched at once (``processing.scale.feature_tile_m: null``): the same objects, the
    same G/I/L trajectory (docs/ARCHITECTURE.md §4.7)."""
    held_project = tmp_path / "held"
    shutil.copytree(project, held_project)
    cfg = yaml.safe_load((held_project / "project.yaml").read_text())
    cfg.setdefault("processing", {}).setdefault("scale", {})["feature_tile_m"] = None
    (held_project / "project.yaml").write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    run_workflow(held_project, out, points=False, cache_dir=_cache(gi_cache, tmp_path / "cache"))
    resolved = yaml.safe_load((gil_full_run / "config.resolved.yaml").read_text())
    assert resolved["processing"]["scale"]["feature_tile_m"] == 200.0  # the default run is the tiled one
    assert (gil_full_run / "features" / "objects.csv").read_text() == (out / "features" / "objects.csv").read_text()
    assert (gil_full_run / "features" / "features.csv").read_text() == (out / "features" / "features.csv").read_text()
    tiled, held = read_sbet(gil_full_run / "gil" / "trajectory.sbet"), read_sbet(out / "gil" / "trajectory.sbet")
    np.testing.assert_allclose(held.lat_rad, tiled.lat_rad, rtol=0, atol=1e-6 / 6.4e6)
    np.testing.assert_allclose(held.lon_rad, tiled.lon_rad, rtol=0, atol=1e-6 / 6.4e6)
    np.testing.assert_allclose(held.h_m, tiled.h_m, rtol=0, atol=1e-6)
    for name in ("roll_rad", "pitch_rad", "heading_rad"):
        np.testing.assert_allclose(getattr(held, name), getattr(tiled, name), rtol=0, atol=1e-6, err_msg=name)
    a, b = WorkflowMetrics.read(gil_full_run / "metrics.json"), WorkflowMetrics.read(out / "metrics.json")
    assert [it.features for it in a.outer_iterations] == [it.features for it in b.outer_iterations]
    assert [it.objects for it in a.outer_iterations] == [it.objects for it in b.outer_iterations]
