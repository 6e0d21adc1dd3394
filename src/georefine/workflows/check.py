"""Validate a project and every input it names (``georefine check``).

Reads ``project.yaml`` and each sensor file with the strict readers of :mod:`georefine.io`
(:mod:`georefine.workflows.project`), then checks what only the files together can tell: GNSS
and IMU time spans overlap, the scans fall inside the navigation data, every scan point has a
configured ``scanner_channel``. A project of several flights (``flights`` in ``project.yaml``,
docs/ARCHITECTURE.md §3) is checked flight by flight: each flight's GNSS and IMU as a project's,
each strip against its own flight's navigation span; and the flights do not overlap in time
(unless two read the same IMU record), and no file is listed as two strips. Scans are streamed in
chunks, so files larger than memory are fine. Nothing is written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from georefine.adjustment.gnss_imu import unmodelled_temperature
from georefine.adjustment.gnss_segments import non_fix_segments
from georefine.config import FlightConfig, GnssFloatOffset, ProjectConfig
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

__all__ = ["FlightSummary", "ProjectSummary", "StripSummary", "inspect_project"]


@dataclass(frozen=True)
class StripSummary:
    """One scan strip: file, point count, time span (GPS s), points per channel, points outside the IMU span
    (of its own flight's navigation, ``flight_id``)."""

    path: Path
    point_count: int
    time_span_gps: tuple[float, float]
    points_per_channel: dict[int, int]
    strip_ids: tuple[int, ...]
    outside_navigation: int
    flight_id: int = 1


@dataclass(frozen=True)
class FlightSummary:
    """One flight: id and name, its navigation's time span (GPS s, where its GNSS and IMU overlap), its
    strips, IMU samples (rate, sampling gaps bridged) and GNSS epochs (of quality ``gnss.min_quality``)."""

    id: int
    name: str
    span_gps: tuple[float, float]
    strips: int
    imu_samples: int
    imu_rate_hz: float
    imu_gaps: int
    gnss_epochs: int
    gnss_usable_epochs: int


@dataclass(frozen=True)
class ProjectSummary:
    """What :func:`inspect_project` found.

    For a project of several flights the GNSS and IMU figures are the flights' together (epochs and
    samples summed, spans from the first flight's start to the last one's end, the IMU rate the
    first flight's) and ``flights`` has one record each; a single-flight project has one record.
    """

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
    flights: tuple[FlightSummary, ...] = ()
    imu_temperature_c: tuple[float, float] | None = None
    """The lowest and highest temperature the IMU file logs (deg C; a single flight), None where it logs none."""

    def summary(self) -> str:
        g0, g1 = self.gnss_span_gps
        i0, i1 = self.imu_span_gps
        lines = [f"Project {self.config.name!r} at {self.root}"]
        several = self.config.multi_flight
        if self.delivered is not None:
            n, rate, acc = self.delivered
            lines.append(f"  delivered trajectory: {n:,} SBET records at {rate:.0f} Hz, {g1 - g0:.1f} s, "
                         + ("smrmsg sigmas" if acc else "default sigmas (no smrmsg)"))
        elif several:
            lines.append(f"  {len(self.flights)} flight{'s' if len(self.flights) != 1 else ''}:")
            for f in self.flights:
                a, b = f.span_gps
                lines.append(
                    f"    flight {f.id} ({f.name}): {a:.3f} .. {b:.3f} GPS s ({b - a:.1f} s), {f.strips} "
                    f"strip{'s' if f.strips != 1 else ''}, IMU {f.imu_samples:,} samples at {f.imu_rate_hz:g} Hz "
                    f"({f.imu_gaps} gaps), GNSS {f.gnss_epochs:,} epochs ({f.gnss_usable_epochs:,} usable)")
        else:
            lines += [
                f"  GNSS: {self.gnss_epochs:,} epochs ({self.gnss_usable_epochs:,} usable), {g1 - g0:.1f} s",
                f"  IMU:  {self.imu_samples:,} samples at {self.imu_rate_hz:g} Hz, {i1 - i0:.1f} s, {len(self.imu_gaps)} gaps"
                + ("" if self.imu_temperature_c is None else
                   ", temperature {:.1f} .. {:.1f} deg C".format(*self.imu_temperature_c)),
            ]
        for s in self.strips:
            per = ", ".join(f"ch{k}: {v:,}" for k, v in sorted(s.points_per_channel.items()))
            name = f"{_relative(s.path, self.root)} (flight {s.flight_id})" if several else s.path.name
            lines.append(
                f"  {name}: {s.point_count:,} points over {s.time_span_gps[1] - s.time_span_gps[0]:.1f} s ({per})"
            )
        if self.reference_surfaces:
            lines.append(f"  reference surfaces: {self.reference_surfaces}")
        if self.photos is not None:
            n, cams, control, check, measured = self.photos
            lines.append(f"  photos: {n} images ({cams} camera{'s' if cams != 1 else ''}), {control} control and "
                         f"{check} check points, {measured} image measurements")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _relative(path: Path, root: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return str(path)


@dataclass(frozen=True)
class _Navigation:
    """What the navigation check of one flight found (GPS s)."""

    gnss_span: tuple[float, float]
    imu_span: tuple[float, float]
    gnss_epochs: int
    gnss_usable: int
    imu_samples: int
    imu_rate_hz: float
    imu_gaps: np.ndarray
    delivered: tuple[int, float, bool] | None = None
    imu_temperature_c: tuple[float, float] | None = None

    @property
    def span(self) -> tuple[float, float]:
        """Where GNSS and IMU overlap: the navigation's span."""
        return max(self.gnss_span[0], self.imu_span[0]), min(self.gnss_span[1], self.imu_span[1])


def _check_navigation(root: Path, cfg: ProjectConfig, warnings: list[str], prefix: str = "") -> _Navigation:
    """The GNSS and IMU of a single-flight configuration (a project's, or one flight's) read and checked
    as the workflow reads them; the warnings (gaps bridged) appended with ``prefix``."""
    if cfg.delivered_trajectory:  # the SBET (and smrmsg) with the workflow's reader and checks (§4.9)
        from georefine.workflows.delivered import read_delivered

        _, t0, prior = read_delivered(root, cfg)
        span = (t0 + float(prior.time[0]), t0 + float(prior.time[-1]))
        return _Navigation(span, span, 0, 0, 0, 0.0, np.zeros((0, 2)),
                           (int(prior.time.size), float(prior.rate_hz), bool(cfg.trajectory.smrmsg)))
    gnss = read_project_gnss(root, cfg)
    imu = read_project_imu(root, cfg)
    usable, g_span, i_span = check_navigation_spans(root, cfg, gnss, imu)
    bridged = bridge_project_imu(root, cfg, imu)
    check_imu_plausible(root, cfg, gnss, bridged.data)
    gaps = np.array([(g.t_before, g.t_after) for g in bridged.gaps]).reshape(-1, 2)
    if bridged.gaps:
        warnings.append(prefix + bridged.describe())
    g_gaps = gnss_gaps(gnss, usable)
    if len(g_gaps):
        k = int(np.argmax(g_gaps[:, 1] - g_gaps[:, 0]))
        warnings.append(f"{prefix}{len(g_gaps)} GNSS gaps (no epoch of quality Q <= {cfg.gnss.min_quality}), the "
                        f"longest {g_gaps[k, 1] - g_gaps[k, 0]:.1f} s from {g_gaps[k, 0]:.1f} GPS s: bridged on the "
                        "IMU alone")
    warnings.extend(prefix + w for w in non_fix_warnings(gnss, usable, cfg))
    temperature = None
    if imu.temperature_c is not None:
        temperature = (float(imu.temperature_c.min()), float(imu.temperature_c.max()))
        note = unmodelled_temperature(imu.temperature_c, cfg.imu.errors, cfg.processing.trajectory)
        if note is not None:
            warnings.append(prefix + note)
    elif cfg.processing.trajectory.estimate_temperature_coefficients is True:
        raise InputError("the IMU file logs no temperature", path=root / cfg.imu.file, field="temperature_c",
                         expected="a temperature_c column where processing.trajectory."
                         "estimate_temperature_coefficients is true", found="none")
    return _Navigation(g_span, i_span, int(gnss.time_gps.size), int(usable.sum()), int(imu.time_gps.size),
                       float(imu.rate_hz), gaps, imu_temperature_c=temperature)


_QUALITY_NAMES = {1: "fix", 2: "float", 3: "SBAS", 4: "DGPS", 5: "single", 6: "PPP"}


def non_fix_warnings(gnss, usable: np.ndarray, cfg: ProjectConfig) -> list[str]:
    """What ``check`` says of the GNSS epochs worse than a fix: those it uses, per quality, in segments
    (the longest named), and how the adjustment takes them; those beyond ``gnss.min_quality``, per quality."""
    q = np.asarray(gnss.quality)
    out = []
    used = usable & (q > 1)
    if np.any(used):
        model = cfg.gnss.float_offset
        seg = non_fix_segments(gnss.time_gps[usable], q[usable], np.zeros((int(usable.sum()), 3, 3)) + np.eye(3),
                               model or GnssFloatOffset())
        length = seg.t_end - seg.t_start
        k = int(np.argmax(length))
        kinds = ", ".join(f"{int((q[used] == v).sum())} Q={v} ({_QUALITY_NAMES.get(int(v), '?')})"
                          for v in np.unique(q[used]))
        how = ("each segment gets an offset of its own (gnss.float_offset)" if model is not None else
               "taken as fixes with their .pos sigma (gnss.float_offset: null)")
        out.append(f"{int(used.sum())} GNSS epochs without a fixed solution ({kinds}) in {len(seg)} segment"
                   f"{'s' if len(seg) != 1 else ''}, the longest {length[k]:.1f} s from {seg.t_start[k]:.1f} GPS s "
                   f"({seg.epochs[k]} epochs): {how}")
    left = ~usable
    if np.any(left):
        kinds = ", ".join(f"{int((q[left] == v).sum())} Q={v} ({_QUALITY_NAMES.get(int(v), '?')})"
                          for v in np.unique(q[left]))
        out.append(f"{int(left.sum())} GNSS epochs left out, worse than gnss.min_quality {cfg.gnss.min_quality}: {kinds}")
    return out


@dataclass(frozen=True)
class _StripFlight:
    """The flight a strip is checked against, in a project of several flights."""

    flight: FlightConfig
    span: tuple[float, float]
    others: tuple[tuple[FlightConfig, tuple[float, float]], ...]


def _check_strip(path: Path, cfg: ProjectConfig, nav: tuple[float, float], channels: set[int], chunk_size: int,
                 progress: Callable[[str, float, float], None] | None, warnings: list[str],
                 flight: _StripFlight | None = None) -> StripSummary:
    """One strip streamed: channels configured, times inside the navigation span ``nav`` (GPS s)."""
    shift = cfg.scanner.time_offset_s  # the strips' time stamps plus this are navigation time
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
        if flight is None:
            raise strip_outside_error(path, (nav[0] - shift, nav[1] - shift), (t_min, t_max), shift)
        raise _strip_outside_flight(path, flight, (t_min, t_max), shift)
    name = path.name if flight is None else f"{path.name} (flight {flight.flight.id})"
    if outside:
        where = "the navigation's time span" if flight is None else \
            f"its flight's navigation time span {nav[0]:.3f} .. {nav[1]:.3f} GPS s"
        warnings.append(f"{name}: {outside:,} points outside {where} (they will be left out)")
    missing = channels - set(per)
    if missing:
        warnings.append(f"{name}: no points of channel(s) {sorted(missing)}")
    return StripSummary(path, done, (t_min, t_max), per, tuple(sorted(ids)), outside,
                        1 if flight is None else flight.flight.id)


def _strip_outside_flight(path: Path, flight: _StripFlight, found_gps: tuple[float, float],
                          shift: float) -> InputError:
    """The error for a strip none of whose points lies in its own flight's navigation span."""
    f, (a, b) = flight.flight, flight.span
    lo, hi = found_gps[0] + shift, found_gps[1] + shift
    inside = [o for o, (oa, ob) in flight.others if lo <= ob and hi >= oa]
    hint = f"; its times lie in the span of flight {inside[0].id}: listed under the wrong flight?" if inside else ""
    return InputError(
        f"no point of the strip lies inside the time span of its flight {f.id} ({f.label}){hint}", path=path,
        field="gps_time",
        expected=f"times within {a - shift:.3f} .. {b - shift:.3f} GPS s (flight {f.id}'s navigation"
        + (f", scanner time offset {shift:g} s applied)" if shift else ")"),
        found=f"{found_gps[0]:.3f} .. {found_gps[1]:.3f} GPS s",
    )


def _check_flights_apart(root: Path, flights: list[tuple[FlightConfig, _Navigation]], warnings: list[str]) -> None:
    """Flights do not overlap in time, unless two read the same IMU record (then a warning).

    Raises
    ------
    InputError
        Naming the later flight's IMU file, both flights and their spans.
    """
    order = sorted(flights, key=lambda fn: fn[1].span[0])
    for i, (f1, n1) in enumerate(order):
        for f2, n2 in order[i + 1:]:
            (a1, b1), (a2, b2) = n1.span, n2.span
            if a2 >= b1:
                continue
            if (root / f1.imu_file).resolve() == (root / f2.imu_file).resolve():
                warnings.append(f"flights {f1.id} and {f2.id} read the same IMU record {f1.imu_file}: their spans "
                                "coincide, and each has its own IMU errors")
                continue
            raise InputError(
                f"flights {f1.id} and {f2.id} overlap in time: each flight is a take-off of its own, flown one after "
                "the other", path=root / f2.imu_file, field="time",
                expected=f"flight {f2.id}'s navigation after flight {f1.id}'s, which spans "
                f"{a1:.3f} .. {b1:.3f} GPS s",
                found=f"flight {f2.id}: {a2:.3f} .. {b2:.3f} GPS s",
            )


def _check_strips_distinct(root: Path, cfg: ProjectConfig) -> None:
    """No file is listed as two strips (two names of one file: a link, ``a/../b``)."""
    seen: dict[Path, tuple[int, int, str]] = {}
    for k, f in enumerate(cfg.flights or ()):
        for j, rel in enumerate(f.strips):
            key = (root / rel).resolve()
            if key in seen:
                fid, _, first = seen[key]
                raise InputError(
                    f"the same file is listed as two strips, {first} (flight {fid}) and {rel} (flight {f.id})",
                    path=root / rel, field=f"flights.{k}.strips.{j}", expected="each strip in exactly one flight",
                    found=f"also flight {fid}'s {first}")
            seen[key] = (f.id, j, rel)


def inspect_project(
    project: ProjectLike,
    *,
    chunk_size: int = 2_000_000,
    progress: Callable[[str, float, float], None] | None = None,
) -> ProjectSummary:
    """Validate a project (an opened :class:`~georefine.workflows.opened.Project` or its folder):
    configuration, every sensor file, and their consistency; for a project of several flights,
    every flight's files, each strip against its own flight, and the flights apart in time.

    Raises
    ------
    InputError
        On the first problem, naming the file, line or record, field, expected and found.
    """
    project = as_project(project)
    root, cfg = project.root, project.config
    warnings: list[str] = []
    channels = {c.id for c in cfg.scanner.channels}

    strips: list[StripSummary] = []
    if cfg.flights is None:
        nav = _check_navigation(root, cfg, warnings)
        flights = [FlightSummary(1, "flight_1", nav.span, len(cfg.scanner.files), nav.imu_samples, nav.imu_rate_hz,
                                 len(nav.imu_gaps), nav.gnss_epochs, nav.gnss_usable)]
        for rel in cfg.scanner.files:
            strips.append(_check_strip(root / rel, cfg, nav.span, channels, chunk_size, progress, warnings))
        g_span, i_span = nav.gnss_span, nav.imu_span
        totals = nav
    else:
        checked = []
        for f in cfg.flights:
            fcfg = cfg.flight_config(f.id)
            checked.append((f, fcfg, _check_navigation(root, fcfg, warnings, prefix=f"flight {f.id}: ")))
        _check_flights_apart(root, [(f, n) for f, _, n in checked], warnings)
        _check_strips_distinct(root, cfg)
        for f, fcfg, n in checked:
            others = tuple((o, on.span) for o, _, on in checked if o.id != f.id)
            for rel in fcfg.scanner.files:
                strips.append(_check_strip(root / rel, fcfg, n.span, channels, chunk_size, progress, warnings,
                                           _StripFlight(f, n.span, others)))
        flights = [FlightSummary(f.id, f.label, n.span, len(f.strips), n.imu_samples, n.imu_rate_hz,
                                 len(n.imu_gaps), n.gnss_epochs, n.gnss_usable) for f, _, n in checked]
        navs = [n for _, _, n in checked]
        g_span = (min(n.gnss_span[0] for n in navs), max(n.gnss_span[1] for n in navs))
        i_span = (min(n.imu_span[0] for n in navs), max(n.imu_span[1] for n in navs))
        totals = _Navigation(g_span, i_span, sum(n.gnss_epochs for n in navs), sum(n.gnss_usable for n in navs),
                             sum(n.imu_samples for n in navs), navs[0].imu_rate_hz,
                             np.concatenate([n.imu_gaps for n in navs]).reshape(-1, 2))

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
        root=root, config=cfg, gnss_epochs=totals.gnss_epochs, gnss_usable_epochs=totals.gnss_usable,
        gnss_span_gps=g_span, imu_samples=totals.imu_samples, imu_rate_hz=totals.imu_rate_hz,
        imu_span_gps=i_span, imu_gaps=totals.imu_gaps, strips=tuple(strips), reference_surfaces=n_ref,
        warnings=tuple(warnings), photos=photos, delivered=totals.delivered, flights=tuple(flights),
        imu_temperature_c=totals.imu_temperature_c if cfg.flights is None else None,
    )
