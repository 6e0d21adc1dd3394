"""Several flights in one project: the ``flights`` list of ``project.yaml``, ``Project.flights`` and
``navigation_of``, and ``georefine check`` on a project of two simulated flights."""

from __future__ import annotations

import copy
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from cli_helpers import run_georefine_here
from georefine.config import ProjectConfig, load_project, validate_model, write_yaml
from georefine.errors import ConfigError, InputError
from georefine.sim.scenarios import simulate_project
from georefine.workflows.check import inspect_project
from georefine.workflows.opened import open_project
from test_config import SPEC, minimal_project

START_GPS_S = 1399708800.0
"""The simulator's default dataset epoch (``flight.start_time_gps_s``): flight 1 starts there."""
SECOND_START_GPS_S = START_GPS_S + 600.0
"""Flight 2 takes off 10 min later (a corridor-tiny flight of 300 m lasts under 5 min)."""
SMALL = ["scene.length_m=300", "scanner.pulse_rate_hz=2000", "scanner.line_rate_hz=100"]
"""As small a corridor-tiny as the simulator makes: check reads the points but extracts no features."""


def flights_project() -> dict:
    """A project of two flights, the second with its own boresight, scanner lever arm and IMU format."""
    return {
        "name": "two flights",
        "gnss": {"lever_arm_m": [0.1, 0.2, -1.0]},
        "imu": {"errors": dict(SPEC), "rate_hz": 200.0},
        "scanner": {"lever_arm_m": [0.3, 0.0, 0.2], "boresight_deg": [0.01, 0.02, 0.03], "time_offset_s": 0.5},
        "flights": [
            {"id": 1, "gnss_files": ["f1/gnss/rover.pos"], "imu_file": "f1/imu/imu.csv",
             "strips": ["f1/scans/strip_1.laz", "f1/scans/strip_2.laz"]},
            {"id": 2, "name": "afternoon", "gnss_files": ["f2/gnss/a.pos", "f2/gnss/b.pos"],
             "imu_file": "f2/imu/imu.imr", "imu_format": "imr", "imu_rate_hz": 400.0, "imu_gps_week": 2314,
             "strips": ["f2/scans/strip_1.laz"], "boresight_deg": [0.1, -0.2, 0.3],
             "scanner_lever_arm_m": [0.31, 0.01, 0.19], "gnss_lever_arm_m": [0.0, 0.0, -1.1],
             "scanner_time_offset_s": 18.0},
        ],
    }


def _write(folder: Path, data: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return folder


def _refused(tmp_path: Path, data: dict) -> str:
    with pytest.raises(ConfigError) as err:
        load_project(_write(tmp_path, data))
    return str(err.value)


def _line_of(tmp_path: Path, text: str, after: str | None = None) -> int:
    lines = (tmp_path / "project.yaml").read_text().splitlines()
    start = 0 if after is None else next(i for i, line in enumerate(lines) if after in line)
    return next(i for i, line in enumerate(lines) if i >= start and text in line) + 1


# --- project.yaml ------------------------------------------------------------------------------


def test_a_project_of_two_flights_validates_and_round_trips(tmp_path):
    cfg = load_project(_write(tmp_path, flights_project()))
    assert cfg.multi_flight and cfg.flight_ids == (1, 2)
    assert [f.label for f in cfg.flights] == ["flight_1", "afternoon"]
    assert cfg.gnss.files == [] and cfg.imu.file is None and cfg.scanner.files == []
    (tmp_path / "again").mkdir()
    write_yaml(tmp_path / "again" / "project.yaml", cfg)
    assert load_project(tmp_path / "again") == cfg


def test_a_flight_is_a_single_flight_configuration_with_its_own_values_over_the_shared_ones(tmp_path):
    cfg = load_project(_write(tmp_path, flights_project()))
    one, two = cfg.flight_config(1), cfg.flight_config(2)
    for c in (one, two):
        assert not c.multi_flight and c.flights is None
        validate_model(ProjectConfig, c.model_dump())  # a valid project of one flight
    # flight 1 states nothing of its own: the shared values
    assert one.gnss.files == ["f1/gnss/rover.pos"] and one.imu.file == "f1/imu/imu.csv"
    assert one.scanner.files == ["f1/scans/strip_1.laz", "f1/scans/strip_2.laz"]
    assert one.gnss.lever_arm_m == (0.1, 0.2, -1.0) and one.scanner.lever_arm_m == (0.3, 0.0, 0.2)
    assert one.scanner.boresight_deg == (0.01, 0.02, 0.03) and one.scanner.time_offset_s == 0.5
    assert (one.imu.format, one.imu.rate_hz, one.imu.gps_week) == ("csv", 200.0, None)
    # flight 2 overrides them, for itself only
    assert two.gnss.files == ["f2/gnss/a.pos", "f2/gnss/b.pos"] and two.imu.file == "f2/imu/imu.imr"
    assert (two.imu.format, two.imu.rate_hz, two.imu.gps_week) == ("imr", 400.0, 2314)
    assert two.scanner.boresight_deg == (0.1, -0.2, 0.3) and two.scanner.lever_arm_m == (0.31, 0.01, 0.19)
    assert two.gnss.lever_arm_m == (0.0, 0.0, -1.1) and two.scanner.time_offset_s == 18.0
    # what no flight can override is the shared section's
    assert two.imu.errors == cfg.imu.errors and two.scanner.channels == cfg.scanner.channels
    assert two.gnss.correlated_error == cfg.gnss.correlated_error
    assert cfg.scanner.boresight_deg == (0.01, 0.02, 0.03) and cfg.flights[1].strips == ["f2/scans/strip_1.laz"]
    with pytest.raises(ConfigError, match=r"field 'flights': no such flight \(expected one of the ids 1, 2, found 3\)"):
        cfg.flight_config(3)


@pytest.mark.parametrize("section, key, value, own", [
    ("gnss", "files", ["gnss/rover.pos"], "gnss_files"),
    ("imu", "file", "imu/imu.csv", "imu_file"),
    ("scanner", "files", ["scans/strip_1.laz"], "strips"),
])
def test_top_level_files_beside_flights_are_refused_naming_the_field(tmp_path, section, key, value, own):
    data = flights_project()
    data[section][key] = value
    text = _refused(tmp_path, data)
    line = _line_of(tmp_path, f"{key}:", after=f"{section}:")
    assert f"project.yaml, line {line}, field '{section}.{key}'" in text
    assert "given both here and under flights" in text and f"each flight lists its own {own}" in text
    assert f"{section}.{key} is absent or empty" in text and f"found {value!r}" in text


def test_empty_top_level_files_beside_flights_are_accepted(tmp_path):
    data = flights_project()
    data["gnss"]["files"], data["scanner"]["files"], data["imu"]["file"] = [], [], None
    assert load_project(_write(tmp_path, data)).flight_ids == (1, 2)


def test_duplicate_flight_ids_and_names_are_refused(tmp_path):
    data = flights_project()
    data["flights"][1]["id"] = 1
    text = _refused(tmp_path, data)
    line = [i for i, text in enumerate((tmp_path / "project.yaml").read_text().splitlines(), 1) if "- id: 1" in text][1]
    assert re.search(rf"line {line}, field 'flights\.1\.id': flight id 1 is also that of flights\.0: each flight "
                     r"has its own id \(found 1\)", text), text
    data = flights_project()
    data["flights"][0]["name"] = "afternoon"
    assert "field 'flights.1.name': flight name 'afternoon' is also that of flights.0" in _refused(tmp_path, data)


def test_a_strip_in_two_flights_is_refused(tmp_path):
    data = flights_project()
    data["flights"][1]["strips"] = ["f2/scans/strip_1.laz", "./f1/scans/strip_2.laz"]  # the same file
    text = _refused(tmp_path, data)
    assert ("field 'flights.1.strips.1': strip ./f1/scans/strip_2.laz is also listed in flight 1 (flights.0.strips): "
            "each strip belongs to exactly one flight (found './f1/scans/strip_2.laz')") in text
    data = flights_project()
    data["flights"][0]["strips"] = ["f1/scans/strip_1.laz", "f1/scans/strip_1.laz"]
    assert re.search(r"field 'flights\.0\.strips': .*each file once: f1/scans/strip_1\.laz listed more than once",
                     _refused(tmp_path, data))


def test_flights_refuse_what_a_flight_cannot_be(tmp_path):
    data = flights_project()
    data["flights"] = []
    assert "field 'flights': List should have at least 1 item" in _refused(tmp_path, data)
    data = flights_project()
    del data["flights"][0]["imu_file"]
    assert "field 'flights.0.imu_file': Field required" in _refused(tmp_path, data)
    data = flights_project()
    data["flights"][0]["imu_files"] = ["x.csv"]
    text = _refused(tmp_path, data)
    assert "field 'flights.0.imu_files': unknown key" in text and "imu_file, imu_format" in text
    data = flights_project()
    data["gnss"]["format"] = "sbet"
    assert "field 'gnss.format': gnss.format sbet takes the one delivered SBET" in _refused(tmp_path, data)
    data = flights_project()
    del data["gnss"], data["imu"]
    data["trajectory"] = {"sbet": "t.sbet", "gps_week": 2314}
    assert "field 'flights': flights need the sections gnss and imu" in _refused(tmp_path, data)


def test_flights_take_the_scanner_calibration_of_their_one_scanner(tmp_path):
    """The range calibration, channel angles and encoder error are the one scanner's: several flights estimate them
    together (:mod:`georefine.workflows.flights`), so ``project.yaml`` may ask for them."""
    data = flights_project()
    data["processing"] = {"lidar": {"estimate_range_calibration": True, "estimate_channel_angles": True,
                                    "estimate_encoder_error": True}}
    lidar = load_project(_write(tmp_path, data)).processing.lidar
    assert lidar.estimate_range_calibration and lidar.estimate_channel_angles and lidar.estimate_encoder_error


def test_a_project_without_flights_needs_its_top_level_files(tmp_path):
    for section, key, what, found in (("gnss", "files", "no GNSS file", "[]"), ("imu", "file", "no IMU file", None),
                                      ("scanner", "files", "no strip", "[]")):
        data = minimal_project()
        del data[section][key]
        text = _refused(tmp_path, data)
        assert f"field '{section}.{key}': {what}: " in text and "project's flights under flights" in text, text
        assert (f"(found {found})" in text) if found else "found" not in text


# --- Project.flights ---------------------------------------------------------------------------


def test_project_flights_of_a_single_flight_project(tmp_path):
    data = minimal_project()
    data["scanner"]["boresight_deg"] = [0.1, 0.2, 0.3]
    project = open_project(_write(tmp_path, data))
    (f,) = project.flights
    assert (f.id, f.name, f.gnss_files, f.imu_file, f.strip_files) == (
        1, "flight_1", ("gnss/rover.pos",), "imu/imu.csv", ("scans/strip_1.laz",))
    assert (f.gnss_lever_arm_m, f.scanner_lever_arm_m, f.boresight_deg, f.scanner_time_offset_s) == (
        (0.1, 0.2, -1.0), (0.3, 0.0, 0.2), (0.1, 0.2, 0.3), 0.0)
    assert not project.multi_flight and project.config.flight_ids == (1,)
    assert project.config.flight_config(1) is project.config and project.flight_project(1) is project
    with pytest.raises(ConfigError, match=r"no such flight \(expected 1 \(a project without a flights list is one "
                                          r"flight\), found 2\)"):
        project.navigation_of(2)


def test_project_flights_of_a_project_of_two(tmp_path):
    project = open_project(_write(tmp_path, flights_project()))
    one, two = project.flights
    assert (one.id, one.name, one.gnss_files, one.imu_file, one.strip_files) == (
        1, "flight_1", ("f1/gnss/rover.pos",), "f1/imu/imu.csv", ("f1/scans/strip_1.laz", "f1/scans/strip_2.laz"))
    assert (one.gnss_lever_arm_m, one.scanner_lever_arm_m, one.boresight_deg, one.scanner_time_offset_s) == (
        (0.1, 0.2, -1.0), (0.3, 0.0, 0.2), (0.01, 0.02, 0.03), 0.5)
    assert (two.id, two.name, two.gnss_files, two.imu_file, two.strip_files) == (
        2, "afternoon", ("f2/gnss/a.pos", "f2/gnss/b.pos"), "f2/imu/imu.imr", ("f2/scans/strip_1.laz",))
    assert (two.gnss_lever_arm_m, two.scanner_lever_arm_m, two.boresight_deg, two.scanner_time_offset_s) == (
        (0.0, 0.0, -1.1), (0.31, 0.01, 0.19), (0.1, -0.2, 0.3), 18.0)
    with pytest.raises(ConfigError) as err:  # before any file is read
        _ = project.navigation
    text = str(err.value)
    assert "field 'flights': a project of several flights has one navigation per flight" in text
    assert "Project.navigation_of(flight_id) with flight_id one of 1, 2" in text and "found 2 flights" in text
    with pytest.raises(ConfigError, match="no such flight"):
        project.navigation_of(7)


# --- two simulated flights ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def two_flights(tmp_path_factory) -> Path:
    """One project folder holding two simulated corridor-tiny flights, ``f1/`` and ``f2/``, ten minutes
    apart, with a ``project.yaml`` whose ``flights`` name both folders' files."""
    root = tmp_path_factory.mktemp("flights") / "two"
    root.mkdir()
    for k, (seed, start) in enumerate(((21, START_GPS_S), (22, SECOND_START_GPS_S)), 1):
        simulate_project("corridor-tiny", root / f"f{k}", seed=seed,
                         overrides=[*SMALL, f"flight.start_time_gps_s={start}"])
        shutil.rmtree(root / f"f{k}" / "truth")
    data = yaml.safe_load((root / "f1" / "project.yaml").read_text())
    data["name"] = "two flights"
    del data["gnss"]["files"], data["imu"]["file"], data["scanner"]["files"]
    data["reference"] = {"surfaces": "f1/reference/surfaces.csv"}
    data["flights"] = [{"id": k, "gnss_files": [f"f{k}/gnss/rover.pos"], "imu_file": f"f{k}/imu/imu.csv",
                        "strips": [f"f{k}/scans/strip_1.laz", f"f{k}/scans/strip_2.laz"]} for k in (1, 2)]
    _write(root, data)
    return root


def _variant(tmp_path: Path, two_flights: Path, edit) -> Path:
    """A project folder with the two flights' files (links to them) and an edited ``project.yaml``."""
    for k in (1, 2):
        (tmp_path / f"f{k}").symlink_to(two_flights / f"f{k}", target_is_directory=True)
    data = yaml.safe_load((two_flights / "project.yaml").read_text())
    edit(data)
    return _write(tmp_path, data)


def test_check_lists_the_flights(two_flights):
    summary = inspect_project(two_flights)
    one, two = summary.flights
    assert (one.id, one.name, two.id, two.name) == (1, "flight_1", 2, "flight_2")
    assert one.span_gps[0] == pytest.approx(START_GPS_S) and two.span_gps[0] == pytest.approx(SECOND_START_GPS_S)
    assert one.span_gps[1] < two.span_gps[0]
    for f in (one, two):
        assert f.strips == 2 and f.imu_samples > 10_000 and f.imu_rate_hz == 200.0 and f.imu_gaps == 0
        assert f.gnss_epochs > 1000 and f.gnss_usable_epochs == f.gnss_epochs
        assert 200.0 < f.span_gps[1] - f.span_gps[0] < 400.0
    assert summary.imu_samples == one.imu_samples + two.imu_samples
    assert summary.gnss_epochs == one.gnss_epochs + two.gnss_epochs
    assert summary.gnss_span_gps[0] == pytest.approx(START_GPS_S) and summary.imu_span_gps[1] > SECOND_START_GPS_S
    assert [(s.path.relative_to(two_flights).as_posix(), s.flight_id) for s in summary.strips] == [
        ("f1/scans/strip_1.laz", 1), ("f1/scans/strip_2.laz", 1), ("f2/scans/strip_1.laz", 2),
        ("f2/scans/strip_2.laz", 2)]
    for s in summary.strips:
        f = one if s.flight_id == 1 else two
        assert f.span_gps[0] <= s.time_span_gps[0] < s.time_span_gps[1] <= f.span_gps[1] and s.outside_navigation == 0
    assert summary.warnings == () and summary.reference_surfaces > 0
    text = summary.summary()
    assert "  2 flights:" in text and "GNSS:" not in text and "IMU: " not in text
    assert re.search(rf"    flight 1 \(flight_1\): {START_GPS_S:.3f} \.\. \d+\.\d{{3}} GPS s \(\d+\.\d s\), 2 strips, "
                     rf"IMU {one.imu_samples:,} samples at 200 Hz \(0 gaps\), GNSS {one.gnss_epochs:,} epochs "
                     rf"\({one.gnss_epochs:,} usable\)", text), text
    assert f"    flight 2 (flight_2): {SECOND_START_GPS_S:.3f} .. " in text
    assert "  f2/scans/strip_1.laz (flight 2): " in text


def test_check_of_one_flight_alone_is_the_single_flight_summary(two_flights):
    summary = inspect_project(two_flights / "f1")
    (f,) = summary.flights
    assert (f.id, f.name, f.strips) == (1, "flight_1", 2) and f.imu_samples == summary.imu_samples
    assert [s.flight_id for s in summary.strips] == [1, 1]
    lines = summary.summary().splitlines()
    assert lines[1].startswith("  GNSS: ") and lines[2].startswith("  IMU:  ")
    assert lines[3].startswith("  strip_1.laz: ") and lines[4].startswith("  strip_2.laz: ")
    assert not any("flights:" in line or "(flight " in line for line in lines)


def test_the_command_line_check_prints_the_flights(two_flights):
    proc = run_georefine_here("check", str(two_flights))
    assert proc.returncode == 0, proc.stderr
    assert "2 flights:" in proc.stdout and "flight 2 (flight_2): " in proc.stdout


def test_commands_that_take_one_flight_refuse_several_with_the_reason(two_flights, tmp_path):
    """One trajectory georeferences one flight; the run evaluation and a partial run take one flight."""
    sbet = two_flights / "truth" / "trajectory.sbet"
    for args, text in ((("georeference", str(two_flights), "--trajectory", str(sbet), "--out", str(tmp_path / "g")),
                        "project of one flight"),
                       (("run", str(two_flights), "--out", str(tmp_path / "r"), "--strips", "1"), "run whole"),
                       (("evaluate", "run", str(two_flights), str(tmp_path / "r")), "several flights is not built")):
        proc = run_georefine_here(*args)
        assert proc.returncode == 2 and text in proc.stderr and "Traceback" not in proc.stderr, (args, proc.stderr)
    assert not (tmp_path / "g").exists()


def test_each_flight_has_its_navigation_in_one_mapping_frame(two_flights):
    project = open_project(two_flights)
    one, two = project.navigation_of(1), project.navigation_of(2)
    assert project.navigation_of(1) is one  # read once
    assert one.frame == two.frame == project.frame
    assert (one.t0_gps, two.t0_gps) == (START_GPS_S, SECOND_START_GPS_S)
    assert one.imu.time_gps.size > 10_000 and two.imu.time_gps.size > 10_000
    assert one.imu.time_gps[-1] < two.imu.time_gps[0]  # each its own IMU record
    assert one.config.scanner.files == ["f1/scans/strip_1.laz", "f1/scans/strip_2.laz"]
    # the frame is the first flight's first fix: flight 1 read alone has the same one
    alone = open_project(two_flights / "f1").navigation
    np.testing.assert_allclose([alone.frame.lat0_rad, alone.frame.lon0_rad, alone.frame.h0_m],
                               [one.frame.lat0_rad, one.frame.lon0_rad, one.frame.h0_m], rtol=0, atol=1e-12)
    np.testing.assert_allclose(one.gnss.gnss_p_w, alone.gnss.gnss_p_w, atol=1e-6)


def test_a_strip_outside_its_flights_span_is_refused(tmp_path, two_flights):
    def swap(data):
        one, two = data["flights"]
        one["strips"], two["strips"] = ["f1/scans/strip_1.laz", "f2/scans/strip_1.laz"], ["f2/scans/strip_2.laz",
                                                                                          "f1/scans/strip_2.laz"]

    with pytest.raises(InputError) as err:
        inspect_project(_variant(tmp_path, two_flights, swap))
    text = str(err.value)
    assert "f2/scans/strip_1.laz, field 'gps_time': no point of the strip lies inside the time span of its flight 1 " \
           "(flight_1); its times lie in the span of flight 2: listed under the wrong flight?" in text, text
    assert re.search(rf"expected times within {START_GPS_S:.3f} \.\. \d+\.\d{{3}} GPS s \(flight 1's navigation\), "
                     rf"found {SECOND_START_GPS_S // 1000:.0f}\d{{3}}\.\d{{3}} \.\. \d+\.\d{{3}} GPS s\)", text), text


def test_overlapping_flights_are_refused(tmp_path, two_flights):
    """A third flight with a copy of flight 1's GNSS and IMU: the same time, another record."""
    f3 = tmp_path / "f3"
    for sub in ("gnss", "imu", "scans"):
        (f3 / sub).mkdir(parents=True)
    for rel in ("gnss/rover.pos", "imu/imu.csv", "scans/strip_1.laz"):
        shutil.copyfile(two_flights / "f1" / rel, f3 / rel)

    def third(data):
        data["flights"].insert(1, {"id": 3, "gnss_files": ["f3/gnss/rover.pos"], "imu_file": "f3/imu/imu.csv",
                                   "strips": ["f3/scans/strip_1.laz"]})

    with pytest.raises(InputError) as err:
        inspect_project(_variant(tmp_path, two_flights, third))
    text = str(err.value)
    assert re.search(r"f3/imu/imu\.csv, field 'time': flights 1 and 3 overlap in time: each flight is a take-off of "
                     rf"its own, flown one after the other \(expected flight 3's navigation after flight 1's, which "
                     rf"spans {START_GPS_S:.3f} \.\. (\d+\.\d{{3}}) GPS s, found flight 3: {START_GPS_S:.3f} \.\. \1 "
                     r"GPS s\)", text), text


def test_flights_of_the_same_imu_record_may_share_its_time(tmp_path, two_flights):
    """Two flights reading one IMU record (one take-off, its strips under two calibrations) are not
    an overlap; the summary says they share it."""
    def split(data):
        one = data["flights"][0]
        second = copy.deepcopy(one)
        second.update(id=3, strips=["f1/scans/strip_2.laz"], boresight_deg=[0.0, 0.0, 0.0])
        one["strips"] = ["f1/scans/strip_1.laz"]
        data["flights"].append(second)

    summary = inspect_project(_variant(tmp_path, two_flights, split))
    assert [f.id for f in summary.flights] == [1, 2, 3] and [f.strips for f in summary.flights] == [1, 2, 1]
    assert summary.warnings == ("flights 1 and 3 read the same IMU record f1/imu/imu.csv: their spans coincide, "
                                "and each has its own IMU errors",)


def test_one_file_under_two_names_is_refused(tmp_path, two_flights):
    (tmp_path / "again").symlink_to(two_flights / "f1", target_is_directory=True)

    def twice(data):
        data["flights"][1]["strips"].append("again/scans/strip_1.laz")

    with pytest.raises(InputError, match=r"again/scans/strip_1\.laz, field 'flights\.1\.strips\.2': the same file is "
                                         r"listed as two strips, f1/scans/strip_1\.laz \(flight 1\) and "
                                         r"again/scans/strip_1\.laz \(flight 2\) \(expected each strip in exactly one "
                                         r"flight"):
        inspect_project(_variant(tmp_path, two_flights, twice))
