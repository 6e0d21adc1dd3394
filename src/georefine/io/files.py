"""Shared helpers of the readers and writers in :mod:`georefine.io`.

Three small concerns live here because every format module needs them:

* **Atomic output** (:func:`atomic_output`, :func:`atomic_path`): a writer writes
  to a temporary name in the destination folder and renames it with
  :func:`os.replace` only when complete, so a reader never sees a half-written
  file. A writer also refuses to write into a protected input (file or folder).
* **GPS time** (:func:`gps_seconds_from_week`, :func:`week_from_gps_seconds`,
  :func:`gps_seconds_from_calendar`, :func:`calendar_from_gps_seconds`): GPS
  seconds since 1980-01-06 00:00:00 GPST, continuous, no leap seconds. Calendar
  dates here are GPST calendar dates (what RTKLIB prints with ``GPST``), not UTC.
* **Text tables** (:func:`read_text_lines`, :func:`data_lines`,
  :func:`parse_float_rows`): parse rows of numbers fast with :func:`numpy.loadtxt`;
  only when that fails, walk the lines to name the exact line and field.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import re
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np

from georefine.errors import InputError

PathLike = str | os.PathLike[str]

SECONDS_PER_WEEK = 604800.0
SECONDS_PER_DAY = 86400
GPS_EPOCH = np.datetime64("1980-01-06", "D")
"""Origin of GPS time (00:00:00 GPST)."""

# ---------------------------------------------------------------------------
# Atomic output
# ---------------------------------------------------------------------------


def check_output_path(path: PathLike, protect: Iterable[PathLike] = ()) -> Path:
    """Return ``path`` resolved, refusing to write into a protected file or folder.

    Parameters
    ----------
    path
        Destination of a writer.
    protect
        Input files and input folders. The destination must not be one of the
        files nor lie inside one of the folders (docs/ARCHITECTURE.md §3: nothing ever writes
        into the input folder).

    Raises
    ------
    InputError
        If the destination is protected or its folder does not exist.
    """
    out = Path(path).resolve()
    for item in protect:
        p = Path(item).resolve()
        if out == p or (p.is_dir() and p in out.parents):
            raise InputError(
                "refusing to write into an input",
                path=out,
                expected="an output path outside the inputs",
                found=f"protected input {p}",
            )
    if not out.parent.is_dir():
        raise InputError("output folder does not exist", path=out)
    return out


def check_output_folder(path: PathLike) -> Path:
    """``path`` as a Path, refusing one that is, or lies below, an existing file (InputError)."""
    out = Path(path)
    blocked = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
    if blocked is not None:
        raise InputError("the output path is not a folder", path=out, expected="a folder or a path that does not exist",
                         found=f"a file at {blocked}")
    return out


OUTPUT_MARK = ".georefine-output"
"""The file by which an output folder says that Georefine made it (:func:`make_output_folder`)."""


def refuse_foreign_output(path: PathLike, force: bool = False) -> Path:
    """Refuse an output folder that holds files Georefine did not write (InputError), unless ``force``.

    A folder is Georefine's when :func:`make_output_folder` made it (it holds :data:`OUTPUT_MARK`);
    a new or empty folder (hidden entries aside) is fine too. Writing into anyone else's folder
    could replace their files, and an evaluation that reads a folder would take them for ours.
    """
    out = check_output_folder(path)
    if force or not out.is_dir() or (out / OUTPUT_MARK).is_file():
        return out
    entries = sorted(e.name for e in out.iterdir() if not e.name.startswith("."))
    if entries:
        shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise InputError("the output folder holds files Georefine did not write", path=out,
                         expected="a new or empty folder, one Georefine made, or --force",
                         found=f"{len(entries)} entries ({shown})")
    return out


def make_output_folder(path: PathLike) -> Path:
    """Create the output folder ``path`` (and its parents) after :func:`check_output_folder`, and mark it as
    Georefine's (:data:`OUTPUT_MARK`, see :func:`refuse_foreign_output`).

    Raises
    ------
    InputError
        ``path`` or one of its parents exists and is not a folder, or the folder cannot be made.
    """
    out = check_output_folder(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        mark = out / OUTPUT_MARK
        if not mark.is_file():
            from georefine import __version__

            mark.write_text(f"Georefine {__version__} writes into this folder.\n")
    except OSError as exc:
        raise InputError("cannot create the output folder", path=out, found=exc.strerror or str(exc)) from None
    return out


CACHE_FOLDER = ".cache"
"""The step cache of an output folder (:mod:`georefine.workflows.cache`)."""


def clean_output(path: PathLike, everything: bool = False) -> tuple[list[Path], int]:
    """Remove the step caches of an output folder Georefine made, or with ``everything`` the folder.

    The caches are the :data:`CACHE_FOLDER` of ``path`` and of every output folder Georefine
    made inside it (the demo's runs). A rerun then recomputes every step; the results stay.
    Returns what was removed and the bytes it held.

    Raises
    ------
    InputError
        ``path`` is not a folder, or does not hold :data:`OUTPUT_MARK` (only Georefine's own
        folders are removed).
    """
    import shutil

    out = Path(path)
    if not out.is_dir():
        raise InputError("no such output folder", path=out, expected="an output folder Georefine made")
    if not (out / OUTPUT_MARK).is_file():
        raise InputError("not an output folder Georefine made", path=out,
                         expected=f"a folder holding {OUTPUT_MARK}", found="no mark")
    if everything:
        targets = [out]
    else:
        targets = sorted(p for p in out.rglob(CACHE_FOLDER) if p.is_dir() and (p.parent / OUTPUT_MARK).is_file())
    size = sum(f.stat().st_size for t in targets for f in t.rglob("*") if f.is_file() and not f.is_symlink())
    for t in targets:
        shutil.rmtree(t)
    return targets, size


@contextlib.contextmanager
def atomic_path(path: PathLike, protect: Iterable[PathLike] = ()) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` on success.

    On an exception the temporary file is removed and ``path`` is untouched.
    """
    out = check_output_path(path, protect)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # mkstemp creates the file private (0600); give the product ordinary permissions.
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_output(
    path: PathLike,
    mode: Literal["w", "wb"] = "w",
    protect: Iterable[PathLike] = (),
) -> Iterator[IO]:
    """Open a temporary file next to ``path`` for writing; rename it on success.

    Text mode writes UTF-8 with ``\\n`` line ends. The data are flushed and
    fsync'ed before the rename so that a crash leaves either the old file or the
    complete new one.
    """
    with atomic_path(path, protect) as tmp:
        kwargs = {"encoding": "utf-8", "newline": "\n"} if mode == "w" else {}
        with open(tmp, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


# ---------------------------------------------------------------------------
# GPS time
# ---------------------------------------------------------------------------


def gps_seconds_from_week(week: np.ndarray | int, seconds_of_week: np.ndarray | float) -> np.ndarray:
    """GPS seconds (since 1980-01-06 GPST) from GPS week and seconds of week."""
    return np.asarray(week, dtype=np.float64) * SECONDS_PER_WEEK + np.asarray(seconds_of_week, dtype=np.float64)


def week_from_gps_seconds(time_gps: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Split GPS seconds into (week (int64), seconds of week (float64))."""
    t = np.asarray(time_gps, dtype=np.float64)
    week = np.floor(t / SECONDS_PER_WEEK).astype(np.int64)
    return week, t - week * SECONDS_PER_WEEK


def unwrap_seconds_of_week(sow: np.ndarray) -> np.ndarray:
    """Undo week rollovers in a series of seconds of week (a drop by more than half a week)."""
    sow = np.asarray(sow, dtype=np.float64)
    if sow.size < 2:
        return sow.copy()
    jumps = np.diff(sow) < -0.5 * SECONDS_PER_WEEK
    return sow + SECONDS_PER_WEEK * np.concatenate(([0], np.cumsum(jumps)))


def gps_seconds_from_calendar(
    year: np.ndarray, month: np.ndarray, day: np.ndarray,
    hour: np.ndarray, minute: np.ndarray, second: np.ndarray,
) -> np.ndarray:
    """GPS seconds from a GPST calendar date and time of day (vectorised).

    Integer-valued float or int arrays are accepted for the date and the hour and
    minute; ``second`` is float. No range checks are made here.
    """
    y = np.asarray(year).astype(np.int64)
    m = np.asarray(month).astype(np.int64)
    d = np.asarray(day).astype(np.int64)
    months = (y - 1970).astype("datetime64[Y]") + (m - 1).astype("timedelta64[M]")
    days = months.astype("datetime64[D]") + (d - 1).astype("timedelta64[D]")
    whole = (days - GPS_EPOCH).astype(np.int64) * SECONDS_PER_DAY
    whole = whole + np.asarray(hour).astype(np.int64) * 3600 + np.asarray(minute).astype(np.int64) * 60
    return whole.astype(np.float64) + np.asarray(second, dtype=np.float64)


def days_in_month(year: np.ndarray, month: np.ndarray) -> np.ndarray:
    """Number of days of the given month (vectorised, proleptic Gregorian)."""
    y = np.asarray(year).astype(np.int64)
    m = np.asarray(month).astype(np.int64)
    start = (y - 1970).astype("datetime64[Y]") + (m - 1).astype("timedelta64[M]")
    return ((start + np.timedelta64(1, "M")).astype("datetime64[D]") - start.astype("datetime64[D]")).astype(np.int64)


def rounded_time_units(time_gps: np.ndarray, decimals: int) -> np.ndarray:
    """GPS time rounded to ``decimals`` places, as int64 count of 10**-decimals s."""
    if not 0 <= decimals <= 9:
        raise ValueError(f"decimals must be in 0..9, got {decimals}")
    return np.round(np.asarray(time_gps, dtype=np.float64) * 10.0**decimals).astype(np.int64)


def calendar_from_gps_seconds(time_gps: np.ndarray, decimals: int = 3) -> tuple[np.ndarray, ...]:
    """GPST calendar fields of GPS seconds, rounded to ``decimals`` places of a second.

    Returns
    -------
    year, month, day, hour, minute, second, fraction
        int64 arrays; ``fraction`` counts units of 10**-decimals s. Rounding is
        done once on the total so that 59.9996 s never prints as 60.000.
    """
    scale = 10**decimals
    units = rounded_time_units(time_gps, decimals)
    whole, fraction = np.divmod(units, scale)
    days, sod = np.divmod(whole, SECONDS_PER_DAY)
    date = GPS_EPOCH + days.astype("timedelta64[D]")
    year = date.astype("datetime64[Y]").astype(np.int64) + 1970
    month_start = date.astype("datetime64[M]")
    month = month_start.astype(np.int64) % 12 + 1
    day = (date - month_start.astype("datetime64[D]")).astype(np.int64) + 1
    hour, rest = np.divmod(sod, 3600)
    minute, second = np.divmod(rest, 60)
    return year, month, day, hour, minute, second, fraction


# ---------------------------------------------------------------------------
# Text tables
# ---------------------------------------------------------------------------


def finite_array(arr, shape: tuple[int, ...], name: str) -> np.ndarray:
    """``arr`` as contiguous float64 of ``shape``; ValueError naming ``name`` otherwise or if not all finite."""
    a = np.ascontiguousarray(arr, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def read_text_lines(path: PathLike) -> list[str]:
    """Read a text file as a list of lines without line ends.

    Raises
    ------
    InputError
        If the file cannot be read or is not UTF-8/ASCII text.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise InputError("file not found", path=p) from exc
    except UnicodeDecodeError as exc:
        raise InputError(
            "not a text file", path=p, expected="UTF-8 or ASCII text",
            found=f"undecodable byte at offset {exc.start}",
        ) from exc
    except OSError as exc:
        raise InputError(f"cannot read file: {exc.strerror}", path=p) from exc
    return text.splitlines()


def data_lines(
    lines: Sequence[str], start: int, comment: str | None = "#"
) -> tuple[list[str], np.ndarray]:
    """Data lines from index ``start`` on, skipping blank and comment lines.

    Returns
    -------
    rows
        The data lines.
    line_numbers
        (N,) int64, 1-based line number of each row in the file.
    """
    body = lines[start:]
    # Fast path: no blank or comment line at all, the numbering is contiguous.
    pattern = r"^\s*$" if comment is None else rf"^\s*(?:{re.escape(comment)}|$)"
    if not re.search(pattern, "\n".join(body), flags=re.M) or not body:
        return list(body), np.arange(start + 1, start + 1 + len(body), dtype=np.int64)
    keep = [i for i, s in enumerate(body) if s.strip() and not (comment and s.lstrip().startswith(comment))]
    return [body[i] for i in keep], np.asarray(keep, dtype=np.int64) + start + 1


def _split(line: str, delimiter: str | None) -> list[str]:
    return [t.strip() for t in line.split(delimiter)] if delimiter else line.split()


def _raise_first_bad(
    path: Path, rows: Sequence[str], line_numbers: np.ndarray, field_names: Sequence[str],
    delimiter: str | None, exact: bool, cause: Exception,
) -> None:
    """Walk the rows (slow path, only after a failed fast parse) and raise for the first bad one."""
    k = len(field_names)
    for row, line in zip(rows, line_numbers.tolist()):
        tokens = _split(row, delimiter)
        if len(tokens) < k or (exact and len(tokens) != k):
            raise InputError(
                "wrong number of fields", path=path, line=line,
                expected=f"{k} fields ({', '.join(field_names)})", found=f"{len(tokens)} fields",
            ) from cause
        for name, tok in zip(field_names, tokens):
            try:
                float(tok)
            except ValueError:
                raise InputError(
                    "not a number", path=path, line=line, field=name,
                    expected="a number", found=repr(tok),
                ) from cause
    raise InputError(f"cannot parse numbers: {cause}", path=path) from cause


def parse_float_rows(
    path: PathLike,
    rows: Sequence[str],
    line_numbers: np.ndarray,
    field_names: Sequence[str],
    *,
    delimiter: str | None = None,
    exact: bool = True,
) -> np.ndarray:
    """Parse rows of numbers into an (N, K) float64 array; K = ``len(field_names)``.

    The fast path is :func:`numpy.loadtxt`. If it fails, the rows are walked to
    name the first bad line and field. Non-finite values (nan, inf) are rejected.

    Parameters
    ----------
    delimiter
        Field separator; ``None`` splits on whitespace.
    exact
        Every row must have exactly K fields; otherwise extra trailing fields are
        ignored.

    Raises
    ------
    InputError
        With the file, line number, field name, expected and found.
    """
    path = Path(path)
    k = len(field_names)
    if not rows:
        return np.empty((0, k))
    try:
        values = np.loadtxt(
            rows, delimiter=delimiter, dtype=np.float64, comments=None, ndmin=2,
            usecols=None if exact else range(k),
        )
        if values.shape != (len(rows), k):
            raise ValueError(f"parsed shape {values.shape}, expected {(len(rows), k)}")
    except ValueError as exc:
        _raise_first_bad(path, rows, line_numbers, field_names, delimiter, exact, exc)
    bad = ~np.isfinite(values)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError(
            "not a finite number", path=path, line=int(line_numbers[i]), field=field_names[j],
            expected="a finite number", found=repr(_split(rows[i], delimiter)[j]),
        )
    return values


def raise_if_not_increasing(
    path: PathLike, time: np.ndarray, numbers: np.ndarray, field: str,
    record_kind: str = "line", formatter=lambda t: f"{t:.6f}",
) -> None:
    """Raise :class:`InputError` at the first sample whose time does not increase.

    ``numbers`` are the 1-based line or record numbers of the samples.
    """
    if time.size < 2:
        return
    bad = np.flatnonzero(np.diff(time) <= 0)
    if bad.size:
        i = int(bad[0])
        what = "repeats" if time[i + 1] == time[i] else "goes backwards"
        raise InputError(
            f"time {what}", path=path, line=int(numbers[i + 1]), field=field,
            expected=f"time after {formatter(time[i])} ({record_kind} {int(numbers[i])})",
            found=formatter(time[i + 1]), record_kind=record_kind,
        )


def _json_clean(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_clean(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return None if not math.isfinite(float(obj)) else float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def write_csv(path: PathLike, header: Sequence[str], rows: Iterable[Sequence], protect: Iterable[PathLike] = ()) -> None:
    """A CSV table written atomically (:func:`atomic_output`) by the csv module: ``\\n`` line
    ends, a field with a comma or a quote quoted, as ``csv.reader`` reads it back."""
    with atomic_output(path, "w", protect) as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


def write_json(path: Path, data: dict) -> None:
    """JSON with NaN/inf as null, written atomically."""
    with atomic_output(path, "w") as fh:
        json.dump(_json_clean(data), fh, indent=2)
        fh.write("\n")
