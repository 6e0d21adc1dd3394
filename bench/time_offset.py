"""LiDAR time offsets on `corridor`: found, estimated, and the attitude they leave.

    python bench/time_offset.py WORK [--offsets 0.002 0.05 1 18] [--uncorrected 1]

Simulates `corridor` (seed 42) once with synchronised strips and once per offset with strips
whose gps_time runs that far behind GPS time (`--set scanner_time_offset_s=X`; project.yaml
states 0), then runs `georefine run --no-points` on each with the default configuration
(search and estimation on). Prints per offset: whether the search adopted a candidate and
which, the final estimate with its sigma, its error against the truth, against the offset the
simulated GNSS errors alone imply (``truth_gnss_time_offset``: the passes' along-track errors)
and against the clean run's estimate (which shares the GNSS errors), the G/I/L roll/pitch/yaw RMSE per pass against
the clean run's, the warnings, and the wall time. `--uncorrected X` adds a run of offset X with
the search and the estimation switched off: what the workflow did before.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from georefine.evaluation.trajectory_files import truth_gnss_time_offset, truth_pass_rmse
from georefine.io.run_metrics import read_adjustment_report


def simulate(workdir: Path, offset: float) -> Path:
    out = workdir / ("corridor" if offset == 0 else f"corridor-offset-{offset:g}")
    if not (out / "truth" / "scenario.yaml").is_file():
        cmd = [sys.executable, "-m", "georefine", "simulate", "corridor", "--out", str(out), "--seed", "42"]
        if offset:
            cmd += ["--set", f"scanner_time_offset_s={offset}"]
        subprocess.run(cmd, check=True, capture_output=True, text=True)
    return out


def uncorrected_copy(project: Path, out: Path) -> Path:
    """``project`` with the search and the estimation off (links to its data)."""
    out.mkdir(parents=True, exist_ok=True)
    for sub in ("gnss", "imu", "scans", "reference", "truth"):
        link = out / sub
        if not link.exists():
            link.symlink_to((project / sub).resolve())
    cfg = yaml.safe_load((project / "project.yaml").read_text())
    cfg.setdefault("processing", {}).setdefault("lidar", {})["time_offset"] = {"search": False, "estimate": False}
    (out / "project.yaml").write_text(yaml.safe_dump(cfg))
    return out


def run(project: Path, out: Path, scheduler: str) -> dict:
    if out.exists():
        shutil.rmtree(out)  # a run from scratch
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "georefine", "run", str(project), "--out", str(out),
                           "--no-points", "--scheduler", scheduler], capture_output=True, text=True)
    if proc.returncode:
        sys.exit(f"georefine run {project} failed:\n{proc.stderr[-3000:]}")
    wall = time.perf_counter() - t
    metrics = json.loads((out / "metrics.json").read_text())
    report = read_adjustment_report(out / "gil" / "adjustment.json").lidar_time_offset
    search = metrics["outer_iterations"][0].get("time_offset_search")
    warnings = [line.split(": ", 1)[1][:150] for line in proc.stderr.splitlines() if line.startswith("WARNING")]
    (out / "run.log").write_text(proc.stderr)
    return {
        "wall": wall, "search": search, "estimate": None if report is None else report.estimate_s,
        "sigma_ms": None if report is None else report.sigma_ms,
        "gnss_sigma_ms": None if report is None else report.gnss_sigma_ms,
        "warnings": warnings, "outer": len(metrics["outer_iterations"]),
        "rmse": {p: truth_pass_rmse(out / "gil" / "trajectory.sbet", project, p) for p in (1, 2)},
        "gi": {p: truth_pass_rmse(out / "gi" / "trajectory.sbet", project, p) for p in (1, 2)},
    }


def fmt(v: np.ndarray) -> str:
    return " / ".join(f"{x:.2f}" for x in v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--offsets", type=float, nargs="+", default=[0.002, 0.05, 1.0, 18.0])
    ap.add_argument("--uncorrected", type=float, nargs="*", default=[1.0])
    ap.add_argument("--scheduler", default="threads")
    a = ap.parse_args()
    a.workdir.mkdir(parents=True, exist_ok=True)
    rows: dict[str, tuple[float, dict]] = {}
    for offset in [0.0, *a.offsets]:
        t = time.perf_counter()
        project = simulate(a.workdir, offset)
        print(f"simulated offset {offset:g} s in {time.perf_counter() - t:.0f} s", flush=True)
        rows[f"{offset:g} s"] = (offset, run(project, a.workdir / f"run-{offset:g}", a.scheduler))
        print(f"  run {rows[f'{offset:g} s'][1]['wall']:.0f} s", flush=True)
    for offset in a.uncorrected:
        project = uncorrected_copy(simulate(a.workdir, offset), a.workdir / f"corridor-offset-{offset:g}-uncorrected")
        rows[f"{offset:g} s, uncorrected"] = (offset, run(project, a.workdir / f"run-{offset:g}-uncorrected",
                                                          a.scheduler))
    clean = rows["0 s"][1]
    implied = truth_gnss_time_offset(a.workdir / "corridor")
    print(f"\nthe simulated GNSS errors alone imply an offset of {implied * 1e3:+.3f} ms; the run's sigma for "
          f"GNSS errors lasting a pass: {clean['gnss_sigma_ms']:.3f} ms")
    print("\nG/I, both passes (mdeg roll / pitch / yaw):", fmt(clean["gi"][1]), "|", fmt(clean["gi"][2]))
    print("\n| offset | search | estimate (s) | sigma (ms) | error vs truth (ms) | vs truth + GNSS-implied (ms) "
          "| vs clean estimate (ms) | G/I/L pass 1 | pass 2 | ratio to clean (pass 1 / 2) | outer | run (s) |")
    print("|---|---|---:|---:|---:|---:|---:|---|---|---|---:|---:|")
    for name, (offset, r) in rows.items():
        s = r["search"]
        search = "off" if s is None else (f"adopted {s['best_s']:+.4f}" if s["adopted"] else "kept 0")
        est = r["estimate"]
        err = "" if est is None else f"{(est - offset) * 1e3:+.3f}"
        rel = "" if est is None or clean["estimate"] is None else f"{(est - offset - clean['estimate']) * 1e3:+.3f}"
        gnss = "" if est is None else f"{(est - offset - implied) * 1e3:+.3f}"
        ratio = " / ".join(fmt(r["rmse"][p] / clean["rmse"][p]) for p in (1, 2))
        est_s = "" if est is None else f"{est:.5f}"
        sigma = "" if r["sigma_ms"] is None else f"{r['sigma_ms']:.3f}"
        print(f"| {name} | {search} | {est_s} | {sigma} | {err} | {gnss} | {rel} | {fmt(r['rmse'][1])} | "
              f"{fmt(r['rmse'][2])} | {ratio} | {r['outer']} | {r['wall']:.0f} |")
    print("\nwarnings:")
    for name, (_, r) in rows.items():
        for w in r["warnings"]:
            print(f"  {name}: {w}")


if __name__ == "__main__":
    main()
