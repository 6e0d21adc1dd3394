"""Cost of the GNSS/IMU adjustment against flight duration (a script, not a test).

docs/ARCHITECTURE.md §4.6 requires the cost to grow linearly with the flight duration. For each target
duration (default 5, 10 and 20 minutes) this simulates the ``corridor`` scenario with the
corridor length chosen so that the flight lasts that long (two passes at the cruise speed
plus the fixed take-off, manoeuvre and turn, ~287 s; the length is solved from the flight
planner itself, the actual duration is read back from ``truth/scenario.yaml``), then runs
the initialisation filter and the G/I adjustment (docs/ARCHITECTURE.md §4.5 steps 1-2) in a fresh child
process per case, so that each case's peak resident memory is its own; there the adjustment runs
once to warm up (numba's cached kernels load on first use) and ``--repeat`` times more: the
fastest run's totals and each phase's least time are reported.

Only the navigation data matter here: the scanner runs at 1 kHz, and the scene has a single
reference site so that the 5-minute corridor (~120 m long) leaves room for it; the same
overrides apply to every case.

Printed per case: corridor length, flight duration, unknowns, LM iterations (trial /
accepted), wall time of the solve alone and of the whole adjustment (spline fit, problem,
solve and posterior covariances), time per minute of flight and per iteration, the ratio
of the time per minute to the first case (1.0 = linear), and peak RSS; then every phase of step 2
(spline start, problem, residuals and Jacobians, assembly, normal matrix, factorisation,
posterior sigma, up-sampling) and the log-log slope of each against the duration.

Usage::

    python bench/trajectory_scaling.py [--durations 5 10 20] [--seed 42] [--keep DIR] [--backend qdldl] [--repeat 2]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import yaml

SIM_OVERRIDES = [
    "scanner.pulse_rate_hz=1000",
    "scanner.line_rate_hz=50",  # >= 10 pulses per line
    "scene.reference_surfaces_per_site=[1]",  # one site fits a 120 m corridor
]


def corridor_length_for(duration_s: float) -> float:
    """Corridor length (m) whose default corridor flight lasts ``duration_s`` (from the flight planner)."""
    from georefine.geometry.frames import LocalFrame
    from georefine.sim.flight import simulate_flight
    from georefine.sim.scenarios import resolve_scenario

    cfg = resolve_scenario("corridor", seed_overrides=SIM_OVERRIDES)
    rp = cfg.reference_point
    frame = LocalFrame.from_degrees(rp.lat_deg, rp.lon_deg, rp.h_m)

    def duration(length_m: float) -> float:  # the horizontal plan alone fixes the duration
        return simulate_flight(cfg.flight, frame, length_m, lambda x, y: np.zeros(np.shape(x))).duration_s

    a, b = 1000.0, 3000.0
    da, db = duration(a), duration(b)
    length = a + (duration_s - da) * (b - a) / (db - da)  # duration is affine in the length
    if length <= 0:
        raise SystemExit(f"a {duration_s:.0f} s flight is shorter than the fixed part of the corridor flight "
                         f"({da - a * (db - da) / (b - a):.0f} s)")
    return round(length, 1)


PHASES = ("start", "build", "evaluation", "assembly", "normal", "factorisation", "covariance", "upsampling")
"""Phases of step 2 timed apart (as in bench/trajectory_vs_gtsam.py)."""


def adjust(project: str, backend: str = "auto", repeat: int = 3) -> dict:
    """Child process: filter and G/I adjustment of one project, ``repeat`` timed runs after a
    warm-up (the fastest run's totals, each phase's least time); timings, sizes and peak RSS."""
    import psutil
    import scipy.signal  # noqa: F401  (imported before the timing, as every other module)

    from georefine import workflows

    nav = workflows.load_navigation(project)
    tcfg = nav.config.processing.trajectory
    nav.config.processing.__dict__["trajectory"] = tcfg.model_copy(update={"linear_solver": backend})
    t = time.perf_counter()
    filt = workflows.step_initialise(nav)
    t_filter = time.perf_counter() - t
    rss_before = psutil.Process().memory_info().rss
    # A warm-up run first: numba's kernels load from its disk cache (or compile, after a change) on
    # first use, a fixed cost every case would pay once and which bent the slopes.
    workflows.step_adjust_gnss_imu(nav, filt)
    t_adjust, adj, phases = float("inf"), None, None
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        run = workflows.step_adjust_gnss_imu(nav, filt)
        elapsed = time.perf_counter() - t
        lm, tm = run.solve.timings, run.timings_s
        # J and N formed for the posterior (where the solve did not leave them): assembly, normal.
        times = {"start": tm["start"], "build": tm["build"], "evaluation": lm.evaluation_s,
                 "assembly": lm.assembly_s + tm.get("covariance_assembly", 0.0),
                 "normal": lm.normal_s + tm.get("covariance_normal", 0.0), "factorisation": lm.factorization_s,
                 "covariance": tm["covariance"], "upsampling": tm.get("upsampling", 0.0)}
        # Each phase's least time over the runs (the runs are the same computation: what differs
        # is the machine's noise, which moved single phases by up to 20 %).
        phases = times if phases is None else {k: min(v, times[k]) for k, v in phases.items()}
        if elapsed < t_adjust:
            t_adjust, adj = elapsed, run
        del run
    s = adj.solve
    return {
        "phases": phases,
        "backend": s.backend,
        "filter_s": t_filter,
        "adjust_s": t_adjust,
        "solve_s": adj.timings_s["solve"],
        "covariance_s": adj.timings_s["covariance"],
        "factorization_s": s.timings.factorization_s,
        "iterations": s.iterations,
        "accepted": s.successful_iterations,
        "unknowns": s.n_unknowns,
        "residuals": s.n_residuals,
        "termination": s.termination,
        "rss_before_gb": rss_before / 2**30,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,  # KiB on Linux
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", type=float, nargs="+", default=[5.0, 10.0, 20.0], help="flight minutes")
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--keep", type=Path, default=None, help="simulate into / reuse the projects in this folder")
    ap.add_argument("--backend", default="auto", help="sparse Cholesky backend (processing.trajectory.linear_solver)")
    ap.add_argument("--repeat", type=int, default=3,
                    help="timed runs per case after a warm-up; the fastest run and each phase's least time are reported")
    args = ap.parse_args()

    from georefine.sim.scenarios import simulate_project

    base = args.keep or Path(tempfile.mkdtemp(prefix="georefine-bench-"))
    base.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for minutes in args.durations:
            length = corridor_length_for(60.0 * minutes)
            project = base / f"corridor-{minutes:g}min-seed{args.seed}"
            if not (project / "truth" / "scenario.yaml").exists():
                if project.exists():
                    shutil.rmtree(project)
                t = time.perf_counter()
                simulate_project("corridor", project, seed=args.seed,
                                 overrides=[*SIM_OVERRIDES, f"scene.length_m={length}"])
                print(f"simulated {project.name} (scene.length_m={length}) in {time.perf_counter() - t:.1f} s",
                      flush=True)
            truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
            with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
                r = pool.submit(adjust, str(project), args.backend, args.repeat).result()
            r.update(minutes=minutes, length_m=length, duration_min=truth["duration_s"] / 60.0)
            rows.append(r)
            print(f"  {minutes:g} min: adjustment {r['adjust_s']:.1f} s ({r['termination']})", flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)

    print()
    print(f"{'target':>6} {'length':>7} {'flight':>6} {'unknowns':>9} {'iter':>6} {'solve':>7} {'cov':>6} {'adjust':>7}"
          f" {'solve/':>7} {'adjust/':>7} {'solve/':>7} {'ratio to first':>15} {'filter':>6} {'RSS':>5} {'peak':>5}")
    print(f"{'min':>6} {'m':>7} {'min':>6} {'':>9} {'':>6} {'s':>7} {'s':>6} {'s':>7}"
          f" {'min':>7} {'min':>7} {'iter':>7} {'solve':>7} {'adjust':>7} {'s':>6} {'GB':>5} {'GB':>5}")
    first = rows[0]
    f_solve = first["solve_s"] / first["duration_min"]
    f_adjust = first["adjust_s"] / first["duration_min"]
    for r in rows:
        d = r["duration_min"]
        print(f"{r['minutes']:6g} {r['length_m']:7.0f} {d:6.2f} {r['unknowns']:9,} {r['iterations']:>3}/{r['accepted']:<2}"
              f" {r['solve_s']:7.1f} {r['covariance_s']:6.1f} {r['adjust_s']:7.1f} {r['solve_s'] / d:7.2f} {r['adjust_s'] / d:7.2f}"
              f" {r['solve_s'] / r['iterations']:7.2f} {r['solve_s'] / d / f_solve:7.2f} {r['adjust_s'] / d / f_adjust:7.2f}"
              f" {r['filter_s']:6.1f} {r['rss_before_gb']:5.2f} {r['peak_rss_gb']:5.2f}")
    print("adjust = spline fit + problem + solve + cov (posterior covariances); '/min' per minute of flight; "
          "'ratio to first' = time per minute relative to the first row (1.00 = linear); "
          "RSS before the adjustment and peak of the child process")
    print(f"\nphases of step 2 (s; backend {rows[0]['backend']}; 'adjust' above is their sum without up-sampling, "
          "plus what lies between them)")
    print(f"{'min':>6}" + "".join(f" {p:>13}" for p in PHASES))
    for r in rows:
        print(f"{r['minutes']:6g}" + "".join(f" {r['phases'][p]:13.3f}" for p in PHASES))
    if len(rows) > 1:
        d = np.log([r["duration_min"] for r in rows])
        print(f"{'slope':>6}" + "".join(f" {np.polyfit(d, np.log([max(r['phases'][p], 1e-6) for r in rows]), 1)[0]:13.2f}"
                                        for p in PHASES) + "   (log-log against duration; 1 = linear)")
        for key in ("solve_s", "covariance_s", "adjust_s"):
            slope = np.polyfit(d, np.log([r[key] for r in rows]), 1)[0]
            per_it = np.polyfit(d, np.log([r[key] / r["iterations"] for r in rows]), 1)[0] if key == "solve_s" else None
            print(f"log-log slope of {key[:-2]} time against duration: {slope:.2f}"
                  + (f" (per iteration {per_it:.2f})" if per_it is not None else "") + "; 1 = linear")


if __name__ == "__main__":
    main()
