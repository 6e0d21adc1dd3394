"""project.yaml model: unknown keys, bad values and overrides give clear errors."""

import numpy as np
import pytest
import yaml

from georefine.config import (
    ProjectConfig,
    apply_overrides,
    boresight_matrix,
    load_project,
    validate_model,
    write_yaml,
)
from georefine.errors import ConfigError

SPEC = {
    "gyro_arw_deg_per_sqrt_h": 0.07,
    "gyro_bias_instability_deg_per_h": 0.5,
    "gyro_turn_on_bias_deg_per_h": 1.0,
    "gyro_scale_factor_ppm": 100.0,
    "acc_vrw_m_per_s_per_sqrt_h": 0.05,
    "acc_bias_instability_ug": 50.0,
    "acc_turn_on_bias_ug": 300.0,
    "acc_scale_factor_ppm": 300.0,
}


def minimal_project() -> dict:
    return {
        "name": "t",
        "gnss": {"files": ["gnss/rover.pos"], "lever_arm_m": [0.1, 0.2, -1.0]},
        "imu": {"file": "imu/imu.csv", "errors": dict(SPEC)},  # a copy: tests change it
        "scanner": {"files": ["scans/strip_1.laz"], "lever_arm_m": [0.3, 0.0, 0.2]},
    }


def test_round_trip(tmp_path):
    cfg = validate_model(ProjectConfig, minimal_project())
    write_yaml(tmp_path / "project.yaml", cfg)
    again = load_project(tmp_path)
    assert again == cfg
    assert [c.name for c in again.scanner.channels] == ["nadir", "forward", "backward"]


def test_unknown_key_names_file_line_and_key(tmp_path):
    data = minimal_project()
    data["imu"]["errors"]["gyro_arw_deg_per_h"] = 1.0
    (tmp_path / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as err:
        load_project(tmp_path)
    text = str(err.value)
    assert "project.yaml" in text and "unknown key" in text
    assert "imu.errors.gyro_arw_deg_per_h" in text
    assert "gyro_arw_deg_per_sqrt_h" in text  # the expected keys are listed
    line = next(i for i, l in enumerate((tmp_path / "project.yaml").read_text().splitlines(), 1) if "gyro_arw_deg_per_h" in l)
    assert f"line {line}" in text


def test_bad_value_names_field(tmp_path):
    data = minimal_project()
    data["imu"]["errors"]["gyro_scale_factor_ppm"] = -5
    (tmp_path / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError, match=r"imu\.errors\.gyro_scale_factor_ppm.*greater than or equal to 0"):
        load_project(tmp_path)


@pytest.mark.parametrize("code, why", [(99999, "not a coordinate reference system PROJ knows"),
                                       (5773, "not a projected or geographic CRS")])
def test_unknown_output_epsg_is_refused_when_the_configuration_is_read(tmp_path, code, why):
    data = minimal_project()
    data["crs"] = {"output_epsg": code}
    (tmp_path / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError, match=rf"project.yaml, line \d+, field 'crs.output_epsg': .*EPSG:{code}.*{why}"):
        load_project(tmp_path)
    from georefine.sim.scenarios import resolve_scenario

    with pytest.raises(ConfigError, match=rf"field 'output_epsg': .*EPSG:{code}"):
        resolve_scenario("corridor-tiny", seed_overrides=[f"output_epsg={code}"])


def test_missing_project_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="no project.yaml"):
        load_project(tmp_path)
    (tmp_path / "project.yaml").write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_project(tmp_path)


def test_overrides_parse_yaml_values_and_do_not_mutate():
    data = {"flight": {"speed_mps": 18.0}, "seed": 1}
    out = apply_overrides(data, ["flight.speed_mps=20", "flight.passes=1", "gnss.outages_s=[[10, 40]]"])
    assert out["flight"] == {"speed_mps": 20, "passes": 1}
    assert out["gnss"]["outages_s"] == [[10, 40]]
    assert data == {"flight": {"speed_mps": 18.0}, "seed": 1}
    with pytest.raises(ConfigError, match=r"field 'overrides': override must look like key.sub=value"):
        apply_overrides(data, ["flight.speed_mps"])
    with pytest.raises(ConfigError, match=r"field 'overrides': override has an empty key"):
        apply_overrides(data, ["=1"])
    with pytest.raises(ConfigError, match="sub-key of a scalar"):
        apply_overrides(data, ["seed.x=1"])


def test_boresight_matrix_small_angles():
    R = boresight_matrix((0.0, 0.0, 90.0))
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(boresight_matrix((0, 0, 0)), np.eye(3))


def test_unknown_imu_grade_names_the_parameter():
    from georefine.sim.scenarios import resolve_scenario

    with pytest.raises(ConfigError, match=r"field 'imu_grade': unknown IMU grade .*expected one of .*mems"):
        resolve_scenario("corridor-tiny", imu_grade="consumer")


def test_scenario_override_changes_only_the_field_it_names(tmp_path):
    """``--set imu.rate_hz=400`` keeps the default preset's errors; every layer works on top of the last."""
    from georefine.sim.imu import DEFAULT_IMU_GRADE, IMU_PRESETS
    from georefine.sim.scenarios import resolve_scenario

    default = IMU_PRESETS[DEFAULT_IMU_GRADE].model_dump()
    imu = resolve_scenario("corridor-tiny", seed_overrides=["imu.rate_hz=400"]).imu.model_dump()
    assert imu["rate_hz"] == 400.0
    assert {k: v for k, v in imu.items() if k != "rate_hz"} == {k: v for k, v in default.items() if k != "rate_hz"}
    assert imu["gyro_arw_deg_per_sqrt_h"] > 0  # not an ideal IMU

    tactical = IMU_PRESETS["tactical"].model_dump()
    for kwargs in ({"imu_grade": "tactical", "seed_overrides": ["imu.rate_hz=400"]},
                   {"seed_overrides": ["imu=tactical", "imu.rate_hz=400"]}):
        imu = resolve_scenario("corridor-tiny", **kwargs).imu.model_dump()
        assert imu == {**tactical, "rate_hz": 400.0}, kwargs

    cfg = tmp_path / "s.yaml"
    cfg.write_text("imu:\n  rate_hz: 250\n")  # a file layer changes the preset's field only
    assert resolve_scenario("corridor-tiny", config_file=cfg).imu.model_dump() == {**default, "rate_hz": 250.0}
    cfg.write_text("imu: tactical\n")
    imu = resolve_scenario("corridor-tiny", config_file=cfg, seed_overrides=["imu.gyro_arw_deg_per_sqrt_h=0.5"])
    assert imu.imu.model_dump() == {**tactical, "gyro_arw_deg_per_sqrt_h": 0.5}
    # the other sections keep their scenario defaults under a neighbour's override
    sc = resolve_scenario("corridor-tiny", seed_overrides=["scanner.line_rate_hz=100"])
    assert (sc.scanner.pulse_rate_hz, sc.scanner.line_rate_hz) == (100000.0, 100.0)
    with pytest.raises(ConfigError, match=r"field 'imu': unknown IMU grade .*from --set imu=consumer"):
        resolve_scenario("corridor-tiny", seed_overrides=["imu=consumer"])


def test_the_resolved_scenario_names_where_each_section_came_from(tmp_path):
    from georefine.sim.scenarios import resolve_scenario

    assert resolve_scenario("corridor").sources == {
        "scene": "defaults", "flight": "defaults", "gnss": "defaults", "scanner": "scenario corridor",
        "imu": "preset mems (the default)"}
    cfg = tmp_path / "s.yaml"
    cfg.write_text("imu: tactical\nflight: {passes: 1}\n")
    src = resolve_scenario("corridor-tiny", config_file=cfg, gnss_grade="ideal",
                           seed_overrides=["imu.rate_hz=400", "scanner.line_rate_hz=100"]).sources
    assert src["imu"] == f"preset tactical ({cfg}), --set imu.rate_hz=400"
    assert src["flight"] == f"scenario corridor-tiny, {cfg}"
    assert src["gnss"] == "defaults, --gnss-grade ideal"
    assert src["scanner"] == "scenario corridor-tiny, --set scanner.line_rate_hz=100"
    assert resolve_scenario("corridor", imu_grade="navigation").sources["imu"] == "preset navigation (--imu-grade)"


# ---------------------------------------------------------------------------- processing.lidargrammetry
def test_lidargrammetry_defaults_are_the_values_the_block_demo_was_tuned_with():
    from georefine.config import LidargrammetryConfig

    st = LidargrammetryConfig()
    assert (st.photo_sigma_position_m, st.photo_sigma_rotation_deg) == (0.1, 0.02)
    assert (st.lidargram_sigma_position_m, st.lidargram_sigma_rotation_deg) == (1.0, (0.01, 0.01, 0.1))
    assert (st.lidargram_scale, st.splat_scale, st.min_coverage, st.point_spacing_m) == (0.5, 2.0, 0.3, None)
    assert st.per_strip and st.fill_holes and st.use_depth and st.feather
    assert (st.matcher, st.sift_ratio, st.verification_threshold_px, st.min_verified_matches) == ("sift", 0.9, 2.0, 15)
    assert (st.deep_max_features, st.max_pair_distance_m, st.lightglue_features) == (6000, 150.0, "disk")
    assert st.pair_kinds == ("photo-photo", "photo-lidargram") and st.max_initial_reprojection_px == 15.0


def test_lidargrammetry_defaults_equal_the_library_defaults_they_stand_for():
    """Fields passed to library functions keep those functions' own defaults (one behaviour either way)."""
    import inspect

    from georefine.config import LidargrammetryConfig
    from georefine.lidargrammetry.bundle import coadjust
    from georefine.lidargrammetry.matching import detect_sift
    from georefine.lidargrammetry.reintersect import reintersect

    st = LidargrammetryConfig()

    def default(fn, name):
        return inspect.signature(fn).parameters[name].default

    for field, fn, name in [("tie_sigma_px", coadjust, "tie_sigma_px"), ("depth_sigma_m", coadjust, "depth_sigma_m"),
                            ("measurement_sigma_px", coadjust, "measurement_sigma_px"),
                            ("tie_loss", coadjust, "tie_loss"), ("tie_loss_scale", coadjust, "tie_loss_scale"),
                            ("sift_max_features", detect_sift, "max_features"),
                            ("sift_contrast_threshold", detect_sift, "contrast_threshold"),
                            ("interpolation_neighbours", reintersect, "k"),
                            ("interpolation_max_distance_m", reintersect, "max_distance_m")]:
        assert getattr(st, field) == default(fn, name), field


def _project_with(tmp_path, section: dict):
    data = minimal_project()
    data["processing"] = {"lidargrammetry": section}
    (tmp_path / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return tmp_path


def test_bad_lidargrammetry_value_in_project_yaml_names_field_and_line(tmp_path):
    _project_with(tmp_path, {"lidargram_scale": 0.25, "lidargram_sigma_rotation_deg": [0.01, 0.1]})
    with pytest.raises(ConfigError) as err:
        load_project(tmp_path)
    text = str(err.value)
    line = next(i for i, l in enumerate((tmp_path / "project.yaml").read_text().splitlines(), 1)
                if "lidargram_sigma_rotation_deg" in l)
    assert "processing.lidargrammetry.lidargram_sigma_rotation_deg" in text and f"line {line}" in text
    assert "one or three sigmas" in text
    _project_with(tmp_path, {"lidargram_sigma_position_m": 0})
    with pytest.raises(ConfigError, match=r"lidargram_sigma_position_m.*greater than 0"):
        load_project(tmp_path)
    _project_with(tmp_path, {"matcher": "lightglue", "lightglue_weights": "lg.pth"})  # one file without the other
    with pytest.raises(ConfigError, match=r"field 'processing.lidargrammetry'.*weight files"):
        load_project(tmp_path)


def test_one_rotation_sigma_stands_for_three():
    from georefine.config import LidargrammetryConfig

    assert LidargrammetryConfig(lidargram_sigma_rotation_deg=0.05).lidargram_sigma_rotation_deg == (0.05,) * 3
    assert LidargrammetryConfig(lidargram_sigma_rotation_deg=[0.05]).lidargram_sigma_rotation_deg == (0.05,) * 3
    with pytest.raises(ValueError, match="positive"):
        LidargrammetryConfig(lidargram_sigma_rotation_deg=[0.01, 0.01, -0.1])


def test_overrides_beat_project_yaml_which_beats_the_defaults(tmp_path):
    from georefine.workflows.lidargrammetry import lidargrammetry_settings

    cfg = load_project(_project_with(tmp_path, {"lidargram_scale": 0.25, "sift_ratio": 0.8}))
    st = lidargrammetry_settings(cfg, {"lidargram_scale": 0.3, "lidargram_sigma_rotation_deg": ["0.02"]})
    assert (st.lidargram_scale, st.sift_ratio, st.lidargram_sigma_rotation_deg) == (0.3, 0.8, (0.02,) * 3)
    assert st.verification_threshold_px == 2.0  # neither given: the default
    assert lidargrammetry_settings(cfg).lidargram_scale == 0.25 and cfg.processing.lidargrammetry.lidargram_scale == 0.25
    with pytest.raises(ConfigError, match=r"field 'processing.lidargrammetry.pair_kinds.0'.*photo-sky"):
        lidargrammetry_settings(cfg, {"pair_kinds": ["photo-sky"]})
    with pytest.raises(ConfigError, match=r"field 'processing.lidargrammetry.scale': unknown key"):
        lidargrammetry_settings(cfg, {"scale": 0.3})


def test_a_project_without_flights_is_one_flight_of_its_top_level_files(tmp_path):
    """project.yaml without flights (every project before them) is one flight: gnss.files, imu.file and
    scanner.files (docs/ARCHITECTURE.md §3); flights: null says the same."""
    cfg = validate_model(ProjectConfig, minimal_project())
    assert cfg.flights is None and not cfg.multi_flight and cfg.flight_ids == (1,)
    assert cfg.flight_config(1) is cfg
    assert validate_model(ProjectConfig, {**minimal_project(), "flights": None}) == cfg
    write_yaml(tmp_path / "project.yaml", cfg)
    assert load_project(tmp_path) == cfg


def test_a_stated_multipath_needs_the_correlated_error_it_adds_to(tmp_path):
    """gnss.multipath is off by default; stated, it validates, and without gnss.correlated_error it is refused with
    the file and the field."""
    assert validate_model(ProjectConfig, minimal_project()).gnss.multipath is None
    data = minimal_project()
    data["gnss"]["multipath"] = {"sigma_horizontal_m": 0.02}
    cfg = validate_model(ProjectConfig, data)
    assert (cfg.gnss.multipath.sigma_horizontal_m, cfg.gnss.multipath.sigma_up_m, cfg.gnss.multipath.time_constant_s) \
        == (0.02, 0.04, 20.0)
    data["gnss"]["correlated_error"] = None
    (tmp_path / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError, match=r"project\.yaml.*gnss.*multipath is estimated beside correlated_error"):
        load_project(tmp_path)
