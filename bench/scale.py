"""Scale of `georefine run` with the point count: memory, time and accuracy at three pulse rates.

For each pulse rate the same corridor (scenario ``corridor``, seed 42, only the scanner's pulse
and line rates changed; 1.8 MHz is ``corridor-paper``) is simulated once into WORKDIR, then run
with both passes and with a single pass (``--strips 1``), each in a fresh process and a fresh
output folder. Printed per rate and run:

* wall time and peak memory summed over the whole process tree (Dask workers included:
  ``bench/proctree.py``), for the simulation and the runs;
* seconds and points per second of each per-point stage (from ``metrics.json``);
* roll, pitch and yaw RMSE (mdeg) of G/I and G/I/L against the simulated truth during each
  pass, and the yaw ratio G/I/L : G/I;
* the ratios the scale criteria ask for: peak memory and wall time against the lowest rate,
  beside the ratio of points.

Usage::

    python bench/scale.py WORKDIR [--rates 100000 400000 1800000] [--scheduler threads]
                                  [--no-single-pass | --single-pass-only] [--single-pass-no-points]
    python bench/scale.py WORKDIR --rates 100000 --schedulers sync threads processes

Projects already in WORKDIR (``corridor-<rate>``) are reused (delete them to re-simulate).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from georefine.evaluation.trajectory_files import truth_pass_rmse as pass_rmse  # noqa: E402
from proctree import run_measured  # noqa: E402

LINE_RATE = {100_000: 120.0, 400_000: 240.0, 1_800_000: 400.0}
"""Lines per second at each pulse rate (the corridor's, between, the VUX-160's in ``corridor-paper``)."""

PER_POINT = ("read", "features", "final_georeferencing")


def simulate(workdir: Path, rate: int) -> tuple[Path, float | None, float | None, dict[int, int]]:
    project = workdir / f"corridor-{rate}"
    wall = peak = None
    if not (project / "truth" / "scenario.yaml").is_file():
        scenario = "corridor-paper" if rate == 1_800_000 else "corridor"
        args = [sys.executable, "-m", "georefine", "simulate", scenario, "--out", str(project), "--seed", "42"]
        if scenario == "corridor":
            args += ["--set", f"scanner.pulse_rate_hz={rate}", "--set", f"scanner.line_rate_hz={LINE_RATE[rate]}"]
        wall, peak, _ = run_measured(args)
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    return project, wall, peak, {int(k): int(v) for k, v in truth["points_per_strip"].items()}


def run(project: Path, out: Path, scheduler: str, extra: list[str]) -> tuple[float, float, dict]:
    args = [sys.executable, "-m", "georefine", "run", str(project), "--out", str(out), "--fresh",
            "--scheduler", scheduler, *extra]
    wall, peak, _ = run_measured(args)
    return wall, peak, json.loads((out / "metrics.json").read_text())


def stage_seconds(timings: dict[str, float]) -> dict[str, float]:
    """Seconds per stage, the outer iterations' features summed."""
    out: dict[str, float] = {}
    for k, v in timings.items():
        key = "features" if k.startswith("features_") else k
        out[key] = out.get(key, 0.0) + v
    return out


def compare_schedulers(workdir: Path, rate: int, schedulers: list[str]) -> None:
    """Both passes on each scheduler: per-point stage seconds, speed-up against the first, memory, same results."""
    from georefine.io.trajectory import read_sbet

    project, _, _, per_strip = simulate(workdir, rate)
    print(f"{rate / 1e3:.0f} kHz, {sum(per_strip.values()):,} points; schedulers {', '.join(schedulers)}")
    first = None
    for name in schedulers:
        out = workdir / f"run-{rate}-{name.replace('://', '-').replace(':', '-')}"
        wall, peak, m = run(project, out, name, [])
        secs = stage_seconds(m["timings_s"])
        n_iter = len(m["outer_iterations"])
        feat = secs["features"] / n_iter
        sbet = read_sbet(out / "gil" / "trajectory.sbet", gps_week=int(m["t0_gps"] // 604800))
        if first is None:
            first = (feat, secs["final_georeferencing"], sbet)
        d_att = max(float(np.degrees(np.abs(getattr(sbet, k) - getattr(first[2], k))).max())
                    for k in ("roll_rad", "pitch_rad", "heading_rad"))
        print(f"  {name:10s} {wall:7.1f} s  peak {peak:5.2f} GB  features {feat:5.1f} s per iteration "
              f"({first[0] / feat:.2f}x)  final georeferencing {secs['final_georeferencing']:5.1f} s "
              f"({first[1] / secs['final_georeferencing']:.2f}x)  max attitude difference to {schedulers[0]} "
              f"{d_att:.1e} deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--rates", type=int, nargs="+", default=[100_000, 400_000, 1_800_000])
    ap.add_argument("--scheduler", default="threads")
    cases = ap.add_mutually_exclusive_group()
    cases.add_argument("--no-single-pass", action="store_true", help="Both passes only.")
    cases.add_argument("--single-pass-only", action="store_true", help="The single pass only.")
    ap.add_argument("--single-pass-no-points", action="store_true",
                    help="The single pass without its point cloud (step 6): the trajectory only.")
    ap.add_argument("--schedulers", nargs="+", metavar="NAME",
                    help="Instead: run the lowest rate's project with each scheduler (e.g. sync threads processes) "
                         "and compare the per-point stages, memory and trajectories.")
    a = ap.parse_args()
    a.workdir.mkdir(parents=True, exist_ok=True)
    if a.schedulers:
        compare_schedulers(a.workdir, min(a.rates), a.schedulers)
        return
    rows = []
    for rate in a.rates:
        project, sim_wall, sim_peak, per_strip = simulate(a.workdir, rate)
        points = sum(per_strip.values())
        sim = "reused" if sim_wall is None else f"{sim_wall:.0f} s, peak {sim_peak:.2f} GB, {points / sim_wall / 1e6:.2f} M points/s"
        print(f"\n{rate / 1e3:.0f} kHz: {points:,} points; simulation {sim}", flush=True)
        single = ["--strips", "1"] + (["--no-points"] if a.single_pass_no_points else [])
        cases = ([] if a.single_pass_only else [("both passes", [], (1, 2))]) + (
            [] if a.no_single_pass else [("single pass", single, (1,))])
        for name, extra, strips in cases:
            out = a.workdir / f"run-{rate}-{'full' if not extra else 'single'}"
            wall, peak, m = run(project, out, a.scheduler, extra)
            secs = stage_seconds(m["timings_s"])
            n_iter = len(m["outer_iterations"])
            pts = sum(per_strip[s] for s in strips)  # the points read (step 6 may be skipped)
            print(f"  {name:12s} {wall:7.1f} s  peak {peak:5.2f} GB  outer iterations {n_iter}", flush=True)
            print("    " + ", ".join(f"{k} {v:.1f} s" for k, v in secs.items()))
            for k in PER_POINT:
                if secs.get(k, 0.0) > 0.01:  # a skipped step 6 records ~0 s
                    n = pts * (n_iter if k == "features" else 1)
                    print(f"    {k}: {n / secs[k] / 1e6:.2f} M points/s")
            for s in strips:
                gi = pass_rmse(out / "gi" / "trajectory.sbet", project, s)
                gil = pass_rmse(out / "gil" / "trajectory.sbet", project, s)
                print(f"    pass {s}: roll/pitch/yaw RMSE G/I {gi.round(1).tolist()} mdeg, G/I/L {gil.round(1).tolist()} mdeg,"
                      f" yaw G/I/L : G/I = {gil[2] / gi[2]:.2f}")
            rows.append((rate, name, points, wall, peak))
    full = sorted((r for r in rows if r[1] == "both passes"), key=lambda r: r[0])
    if len(full) > 1:
        base = full[0]
        print("\nagainst the lowest rate (both passes): points, wall time, peak memory")
        for r in full[1:]:
            print(f"  {r[0] / 1e3:.0f} kHz: points {r[2] / base[2]:.2f}x, time {r[3] / base[3]:.2f}x "
                  f"(time/points {r[3] / base[3] / (r[2] / base[2]):.2f}), memory {r[4] / base[4]:.2f}x ({r[4]:.2f} GB)")


if __name__ == "__main__":
    main()
