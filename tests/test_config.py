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
        "imu": {"file": "imu/imu.csv", "errors": SPEC},
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
