"""Orthometric heights: what the geoid grid costs per point (a script, not a test).

``GeoidHeights.orthometric_xyz`` (the conversion the georeferencing tasks apply to every final
point when ``crs.geoid_grid`` is set: output CRS to geodetic, then PROJ's ``vgridshift``)
against its peer measured in the same run, the projection alone that every point already
passes through (``OutputCRS.from_geodetic``). The grid is written here: a GTX of random
undulations over the corridor's area (a 3 by 4 degree grid at 0.05 degrees, as GCG2016's size).

Usage::

    python bench/geoid.py [--points 2000000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import struct
import tempfile
import time
from pathlib import Path

import numpy as np

from georefine.geometry.frames import GeoidHeights, OutputCRS


def write_gtx(path: Path, lat0: float, lon0: float, step: float, N: np.ndarray) -> Path:
    """A GTX grid: big-endian header (lat0, lon0, dlat, dlon, rows, cols), rows south to north."""
    with open(path, "wb") as fh:
        fh.write(struct.pack(">4d2i", lat0, lon0, step, step, *N.shape))
        fh.write(N.astype(">f4").tobytes())
    return path


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(1)
    n = args.points
    with tempfile.TemporaryDirectory() as tmp:
        grid = write_gtx(Path(tmp) / "geoid.gtx", 45.0, 9.0, 0.05, rng.uniform(45.0, 50.0, (61, 81)))
        geoid, out = GeoidHeights(str(grid), 7837), OutputCRS(25832)
        lat = np.radians(rng.uniform(46.5, 47.5, n))
        lon = np.radians(rng.uniform(10.5, 12.5, n))
        h = rng.uniform(400.0, 600.0, n)
        xyz = out.from_geodetic(lat, lon, h)
        geoid.orthometric_xyz(out, xyz[:10])  # the grid opened once, as a task does
        t_geoid = best(lambda: geoid.orthometric_xyz(out, xyz), args.repeat)
        t_proj = best(lambda: out.from_geodetic(lat, lon, h), args.repeat)
    print(f"{n:,} points, best of {args.repeat}")
    print(f"geoid (orthometric_xyz): {n / t_geoid / 1e6:6.2f} M points/s")
    print(f"projection alone (peer): {n / t_proj / 1e6:6.2f} M points/s")
    print(f"geoid / projection time: {t_geoid / t_proj:.2f}")


if __name__ == "__main__":
    main()
