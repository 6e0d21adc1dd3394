"""Throughput of the point-wise LiDAR work (a script, not a test).

For one strip of a project, separately:

* LAZ decode (laspy + lazrs, chunked as the workflow reads),
* georeferencing arithmetic with the workflow's per-point interpolator (linear position,
  normalised linear quaternion blend between IMU-rate samples, one numba loop) and, measured in
  the same run as peers, the same blend in numpy and exact SLERP between the same samples
  (``Trajectory.interpolate``),
* the output CRS transform (pyproj) and LAZ encode of the result,
* planar feature extraction per view (strip x channel).

All rates are points per second of wall time in this single process; numpy runs these
operations on one core, so they are also rates per core (the LAZ decoder may use a second core:
``lazrs`` decompresses chunks in parallel).

Usage::

    python bench/lidar_throughput.py [PROJECT] [--strip 1]

Without PROJECT it simulates ``corridor-tiny`` with the corridor's scanner (100 kHz) into a
temporary folder.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

from georefine.config import boresight_matrix
from georefine.geometry.frames import OutputCRS
from georefine.io.las import iter_las_chunks
from georefine.io.trajectory import read_sbet
from georefine.lidar.georeference import PoseInterpolator, georeference
from georefine.lidar.planes import extract_features
from georefine.sim.scenarios import simulate_project
from georefine.trajectory.sampled import trajectory_from_sbet
from georefine.workflows import load_navigation


def rate(n: int, seconds: float) -> str:
    return f"{n / seconds / 1e6:7.2f} M points/s  ({seconds:6.2f} s)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", nargs="?", type=Path)
    ap.add_argument("--strip", type=int, default=1)
    args = ap.parse_args()
    tmp = None
    project = args.project
    if project is None:
        tmp = tempfile.TemporaryDirectory()
        project = Path(tmp.name) / "p"
        simulate_project("corridor-tiny", project, seed=3,
                         overrides=["scanner.pulse_rate_hz=100000", "scanner.line_rate_hz=120"])
    nav = load_navigation(project)
    cfg = nav.config
    path = project / f"scans/strip_{args.strip}.laz"

    t = time.perf_counter()
    chunks = list(iter_las_chunks(path, 5_000_000))
    t_dec = time.perf_counter() - t
    tm = np.concatenate([c.time_gps for c in chunks]) - nav.t0_gps
    xs = np.concatenate([c.xyz for c in chunks])
    ch = np.concatenate([c.scanner_channel for c in chunks])
    n = tm.size
    print(f"strip {path.name}: {n:,} points")
    print(f"LAZ decode                    {rate(n, t_dec)}")

    sb = read_sbet(project / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800))
    traj = trajectory_from_sbet(sb, nav.frame, nav.t0_gps)
    p_b_s = np.asarray(cfg.scanner.lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)
    interp = PoseInterpolator(traj)
    t = time.perf_counter()
    x_w = georeference(tm, xs, interp, p_b_s, R_b_s)
    t_geo = time.perf_counter() - t
    m = min(n, 2_000_000)
    t = time.perf_counter()
    x_ref = georeference(tm[:m], xs[:m], traj, p_b_s, R_b_s)
    t_slerp = (time.perf_counter() - t) * n / m
    dev = np.abs(x_ref - x_w[:m]).max()
    t = time.perf_counter()  # the same nlerp in numpy (batched 3x3 matrices), the second peer
    p_w_b, R_w_b = interp(tm[:m])
    x_np = p_w_b + np.einsum("nij,nj->ni", R_w_b, xs[:m] @ R_b_s.T + p_b_s)
    t_np = (time.perf_counter() - t) * n / m
    dev_np = np.abs(x_np - x_w[:m]).max()
    print(f"georeference (nlerp, numba)   {rate(n, t_geo)}")
    print(f"georeference (nlerp, numpy)   {rate(n, t_np)}   ratio {t_np / t_geo:.1f}x, max difference {dev_np * 1e3:.2e} mm")
    print(f"georeference (SLERP, peer)    {rate(n, t_slerp)}   ratio {t_slerp / t_geo:.1f}x, max difference {dev * 1e3:.3f} mm")

    crs = OutputCRS(cfg.crs.output_epsg)
    t = time.perf_counter()
    xyz_out = crs.from_w(nav.frame, x_w)
    e, nn, h = xyz_out[:, 0], xyz_out[:, 1], xyz_out[:, 2]
    t_crs = time.perf_counter() - t
    print(f"output CRS transform          {rate(n, t_crs)}")

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-3, 1e-3, 1e-3])
    header.offsets = np.floor(np.array([np.min(e), np.min(nn), np.min(h)]))
    las = laspy.LasData(header)
    las.x, las.y, las.z = e, nn, h
    las.gps_time = tm + nav.t0_gps - 1e9
    las.scanner_channel = ch
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        las.write(Path(d) / "out.laz")
        t_enc = time.perf_counter() - t
    print(f"LAZ encode                    {rate(n, t_enc)}")

    total_feat, t_feat = 0, 0.0
    for c in cfg.scanner.channels:
        sel = ch == c.id
        t = time.perf_counter()
        f = extract_features(x_w[sel], tm[sel], args.strip, c.id, interp, p_b_s, R_b_s, cfg.processing.planes)
        t_feat += time.perf_counter() - t
        total_feat += int(np.count_nonzero(sel))
        print(f"  view {c.name:9s}: {len(f):7,} features from {np.count_nonzero(sel):,} points")
    print(f"planar feature extraction     {rate(total_feat, t_feat)}")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
