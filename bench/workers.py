"""Throughput of the per-point stages on one and on two Dask worker processes (a script, not a test).

A ``dask scheduler`` and ``dask worker --nworkers N --nthreads 1`` are started from the shell, as
a user would, for each N of ``--workers``; Georefine is pointed at the scheduler's address. Timed
per N, each the same work on the same project:

* ``features``: steps 3-4a of one outer iteration (``step_features``: every time tile read,
  georeferenced with the true trajectory and searched for planar features; tasks return
  features only);
* ``georeference``: ``run_georeference`` with the true trajectory (every tile read,
  georeferenced, transformed to the output CRS and compressed into LAZ chunks by its task; this
  process appends the chunks to the LAZ files).

Printed: seconds, points per second and the ratio against the first N, and whether the results
are the same (features equal, LAZ points equal record for record).

By default each worker is one core: lazrs decodes on one thread (``RAYON_NUM_THREADS=1``), the
numba kernels and BLAS run on one thread (``NUMBA_NUM_THREADS``, ``OMP_NUM_THREADS``,
``OPENBLAS_NUM_THREADS`` = 1). ``--library-threads`` leaves the libraries their default thread
pools in every worker (one worker then already uses several cores for parts of a task).

Usage::

    python bench/workers.py PROJECT WORKDIR [--workers 1 2] [--strips 1] [--library-threads]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np

ONE_CORE = ("RAYON_NUM_THREADS", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")
"""Thread-pool sizes set to 1 in the workers so that a worker is one core."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """``dask scheduler`` and ``dask worker`` processes started as a user starts them."""

    def __init__(self, workers: int, one_core: bool) -> None:
        self.port = free_port()
        env = dict(os.environ)
        if one_core:
            env.update({k: "1" for k in ONE_CORE})
        dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
        self.procs = [subprocess.Popen([*dask, "--port", str(self.port), "--dashboard-address", ":0"],
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
        time.sleep(2.0)
        worker = [sys.executable, "-m", "distributed.cli.dask_worker", self.address, "--nworkers", str(workers),
                  "--nthreads", "1", "--dashboard-address", ":0", "--memory-limit", "0"]
        self.procs.append(subprocess.Popen(worker, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        self.workers = workers

    @property
    def address(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    def wait(self):
        from dask.distributed import Client

        with Client(self.address, timeout="30s") as c:
            c.wait_for_workers(self.workers, timeout=60)

    def close(self) -> None:
        for p in reversed(self.procs):
            p.terminate()
        for p in self.procs:
            p.wait(timeout=30)


def same_feature_sets(a, b) -> bool:
    """The same features: counts, views and points exactly; times and planes to 1e-12 (the tiles
    sum a feature's points in another order when they are cut elsewhere; ``tests/test_tiles.py``)."""
    if len(a) != len(b) or not (np.array_equal(a.channel, b.channel) and np.array_equal(a.n_points, b.n_points)):
        return False
    return all(np.allclose(getattr(a, k), getattr(b, k), rtol=1e-12, atol=1e-12)
               for k in ("time", "centre_w", "normal_w"))


def same_points_in(path_a: Path, path_b: Path) -> bool:
    """The same points, record for record: coordinates and times (the header offsets may differ:
    the writer takes them from the first tile, whose size follows the task slots)."""
    a, b = laspy.read(path_a), laspy.read(path_b)
    return len(a.points) == len(b.points) and all(np.array_equal(a[k], b[k]) for k in ("x", "y", "z", "gps_time"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", type=Path)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--strips", type=int, nargs="*", default=None, help="strip ids (default all)")
    ap.add_argument("--library-threads", action="store_true", help="leave lazrs, numba and BLAS their thread pools")
    args = ap.parse_args()

    from georefine.io.trajectory import read_sbet
    from georefine.tasks import TaskRunner
    from georefine.trajectory.sampled import trajectory_from_sbet
    from georefine.workflows import load_navigation, run_georeference
    from georefine.workflows.strips import read_strips, step_features

    nav = load_navigation(args.project)
    truth_sbet = args.project / "truth" / "trajectory.sbet"
    week = int(nav.t0_gps // 604800)
    traj = trajectory_from_sbet(read_sbet(truth_sbet, gps_week=week), nav.frame, nav.t0_gps)
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows, first = [], None
    for n in args.workers:
        cluster = Cluster(n, not args.library_threads)
        try:
            cluster.wait()
            with TaskRunner(cluster.address) as runner:
                strips = read_strips(nav, args.strips, slots=runner.workers)
                points = sum(s.point_count for s in strips)
                t = time.perf_counter()
                features, _ = step_features(nav, traj, strips, runner=runner)
                t_feat = time.perf_counter() - t
                out = args.workdir / f"georeference-{n}"
                shutil.rmtree(out, ignore_errors=True)
                t = time.perf_counter()
                geo = run_georeference(args.project, truth_sbet, out, gps_week=week, scheduler=runner)
                t_geo = time.perf_counter() - t
                geo_points = sum(r.points_written for r in geo.strips)
        finally:
            cluster.close()
        row = dict(workers=n, points=points, features_s=t_feat, georef_s=t_geo, georef_points=geo_points,
                   features=features, out=out, tiles=sum(len(s.tiles) for s in strips))
        rows.append(row)
        first = first or row
        same_features = same_feature_sets(features, first["features"])
        same_points = all(same_points_in(f, first["out"] / f.name) for f in sorted(out.glob("*.laz")))
        print(f"{n} worker(s), {row['tiles']} tiles: features {t_feat:6.1f} s "
              f"({points / t_feat / 1e6:5.2f} M points/s, "
              f"{first['features_s'] / t_feat:4.2f}x), georeference {t_geo:6.1f} s "
              f"({geo_points / t_geo / 1e6:5.2f} M points/s, {first['georef_s'] / t_geo:4.2f}x); "
              f"same features: {same_features}, same points: {same_points}", flush=True)


if __name__ == "__main__":
    main()
