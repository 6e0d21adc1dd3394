"""An area block end to end: per-strip attitude, strip-pair differences, time and memory (a script, not a test).

For each seed the ``area`` scenario (8 parallel strips at 30 % sidelap in a racetrack order and
2 cross strips, 46 minutes of flight; docs/ARCHITECTURE.md §6 "Flight plans") is simulated, run
with ``georefine run`` (default configuration) in a child process whose process tree's peak
memory is sampled (``bench/proctree.py``), and evaluated against its truth
(:func:`georefine.api.evaluate_run`). Printed per seed:

* per strip, the G/I and G/I/L roll/pitch/yaw RMSE against the truth (mdeg), the G/I/L's RMS of
  error/sigma per angle (its stated posterior against the actual error), the per-strip baseline's
  figures where the run has them, and the checks of the block's acceptance: G/I/L yaw at most
  0.3 x G/I or at most 3 mdeg; roll and pitch never worse than G/I by more than 10 % + 0.3 mdeg;
  RMS of error/sigma within 0.5-2;
* the strip-pair matrix (median and P95 of the differences on planar surfaces, G/I -> G/I/L) and
  whether every overlapping pair's G/I/L median is at most 5 mm;
* the run's wall time, its peak memory, and the G/I/L time per outer iteration.

``--corridor`` also simulates and runs a ``corridor`` of the same flight time and the same strip
time (two passes whose length gives the block's seconds of strips; the static alignment makes up
the rest of the flight), and prints its G/I/L time per outer iteration beside the block's: the
cost of the trajectory coupling that cross strips bring.

Usage::

    python bench/area_block.py WORKDIR [--seeds 42 7] [--corridor]

Projects and runs already in WORKDIR are reused (delete a folder to measure it again).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from proctree import run_measured  # noqa: E402

ANGLES = ("roll", "pitch", "yaw")


def simulate(project: Path, scenario: str, seed: int, overrides: list[str] = ()) -> None:
    if (project / "truth" / "scenario.yaml").exists():
        return
    args = ["georefine", "simulate", scenario, "--out", str(project), "--seed", str(seed)]
    for o in overrides:
        args += ["--set", o]
    wall, peak, res = run_measured(args)
    if res.returncode:
        sys.exit(f"simulation failed:\n{res.stderr[-3000:]}")
    print(f"simulated {project.name} in {wall:.0f} s (peak {peak:.2f} GB)", flush=True)


def run(project: Path, out: Path) -> dict:
    """``georefine run``; wall time and peak memory (recorded beside the run, so a reused run keeps them)."""
    record = out.parent / f"{out.name}.measure.json"
    if (out / "metrics.json").exists() and record.exists():
        return json.loads(record.read_text())
    wall, peak, res = run_measured(["georefine", "run", str(project), "--out", str(out)])
    if res.returncode:
        sys.exit(f"run failed:\n{res.stderr[-3000:]}")
    m = {"wall_s": wall, "peak_gb": peak}
    record.write_text(json.dumps(m))
    return m


def per_outer_iteration(out: Path) -> tuple[float, int]:
    """Mean G/I/L adjustment time per outer iteration (s) and the number of outer iterations."""
    m = json.loads((out / "metrics.json").read_text())
    t = m["timings_s"]
    each = [v for k, v in t.items() if k.startswith("gil_adjustment_")]
    return float(np.mean(each)), len(each)


def strip_table(project: Path, out: Path) -> list[dict]:
    from georefine.evaluation.trajectory_files import truth_pass_accuracy

    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    rows = []
    for p in truth["passes"]:
        sid = int(p["strip_id"])
        gi = truth_pass_accuracy(out / "gi" / "trajectory.sbet", project, sid)
        gil = truth_pass_accuracy(out / "gil" / "trajectory.sbet", project, sid)
        row = {"strip": sid, "gi": gi.rmse_mdeg, "gil": gil.rmse_mdeg, "z": gil.z_rms, "gi_z": gi.z_rms}
        baseline = out / "baseline" / "trajectory.sbet"
        if baseline.exists():
            row["baseline"] = truth_pass_accuracy(baseline, project, sid).rmse_mdeg
        rows.append(row)
    return rows


def checks(row: dict) -> dict:
    gi, gil, z = row["gi"], row["gil"], row["z"]
    return {
        "yaw": bool(gil[2] <= 0.3 * gi[2] or gil[2] <= 3.0),
        "roll/pitch": bool(np.all(gil[:2] <= 1.1 * gi[:2] + 0.3)),
        "error/sigma": bool(np.all((z >= 0.5) & (z <= 2.0))),
    }


def evaluate(project: Path, out: Path) -> dict:
    summary = out / "evaluation" / "summary.json"
    if not summary.exists():
        import georefine

        georefine.evaluate_run(project, out)
    return json.loads(summary.read_text())


def report(seed: int, project: Path, out: Path, measured: dict) -> tuple[float, bool]:
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    summary = evaluate(project, out)
    rows = strip_table(project, out)
    points = sum(truth["points_per_strip"].values())
    print(f"\n## area, seed {seed}: {len(rows)} strips, {truth['duration_s'] / 60:.1f} min of flight, {points:,} points\n")
    has_baseline = any("baseline" in r for r in rows)
    head = "| strip | G/I roll / pitch / yaw | G/I/L roll / pitch / yaw | G/I/L error/sigma |"
    head += " per-strip baseline |" if has_baseline else ""
    print(head + " yaw | roll/pitch | error/sigma |")
    print("|---:|---|---|---|" + ("---|" if has_baseline else "") + "---|---|---|")
    ok = True
    for r in rows:
        c = checks(r)
        ok &= all(c.values())
        line = (f"| {r['strip']} | {' / '.join(f'{v:.2f}' for v in r['gi'])} | {' / '.join(f'{v:.2f}' for v in r['gil'])} "
                f"| {' / '.join(f'{v:.2f}' for v in r['z'])} |")
        if has_baseline:
            line += f" {' / '.join(f'{v:.2f}' for v in r['baseline'])} |" if "baseline" in r else " - |"
        print(line + "".join(f" {'yes' if v else 'NO'} |" for v in c.values()))
    pairs = summary.get("strip_pairs") or {}
    worst = np.nan
    if "G/I/L" in pairs:
        before = {(p["strip_a"], p["strip_b"]): p for p in pairs.get("G/I", {}).get("pairs", [])}
        print("\n| pair | planar cells | G/I median / P95 (mm) | G/I/L median / P95 (mm) |")
        print("|---|---:|---|---|")
        medians = []
        for p in pairs["G/I/L"]["pairs"]:
            if p["median_mm"] is None:
                continue
            b = before.get((p["strip_a"], p["strip_b"]), {})
            medians.append(p["median_mm"])
            gi_text = f"{b['median_mm']:.1f} / {b['p95_mm']:.1f}" if b.get("median_mm") is not None else "-"
            print(f"| {p['strip_a']}-{p['strip_b']} | {p['cells']:,} | {gi_text} | {p['median_mm']:.1f} / {p['p95_mm']:.1f} |")
        worst = max(medians) if medians else np.nan
        print(f"\noverlapping pairs: {len(medians)}; largest G/I/L median {worst:.2f} mm "
              f"({'at most' if worst <= 5.0 else 'MORE than'} 5 mm)")
        ok &= bool(worst <= 5.0)
    else:
        print("\nno strip-pair figures in the evaluation")
        ok = False
    per_it, n_it = per_outer_iteration(out)
    print(f"\nrun: {measured['wall_s']:.0f} s wall, peak {measured['peak_gb']:.2f} GB; G/I/L {per_it:.1f} s per outer "
          f"iteration ({n_it} iterations)")
    print(f"all checks {'hold' if ok else 'do NOT hold'} for seed {seed}")
    return per_it, ok


def corridor_like(workdir: Path, area_project: Path) -> Path:
    """A corridor with the block's strip seconds and flight duration (the static alignment fills the rest)."""
    from georefine.sim.scenarios import flight_passes, resolve_scenario

    truth = yaml.safe_load((area_project / "truth" / "scenario.yaml").read_text())
    strip_s = sum(p["t_end_s"] - p["t_start_s"] for p in truth["passes"])
    corridor = resolve_scenario("corridor")
    lead = corridor.flight.lead_in_m + corridor.flight.lead_out_m
    length = strip_s / 2 * corridor.flight.speed_mps - lead
    probe = resolve_scenario("corridor", seed_overrides=[f"scene.length_m={length:.0f}"])
    end = flight_passes(probe, 42)[-1][2] + 3.0
    static = corridor.flight.static_duration_s + max(0.0, truth["duration_s"] - end)
    project = workdir / "corridor-same-time"
    simulate(project, "corridor", 42, [f"scene.length_m={length:.0f}", f"flight.static_duration_s={static:.0f}"])
    return project


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[42, 7])
    ap.add_argument("--corridor", action="store_true", help="also a corridor of the same flight and strip time")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    per_it = {}
    for seed in args.seeds:
        project = args.workdir / f"area-s{seed}"
        simulate(project, "area", seed)
        out = args.workdir / f"area-s{seed}-run"
        measured = run(project, out)
        per_it[seed], _ = report(seed, project, out, measured)
    if args.corridor:
        project = corridor_like(args.workdir, args.workdir / f"area-s{args.seeds[0]}")
        out = args.workdir / "corridor-same-time-run"
        measured = run(project, out)
        t, n = per_outer_iteration(out)
        truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
        print(f"\ncorridor of the same flight time ({truth['duration_s'] / 60:.1f} min, "
              f"{sum(truth['points_per_strip'].values()):,} points): G/I/L {t:.1f} s per outer iteration ({n}); "
              f"block seed {args.seeds[0]}: {per_it[args.seeds[0]]:.1f} s ({per_it[args.seeds[0]] / t:.2f} x); run "
              f"{measured['wall_s']:.0f} s, peak {measured['peak_gb']:.2f} GB")


if __name__ == "__main__":
    main()
