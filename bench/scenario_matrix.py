"""G/I and G/I/L attitude across operating conditions: accuracy against the truth and honesty of the sigmas.

    python bench/scenario_matrix.py WORK [--design full|oat] [--only SUBSTRING ...] [--length 2400] [--draws 1]

The matrix (its own seeds, one per scenario; ``--draws K`` adds K - 1 more per scenario, seeds
1000 apart, so that the errors a single pass samples once -- the tilt of the whole scene, the
roll common to both passes -- are seen over several draws):

| factor | levels |
|---|---|
| IMU grade | mems (STIM300), tactical (HG1700), navigation (HG9900) |
| flight | slow-low: 18 m/s at 160 m AGL, 100 kHz; fast-high: 30 m/s at 300 m AGL, 300 kHz |
| GNSS | ppk-5hz (the simulator's default); ppk-1hz: 1 Hz with twice the white and correlated errors; outage: 60 s without GNSS from 10 s into pass 1, shortened to end 10 s before the pass does when the pass is shorter |
| latitude | mid (46.7 N, EPSG:25832), south (33.9 S, EPSG:32734), high (69.6 N, EPSG:32634) |
| vibration | off, on (rotor harmonics at 6.5/13/26 Hz) |

``--design full`` is all 108 combinations; ``--design oat`` the baseline of every IMU grade x
flight (ppk-5hz, mid, off) and every other level changed one at a time (6 per cell, 36 in all).
Each scenario is `corridor` at ``--length`` metres (both passes grow with it), simulated once,
then ``georefine run --no-points`` on both passes and on pass 1 alone. Each solution's SBET is
compared with the truth during each pass (1 s inset; ``truth_pass_accuracy``): roll, pitch and
yaw RMSE, and, from the ``smrmsg`` beside it, the RMS of error / stated sigma and the share of
epochs beyond three sigma.

Checks printed per row (the issue's acceptance): G/I/L no worse than G/I by more than 10 % +
0.3 mdeg in any angle; yaw at most 0.3 x G/I or 3 mdeg; RMS of error/sigma within 0.5-2 and at
most 1 % of epochs beyond 3 sigma, per angle and solution. Where a scenario has several draws the
accuracy checks are also applied to the RMS of each pass's RMSE over them (``over draws``):
a G/I/L at its bound is "worse" than a G/I pass that drew small, and only the draws tell the
estimators apart. One pass gives a low-frequency error
(a heading or tilt offset) one or two independent samples, so a single row's RMS of error/sigma
scatters widely even for exact sigmas (|N(0,1)| is below 0.5 in 38 % of draws); the summary
pools every row of an angle and solution, which is the test of the sigmas.

The column ``yaw/sigma`` is the G/I/L yaw RMSE over the RMS of the yaw sigma the solution
states; ``G/I/L : bound`` its roll, pitch and yaw RMSE over the Cramér-Rao bound of the run at
the true trajectory (:func:`georefine.workflows.cramer_rao.cramer_rao_bound`, with the a-priori
weights; the precision the simulated sensors allow), computed after the runs (``--no-bounds``:
not) and added to kept results that lack it while their runs are there. With it come the RMSE
of each model's optimum from the truth (the G/I's and the G/I/L's own adjustment converged from
the true trajectory: the error this draw of the noise allows) and the G/I's bound; a row that
fails the checks says whether the optima fail them too (``optima fail``: the model gives that
error on this draw, whether by chance or by a defect of its own; not the run's solve or start).

Results are kept per scenario in ``WORK/results/NAME.json`` (those of the last whole run of the
one-at-a-time design are in ``bench/results/scenario_matrix_oat``: ``python bench/scenario_matrix.py
bench/results/scenario_matrix_oat --length 1200 --report-only --markdown`` prints its tables, with
``--draws 3`` the scenarios drawn three times): a rerun skips scenarios done
(delete the file to redo one), so the matrix can be run in parts. ``--redo single`` (or
``both``) runs that solution of kept scenarios again, and its bound, and keeps the other: for a
change that only one of them can feel (the LiDAR time offset, which one strip cannot show, is
held in single passes).
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from georefine.errors import ConfigError
from georefine.evaluation.trajectory_files import truth_pass_accuracy
from georefine.sim.conditions import FLIGHT, GNSS, IMU, LATITUDE, VIBRATION, condition_overrides
from georefine.workflows.cramer_rao import cramer_rao_bound

OUTAGE_S = (10.0, 60.0, 10.0)  # starts this long into pass 1, lasts at most this, ends at least this before the pass


def scenarios(design: str) -> list[tuple[str, str, str, str, str]]:
    full = list(itertools.product(IMU, FLIGHT, GNSS, LATITUDE, VIBRATION))
    if design == "full":
        return full
    base = ("ppk-5hz", "mid", "off")
    keep = [s for s in full if sum(a != b for a, b in zip(s[2:], base)) <= 1]
    # every cell's baseline first, then the one-at-a-time changes: a partial run covers every cell
    return sorted(keep, key=lambda s: s[2:] != base)


def name_of(s) -> str:
    return "_".join(s)


def simulate(work: Path, s, seed: int, length: float, key: str) -> Path:
    imu, flight, gnss, lat, vib = s
    out = work / "projects" / key
    if (out / "truth" / "scenario.yaml").is_file() and (out / "scans").is_dir():  # the strips go once a run is done
        return out
    try:
        overrides = condition_overrides("corridor", imu, flight, gnss, lat, vib, seed,
                                        base=[f"scene.length_m={length:g}"], outage_s=OUTAGE_S)
    except ConfigError as exc:
        raise SystemExit(f"{key}: {exc} (--length)") from None
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "georefine", "simulate", "corridor", "--out", str(out), "--seed", str(seed),
           "--imu-grade", imu]
    for o in overrides:
        cmd += ["--set", o]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
    return out


def run(project: Path, out: Path, strips: str | None) -> dict:
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "georefine", "run", str(project), "--out", str(out), "--no-points"]
    if strips:
        cmd += ["--strips", strips]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("WARNING")]
    return {"wall_s": time.perf_counter() - t, "warnings": warnings}


def evaluate(project: Path, out: Path, strips: list[int]) -> dict:
    res = {}
    for sol in ("gi", "gil"):
        res[sol] = [truth_pass_accuracy(out / sol / "trajectory.sbet", project, k).to_dict() for k in strips]
    return res


def key_of(s, draw: int = 0) -> str:
    """File name of a scenario's draw: the name, and ``~K`` for the K-th extra seed (``--draws``)."""
    return name_of(s) + (f"~{draw}" if draw else "")


def has_bounds(rec: dict, kind: str) -> bool:
    """Whether ``rec[kind]`` holds the bound of every pass with the optima and the G/I's bound."""
    return bool(rec[kind].get("bound")) and all("gi" in b for b in rec[kind]["bound"])


def bounds(work: Path, key: str, rec: dict) -> dict:
    """``rec`` with the Cramér-Rao bound of both runs (``rec[kind]["bound"]``, per pass) where it has
    none and the runs and the project are still there (the bound needs no scans)."""
    project = work / "projects" / key
    for kind in ("both", "single"):
        run_dir = run_dir_of(work, key, kind)
        if has_bounds(rec, kind) or not (run_dir / "features" / "features.csv").is_file():
            continue
        if not (project / "truth" / "scenario.yaml").is_file():
            continue
        rec[kind]["bound"] = [p.to_dict() for p in cramer_rao_bound(project, run_dir).passes]
    return rec


def run_dir_of(work: Path, key: str, kind: str) -> Path:
    """Where the ``kind`` run (``both`` or ``single``) of scenario ``key`` goes."""
    return work / "runs" / (key if kind == "both" else f"{key}_single")


def solution(work: Path, project: Path, key: str, kind: str) -> dict:
    """Run ``kind`` (both passes, or the first pass alone) and evaluate it against the truth."""
    strips = [p["strip_id"] for p in yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"]]
    run_dir = run_dir_of(work, key, kind)
    done = run(project, run_dir, None if kind == "both" else str(strips[0]))
    return {**evaluate(project, run_dir, strips if kind == "both" else strips[:1]), **done}


def one(work: Path, s, seed: int, length: float, draw: int = 0, with_bounds: bool = True,
        again: str | None = None) -> dict:
    """Scenario ``s``'s draw: kept, or simulated and run; with ``again`` (``--redo``) that
    solution of a kept one run again and its bound dropped; the bounds added where missing."""
    key = key_of(s, draw)
    path = work / "results" / f"{key}.json"
    kept = path.is_file()
    if kept and again is None:
        rec = json.loads(path.read_text())
        if with_bounds and not all(has_bounds(rec, kind) for kind in ("both", "single")):
            rec = bounds(work, key, rec)
            path.write_text(json.dumps(rec, indent=1))
        return rec
    t = time.perf_counter()
    project = simulate(work, s, seed, length, key)
    if kept:
        rec = json.loads(path.read_text())
        rec[again] = solution(work, project, key, again)
        rec["wall_s"] = rec.get("wall_s", 0.0) + time.perf_counter() - t
    else:
        rec = {"scenario": dict(zip(("imu", "flight", "gnss", "latitude", "vibration"), s)), "seed": seed,
               "draw": draw, "length_m": length,
               **{kind: solution(work, project, key, kind) for kind in ("both", "single")}}
        rec["wall_s"] = time.perf_counter() - t
    if with_bounds:
        rec = bounds(work, key, rec)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rec, indent=1))
    shutil.rmtree(project / "scans", ignore_errors=True)  # the runs are done: the strips are the bulk
    return rec


ANGLES = ("roll", "pitch", "yaw")


def checks(gi: dict, gil: dict) -> list[str]:
    """The acceptance per pass: what fails, as short texts."""
    bad = []
    for a in ANGLES:
        g, l_ = gi["rmse_mdeg"][a], gil["rmse_mdeg"][a]
        if l_ > 1.1 * g + 0.3:
            bad.append(f"{a} {l_:.2f}>{g:.2f}")
    g, l_ = gi["rmse_mdeg"]["yaw"], gil["rmse_mdeg"]["yaw"]
    if not (l_ <= 0.3 * g or l_ <= 3.0):
        bad.append(f"yaw {l_:.2f} vs {g:.2f}")
    return bad


def optima_fail(gi: dict, gil: dict) -> bool | None:
    """Whether the two models' optima from the truth fail :func:`checks` too (None: not computed)."""
    a, b = gi.get("optimum_mdeg"), gil.get("optimum_mdeg")
    if not a or not b:
        return None
    return bool(checks({"rmse_mdeg": a}, {"rmse_mdeg": b}))


def fails_text(gi: dict, gil: dict) -> str:
    bad = checks(gi, gil)
    if not bad:
        return ""
    both = optima_fail(gi, gil)
    return "; ".join(bad) + ("" if both is None else " (optima fail)" if both else " (optima pass)")


def rows(rec: dict):
    for kind in ("both", "single"):
        for k in range(len(rec[kind]["gi"])):
            gi, gil = dict(rec[kind]["gi"][k]), dict(rec[kind]["gil"][k])
            bound = {b["strip"]: b for b in rec[kind].get("bound", [])}.get(gil["strip"])
            if bound is not None:
                gil["bound_mdeg"] = bound["sigma_rms_mdeg"]
                gil["optimum_mdeg"] = bound.get("optimum_rmse_mdeg")
                if "gi" in bound:
                    gi["bound_mdeg"] = bound["gi"]["sigma_rms_mdeg"]
                    gi["optimum_mdeg"] = bound["gi"]["optimum_rmse_mdeg"]
            yield kind, k, gi, gil


def fmt3(d: dict, f: str) -> str:
    return "/".join(("-" if d[a] is None else format(d[a], f)) for a in ANGLES)


def yaw_sigma(d: dict) -> str:
    """G/I/L yaw RMSE over the RMS of its stated sigma."""
    s = d.get("sigma_rms_mdeg", {}).get("yaw")
    return "-" if not s else f"{d['rmse_mdeg']['yaw'] / s:.2f}"


def over_bound(d: dict) -> str:
    """G/I/L roll/pitch/yaw RMSE over the Cramér-Rao bound at the truth (module docstring), or -."""
    b = d.get("bound_mdeg")
    return "-" if not b else fmt3({a: d["rmse_mdeg"][a] / b[a] for a in ANGLES}, ".2f")


def optimum(d: dict) -> str:
    """The RMSE of the model's optimum from the truth, roll/pitch/yaw (module docstring), or -."""
    b = d.get("optimum_mdeg")
    return "-" if not b else fmt3(b, ".2f")


def report_markdown(records: list[dict]) -> None:
    """The rows of :func:`report` as a Markdown table (BENCHMARKS.md)."""
    print("| scenario | run | pass | G/I r/p/y (mdeg) | G/I/L r/p/y (mdeg) | G/I/L : G/I | error/sigma G/I | "
          "error/sigma G/I/L | > 3 sigma G/I/L (%) | yaw/sigma | G/I/L : bound r/p/y | optimum G/I | "
          "optimum G/I/L | fails |")
    print("|---|---|---:|---|---|---|---|---|---|---:|---|---|---|---|")
    for rec in records:
        name = key_of(tuple(rec["scenario"].values()), rec.get("draw", 0))
        for kind, _k, gi, gil in rows(rec):
            ratio = {a: gil["rmse_mdeg"][a] / gi["rmse_mdeg"][a] for a in ANGLES}
            beyond = {a: 100 * gil["beyond_3_sigma"][a] for a in ANGLES}
            print(f"| {name} | {kind} | {gi['strip']} | {fmt3(gi['rmse_mdeg'], '.2f')} | {fmt3(gil['rmse_mdeg'], '.2f')} | "
                  f"{fmt3(ratio, '.2f')} | {fmt3(gi['z_rms'], '.2f')} | {fmt3(gil['z_rms'], '.2f')} | "
                  f"{fmt3(beyond, '.1f')} | {yaw_sigma(gil)} | {over_bound(gil)} | {optimum(gi)} | {optimum(gil)} | "
                  f"{fails_text(gi, gil) or '-'} |")


def over_draws(records: list[dict]) -> None:
    """The accuracy checks on the RMS over the draws of each scenario's pass (those with two or more).

    One draw samples once the errors that last a pass (the tilt of the scene, the common roll of
    both passes): there a G/I/L at its bound is "worse" than a G/I pass that drew small. Over
    draws the checks compare the two estimators' accuracy, not one draw of each.
    """
    groups: dict[tuple[str, str, int], list[tuple[dict, dict]]] = {}
    for rec in records:
        name = name_of(tuple(rec["scenario"].values()))
        for kind, k, gi, gil in rows(rec):
            groups.setdefault((name, kind, k), []).append((gi, gil))
    many = {key: v for key, v in groups.items() if len(v) > 1}
    if not many:
        return
    print("over draws (RMS of each pass's RMSE over the scenario's draws; the same checks):")
    n_fail = 0
    for (name, kind, _k), pairs in many.items():
        rms = [{a: float(np.sqrt(np.mean([p[i]["rmse_mdeg"][a] ** 2 for p in pairs]))) for a in ANGLES} for i in (0, 1)]
        bad = checks({"rmse_mdeg": rms[0]}, {"rmse_mdeg": rms[1]})
        n_fail += bool(bad)
        print(f"  {name:44s} {kind:6s} {pairs[0][0]['strip']:4d}  {len(pairs)} draws  G/I {fmt3(rms[0], '.2f'):16s} "
              f"G/I/L {fmt3(rms[1], '.2f'):16s} {'; '.join(bad)}")
    print(f"  passes failing the checks over draws: {n_fail} of {len(many)}")


def report(records: list[dict]) -> None:
    print(f"{'scenario':44s} {'run':6s} pass  {'G/I rmse r/p/y':16s} {'G/I/L rmse':16s} {'ratio':14s} "
          f"{'z G/I':14s} {'z G/I/L':14s} {'>3s G/I/L %':12s} {'yaw/sigma':9s} {'G/I/L:bound':14s} "
          f"{'opt G/I':16s} {'opt G/I/L':16s} fails")
    pooled = {sol: {a: [] for a in ANGLES} for sol in ("gi", "gil")}
    beyond = {sol: {a: [] for a in ANGLES} for sol in ("gi", "gil")}
    n_fail = n_fail_optima = 0
    for rec in records:
        name = key_of(tuple(rec["scenario"].values()), rec.get("draw", 0))
        for kind, _k, gi, gil in rows(rec):
            ratio = {a: gil["rmse_mdeg"][a] / gi["rmse_mdeg"][a] for a in ANGLES}
            fails = fails_text(gi, gil)
            n_fail += bool(fails)
            n_fail_optima += bool(fails) and optima_fail(gi, gil) is True
            for sol, d in (("gi", gi), ("gil", gil)):
                for a in ANGLES:
                    if d["z_rms"][a] is not None:
                        pooled[sol][a].append((d["z_rms"][a] ** 2, d["epochs"]))
                        beyond[sol][a].append((d["beyond_3_sigma"][a], d["epochs"]))
            print(f"{name:44s} {kind:6s} {gi['strip']:4d}  {fmt3(gi['rmse_mdeg'], '.2f'):16s} "
                  f"{fmt3(gil['rmse_mdeg'], '.2f'):16s} {fmt3(ratio, '.2f'):14s} {fmt3(gi['z_rms'], '.2f'):14s} "
                  f"{fmt3(gil['z_rms'], '.2f'):14s} {fmt3({a: 100 * gil['beyond_3_sigma'][a] for a in ANGLES}, '.1f'):12s} "
                  f"{yaw_sigma(gil):9s} {over_bound(gil):14s} {optimum(gi):16s} {optimum(gil):16s} {fails}")
    print(f"\nrows failing the accuracy checks: {n_fail}, of which the optima from the truth fail them too: {n_fail_optima}")
    over_draws(records)
    print("pooled over every row (epoch-weighted): RMS of error/sigma, share beyond 3 sigma")
    for sol in ("gi", "gil"):
        parts = []
        for a in ANGLES:
            if pooled[sol][a]:
                z2, n = np.array(pooled[sol][a]).T
                b, _ = np.array(beyond[sol][a]).T
                parts.append(f"{a} {np.sqrt(np.sum(z2 * n) / np.sum(n)):.2f} ({100 * np.sum(b * n) / np.sum(n):.1f} %)")
        print(f"  {sol.upper():4s} " + ", ".join(parts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--design", choices=("full", "oat"), default="oat")
    ap.add_argument("--only", nargs="*", default=[], help="run the scenarios whose name holds all of these")
    ap.add_argument("--length", type=float, default=2400.0, help="corridor length (m)")
    ap.add_argument("--draws", type=int, default=1,
                    help="independent draws per scenario: the K-th extra one has seed + 1000 K and is named NAME~K")
    ap.add_argument("--report-only", action="store_true", help="print the results kept in WORK, run nothing")
    ap.add_argument("--no-bounds", action="store_true",
                    help="no Cramér-Rao bound of the runs (17-46 s per run on a 1.2 km corridor; added to kept "
                    "results that lack it while their runs are there)")
    ap.add_argument("--redo", choices=("both", "single"),
                    help="run this solution of the kept scenarios again (and its bound), keep the other")
    ap.add_argument("--markdown", action="store_true", help="also print the rows as a Markdown table")
    ap.add_argument("--reverse", action="store_true",
                    help="run the scenarios from the last: a second process on another core meets the first in the middle")
    a = ap.parse_args()
    todo = [s for s in scenarios(a.design) if all(o in name_of(s) for o in a.only)]
    if a.reverse:
        todo = todo[::-1]
    seeds = {s: 1600 + i for i, s in enumerate(scenarios("full"))}
    records = []
    for s in todo:
        for draw in range(a.draws):
            path = a.work / "results" / f"{key_of(s, draw)}.json"
            if a.report_only and not path.is_file():
                continue
            t = time.perf_counter()
            records.append(one(a.work, s, seeds[s] + 1000 * draw, a.length, draw,
                               with_bounds=not (a.no_bounds or a.report_only),
                               again=None if a.report_only else a.redo))
            if not a.report_only:
                print(f"{key_of(s, draw)}: {time.perf_counter() - t:.0f} s", file=sys.stderr, flush=True)
    report(records)
    if a.markdown:
        print()
        report_markdown(records)


if __name__ == "__main__":
    main()
