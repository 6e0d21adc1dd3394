"""Which point files in a folder Georefine wrote: ``georefine-points.json`` (docs/ARCHITECTURE.md §3).

Every writer of georeferenced strips (``georefine run``'s ``points/``, ``georefine
georeference``) records the files it completed, with their size and modification time, in the
folder's manifest (merged with what earlier runs recorded). Evaluations that are given a folder
then read exactly those files: a LAS/LAZ file left there by something else, or by an older run
with other strips, is named in a warning and left out instead of silently changing the figures,
and a recorded file that has gone is an error. A folder without a manifest (another tool's
output) is read whole.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from georefine.errors import InputError
from georefine.io.files import atomic_output

__all__ = ["MANIFEST", "record_point_files", "manifest_files"]

log = logging.getLogger(__name__)

MANIFEST = "georefine-points.json"


def _stamp(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def record_point_files(paths: list[Path], points: list[int]) -> None:
    """Add the completed files ``paths`` (with their point counts) to their folders' manifests."""
    by_folder: dict[Path, list[tuple[Path, int]]] = {}
    for p, n in zip(map(Path, paths), points):
        by_folder.setdefault(p.parent, []).append((p, int(n)))
    for folder, items in by_folder.items():
        path = folder / MANIFEST
        entries = {}
        if path.is_file():
            try:
                entries = {e["file"]: e for e in json.loads(path.read_text())["files"]}
            except (ValueError, KeyError, TypeError):
                entries = {}  # unreadable: rewritten from what is known now
        for p, n in items:
            entries[p.name] = {"file": p.name, "points": n, "stamp": _stamp(p)}
        with atomic_output(path, "w") as fh:
            json.dump({"files": sorted(entries.values(), key=lambda e: e["file"])}, fh, indent=1)


def manifest_files(folder: Path) -> list[Path] | None:
    """The point files of ``folder`` its manifest lists (None without a manifest); others are warned about.

    Raises
    ------
    InputError
        The manifest is unreadable or names a file that is no longer there.
    """
    path = Path(folder) / MANIFEST
    if not path.is_file():
        return None
    try:
        entries = json.loads(path.read_text())["files"]
        names = [str(e["file"]) for e in entries]
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError("unreadable manifest of the point files", path=path, found=str(exc)) from None
    files = []
    for e, name in zip(entries, names):
        f = path.parent / name
        if not f.is_file():
            raise InputError("a point file the manifest lists is missing", path=f, expected=f"listed in {MANIFEST}")
        if _stamp(f) != list(e.get("stamp", [])):
            log.warning("%s changed after Georefine wrote it (size or time differ from %s); used as it is", f, MANIFEST)
        files.append(f)
    others = sorted(q.name for q in path.parent.iterdir()
                    if q.suffix.lower() in (".las", ".laz") and q.name not in set(names))
    if others:
        log.warning("%s: left out %d LAS/LAZ file(s) that Georefine did not write there (%s); name them to use them",
                    path.parent, len(others), ", ".join(others))
    return sorted(files)
