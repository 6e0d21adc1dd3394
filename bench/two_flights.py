"""Two flights adjusted together against each flight alone (a script, not a test).

For each seed the ``two-flights`` scenario (the 3 km ``corridor`` flown on two days: strips 1, 2
in flight 1 and 3, 4 in flight 2, each flight with its own static alignment, IMU turn-on biases
and GNSS session; docs/ARCHITECTURE.md §6) is simulated with a boresight error in
``project.yaml`` (``--boresight-error``, mdeg per angle) and ``processing.lidar.estimate_boresight``,
then run three times, the process tree's peak memory sampled (``bench/proctree.py``):
``georefine run`` on the whole project (one G/I/L holding both flights, one boresight and one
LiDAR time offset: ``workflows/flights.py``), and each flight alone (``Project.flight_project``,
sharing the G/I through one step cache). Printed per seed:

* per strip, the G/I/L roll/pitch/yaw RMSE against the truth, together and alone, the stated
  sigma, and the RMS of error/sigma together;
* the boresight and the time offset, together and alone, with their sigmas, and their error in
  sigmas against the truth (boresight: the scenario's; time offset: 0);
* wall time and peak memory of each run;

and over all seeds, per angle: on how many flights the joint run is at least as good as the
flight alone (RMSE over the flight's strips), and the RMS over seeds and flights of both. With
one boresight for both flights, each flight gets about the mean of the flights' heading errors
alone, so one draw may favour either; the RMS over seeds says which is better.
``--scenario two-flights-tiny`` (corridor-tiny on two days, minutes per seed) gives many seeds.

Usage::

    python bench/two_flights.py WORKDIR [--seeds 42 7] [--boresight-error 40 -40 50] [--scenario two-flights-tiny]

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

RUN_ALONE = """
import sys
from georefine.workflows.lidar import run_workflow
from georefine.workflows.opened import open_project
run_workflow(open_project(sys.argv[1]).flight_project(int(sys.argv[2])), sys.argv[3], cache_dir=sys.argv[4])
"""


def simulate(project: Path, scenario: str, seed: int, error_mdeg: np.ndarray) -> np.ndarray:
    """The project (made once) and its true boresight (deg)."""
    if not (project / "truth" / "scenario.yaml").exists():
        from georefine.sim.scenarios import resolve_scenario

        true = np.array(resolve_scenario(scenario).boresight_deg)
        stated = true + error_mdeg * 1e-3
        args = ["georefine", "simulate", scenario, "--out", str(project), "--seed", str(seed),
                "--set", "project_boresight_deg=[" + ",".join(f"{v:.6f}" for v in stated) + "]"]
        wall, peak, res = run_measured(args)
        if res.returncode:
            sys.exit(f"simulation failed:\n{res.stderr[-3000:]}")
        cfg = yaml.safe_load((project / "project.yaml").read_text())
        cfg.setdefault("processing", {}).setdefault("lidar", {})["estimate_boresight"] = True
        (project / "project.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        print(f"simulated {project.name} in {wall:.0f} s", flush=True)
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    return np.array(truth["scenario"]["boresight_deg"])


def measured(args: list[str], out: Path) -> dict:
    record = out.parent / f"{out.name}.measure.json"
    if (out / "metrics.json").exists() and record.exists():
        return json.loads(record.read_text())
    wall, peak, res = run_measured(args)
    if res.returncode:
        sys.exit(f"{' '.join(args[:3])} failed:\n{res.stderr[-3000:]}")
    m = {"wall_s": wall, "peak_gb": peak}
    record.write_text(json.dumps(m))
    return m


def report_of(folder: Path):
    from georefine.io.run_metrics import read_adjustment_report

    return read_adjustment_report(folder / "adjustment.json")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[42, 7])
    ap.add_argument("--boresight-error", type=float, nargs=3, default=[40.0, -40.0, 50.0], help="mdeg")
    ap.add_argument("--scenario", default="two-flights", choices=["two-flights", "two-flights-tiny"])
    args = ap.parse_args()
    from georefine.evaluation.trajectory_files import truth_pass_accuracy
    from georefine.io.run_metrics import WorkflowMetrics
    from georefine.workflows.opened import open_project

    args.workdir.mkdir(parents=True, exist_ok=True)
    rmse: dict[str, list[np.ndarray]] = {"together": [], "alone": []}  # per (seed, flight): RMSE over its strips
    for seed in args.seeds:
        name = f"{args.scenario}-s{seed}"
        project = args.workdir / name
        true_bs = simulate(project, args.scenario, seed, np.array(args.boresight_error))
        joint = args.workdir / f"{name}-joint"
        cache = args.workdir / f"{name}-cache"
        times = {"together": measured(["georefine", "run", str(project), "--out", str(joint)], joint)}
        alone = {f.id: args.workdir / f"{name}-alone{f.id}" for f in open_project(project).flights}
        for f, out in alone.items():
            times[f"flight {f} alone"] = measured(
                [sys.executable, "-c", RUN_ALONE, str(project), str(f), str(out), str(cache)], out)
        flights = {f: WorkflowMetrics.read(out / "metrics.json").strips for f, out in alone.items()}  # its strip ids
        print(f"\n## {args.scenario}, seed {seed}\n")
        print("| flight | strip | together roll / pitch / yaw (mdeg) | alone | sigma together / alone (yaw) "
              "| together error/sigma |")
        print("|---:|---:|---|---|---|---|")
        for f, strips in flights.items():
            per_strip = {"together": [], "alone": []}
            for s in strips:
                j = truth_pass_accuracy(joint / "gil" / f"flight_{f}" / "trajectory.sbet", project, s)
                a = truth_pass_accuracy(alone[f] / "gil" / "trajectory.sbet", project, s)
                per_strip["together"].append(j.rmse_mdeg)
                per_strip["alone"].append(a.rmse_mdeg)
                print(f"| {f} | {s} | {' / '.join(f'{v:.2f}' for v in j.rmse_mdeg)} "
                      f"| {' / '.join(f'{v:.2f}' for v in a.rmse_mdeg)} "
                      f"| {j.sigma_rms_mdeg[2]:.2f} / {a.sigma_rms_mdeg[2]:.2f} "
                      f"| {' / '.join(f'{v:.2f}' for v in j.z_rms)} |")
            for k, v in per_strip.items():
                rmse[k].append(np.sqrt(np.mean(np.square(v), axis=0)))
        print("\n| solution | boresight r / p / y (mdeg) | sigma (mdeg) | error / sigma | time offset (ms) |")
        print("|---|---|---|---|---|")
        folders = {"together": joint / "gil" / "flight_1",
                   **{f"flight {f} alone": out / "gil" for f, out in alone.items()}}
        for label, folder in folders.items():
            r = report_of(folder)
            est, sig = np.array(r.boresight_deg), np.array(r.boresight_sigma_mdeg)
            err = (est - true_bs) * 1e3
            o = r.lidar_time_offset
            off = "held" if o is None or o.sigma_ms is None else f"{o.estimate_s * 1e3:+.3f} ± {o.sigma_ms:.3f}"
            print(f"| {label} | {' / '.join(f'{v * 1e3:.1f}' for v in est)} | {' / '.join(f'{v:.2f}' for v in sig)} "
                  f"| {' / '.join(f'{v:.2f}' for v in err / sig)} | {off} |")
        print("\n" + "; ".join(f"{k}: {v['wall_s']:.0f} s, {v['peak_gb']:.2f} GB" for k, v in times.items()))
    together, alone = np.array(rmse["together"]), np.array(rmse["alone"])
    print(f"\n## over {len(args.seeds)} seed(s), {len(together)} flights\n")
    print("| angle | flights at least as good together | RMS together (mdeg) | RMS alone |")
    print("|---|---|---|---|")
    for k, angle in enumerate(("roll", "pitch", "yaw")):
        print(f"| {angle} | {int(np.sum(together[:, k] <= alone[:, k]))} of {len(together)} "
              f"| {np.sqrt(np.mean(together[:, k] ** 2)):.2f} | {np.sqrt(np.mean(alone[:, k] ** 2)):.2f} |")


if __name__ == "__main__":
    main()
