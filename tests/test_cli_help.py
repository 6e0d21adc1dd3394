"""The command line's help and tables render units and flags as written (no rich markup)."""

from __future__ import annotations

import re
from io import StringIO

import pytest
import typer
from cli_helpers import run_georefine_here
from rich.table import Table

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
