"""Vectorised SO(3): exponential and logarithm maps, Jacobians, quaternions, Euler angles.

All functions accept a single element (``(3,)`` vectors, ``(3, 3)`` matrices) or stacks with
any leading shape (``(..., 3)``, ``(..., 3, 3)``) and return the same leading shape.

Perturbations are on the right, in the body frame: ``R <- R @ Exp(dtheta)``. With this
convention the right Jacobian ``Jr`` gives ``Exp(phi + dphi) ~= Exp(phi) Exp(Jr(phi) dphi)``
and ``Log(Exp(phi) Exp(d)) ~= phi + Jr^-1(phi) d`` (Barfoot, *State Estimation for
Robotics*, 2017, §7.1; Sola et al., *A micro Lie theory*, 2018, Eq. 143-146).

Quaternions are stored ``xyzw`` (SciPy's order), scalar last.

Roll, pitch and heading are the aerospace z-y-x Euler angles of ``R_n_b`` (body
forward-right-down relative to local north-east-down):
``R_n_b = Rz(heading) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import numba
import numpy as np

_SMALL = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(a) @ b == np.cross(a, b)``. ``(..., 3) -> (..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def _coefficients(theta: np.ndarray):
    """Return ``sin(t)/t``, ``(1-cos t)/t^2``, ``(t - sin t)/t^3`` with Taylor series near 0."""
    t2 = theta * theta
    small = theta < 1e-4
    ts = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(ts)) / ts**2)
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (ts - np.sin(ts)) / ts**3)
    return a, b, c


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix ``Exp(phi)`` of rotation vectors ``phi`` (rad). ``(..., 3) -> (..., 3, 3)``.

    Rodrigues' formula element by element (:func:`_exp_so3`, numba): the stacked numpy form made
    five temporaries of the whole stack and slowed down past the cache (11x the time for 6x the
    IMU samples of a 60-minute flight)."""
    phi = np.asarray(phi, dtype=float)
    flat = np.ascontiguousarray(phi.reshape(-1, 3))
    out = np.empty((flat.shape[0], 3, 3))
    _exp_so3(flat, out)
    return out.reshape(phi.shape[:-1] + (3, 3))


@numba.njit(cache=True, nogil=True)
def _exp_so3(phi, out):  # pragma: no cover - numba
    """``out[n] = Exp(phi[n])`` for every row (:func:`exp_so3_into`)."""
    for n in range(phi.shape[0]):
        exp_so3_into(phi[n], out[n])


@numba.njit(cache=True, nogil=True, inline="always")
def exp_so3_into(phi, out):  # pragma: no cover - numba
    """``Exp(phi)`` of one rotation vector into ``out`` (3, 3), for numba kernels:
    ``I + a K + b K^2`` with ``K = skew(phi)`` and the coefficients of :func:`_coefficients`."""
    t2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    t = np.sqrt(t2)
    if t < 1e-4:
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    else:
        a = np.sin(t) / t
        b = (1.0 - np.cos(t)) / t2
    x, y, z = phi[0], phi[1], phi[2]
    out[0, 0] = 1.0 - b * (y * y + z * z)
    out[1, 1] = 1.0 - b * (x * x + z * z)
    out[2, 2] = 1.0 - b * (x * x + y * y)
    out[0, 1] = -a * z + b * x * y
    out[1, 0] = a * z + b * x * y
    out[0, 2] = a * y + b * x * z
    out[2, 0] = -a * y + b * x * z
    out[1, 2] = -a * x + b * y * z
    out[2, 1] = a * x + b * y * z


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``Log(R)`` (rad, angle in [0, pi]). ``(..., 3, 3) -> (..., 3)``.

    Uses the quaternion route (via :func:`quat_from_matrix`), which is accurate for small
    angles and near pi alike.
    """
    q = quat_from_matrix(R)
    return rotvec_from_quat(q)


def right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3): ``Jr(phi) = I - b K + c K^2`` with ``K = skew(phi)``."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    _, b, c = _coefficients(theta)
    K = skew(phi)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye - b[..., None, None] * K + c[..., None, None] * (K @ K)


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3): ``Jl(phi) = Jr(-phi)``."""
    return right_jacobian(-np.asarray(phi, dtype=float))


def right_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian: ``Jr^-1(phi) = I + K/2 + (1/t^2 - (1+cos t)/(2 t sin t)) K^2``."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    t2 = theta * theta
    small = theta < 1e-4
    ts = np.where(small, 1.0, theta)
    d = np.where(
        small,
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
        1.0 / ts**2 - (1.0 + np.cos(ts)) / (2.0 * ts * np.sin(ts)),
    )
    K = skew(phi)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + 0.5 * K + d[..., None, None] * (K @ K)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``xyzw`` with ``w >= 0`` from rotation matrices (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], tr], axis=1)
    choice = np.argmax(diag, axis=1)
    q = np.empty((R.shape[0], 4))
    # Case w is largest.
    m = choice == 3
    s = np.sqrt(1.0 + tr[m]) * 2.0
    q[m, 3] = 0.25 * s
    q[m, 0] = (R[m, 2, 1] - R[m, 1, 2]) / s
    q[m, 1] = (R[m, 0, 2] - R[m, 2, 0]) / s
    q[m, 2] = (R[m, 1, 0] - R[m, 0, 1]) / s
    # Cases x, y, z largest.
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        m = choice == i
        s = np.sqrt(1.0 + R[m, i, i] - R[m, j, j] - R[m, k, k]) * 2.0
        q[m, i] = 0.25 * s
        q[m, 3] = (R[m, k, j] - R[m, j, k]) / s
        q[m, j] = (R[m, j, i] + R[m, i, j]) / s
        q[m, k] = (R[m, k, i] + R[m, i, k]) / s
    q *= np.where(q[:, 3:4] < 0.0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(shape + (4,))


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from quaternions ``xyzw`` (normalised first). ``(..., 4) -> (..., 3, 3)``."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector from quaternion ``xyzw`` (the shorter of the two rotations)."""
    q = np.asarray(q, dtype=float)
    q = q * np.where(q[..., 3:4] < 0.0, -1.0, 1.0)
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1)
    w = q[..., 3]
    angle = 2.0 * np.arctan2(s, w)
    small = s < _SMALL
    # angle / s -> 2 / w (1 - s^2 / (3 w^2)) for s -> 0.
    scale = np.where(small, 2.0 / np.where(small, w, 1.0), angle / np.where(small, 1.0, s))
    return v * scale[..., None]


def quat_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """Quaternion ``xyzw`` of rotation vectors (rad)."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)
    half = 0.5 * theta
    small = theta < 1e-4
    k = np.where(small, 0.5 - theta**2 / 48.0, np.sin(half) / np.where(small, 1.0, theta))
    return np.concatenate([phi * k[..., None], np.cos(half)[..., None]], axis=-1)


def rot_x(angle: np.ndarray) -> np.ndarray:
    """Rotation about x by ``angle`` (rad), active: ``[[1,0,0],[0,c,-s],[0,s,c]]``."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(angle: np.ndarray) -> np.ndarray:
    """Rotation about y by ``angle`` (rad): ``[[c,0,s],[0,1,0],[-s,0,c]]``."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(angle: np.ndarray) -> np.ndarray:
    """Rotation about z by ``angle`` (rad): ``[[c,-s,0],[s,c,0],[0,0,1]]``."""
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def R_n_b_from_rph(roll: np.ndarray, pitch: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """``R_n_b = Rz(heading) Ry(pitch) Rx(roll)`` (rad; body FRD, local level NED)."""
    roll, pitch, heading = np.broadcast_arrays(
        np.asarray(roll, float), np.asarray(pitch, float), np.asarray(heading, float)
    )
    # The product written out: one pass over the angles instead of three stacked matrices and
    # two batched matrix products (3x faster on the simulator's per-pulse poses).
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    sh, ch = np.sin(heading), np.cos(heading)
    R = np.empty(roll.shape + (3, 3))
    R[..., 0, 0] = cp * ch
    R[..., 0, 1] = sr * sp * ch - cr * sh
    R[..., 0, 2] = cr * sp * ch + sr * sh
    R[..., 1, 0] = cp * sh
    R[..., 1, 1] = sr * sp * sh + cr * ch
    R[..., 1, 2] = cr * sp * sh - sr * ch
    R[..., 2, 0] = -sp
    R[..., 2, 1] = sr * cp
    R[..., 2, 2] = cr * cp
    return R


def wrap_angle(a: np.ndarray, period: float = 2.0 * np.pi, *, closed: str = "upper") -> np.ndarray:
    """Angles wrapped into the period centred on 0.

    Radians by default (``period`` 2 pi); degrees with ``period=360.0``. ``closed`` names the end
    of the interval that is kept: ``"upper"`` gives (-period/2, period/2] (-pi becomes +pi),
    ``"lower"`` gives [-period/2, period/2) (+180 becomes -180). Angles inside the interval come
    back unchanged up to the rounding of one addition and one subtraction.
    """
    half = period / 2.0
    a = np.asarray(a, dtype=float)
    if closed == "upper":
        return half - np.mod(half - a, period)
    if closed == "lower":
        return np.mod(a + half, period) - half
    raise ValueError(f"closed must be 'upper' or 'lower', not {closed!r}")


def rph_from_R_n_b(R_n_b: np.ndarray) -> np.ndarray:
    """Roll, pitch, heading (rad) of ``R_n_b``; heading in [0, 2 pi). ``(..., 3, 3) -> (..., 3)``.

    Pitch is in [-pi/2, pi/2]; at exactly +-90 deg pitch roll and heading are not separable
    (never the case for aircraft attitude).
    """
    R = np.asarray(R_n_b, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    heading = np.mod(np.arctan2(R[..., 1, 0], R[..., 0, 0]), 2.0 * np.pi)
    return np.stack([roll, pitch, heading], axis=-1)


def omega_nb_b_from_rph_rates(rph: np.ndarray, rph_dot: np.ndarray) -> np.ndarray:
    """Body rate ``omega_nb_b`` (rad/s) from z-y-x Euler angles and their time derivatives.

    ``omega_nb_b = [r' - h' sin p, p' cos r + h' sin r cos p, -p' sin r + h' cos r cos p]``
    for ``rph = (r, p, h)``.
    """
    rph = np.asarray(rph, dtype=float)
    d = np.asarray(rph_dot, dtype=float)
    r, p = rph[..., 0], rph[..., 1]
    rd, pd, hd = d[..., 0], d[..., 1], d[..., 2]
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    return np.stack([rd - hd * sp, pd * cr + hd * sr * cp, -pd * sr + hd * cr * cp], axis=-1)


