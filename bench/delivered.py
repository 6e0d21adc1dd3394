"""Delivered data on `corridor`: the vendor's strips and SBET imported and adjusted, against the raw data.

    python bench/delivered.py WORK [--seed 42]

What a LiDAR vendor delivers is simulated from the raw project: `georefine run --no-lidar` gives
the G/I trajectory (``gi/trajectory.sbet`` with ``smrmsg_trajectory.out``, the posterior
sigmas) and the strips georeferenced with it in the output CRS (``points/*.laz``) -- the
loosely coupled product. `georefine import-strips` turns those into a project with the
delivered trajectory and no raw GNSS/IMU, and `georefine run` adjusts it with the LiDAR planes
(docs/ARCHITECTURE.md §4.9). The raw project's own `georefine run` is the tightly coupled
reference. Prints per pass the roll/pitch/yaw RMSE against the truth (1 s inset) of G/I, the
delivered mode and the tightly coupled run, the strip differences (median and RMS over the
gated planar cells) of the three clouds, the ratios delivered / tightly coupled, and the wall
times; writes them to WORK/delivered.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from georefine.evaluation.trajectory_files import truth_pass_rmse


def georefine(*args: str) -> float:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "georefine", *args], capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"georefine {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    for line in proc.stderr.splitlines():
        if "WARNING" in line:
            print("  ", line[:300])
    return time.perf_counter() - t


def strip_differences(points: Path, out: Path) -> dict:
    if not (out / "strip_differences.json").is_file():
        georefine("evaluate", "strip-differences", str(points), "--out", str(out))
    d = json.loads((out / "strip_differences.json").read_text())
    return {"median_mm": d["median_m"] * 1e3, "rms_mm": d["rms_m"] * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--seed", type=int, default=42)
    args = ap.parse_args()
    w = args.work
    w.mkdir(parents=True, exist_ok=True)
    project = w / "corridor"
    times = {}
    if not (project / "truth" / "scenario.yaml").is_file():
        times["simulate"] = georefine("simulate", "corridor", "--out", str(project), "--seed", str(args.seed))
    if not (w / "raw" / "metrics.json").is_file():
        times["raw G/I/L"] = georefine("run", str(project), "--out", str(w / "raw"))
    if not (w / "vendor" / "metrics.json").is_file():
        times["G/I (vendor)"] = georefine("run", str(project), "--out", str(w / "vendor"), "--no-lidar")
    sc = yaml.safe_load((project / "project.yaml").read_text())["scanner"]
    if not (w / "delivered" / "project.yaml").is_file():
        strips = sorted(str(p) for p in (w / "vendor" / "points").glob("*.laz"))
        times["import-strips"] = georefine(
            "import-strips", *strips, "--sbet", str(w / "vendor" / "gi" / "trajectory.sbet"),
            "--lever-arm=" + ",".join(map(str, sc["lever_arm_m"])), "--boresight=" + ",".join(map(str, sc["boresight_deg"])),
            "--out", str(w / "delivered"))
    if not (w / "delivered-run" / "metrics.json").is_file():
        times["delivered G/I/L"] = georefine("run", str(w / "delivered"), "--out", str(w / "delivered-run"))

    rows = {
        "G/I": (w / "vendor" / "gi" / "trajectory.sbet", w / "vendor" / "points"),
        "delivered G/I/L": (w / "delivered-run" / "gil" / "trajectory.sbet", w / "delivered-run" / "points"),
        "tightly coupled G/I/L": (w / "raw" / "gil" / "trajectory.sbet", w / "raw" / "points"),
    }
    result = {"times_s": times, "solutions": {}}
    print(f"{'solution':<24} {'pass 1 r/p/y (mdeg)':>22} {'pass 2 r/p/y (mdeg)':>22} {'strip diff median/RMS (mm)':>28}")
    for name, (sbet, points) in rows.items():
        rmse = [truth_pass_rmse(sbet, project, s).tolist() for s in (1, 2)]
        sd = strip_differences(points, w / "strip-differences" / name.replace("/", "").replace(" ", "-"))
        result["solutions"][name] = {"pass_rmse_mdeg": rmse, "strip_differences": sd}
        print(f"{name:<24} {'/'.join(f'{x:.1f}' for x in rmse[0]):>22} {'/'.join(f'{x:.1f}' for x in rmse[1]):>22} "
              f"{sd['median_mm']:>13.2f} / {sd['rms_mm']:.2f}")
    d, t = result["solutions"]["delivered G/I/L"], result["solutions"]["tightly coupled G/I/L"]
    ratio_yaw = [d["pass_rmse_mdeg"][k][2] / t["pass_rmse_mdeg"][k][2] for k in (0, 1)]
    ratio_sd = d["strip_differences"]["median_mm"] / t["strip_differences"]["median_mm"]
    result["ratios"] = {"yaw_per_pass": ratio_yaw, "strip_difference_median": ratio_sd}
    print(f"delivered / tightly coupled: yaw {ratio_yaw[0]:.2f} and {ratio_yaw[1]:.2f}, strip differences {ratio_sd:.2f}")
    print("wall times: " + ", ".join(f"{k} {v:.0f} s" for k, v in times.items()))
    (w / "delivered.json").write_text(json.dumps(result, indent=1))
    assert np.isfinite(ratio_sd)


if __name__ == "__main__":
    main()
