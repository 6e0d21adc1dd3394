"""Simulation time and peak memory of the scenarios (a script, not a test).

Runs ``georefine simulate SCENARIO`` in a fresh process per scenario and prints wall time,
peak resident memory (of the child process, from ``getrusage``), points written and points
per second. As a yardstick measured in the same run, it also times the bare Embree ray cast
of the same number of rays on the same scene, so the share of the simulation spent outside
ray casting (trajectory evaluation, noise, LAZ encoding of scan and truth files) is visible.

With several ``--schedulers`` each scenario is simulated on each (``georefine simulate
--scheduler``: the scan chunks as tasks); peak memory is then summed over the process tree
(``bench/proctree.py``, Dask workers included), the speed-up is against the first scheduler,
and the scan and truth files are compared byte for byte with the first scheduler's.

Usage::

    python bench/simulate.py [--scenarios corridor-tiny corridor] [--seed 42] [--keep DIR]
                             [--schedulers sync threads processes]
"""

from __future__ import annotations

import argparse
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml


def run_scenario(name: str, seed: int, out: Path, scheduler: str | None = None) -> tuple[float, float, int]:
    args = [sys.executable, "-m", "georefine.cli", "simulate", name, "--out", str(out), "--seed", str(seed)]
    if scheduler is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from proctree import run_measured

        wall, peak_gb, proc = run_measured([*args, "--scheduler", scheduler])
        if proc.returncode != 0:
            raise RuntimeError(proc.stderr[-2000:])
    else:
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        t = time.perf_counter()
        subprocess.run(args, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t
        peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        if peak_kib < before:  # ru_maxrss is the maximum over all children so far
            peak_kib = before
        peak_gb = peak_kib / 1024**2
    truth = yaml.safe_load((out / "truth" / "scenario.yaml").read_text())
    return wall, peak_gb, int(sum(truth["points_per_strip"].values()))


def compare_schedulers(name: str, seed: int, base: Path, schedulers: list[str]) -> None:
    first = None
    for sch in schedulers:
        out = base / f"{name}-{sch}"
        if out.exists():
            shutil.rmtree(out)
        wall, peak_gb, points = run_scenario(name, seed, out, sch)
        files = sorted(p.relative_to(out) for p in out.rglob("*.laz"))
        same = "" if first is None else (
            ", files identical to " + schedulers[0] if all((out / f).read_bytes() == (first[1] / f).read_bytes()
                                                            for f in files) else ", FILES DIFFER")
        first = first or (wall, out)
        print(f"{name:<15} {sch:<10} {wall:8.1f} s {peak_gb:6.2f} GB {points:12,} points "
              f"{points / wall / 1e6:6.2f} M/s  {first[0] / wall:4.2f}x{same}", flush=True)


def raycast_time(name: str, seed: int, n_rays: int) -> float:
    from georefine.sim.scenarios import resolve_scenario
    from georefine.sim.scene import build_scene

    cfg = resolve_scenario(name)
    scene = build_scene(cfg.scene, np.random.default_rng(seed))
    rng = np.random.default_rng(1)
    n = min(n_rays, 5_000_000)
    y = np.sort(rng.uniform(0, cfg.scene.length_m, n))
    origins = np.column_stack([rng.uniform(-150, 150, n), y, np.full(n, 900.0)])
    dirs = np.tile([0.0, 0.0, -1.0], (n, 1))
    scene.intersect(origins[:10], dirs[:10])
    t = time.perf_counter()
    scene.intersect(origins, dirs)
    return (time.perf_counter() - t) * n_rays / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["corridor-tiny", "corridor"])
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--keep", type=Path, default=None, help="keep the projects in this folder")
    ap.add_argument("--schedulers", nargs="+", default=None, help="compare these schedulers")
    args = ap.parse_args()
    base = args.keep or Path(tempfile.mkdtemp(prefix="georefine-bench-"))
    base.mkdir(parents=True, exist_ok=True)
    if args.schedulers:
        try:
            for name in args.scenarios:
                compare_schedulers(name, args.seed, base, args.schedulers)
        finally:
            if args.keep is None:
                shutil.rmtree(base, ignore_errors=True)
        return
    print(f"{'scenario':<15} {'wall s':>8} {'peak GB':>8} {'points':>12} {'Mpts/s':>7} {'raycast s':>9} {'other':>6}")
    try:
        for name in args.scenarios:
            out = base / name
            if out.exists():
                shutil.rmtree(out)
            wall, peak_gb, points = run_scenario(name, args.seed, out)
            rc = raycast_time(name, args.seed, points)
            print(f"{name:<15} {wall:8.1f} {peak_gb:8.2f} {points:12,} {points / wall / 1e6:7.2f} {rc:9.1f} {wall / rc:5.1f}x")
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
