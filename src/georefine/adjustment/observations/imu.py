"""IMU specific-force and angular-rate observations (docs/ARCHITECTURE.md §4.3, §4.6; paper 000 Eq. 4).

At time ``t`` the model of the accelerometer and gyro readings is

``f~ = (I + S_f + A_f) R_w_b^T (p''_w + 2 omega_ie_w x p'_w - g_w(p_w)) + b_f(t)``
``w~ = (I + S_g + A_g) (omega_wb_b + R_w_b^T omega_ie_w) + b_g(t)``

with piecewise-linear biases on their own knots, constant diagonal scale factors ``S`` and,
where estimated, each triad's constant misalignment ``A``: its six off-diagonal elements
(:data:`OFF_DIAGONAL` order), the triad's turn and shear against the body frame; and where
the IMU logs its temperature and the coefficients are estimated, each bias has a part
``k (T - T_ref)`` more, a coefficient per axis times the window's temperature against the
file's first (``temperature``).

Down-sampling (Pöppl et al. 2025): consecutive samples are averaged over windows
(``processing.trajectory.imu_window_s``, default 0.02 s; the G/I's ``gnss_imu_window_s``, 0.1 s)
and compared with the model averaged the same way, so the adjustment size follows the window
rate, not the IMU rate. How depends on what a sample is (``ImuData.kind``, :mod:`georefine.io.imu`):

* ``"rates"``, the sensor's value at its time tag: the model's mean at the window's sample
  times. A quadrature of the continuous mean instead (the samples as its midpoint rule)
  differs from the samples' mean by ``(2 pi f dt)^2 / 24`` of a line at ``f``: 0.7 % at 13 Hz
  and 200 Hz, which with rotor vibration and a navigation-grade IMU is up to 12 times its
  window noise (BENCHMARKS.md, Operating conditions). The mean at the samples is taken by the
  ``nodes``-point Gauss rule of the samples themselves (:func:`discrete_gauss_rule`: exact for
  polynomials of degree ``2 nodes - 1``), per piece of the window on either side of a knot, so
  that each piece is one polynomial piece of the spline: a window of 20 samples costs 3 model
  evaluations (6 across a knot) instead of 20, and on the corridor's G/I the window means
  differ from the sample means by at most 3e-7 of a window's sigma. Windows of at most
  ``nodes`` samples are evaluated at their samples;
* ``"increments"``, the mean over the interval that ends at the time tag: the window covers
  ``(t_first - dt, t_last]`` and the model's continuous mean over it is a Gauss-Legendre
  quadrature (``nodes``), per piece on either side of a knot.

A window's standard deviation follows from the noise density ``N`` (ARW/VRW): for ``n``
samples at rate ``f`` the mean has ``sigma = N sqrt(f / n)``. Windows never span a sampling gap.

Jacobians (right perturbation ``R <- R Exp(delta)``): ``d(R^T x)/d delta = skew(R^T x)``;
``d(R^T x)/d p'' = R^T``, ``d/d p' = 2 R^T skew(omega_ie_w)``, ``d/d p = -R^T G`` with
``G`` the normal-gravity gradient ``(gamma / r)(3 u u^T - I)`` (``u`` the up direction); each
is taken through the triad's ``M = I + S + A``. ``d f~_i / d A_ij = (R^T x)_j``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal, Mapping

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.observations.bias import BiasGrid
from georefine.adjustment.observations.trajectory_blocks import (
    TrajectoryBlocks,
    orientation_jacobians,
)
from georefine.adjustment.robust import RobustLoss
from georefine.geometry.earth import WGS84_A
from georefine.geometry.frames import LocalFrame
from georefine.geometry.rotation import skew
from georefine.trajectory.spline import KnotGrid, eval_orientation, knot_sum, position_basis

OFF_DIAGONAL = (np.array([0, 0, 1, 1, 2, 2]), np.array([1, 2, 0, 2, 0, 1]))
"""Row and column of the six misalignment elements of a triad, in their block's order."""


def triad_matrix(scale: np.ndarray, misalignment: np.ndarray | None = None) -> np.ndarray:
    """A triad's sensitivity ``M = I + diag(scale) + A`` (3, 3), ``A`` from its six off-diagonal
    elements (:data:`OFF_DIAGONAL` order; None: zero)."""
    m = np.diag(1.0 + np.asarray(scale, dtype=float).reshape(3))
    if misalignment is not None:
        m[OFF_DIAGONAL] = np.asarray(misalignment, dtype=float).reshape(6)
    return m


@dataclass(frozen=True)
class ImuWindows:
    """IMU samples averaged over windows.

    Attributes
    ----------
    t_start, t_end : (W,)
        Window limits, s relative to the epoch: for rates half a sample interval beyond the
        first and last sample, for increments from one interval before the first sample to
        the last.
    gyro, acc : (W, 3)
        Mean angular rate (rad/s) and specific force (m/s²), body frame.
    n_samples : (W,) int
    gyro_bridged_sigma, acc_bridged_sigma : (W,) or None
        Standard deviation the bridged samples of a sampling gap add to each window mean
        (:mod:`georefine.io.imu_gaps`): the window's mean of its samples' interpolation sigma,
        i.e. ``(k / n) sigma`` for ``k`` of ``n`` samples bridged (fully correlated errors).
        None: every sample was measured.
    kind
        ``"rates"`` or ``"increments"``: what a sample is (module docstring).
    """

    t_start: np.ndarray
    t_end: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    n_samples: np.ndarray
    gyro_bridged_sigma: np.ndarray | None = None
    acc_bridged_sigma: np.ndarray | None = None
    kind: Literal["rates", "increments"] = "rates"

    def __len__(self) -> int:
        return self.t_start.size


def make_imu_windows(
    time: np.ndarray, gyro: np.ndarray, acc: np.ndarray, rate_hz: float, window_s: float, max_gap_factor: float = 1.5,
    gyro_sigma: np.ndarray | None = None, acc_sigma: np.ndarray | None = None,
    kind: Literal["rates", "increments"] = "rates",
) -> ImuWindows:
    """Average consecutive samples over windows of ``round(window_s * rate_hz)`` samples.

    Windows restart after every sampling gap (interval > ``max_gap_factor / rate_hz``) so that
    no window spans missing data; the last window of a segment may be shorter. ``gyro_sigma``
    and ``acc_sigma`` (N,) are the interpolation sigma of bridged samples (0 for measured ones).
    ``kind``: what a sample is (module docstring); it sets the window limits.
    """
    if kind not in ("rates", "increments"):
        raise ValueError(f"kind must be 'rates' or 'increments', got {kind!r}")
    time = np.asarray(time, dtype=float)
    n = max(1, int(round(window_s * rate_hz)))
    dt = 1.0 / rate_hz
    gap = np.diff(time) > max_gap_factor * dt
    segment = np.concatenate([[0], np.cumsum(gap)])
    seg_start = np.flatnonzero(np.concatenate([[True], gap]))
    index_in_segment = np.arange(time.size) - seg_start[segment]
    window_id = segment * (time.size + 1) + index_in_segment // n
    starts = np.flatnonzero(np.concatenate([[True], np.diff(window_id) != 0]))
    counts = np.diff(np.concatenate([starts, [time.size]]))
    ends = starts + counts - 1
    before, after = sample_support(kind, rate_hz)
    return ImuWindows(
        t_start=time[starts] - before,
        t_end=time[ends] + after,
        gyro=np.add.reduceat(gyro, starts, axis=0) / counts[:, None],
        acc=np.add.reduceat(acc, starts, axis=0) / counts[:, None],
        n_samples=counts,
        gyro_bridged_sigma=None if gyro_sigma is None or not np.any(gyro_sigma) else
        np.add.reduceat(np.asarray(gyro_sigma, float), starts) / counts,
        acc_bridged_sigma=None if acc_sigma is None or not np.any(acc_sigma) else
        np.add.reduceat(np.asarray(acc_sigma, float), starts) / counts,
        kind=kind,
    )


def sample_support(kind: str, rate_hz: float) -> tuple[float, float]:
    """How far before and after its time tag a sample's window reaches (s): half an interval
    either side for rates, the interval before the tag for increments."""
    dt = 1.0 / rate_hz
    return (dt, 0.0) if kind == "increments" else (0.5 * dt, 0.5 * dt)


@dataclass
class ImuObservation:
    """Window-averaged IMU readings observing a spline trajectory and the IMU errors.

    Parameters
    ----------
    grid
        Knot grid of the trajectory; every window must lie inside its span.
    windows
        Averaged IMU data (:func:`make_imu_windows`).
    frame
        Mapping frame (gravity and Earth rate).
    acc_bias_grid, gyro_bias_grid
        Knots of the piecewise-linear biases (blocks ``acc_bias``, ``gyro_bias``, (J, 3)).
    sigma_acc, sigma_gyro : float or (W,)
        Standard deviation of each window mean (m/s², rad/s).
    acc_scale, gyro_scale
        Names of the (1, 3) scale-factor blocks, or None to leave scale factors out.
    acc_misalignment, gyro_misalignment
        Names of the (1, 6) misalignment blocks (:data:`OFF_DIAGONAL`), or None (the default) to
        leave them out.
    temperature, acc_temperature, gyro_temperature
        The unit's temperature over each window against its reference, ``T - T_ref`` ((W,), deg
        C), and the names of the (1, 3) blocks of the biases' temperature coefficients (per deg
        C): each window's bias is ``b(t) + k (T - T_ref)``; None (the default) leaves them out.
    nodes
        Gauss-Legendre nodes per window of increments (1 for single samples). Windows of
        rates are averaged at their samples (module docstring).
    consumed_redundancy
        Degrees of freedom of the windows that were spent before the adjustment: readings
        cleaned of a vibration rebuilt from themselves
        (:func:`georefine.adjustment.gnss_imu.cleaning_redundancy`). The solver and the
        variance components subtract it from the redundancy.
    """

    grid: KnotGrid
    windows: ImuWindows
    frame: LocalFrame
    acc_bias_grid: BiasGrid
    gyro_bias_grid: BiasGrid
    sigma_acc: np.ndarray | float
    sigma_gyro: np.ndarray | float
    acc_bias: str = "acc_bias"
    gyro_bias: str = "gyro_bias"
    acc_scale: str | None = "acc_scale"
    gyro_scale: str | None = "gyro_scale"
    acc_misalignment: str | None = None
    gyro_misalignment: str | None = None
    nodes: int = 3
    blocks: TrajectoryBlocks = field(default_factory=TrajectoryBlocks)
    loss: RobustLoss | None = None
    name: str = "imu"
    consumed_redundancy: float = 0.0
    sample_rule: bool = True
    temperature: np.ndarray | None = None
    acc_temperature: str | None = None
    gyro_temperature: str | None = None

    def __post_init__(self) -> None:
        w = self.windows
        n = len(w)
        # The nodes of all windows in one flat list: node i belongs to window self._win[i] with
        # weight self._q[i] (module docstring, Down-sampling).
        split = _knot_inside(self.grid, w.t_start, w.t_end)
        if w.kind == "rates":
            t_nodes, q, win = _sample_mean_nodes(w.t_start, w.t_end, w.n_samples, split,
                                                 self.nodes if self.sample_rule else 0)
        else:
            t_nodes, q, win = _interval_mean_nodes(w.t_start, w.t_end, split, self.nodes)
        self._t = np.clip(t_nodes, self.grid.t_start, self.grid.t_end)
        self._q = q
        self._win = win
        k, u = self.grid.locate(self._t)
        self._k = k
        self._basis = [position_basis(u, self.grid.dt, order) for order in (0, 1, 2)]
        self._jb_a, self._lb_a = self.acc_bias_grid.weights(self._t)
        self._jb_g, self._lb_g = self.gyro_bias_grid.weights(self._t)
        self._sa = np.broadcast_to(np.asarray(self.sigma_acc, dtype=float), (n,)).copy()
        self._sg = np.broadcast_to(np.asarray(self.sigma_gyro, dtype=float), (n,)).copy()
        rows = np.arange(6 * n).reshape(n, 6)
        self._rows_f, self._rows_g = rows[:, :3], rows[:, 3:]
        self._obs = np.repeat(np.arange(2 * n), 3)
        self._n = n
        if (self.temperature is None) != (self.acc_temperature is None and self.gyro_temperature is None):
            raise ValueError(f"{self.name}: temperature and the temperature coefficient blocks go together")
        if self.temperature is not None:
            self.temperature = np.asarray(self.temperature, dtype=float).reshape(n)

    @property
    def n_nodes(self) -> int:
        """Points at which the model is evaluated: the cost of a linearisation."""
        return self._t.size

    # ---------------------------------------------------------------- model
    def _node_terms(self, values, jacobians):
        P, V, A, R, W = self.blocks.knots(values)
        k, (w0, w1, w2) = self._k, self._basis
        p, v, a = (knot_sum(P, V, A, k, w) for w in (w0, w1, w2))
        ev = eval_orientation(self.grid, R, W, self._t, rate=True, jacobians=jacobians)
        g = self.frame.gravity_w(p)
        omega_ie = self.frame.omega_ie_w
        x = a + 2.0 * np.cross(omega_ie, v) - g
        Rt = np.swapaxes(ev.R_w_b, 1, 2)
        Rt_x = np.einsum("nij,nj->ni", Rt, x)
        Rt_W = Rt @ omega_ie
        b_a = self.acc_bias_grid.evaluate(np.asarray(values[self.acc_bias]), self._t)
        b_g = self.gyro_bias_grid.evaluate(np.asarray(values[self.gyro_bias]), self._t)
        s_a = np.asarray(values[self.acc_scale]).reshape(3) if self.acc_scale else np.zeros(3)
        s_g = np.asarray(values[self.gyro_scale]).reshape(3) if self.gyro_scale else np.zeros(3)
        rate = ev.omega_wb_b + Rt_W
        f_node = (1.0 + s_a) * Rt_x + b_a
        w_node = (1.0 + s_g) * rate + b_g
        M_a, M_g = np.diag(1.0 + s_a), np.diag(1.0 + s_g)
        if self.acc_misalignment:
            M_a = triad_matrix(s_a, values[self.acc_misalignment])
            f_node += Rt_x @ (M_a - np.diag(np.diag(M_a))).T
        if self.gyro_misalignment:
            M_g = triad_matrix(s_g, values[self.gyro_misalignment])
            w_node += rate @ (M_g - np.diag(np.diag(M_g))).T
        return dict(p=p, g=g, ev=ev, Rt=Rt, Rt_x=Rt_x, Rt_W=Rt_W, rate=rate, M_a=M_a, M_g=M_g, f=f_node, w=w_node)

    def _average(self, node_values: np.ndarray) -> np.ndarray:
        weighted = node_values * self._q[:, None]
        return np.column_stack([np.bincount(self._win, weights=weighted[:, c], minlength=self._n) for c in range(3)])

    def _temperature_bias(self, values: Mapping[str, np.ndarray], name: str | None) -> np.ndarray | float:
        """``k (T - T_ref)`` per window (W, 3), or 0 without the block."""
        if not name:
            return 0.0
        return self.temperature[:, None] * np.asarray(values[name]).reshape(1, 3)

    def predict(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Modelled window means ``(acc (W,3), gyro (W,3))``."""
        terms = self._node_terms(values, jacobians=False)
        return (self._average(terms["f"]) + self._temperature_bias(values, self.acc_temperature),
                self._average(terms["w"]) + self._temperature_bias(values, self.gyro_temperature))

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        terms = self._node_terms(values, jacobians)
        wins = self.windows
        f = self._average(terms["f"]) + self._temperature_bias(values, self.acc_temperature)
        w = self._average(terms["w"]) + self._temperature_bias(values, self.gyro_temperature)
        r_f = (f - wins.acc) / self._sa[:, None]
        r_g = (w - wins.gyro) / self._sg[:, None]
        r = np.concatenate([r_f, r_g], axis=1).ravel()
        jac: list[JacobianBlock] = []
        if jacobians:
            jac = self._jacobians(terms)
        return Linearization(r, jac, self._obs)

    def _jacobians(self, t) -> list[JacobianBlock]:
        out = []
        omega_ie = self.frame.omega_ie_w
        g = t["g"]
        gamma = np.linalg.norm(g, axis=1)
        up = -g / gamma[:, None]
        G = (gamma / WGS84_A)[:, None, None] * (3.0 * up[:, :, None] * up[:, None, :] - np.eye(3))
        Da, Dg = t["M_a"], t["M_g"]
        ev = t["ev"]
        eye = np.eye(3)
        win = self._win
        ca = (self._q / self._sa[win])[:, None, None]
        cg = (self._q / self._sg[win])[:, None, None]
        rows_f, rows_g = self._rows_f[win], self._rows_g[win]
        M_a = ca * (Da @ t["Rt"])
        M_v = M_a @ (2.0 * skew(omega_ie))
        M_p = -M_a @ G
        k = self._k
        w0, w1, w2 = self._basis
        for j, name in enumerate(self.blocks.position_states):
            val = M_a * w2[:, j, None, None] + M_v * w1[:, j, None, None] + M_p * w0[:, j, None, None]
            out.append(JacobianBlock(name, rows_f, k if j < 3 else k + 1, val))
        out += orientation_jacobians(self.blocks, rows_f, ev.jacobians, ca * Da @ skew(t["Rt_x"]))
        out += orientation_jacobians(
            self.blocks, rows_g, ev.jacobians, cg * Dg @ skew(t["Rt_W"]), cg * np.broadcast_to(Dg, (win.size, 3, 3))
        )
        for name, rows, jb, lb, c in (
            (self.acc_bias, rows_f, self._jb_a, self._lb_a, ca),
            (self.gyro_bias, rows_g, self._jb_g, self._lb_g, cg),
        ):
            out.append(JacobianBlock(name, rows, jb, c * (1.0 - lb)[:, None, None] * eye))
            out.append(JacobianBlock(name, rows, jb + 1, c * lb[:, None, None] * eye))
        zeros = np.zeros(win.size, dtype=np.int64)
        if self.acc_scale:
            d = t["Rt_x"]
            out.append(JacobianBlock(self.acc_scale, rows_f, zeros, ca * (d[:, :, None] * eye)))
        if self.gyro_scale:
            d = t["rate"]
            out.append(JacobianBlock(self.gyro_scale, rows_g, zeros, cg * (d[:, :, None] * eye)))
        for name, rows, d, c in ((self.acc_misalignment, rows_f, t["Rt_x"], ca),
                                 (self.gyro_misalignment, rows_g, t["rate"], cg)):
            if name:
                val = np.zeros((win.size, 3, 6))
                val[:, OFF_DIAGONAL[0], np.arange(6)] = d[:, OFF_DIAGONAL[1]]
                out.append(JacobianBlock(name, rows, zeros, c * val))
        for name, rows, sigma in ((self.acc_temperature, self._rows_f, self._sa),
                                  (self.gyro_temperature, self._rows_g, self._sg)):
            if name:  # per window, not per node: the temperature is the window's
                val = (self.temperature / sigma)[:, None, None] * eye
                out.append(JacobianBlock(name, rows, np.zeros(self._n, dtype=np.int64), val))
        return out


QUADRATURE_TOLERANCE = 0.01
"""Largest change of a window mean, in its sigma, that one node fewer per window may make."""


def fewest_nodes(obs: ImuObservation, values: Mapping[str, np.ndarray],
                 tolerance: float = QUADRATURE_TOLERANCE) -> tuple[ImuObservation, float]:
    """``obs`` with one node fewer per window where that moves no window mean by more than
    ``tolerance`` of its sigma at ``values`` (the adjustment's start); else ``obs`` itself.
    Returns the observation and the largest change found.

    The rule of ``obs.nodes`` nodes is the reference: exact for polynomials of degree
    ``2 nodes - 1``, it is within 3e-7 of a window's sigma of the samples' mean on the corridor's
    G/I (module docstring). The spline's motion inside a 0.1 s window is smooth at the knots'
    scale (what is faster is up-sampled apart), so two nodes usually do: on the corridor's G/I
    (MEMS) they move the means by at most 9e-4 of a sigma, and an evaluation costs two thirds.
    A navigation-grade IMU, whose window sigma is a hundred times smaller, keeps three nodes
    where the motion asks for them: on ``corridor-tiny`` two would move them by 0.07 sigma (0.15
    with rotor vibration) at the G/I's start. One extra evaluation of the means decides.
    """
    if obs.nodes <= 1 or (obs.windows.kind == "rates" and not obs.sample_rule):
        return obs, 0.0
    fewer = replace(obs, nodes=obs.nodes - 1)
    if fewer.n_nodes == obs.n_nodes:  # windows of at most that many samples: evaluated at them anyway
        return obs, 0.0
    f_ref, w_ref = obs.predict(values)
    f, w = fewer.predict(values)
    change = max(float(np.max(np.abs(f - f_ref) / obs._sa[:, None], initial=0.0)),
                 float(np.max(np.abs(w - w_ref) / obs._sg[:, None], initial=0.0)))
    return (fewer, change) if change <= tolerance else (obs, change)


def discrete_gauss_rule(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss rule of ``m`` nodes for the mean over the points ``0, 1, ..., n-1``.

    Returns nodes ``x`` (m,), real numbers in ``[0, n-1]``, and weights ``q`` (m,) summing to 1
    such that ``sum q f(x) = mean_i f(i)`` for every polynomial ``f`` of degree ``<= 2m - 1``.
    Golub-Welsch on the recurrence of the discrete Chebyshev (Gram) polynomials, monic
    ``p_{k+1}(x) = (x - (n-1)/2) p_k(x) - beta_k p_{k-1}(x)``,
    ``beta_k = k^2 (n^2 - k^2) / (4 (4k^2 - 1))`` (Abramowitz and Stegun 22.17; Gautschi,
    *Orthogonal Polynomials*, 2004, §1.5). With ``m >= n`` the points themselves, weight ``1/n``.
    """
    if n < 1 or m < 1:
        raise ValueError(f"need n >= 1 and m >= 1, got n={n}, m={m}")
    if m >= n:
        return np.arange(n, dtype=float), np.full(n, 1.0 / n)
    k = np.arange(1, m, dtype=float)
    off = np.sqrt(k**2 * (n**2 - k**2) / (4.0 * (4.0 * k**2 - 1.0)))
    J = np.diag(np.full(m, 0.5 * (n - 1))) + np.diag(off, 1) + np.diag(off, -1)
    x, V = np.linalg.eigh(J)
    return x, V[0] ** 2


def _knot_inside(grid: KnotGrid, t_start: np.ndarray, t_end: np.ndarray) -> np.ndarray:
    """The knot strictly inside each window ``(t_start, t_end)``, NaN where none is (windows are at
    most a quarter of a knot interval long, so never more than one)."""
    k = np.floor((t_end - grid.t_start) / grid.dt - 1e-9)
    knot = grid.t_start + k * grid.dt
    return np.where((knot > t_start + 1e-9 * grid.dt) & (k >= 1) & (k <= grid.n_knots - 2), knot, np.nan)


def _sample_mean_nodes(t_start: np.ndarray, t_end: np.ndarray, n_samples: np.ndarray, split: np.ndarray, m: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes, weights and windows (flat) of the mean over each window's samples.

    A window's samples lie at ``t_start + (i + 1/2) (t_end - t_start) / n``; those on either side
    of a knot inside it (``split``) form two pieces, each in one polynomial piece of the spline. A
    piece of ``c`` samples gets the ``m``-node discrete Gauss rule over them
    (:func:`discrete_gauss_rule`: the mean of a polynomial of degree ``<= 2m - 1`` at the samples,
    exactly), weighted ``c / n``; with ``m == 0`` every sample is a node (no split needed).
    """
    n_samples = np.asarray(n_samples, dtype=np.int64)
    step = (t_end - t_start) / n_samples
    if m == 0:
        split = np.full(n_samples.size, np.nan)
    # samples before the knot: those whose time tag t_start + (i + 1/2) step lies below it
    before = np.ceil((np.nan_to_num(split, nan=np.inf) - t_start) / step - 0.5 - 1e-9)
    cut = np.clip(np.where(np.isnan(split), n_samples, before), 0, n_samples).astype(np.int64)
    two = np.flatnonzero((cut > 0) & (cut < n_samples))
    win = np.concatenate([np.arange(n_samples.size), two])
    first = np.concatenate([np.zeros(n_samples.size, dtype=np.int64), cut[two]])
    count = np.concatenate([np.where(cut > 0, cut, n_samples), n_samples[two] - cut[two]])
    t_out, q_out, w_out = [], [], []
    for c in np.unique(count):
        sel = np.flatnonzero(count == c)
        x, q = discrete_gauss_rule(int(c), int(m) if m else int(c))
        ws = win[sel]
        t_out.append(t_start[ws][:, None] + (first[sel][:, None] + x[None, :] + 0.5) * step[ws][:, None])
        q_out.append(q[None, :] * (c / n_samples[ws])[:, None])
        w_out.append(np.repeat(ws[:, None], x.size, axis=1))
    order = np.argsort(np.concatenate([a.ravel() for a in w_out]), kind="stable")  # window by window
    return (np.concatenate([a.ravel() for a in t_out])[order], np.concatenate([a.ravel() for a in q_out])[order],
            np.concatenate([a.ravel() for a in w_out])[order])


def _interval_mean_nodes(t_start: np.ndarray, t_end: np.ndarray, split: np.ndarray, m: int
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes, weights and windows (flat) of the continuous mean over each window: ``m``-node
    Gauss-Legendre over each piece between the window's limits and a knot inside it (``split``),
    weighted by the piece's share of the window."""
    x, qg = np.polynomial.legendre.leggauss(m)
    has = ~np.isnan(split)
    n = t_start.size
    two = np.flatnonzero(has)
    win = np.concatenate([np.arange(n), two])
    a = np.concatenate([t_start, split[two]])
    b = np.concatenate([np.where(has, split, t_end), t_end[two]])
    mid, half = 0.5 * (a + b), 0.5 * (b - a)
    share = (b - a) / (t_end - t_start)[win]
    t = mid[:, None] + half[:, None] * x[None, :]
    q = 0.5 * qg[None, :] * share[:, None]
    w = np.repeat(win, m)
    order = np.argsort(w, kind="stable")  # window by window
    return t.ravel()[order], q.ravel()[order], w[order]
