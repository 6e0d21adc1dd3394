"""Test ordering for the parallel run, and the simulated project two files share.

``--dist loadfile`` hands whole files to the two workers in collection order. Collected
alphabetically, the long end-to-end files (minutes each) came last, and one worker was left
running one of them while the other had finished: the slowest files go first, so that the short
ones fill the gaps at the end.

tests/test_workflow_gil.py and tests/test_workflow_gil_variants.py run on the same simulated
``corridor-tiny`` project and start from its G/I adjustment: :func:`gil_project` and
:func:`gil_gi_cache` build them once per test run, whichever worker asks first (the other
reuses them; a simulation is 35-40 s, the G/I adjustment 12-15 s).
"""

from __future__ import annotations

import os
from pathlib import Path

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Each worker is one process on one core: BLAS, OpenMP and numba thread pools of the size of
    # the machine in every worker oversubscribe the cores (a G/I test alone: 72 s with them, 58 s
    # without). Set before numpy is imported; subprocesses and dask workers inherit it.
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import pytest
from shared_projects import GIL_SCAN, built_once

SLOW_FIRST = (
    "test_coadjust.py",
    "test_workflow_gil.py",
    "test_workflow_gil_variants.py",
    "test_readme_tiny.py",
    "test_trajectory_gi.py",
    "test_bad_inputs.py",
    "test_delivered.py",
    "test_time_offset.py",
    "test_operating_conditions.py",
    "test_upsampling.py",
)
"""Files of about half a minute or more, longest first (``python -m pytest --durations=60``),
except that the two files sharing :func:`gil_project` do not start side by side (the second
would wait for the first to build it)."""


def pytest_collection_modifyitems(session, config, items) -> None:
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order kept otherwise


@pytest.fixture(scope="session")
def gil_project(tmp_path_factory) -> Path:
    """``corridor-tiny``, seed 7, the corridor's scanner (:data:`GIL_SCAN`): read only."""
    from georefine.sim.scenarios import simulate_project

    return built_once(tmp_path_factory, "gil_project",
                      lambda out: simulate_project("corridor-tiny", out, seed=7, overrides=GIL_SCAN))


@pytest.fixture(scope="session")
def gil_gi_cache(gil_project, tmp_path_factory) -> Path:
    """A step cache holding :func:`gil_project`'s G/I adjustment (steps 1-2): read only, copy it to add steps."""
    from georefine.workflows.lidar import precompute_gnss_imu

    return built_once(tmp_path_factory, "gil_gi_cache", lambda out: precompute_gnss_imu(gil_project, out))
