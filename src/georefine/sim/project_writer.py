"""The writer of a simulated project folder: one or several sorties (docs/ARCHITECTURE.md §6).

:func:`write_project` flies a resolved scenario (:class:`~georefine.sim.scenarios.ScenarioConfig`)
and writes what a real helicopter LiDAR system delivers, plus the truth (the files are listed in
:mod:`georefine.sim.scenarios`). With ``sorties: N > 1`` the same plan is flown N times,
``sortie_interval_s`` apart (take-off to take-off: days, hours): each sortie has its own static
alignment and take-off, its own IMU record with its own turn-on biases, its own GNSS session and
its own strips, numbered on from the sortie before (a two-pass corridor flown twice gives strips
1, 2 and 3, 4); the scanner, its calibration and its boresight error are the same. The project
then lists its flights (``project.yaml`` ``flights:``, docs/ARCHITECTURE.md §3) with
``gnss/flight_K.pos``, ``imu/flight_K.csv`` and the truth per flight
(``truth/trajectory_flight_K.sbet``, ``truth/imu_errors_flight_K.npz``,
``truth/gnss_errors_flight_K.npz``); ``truth/trajectory.sbet`` and the error files hold all
sorties in time order (one GPS week), so that the evaluation reads them as for one flight, and
``truth/scenario.yaml`` lists every strip's times from the first sortie's epoch and each
sortie under ``flights``.

Random streams: the first sortie uses exactly the streams of a single-sortie project (children
0-5 of ``SeedSequence(seed)``), so that its files are those of the same scenario flown once;
sortie K > 1 draws its IMU and GNSS errors from children ``6 + 2 (K - 2)`` and ``7 + 2 (K - 2)``,
and its scan noise from its own strip ids.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from georefine.config import (
    ChannelConfig,
    CrsConfig,
    GnssCorrelatedError,
    GnssFileConfig,
    GnssMultipath,
    ImuErrorSpec,
    ImuFileConfig,
    PhotosFileConfig,
    ProjectConfig,
    ReferenceConfig,
    ScannerFileConfig,
    boresight_matrix,
    write_yaml,
)
from georefine.config import FlightConfig as ProjectFlight
from georefine.errors import ConfigError
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.files import week_from_gps_seconds
from georefine.progress import Progress
from georefine.sim.camera import write_photo_block
from georefine.sim.flight import FlightConfig, TrueTrajectory, simulate_flight
from georefine.sim.flight_plan import plan_lines, swath_width_m
from georefine.sim.gnss import GnssConfig, SimulatedGnss, simulate_gnss
from georefine.sim.imu import SimulatedImu, simulate_imu
from georefine.sim.scanner import chunk_seed, scan
from georefine.sim.scene import build_scene
from georefine.tasks import TaskRunner

__all__ = ["fly", "write_project"]


def stated_gnss_error(gnss: GnssConfig) -> GnssCorrelatedError | None:
    """The correlated GNSS error project.yaml states: the simulated one (as it states the IMU's errors)."""
    h, u = gnss.gm_sigma_horizontal_m, gnss.gm_sigma_up_m
    if gnss.grade != "ppk" or max(h, u) <= 0.0:
        return None
    floor = 1e-4  # a sigma must be positive; 0.1 mm is none to speak of
    return GnssCorrelatedError(sigma_horizontal_m=max(h, floor), sigma_up_m=max(u, floor),
                               time_constant_s=gnss.gm_time_constant_s)


def stated_gnss_multipath(gnss: GnssConfig) -> GnssMultipath | None:
    """The multipath project.yaml states: the simulated one, where the correlated error is stated beside it."""
    h, u = gnss.multipath_sigma_horizontal_m, gnss.multipath_sigma_up_m
    if stated_gnss_error(gnss) is None or max(h, u) <= 0.0:
        return None
    floor = 1e-4
    return GnssMultipath(sigma_horizontal_m=max(h, floor), sigma_up_m=max(u, floor),
                         time_constant_s=gnss.multipath_time_constant_s)


def fly(cfg: Any, frame: LocalFrame, terrain_height, flight: FlightConfig | None = None) -> TrueTrajectory:
    """The true trajectory of a scenario ``cfg``: its flight plan's lines, or the corridor passes
    without one; ``flight`` replaces ``cfg.flight`` (another sortie's take-off time)."""
    flight = cfg.flight if flight is None else flight
    if cfg.plan is None:
        return simulate_flight(flight, frame, cfg.scene.length_m, terrain_height)
    crs = OutputCRS(cfg.output_epsg)
    h0 = cfg.reference_point.h_m

    def to_w(en: np.ndarray) -> np.ndarray:
        return crs.to_w(frame, np.column_stack([en, np.full(len(en), h0)]))

    lines = plan_lines(cfg.plan, length_m=cfg.scene.length_m, width_m=cfg.scene.width_m,
                       swath_m=swath_width_m(flight.altitude_agl_m, cfg.scanner.field_of_view_deg), to_w=to_w,
                       axis_m=cfg.scene.axis_m)
    return simulate_flight(flight, frame, cfg.scene.length_m, terrain_height, lines,
                           bend_radius_m=cfg.plan.bend_radius_m, transit_m=cfg.plan.transit_m)


@dataclass(frozen=True)
class Sortie:
    """One sortie as flown: its number (1, 2, ...), true trajectory, IMU and GNSS, the strips
    ``(strip_id, t_start, t_end)`` (s from its own epoch), and its outages."""

    number: int
    traj: TrueTrajectory
    imu: SimulatedImu
    gnss: SimulatedGnss
    strips: tuple[tuple[int, float, float], ...]
    outages: tuple[tuple[float, float], ...]

    def name(self, single: bool, stem: str) -> str:
        return stem if single else f"flight_{self.number}"


def _sorties(cfg: Any, frame: LocalFrame, scene, seeds, rng_imu, rng_gnss) -> list[Sortie]:
    out, first_id = [], 0
    for k in range(cfg.sorties):
        flight = cfg.flight if k == 0 else cfg.flight.model_copy(
            update={"start_time_gps_s": cfg.flight.start_time_gps_s + k * cfg.sortie_interval_s})
        traj = fly(cfg, frame, scene.terrain_height, flight)
        r_imu = rng_imu if k == 0 else np.random.default_rng(seeds[6 + 2 * (k - 1)])
        r_gnss = rng_gnss if k == 0 else np.random.default_rng(seeds[7 + 2 * (k - 1)])
        imu = simulate_imu(traj, cfg.imu, 0.0, traj.duration_s, r_imu)
        gnss_cfg = cfg.gnss
        if cfg.jamming is not None:
            j = cfg.jamming
            jams = [(traj.passes[0][1] + j.after_first_pass_start_s, traj.passes[-1][2] - j.before_last_pass_end_s)]
            gnss_cfg = gnss_cfg.model_copy(update={"outages": [*gnss_cfg.outages, *jams]})
        gnss = simulate_gnss(traj, np.asarray(cfg.gnss_lever_arm_m), gnss_cfg, 0.0, traj.duration_s, r_gnss)
        strips = tuple((first_id + sid, a, b) for sid, a, b in traj.passes)
        first_id = max(s for s, _, _ in strips)
        out.append(Sortie(k + 1, traj, imu, gnss, strips, tuple(tuple(o) for o in gnss_cfg.outages)))
    if len({week_from_gps_seconds(s.traj.t0_gps + s.traj.duration_s)[0] for s in out} | {
            week_from_gps_seconds(out[0].traj.t0_gps)[0]}) > 1:
        raise ConfigError("the sorties span more than one GPS week", field="sortie_interval_s",
                          expected="all sorties within the week of the first (the truth SBET is in seconds of the week)",
                          found=f"{cfg.sorties} sorties {cfg.sortie_interval_s:.0f} s apart")
    return out


def _write_navigation(root: Path, sorties: list[Sortie], crs: OutputCRS, write_imr: bool) -> None:
    from georefine.sim import writers

    single = len(sorties) == 1
    for s in sorties:
        gnss_name, imu_name = s.name(single, "rover"), s.name(single, "imu")
        writers.write_gnss(root / "gnss" / f"{gnss_name}.pos", s.gnss)
        writers.write_imu(root / "imu" / f"{imu_name}.csv", s.imu,
                          imr_path=root / "imu" / f"{imu_name}.imr" if write_imr else None)
        sbet = root / "truth" / ("trajectory.sbet" if single else f"trajectory_flight_{s.number}.sbet")
        writers.write_truth_trajectory(sbet, s.traj, s.imu.time, crs.epsg)
        if not single:
            np.savez_compressed(root / "truth" / f"imu_errors_flight_{s.number}.npz", **_imu_errors(s.imu))
            np.savez_compressed(root / "truth" / f"gnss_errors_flight_{s.number}.npz", **_gnss_errors(s.gnss))
    if not single:  # all sorties in one truth, in time order (their records do not interleave)
        with open(root / "truth" / "trajectory.sbet", "wb") as fh:
            for s in sorties:
                fh.write((root / "truth" / f"trajectory_flight_{s.number}.sbet").read_bytes())
        (root / "truth" / "trajectory.sbet.json").write_bytes(
            (root / "truth" / "trajectory_flight_1.sbet.json").read_bytes())
    imu = [_imu_errors(s.imu) for s in sorties]
    np.savez_compressed(root / "truth" / "imu_errors.npz", **{k: np.concatenate([e[k] for e in imu]) if k in (
        "time_gps", "bias_gyro", "bias_acc", "temperature_c", "quantisation_gyro", "quantisation_acc") else imu[0][k]
        for k in imu[0]})
    gnss = [_gnss_errors(s.gnss) for s in sorties]
    np.savez_compressed(root / "truth" / "gnss_errors.npz", **{k: np.concatenate([e[k] for e in gnss]) for k in gnss[0]})


def _imu_errors(imu: SimulatedImu) -> dict[str, np.ndarray]:
    """The IMU truth (SI units). The vibration's rectification bias is in ``bias_acc``; the vibration itself is
    ``sqrt(2) vibration_g_rms g0 sin(2 pi f (t - t_first) + vibration_phase)`` of the scenario's ``imu`` settings
    (``t_first``: the sortie's first ``time_gps``; the file of all sorties has the first sortie's phases and
    coefficients, as for the other constants); the quantisation error is per sample (0: off)."""
    zero = np.zeros((imu.time.size, 3))
    return dict(time_gps=imu.t0_gps + imu.time, bias_gyro=imu.bias_gyro, bias_acc=imu.bias_acc,
                scale_gyro=imu.scale_gyro, scale_acc=imu.scale_acc,
                misalignment_gyro=imu.misalignment_gyro, misalignment_acc=imu.misalignment_acc,
                g_sensitivity=imu.g_sensitivity, temperature_gyro=imu.temperature_gyro,
                temperature_acc=imu.temperature_acc,
                temperature_c=imu.temperature_c if imu.temperature_c is not None else np.zeros(imu.time.size),
                quantisation_gyro=zero if imu.quantisation_gyro is None else imu.quantisation_gyro,
                quantisation_acc=zero if imu.quantisation_acc is None else imu.quantisation_acc,
                vibration_phase=imu.vibration_phase, vibration_rectification=imu.vibration_rectification,
                vibration_bias_acc=imu.vibration_bias_acc)


def _rms_or_zero(x: np.ndarray | None, unit: float) -> list[float]:
    """Per-axis rms of ``x`` (N, 3) times ``unit``; zeros where there is none."""
    return [0.0] * 3 if x is None else (np.sqrt(np.mean(x**2, axis=0)) * unit).tolist()


def _gnss_errors(gnss: SimulatedGnss) -> dict[str, np.ndarray]:
    """The GNSS truth: the total error, and the multipath and wrong fixes' offsets it holds (NED, m)."""
    zero = np.zeros_like(gnss.error_ned)
    return dict(time_gps=gnss.t0_gps + gnss.time, error_ned=gnss.error_ned,
                multipath_ned=zero if gnss.multipath_ned is None else gnss.multipath_ned,
                jump_ned=zero if gnss.jump_ned is None else gnss.jump_ned)


def _project_config(cfg: Any, sorties: list[Sortie], ext: str) -> ProjectConfig:
    single = len(sorties) == 1
    errors = ImuErrorSpec(**{k: v for k, v in cfg.imu.model_dump().items() if k in ImuErrorSpec.model_fields})
    strips = {s.number: [f"scans/strip_{sid}.{ext}" for sid, _, _ in s.strips] for s in sorties}
    flights = None if single else [
        ProjectFlight(id=s.number, gnss_files=[f"gnss/flight_{s.number}.pos"], imu_file=f"imu/flight_{s.number}.csv",
                      strips=strips[s.number]) for s in sorties]
    return ProjectConfig(
        name=cfg.name,
        crs=CrsConfig(output_epsg=cfg.output_epsg),
        gnss=GnssFileConfig(files=["gnss/rover.pos"] if single else [], lever_arm_m=cfg.gnss_lever_arm_m,
                            correlated_error=stated_gnss_error(cfg.gnss),
                            multipath=stated_gnss_multipath(cfg.gnss)),
        imu=ImuFileConfig(file="imu/imu.csv" if single else None, format="csv", rate_hz=cfg.imu.rate_hz,
                          errors=errors),
        scanner=ScannerFileConfig(
            files=strips[1] if single else [],
            lever_arm_m=cfg.scanner_lever_arm_m,
            boresight_deg=cfg.project_boresight_deg or cfg.boresight_deg,
            range_sigma_m=cfg.scanner.range_sigma_m,
            channels=[
                ChannelConfig(id=i, name=n, tilt_deg=tilt)
                for i, (n, tilt) in enumerate(zip(("nadir", "forward", "backward"), cfg.scanner.facet_tilt_deg))
            ],
        ),
        reference=ReferenceConfig(surfaces="reference/surfaces.csv"),
        photos=PhotosFileConfig() if cfg.photos is not None else None,
        flights=flights,
    )


def write_project(cfg: Any, root: Path, seed: int, write_imr: bool, progress: Progress,
                  on_navigation: Callable[[Path], None] | None, runner: TaskRunner) -> dict:
    """Fly ``cfg`` and write the project into ``root`` (an empty folder with the sub-folders made);
    returns the fields of :class:`~georefine.sim.scenarios.SimulationResult`."""
    from georefine.sim import writers

    timings: dict[str, float] = {}
    seeds = np.random.SeedSequence(seed).spawn(6 + 2 * (cfg.sorties - 1))
    rng_scene, rng_imu, rng_gnss, _, rng_survey, rng_photos = (np.random.default_rng(s) for s in seeds[:6])
    # The scan noise: one seed per strip and chunk below it (sim.scanner.chunk_seed).
    seed_scan = seeds[3]
    rp = cfg.reference_point
    frame = LocalFrame.from_degrees(rp.lat_deg, rp.lon_deg, rp.h_m)
    crs = OutputCRS(cfg.output_epsg)

    t = _time.perf_counter()
    progress("scene", 0, 1)
    scene = build_scene(cfg.scene, rng_scene)
    progress("scene", 1, 1)
    timings["scene"] = _time.perf_counter() - t

    t = _time.perf_counter()
    sorties = _sorties(cfg, frame, scene, seeds, rng_imu, rng_gnss)
    timings["flight and sensors"] = _time.perf_counter() - t

    t = _time.perf_counter()
    _write_navigation(root, sorties, crs, write_imr)
    writers.write_reference(root, scene.reference_surfaces, frame, crs, cfg.reference_survey_sigma_m, rng_survey)
    timings["write navigation files"] = _time.perf_counter() - t

    ext = "laz" if cfg.laz else "las"
    project = _project_config(cfg, sorties, ext)
    # Sensor configuration only: the processing options keep their documented defaults unless a
    # user writes them into project.yaml.
    exclude = {"processing"} | ({"photos"} if project.photos is None else set()) | (
        {"flights"} if project.flights is None else set())
    write_yaml(root / "project.yaml", project.model_dump(mode="json", exclude=exclude, exclude_none=False))
    if on_navigation is not None:  # the navigation part of the project is complete
        on_navigation(root)

    photo_summary = None
    if cfg.photos is not None:
        t = _time.perf_counter()
        photo_summary = write_photo_block(root, scene, cfg.photos, frame, crs, rng_photos, progress)
        timings["photos"] = _time.perf_counter() - t

    t = _time.perf_counter()
    p_b_s = np.asarray(cfg.scanner_lever_arm_m)
    R_b_s = boresight_matrix(cfg.boresight_deg)
    points: dict[int, int] = {}
    total = sum(t1 - t0 for s in sorties for _, t0, t1 in s.strips)
    done = 0.0
    for sortie in sorties:
        traj = sortie.traj
        for strip_id, t0, t1 in sortie.strips:
            # Chunks of at most ~400 k pulses (1 s up to 400 kHz, as before; 0.22 s at 1.8 MHz): the
            # memory of a chunk, not the pulse rate, bounds the simulation's memory.
            chunk_s = min(1.0, 400_000.0 / cfg.scanner.pulse_rate_hz)
            # Each task scans its chunk and makes its file records (the truth in the output CRS
            # included); this process only encodes them, in time order.
            records = scan(traj.pose, t0, t1, scene, cfg.scanner, p_b_s, R_b_s, chunk_seed(seed_scan, strip_id),
                           chunk_duration_s=chunk_s, runner=runner, finish=writers.strip_records,
                           finish_args=(strip_id, traj.t0_gps, frame, crs, cfg.scanner_time_offset_s))

            def tick(t_gps_end: float, _t0=traj.t0_gps + t0, _done=done) -> None:
                progress("scanning", _done + (t_gps_end - _t0), total)

            points[strip_id] = writers.write_strip(
                root / "scans" / f"strip_{strip_id}.{ext}", root / "truth" / f"strip_{strip_id}.{ext}", records, tick,
                crs)
            done += t1 - t0
    progress("scanning", total, total)  # the last chunk's end may fall a rounding short of the total
    timings["scanning"] = _time.perf_counter() - t

    first = sorties[0]
    t0_gps = first.traj.t0_gps

    def shifted(s: Sortie, a: float) -> float:
        return s.traj.t0_gps - t0_gps + a

    imu = first.imu
    truth = {
        "seed": seed,
        "t0_gps": t0_gps,
        "duration_s": shifted(sorties[-1], sorties[-1].traj.duration_s),
        "passes": [{"strip_id": sid, "t_start_s": shifted(s, a), "t_end_s": shifted(s, b)}
                   for s in sorties for sid, a, b in s.strips],
        "phases": [{"name": n, "t_start_s": shifted(s, a), "t_end_s": shifted(s, b)}
                   for s in sorties for n, a, b in s.traj.phases],
        "imu_scale_gyro_ppm": (imu.scale_gyro * 1e6).tolist(),
        "imu_scale_acc_ppm": (imu.scale_acc * 1e6).tolist(),
        "imu_bias_gyro_start_deg_per_h": np.degrees(imu.bias_gyro[0] * 3600).tolist(),
        "imu_bias_acc_start_ug": (imu.bias_acc[0] / 9.80665e-6).tolist(),
        "imu_misalignment_gyro_mrad": (imu.misalignment_gyro * 1e3).tolist(),
        "imu_misalignment_acc_mrad": (imu.misalignment_acc * 1e3).tolist(),
        "imu_g_sensitivity_deg_per_h_per_g": np.degrees(imu.g_sensitivity * 3600 * 9.80665).tolist(),
        "imu_temperature_gyro_deg_per_h_per_c": np.degrees(imu.temperature_gyro * 3600).tolist(),
        "imu_temperature_acc_ug_per_c": (imu.temperature_acc / 9.80665e-6).tolist(),
        "imu_vibration_rectification_ug_per_g2": (imu.vibration_rectification * 9.80665 / 1e-6).tolist(),
        "imu_vibration_bias_acc_ug": (imu.vibration_bias_acc / 9.80665e-6).tolist(),
        "imu_vibration_phase_rad": imu.vibration_phase.tolist(),
        "imu_quantisation_rms_gyro_deg_per_h": _rms_or_zero(imu.quantisation_gyro, 3600 * 180 / np.pi),
        "imu_quantisation_rms_acc_ug": _rms_or_zero(imu.quantisation_acc, 1 / 9.80665e-6),
        "points_per_strip": points,
        "scenario": cfg.model_dump(mode="json"),
    }
    if len(sorties) > 1:
        truth["flights"] = [{
            "id": s.number, "t0_gps": s.traj.t0_gps, "duration_s": s.traj.duration_s,
            "strips": [sid for sid, _, _ in s.strips],
            "imu_scale_gyro_ppm": (s.imu.scale_gyro * 1e6).tolist(),
            "imu_scale_acc_ppm": (s.imu.scale_acc * 1e6).tolist(),
            "imu_bias_gyro_start_deg_per_h": np.degrees(s.imu.bias_gyro[0] * 3600).tolist(),
            "imu_bias_acc_start_ug": (s.imu.bias_acc[0] / 9.80665e-6).tolist(),
        } for s in sorties]
    if photo_summary is not None:
        truth["photos"] = photo_summary
    outages = [[shifted(s, a), shifted(s, b)] for s in sorties for a, b in s.outages]
    if outages:
        truth["gnss_outages_s"] = outages
    write_yaml(root / "truth" / "scenario.yaml", truth)
    return dict(
        scenario=cfg, seed=seed, duration_s=truth["duration_s"], points_per_strip=points,
        n_imu=sum(s.imu.time.size for s in sorties), n_gnss=sum(s.gnss.time.size for s in sorties), timings_s=timings,
    )
