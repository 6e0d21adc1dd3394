"""The strip adjustment of a run (docs/ARCHITECTURE.md §4.5, §5): the corrected trajectory against
the truth, the priors from the G/I's sigmas, the call as a run makes it, the written products."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from georefine.config import LidarAdjustmentConfig
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import exp_so3, log_so3
from georefine.io.trajectory import read_sbet
from georefine.lidar.strip_adjustment import StripCorrections, adjust_strips, apply_strip_corrections
from georefine.trajectory.sampled import Trajectory, trajectory_from_sbet
from georefine.workflows.strip_baseline import (
    gi_strip_priors,
    run_strip_baseline,
    strip_baseline,
    write_strip_baseline,
)
from test_strip_adjustment import MDEG, PRIORS, SIGMA_POS, SIGMA_ROT, STRIPS, simulated_block

SPANS = {st.sid: (st.t0 - 1.0, st.t0 + st.length_m / st.speed_mps + 1.0) for st in STRIPS}


def flown(truth_like: bool = False) -> Trajectory:
    """A trajectory over the five strips (10 Hz, 400 m up along each flight line)."""
    t = np.arange(-5.0, 420.0, 0.1)
    p = np.zeros((t.size, 3))
    v = np.zeros((t.size, 3))
    heading = np.zeros(t.size)
    for st in STRIPS:
        sel = (t >= st.t0 - 5.0) & (t < st.t0 + 95.0)
        p[sel, :2] = st.start + np.outer(t[sel] - st.t0, st.direction * st.speed_mps)
        v[sel, :2] = st.direction * st.speed_mps
        heading[sel] = np.arctan2(st.direction[1], st.direction[0])
    p[:, 2] = 400.0
    R = exp_so3(np.column_stack([0.01 * np.sin(t), 0.01 * np.cos(0.7 * t), heading]))
    return Trajectory(t, p, R, t0_gps=1.4e9, v_w_b=v)


def truth_corrections(truth, like: StripCorrections) -> StripCorrections:
    """The truth's corrections in the form of ``like`` (about the truth's points and times)."""
    z = np.zeros_like(truth.omega)
    return StripCorrections(
        order=1, strip=truth.sid, reference_point_w=truth.q, reference_time=truth.t_ref, omega_rad=truth.omega,
        translation_m=truth.translation, omega_rate_rad_per_s=truth.omega_rate,
        translation_rate_m_per_s=truth.translation_rate, sigma_omega_rad=z, sigma_translation_m=z,
        sigma_omega_rate_rad_per_s=z, sigma_translation_rate_m_per_s=z, n_features=like.n_features,
        n_objects=like.n_objects, rms_distance=like.rms_distance, rms_slope=like.rms_slope,
        robust_sigma_distance=like.robust_sigma_distance, variance_factor=1.0, redundancy=1, objects_used=1,
    )


def attitude_error_mdeg(a: Trajectory, b: Trajectory, sel: np.ndarray) -> float:
    d = log_so3(np.swapaxes(b.R_w_b[sel], 1, 2) @ a.R_w_b[sel])
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))) / MDEG)


def test_the_baseline_brings_the_trajectory_towards_the_truth():
    rng = np.random.default_rng(5)
    features, objects, truth = simulated_block(rng)
    prelim = flown()
    base = strip_baseline(features, objects, prelim, SPANS, PRIORS)
    # The same as the two steps by hand.
    direct = adjust_strips(features, objects, PRIORS)
    np.testing.assert_allclose(base.corrections.omega_rad, direct.omega_rad, atol=1e-12)
    np.testing.assert_array_equal(base.trajectory.p_w_b, apply_strip_corrections(prelim, direct, SPANS).p_w_b)
    # The truth is the preliminary trajectory with the true corrections (the features were
    # perturbed by their inverse).
    true = apply_strip_corrections(prelim, truth_corrections(truth, direct), SPANS)
    inside = np.zeros(prelim.time.size, bool)
    for t0, t1 in SPANS.values():
        inside |= (prelim.time >= t0) & (prelim.time <= t1)
    before = attitude_error_mdeg(prelim, true, inside)
    after = attitude_error_mdeg(base.trajectory, true, inside)
    pos_before = float(np.sqrt(np.mean(np.sum((prelim.p_w_b - true.p_w_b)[inside] ** 2, axis=1))))
    pos_after = float(np.sqrt(np.mean(np.sum((base.trajectory.p_w_b - true.p_w_b)[inside] ** 2, axis=1))))
    assert after < 0.6 * before, (before, after)
    assert pos_after < 0.6 * pos_before, (pos_before, pos_after)
    # Outside the strips' spans nothing moves.
    np.testing.assert_array_equal(base.trajectory.p_w_b[~inside], prelim.p_w_b[~inside])
    assert "strip 1" in base.summary()


def fake_gi(t, sigma_rph, sigma_p):
    return SimpleNamespace(sigma_time=t, sigma_rph_rad=np.tile(sigma_rph, (t.size, 1)),
                           sigma_position_m=np.tile(sigma_p, (t.size, 1)))


def test_priors_from_the_gi_sigmas():
    t = np.arange(0.0, 500.0, 1.0)
    gi = fake_gi(t, np.array([3.0, 4.0, 12.0]) * MDEG, np.array([0.02, 0.03, 0.05]))
    p0 = gi_strip_priors(gi, SPANS)
    np.testing.assert_allclose(p0.rotation_rad, np.array([np.sqrt(12.5), np.sqrt(12.5), 12.0]) * MDEG)
    np.testing.assert_allclose(p0.translation_m, [0.02, 0.03, 0.05])
    assert p0.rotation_rate_rad_per_s is None
    p1 = gi_strip_priors(gi, SPANS, order=1)
    half = 0.5 * np.mean([b - a for a, b in SPANS.values()])
    np.testing.assert_allclose(p1.translation_rate_m_per_s, np.array([0.02, 0.03, 0.05]) / half)
    # A strip turned rigidly moves its trajectory's ends, which the GNSS holds: a 40 mdeg heading
    # sigma shrinks to the position sigma over the shortest strip's lever (500 m of span: 144 m RMS);
    # about east and north the strips along the other axis have no lever (no bound).
    loose = fake_gi(t, np.array([3.0, 4.0, 40.0]) * MDEG, np.array([0.02, 0.03, 0.05]))
    bounded = gi_strip_priors(loose, SPANS, trajectory=flown())
    lever = 500.0 / np.sqrt(12.0)
    np.testing.assert_allclose(bounded.rotation_rad[2], np.sqrt(np.mean(np.square([0.02, 0.03, 0.05]))) / lever,
                               rtol=0.01)
    np.testing.assert_allclose(bounded.rotation_rad[:2], p0.rotation_rad[:2])
    np.testing.assert_allclose(gi_strip_priors(gi, SPANS, trajectory=flown()).rotation_rad, p0.rotation_rad)
    with pytest.raises(InputError, match="posterior"):
        gi_strip_priors(fake_gi(np.zeros(0), np.zeros(3), np.zeros(3)), SPANS)
    with pytest.raises(InputError, match="inside"):
        gi_strip_priors(fake_gi(np.arange(1000.0, 1010.0), np.ones(3), np.ones(3)), SPANS)


def test_as_a_run_calls_it_and_the_products(tmp_path):
    rng = np.random.default_rng(6)
    features, objects, _ = simulated_block(rng)
    prelim = flown()
    t = np.arange(-5.0, 420.0, 1.0)
    gi = fake_gi(t, np.array([SIGMA_ROT, SIGMA_ROT, SIGMA_ROT]), np.full(3, SIGMA_POS))
    gi.spline, gi.high_rate = None, SimpleNamespace(trajectory=lambda spline: prelim)  # imu_rate_trajectory
    frame = LocalFrame.from_degrees(47.0, 11.0, 600.0)
    nav = SimpleNamespace(config=SimpleNamespace(processing=SimpleNamespace(lidar=LidarAdjustmentConfig())),
                          frame=frame, t0_gps=prelim.t0_gps)
    strips = [SimpleNamespace(strip_id=sid, t_first=a, t_last=b) for sid, (a, b) in SPANS.items()]
    base = run_strip_baseline(nav, gi, features, objects, strips)
    assert base.corrections.solve.group("strip_planes").robust_loss == "cauchy"  # the plane observations' loss
    assert base.spans == SPANS
    np.testing.assert_allclose(base.priors.rotation_rad, SIGMA_ROT)
    with pytest.raises(InputError, match="singular"):
        strip_baseline(features, objects, prelim, SPANS, None)

    write_strip_baseline(tmp_path / "strips", nav, base, SimpleNamespace(epsg=25832))
    back = trajectory_from_sbet(read_sbet(tmp_path / "strips" / "trajectory.sbet"), frame, prelim.t0_gps)
    np.testing.assert_allclose(back.time, base.trajectory.time, atol=1e-5)
    np.testing.assert_allclose(back.p_w_b, base.trajectory.p_w_b, atol=2e-3)
    assert attitude_error_mdeg(back, base.trajectory, np.ones(back.time.size, bool)) < 0.1
    record = json.loads((tmp_path / "strips" / "strip_corrections.json").read_text())
    assert record["spans_gps"]["1"][0] == pytest.approx(SPANS[1][0] + prelim.t0_gps)
    np.testing.assert_allclose(StripCorrections.from_dict(record).omega_rad, base.corrections.omega_rad, rtol=1e-12)
