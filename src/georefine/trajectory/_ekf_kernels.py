"""Numba kernels of the error-state Kalman filter and RTS smoother (:mod:`.ekf`).

Per-sample transition accumulation, process noise, GNSS update model, the forward filter
loop, the backward smoother and the application of the smoothed corrections: the parts whose
per-sample Python overhead would dominate. See :mod:`georefine.trajectory.ekf` for the model.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from georefine.geometry.rotation import exp_so3_into
from georefine.trajectory import strapdown as sd

_NX = 21  # error states: 15 navigation + 6 scale factors


@nb.njit(cache=True)
def _addmul(out, r0, M, s, X, c0):
    """``out[r0:r0+3] += s M X[c0:c0+3]`` for a 3x3 ``M`` over all columns."""
    for i in range(3):
        for k in range(3):
            m = s * M[i, k]
            if m != 0.0:
                for j in range(_NX):
                    out[r0 + i, j] += m * X[c0 + k, j]


@nb.njit(cache=True)
def _accumulate(Phi, dt, R, f, w, W_ie, Gam, A, B, Wx, Dw, FX):
    """``Phi <- (I + F dt) Phi`` (rows 0-8 change) at attitude ``R`` and corrected IMU ``f``, ``w``.

    Semi-implicit: the attitude rows are stepped first (Euler), the velocity rows use the
    mean of the old and new attitude rows, the position rows the mean of the old and new
    velocity rows, so the chained terms (position from attitude or gyro errors) are second order.
    """
    for i in range(3):  # A = -R [f]x: row i is -(r_i x f); B = -R diag(f)
        A[i, 0] = -(R[i, 1] * f[2] - R[i, 2] * f[1])
        A[i, 1] = -(R[i, 2] * f[0] - R[i, 0] * f[2])
        A[i, 2] = -(R[i, 0] * f[1] - R[i, 1] * f[0])
        for j in range(3):
            B[i, j] = -R[i, j] * f[j]
        Dw[i, i] = -w[i]
    Wx[0, 1], Wx[0, 2], Wx[1, 2] = w[2], -w[1], w[0]  # -[w]x
    Wx[1, 0], Wx[2, 0], Wx[2, 1] = -w[2], w[1], -w[0]
    FX[:, :] = 0.0  # rows 0-2: old velocity rows, 3-5: velocity rate, 6-8: old attitude rows
    for i in range(3):
        for j in range(_NX):
            FX[i, j] = Phi[3 + i, j]
            FX[6 + i, j] = Phi[6 + i, j]
            FX[9 + i, j] = -Phi[12 + i, j]
    _addmul(FX, 9, Wx, 1.0, Phi, 6)
    _addmul(FX, 9, Dw, 1.0, Phi, 18)
    for i in range(6, 9):
        for j in range(_NX):
            Phi[i, j] += dt * FX[i + 3, j]
    _addmul(FX, 3, Gam, 1.0, Phi, 0)
    _addmul(FX, 3, W_ie, -2.0, Phi, 3)
    _addmul(FX, 3, A, 0.5, FX, 6)
    _addmul(FX, 3, A, 0.5, Phi, 6)
    _addmul(FX, 3, R, -1.0, Phi, 9)
    _addmul(FX, 3, B, 1.0, Phi, 15)
    for i in range(3):
        for j in range(_NX):
            Phi[3 + i, j] += dt * FX[3 + i, j]
            Phi[i, j] += 0.5 * dt * (FX[i, j] + Phi[3 + i, j])


@nb.njit(cache=True)
def _full_phi(top):
    """Transition (21, 21) from its first nine rows (the sensor-error rows are the identity)."""
    Phi = np.eye(_NX)
    Phi[:9] = top
    return Phi


@nb.njit(cache=True)
def _process_noise(Phi, qc, T):
    """``Q = (Phi Qc Phi^T + Qc) T / 2`` for diagonal ``Qc = diag(qc)``."""
    Q = (Phi * qc[None, :]) @ Phi.T
    for i in range(_NX):
        Q[i, i] += qc[i]
    return 0.5 * T * Q


@nb.njit(cache=True)
def _corrected(raw, nom, b0, s0, out):
    """Sensor model inverse ``(raw - b) / (1 + s)`` with ``b = nom[b0:b0+3]``, ``s = nom[s0:s0+3]``."""
    for i in range(3):
        out[i] = (raw[i] - nom[b0 + i]) / (1.0 + nom[s0 + i])


@nb.njit(cache=True)
def _inject(k, d, P_n, V_n, R_n, nom, E):
    """Add the error state ``d`` to the nominal state at sample ``k`` and to ``nom`` (12,)."""
    for i in range(3):
        P_n[k, i] += d[i]
        V_n[k, i] += d[3 + i]
    exp_so3_into(d[6:9].copy(), E)
    R_n[k] = R_n[k] @ E
    for i in range(12):
        nom[i] += d[9 + i]


@nb.njit(cache=True)
def _gnss_model(p, v, R, omega_ib_b, w_ie, p_b_a, d, H):
    """Predicted antenna position at ``t_k + d``; writes the Jacobian ``H`` (3, 21)."""
    om = omega_ib_b - R.T @ w_ie  # omega_wb_b
    lev = p_b_a + d * np.cross(om, p_b_a)
    H[:, :] = 0.0
    for i in range(3):
        H[i, i] = 1.0
        H[i, 3 + i] = d
    # d/dtheta of R Exp(dtheta) lev = -R [lev]x
    H[:, 6] = -(R[:, 1] * lev[2] - R[:, 2] * lev[1])
    H[:, 7] = -(R[:, 2] * lev[0] - R[:, 0] * lev[2])
    H[:, 8] = -(R[:, 0] * lev[1] - R[:, 1] * lev[0])
    return p + d * v + R @ lev


@nb.njit(cache=True)
def forward_pass(t, w, f, wm, fm, k0, k1, ep_flag, g_k, g_dt, g_z, g_R, p_b_a, P0, qc, Gam, gate,
             gate_reset, R_e_w, p_e_w, w_ie, P_n, V_n, R_n, ep_idx, ep_Pp, ep_Phi, ep_dx, ep_nom,
             g_status, g_nis):
    """Forward filter from sample ``k0`` (initial nominal state in ``P_n[k0]`` ...) to ``k1``."""
    W_ie = np.zeros((3, 3))
    W_ie[0, 1], W_ie[0, 2], W_ie[1, 2] = -w_ie[2], w_ie[1], -w_ie[0]
    W_ie[1, 0], W_ie[2, 0], W_ie[2, 1] = w_ie[2], -w_ie[1], w_ie[0]
    A, B, Wx, Dw, E = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    FX = np.zeros((_NX, _NX))
    nom = np.zeros(12)  # b_a, b_g, s_a, s_g
    P = P0.copy()
    Phi = np.eye(_NX)
    I_nx = np.eye(_NX)
    w0, f0, w1, f1, wmid, fmid = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    H = np.zeros((3, _NX))
    e, gi, n_g = 0, 0, g_k.shape[0]
    t_streak = np.nan
    for k in range(k0, k1 + 1):
        if k > k0:
            _corrected(w[k - 1], nom, 3, 9, w0)
            _corrected(f[k - 1], nom, 0, 6, f0)
            _corrected(w[k], nom, 3, 9, w1)
            _corrected(f[k], nom, 0, 6, f1)
            _corrected(wm[k - 1], nom, 3, 9, wmid)
            _corrected(fm[k - 1], nom, 0, 6, fmid)
            dt = t[k] - t[k - 1]
            _accumulate(Phi, dt, R_n[k - 1], fmid, wmid, W_ie, Gam, A, B, Wx, Dw, FX)
            sd.rkmk4_step(P_n[k - 1], V_n[k - 1], R_n[k - 1], w0, f0, wmid, fmid, w1, f1, dt,
                          R_e_w, p_e_w, w_ie, P_n[k], V_n[k], R_n[k])
        if not ep_flag[k]:
            continue
        if k > k0:
            P = Phi @ P @ Phi.T + _process_noise(Phi, qc, t[k] - t[ep_idx[e - 1]])
        ep_Phi[e] = Phi[:9]
        Phi = np.eye(_NX)
        dx = np.zeros(_NX)
        while gi < n_g and g_k[gi] == k:
            _corrected(w[k], nom, 3, 9, w1)
            nu = g_z[gi] - _gnss_model(P_n[k], V_n[k], R_n[k], w1, w_ie, p_b_a, g_dt[gi], H)
            PHt = P @ H.T
            Si = np.linalg.inv(H @ PHt + g_R[gi])
            nis = nu @ (Si @ nu)
            g_nis[gi] = nis
            tg = t[k] + g_dt[gi]
            g_status[gi] = 1
            if nis > gate:
                if np.isnan(t_streak):
                    t_streak = tg
                if tg - t_streak < gate_reset:
                    g_status[gi] = 0
                    gi += 1
                    continue
                g_status[gi] = 2
            t_streak = np.nan
            K = PHt @ Si
            IKH = I_nx - K @ H
            P = IKH @ P @ IKH.T + K @ g_R[gi] @ K.T
            P = 0.5 * (P + P.T)
            delta = K @ nu
            _inject(k, delta, P_n, V_n, R_n, nom, E)
            dx += delta
            gi += 1
        ep_idx[e] = k
        ep_Pp[e] = P
        ep_dx[e] = dx
        ep_nom[e] = nom
        e += 1
    return e


@nb.njit(cache=True)
def rts_smooth(ep_t, ep_Pp, ep_Phi, ep_dx, qc, ds, sig):
    """RTS recursion on the error state (module docstring); writes ``ds`` and ``sig`` (E, 21)."""
    n = ep_t.shape[0]
    Ps = ep_Pp[n - 1].copy()
    ds[n - 1] = 0.0
    for i in range(_NX):
        sig[n - 1, i] = np.sqrt(max(Ps[i, i], 0.0))
    for e in range(n - 2, -1, -1):
        Phi, Pp = _full_phi(ep_Phi[e + 1]), ep_Pp[e]
        Pm = Phi @ Pp @ Phi.T + _process_noise(Phi, qc, ep_t[e + 1] - ep_t[e])
        # C^T = Pm^-1 Phi Pp, solved with diagonal scaling (variances span ~14 orders of magnitude)
        s = 1.0 / np.sqrt(np.diag(Pm))
        CT = np.linalg.solve(Pm * s[:, None] * s[None, :], (Phi @ Pp) * s[:, None]) * s[:, None]
        C = CT.T.copy()
        ds[e] = C @ (ds[e + 1] + ep_dx[e + 1])
        Ps = Pp + C @ (Ps - Pm) @ C.T
        Ps = 0.5 * (Ps + Ps.T)
        for i in range(_NX):
            sig[e, i] = np.sqrt(max(Ps[i, i], 0.0))


@nb.njit(cache=True)
def apply_smoothed(t, ep_idx, ds, ep_dx, ep_nom, P_n, V_n, R_n, nom_out):
    """Apply the smoothed corrections at every sample (interpolated between epochs), in place."""
    E = np.zeros((3, 3))
    n = ep_idx.shape[0]
    d = np.empty(_NX)
    nom = np.empty(12)
    for e in range(n):
        k = ep_idx[e]
        kn = ep_idx[e + 1] if e + 1 < n else k + 1
        for j in range(k, kn):
            u = 0.0 if j == k else (t[j] - t[k]) / (t[kn] - t[k])
            for i in range(_NX):
                b = ds[e + 1, i] + ep_dx[e + 1, i] if e + 1 < n else 0.0
                d[i] = (1.0 - u) * ds[e, i] + u * b
            nom[:] = ep_nom[e]
            _inject(j, d, P_n, V_n, R_n, nom, E)
            nom_out[j] = nom[:6]


# ---------------------------------------------------------------------------- alignment
