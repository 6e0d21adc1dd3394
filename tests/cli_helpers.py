"""The ``georefine`` command as the tests run it: a fresh process, wide lines, output captured; or,
for the tables of refused inputs, in this process (the same typer application, without the second
of start-up that each fresh process spends importing)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path


def run_georefine(*args: str, timeout: float = 600, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``georefine ARGS`` (the installed script, else ``python -m georefine.cli``) in ``cwd`` (default this
    process's) with stdout and stderr captured."""
    exe = shutil.which("georefine")
    cmd = [exe, *args] if exe else [sys.executable, "-m", "georefine.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, COLUMNS="200"), timeout=timeout,
                          cwd=cwd)


def run_georefine_here(*args: str) -> subprocess.CompletedProcess:
    """``georefine ARGS`` in this process (typer's ``CliRunner``): exit code, stdout and stderr as
    :func:`run_georefine` gives them. For commands that are refused early (bad input, bad options),
    where a fresh process would spend its time importing; the command line itself, as installed, is
    run by :func:`run_georefine` in the other tests."""
    from typer.testing import CliRunner

    from georefine.cli import app

    result = CliRunner(env={"COLUMNS": "200"}).invoke(app, list(args))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        import traceback

        stderr = result.stderr + "".join(traceback.format_exception(result.exception))  # as a fresh process shows it
    else:
        stderr = result.stderr
    return subprocess.CompletedProcess(["georefine", *args], result.exit_code, result.stdout, stderr)


STAGE_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d  ")  # georefine.cli.stages' lines off a terminal


def messages(stderr: str) -> str:
    """``stderr`` without the timestamped stage lines a command prints off a terminal: its messages."""
    return "\n".join(line for line in stderr.splitlines() if not STAGE_LINE.match(line))
