"""Validate a project and every input it names (``georefine check``).

Reads ``project.yaml`` and each sensor file with the strict readers of :mod:`georefine.io`
(:mod:`georefine.workflows.project`), then checks what only the files together can tell: GNSS
and IMU time spans overlap, the scans fall inside the navigation data, every scan point has a
configured ``scanner_channel``. Scans are streamed in chunks, so files larger than memory are
fine. Nothing is written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from georefine.config import ProjectConfig
from georefine.errors import InputError
from georefine.io.las import iter_las_chunks, read_las_info
from georefine.io.reference import ReferenceSurfaces, read_reference_surfaces
from georefine.lidar.tiles import strip_outside_error
from georefine.progress import no_progress
from georefine.workflows.opened import ProjectLike, as_project
from georefine.workflows.project import (
    bridge_project_imu,
    check_imu_plausible,
    check_navigation_spans,
    gnss_gaps,
    read_project_gnss,
    read_project_imu,
)

__all__ = ["ProjectSummary", "StripSummary", "inspect_project"]


@dataclass(frozen=True)
class StripSummary:
    """One scan strip: file, point count, time span (GPS s), points per channel, points outside the IMU span."""

    path: Path
    point_count: int
    time_span_gps: tuple[float, float]
    points_per_channel: dict[int, int]
    strip_ids: tuple[int, ...]
    outside_navigation: int


@dataclass(frozen=True)
class ProjectSummary:
    """What :func:`inspect_project` found."""

    root: Path
    config: ProjectConfig
    gnss_epochs: int
    gnss_usable_epochs: int
    gnss_span_gps: tuple[float, float]
    imu_samples: int
    imu_rate_hz: float
    imu_span_gps: tuple[float, float]
    imu_gaps: np.ndarray
    strips: tuple[StripSummary, ...]
    reference_surfaces: int = 0
    warnings: tuple[str, ...] = field(default_factory=tuple)
    photos: tuple[int, int, int, int, int] | None = None
    """Images, cameras, control points, check points, image measurements (None: no photos section)."""
    delivered: tuple[int, float, bool] | None = None
    """A delivered trajectory (docs/ARCHITECTURE.md §4.9): SBET records, their rate (Hz), whether an smrmsg is given."""

    def summary(self) -> str:
        g0, g1 = self.gnss_span_gps
        i0, i1 = self.imu_span_gps
        lines = [f"Project {self.config.name!r} at {self.root}"]
        if self.delivered is not None:
            n, rate, acc = self.delivered
            lines.append(f"  delivered trajectory: {n:,} SBET records at {rate:.0f} Hz, {g1 - g0:.1f} s, "
                         + ("smrmsg sigmas" if acc else "default sigmas (no smrmsg)"))
        else:
            lines += [
                f"  GNSS: {self.gnss_epochs:,} epochs ({self.gnss_usable_epochs:,} usable), {g1 - g0:.1f} s",
                f"  IMU:  {self.imu_samples:,} samples at {self.imu_rate_hz:g} Hz, {i1 - i0:.1f} s, {len(self.imu_gaps)} gaps",
            ]
        for s in self.strips:
            per = ", ".join(f"ch{k}: {v:,}" for k, v in sorted(s.points_per_channel.items()))
            lines.append(
                f"  {s.path.name}: {s.point_count:,} points over {s.time_span_gps[1] - s.time_span_gps[0]:.1f} s ({per})"
            )
        if self.reference_surfaces:
            lines.append(f"  reference surfaces: {self.reference_surfaces}")
        if self.photos is not None:
            n, cams, control, check, measured = self.photos
            lines.append(f"  photos: {n} images ({cams} camera{'s' if cams != 1 else ''}), {control} control and "
                         f"{check} check points, {measured} image measurements")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def inspect_project(
    project: ProjectLike,
    *,
    chunk_size: int = 2_000_000,
    progress: Callable[[str, float, float], None] | None = None,
) -> ProjectSummary:
    """Validate a project (an opened :class:`~georefine.workflows.opened.Project` or its folder):
    configuration, every sensor file, and their consistency.

    Raises
    ------
    InputError
        On the first problem, naming the file, line or record, field, expected and found.
    """
    project = as_project(project)
    root, cfg = project.root, project.config
    warnings: list[str] = []

    delivered = None
    if cfg.delivered_trajectory:  # the SBET (and smrmsg) with the workflow's reader and checks (§4.9)
        from georefine.workflows.delivered import read_delivered

        _, t0, prior = read_delivered(root, cfg)
        g_span = i_span = (t0 + float(prior.time[0]), t0 + float(prior.time[-1]))
        delivered = (int(prior.time.size), float(prior.rate_hz), bool(cfg.trajectory.smrmsg))
        n_gnss = n_usable = n_imu = 0
        rate, gaps = 0.0, np.zeros((0, 2))
    else:
        gnss = read_project_gnss(root, cfg)
        imu = read_project_imu(root, cfg)
        usable, g_span, i_span = check_navigation_spans(root, cfg, gnss, imu)
        bridged = bridge_project_imu(root, cfg, imu)
        check_imu_plausible(root, cfg, gnss, bridged.data)
        gaps = np.array([(g.t_before, g.t_after) for g in bridged.gaps]).reshape(-1, 2)
        if bridged.gaps:
            warnings.append(bridged.describe())
        g_gaps = gnss_gaps(gnss, usable)
        if len(g_gaps):
            k = int(np.argmax(g_gaps[:, 1] - g_gaps[:, 0]))
            warnings.append(f"{len(g_gaps)} GNSS gaps (no epoch of quality Q <= {cfg.gnss.min_quality}), the longest "
                            f"{g_gaps[k, 1] - g_gaps[k, 0]:.1f} s from {g_gaps[k, 0]:.1f} GPS s: bridged on the IMU alone")
        n_gnss, n_usable, n_imu, rate = int(gnss.time_gps.size), int(usable.sum()), int(imu.time_gps.size), float(imu.rate_hz)

    channels = {c.id for c in cfg.scanner.channels}
    nav = (max(g_span[0], i_span[0]), min(g_span[1], i_span[1]))
    shift = cfg.scanner.time_offset_s  # the strips' time stamps plus this are navigation time
    strips = []
    for rel in cfg.scanner.files:
        path = root / rel
        info = read_las_info(path)
        per: dict[int, int] = {}
        ids: set[int] = set()
        t_min, t_max, outside, done = np.inf, -np.inf, 0, 0
        for chunk in iter_las_chunks(path, chunk_size):
            ch, cnt = np.unique(chunk.scanner_channel, return_counts=True)
            unknown = ch[~np.isin(ch, list(channels))]
            if unknown.size:
                first = done + int(np.flatnonzero(np.isin(chunk.scanner_channel, unknown))[0]) + 1
                raise InputError(
                    "point with a scanner_channel not configured in project.yaml",
                    path=path, line=first, record_kind="point", field="scanner_channel",
                    expected="one of " + ", ".join(map(str, sorted(channels))), found=str(int(unknown[0])),
                )
            for c, k in zip(ch.tolist(), cnt.tolist()):
                per[c] = per.get(c, 0) + k
            ids.update(np.unique(chunk.point_source_id).tolist())
            if len(chunk):
                t_min = min(t_min, float(chunk.time_gps.min()))
                t_max = max(t_max, float(chunk.time_gps.max()))
                t = chunk.time_gps + shift
                outside += int(np.count_nonzero((t < nav[0]) | (t > nav[1])))
            done += len(chunk)
            if progress is not None:
                progress(f"check {path.name}", done, info.point_count)
        if done == 0:
            raise InputError("strip has no points", path=path)
        if outside == done:  # as the workflow refuses it (lidar.tiles.refuse_strips_outside)
            raise strip_outside_error(path, (nav[0] - shift, nav[1] - shift), (t_min, t_max), shift)
        if outside:
            warnings.append(f"{path.name}: {outside:,} points outside the navigation's time span (they will be left out)")
        missing = channels - set(per)
        if missing:
            warnings.append(f"{path.name}: no points of channel(s) {sorted(missing)}")
        strips.append(StripSummary(path, done, (t_min, t_max), per, tuple(sorted(ids)), outside))

    n_ref = 0
    if cfg.reference.surfaces:
        surfaces: ReferenceSurfaces = read_reference_surfaces(root / cfg.reference.surfaces)
        n_ref = len(surfaces.surface_ids())

    photos = None
    if cfg.photos is not None:  # the same reading as the co-adjustment's, and every image decoded
        from georefine.workflows.photo_block import load_photo_project

        pp = load_photo_project(root, cfg)
        pp.read_photos(progress if progress is not None else no_progress)
        warnings.extend(pp.warnings)
        control = int(pp.gcps.is_control.sum())
        photos = (len(pp.eop), len(pp.cameras), control, len(pp.gcps) - control, len(pp.image_points))

    return ProjectSummary(
        root=root, config=cfg, gnss_epochs=n_gnss, gnss_usable_epochs=n_usable,
        gnss_span_gps=g_span, imu_samples=n_imu, imu_rate_hz=rate,
        imu_span_gps=i_span, imu_gaps=gaps, strips=tuple(strips), reference_surfaces=n_ref, warnings=tuple(warnings),
        photos=photos, delivered=delivered,
    )
