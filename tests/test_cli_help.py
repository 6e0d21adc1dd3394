"""The command line's help and tables render units and flags as written (no rich markup)."""

from __future__ import annotations

import re
from io import StringIO

import pytest
import typer
from rich.table import Table

from cli_helpers import run_georefine_here
from georefine.errors import GeorefineError


def test_help_keeps_units_in_brackets_and_shows_on_off_options_as_flags():
    coadjust = run_georefine_here("coadjust", "--help")
    assert coadjust.returncode == 0, coadjust.stderr
    assert "A-priori sigma of lidargram positions [m]." in " ".join(coadjust.stdout.split())
    run = run_georefine_here("run", "--help")
    assert run.returncode == 0, run.stderr
    text = run.stdout
    assert "<bool>" not in text and "╭" not in text
    for flag in ("--no-lidar", "--fresh", "--no-points", "--force"):
        assert re.search(rf"^\s+{flag}\s{{2,}}\S", text, re.MULTILINE), (flag, text)  # a flag: no value follows
    assert re.search(r"^\s+--strips <str>", text, re.MULTILINE), text
    assert "steps 1, 2 and 6" in " ".join(text.split())  # as README.md says of --no-lidar


def test_tables_and_errors_keep_brackets():
    from georefine.cli import common

    out = StringIO()
    console = common.stdout.__class__(file=out, width=80, markup=common.stdout._markup)
    table = Table()
    table.add_column("RMSE X [m]")
    table.add_row("0.4 [px]")
    console.print(table)
    assert "RMSE X [m]" in out.getvalue() and "0.4 [px]" in out.getvalue()
    with common.console.capture() as captured:
        with pytest.raises(typer.Exit) as exit_info:
            with common.user_errors():
                raise GeorefineError("lidargram sigma [m] must be positive")
    assert exit_info.value.exit_code == 2
    assert "error: lidargram sigma [m] must be positive" in captured.get()


def test_the_readme_names_the_workflow_steps_as_the_help_does():
    """README.md's numbered steps 1-6 (the trajectory and the whole-workflow sections) are
    georefine.steps.WORKFLOW_STEPS, which the help quotes: one source for the step names."""
    from pathlib import Path

    from georefine.steps import WORKFLOW_STEPS, steps_text

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    start = readme.index("## Estimating the trajectory from GNSS and IMU")
    end = readme.index("\n## ", readme.index("## GNSS/IMU/LiDAR: the whole workflow"))
    named = {int(n): name.lower() for n, name in re.findall(r"^([1-6])\. \*\*(.+?)\*\*", readme[start:end], re.MULTILINE)}
    assert named == {k: v.lower() for k, v in WORKFLOW_STEPS.items()}, named
    assert steps_text(1, 2, 6) == "steps 1, 2 and 6 (initialisation, GNSS/IMU adjustment, final georeferencing)"
    assert steps_text(6) == "step 6 (final georeferencing)"
    with pytest.raises(ValueError):
        steps_text(7)
