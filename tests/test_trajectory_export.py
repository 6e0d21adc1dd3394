"""`georefine export trajectory` (TUM for evo, trajectopy's format) and the trajectory products
beside an SBET (companion file with the GPS week, smrmsg accuracy file).

Two trajectories are written with the run's own product writer (``write_sbet_product``): a
smooth flight as the reference and the same flight with correlated position (a few cm) and
attitude (a few mdeg) errors as the estimate. Where the tools are installed, their readers and
absolute-error figures (without alignment) are compared with ``georefine evaluate trajectory``:

* evo: ``evo_ape`` found on the PATH (``shutil.which``), run as ``evo_ape tum REF EST`` for the
  translation and ``-r angle_deg`` for the rotation angle;
* trajectopy: the Python interpreter named by the environment variable
  ``GEOREFINE_TRAJECTOPY_PYTHON`` (e.g. a virtual environment with ``pip install trajectopy``),
  or this interpreter if it imports ``trajectopy``; it reads the ``.traj`` exports with
  ``Trajectory.from_file`` and computes ``trajectopy.ate(..., align=False)``.

Both tests are skipped when their tool is missing (``tests/trajectory_tools.py`` runs the tools).
The README's example run is checked the same way in ``tests/test_readme_tiny.py``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import run_georefine
from georefine.errors import InputError
from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.geometry.rotation import exp_so3
from georefine.io.pose_files import geodetic_from_poses, read_trajectopy, read_tum
from georefine.io.trajectory import (
    read_sbet,
    read_sbet_companion,
    read_smrmsg,
    smrmsg_path,
    write_sbet,
)
from georefine.io.trajectory_csv import read_trajectory_csv
from georefine.workflows.products import accuracy_from_sigmas, write_csv_product, write_sbet_product
from trajectory_tools import (
    assert_same_figures,
    evo_ape_rmse,
    export_pair,
    georefine_figures,
    trajectopy_ate,
    trajectopy_python,
)

T0 = 1_399_708_800.0 + 3 * 86400.0 + 0.25  # GPS week 2314, Wednesday
EPSG = 25832
FRAME = LocalFrame.from_degrees(47.0, 11.0, 700.0)  # 2 deg east of UTM 32's central meridian


def _flight(rate_hz: float = 50.0, duration_s: float = 120.0):
    """A smooth flight in ``w``: a turn into a straight line at 20 m/s with rolling and pitching."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    psi = 0.3 + 0.4 * np.sin(2 * np.pi * t / 80.0)
    p = np.column_stack([np.cumsum(20.0 * np.sin(psi)) / rate_hz, np.cumsum(20.0 * np.cos(psi)) / rate_hz,
                         150.0 + 5.0 * np.sin(2 * np.pi * t / 40.0)])
    v = np.gradient(p, t, axis=0)
    rph = np.column_stack([0.1 * np.sin(2 * np.pi * t / 13.0), 0.05 * np.cos(2 * np.pi * t / 17.0), psi])
    R = FRAME.R_w_b_from_rph(p, rph)
    return t, p, v, R


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    """``(estimate, reference)`` SBETs written as a run writes them (companion, accuracy, CSV)."""
    d = tmp_path_factory.mktemp("export")
    rng = np.random.default_rng(15)
    t, p, v, R = _flight()
    n = t.size
    write_sbet_product(d / "truth.sbet", FRAME, T0, t, p, v, R, output_epsg=EPSG)
    walk = np.cumsum(rng.normal(scale=0.004, size=(n, 3)), axis=0)
    dp = 0.03 * walk / np.abs(walk).max(axis=0) + rng.normal(scale=0.005, size=(n, 3))
    dtheta = np.radians(np.column_stack([np.sin(2 * np.pi * t / 30.0 + k) for k in range(3)]) * 4e-3
                        + rng.normal(scale=1e-3, size=(n, 3)))
    R_est = R @ exp_so3(dtheta)
    sig_p, sig_v = np.full((n, 3), 0.02), np.full((n, 3), 0.005)
    sig_rph = np.radians(np.full((n, 3), 3e-3))
    accuracy = accuracy_from_sigmas(FRAME, T0, t[::50], p[::50], sig_p[::50], sig_v[::50], sig_rph[::50])
    (d / "run").mkdir()
    write_sbet_product(d / "run" / "trajectory.sbet", FRAME, T0, t, p + dp, v, R_est, output_epsg=EPSG,
                       accuracy=accuracy)
    write_csv_product(d / "run" / "trajectory.csv", FRAME, OutputCRS(EPSG), T0, t[::5], (p + dp)[::5], R_est[::5],
                      sig_rph[::5], sig_p[::5])
    return d / "run" / "trajectory.sbet", d / "truth.sbet"


def test_sbet_products_in_seconds_of_week_with_week_and_accuracy(pair):
    est, _ = pair
    assert np.fromfile(est, "<f8", count=1)[0] == pytest.approx(T0 - 2314 * 604800.0, abs=1e-6)
    companion = read_sbet_companion(est)
    assert companion.gps_week == 2314 and companion.output_epsg == EPSG
    assert companion.accuracy_file == "smrmsg_trajectory.out" == smrmsg_path(est).name
    sbet = read_sbet(est)
    assert sbet.time_gps[0] == pytest.approx(T0, abs=1e-6)
    acc = read_smrmsg(smrmsg_path(est), gps_week=companion.gps_week)
    assert acc.time_gps[0] == pytest.approx(T0, abs=1e-6) and len(acc) == 120
    # w's axes are east, north, up at 47 N 11 E; the accuracy file's are the local north, east, down
    np.testing.assert_allclose(acc.sigma_ned_m, 0.02, rtol=1e-6)
    np.testing.assert_allclose(np.degrees(acc.sigma_rph_rad) * 60, 3e-3 * 60, rtol=1e-12)
    assert f"# gps_week: {companion.gps_week}" in (est.parent / "trajectory.csv").read_text()


def test_accuracy_sigmas_are_rotated_into_the_local_level_frame():
    """sigma_w (east, north, up) = (1, 2, 3) cm 90 deg of longitude away: north-down swap with east."""
    frame = LocalFrame.from_degrees(0.0, 0.0, 0.0)
    p_w = frame.from_geodetic(np.radians([0.0]), np.radians([90.0]), np.array([0.0]))
    acc = accuracy_from_sigmas(frame, T0, np.array([0.0]), p_w, np.array([[0.01, 0.02, 0.03]]),
                               np.array([[1.0, 2.0, 3.0]]), np.zeros((1, 3)))
    # at 90 deg E the local east is -x_e (w's up), north is w's north, down is -y_e (-w's east)
    np.testing.assert_allclose(acc.sigma_ned_m[0], [0.02, 0.03, 0.01], atol=1e-12)
    np.testing.assert_allclose(acc.sigma_velocity_ned_m_s[0], [2.0, 3.0, 1.0], atol=1e-9)


@pytest.mark.parametrize("fmt, reader", [("tum", read_tum), ("trajectopy", read_trajectopy)])
def test_export_cli_writes_every_pose_in_the_output_crs(pair, tmp_path, fmt, reader):
    est, _ = pair
    run = run_georefine("export", "trajectory", str(est), "--format", fmt, "--out", str(tmp_path / f"e.{fmt}"))
    assert run.returncode == 0, run.stderr
    assert "EPSG:25832" in run.stdout and "GPS week 2314" in run.stdout
    poses = reader(tmp_path / f"e.{fmt}")
    sbet = read_sbet(est)
    assert poses.epsg == EPSG and len(poses) == len(sbet)
    np.testing.assert_allclose(poses.time_gps, sbet.time_gps, rtol=0, atol=1e-9)
    lat, lon, h, rph = geodetic_from_poses(poses)
    np.testing.assert_allclose(lat, sbet.lat_rad, rtol=0, atol=1e-12)
    np.testing.assert_allclose(lon, sbet.lon_rad, rtol=0, atol=1e-12)
    np.testing.assert_allclose(h, sbet.h_m, rtol=0, atol=1e-6)
    d = np.angle(np.exp(1j * (rph - np.column_stack([sbet.roll_rad, sbet.pitch_rad, sbet.heading_rad]))))
    assert np.abs(d).max() < 1e-9


def test_export_of_the_csv(pair, tmp_path):
    csv = pair[0].parent / "trajectory.csv"
    run = run_georefine("export", "trajectory", str(csv), "-f", "tum", "-o", str(tmp_path / "c.tum"))
    assert run.returncode == 0, run.stderr
    poses, table = read_tum(tmp_path / "c.tum"), read_trajectory_csv(csv)
    np.testing.assert_allclose(poses.xyz, table.xyz, rtol=0, atol=1e-6)  # the CSV's own CRS: through pyproj and back
    np.testing.assert_allclose(poses.time_gps, table.time_gps, rtol=0, atol=1e-9)


def test_export_bad_inputs_are_one_line_and_exit_2(pair, tmp_path):
    est, _ = pair
    bare = tmp_path / "bare.sbet"
    write_sbet(bare, read_sbet(est), time_scale="week")  # seconds of week, no companion file
    cases = [
        (["--format", "tum"], bare, ["bare.sbet", "GPS week is needed", "--gps-week"]),
        (["--format", "tum", "--gps-week", "2314"], bare, ["no CRS for the poses", "--epsg"]),
        (["--format", "kml"], est, ["unknown trajectory format", "tum or trajectopy", "'kml'"]),
        (["--format", "tum", "--epsg", "4326"], est, ["projected or geocentric", "EPSG:4326"]),
        (["--format", "tum", "--epsg", "999999"], est, ["unknown CRS", "EPSG:999999"]),
    ]
    for options, source, words in cases:
        out = tmp_path / "x.tum"
        run = run_georefine("export", "trajectory", str(source), *options, "--out", str(out))
        assert run.returncode == 2, (options, run.stderr)
        assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr, run.stderr
        for w in words:
            assert w in run.stderr, (w, run.stderr)
        assert not out.exists()
    run = run_georefine("export", "trajectory", str(est), "--format", "tum", "--out", str(est))
    assert run.returncode == 2 and "refusing to write into an input" in run.stderr


# ---------------------------------------------------------------------------
# evo and trajectopy on the exports
# ---------------------------------------------------------------------------


@pytest.mark.skipif(shutil.which("evo_ape") is None, reason="evo (evo_ape) is not installed")
def test_evo_ape_reproduces_georefine_figures(pair, tmp_path):
    est, ref = pair
    ours = georefine_figures(est, ref, tmp_path / "eval")
    est_tum, ref_tum = export_pair(est, ref, tmp_path, "tum")
    position = evo_ape_rmse(ref_tum, est_tum, "trans_part", tmp_path)
    angle = evo_ape_rmse(ref_tum, est_tum, "angle_deg", tmp_path) * 1e3
    assert_same_figures(ours, position, angle, "evo_ape")
    assert 0.01 < ours["3d_rmse_m"] < 0.1 and 1.0 < ours["attitude_angle_rmse_mdeg"] < 20.0  # errors of the fixture


@pytest.mark.skipif(trajectopy_python() is None,
                    reason="trajectopy is not installed (GEOREFINE_TRAJECTOPY_PYTHON names an interpreter with it)")
def test_trajectopy_reproduces_georefine_figures(pair, tmp_path):
    est, ref = pair
    ours = georefine_figures(est, ref, tmp_path / "eval")
    est_traj, ref_traj = export_pair(est, ref, tmp_path, "trajectopy")
    ate = trajectopy_ate(est_traj, ref_traj)
    assert ate["epsg"] == EPSG and ate["n"] == ours["n_epochs"]
    assert_same_figures(ours, ate["pos_rms_m"], np.degrees(ate["rot_rms_rad"]) * 1e3, "trajectopy")


def test_the_evaluation_takes_the_week_from_the_companion_files(pair):
    """compare_sbet_files resolves both files with their companions: absolute GPS time, no assumption."""
    est, ref = pair
    cmp = compare_sbet_files(est, ref)
    assert cmp.time_scale == "gps" and cmp.gps_week == 2314
    assert all("from trajectory.sbet.json" in n or "from truth.sbet.json" in n for n in cmp.notes), cmp.notes
    with pytest.raises(InputError, match="contradicts"):
        compare_sbet_files(est, ref, gps_week=2313)
