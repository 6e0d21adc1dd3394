"""Classical strip adjustment: one rigid correction per strip, from the plane correspondences.

A baseline beside the trajectory-level adjustment (docs/ARCHITECTURE.md §4.5 step 5): the
strip-adjustment tools in common use (TerraMatch, OPALS StripAdjust) correct each strip as a whole
by a constant rotation and translation, or a low-order polynomial in time, estimated from
correspondences between overlapping strips. This module does that with the same planar features
and objects the G/I/L observes (§4.5 step 4), so the two methods can be compared on one project.

Model (per strip ``s``)
-----------------------
A fixed reference point ``c_s`` (the centroid of the strip's features used, in ``w``) and time
``t_s`` (their mean time). At time ``t`` the correction is the rotation and translation

``R_s(t) = Exp(omega_s + (t - t_s) omega_dot_s)``,  ``T_s(t) = T_s + (t - t_s) T_dot_s``

(``order`` 0: the rates are absent, a constant correction; ``order`` 1: a linear drift of the
rotation vector and the translation per second). A feature of strip ``s`` with centre ``x`` and
normal ``n`` in ``w`` under the preliminary trajectory, at its mean time ``t_f``, becomes

``x' = c_s + R_s(t_f) (x - c_s) + T_s(t_f)``,   ``n' = R_s(t_f) n``.

The rotation vectors are Euclidean parameters (the corrections are milli-degrees), so the drift
is a plain linear term; rotations are in ``w`` (left of ``R_w_b``).

Observations (:class:`StripPlaneObservation`)
---------------------------------------------
The planar objects of :mod:`georefine.lidar.correspondences` with their fixed frames
``(c0, k1, k2, n0)`` and unknown ``(d, alpha, beta)``: ``c = c0 + d n0``,
``n_o = normalize(n0 + alpha k1 + beta k2)`` (docs/ARCHITECTURE.md §4.3). Per feature three
whitened rows, as the plane observation of the G/I/L has them:

``r1 = n_o . (x' - c) / sigma_d``,  ``r2 = n_o . (R_s k1_f) / sigma_slope``,
``r3 = n_o . (R_s k2_f) / sigma_slope``,

``k1_f, k2_f`` an orthonormal pair of in-plane axes of the feature normal ``n`` (the slope sigma
is the same for both, so any pair serves), ``sigma_d`` and ``sigma_slope`` the feature's
(``sigma_d_m``, ``sigma_slope_rad``, §4.5 step 4). A robust loss (the plane observations' Cauchy
by default in the workflow) acts on each feature's three rows. Only objects seen from at least
``min_strips_per_object`` strips (default 2) are used: an object of one strip says nothing about
a constant correction of that strip.

Jacobians (``d (a . R v) / d phi = (v x R^T a)^T Jr(phi)`` for ``R = Exp(phi)``, ``Jr`` the
right Jacobian): ``r1`` w.r.t. ``omega_s``: ``((x - c_s) x n_b)^T Jr / sigma_d`` with
``n_b = R_s^T n_o``, ``r_i+1``: ``(k_i_f x n_b)^T Jr / sigma_slope``; w.r.t. ``T_s``:
``n_o^T / sigma_d``; the rates: ``(t_f - t_s)`` times these; the object parameters as in the
G/I/L's plane observation. Every one is checked against finite differences
(``tests/test_strip_adjustment.py``).

Datum
-----
Planes compare strips with one another, so a correction common to all strips (a rotation and a
translation of the whole block, and with ``order`` 1 a common drift) is not observed: the normal
matrix is singular. The GNSS frames the block, so each strip's correction has a zero-mean prior
whose sigmas the caller states (:class:`StripPriors`; e.g. the G/I's posterior attitude and
position sigmas). Without priors :func:`adjust_strips` raises; it never returns a solution
whose datum is arbitrary.

Solution and statistics
-----------------------
The engine of §4.4 (:class:`~georefine.adjustment.problem.Problem`, Levenberg-Marquardt, sparse
Cholesky): the problem is small (``6 S`` or ``12 S`` strip unknowns plus ``3 O`` object ones) but
sparse in the objects, and the engine gives the robust reweighting, the statistics and the
posterior covariance the other adjustments report. Posterior sigmas are those of ``N^-1``
times the variance factor where it exceeds 1 (as the trajectory adjustments state theirs,
:func:`~georefine.adjustment.gnss_imu.posterior_scale`). A variance factor above
:data:`MISFIT_VARIANCE_FACTOR`, or a strip whose median-based sigma of the normalised distance
residuals exceeds :data:`MISFIT_SIGMA`, means the per-strip model does not explain the
correspondences (the trajectory errors vary within a strip faster than the model): a warning
with the figures is logged and :attr:`StripCorrections.misfit` says so.

Applied to a trajectory (:func:`apply_strip_corrections`): inside strip ``s``'s time span
``R_w_b' = R_s(t) R_w_b`` and ``p' = c_s + R_s(t) (p - c_s) + T_s(t)``, which moves every point
georeferenced from the pose exactly as the features were moved (``x = p + R_w_b x_b``); outside
every span the trajectory is unchanged (it jumps at the spans' ends, as a strip-wise correction
does).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization
from georefine.adjustment.gnss_imu import posterior_scale
from georefine.adjustment.observations.prior import EuclideanPrior
from georefine.adjustment.problem import Problem
from georefine.adjustment.robust import RobustLoss
from georefine.adjustment.solver import SolveResult, SolverOptions
from georefine.errors import InputError
from georefine.geometry.rotation import exp_so3, right_jacobian, skew
from georefine.lidar.correspondences import PlanarObjects
from georefine.lidar.planes import PlanarFeatures
from georefine.trajectory.sampled import Trajectory

__all__ = [
    "MISFIT_SIGMA",
    "MISFIT_VARIANCE_FACTOR",
    "ROTATION",
    "ROTATION_RATE",
    "TRANSLATION",
    "TRANSLATION_RATE",
    "StripCorrections",
    "StripPlaneObservation",
    "StripPriors",
    "adjust_strips",
    "apply_strip_corrections",
    "correct_features",
    "in_plane_axes",
]

_log = logging.getLogger(__name__)

ROTATION = "strip_rotation"
"""Block of the rotation vectors ``omega_s`` (S, 3), rad, in ``w``."""
TRANSLATION = "strip_translation"
"""Block of the translations ``T_s`` (S, 3), m, in ``w``."""
ROTATION_RATE = "strip_rotation_rate"
"""Block of the rotation drifts ``omega_dot_s`` (S, 3), rad/s (``order`` 1)."""
TRANSLATION_RATE = "strip_translation_rate"
"""Block of the translation drifts ``T_dot_s`` (S, 3), m/s (``order`` 1)."""
OBJECTS = "plane_params"
"""Block of the object parameters ``(d, alpha, beta)`` (O, 3)."""

MISFIT_VARIANCE_FACTOR = 1.5
"""A variance factor above this (``sigma0`` above 1.22): the per-strip model does not fit the
correspondences. On the simulated block of the tests a constant model of strips drifting by up to
2 mdeg and 2 cm over a strip came out at 1.6, the linear model at 1.0."""
MISFIT_SIGMA = 1.5
"""A strip whose median-based sigma of the normalised distance residuals (``1.4826 median |r1|``)
exceeds this does not fit (robust to the few wrong matches a robust loss takes care of)."""

_MAD = 1.4826  # sigma of a normal distribution per median absolute value


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", a, b)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def in_plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal axes ``k1, k2`` (F, 3) of the planes with normals ``normal`` (F, 3):
    ``k1 = normalize(h x n)``, ``h = e_z`` (``e_x`` where ``|n_z| >= 0.9``), ``k2 = n x k1``."""
    n = _unit(np.asarray(normal, dtype=float).reshape(-1, 3))
    h = np.where((np.abs(n[:, 2]) < 0.9)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    k1 = _unit(np.cross(h, n))
    return k1, np.cross(n, k1)


def _sigma3(name: str, value) -> np.ndarray | None:
    """A prior sigma as (3,) float64 (a scalar is taken for all three axes), or None."""
    if value is None:
        return None
    try:
        a = np.broadcast_to(np.asarray(value, dtype=float), (3,)).copy()
    except (TypeError, ValueError):
        a = None
    if a is None or not np.all(np.isfinite(a) & (a > 0)):
        raise InputError("a prior sigma of the strip corrections must be finite and positive", field=name,
                         expected="a positive number or three (east, north, up)", found=repr(value))
    return a


@dataclass(frozen=True)
class StripPriors:
    """Zero-mean priors on every strip's correction: the datum (module docstring).

    Each is a scalar or three sigmas about (or along) the axes of ``w`` (east, north, up).

    Attributes
    ----------
    rotation_rad
        Sigma of ``omega_s`` (rad), e.g. the G/I's roll and pitch sigma about east and north and
        its heading sigma about up.
    translation_m
        Sigma of ``T_s`` (m), e.g. the G/I's position sigma.
    rotation_rate_rad_per_s, translation_rate_m_per_s
        Sigmas of the drifts (``order`` 1 needs them; ignored by ``order`` 0).
    """

    rotation_rad: np.ndarray | float
    translation_m: np.ndarray | float
    rotation_rate_rad_per_s: np.ndarray | float | None = None
    translation_rate_m_per_s: np.ndarray | float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.name in ("rotation_rad", "translation_m"):
                raise InputError("the strip corrections need a prior on the rotation and the translation",
                                 field=f.name, expected="sigmas (the datum)", found="None")
            object.__setattr__(self, f.name, _sigma3(f.name, value))

    def sigmas(self, order: int) -> dict[str, np.ndarray]:
        """Block name -> (3,) sigma for the blocks of ``order``."""
        out = {ROTATION: self.rotation_rad, TRANSLATION: self.translation_m}
        if order == 1:
            missing = [n for n, v in (("rotation_rate_rad_per_s", self.rotation_rate_rad_per_s),
                                      ("translation_rate_m_per_s", self.translation_rate_m_per_s)) if v is None]
            if missing:
                raise InputError("a strip adjustment of order 1 needs priors on the drifts: without them the "
                                 "drift common to all strips is not observed (the normal matrix is singular)",
                                 field=", ".join(missing), expected="sigmas", found="None")
            out |= {ROTATION_RATE: self.rotation_rate_rad_per_s, TRANSLATION_RATE: self.translation_rate_m_per_s}
        return out


# --------------------------------------------------------------------------- observation


@dataclass
class StripPlaneObservation:
    """Features of strips, corrected per strip, observing planar objects (module docstring).

    Parameters
    ----------
    centre_w, normal_w : (F, 3)
        Feature centres (m) and normals in ``w`` under the preliminary trajectory.
    time : (F,)
        Feature mean times, s relative to the dataset epoch.
    strip_index : (F,) int
        Element of the strip blocks each feature belongs to.
    reference_point : (S, 3)
        ``c_s`` (m, ``w``).
    reference_time : (S,)
        ``t_s`` (s).
    sigma_d, sigma_slope : (F,) or scalar
        Standard deviations of the distance (m) and of each slope (rad).
    object_index : (F,) int
        Object of each feature.
    c0, k1, k2, n0 : (O, 3)
        Object reference frames in ``w``.
    rotation, translation
        Euclidean blocks (S, 3) of ``omega_s`` and ``T_s``.
    rotation_rate, translation_rate
        Euclidean blocks (S, 3) of the drifts, or None (``order`` 0).
    objects
        Euclidean block (O, 3) of ``(d, alpha, beta)``.
    loss
        Robust loss per feature, or None.
    name
        Group name.
    """

    centre_w: np.ndarray
    normal_w: np.ndarray
    time: np.ndarray
    strip_index: np.ndarray
    reference_point: np.ndarray
    reference_time: np.ndarray
    sigma_d: np.ndarray
    sigma_slope: np.ndarray
    object_index: np.ndarray
    c0: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    n0: np.ndarray
    rotation: str = ROTATION
    translation: str = TRANSLATION
    rotation_rate: str | None = None
    translation_rate: str | None = None
    objects: str = OBJECTS
    loss: RobustLoss | None = None
    consumed_redundancy = 0.0  # degrees of freedom spent before the adjustment (ObservationGroup): none
    name: str = "strip_planes"
    _axes: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.time = np.atleast_1d(np.asarray(self.time, dtype=float))
        f = self.time.size
        self.centre_w = np.asarray(self.centre_w, dtype=float).reshape(f, 3)
        self.normal_w = _unit(np.asarray(self.normal_w, dtype=float).reshape(f, 3))
        self.sigma_d = np.broadcast_to(np.asarray(self.sigma_d, dtype=float), (f,)).copy()
        self.sigma_slope = np.broadcast_to(np.asarray(self.sigma_slope, dtype=float), (f,)).copy()
        if np.any(~(self.sigma_d > 0)) or np.any(~(self.sigma_slope > 0)):
            raise ValueError("StripPlaneObservation: sigma_d and sigma_slope must be positive")
        self.reference_point = np.asarray(self.reference_point, dtype=float).reshape(-1, 3)
        self.reference_time = np.asarray(self.reference_time, dtype=float).reshape(-1)
        n_strips = self.reference_point.shape[0]
        if self.reference_time.shape != (n_strips,):
            raise ValueError(f"StripPlaneObservation: reference_time must have shape ({n_strips},)")
        self.c0, self.k1, self.k2, self.n0 = (np.asarray(v, dtype=float).reshape(-1, 3)
                                              for v in (self.c0, self.k1, self.k2, self.n0))
        n_obj = self.c0.shape[0]
        for label, idx, n in (("strip_index", self.strip_index, n_strips), ("object_index", self.object_index, n_obj)):
            idx = np.asarray(idx)
            if idx.shape != (f,) or (f and (not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= n)):
                raise ValueError(f"StripPlaneObservation: {label} must be ({f},) integers in [0, {n})")
        self.strip_index = np.asarray(self.strip_index, dtype=np.int64)
        self.object_index = np.asarray(self.object_index, dtype=np.int64)
        if (self.rotation_rate is None) != (self.translation_rate is None):
            raise ValueError("StripPlaneObservation: give both drift blocks or neither")
        self._axes = in_plane_axes(self.normal_w) if f else (np.zeros((0, 3)), np.zeros((0, 3)))
        self._rows = np.arange(3 * f).reshape(f, 3)
        self._obs = np.repeat(np.arange(f), 3)

    @property
    def n_features(self) -> int:
        return int(self.time.size)

    @property
    def timed(self) -> bool:
        """Whether the corrections drift in time (``order`` 1)."""
        return self.rotation_rate is not None

    def _dt(self) -> np.ndarray:
        return self.time - self.reference_time[self.strip_index]

    def corrections(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Each feature's ``phi = omega_s + dt omega_dot_s`` and ``T_s(t_f)``, (F, 3) each."""
        s, dt = self.strip_index, self._dt()[:, None]
        phi = np.asarray(values[self.rotation], dtype=float)[s]
        trans = np.asarray(values[self.translation], dtype=float)[s]
        if self.timed:
            phi = phi + dt * np.asarray(values[self.rotation_rate], dtype=float)[s]
            trans = trans + dt * np.asarray(values[self.translation_rate], dtype=float)[s]
        return phi, trans

    def corrected(self, values: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Corrected centres and normals (F, 3) each, ``w``."""
        phi, trans = self.corrections(values)
        R = exp_so3(phi)
        c = self.reference_point[self.strip_index]
        x = c + np.einsum("nij,nj->ni", R, self.centre_w - c) + trans
        return x, np.einsum("nij,nj->ni", R, self.normal_w)

    def residual_rows(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """Whitened residuals (F, 3): distance, slope 1, slope 2."""
        return self.linearize(values, jacobians=False).residuals.reshape(-1, 3)

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        """Whitened residuals (3 rows per feature) and Jacobian blocks (module docstring)."""
        params = np.asarray(values[self.objects], dtype=float)
        if params.shape != (self.c0.shape[0], 3):
            raise ValueError(f"block {self.objects!r} must have shape ({self.c0.shape[0]}, 3), found {params.shape}")
        f = self.n_features
        if f == 0:
            return Linearization(np.zeros(0), [], np.zeros(0, dtype=np.int64))
        s, j = self.strip_index, self.object_index
        phi, trans = self.corrections(values)
        R = exp_so3(phi)
        u = self.centre_w - self.reference_point[s]
        a1, a2 = self._axes
        x = self.reference_point[s] + np.einsum("nij,nj->ni", R, u) + trans
        k1_t = np.einsum("nij,nj->ni", R, a1)
        k2_t = np.einsum("nij,nj->ni", R, a2)
        m = self.n0[j] + params[j, 1:2] * self.k1[j] + params[j, 2:3] * self.k2[j]
        m_norm = np.linalg.norm(m, axis=1)
        n = m / m_norm[:, None]
        e = x - (self.c0[j] + params[j, 0:1] * self.n0[j])
        w_d, w_s = 1.0 / self.sigma_d, 1.0 / self.sigma_slope
        r = np.column_stack([_dot(n, e) * w_d, _dot(n, k1_t) * w_s, _dot(n, k2_t) * w_s])
        if not jacobians:
            return Linearization(r.ravel(), [], self._obs)

        rows = self._rows
        scale = np.column_stack([w_d, w_s, w_s])[:, :, None]  # (F, 3, 1)
        n_b = np.einsum("nji,nj->ni", R, n)  # R^T n
        lever = np.stack([u, a1, a2], axis=1)  # (F, 3 rows, 3)
        J_phi = np.einsum("nri,nij->nrj", np.cross(lever, n_b[:, None, :]), right_jacobian(phi)) * scale
        J_t = (n * w_d[:, None])[:, None, :]  # (F, 1, 3): the distance row only
        jac = [JacobianBlock(self.rotation, rows, s, J_phi), JacobianBlock(self.translation, rows[:, :1], s, J_t)]
        if self.timed:
            dt = self._dt()[:, None, None]
            jac += [JacobianBlock(self.rotation_rate, rows, s, J_phi * dt),
                    JacobianBlock(self.translation_rate, rows[:, :1], s, J_t * dt)]
        dn_da = (self.k1[j] - n * _dot(n, self.k1[j])[:, None]) / m_norm[:, None]
        dn_db = (self.k2[j] - n * _dot(n, self.k2[j])[:, None]) / m_norm[:, None]
        vecs = np.stack([e, k1_t, k2_t], axis=1)
        J_obj = np.zeros((f, 3, 3))
        J_obj[:, 0, 0] = -_dot(n, self.n0[j])
        J_obj[:, :, 1] = np.einsum("nri,ni->nr", vecs, dn_da)
        J_obj[:, :, 2] = np.einsum("nri,ni->nr", vecs, dn_db)
        jac.append(JacobianBlock(self.objects, rows, j, J_obj * scale))
        return Linearization(r.ravel(), jac, self._obs)


# --------------------------------------------------------------------------- result


_STRIP_ARRAYS = {  # field -> (to_dict key, factor into the file's unit)
    "reference_point_w": ("reference_point_w_m", 1.0),
    "omega_rad": ("omega_mdeg", np.degrees(1.0) * 1e3),
    "translation_m": ("translation_m", 1.0),
    "omega_rate_rad_per_s": ("omega_rate_mdeg_per_s", np.degrees(1.0) * 1e3),
    "translation_rate_m_per_s": ("translation_rate_m_per_s", 1.0),
    "sigma_omega_rad": ("sigma_omega_mdeg", np.degrees(1.0) * 1e3),
    "sigma_translation_m": ("sigma_translation_m", 1.0),
    "sigma_omega_rate_rad_per_s": ("sigma_omega_rate_mdeg_per_s", np.degrees(1.0) * 1e3),
    "sigma_translation_rate_m_per_s": ("sigma_translation_rate_m_per_s", 1.0),
}
_STRIP_SCALARS = {"reference_time": "reference_time_s", "n_features": "n_features", "n_objects": "n_objects",
                  "rms_distance": "rms_distance", "rms_slope": "rms_slope",
                  "robust_sigma_distance": "robust_sigma_distance"}


@dataclass(frozen=True, eq=False)
class StripCorrections:
    """The estimated correction of every strip (module docstring), a struct of arrays over S strips.

    Attributes
    ----------
    order
        0 (constant) or 1 (linear in time).
    strip : (S,) int64
        Strip ids, ascending.
    reference_point_w : (S, 3)
        ``c_s`` (m, ``w``): the centroid of the strip's features used.
    reference_time : (S,)
        ``t_s`` (s relative to the dataset epoch): their mean time.
    omega_rad, translation_m : (S, 3)
        ``omega_s`` (rotation vector in ``w``, rad) and ``T_s`` (m) at ``t_s``.
    omega_rate_rad_per_s, translation_rate_m_per_s : (S, 3)
        The drifts (zero for ``order`` 0).
    sigma_omega_rad, sigma_translation_m, sigma_omega_rate_rad_per_s, sigma_translation_rate_m_per_s : (S, 3)
        Posterior sigmas per axis of ``w`` (the variance factor applied where it exceeds 1;
        zero for the drifts of ``order`` 0).
    n_features, n_objects : (S,) int64
        Features of the strip used, and objects they observe.
    rms_distance, rms_slope : (S,)
        RMS of the strip's normalised (whitened) distance and slope residuals.
    robust_sigma_distance : (S,)
        ``1.4826 median |r1|`` of its distance residuals (the misfit test, :data:`MISFIT_SIGMA`).
    variance_factor : float
        A-posteriori variance factor ``sigma0^2`` (robust weights applied).
    redundancy : int
        Rows minus unknowns.
    objects_used : int
        Planar objects in the adjustment.
    misfit : str or None
        Why the model does not fit the correspondences (the logged warning), or None.
    solve : SolveResult or None
        The solver's statistics.
    """

    order: int
    strip: np.ndarray
    reference_point_w: np.ndarray
    reference_time: np.ndarray
    omega_rad: np.ndarray
    translation_m: np.ndarray
    omega_rate_rad_per_s: np.ndarray
    translation_rate_m_per_s: np.ndarray
    sigma_omega_rad: np.ndarray
    sigma_translation_m: np.ndarray
    sigma_omega_rate_rad_per_s: np.ndarray
    sigma_translation_rate_m_per_s: np.ndarray
    n_features: np.ndarray
    n_objects: np.ndarray
    rms_distance: np.ndarray
    rms_slope: np.ndarray
    robust_sigma_distance: np.ndarray
    variance_factor: float
    redundancy: int
    objects_used: int
    misfit: str | None = None
    solve: SolveResult | None = None

    def __post_init__(self) -> None:
        strip = np.asarray(self.strip, dtype=np.int64).reshape(-1)
        s = strip.size
        object.__setattr__(self, "strip", strip)
        for name in _STRIP_ARRAYS:
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != (s, 3):
                raise ValueError(f"StripCorrections.{name} must have shape ({s}, 3), found {a.shape}")
            object.__setattr__(self, name, a)
        for name in _STRIP_SCALARS:
            a = np.asarray(getattr(self, name), dtype=np.int64 if name.startswith("n_") else float).reshape(-1)
            if a.shape != (s,):
                raise ValueError(f"StripCorrections.{name} must have shape ({s},), found {a.shape}")
            object.__setattr__(self, name, a)
        if self.order not in (0, 1):
            raise ValueError(f"StripCorrections.order must be 0 or 1, found {self.order}")

    def __len__(self) -> int:
        return int(self.strip.size)

    def index(self, strip: int) -> int:
        """Position of strip id ``strip`` in the arrays."""
        hit = np.flatnonzero(self.strip == int(strip))
        if hit.size == 0:
            raise KeyError(f"no correction for strip {strip} (have {self.strip.tolist()})")
        return int(hit[0])

    def rotation_vector(self, strip: int, t: np.ndarray) -> np.ndarray:
        """``phi_s(t) = omega_s + (t - t_s) omega_dot_s`` (M, 3) at times ``t`` (M,)."""
        i, t = self.index(strip), np.atleast_1d(np.asarray(t, dtype=float))
        return self.omega_rad[i] + (t - self.reference_time[i])[:, None] * self.omega_rate_rad_per_s[i]

    def at(self, strip: int, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The correction of strip ``strip`` at times ``t`` (M,): ``R_s(t)`` (M, 3, 3), ``T_s(t)`` (M, 3)."""
        i, t = self.index(strip), np.atleast_1d(np.asarray(t, dtype=float))
        trans = self.translation_m[i] + (t - self.reference_time[i])[:, None] * self.translation_rate_m_per_s[i]
        return exp_so3(self.rotation_vector(strip, t)), trans

    def to_dict(self) -> dict:
        """JSON-serialisable figures (mdeg and m; one record per strip)."""
        strips = []
        for k in range(len(self)):
            rec = {"strip": int(self.strip[k])}
            for name, key in _STRIP_SCALARS.items():
                v = getattr(self, name)[k]
                rec[key] = int(v) if name.startswith("n_") else float(v)
            for name, (key, factor) in _STRIP_ARRAYS.items():
                rec[key] = [float(v) for v in getattr(self, name)[k] * factor]
            strips.append(rec)
        return {
            "order": self.order, "variance_factor": _real_or_none(self.variance_factor),
            "redundancy": int(self.redundancy), "objects_used": int(self.objects_used), "misfit": self.misfit,
            "strips": strips, "adjustment": None if self.solve is None else self.solve.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> StripCorrections:
        """What :meth:`to_dict` wrote."""
        recs = d["strips"]
        kw = {name: np.array([r[key] for r in recs], dtype=float).reshape(-1, 3) / factor
              for name, (key, factor) in _STRIP_ARRAYS.items()}
        kw |= {name: np.array([r[key] for r in recs]) for name, key in _STRIP_SCALARS.items()}
        vf = d["variance_factor"]
        return cls(order=int(d["order"]), strip=np.array([r["strip"] for r in recs], dtype=np.int64),
                   variance_factor=float("nan") if vf is None else float(vf), redundancy=int(d["redundancy"]),
                   objects_used=int(d["objects_used"]), misfit=d.get("misfit"),
                   solve=None if d.get("adjustment") is None else SolveResult.from_dict(d["adjustment"]), **kw)


def _real_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


# --------------------------------------------------------------------------- the adjustment


@dataclass(frozen=True)
class _Selection:
    """The features and objects the adjustment uses, renumbered."""

    features: PlanarFeatures
    strip_ids: np.ndarray  # (S,) ascending
    strip_index: np.ndarray  # (F,)
    object_index: np.ndarray  # (F,) into the used objects
    objects: np.ndarray  # (O,) indices into the input objects


def _select(features: PlanarFeatures, objects: PlanarObjects, min_strips: int) -> _Selection:
    """Matched features of objects seen from at least ``min_strips`` strips."""
    if objects.feature_object.size != len(features):
        raise InputError("the planar objects index another set of features", field="objects",
                         expected=f"{len(features)} features", found=f"{objects.feature_object.size}")
    fo = objects.feature_object
    matched = np.flatnonzero(fo >= 0)
    strip = np.asarray(features.strip, dtype=np.int64)
    pairs = np.unique(np.column_stack([fo[matched], strip[matched]]), axis=0)
    strips_per_object = np.bincount(pairs[:, 0], minlength=len(objects)) if pairs.size else np.zeros(len(objects))
    keep = matched[strips_per_object[fo[matched]] >= min_strips]
    if keep.size == 0:
        raise InputError("no planar object is seen from enough strips for a strip adjustment",
                         field="objects", expected=f"objects seen from at least {min_strips} strips",
                         found=f"{len(objects)} objects, {matched.size} matched features")
    used_objects, object_index = np.unique(fo[keep], return_inverse=True)
    strip_ids, strip_index = np.unique(strip[keep], return_inverse=True)
    return _Selection(features.select(keep), strip_ids, strip_index.ravel(), object_index.ravel(), used_objects)


def _strip_means(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    count = np.bincount(index, minlength=n).astype(float)
    if values.ndim == 1:
        return np.bincount(index, values, n) / count
    return np.column_stack([np.bincount(index, values[:, k], n) for k in range(values.shape[1])]) / count[:, None]


def adjust_strips(
    features: PlanarFeatures,
    objects: PlanarObjects,
    priors: StripPriors | None,
    *,
    order: int = 0,
    loss: RobustLoss | None = None,
    min_strips_per_object: int = 2,
    options: SolverOptions | None = None,
) -> StripCorrections:
    """Estimate one correction per strip from the plane correspondences (module docstring).

    Parameters
    ----------
    features
        Planar features with ``centre_w``, ``normal_w`` under the preliminary trajectory (the
        one the corrections are later applied to), ``strip``, ``time`` and sigmas.
    objects
        Their matching into planar objects (``feature_object`` indexes ``features``).
    priors
        The datum: zero-mean sigmas of every strip's correction. Required.
    order
        0: constant rotation and translation per strip; 1: plus a linear drift of both.
    loss
        Robust loss per feature (e.g. ``make_loss("cauchy", 2.0)`` as the G/I/L uses), or None.
    min_strips_per_object
        Objects seen from fewer strips are left out.
    options
        Solver options (default: at most 100 iterations, from a damping of 1e-9, the problem being
        near-linear without a robust loss; a relative cost change of 1e-6 ends it).

    Returns
    -------
    StripCorrections
        For the strips that have features in the objects used, ascending ids.

    Raises
    ------
    InputError
        Without priors (the datum), ``order`` 1 without drift priors, an ``order`` other than 0
        or 1, objects that index other features, or no object seen from enough strips.
    """
    if priors is None:
        raise InputError("a strip adjustment needs priors on the strip corrections: planes compare strips with "
                         "one another, so without them a rotation and translation common to all strips is not "
                         "observed and the normal matrix is singular", field="priors",
                         expected="StripPriors (e.g. the G/I's attitude and position sigmas)", found="None")
    if order not in (0, 1):
        raise InputError("unknown order of the strip corrections", field="order", expected="0 or 1", found=repr(order))
    sigmas = priors.sigmas(order)
    if int(min_strips_per_object) < 1:
        raise InputError("min_strips_per_object must be at least 1", field="min_strips_per_object",
                         expected=">= 1", found=repr(min_strips_per_object))
    sel = _select(features, objects, int(min_strips_per_object))
    f, n_strips, n_obj = sel.features, sel.strip_ids.size, sel.objects.size
    ref_point = _strip_means(sel.strip_index, f.centre_w, n_strips)
    ref_time = _strip_means(sel.strip_index, f.time, n_strips)

    group = StripPlaneObservation(
        f.centre_w, f.normal_w, f.time, sel.strip_index, ref_point, ref_time, f.sigma_d_m, f.sigma_slope_rad,
        sel.object_index, objects.c0[sel.objects], objects.k1[sel.objects], objects.k2[sel.objects],
        objects.n0[sel.objects], rotation_rate=ROTATION_RATE if order else None,
        translation_rate=TRANSLATION_RATE if order else None, loss=loss,
    )
    problem = Problem()
    for name, sigma in sigmas.items():
        problem.add_block(name, np.zeros((n_strips, 3)))
        problem.add_group(EuclideanPrior(f"{name}_prior", name, np.arange(n_strips), np.zeros((n_strips, 3)),
                                         np.broadcast_to(sigma, (n_strips, 3))))
    problem.add_block(OBJECTS, np.zeros((n_obj, 3)))
    problem.add_group(group)
    options = options or SolverOptions(max_iterations=100, function_tolerance=1e-6, initial_lambda=1e-9, polish=False)
    result = problem.solve(options)
    if not result.converged:
        _log.warning("strip adjustment: the solve ended by %s after %d iterations", result.termination,
                     result.iterations)

    problem.expect_covariance(n_strips * 3 * len(sigmas))
    scale = posterior_scale(result)
    est, sig = {}, {}
    for name in (ROTATION, TRANSLATION, ROTATION_RATE, TRANSLATION_RATE):
        if name in sigmas:
            est[name] = problem.values(name)
            cov = problem.covariance(name, scale_by_variance_factor=False)
            sig[name] = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0) * scale)
        else:
            est[name] = sig[name] = np.zeros((n_strips, 3))

    values = {name: problem.values(name) for name in problem.blocks}
    r = group.residual_rows(values)
    count = np.bincount(sel.strip_index, minlength=n_strips)
    rms_d = np.sqrt(_strip_means(sel.strip_index, r[:, 0] ** 2, n_strips))
    rms_s = np.sqrt(_strip_means(sel.strip_index, 0.5 * (r[:, 1] ** 2 + r[:, 2] ** 2), n_strips))
    robust_d = np.array([_MAD * np.median(np.abs(r[sel.strip_index == k, 0])) for k in range(n_strips)])
    n_objects_seen = np.bincount(np.unique(np.column_stack([sel.strip_index, sel.object_index]), axis=0)[:, 0],
                                 minlength=n_strips)
    misfit = _misfit(result.variance_factor, sel.strip_ids, robust_d, rms_d)
    if misfit is not None:
        _log.warning("strip adjustment (order %d): %s", order, misfit)
    _log.info("strip adjustment (order %d): %d strips, %d objects, %d features; variance factor %.3g",
              order, n_strips, n_obj, len(f), result.variance_factor)
    return StripCorrections(
        order=order, strip=sel.strip_ids, reference_point_w=ref_point, reference_time=ref_time,
        omega_rad=est[ROTATION], translation_m=est[TRANSLATION], omega_rate_rad_per_s=est[ROTATION_RATE],
        translation_rate_m_per_s=est[TRANSLATION_RATE], sigma_omega_rad=sig[ROTATION],
        sigma_translation_m=sig[TRANSLATION], sigma_omega_rate_rad_per_s=sig[ROTATION_RATE],
        sigma_translation_rate_m_per_s=sig[TRANSLATION_RATE], n_features=count, n_objects=n_objects_seen,
        rms_distance=rms_d, rms_slope=rms_s, robust_sigma_distance=robust_d,
        variance_factor=float(result.variance_factor), redundancy=int(result.redundancy), objects_used=int(n_obj),
        misfit=misfit, solve=result,
    )


def _misfit(variance_factor: float, strips: np.ndarray, robust_d: np.ndarray, rms_d: np.ndarray) -> str | None:
    """The sentence of the misfit warning (module docstring), or None where the model fits."""
    bad = np.flatnonzero(robust_d > MISFIT_SIGMA)
    if not (variance_factor > MISFIT_VARIANCE_FACTOR or bad.size):
        return None
    per_strip = ", ".join(f"{int(s)}: {d:.2f} (RMS {q:.2f})" for s, d, q in zip(strips, robust_d, rms_d))
    return (f"the per-strip model does not fit the plane correspondences: variance factor "
            f"{variance_factor:.3g} (above {MISFIT_VARIANCE_FACTOR:g} means misfit), median-based sigma of the "
            f"normalised distance residuals per strip {per_strip} (above {MISFIT_SIGMA:g} means misfit); the "
            "trajectory errors vary within a strip more than the model allows")


# --------------------------------------------------------------------------- applying the corrections


def correct_features(features: PlanarFeatures, corrections: StripCorrections) -> PlanarFeatures:
    """``features`` with ``centre_w`` and ``normal_w`` corrected (module docstring); features of
    strips without a correction are unchanged (the scanner-frame fields always are)."""
    centre, normal = features.centre_w.copy(), features.normal_w.copy()
    for k, sid in enumerate(corrections.strip):
        sel = np.flatnonzero(features.strip == sid)
        if sel.size == 0:
            continue
        R, trans = corrections.at(int(sid), features.time[sel])
        c = corrections.reference_point_w[k]
        centre[sel] = c + np.einsum("nij,nj->ni", R, centre[sel] - c) + trans
        normal[sel] = np.einsum("nij,nj->ni", R, normal[sel])
    return replace(features, centre_w=centre, normal_w=normal)


def _checked_spans(corrections: StripCorrections, spans: Mapping[int, tuple[float, float]]) -> list[tuple]:
    """(index, t0, t1) per corrected strip, sorted by time; the spans must not overlap."""
    out = []
    for k, sid in enumerate(corrections.strip.tolist()):
        if sid not in spans:
            raise InputError("no time span for a corrected strip", field="spans",
                             expected=f"a span for every strip of {corrections.strip.tolist()}",
                             found=f"spans of {sorted(spans)}")
        t0, t1 = (float(v) for v in spans[sid])
        if not t1 >= t0:
            raise InputError("a strip's time span ends before it starts", field=f"spans[{sid}]",
                             expected="t0 <= t1", found=f"{t0}, {t1}")
        out.append((k, t0, t1))
    out.sort(key=lambda r: r[1])
    for (ka, _, a1), (kb, b0, _) in zip(out, out[1:]):
        if b0 <= a1:
            raise InputError("the time spans of two corrected strips overlap", field="spans",
                             expected="disjoint spans",
                             found=f"strips {corrections.strip[ka]} and {corrections.strip[kb]}")
    return out


def apply_strip_corrections(trajectory: Trajectory, corrections: StripCorrections,
                            spans: Mapping[int, tuple[float, float]]) -> Trajectory:
    """The trajectory with each strip's correction applied inside the strip's time span.

    ``R_w_b' = R_s(t) R_w_b``, ``p' = c_s + R_s(t) (p - c_s) + T_s(t)``; a velocity, where the
    trajectory has one, becomes ``R_s v + dR_s/dt (p - c_s) + T_dot_s``. Samples outside every
    span are unchanged.

    Parameters
    ----------
    trajectory
        The preliminary trajectory the features were georeferenced with.
    corrections
        From :func:`adjust_strips`.
    spans
        Strip id -> ``(t0, t1)``, s relative to the dataset epoch (the trajectory's times),
        closed intervals; every corrected strip needs one, and they must not overlap.

    Raises
    ------
    InputError
        A corrected strip without a span, a reversed span, or overlapping spans.
    """
    time = trajectory.time
    p, R = trajectory.p_w_b.copy(), trajectory.R_w_b.copy()
    v = None if trajectory.v_w_b is None else trajectory.v_w_b.copy()
    for k, t0, t1 in _checked_spans(corrections, spans):
        sel = np.flatnonzero((time >= t0) & (time <= t1))
        if sel.size == 0:
            continue
        sid = int(corrections.strip[k])
        Rs, trans = corrections.at(sid, time[sel])
        lever = p[sel] - corrections.reference_point_w[k]
        if v is not None:
            phi = corrections.rotation_vector(sid, time[sel])
            omega = np.einsum("nij,j->ni", right_jacobian(phi), corrections.omega_rate_rad_per_s[k])
            dR = Rs @ skew(omega)  # d Exp(phi(t)) / dt = Exp(phi) [Jr(phi) phi_dot]x
            v[sel] = (np.einsum("nij,nj->ni", Rs, v[sel]) + np.einsum("nij,nj->ni", dR, lever)
                      + corrections.translation_rate_m_per_s[k])
        p[sel] = corrections.reference_point_w[k] + np.einsum("nij,nj->ni", Rs, lever) + trans
        R[sel] = Rs @ R[sel]
    return Trajectory(time.copy(), p, R, t0_gps=trajectory.t0_gps, v_w_b=v)
