"""Wall time and peak memory of the whole `georefine run` (a script, not a test).

Runs, each in a fresh process and a fresh output folder (``--fresh``: nothing resumed):

1. ``georefine run PROJECT`` (steps 1-6, both passes),
2. ``georefine run PROJECT --strips FIRST`` (the single-pass case),
3. ``georefine run PROJECT --no-lidar`` (steps 1, 2 and 6) as the yardstick measured in the
   same session: the difference is the cost of the LiDAR part (features, matching, G/I/L).

and prints wall time, peak resident memory (``getrusage`` of the child) and the per-step
timings from ``metrics.json``.

Usage::

    python bench/run_corridor.py PROJECT [--keep DIR]

PROJECT is e.g. ``georefine simulate corridor --out corridor --seed 42``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# A fresh interpreter per case reports its own children's peak (getrusage's maximum is over all
# children waited for so far, so measuring in this process would carry the first case's peak).
_WRAP = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL); "
         "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")


def run(args: list[str], out: Path) -> tuple[float, float, dict]:
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", _WRAP, sys.executable, "-m", "georefine", "run", *args, "--out", str(out), "--fresh"],
        check=True, capture_output=True, text=True,
    )
    wall = time.perf_counter() - t
    peak = int(proc.stdout.split()[-1]) / 1024**2  # KiB -> GiB
    return wall, peak, json.loads((out / "metrics.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", type=Path)
    ap.add_argument("--keep", type=Path, help="Keep the run folders here.")
    a = ap.parse_args()
    base = a.keep or Path(tempfile.mkdtemp())
    cases = [("both passes", [str(a.project)], "run"), ("single pass", [str(a.project), "--strips", "1"], "run1"),
             ("G/I only (--no-lidar)", [str(a.project), "--no-lidar"], "run_gi")]
    rows = []
    for name, args, folder in cases:
        wall, peak, m = run(args, base / folder)
        rows.append((name, wall, peak, m))
        steps = ", ".join(f"{k} {v:.1f}" for k, v in m["timings_s"].items())
        print(f"{name:22s} {wall:7.1f} s  peak {peak:5.2f} GB  outer iterations {len(m['outer_iterations'])}\n    {steps}")
    gi_wall = rows[2][1]
    print(f"LiDAR part (both passes minus G/I only): {rows[0][1] - gi_wall:.1f} s; ratio {rows[0][1] / gi_wall:.1f}x")


if __name__ == "__main__":
    main()
