"""Wrong GNSS fixes (ambiguity jumps) found in the G/I's residuals (docs/ARCHITECTURE.md §4.3 GNSS).

The detector (:func:`georefine.adjustment.gnss_jumps.find_jumps`) on synthetic residual series at 5 Hz
with 1-2 cm of correlated noise: a 10 cm jump of 60 s is found with its span, as a box and as the G/I
leaves it (the trajectory follows the offset within seconds, so only its edges stay in the residuals);
clean noise gives no alarm over many seeds. End to end on corridor-tiny, a simulated wrong fix
(``gnss.ambiguity_jumps``) is found, warned of and taken with an offset of its own; switched off, the
pass follows it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from georefine.adjustment.gnss_jumps import find_jumps, jump_warning
from georefine.adjustment.gnss_segments import jump_spans, non_fix_segments
from georefine.config import GnssFloatOffset
from georefine.evaluation.trajectory_files import compare_sbet_files, read_sbet_companion
from georefine.io.trajectory import read_smrmsg, smrmsg_path
from georefine.sim.gnss import _gauss_markov
from georefine.sim.scenarios import simulate_project
from georefine.trajectory.sampled import interp_columns
from georefine.workflows import run_trajectory

RATE = 5.0
SIGMA = np.array([0.01, 0.01, 0.02])  # the residuals' stated (white) sigma east/north/up


def _noise(rng, duration_s: float, gm_sigma: float = 0.015, tau_s: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Epochs at 5 Hz and residuals of white noise of ``SIGMA`` plus a Gauss-Markov error (``gm_sigma``
    horizontal, twice up; ``tau_s``): 1.8 cm horizontal and 3.6 cm up in total."""
    t = np.arange(0.0, duration_s, 1.0 / RATE)
    gm = _gauss_markov(rng, t.size, 1.0 / RATE, np.array([1.0, 1.0, 2.0]) * gm_sigma, tau_s)
    return t, rng.normal(0.0, 1.0, (t.size, 3)) * SIGMA + gm


def _followed(box: np.ndarray, tau_s: float = 2.0) -> np.ndarray:
    """What of ``box`` (M, 3) the G/I, which follows it within ``tau_s``, leaves in the residuals: the box less
    its convolution with a two-sided exponential (the mean of a forward and a backward first-order filter;
    on corridor-tiny the residuals of a 10.5 cm step were -4.2/+4.5 cm in the second before and after it)."""
    a = np.exp(-1.0 / (RATE * tau_s))
    passes = []
    for order in (slice(None), slice(None, None, -1)):
        x = box[order].copy()
        for i in range(1, x.shape[0]):
            x[i] = a * x[i - 1] + (1.0 - a) * x[i]
        passes.append(x[order])
    return box - 0.5 * (passes[0] + passes[1])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("shape", ["box", "followed"])
def test_a_10_cm_jump_of_60_s_is_found_with_its_span(seed, shape):
    """10 cm horizontally in any direction (and a few cm in height) over 60 s, in 1.8/3.6 cm of noise."""
    rng = np.random.default_rng(seed)
    t, r = _noise(rng, 600.0)
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    offset = np.array([0.10 * np.sin(azimuth), 0.10 * np.cos(azimuth), rng.normal(0.0, 0.03)])
    inside = (t >= 200.0) & (t < 260.0)
    box = np.where(inside[:, None], offset, 0.0)
    r = r + (box if shape == "box" else _followed(box))
    jumps = find_jumps(t, r, SIGMA)
    assert len(jumps) == 1, [jump_warning(j, 0.0) for j in jumps]
    j = jumps[0]
    assert abs(j.t_start - 200.0) <= 0.4 and abs(j.t_end - 259.8) <= 0.4, j
    assert np.linalg.norm(j.sigmas_start) > 6.0 and np.linalg.norm(j.sigmas_end) > 6.0
    axis = np.argmax(np.abs(offset))
    assert np.sign(j.step_start_m[axis]) == np.sign(offset[axis]) == -np.sign(j.step_end_m[axis])
    if shape == "box":  # the whole step shows: the window difference measures it (less the noise)
        np.testing.assert_allclose(j.step_start_m, offset, atol=0.035)  # s_D: 0.7 cm, 1.4 cm in height
        np.testing.assert_allclose(j.step_end_m, -offset, atol=0.035)
    message = jump_warning(j, 1000.0)
    assert "from 1200.0 to 1259.8 GPS s (300 epochs, 59.8 s)" in message and "gnss.float_offset" in message


def test_clean_noise_raises_no_alarm():
    """No alarm in 300 series of 10 minutes (50 hours of 5 Hz residuals) with 1.5-2 cm of noise correlated
    over 20 and over 5 s at the default threshold of 6: a false-alarm rate below 6 % per hour of flight at
    95 % confidence. The tail is near: at 5.5 one series raises one, at 5 five."""
    alarms = {6.0: 0, 5.0: 0}
    for seed in range(300):
        rng = np.random.default_rng(1000 + seed)
        t, r = _noise(rng, 600.0, gm_sigma=0.015 if seed % 2 else 0.02, tau_s=20.0 if seed % 3 else 5.0)
        for threshold in alarms:
            alarms[threshold] += bool(find_jumps(t, r, SIGMA, threshold=threshold))
    assert alarms[6.0] == 0, alarms
    assert 1 <= alarms[5.0] <= 15, alarms  # measured: 5


def test_outliers_a_gap_and_a_jump_to_the_end_of_the_run():
    """A 30-sigma outlier is no jump; a jump the data end in is one to the end of its run; a gap ends a run."""
    rng = np.random.default_rng(5)
    t, r = _noise(rng, 300.0)
    r[700] += 30.0 * SIGMA
    assert find_jumps(t, r, SIGMA) == []
    r[t >= 250.0] += [0.0, 0.0, 0.15]  # the last 50 s: a wrong fix the data end in
    keep = (t < 100.0) | (t > 130.0)  # a 30 s gap
    jumps = find_jumps(t[keep], r[keep], SIGMA)
    assert len(jumps) == 1 and jumps[0].t_start == pytest.approx(250.0) and jumps[0].t_end == pytest.approx(t[-1])
    assert jumps[0].step_end_m is None and "the run ends with it" in jump_warning(jumps[0], 0.0)


def test_jumps_are_segments_after_those_of_the_flags():
    t = np.arange(0.0, 100.0, 0.2)
    q = np.ones(t.size, dtype=np.int64)
    q[(t >= 10.0) & (t <= 20.0)] = 2
    cov = np.broadcast_to(np.diag(SIGMA**2), (t.size, 3, 3))
    seg = non_fix_segments(t, q, cov, GnssFloatOffset(), jumps=np.array([[15.0, 40.0], [60.0, 70.0]]))
    assert len(seg) == 3 and seg.quality.tolist() == [2, 1, 1]
    np.testing.assert_allclose(seg.t_start, [10.0, 20.2, 60.0])  # the float epochs stay in their segment
    np.testing.assert_allclose(seg.t_end, [20.0, 40.0, 70.0])
    assert seg.epochs.tolist() == [51, 100, 51]
    np.testing.assert_allclose(jump_spans(seg), [[20.2, 40.0], [60.0, 70.0]])
    assert jump_spans(non_fix_segments(t, q, cov, GnssFloatOffset())) is None
    assert non_fix_segments(t, q, cov, None, jumps=np.array([[15.0, 40.0]])) is None


JUMP = (105.0, 135.0)  # inside the first pass of corridor-tiny (94 .. 150 s)
FAST_SCAN = ["scanner.pulse_rate_hz=2000", "scanner.line_rate_hz=100"]  # the navigation data do not depend on the scanner


def _window_errors(solution: Path, project: Path) -> tuple[np.ndarray, np.ndarray]:
    """RMS position error (m) and error/sigma (north/east/down) inside the jump."""
    sbet = solution / "trajectory.sbet"
    cmp = compare_sbet_files(sbet, project / "truth" / "trajectory.sbet")
    rel = cmp.t0_gps + cmp.time - yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["t0_gps"]
    inside = (rel > JUMP[0]) & (rel < JUMP[1])
    sig = read_smrmsg(smrmsg_path(sbet), gps_week=read_sbet_companion(sbet).gps_week)
    s = interp_columns(cmp.t0_gps + cmp.time[inside], sig.time_gps, sig.sigma_ned_m)
    e = cmp.d_ned_m[inside]
    return np.sqrt(np.mean(e**2, axis=0)), np.sqrt(np.mean((e / s) ** 2, axis=0))


def test_the_gi_finds_a_wrong_fix_and_gives_it_an_offset(tmp_path, caplog):
    """A wrong fix of 19 cm (seed 3) over 30 s, flagged Q=1 with the fixed sigmas: found with its span and
    warned of, estimated within 1 cm of the truth; the pass inside it then within its stated sigma. Taken
    as it is, the pass follows it by 12-14 cm horizontally."""
    project = tmp_path / "tiny"
    simulate_project("corridor-tiny", project, seed=3, overrides=FAST_SCAN + [
        f"gnss.ambiguity_jumps=[[{JUMP[0]}, {JUMP[1]}]]", "gnss.jump_sigma_horizontal_m=0.1"])
    with caplog.at_level("WARNING", logger="georefine.adjustment.gnss_imu"):
        run_trajectory(project, tmp_path / "found")
    warned = [r.getMessage() for r in caplog.records if "stand off their neighbours" in r.getMessage()]
    assert len(warned) == 1 and "(151 epochs, 30.0 s)" in warned[0], warned
    seg = json.loads((tmp_path / "found" / "adjustment.json").read_text())["gnss_error"]["segments"]
    assert len(seg) == 1 and seg[0]["quality"] == 1 and seg[0]["epochs"] == 151
    assert seg[0]["t_start_s"] == JUMP[0] and seg[0]["t_end_s"] == JUMP[1]
    truth = np.load(project / "truth" / "gnss_errors.npz")
    t0 = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["t0_gps"]
    ned = truth["jump_ned"][np.argmin(np.abs(truth["time_gps"] - t0 - 120.0))]
    true_enu = np.array([ned[1], ned[0], -ned[2]])  # measured: +0.121/-0.134/+0.071 m, estimated +0.116/-0.134/+0.064
    assert np.all(np.abs(np.asarray(seg[0]["offset_enu_m"]) - true_enu) < 0.015), (seg, true_enu)
    err, z = _window_errors(tmp_path / "found", project)
    # Measured: 1.6/1.3/3.1 cm, error/sigma 0.98/0.81/0.98 (the correlated GNSS error's, which no offset removes).
    assert np.linalg.norm(err) < 0.05 and 0.5 < np.sqrt(np.mean(z**2)) < 2.0 and np.all(z < 2.5), (err, z)

    taken = tmp_path / "taken-as-it-is"
    shutil.copytree(project, taken, symlinks=True)
    cfg = yaml.safe_load((taken / "project.yaml").read_text())
    cfg["gnss"]["float_offset"] = {"detect_jumps": False}
    (taken / "project.yaml").write_text(yaml.safe_dump(cfg))
    run_trajectory(taken, tmp_path / "taken")
    bad, bad_z = _window_errors(tmp_path / "taken", taken)
    # Measured: 14.5/12.4/3.2 cm, error/sigma 8.8/7.5/1.0.
    assert np.linalg.norm(bad) > 3.0 * np.linalg.norm(err) and bad_z.max() > 5.0, (bad, err, bad_z)
    assert json.loads((tmp_path / "taken" / "adjustment.json").read_text())["gnss_error"].get("segments") is None
