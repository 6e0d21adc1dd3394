"""Compare two JSON results of Georefine (``metrics.json``, ``summary.json``) figure by figure.

    python bench/compare_metrics.py BEFORE/metrics.json AFTER/metrics.json [--rtol 1e-9]

Every numeric leaf of both trees is compared (timings, resumed steps and per-pair match lists
are left out: they describe the run, not the result); keys present in one file only and
differing strings are listed. Prints the differences and a closing count; exits 1 when a
figure differs, so that "no behaviour change" can be checked after a refactoring.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

SKIP = ("timings", "timings_s", "resumed", "per_pair")


def compare(a, b, rtol: float, path: str = "") -> tuple[int, list[str]]:
    """``(numbers compared, differences)`` of two JSON trees."""
    if any(part in SKIP for part in path.split("/")):
        return 0, []
    if isinstance(a, dict) and isinstance(b, dict):
        n, out = 0, []
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                out.append(f"{path}/{k}: only in {'the first' if k in a else 'the second'} file")
                continue
            m, d = compare(a[k], b[k], rtol, f"{path}/{k}")
            n, out = n + m, out + d
        return n, out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return 0, [f"{path}: {len(a)} against {len(b)} entries"]
        n, out = 0, []
        for i, (u, v) in enumerate(zip(a, b)):
            m, d = compare(u, v, rtol, f"{path}[{i}]")
            n, out = n + m, out + d
        return n, out
    numeric = (int, float)
    if isinstance(a, numeric) and isinstance(b, numeric) and not isinstance(a, bool) and not isinstance(b, bool):
        same = a == b or (math.isnan(a) and math.isnan(b)) or abs(a - b) <= rtol * max(abs(a), abs(b))
        return 1, [] if same else [f"{path}: {a} -> {b}"]
    return 0, [] if a == b else [f"{path}: {str(a)[:60]!r} -> {str(b)[:60]!r}"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first")
    parser.add_argument("second")
    parser.add_argument("--rtol", type=float, default=1e-9, help="relative tolerance of a figure")
    args = parser.parse_args()
    with open(args.first) as fa, open(args.second) as fb:
        n, diffs = compare(json.load(fa), json.load(fb), args.rtol)
    for d in diffs:
        print(d)
    print(f"{n} figures compared, {len(diffs)} differ")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
