"""Trajectory evaluation with files: SBET inputs on either time scale, JSON and plot outputs.

:func:`compare_sbet_files` reads two SBETs, settles their time scale (see the conventions in
:mod:`georefine.evaluation.trajectory`) and compares them; :func:`write_trajectory_evaluation`
writes the comparison as JSON and the Fig. 9-style plots. The CLI only calls these two.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.evaluation.trajectory import TrajectoryComparison, compare_trajectories
from georefine.io.files import (
    SECONDS_PER_WEEK,
    PathLike,
    atomic_output,
    make_output_folder,
    week_from_gps_seconds,
)
from georefine.io.trajectory import SBET_RECORD_SIZE, read_sbet, read_sbet_companion, sbet_companion_path
from georefine.trajectory.sampled import interp_columns

_log = logging.getLogger(__name__)

def _first_time(path: Path) -> float | None:
    """First SBET time field, or None if the file cannot hold one (read_sbet then says why)."""
    try:
        if path.stat().st_size < SBET_RECORD_SIZE:
            return None
        return float(np.fromfile(path, dtype="<f8", count=1)[0])
    except OSError:
        return None


def _window_on_scale(window: tuple[float, float], *, week: int | None) -> tuple[float, float]:
    """Bring a window to the data's scale: seconds of week (< 604800) and absolute GPS seconds."""
    out = []
    for v in (float(window[0]), float(window[1])):
        if week is None:  # data are seconds of week
            out.append(v if v < SECONDS_PER_WEEK else float(week_from_gps_seconds(v)[1]))
        else:
            out.append(v + week * SECONDS_PER_WEEK if v < SECONDS_PER_WEEK else v)
    return out[0], out[1]


def compare_sbet_files(
    estimate_path: PathLike,
    reference_path: PathLike,
    *,
    gps_week: int | None = None,
    time_window: tuple[float, float] | None = None,
    max_time_offset_s: float = 1e-4,
    max_gap_s: float | None = None,
) -> TrajectoryComparison:
    """Read two SBET files and compare them (:func:`compare_trajectories`).

    Parameters
    ----------
    estimate_path, reference_path
        SBET files (:mod:`georefine.io.trajectory`).
    gps_week
        GPS week of files whose times are seconds of week. Without it, a seconds-of-week
        file takes the week of its companion file (``<name>.json``, which Georefine writes
        beside its SBETs) or, without one, is assumed to be in the same week as the other
        file (module docstring).
    time_window
        ``(start, end)``: values below 604800 are seconds of week, others GPS seconds; both
        are brought to the data's scale (with the GPS week of the later start of the two
        trajectories).

    Raises
    ------
    InputError
        From :func:`~georefine.io.trajectory.read_sbet` (file, record, field) and
        :func:`compare_trajectories`.
    """
    paths = {"estimate": Path(estimate_path), "reference": Path(reference_path)}
    first = {k: _first_time(p) for k, p in paths.items()}
    for p, t in zip(paths.values(), first.values()):
        if t is None:  # missing, or shorter than one record: the reader says which
            read_sbet(p, gps_week=gps_week if gps_week is not None else 0)
    sow = {k: v is not None and v < SECONDS_PER_WEEK for k, v in first.items()}
    companion = {k: read_sbet_companion(p) if sow[k] else None for k, p in paths.items()}
    notes: list[str] = []
    weeks: dict[str, int | None] = {}
    # seconds of week that no companion file resolves
    open_week = {k: sow[k] and companion[k] is None for k in paths}
    if gps_week is not None:
        weeks = {k: gps_week for k in paths}
        for k in paths:
            if sow[k]:
                notes.append(f"{k} ({paths[k].name}): seconds of week, GPS week {gps_week} given")
    else:
        for k, c in companion.items():
            if c is not None:
                notes.append(f"{k} ({paths[k].name}): seconds of week, GPS week {c.gps_week} from "
                             f"{sbet_companion_path(paths[k]).name}")
        if not any(open_week.values()):
            weeks = {k: None for k in paths}
        elif all(open_week.values()):
            weeks = {k: 0 for k in paths}
            notes.append("both files store seconds of week and no GPS week was given: both are assumed to be "
                         "in the same GPS week and compared as seconds of week")
        else:
            absolute = "reference" if open_week["estimate"] else "estimate"
            c = companion[absolute]
            start = first[absolute] + (c.gps_week * SECONDS_PER_WEEK if c is not None else 0.0)
            week = int(week_from_gps_seconds(start)[0])
            weeks = {k: week if open_week[k] else None for k in paths}
            relative = "estimate" if absolute == "reference" else "reference"
            notes.append(f"{relative} ({paths[relative].name}) stores seconds of week and no GPS week was given: "
                         f"assumed to be in GPS week {week} of the {absolute} ({paths[absolute].name})")
    data = {k: read_sbet(p, gps_week=weeks[k]) for k, p in paths.items()}
    same_week_assumed = gps_week is None and all(open_week.values())
    if time_window is not None:
        if same_week_assumed:
            week_of_data = None
        else:
            start = max(float(d.time_gps[0]) for d in data.values())
            week_of_data = int(week_from_gps_seconds(start)[0])
        time_window = _window_on_scale(time_window, week=week_of_data)
    result = compare_trajectories(data["estimate"], data["reference"], time_window=time_window,
                                  max_time_offset_s=max_time_offset_s, max_gap_s=max_gap_s)
    return dataclasses.replace(
        result, time_scale="seconds_of_week" if same_week_assumed else "gps", notes=tuple(notes),
        sources={k: str(p) for k, p in paths.items()},
    )


@dataclass(frozen=True)
class TrajectoryEvaluationFiles:
    """Files written by :func:`write_trajectory_evaluation`."""

    json: Path
    attitude_plot: Path
    position_plot: Path

    def all(self) -> tuple[Path, ...]:
        return (self.json, self.attitude_plot, self.position_plot)


def _output_folder(out_dir: Path, protect: tuple[PathLike, ...]) -> Path:
    """Create ``out_dir`` unless it is (or lies inside) a protected input; raise InputError."""
    out = Path(out_dir).resolve()
    for item in protect:
        p = Path(item).resolve()
        if out == p or p in out.parents:
            raise InputError("refusing to write into an input", path=out,
                             expected="an output folder that is not an input", found=f"input {p}")
    return make_output_folder(out)


def write_trajectory_evaluation(
    out_dir: PathLike,
    comparison: TrajectoryComparison,
    *,
    label: str | None = None,
    protect: tuple[PathLike, ...] = (),
) -> TrajectoryEvaluationFiles:
    """Write ``trajectory_comparison.json``, ``attitude_differences.png`` and ``position_differences.png``.

    The folder is created if needed; every file is written atomically.

    Parameters
    ----------
    label
        Legend label of the comparison in the plots (default: ``estimate - reference``
        from the sources, or ``"estimate - reference"``).
    protect
        Input files or folders that ``out_dir`` must not be or lie inside.

    Raises
    ------
    InputError
        If ``out_dir`` is a protected input or an existing file, or cannot be created.
    """
    from georefine.evaluation.plots import (
        plot_attitude_differences,
        plot_position_differences,
    )

    out = _output_folder(Path(out_dir), protect)
    if label is None:
        src = comparison.sources
        label = (f"{Path(src['estimate']).name} - {Path(src['reference']).name}"
                 if "estimate" in src and "reference" in src else "estimate - reference")
    json_path = out / "trajectory_comparison.json"
    with atomic_output(json_path, "w", protect=protect) as fh:
        json.dump(comparison.to_dict(), fh, indent=2, allow_nan=False)
        fh.write("\n")
    att = plot_attitude_differences({label: comparison}, out / "attitude_differences.png",
                                    title="Attitude differences (estimate - reference)", protect=protect)
    pos = plot_position_differences({label: comparison}, out / "position_differences.png",
                                    title="Position differences (estimate - reference)", protect=protect)
    return TrajectoryEvaluationFiles(json_path, att, pos)


def truth_pass_rmse(sbet: PathLike, project: PathLike, strip: int) -> np.ndarray:
    """Roll, pitch, yaw RMSE (mdeg) of ``sbet`` against a simulated project's truth during one pass.

    The pass's span comes from ``truth/scenario.yaml``, shortened by 1 s at both ends.
    """
    cmp = truth_pass_comparison(sbet, project, strip)
    return np.array([cmp.stats[f"{a}_rmse_mdeg"] for a in ("roll", "pitch", "yaw")])


def truth_pass_comparison(sbet: PathLike, project: PathLike, strip: int) -> TrajectoryComparison:
    """``sbet`` against a simulated project's truth during pass ``strip`` (``truth/scenario.yaml``, 1 s inset):
    the comparison's ``stats`` hold each angle's RMSE, mean, sigma and largest error (mdeg)."""
    import yaml

    project = Path(project)
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    p = next(p for p in truth["passes"] if p["strip_id"] == strip)
    t0 = truth["t0_gps"]
    return compare_sbet_files(Path(sbet), project / "truth" / "trajectory.sbet",
                              time_window=(t0 + p["t_start_s"] + 1.0, t0 + p["t_end_s"] - 1.0))


@dataclass(frozen=True)
class PassAccuracy:
    """Attitude errors of a solution against a simulated project's truth during one pass.

    ``rmse_mdeg``: roll, pitch, yaw RMSE (mdeg). ``z_rms``: RMS of error / stated sigma per
    angle (the solution's ``smrmsg`` interpolated to the truth's times; 1 for honest sigmas,
    above 1 optimistic, below 1 pessimistic); ``beyond_3_sigma``: the fraction of epochs whose
    error exceeds three stated sigmas (0.3 % for Gaussian errors); ``sigma_rms_mdeg``: the RMS of
    the stated sigma over the pass, the precision the solution claims. All NaN without an
    accuracy file.
    """

    strip: int
    rmse_mdeg: np.ndarray
    z_rms: np.ndarray
    beyond_3_sigma: np.ndarray
    epochs: int
    sigma_rms_mdeg: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))

    def to_dict(self) -> dict:
        """Plain JSON values per angle (NaN as None)."""
        def values(a: np.ndarray) -> dict:
            return {k: (float(v) if np.isfinite(v) else None) for k, v in zip(("roll", "pitch", "yaw"), a)}

        return {"strip": self.strip, "epochs": self.epochs, "rmse_mdeg": values(self.rmse_mdeg),
                "z_rms": values(self.z_rms), "beyond_3_sigma": values(self.beyond_3_sigma),
                "sigma_rms_mdeg": values(self.sigma_rms_mdeg)}


def truth_pass_accuracy(sbet: PathLike, project: PathLike, strip: int) -> PassAccuracy:
    """RMSE and sigma consistency of ``sbet`` against a simulated project's truth during one pass.

    The pass's span comes from ``truth/scenario.yaml``, shortened by 1 s at both ends (as
    :func:`truth_pass_rmse`); the sigmas from the accuracy file beside ``sbet``
    (:func:`~georefine.io.trajectory.smrmsg_path`), when there is one.
    """
    from georefine.io.trajectory import read_smrmsg, smrmsg_path

    sbet = Path(sbet)
    cmp = truth_pass_comparison(sbet, project, strip)
    rmse = np.array([cmp.stats[f"{a}_rmse_mdeg"] for a in ("roll", "pitch", "yaw")])
    z_rms = beyond = sigma_rms = np.full(3, np.nan)
    accuracy = smrmsg_path(sbet)
    if accuracy.is_file():
        companion = read_sbet_companion(sbet)
        sig = read_smrmsg(accuracy, gps_week=companion.gps_week if companion is not None else None)
        if cmp.time_scale == "gps":
            tq = cmp.t0_gps + cmp.time
            s = interp_columns(tq, sig.time_gps, sig.sigma_rph_rad)
            z = cmp.d_rph_rad / s
            z_rms = np.sqrt(np.mean(z * z, axis=0))
            beyond = np.mean(np.abs(z) > 3.0, axis=0)
            sigma_rms = np.degrees(np.sqrt(np.mean(s * s, axis=0))) * 1e3
    return PassAccuracy(strip, rmse, z_rms, beyond, len(cmp.time), sigma_rms)


def truth_gnss_time_offset(project: PathLike) -> float:
    """The LiDAR time offset (s) that a simulated project's GNSS errors alone make the passes show.

    The GNSS errors of the simulator are correlated in time, so each pass's trajectory sits a few
    millimetres off along its track; two passes flown in opposite directions then disagree as
    if the strips' times were off by ``-(e_1 + e_2) / (v_1 + v_2)`` (``e_i`` the mean along-track
    GNSS error of pass ``i``, ``v_i`` its speed). A time-offset estimate can be no closer to the
    truth than this; it uses the first two passes of ``truth/scenario.yaml`` and
    ``truth/gnss_errors.npz``.
    """
    import yaml

    project = Path(project)
    truth = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())
    errors = np.load(project / "truth" / "gnss_errors.npz")
    t0 = truth["t0_gps"]
    sbet = read_sbet(project / "truth" / "trajectory.sbet", gps_week=int(t0 // 604800))
    velocity = sbet.velocity_ned()
    along, speed = [], []
    for p in truth["passes"][:2]:
        a, b = t0 + p["t_start_s"], t0 + p["t_end_s"]
        e = errors["error_ned"][(errors["time_gps"] >= a) & (errors["time_gps"] <= b)].mean(axis=0)
        v = velocity[(sbet.time_gps >= a) & (sbet.time_gps <= b)].mean(axis=0)
        along.append(float(e[:2] @ v[:2]) / float(np.linalg.norm(v[:2])))
        speed.append(float(np.linalg.norm(v[:2])))
    return -sum(along) / sum(speed)
