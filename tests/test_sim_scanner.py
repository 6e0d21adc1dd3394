"""Tests of the multi-view scanner simulation (georefine.sim.scanner)."""

import numpy as np
import pydantic
import pytest
from scipy.spatial.transform import Rotation

from georefine.sim.scanner import FACET_SWEEP_RAD, ScanChunk, ScannerConfig, scan
from georefine.sim.scene import SceneConfig, build_scene

H_AGL, SPEED = 160.0, 18.0
# body x forward = south (-y), y right = west (-x), z down: columns of R_w_b
R_SOUTH = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
T0 = 1000.0  # times are relative to the dataset epoch, not zero at the start


def level_flight(y0, z, wobble=0.0):
    """Straight flight heading south at height z; optional small roll/pitch/yaw wobble [rad]."""

    def pose_fn(t):
        t = np.asarray(t, float)
        p = np.column_stack([np.zeros_like(t), y0 - SPEED * (t - T0), np.full_like(t, z)])
        rv = wobble * np.column_stack([np.sin(2.1 * t), np.cos(1.3 * t), np.sin(0.7 * t + 1)])
        return p, R_SOUTH @ Rotation.from_rotvec(rv).as_matrix()

    return pose_fn


@pytest.fixture(scope="module")
def flat_scene():
    cfg = SceneConfig(length_m=600.0, width_m=500.0, end_margin_m=100.0, side_rise_m=0.0,
                      undulation_m=0.0, floor_slope_m_per_m=0.0, settlement_count=0,
                      scattered_building_count=0, power_line=False, vegetation_per_ha=0.0)
    return build_scene(cfg, np.random.default_rng(5))


@pytest.fixture(scope="module")
def scene():
    cfg = SceneConfig(length_m=600.0, width_m=500.0, end_margin_m=100.0, settlement_count=2,
                      buildings_per_settlement=8, scattered_building_count=2)
    return build_scene(cfg, np.random.default_rng(6))


def concat(chunks):
    chunks = list(chunks)
    assert all(isinstance(c, ScanChunk) for c in chunks)
    return {name: np.concatenate([getattr(c, name) for c in chunks]) for name in
            ("time", "xyz_s", "channel", "scan_angle_rad", "intensity", "range_error_m",
             "face_id", "xyz_w_true")}


@pytest.fixture(scope="module")
def realistic(scene):
    cfg = ScannerConfig()
    p_b_s = np.array([0.35, -0.12, 0.48])
    R_b_s = Rotation.from_rotvec([0.004, -0.006, 0.01]).as_matrix()
    z = np.mean(scene.axis_w[:, 2]) + H_AGL
    pose_fn = level_flight(400.0, z, wobble=0.03)
    pts = concat(scan(pose_fn, T0, T0 + 2.0, scene, cfg, p_b_s, R_b_s, np.random.default_rng(7),
                      chunk_duration_s=0.5))
    return pts, pose_fn, p_b_s, R_b_s, cfg


def test_measurements_consistent_with_pose(realistic, scene):
    pts, pose_fn, p_b_s, R_b_s, cfg = realistic
    assert len(pts["time"]) > 0.9 * 2.0 * cfg.pulse_rate_hz * 100 / 120
    p_w_b, R_w_b = pose_fn(pts["time"])
    p_w_s = p_w_b + R_w_b @ p_b_s
    true_range = np.linalg.norm(pts["xyz_w_true"] - p_w_s, axis=1)
    d_w = (pts["xyz_w_true"] - p_w_s) / true_range[:, None]
    # |xyz_s| = true range + noise
    np.testing.assert_allclose(np.linalg.norm(pts["xyz_s"], axis=1),
                               true_range + pts["range_error_m"], atol=1e-6)
    # georeferencing with the true pose reproduces the true point plus the noise
    x_w = p_w_b + np.einsum("nij,nj->ni", R_w_b, pts["xyz_s"] @ R_b_s.T + p_b_s)
    np.testing.assert_allclose(x_w, pts["xyz_w_true"] + pts["range_error_m"][:, None] * d_w,
                               atol=1e-6)
    # the true point is on the surface that was hit
    v0 = np.asarray(scene.mesh.vertices)[np.asarray(scene.mesh.faces)[pts["face_id"], 0]]
    dist = np.einsum("ij,ij->i", pts["xyz_w_true"] - v0, scene.surface_normal(pts["face_id"]))
    assert np.max(np.abs(dist)) < 1e-6
    # the beam leaves the scanner in the commanded direction
    d_s = pts["xyz_s"] / np.linalg.norm(pts["xyz_s"], axis=1, keepdims=True)
    tau = np.radians(np.array(cfg.facet_tilt_deg))[pts["channel"]]
    np.testing.assert_allclose(d_s[:, 0], np.sin(tau), atol=1e-12)
    np.testing.assert_allclose(np.arctan2(d_s[:, 1], d_s[:, 2]), pts["scan_angle_rad"], atol=1e-12)


def test_noise_and_intensity(realistic):
    pts, *_, cfg = realistic
    err = pts["range_error_m"]
    assert abs(np.mean(err)) < 3e-4 and abs(np.std(err) / cfg.range_sigma_m - 1) < 0.02
    inten = pts["intensity"]
    assert inten.dtype == np.uint16 and inten.min() >= 1
    assert 500 < np.median(inten) < 20000


def test_range_offset_and_scale_of_the_unit(scene):
    """``(1 + k) r + r0 + e``: the same pulses and noise as an ideal unit, every range longer by ``k r + r0``."""
    p_b_s, R_b_s = np.array([0.35, -0.12, 0.48]), np.eye(3)
    pose_fn = level_flight(400.0, np.mean(scene.axis_w[:, 2]) + H_AGL)
    ideal = concat(scan(pose_fn, T0, T0 + 0.5, scene, ScannerConfig(), p_b_s, R_b_s, np.random.default_rng(3)))
    unit = concat(scan(pose_fn, T0, T0 + 0.5, scene, ScannerConfig(range_offset_m=0.03, range_scale_ppm=100.0),
                       p_b_s, R_b_s, np.random.default_rng(3)))
    np.testing.assert_array_equal(unit["time"], ideal["time"])
    r_ideal = np.linalg.norm(ideal["xyz_s"], axis=1)
    true_range = r_ideal - ideal["range_error_m"]
    np.testing.assert_allclose(np.linalg.norm(unit["xyz_s"], axis=1) - r_ideal, 0.03 + 100e-6 * true_range, atol=1e-9)
    np.testing.assert_allclose(unit["range_error_m"] - ideal["range_error_m"], 0.03 + 100e-6 * true_range, atol=1e-9)


def test_channels_cycle_per_line(realistic):
    pts, *_, cfg = realistic
    t = pts["time"]
    assert np.all(np.diff(t) > 0) and t[0] >= T0 and t[-1] < T0 + 2.0
    line = np.floor(t * cfg.line_rate_hz).astype(np.int64)
    np.testing.assert_array_equal(pts["channel"], line % 3)
    first = np.r_[True, np.diff(line) > 0]
    seq = pts["channel"][first]
    np.testing.assert_array_equal(np.diff(seq.astype(int)) % 3, 1)  # 0 -> 1 -> 2 -> 0 ...
    assert np.max(np.abs(pts["scan_angle_rad"])) <= np.radians(cfg.field_of_view_deg) / 2


@pytest.fixture(scope="module")
def flat_points(flat_scene):
    cfg = ScannerConfig()
    pose_fn = level_flight(450.0, H_AGL)
    pts = concat(scan(pose_fn, T0, T0 + 6.0, flat_scene, cfg, np.zeros(3), np.eye(3),
                      np.random.default_rng(8)))
    return pts, pose_fn, cfg


def test_view_footprints_separated_along_track(flat_points):
    pts, pose_fn, cfg = flat_points
    p_w_b, _ = pose_fn(pts["time"])
    near_nadir = np.abs(pts["scan_angle_rad"]) < 0.02
    along = pts["xyz_w_true"][:, 1] - p_w_b[:, 1]
    offset = {c: np.median(along[near_nadir & (pts["channel"] == c)]) for c in range(3)}
    ahead = H_AGL * np.tan(np.radians(10.0))  # 28.2 m; heading south: forward is -y
    assert abs(offset[0]) < 0.05
    assert abs(offset[1] + ahead) < 0.1 and abs(offset[2] - ahead) < 0.1
    assert abs((offset[2] - offset[1]) - 2 * H_AGL * np.tan(np.radians(10.0))) < 0.1  # ~56.4 m
    # positive scan angles look right = west (-x) when heading south
    right = pts["scan_angle_rad"] > 0.3
    assert np.all(pts["xyz_w_true"][right, 0] < 0)
    # swath width of the nadir view: +-h tan(50 deg)
    x0 = pts["xyz_w_true"][pts["channel"] == 0, 0]
    assert abs(x0.max() - H_AGL * np.tan(np.radians(50.0))) < 1.0


def test_point_density_per_view(flat_points):
    pts, pose_fn, cfg = flat_points
    # a window seen by all three views during the 6 s pass (body y from 450 to 342)
    y_lo, y_hi, half_x = 375.0, 417.0, 10.0
    xyz = pts["xyz_w_true"]
    inside = (np.abs(xyz[:, 0]) < half_x) & (xyz[:, 1] > y_lo) & (xyz[:, 1] < y_hi)
    # lines per metre along: line_rate / (3 v); pulses per radian: pulse_rate / line_rate / 120 deg
    expected = ((y_hi - y_lo) * cfg.line_rate_hz / (3 * SPEED) * 2 * np.arctan(half_x / H_AGL)
                * cfg.pulse_rate_hz / cfg.line_rate_hz / FACET_SWEEP_RAD)
    area = 2 * half_x * (y_hi - y_lo)
    for c in range(3):
        count = np.count_nonzero(inside & (pts["channel"] == c))
        assert abs(count / expected - 1) < 0.03, (c, count, expected)
        assert count / area > 10.0  # >= ~5 points/m^2 per view required; ~11 at nadir


def test_chunking_does_not_change_geometry(flat_scene):
    cfg = ScannerConfig(pulse_rate_hz=50_000.0, line_rate_hz=90.0)
    pose_fn = level_flight(300.0, H_AGL, wobble=0.02)
    a = concat(scan(pose_fn, T0 + 0.123, T0 + 1.5, flat_scene, cfg, np.zeros(3), np.eye(3),
                    np.random.default_rng(1), chunk_duration_s=0.37))
    b = concat(scan(pose_fn, T0 + 0.123, T0 + 1.5, flat_scene, cfg, np.zeros(3), np.eye(3),
                    np.random.default_rng(1), chunk_duration_s=5.0))
    np.testing.assert_array_equal(a["time"], b["time"])
    np.testing.assert_array_equal(a["xyz_w_true"], b["xyz_w_true"])


def test_chunks_as_tasks_give_the_same_scan(flat_scene):
    """Each chunk draws its noise from its own seed: tasks on two threads give the serial scan."""
    from georefine.tasks import TaskRunner

    cfg = ScannerConfig(pulse_rate_hz=50_000.0, line_rate_hz=90.0)
    pose_fn = level_flight(300.0, H_AGL, wobble=0.02)
    seed = np.random.SeedSequence(3)
    serial = list(scan(pose_fn, T0, T0 + 2.0, flat_scene, cfg, np.zeros(3), np.eye(3), seed, chunk_duration_s=0.3))
    with TaskRunner("threads", workers=2) as runner:
        tasks = list(scan(pose_fn, T0, T0 + 2.0, flat_scene, cfg, np.zeros(3), np.eye(3), seed,
                          chunk_duration_s=0.3, runner=runner))
    assert len(serial) == len(tasks) == 7
    a, b = concat(serial), concat(tasks)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert [c.pulses for c in serial] == [c.pulses for c in tasks] and sum(c.pulses for c in serial) >= len(a["time"]) > 0
    # the noise is seeded per chunk: chunks differ from each other, and a generator seeds them too
    assert not np.array_equal(serial[0].range_error_m[:100], serial[1].range_error_m[:100])
    again = concat(scan(pose_fn, T0, T0 + 2.0, flat_scene, cfg, np.zeros(3), np.eye(3),
                        np.random.default_rng(9), chunk_duration_s=0.3))
    np.testing.assert_array_equal(again["xyz_w_true"], a["xyz_w_true"])
    assert not np.array_equal(again["range_error_m"], a["range_error_m"])


def test_max_range_and_arguments(flat_scene):
    cfg = ScannerConfig(max_range_m=120.0)
    chunks = list(scan(level_flight(300.0, H_AGL), T0, T0 + 0.3, flat_scene, cfg, np.zeros(3),
                       np.eye(3), np.random.default_rng(0), chunk_duration_s=0.1))
    assert len(chunks) == 3 and sum(len(c) for c in chunks) == 0
    with pytest.raises(ValueError):
        scan(level_flight(300.0, H_AGL), T0, T0 + 1, flat_scene, cfg, np.zeros(3), 2 * np.eye(3),
             np.random.default_rng(0))
    with pytest.raises(pydantic.ValidationError):
        ScannerConfig(pulse_rate=1.0)


def test_channel_angle_errors_are_taken_out_by_the_calibration(scene):
    """A facet tilted and a scan angle offset per channel: the beam leaves at the true angles, the point is
    recorded along the calibrated ones; turning each point by its channel's errors
    (:func:`calibrated_channels`) puts it, with the true pose, on the true point plus its range noise."""
    from georefine.lidar.georeference import ScannerCalibration, calibrated_channels

    p_b_s, R_b_s = np.array([0.35, -0.12, 0.48]), np.eye(3)
    pose_fn = level_flight(400.0, np.mean(scene.axis_w[:, 2]) + H_AGL)
    tilt, alpha = (40.0, -25.0, 10.0), (-15.0, 30.0, 5.0)  # mdeg
    cfg = ScannerConfig(channel_tilt_error_mdeg=tilt, channel_scan_angle_error_mdeg=alpha)
    ideal = concat(scan(pose_fn, T0, T0 + 0.5, scene, ScannerConfig(), p_b_s, R_b_s, np.random.default_rng(3)))
    unit = concat(scan(pose_fn, T0, T0 + 0.5, scene, cfg, p_b_s, R_b_s, np.random.default_rng(3)))
    assert abs(unit["time"].size - ideal["time"].size) < 0.01 * ideal["time"].size
    # recorded along the calibrated beam: the channel's nominal tilt and the recorded scan angle
    d_s = unit["xyz_s"] / np.linalg.norm(unit["xyz_s"], axis=1, keepdims=True)
    np.testing.assert_allclose(d_s[:, 0], np.sin(np.radians(np.array(cfg.facet_tilt_deg))[unit["channel"]]),
                               atol=1e-12)
    np.testing.assert_allclose(np.arctan2(d_s[:, 1], d_s[:, 2]), unit["scan_angle_rad"], atol=1e-12)
    p_w_b, R_w_b = pose_fn(unit["time"])
    p_w_s = p_w_b + R_w_b @ p_b_s
    d_w = unit["xyz_w_true"] - p_w_s
    d_w /= np.linalg.norm(d_w, axis=1, keepdims=True)
    expected = unit["xyz_w_true"] + unit["range_error_m"][:, None] * d_w

    def to_w(x_s):
        return p_w_b + np.einsum("nij,nj->ni", R_w_b, x_s @ R_b_s.T + p_b_s)

    angles = np.radians(np.column_stack([tilt, alpha]) * 1e-3)
    fixed = calibrated_channels(unit["xyz_s"], unit["channel"], angles)
    np.testing.assert_allclose(to_w(fixed), expected, atol=1e-6)
    np.testing.assert_allclose(ScannerCalibration(channel_angles=angles).apply(unit["xyz_s"], unit["channel"]),
                               fixed, atol=1e-12)
    miss = np.linalg.norm(to_w(unit["xyz_s"]) - expected, axis=1)
    r = np.linalg.norm(unit["xyz_s"], axis=1)
    for c in range(3):  # as recorded, each channel's points are off by its angle errors times the range
        on = unit["channel"] == c
        assert on.sum() > 1000
        np.testing.assert_allclose(miss[on] / r[on], np.hypot(angles[c, 0], np.cos(np.radians(
            cfg.facet_tilt_deg[c])) * angles[c, 1]), rtol=0.02)
    # a channel the adjustment had no feature of (no row of angles) is left as read
    two = calibrated_channels(unit["xyz_s"], unit["channel"], angles[:2])
    last = unit["channel"] == 2
    np.testing.assert_allclose(two[last], unit["xyz_s"][last], rtol=0, atol=1e-9)
    np.testing.assert_allclose(two[~last], fixed[~last], atol=1e-12)
    with pytest.raises(ValueError, match="negative"):
        calibrated_channels(unit["xyz_s"], unit["channel"].astype(np.int64) - 1, angles)


# ------------------------------------------------------------------------------ encoder and range biases
P_B_S = np.array([0.35, -0.12, 0.48])
R_B_S = Rotation.from_rotvec([0.004, -0.006, 0.01]).as_matrix()
SLOPE = 0.2  # m/m along y: the tilted plane's normal is (0, -SLOPE, 1)


@pytest.fixture(scope="module")
def tilted_scene():
    """A plane rising SLOPE along +y (11.3 deg), nothing on it (roads flattened across cross roads aside)."""
    cfg = SceneConfig(length_m=600.0, width_m=500.0, end_margin_m=100.0, side_rise_m=0.0, undulation_m=0.0,
                      floor_slope_m_per_m=SLOPE, settlement_count=0, scattered_building_count=0, power_line=False,
                      vegetation_per_ha=0.0)
    return build_scene(cfg, np.random.default_rng(5))


def scan_points(scene, cfg, pose_fn, seed=3, duration=0.4):
    """One chunk of ``duration`` s scanned with the lever arm and boresight above (seeded)."""
    chunks = list(scan(pose_fn, T0, T0 + duration, scene, cfg, P_B_S, R_B_S, np.random.SeedSequence(seed),
                       chunk_duration_s=1.0))
    assert len(chunks) == 1
    return concat(chunks)


def true_beams(pts, pose_fn):
    """Scanner position in ``w``, unit beam to the true hit in ``w`` and in ``s`` (from the pose alone)."""
    p_w_b, R_w_b = pose_fn(pts["time"])
    p_w_s = p_w_b + R_w_b @ P_B_S
    d_w = pts["xyz_w_true"] - p_w_s
    d_w /= np.linalg.norm(d_w, axis=1, keepdims=True)
    d_s = np.einsum("nji,nj->ni", R_w_b, d_w) @ R_B_S  # R_b_s^T R_w_b^T d_w
    return p_w_s, d_w, d_s


def georeferenced(pts, pose_fn):
    p_w_b, R_w_b = pose_fn(pts["time"])
    return p_w_b + np.einsum("nij,nj->ni", R_w_b, pts["xyz_s"] @ R_B_S.T + P_B_S)


NEW_FIELDS_OFF = dict(encoder_error_mdeg=(0.0, 0.0), encoder_error_phase_deg=(0.0, 0.0), encoder_resolution_mdeg=0.0,
                      range_incidence_bias_m=0.0, range_walk_m=0.0)


def test_encoder_and_range_biases_off_change_nothing_and_draw_nothing(flat_scene):
    """The new fields at 0 give the scan of before: explicitly zero is the default, the range error is the chunk
    generator's first draws (N(0, sigma)) and the intensity its next (nothing drawn in between)."""
    from georefine.sim.scanner import chunk_seed

    pose_fn = level_flight(400.0, H_AGL, wobble=0.02)
    default = scan_points(flat_scene, ScannerConfig(), pose_fn, seed=11)
    zero = scan_points(flat_scene, ScannerConfig(**NEW_FIELDS_OFF), pose_fn, seed=11)
    for name in default:
        np.testing.assert_array_equal(zero[name], default[name], err_msg=name)
    cfg, n = ScannerConfig(), default["time"].size
    g = np.random.default_rng(chunk_seed(np.random.SeedSequence(11), 0))
    np.testing.assert_array_equal(default["range_error_m"], g.normal(0.0, cfg.range_sigma_m, n))
    p_w_s, d_w, d_s = true_beams(default, pose_fn)
    cos_inc = np.abs(np.einsum("ij,ij->i", flat_scene.surface_normal(default["face_id"]), d_w))
    r = np.linalg.norm(default["xyz_w_true"] - p_w_s, axis=1)
    amplitude = (cfg.intensity_at_reference * flat_scene.albedo(default["xyz_w_true"], default["face_id"]) * cos_inc
                 * (cfg.intensity_reference_range_m / r) ** 2)
    expected = np.clip(np.rint(amplitude * (1.0 + cfg.intensity_noise_rel * g.standard_normal(n))), 1, 65535)
    assert np.max(np.abs(default["intensity"] - expected)) <= 1  # rounding of a recomputed amplitude
    # the beam left along the recorded angle: the true hit's direction in s is d_s(alpha, tau_c)
    np.testing.assert_allclose(np.arctan2(d_s[:, 1], d_s[:, 2]), default["scan_angle_rad"], atol=1e-9)


def test_encoder_error_sends_the_beam_off_the_recorded_angle(flat_scene):
    """The beam leaves at ``alpha + sum_k a_k sin(k alpha + phi_k)``, the point is recorded along ``alpha``; with a
    resolution the recorded angle is a multiple of it and the beam is where it was without one."""
    from georefine.sim.scanner import encoder_error_rad

    pose_fn = level_flight(400.0, H_AGL, wobble=0.02)
    cfg = ScannerConfig(encoder_error_mdeg=(20.0, 8.0), encoder_error_phase_deg=(30.0, -75.0))
    pts = scan_points(flat_scene, cfg, pose_fn)
    alpha = pts["scan_angle_rad"]
    e = np.radians(1e-3 * (20.0 * np.sin(alpha + np.radians(30.0)) + 8.0 * np.sin(2 * alpha - np.radians(75.0))))
    assert np.ptp(e) > np.radians(25e-3)  # the window below is 1e-9 rad
    np.testing.assert_allclose(encoder_error_rad(alpha, cfg), e, rtol=0, atol=1e-15)
    _, d_w, d_s = true_beams(pts, pose_fn)
    np.testing.assert_allclose(np.arctan2(d_s[:, 1], d_s[:, 2]) - alpha, e, rtol=0, atol=1e-9)
    tau = np.radians(np.array(cfg.facet_tilt_deg))[pts["channel"]]
    np.testing.assert_allclose(d_s[:, 0], np.sin(tau), atol=1e-9)  # the tilt is the channel's
    rec = pts["xyz_s"] / np.linalg.norm(pts["xyz_s"], axis=1, keepdims=True)  # recorded along the nominal beam
    np.testing.assert_allclose(np.arctan2(rec[:, 1], rec[:, 2]), alpha, atol=1e-12)
    np.testing.assert_allclose(rec[:, 0], np.sin(tau), atol=1e-12)
    # as recorded, the point misses the true one by the encoder error times the range, across the beam
    miss = np.linalg.norm(georeferenced(pts, pose_fn) - pts["xyz_w_true"] - pts["range_error_m"][:, None] * d_w, axis=1)
    r = np.linalg.norm(pts["xyz_s"], axis=1)
    np.testing.assert_allclose(miss / r, np.cos(tau) * np.abs(e), rtol=1e-3, atol=1e-9)

    q_mdeg = 5.0
    coarse = scan_points(flat_scene, cfg.model_copy(update={"encoder_resolution_mdeg": q_mdeg}), pose_fn)
    np.testing.assert_array_equal(coarse["xyz_w_true"], pts["xyz_w_true"])  # the beam does not depend on the record
    q = np.radians(q_mdeg * 1e-3)
    steps = coarse["scan_angle_rad"] / q
    np.testing.assert_allclose(steps, np.rint(steps), rtol=0, atol=1e-6)
    resid = pts["scan_angle_rad"] - coarse["scan_angle_rad"]  # true polygon angle minus the recorded one
    assert np.max(np.abs(resid)) <= q / 2 * (1 + 1e-9) and abs(np.std(resid) / (q / np.sqrt(12)) - 1) < 0.05
    _, _, d_s = true_beams(coarse, pose_fn)
    np.testing.assert_allclose(np.arctan2(d_s[:, 1], d_s[:, 2]) - coarse["scan_angle_rad"],
                               encoder_error_rad(pts["scan_angle_rad"], cfg) + resid, rtol=0, atol=1e-9)
    rec = coarse["xyz_s"] / np.linalg.norm(coarse["xyz_s"], axis=1, keepdims=True)
    np.testing.assert_allclose(np.arctan2(rec[:, 1], rec[:, 2]), coarse["scan_angle_rad"], atol=1e-12)


def test_encoder_error_is_taken_out_by_its_legendre_terms(flat_scene):
    """The simulated encoder error written as the estimator writes it (:func:`encoder_legendre_terms`): its mean
    taken out as a scan-angle offset of every channel (the boresight's roll) and its four Legendre terms by
    :class:`ScannerCalibration` put every point on its true one, to the range noise and the part of the error
    the four terms do not hold (0.1 mdeg of harmonics of 20 and 10 mdeg over +-50 degrees)."""
    from georefine.lidar.georeference import ScannerCalibration
    from georefine.sim.scanner import encoder_legendre_terms

    pose_fn = level_flight(400.0, H_AGL, wobble=0.02)
    cfg = ScannerConfig(encoder_error_mdeg=(20.0, 10.0), encoder_error_phase_deg=(30.0, 60.0))
    pts = scan_points(flat_scene, cfg, pose_fn)
    mean, terms, residual = encoder_legendre_terms(cfg)
    np.testing.assert_allclose(np.degrees([mean, *terms]) * 1e3, [13.66, 20.34, -9.44, -2.23, 0.72], atol=0.01)
    assert np.degrees(residual) * 1e3 < 0.15
    _, d_w, _ = true_beams(pts, pose_fn)
    expected = pts["xyz_w_true"] + pts["range_error_m"][:, None] * d_w
    r = np.linalg.norm(pts["xyz_s"], axis=1)
    offset = np.column_stack([np.zeros(3), np.full(3, mean)])
    fixed = ScannerCalibration(channel_angles=offset, encoder=terms).apply(pts["xyz_s"], pts["channel"])
    before = np.linalg.norm(georeferenced(pts, pose_fn) - expected, axis=1) / r
    after = np.linalg.norm(georeferenced({**pts, "xyz_s": fixed}, pose_fn) - expected, axis=1) / r
    assert np.percentile(before, 50) > np.radians(5e-3)  # mdeg-level misses as recorded
    assert np.max(after) < residual * (1 + 1e-6) + 1e-9, np.degrees(np.max(after)) * 1e3


def test_incidence_range_bias_on_a_tilted_plane(tilted_scene):
    """``b = B (1/cos(theta) - 1)`` with the incidence from the plane's normal and the true beam: in
    ``range_error_m``, and the true point minus the one georeferenced from the record lies along the beam by -b."""
    bias = 0.05
    cfg = ScannerConfig(range_sigma_m=0.0, range_incidence_bias_m=bias)
    pose_fn = level_flight(400.0, SLOPE * 400.0 + H_AGL, wobble=0.02)
    pts = scan_points(tilted_scene, cfg, pose_fn)
    normal = np.array([0.0, -SLOPE, 1.0]) / np.hypot(1.0, SLOPE)
    on = np.linalg.norm(tilted_scene.surface_normal(pts["face_id"]) - normal, axis=1) < 1e-9
    assert on.mean() > 0.9
    _, d_w, _ = true_beams(pts, pose_fn)
    cos_theta = np.abs(d_w @ normal)
    expected = bias * (1.0 / cos_theta - 1.0)
    assert expected[on].min() < 0.002 and expected[on].max() > 0.02  # near-normal to ~45 deg incidence
    np.testing.assert_allclose(pts["range_error_m"][on], expected[on], rtol=0, atol=1e-9)
    diff = pts["xyz_w_true"] - georeferenced(pts, pose_fn)
    along = np.einsum("ij,ij->i", diff, d_w)
    np.testing.assert_allclose(along[on], -expected[on], rtol=0, atol=1e-6)
    np.testing.assert_allclose(diff - along[:, None] * d_w, 0.0, atol=1e-6)
    # on top of the noise and the offset, from the same draws
    noisy = scan_points(tilted_scene, ScannerConfig(range_incidence_bias_m=bias, range_offset_m=0.01), pose_fn)
    plain = scan_points(tilted_scene, ScannerConfig(), pose_fn)
    np.testing.assert_allclose(noisy["range_error_m"][on] - plain["range_error_m"][on], expected[on] + 0.01, atol=1e-9)


class _Painted:
    """``scene`` with one albedo everywhere (what the scanner asks of a scene)."""

    def __init__(self, scene, rho):
        self.scene, self.rho = scene, rho

    def intersect(self, *args, **kwargs):
        return self.scene.intersect(*args, **kwargs)

    def surface_normal(self, face_id):
        return self.scene.surface_normal(face_id)

    def albedo(self, points_w, face_ids):
        return np.full(len(face_ids), self.rho)


def test_range_walk_dark_targets_read_long_by_walk_times_log_ratio(flat_scene):
    """``b = W ln(I_ref / I_0)``: the same pulses on a target of albedo 0.1 and one of 0.8 differ by ``W ln 8`` in
    range error (and read 8 times weaker), and on the scene's texture each point has the bias of its noise-free
    amplitude."""
    walk = 0.02
    pose_fn = level_flight(400.0, H_AGL, wobble=0.02)
    cfg = ScannerConfig(range_walk_m=walk)
    dark = scan_points(_Painted(flat_scene, 0.1), cfg, pose_fn)
    bright = scan_points(_Painted(flat_scene, 0.8), cfg, pose_fn)
    np.testing.assert_array_equal(dark["xyz_w_true"], bright["xyz_w_true"])
    np.testing.assert_allclose(dark["range_error_m"] - bright["range_error_m"], walk * np.log(8.0), rtol=0, atol=1e-12)
    assert abs(np.median(bright["intensity"] / dark["intensity"].astype(float)) - 8.0) < 0.2
    # against the formula with the geometry and the scene's own albedo
    pts = scan_points(flat_scene, cfg, pose_fn)
    ideal = scan_points(flat_scene, ScannerConfig(), pose_fn)
    p_w_s, d_w, _ = true_beams(pts, pose_fn)
    r = np.linalg.norm(pts["xyz_w_true"] - p_w_s, axis=1)
    cos_inc = np.abs(np.einsum("ij,ij->i", flat_scene.surface_normal(pts["face_id"]), d_w))
    amplitude = (cfg.intensity_at_reference * flat_scene.albedo(pts["xyz_w_true"], pts["face_id"]) * cos_inc
                 * (cfg.intensity_reference_range_m / r) ** 2)
    expected = walk * np.log(cfg.intensity_at_reference / amplitude)
    assert np.ptp(expected) > 0.02 and np.all(expected > 0)
    np.testing.assert_allclose(pts["range_error_m"] - ideal["range_error_m"], expected, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(pts["intensity"], ideal["intensity"])  # the intensity's own noise is unchanged


def test_new_scanner_errors_flow_from_the_scenario_into_its_truth(tmp_path):
    """A scenario's YAML and ``--set`` reach the scanner; the truth (``truth/scenario.yaml``'s ``scenario``, the
    scenario's dump) holds them and reads back to the same scanner."""
    import yaml

    from georefine.sim.scenarios import ScenarioConfig, resolve_scenario

    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump({"scanner": {"encoder_error_mdeg": [20.0, 8.0], "encoder_error_phase_deg": [30, -75],
                                                "range_incidence_bias_m": 0.01}}))
    cfg = resolve_scenario("corridor-tiny", config_file=path,
                           seed_overrides=["scanner.encoder_resolution_mdeg=1", "scanner.range_walk_m=0.004"])
    sc = cfg.scanner
    assert (sc.encoder_error_mdeg, sc.encoder_error_phase_deg) == ((20.0, 8.0), (30.0, -75.0))
    assert (sc.encoder_resolution_mdeg, sc.range_incidence_bias_m, sc.range_walk_m) == (1.0, 0.01, 0.004)
    dumped = yaml.safe_load(yaml.safe_dump(cfg.model_dump(mode="json")))
    assert dumped["scanner"]["encoder_error_mdeg"] == [20.0, 8.0] and dumped["scanner"]["range_walk_m"] == 0.004
    assert ScenarioConfig.model_validate(dumped).scanner == sc
    with pytest.raises(pydantic.ValidationError):
        ScannerConfig(encoder_resolution_mdeg=-1.0)
