"""Exceptions raised by the library.

The library raises, the CLI speaks: every problem with user input is an
:class:`InputError` that names the file, the record or line, the field, what
was expected and what was found. ``georefine.cli`` prints ``str(error)`` as one
line and exits with code 2.
"""

from __future__ import annotations

from pathlib import Path


class GeorefineError(Exception):
    """Base class of all errors raised deliberately by Georefine."""


class InputError(GeorefineError, ValueError):
    """Bad user input: a file, a record in it, or a configuration value.

    Parameters
    ----------
    message
        What is wrong, in one sentence.
    path
        The file concerned, if any.
    line
        1-based line number (text files) or record number (binary files).
    field
        Name of the column, key or attribute concerned.
    expected, found
        What the reader expected and what it found instead.
    record_kind
        ``"line"`` for text files, ``"record"`` for binary ones.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | Path | None = None,
        line: int | None = None,
        field: str | None = None,
        expected: str | None = None,
        found: str | None = None,
        record_kind: str = "line",
    ) -> None:
        self.message = message
        self.path = None if path is None else Path(path)
        self.line = line
        self.field = field
        self.expected = expected
        self.found = found
        self.record_kind = record_kind
        super().__init__(self._format())

    def __reduce__(self):
        """Pickle with every field (a task's error crosses process boundaries intact)."""
        kw = dict(path=self.path, line=self.line, field=self.field, expected=self.expected, found=self.found,
                  record_kind=self.record_kind)
        return _rebuild, (type(self), self.message, kw)

    def _format(self) -> str:
        where = []
        if self.path is not None:
            where.append(str(self.path))
        if self.line is not None:
            where.append(f"{self.record_kind} {self.line}")
        if self.field is not None:
            where.append(f"field '{self.field}'")
        text = (", ".join(where) + ": " if where else "") + self.message
        if self.expected is not None:
            text += f" (expected {self.expected}"
            text += f", found {self.found})" if self.found is not None else ")"
        elif self.found is not None:
            text += f" (found {self.found})"
        return text


def _rebuild(cls, message, kw):
    return cls(message, **kw)


class ConfigError(InputError):
    """Invalid configuration (``project.yaml``, scenario YAML or ``--set`` override)."""
