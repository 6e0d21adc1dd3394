"""Results of workflow steps cached in the output folder, so that a rerun resumes.

Every step's result is stored in ``OUT/.cache/NAME-KEY.pkl``, where the *key* is a SHA-256 over
everything the result depends on -- the Georefine version, the configuration sections the step
reads, the size and modification time of its input files (as ``make`` judges files), and the
key of the step before it. A rerun with the same key loads the result instead of computing it;
any change upstream changes every key below it, so stale results are never used. Because the
key is in the file name, runs that share a step (a single-pass run and a full run share the
GNSS/IMU adjustment) can share one cache folder. Files are
written under a temporary name and renamed when complete, so an interrupted run leaves either
the old entry or the new one.

The cache holds Python objects (pickle) of this version of Georefine only: it is a private
working store of the output folder, not an exchange format (the products beside it are). Like
any pickle, load it only from output folders you wrote yourself.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
from pathlib import Path
from typing import Any, Callable

from georefine import __version__

log = logging.getLogger(__name__)

__all__ = ["StepCache", "file_stamp"]


def file_stamp(path: Path, root: Path | None = None) -> list:
    """``[name, size, mtime_ns]`` of a file: what identifies an unchanged input.

    With ``root`` the name is relative to it, so that a project folder that is moved or renamed
    (with its files' times kept, as ``mv`` does) keeps its cache.
    """
    path = Path(path)
    st = path.stat()
    name = path.relative_to(root).as_posix() if root is not None and path.is_relative_to(root) else str(path)
    return [name, st.st_size, st.st_mtime_ns]


class StepCache:
    """Keyed results of workflow steps in ``folder`` (``enabled=False``: never loads, still stores)."""

    def __init__(self, folder: Path, enabled: bool = True) -> None:
        self.folder = Path(folder)
        self.enabled = enabled
        self.hits: list[str] = []
        self._written: dict[str, Path] = {}

    @staticmethod
    def key(*parts: Any) -> str:
        """SHA-256 (hex) of the JSON form of ``parts`` and the Georefine version."""
        text = json.dumps([__version__, *parts], sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()

    def _path(self, name: str, key: str) -> Path:
        return self.folder / f"{name}-{key[:20]}.pkl"

    def load(self, name: str, key: str, valid: Callable[[Any], bool] | None = None) -> Any | None:
        """The stored result of step ``name`` if it was stored under ``key`` (and passes ``valid``)."""
        if not self.enabled:
            return None
        path = self._path(name, key)
        if not path.is_file():
            return None
        try:
            with open(path, "rb") as fh:
                if pickle.load(fh) != key:  # the key, then the value: two pickles
                    return None
                value = pickle.load(fh)
        except Exception as exc:  # unreadable (another version, truncated): recompute
            log.info("cache entry %s unusable (%s); recomputing", path, exc)
            return None
        if valid is not None and not valid(value):
            return None
        self.hits.append(name)
        log.info("resumed %s from %s", name, path)
        return value

    def exists(self, name: str, key: str) -> bool:
        """Whether an entry of step ``name`` is stored under ``key`` (without loading it)."""
        path = self._path(name, key)
        if not (self.enabled and path.is_file()):
            return False
        try:
            with open(path, "rb") as fh:
                return pickle.load(fh) == key  # the key is pickled ahead of the (large) value
        except Exception:  # noqa: BLE001 - unreadable: as good as absent
            return False

    def store(self, name: str, key: str, value: Any, *, latest_only: bool = False) -> None:
        """Store ``value`` for step ``name`` under ``key`` (atomically).

        ``latest_only``: remove the entry of the same name this object stored before (large
        intermediate results of which a resume needs only the last).
        """
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self._path(name, key)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as fh:
                pickle.dump(key, fh, protocol=pickle.HIGHEST_PROTOCOL)
                pickle.dump(value, fh, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        before = self._written.get(name)
        if latest_only and before is not None and before != path:
            before.unlink(missing_ok=True)
        self._written[name] = path
