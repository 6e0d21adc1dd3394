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

A workflow runs each cached step through :meth:`StepRunner.cached`: the one place that loads
or computes and stores, times the step and records whether it was resumed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, TypeVar

from georefine import __version__

log = logging.getLogger(__name__)

__all__ = ["StepCache", "StepRunner", "file_stamp"]

T = TypeVar("T")


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


class StepRunner:
    """Runs the steps of a workflow through a :class:`StepCache` and times them.

    ``timings_s`` holds each timed step's wall time in the order run. A step's time excludes
    the steps timed inside it (as a profiler's *self* time), so that nested steps -- the
    filter inside the GNSS/IMU step -- are counted once and the timings add up.
    """

    def __init__(self, cache: StepCache) -> None:
        self.cache = cache
        self.timings_s: dict[str, float] = {}
        self._inner: list[float] = []  # per open timed block: time of the timed blocks inside it

    @property
    def resumed(self) -> tuple[str, ...]:
        """The steps loaded from the cache so far, in the order loaded."""
        return tuple(self.cache.hits)

    @contextmanager
    def timed(self, name: str) -> Iterator[None]:
        """Record the wall time of the block under ``name`` (less that of timed blocks inside it)."""
        start = time.perf_counter()
        self._inner.append(0.0)
        try:
            yield
        finally:
            inner = self._inner.pop()
            elapsed = time.perf_counter() - start
            self.timings_s[name] = elapsed - inner
            if self._inner:
                self._inner[-1] += elapsed

    def cached(
        self,
        name: str,
        key: str,
        compute: Callable[[], T],
        *,
        timing: str | None = None,
        valid: Callable[[Any], bool] | None = None,
        encode: Callable[[T], Any] | None = None,
        decode: Callable[[Any], T] | None = None,
        store: bool = True,
    ) -> T:
        """The result of step ``name``: loaded from the cache under ``key``, else computed (and stored).

        Parameters
        ----------
        name, key
            The cache entry (:meth:`StepCache.load`); a load counts as resumed.
        compute
            Computes the result when the cache has none.
        timing
            Name under which the step's time (load, or compute and store) is recorded; ``None``:
            not timed here (``compute`` may time its parts itself).
        valid
            Rejects a stored value (e.g. when the files it describes are gone).
        encode, decode
            What is stored is ``encode(result)`` and a loaded value is ``decode(stored)``: the
            cache keeps a plain form, the workflow gets the result with what only a computation
            has (the problem to reuse, the features in memory).
        store
            ``False``: a computed result is not stored (a recovery of an entry that is
            stored elsewhere).
        """
        if timing is not None:
            with self.timed(timing):
                return self.cached(name, key, compute, valid=valid, encode=encode, decode=decode, store=store)
        stored = self.cache.load(name, key, valid=valid)
        if stored is not None:
            return stored if decode is None else decode(stored)
        value = compute()
        if store:
            self.cache.store(name, key, value if encode is None else encode(value))
        return value

    def keep(self, name: str, key: str, value: Any) -> None:
        """Store a side result of a step that a later step may need (only the latest entry of ``name``)."""
        self.cache.store(name, key, value, latest_only=True)
