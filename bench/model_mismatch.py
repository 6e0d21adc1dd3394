"""Sensor errors beyond the basic model, at several magnitudes: what the G/I and the G/I/L make of them.

    python bench/model_mismatch.py WORK [--scenario corridor] [--seed 42]
                                   [--kinds imu-misalignment gnss-float] [--magnitudes M ...] [--report-only]

Per kind and magnitude the scenario is simulated once with the error (the truth unchanged, its own
files say what was applied), then ``georefine run --no-points`` runs on it twice:

* ``stated``: ``project.yaml`` as the simulator writes it, stating the error's datasheet figure, so
  the adjustments estimate what they can of it;
* ``unstated``: the same data with the figure taken out of ``project.yaml``: what a user who does not
  know the error gets.

A ``clean`` case (the scenario without the error, same seed) is the reference. Kinds:

| kind | simulated (``--set``) | stated in ``project.yaml`` / unstated |
|---|---|---|
| ``imu-misalignment`` | ``imu.gyro_misalignment_mrad``, ``imu.acc_misalignment_mrad`` = M mrad (each off-diagonal element, 1 sigma) | ``imu.errors.*_misalignment_mrad`` / removed |
| ``lidar-range`` | ``scanner.range_offset_m`` = M m and ``scanner.range_scale_ppm`` = 100 | ``processing.lidar.estimate_range_calibration: true`` / as simulated (not estimated) |
| ``imu-thermal`` | ``imu.temperature_change_c`` = M deg C over 900 s with bias coefficients of 0.1 deg/h and 10 ug per deg C and a gyro g-sensitivity of 2 deg/h/g (1 sigma) | ``imu.errors``' figures (the coefficients estimated against the temperature the IMU file logs) / removed (not modelled) |
| ``gnss-jump`` | a wrong fix of 60 s from 20 s into the first pass (``gnss.ambiguity_jumps``; Q=1, fixed sigmas), its offset drawn with M m horizontal and 1.5 M m up | searched for (``gnss.float_offset.detect_jumps``, the default) / not searched |
| ``gnss-multipath`` | ``gnss.multipath_sigma_horizontal_m`` = M m, ``_up_m`` = 2 M m (20 s correlation) | ``gnss.multipath`` (the simulated figures, estimated beside the correlated error) / removed (not modelled) |
| ``lidar-channel`` | ``scanner.channel_tilt_error_mdeg`` = (0, M, -M), ``channel_scan_angle_error_mdeg`` = (0, -M/2, M) | ``processing.lidar.estimate_channel_angles: true`` / as simulated (not estimated) |
| ``gnss-outage`` | no GNSS for M s from 20 s into the first pass (``gnss.outages``): not an error of the model, a direction less observed | one case |
| ``lidar-incidence`` | ``scanner.range_incidence_bias_m`` = M m: every range B (1/cos(theta) - 1) long at incidence theta | one case: not modelled (the calibration check estimates it) |
| ``lidar-walk`` | ``scanner.range_walk_m`` = M m: every range W ln(I_ref / I) long (a detector's range walk with the return's strength) | one case: not modelled |
| ``lidar-encoder`` | ``scanner.encoder_error_mdeg`` = (M, M/2) at phases (30, 60) deg: the scan-angle encoder's periodic error | ``processing.lidar.estimate_encoder_error`` and ``estimate_boresight: true`` / as simulated (not estimated) |
| ``imu-vibration`` | 0.5 g rms of 70 Hz vibration (``imu.vibration_g_rms``), rectified with M ug/g^2 (``imu.acc_vibration_rectification_ug_per_g2``) | one case: not modelled |
| ``imu-quantisation`` | M times an LN-200's output steps (1.9 urad, 0.061 mm/s: ``imu.*_quantisation_*``) | one case: not modelled |
| ``imu-unit`` | the ``stim300`` unit preset (``mems`` with the datasheet's misalignment, g-sensitivity and temperature coefficients; ``sim/imu.py``), warming by M deg C over 900 s | ``imu.errors`` as the preset states them (misalignment and temperature coefficients estimated) / those figures removed |
| ``gnss-float`` | a 60 s float segment from 20 s into the first pass (``gnss.float_segments``; Q=2, 5/5/10 cm stated), its offset drawn with M m horizontal and 1.5 M m up (1 sigma) | ``gnss.float_offset`` (an offset per segment) / ``null`` (taken as fixes) |

Printed per case and solution (G/I, G/I/L), each pass compared with the truth (1 s inset;
``truth_pass_accuracy``): roll, pitch and yaw RMSE (the larger of the passes), the RMS of error /
stated sigma (range over the passes) and the largest share of epochs beyond three sigma; the 3-D
position RMSE and its RMS of error / sigma (and in the window of the float segment, wrong fix or outage, where
there is one: "window"); where
the solution calibrated something (the IMU misalignment, the range calibration, the channel angles), the RMS and
the largest |estimate - truth| / sigma over its elements; and the run's warnings (the strip
baseline's misfit warnings, which every corridor run gives, only counted). Checks (the acceptance of the issue that asked for this): G/I/L within 1.3x the clean
run's roll, pitch and yaw and no worse than the G/I by more than 10 % + 0.3 mdeg; error/sigma within
0.5-2 with at most 1 % beyond three sigma; else a warning that names the error.

Results are kept per case in ``WORK/results/CASE.json``; a rerun skips cases done.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from georefine.config import boresight_matrix
from georefine.evaluation.trajectory_files import compare_sbet_files, truth_pass_accuracy
from georefine.geometry.rotation import log_so3
from georefine.io.trajectory import read_sbet_companion, read_smrmsg, smrmsg_path
from georefine.sim.scanner import ScannerConfig, encoder_legendre_terms
from georefine.sim.scenarios import simulate_project


def _first_pass(clean: Path) -> tuple[float, float]:
    """Start and end (s from the epoch) of the first pass of the clean project (the same flight)."""
    p = yaml.safe_load((clean / "truth" / "scenario.yaml").read_text())["passes"][0]
    return p["t_start_s"], p["t_end_s"]


def _float_overrides(m: float, clean: Path) -> list[str]:
    a = _first_pass(clean)[0] + 20.0
    return [f"gnss.float_segments=[[{a}, {a + 60.0}]]", f"gnss.float_offset_sigma_horizontal_m={m}",
            f"gnss.float_offset_sigma_up_m={1.5 * m}"]


def _jump_overrides(m: float, clean: Path) -> list[str]:
    a = _first_pass(clean)[0] + 20.0
    return [f"gnss.ambiguity_jumps=[[{a}, {a + 60.0}]]", f"gnss.jump_sigma_horizontal_m={m}",
            f"gnss.jump_sigma_up_m={1.5 * m}"]


def _channel_overrides(m: float, clean: Path) -> list[str]:
    return [f"scanner.channel_tilt_error_mdeg=[0.0, {m}, {-m}]", f"scanner.channel_scan_angle_error_mdeg=[0.0, {-m / 2}, {m}]"]


def _without_jump_search(cfg: dict) -> None:
    cfg["gnss"].setdefault("float_offset", {})["detect_jumps"] = False


def _without_misalignment(cfg: dict) -> None:
    for key in ("gyro_misalignment_mrad", "acc_misalignment_mrad"):
        cfg["imu"]["errors"].pop(key, None)


THERMAL = {"gyro_g_sensitivity_deg_per_h_per_g": 2.0, "temperature_time_constant_s": 900.0,
           "gyro_temperature_deg_per_h_per_c": 0.1, "acc_temperature_ug_per_c": 10.0}
"""The ``imu-thermal`` kind's figures besides the temperature change M (deg C): a MEMS gyro's g-sensitivity and
residual temperature coefficients of the biases."""


def _without_thermal(cfg: dict) -> None:
    for key in (*THERMAL, "temperature_change_c"):
        cfg["imu"]["errors"].pop(key, None)


def _without_multipath(cfg: dict) -> None:
    cfg["gnss"].pop("multipath", None)


def _float_as_fix(cfg: dict) -> None:
    cfg["gnss"]["float_offset"] = None


KINDS = {  # kind: (simulation overrides for magnitude M given the clean project, project.yaml unstated)
    "imu-misalignment": (lambda m, clean: [f"imu.gyro_misalignment_mrad={m}", f"imu.acc_misalignment_mrad={m}"],
                         _without_misalignment),
    "gnss-float": (_float_overrides, _float_as_fix),
    "lidar-range": (lambda m, clean: [f"scanner.range_offset_m={m}", "scanner.range_scale_ppm=100"], lambda cfg: None),
    "imu-thermal": (lambda m, clean: [f"imu.temperature_change_c={m}"] + [f"imu.{k}={v}" for k, v in THERMAL.items()],
                    _without_thermal),
    "gnss-jump": (_jump_overrides, _without_jump_search),
    "gnss-multipath": (lambda m, clean: [f"gnss.multipath_sigma_horizontal_m={m}", f"gnss.multipath_sigma_up_m={2 * m}"],
                       _without_multipath),
    "lidar-channel": (_channel_overrides, lambda cfg: None),
    "gnss-outage": (lambda m, clean: [f"gnss.outages=[[{_first_pass(clean)[0] + 20.0}, {_first_pass(clean)[0] + 20.0 + m}]]"],
                    None),
    "lidar-incidence": (lambda m, clean: [f"scanner.range_incidence_bias_m={m}"], None),
    "lidar-walk": (lambda m, clean: [f"scanner.range_walk_m={m}"], None),
    "lidar-encoder": (lambda m, clean: [f"scanner.encoder_error_mdeg=[{m}, {m / 2}]",
                                        "scanner.encoder_error_phase_deg=[30.0, 60.0]"], lambda cfg: None),
    "imu-vibration": (lambda m, clean: ["imu.vibration_g_rms=0.5", f"imu.acc_vibration_rectification_ug_per_g2={m}"],
                      None),
    "imu-quantisation": (lambda m, clean: [f"imu.gyro_quantisation_urad={1.9 * m}",
                                           f"imu.acc_quantisation_mm_per_s={0.061 * m}"], None),
    "imu-unit": (lambda m, clean: ["imu=stim300", f"imu.temperature_change_c={m}"],
                 lambda cfg: (_without_misalignment(cfg), _without_thermal(cfg))),
}
STATE = {  # how the stated run's project.yaml differs from the simulated one, where it does
    "lidar-range": lambda cfg: cfg.setdefault("processing", {}).setdefault("lidar", {}).update(
        estimate_range_calibration=True),
    "lidar-channel": lambda cfg: cfg.setdefault("processing", {}).setdefault("lidar", {}).update(
        estimate_channel_angles=True),
    "lidar-encoder": lambda cfg: cfg.setdefault("processing", {}).setdefault("lidar", {}).update(
        estimate_encoder_error=True, estimate_boresight=True),
}
DEFAULT_MAGNITUDES = {"imu-misalignment": [0.25, 0.5, 1.0], "gnss-float": [0.1, 0.2, 0.4], "lidar-range": [0.01, 0.03],
                      "imu-thermal": [10.0, 20.0], "gnss-jump": [0.1, 0.2], "gnss-multipath": [0.01, 0.02],
                      "lidar-channel": [20.0, 50.0], "gnss-outage": [60.0], "lidar-incidence": [0.05],
                      "lidar-walk": [0.01], "lidar-encoder": [20.0], "imu-vibration": [100.0], "imu-quantisation": [1.0],
                      "imu-unit": [10.0]}


def _unstate(project: Path, out: Path, unstate) -> Path:
    """A copy of ``project`` (data linked) whose ``project.yaml`` ``unstate`` edited."""
    out.mkdir(parents=True)
    for item in project.iterdir():
        if item.name != "project.yaml":
            (out / item.name).symlink_to(item.resolve(), target_is_directory=item.is_dir())
    cfg = yaml.safe_load((project / "project.yaml").read_text())
    unstate(cfg)
    (out / "project.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return out


def _position(sbet: Path, project: Path, window: tuple[float, float] | None = None) -> tuple[float, float]:
    """3-D position RMSE (m) over the whole solution (or the ``window``, s from the epoch) and the RMS of
    error / stated sigma per axis, pooled."""
    cmp = compare_sbet_files(sbet, project / "truth" / "trajectory.sbet")
    sig = read_smrmsg(smrmsg_path(sbet), gps_week=read_sbet_companion(sbet).gps_week)
    t = cmp.t0_gps + cmp.time
    s = np.column_stack([np.interp(t, sig.time_gps, sig.sigma_ned_m[:, i]) for i in range(3)])
    d = cmp.d_ned_m
    if window is not None:
        rel = t - yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["t0_gps"]
        inside = (rel >= window[0]) & (rel <= window[1])
        d, s = d[inside], s[inside]
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1)))), float(np.sqrt(np.mean((d / s) ** 2)))


def _calibration_z(solution: Path, project: Path) -> list[float] | None:
    """RMS and largest |estimate - truth| / sigma of what the solution calibrated: the IMU misalignment's twelve
    elements, the biases' six temperature coefficients, the scanner's range offset and scale, the channels' angles (against channel 0's), the encoder error's
    Legendre terms (the truth's least-squares terms, :func:`~georefine.sim.scanner.encoder_legendre_terms`) and the
    boresight's roll (the stated plus the encoder error's mean); None: none."""
    report = json.loads((solution / "adjustment.json").read_text())
    scenario = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["scenario"]["scanner"]
    z = []
    e = report.get("imu_errors") or {}
    if e.get("acc_misalignment_mrad"):
        truth = np.load(project / "truth" / "imu_errors.npz")
        off = ~np.eye(3, dtype=bool)
        z += [(np.asarray(e[f"{t}_misalignment_mrad"]) - truth[f"misalignment_{t}"][off] * 1e3)
              / np.asarray(e[f"{t}_misalignment_sigma_mrad"]) for t in ("acc", "gyro")]
    if e.get("gyro_temperature_deg_per_h_per_c") is not None:  # the biases' temperature coefficients
        truth = np.load(project / "truth" / "imu_errors.npz")
        z += [(np.asarray(e["gyro_temperature_deg_per_h_per_c"]) - truth["temperature_gyro"] / (np.pi / 180 / 3600))
              / np.asarray(e["gyro_temperature_sigma_deg_per_h_per_c"]),
              (np.asarray(e["acc_temperature_ug_per_c"]) - truth["temperature_acc"] / 9.80665e-6)
              / np.asarray(e["acc_temperature_sigma_ug_per_c"])]
    rc = report.get("range_calibration")
    if rc:
        z.append(np.array([(rc["offset_m"] - scenario["range_offset_m"]) / rc["offset_sigma_m"],
                           (rc["scale_ppm"] - scenario["range_scale_ppm"]) / rc["scale_sigma_ppm"]]))
    ch = report.get("channel_angles")
    if ch:
        for key, true in (("tilt", "channel_tilt_error_mdeg"), ("scan_angle", "channel_scan_angle_error_mdeg")):
            t = np.asarray(scenario[true], dtype=float)
            z.append((np.asarray(ch[f"{key}_mdeg"])[1:] - (t[1:] - t[0])) / np.asarray(ch[f"{key}_sigma_mdeg"])[1:])
    enc = report.get("encoder_error")
    if enc:
        mean, terms, _ = encoder_legendre_terms(ScannerConfig(**{k: scenario[k] for k in (
            "encoder_error_mdeg", "encoder_error_phase_deg")}))
        z.append((np.asarray(enc["terms_mdeg"]) - np.degrees(terms) * 1e3) / np.asarray(enc["terms_sigma_mdeg"]))
        if report.get("boresight_deg") is not None:  # the scan angle turns about -x_s: a roll of -mean
            true = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["scenario"]["boresight_deg"]
            d = log_so3(boresight_matrix(tuple(true)).T @ boresight_matrix(tuple(report["boresight_deg"])))
            z.append(np.array([(np.degrees(d[0]) * 1e3 + np.degrees(mean) * 1e3) / report["boresight_sigma_mdeg"][0]]))
    if not z:
        return None
    z = np.concatenate(z)
    return [float(np.sqrt(np.mean(z**2))), float(np.max(np.abs(z)))]


def evaluate(run: Path, project: Path, truth: Path) -> dict:
    """The run's solutions against the truth of ``truth`` (the simulated project)."""
    passes = [p["strip_id"] for p in yaml.safe_load((truth / "truth" / "scenario.yaml").read_text())["passes"]]
    out: dict = {}
    for sol, folder in (("G/I", "gi"), ("G/I/L", "gil")):
        sbet = run / folder / "trajectory.sbet"
        acc = [truth_pass_accuracy(sbet, truth, s) for s in passes]
        pos, pos_z = _position(sbet, truth)
        gnss = yaml.safe_load((truth / "truth" / "scenario.yaml").read_text())["scenario"]["gnss"]
        segments = gnss.get("float_segments") or gnss.get("ambiguity_jumps") or gnss.get("outages") or []
        window = _position(sbet, truth, tuple(segments[0])) if segments else None
        out[sol] = {"rmse_mdeg": np.max([a.rmse_mdeg for a in acc], axis=0).tolist(),
                    "z_min": np.min([a.z_rms for a in acc], axis=0).tolist(),
                    "z_max": np.max([a.z_rms for a in acc], axis=0).tolist(),
                    "beyond_3_sigma": np.max([a.beyond_3_sigma for a in acc], axis=0).tolist(),
                    "position_rmse_m": pos, "position_z": pos_z, "float_window": window,
                    "calibration_z": _calibration_z(run / folder, truth)}
    log = (run / "georefine.log").read_text().splitlines()
    out["warnings"] = [line.split("WARNING", 1)[1].strip() for line in log if " WARNING " in line]
    return out


def run_case(work: Path, name: str, overrides, unstate, scenario: str, seed: int) -> dict:
    """One case: simulated (once per kind and magnitude), ``project.yaml`` edited by ``unstate`` where given,
    run, evaluated; kept in ``WORK/results``."""
    results = work / "results" / f"{name}.json"
    if results.is_file():
        return json.loads(results.read_text())
    sim_name = name.removesuffix("-unstated").removesuffix("-stated")
    project = work / sim_name
    if not project.is_dir():
        t = time.perf_counter()
        simulate_project(scenario, project, seed=seed, overrides=overrides(work / "clean") if overrides else [])
        print(f"  simulated {sim_name} in {time.perf_counter() - t:.0f} s", flush=True)
    if unstate is not None:
        shutil.rmtree(work / f"{name}-project", ignore_errors=True)  # a case run again edits a fresh copy
    target = project if unstate is None else _unstate(project, work / f"{name}-project", unstate)
    run = work / f"{name}-run"
    shutil.rmtree(run, ignore_errors=True)
    t = time.perf_counter()
    proc = subprocess.run(["georefine", "run", str(target), "--out", str(run), "--no-points"],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{name}: georefine run failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    out = {"case": name, "seconds": time.perf_counter() - t, **evaluate(run, target, project)}
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps(out, indent=1))
    return out


def _fmt(v, digits=2) -> str:
    return "/".join(f"{x:.{digits}f}" for x in v)


def report(rows: list[dict]) -> None:
    clean = next((r for r in rows if r["case"] == "clean"), None)
    print("| case | solution | roll/pitch/yaw RMSE (mdeg) | error/sigma roll / pitch / yaw (passes) | > 3 sigma | position (cm), error/sigma "
          "| calibration z RMS, max | checks | warnings |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        for sol in ("G/I", "G/I/L"):
            s = r[sol]
            checks = []
            if sol == "G/I/L":
                gi = np.asarray(r["G/I"]["rmse_mdeg"])
                rm = np.asarray(s["rmse_mdeg"])
                if clean is not None and r is not clean:
                    ratio = rm / np.asarray(clean["G/I/L"]["rmse_mdeg"])
                    checks.append(("ok" if np.all(ratio <= 1.3) else "FAIL") + f" x clean {_fmt(ratio)}")
                checks.append("ok vs G/I" if np.all(rm <= 1.1 * gi + 0.3) else "FAIL vs G/I")
            z_ok = np.all((np.asarray(s["z_min"]) >= 0.5) & (np.asarray(s["z_max"]) <= 2.0))
            checks.append("sigma ok" if z_ok and max(s["beyond_3_sigma"]) <= 0.01 else "sigma FAIL")
            z = " / ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in zip(s["z_min"], s["z_max"]))
            cz = s.get("calibration_z", s.get("misalignment_z"))  # results kept by an earlier version name it so
            mz = "–" if cz is None else _fmt(cz)
            # The strip baseline's misfit warnings come with every corridor run, clean too: counted apart.
            warn = [x for x in r["warnings"] if "strip_adjustment" not in x]
            baseline = len(r["warnings"]) - len(warn)
            w = ""
            if sol == "G/I/L":
                w = "; ".join(x.split(": ", 1)[-1][:110] for x in warn) or "none"
                w += f" (+{baseline} strip baseline)" if baseline else ""
            pos = f"{100 * s['position_rmse_m']:.1f}, {s['position_z']:.2f}"
            if s.get("float_window"):
                pos += f"; window {100 * s['float_window'][0]:.1f}, {s['float_window'][1]:.2f}"
            print(f"| {r['case']} | {sol} | {_fmt(s['rmse_mdeg'])} | {z} | {_fmt(s['beyond_3_sigma'], 3)} | "
                  f"{pos} | {mz} | {'; '.join(checks)} | {w} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--scenario", default="corridor")
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(KINDS))
    ap.add_argument("--magnitudes", nargs="+", type=float, default=None,
                    help="of every kind asked for (default: imu-misalignment 0.25 0.5 1.0 mrad, gnss-float 0.1 0.2 0.4 m)")
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    cases = [("clean", None, None)]
    for kind in args.kinds:
        make, unstate = KINDS[kind]
        for m in args.magnitudes or DEFAULT_MAGNITUDES[kind]:
            for unstated in (False, True) if unstate is not None else (False,):
                edit = (unstate if unstated else STATE.get(kind))
                cases.append((f"{kind}-{m:g}-{'unstated' if unstated else 'stated'}",
                              lambda clean, make=make, m=m: make(m, clean), edit))
    rows = []
    for name, overrides, unstate in cases:
        kept = work / "results" / f"{name}.json"
        if args.report_only:
            if kept.is_file():
                rows.append(json.loads(kept.read_text()))
            continue
        print(f"{name} ...", flush=True)
        rows.append(run_case(work, name, overrides, unstate, args.scenario, args.seed))
        print(f"  {rows[-1]['seconds']:.0f} s", flush=True)
    report(rows)


if __name__ == "__main__":
    sys.exit(main())
