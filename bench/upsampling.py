"""IMU down- and up-sampling on a vibrating platform (docs/ARCHITECTURE.md §4.6; a script, not a test).

A corridor is simulated with ``flight.vibration`` on (a light helicopter: 6.5, 13 and 26 Hz,
0.005 deg and 0.05 mm per frequency and axis), then the GNSS/IMU adjustment (steps 1-2) is run
in several configurations on the same data:

* ``full-rate``: knots every ``--full-knot`` s (default 0.02 s) and every IMU sample its own
  window, no up-sampling: the spline itself follows the vibration;
* for each knot interval (default 0.1, 0.25, 0.5, 1 s; IMU window = knot / 5):
  ``up`` (down-sampled windows, the high-frequency motion rebuilt from the raw IMU; with
  ``--iterations`` 0, 1, ... re-solves with that motion taken out of the windows) and ``down only`` (the same windows,
  georeferencing with the spline alone).

Printed per case: adjustment time (every solve plus the up-sampling work, not the filter),
unknowns, roll/pitch/yaw RMSE (mdeg) against the truth during both passes (the trajectory as
written to ``trajectory.sbet``, at the IMU samples), and the 3-D and vertical RMS error of the
LiDAR points against the simulated truth: every ``--point-step``-th record of every strip
georeferenced with the case's IMU-rate trajectory and compared record by record with
``truth/strip_N.laz``. The last columns give each case's point error and time against the
full-rate case.

Usage::

    python bench/upsampling.py WORKDIR [--scenario corridor-tiny] [--knots 0.1 0.25 0.5 1]
                                       [--iterations 0 1] [--point-step 20] [--smooth]

The project ``WORKDIR/<scenario>-vibration`` (``-smooth`` with ``--smooth``: no vibration) is
simulated once and reused.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from georefine.config import boresight_matrix
from georefine.evaluation.trajectory_files import truth_pass_rmse
from georefine.geometry.frames import OutputCRS
from georefine.geometry.rotation import log_so3
from georefine.io.las import read_las
from georefine.io.trajectory import read_sbet
from georefine.lidar.georeference import PoseInterpolator, georeference
from georefine.trajectory.highrate import high_pass
from georefine.trajectory.sampled import trajectory_from_sbet
from georefine.workflows.navigation import (
    imu_rate_trajectory,
    load_navigation,
    step_adjust_gnss_imu,
    step_initialise,
    write_trajectory_products,
)


def simulate(workdir: Path, scenario: str, vibration: bool) -> Path:
    project = workdir / f"{scenario}-{'vibration' if vibration else 'smooth'}"
    if not (project / "project.yaml").exists():
        subprocess.run(["georefine", "simulate", scenario, "-o", str(project),
                        "--set", f"flight.vibration.enabled={str(vibration).lower()}"], check=True)
    return project


def with_trajectory(nav, **changes):
    """``nav`` with processing.trajectory settings changed (validated like project.yaml)."""
    cfg = nav.config
    tcfg = type(cfg.processing.trajectory).model_validate({**cfg.processing.trajectory.model_dump(), **changes})
    return replace(nav, config=cfg.model_copy(update={"processing": cfg.processing.model_copy(update={"trajectory": tcfg})}))


def point_errors(nav, adj, step: int) -> tuple[float, float]:
    """3-D and vertical RMS (mm) of every ``step``-th point against the simulated truth."""
    cfg = nav.config
    poses = PoseInterpolator(imu_rate_trajectory(nav, adj))
    crs = OutputCRS(cfg.crs.output_epsg)
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    d = []
    for f in cfg.scanner.files:
        scan = read_las(nav.root / f)
        truth = read_las(nav.root / "truth" / Path(f).name)
        t = scan.time_gps[::step] - nav.t0_gps
        keep = poses.inside(t)
        est = crs.from_w(nav.frame, georeference(t[keep], scan.xyz[::step][keep], poses, p_b_s, R_b_s))
        d.append(est - truth.xyz[::step][keep])
    d = np.concatenate(d)
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))) * 1e3), float(np.sqrt(np.mean(d[:, 2] ** 2)) * 1e3)


def high_frequency_errors(nav, adj, truth) -> tuple[float, float]:
    """RMS (mdeg, mm) of the attitude and position error faster than 1 s, during the passes.

    The error against the truth at the IMU samples, minus its least-squares cubic spline on
    1 s knots (:func:`georefine.trajectory.highrate.high_pass`): what vibration leaves as noise
    on the surfaces, apart from the slow errors that GNSS and IMU errors cause.
    """
    est = imu_rate_trajectory(nav, adj)
    passes = yaml.safe_load((nav.root / "truth" / "scenario.yaml").read_text())["passes"]
    att, pos = [], []
    for p in passes:
        m = (est.time >= p["t_start_s"] + 1.0) & (est.time <= p["t_end_s"] - 1.0)
        t = est.time[m]
        pt, Rt = truth.interpolate(t)
        e_att = log_so3(np.swapaxes(Rt, 1, 2) @ est.R_w_b[m])
        att.append(high_pass(t, e_att, 1.0))
        pos.append(high_pass(t, est.p_w_b[m] - pt, 1.0))
    att, pos = np.concatenate(att), np.concatenate(pos)
    return (float(np.degrees(np.sqrt(np.mean(np.sum(att**2, axis=1)))) * 1e3),
            float(np.sqrt(np.mean(np.sum(pos**2, axis=1))) * 1e3))


def run_case(nav, filt, truth, name: str, step: int, **changes) -> dict:
    n = with_trajectory(nav, **changes)
    t = time.perf_counter()
    adj = step_adjust_gnss_imu(n, filt)
    wall = time.perf_counter() - t - adj.timings_s.get("covariance", 0.0)
    with tempfile.TemporaryDirectory() as tmp:
        write_trajectory_products(Path(tmp), n, adj, OutputCRS(n.config.crs.output_epsg))
        passes = [p["strip_id"] for p in yaml.safe_load((nav.root / "truth" / "scenario.yaml").read_text())["passes"]]
        rph = np.mean([truth_pass_rmse(Path(tmp) / "trajectory.sbet", nav.root, i) ** 2 for i in passes], axis=0) ** 0.5
    e3, ez = point_errors(n, adj, step)
    hf_att, hf_pos = high_frequency_errors(n, adj, truth)
    unknowns = adj.spline.grid.n_knots * 15
    row = dict(case=name, knot=changes.get("knot_interval_s"), window=changes.get("imu_window_s"), time_s=wall,
               unknowns=unknowns, roll=rph[0], pitch=rph[1], yaw=rph[2], point_3d_mm=e3, point_z_mm=ez,
               hf_att_mdeg=hf_att, hf_pos_mm=hf_pos)
    print(f"  {name:28s} {wall:7.1f} s  rpy {rph[0]:6.2f} {rph[1]:6.2f} {rph[2]:6.2f} mdeg  "
          f"points {e3:6.2f} mm (z {ez:5.2f})  high-frequency {hf_att:5.2f} mdeg {hf_pos:5.2f} mm", flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--scenario", default="corridor-tiny")
    ap.add_argument("--knots", type=float, nargs="+", default=[0.1, 0.25, 0.5, 1.0])
    ap.add_argument("--full-knot", type=float, default=0.02)
    ap.add_argument("--iterations", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--point-step", type=int, default=20)
    ap.add_argument("--smooth", action="store_true", help="no vibration (does up-sampling cost accuracy there?)")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    project = simulate(args.workdir, args.scenario, not args.smooth)
    vib = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["scenario"]["flight"]["vibration"]
    print(f"{project.name}: vibration {'on' if vib['enabled'] else 'off'}, {vib['frequencies_hz']} Hz, "
          f"{vib['angular_amplitude_deg']} deg, {vib['linear_amplitude_m']} m per frequency and axis")
    nav = load_navigation(project)
    filt = step_initialise(nav)
    truth = trajectory_from_sbet(read_sbet(project / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800)), nav.frame, nav.t0_gps)
    rows = []
    rate = nav.gnss.imu_rate_hz
    rows.append(run_case(nav, filt, truth, "full rate", args.point_step,
                         knot_interval_s=args.full_knot, imu_window_s=1.0 / rate, upsampling=False))
    for k in args.knots:
        w = round(k / 5.0, 6)
        for it in args.iterations:
            rows.append(run_case(nav, filt, truth, f"up, {it} re-solve" + "s" * (it != 1), args.point_step, knot_interval_s=k,
                                 imu_window_s=w, upsampling=True, upsampling_iterations=it))
        rows.append(run_case(nav, filt, truth, "down only", args.point_step, knot_interval_s=k, imu_window_s=w, upsampling=False))
    full = rows[0]
    print("\n| case | knots / window | adjustment s | full rate : case time | roll | pitch | yaw (mdeg) "
          "| points 3-D mm | z mm | points : full rate | attitude > 1 Hz (mdeg) | position > 1 Hz (mm) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['case']} | {r['knot']:g} s / {r['window']:g} s | {r['time_s']:.1f} | {full['time_s'] / r['time_s']:.1f} "
              f"| {r['roll']:.2f} | {r['pitch']:.2f} | {r['yaw']:.2f} | {r['point_3d_mm']:.2f} | {r['point_z_mm']:.2f} "
              f"| {r['point_3d_mm'] / full['point_3d_mm']:.2f} | {r['hf_att_mdeg']:.2f} | {r['hf_pos_mm']:.3f} |")

if __name__ == "__main__":
    sys.exit(main())
