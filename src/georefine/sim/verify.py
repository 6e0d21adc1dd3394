"""Consistency check of a simulated project: the files reproduce the truth.

Georeferencing the scanner-frame strips with the true trajectory (``truth/trajectory.sbet``),
the lever arm and the boresight of ``project.yaml`` must give the true georeferenced points of
``truth/strip_*.laz`` (same point order) to well below a millimetre. This exercises the LAZ,
SBET and YAML round trip, the time conventions and the direct georeferencing together.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from georefine.config import boresight_matrix, load_project
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.las import gps_week_of_strip, iter_las_chunks, read_las_info
from georefine.io.trajectory import read_sbet, read_sbet_companion
from georefine.lidar.georeference import georeference
from georefine.trajectory.sampled import trajectory_from_sbet


@dataclass(frozen=True)
class VerifyResult:
    """Per strip: number of points, RMS and maximum 3D difference to the truth (m)."""

    strips: dict[str, tuple[int, float, float]]

    @property
    def max_error_m(self) -> float:
        return max((v[2] for v in self.strips.values()), default=0.0)

    def summary(self) -> str:
        lines = ["Georeferencing the scans with the true trajectory against truth/:"]
        for name, (n, rms, mx) in self.strips.items():
            lines.append(f"  {name}: {n:,} points, RMS {rms * 1e3:.3f} mm, max {mx * 1e3:.3f} mm")
        return "\n".join(lines)


def verify_project(
    project_dir: str | Path,
    *,
    chunk_size: int = 2_000_000,
    progress: Callable[[str, float, float], None] | None = None,
) -> VerifyResult:
    """Georeference every strip with the true trajectory and compare with ``truth/``."""
    root = Path(project_dir)
    cfg = load_project(root)
    sbet_path = root / "truth" / "trajectory.sbet"
    # The truth SBET is in seconds of week; its companion file states the week (projects simulated
    # before it was written: the week follows from the scans' absolute times).
    week = None if read_sbet_companion(sbet_path) else gps_week_of_strip(root / cfg.scanner.files[0])
    sbet = read_sbet(sbet_path, gps_week=week)
    t0 = float(np.floor(sbet.time_gps[0]))
    frame = LocalFrame(float(sbet.lat_rad[0]), float(sbet.lon_rad[0]), float(sbet.h_m[0]))
    trajectory = trajectory_from_sbet(sbet, frame, t0)
    crs = OutputCRS(cfg.crs.output_epsg)
    p_b_s = np.asarray(cfg.scanner.lever_arm_m)
    R_b_s = boresight_matrix(cfg.scanner.boresight_deg)

    strips: dict[str, tuple[int, float, float]] = {}
    for rel in cfg.scanner.files:
        scan_path = root / rel
        truth_path = root / "truth" / Path(rel).name
        if not truth_path.is_file():
            raise InputError("no truth file for this strip", path=truth_path)
        total = read_las_info(scan_path).point_count
        n, sq, mx = 0, 0.0, 0.0
        for scan, truth in zip(iter_las_chunks(scan_path, chunk_size), iter_las_chunks(truth_path, chunk_size)):
            if len(scan) != len(truth) or not np.array_equal(scan.time_gps, truth.time_gps):
                raise InputError("scan and truth strips differ in point order", path=truth_path, record_kind="point", line=n + 1)
            x_w = georeference(scan.time_gps - t0, scan.xyz, trajectory, p_b_s, R_b_s)
            d = np.linalg.norm(crs.from_w(frame, x_w) - truth.xyz, axis=1)
            n += d.size
            sq += float(np.sum(d * d))
            mx = max(mx, float(d.max()))
            if progress is not None:
                progress(f"verify {Path(rel).name}", n, total)
        strips[Path(rel).name] = (n, float(np.sqrt(sq / max(n, 1))), mx)
    return VerifyResult(strips)
