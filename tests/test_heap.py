"""glibc's heap thresholds fixed (georefine.heap): freed arrays go back to the system."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")

# A freed 30 MiB mapping raises glibc's dynamic mmap threshold to 30 MiB; forty 16 MiB arrays then
# come from the heap, with small live objects between them, and freeing them returns nothing
# unless the threshold stays fixed. Prints the MiB the process's resident memory fell by.
PROBE = textwrap.dedent("""
    import sys
    import numpy as np
    import psutil
    if sys.argv[1] == "bound":
        from georefine.heap import bound_heap
        print(bound_heap())
    proc = psutil.Process()
    big = np.ones(30 * 2**20 // 8)
    del big
    keep, arrays = [], []
    for _ in range(40):
        arrays.append(np.ones(16 * 2**20 // 8))
        keep.append(bytearray(4096))
    before = proc.memory_info().rss
    del arrays
    print((before - proc.memory_info().rss) / 2**20)
""")


def _run(code: str, *args: str, **env: str) -> list[str]:
    """``code`` in a fresh interpreter whose environment holds no heap setting but ``env``; its printed words."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GEOREFINE_HEAP"}
    out = subprocess.run([sys.executable, "-c", code, *args], env={**clean, **env}, capture_output=True, text=True,
                         check=True)
    return out.stdout.split()


def _probe(mode: str, **env: str) -> list[str]:
    return _run(PROBE, mode, **env)


def test_freed_arrays_go_back_to_the_system_only_with_the_thresholds_fixed():
    assert float(_probe("plain")[-1]) < 100.0  # glibc's own behaviour: the 640 MiB stay resident
    applied, returned = _probe("bound")
    assert applied == "True" and float(returned) > 600.0


def test_the_environment_can_keep_glibcs_own_behaviour():
    applied, _ = _probe("bound", GEOREFINE_HEAP="default")
    assert applied == "False"
    applied, _ = _probe("bound", MALLOC_MMAP_THRESHOLD_="65536")  # the user's own setting is left alone
    assert applied == "False"


def test_a_task_runner_passes_the_thresholds_to_the_processes_it_starts():
    code = ("import os; from georefine.tasks import TaskRunner; TaskRunner('sync'); "
            "print(os.environ.get('MALLOC_MMAP_THRESHOLD_'), os.environ.get('MALLOC_TRIM_THRESHOLD_'))")
    assert _run(code) == [str(4 * 2**20)] * 2
