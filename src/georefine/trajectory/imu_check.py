"""Is the IMU record what project.yaml says it is? Units, axes and signs against the GNSS trajectory.

A gyro written in deg/s, two swapped gyro axes or an accelerometer axis of the wrong sign pass
every format check, and the filter and the adjustment then fail minutes later with a message
about the normal matrix. :func:`check_imu_frame` finds such faults in a second, before any
work, from the data alone (docs/ARCHITECTURE.md §3.2):

1. **Accelerometer units**: in flight the median ``|f|`` is gravity, ~9.8 m/s²; about 1 means
   the file holds g.
2. **Accelerometer frame**: the body frame is forward-right-down, so over a flight the mean
   specific force points along ``-z`` (the aircraft flies roughly level). Its largest component
   along ``+z`` is a flipped ``acc_z``; along ``x`` or ``y`` swapped axes.
3. **Gyro against accelerometer** (units, order and signs): over a window of ``window_s`` the
   attitude ``R(t) = R0 dR(t)``, where ``dR`` integrates the gyro from the window's start and
   ``R0`` is unknown. The velocity change between 1 s epochs from GNSS positions,
   ``dv - g dt``, must then equal ``R0 sum w(t) dR(t) f(t) dt`` with the triangular weight ``w``
   that the position differences imply. ``R0`` follows in closed form (Wahba's problem, SVD);
   the RMS residual measures how well the gyro explains the accelerometer's rotation. The
   record as read is compared with every reading of the gyro through a signed axis
   permutation (48) in rad/s or deg/s: if one of them fits clearly better, the data were
   written that way, and the simplest fault that implies it is named (a gyro in deg/s, two
   gyro axes swapped, one gyro axis flipped; the mirror images of one accelerometer axis
   flipped or two swapped).

Windows are taken where the GNSS trajectory turns or changes speed most (a straight, steady
line leaves the rotation about the vertical unobservable). The GNSS antenna lever arm is
ignored: it adds centimetres per second in turns, far below the metres per second a wrong
gyro reading makes. Written by hand: no library checks an IMU's frame against GNSS.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from georefine.trajectory.sampled import interp_columns

__all__ = ["ImuFrameFinding", "check_imu_frame", "gyro_fit_residuals", "signed_permutations"]

_AXES = "xyz"


@dataclass(frozen=True)
class ImuFrameFinding:
    """One fault in the IMU record: the fields concerned, what was expected and what was found."""

    field: str
    message: str
    expected: str
    found: str


def signed_permutations() -> np.ndarray:
    """The 48 signed 3x3 permutation matrices, the identity first."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            out.append(m)
    out.sort(key=lambda m: not np.array_equal(m, np.eye(3)))
    return np.array(out)


def _epochs(gnss_time: np.ndarray, gnss_p: np.ndarray, t_first: float, t_last: float):
    """1 s epochs ``T`` with GNSS velocity ``v(T) = p(T + 0.5) - p(T - 0.5)`` inside the GNSS coverage."""
    T = np.arange(np.ceil(t_first + 0.5), np.floor(t_last - 0.5) + 1e-9, 1.0)
    # a velocity only where both ends fall between GNSS epochs at most 1 s apart (no interpolation over gaps)
    gap_ok = np.ones(T.size, bool)
    for dt in (-0.5, 0.5):
        k = np.clip(np.searchsorted(gnss_time, T + dt), 1, gnss_time.size - 1)
        gap_ok &= (gnss_time[k] - gnss_time[k - 1] <= 1.0) & (T + dt >= gnss_time[0]) & (T + dt <= gnss_time[-1])
    p = lambda t: interp_columns(t, gnss_time, gnss_p)  # noqa: E731
    return T, p(T + 0.5) - p(T - 0.5), gap_ok


def gyro_fit_residuals(t: np.ndarray, gyro: np.ndarray, acc: np.ndarray, T: np.ndarray, v: np.ndarray,
                       g_w: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """RMS residual (m/s) of the velocity changes ``v[j+1] - v[j]`` for each gyro reading ``transforms @ gyro``.

    ``t`` (K,) regular IMU times covering ``[T[0] - 0.5, T[-1] + 0.5]``; ``gyro``, ``acc`` (K, 3);
    ``T`` (J,) 1 s epochs and ``v`` (J, 3) GNSS velocities in ``w`` at them; ``g_w`` (3,)
    gravity in ``w``; ``transforms`` (H, 3, 3). Returns (H,).
    """
    dt = float(np.median(np.diff(t)))
    H = transforms.shape[0]
    omega = np.einsum("hij,kj->hki", transforms, gyro)  # (H, K, 3)
    # dR(t_k): body at t_k -> body at the window start, one exact rotation-vector step per sample
    steps = Rotation.from_rotvec((omega * dt).reshape(-1, 3)).as_quat().reshape(H, -1, 4)
    q = np.empty_like(steps)
    cur = np.tile([0.0, 0.0, 0.0, 1.0], (H, 1))
    for k in range(steps.shape[1]):
        q[:, k] = cur
        cur = _qmul(cur, steps[:, k])
    f_s = Rotation.from_quat(q.reshape(-1, 4)).apply(np.tile(acc, (H, 1))).reshape(H, -1, 3)
    # triangular weight of a(t) in v(T_j+1) - v(T_j): 0 at T_j - 0.5, 1 at T_j + 0.5, 0 at T_j + 1.5
    W = np.clip(1.0 - np.abs(t[None, :] - (T[:-1, None] + 0.5)), 0.0, None) * dt  # (J-1, K)
    u = np.einsum("jk,hkc->hjc", W, f_s)  # (H, J-1, 3)
    y = (v[1:] - v[:-1]) - g_w[None, :] * W.sum(axis=1)[:, None]  # (J-1, 3)
    B = np.einsum("jc,hjd->hcd", y, u)
    U, _, Vt = np.linalg.svd(B)
    d = np.sign(np.linalg.det(U @ Vt))
    R0 = U @ (np.eye(3)[None] * np.stack([np.ones(H), np.ones(H), d], axis=1)[:, None, :]) @ Vt
    r = y[None] - np.einsum("hcd,hjd->hjc", R0, u)
    return np.sqrt(np.mean(np.sum(r ** 2, axis=2), axis=1))


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of scalar-last quaternions, row by row."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.stack([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz], axis=1)


def _describe(G: np.ndarray, scale: float) -> ImuFrameFinding:
    """The simplest fault that makes ``scale * G @ gyro`` the right reading."""
    if scale != 1.0:
        what = "the gyro readings look like deg/s" + ("" if np.array_equal(G, np.eye(3)) else
                                                       f" (and their axes fit best as {_rows(G)})")
        return ImuFrameFinding("gyro_x, gyro_y, gyro_z", what, "rad/s",
                               "the readings times pi/180 fit the GNSS trajectory, as read they do not")
    diag = np.allclose(G, np.diag(np.diag(G)))
    flipped = [i for i in range(3) if G[i, i] < 0] if diag else []
    if diag and len(flipped) == 1:
        a = _AXES[flipped[0]]
        return ImuFrameFinding(f"gyro_{a}", f"gyro_{a} looks like it has the wrong sign", "a forward-right-down body "
                               "frame for gyro and accelerometer", f"-gyro_{a} fits the GNSS trajectory")
    P = np.abs(G)
    moved = [i for i in range(3) if P[i, i] == 0]
    if len(moved) == 2 and np.all(G[P > 0] > 0):
        a, b = (_AXES[i] for i in moved)
        return ImuFrameFinding(f"gyro_{a}, gyro_{b}", f"gyro_{a} and gyro_{b} look swapped", "gyro axes in the order "
                               "x, y, z of the accelerometer", f"the gyro fits with {a} and {b} exchanged")
    if np.linalg.det(G) < 0:
        # A mirror that is no single gyro flip or swap: the accelerometer's frame is the mirrored
        # one (an axis of the wrong sign, or two swapped). In flight the specific force is mostly
        # gravity, so which accelerometer axis is not always decidable: the sensor is named.
        return ImuFrameFinding("acc_x, acc_y, acc_z", "the accelerometer axes are mirrored against the gyro's: an "
                               "axis has the wrong sign or two are swapped", "one right-handed forward-right-down "
                               "frame for gyro and accelerometer", f"the gyro fits only read as {_rows(G)}")
    return ImuFrameFinding("gyro_x, gyro_y, gyro_z, acc_x, acc_y, acc_z", "the gyro and accelerometer axes do not "
                           "agree: an axis of one of them has the wrong sign, or their axes are in another order",
                           "both in the same forward-right-down body frame", f"the gyro fits best read as {_rows(G)}")


def _rows(G: np.ndarray) -> str:
    names = []
    for row in G:
        i = int(np.flatnonzero(row)[0])
        names.append(("-" if row[i] < 0 else "") + "gyro_" + _AXES[i])
    return "(" + ", ".join(names) + ")"


def check_imu_frame(imu_time: np.ndarray, gyro: np.ndarray, acc: np.ndarray, gnss_time: np.ndarray,
                    gnss_p_w: np.ndarray, gravity: float = 9.81, *, window_s: float = 40.0,
                    n_windows: int = 3, min_residual_ms: float = 0.3, ratio: float = 2.5) -> ImuFrameFinding | None:
    """The first fault found in the IMU record (module docstring), or None when it is plausible.

    ``imu_time`` (N,) and ``gnss_time`` (G,) on one time scale (s); ``gyro`` (N, 3) rad/s,
    ``acc`` (N, 3) m/s² as read; ``gnss_p_w`` (G, 3) antenna positions in the east-north-up
    frame ``w`` (m). A gyro fault is reported only when the record as read leaves a residual
    above ``min_residual_ms`` (m/s) and ``ratio`` times that of the best reading.
    """
    norm = float(np.median(np.linalg.norm(acc, axis=1)))
    if 0.5 < norm < 2.0:
        return ImuFrameFinding("acc_x, acc_y, acc_z", "the accelerometer readings look like g", "m/s² (|f| near "
                               f"{gravity:.2f} in flight)", f"a median |f| of {norm:.3f}")
    if not 0.5 * gravity < norm < 2.0 * gravity:
        return ImuFrameFinding("acc_x, acc_y, acc_z", "implausible accelerometer readings",
                               f"m/s² (|f| near {gravity:.2f} in flight)", f"a median |f| of {norm:.3g}")
    mean = acc.mean(axis=0)
    k = int(np.argmax(np.abs(mean)))
    if k != 2 or mean[2] > 0:
        sign = "+" if mean[k] > 0 else "-"
        field = "acc_z" if k == 2 else f"acc_{_AXES[k]}, acc_z"
        return ImuFrameFinding(field, "gravity is not along the body's down axis", "the mean specific force along -z "
                               "(forward-right-down body frame, z down)",
                               f"it points along {sign}{_AXES[k]} ({mean.round(2).tolist()} m/s²)")
    T, v, ok = _epochs(gnss_time, gnss_p_w, max(imu_time[0], gnss_time[0]), min(imu_time[-1], gnss_time[-1]))
    if T.size < 10:
        return None  # too short to tell
    # windows where the trajectory turns or changes speed most
    n_per = int(window_s)
    dv = np.linalg.norm(np.diff(v[:, :2], axis=0), axis=1)
    scores = []
    for s in range(0, T.size - n_per, n_per // 2):
        if ok[s:s + n_per + 1].all():
            scores.append((float(np.sum(dv[s:s + n_per] ** 2)), s))
    chosen: list[int] = []
    for _, s in sorted(scores, reverse=True):
        if all(abs(s - c) >= n_per for c in chosen):
            chosen.append(s)
        if len(chosen) == n_windows:
            break
    if not chosen:
        return None
    # block means of ~50 Hz: the rotation over 0.02 s is still one exact step, and 4x fewer steps
    rate = 1.0 / float(np.median(np.diff(imu_time)))
    m = max(1, int(round(rate / 50.0)))
    n = (imu_time.size // m) * m
    imu_time, gyro, acc = (a[:n].reshape(n // m, m, *a.shape[1:]).mean(axis=1) for a in (imu_time, gyro, acc))
    perms = signed_permutations()
    transforms = np.concatenate([perms, perms * (np.pi / 180.0)])
    total = np.zeros(transforms.shape[0])
    for s in chosen:
        Tw, vw = T[s:s + n_per + 1], v[s:s + n_per + 1]
        sel = (imu_time >= Tw[0] - 0.5) & (imu_time <= Tw[-1] + 0.5)
        total += gyro_fit_residuals(imu_time[sel], gyro[sel], acc[sel], Tw, vw, np.array([0.0, 0.0, -gravity]),
                                    transforms) ** 2
    rms = np.sqrt(total / len(chosen))
    best = int(np.argmin(rms))
    if best == 0 or rms[0] < max(min_residual_ms, ratio * rms[best]):
        return None
    finding = _describe(transforms[best] / (np.pi / 180.0 if best >= perms.shape[0] else 1.0),
                        np.pi / 180.0 if best >= perms.shape[0] else 1.0)
    return ImuFrameFinding(finding.field, finding.message, finding.expected,
                           f"{finding.found} (velocity-change residual {rms[0]:.2f} m/s as read, "
                           f"{rms[best]:.2f} m/s so read)")
