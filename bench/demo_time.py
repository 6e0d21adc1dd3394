"""Wall time and peak memory of `georefine demo` as a newcomer runs it (a script, not a test).

Runs ``georefine demo --out DIR`` in a fresh process and a fresh folder, optionally with an
empty numba cache (``--cold``: the kernels are compiled on the way, as on a fresh clone),
samples the resident memory of the whole process tree (the demo and its second process) every
0.2 s, and prints the wall time, the peak of the summed memory, the demo's stage timings and,
as the yardstick measured in the same run, the time the same stages take one after the other
(simulation, both passes, single pass, the boresight calibration, both clouds' evaluation): their
ratio is what the two lanes gain.

Usage::

    python bench/demo_time.py [--out DIR] [--cold] [-- extra demo options]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil


def tree_rss(proc: psutil.Process) -> int:
    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="Demo folder (default: a new temporary folder).")
    ap.add_argument("--cold", action="store_true", help="Empty numba cache: compile every kernel on the way.")
    ap.add_argument("extra", nargs="*", help="Further `georefine demo` options.")
    a = ap.parse_args()
    out = a.out or Path(tempfile.mkdtemp()) / "demo"
    env = dict(os.environ)
    if a.cold:
        env["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="numba-cold-")
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "georefine", "demo", "--out", str(out), *a.extra], env=env,
                            stdout=subprocess.DEVNULL)
    ps, peak = psutil.Process(proc.pid), 0
    while proc.poll() is None:
        peak = max(peak, tree_rss(ps))
        time.sleep(0.2)
    wall = time.perf_counter() - t
    if proc.returncode:
        sys.exit(f"georefine demo failed with exit code {proc.returncode}")
    timings = json.loads((out / "metrics.json").read_text())["timings_s"]
    one_lane = sum(timings.get(k, 0.0) for k in ("simulate", "run_both_passes", "run_single_pass", "run_boresight",
                                                  "evaluate_gil_cloud", "evaluate_gi_cloud", "evaluate", "report"))
    print(f"georefine demo ({'cold' if a.cold else 'warm'} numba cache): {wall:.0f} s wall, "
          f"peak memory {peak / 1024**3:.1f} GB (process tree)")
    print("  stages: " + ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()))
    print(f"  the same stages one after the other: {one_lane:.0f} s; two lanes: {one_lane / wall:.2f}x")
    print(f"  output: {out}")


if __name__ == "__main__":
    main()
