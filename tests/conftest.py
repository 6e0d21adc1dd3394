"""Test ordering for the parallel run, and the simulated project and runs three files share.

``--dist loadfile`` hands whole files to the two workers in collection order. Collected
alphabetically, the long end-to-end files (minutes each) came last, and one worker was left
running one of them while the other had finished: the slowest files go first, so that the short
ones fill the gaps at the end.

The README's smallest example (tests/test_readme_tiny.py), tests/test_workflow_gil.py and
tests/test_workflow_gil_variants.py share one simulated ``corridor-tiny`` project and its runs:
:func:`readme_example` runs the README's commands once per test run, whichever worker asks first
(the others wait for it and reuse it: a simulation of 35-40 s, a run of both passes and a
single-pass run of a minute or two each). The other files' fixtures are views of it: the
project, its G/I adjustment as a step cache, the run of both passes and the single pass.
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

from shared_projects import built_once, run_readme_example

SLOW_FIRST = (
    "test_coadjust.py",
    "test_workflow_gil.py",
    "test_operating_matrix.py",
    "test_trajectory_gi.py",
    "test_workflow_gil_variants.py",
    "test_readme_tiny.py",
    "test_api.py",
    "test_bad_inputs.py",
    "test_delivered.py",
    "test_time_offset.py",
    "test_operating_conditions.py",
    "test_upsampling.py",
)
"""Files of about half a minute or more, longest first (``python -m pytest --durations=60``),
except that the files sharing :func:`readme_example` do not start side by side (the second
would wait for the first to build it)."""


def pytest_collection_modifyitems(session, config, items) -> None:
    rank = {name: k for k, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order kept otherwise


@pytest.fixture(scope="session")
def readme_example(tmp_path_factory) -> Path:
    """The folder in which the README's smallest example ran (:data:`shared_projects.README_COMMANDS`):
    ``tiny`` (``corridor-tiny``, seed 4, the corridor's scanner), ``r`` (both passes), ``r/eval``
    and ``r1`` (strip 1). Read only: copy what you modify."""
    return built_once(tmp_path_factory, "readme_example", run_readme_example)


@pytest.fixture(scope="session")
def gil_project(readme_example) -> Path:
    """The README example's project (``corridor-tiny``, seed 4): read only."""
    return readme_example / "tiny"


@pytest.fixture(scope="session")
def gil_gi_cache(readme_example, tmp_path_factory) -> Path:
    """A step cache holding only :func:`gil_project`'s G/I adjustment (steps 1-2, from the README's
    run of both passes): read only, copy it to add steps."""
    import shutil

    def build(out: Path) -> None:
        out.mkdir()
        for f in (readme_example / "r" / ".cache").glob("gi-*.pkl"):
            shutil.copy(f, out / f.name)
        assert any(out.iterdir()), "the README run's cache holds no G/I step"

    return built_once(tmp_path_factory, "gil_gi_cache", build)


@pytest.fixture(scope="session")
def gil_full_run(readme_example) -> Path:
    """The README's ``georefine run tiny --out r`` (both passes, points, step cache in ``.cache``): read only."""
    return readme_example / "r"


@pytest.fixture(scope="session")
def gil_single_pass(readme_example) -> Path:
    """The README's ``georefine run tiny --out r1 --strips 1``: read only."""
    return readme_example / "r1"
