"""The Cramér-Rao bound of a simulated project's G/I/L attitude (docs/ARCHITECTURE.md §4.4).

The precision the simulated sensors allow: the attitude covariance of a perfectly modelled
G/I/L adjustment, from its information at the true trajectory. The problem is the one the run's
last outer iteration solved (:func:`~georefine.workflows.gil.build_gil_problem`: the same GNSS
epochs, IMU windows, priors and matched planar features, read from the run's ``features/``),
linearised at the truth:

1. the knots are fitted to ``truth/trajectory.sbet`` (:func:`~georefine.trajectory.spline_fit.fit_spline`)
   and held there; the motion faster than them is rebuilt from the IMU and taken out of its
   windows as the run does it (up-sampling, docs/ARCHITECTURE.md §4.6);
2. what the truth does not hold -- the plane parameters, the GNSS error's knots (the simulator
   keeps its white part in the same series), the biases' knots, the boresight and the time offset
   -- is estimated with the trajectory held, by plain least squares (no robust loss), started
   at the simulated IMU errors and GNSS error;
3. the covariance is ``N^-1`` at that point, with the a-priori weights: no variance factor,
   no variance components, no robust weights (the bound of a model that fits its weights).

The group fits at that point (``sum w r^2 / n``) say how well the model describes the data when
the trajectory is right: near 1 where the weights are the sensors' (GNSS, IMU windows), below
or above where the model is conservative or misses something. The bound is the
attitude sigma's RMS over each pass's epochs (1 s inset, as
:func:`~georefine.evaluation.trajectory_files.truth_pass_accuracy`).

Two more figures per pass split a run's error into what these data allow and what the run adds:

4. **the model's optimum**: the adjustment the run makes (a-priori weights, the planes' robust
   loss) started at that point and iterated to its minimum (:data:`OPTIMUM_ITERATIONS` steps from
   the least damping); its attitude error against the truth at the knots inside the pass (RMS
   and mean of the wrapped roll/pitch/heading differences, as the runs' errors are measured).
   It is the error a converged adjustment of this model has on
   *these* data (this draw of the sensor noise): a run beyond it is held back by its solve, its
   starting point (the G/I and the features matched on it) or its up-sampling, while in a run
   near it that is large against the bound the model itself gives that error on these data:
   a large draw, or a defect of the model, which more draws tell apart (BENCHMARKS.md,
   Operating conditions). Without vibration the run and the optimum minimise the same function
   of the same data and should agree; where they do not, the run stopped short (one pass of
   the tactical unit, fast and high: pitch 1.20 mdeg against the optimum's 2.27; re-solved to a
   cost-change tolerance of 1e-6 the run reaches 2.19). Without the robust loss the planes' misfitting tail
   (the group fit) moves the optimum: on the tests' single pass its heading RMSE was 3.6 mdeg
   against the run's 1.7 and 1.6 of the bound;
5. **the G/I's bound and optimum**: the same, with the LiDAR taken out (the plane observations
   and the boresight's and time offset's priors; their blocks held), from the same point. With it
   a row where the G/I/L's error exceeds the G/I's can be read: the G/I's bound says what the
   G/I's error is worth, its optimum how lucky this draw was.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from georefine.adjustment.gnss_imu import GnssErrorEstimate, GnssImuResult, ImuErrorEstimate, trajectory_sigma
from georefine.adjustment.observations.bias import BiasGrid
from georefine.adjustment.observations.imu import OFF_DIAGONAL
from georefine.adjustment.observations.plane import PlaneObservation
from georefine.adjustment.problem import Problem
from georefine.adjustment.solver import SolverOptions
from georefine.adjustment.upsampling import rebuild_high_rate
from georefine.errors import InputError
from georefine.geometry.rotation import rph_from_R_n_b, wrap_angle
from georefine.io.trajectory import read_sbet
from georefine.lidar.object_files import read_objects
from georefine.lidar.planes import read_features
from georefine.trajectory.sampled import interp_columns, trajectory_from_sbet
from georefine.trajectory.spline_fit import fit_spline
from georefine.workflows.gil import build_gil_problem
from georefine.workflows.navigation import knot_grid
from georefine.workflows.opened import NavigationData, load_navigation
from georefine.workflows.time_offset import OFFSET_BLOCK, TimeOffsetStart

__all__ = ["CramerRaoBound", "PassBound", "SolutionBound", "cramer_rao_bound", "truth_start"]

ANGLES = ("roll", "pitch", "yaw")
NUISANCE_ITERATIONS = 10
"""Gauss-Newton steps for what the truth does not hold (step 2 of the module docstring): the
problem is nearly linear in it once the trajectory is right (two or three steps converge)."""

OPTIMUM_ITERATIONS = 40
"""Most steps from the truth to the model's optimum (4. of the module docstring). The robust
loss's reweighting converges linearly (a few per cent of the cost change per step are left)."""

OPTIMUM_TOLERANCE = 1e-5
"""Their cost-change test, as the G/I's (``processing.trajectory.function_tolerance``). On the
tests' single pass 1e-6 moved the optimum's RMSE by 0.02 mdeg at most (1 % of the bound), 1e-4
by 0.15 mdeg (pitch)."""

OPTIMUM_REUSE_FACTOR = 0
"""Their steps after the first are solved by conjugate gradients on the last factor
(``SolverOptions.reuse_factor_from``) whatever the problem's size: from the truth only the
robust weights change from step to step. On the tests' single pass the optimum is the same to
0.001 mdeg and the bound takes 81 s instead of 111 s."""

OPTIMUM_LAMBDA = 1e-15
"""The damping they start from (relative to ``diag(N)``): a damping of ``lambda diag(N)`` holds
back the directions whose curvature is far below the diagonal (a single pass's heading), which
are the ones this figure is for."""

BOUND_INTERVAL_S = 1.0
"""The bound's epochs are this far apart (s) over the whole flight: finer than the runs' products
(``covariance_interval_s``, ``max_covariance_knots``), since a pass's RMS should not rest on a
dozen epochs. Each costs three columns of ``N^-1`` (a look-up or three solves)."""


_NAN3 = np.full(3, np.nan)


def _angles(v: np.ndarray) -> dict[str, float]:
    return dict(zip(ANGLES, map(float, v)))


@dataclass(frozen=True)
class SolutionBound:
    """One solution's figures over one pass, roll / pitch / yaw (mdeg): ``sigma_rms_mdeg``, the RMS
    of the attitude sigma at the truth over the pass's covariance epochs; ``optimum_rmse_mdeg``
    and ``optimum_mean_mdeg``, the RMS and the mean over the pass's knots of the model's optimum's
    error (module docstring, 4.)."""

    sigma_rms_mdeg: np.ndarray
    optimum_rmse_mdeg: np.ndarray = field(default_factory=lambda: _NAN3.copy())
    optimum_mean_mdeg: np.ndarray = field(default_factory=lambda: _NAN3.copy())

    def to_dict(self) -> dict:
        return {"sigma_rms_mdeg": _angles(self.sigma_rms_mdeg), "optimum_rmse_mdeg": _angles(self.optimum_rmse_mdeg),
                "optimum_mean_mdeg": _angles(self.optimum_mean_mdeg)}


@dataclass(frozen=True)
class PassBound:
    """The figures of one pass (``epochs`` covariance epochs): ``gil`` those of the G/I/L, ``gi``
    those of the G/I (None when not computed)."""

    strip: int
    epochs: int
    gil: SolutionBound
    gi: SolutionBound | None = None

    @property
    def sigma_rms_mdeg(self) -> np.ndarray:
        """The G/I/L's bound (the RMS of its attitude sigma at the truth over the pass)."""
        return self.gil.sigma_rms_mdeg

    def to_dict(self) -> dict:
        out = {"strip": self.strip, "epochs": self.epochs, **self.gil.to_dict()}
        if self.gi is not None:
            out["gi"] = self.gi.to_dict()
        return out


@dataclass(frozen=True)
class CramerRaoBound:
    """:func:`cramer_rao_bound`'s result.

    ``passes``: the bound per pass; ``group_fit``: ``sum w r^2 / n`` of every observation group
    at the truth (the trajectory held, the rest estimated); ``plane_robust_sigma0``: the plane
    residuals' median-based sigma (``1.4826 MAD`` of the whitened distance and two slopes) there,
    which a heavy tail of misfitting features does not raise; ``features_used`` and
    ``objects_used``: the plane observations; ``unknowns`` and ``rows`` of the problem.
    """

    passes: tuple[PassBound, ...]
    group_fit: dict[str, float]
    plane_robust_sigma0: np.ndarray
    features_used: int
    objects_used: int
    unknowns: int
    rows: int

    def to_dict(self) -> dict:
        return {"passes": [p.to_dict() for p in self.passes], "group_fit": self.group_fit,
                "plane_robust_sigma0": dict(zip(("distance", "slope_1", "slope_2"), map(float, self.plane_robust_sigma0))),
                "features_used": self.features_used, "objects_used": self.objects_used,
                "unknowns": self.unknowns, "rows": self.rows}


def _truth(root: Path) -> dict:
    path = root / "truth" / "scenario.yaml"
    if not path.is_file():
        raise InputError("not a simulated project: no truth", path=str(path),
                         expected="truth/scenario.yaml, truth/trajectory.sbet, truth/imu_errors.npz, truth/gnss_errors.npz")
    return yaml.safe_load(path.read_text())


def truth_start(nav: NavigationData, root: Path) -> GnssImuResult:
    """The starting point at the truth: the knots fitted to the true trajectory, the simulated
    IMU errors at the bias knots, the simulated GNSS error (east, north, up) at its knots."""
    tcfg = nav.config.processing.trajectory
    sbet = read_sbet(root / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800))
    truth = trajectory_from_sbet(sbet, nav.frame, nav.t0_gps)
    grid = knot_grid(*nav.span, tcfg.knot_interval_s)  # the run's knots: over the GNSS and IMU overlap
    if truth.time[0] > grid.t_start or truth.time[-1] < grid.t_end:
        raise InputError("the true trajectory does not cover the navigation data", path=str(root / "truth" / "trajectory.sbet"),
                         expected=f"[{grid.t_start:.3f}, {grid.t_end:.3f}] s",
                         found=f"[{truth.time[0]:.3f}, {truth.time[-1]:.3f}] s")
    sel = (truth.time >= grid.t_start) & (truth.time <= grid.t_end)
    spline = fit_spline(grid, truth.time[sel], truth.p_w_b[sel], truth.R_w_b[sel],
                        None if truth.v_w_b is None else truth.v_w_b[sel], t0_gps=nav.t0_gps)
    imu = np.load(root / "truth" / "imu_errors.npz")
    bias_grid = BiasGrid.covering(grid.t_start, grid.t_end, tcfg.bias_knot_interval_s)
    tb = bias_grid.times + nav.t0_gps
    errors = ImuErrorEstimate(bias_grid, interp_columns(tb, imu["time_gps"], imu["bias_acc"]),
                              interp_columns(tb, imu["time_gps"], imu["bias_gyro"]),
                              np.asarray(imu["scale_acc"], dtype=float), np.asarray(imu["scale_gyro"], dtype=float),
                              **{f"{triad}_misalignment": np.asarray(imu[f"misalignment_{triad}"], dtype=float)[OFF_DIAGONAL]
                                 for triad in ("acc", "gyro") if f"misalignment_{triad}" in imu})
    gnss_error = None
    if nav.gnss.gnss_correlated is not None:
        g = np.load(root / "truth" / "gnss_errors.npz")
        egrid = BiasGrid.covering(grid.t_start, grid.t_end, tcfg.gnss_error_knot_interval_s)
        ned = interp_columns(egrid.times + nav.t0_gps, g["time_gps"], g["error_ned"])
        gnss_error = GnssErrorEstimate(egrid, np.column_stack([ned[:, 1], ned[:, 0], -ned[:, 2]]))
    # Only what build_gil_problem reads of a previous result: the spline, the errors and the motion
    # faster than the knots, rebuilt from the IMU as the run rebuilds it (§4.6), so that a
    # vibrating platform's windows are cleaned as the run's are.
    start = GnssImuResult(spline, errors, None, np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), gnss_error=gnss_error)
    if tcfg.upsampling:
        start = replace(start, high_rate=rebuild_high_rate(nav.gnss, start))
    return start


@dataclass(frozen=True)
class _Figures:
    """One solution over the whole flight: the attitude sigma (rad) at the truth at the covariance
    epochs ``times``, and its optimum's attitude error (rad) at the knots ``knot_times``."""

    times: np.ndarray
    sigma_rph: np.ndarray
    knot_times: np.ndarray
    error_rph: np.ndarray


def _figures(P: Problem, gil, nav: NavigationData, tcfg, truth_state: dict[str, np.ndarray],
             optimum: bool) -> _Figures:
    """The bound of ``P`` (solved with no step at the truth) and, with ``optimum``, its optimum
    (module docstring, 3.-4.; NaN without); ``P`` is left at its optimum."""
    blocks, grid = gil.built.blocks, gil.built.grid
    times, sigma_rph, _, _ = trajectory_sigma(P, blocks, grid, tcfg, nav.frame, gil.built.spline(), scale=1.0)
    if not optimum:
        return _Figures(times, sigma_rph, grid.knot_times, np.full((grid.n_knots, 3), np.nan))
    P.solve(SolverOptions(max_iterations=OPTIMUM_ITERATIONS, function_tolerance=OPTIMUM_TOLERANCE,
                          initial_lambda=OPTIMUM_LAMBDA, reuse_factor_from=OPTIMUM_REUSE_FACTOR))
    # As the runs' errors are measured (evaluation.trajectory): the difference of the NED roll,
    # pitch and heading of each trajectory at its own position, wrapped.
    rph_true, rph_opt = (rph_from_R_n_b(np.swapaxes(nav.frame.R_w_n_at(state[blocks.position]), 1, 2)
                                        @ state[blocks.attitude])
                         for state in (truth_state, {name: P.values(name) for name in P.blocks}))
    return _Figures(times, sigma_rph, grid.knot_times, wrap_angle(rph_opt - rph_true))


def _mdeg(x: np.ndarray) -> np.ndarray:
    return np.degrees(x) * 1e3


def _solution_bound(fig: _Figures, window: tuple[float, float]) -> SolutionBound | None:
    lo, hi = window
    at = (fig.times >= lo) & (fig.times <= hi)
    knots = (fig.knot_times >= lo) & (fig.knot_times <= hi)
    if not np.any(at) or not np.any(knots):
        return None
    e = fig.error_rph[knots]
    return SolutionBound(_mdeg(np.sqrt(np.mean(fig.sigma_rph[at] ** 2, axis=0))),
                         _mdeg(np.sqrt(np.mean(e ** 2, axis=0))), _mdeg(e.mean(axis=0)))


def _pass_bounds(nav: NavigationData, truth: dict, strips: set[int], gil: _Figures,
                 gi: _Figures | None) -> tuple[PassBound, ...]:
    out = []
    t0 = float(truth["t0_gps"]) - nav.t0_gps
    for p in truth["passes"]:
        if p["strip_id"] not in strips:
            continue
        window = (t0 + p["t_start_s"] + 1.0, t0 + p["t_end_s"] - 1.0)
        b = _solution_bound(gil, window)
        if b is None:
            continue
        epochs = int(np.count_nonzero((gil.times >= window[0]) & (gil.times <= window[1])))
        out.append(PassBound(int(p["strip_id"]), epochs, b, None if gi is None else _solution_bound(gi, window)))
    return tuple(out)


def cramer_rao_bound(project_dir: str | Path, run_dir: str | Path, optimum: bool = True,
                     with_gi: bool = True) -> CramerRaoBound:
    """The Cramér-Rao bound of the attitude of the G/I/L run ``run_dir`` of the simulated project
    ``project_dir`` (see the module docstring), for the passes whose strips the run matched; with
    ``optimum``, the model's optimum from the truth (its figures NaN without); with ``with_gi``,
    the same for the G/I. The optimum is the dearest part: on the tests' single pass the bound
    alone took about 17 s, the G/I/L's optimum about 30 s more (29 Cauchy-reweighted steps,
    those after the first by conjugate gradients, :data:`OPTIMUM_REUSE_FACTOR`; 38 steps and 64 s
    each factorised while the single pass still estimated the LiDAR time offset), the G/I's
    bound and optimum 11 s.

    Raises
    ------
    InputError
        Not a simulated project, a project with a delivered trajectory, or a run without
        matched features (``features/``) or outer iterations (``metrics.json``): not a G/I/L run.
    """
    root, run = Path(project_dir), Path(run_dir)
    truth = _truth(root)
    nav = load_navigation(root)
    if nav.prior is not None:
        raise InputError("the bound needs raw GNSS and IMU, not a delivered trajectory", path=str(root / "project.yaml"),
                         field="delivered_trajectory")
    folder = run / "features"
    if not (folder / "features.csv").is_file() or not (folder / "objects.csv").is_file():
        raise InputError("no matched features: the bound needs a G/I/L run", path=str(folder),
                         expected="features.csv and objects.csv (georefine run without --no-lidar)")
    metrics_path = run / "metrics.json"
    try:
        last = json.loads(metrics_path.read_text())["outer_iterations"][-1]
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise InputError("the run's metrics do not name its outer iterations", path=str(metrics_path),
                         field="outer_iterations", expected="the metrics.json of a G/I/L run",
                         found=type(exc).__name__) from None
    features, objects = read_features(folder / "features.csv"), read_objects(folder / "objects.csv")
    configured = nav.config.scanner.time_offset_s
    start_s, prior_s = (configured if last.get(k) is None else float(last[k])
                        for k in ("time_offset_start_s", "time_offset_prior_s"))
    gil = build_gil_problem(nav, truth_start(nav, root), features, objects,
                            time_offset=TimeOffsetStart(start_s, prior_s))
    P, blocks = gil.built.problem, gil.built.blocks
    if gil.estimates_offset:  # the scan times run the simulated offset behind GPS time
        P.set_values(OFFSET_BLOCK, np.array([[float(truth["scenario"].get("scanner_time_offset_s", 0.0)) - start_s]]))
    held = (blocks.position, blocks.velocity, blocks.acceleration, blocks.attitude, blocks.rate)
    for name in held:
        P.set_constant(name, True)
    P.solve(SolverOptions(max_iterations=NUISANCE_ITERATIONS, robust=False, initial_lambda=1e-9))
    for name in held:
        P.set_constant(name, False)
    truth_state = {name: P.values(name) for name in P.blocks}
    at_truth = P.solve(SolverOptions(max_iterations=0, robust=False))
    grid = gil.built.grid
    tcfg = nav.config.processing.trajectory.model_copy(update={
        "covariance_interval_s": BOUND_INTERVAL_S, "max_covariance_knots": int((grid.t_end - grid.t_start) / BOUND_INTERVAL_S) + 2})
    strips = set(np.unique(features.strip[objects.feature_object >= 0]).astype(int).tolist())
    fit = {g.name: float(g.variance_factor) for g in at_truth.groups if g.n_residuals}
    planes = next(g for g in P.groups if isinstance(g, PlaneObservation))
    r = planes.linearize(truth_state, jacobians=False).residuals.reshape(-1, 3)
    robust = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
    gil_figures = _figures(P, gil, nav, tcfg, truth_state, optimum)
    gi_figures = None
    if with_gi:  # the same problem without the LiDAR, from the same point
        for name, values in truth_state.items():
            P.set_values(name, values)
        for name in gil.lidar_groups:
            P.remove_group(name)
        for name in gil.lidar_blocks:
            P.set_constant(name, True)
        P.solve(SolverOptions(max_iterations=0, robust=False))
        gi_figures = _figures(P, gil, nav, tcfg, truth_state, optimum)
    return CramerRaoBound(_pass_bounds(nav, truth, strips, gil_figures, gi_figures), fit, robust, gil.features_used,
                          gil.objects_used, int(at_truth.n_unknowns), int(at_truth.n_residuals))
