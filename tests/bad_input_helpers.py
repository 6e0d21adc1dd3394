"""File edits and the refusal check shared by the tables of damaged inputs
(test_bad_inputs.py, test_bad_photo_inputs.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from cli_helpers import messages, run_georefine_here


def lines(p: Path) -> list[str]:
    return p.read_text().splitlines()


def write(p: Path, rows: list[str]) -> None:
    p.write_text("\n".join(rows) + "\n")


def edit_line(rel: str, k: int, fn: Callable[[str], str]) -> Callable[[Path], None]:
    """Replace the ``k``-th data line (``%`` comments and the CSV header skipped) of ``rel``."""
    def edit(p: Path) -> None:
        f = p / rel
        rows = lines(f)
        idx = [i for i, row in enumerate(rows) if not row.startswith("%")]
        if rel.endswith(".csv"):
            idx = idx[1:]
        rows[idx[k]] = fn(rows[idx[k]])
        write(f, rows)
    return edit


def set_field(line: str, i: int, value: str, sep: str | None = None) -> str:
    f = line.split(sep) if sep else line.split()
    f[i] = value
    return (sep or "  ").join(f)


def truncate(rel: str, fraction: float) -> Callable[[Path], None]:
    def edit(p: Path) -> None:
        data = (p / rel).read_bytes()
        (p / rel).write_bytes(data[: int(len(data) * fraction)])
    return edit


def remove(rel: str) -> Callable[[Path], None]:
    return lambda p: (p / rel).unlink()


def assert_refused(name: str, commands: list[list[str]], words: tuple[str, ...], out: Path) -> None:
    """Each command exits 2 with one line on stderr holding ``words``, no traceback, and ``out`` is not made."""
    for cmd in commands:
        run = run_georefine_here(*cmd)
        err = messages(run.stderr).strip()
        assert run.returncode == 2, (name, cmd[0], run.returncode, run.stderr[-2000:])
        assert "Traceback" not in run.stderr and err.count("\n") == 0 and err.startswith("error: "), (name, err)
        for w in words:
            assert w in err, (name, cmd[0], w, err)
    assert not out.exists(), name
