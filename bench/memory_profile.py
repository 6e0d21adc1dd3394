"""Peak memory of a Georefine command per stage (a script, not a test).

Runs the command in a child process, samples the resident memory of its process tree every
``--interval`` seconds (psutil) and reads its log (standard error) for the stages it starts and
ends (``<stage>: started``, ``<stage>: done in``). Prints, per stage in the order they ran,
its duration and the peak memory while it ran, then the peak of the whole run and the stage
it fell in.

Usage::

    python bench/memory_profile.py [--interval 1.0] -- georefine run PROJECT --out RUN --no-points
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from demo_time import tree_rss  # noqa: E402

STAGE = re.compile(r"^\S+ \S+\s+(?P<stage>.+?): (?P<what>started|done in)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--interval", type=float, default=1.0, help="seconds between samples")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="the command, after --")
    args = ap.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("no command given")
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, bufsize=1)
    events: list[tuple[float, str, str]] = []

    def read_log() -> None:
        for line in child.stderr:
            m = STAGE.match(line.strip())
            if m:
                events.append((time.monotonic(), m["stage"], m["what"]))

    reader = threading.Thread(target=read_log, daemon=True)
    reader.start()
    proc = psutil.Process(child.pid)
    samples: list[tuple[float, float]] = []
    start = time.monotonic()
    while child.poll() is None:
        try:
            samples.append((time.monotonic(), tree_rss(proc) / 2**30))
        except psutil.Error:
            break
        time.sleep(args.interval)
    reader.join(timeout=5.0)
    if not samples:
        raise SystemExit(f"the command ended before the first sample (exit code {child.returncode})")
    stages: list[list] = []  # [name, start, end]
    for t, name, what in events:
        if what == "started":
            stages.append([name, t, None])
        else:
            for s in reversed(stages):
                if s[0] == name and s[2] is None:
                    s[2] = t
                    break
    print(f"{'stage':50s} {'time':>8s} {'peak':>9s}")
    for name, t0, t1 in stages:
        t1 = t1 if t1 is not None else samples[-1][0]
        inside = [gb for t, gb in samples if t0 <= t <= t1]
        peak = f"{max(inside):.2f} GB" if inside else "-"
        print(f"{name:50s} {t1 - t0:7.0f}s {peak:>9s}")
    t_peak, peak = max(samples, key=lambda s: s[1])
    where = [name for name, t0, t1 in stages if t0 <= t_peak <= (t1 if t1 is not None else t_peak)]
    print(f"peak {peak:.2f} GB at {t_peak - start:.0f} s ({', '.join(where) or 'between stages'}); "
          f"whole run {samples[-1][0] - start:.0f} s, exit code {child.returncode}")
    sys.exit(child.returncode)


if __name__ == "__main__":
    main()
