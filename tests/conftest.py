"""Test ordering for the parallel run.

``--dist loadfile`` hands whole files to the two workers in collection order. Collected
alphabetically, the long end-to-end files (minutes each) came last, and one worker was left
running one of them while the other had finished: the slowest files go first, so that the short
ones fill the gaps at the end.
"""

from __future__ import annotations

SLOW_FIRST = (
    "test_coadjust.py",
    "test_workflow_gil.py",
    "test_delivered.py",
    "test_readme_tiny.py",
    "test_workflow_gil_variants.py",
    "test_trajectory_gi.py",
    "test_time_offset.py",
)
"""Files of about a minute or more, longest first (``python -m pytest --durations=40``)."""


def pytest_collection_modifyitems(session, config, items) -> None:
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order kept otherwise
