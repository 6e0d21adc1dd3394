"""G/I and G/I/L adjustment time and memory against the flight length (a script, not a test).

For each flight length (default 10, 30 and 60 minutes) the ``corridor`` scenario is lengthened
(``scene.length_m`` solved from the flight planner, as in ``bench/trajectory_scaling.py``) and
simulated with a LiDAR that keeps the planar features representative at a quarter of the
points: 25 kHz at 60 lines/s (0.8 m across and 0.9 m along track per view, ~1.4 points/m²)
with a 2 m feature radius (``processing.planes.radius_m``) holds about the points a 1 m ball
holds at the default 100 kHz. Then ``georefine run --no-points`` (steps 1-5, default
configuration otherwise: up-sampling on, two outer iterations at most) runs in a fresh child
process per case so that its peak memory is its own.

Printed per case: flight minutes, knots, features and objects used by the last G/I/L
adjustment, the initialisation filter's time, the G/I adjustment time (step 2, without the
filter), the G/I/L adjustment time (all outer iterations, solves only), feature extraction and matching time, the G/I/L posterior, the whole run, peak memory,
and the time per minute of flight relative to the first case (1.00 = linear); then log-log
slopes, and a log-log plot (``--plot``).

Usage::

    python bench/flight_length.py WORKDIR [--durations 10 30 60] [--plot flight_length.png]

Projects already in WORKDIR (``corridor-<N>min``) are reused.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from trajectory_scaling import corridor_length_for  # noqa: E402

SIM_OVERRIDES = ["scanner.pulse_rate_hz=25000", "scanner.line_rate_hz=60"]
PROCESSING = {"planes": {"radius_m": 2.0}}


def simulate(workdir: Path, minutes: float) -> Path:
    from georefine.sim.scenarios import simulate_project

    project = workdir / f"corridor-{minutes:g}min"
    if not (project / "truth" / "scenario.yaml").exists():
        length = corridor_length_for(60.0 * minutes)
        t = time.perf_counter()
        simulate_project("corridor", project, seed=42, overrides=[*SIM_OVERRIDES, f"scene.length_m={length}"])
        cfg = yaml.safe_load((project / "project.yaml").read_text())
        cfg["processing"] = PROCESSING
        (project / "project.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        print(f"simulated {project.name} ({length:.0f} m) in {time.perf_counter() - t:.0f} s", flush=True)
    return project


def run(project: str, out: str) -> dict:
    """Child process: steps 1-5; the timings of metrics.json and the peak RSS."""
    from georefine.workflows.lidar import run_workflow

    t = time.perf_counter()
    run_workflow(project, out, points=False, resume=False)
    wall = time.perf_counter() - t
    m = json.loads((Path(out) / "metrics.json").read_text())
    return {"wall_s": wall, "metrics": m, "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def _sum(timings: dict, prefix: str) -> float:
    return float(sum(v for k, v in timings.items() if k.startswith(prefix)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--durations", type=float, nargs="+", default=[10.0, 30.0, 60.0], help="flight minutes")
    ap.add_argument("--plot", type=Path, default=None, help="log-log plot (PNG); default WORKDIR/flight_length.png")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for minutes in args.durations:
        project = simulate(args.workdir, minutes)
        out = args.workdir / f"run-{minutes:g}min"
        with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
            r = pool.submit(run, str(project), str(out)).result()
        m, t = r["metrics"], r["metrics"]["timings_s"]
        truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
        last = m["outer_iterations"][-1]
        row = {
            "minutes": truth["duration_s"] / 60.0, "wall_s": r["wall_s"], "peak_gb": r["peak_rss_gb"],
            # "gi_adjustment" times steps 1-2 (the cached stage); the G/I adjustment is step 2.
            "filter_s": t.get("filter", np.nan), "gi_s": t.get("gi_adjustment", np.nan) - t.get("filter", 0.0),
            "gil_s": _sum(t, "gil_adjustment_"),
            "features_s": _sum(t, "features_"), "matching_s": _sum(t, "matching_"),
            "posterior_s": t.get("gil_covariance", np.nan), "iterations": len(m["outer_iterations"]),
            "features": last["features_used"], "objects": last["objects_used"],
        }
        rows.append(row)
        print(f"  {row['minutes']:.1f} min: G/I {row['gi_s']:.1f} s, G/I/L {row['gil_s']:.1f} s "
              f"({row['iterations']} outer iterations, {row['features']:,} features), whole run {row['wall_s']:.0f} s, "
              f"peak {row['peak_gb']:.2f} GB", flush=True)

    first = rows[0]
    print("\n| flight | filter (step 1) | G/I adjustment (step 2) | G/I/L adjustments | outer iterations "
          "| features / objects | features + matching | G/I/L posterior | whole run | peak memory | G/I per min : first | G/I/L per min : first |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['minutes']:.1f} min | {r['filter_s']:.1f} s | {r['gi_s']:.1f} s | {r['gil_s']:.1f} s "
              f"| {r['iterations']} "
              f"| {r['features']:,} / {r['objects']:,} | {r['features_s'] + r['matching_s']:.0f} s | {r['posterior_s']:.1f} s "
              f"| {r['wall_s']:.0f} s | {r['peak_gb']:.2f} GB "
              f"| {r['gi_s'] / r['minutes'] / (first['gi_s'] / first['minutes']):.2f} "
              f"| {r['gil_s'] / r['minutes'] / (first['gil_s'] / first['minutes']):.2f} |")
    if len(rows) > 1:
        d = np.log([r["minutes"] for r in rows])
        for key in ("gi_s", "gil_s", "peak_gb", "wall_s"):
            print(f"log-log slope of {key} against flight length: {np.polyfit(d, np.log([r[key] for r in rows]), 1)[0]:.2f}"
                  " (1 = linear)")
    _plot(rows, args.plot or args.workdir / "flight_length.png")


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.array([r["minutes"] for r in rows])
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6))
    for key, label in (("gi_s", "G/I adjustment"), ("gil_s", "G/I/L adjustments"), ("wall_s", "whole run (steps 1-5)")):
        a.loglog(x, [r[key] for r in rows], "o-", label=label)
    ref = np.array([rows[0]["gil_s"] * xi / x[0] for xi in x])
    a.loglog(x, ref, "k:", label="linear")
    a.set_xlabel("flight (min)")
    a.set_ylabel("time (s)")
    a.legend(fontsize=8)
    b.loglog(x, [r["peak_gb"] for r in rows], "o-", label="peak memory")
    b.loglog(x, [rows[0]["peak_gb"] * xi / x[0] for xi in x], "k:", label="linear")
    b.set_xlabel("flight (min)")
    b.set_ylabel("GB")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


if __name__ == "__main__":
    main()
