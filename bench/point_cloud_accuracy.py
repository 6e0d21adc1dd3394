"""Point-cloud accuracy of a `georefine run` output, G/I against G/I/L (a script, not a test).

Georeferences the project's strips with ``RUN/gi/trajectory.sbet`` (the run itself writes only
the G/I/L points) and compares both clouds with the simulated truth:

* distance to the true surface (planar neighbourhoods, every 20th point): mean, RMS, P95;
* strip-to-strip discrepancy on 1 m cells where both passes are planar: median, P95;
* trajectory roll/pitch/yaw RMSE per pass (1 s inset) for G/I and G/I/L.

Usage::

    python bench/point_cloud_accuracy.py PROJECT RUN_DIR
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import yaml

from georefine.evaluation.point_cloud import compare_with_truth
from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.workflows import run_georeference


def cloud_metrics(points_dir: Path, project: Path, names: set[str]) -> dict:
    m = compare_with_truth(points_dir, project / "truth", names)
    return {(k[:-2] + "_mm" if k.endswith("_m") else k): (v * 1e3 if k.endswith("_m") else v) for k, v in m.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", type=Path)
    ap.add_argument("run", type=Path)
    args = ap.parse_args()
    truth = yaml.safe_load((args.project / "truth" / "scenario.yaml").read_text())
    t0 = truth["t0_gps"]
    names = {f.name for f in (args.run / "points").glob("strip_*.laz")}
    strips = {int(n.split(".")[0].split("_")[1]) for n in names}
    print("trajectory RMSE per pass (roll / pitch / yaw, mdeg)")
    for p in truth["passes"]:
        if p["strip_id"] not in strips:
            continue
        row = []
        for name in ("gi", "gil"):
            c = compare_sbet_files(args.run / name / "trajectory.sbet", args.project / "truth" / "trajectory.sbet",
                                   time_window=(t0 + p["t_start_s"] + 1, t0 + p["t_end_s"] - 1))
            row.append(" / ".join(f"{c.stats[f'{a}_rmse_mdeg']:.2f}" for a in ("roll", "pitch", "yaw")))
        print(f"  pass {p['strip_id']}:  G/I {row[0]}   G/I/L {row[1]}")
    with tempfile.TemporaryDirectory() as d:
        run_georeference(args.project, args.run / "gi" / "trajectory.sbet", Path(d) / "gi")
        gi = cloud_metrics(Path(d) / "gi", args.project, names)
    gil = cloud_metrics(args.run / "points", args.project, names)
    print(f"{'point cloud':28s} {'G/I':>10s} {'G/I/L':>10s}")
    for k in gi:
        print(f"  {k:26s} {gi[k]:10.2f} {gil[k]:10.2f}")


if __name__ == "__main__":
    main()
