"""Memory and time of `georefine coadjust` against the point count (a script, not a test).

The `block` scenario (seed 3) simulated at several pulse rates (the same scan lines, denser
along them), its jammed G/I cloud (`georefine run --no-lidar`), then `georefine coadjust
--case 1` on that cloud in a fresh process. Peak memory is summed over the process tree
(``bench/proctree.py``, Dask workers included). Per stage: indexing the cloud (`read`), the
lidargrams, matching, the co-adjustment and the re-intersection, which reads, moves and writes
every point. The refined cloud's RMS 3-D error against the truth (inside the block) shows that
the accuracy holds.

Usage::

    python bench/coadjust_scale.py WORK --rates 100000 800000 [--scheduler threads]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).parent))
from georefine.evaluation.coadjust import cloud_errors  # noqa: E402
from proctree import run_measured  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--rates", type=int, nargs="+", default=[100_000, 800_000])
    ap.add_argument("--scheduler", default="threads")
    a = ap.parse_args()
    py = sys.executable
    rows = []
    for rate in a.rates:
        project, gi = a.work / f"block-{rate}", a.work / f"block-{rate}-gi"
        if not (project / "truth" / "scenario.yaml").is_file():
            run_measured([py, "-m", "georefine", "simulate", "block", "--out", str(project), "--seed", "3",
                          "--set", f"scanner.pulse_rate_hz={rate}"])
        if not (gi / "points").is_dir():
            run_measured([py, "-m", "georefine", "run", str(project), "--out", str(gi), "--no-lidar"])
        points = int(sum(yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
                         ["points_per_strip"].values()))
        out = a.work / f"block-{rate}-case1"
        wall, peak, _ = run_measured([py, "-m", "georefine", "coadjust", str(project), "--points", str(gi / "points"),
                                      "--out", str(out), "--case", "1", "--scheduler", a.scheduler])
        m = json.loads((out / "metrics.json").read_text())
        err = cloud_errors(gi / "points", out / "points", project / "truth").summary()
        rows.append((rate, points, wall, peak, m["timings_s"], err))
        print(f"{rate} Hz: {points / 1e6:.1f} M points, {wall:.1f} s, peak {peak:.2f} GB, {m['timings_s']}, "
              f"cloud {err.rms_before_m:.3f} -> {err.rms_after_m:.3f} m", flush=True)
    print("\n| pulse rate | points | wall | peak memory | read (index) | lidargrams | matching | co-adjustment "
          "| re-intersection | cloud RMS jammed → refined |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for rate, points, wall, peak, t, err in rows:
        ri = t.get("reintersection", float("nan"))
        print(f"| {rate / 1e3:.0f} kHz | {points / 1e6:.1f} M | {wall:.1f} s | {peak:.2f} GB | {t['read']:.1f} s "
              f"({points / t['read'] / 1e6:.1f} M/s) | {t['lidargrams']:.1f} s | {t['matching']:.1f} s "
              f"| {t['coadjustment']:.1f} s | {ri:.1f} s ({points / ri / 1e6:.2f} M/s) "
              f"| {err.rms_before_m:.3f} → {err.rms_after_m:.3f} m ({err.ratio:.2f}×) |")
    if len(rows) > 1:
        (r0, n0, w0, p0, *_), (r1, n1, w1, p1, *_) = rows[0], rows[-1]
        print(f"\n{r1 / 1e3:.0f} kHz against {r0 / 1e3:.0f} kHz: {n1 / n0:.2f}× the points, {w1 / w0:.2f}× the time, "
              f"{p1 / p0:.2f}× the memory")


if __name__ == "__main__":
    main()
