"""Progress reporting of long stages: the callback the workflows call and the CLI draws.

A stage reports ``progress(task, done, total)`` whenever it advances; the command line turns
the calls into progress bars, the demo relays them from its second process. The library never
prints (docs/ARCHITECTURE.md §1).
"""

from __future__ import annotations

from typing import Callable

__all__ = ["Progress", "no_progress"]

Progress = Callable[[str, float, float], None]
"""``progress(task, done, total)``: ``task`` names the stage, ``done`` of ``total`` units are finished."""


def no_progress(name: str, done: float, total: float) -> None:
    """The default callback: reports nothing."""
    return None
