"""GNSS epochs without a fixed solution: one offset per segment (docs/ARCHITECTURE.md §4.3 GNSS).

A kinematic solution whose ambiguities are float (RTKLIB ``Q=2``) is off by about one offset of
decimetres for as long as they stay float, while the ``.pos`` file states sigmas of a few
centimetres (RTKLIB writes 5/5/10 cm for a typical float epoch). Taken as white errors, the 300
epochs of a one-minute segment averaged that offset to millimetres: the G/I put a pass 14 cm off
and stated 1.6 cm. Here each run of consecutive epochs worse than a fix gets one offset in ``w``
(east, north, up) with the prior of ``gnss.float_offset``; its epochs keep their ``.pos`` sigma as
their white error. The segment's positions then give the trajectory's shape, the fixes around it
and the IMU its place, and the position sigma inside it grows as the fixes are further away.

Fixed epochs found off their neighbours in the G/I's residuals (a wrong ambiguity fix,
:mod:`georefine.adjustment.gnss_jumps`) are segments of the same kind, after those of the flags,
with ``quality`` 1.

The estimated offsets are reported (``adjustment.json``, ``gnss_error.segments``), and an offset
beyond three times what the file states for its epochs is a warning: the file understates them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from georefine.config import GnssFloatOffset

log = logging.getLogger(__name__)

__all__ = ["GNSS_SEGMENT_BLOCK", "GnssSegments", "jump_spans", "non_fix_segments", "segment_warnings"]

GNSS_SEGMENT_BLOCK = "gnss_segment_offset"
"""Block of the segments' offsets ((S, 3), m in ``w``)."""


@dataclass(frozen=True)
class GnssSegments:
    """Segments of GNSS epochs worse than a fix, and their offsets where estimated.

    Attributes
    ----------
    index : (M,) int
        Segment of each epoch, -1 for a fix.
    t_start, t_end : (S,)
        First and last epoch of each segment (s from the dataset epoch).
    quality : (S,) int
        Worst RTKLIB Q in the segment; 1 for fixed epochs found off their neighbours (a wrong fix).
    epochs : (S,) int
    stated_sigma_w : (S, 3)
        RMS of the file's sigma of the segment's epochs per axis of ``w`` (m).
    prior_sigma_w : (3,)
        Prior sigma of each offset (m).
    value_w, sigma_w : (S, 3) or None
        Estimated offsets and their posterior sigma (m), where known.
    """

    index: np.ndarray
    t_start: np.ndarray
    t_end: np.ndarray
    quality: np.ndarray
    epochs: np.ndarray
    stated_sigma_w: np.ndarray
    prior_sigma_w: np.ndarray
    value_w: np.ndarray | None = None
    sigma_w: np.ndarray | None = None

    def __len__(self) -> int:
        return self.t_start.size

    def to_dict(self) -> list[dict]:
        """One record per segment for ``adjustment.json``: times (s from ``t0_gps``), worst Q, epochs, the
        file's sigma, the offset and its sigma (east, north, up; m)."""
        out = []
        for k in range(len(self)):
            rec = {"t_start_s": round(float(self.t_start[k]), 3), "t_end_s": round(float(self.t_end[k]), 3),
                   "quality": int(self.quality[k]), "epochs": int(self.epochs[k]),
                   "stated_sigma_enu_m": np.round(self.stated_sigma_w[k], 4).tolist()}
            if self.value_w is not None:
                rec["offset_enu_m"] = np.round(self.value_w[k], 4).tolist()
            if self.sigma_w is not None:
                rec["offset_sigma_enu_m"] = np.round(self.sigma_w[k], 4).tolist()
            out.append(rec)
        return out


def non_fix_segments(time: np.ndarray, quality: np.ndarray | None, cov_w: np.ndarray,
                     model: GnssFloatOffset | None, jumps: np.ndarray | None = None) -> GnssSegments | None:
    """The segments of epochs (``time`` increasing, s) whose ``quality`` is worse than a fix (Q > 1), then
    one per span of ``jumps`` ((J, 2) first and last epoch, s; wrong fixes) over the fixed epochs in it;
    None where there is none or no ``model``."""
    if model is None:
        return None
    time = np.asarray(time, dtype=float)
    flagged = None if quality is None else _flagged_segments(time, np.asarray(quality), cov_w, model)
    if jumps is None or len(jumps) == 0:
        return flagged
    fixed = np.ones(time.size, dtype=bool) if quality is None else np.asarray(quality) <= 1
    s0 = 0 if flagged is None else len(flagged)
    index = np.full(time.size, -1, dtype=np.int64) if flagged is None else flagged.index.copy()
    spans = []
    for a, b in np.asarray(jumps, dtype=float).reshape(-1, 2):
        k = np.flatnonzero(fixed & (time >= a - 1e-6) & (time <= b + 1e-6) & (index < 0))
        if k.size:
            index[k] = s0 + len(spans)
            spans.append(k)
    if not spans:
        return flagged
    var = np.diagonal(np.asarray(cov_w, dtype=float), axis1=1, axis2=2)
    stated = np.array([np.sqrt(var[k].mean(axis=0)) for k in spans])
    t_start = np.array([time[k[0]] for k in spans])
    t_end = np.array([time[k[-1]] for k in spans])
    epochs = np.array([k.size for k in spans], dtype=np.int64)
    prior = np.array([model.sigma_horizontal_m, model.sigma_horizontal_m, model.sigma_up_m])
    if flagged is None:
        return GnssSegments(index, t_start, t_end, np.ones(len(spans), dtype=np.int64), epochs, stated, prior)
    return GnssSegments(index, np.concatenate([flagged.t_start, t_start]), np.concatenate([flagged.t_end, t_end]),
                        np.concatenate([flagged.quality, np.ones(len(spans), dtype=np.int64)]),
                        np.concatenate([flagged.epochs, epochs]), np.vstack([flagged.stated_sigma_w, stated]), prior)


def jump_spans(segments: GnssSegments | None) -> np.ndarray | None:
    """(J, 2) first and last epoch (s) of the segments found off their neighbours (quality 1), or None."""
    if segments is None or not np.any(segments.quality == 1):
        return None
    k = segments.quality == 1
    return np.column_stack([segments.t_start[k], segments.t_end[k]])


def _flagged_segments(time: np.ndarray, quality: np.ndarray, cov_w: np.ndarray,
                      model: GnssFloatOffset) -> GnssSegments | None:
    """The segments of epochs worse than a fix (:func:`non_fix_segments` without jumps)."""
    bad = quality > 1
    if not np.any(bad):
        return None
    k = np.flatnonzero(bad)
    # A new segment where the previous epoch was a fix (or none) or the gap since the last non-fix epoch is long.
    prev_bad = np.concatenate([[False], bad[:-1]])[k]
    gap = np.concatenate([[np.inf], np.diff(time[k])])
    starts = ~prev_bad | (gap > model.max_gap_s)
    seg = np.cumsum(starts) - 1
    index = np.full(time.size, -1, dtype=np.int64)
    index[k] = seg
    n = int(seg[-1]) + 1
    var = np.diagonal(np.asarray(cov_w, dtype=float)[k], axis1=1, axis2=2)
    epochs = np.bincount(seg, minlength=n)
    stated = np.sqrt(np.column_stack([np.bincount(seg, weights=var[:, i], minlength=n) for i in range(3)])
                     / epochs[:, None])
    q = np.zeros(n, dtype=np.int64)
    np.maximum.at(q, seg, np.asarray(quality)[k].astype(np.int64))
    first = np.flatnonzero(starts)
    last = np.concatenate([first[1:], [k.size]]) - 1
    prior = np.array([model.sigma_horizontal_m, model.sigma_horizontal_m, model.sigma_up_m])
    return GnssSegments(index, time[k][first], time[k][last], q, epochs, stated, prior)


def segment_warnings(segments: GnssSegments, t0_gps: float, limit: float = 3.0) -> list[str]:
    """A message per segment whose estimated offset exceeds ``limit`` times the file's sigma on some axis
    (and two of its own sigmas): the file understates those epochs' error."""
    if segments.value_w is None:
        return []
    out = []
    sigma = segments.sigma_w if segments.sigma_w is not None else np.zeros_like(segments.value_w)
    for k in range(len(segments)):
        v, s = segments.value_w[k], segments.stated_sigma_w[k]
        ratio = np.abs(v) / s
        if np.any((ratio > limit) & (np.abs(v) > 2.0 * sigma[k])):
            what = ("fixed GNSS epochs (Q=1) found off their neighbours" if segments.quality[k] == 1
                    else f"GNSS epochs of quality Q={segments.quality[k]}")
            out.append(
                f"{what[0].upper() + what[1:]} from {t0_gps + segments.t_start[k]:.1f} to "
                f"{t0_gps + segments.t_end[k]:.1f} GPS s ({segments.epochs[k]} epochs): estimated offset east/north/up "
                f"{v[0]:+.3f}/{v[1]:+.3f}/{v[2]:+.3f} m (sigma {sigma[k][0]:.3f}/{sigma[k][1]:.3f}/{sigma[k][2]:.3f}), "
                f"up to {ratio.max():.1f} times the file's sigma ({s[0]:.3f}/{s[1]:.3f}/{s[2]:.3f} m): the file "
                "understates these epochs' error; the adjustment took them with an offset of their own "
                "(gnss.float_offset)")
    return out
