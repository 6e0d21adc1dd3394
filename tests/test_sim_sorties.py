"""Several sorties in one simulated project: each its own take-off, IMU record, GNSS session and strips."""

from __future__ import annotations

import filecmp

import numpy as np
import pytest
import yaml

import georefine
from georefine.config import load_project
from georefine.io.trajectory import read_sbet

SMALL = ["scanner.pulse_rate_hz=20000", "scanner.line_rate_hz=60", "scene.length_m=300"]


@pytest.fixture(scope="module")
def projects(tmp_path_factory):
    base = tmp_path_factory.mktemp("sorties")
    georefine.simulate("two-flights-tiny", base / "two", seed=5, overrides=SMALL)
    georefine.simulate("corridor-tiny", base / "one", seed=5, overrides=SMALL)
    return base / "two", base / "one"


def test_two_sorties_are_two_flights_of_one_project(projects):
    two, _ = projects
    cfg = load_project(two)
    assert [f.id for f in cfg.flights] == [1, 2]
    assert [f.strips for f in cfg.flights] == [["scans/strip_1.laz", "scans/strip_2.laz"],
                                               ["scans/strip_3.laz", "scans/strip_4.laz"]]
    summary = georefine.check(two)
    spans = [f.span_gps for f in summary.flights]
    assert spans[1][0] - spans[0][0] == pytest.approx(91800.0)  # the next day, 1.5 h later
    truth = yaml.safe_load((two / "truth" / "scenario.yaml").read_text())
    assert [p["strip_id"] for p in truth["passes"]] == [1, 2, 3, 4]
    flights = truth["flights"]
    # Each take-off has its own turn-on biases; the scanner's boresight is the same.
    assert not np.allclose(flights[0]["imu_bias_gyro_start_deg_per_h"], flights[1]["imu_bias_gyro_start_deg_per_h"])
    assert truth["scenario"]["boresight_deg"] == list(cfg.scanner.boresight_deg)
    # One truth for both: the passes' times of flight 2 lie in it, a day after flight 1's.
    sbet = read_sbet(two / "truth" / "trajectory.sbet", gps_week=int(truth["t0_gps"] // 604800))
    t = sbet.time_gps - truth["t0_gps"]
    for p in truth["passes"]:
        assert np.any((t >= p["t_start_s"]) & (t <= p["t_end_s"]))
    assert np.all(np.diff(sbet.time_gps) > 0)


def test_the_first_sortie_is_the_scenario_flown_once(projects):
    two, one = projects
    # The first sortie draws from the single-flight streams: the same IMU, GNSS and strips.
    for a, b in (("imu/flight_1.csv", "imu/imu.csv"), ("gnss/flight_1.pos", "gnss/rover.pos"),
                 ("scans/strip_1.laz", "scans/strip_1.laz"), ("scans/strip_2.laz", "scans/strip_2.laz")):
        assert filecmp.cmp(two / a, one / b, shallow=False), a
    assert not filecmp.cmp(two / "imu/flight_2.csv", one / "imu/imu.csv", shallow=False)
