"""A small area block end to end on simulated truth: 3 parallel strips and a cross strip.

`area-tiny` (docs/ARCHITECTURE.md §6 "Flight plans"): strips 1, 3, 2 flown back and forth in a
racetrack order at 30 % sidelap and strip 4 across them. The G/I/L holds one trajectory through
all four strips, tied by planes that strips flown minutes apart see; the evaluation gives every
strip's attitude against the truth and every pair of strips' differences on planar surfaces.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import georefine
from georefine.evaluation.trajectory_files import truth_pass_accuracy
from georefine.io.run_metrics import WorkflowMetrics

pytestmark = pytest.mark.slow

STRIPS = [1, 3, 2, 4]  # in flying order


@pytest.fixture(scope="module")
def block(tmp_path_factory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("block")
    project, out = base / "area", base / "run"
    georefine.simulate("area-tiny", project, seed=11)
    georefine.run(project, out)
    return project, out


@pytest.fixture(scope="module")
def evaluation(block):
    project, out = block
    return georefine.evaluate_run(project, out)


def test_the_block_is_checked_and_every_strip_is_georeferenced(block):
    project, out = block
    summary = georefine.check(project)
    assert sorted(i for s in summary.strips for i in s.strip_ids) == sorted(STRIPS)
    metrics = WorkflowMetrics.from_dict(json.loads((out / "metrics.json").read_text()))
    assert sorted(metrics.strips) == sorted(STRIPS)
    assert sorted(p.strip for p in metrics.points) == sorted(STRIPS)
    assert all(p.points > 100_000 for p in metrics.points)


def test_every_strip_gains_from_the_lidar_and_states_its_accuracy(block):
    project, out = block
    for strip in STRIPS:
        gi = truth_pass_accuracy(out / "gi" / "trajectory.sbet", project, strip)
        gil = truth_pass_accuracy(out / "gil" / "trajectory.sbet", project, strip)
        # Yaw at most 0.3 x G/I or 3 mdeg (what the full `area` block reaches, BENCHMARKS.md) -- or
        # within twice the sigma the G/I/L states for it: on 300 m strips that is 2.9-3.5 mdeg, and
        # the middle strip of seed 11 has 5.5 mdeg against 7.8 from the G/I (1.5 sigma).
        # Roll and pitch never worse than G/I by more than 10 % + 0.3 mdeg.
        yaw_bound = max(0.3 * gi.rmse_mdeg[2], 3.0, 2.0 * gil.sigma_rms_mdeg[2])
        assert gil.rmse_mdeg[2] <= yaw_bound, (strip, gi.rmse_mdeg, gil.rmse_mdeg, gil.sigma_rms_mdeg)
        assert np.all(gil.rmse_mdeg[:2] <= 1.1 * gi.rmse_mdeg[:2] + 0.3), (strip, gi.rmse_mdeg, gil.rmse_mdeg)
        assert np.all(gil.rmse_mdeg[:2] < 2.5) and gil.rmse_mdeg[2] < 7.0, (strip, gil.rmse_mdeg)
        # Consistency: the stated G/I/L sigma against the actual error, per angle.
        assert np.all((gil.z_rms > 0.4) & (gil.z_rms < 2.5)), (strip, gil.z_rms)


def test_strips_of_a_block_agree_pair_by_pair(evaluation):
    pairs = evaluation.strip_pairs
    before, after = pairs["G/I"].pairs, pairs["G/I/L"].pairs
    overlapping = [p for p in after.pairs if p.median_mm is not None]
    # 1-2, 2-3 side by side; the cross strip 4 over all three; 1 and 3 do not overlap at 30 % sidelap.
    assert {(p.strip_a, p.strip_b) for p in overlapping} == {(1, 2), (2, 3), (1, 4), (2, 4), (3, 4)}
    assert all(p.cells >= 1000 for p in overlapping)
    assert max(p.median_mm for p in overlapping) <= 5.0
    gi = {(p.strip_a, p.strip_b): p for p in before.pairs}
    # The adjustment brings the cross strip onto the others: a centimetre-level disagreement before.
    assert np.mean([gi[(p.strip_a, p.strip_b)].median_mm for p in overlapping]) > 2.0 * np.mean(
        [p.median_mm for p in overlapping])


def test_the_strip_adjustment_baseline_beside_the_trajectory_adjustment(block, evaluation):
    _, out = block
    assert (out / "baseline" / "trajectory.sbet").is_file() and (out / "baseline" / "strip_corrections.json").is_file()
    base, gil = evaluation.trajectory["strip adjustment"], evaluation.trajectory["G/I/L"]
    assert sorted(base.strips) == sorted(STRIPS)
    # A rotation and translation per strip fits the strips to each other (the pairs agree better
    # than under the G/I) but cannot follow the trajectory within a strip: the G/I/L does both.
    pairs = {label: {(p.strip_a, p.strip_b): p.median_mm for p in v.pairs.pairs if p.median_mm is not None}
             for label, v in evaluation.strip_pairs.items()}
    assert set(pairs["strip adjustment"]) == set(pairs["G/I/L"])
    assert np.mean(list(pairs["strip adjustment"].values())) < 0.5 * np.mean(list(pairs["G/I"].values()))
    assert np.mean(list(pairs["G/I/L"].values())) < np.mean(list(pairs["strip adjustment"].values()))
    for strip in STRIPS:
        assert gil.strips[strip].yaw_rmse_mdeg < base.strips[strip].yaw_rmse_mdeg
