"""Dropped IMU samples and a short IMU gap on ``corridor``: does the whole workflow hold? (a script, not a test)

The corridor (seed 42) is simulated once into WORKDIR, then copied (scans and truth linked, not
copied) with its IMU record damaged the way real loggers damage it: one sample dropped every
``--every`` seconds and one run of ``--gap`` seconds removed in the middle of the first pass.
``georefine run`` (steps 1-5, ``--no-points``: the trajectory) runs on the clean and on the
damaged project in fresh processes. Printed: wall time, the gaps ``georefine check`` reports,
and G/I and G/I/L roll / pitch / yaw RMSE (mdeg) against the truth during each pass, with the
damaged run's ratio to the clean one, over the whole pass and over the 10 s around the gap.

Usage::

    python bench/imu_gaps.py WORKDIR [--every 10] [--gap 0.5] [--scheduler threads]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from georefine.evaluation.trajectory_files import compare_sbet_files, truth_pass_rmse


def simulate(workdir: Path) -> Path:
    project = workdir / "corridor"
    if not (project / "truth" / "scenario.yaml").is_file():
        subprocess.run([sys.executable, "-m", "georefine", "simulate", "corridor", "--out", str(project),
                        "--seed", "42"], check=True)
    return project


def damaged_copy(project: Path, out: Path, every_s: float, gap_s: float) -> tuple[Path, float, int]:
    """``project`` with samples dropped from ``imu/imu.csv``; the gap's start (GPS s) and the samples removed."""
    if out.exists():
        import shutil

        shutil.rmtree(out)
    out.mkdir(parents=True)
    for entry in project.iterdir():
        if entry.name != "imu":
            os.symlink(entry.resolve(), out / entry.name)
    (out / "imu").mkdir()
    lines = (project / "imu" / "imu.csv").read_text().splitlines()
    header, body = lines[0], lines[1:]
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    first = next(p for p in truth["passes"] if p["strip_id"] == 1)
    t = np.array([float(line.split(",", 1)[0]) for line in body])
    rate = 1.0 / np.median(np.diff(t))
    keep = np.ones(t.size, bool)
    step = int(round(every_s * rate))
    keep[step // 2::step] = False
    t_gap = truth["t0_gps"] + 0.5 * (first["t_start_s"] + first["t_end_s"])
    k = int(np.searchsorted(t, t_gap))
    keep[k:k + int(round(gap_s * rate))] = False
    (out / "imu" / "imu.csv").write_text("\n".join([header] + [b for b, ok in zip(body, keep) if ok]) + "\n")
    return out, float(t[k]), int((~keep).sum())


def run(project: Path, out: Path, scheduler: str) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "georefine", "run", str(project), "--out", str(out), "--fresh",
                    "--no-points", "--scheduler", scheduler], check=True, capture_output=True, text=True)
    return time.perf_counter() - t


def near_rmse(sbet: Path, project: Path, t_gap: float, half_s: float = 5.0) -> np.ndarray:
    cmp = compare_sbet_files(sbet, project / "truth" / "trajectory.sbet", time_window=(t_gap - half_s, t_gap + half_s))
    return np.array([cmp.stats[f"{a}_rmse_mdeg"] for a in ("roll", "pitch", "yaw")])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--every", type=float, default=10.0, help="one sample dropped every this many seconds")
    ap.add_argument("--gap", type=float, default=0.5, help="seconds of samples removed mid-pass 1")
    ap.add_argument("--scheduler", default="threads")
    a = ap.parse_args()
    a.workdir.mkdir(parents=True, exist_ok=True)
    project = simulate(a.workdir)
    damaged, t_gap, removed = damaged_copy(project, a.workdir / "corridor-imu-gaps", a.every, a.gap)
    check = subprocess.run([sys.executable, "-m", "georefine", "check", str(damaged)], capture_output=True, text=True)
    print(f"damaged IMU: {removed} samples removed; georefine check exit {check.returncode}:")
    print("  " + "\n  ".join(line.strip() for line in check.stdout.splitlines() if "IMU" in line))
    rows = {}
    for name, proj in (("clean", project), ("damaged", damaged)):
        out = a.workdir / f"run-{name}"
        wall = run(proj, out, a.scheduler)
        rows[name] = {
            "wall": wall,
            **{f"{s} pass {p}": truth_pass_rmse(out / s.lower().replace("/", "") / "trajectory.sbet", project, p)
               for s in ("G/I", "G/I/L") for p in (1, 2)},
            **{f"{s} near gap": near_rmse(out / s.lower().replace("/", "") / "trajectory.sbet", project, t_gap)
               for s in ("G/I", "G/I/L")},
        }
        print(f"{name:8s} run {wall:6.1f} s", flush=True)
    print("\nroll / pitch / yaw RMSE against the truth (mdeg): clean | damaged | damaged : clean")
    for key in [k for k in rows["clean"] if k != "wall"]:
        c, d = rows["clean"][key], rows["damaged"][key]
        print(f"  {key:18s} {' / '.join(f'{v:.2f}' for v in c):>20s} | {' / '.join(f'{v:.2f}' for v in d):>20s}"
              f" | {' / '.join(f'{v:.2f}' for v in d / c)}")


if __name__ == "__main__":
    main()
