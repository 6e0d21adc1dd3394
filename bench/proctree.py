"""Peak memory of a command and every process it starts (workers included), for the benchmarks.

``getrusage`` reports the largest single descendant, not the sum: a run whose Dask workers are
processes would look smaller than it is. :func:`run_measured` samples the resident memory of
the whole process tree (``psutil``) every ``interval`` seconds and keeps the largest sum.
"""

from __future__ import annotations

import subprocess
import threading
import time

import psutil


def tree_rss(pid: int) -> int:
    """Resident bytes of process ``pid`` and all its descendants (0 once it is gone)."""
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.NoSuchProcess:
            pass
    return total


def run_measured(args: list[str], *, interval: float = 0.2, **kwargs) -> tuple[float, float, subprocess.CompletedProcess]:
    """Run ``args``; return wall time (s), peak memory of its process tree (GB) and the result."""
    t = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)
    peak = [0]
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], tree_rss(proc.pid))
            stop.wait(interval)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    out, err = proc.communicate()
    stop.set()
    th.join()
    wall = time.perf_counter() - t
    result = subprocess.CompletedProcess(args, proc.returncode, out, err)
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, args, out, err)
    return wall, peak[0] / 1e9, result
