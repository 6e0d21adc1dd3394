"""Lidargrammetric co-adjustment on a simulated `block` (a script, not a test).

For each case: ``run_coadjust`` (the code behind ``georefine coadjust``), then the tables of
paper 004 (RMSE X/Y/Z and reprojection error of control and check points) and, for cases 1
and 2, the refined cloud's RMS 3-D error against the truth beside the jammed cloud's, over the
points inside the block (those the re-intersection moved). Case 3 takes the true cloud as the
LiDAR refined beforehand.

Usage::

    georefine simulate block --out block --seed 3
    georefine run block --out block-gi --no-lidar
    python bench/coadjust_block.py block block-gi/points --cases 1 2 3 [--method xfeat] [--out DIR]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

from georefine.pipeline.lidargrammetry import run_coadjust


def cloud_errors(jammed: Path, refined: Path, truth: Path) -> tuple[float, float]:
    e0, e1 = [], []
    for f in sorted(refined.glob("*.laz")):
        a, b, c = laspy.read(jammed / f.name), laspy.read(truth / f.name), laspy.read(f)
        inside = np.asarray(c.lidargrams) >= 0
        e0.append(np.column_stack([a.x - b.x, a.y - b.y, a.z - b.z])[inside])
        e1.append(np.column_stack([c.x - b.x, c.y - b.y, c.z - b.z])[inside])
    rms = lambda e: float(np.sqrt(np.mean(np.sum(np.concatenate(e) ** 2, axis=1))))  # noqa: E731
    return rms(e0), rms(e1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", type=Path)
    ap.add_argument("points", type=Path, help="The jammed cloud (georefine run --no-lidar output points/).")
    ap.add_argument("--cases", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--method", default="sift")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    base = a.out or Path(tempfile.mkdtemp())
    print("| case | points | RMSE X [m] | RMSE Y [m] | RMSE Z [m] | RE [px] |\n|---|---|---:|---:|---:|---:|")
    notes = []
    for case in a.cases:
        pts = a.project / "truth" if case == 3 else a.points
        t = time.perf_counter()
        _, m = run_coadjust(a.project, [pts], base / f"case{case}", case, method=a.method)
        wall = time.perf_counter() - t
        for label in ("control_points", "check_points"):
            st = m.get(label)
            if st:
                print(f"| {case} | {'GCPs' if label == 'control_points' else 'ChPs'} ({st['n']}) | {st['rmse_x_m']:.3f} "
                      f"| {st['rmse_y_m']:.3f} | {st['rmse_z_m']:.3f} | {st['reprojection_px']:.2f} |")
        pl = m["photo_lidargram_matches"]
        note = (f"case {case}: {wall:.0f} s, {m['lidargrams']} lidargrams, median {pl['median']:.0f} verified matches "
                f"per photo-lidargram pair, tie RE {m['tie_reprojection_px']}")
        if case in (1, 2):
            before, after = cloud_errors(a.points, base / f"case{case}" / "points", a.project / "truth")
            note += f", cloud RMS inside the block {before:.3f} -> {after:.3f} m ({after / before:.2f}x)"
        notes.append(note)
    print("\n".join(notes))


if __name__ == "__main__":
    main()
