"""The README's smallest example, run exactly as written through the CLI in an empty folder
(once per test run, tests/conftest.py: the G/I/L tests reuse its project and runs).

    georefine simulate corridor-tiny --out tiny --seed 4
    georefine check tiny
    georefine run tiny --out r
    georefine evaluate trajectory r/gil/trajectory.sbet --reference tiny/truth/trajectory.sbet --out r/eval
    georefine run tiny --out r1 --strips 1

and the README's exports for evo and trajectopy of the same run (``georefine export trajectory``
of ``r/gil`` and of the truth, as TUM and as ``.traj``); where evo (``evo_ape``) and trajectopy
(``GEOREFINE_TRAJECTOPY_PYTHON``, see ``tests/trajectory_tools.py``) are installed, their
figures without alignment must equal the evaluation's within 1 % (measured: evo 0.043554 m and
10.751 mdeg, trajectopy 0.043554 m and 10.7505 mdeg, against Georefine's 0.043554 m and 10.7505 mdeg).

With the scenario's defaults and the default processing configuration: no scanner or processing
overrides, so this catches a scenario too sparse for the planar-feature extraction.

Accuracy windows (roll, pitch, yaw RMSE against the truth during a pass, 1 s inset; mdeg), from
the measured seed-4 run:

* both passes: G/I 2.6 / 3.5 / 9.7 (pass 1) and 3.7 / 3.8 / 75 (pass 2); G/I/L 0.49 / 0.77 / 1.7
  and 0.51 / 0.72 / 1.9;
* single pass (strip 1): G/I/L 0.86 / 1.28 / 1.7;
* the whole flight (the README's `evaluate`, turns and manoeuvre included): G/I 4.0 / 3.4 / 38,
  G/I/L 3.3 / 2.3 / 10.1, 3-D position 44 mm.

The checks: G/I/L within 2 mdeg in roll and pitch and 5 mdeg in yaw during the passes (about
twice the measured values); its roll and pitch no worse than G/I's plus 10 % (the LiDAR fixes
heading, it must not spoil the levelling); its yaw at most half of G/I's (measured: a fifth or
less); over the whole flight roll and pitch no worse than G/I's plus 10 %, yaw at most half,
and the position within 0.1 m (it stays on the GNSS, a few centimetres off).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest

from georefine.evaluation.trajectory_files import compare_sbet_files
from georefine.io.pose_files import read_trajectopy, read_tum
from georefine.io.trajectory import read_sbet
from shared_projects import README_COMMANDS, georefine_in, ok
from trajectory_tools import assert_same_figures, evo_ape_rmse, trajectopy_ate, trajectopy_python
from truth_helpers import pass_rmse

pytestmark = pytest.mark.slow  # simulation plus two runs: minutes on two cores


@pytest.fixture(scope="module")
def example(readme_example) -> Path:
    """The folder in which the README's commands ran (tests/conftest.py: once per test run, shared)."""
    return readme_example


def test_the_readme_shows_exactly_the_commands_that_ran():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = "\n".join(f"georefine {' '.join(cmd)}" for cmd in README_COMMANDS)
    assert f"```bash\n{block}\n```" in readme


def _check_pass(gi: np.ndarray, gil: np.ndarray, what: str) -> None:
    assert np.all(gil[:2] <= 2.0) and gil[2] <= 5.0, (what, gi, gil)
    assert np.all(gil[:2] <= 1.1 * gi[:2]), (what, gi, gil)
    assert gil[2] <= 0.5 * gi[2], (what, gi, gil)


def _point_count(path: Path) -> int:
    with laspy.open(path) as f:
        return int(f.header.point_count)


def test_readme_example_runs_and_improves_the_attitude(example):
    tiny, r = example / "tiny", example / "r"
    for rel in ("gi/trajectory.sbet", "gil/trajectory.sbet", "metrics.json", "eval/trajectory_comparison.json"):
        assert (r / rel).is_file(), rel
    metrics = json.loads((r / "metrics.json").read_text())
    assert metrics["strips"] == [1, 2]
    assert all(it["features_used"] > 0 and it["objects"] > 0 for it in metrics["outer_iterations"])
    # Every scanned point georeferenced, one LAZ per strip.
    points = sorted((r / "points").glob("*.laz"))
    assert [p.name for p in points] == ["strip_1.laz", "strip_2.laz"]
    for p in points:
        n = _point_count(p)
        assert n > 0 and n == _point_count(tiny / "scans" / p.name), p.name
    assert all(s["outside_trajectory"] == 0 for s in metrics["points"])

    for strip in (1, 2):
        _check_pass(pass_rmse(r / "gi" / "trajectory.sbet", tiny, strip),
                    pass_rmse(r / "gil" / "trajectory.sbet", tiny, strip), f"pass {strip}")

    # The README's evaluation: the whole flight, against G/I over the same span.
    ev = json.loads((r / "eval" / "trajectory_comparison.json").read_text())
    cmp = compare_sbet_files(r / "gi" / "trajectory.sbet", tiny / "truth" / "trajectory.sbet")
    assert ev["n_epochs"] == len(cmp.time)
    gi = cmp.stats
    for a in ("roll", "pitch"):
        assert ev[f"{a}_rmse_mdeg"] <= 1.1 * gi[f"{a}_rmse_mdeg"], (a, gi, ev)
    assert ev["yaw_rmse_mdeg"] <= 0.5 * gi["yaw_rmse_mdeg"], (gi, ev)
    assert ev["3d_rmse_m"] < 0.1, ev


def test_readme_single_pass_run(example):
    tiny, r1 = example / "tiny", example / "r1"
    metrics = json.loads((r1 / "metrics.json").read_text())
    assert metrics["strips"] == [1]
    assert [p.name for p in (r1 / "points").glob("*.laz")] == ["strip_1.laz"]
    assert _point_count(r1 / "points" / "strip_1.laz") == _point_count(tiny / "scans" / "strip_1.laz")
    _check_pass(pass_rmse(r1 / "gi" / "trajectory.sbet", tiny, 1),
                pass_rmse(r1 / "gil" / "trajectory.sbet", tiny, 1), "single pass")


README_EXPORTS = [("tum", "est.tum", "r/gil/trajectory.sbet"), ("tum", "ref.tum", "tiny/truth/trajectory.sbet"),
                  ("trajectopy", "est.traj", "r/gil/trajectory.sbet"),
                  ("trajectopy", "ref.traj", "tiny/truth/trajectory.sbet")]


@pytest.fixture(scope="module")
def exports(example) -> dict:
    """The README's `georefine export trajectory` commands, run in the example's folder; its evaluation's figures."""
    for fmt, out, source in README_EXPORTS:
        ok(georefine_in(example, "export", "trajectory", source, "--format", fmt, "--out", out))
    return json.loads((example / "r" / "eval" / "trajectory_comparison.json").read_text())


def test_readme_exports_hold_every_pose_in_the_output_crs(example, exports):
    for fmt, out, source in README_EXPORTS:
        poses = (read_tum if fmt == "tum" else read_trajectopy)(example / out)
        sbet = read_sbet(example / source)
        assert poses.epsg == 25832 and len(poses) == len(sbet), out
        np.testing.assert_allclose(poses.time_gps, sbet.time_gps, rtol=0, atol=1e-9)


@pytest.mark.skipif(shutil.which("evo_ape") is None, reason="evo (evo_ape) is not installed")
def test_readme_evo_ape_reproduces_the_evaluation(example, exports, tmp_path):
    position = evo_ape_rmse(example / "ref.tum", example / "est.tum", "trans_part", tmp_path)
    angle = evo_ape_rmse(example / "ref.tum", example / "est.tum", "angle_deg", tmp_path) * 1e3
    assert_same_figures(exports, position, angle, "evo_ape")


@pytest.mark.skipif(trajectopy_python() is None,
                    reason="trajectopy is not installed (GEOREFINE_TRAJECTOPY_PYTHON names an interpreter with it)")
def test_readme_trajectopy_reproduces_the_evaluation(example, exports):
    ate = trajectopy_ate(example / "est.traj", example / "ref.traj")
    assert ate["n"] == exports["n_epochs"]
    assert_same_figures(exports, ate["pos_rms_m"], np.degrees(ate["rot_rms_rad"]) * 1e3, "trajectopy")
