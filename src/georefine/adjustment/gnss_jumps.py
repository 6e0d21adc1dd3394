"""Wrong GNSS fixes found in the G/I's residuals (docs/ARCHITECTURE.md §4.3 GNSS).

A kinematic solution whose ambiguities were fixed to wrong integers (RTKLIB's ratio test passes a
wrong set now and then; Teunissen & Verhagen 2009, "The GNSS ambiguity ratio-test revisited",
Survey Review 41(312)) steps by a constant offset of centimetres to decimetres and stays there
until the next re-fix, while the ``.pos`` file keeps ``Q=1`` and its fixed-solution sigmas. The
IMU does not let the trajectory step with it: the G/I follows the offset over a few seconds, so
its GNSS residuals (measured minus modelled antenna position) step at the wrong fix's start and
end by most of the offset and return to zero between (on corridor-tiny, a 10.5 cm step left
-4.2/+4.5 cm in the seconds before and after it, 0 +- 1 cm inside: about the step less its
convolution with a two-sided exponential of 2 s).

The test (:func:`find_jumps`) is a two-sided windowed mean difference on the residuals whitened by
their stated sigma, per axis of ``w``:

    D_k = mean(z_k .. z_k+n-1) - mean(z_k-n .. z_k-1),   T_k = D_k / s_D

over runs of consecutive fixed epochs (``n`` epochs of ``window_s`` on either side; an outlier's
share is clipped at six of the residual's own spread). ``s_D`` is the spread of ``D`` itself
(1.4826 times its median absolute deviation over all epochs, at least half of what white residuals
of the stated sigma give, ``sqrt(2 / n)``): it holds the residual's own correlation (multipath,
the correlated error's chord) and its scale, where the file's sigma is off. An epoch where the norm
``|T_k|`` over the three axes exceeds the threshold and is the largest within ``2 n`` epochs is an
edge; the G/I, which follows the offset within seconds, leaves lobes of the other sign and up to
half the size two to four seconds either side of a step, which do not count within ``4 n`` epochs
of a larger step (:data:`REBOUND_SHARE`). The edges cut a run into intervals whose levels are the
sums of the steps before them; the level held by most epochs is the right one, and every interval
that stands off it by the threshold (or :data:`RELATIVE_TOLERANCE` of the steps between, if more)
is a wrong fix, consecutive ones at one level one fix (also one that runs to the end of the run).
Each becomes a segment like one without a fix (:mod:`georefine.adjustment.gnss_segments`): one
offset with the prior of ``gnss.float_offset``, and the G/I runs again once.

White residuals give ``|T_k|`` the spread of the norm of three unit normals, independent every
``2 n`` epochs or so: at the default threshold of 6 it passes by chance about once in 1.4e7 tests
(an hour at 5 Hz holds 900). On the synthetic series of ``tests/test_gnss_jumps.py`` (1.5-2 cm of
noise correlated over 5-20 s) no alarm in 300 series of 10 minutes; a 10 cm horizontal jump of
60 s is found with its span. With the G/I's response, a step's window difference is about 0.63 of
it, so a jump needs about 6 of ``s_D`` / 0.63 on an axis: at 5 Hz with 1 cm white and 1.5 cm
correlated error about 7 cm horizontally, twice that in height. A wrong fix that begins at a gap
(a re-fix after an outage) has no edge the residuals show: the trajectory follows it across the
gap. Such a jump is not found.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["GnssJump", "find_jumps", "jump_warning"]

MAD_TO_SIGMA = 1.4826
CLIP = 6.0
"""An epoch's whitened residual counts at most this many of the residuals' own spreads in a window mean."""
REBOUND_SHARE = 0.6
"""A step of the other sign within ``4 n`` epochs of a larger one and below this share of it is the G/I's
rebound from that one, not an edge of its own."""
RELATIVE_TOLERANCE = 0.3
"""Levels agree within the threshold or this share of the steps between them, whichever is more."""


@dataclass(frozen=True)
class GnssJump:
    """Fixed epochs found off their neighbours.

    Attributes
    ----------
    t_start, t_end : float
        First and last epoch (s, as the series' times).
    epochs : int
    step_start_m, step_end_m : (3,) or None
        Step of the residuals at the first and after the last epoch (m per axis of ``w``); None
        where the segment starts or ends with its run.
    sigmas_start, sigmas_end : (3,) or None
        The same steps in their own spread ``s_D``.
    """

    t_start: float
    t_end: float
    epochs: int
    step_start_m: np.ndarray | None
    step_end_m: np.ndarray | None
    sigmas_start: np.ndarray | None
    sigmas_end: np.ndarray | None


def _runs(time: np.ndarray) -> list[np.ndarray]:
    """Indices of runs of consecutive epochs: a gap of more than 2.5 epoch intervals ends one."""
    if time.size < 2:
        return [np.arange(time.size)]
    dt = np.diff(time)
    cut = np.flatnonzero(dt > 2.5 * np.median(dt)) + 1
    return np.split(np.arange(time.size), cut)


def _window_difference(z: np.ndarray, n: int) -> np.ndarray:
    """``D_k`` of :func:`find_jumps` for ``k = n .. m - n`` of ``z`` (m, 3)."""
    c = np.vstack([np.zeros((1, z.shape[1])), np.cumsum(z, axis=0)])
    k = np.arange(n, z.shape[0] - n + 1)
    return (c[k + n] - 2.0 * c[k] + c[k - n]) / n


def find_jumps(time: np.ndarray, residual: np.ndarray, sigma: np.ndarray, window_s: float = 2.0,
               threshold: float = 6.0) -> list[GnssJump]:
    """Segments of epochs whose residuals stand off their neighbours' (the module docstring's test).

    Parameters
    ----------
    time : (M,)
        Epochs of fixed solutions, increasing (s).
    residual : (M, 3)
        Measured minus modelled antenna position per axis (m).
    sigma : (M, 3)
        The residuals' stated sigma per axis (m), e.g. the white part of the file's.
    window_s : float
        Length of each of the two windows compared (s).
    threshold : float
        An edge's step in its own spread, the norm ``|T_k|`` over the three axes.

    Returns
    -------
    list of GnssJump
        In time order; empty where none is found.
    """
    time = np.asarray(time, dtype=float)
    r = np.asarray(residual, dtype=float).reshape(time.size, 3)
    s = np.broadcast_to(np.asarray(sigma, dtype=float), r.shape)
    if time.size < 4:
        return []
    n = max(2, int(round(window_s / np.median(np.diff(time)))))
    z = r / s
    spread = MAD_TO_SIGMA * np.median(np.abs(z - np.median(z, axis=0)), axis=0)
    z = np.clip(z, -CLIP * spread, CLIP * spread)
    runs = [k for k in _runs(time) if k.size >= 2 * n]
    if not runs:
        return []
    diffs = [_window_difference(z[k], n) for k in runs]
    pooled = np.vstack(diffs)
    s_d = np.maximum(MAD_TO_SIGMA * np.median(np.abs(pooled - np.median(pooled, axis=0)), axis=0),
                     0.5 * np.sqrt(2.0 / n))
    out = []
    for k, d in zip(runs, diffs):
        t_score = d / s_d
        score = np.linalg.norm(t_score, axis=1)
        edges = []
        for i in np.argsort(-score, kind="stable"):  # the largest first
            if score[i] <= threshold:
                break
            if all(abs(i - j) >= 2 * n and not _rebound(t_score[i], t_score[j], abs(i - j), n) for j in edges):
                edges.append(int(i))
        if not edges:
            continue
        edges.sort()
        steps = t_score[edges]
        at = np.array(edges) + n  # index in the run of the first epoch after each step
        bounds = np.concatenate([[0], at, [k.size]])
        levels = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
        # Two intervals are at the same level where they differ by less than the threshold, or than what the
        # steps between them are uncertain by where that is more (the G/I's response to a step varies with its size).
        swing = np.concatenate([[0.0], np.cumsum(np.linalg.norm(steps, axis=1))])
        tol = np.maximum(threshold, RELATIVE_TOLERANCE * np.abs(swing[:, None] - swing[None, :]))
        same = np.linalg.norm(levels[:, None, :] - levels[None, :, :], axis=2) < tol
        ref = int(np.argmax(same.astype(float) @ np.diff(bounds)))
        off = ~same[ref]
        step_m = _window_difference(r[k], n)[edges]  # the steps in metres, as they are
        i = 0
        while i < off.size:  # consecutive off intervals at one level are one wrong fix
            if not off[i]:
                i += 1
                continue
            j = i
            while j + 1 < off.size and off[j + 1] and same[i, j + 1]:
                j += 1
            a, b = bounds[i], bounds[j + 1] - 1
            first, last = i > 0, j < len(edges)
            out.append(GnssJump(
                float(time[k[a]]), float(time[k[b]]), int(b - a + 1),
                step_m[i - 1] if first else None, step_m[j] if last else None,
                steps[i - 1] if first else None, steps[j] if last else None))
            i = j + 1
    return out


def _rebound(t_i: np.ndarray, t_j: np.ndarray, distance: int, n: int) -> bool:
    """Whether a step ``t_i`` ``distance`` epochs from a larger one ``t_j`` is its rebound: of the other sign,
    within ``4 n`` epochs and at most :data:`REBOUND_SHARE` of it."""
    return bool(distance < 4 * n and np.dot(t_i, t_j) < 0.0
                and np.linalg.norm(t_i) < REBOUND_SHARE * np.linalg.norm(t_j))


def jump_warning(jump: GnssJump, t0_gps: float) -> str:
    """The warning for one jump: its span, its residual steps in cm and in their own spread."""
    def step(m, z, where):
        if m is None:
            return f"the run {where}s with it"
        return (f"the residuals step by {m[0] * 100:+.1f}/{m[1] * 100:+.1f}/{m[2] * 100:+.1f} cm east/north/up "
                f"at its {where} ({np.linalg.norm(z):.1f} times their own spread)")

    return (f"GNSS fixed epochs (Q=1) from {t0_gps + jump.t_start:.1f} to {t0_gps + jump.t_end:.1f} GPS s "
            f"({jump.epochs} epochs, {jump.t_end - jump.t_start:.1f} s) stand off their neighbours: "
            f"{step(jump.step_start_m, jump.sigmas_start, 'start')}, {step(jump.step_end_m, jump.sigmas_end, 'end')}. "
            "A wrong ambiguity fix? The adjustment takes them with an offset of their own "
            "(gnss.float_offset.detect_jumps) and runs again")
