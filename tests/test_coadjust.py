"""Lidargrammetric co-adjustment end to end on a small `block` (paper 004, cases 1-3)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from georefine.io import photos
from georefine.io.colmap import block_from_reconstruction, read_model
from georefine.lidargrammetry.crosscheck import solve_both
from georefine.pipeline.lidar import run_workflow
from georefine.pipeline.lidargrammetry import run_coadjust
from georefine.sim.scenarios import simulate_project

# The default camera and GSD (8 cm) over a shorter town (3 photos per strip), a lighter scanner.
SMALL = ["scene.length_m=260", "scanner.pulse_rate_hz=50000", "scanner.line_rate_hz=100"]
GSD = 0.08


@pytest.fixture(scope="module")
def block(tmp_path_factory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("coadjust")
    project = base / "p"
    simulate_project("block", project, seed=11, overrides=SMALL)
    run_workflow(project, base / "gi", lidar=False)  # the jammed G/I cloud
    return project, base / "gi" / "points"


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
def test_case_1_refines_the_jammed_cloud(block, tmp_path):
    project, cloud = block
    _, m = run_coadjust(project, [cloud], tmp_path / "c1", 1)
    assert m["control_points"]["reprojection_px"] <= 0.5 and m["check_points"]["reprojection_px"] <= 0.5
    assert m["photo_lidargram_matches"]["median"] >= 15
    covered = {f.name: np.asarray(laspy.read(f).lidargrams) >= 0 for f in (tmp_path / "c1" / "points").glob("*.laz")}
    before = _cloud_error(cloud, project / "truth", covered)  # inside the photo block
    after = _cloud_error(tmp_path / "c1" / "points", project / "truth", covered)
    print(f"case 1 cloud: {before:.3f} -> {after:.3f} m ({after / before:.2f}x)")
    assert after < 0.8 * before, (before, after)
    # The exported COLMAP model opens in pycolmap, and COLMAP's bundle adjuster on its tie problem
    # (photos fixed) reaches the reprojection error of Georefine's engine on the same problem.
    b = block_from_reconstruction(read_model(tmp_path / "c1" / "colmap"))
    is_lg = np.array([name.startswith("LG_") for name in b.names])
    assert len(b.names) == m["photos"] + m["lidargrams"] and is_lg.sum() == m["lidargrams"]
    ours, theirs = solve_both(b, ~is_lg)
    assert theirs.re_px == pytest.approx(ours.re_px, rel=0.05), (ours.re_px, theirs.re_px)
    assert ours.re_px <= 0.5
    eop = photos.read_eop(tmp_path / "c1" / "eop_lidargrams.csv")
    assert len(eop) == m["lidargrams"] and (tmp_path / "c1" / "matches_lidargram_photo.png").is_file()
    saved = json.loads((tmp_path / "c1" / "metrics.json").read_text())
    assert saved["check_points"] == m["check_points"] and saved["reintersection"]["points"] > 0


@pytest.mark.slow
def test_case_3_orients_the_photos_on_the_lidar_without_control(block, tmp_path):
    project, cloud = block
    # Case 3 takes the LiDAR as control: use the true cloud (the paper's "refined a priori").
    _, m = run_coadjust(project, [project / "truth"], tmp_path / "c3", 3)
    chk = m["check_points"]
    assert m["control_points"] is None and chk["n"] == 18
    assert chk["reprojection_px"] <= 0.5
    # SIFT on this small block: within 1.5 GSD horizontally and 2 GSD vertically (the benchmark
    # on the full block with XFeat is held to the paper's 1 and 2 GSD, BENCHMARKS.md).
    assert max(chk["rmse_x_m"], chk["rmse_y_m"]) <= 1.5 * GSD and chk["rmse_z_m"] <= 2 * GSD, chk
    assert not (tmp_path / "c3" / "points").exists()


def test_coadjust_refuses_a_project_without_photos(tmp_path):
    project = tmp_path / "p"
    simulate_project("corridor-tiny", project, seed=2, overrides=["scanner.pulse_rate_hz=2000"])
    proc = subprocess.run([sys.executable, "-m", "georefine", "coadjust", str(project), "--points",
                           str(project / "truth"), "--out", str(tmp_path / "o"), "--case", "1"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "project.yaml" in proc.stderr and "has no photos" in proc.stderr, proc.stderr


@pytest.mark.slow
def test_lidargrams_command_writes_loadable_lidargrams(block, tmp_path):
    from georefine.lidargrammetry.render import load_lidargram

    project, cloud = block
    proc = subprocess.run([sys.executable, "-m", "georefine", "lidargrams", str(project), "--points", str(cloud),
                           "--out", str(tmp_path / "lg")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    npz = sorted((tmp_path / "lg").glob("*.npz"))
    assert npz and len(npz) == len(list((tmp_path / "lg").glob("*.png")))
    cam = photos.read_cameras(project / "photos" / "cameras.yaml")["camera"].scaled(0.5)
    lg = load_lidargram(tmp_path / "lg", npz[0].stem, cam)
    assert (lg.ulpi >= 0).mean() > 0.3 and np.all(np.diff(lg.point_index) > 0)
