"""GNSS/IMU trajectory estimation end to end on simulated truth (workflow steps 1-2).

Accuracy windows, consistency of the posterior sigma, recovery of the IMU errors, a GNSS
outage, multipath jumps, and bad input. The corridor runs are marked slow (CI runs them).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from cli_helpers import run_georefine as _georefine
from georefine.evaluation.trajectory import consistency
from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.io.run_metrics import read_adjustment_report
from georefine.io.trajectory import read_sbet, read_sbet_companion, read_smrmsg
from georefine.io.trajectory_csv import read_trajectory_csv
from georefine.sim.scenarios import simulate_project
from georefine.workflows import load_navigation, run_trajectory

FAST_SCAN = ["scanner.pulse_rate_hz=2000", "scanner.line_rate_hz=100"]  # the navigation data do not depend on the scanner


def _errors_against_truth(out: Path, project: Path):
    cmp = compare_sbet_files(out / "trajectory.sbet", project / "truth" / "trajectory.sbet")
    return cmp, cmp.stats


def _z_scores(out: Path, project: Path) -> dict[str, np.ndarray]:
    """(estimate - truth) / sigma of the biases at their knots and of the scale factors."""
    rep = json.loads((out / "adjustment.json").read_text())
    e, t0 = rep["imu_errors"], rep["t0_gps"]
    truth = np.load(project / "truth" / "imu_errors.npz")
    tb = np.asarray(e["bias_knot_times_s"]) + t0
    z = {}
    for key, tkey, f in (("acc_bias_ug", "bias_acc", 1 / 9.80665e-6), ("gyro_bias_deg_per_h", "bias_gyro", 180 / np.pi * 3600)):
        true = np.column_stack([np.interp(tb, truth["time_gps"], truth[tkey][:, i]) for i in range(3)]) * f
        sig_key = key.replace("_ug", "_sigma_ug").replace("_deg_per_h", "_sigma_deg_per_h")
        z[key] = (np.asarray(e[key]) - true) / np.asarray(e[sig_key])
    for key, tkey in (("acc_scale_ppm", "scale_acc"), ("gyro_scale_ppm", "scale_gyro")):
        z[key] = (np.asarray(e[key]) - truth[tkey] * 1e6) / np.asarray(e[key.replace("_ppm", "_sigma_ppm")])
    return z


def _white_gnss_copy(project: Path, out: Path) -> Path:
    """``project`` with ``gnss.correlated_error: null`` (every epoch's error white, as the filter has it)."""
    shutil.copytree(project, out, symlinks=True)
    cfg = yaml.safe_load((out / "project.yaml").read_text())
    cfg["gnss"]["correlated_error"] = None
    (out / "project.yaml").write_text(yaml.safe_dump(cfg))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1])  # seeds 42, 2, 3: BENCHMARKS.md (the default corridor's G/I)
def test_gnss_imu_adjustment_on_the_corridor(seed, tmp_path):
    project = tmp_path / "corridor"
    simulate_project("corridor", project, seed=seed, overrides=FAST_SCAN)
    gi = run_trajectory(project, tmp_path / "gi")
    assert gi.adjustment.solve.converged
    cmp, s = _errors_against_truth(tmp_path / "gi", project)
    if seed == 1:  # the model comparisons on one seed (each is two more runs of steps 1-2)
        run_trajectory(project, tmp_path / "filter", filter_only=True)
        run_trajectory(_white_gnss_copy(project, tmp_path / "white"), tmp_path / "gi_white")
        _, f = _errors_against_truth(tmp_path / "filter", project)
        _, w = _errors_against_truth(tmp_path / "gi_white", project)
        # With white GNSS errors, as the filter models them, the batch adjustment and the RTS
        # smoother use the same information: the adjustment must not be worse in any angle (2 % +
        # 0.05 mdeg for rounding of two near-optimal estimates).
        for angle in ("roll", "pitch", "yaw"):
            assert w[f"{angle}_rmse_mdeg"] <= 1.02 * f[f"{angle}_rmse_mdeg"] + 0.05, (angle, w, f)
        # The correlated GNSS error estimated (the default) gives the white part its weight: yaw
        # improves by 11 % over seeds 42 and 1-3 (measured 22.2/23.9/14.9/17.4 against
        # 26.2/21.9/19.1/20.9 mdeg), this seed the one 9 % worse; roll and pitch change by a few %.
        assert s["yaw_rmse_mdeg"] <= 1.15 * w["yaw_rmse_mdeg"], (s, w)
        for angle in ("roll", "pitch"):
            assert s[f"{angle}_rmse_mdeg"] <= 1.1 * w[f"{angle}_rmse_mdeg"], (angle, s, w)
    # Heading is the weak angle of straight corridor flight (paper 000): the largest error.
    assert s["yaw_rmse_mdeg"] > max(s["roll_rmse_mdeg"], s["pitch_rmse_mdeg"])
    assert s["roll_rmse_mdeg"] < 10 and s["pitch_rmse_mdeg"] < 10 and s["yaw_rmse_mdeg"] < 60

    # Position: within 1.5x the simulated GNSS noise (3-D, from the reported standard deviations).
    sc = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["scenario"]["gnss"]
    gnss_3d = np.sqrt(
        sc["sigma_north_m"] ** 2 + sc["sigma_east_m"] ** 2 + sc["sigma_up_m"] ** 2
        + 2 * sc["gm_sigma_horizontal_m"] ** 2 + sc["gm_sigma_up_m"] ** 2
    )
    assert s["3d_rmse_m"] <= 1.5 * gnss_3d

    # Consistency: the posterior sigma describe the actual errors.
    table = read_trajectory_csv(tmp_path / "gi" / "trajectory.csv")
    ratio = consistency(cmp, table.sigma_rpy_rad, table.time_gps)
    # The heading sigma is pessimistic: RMS of error/sigma 0.46-0.72 over seeds 42 and 1-3 (0.56-0.79
    # with white GNSS epochs, whose yaw errors are 11 % larger under the same sigma); 0.45 is the
    # lower bound until the cause is found.
    assert np.all((ratio > 0.45) & (ratio < 2.0)), ratio
    # ... the position's too, now that the GNSS error that lasts minutes is in the model (with
    # white epochs the sigma was ten times optimistic: 3 mm against 3 cm).
    t = cmp.t0_gps + cmp.time
    sig = np.column_stack([np.interp(t, table.time_gps, table.sigma_xyz_m[:, i]) for i in (1, 0, 2)])  # N, E, up
    z_pos = np.sqrt(np.mean((cmp.d_ned_m / sig) ** 2, axis=0))
    assert np.all((z_pos > 0.4) & (z_pos < 2.0)), z_pos

    # IMU errors recovered within 3 sigma. The biases are ~60 knots x 3 axes of a random walk:
    # for Gaussian errors 0.3 % of them exceed 3 sigma, so the bias test allows 2 % beyond 3
    # sigma and requires a consistent RMS of the normalised errors; scale factors: all within 3.
    for key, z in _z_scores(tmp_path / "gi", project).items():
        if "scale" in key:
            assert np.max(np.abs(z)) < 3.0, (key, z)
        else:
            assert np.mean(np.abs(z) > 3.0) <= 0.02, (key, z)
            assert 0.2 < np.sqrt(np.mean(z**2)) < 1.5, (key, z)

    rep = json.loads((tmp_path / "gi" / "adjustment.json").read_text())
    assert {g["name"] for g in rep["adjustment"]["groups"]} >= {"gnss", "imu", "gnss_error_prior"}
    # The report reads back into its type (the trajectory command's: with the filter and the frame).
    typed = read_adjustment_report(tmp_path / "gi" / "adjustment.json")
    assert typed.to_dict() == rep and typed.solution == "G/I" and typed.filter.gnss_updates > 0
    assert typed.frame is not None and typed.gnss_error is not None and typed.lidar_time_offset is None
    if seed == 1:  # the filter alone: no adjustment
        assert read_adjustment_report(tmp_path / "filter" / "adjustment.json").adjustment is None
    # The posterior's variance components: in the G/I one, the navigation sensors (GNSS, IMU, priors,
    # random walks), with the adjustment's redundancy and its variance factor floored at 1.
    (comp,) = rep["adjustment"]["variance_components"]
    a = rep["adjustment"]
    assert set(comp["groups"]) == {g["name"] for g in a["groups"]}
    assert comp["redundancy"] == a["redundancy"] and comp["redundancy_sd"] == 0.0
    assert comp["scale"] == pytest.approx(max(1.0, a["variance_factor"]), rel=1e-9)
    # The estimated GNSS error against the simulated one at its knots (north, east, down -> east, north,
    # up). The simulated error holds its white part too (1/1/2 cm), so the window is loose.
    ge, truth = rep["gnss_error"], np.load(project / "truth" / "gnss_errors.npz")
    tk = np.asarray(ge["knot_times_s"]) + rep["t0_gps"]
    ned = np.column_stack([np.interp(tk, truth["time_gps"], truth["error_ned"][:, i]) for i in range(3)])
    inside = (tk > truth["time_gps"][0]) & (tk < truth["time_gps"][-1])
    z_gnss = ((np.asarray(ge["enu_m"]) - np.column_stack([ned[:, 1], ned[:, 0], -ned[:, 2]])) / np.asarray(ge["enu_sigma_m"]))[inside]
    assert 0.3 < np.sqrt(np.mean(z_gnss**2)) < 2.0, np.sqrt(np.mean(z_gnss**2, axis=0))
    assert 0.8 < rep["adjustment"]["variance_factor"] < 1.25
    # Started from the smoother with little damping, the near-linear G/I converges in a few steps
    # (with the solver's general 1e-4 it crept along the heading for 9: docs/ARCHITECTURE.md §4.4).
    assert rep["adjustment"]["iterations"] <= 4, rep["adjustment"]["cost_history"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("gi") / "tiny"
    simulate_project("corridor-tiny", out, seed=21, overrides=FAST_SCAN)
    return out


def _pass_span(project: Path, strip: int = 1) -> tuple[float, float]:
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    p = next(p for p in truth["passes"] if p["strip_id"] == strip)
    return p["t_start_s"], p["t_end_s"]


@pytest.mark.slow
def test_gnss_outage_of_30_s_is_bridged(tmp_path):
    t0, t1 = 100.0, 130.0  # inside the first pass of corridor-tiny (94 .. 150 s)
    project = tmp_path / "outage"
    simulate_project("corridor-tiny", project, seed=21, overrides=FAST_SCAN + [f"gnss.outages=[[{t0}, {t1}]]"])
    assert _pass_span(project)[0] < t0 and t1 < _pass_span(project)[1]
    run_trajectory(project, tmp_path / "gi")
    cmp, s = _errors_against_truth(tmp_path / "gi", project)
    rel = cmp.time_gps - load_navigation(project).t0_gps
    in_gap = (rel > t0) & (rel < t1)
    assert in_gap.sum() > 1000
    horizontal = np.linalg.norm(cmp.d_ned_m[in_gap, :2], axis=1)
    assert horizontal.max() < 0.25, horizontal.max()  # MEMS IMU over 30 s: centimetres to decimetres
    assert np.degrees(np.abs(cmp.d_rph_rad[in_gap]).max()) < 0.1  # no divergence of the attitude
    assert s["3d_rmse_m"] < 0.1


@pytest.mark.slow
def test_multipath_jumps_do_not_move_the_solution_elsewhere(tiny, tmp_path, caplog):
    with caplog.at_level("INFO", logger="georefine.adjustment.upsampling"):
        clean = run_trajectory(tiny, tmp_path / "clean")
    # A smooth platform: the up-sampled readings are sensor noise and the re-solve is skipped.
    assert any("no re-solve" in r.getMessage() for r in caplog.records)
    assert clean.adjustment.high_rate is not None
    # Copy the project and put 1 m jumps into a few epochs of the .pos file.
    jumped = tmp_path / "jumped"
    shutil.copytree(tiny, jumped, ignore=shutil.ignore_patterns("*.laz"))
    pos = jumped / "gnss" / "rover.pos"
    lines = pos.read_text().splitlines()
    data = [i for i, l in enumerate(lines) if not l.startswith("%")]
    rng = np.random.default_rng(5)
    bad = sorted(rng.choice(np.arange(200, len(data) - 200), size=6, replace=False))
    for k in bad:
        f = lines[data[k]].split()
        f[4] = f"{float(f[4]) + 1.0:.4f}"  # height +1 m
        lines[data[k]] = "  ".join(f)
    pos.write_text("\n".join(lines) + "\n")
    jump = run_trajectory(jumped, tmp_path / "jump")
    nav = load_navigation(jumped)
    t_jumps = nav.gnss.gnss_time[np.asarray(bad)]
    tk = clean.adjustment.spline.grid.knot_times
    far = np.min(np.abs(tk[:, None] - t_jumps[None, :]), axis=1) > 2.0
    p_clean, _ = clean.adjustment.spline.pose(tk[far])
    p_jump, _ = jump.adjustment.spline.pose(tk[far])
    assert np.abs(p_jump - p_clean).max() < 0.01
    gstats = jump.adjustment.solve.group("gnss")
    assert gstats.n_downweighted >= len(bad)


# ------------------------------------------------------------------------------ bad input




def _nav_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.laz", "truth"))
    return dst


def _project_copy(src: Path, dst: Path) -> Path:
    """The inputs with the (small) scans, for ``georefine check``; no truth."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("truth"))
    return dst


def test_non_overlapping_gnss_and_imu_is_an_error(tiny, tmp_path):
    p = _nav_copy(tiny, tmp_path / "p")
    csv = p / "imu" / "imu.csv"
    lines = csv.read_text().splitlines()
    out = [lines[0]]
    for l in lines[1:]:
        t, rest = l.split(",", 1)
        out.append(f"{float(t) + 86400.0:.9f},{rest}")
    csv.write_text("\n".join(out) + "\n")
    run = _georefine("trajectory", str(p), "--out", str(tmp_path / "o"))
    assert run.returncode == 2
    assert "imu.csv" in run.stderr and "do not overlap" in run.stderr


def test_imu_gap_longer_than_max_gap_s_is_an_error_in_check_and_run(tiny, tmp_path):
    p = _project_copy(tiny, tmp_path / "p")
    csv = p / "imu" / "imu.csv"
    lines = csv.read_text().splitlines()
    del lines[5001:6201]  # 6 s of samples, more than imu.max_gap_s (5 s) bridges
    csv.write_text("\n".join(lines) + "\n")
    for cmd in (["check", str(p)], ["trajectory", str(p), "--out", str(tmp_path / "o")]):
        run = _georefine(*cmd)
        assert run.returncode == 2, (cmd, run.stderr)
        # The first sample after the gap: file line 5002 (header on line 1, lines 5002-6201 removed).
        assert "imu.csv" in run.stderr and "gap" in run.stderr and "line 5002" in run.stderr, run.stderr
        assert "imu.max_gap_s" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_dropped_imu_samples_and_a_short_gap_are_bridged(tiny, tmp_path):
    """A sample dropped every 10 s and a 0.5 s gap in the first pass: G/I as good as on the whole record."""
    p = _project_copy(tiny, tmp_path / "p")
    csv = p / "imu" / "imu.csv"
    lines = csv.read_text().splitlines()
    header, body = lines[0], lines[1:]
    t0, t1 = _pass_span(tiny)
    start = int(round((0.5 * (t0 + t1)) * 200.0))  # mid-pass (the IMU starts at the dataset epoch, 200 Hz)
    keep = np.ones(len(body), bool)
    keep[1000::2000] = False
    keep[start:start + 100] = False
    csv.write_text("\n".join([header] + [l for l, k in zip(body, keep) if k]) + "\n")

    check = _georefine("check", str(p))
    assert check.returncode == 0, check.stderr
    n_gaps = int(keep[1000::2000].size - keep[1000::2000].sum()) + 1
    assert f"{n_gaps} IMU sampling gaps bridged" in check.stdout and "the longest 0.505 s" in check.stdout
    clean = run_trajectory(tiny, tmp_path / "clean")
    gapped = run_trajectory(p, tmp_path / "gapped")
    assert gapped.adjustment.solve.converged
    nav = load_navigation(p)
    assert nav.imu.time_gps.size == len(body)  # bridged back onto the full grid
    window = (t0 + 1.0, t1 - 1.0)
    rms = {}
    for name in ("clean", "gapped"):
        cmp, _ = _errors_against_truth(tmp_path / name, tiny)
        rel = cmp.time_gps - nav.t0_gps
        sel = (rel > window[0]) & (rel < window[1])
        rms[name] = np.degrees(np.sqrt(np.mean(cmp.d_rph_rad[sel] ** 2, axis=0))) * 1e3
        if name == "gapped":  # in and right after the 0.5 s gap: no jump in the attitude
            near = (rel > start / 200.0 - 1.0) & (rel < start / 200.0 + 2.0)
            gap_err = np.degrees(np.abs(cmp.d_rph_rad[near]).max(axis=0)) * 1e3
    assert np.all(rms["gapped"] <= 1.1 * rms["clean"] + 0.1), rms  # roll, pitch, yaw within 10 % (+0.1 mdeg)
    assert np.all(gap_err < 3.0 * rms["clean"] + 1.0), (gap_err, rms)
    assert gapped.adjustment.solve.n_observations == clean.adjustment.solve.n_observations


def test_check_lists_a_gnss_outage(tmp_path):
    project = tmp_path / "outage"
    simulate_project("corridor-tiny", project, seed=21, overrides=FAST_SCAN + ["gnss.outages=[[100.0, 160.0]]"])
    run = _georefine("check", str(project))
    assert run.returncode == 0, run.stderr
    assert "1 GNSS gaps" in run.stdout and re.search(r"the longest 60\.\d s", run.stdout), run.stdout


def test_out_naming_a_file_is_one_line_and_exit_2(tiny, tmp_path):
    f = tmp_path / "results"
    f.write_text("keep")
    for cmd in (["trajectory", str(tiny)], ["run", str(tiny)], ["demo"]):
        for out in (f, f / "sub"):
            run = _georefine(*cmd, "--out", str(out))
            assert run.returncode == 2, (cmd, run.stderr)
            assert run.stderr.strip().count("\n") == 0 and "Traceback" not in run.stderr, run.stderr
            assert "output path is not a folder" in run.stderr and f"a file at {f}" in run.stderr
    assert f.read_text() == "keep"


def test_pos_without_fix_quality_is_an_error(tiny, tmp_path):
    p = _nav_copy(tiny, tmp_path / "p")
    pos = p / "gnss" / "rover.pos"
    lines = pos.read_text().splitlines()
    for i, l in enumerate(lines):
        if not l.startswith("%"):
            f = l.split()
            f[5] = "5"  # single point positioning everywhere
            lines[i] = "  ".join(f)
    pos.write_text("\n".join(lines) + "\n")
    run = _georefine("trajectory", str(p), "--out", str(tmp_path / "o"))
    assert run.returncode == 2
    assert "rover.pos" in run.stderr and "quality" in run.stderr and "Q" in run.stderr


def test_trajectory_cli_writes_products(tiny, tmp_path):
    run = _georefine("trajectory", str(tiny), "--out", str(tmp_path / "o"), "--filter-only")
    assert run.returncode == 0, run.stderr
    for name in ("trajectory.sbet", "trajectory.csv", "adjustment.json", "config.resolved.yaml"):
        assert (tmp_path / "o" / name).is_file()
    report = read_adjustment_report(tmp_path / "o" / "adjustment.json")  # the filter alone: no adjustment
    assert report.solution == "filter" and report.adjustment is None and report.filter.gnss_updates > 0
    _, s = _errors_against_truth(tmp_path / "o", tiny)
    assert s["3d_rmse_m"] < 0.1 and s["roll_rmse_mdeg"] < 20
    # The SBET's body specific force and angular rate are the corrected IMU readings: they match
    # the true ones up to the sensor noise of one sample (not zeros, not raw biased readings).
    est = read_sbet(tmp_path / "o" / "trajectory.sbet")
    tru = read_sbet(tiny / "truth" / "trajectory.sbet", gps_week=int(est.time_gps[0] // 604800))
    common, ie, it = np.intersect1d(np.round(est.time_gps, 4), np.round(tru.time_gps, 4), return_indices=True)
    assert common.size > 0.9 * est.time_gps.size
    df = est.accel_b[ie] - tru.accel_b[it]
    dw = est.angular_rate_b[ie] - tru.angular_rate_b[it]
    assert np.sqrt(np.mean(df**2)) < 0.05 and np.abs(np.mean(df, axis=0)).max() < 2e-3  # m/s^2
    assert np.sqrt(np.mean(dw**2)) < 2e-3 and np.abs(np.mean(dw, axis=0)).max() < 2e-5  # rad/s
    # Seconds of the GPS week, the week in trajectory.sbet.json; the filter's sigma in the smrmsg file.
    assert np.fromfile(tmp_path / "o" / "trajectory.sbet", "<f8", count=1)[0] < 604800.0
    companion = read_sbet_companion(tmp_path / "o" / "trajectory.sbet")
    assert companion.gps_week == int(est.time_gps[0] // 604800) and companion.output_epsg == 25832
    acc = read_smrmsg(tmp_path / "o" / companion.accuracy_file, gps_week=companion.gps_week)
    table = read_trajectory_csv(tmp_path / "o" / "trajectory.csv")
    np.testing.assert_allclose(acc.time_gps, table.time_gps, rtol=0, atol=1e-6)
    # north, east, down against the CSV's x (east), y (north), z: equal up to the angle the flight spans at
    # the Earth's centre (w's axes are those of its reference point) and the CSV's rounding
    np.testing.assert_allclose(acc.sigma_ned_m[:, [1, 0, 2]], table.sigma_xyz_m, rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(acc.sigma_rph_rad, table.sigma_rpy_rad, rtol=1e-4, atol=1e-9)
    common, ie, it = np.intersect1d(np.round(est.time_gps, 4), np.round(acc.time_gps, 4), return_indices=True)
    _, je, jt = np.intersect1d(np.round(est.time_gps[ie], 4), np.round(tru.time_gps, 4), return_indices=True)
    dv = est.velocity_ned()[ie][je] - tru.velocity_ned()[jt]
    z = np.sqrt(np.mean((dv / acc.sigma_velocity_ned_m_s[it][je]) ** 2, axis=0))
    assert np.all((z > 0.5) & (z < 2.0)), z  # the velocity sigma describe the velocity errors (measured 0.95-0.98)
    run = _georefine("trajectory", str(tiny), "--out", str(tiny / "inside"))
    assert run.returncode == 2 and "project folder" in run.stderr
