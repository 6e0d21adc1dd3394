"""A table of damaged inputs through ``georefine check`` and the command that consumes them.

Every case must give, from both commands: exit code 2, one line on stderr naming the file and
the field (or the option), no traceback, and no output folder. ``check`` and the workflow use
the same rules, so a case ``check`` lets through would be a case the workflow meets hours later.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Callable

import laspy
import numpy as np
import pytest
import yaml

from bad_input_helpers import assert_refused
from bad_input_helpers import edit_line as _edit_line
from bad_input_helpers import lines as _lines
from bad_input_helpers import remove as _remove
from bad_input_helpers import set_field as _set_field
from bad_input_helpers import truncate as _truncate
from bad_input_helpers import write as _write
from cli_helpers import messages, run_georefine_here
from cli_helpers import run_georefine as _georefine
from georefine.sim.scenarios import simulate_project
from test_bad_photo_inputs import PHOTO_CASES

FAST_SCAN = ["scanner.pulse_rate_hz=2000", "scanner.line_rate_hz=100"]


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bad") / "tiny"
    simulate_project("corridor-tiny", out, seed=41, overrides=FAST_SCAN)
    shutil.rmtree(out / "truth")
    return out


def _edit_imu_rows(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], None]:
    def edit(p: Path) -> None:
        f = p / "imu" / "imu.csv"
        lines = _lines(f)
        a = np.array([[float(x) for x in line.split(",")] for line in lines[1:]])
        a = fn(a)
        _write(f, [lines[0], *(f"{r[0]:.9f}," + ",".join(f"{x:.10e}" for x in r[1:]) for r in a)])
    return edit


def _yaml(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def edit(p: Path) -> None:
        data = yaml.safe_load((p / "project.yaml").read_text())
        fn(data)
        (p / "project.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return edit


def _las(fn: Callable[[laspy.LasData], None], strip: int = 2) -> Callable[[Path], None]:
    def edit(p: Path) -> None:
        f = p / "scans" / f"strip_{strip}.laz"
        las = laspy.read(f)
        fn(las)
        las.write(f)
    return edit


def _shift_imu_time(seconds: float) -> Callable[[np.ndarray], np.ndarray]:
    def fn(a: np.ndarray) -> np.ndarray:
        a = a.copy()
        a[:, 0] += seconds
        return a
    return fn


def _cols(fn: Callable[[np.ndarray], None]) -> Callable[[np.ndarray], np.ndarray]:
    def wrap(a: np.ndarray) -> np.ndarray:
        a = a.copy()
        fn(a)
        return a
    return wrap


IMU, POS, YAML, REF = "imu.csv", "rover.pos", "project.yaml", "surfaces.csv"


def _planes(p: Path, out: Path) -> list[str]:
    """The consumer of the reference surfaces: ``evaluate reference-planes`` (any strips will do)."""
    return ["evaluate", "reference-planes", str(p / "scans"), "--reference", str(p / "reference/surfaces.csv"),
            "--out", str(out)]

# (case id, edit of the project, consuming command (``command PROJECT --out OUT``, or a function
# of the project and OUT giving the arguments), words the message must hold)
CASES: list[tuple[str, Callable[[Path], None], str | Callable[[Path, Path], list[str]], tuple[str, ...]]] = [
    # IMU record
    ("imu cut line", lambda p: (p / "imu/imu.csv").write_text((p / "imu/imu.csv").read_text()[:-40]), "trajectory",
     (IMU, "line")),
    ("imu NaN", _edit_line("imu/imu.csv", 300, lambda s: _set_field(s, 1, "nan", ",")), "trajectory", (IMU, "gyro_x")),
    ("imu text", _edit_line("imu/imu.csv", 300, lambda s: _set_field(s, 5, "abc", ",")), "trajectory", (IMU, "acc_y")),
    ("imu repeated time", _edit_imu_rows(_cols(lambda a: a.__setitem__((301, 0), a[300, 0]))), "trajectory",
     (IMU, "time")),
    ("imu backward time", _edit_imu_rows(_cols(lambda a: a.__setitem__((500, 0), a[498, 0]))), "trajectory",
     (IMU, "time")),
    ("imu missing column", lambda p: _write(p / "imu/imu.csv", [",".join(line.split(",")[:6])
                                                                  for line in _lines(p / "imu/imu.csv")]),
     "trajectory", (IMU,)),
    ("imu header only", lambda p: _write(p / "imu/imu.csv", _lines(p / "imu/imu.csv")[:1]), "trajectory", (IMU,)),
    ("imu gyro deg/s", _edit_imu_rows(_cols(lambda a: a.__setitem__((slice(None), slice(1, 4)),
                                                                     np.degrees(a[:, 1:4])))), "trajectory",
     (IMU, "gyro_x, gyro_y, gyro_z", "deg/s")),
    ("imu gyro x<->y", _edit_imu_rows(lambda a: a[:, [0, 2, 1, 3, 4, 5, 6]]), "trajectory",
     (IMU, "gyro_x, gyro_y", "swapped")),
    ("imu gyro -z", _edit_imu_rows(lambda a: a * [1, 1, 1, -1, 1, 1, 1]), "trajectory", (IMU, "gyro_z", "sign")),
    ("imu acc -z", _edit_imu_rows(lambda a: a * [1, 1, 1, 1, 1, 1, -1]), "trajectory", (IMU, "acc_z")),
    ("imu acc in g", _edit_imu_rows(_cols(lambda a: a.__setitem__((slice(None), slice(4, 7)), a[:, 4:7] / 9.80665))),
     "trajectory", (IMU, "acc_x, acc_y, acc_z", "like g")),
    ("imu 6 s gap", lambda p: _write(p / "imu/imu.csv", (lambda ls: ls[:5001] + ls[6201:])(_lines(p / "imu/imu.csv"))),
     "trajectory", (IMU, "time", "imu.max_gap_s")),
    ("imu a day late", _edit_imu_rows(_shift_imu_time(86400.0)), "trajectory", (IMU, "time", "overlap")),
    ("imu huge value", _edit_line("imu/imu.csv", 300, lambda s: _set_field(s, 2, "1e6", ",")), "trajectory",
     (IMU, "gyro_y")),
    ("imu missing file", _remove("imu/imu.csv"), "trajectory", (IMU,)),
    # GNSS solution
    ("pos cut line", _edit_line("gnss/rover.pos", 100, lambda s: s[:30]), "trajectory", (POS, "line 1")),
    ("pos NaN latitude", _edit_line("gnss/rover.pos", 100, lambda s: _set_field(s, 2, "nan")), "trajectory",
     (POS, "lat")),
    ("pos longitude 400", _edit_line("gnss/rover.pos", 100, lambda s: _set_field(s, 3, "400.0")), "trajectory",
     (POS, "lon")),
    ("pos bad date", _edit_line("gnss/rover.pos", 100, lambda s: s.replace("/", "-", 2)), "trajectory", (POS,)),
    ("pos no usable epoch", lambda p: _write(p / "gnss/rover.pos", [
        line if line.startswith("%") else _set_field(line, 5, "5") for line in _lines(p / "gnss/rover.pos")]),
     "trajectory", (POS, "Q")),
    ("pos text height", _edit_line("gnss/rover.pos", 100, lambda s: _set_field(s, 4, "high")), "trajectory",
     (POS, "height")),
    ("pos missing file", _remove("gnss/rover.pos"), "trajectory", (POS,)),
    # project.yaml
    ("yaml unknown key", _yaml(lambda d: d["imu"].__setitem__("rate", 200)), "trajectory", (YAML, "imu.rate")),
    ("yaml not yaml", lambda p: (p / "project.yaml").write_text("name: [unclosed\n"), "trajectory", (YAML,)),
    ("yaml negative arw", _yaml(lambda d: d["imu"]["errors"].__setitem__("gyro_arw_deg_per_sqrt_h", -1)), "trajectory",
     (YAML, "imu.errors.gyro_arw_deg_per_sqrt_h")),
    ("yaml unknown epsg", _yaml(lambda d: d["crs"].__setitem__("output_epsg", 99999)), "trajectory",
     (YAML, "crs.output_epsg", "EPSG:99999")),
    ("yaml lever arm text", _yaml(lambda d: d["gnss"].__setitem__("lever_arm_m", "front")), "trajectory",
     (YAML, "gnss.lever_arm_m")),
    ("yaml no imu file", _yaml(lambda d: d["imu"].__setitem__("file", "imu/none.csv")), "trajectory", ("none.csv",)),
    ("yaml max gap 0", _yaml(lambda d: d["imu"].__setitem__("max_gap_s", 0)), "trajectory", (YAML, "imu.max_gap_s")),
    ("yaml knots vs windows", _yaml(lambda d: d.setdefault("processing", {}).__setitem__(
        "trajectory", {"knot_interval_s": 0.05, "imu_window_s": 0.02})), "trajectory",
     (YAML, "processing.trajectory")),
    ("yaml duplicate channel", _yaml(lambda d: d["scanner"]["channels"][1].__setitem__("id", 0)), "run",
     (YAML, "scanner.channels")),
    ("yaml missing scan", _yaml(lambda d: d["scanner"]["files"].append("scans/strip_9.laz")), "run",
     ("strip_9.laz",)),
    # scans
    ("las unknown channel", _las(lambda las: setattr(las, "scanner_channel", np.full(len(las.points), 3, np.uint8))),
     "run", ("strip_2.laz", "scanner_channel")),
    ("las truncated", _truncate("scans/strip_2.laz", 0.4), "run", ("strip_2.laz",)),
    ("las not a las file", lambda p: (p / "scans/strip_2.laz").write_text("x,y,z\n1,2,3\n"), "run", ("strip_2.laz",)),
    ("las empty", _las(lambda las: las.points.__setattr__("array", las.points.array[:0])), "run", ("strip_2.laz",)),
    ("las a day late", _las(lambda las: setattr(las, "gps_time", las.gps_time + 86400.0)), "run",
     ("strip_2.laz", "gps_time", "inside the trajectory")),
    ("yaml time offset a day", _yaml(lambda d: d["scanner"].__setitem__("time_offset_s", 86400.0)), "run",
     ("gps_time", "scanner.time_offset_s 86400 s applied")),
    ("yaml time offset text", _yaml(lambda d: d["scanner"].__setitem__("time_offset_s", "utc")), "run",
     (YAML, "scanner.time_offset_s")),
    # reference surfaces
    ("ref missing column", lambda p: _write(p / "reference/surfaces.csv", [
        ",".join(line.split(",")[:4]) for line in _lines(p / "reference/surfaces.csv")]), _planes, (REF,)),
    ("ref NaN", _edit_line("reference/surfaces.csv", 3, lambda s: _set_field(s, 4, "nan", ",")), _planes, (REF, "z")),
    ("ref text", _edit_line("reference/surfaces.csv", 3, lambda s: _set_field(s, 2, "east", ",")), _planes,
     (REF, "x")),
]




def test_the_table_has_at_least_forty_cases():
    assert len(CASES) + len(OPTION_CASES) + len(PHOTO_CASES) >= 40
    assert len({c[0] for c in CASES}) == len(CASES)


@pytest.mark.parametrize("name, edit, command, words", CASES, ids=[c[0] for c in CASES])
def test_a_damaged_input_is_one_line_and_exit_2_from_check_and_the_workflow(clean, tmp_path, name, edit, command,
                                                                             words):
    p = tmp_path / "p"
    shutil.copytree(clean, p)
    edit(p)
    consumer = command(p, tmp_path / "o") if callable(command) else [command, str(p), "--out", str(tmp_path / "o")]
    assert_refused(name, [["check", str(p)], consumer], words, tmp_path / "o")


def _a_file(folder: Path) -> Path:
    (folder / "results").write_text("keep")
    return folder / "results"


def _foreign(folder: Path) -> Path:
    (folder / "f").mkdir()
    (folder / "f" / "survey.laz").write_text("theirs")
    return folder / "f"


OPTION_CASES = [
    ("out inside the project", lambda p, t: ["trajectory", str(p), "--out", str(p / "out")], ("project folder",)),
    ("out is a file", lambda p, t: ["run", str(p), "--out", str(_a_file(t))], ("not a folder",)),
    ("unknown strip", lambda p, t: ["run", str(p), "--out", str(t / "o"), "--strips", "9"], ("--strips",)),
    ("no project", lambda p, t: ["check", str(t / "nowhere")], ("nowhere",)),
    ("out holds other files", lambda p, t: ["run", str(p), "--out", str(_foreign(t))],
     ("did not write", "--force", "survey.laz")),
    ("evaluation into other files", lambda p, t: ["evaluate", "strip-differences", str(p / "scans"), "--out",
                                                  str(_foreign(t))], ("did not write", "--force")),
    # simulate, demo, evaluate, coadjust: bad options and inputs without a project edit
    ("simulate unknown scenario", lambda p, t: ["simulate", "nothing", "--out", str(t / "o")], ("SCENARIO", "nothing")),
    ("simulate negative pulse rate", lambda p, t: ["simulate", "corridor-tiny", "--out", str(t / "o"), "--set",
                                                   "scanner.pulse_rate_hz=-5"], ("scanner.pulse_rate_hz",)),
    ("simulate unknown imu grade", lambda p, t: ["simulate", "corridor-tiny", "--out", str(t / "o"), "--imu-grade",
                                                 "best"], ("imu_grade", "best")),
    ("simulate into a full folder", lambda p, t: ["simulate", "corridor-tiny", "--out", str(_foreign(t))],
     ("not empty",)),
    ("demo unknown key", lambda p, t: ["demo", "--out", str(t / "o"), "--set", "flight.speed=abc"], ("flight.speed",)),
    ("demo block bad value", lambda p, t: ["demo", "--scenario", "block", "--out", str(t / "o"), "--set",
                                           "photos.strips=0"], ("photos.strips",)),
    ("demo unknown method", lambda p, t: ["demo", "--scenario", "block", "--method", "orb", "--out", str(t / "o")],
     ("--method", "orb")),
    ("evaluate missing trajectory", lambda p, t: ["evaluate", "trajectory", str(t / "none.sbet"), "--reference",
                                                  str(t / "none.sbet"), "--out", str(t / "o")], ("none.sbet", "not found")),
    ("evaluate cut trajectory", lambda p, t: ["evaluate", "trajectory", str(_cut_sbet(t)), "--reference",
                                              str(_cut_sbet(t)), "--out", str(t / "o")], ("cut.sbet", "record 1")),
    ("evaluate no strips", lambda p, t: ["evaluate", "strip-differences", str(p / "gnss"), "--out", str(t / "o")],
     ("gnss", "no LAS/LAZ")),
    ("coadjust without photos", lambda p, t: ["coadjust", str(p), "--points", str(p / "scans"), "--out", str(t / "o"),
                                              "--case", "1"], ("project.yaml", "photos")),
]


def _cut_sbet(folder: Path) -> Path:
    (folder / "cut.sbet").write_bytes(bytes(100))  # shorter than one 136-byte record
    return folder / "cut.sbet"



@pytest.mark.parametrize("name, args, words", OPTION_CASES, ids=[c[0] for c in OPTION_CASES])
def test_a_bad_option_is_one_line_and_exit_2(clean, tmp_path, name, args, words):
    before = sorted(q.name for q in clean.rglob("*"))
    run = run_georefine_here(*args(clean, tmp_path))
    err = messages(run.stderr).strip()
    assert run.returncode == 2 and "Traceback" not in run.stderr and err.count("\n") == 0, (name, run.stderr[-2000:])
    assert all(w in err for w in words), (name, err)
    assert sorted(q.name for q in clean.rglob("*")) == before and not (tmp_path / "o").exists()


def test_force_writes_into_a_folder_of_other_files_and_marks_it_as_georefines(clean, tmp_path):
    out = _foreign(tmp_path)
    run = _georefine("trajectory", str(clean), "--out", str(out), "--filter-only", "--force")
    assert run.returncode == 0, run.stderr[-2000:]
    assert (out / "survey.laz").read_text() == "theirs" and (out / "trajectory.sbet").is_file()
    assert (out / ".georefine-output").is_file()
    again = _georefine("trajectory", str(clean), "--out", str(out), "--filter-only")  # now Georefine's folder
    assert again.returncode == 0, again.stderr[-2000:]
