"""Simulated projects that several test files share, built once per test run (tests/conftest.py)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable

from filelock import FileLock

GIL_SCAN = ["scanner.pulse_rate_hz=100000", "scanner.line_rate_hz=120"]  # the corridor's scanner
"""Scanner overrides of the shared G/I/L project (``gil_project`` in tests/conftest.py)."""


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
