"""G/I and G/I/L adjustment time and memory against the flight length (a script, not a test).

For each flight length (default 10, 30 and 60 minutes) the ``corridor`` scenario is lengthened
(``scene.length_m`` solved from the flight planner, as in ``bench/trajectory_scaling.py``) and
simulated with a LiDAR that keeps the planar features representative at a quarter of the
points: 25 kHz at 60 lines/s (0.8 m across and 0.9 m along track per view, ~1.4 points/m²)
with a 2 m feature radius (``processing.planes.radius_m``) holds about the points a 1 m ball
holds at the default 100 kHz. Then ``georefine run --no-points`` (steps 1-5, default
configuration otherwise: up-sampling on, at most three outer iterations, the first on 0.25 s
knots) runs in a fresh child process per case so that its peak memory is its own.

``--feature-tiles 200 whole`` runs each flight once per ``processing.scale.feature_tile_m`` (``whole``:
the whole flight's features held and matched at once), in folders ``corridor-<N>min-t<tiles>``.

``--rate 100000`` simulates the corridor's own scanner (100 kHz, 120 lines/s) and keeps the default
1 m feature radius, in folders ``corridor-<N>min-100khz``.

``--budget 7000 20000`` runs each flight once per ``processing.lidar.max_features_per_minute``, in
folders ``corridor-<N>min-b<budget>``.

``--knots 0.1 0.25`` runs each flight once per knot interval (``processing.trajectory.knot_interval_s``,
IMU window a fifth of it), each in a folder ``corridor-<N>min-k<knots>`` beside the simulated
project that links its data and holds its own ``project.yaml``.

Printed per case: flight minutes, knot interval, features and objects used by the last G/I/L
adjustment, roll/pitch/yaw RMSE of the G/I/L trajectory against the truth over both passes,
the initialisation filter's time, the G/I adjustment time (step 2, without the filter), the
G/I/L adjustment time (all outer iterations, each building and solving its problem; feature
extraction and matching have their own column) with each outer iteration's time and
trajectory change, the G/I/L posterior, the whole run, peak memory, and the time per minute of
flight relative to the first case (1.00 = linear); then log-log slopes, and a log-log plot
(``--plot``).

Usage::

    python bench/flight_length.py WORKDIR [--durations 10 30 60] [--knots 0.1 0.25] [--feature-tiles 200 whole]
                                  [--budget 7000 20000]
                                  [--plot flight_length.png]

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
FULL_RATE = 100_000
"""``--rate 100000``: the corridor's own scanner (100 kHz, 120 lines/s) and the default 1 m feature radius."""


def simulate(workdir: Path, minutes: float, rate: int | None = None) -> Path:
    """The ``corridor`` lengthened to ``minutes`` of flight in WORKDIR (kept), at 25 kHz with a 2 m
    feature radius, or at the corridor's 100 kHz with the default radius (``rate`` 100000)."""
    from georefine.sim.scenarios import simulate_project

    full = rate == FULL_RATE
    if rate not in (None, FULL_RATE):
        raise SystemExit(f"--rate: 100000 (the corridor's scanner) or none (25 kHz), got {rate}")
    project = workdir / (f"corridor-{minutes:g}min" + ("-100khz" if full else ""))
    if not (project / "truth" / "scenario.yaml").exists():
        length = corridor_length_for(60.0 * minutes)
        t = time.perf_counter()
        simulate_project("corridor", project, seed=42,
                         overrides=[*([] if full else SIM_OVERRIDES), f"scene.length_m={length}"])
        if not full:
            cfg = yaml.safe_load((project / "project.yaml").read_text())
            cfg["processing"] = PROCESSING
            (project / "project.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        print(f"simulated {project.name} ({length:.0f} m) in {time.perf_counter() - t:.0f} s", flush=True)
    return project


def with_knots(project: Path, knots: float | None, tiles: str | None = None, budget: int | None = None) -> Path:
    """``project`` itself (``knots``, ``tiles`` and ``budget`` None), or a sibling that links its data
    with other knots, feature tiles (``processing.scale.feature_tile_m``: metres, or ``whole`` for
    null) or features per minute (``processing.lidar.max_features_per_minute``)."""
    if knots is None and tiles is None and budget is None:
        return project
    name = (project.name + ("" if knots is None else f"-k{knots:g}") + ("" if tiles is None else f"-t{tiles}")
            + ("" if budget is None else f"-b{budget}"))
    variant = project.with_name(name)
    variant.mkdir(exist_ok=True)
    for entry in project.iterdir():
        if entry.name != "project.yaml" and not (variant / entry.name).exists():
            (variant / entry.name).symlink_to(entry.resolve())
    cfg = yaml.safe_load((project / "project.yaml").read_text())
    if knots is not None:
        cfg.setdefault("processing", {})["trajectory"] = {"knot_interval_s": knots, "imu_window_s": knots / 5.0}
    if tiles is not None:
        cfg.setdefault("processing", {})["scale"] = {"feature_tile_m": None if tiles == "whole" else float(tiles)}
    if budget is not None:
        cfg.setdefault("processing", {})["lidar"] = {"max_features_per_minute": int(budget)}
    (variant / "project.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return variant


def pass_rmse(project: Path, out: Path) -> tuple[np.ndarray, list[float]]:
    """Roll, pitch, yaw RMSE (mdeg) of the G/I/L trajectory over both passes, and the mean roll
    error of each pass (mdeg): opposite means on passes flown in opposite directions are one tilt
    of the world, which the planes both passes share cannot see."""
    from georefine.evaluation.trajectory_files import truth_pass_comparison

    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    stats = [truth_pass_comparison(out / "gil" / "trajectory.sbet", project, int(p["strip_id"])).stats
             for p in truth["passes"]]
    per_pass = [[st[f"{a}_rmse_mdeg"] for a in ("roll", "pitch", "yaw")] for st in stats]
    return np.sqrt(np.mean(np.square(per_pass), axis=0)), [st["roll_mean_mdeg"] for st in stats]


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
    ap.add_argument("--knots", type=float, nargs="+", default=[None],
                    help="knot intervals (s); default: the project's configuration")
    ap.add_argument("--feature-tiles", nargs="+", default=[None],
                    help="processing.scale.feature_tile_m per run (metres, or 'whole': the whole flight's features "
                         "held and matched at once); default: the project's configuration")
    ap.add_argument("--budget", type=int, nargs="+", default=[None],
                    help="processing.lidar.max_features_per_minute per run; default: the project's configuration")
    ap.add_argument("--rate", type=int, default=None,
                    help="100000: the corridor's own 100 kHz scanner and 1 m feature radius (folders "
                         "corridor-<N>min-100khz); default 25 kHz with a 2 m radius")
    ap.add_argument("--plot", type=Path, default=None, help="log-log plot (PNG); default WORKDIR/flight_length.png")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for minutes, knots, tiles, budget in [(m, k, t, b) for b in args.budget for t in args.feature_tiles
                                          for k in args.knots for m in args.durations]:
        simulated = simulate(args.workdir, minutes, args.rate)
        project = with_knots(simulated, knots, tiles, budget)
        out = args.workdir / ("run-" + project.name.removeprefix("corridor-"))
        with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
            r = pool.submit(run, str(project), str(out)).result()
        m, t = r["metrics"], r["metrics"]["timings_s"]
        truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
        cfg = yaml.safe_load((project / "project.yaml").read_text())
        last = m["outer_iterations"][-1]
        row = {
            "minutes": truth["duration_s"] / 60.0,
            "knots": cfg.get("processing", {}).get("trajectory", {}).get("knot_interval_s", 0.1),
            "tiles": tiles or "default",
            "budget": budget or "default",
            "rpy": pass_rmse(simulated, out)[0], "roll_mean": pass_rmse(simulated, out)[1], "wall_s": r["wall_s"], "peak_gb": r["peak_rss_gb"],
            # "gi_adjustment" times steps 1-2 (the cached stage); the G/I adjustment is step 2.
            "filter_s": t.get("filter", np.nan), "gi_s": t.get("gi_adjustment", np.nan) - t.get("filter", 0.0),
            "gil_s": _sum(t, "gil_adjustment_"),
            "features_s": _sum(t, "features_"), "matching_s": _sum(t, "matching_"),
            "posterior_s": t.get("gil_covariance", np.nan), "iterations": len(m["outer_iterations"]),
            "features": last["features_used"], "objects": last["objects_used"],
            "each": [(t.get(f"gil_adjustment_{it['iteration']}", np.nan), it["attitude_change_mdeg"])
                     for it in m["outer_iterations"]],
        }
        rows.append(row)
        print(f"  {row['minutes']:.1f} min, {row['knots']:g} s knots, feature tiles {row['tiles']}, budget {row['budget']}: G/I {row['gi_s']:.1f} s, G/I/L {row['gil_s']:.1f} s "
              f"({row['iterations']} outer iterations, {row['features']:,} features), whole run {row['wall_s']:.0f} s, "
              f"peak {row['peak_gb']:.2f} GB, G/I/L roll/pitch/yaw {np.round(row['rpy'], 2).tolist()} mdeg "
              f"(mean roll per pass {', '.join(f'{m:+.2f}' for m in row['roll_mean'])})", flush=True)

    print("\n| flight | knots | filter (step 1) | G/I adjustment (step 2) | G/I/L adjustments | outer iterations (time each; change each) "
          "| features / objects | feature tiles | features per minute | features + matching | G/I/L posterior | whole run | peak memory | G/I per min : first | G/I/L per min : first "
          "| G/I/L roll | pitch | yaw (mdeg) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        first = next(f for f in rows if (f["knots"], f["tiles"], f["budget"]) == (r["knots"], r["tiles"], r["budget"]))
        print(f"| {r['minutes']:.1f} min | {r['knots']:g} s | {r['filter_s']:.1f} s | {r['gi_s']:.1f} s | {r['gil_s']:.1f} s "
              f"| {r['iterations']} ({' + '.join(f'{t:.0f}' for t, _ in r['each'])} s; "
              f"{' / '.join(f'{c:.2f}' for _, c in r['each'])} mdeg) "
              f"| {r['features']:,} / {r['objects']:,} | {r['tiles']} | {r['budget']} | {r['features_s'] + r['matching_s']:.0f} s | {r['posterior_s']:.1f} s "
              f"| {r['wall_s']:.0f} s | {r['peak_gb']:.2f} GB "
              f"| {r['gi_s'] / r['minutes'] / (first['gi_s'] / first['minutes']):.2f} "
              f"| {r['gil_s'] / r['minutes'] / (first['gil_s'] / first['minutes']):.2f} "
              f"| {r['rpy'][0]:.2f} | {r['rpy'][1]:.2f} | {r['rpy'][2]:.2f} |")
    for knots, tiles, budget in dict.fromkeys((r["knots"], r["tiles"], r["budget"]) for r in rows):
        same = [r for r in rows if (r["knots"], r["tiles"], r["budget"]) == (knots, tiles, budget)]
        if len(same) > 1:
            d = np.log([r["minutes"] for r in same])
            for key in ("gi_s", "gil_s", "peak_gb", "wall_s"):
                slope = np.polyfit(d, np.log([r[key] for r in same]), 1)[0]
                print(f"{knots:g} s knots, feature tiles {tiles}, budget {budget}: log-log slope of {key} against flight length: {slope:.2f} (1 = linear)")
    _plot(rows, args.plot or args.workdir / "flight_length.png")


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.8))
    styles = ("o-", "s--", "^-.", "d:")
    for i, case in enumerate(dict.fromkeys((r["knots"], r["tiles"], r["budget"]) for r in rows)):
        same = [r for r in rows if (r["knots"], r["tiles"], r["budget"]) == case]
        x, style = np.array([r["minutes"] for r in same]), styles[i % len(styles)]
        name = f"{case[0]:g} s knots" + (f", tiles {case[1]}" if case[1] != "default" else "") + (
            f", {case[2]}/min" if case[2] != "default" else "")
        for j, (key, label) in enumerate((("gi_s", "G/I"), ("gil_s", "G/I/L"), ("wall_s", "whole run"))):
            a.loglog(x, [r[key] for r in same], style, color=f"C{j}", label=f"{label}, {name}")
        b.loglog(x, [r["peak_gb"] for r in same], style, color="C0", label=f"peak memory, {name}")
    x = np.array(sorted({r["minutes"] for r in rows}))
    a.loglog(x, 300.0 * x / x[-1], "k:", label="linear (5 min at the longest)")
    a.set_xlabel("flight (min)")
    a.set_ylabel("time (s)")
    a.legend(fontsize=7)
    first = min(rows, key=lambda r: r["minutes"])
    b.loglog(x, first["peak_gb"] * x / x[0], "k:", label="linear")
    b.set_xlabel("flight (min)")
    b.set_ylabel("GB")
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


if __name__ == "__main__":
    main()
