"""IMU specific-force and angular-rate observations (docs/ARCHITECTURE.md §4.3, §4.6; paper 000 Eq. 4).

At time ``t`` the model of the accelerometer and gyro readings is

``f~ = (I + S_f) R_w_b^T (p''_w + 2 omega_ie_w x p'_w - g_w(p_w)) + b_f(t)``
``w~ = (I + S_g) (omega_wb_b + R_w_b^T omega_ie_w) + b_g(t)``

with piecewise-linear biases on their own knots and constant diagonal scale factors.

Down-sampling (Pöppl et al. 2025): consecutive samples are averaged over windows
(``processing.trajectory.imu_window_s``, default 0.02 s) and compared with the model averaged
the same way, so the adjustment size follows the window rate, not the IMU rate. How depends on
what a sample is (``ImuData.kind``, :mod:`georefine.io.imu`):

* ``"rates"``, the sensor's value at its time tag: the model's mean at the window's sample
  times, exact whatever the motion. A quadrature of the continuous mean instead (the samples
  as its midpoint rule) differs from the samples' mean by ``(2 pi f dt)^2 / 24`` of a line at
  ``f``: 0.7 % at 13 Hz and 200 Hz, which with rotor vibration and a navigation-grade IMU is
  up to 12 times its window noise (BENCHMARKS.md, Operating conditions);
* ``"increments"``, the mean over the interval that ends at the time tag: the window covers
  ``(t_first - dt, t_last]`` and the model's continuous mean over it is a Gauss-Legendre
  quadrature (``nodes``).

A window's standard deviation follows from the noise density ``N`` (ARW/VRW): for ``n``
samples at rate ``f`` the mean has ``sigma = N sqrt(f / n)``. Windows never span a sampling gap.

Jacobians (right perturbation ``R <- R Exp(delta)``): ``d(R^T x)/d delta = skew(R^T x)``;
``d(R^T x)/d p'' = R^T``, ``d/d p' = 2 R^T skew(omega_ie_w)``, ``d/d p = -R^T G`` with
``G`` the normal-gravity gradient ``(gamma / r)(3 u u^T - I)`` (``u`` the up direction).
"""

from __future__ import annotations

from dataclasses import dataclass, field
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
    nodes: int = 3
    blocks: TrajectoryBlocks = field(default_factory=TrajectoryBlocks)
    loss: RobustLoss | None = None
    name: str = "imu"
    consumed_redundancy: float = 0.0

    def __post_init__(self) -> None:
        w = self.windows
        n = len(w)
        if w.kind == "rates":  # the mean at the samples: node i is sample i, weight 1/n (0 past a short window's end)
            i = np.arange(int(w.n_samples.max()))[:, None]
            step = (w.t_end - w.t_start) / w.n_samples
            t_nodes = w.t_start + (np.minimum(i, w.n_samples - 1) + 0.5) * step
            q = np.where(i < w.n_samples, 1.0 / w.n_samples, 0.0)
        else:
            x, qg = np.polynomial.legendre.leggauss(self.nodes)
            mid, half = 0.5 * (w.t_start + w.t_end), 0.5 * (w.t_end - w.t_start)
            t_nodes = mid + half * x[:, None]
            q = np.broadcast_to(0.5 * qg[:, None], (self.nodes, n))
        self._nodes = t_nodes.shape[0]
        # node-major: node i of all windows is a contiguous slice
        self._t = np.clip(t_nodes, self.grid.t_start, self.grid.t_end).ravel()
        self._q = np.ascontiguousarray(q)  # (nodes, W) weights
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
        return dict(p=p, g=g, ev=ev, Rt=Rt, Rt_x=Rt_x, Rt_W=Rt_W, rate=rate, s_a=s_a, s_g=s_g, f=f_node, w=w_node)

    def _average(self, node_values: np.ndarray) -> np.ndarray:
        return np.einsum("in,ind->nd", self._q, node_values.reshape(self._nodes, self._n, 3))

    def predict(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Modelled window means ``(acc (W,3), gyro (W,3))``."""
        terms = self._node_terms(values, jacobians=False)
        return self._average(terms["f"]), self._average(terms["w"])

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        terms = self._node_terms(values, jacobians)
        wins = self.windows
        r_f = (self._average(terms["f"]) - wins.acc) / self._sa[:, None]
        r_g = (self._average(terms["w"]) - wins.gyro) / self._sg[:, None]
        r = np.concatenate([r_f, r_g], axis=1).ravel()
        jac: list[JacobianBlock] = []
        if jacobians:
            jac = self._jacobians(terms)
        return Linearization(r, jac, self._obs)

    def _jacobians(self, t) -> list[JacobianBlock]:
        n, out = self._n, []
        omega_ie = self.frame.omega_ie_w
        g = t["g"]
        gamma = np.linalg.norm(g, axis=1)
        up = -g / gamma[:, None]
        G = (gamma / WGS84_A)[:, None, None] * (3.0 * up[:, :, None] * up[:, None, :] - np.eye(3))
        Da, Dg = np.diag(1.0 + t["s_a"]), np.diag(1.0 + t["s_g"])
        ev = t["ev"]
        eye = np.eye(3)
        for i in range(self._nodes):
            sl = slice(i * n, (i + 1) * n)
            ca = (self._q[i] / self._sa)[:, None, None]
            cg = (self._q[i] / self._sg)[:, None, None]
            Rt = t["Rt"][sl]
            DRt = Da @ Rt
            M_a = ca * DRt
            M_v = ca * DRt @ (2.0 * skew(omega_ie))
            M_p = -ca * DRt @ G[sl]
            k = self._k[sl]
            w0, w1, w2 = (b[sl] for b in self._basis)
            for j, name in enumerate(self.blocks.position_states):
                val = M_a * w2[:, j, None, None] + M_v * w1[:, j, None, None] + M_p * w0[:, j, None, None]
                out.append(JacobianBlock(name, self._rows_f, k if j < 3 else k + 1, val))
            jac_i = _slice_jacobians(ev.jacobians, sl)
            out += orientation_jacobians(self.blocks, self._rows_f, jac_i, ca * Da @ skew(t["Rt_x"][sl]))
            out += orientation_jacobians(
                self.blocks, self._rows_g, jac_i, cg * Dg @ skew(t["Rt_W"][sl]), cg * np.broadcast_to(Dg, (n, 3, 3))
            )
            for name, rows, jb, lb, c in (
                (self.acc_bias, self._rows_f, self._jb_a[sl], self._lb_a[sl], ca),
                (self.gyro_bias, self._rows_g, self._jb_g[sl], self._lb_g[sl], cg),
            ):
                out.append(JacobianBlock(name, rows, jb, c * (1.0 - lb)[:, None, None] * eye))
                out.append(JacobianBlock(name, rows, jb + 1, c * lb[:, None, None] * eye))
            zeros = np.zeros(n, dtype=np.int64)
            if self.acc_scale:
                d = t["Rt_x"][sl]
                out.append(JacobianBlock(self.acc_scale, self._rows_f, zeros, ca * (d[:, :, None] * eye)))
            if self.gyro_scale:
                d = t["rate"][sl]
                out.append(JacobianBlock(self.gyro_scale, self._rows_g, zeros, cg * (d[:, :, None] * eye)))
        return out


def _slice_jacobians(jac, sl):
    from georefine.trajectory.spline import OrientationJacobians

    return OrientationJacobians(jac.k[sl], jac.dR[sl], None if jac.domega is None else jac.domega[sl])
