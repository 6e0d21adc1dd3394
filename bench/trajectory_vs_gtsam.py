"""GNSS/IMU adjustment of Georefine against a gtsam factor graph on the same data (a script, not a test).

Simulates the ``corridor`` scenario (navigation data only: the scanner runs at 1 kHz so
that the simulation takes seconds), runs Georefine's initialisation filter and G/I
adjustment (docs/ARCHITECTURE.md §4.5 steps 1-2), then solves the same GNSS/IMU problem as a batch gtsam
factor graph and compares both with the true trajectory.

gtsam graph (the peer, measured in the same run)
    * States every ``--keyframe-interval`` s (default 0.1 s, the G/I/L's knot spacing) on
      the same span as Georefine's spline, each snapped to the nearest IMU sample:
      ``X`` = Pose3(Rot3(R_w_b), p_w_b) (body in the navigation frame), ``V`` = v_w_b,
      ``B`` = imuBias.ConstantBias(acc, gyro).
    * CombinedImuFactor between consecutive states (PreintegratedCombinedMeasurements). The
      IMU samples are instantaneous values, so each sample interval integrates the mean of
      its two end samples, the acceleration rotated forward by half the interval's rotation
      (midpoint rule; gtsam rotates a step's acceleration with the attitude at the step's
      start, see ``build_gtsam_graph``). Navigation frame = Georefine's ``w`` (ENU at the
      reference point, Earth-fixed): ``n_gravity = g_w(0) = [0, 0, -|g|]`` (normal gravity at the
      reference point, held constant: gtsam has no position-dependent gravity),
      ``omegaCoriolis = frame.omega_ie_w`` (first order: Earth rate in the attitude and
      Coriolis in the velocity; the centrifugal part is already in normal gravity).
      Noise densities exactly as Georefine's (``gnss_imu._densities``, incl. its floors):
      gyro radians(ARW)/60 rad/s/sqrt(Hz), acc VRW/60 m/s^2/sqrt(Hz), bias random walk
      ``q = B sqrt(2/tau)`` (continuous-time, so gtsam's bias covariance grows as q^2 dt).
    * GPSFactorArm at the states that coincide with a GNSS epoch (5 Hz, i.e. every other
      state; epochs between states are counted and left out): ``p + R p_b_a - z``, full 3x3
      covariance from the ``.pos`` file, Huber loss with Georefine's threshold (3 sigma).
    * Priors: turn-on bias prior at zero with the datasheet sigma (as Georefine); weak
      pose/velocity priors on the first state (1 m, 1 deg, 0.5 m/s; GNSS fixes the datum).
    * Initial values from Georefine's smoothed filter at the state times (the same starting
      point as Georefine's spline fit); the preintegration bias linearisation point too.
    * gtsam.LevenbergMarquardtOptimizer (multifrontal Cholesky, COLAMD), at most the same
      number of iterations as Georefine and the same relative cost tolerance (1e-8).
    * Covariance (column ``cov``): gtsam.Marginals and the pose marginals every 5 s, the
      counterpart of Georefine's posterior attitude/position sigma at knots 5 s apart.

Model differences (why variants): Georefine also estimates diagonal IMU scale factors and
uses position-dependent normal gravity ``g_w(p)``; gtsam's IMU factor has neither. The
variant ``plain`` feeds the raw IMU data. ``scale`` divides the samples by ``1 + s`` with
the scale factors of the shared filter result; ``gravity`` adds
``R_w_b^T (g_w(p_w_b) - g_w(0))`` along the filter trajectory to the specific force, so
that gtsam's constant gravity becomes exact to first order (normal gravity tilts against
w's z-axis by distance / Earth radius, ~40 mdeg at the far end of the ~5 km flight, which
otherwise appears as roll/pitch error).
``scale+gravity`` applies both. These corrections use only the shared filter result, never
the truth.

Errors: roll/pitch/yaw (NED Euler angles, wrapped) and 3-D position of each solution minus
the truth (``truth/trajectory.sbet``), at the gtsam state times (Georefine's spline is
evaluated there), over the whole common span and over the two mapping passes.

Georefine (measured with each ``--backends`` in the same run): step 2 with the defaults (knots
every 0.4 s, IMU windows of 0.1 s, up-sampling on), timed phase by phase: spline start, problem,
residuals and Jacobians, assembly, normal matrix, factorisation, the solver's rest, posterior
sigma; the total is of these. The up-sampling (the motion faster than the knots, rebuilt from the
raw IMU for the IMU-rate trajectory, which the gtsam states do not give either) is timed apart.
Every solver runs ``--repeat`` times and the fastest run is reported; imports are not timed.
``auto:default`` and ``auto:fast`` are what ``linear_solver: auto`` does on the default install
(QDLDL, cholespy, SciPy) and with the ``fast`` extra (CVXOPT too): Georefine is made to see only
those backends (:func:`installed`), so one machine measures both installs.

Usage::

    python bench/trajectory_vs_gtsam.py [--seed 42] [--keep DIR] [--keyframe-interval 0.1]
        [--variants plain scale+gravity] [--backends auto:default auto:fast qdldl cvxopt] [--repeat 2]
        [--no-marginals] [--set scene.length_m=2000 ...]
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

SIM_OVERRIDES = ["scanner.pulse_rate_hz=1000", "scanner.line_rate_hz=50"]  # >= 10 pulses per line
MDEG_PER_RAD = 180e3 / np.pi


@dataclass
class Solution:
    """One solver's result at the evaluation times: times (K,), p_w_b (K,3), R_w_b (K,3,3)."""

    name: str
    time: np.ndarray | None = None
    p_w_b: np.ndarray | None = None
    R_w_b: np.ndarray | None = None
    timings_s: dict = field(default_factory=dict)
    unknowns: int = 0
    states: int = 0
    iterations: str = ""
    note: str = ""
    error: str | None = None
    spline: object = None  # Georefine only: the adjusted SplineTrajectory


def simulate(base: Path, seed: int, extra: list[str]) -> tuple[Path, dict]:
    """Simulate (or reuse) the corridor project under ``base``; returns the folder and truth/scenario.yaml."""
    from georefine.sim.scenarios import simulate_project

    tag = "".join(c if c.isalnum() or c in ".-" else "_" for c in "-".join(extra))
    out = base / (f"corridor-seed{seed}" + (f"-{tag}" if tag else ""))
    if not (out / "truth" / "scenario.yaml").exists():
        if out.exists():
            shutil.rmtree(out)
        simulate_project("corridor", out, seed=seed, overrides=SIM_OVERRIDES + extra)
    return out, yaml.safe_load((out / "truth" / "scenario.yaml").read_text())


def load_truth(nav, project: Path):
    """The true IMU trajectory (truth/trajectory.sbet) in ``w``."""
    from georefine.io.trajectory import read_sbet
    from georefine.trajectory.sampled import trajectory_from_sbet

    sbet = read_sbet(project / "truth" / "trajectory.sbet", gps_week=int(nav.t0_gps // 604800))
    return trajectory_from_sbet(sbet, nav.frame, nav.t0_gps)


def errors(nav, truth, t: np.ndarray, p_w_b: np.ndarray, R_w_b: np.ndarray, mask: np.ndarray) -> dict:
    """RMSE of roll/pitch/yaw (mdeg) and of the 3-D position (m) against the truth at ``t[mask]``."""
    p_ref, R_ref = truth.interpolate(t[mask])
    rph_ref = nav.frame.rph_from_R_w_b(p_ref, R_ref)
    rph = nav.frame.rph_from_R_w_b(p_w_b[mask], R_w_b[mask])
    d = np.angle(np.exp(1j * (rph - rph_ref))) * MDEG_PER_RAD
    rmse = np.sqrt(np.mean(d**2, axis=0))
    d_p = np.linalg.norm(p_w_b[mask] - p_ref, axis=1)
    return {"roll": rmse[0], "pitch": rmse[1], "yaw": rmse[2], "pos": float(np.sqrt(np.mean(d_p**2))),
            "max_att": float(np.max(np.abs(d)))}


PHASES = ("start", "build", "evaluation", "assembly", "normal", "factorisation", "lm_other", "covariance")
"""Georefine's phases, in the order of the profile table (the adjustment; up-sampling apart)."""


INSTALLS = {"default": ("qdldl", "cholespy", "scipy"), "fast": ("cvxopt", "qdldl", "cholespy", "scipy")}
"""The backends each install brings (``pip install georefine``, ``georefine[fast]``), in auto's order."""


@contextlib.contextmanager
def installed(backends: tuple[str, ...] | None):
    """Georefine seeing only ``backends`` (None: what is installed), as on an install without the others:
    every module's ``available_backends`` is swapped for the duration."""
    import sys

    from georefine.adjustment import linalg

    if backends is None:
        yield
        return
    missing = [b for b in backends if b not in linalg.available_backends()]
    if missing:
        raise SystemExit(f"cannot emulate an install with {', '.join(missing)}: not installed here")
    original = linalg.available_backends
    patched = [m for m in list(sys.modules.values())
               if getattr(m, "__name__", "").startswith("georefine") and getattr(m, "available_backends", None) is original]
    for m in patched:
        m.available_backends = lambda: backends
    try:
        yield
    finally:
        for m in patched:
            m.available_backends = original


def run_georefine(nav, filt, backend: str) -> Solution:
    """Step 2 of the workflow with ``backend``, timed phase by phase (the filter's result is shared).
    ``auto:default`` and ``auto:fast``: ``linear_solver: auto`` on the backends of that install (:data:`INSTALLS`)."""
    from georefine.workflows import step_adjust_gnss_imu

    install = None
    if backend.startswith("auto:"):
        install = INSTALLS[backend.split(":", 1)[1]]
    tcfg = nav.config.processing.trajectory
    nav.config.processing.__dict__["trajectory"] = tcfg.model_copy(
        update={"linear_solver": "auto" if install else backend})
    try:
        sol = Solution(f"Georefine {backend}")
        t = time.perf_counter()
        with installed(install):
            adj = step_adjust_gnss_imu(nav, filt)
        wall = time.perf_counter() - t
    finally:
        nav.config.processing.__dict__["trajectory"] = tcfg
    tm, lm = adj.timings_s, adj.solve.timings
    # J and N formed for the posterior (where the solve did not leave them) count as assembly and normal.
    sol.timings_s = {
        "start": tm["start"], "build": tm["build"], "evaluation": lm.evaluation_s,
        "assembly": lm.assembly_s + tm.get("covariance_assembly", 0.0),
        "normal": lm.normal_s + tm.get("covariance_normal", 0.0), "factorisation": lm.factorization_s,
        "lm_other": tm["solve"] - lm.evaluation_s - lm.assembly_s - lm.normal_s - lm.factorization_s,
        "covariance": tm["covariance"], "upsampling": tm.get("upsampling", 0.0),
    }
    sol.timings_s["solve"] = tm["solve"]
    sol.timings_s["posterior"] = tm["covariance"] + tm.get("covariance_assembly", 0.0) + tm.get("covariance_normal", 0.0)
    sol.timings_s["total"] = sum(sol.timings_s[k] for k in PHASES)  # the adjustment: fit, problem, LM, sigma
    sol.timings_s["wall"] = wall  # all of step 2, up-sampling included
    sol.unknowns = adj.solve.n_unknowns
    sol.iterations = f"{adj.solve.iterations}/{adj.solve.successful_iterations}"
    sol.states = adj.spline.grid.n_knots
    h = adj.solve.cost_history
    sol.note = (f"{adj.solve.backend}; {sol.states} knots x (p,v,a,R,w) every {adj.spline.grid.dt:g} s + "
                f"{adj.imu_errors.bias_grid.n_knots} bias knots x (acc, gyro) + 2 scale-factor triples; "
                f"{adj.solve.termination}; cost {adj.solve.initial_cost:.4g} -> "
                + " -> ".join(f"{c:.6g}" for c in h))
    sol.spline = adj.spline
    return sol


def fastest(runs: list[Solution]) -> Solution:
    """The run with the least total time (repeats of one solver: the first pays for loading caches)."""
    ok = [r for r in runs if r.error is None]
    return min(ok, key=lambda r: r.timings_s["total"]) if ok else runs[0]


def keyframes(nav, grid, dt: float) -> np.ndarray:
    """IMU sample indices of the gtsam states: every ``dt`` on Georefine's knot span, snapped to the nearest sample."""
    t_imu = nav.gnss.imu_time
    want = grid.t_start + dt * np.arange(int(np.floor((grid.t_end - grid.t_start) / dt + 1e-9)) + 1)
    i = np.clip(np.searchsorted(t_imu, want), 1, t_imu.size - 1)
    i -= (want - t_imu[i - 1]) < (t_imu[i] - want)
    i = np.unique(i)
    return i[(t_imu[i] >= grid.t_start) & (t_imu[i] <= grid.t_end)]


def gtsam_inputs(nav, filt, variant: str) -> tuple[np.ndarray, np.ndarray, str]:
    """The IMU samples fed to gtsam (acc, gyro; (N,3)) with the variant's corrections."""
    acc = nav.gnss.imu_acc.copy()
    gyro = nav.gnss.imu_gyro.copy()
    parts = set(variant.split("+")) - {"plain"}
    unknown = parts - {"scale", "gravity"}
    if unknown:
        raise ValueError(f"unknown variant part(s) {sorted(unknown)}; use plain, scale, gravity or scale+gravity")
    notes = []
    if "scale" in parts:
        acc /= 1.0 + np.asarray(filt.scale_acc)
        gyro /= 1.0 + np.asarray(filt.scale_gyro)
        notes.append("IMU / (1 + filter scale factors)")
    if "gravity" in parts:
        # Filter states at every IMU sample it covers; outside, the nearest one (not used by the graph).
        j = np.clip(np.searchsorted(filt.time, nav.gnss.imu_time), 0, filt.time.size - 1)
        g0 = nav.frame.gravity_w(np.zeros(3))
        dg_w = nav.frame.gravity_w(filt.p_w_b[j]) - g0
        acc += np.einsum("nji,nj->ni", filt.R_w_b[j], dg_w)
        g_w = g0 + dg_w
        cos_tilt = (g_w @ g0) / (np.linalg.norm(g_w, axis=1) * np.linalg.norm(g0))
        tilt_mdeg = np.degrees(np.arccos(np.clip(cos_tilt, -1.0, 1.0))).max() * 1e3
        notes.append(f"specific force + R^T (g_w(p) - g_w(0)) (gravity tilts by up to {tilt_mdeg:.0f} mdeg)")
    return acc, gyro, "; ".join(notes) or "raw IMU"


def build_gtsam_graph(nav, filt, kf: np.ndarray, variant: str):
    """The gtsam graph and initial values (module docstring); returns (graph, values, note)."""
    import gtsam
    from gtsam.symbol_shorthand import B, V, X

    # Georefine's own noise densities, floors included, so that both weight the IMU alike.
    from georefine.adjustment.gnss_imu import _densities

    d = nav.gnss
    frame = nav.frame
    acc, gyro, note = gtsam_inputs(nav, filt, variant)
    dens = _densities(nav.config.imu.errors, nav.config.processing.trajectory)
    params = gtsam.PreintegrationCombinedParams(frame.gravity_w(np.zeros(3)))
    params.setOmegaCoriolis(frame.omega_ie_w)
    params.setGyroscopeCovariance(dens["gyro_noise"] ** 2 * np.eye(3))
    params.setAccelerometerCovariance(dens["acc_noise"] ** 2 * np.eye(3))
    params.setIntegrationCovariance(1e-10 * np.eye(3))
    params.setBiasAccCovariance(dens["acc_rw"] ** 2 * np.eye(3))
    params.setBiasOmegaCovariance(dens["gyro_rw"] ** 2 * np.eye(3))

    t_imu = d.imu_time
    t_kf = t_imu[kf]
    fi = np.clip(np.searchsorted(filt.time, t_kf), 0, filt.time.size - 1)
    if np.any(np.abs(filt.time[fi] - t_kf) > 1e-9):
        raise RuntimeError("a gtsam state time is not a filter epoch")
    dts = np.diff(t_imu)
    # Midpoint rule for instantaneous samples: the mean of the two end samples belongs to the middle
    # of the step, but gtsam rotates a step's acceleration with the attitude at its start, so rotate
    # it forward by Exp(omega dt/2) (first order). Without this, a banked turn leaves a bias
    # f_z omega_y dt/2 (1.7e-3 m/s^2 at 10 deg/s) along x; feeding the first sample instead shifts the
    # solution by half a sample (2.5 ms, ~25 mdeg of heading in a turn).
    gyro_mid = 0.5 * (gyro[:-1] + gyro[1:])
    acc_mid = 0.5 * (acc[:-1] + acc[1:])
    acc_mid += np.cross(0.5 * dts[:, None] * gyro_mid, acc_mid)

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    K = kf.size
    for k in range(K):
        f = fi[k]
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(filt.R_w_b[f]), filt.p_w_b[f]))
        values.insert(V(k), filt.v_w_b[f])
        values.insert(B(k), gtsam.imuBias.ConstantBias(filt.bias_acc[f], filt.bias_gyro[f]))
    for k in range(K - 1):
        f = fi[k]
        pim = gtsam.PreintegratedCombinedMeasurements(
            params, gtsam.imuBias.ConstantBias(filt.bias_acc[f], filt.bias_gyro[f]))
        for i in range(kf[k], kf[k + 1]):
            pim.integrateMeasurement(acc_mid[i], gyro_mid[i], dts[i])
        graph.add(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim))

    # GNSS epochs that coincide with a state (the others are counted, not used).
    gk = np.clip(np.searchsorted(t_kf, d.gnss_time), 1, K - 1)
    gk -= (d.gnss_time - t_kf[gk - 1]) < (t_kf[gk] - d.gnss_time)
    on_state = np.abs(t_kf[gk] - d.gnss_time) < 1e-4
    huber = gtsam.noiseModel.mEstimator.Huber.Create(nav.config.processing.trajectory.gnss_loss_scale)
    for g in np.flatnonzero(on_state):
        model = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(d.gnss_cov_w[g]))
        graph.add(gtsam.GPSFactorArm(X(int(gk[g])), d.gnss_p_w[g], d.p_b_a, model))
    note += f"; {int(on_state.sum())} GNSS factors, {int((~on_state).sum())} epochs not on a state"

    zero = np.zeros(3)
    bias_sigma = np.r_[[dens["acc_turn_on"]] * 3, [dens["gyro_turn_on"]] * 3]
    graph.add(gtsam.PriorFactorConstantBias(
        B(0), gtsam.imuBias.ConstantBias(zero, zero), gtsam.noiseModel.Diagonal.Sigmas(bias_sigma)))
    graph.add(gtsam.PriorFactorPose3(
        X(0), values.atPose3(X(0)), gtsam.noiseModel.Diagonal.Sigmas(np.r_[[np.radians(1.0)] * 3, [1.0] * 3])))
    graph.add(gtsam.PriorFactorVector(V(0), filt.v_w_b[fi[0]], gtsam.noiseModel.Isotropic.Sigma(3, 0.5)))
    return graph, values, note


def run_gtsam(nav, filt, kf: np.ndarray, variant: str, max_iterations: int, marginals_every_s: float | None) -> Solution:
    """Build and optimise the gtsam graph for one variant; failures are caught and reported."""
    sol = Solution(f"gtsam {variant}")
    try:
        import gtsam
        from gtsam.symbol_shorthand import X

        t = time.perf_counter()
        graph, values, sol.note = build_gtsam_graph(nav, filt, kf, variant)
        sol.timings_s["build"] = time.perf_counter() - t

        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(max_iterations)
        lm.setRelativeErrorTol(1e-8)
        lm.setAbsoluteErrorTol(0.0)
        t = time.perf_counter()
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, lm)
        result = opt.optimize()
        sol.timings_s["solve"] = time.perf_counter() - t
        sol.iterations = str(opt.iterations())
        sol.note += f"; cost {graph.error(values):.4g} -> {graph.error(result):.4g}"

        K = kf.size
        if marginals_every_s:
            t = time.perf_counter()
            marg = gtsam.Marginals(graph, result)
            step = max(1, round(marginals_every_s / float(np.median(np.diff(nav.gnss.imu_time[kf])))))
            for k in range(0, K, step):
                marg.marginalCovariance(X(k))
            sol.timings_s["covariance"] = time.perf_counter() - t

        sol.timings_s["total"] = sum(sol.timings_s.get(k, 0.0) for k in ("build", "solve", "covariance"))
        sol.time = nav.gnss.imu_time[kf]
        sol.p_w_b = np.array([result.atPose3(X(k)).translation() for k in range(K)])
        sol.R_w_b = np.array([result.atPose3(X(k)).rotation().matrix() for k in range(K)])
        sol.states = K
        sol.unknowns = int(result.dim())
    except Exception as exc:  # noqa: BLE001  (the peer may fail: report it and carry on)
        sol.error = f"{type(exc).__name__}: {exc}"
    return sol


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--keep", type=Path, default=None, help="simulate into / reuse the project in this folder")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="extra scenario override, e.g. scene.length_m=2000 (repeatable)")
    ap.add_argument("--keyframe-interval", type=float, default=0.1, help="gtsam state spacing (s)")
    ap.add_argument("--variants", nargs="+", default=["scale+gravity"],
                    help="gtsam input variants: plain, scale, gravity, scale+gravity")
    ap.add_argument("--backends", nargs="+", default=None,
                    help="Georefine's sparse Cholesky backends, or auto:default / auto:fast (linear_solver auto on "
                         "the backends of the default install / the fast extra) (default: both installs, then every "
                         "installed one of qdldl, cvxopt, cholmod, cholespy)")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each solver; the fastest is reported")
    ap.add_argument("--no-marginals", action="store_true", help="skip gtsam's marginal covariances")
    args = ap.parse_args()

    import gtsam  # noqa: F401  (fail early if the peer is missing)
    import scipy.signal  # noqa: F401  (imports are not timed, for either peer)

    from georefine.adjustment.linalg import available_backends
    from georefine.workflows import load_navigation, step_initialise

    backends = args.backends or ["auto:default", "auto:fast"] + [
        b for b in ("qdldl", "cvxopt", "cholmod", "cholespy") if b in available_backends()]
    base = args.keep or Path(tempfile.mkdtemp(prefix="georefine-bench-"))
    base.mkdir(parents=True, exist_ok=True)
    try:
        t = time.perf_counter()
        project, truth_yaml = simulate(base, args.seed, args.overrides)
        print(f"project {project} (simulated or reused in {time.perf_counter() - t:.1f} s): corridor, seed {args.seed}, "
              f"flight {truth_yaml['duration_s']:.0f} s, IMU {truth_yaml['scenario']['imu']['name']}")
        nav = load_navigation(project)
        truth = load_truth(nav, project)
        print(f"IMU {nav.gnss.imu_time.size:,} samples at {nav.gnss.imu_rate_hz:g} Hz, "
              f"GNSS {nav.gnss.gnss_time.size:,} epochs")
        t = time.perf_counter()
        filt = step_initialise(nav)  # shared: both peers start from it
        filter_s = time.perf_counter() - t

        sols = []
        for backend in backends:
            geo = fastest([run_georefine(nav, filt, backend) for _ in range(args.repeat)])
            sols.append(geo)
            print(f"{geo.name}: {geo.note}")
        grid = sols[0].spline.grid
        kf = keyframes(nav, grid, args.keyframe_interval)
        t_eval = nav.gnss.imu_time[kf]
        for geo in sols:
            geo.time = t_eval
            geo.p_w_b, geo.R_w_b = geo.spline.pose(t_eval)
        print(f"gtsam states: {kf.size:,} every {args.keyframe_interval:g} s (IMU samples nearest to the knots)")
        peers = []
        for v in args.variants:
            s = fastest([run_gtsam(nav, filt, kf, v, nav.config.processing.trajectory.max_iterations,
                                   None if args.no_marginals else nav.config.processing.trajectory.covariance_interval_s)
                         for _ in range(args.repeat)])
            peers.append(s)
            print(f"{s.name}: " + (f"FAILED {s.error}" if s.error else s.note))
        sols += peers

        passes = np.zeros(t_eval.size, dtype=bool)
        for ps in truth_yaml["passes"]:
            passes |= (t_eval >= ps["t_start_s"]) & (t_eval <= ps["t_end_s"])
        everywhere = truth.contains(t_eval)
        ok = [s for s in sols if s.error is None]

        print(f"\nErrors against the truth at the {int(everywhere.sum()):,} gtsam state times "
              f"(RMSE; 'max' = largest |attitude error|):")
        print(f"{'solution':<24} {'span':<7} {'roll':>7} {'pitch':>7} {'yaw':>7} {'max':>7} {'3D pos':>7}")
        print(f"{'':<24} {'':<7} {'mdeg':>7} {'mdeg':>7} {'mdeg':>7} {'mdeg':>7} {'m':>7}")
        for s in ok:
            for label, mask in (("flight", everywhere), ("passes", passes & everywhere)):
                e = errors(nav, truth, s.time, s.p_w_b, s.R_w_b, mask)
                print(f"{s.name if label == 'flight' else '':<24} {label:<7} {e['roll']:7.2f} {e['pitch']:7.2f}"
                      f" {e['yaw']:7.2f} {e['max_att']:7.1f} {e['pos']:7.4f}")

        print(f"\nWall time (s, the fastest of {args.repeat} runs; build = Georefine's spline start and problem, "
              "gtsam's preintegration and graph; cov = posterior covariances every 5 s; total = build + solve + cov)")
        print(f"{'solution':<24} {'build':>6} {'solve':>6} {'cov':>6} {'total':>6} {'iter':>6} {'unknowns':>9}"
              f" {'states':>7}")
        for s in ok:
            tm = s.timings_s
            build = tm.get("build", 0.0) + tm.get("start", 0.0)
            cov = tm.get("posterior", tm.get("covariance", float("nan")))  # Georefine's with its own J and N
            print(f"{s.name:<24} {build:6.3f} {tm['solve']:6.3f} {cov:6.3f}"
                  f" {tm['total']:6.3f} {s.iterations:>6} {s.unknowns:9,} {s.states:7,}")
        geos = [s for s in ok if s.name.startswith("Georefine")]
        for peer in [s for s in ok if s.name.startswith("gtsam")]:
            print(f"{peer.name} / Georefine total: " + ", ".join(
                f"{g.name.split()[-1]} {peer.timings_s['total'] / g.timings_s['total']:.2f}x" for g in geos))

        print("\nGeorefine's profile (s): start = spline fit to the filter, build = the problem, evaluation = "
              "residuals and Jacobians, assembly = J, normal = lower(J^T J) and damping, factorisation = "
              "factorisations and solves, lm_other = the rest of the solver, covariance = posterior sigma "
              "(variance components, selected inversion); up-sampling (the motion faster than the knots, "
              "rebuilt from the raw IMU for the IMU-rate trajectory) is not part of the total")
        print(f"{'backend':<14}" + "".join(f" {p:>13}" for p in PHASES) + f" {'total':>7} {'up-sampling':>11}")
        for g in geos:
            tm = g.timings_s
            print(f"{g.name.split()[-1]:<14}" + "".join(f" {tm[p]:13.3f}" for p in PHASES)
                  + f" {tm['total']:7.3f} {tm['upsampling']:11.3f}")
        print(f"filter (step 1, shared by both peers, not timed in either) {filter_s:.2f} s; "
              f"'iter' = trial/accepted steps (Georefine), LM iterations (gtsam)")
        print(f"peak RSS of this process {_peak_rss_gb():.2f} GB")
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)


def _peak_rss_gb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


if __name__ == "__main__":
    main()
