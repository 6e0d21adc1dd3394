"""Regenerate the README's demo table and strip-difference figure (a script, not a test).

Usage::

    georefine demo --out georefine-demo          # corridor, seed 42 (about 6 minutes here)
    python bench/readme_figures.py georefine-demo

Writes ``docs/strip_differences.png`` (the G/I and G/I/L detail maps side by side, as paper 000's
Fig. 7) and prints the summary table as Markdown for the README.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from PIL import Image

from georefine.evaluation.report import summary_rows, summary_verdicts
from georefine.evaluation.summary import RunEvaluation

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("demo", type=Path, help="Output folder of `georefine demo`.")
    a = ap.parse_args()
    ev = RunEvaluation.read(a.demo / "run" / "evaluation" / "summary.json")
    maps = [a.demo / "run" / "evaluation" / ev.strip_differences[k].zoom_map for k in ("G/I", "G/I/L")]
    images = [Image.open(p).convert("RGB") for p in maps]
    pair = Image.new("RGB", (sum(i.width for i in images), max(i.height for i in images)), "white")
    x = 0
    for im in images:
        pair.paste(im, (x, 0))
        x += im.width
    pair = pair.resize((pair.width // 2, pair.height // 2), Image.LANCZOS)
    out = ROOT / "docs" / "strip_differences.png"
    out.parent.mkdir(exist_ok=True)
    pair.quantize(colors=128).save(out, optimize=True)  # a palette image: a few hundred kB
    print(f"wrote {out}\n")
    print("| quantity | paper 000 (G/I / G/I/L / single pass) | G/I | G/I/L | single-pass G/I/L | against paper 000 |")
    print("|---|---:|---:|---:|---:|---|")
    for row, verdict in zip(summary_rows(ev), summary_verdicts(ev)):
        print("| " + " | ".join([*row, verdict]) + " |")


if __name__ == "__main__":
    main()
