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

from georefine.evaluation.coadjust import cloud_errors
from georefine.workflows.lidargrammetry import run_coadjust


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
        m = run_coadjust(a.project, [pts], base / f"case{case}", case, overrides={"matcher": a.method})
        wall = time.perf_counter() - t
        for label, st in (("GCPs", m.control_points), ("ChPs", m.check_points)):
            if st is not None:
                x, y, z = st.rmse_xyz_m
                print(f"| {case} | {label} ({st.n}) | {x:.3f} | {y:.3f} | {z:.3f} | {st.reprojection_px:.2f} |")
        pl = m.photo_lidargram_matches
        note = (f"case {case}: {wall:.0f} s, {m.lidargrams} lidargrams, median {pl.median_verified:.0f} verified "
                f"matches per photo-lidargram pair, tie RE {m.tie_reprojection.to_dict()}")
        if case in (1, 2):
            e = cloud_errors(a.points, base / f"case{case}" / "points", a.project / "truth").summary()
            note += f", cloud RMS inside the block {e.rms_before_m:.3f} -> {e.rms_after_m:.3f} m ({e.ratio:.2f}x)"
        notes.append(note)
    print("\n".join(notes))


if __name__ == "__main__":
    main()
