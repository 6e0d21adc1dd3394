"""Named simulation scenarios and the simulation of a project folder.

A scenario is a :class:`ScenarioConfig`: every parameter of the scene, the flight, the IMU,
the GNSS and the scanner, with defaults per scenario name. The user overrides any of them
with a YAML file (same nesting) and ``key.sub=value`` strings; unknown keys are errors.

:func:`simulate_project` writes what a real helicopter LiDAR system delivers (docs/ARCHITECTURE.md §3),
plus the truth:

``project.yaml``, ``gnss/rover.pos``, ``imu/imu.csv`` (and ``imu/imu.imr`` on request),
``scans/strip_<id>.laz`` (scanner frame), ``reference/surfaces.csv`` (surveyed corners with
survey noise), ``truth/trajectory.sbet`` (true IMU trajectory at IMU rate, seconds of GPS week;
the week in its companion ``truth/trajectory.sbet.json``),
``truth/strip_<id>.laz`` (every return georeferenced with the true trajectory, output CRS,
same point order as the scan file, extra dimension ``range_error_m``),
``truth/reference_surfaces.csv`` (exact corners), ``truth/imu_errors.npz``,
``truth/gnss_errors.npz`` and ``truth/scenario.yaml`` (every parameter used and the true
sensor errors). The writing, of one sortie or several, is in :mod:`georefine.sim.project_writer`.

The whole folder is written under a temporary name next to ``out`` and renamed when complete.
Independent random streams (``SeedSequence(seed).spawn``) drive the scene, IMU, GNSS, scanner
and survey, so changing one sensor's parameters leaves the others' errors unchanged. The scan
noise has one stream per strip and chunk, so the scan chunks run as tasks on any scheduler
(``georefine simulate --scheduler``) and give the same files.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from pydantic import Field, field_validator

from georefine.config import (
    ReferencePoint,
    StrictModel,
    apply_overrides,
    check_output_epsg,
    deep_merge,
    read_yaml,
    validate_model,
)
from georefine.errors import ConfigError, InputError
from georefine.geometry.frames import LocalFrame
from georefine.progress import Progress, no_progress
from georefine.sim.camera import PhotoBlockConfig
from georefine.sim.flight import FlightConfig
from georefine.sim.flight_plan import FlightPlanConfig
from georefine.sim.gnss import GnssConfig
from georefine.sim.imu import DEFAULT_IMU_GRADE, IMU_PRESETS, ImuGrade
from georefine.sim.project_writer import fly, write_project
from georefine.sim.scanner import ScannerConfig
from georefine.sim.scene import SceneConfig, build_scene
from georefine.tasks import TaskRunner, runner_for

log = logging.getLogger(__name__)

SIMULATOR_VERSION = 2
"""Bumped whenever the same scenario and seed give different files (2: one noise seed per scan
chunk, so that chunks can be simulated in parallel); a demo re-simulates a project of another version."""


class JammingConfig(StrictModel):
    """GNSS jamming over the scanning (paper 004's motivating case): one outage from shortly after
    the first pass starts to shortly before the last pass ends, turn included, so that the
    trajectory drifts on the IMU alone for minutes while GNSS still frames the strips."""

    after_first_pass_start_s: float = Field(5.0, ge=0.0, description="outage start after the first pass starts (s)")
    before_last_pass_end_s: float = Field(5.0, ge=0.0, description="outage end before the last pass ends (s)")


class ScenarioConfig(StrictModel):
    """Every parameter of a simulated project."""

    name: str
    description: str = ""
    reference_point: ReferencePoint = Field(
        default_factory=lambda: ReferencePoint(lat_deg=46.70, lon_deg=11.65, h_m=600.0),
        description="Origin of the scene (w frame); default in the Eisacktal, South Tyrol.",
    )
    output_epsg: int = Field(25832, description="Output CRS of truth and reference files.")

    @field_validator("output_epsg")
    @classmethod
    def _known_epsg(cls, v: int) -> int:
        return check_output_epsg(v)

    scene: SceneConfig = Field(default_factory=SceneConfig)
    flight: FlightConfig = Field(default_factory=FlightConfig)
    imu: ImuGrade = Field(default_factory=lambda: IMU_PRESETS[DEFAULT_IMU_GRADE])
    gnss: GnssConfig = Field(default_factory=GnssConfig)
    scanner: ScannerConfig = Field(default_factory=ScannerConfig)
    gnss_lever_arm_m: tuple[float, float, float] = Field(
        (-0.85, 0.12, -1.45), description="Antenna in the body frame (FRD): behind and above the IMU."
    )
    scanner_lever_arm_m: tuple[float, float, float] = Field(
        (0.18, 0.0, 0.22), description="Scanner origin in the body frame (FRD)."
    )
    boresight_deg: tuple[float, float, float] = Field(
        (0.012, -0.021, 0.034), description="True boresight roll, pitch, yaw (deg); project.yaml states the same."
    )
    project_boresight_deg: tuple[float, float, float] | None = Field(
        None, description="Boresight written to project.yaml if it differs from the truth (calibration error)."
    )
    scanner_time_offset_s: float = Field(
        0.0, ge=-60.0, le=60.0,
        description="The strips' gps_time runs this far behind GPS time (an unsynchronised scanner: 18 for time "
        "stamps in UTC). project.yaml does not know it (scanner.time_offset_s: 0); the truth strips keep GPS time.",
    )
    reference_survey_sigma_m: float = Field(0.003, ge=0.0, description="RTK survey noise of the reference corners.")
    laz: bool = Field(True, description="Compress strips (LAZ) or not (LAS).")
    plan: FlightPlanConfig | None = Field(
        None, description="A flight plan of several lines (area block, bending or parallel corridor lines, a file of "
        "line end points); without one the flight is the corridor's one or two passes (flight.passes).")
    sorties: int = Field(1, ge=1, le=9, description="Flights of the plan, each with its own take-off, static "
                         "alignment, IMU record (its own turn-on biases), GNSS session and strips; one scanner and "
                         "calibration (sim/project_writer.py).")
    sortie_interval_s: float = Field(91800.0, gt=0.0, description="Take-off to take-off of consecutive sorties (s); "
                                     "default the next day, 1.5 h later.")
    jamming: JammingConfig | None = Field(None, description="GNSS outage in every pass (the LiDAR's trajectory).")
    photos: PhotoBlockConfig | None = Field(None, description="A photo block over the scene (paper 004).")
    sources: dict[str, str] = Field(
        default_factory=dict, description="Where each section's values came from: the scenario's defaults, an IMU "
        "preset, the --config file, --imu-grade/--gnss-grade, each --set (filled by resolve_scenario).",
    )



def _scenario_defaults(name: str) -> dict[str, Any]:
    """Default parameters of a named scenario, as a plain dict (before overrides)."""
    if name == "corridor":
        return {
            "name": "corridor",
            "description": "Helicopter power-line corridor, two passes N->S and S->N at 160 m AGL and 18 m/s "
            "(paper 000 at reduced length and point rate).",
            # 100 kHz over three views gives ~5 points/m^2 per view, ~15 per 1 m feature
            # neighbourhood; 30 M points keep simulation plus the whole workflow within minutes.
            "scanner": {"pulse_rate_hz": 100000.0, "line_rate_hz": 120.0},
        }
    if name == "corridor-paper":
        return {
            "name": "corridor-paper",
            "description": "The corridor at paper 000's pulse rate: a RIEGL VUX-160 at 1.8 MHz and 400 lines/s "
            "(about 550 M points; the scale benchmark, docs/ARCHITECTURE.md §4.7).",
            # 1.8 MHz over 400 lines/s: 4,500 pulses a line, a view every third line: 0.14 m along
            # and 0.07 m across track at nadir, ~90 points/m^2 per view. Lengthen the flight with
            # --set scene.length_m=... (both passes grow).
            "scanner": {"pulse_rate_hz": 1800000.0, "line_rate_hz": 400.0},
        }
    if name == "corridor-paper-full":
        return {
            "name": "corridor-paper-full",
            "description": "Paper 000's whole flight: the corridor over 30 km, flown N->S and S->N with a RIEGL VUX-160 "
            "at 1.8 MHz and 400 lines/s (about an hour of strips, about 5.5 G points); for benchmarks lower the pulse "
            "rate with --set scanner.pulse_rate_hz=400000 (about 1.2 G points).",
            "scanner": {"pulse_rate_hz": 1800000.0, "line_rate_hz": 400.0},
            "scene": {"length_m": 30000.0},
        }
    if name == "block":
        return {
            "name": "block",
            "description": "Small town in a valley: a photo block of two strips at 8 cm GSD and two LiDAR passes "
            "whose GNSS is jammed from the first pass to the last, turn included (paper 004).",
            "scene": {"length_m": 500.0, "width_m": 640.0, "settlement_count": 4, "buildings_per_settlement": 30,
                      "settlement_radius_m": 90.0, "scattered_building_count": 15, "vegetation_per_ha": 18.0,
                      "power_line": False, "reference_surfaces_per_site": [1, 1]},
            "flight": {"static_duration_s": 5.0, "manoeuvre": "s_turns"},
            "scanner": {"pulse_rate_hz": 100000.0, "line_rate_hz": 120.0},
            "jamming": {},
            "photos": {},
        }
    if name == "area":
        return {
            "name": "area",
            "description": "An area block: 8 parallel strips at 30 % sidelap flown in a racetrack pattern and 2 cross "
            "strips over 2.2 x 2.3 km of rolling country with villages, a helicopter at 160 m AGL and 18 m/s after a "
            "5-minute static alignment and a 3 km transit: over 40 minutes of flight.",
            "scene": {"layout": "area", "length_m": 2200.0, "width_m": 2300.0, "floor_half_width_m": 1000.0,
                      "side_rise_m": 30.0, "floor_slope_m_per_m": 0.005, "undulation_m": 4.0, "settlement_count": 6,
                      "buildings_per_settlement": 16, "scattered_building_count": 30, "power_line": False,
                      "reference_surfaces_per_site": [1, 1, 1, 1, 1, 1, 1, 1, 1]},
            "flight": {"static_duration_s": 300.0},
            "plan": {"kind": "area", "lines": 8, "sidelap": 0.3, "cross_lines": 2, "transit_m": 3000.0},
            "scanner": {"pulse_rate_hz": 100000.0, "line_rate_hz": 120.0},
        }
    if name == "area-tiny":
        return {
            "name": "area-tiny",
            "description": "A small block for tests: 3 parallel strips of 300 m at 30 % sidelap and 1 cross strip, "
            "the corridor's scanner over a 60-degree field of view.",
            "scene": {"layout": "area", "length_m": 300.0, "width_m": 520.0, "floor_half_width_m": 200.0,
                      "side_rise_m": 10.0, "end_margin_m": 120.0, "settlement_count": 2, "buildings_per_settlement": 10,
                      "settlement_radius_m": 60.0, "scattered_building_count": 8, "power_line": False,
                      "reference_surfaces_per_site": [1, 1, 1, 1]},
            "flight": {"static_duration_s": 5.0, "manoeuvre": "s_turns", "lead_in_m": 100.0, "lead_out_m": 100.0},
            "plan": {"kind": "area", "lines": 3, "sidelap": 0.3, "cross_lines": 1},
            "scanner": {"pulse_rate_hz": 100000.0, "line_rate_hz": 120.0, "field_of_view_deg": 60.0},
        }
    if name in ("two-flights", "two-flights-tiny"):
        base = _scenario_defaults(name.replace("two-flights", "corridor"))
        return {**base, "name": name, "sorties": 2,
                "description": f"{base['description']} Flown on two days (the next day 1.5 h later): each flight its own "
                "static alignment, IMU turn-on biases and GNSS session, the same scanner and boresight error."}
    if name == "corridor-tiny":
        return {
            "name": "corridor-tiny",
            "description": "Small corridor for tests: 600 m with the corridor's scanner, short manoeuvre.",
            "scene": {"length_m": 600.0, "width_m": 500.0},
            "flight": {"static_duration_s": 5.0, "manoeuvre": "s_turns"},
            # The corridor's scanner, so that `georefine run` works with the default plane extraction
            # (a 1 m ball around a seed point must hold >= 10 points). At 160 m and 18 m/s, 100 kHz at
            # 120 lines/s spaces the points of a view 0.45 m along and 0.40 m across track at nadir:
            # a median of 19 points per ball near nadir and 11 at the swath edges, >= 10 for 85 % of
            # the seeds (measured). The scan pattern is a near-regular grid, and with both spacings
            # between 0.5 and 0.7 m a 1 m ball holds at most the seed's 3 x 3 neighbours: 60 kHz at
            # 100 lines/s (0.54 x 0.56 m) gave at most 9 points per ball, the former 20 kHz at
            # 60 lines/s (0.9 x 1.0 m, ~1 point/m^2 per view) at most 5, and neither any feature.
            "scanner": {"pulse_rate_hz": 100000.0, "line_rate_hz": 120.0},
        }
    raise ConfigError("unknown scenario", field="SCENARIO", expected="one of " + ", ".join(SCENARIOS), found=repr(name))


SCENARIOS = ("corridor", "corridor-tiny", "corridor-paper", "corridor-paper-full", "block", "area", "area-tiny", "two-flights",
             "two-flights-tiny")


def resolve_scenario(
    name: str,
    *,
    seed_overrides: list[str] | None = None,
    config_file: str | Path | None = None,
    imu_grade: str | None = None,
    gnss_grade: str | None = None,
) -> ScenarioConfig:
    """Scenario defaults <- YAML file <- grade options <- ``key=value`` overrides, validated.

    Each layer changes only the fields it names, on top of what the layers before it chose: the
    IMU section is always a whole preset (the default grade unless a layer names another, by
    ``--imu-grade``, ``imu: tactical`` in the file or ``--set imu=tactical``), so
    ``--set imu.rate_hz=400`` changes the rate of that preset and keeps its errors. Overrides
    apply in order, so ``--set imu=tactical --set imu.rate_hz=400`` works too.
    """
    defaults = _scenario_defaults(name)
    sources = {k: "defaults" for k in ("scene", "flight", "gnss", "scanner")}
    sources.update({k: f"scenario {name}" for k in defaults if k not in ("name", "description")})
    sources["imu"] = f"preset {defaults.get('imu', DEFAULT_IMU_GRADE)} (the default)"

    def note(section: str, what: str) -> None:
        sources[section] = f"{sources[section]}, {what}" if section in sources else what

    data = _with_imu_preset(defaults, "scenario " + name)
    if config_file is not None:
        layer = read_yaml(config_file)
        layer.pop("sources", None)  # a resolved scenario given back as a file: its record is rewritten below
        for section, value in layer.items():
            if section == "imu" and isinstance(value, str):
                sources["imu"] = f"preset {value} ({config_file})"
            else:
                note(section, str(config_file))
        data = _with_imu_preset(_merge_layer(data, layer), str(config_file))
    if imu_grade is not None:
        data = _with_imu_preset({**data, "imu": imu_grade}, "--imu-grade", field="imu_grade")
        sources["imu"] = f"preset {imu_grade} (--imu-grade)"
    if gnss_grade is not None:
        data = deep_merge(data, {"gnss": {"grade": gnss_grade}})
        note("gnss", f"--gnss-grade {gnss_grade}")
    for item in seed_overrides or ():
        data = _with_imu_preset(apply_overrides(data, [item]), "--set " + item)
        key = item.partition("=")[0].strip()
        if key == "imu" and isinstance(data.get("imu"), dict):
            sources["imu"] = f"preset {item.partition('=')[2].strip()} (--set)"
        else:
            note(key.split(".")[0], f"--set {item}")
    data["sources"] = sources
    return validate_model(ScenarioConfig, data, config_file)  # type: ignore[return-value]


def _merge_layer(data: dict[str, Any], layer: dict[str, Any]) -> dict[str, Any]:
    """``layer`` merged onto ``data``; an IMU preset named in ``layer`` replaces the whole section."""
    if isinstance(layer.get("imu"), str):
        return {**deep_merge(data, {k: v for k, v in layer.items() if k != "imu"}), "imu": layer["imu"]}
    return deep_merge(data, layer)


def _with_imu_preset(data: dict[str, Any], source: str, field: str = "imu") -> dict[str, Any]:
    """``data`` with its IMU section a whole preset: the default grade if absent, the named one if a name."""
    preset = data.get("imu", DEFAULT_IMU_GRADE)
    if not isinstance(preset, str):
        return data
    if preset not in IMU_PRESETS:
        raise ConfigError("unknown IMU grade", field=field, expected="one of " + ", ".join(IMU_PRESETS),
                          found=f"{preset!r} (from {source})")
    return {**data, "imu": IMU_PRESETS[preset].model_dump()}


@dataclass(frozen=True)
class SimulationResult:
    """What :func:`simulate_project` wrote."""

    out: Path
    scenario: ScenarioConfig
    seed: int
    duration_s: float
    points_per_strip: dict[int, int]
    n_imu: int
    n_gnss: int
    timings_s: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        pts = ", ".join(f"strip {k}: {v:,}" for k, v in self.points_per_strip.items())
        t = ", ".join(f"{k} {v:.1f} s" for k, v in self.timings_s.items())
        return (
            f"Simulated '{self.scenario.name}' (seed {self.seed}) into {self.out}\n"
            f"  flight {self.duration_s:.0f} s, IMU {self.n_imu:,} samples, GNSS {self.n_gnss:,} epochs\n"
            f"  points: {pts}\n  timings: {t}"
        )


def _prepare_output(out: Path) -> Path:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("output folder exists and is not empty", path=out, expected="a new or empty folder")
    parent = out.resolve().parent
    if not parent.is_dir():
        raise InputError("parent folder of the output does not exist", path=out)
    tmp = parent / f".{out.name}.part-{np.random.default_rng().integers(1 << 32):08x}"
    tmp.mkdir()
    for sub in ("gnss", "imu", "scans", "reference", "truth"):
        (tmp / sub).mkdir()
    return tmp


def simulate_project(
    scenario: str,
    out: str | Path,
    *,
    seed: int = 42,
    overrides: list[str] | None = None,
    config_file: str | Path | None = None,
    imu_grade: str | None = None,
    gnss_grade: str | None = None,
    write_imr: bool = False,
    progress: Progress = no_progress,
    on_navigation: Callable[[Path], None] | None = None,
    scheduler: str | TaskRunner = "sync",
) -> SimulationResult:
    """Simulate scenario ``scenario`` and write a project folder at ``out`` (see module docstring).

    The project is written into a temporary folder beside ``out`` and renamed when complete.
    ``on_navigation(folder)`` is called with that folder as soon as ``project.yaml``, the GNSS and
    the IMU files are written, before the (long) scanning: the navigation steps can start then.
    ``scheduler`` (a name or address, or a running :class:`~georefine.tasks.TaskRunner`) is where
    the scan chunks are simulated; every chunk draws its noise from its own seed
    (:func:`~georefine.sim.scanner.chunk_seed`), so the files do not depend on it.
    """
    cfg = resolve_scenario(
        scenario, seed_overrides=overrides, config_file=config_file, imu_grade=imu_grade, gnss_grade=gnss_grade
    )
    out = Path(out)
    tmp = _prepare_output(out)
    try:
        with runner_for(scheduler) as runner:
            result = write_project(cfg, tmp, seed, write_imr, progress, on_navigation, runner)
        tmp.rename(out) if not out.exists() else _replace_empty_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return SimulationResult(out=out, **{k: v for k, v in result.items()})


def flight_passes(cfg: ScenarioConfig, seed: int) -> tuple[tuple[int, float, float], ...]:
    """``(strip_id, t_start, t_end)`` of the passes :func:`simulate_project` flies with ``cfg`` and
    ``seed`` (s from the start of the data), without simulating the sensors."""
    rp = cfg.reference_point
    # The scene's stream is the first child of the seed, as in the simulation (children do not
    # depend on how many are spawned); the terrain shapes the flight.
    scene = build_scene(cfg.scene, np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0]))
    traj = fly(cfg, LocalFrame.from_degrees(rp.lat_deg, rp.lon_deg, rp.h_m), scene.terrain_height)
    return tuple((int(sid), float(t0), float(t1)) for sid, t0, t1 in traj.passes)


def outage_inside_pass(cfg: ScenarioConfig, seed: int, *, strip: int = 1, start_after_s: float = 10.0,
                       length_s: float = 60.0, margin_s: float = 10.0, min_length_s: float = 10.0) -> str:
    """The override ``gnss.outages=[[a, b]]`` of a GNSS outage inside pass ``strip`` of this flight.

    The outage starts ``start_after_s`` into the pass and lasts ``length_s``, or less so that it
    ends ``margin_s`` before the pass does: GNSS is lost and regained during the pass, whatever
    the corridor's length. The pass times are those :func:`simulate_project` flies with ``cfg``
    and ``seed`` (the scene's terrain shapes the flight).

    Raises
    ------
    ConfigError
        The pass is too short for an outage of ``min_length_s`` there.
    """
    spans = {sid: (t0, t1) for sid, t0, t1 in flight_passes(cfg, seed)}
    if strip not in spans:
        raise ConfigError("no such pass", field="strip", expected=f"one of {sorted(spans)}", found=str(strip))
    start, end = spans[strip]
    a = start + start_after_s
    b = min(a + length_s, end - margin_s)
    if b - a < min_length_s:
        raise ConfigError("pass too short for an outage inside it", field="scene.length_m",
                          expected=f"a pass of at least {start_after_s + min_length_s + margin_s:.0f} s",
                          found=f"pass {strip} of {end - start:.0f} s")
    return f"gnss.outages=[[{a:.1f}, {b:.1f}]]"


def _replace_empty_dir(tmp: Path, out: Path) -> None:
    out.rmdir()
    tmp.rename(out)
