"""The step cache and the one helper the workflow runs its cached steps through."""

from __future__ import annotations

import time

import numpy as np

from georefine.workflows.cache import StepCache, StepRunner


def _counting(value):
    calls = []

    def compute():
        calls.append(1)
        return value

    return compute, calls


def test_a_step_is_computed_once_and_resumed_by_the_next_run(tmp_path):
    value = np.random.default_rng(5).normal(size=(4, 3))
    key = StepCache.key("step", [1, 2, 3])
    compute, calls = _counting(value)
    first = StepRunner(StepCache(tmp_path))
    assert first.cached("step", key, compute, timing="step_s") is value
    assert first.resumed == () and list(first.timings_s) == ["step_s"] and len(calls) == 1
    again = StepRunner(StepCache(tmp_path))
    assert np.array_equal(again.cached("step", key, compute, timing="step_s"), value)
    assert again.resumed == ("step",) and len(calls) == 1
    # Another key, a disabled cache, or a stored value that is no longer valid: computed again.
    assert StepRunner(StepCache(tmp_path)).cached("step", StepCache.key("step", [1, 2, 4]), compute) is value
    assert StepRunner(StepCache(tmp_path, enabled=False)).cached("step", key, compute) is value
    rejected = StepRunner(StepCache(tmp_path))
    assert rejected.cached("step", key, compute, valid=lambda v: False) is value
    assert rejected.resumed == () and len(calls) == 4


def test_encode_decode_and_store_false(tmp_path):
    key = StepCache.key("x")
    runner = StepRunner(StepCache(tmp_path))
    full = runner.cached("x", key, lambda: {"kept": 1, "large": [0] * 10}, encode=lambda v: v["kept"],
                         decode=lambda kept: {"kept": kept, "large": None})
    assert full["large"] == [0] * 10  # the computed result, whole
    assert StepRunner(StepCache(tmp_path)).cached("x", key, lambda: None, encode=lambda v: v["kept"],
                                                   decode=lambda kept: {"kept": kept, "large": None}) == {
        "kept": 1, "large": None}  # the stored form, decoded
    runner.cached("y", key, lambda: 3, store=False)
    assert not StepCache(tmp_path).exists("y", key)
    runner.keep("z", StepCache.key("z1"), 1)
    runner.keep("z", StepCache.key("z2"), 2)  # only the latest entry of a kept side result stays
    assert len(list(tmp_path.glob("z-*.pkl"))) == 1 and StepCache(tmp_path).exists("z", StepCache.key("z2"))


def test_a_step_time_excludes_the_steps_timed_inside_it(tmp_path):
    runner = StepRunner(StepCache(tmp_path))

    def compute():
        with runner.timed("inner"):
            time.sleep(0.2)
        time.sleep(0.05)
        return 1

    runner.cached("outer", StepCache.key("o"), compute, timing="outer")
    assert list(runner.timings_s) == ["inner", "outer"]  # in the order they ended
    assert runner.timings_s["inner"] >= 0.2
    assert 0.05 <= runner.timings_s["outer"] < 0.2, runner.timings_s
