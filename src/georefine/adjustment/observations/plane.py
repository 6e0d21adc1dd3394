"""Plane correspondences: planar LiDAR features observing planar objects (docs/ARCHITECTURE.md §4.3).

Paper 000 §2, Eq. 5; Pöppl et al. (2024). A planar *feature* is extracted from one view
(strip x scanner channel) and stored in the scanner frame ``s`` at its mean time ``t_f``:
centre ``c_s``, orthonormal in-plane axes ``k1_s, k2_s``. With the current trajectory and
mounting calibration it is georeferenced as

``c~ = p_w_b(t_f) + R_w_b(t_f) (p_b_s + R_b_s c_s)``,   ``k~_i = R_w_s(t_f) k_i_s``,
``R_w_s = R_w_b R_b_s``.

A planar *object* (all features matched to one physical surface) has a fixed reference frame
``(c0, k1_0, k2_0, n0)`` in ``w`` (orthonormal; e.g. from the initial matched features, see
:func:`plane_reference_frames`) and three parameters ``x = (d, alpha, beta)``:

``n = m / |m|``,  ``m = n0 + alpha k1_0 + beta k2_0``,   ``c = c0 + d n0``.

Each feature gives one observation of three whitened rows (normal distance and two slopes):

``r1 = n . (c~ - c) / sigma_d``,  ``r2 = n . k~1 / sigma_s``,  ``r3 = n . k~2 / sigma_s``.

The paper's Eq. 5 writes the distance as ``(c - c~) . n~`` (along the feature normal) and
divides the slopes by ``n . n~``. Here (docs/ARCHITECTURE.md §4.3) all three rows use the object normal: every
feature of an object refers to the same plane, the rows are linear in the georeferenced feature,
the slopes differ from the paper's by the factor ``n . n~ = 1 - O(slope²)`` and the distances
coincide where the slopes vanish (at a consistent solution); the sign is immaterial. The
standard deviations come from the feature's roughness, point count and extent (feature
extraction, ``lidar/planes.py``). A robust loss (Cauchy or Huber) on each observation's
squared norm guards against wrong matches.

Jacobians (right perturbations ``R <- R Exp(delta)``, docs/ARCHITECTURE.md §2; ``a . (R x)`` has the
derivative ``-(R^T a)^T skew(x) = (x x R^T a)^T`` w.r.t. ``delta``):

* trajectory: ``d r1 / d p_w_b = n^T / sigma_d`` times the position-basis weights of the six
  position knot states; w.r.t. the right tangent of ``R_w_b(t_f)`` with ``n_b = R_w_b^T n``:
  ``r1: (p_b_s + R_b_s c_s) x n_b / sigma_d``, ``r_i+1: (R_b_s k_i_s) x n_b / sigma_s``,
  chained with :attr:`~georefine.trajectory.spline.OrientationJacobians.dR` to the knots;
* boresight ``R_b_s <- R_b_s Exp(eps)`` with ``n_s = R_w_s^T n``: ``r1: c_s x n_s / sigma_d``,
  ``r_i+1: k_i_s x n_s / sigma_s``; lever arm: ``d r1 / d p_b_s = n_b^T / sigma_d``;
* object: ``dn/dm = (I - n n^T) / |m|``, ``dm/dalpha = k1_0``, ``dm/dbeta = k2_0``,
  ``dc/dd = n0``: ``r1: [-(n . n0), (c~ - c) . n_alpha, (c~ - c) . n_beta] / sigma_d``,
  ``r_i+1: [0, k~_i . n_alpha, k~_i . n_beta] / sigma_s``;
* range calibration ``(r0, k)`` (optional block): every range of the feature's points read
  ``(1 + k) r + r0`` of the true ``r``, so the measured centre is corrected to
  ``c_s' = (c_s - r0 u_s) / (1 + k)`` with ``u_s = c_s / |c_s|`` (the beam to the centre; the mean
  of the points' beams differs by the square of the feature's angular size, 1e-4 for a 1 m
  feature at 100 m). The axes are kept: a scale leaves a plane's angles, and an offset tilts a
  plane seen under an incidence ``phi`` by about ``r0 sin(phi) / r``, 0.3 mrad for 3 cm at
  100 m, a fraction of a slope's sigma. ``d r1 / d (r0, k) = n_s . (-u_s, -c_s') / (1 + k) / sigma_d``.
* range incidence bias ``b`` (optional block ``(1, 1)``): a return's range grows with the incidence
  ``phi`` of the beam on the surface (the footprint's far part pulls the pulse's centroid), modelled as
  ``b g`` with ``g = 1 / cos(phi) - 1`` (``cos(phi)`` floored at :data:`INCIDENCE_COS_FLOOR`): each feature's
  ``phi`` is fixed, between its own beam ``u_s`` and its normal ``a1 x a2``, and the bias adds to
  ``r0``: ``c_s' = (c_s - (r0 + b g) u_s) / (1 + k)``, ``d r1 / d b = -g n_s . u_s / (1 + k) / sigma_d``.
* channel angles (optional block ``(C, 2)``): channel ``c``'s beams leave ``d_tau_c`` steeper in facet
  tilt and ``d_alpha_c`` further in scan angle than the unit records (a facet's tilt, its angle on the
  mirror wheel, the encoder's offset), so a point recorded at range ``r`` along ``d(tau, alpha) =
  [sin tau, cos tau sin alpha, cos tau cos alpha]`` lies at ``r d(tau + d_tau_c, alpha + d_alpha_c)``.
  The feature's centre is corrected so, with ``(tau, alpha)`` of its own beam and ``rho`` its range
  after the range calibration: ``c_s' = rho d'``, ``d' = d(tau + d_tau_c, alpha + d_alpha_c)`` (the
  points' mean moves as its centre does to the square of the feature's angular size). The axes are
  kept: the correction turns a feature by about the angle errors themselves (mdeg), a fraction of a
  slope's sigma. ``d r1 / d (d_tau_c, d_alpha_c) = rho n_s . (d d/d tau, d d/d alpha) / sigma_d``; with
  both, the range rows take ``d'`` for ``u_s``. A scan-angle error common to all channels is a roll of the
  boresight (and, where the planes cannot see a common tilt, of the trajectory): the caller holds one
  channel as the reference (``channel`` -1) and estimates the others' errors against it.
* encoder error (optional block ``(1, 4)``): the scan-angle encoder's periodic error, the same on every
  channel, a smooth function of the recorded scan angle ``alpha`` across the field of view, written as
  ``e(alpha) = sum_j e_j P_j(alpha / A)`` with the Legendre polynomials ``P_1 .. P_4`` and ``A`` =
  :data:`ENCODER_HALF_WIDTH_DEG` (:func:`encoder_basis`). Not harmonics ``sin(k alpha + phi_k)``: over a
  field of view of 100 degrees ``sin alpha`` and ``sin 2 alpha`` correlate at 0.993 and ``cos alpha`` and
  ``cos 2 alpha`` at 0.999, while the Legendre terms are orthogonal over it. Their mean over the field of
  view is zero: the mean is a roll of the boresight. The beam leaves at ``alpha + d_alpha_c + e(alpha)``, so
  ``d r1 / d e_j = rho P_j n_s . d d/d alpha / sigma_d``.
* LiDAR time offset ``tau`` and drift ``kappa`` (optional blocks): the feature is georeferenced
  at ``t_f + tau + kappa (t_f - t_ref)`` (its time stamp is that far behind the navigation's
  time). ``d c~ / dt = v_w_b + R_w_b (omega x x_b)``, ``d k~_i / dt = R_w_b (omega x R_b_s k_i_s)``
  with the spline's velocity and body rate ``omega`` at that time, so
  ``d r1 / d tau = (n . v_w_b + (x_b x n_b) . omega) / sigma_d``,
  ``d r_i+1 / d tau = ((R_b_s k_i_s) x n_b) . omega / sigma_s``, and ``d / d kappa`` is
  ``(t_f - t_ref)`` times that.

References
----------
Pöppl, F., Ullrich, A., Mandlburger, G., Pfeifer, N. (2024): A flexible trajectory estimation
methodology for kinematic laser scanning. ISPRS J. Photogramm. Remote Sens. 215.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.observations.trajectory_blocks import (
    TrajectoryBlocks,
    checked_rows,
    orientation_jacobians,
    position_jacobians,
    single_element,
)
from georefine.adjustment.robust import RobustLoss
from georefine.trajectory.spline import KnotGrid, eval_orientation, knot_sum, locate_near, position_basis

__all__ = [
    "ENCODER_HALF_WIDTH_DEG",
    "ENCODER_TERMS",
    "FeatureFrames",
    "PlaneObservation",
    "encoder_basis",
    "incidence_term",
    "object_planes",
    "plane_parameters",
    "plane_reference_frames",
]

_ORTHONORMAL_TOL = 1e-6  # unit length and orthogonality of axes and reference frames
_MIN_COS_TILT = 1e-3  # |n . n0| below this: the plane is (nearly) perpendicular to its reference
_MIN_SIN_TILT = 0.1  # planes tilted less than ~6 deg take e_x, not the strike, as first axis


class FeatureFrames(NamedTuple):
    """Georeferenced features in ``w``: ``centre_w``, ``axis1_w``, ``axis2_w``, ``normal_w`` (F, 3) each."""

    centre_w: np.ndarray
    axis1_w: np.ndarray
    axis2_w: np.ndarray
    normal_w: np.ndarray


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


INCIDENCE_COS_FLOOR = float(np.cos(np.radians(80.0)))
"""``cos(phi)`` floor of :func:`incidence_term`: beyond 80 degrees a plane's footprint is a streak."""


def incidence_term(beam: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """``g = 1 / cos(phi) - 1`` (F,) of unit beams and surface normals (F, 3), either side; ``cos(phi)`` floored
    at :data:`INCIDENCE_COS_FLOOR`."""
    n = normal / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)[:, None]
    return 1.0 / np.maximum(np.abs(_dot(beam, n)), INCIDENCE_COS_FLOOR) - 1.0


ENCODER_HALF_WIDTH_DEG = 50.0
"""``A`` of :func:`encoder_basis`: half the field of view of a wide polygon scanner (the polynomials stay
bounded by 1 inside it, and grow as ``|alpha / A|^4`` outside)."""
ENCODER_TERMS = 4
"""Number of encoder-error terms ``P_1 .. P_4``."""


def encoder_basis(alpha: np.ndarray) -> np.ndarray:
    """Legendre polynomials ``P_1 .. P_4`` (N, 4) of ``x = alpha / A`` for scan angles ``alpha`` (rad), ``A`` =
    :data:`ENCODER_HALF_WIDTH_DEG`: the encoder error is ``encoder_basis(alpha) @ e`` (module docstring)."""
    x = np.asarray(alpha, dtype=float) / np.radians(ENCODER_HALF_WIDTH_DEG)
    x2 = x * x
    return np.stack([x, 0.5 * (3.0 * x2 - 1.0), 0.5 * x * (5.0 * x2 - 3.0),
                     0.125 * ((35.0 * x2 - 30.0) * x2 + 3.0)], axis=-1)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", a, b)


def plane_reference_frames(
    centre_w: np.ndarray, normal_w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal reference frames ``(c0, k1_0, k2_0, n0)`` of planar objects.

    Parameters
    ----------
    centre_w : (O, 3)
        A point on each plane (m, ``w``), e.g. the mean of its matched features' centres.
    normal_w : (O, 3)
        Plane normals (any length > 0, any sign).

    Returns
    -------
    c0, k1_0, k2_0, n0 : (O, 3) each
        ``c0 = centre_w``; ``n0`` the unit normal; ``k1_0`` the horizontal strike direction
        ``normalize(e_z x n0)`` of planes tilted by more than ~6 deg, else ``e_x`` projected into
        the plane; ``k2_0 = n0 x k1_0`` (the dip direction), so ``[k1_0 k2_0 n0]`` is a
        right-handed rotation.
    """
    c0 = np.array(centre_w, dtype=float).reshape(-1, 3)
    normal = np.asarray(normal_w, dtype=float).reshape(c0.shape)
    length = np.linalg.norm(normal, axis=1)
    if not np.all(np.isfinite(c0)) or not np.all(length > 0):
        raise ValueError("plane_reference_frames: centres must be finite and normals non-zero")
    n0 = normal / length[:, None]
    strike = np.cross(np.array([0.0, 0.0, 1.0]), n0)
    flat = np.linalg.norm(strike, axis=1) < _MIN_SIN_TILT
    east = np.array([1.0, 0.0, 0.0]) - n0[:, 0:1] * n0
    k1 = _unit(np.where(flat[:, None], east, strike))
    return c0, k1, np.cross(n0, k1), n0


def object_planes(
    c0: np.ndarray, k1_0: np.ndarray, k2_0: np.ndarray, n0: np.ndarray, params: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Object planes from their reference frames and parameters.

    Parameters
    ----------
    c0, k1_0, k2_0, n0 : (O, 3)
        Reference frames in ``w``.
    params : (O, 3)
        ``(d, alpha, beta)``: offset along ``n0`` (m) and the two slopes.

    Returns
    -------
    c, n : (O, 3)
        ``c = c0 + d n0`` (m) and ``n = normalize(n0 + alpha k1_0 + beta k2_0)``.
    """
    params = np.asarray(params, dtype=float)
    m = n0 + params[:, 1:2] * k1_0 + params[:, 2:3] * k2_0
    return c0 + params[:, 0:1] * n0, _unit(m)


def plane_parameters(
    c0: np.ndarray,
    k1_0: np.ndarray,
    k2_0: np.ndarray,
    n0: np.ndarray,
    point_w: np.ndarray,
    normal_w: np.ndarray,
) -> np.ndarray:
    """Parameters ``(d, alpha, beta)`` of given planes in given reference frames.

    The inverse of :func:`object_planes` (up to the sign of the normal): the plane through
    ``point_w`` with normal ``normal_w`` has ``alpha = n.k1_0 / n.n0``, ``beta = n.k2_0 / n.n0``
    and ``d = n.(point_w - c0) / n.n0``. Use it to start objects from known planes or to
    re-anchor the reference frames after an adjustment.

    Parameters
    ----------
    c0, k1_0, k2_0, n0 : (O, 3)
        Reference frames in ``w``.
    point_w, normal_w : (O, 3)
        A point on each plane (m) and its normal (any length, any sign).

    Returns
    -------
    (O, 3)

    Raises
    ------
    ValueError
        If a plane is perpendicular to its reference plane (no finite parameters).
    """
    n = np.asarray(normal_w, dtype=float).reshape(-1, 3)
    cos_tilt = _dot(n, n0) / np.linalg.norm(n, axis=1)
    if not np.all(np.abs(cos_tilt) > _MIN_COS_TILT):
        bad = np.flatnonzero(~(np.abs(cos_tilt) > _MIN_COS_TILT))
        raise ValueError(f"plane_parameters: planes {bad[:10].tolist()} are perpendicular to their reference planes")
    along = _dot(n, n0)
    point = np.asarray(point_w, dtype=float).reshape(n.shape)
    return np.column_stack([_dot(n, point - c0) / along, _dot(n, k1_0) / along, _dot(n, k2_0) / along])


def _beam(tau: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Unit beams ``[sin tau, cos tau sin alpha, cos tau cos alpha]`` (F, 3)."""
    ct = np.cos(tau)
    return np.column_stack([np.sin(tau), ct * np.sin(alpha), ct * np.cos(alpha)])


def _as_rows(name: str, value, n: int, width: int | None = 3) -> np.ndarray:
    return checked_rows("PlaneObservation", name, value, n, width)


def _check_orthonormal(label: str, vectors: dict[str, np.ndarray]) -> None:
    """Raise if the named (n, 3) vectors are not unit length and pairwise orthogonal."""
    names = list(vectors)
    bad = np.zeros(next(iter(vectors.values())).shape[0], dtype=bool)
    for i, a in enumerate(names):
        bad |= np.abs(np.linalg.norm(vectors[a], axis=1) - 1.0) > _ORTHONORMAL_TOL
        for b in names[i + 1 :]:
            bad |= np.abs(_dot(vectors[a], vectors[b])) > _ORTHONORMAL_TOL
    if np.any(bad):
        idx = np.flatnonzero(bad)
        raise ValueError(
            f"PlaneObservation: {', '.join(names)} of {label} {idx[:10].tolist()} "
            f"({idx.size} in all) are not orthonormal (tolerance {_ORTHONORMAL_TOL:g})"
        )


@dataclass
class PlaneObservation:
    """Plane correspondences (feature -> object) observing a spline trajectory.

    One observation of three whitened rows per feature (module docstring). The group reads
    the trajectory blocks, the object block and, when named, a boresight and a lever-arm
    block; any of them may be held constant in the :class:`~georefine.adjustment.problem.Problem`.

    Parameters
    ----------
    grid
        Knot grid of the trajectory.
    time : (F,)
        Feature mean times, s relative to the dataset epoch, inside the grid's span.
    centre_s, axis1_s, axis2_s : (F, 3)
        Feature centres (m) and orthonormal in-plane axes in the scanner frame ``s``.
    sigma_d : (F,) or scalar
        Standard deviation of the normal distance (m).
    sigma_slope : (F,) or scalar
        Standard deviation of the two slopes (rad).
    object_index : (F,) int
        Object of each feature (element of the ``objects`` block).
    c0, k1, k2, n0 : (O, 3)
        Object reference frames in ``w`` (orthonormal ``k1, k2, n0``).
    p_b_s : (3,)
        Scanner origin in the body frame (m); used when ``lever_arm`` is None.
    R_b_s : (3, 3)
        Boresight (nominal); used when ``boresight`` is None.
    objects
        Euclidean block ``(O, 3)`` of ``(d [m], alpha, beta)``.
    boresight
        Optional SO(3) block ``(1, 3, 3)`` holding ``R_b_s`` (right perturbation
        ``R_b_s Exp(eps)``, scanner frame).
    lever_arm
        Optional Euclidean block ``(1, 3)`` holding ``p_b_s`` (m).
    time_offset
        Optional Euclidean block ``(1, 1)``: the LiDAR time offset ``tau`` (s) added to every
        feature time (module docstring).
    time_drift
        Optional Euclidean block ``(1, 1)``: the drift ``kappa`` (s/s) of the LiDAR clock,
        adding ``kappa (t_f - time_reference)``.
    time_reference
        ``t_ref`` of the drift (s); default the middle of the feature times.
    range_calibration
        Optional Euclidean block ``(1, 2)``: the scanner's range offset ``r0`` (m) and scale error
        ``k`` (module docstring).
    range_incidence
        Optional Euclidean block ``(1, 1)``: a range bias ``b`` (m) growing with the incidence angle as
        ``b (1 / cos(phi) - 1)`` (module docstring).
    channel : (F,) int, optional
        Element of ``channel_angles`` for each feature (needed with it); -1: a channel without
        correction (the reference channel).
    channel_angles
        Optional Euclidean block ``(C, 2)``: each channel's tilt and scan-angle error (rad; module docstring).
    encoder
        Optional Euclidean block ``(1, 4)``: the encoder error's Legendre coefficients (rad; module docstring).
    blocks
        Trajectory block names.
    loss
        Robust loss per feature (Cauchy or Huber against wrong matches); None = plain LS.
    name
        Group name.
    """

    grid: KnotGrid
    time: np.ndarray
    centre_s: np.ndarray
    axis1_s: np.ndarray
    axis2_s: np.ndarray
    sigma_d: np.ndarray
    sigma_slope: np.ndarray
    object_index: np.ndarray
    c0: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    n0: np.ndarray
    p_b_s: np.ndarray
    R_b_s: np.ndarray
    objects: str = "plane_params"
    boresight: str | None = None
    lever_arm: str | None = None
    time_offset: str | None = None
    time_drift: str | None = None
    time_reference: float | None = None
    range_calibration: str | None = None
    range_incidence: str | None = None
    channel: np.ndarray | None = None
    channel_angles: str | None = None
    encoder: str | None = None
    blocks: TrajectoryBlocks = field(default_factory=TrajectoryBlocks)
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none
    name: str = "planes"

    def __post_init__(self) -> None:
        self.time = np.atleast_1d(np.asarray(self.time, dtype=float))
        if self.time.ndim != 1:
            raise ValueError(f"PlaneObservation: time must be 1-D, found shape {self.time.shape}")
        f = self.time.size
        self.centre_s = _as_rows("centre_s", self.centre_s, f)
        self.axis1_s = _as_rows("axis1_s", self.axis1_s, f)
        self.axis2_s = _as_rows("axis2_s", self.axis2_s, f)
        self.sigma_d = _as_rows("sigma_d", self.sigma_d, f, None)
        self.sigma_slope = _as_rows("sigma_slope", self.sigma_slope, f, None)
        if np.any(self.sigma_d <= 0) or np.any(self.sigma_slope <= 0):
            raise ValueError("PlaneObservation: sigma_d and sigma_slope must be positive")
        _check_orthonormal("features", {"axis1_s": self.axis1_s, "axis2_s": self.axis2_s})
        if np.ndim(self.c0) != 2:
            raise ValueError(f"PlaneObservation: c0 must have shape (O, 3), found {np.shape(self.c0)}")
        n_obj = np.shape(self.c0)[0]
        self.c0, self.k1, self.k2, self.n0 = (
            _as_rows(label, v, n_obj) for label, v in (("c0", self.c0), ("k1", self.k1), ("k2", self.k2), ("n0", self.n0))
        )
        _check_orthonormal("objects", {"k1": self.k1, "k2": self.k2, "n0": self.n0})
        idx = np.asarray(self.object_index)
        if idx.shape != (f,) or (f and not np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(f"PlaneObservation: object_index must be ({f},) integers, found {idx.shape} {idx.dtype}")
        if f and (idx.min() < 0 or idx.max() >= n_obj):
            raise ValueError(f"PlaneObservation: object_index must lie in [0, {n_obj}), found {idx.min()} .. {idx.max()}")
        self.object_index = idx.astype(np.int64)
        self.p_b_s = np.asarray(self.p_b_s, dtype=float).reshape(3)
        self.R_b_s = np.asarray(self.R_b_s, dtype=float).reshape(3, 3)
        if np.abs(self.R_b_s @ self.R_b_s.T - np.eye(3)).max() > _ORTHONORMAL_TOL or np.linalg.det(self.R_b_s) <= 0:
            raise ValueError("PlaneObservation: R_b_s is not a rotation matrix")
        if self.time_reference is None:
            self.time_reference = 0.5 * float(self.time.min() + self.time.max()) if f else 0.0
        self._k, u = self.grid.locate(self.time) if f else (np.zeros(0, np.int64), np.zeros(0))
        self._w0 = position_basis(u, self.grid.dt, 0)
        self._w_d = 1.0 / self.sigma_d
        self._w_s = 1.0 / self.sigma_slope
        self._rows = np.arange(3 * f).reshape(f, 3)
        self._obs = np.repeat(np.arange(f), 3)
        self._beam_s = self.centre_s / np.maximum(np.linalg.norm(self.centre_s, axis=1), 1e-9)[:, None]
        self._incidence_g = incidence_term(self._beam_s, np.cross(self.axis1_s, self.axis2_s))
        if self.channel_angles is not None:
            if self.channel is None or np.shape(self.channel) != (f,):
                raise ValueError(f"PlaneObservation: channel_angles needs the channel of each of the {f} features")
            self.channel = np.asarray(self.channel, dtype=np.int64)
        if self.channel_angles is not None or self.encoder is not None:
            r = np.linalg.norm(self.centre_s, axis=1)
            self._tau = np.arcsin(np.clip(self.centre_s[:, 0] / np.maximum(r, 1e-9), -1.0, 1.0))
            self._alpha = np.arctan2(self.centre_s[:, 1], self.centre_s[:, 2])
            self._encoder_basis = encoder_basis(self._alpha)

    @property
    def n_features(self) -> int:
        """Number of features (observations) ``F``."""
        return int(self.time.size)

    @property
    def n_objects(self) -> int:
        """Number of objects ``O`` (elements of the object block)."""
        return int(self.c0.shape[0])

    # -- model ----------------------------------------------------------------------------------
    def calibration(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Current ``(R_b_s (3,3), p_b_s (3,))``: from the blocks when named, else the fixed ones."""
        R_b_s, p_b_s = self.R_b_s, self.p_b_s
        if self.boresight is not None:
            R_b_s = single_element(values, self.boresight, (3, 3))
        if self.lever_arm is not None:
            p_b_s = single_element(values, self.lever_arm, (3,))
        return R_b_s, p_b_s

    def object_planes(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Current object planes: centres ``c`` (O, 3) m and unit normals ``n`` (O, 3) in ``w``."""
        return object_planes(self.c0, self.k1, self.k2, self.n0, self._params(values))

    def feature_frames(self, values: Mapping[str, np.ndarray]) -> FeatureFrames:
        """Features georeferenced with the current trajectory, calibration and time offset (``w``)."""
        _, R_w_b, R_b_s, _, centre_w, _ = self._pose(values, jacobians=False)
        R_w_s = R_w_b @ R_b_s
        k1_w = np.einsum("nij,nj->ni", R_w_s, self.axis1_s)
        k2_w = np.einsum("nij,nj->ni", R_w_s, self.axis2_s)
        return FeatureFrames(centre_w, k1_w, k2_w, np.cross(k1_w, k2_w))

    def residual_norms(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """Norm of each feature's whitened 3-vector (F,), e.g. to flag wrong matches after a solve."""
        r = self.linearize(values, jacobians=False).residuals.reshape(-1, 3)
        return np.linalg.norm(r, axis=1)

    def feature_times(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """Times (F,) the features are georeferenced at: their stamps plus the current time offset and drift."""
        t = self.time
        if self.time_offset is not None:
            t = t + single_element(values, self.time_offset, (1,))[0]
        if self.time_drift is not None:
            t = t + single_element(values, self.time_drift, (1,))[0] * (self.time - self.time_reference)
        return t

    def _located(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(t, k, u, w0)``: feature times, their knot intervals, normalised times and position basis.

        Without time parameters the stamps' look-up made at construction; with them the shifted
        times, clamped to the grid (the caller keeps the features a margin inside it), in the
        intervals of the stamps while the shift stays within half an interval
        (:func:`~georefine.trajectory.spline.locate_near`): the Jacobian keeps its structure while
        the offset moves. On the corridor's G/I/L features crossing knots made every outer
        iteration analyse ``J`` three times and factorise symbolically twice (1.9 s and 1.1 s of a
        20 s adjustment).
        """
        if self.time_offset is None and self.time_drift is None:
            return self.time, self._k, None, self._w0
        t = np.clip(self.feature_times(values), self.grid.t_start, self.grid.t_end)
        k, u = locate_near(self.grid, t, self._k)
        return t, k, u, position_basis(u, self.grid.dt, 0)

    def _params(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        params = np.asarray(values[self.objects], dtype=float)
        if params.shape != (self.n_objects, 3):
            raise ValueError(f"block {self.objects!r} must have shape ({self.n_objects}, 3), found {params.shape}")
        return params

    def _timed(self) -> bool:
        return self.time_offset is not None or self.time_drift is not None

    def centres_s(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """Feature centres in ``s`` (F, 3) with the current range calibration and channel angles applied
        (module docstring)."""
        return self._calibrated(values)[0]

    def _calibrated(self, values: Mapping[str, np.ndarray]):
        """``(c_s', d', rho, angles)``: the corrected centres, their beams and ranges, and each feature's
        ``(d_tau, d_alpha)`` (None without ``channel_angles`` and ``encoder``)."""
        c_s, beam = self.centre_s, self._beam_s
        if self.range_incidence is not None:
            b = single_element(values, self.range_incidence, (1,))[0]
            c_s = c_s - (b * self._incidence_g)[:, None] * beam
        if self.range_calibration is not None:
            r0, k = single_element(values, self.range_calibration, (2,))
            c_s = (c_s - r0 * beam) / (1.0 + k)
        if self.channel_angles is None and self.encoder is None:
            return c_s, beam, None, None
        a = np.zeros((self.n_features, 2))
        if self.channel_angles is not None:
            angles = np.asarray(values[self.channel_angles], dtype=float)
            if (angles.ndim != 2 or angles.shape[1] != 2
                    or (self.channel.size and self.channel.max() >= angles.shape[0])):
                raise ValueError(f"block {self.channel_angles!r} must have shape (C, 2) with C > "
                                 f"{int(self.channel.max()) if self.channel.size else -1}, found {angles.shape}")
            on = self.channel >= 0
            a[on] = angles[self.channel[on]]
        if self.encoder is not None:
            a[:, 1] += self._encoder_basis @ single_element(values, self.encoder, (ENCODER_TERMS,))
        rho = np.linalg.norm(c_s, axis=1)
        d = _beam(self._tau + a[:, 0], self._alpha + a[:, 1])
        return rho[:, None] * d, d, rho, a

    def _pose(self, values: Mapping[str, np.ndarray], jacobians: bool, located=None):
        """``(ev, R_w_b, R_b_s, x_b, c~, c_s)``: spline attitude, calibration, centre in b, centre in w,
        centre in s (range-calibrated).

        With time parameters and ``jacobians`` the body rate is evaluated too (``ev.omega_wb_b``).
        """
        P, V, A, R, W = self.blocks.knots(values)
        t, k, u, w0 = located if located is not None else self._located(values)
        p = knot_sum(P, V, A, k, w0)
        ev = eval_orientation(self.grid, R, W, t, rate=jacobians and self._timed(), jacobians=jacobians,
                              located=None if u is None else (k, u))
        R_b_s, p_b_s = self.calibration(values)
        c_s = self.centres_s(values)
        x_b = p_b_s + c_s @ R_b_s.T  # feature centre relative to the IMU, body frame
        return ev, ev.R_w_b, R_b_s, x_b, p + np.einsum("nij,nj->ni", ev.R_w_b, x_b), c_s

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        """Whitened residuals (3 rows per feature) and Jacobian blocks; see the module docstring."""
        params = self._params(values)
        if self.n_features == 0:
            return Linearization(np.zeros(0), [], np.zeros(0, dtype=np.int64))
        located = self._located(values)
        ev, R_w_b, R_b_s, x_b, c_t, c_s = self._pose(values, jacobians, located)
        R_w_s = R_w_b @ R_b_s
        k1_t = np.einsum("nij,nj->ni", R_w_s, self.axis1_s)
        k2_t = np.einsum("nij,nj->ni", R_w_s, self.axis2_s)
        j = self.object_index
        m = self.n0[j] + params[j, 1:2] * self.k1[j] + params[j, 2:3] * self.k2[j]
        m_norm = np.linalg.norm(m, axis=1)
        n = m / m_norm[:, None]
        e = c_t - (self.c0[j] + params[j, 0:1] * self.n0[j])
        w_d, w_s = self._w_d, self._w_s
        r = np.column_stack([_dot(n, e) * w_d, _dot(n, k1_t) * w_s, _dot(n, k2_t) * w_s])
        if not jacobians:
            return Linearization(r.ravel(), [], self._obs)

        rows, f = self._rows, self.n_features
        scale = np.column_stack([w_d, w_s, w_s])[:, :, None]  # (F, 3, 1) row whitening
        _, k_t, u_t, w0_t = located
        jac = position_jacobians(self.blocks, rows[:, :1], k_t, w0_t, (n * w_d[:, None])[:, None, :])
        # Attitude of the body: a . (R_w_b x) -> x x (R_w_b^T a) per right tangent.
        n_b = np.einsum("nji,nj->ni", R_w_b, n)
        lever_b = np.stack([x_b, self.axis1_s @ R_b_s.T, self.axis2_s @ R_b_s.T], axis=1)  # (F, 3, 3)
        M_R = np.cross(lever_b, n_b[:, None, :]) * scale
        jac += orientation_jacobians(self.blocks, rows, ev.jacobians, M_R)
        # Objects: d r / d (d, alpha, beta).
        dn_da = (self.k1[j] - n * _dot(n, self.k1[j])[:, None]) / m_norm[:, None]
        dn_db = (self.k2[j] - n * _dot(n, self.k2[j])[:, None]) / m_norm[:, None]
        vecs = np.stack([e, k1_t, k2_t], axis=1)  # (F, 3 rows, 3)
        J_obj = np.zeros((f, 3, 3))
        J_obj[:, 0, 0] = -_dot(n, self.n0[j])
        J_obj[:, :, 1] = np.einsum("nri,ni->nr", vecs, dn_da)
        J_obj[:, :, 2] = np.einsum("nri,ni->nr", vecs, dn_db)
        jac.append(JacobianBlock(self.objects, rows, j, J_obj * scale))
        zeros = np.zeros(f, dtype=np.int64)
        if (self.boresight is not None or self.range_calibration is not None or self.channel_angles is not None
                or self.range_incidence is not None or self.encoder is not None):
            n_s = np.einsum("nji,nj->ni", R_w_s, n)
            _, beam, rho, a = self._calibrated(values)
        if self.boresight is not None:
            feat_s = np.stack([c_s, self.axis1_s, self.axis2_s], axis=1)
            jac.append(JacobianBlock(self.boresight, rows, zeros, np.cross(feat_s, n_s[:, None, :]) * scale))
        if self.range_calibration is not None:
            k = single_element(values, self.range_calibration, (2,))[1]
            J_rc = -np.column_stack([_dot(n_s, beam), _dot(n_s, c_s)]) * (w_d / (1.0 + k))[:, None]
            jac.append(JacobianBlock(self.range_calibration, rows[:, :1], zeros, J_rc[:, None, :]))
        if self.range_incidence is not None:
            k = single_element(values, self.range_calibration, (2,))[1] if self.range_calibration is not None else 0.0
            J_ri = -_dot(n_s, beam) * self._incidence_g * w_d / (1.0 + k)
            jac.append(JacobianBlock(self.range_incidence, rows[:, :1], zeros, J_ri[:, None, None]))
        if self.channel_angles is not None or self.encoder is not None:
            tau, alpha = self._tau + a[:, 0], self._alpha + a[:, 1]
            st, ct, sa, ca = np.sin(tau), np.cos(tau), np.sin(alpha), np.cos(alpha)
            d_tau = np.column_stack([ct, -st * sa, -st * ca])
            d_alpha = np.column_stack([np.zeros_like(ct), ct * ca, -ct * sa])
            J_ch = np.column_stack([_dot(n_s, d_tau), _dot(n_s, d_alpha)]) * (rho * w_d)[:, None]
        if self.channel_angles is not None:
            on = self.channel >= 0
            jac.append(JacobianBlock(self.channel_angles, rows[on, :1], self.channel[on], J_ch[on, None, :]))
        if self.encoder is not None:
            jac.append(JacobianBlock(self.encoder, rows[:, :1], zeros,
                                     (J_ch[:, 1:2] * self._encoder_basis)[:, None, :]))
        if self.lever_arm is not None:
            jac.append(JacobianBlock(self.lever_arm, rows[:, :1], zeros, (n_b * w_d[:, None])[:, None, :]))
        if self._timed():
            P, V, A, _, _ = self.blocks.knots(values)
            v = knot_sum(P, V, A, k_t, position_basis(u_t, self.grid.dt, 1))
            # d r / d t: velocity along n for the centre, the body rate turning lever and axes.
            dr_dt = np.einsum("nri,ni->nr", np.cross(lever_b, n_b[:, None, :]), ev.omega_wb_b)
            dr_dt[:, 0] += _dot(n, v)
            dr_dt = dr_dt[:, :, None] * scale  # (F, 3, 1)
            if self.time_offset is not None:
                jac.append(JacobianBlock(self.time_offset, rows, zeros, dr_dt))
            if self.time_drift is not None:
                jac.append(JacobianBlock(self.time_drift, rows, zeros,
                                         dr_dt * (self.time - self.time_reference)[:, None, None]))
        return Linearization(r.ravel(), jac, self._obs)

