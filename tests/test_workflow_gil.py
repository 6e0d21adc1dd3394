"""GNSS/IMU/LiDAR workflow (steps 3-6) end to end on simulated truth: `georefine run`.

Both passes and a single pass against G/I of the same data, boresight recovery, robustness to
wrong matches, point-cloud accuracy, and bad input. The full runs are marked slow (CI runs them).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from browser_helpers import WINDOW, check_rendered_images, chromium, rendered_images
from cli_helpers import STAGE_LINE, messages
from georefine.errors import InputError
from georefine.evaluation.point_cloud import compare_with_truth
from georefine.evaluation.summary import RunEvaluation
from georefine.io.files import make_output_folder
from georefine.io.las import read_las
from georefine.io.run_metrics import WorkflowMetrics, read_adjustment_report
from georefine.io.trajectory import read_sbet
from georefine.io.trajectory_csv import read_trajectory_csv
from georefine.lidar.object_files import read_objects
from georefine.lidar.planes import read_features
from georefine.sim.scenarios import simulate_project
from georefine.trajectory.sampled import Trajectory, trajectory_from_sbet
from georefine.workflows import (
    load_navigation,
    run_georeference,
)
from georefine.workflows.lidar import (
    precompute_gnss_imu,
    read_strips,
    run_workflow,
    step_features,
)
from shared_projects import README_SEED
from truth_helpers import pass_rmse


@pytest.fixture(scope="module")
def project(gil_project) -> Path:
    """The README example's project (corridor-tiny, seed 4, the corridor's scanner): shared (read only)."""
    return gil_project


@pytest.fixture(scope="module")
def sparse_project(tmp_path_factory) -> Path:
    """Too few points per square metre for any planar feature."""
    out = tmp_path_factory.mktemp("gil_sparse") / "p"
    simulate_project("corridor-tiny", out, seed=8, overrides=["scanner.pulse_rate_hz=3000", "scanner.line_rate_hz=60"])
    return out


@pytest.fixture(scope="module")
def full_run(gil_full_run) -> Path:
    """The README's `georefine run tiny --out r`: both passes, points and the step cache (read only)."""
    return gil_full_run


def _rms3(e: np.ndarray) -> float:
    """3-D RMS of errors (N, 3)."""
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def _point_errors(points: Path, project: Path, step: int = 20) -> np.ndarray:
    """Every ``step``-th point's 3-D error against the truth (the files hold the same points in the same order)."""
    errors = []
    for f in sorted(points.glob("strip_*.laz")):
        est, tru = laspy.read(f), laspy.read(project / "truth" / f.name)
        errors.append(np.column_stack([est.x - tru.x, est.y - tru.y, est.z - tru.z])[::step])
    return np.concatenate(errors)


@pytest.mark.slow
def test_run_both_passes_fixes_heading_and_the_point_cloud(project, full_run, tmp_path):
    out = full_run
    for rel in ("gi/trajectory.sbet", "gil/trajectory.sbet", "gil/trajectory.csv", "gil/adjustment.json",
                "points/strip_1.laz", "points/strip_2.laz", "features/features.csv", "features/objects.csv",
                "metrics.json", "config.resolved.yaml"):
        assert (out / rel).is_file(), rel
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["strips"] == [1, 2] and 2 <= len(metrics["outer_iterations"]) <= 3
    # The first outer iteration on coarse knots (processing.lidar.first_knot_interval_s), the rest on 0.1 s.
    knots = [it["knot_interval_s"] for it in metrics["outer_iterations"]]
    assert knots[0] == pytest.approx(0.25, rel=1e-3) and knots[1:] == pytest.approx([0.1] * (len(knots) - 1), rel=1e-6)
    # The typed record reads the file back to exactly what was written.
    typed = WorkflowMetrics.from_dict(metrics)
    assert typed.to_dict() == metrics
    assert typed.outer_iterations[-1].features == metrics["outer_iterations"][-1]["features"]
    assert [p.file for p in typed.points] == ["strip_1.laz", "strip_2.laz"]
    assert typed.strip_time_gps[1][0] < typed.strip_time_gps[1][1] <= typed.strip_time_gps[2][0]
    assert all(p["outside_trajectory"] == 0 for p in metrics["points"])
    # What the planes added per pass: the posterior attitude sigma of G/I and G/I/L during each strip,
    # the RMS of each solution's trajectory.csv sigma over the strip's span.
    assert [p.strip for p in typed.pass_precision] == [1, 2]
    for p in typed.pass_precision:
        t0, t1 = typed.strip_time_gps[p.strip]
        for sol, stated in (("gi", p.gi_sigma_mdeg), ("gil", p.gil_sigma_mdeg)):
            table = read_trajectory_csv(out / sol / "trajectory.csv")
            inside = (table.time_gps >= t0) & (table.time_gps <= t1)
            rms = 1e3 * np.degrees(np.sqrt(np.mean(table.sigma_rpy_rad[inside] ** 2, axis=0)))
            np.testing.assert_allclose(stated, rms, rtol=0.05)
        assert p.gil_sigma_mdeg[2] < 0.3 * p.gi_sigma_mdeg[2]  # heading: the planes' contribution
    # Those sigmas come from two variance components: the planes, and the navigation sensors with
    # the rest of the redundancy (rows - unknowns, exact); each scale its factor floored at 1.
    # The adjustments' reports read back into their type, to what the files hold.
    reports = {sol: read_adjustment_report(out / sol / "adjustment.json") for sol in ("gi", "gil")}
    for sol, report in reports.items():
        assert report.to_dict() == json.loads((out / sol / "adjustment.json").read_text()), sol
        assert report.t0_gps == typed.t0_gps and report.imu_errors is not None and report.frame is not None
    assert reports["gi"].solution == "G/I" and reports["gi"].lidar_time_offset is None
    assert reports["gil"].solution == "G/I/L" and reports["gil"].lidar_time_offset.sigma_ms > 0
    adj = reports["gil"].adjustment
    planes, navigation = adj["variance_components"]
    assert planes["groups"] == ["planes"] and "imu" in navigation["groups"] and "gnss" in navigation["groups"]
    assert planes["redundancy"] + navigation["redundancy"] == pytest.approx(adj["redundancy"], rel=1e-9)
    assert 0 < planes["redundancy_sd"] < 1e-3 * planes["redundancy"]
    for c in (planes, navigation):
        assert c["scale"] == pytest.approx(max(1.0, c["factor"])) and 0.3 < c["factor"] < 3.0, c
    # The feature tables hold the features that entered the adjustment; objects refer to their rows.
    last = metrics["outer_iterations"][-1]
    features = read_features(out / "features" / "features.csv")
    objects = read_objects(out / "features" / "objects.csv")
    assert last["features_used"] <= len(features) == objects.n_features.sum() < last["features"]
    assert len(objects) == last["objects"]
    assert np.all(objects.feature_object >= 0) and np.array_equal(np.bincount(objects.feature_object), objects.n_features)
    for strip in (1, 2):
        gi = pass_rmse(out / "gi" / "trajectory.sbet", project, strip)
        gil = pass_rmse(out / "gil" / "trajectory.sbet", project, strip)
        assert gil[2] <= 0.3 * gi[2], (strip, gi, gil)
        assert np.all(gil[:2] <= 1.1 * gi[:2]), (strip, gi, gil)
    # The point cloud: closer to the truth point by point, and the strips agree better. What is
    # left is the offset all strips share, the GNSS's: no plane observes it. (The mean distance to
    # the true surface is no measure of this: on this seed G/I's two strips lie 27 and 0.5 mm
    # above the truth, G/I/L's both 22 mm, and the mean distance is 18 against 21 mm.)
    gi_pts = run_georeference(project, out / "gi" / "trajectory.sbet", tmp_path / "gi_points")
    assert all(s.points_outside == 0 for s in gi_pts.strips)
    s_gi = compare_with_truth(tmp_path / "gi_points", project / "truth")["strip_median_m"]
    s_gil = compare_with_truth(out / "points", project / "truth")["strip_median_m"]
    e_gi, e_gil = _point_errors(tmp_path / "gi_points", project), _point_errors(out / "points", project)
    # Measured (mm): 3-D RMSE 103 -> 40, about the common offset 98 -> 6.3; strip median 27 -> 1.3.
    assert _rms3(e_gil) < 0.7 * _rms3(e_gi), (_rms3(e_gi), _rms3(e_gil))
    assert _rms3(e_gil - e_gil.mean(axis=0)) < 0.2 * _rms3(e_gi - e_gi.mean(axis=0)), (e_gi.mean(axis=0), e_gil.mean(axis=0))
    assert np.linalg.norm(e_gil.mean(axis=0)) < 0.1, e_gil.mean(axis=0)  # the GNSS's few centimetres
    assert s_gil < 0.2 * s_gi, (s_gi, s_gil)
    # A rerun resumes every step from out/.cache and writes the same products (in a copy: the
    # run is shared). The README ran it as `run tiny`, from the project's parent: the rerun names
    # the project by its absolute path, and the steps' keys do not depend on that.
    shutil.copytree(full_run, tmp_path / "again")
    out = tmp_path / "again"
    before = (out / "gil" / "trajectory.sbet").read_bytes()
    proc = subprocess.run([sys.executable, "-m", "georefine", "run", str(project), "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    again = json.loads((out / "metrics.json").read_text())
    n_outer = len(metrics["outer_iterations"])
    # The strip-adjustment baseline comes from the first outer iteration's planes, right after it.
    assert again["resumed"] == ["gi", "gil_1", "strip_baseline", *[f"gil_{i}" for i in range(2, n_outer + 1)],
                                "gil_features", "gil_posterior", "calibration_check", "points"]
    assert len(list((out / ".cache").glob("gil_features-*.pkl"))) == 1  # the last one only
    assert again["outer_iterations"] == metrics["outer_iterations"]
    assert (out / "gil" / "trajectory.sbet").read_bytes() == before


@pytest.fixture(scope="module")
def demo(project, full_run, gil_single_pass, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """A reduced `georefine demo` (the README example stands in for it: its project for the
    simulation, its run of both passes and its single-pass run for the demo's: their steps are
    in the demo's cache): its folder and its process (read only)."""
    from georefine.demo.lanes import demo_stamp

    out = make_output_folder(tmp_path_factory.mktemp("demo") / "demo")  # an earlier demo's folder, with its project
    shutil.copytree(project, out / "project")
    shutil.copytree(full_run / ".cache", out / ".cache")  # the same project and configuration: the same keys
    for f in (gil_single_pass / ".cache").glob("*.pkl"):
        if not (out / ".cache" / f.name).exists():
            shutil.copy(f, out / ".cache" / f.name)
    (out / "project" / "truth" / "demo.json").write_text(json.dumps(demo_stamp("corridor-tiny", README_SEED, [])))
    args = ["demo", "--out", str(out), "--scenario", "corridor-tiny", "--seed", str(README_SEED)]
    proc = subprocess.run([sys.executable, "-m", "georefine", *args], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "200"})
    return out, proc


@pytest.mark.slow
def test_demo_single_pass_and_report(demo, gil_single_pass):
    """The reduced demo's figures, files, log and report."""
    import html as _html

    from georefine.evaluation.report import summary_rows

    out, proc = demo
    assert proc.returncode == 0, proc.stderr
    assert "yaw RMSE" in proc.stdout and "report:" in proc.stdout and "AVG-SD" in proc.stdout
    # Off a terminal (`georefine demo > log 2>&1`) the stages are timestamped lines, kept in OUT/georefine.log too.
    stages = [line for line in proc.stderr.splitlines() if STAGE_LINE.match(line)]
    assert any(line.endswith("G/I/L posterior sigma: started") for line in stages), proc.stderr[-3000:]
    log = (out / "georefine.log").read_text().splitlines()
    assert all(line in log for line in stages) and "demo" in log[0]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["timings_s"]["simulate"] < 1.0  # reused
    assert "gil_posterior" in json.loads((out / "run" / "metrics.json").read_text())["resumed"]
    # metrics.json is the typed demo record, its evaluation that of summary.json (NaN aside: none here).
    from georefine.demo.corridor import DemoMetrics

    demo = DemoMetrics.from_dict(metrics)
    assert demo.to_dict() == metrics
    summary = json.loads((out / "run" / "evaluation" / "summary.json").read_text())
    assert RunEvaluation.from_dict(summary).to_dict() == summary == metrics["evaluation"]
    assert demo.run == WorkflowMetrics.read(out / "run" / "metrics.json")
    for rel in ("report.html", "metrics.json", "run/evaluation/attitude_differences.png",
                "run/evaluation/gi/strip_differences.png", "run/evaluation/gil/strip_differences.tif",
                "run/evaluation/gil/strip_differences_zoom.png",
                "run/evaluation/gil/reference_planes.csv", "run-single-pass/gil/trajectory.sbet"):
        assert (out / rel).is_file(), rel
    # The single pass shared the G/I adjustment with the full run (one step cache), and resumed
    # the steps of the shared single-pass run: the same project, configuration and options.
    single = json.loads((out / "run-single-pass" / "metrics.json").read_text())
    assert single["strips"] == [1] and single["resumed"][:2] == ["gi", "gil_1"]
    assert single["outer_iterations"] == json.loads((gil_single_pass / "metrics.json").read_text())["outer_iterations"]
    # --no-points: the trajectory is what counts, and no points/ folder is made for nothing
    assert not (out / "run-single-pass" / "points").exists()

    ev = metrics["evaluation"]
    traj = ev["trajectory"]
    gi1 = traj["G/I"]["strips"]["1"]
    one = traj["G/I/L single pass (strip 1)"]["strips"]["1"]
    assert one["yaw_rmse_mdeg"] <= 0.3 * gi1["yaw_rmse_mdeg"], (gi1, one)
    assert one["pitch_rmse_mdeg"] <= 1.1 * gi1["pitch_rmse_mdeg"], (gi1, one)
    # G/I/L makes the strips and views agree (paper 000: AVG-SD 10.1 -> 3.3 mm; Fig. 7).
    rp, sd = ev["reference_planes"], ev["strip_differences"]
    assert rp["G/I/L"]["n_observations"] == rp["G/I"]["n_observations"] == 36
    assert rp["G/I/L"]["avg_sd_m"] <= 0.5 * rp["G/I"]["avg_sd_m"]
    # The level reference surfaces as vertical check points, to ASPRS 2023 / NSSDA.
    va = rp["G/I/L"]["asprs_vertical"]
    assert 1 <= va["n_checkpoints"] <= 36 and va["rmse_v_m"] == pytest.approx(np.hypot(va["rmse_v1_m"], va["rmse_v2_m"]))
    assert va["nssda_vertical_95_m"] == pytest.approx(1.96 * va["rmse_v1_m"]) and va["rmse_h_m"] is None
    assert sd["G/I/L"]["p95_m"] < sd["G/I"]["p95_m"]
    # The report shows the figures of metrics.json.
    page = _html.unescape((out / "report.html").read_text())
    rows = summary_rows(demo.evaluation)
    single_all = traj["G/I/L single pass (strip 1)"]["all"]
    assert rows[2][4] == f"{single_all['yaw_rmse_mdeg']:.1f} (G/I {gi1['yaw_rmse_mdeg']:.1f})"  # beside G/I, strip 1
    for row in rows:
        assert "".join(f"<td>{c}</td>" for c in row) in page, row
    assert f"{rp['G/I/L']['avg_sd_m'] * 1e3:.1f}" in page and page.count("data:image/png;base64,") >= 4
    assert "Vertical accuracy to the standards" in page and f"{va['rmse_v_m'] * 1e3:.1f}" in page
    # The flight on a map first, then the adjustments' IMU errors against the simulated truth, with their plot.
    assert (out / "run" / "evaluation" / ev["overview_plot"]).is_file() and "The flight: the trajectory" in page
    assert sorted(ev["imu_errors"]) == ["G/I", "G/I/L"] and (out / "run" / "evaluation" / ev["imu_errors_plot"]).is_file()
    assert "IMU errors and boresight against the simulated truth" in page
    # The boresight calibration: stated 0.05 deg off in roll, recovered within 5 mdeg and shown against the truth.
    b = ev["boresight"]
    assert b["stated_deg"][0] - b["true_deg"][0] == pytest.approx(0.05) and abs(b["error_mdeg"][0]) < 5.0, b
    assert all(abs(e) < 3.0 * s for e, s in zip(b["error_mdeg"], b["sigma_mdeg"])), b
    assert "boresight calibration (started +50, +0, +0 mdeg off)" in proc.stdout
    assert f"<td>error (mdeg)</td><td>{b['error_mdeg'][0]:.1f}</td>" in page
    assert (out / "run-boresight" / "gil" / "adjustment.json").is_file()
    # Point density and strip overlap, from the same scan as the strip differences, in the overview.
    cov = ev["coverage"]["G/I/L"]
    assert 0.0 < cov["density_p5_per_m2"] <= cov["density_median_per_m2"] and 0.5 < cov["overlap_share"] <= 1.0
    gi = ev["coverage"]["G/I"]  # the same points, georeferenced twice: a few cross a cell's edge
    assert cov["max_strips"] == gi["max_strips"] == 2 and cov["area_km2"] == pytest.approx(gi["area_km2"], rel=1e-3)
    assert cov["overlap_share"] == pytest.approx(gi["overlap_share"], abs=2e-3)
    assert cov["density_median_per_m2"] == pytest.approx(gi["density_median_per_m2"], abs=1.0)
    assert all((out / "run" / "evaluation" / cov[k]).is_file() for k in ("density_map", "overlap_map"))
    assert "Points per m²" in page and f"{100 * cov['overlap_share']:.0f} %" in page


@pytest.mark.slow
@pytest.mark.skipif(chromium() is None, reason="headless Chromium is not installed (apt-get install chromium)")
def test_the_demo_report_reads_in_a_browser(demo, tmp_path):
    """The demo's report in headless Chromium at a laptop's window: every map at equal aspect, no
    image stretched, the smallest text of every figure readable as the page shows it."""
    out, proc = demo
    assert proc.returncode == 0, proc.stderr
    shown, shot = rendered_images(out / "report.html", tmp_path)
    check_rendered_images(shown, maps=("overview", "map", "G/I"))
    assert {"flight overview", "point density map", "strip overlap map"} <= {im["alt"] for im in shown}
    from PIL import Image

    pixels = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert pixels.shape == (WINDOW[1], WINDOW[0]) and pixels.std() > 10.0  # the page drew, not a blank window


@pytest.mark.slow
def test_a_single_pass_holds_the_time_offset_that_both_passes_estimate(full_run, gil_single_pass):
    """One strip cannot show a LiDAR time offset (it moves all its views alike): the single pass
    holds it where it started and says why; both passes, flown opposite ways, estimate it."""
    both = read_adjustment_report(full_run / "gil" / "adjustment.json").lidar_time_offset
    one = read_adjustment_report(gil_single_pass / "gil" / "adjustment.json").lidar_time_offset
    assert both.held is None and both.sigma_ms > 0
    assert one.held.startswith("one strip only") and one.sigma_ms is None
    assert one.estimate_s == one.configured_s
    last = json.loads((gil_single_pass / "metrics.json").read_text())["outer_iterations"][-1]
    assert last["time_offset_s"] == last["time_offset_start_s"] == one.configured_s


def test_rerun_resumes_unchanged_steps_and_recomputes_changed_ones(sparse_project, tmp_path):
    import os

    out = tmp_path / "out"
    first = run_workflow(sparse_project, out, lidar=False)
    assert first.metrics.resumed == ()
    # metrics.json is the result's typed record, and reads back to it.
    written = json.loads((out / "metrics.json").read_text())
    assert written == first.metrics.to_dict() and WorkflowMetrics.from_dict(written) == first.metrics
    assert first.metrics.strips == (1, 2) and first.metrics.outer_iterations == ()
    assert [(p.strip, p.file) for p in first.metrics.points] == [(1, "strip_1.laz"), (2, "strip_2.laz")]
    assert list(first.metrics.timings_s) == ["read", "filter", "gi_adjustment", "final_georeferencing"]
    sbet = (out / "gi" / "trajectory.sbet").read_bytes()
    again = run_workflow(sparse_project, out, lidar=False).metrics
    assert again.resumed == ("gi", "points") and again.points == first.metrics.points
    assert list(again.timings_s) == ["read", "gi_adjustment", "final_georeferencing"]  # no filter: resumed
    assert (out / "gi" / "trajectory.sbet").read_bytes() == sbet
    (out / "points" / "strip_2.laz").unlink()  # a lost product is written again
    assert run_workflow(sparse_project, out, lidar=False).metrics.resumed == ("gi",)
    assert (out / "points" / "strip_2.laz").is_file()
    assert run_workflow(sparse_project, out, lidar=False, resume=False).metrics.resumed == ()
    # A copy of the project (the same files, sizes and times) resumes from a copy of the run: the
    # steps' keys hold the inputs' names relative to the project, not where it lies.
    copy = tmp_path / "p"
    shutil.copytree(sparse_project, copy)
    out2 = tmp_path / "out2"
    shutil.copytree(out, out2)
    assert run_workflow(copy, out2, lidar=False).metrics.resumed == ("gi", "points")
    # A changed input invalidates its step and everything after it (file size and mtime).
    imu = copy / "imu" / "imu.csv"
    st = imu.stat()
    os.utime(imu, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert run_workflow(copy, out2, lidar=False).metrics.resumed == ()


def test_navigation_steps_run_while_the_scans_are_simulated(tmp_path):
    """`georefine demo`'s pipelining: steps 1-2 start from the simulator's callback, the run resumes them."""
    seen = []

    def start(root: Path) -> None:
        assert (root / "project.yaml").is_file() and (root / "imu" / "imu.csv").is_file()
        seen.append(not any((root / "scans").iterdir()))  # before any scan is written
        seen.append(precompute_gnss_imu(root, tmp_path / "cache"))

    project = tmp_path / "p"
    simulate_project("corridor-tiny", project, seed=8, on_navigation=start,
                     overrides=["scanner.pulse_rate_hz=3000", "scanner.line_rate_hz=60"])
    assert seen[0] is True and set(seen[1]) == {"filter", "gi_adjustment"}
    # The temporary folder was renamed; names relative to the project keep the cache valid.
    run = run_workflow(project, tmp_path / "run", lidar=False, points=False, cache_dir=tmp_path / "cache")
    assert run.metrics.resumed == ("gi",)


def test_points_outside_the_trajectory_are_counted_not_extrapolated(project):
    nav = load_navigation(project)
    sb = read_sbet(project / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800))
    truth = trajectory_from_sbet(sb, nav.frame, nav.t0_gps)
    # Small time tiles (a 50 MB budget): the strip is streamed in several tiles.
    cfg = nav.config
    scale = cfg.processing.scale.model_copy(update={"memory_budget_gb": 0.05, "min_tile_points": 200_000})
    nav = dataclasses.replace(nav, config=cfg.model_copy(
        update={"processing": cfg.processing.model_copy(update={"scale": scale})}))
    strips = read_strips(nav, [1])
    assert len(strips[0].tiles) >= 4
    t = read_las(strips[0].path).time_gps - nav.t0_gps
    t_cut = float(np.median(t))
    keep = truth.time <= t_cut
    short = Trajectory(truth.time[keep], truth.p_w_b[keep], truth.R_w_b[keep])
    features, counts = step_features(nav, short, strips)
    n_outside = int(np.count_nonzero((t < short.time[0]) | (t > short.time[-1])))
    assert counts.points_outside_trajectory == n_outside > 0.4 * t.size
    assert sum(counts.views.values()) == len(features)
    assert features.time.max() <= short.time[-1]


def test_a_strip_outside_the_trajectory_is_an_error_not_an_empty_file(sparse_project, tmp_path):
    from georefine.io.trajectory import write_sbet

    nav = load_navigation(sparse_project)
    sb = read_sbet(sparse_project / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800))
    t_end = float(read_las(sparse_project / "scans" / "strip_1.laz").time_gps.max()) + 5.0  # pass 1 only
    keep = sb.time_gps <= t_end
    short = dataclasses.replace(sb, **{f.name: getattr(sb, f.name)[keep] for f in dataclasses.fields(sb)})
    write_sbet(tmp_path / "pass1.sbet", short)
    proc = subprocess.run([sys.executable, "-m", "georefine", "georeference", str(sparse_project), "--trajectory",
                           str(tmp_path / "pass1.sbet"), "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    assert "strip_2.laz" in proc.stderr and "gps_time" in proc.stderr and "inside the trajectory" in proc.stderr
    assert messages(proc.stderr).strip().count("\n") == 0 and "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()


def test_strip_without_configured_scanner_channel_is_rejected(sparse_project, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(sparse_project, bad)
    las = laspy.read(bad / "scans" / "strip_2.laz")
    las.scanner_channel = np.full(len(las.points), 3, dtype=np.uint8)
    las.write(bad / "scans" / "strip_2.laz")
    proc = subprocess.run([sys.executable, "-m", "georefine", "run", str(bad), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "strip_2.laz" in proc.stderr and "scanner_channel" in proc.stderr
    assert not (tmp_path / "o" / "gil").exists()


def test_views_without_features_are_reported(sparse_project, tmp_path, caplog):
    nav = load_navigation(sparse_project)
    sb = read_sbet(sparse_project / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800))
    truth = trajectory_from_sbet(sb, nav.frame, nav.t0_gps)
    with caplog.at_level(logging.WARNING), pytest.raises(InputError, match="no planar features"):
        step_features(nav, truth, read_strips(nav))
    assert "channel 0 (nadir) gave no planar features" in caplog.text
    proc = subprocess.run([sys.executable, "-m", "georefine", "run", str(sparse_project), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "no planar features" in proc.stderr


def test_an_unknown_strip_id_names_the_parameter_and_the_cli_its_option(sparse_project, tmp_path):
    with pytest.raises(InputError, match="no strip with this id") as err:
        read_strips(load_navigation(sparse_project), [1, 99])
    assert err.value.field == "strips" and err.value.found == "99"
    proc = subprocess.run([sys.executable, "-m", "georefine", "run", str(sparse_project), "--out", str(tmp_path / "o"),
                           "--strips", "99", "--no-lidar"], capture_output=True, text=True)
    assert proc.returncode == 2 and "--strips" in proc.stderr and "99" in proc.stderr, proc.stderr


def test_only_a_first_outer_iteration_that_others_follow_takes_coarse_knots():
    from georefine.config import LidarAdjustmentConfig as Lidar
    from georefine.workflows.run_parts import outer_knot_interval

    assert outer_knot_interval(Lidar(), 0.1, 1) == 0.25 and outer_knot_interval(Lidar(), 0.1, 2) is None
    assert outer_knot_interval(Lidar(outer_iterations=1), 0.1, 1) is None  # the only one is the result
    assert outer_knot_interval(Lidar(first_knot_interval_s=None), 0.1, 1) is None
    assert outer_knot_interval(Lidar(first_knot_interval_s=0.1), 0.1, 1) is None  # not coarser
    assert outer_knot_interval(Lidar(), 0.5, 1) is None
    assert outer_knot_interval(Lidar(first_knot_interval_s=0.5), 0.1, 1) == 0.5
    assert outer_knot_interval(Lidar(), 0.1, 1, vibrating=True) is None  # the vibration would alias


def test_outer_iterations_that_do_not_converge_are_reported_with_their_figures(caplog):
    """The last allowed outer iteration still moving the trajectory is a warning with the changes, not silence."""
    from georefine.config import LidarAdjustmentConfig
    from georefine.io.run_metrics import OuterIteration
    from georefine.workflows.outer_checks import outer_converged, warn_unconverged

    lcfg = LidarAdjustmentConfig(outer_iterations=3)
    moving = [OuterIteration(k, 15_555_953, 57_841, 200_000, 56_725, change, 3e-4, 0, {})
              for k, change in ((1, 57.7), (2, 2.6), (3, 2.43))]
    with caplog.at_level(logging.WARNING, logger="georefine.workflows.outer_checks"):
        warn_unconverged(moving, lcfg)
    text = caplog.text
    assert "did not converge" in text and "2.43 mdeg" in text and "57.70 mdeg, 2.60 mdeg" in text
    assert "200,000 of 15,555,953" in text and "processing.lidar.max_features, max_features_per_minute" in text
    caplog.clear()
    settled = [*moving[:2], dataclasses.replace(moving[2], attitude_change_mdeg=0.9)]
    assert outer_converged(settled[-1], lcfg) and not outer_converged(moving[-1], lcfg)
    with caplog.at_level(logging.WARNING, logger="georefine.workflows.outer_checks"):
        warn_unconverged(settled, lcfg)
    assert caplog.text == ""
    # One outer iteration configured: no convergence test asked for, so no warning; the change is logged.
    with caplog.at_level(logging.INFO, logger="georefine.workflows.outer_checks"):
        warn_unconverged(moving[:1], LidarAdjustmentConfig(outer_iterations=1))
    assert [r.levelno for r in caplog.records] == [logging.INFO] and "57.70 mdeg" in caplog.text


def _gps_seconds(las) -> np.ndarray:
    """GPS seconds of a file laspy read: adjusted standard time (the global encoding's bit) plus 1e9."""
    adjusted = int(las.header.global_encoding.gps_time_type) == 1
    return np.asarray(las.gps_time) + (1e9 if adjusted else 0.0)


@pytest.mark.slow
def test_a_points_identifier_leads_to_its_scan_return(project, full_run, tmp_path):
    """ULPI values (record numbers across the run's point files) lead to the scan records behind
    them: time and scanner-frame vector as laspy reads them from the scan file. A cloud that is not
    every record of its scans in order is refused, naming the file."""
    from georefine.workflows.returns import returns_of_points

    points = sorted((full_run / "points").glob("strip_*.laz"))
    scans = sorted((project / "scans").glob("strip_*.laz"))
    counts = [laspy.open(p).header.point_count for p in points]
    rng = np.random.default_rng(5)
    ids = np.r_[rng.integers(0, sum(counts), 500), 0, counts[0] - 1, counts[0], sum(counts) - 1, 17, 17]
    ret = returns_of_points(points, scans, ids)
    # The points carry the time offset the run estimated (one constant), the scans their own times.
    estimate = json.loads((full_run / "gil" / "adjustment.json").read_text())["lidar_time_offset"]["estimate_s"]
    assert ret.offset_s == pytest.approx({1: estimate, 2: estimate}, abs=1e-6)
    start = np.r_[0, np.cumsum(counts)]
    for f, (pts, scan) in enumerate(zip(points, scans)):
        mine = (ids >= start[f]) & (ids < start[f + 1])
        rec = ids[mine] - start[f]
        las, pl = laspy.read(scan), laspy.read(pts)
        np.testing.assert_array_equal(ret.record[mine], rec)
        assert np.all(ret.strip_id[mine] == pl.point_source_id[0])
        np.testing.assert_array_equal(ret.time_gps[mine], _gps_seconds(pl)[rec])
        np.testing.assert_allclose(ret.time_gps[mine] - _gps_seconds(las)[rec], estimate, atol=1e-6)
        np.testing.assert_array_equal(ret.x_s[mine], np.column_stack([las.x, las.y, las.z])[rec])
        np.testing.assert_array_equal(ret.channel[mine], np.asarray(las.scanner_channel)[rec])
    # A strip without its first record, and one in another order, are not their scans.
    pl = laspy.read(points[0])
    short = tmp_path / "short.las"  # uncompressed: quicker to write
    pl[1:].write(short)
    with pytest.raises(InputError, match="does not hold every record") as err:
        returns_of_points([short], scans, [3])
    assert str(short) in str(err.value)
    swapped = tmp_path / "swapped.las"
    order = np.arange(counts[0])
    order[[10, 20]] = [20, 10]
    pl[order].write(swapped)
    returns_of_points([swapped], scans, [9, 11])  # records the swap left alone
    with pytest.raises(InputError, match="not its scan's") as err:
        returns_of_points([swapped], scans, [9, 10])
    assert "record 11" in str(err.value) and "gps_time" in str(err.value)
    with pytest.raises(InputError, match="outside the cloud"):
        returns_of_points(points, scans, [sum(counts)])
    with pytest.raises(InputError, match="no scan file"):
        returns_of_points(points[1:], scans[:1], [0])
