"""Simulated projects that several test files share, built once per test run (tests/conftest.py)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import Callable

from filelock import FileLock

from cli_helpers import run_georefine

README_SEED = 4
"""The seed of the README's smallest example (``georefine simulate corridor-tiny --seed 4``)."""

README_COMMANDS: list[list[str]] = [
    ["simulate", "corridor-tiny", "--out", "tiny", "--seed", str(README_SEED)],
    ["check", "tiny"],
    ["run", "tiny", "--out", "r"],
    ["evaluate", "trajectory", "r/gil/trajectory.sbet", "--reference", "tiny/truth/trajectory.sbet", "--out", "r/eval"],
    ["run", "tiny", "--out", "r1", "--strips", "1"],
]
"""The README's smallest example, in order (README.md, "The smallest example"; test_readme_tiny.py
checks that the README holds exactly these lines)."""


def georefine_in(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """`georefine ARGS` in ``cwd`` as the user types it (:func:`cli_helpers.run_georefine`), output captured."""
    return run_georefine(*args, timeout=1800, cwd=cwd)


def ok(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == 0, f"{' '.join(map(str, proc.args))}: exit {proc.returncode}\n{proc.stderr[-3000:]}"


def run_readme_example(folder: Path) -> None:
    """The README's commands (:data:`README_COMMANDS`) in the empty ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for cmd in README_COMMANDS:
        ok(georefine_in(folder, *cmd))


def built_once(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """The folder ``name`` that ``build`` fills once per test run, shared by the pytest-xdist workers.

    The workers' temporary folders lie in one folder of the run: the first worker to ask builds
    it under a file lock, the others wait for it and reuse it (a build that failed is retried).
    Users must not change it: they copy what they modify.
    """
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # this run's folder, above the workers' own
    folder = base / "shared" / name
    folder.parent.mkdir(parents=True, exist_ok=True)
    done = folder.with_name(f"{name}.done")
    with FileLock(str(folder.with_name(f"{name}.lock"))):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            build(folder)
            done.touch()
    return folder
