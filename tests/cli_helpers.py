"""The ``georefine`` command as the tests run it: a fresh process, wide lines, output captured."""

from __future__ import annotations

import os
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
