"""Cross-check of a co-adjustment against COLMAP's bundle adjuster (a script, not a test).

``georefine coadjust`` writes the adjusted block as a COLMAP model (``OUT/colmap``: photos and
lidargrams, tie points and their inlier observations). This script opens that model with
pycolmap and solves the same problem -- tie reprojections only, unit weights, no robust loss,
intrinsics fixed -- with COLMAP's bundle adjuster (Ceres) and with Georefine's engine
(:mod:`georefine.adjustment`), from two starts:

* ``exported``: the model as written (the co-adjustment's result, which also had EOP priors,
  lidargram depths, control points and a Huber loss, so the pure tie problem still moves a
  little);
* ``a-priori``: the free images reset to their approximate orientation (``eop.csv``; a
  lidargram to the pose it was rendered from), the points as exported.

Images held fixed: the photos in cases 1 and 2 (case 2 adjusts them with control points, which
COLMAP does not have, so they fix the datum here), the lidargrams in case 3.

Printed: reprojection error by COLMAP's statistic (mean over 3-D points of each point's mean
error) and per observation, the ratio COLMAP/Georefine, the sum of squares of COLMAP's solution
evaluated with Georefine's camera model, and the wall time of both solvers.

Usage::

    georefine coadjust block --points block-gi/points --case 1 --out co1
    python bench/colmap_block.py block co1
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from georefine.io.colmap import (
    block_from_reconstruction,
    mean_reprojection_error,
    read_model,
)
from georefine.lidargrammetry.crosscheck import reprojection_errors, solve_both
from georefine.workflows.lidargrammetry import load_photo_project


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", type=Path)
    ap.add_argument("coadjust", type=Path, help="Output folder of georefine coadjust (metrics.json, colmap/).")
    a = ap.parse_args()
    case = json.loads((a.coadjust / "metrics.json").read_text())["case"]
    b = block_from_reconstruction(read_model(a.coadjust / "colmap"))
    is_lg = np.array([n.startswith("LG_") for n in b.names])
    fixed = ~is_lg if case in (1, 2) else is_lg
    pp = load_photo_project(a.project)
    R_ap, p_ap = b.R_w_c.copy(), b.p_w_c.copy()
    for k, name in enumerate(b.names):
        i = [j for j, ph in enumerate(pp.eop.images) if name == ph or name.endswith("_" + ph)]
        if not fixed[k]:
            R_ap[k], p_ap[k] = pp.R_w_c[i[0]], pp.p_w_c[i[0]]
    print(f"case {case}: {len(b.names)} images ({int(fixed.sum())} fixed), {len(b.points_w)} tie points, "
          f"{len(b.obs_image)} observations")
    e = reprojection_errors(b, b.R_w_c, b.p_w_c, b.points_w)
    print(f"exported model: RE {mean_reprojection_error(e, b.obs_point):.3f} px (COLMAP's statistic), "
          f"{e.mean():.3f} px per observation")
    print("| start | solver | RE [px] (COLMAP's) | RE per obs. [px] | sum of squares [px²] | time [s] |\n"
          "|---|---|---:|---:|---:|---:|")
    for start, (R0, p0) in (("exported", (b.R_w_c, b.p_w_c)), ("a-priori", (R_ap, p_ap))):
        g, c = solve_both(b, fixed, R0, p0)
        for r in (g, c):
            it = f" ({r.iterations} it.)" if r.iterations >= 0 else ""
            bad = f" ({r.invalid} observations behind their camera)" if r.invalid else ""
            print(f"| {start} | {r.solver}{it}{bad} | {r.re_px:.4f} | {np.nanmean(r.errors_px):.4f} "
                  f"| {r.sum_of_squares:.1f} | {r.seconds:.2f} |")
        print(f"|   | COLMAP / Georefine | {c.re_px / g.re_px:.4f} | "
              f"{np.nanmean(c.errors_px) / np.nanmean(g.errors_px):.4f} | "
              f"{c.sum_of_squares / g.sum_of_squares:.4f} | {c.seconds / g.seconds:.2f} |")


if __name__ == "__main__":
    main()
