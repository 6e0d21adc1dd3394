"""Open a project folder and validate every input it names (``georefine check``).

Reads ``project.yaml`` and each sensor file with the strict readers of :mod:`georefine.io`,
then checks what only the files together can tell: GNSS and IMU time spans overlap, the scans
fall inside the navigation data, every scan point has a configured ``scanner_channel``.
Scans are streamed in chunks, so files larger than memory are fine. Nothing is written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from georefine.config import ProjectConfig, load_project
from georefine.errors import InputError
from georefine.geometry.earth import normal_gravity
from georefine.geometry.frames import LocalFrame
from georefine.io.files import check_output_folder
from georefine.io.gnss import GnssSolution, gnss_in_w, read_pos
from georefine.io.imu import ImuData, read_imr, read_imu_csv
from georefine.io.imu_gaps import BridgedImu, bridge_imu_gaps
from georefine.io.las import iter_las_chunks, read_las_info
from georefine.io.reference import ReferenceSurfaces, read_reference_surfaces
from georefine.lidar.tiles import strip_outside_error
from georefine.progress import no_progress
from georefine.trajectory.imu_check import check_imu_frame
from georefine.trajectory.sampled import interp_columns


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


def gnss_from_sbet(root: Path, cfg: ProjectConfig) -> GnssSolution:
    """``gnss.format: sbet``: the delivered SBET's positions at ``gnss.sbet_rate_hz`` as GNSS epochs.

    The covariance is the ``smrmsg`` north/east/down sigma (or ``gnss.sbet_sigma_m``) rotated to
    ECEF; quality 1. The raw IMU then rebuilds the attitude with them as from GNSS
    (docs/ARCHITECTURE.md §4.9).
    """
    from georefine.geometry.earth import R_e_n, geodetic_to_ecef
    from georefine.io.trajectory import read_sbet, read_smrmsg

    g = cfg.gnss
    sbet = read_sbet(root / g.files[0], gps_week=g.gps_week)
    step = max(1, int(round(1.0 / (g.sbet_rate_hz * float(np.median(np.diff(sbet.time_gps)))))))
    k = np.arange(0, len(sbet), step)
    t = sbet.time_gps[k]
    lat, lon, h = sbet.lat_rad[k], sbet.lon_rad[k], sbet.h_m[k]
    if g.smrmsg:
        acc = read_smrmsg(root / g.smrmsg, gps_week=g.gps_week if g.gps_week is not None else int(t[0] // 604800))
        sig = interp_columns(t, acc.time_gps, acc.sigma_ned_m)
    else:
        sig = np.full((t.size, 3), g.sbet_sigma_m)
    R = R_e_n(lat, lon)
    cov = np.einsum("nij,nj,nkj->nik", R, sig**2, R)
    n = t.size
    return GnssSolution(t, geodetic_to_ecef(lat, lon, h), cov, np.ones(n, dtype=np.int64), np.zeros(n, dtype=np.int64),
                        np.zeros(n), np.zeros(n))


def read_project_gnss(root: Path, cfg: ProjectConfig) -> GnssSolution:
    """Read and concatenate the project's ``.pos`` files (time-ordered, no duplicates), or the SBET's positions."""
    if cfg.gnss.format == "sbet":
        return gnss_from_sbet(root, cfg)
    parts = [read_pos(root / f) for f in cfg.gnss.files]
    if len(parts) == 1:
        return parts[0]
    order = np.argsort(np.concatenate([p.time_gps for p in parts]), kind="stable")
    cat = {
        name: np.concatenate([getattr(p, name) for p in parts])[order]
        for name in ("time_gps", "position_ecef", "covariance_ecef", "quality", "num_sats", "age_s", "ratio")
    }
    if np.any(np.diff(cat["time_gps"]) <= 0):
        raise InputError(
            "GNSS files overlap in time", path=root / cfg.gnss.files[1], field="time", expected="disjoint files"
        )
    return GnssSolution(**cat)


def read_project_imu(root: Path, cfg: ProjectConfig) -> ImuData:
    """Read the project's IMU file in the configured format."""
    path = root / cfg.imu.file
    if cfg.imu.format == "imr":
        return read_imr(path, gps_week=cfg.imu.gps_week)
    return read_imu_csv(path, rate_hz=cfg.imu.rate_hz)


def check_navigation_spans(
    root: Path, cfg: ProjectConfig, gnss: GnssSolution, imu: ImuData
) -> tuple[np.ndarray, tuple[float, float], tuple[float, float]]:
    """Usable GNSS epochs and the GNSS/IMU time spans (GPS s); they must overlap.

    Raises
    ------
    InputError
        No epoch of the configured quality, or GNSS and IMU spans that do not overlap.
    """
    usable = gnss.quality <= cfg.gnss.min_quality
    if not np.any(usable):
        raise InputError(
            "no epoch of sufficient quality",
            path=root / cfg.gnss.files[0],
            field="Q",
            expected=f"Q <= {cfg.gnss.min_quality} (gnss.min_quality)",
            found=f"best Q = {int(gnss.quality.min())}",
        )
    g_span = (float(gnss.time_gps[usable][0]), float(gnss.time_gps[usable][-1]))
    i_span = (float(imu.time_gps[0]), float(imu.time_gps[-1]))
    if g_span[1] <= i_span[0] or i_span[1] <= g_span[0]:
        raise InputError(
            "GNSS and IMU time spans do not overlap",
            path=root / cfg.imu.file,
            field="time",
            expected=f"overlap with GNSS {g_span[0]:.3f} .. {g_span[1]:.3f} GPS s",
            found=f"{i_span[0]:.3f} .. {i_span[1]:.3f} GPS s",
        )
    return usable, g_span, i_span


def bridge_project_imu(root: Path, cfg: ProjectConfig, imu: ImuData) -> BridgedImu:
    """The project's IMU with its sampling gaps bridged (:mod:`georefine.io.imu_gaps`), as check and run see it.

    Raises
    ------
    InputError
        A gap longer than ``imu.max_gap_s``, naming the file and the record after it.
    """
    bridged, too_long = bridge_imu_gaps(imu, cfg.imu.max_gap_s)
    if too_long is not None:
        k = too_long.index + 1  # the first sample after the gap: CSV line k + 2 (a header line), IMR record k + 1
        raise InputError(
            f"IMU sampling gap of {too_long.duration_s:.3f} s ({too_long.missing} samples missing), longer than "
            "imu.max_gap_s can bridge",
            path=root / cfg.imu.file, line=k + 2 if cfg.imu.format == "csv" else k + 1,
            record_kind="line" if cfg.imu.format == "csv" else "record", field="time",
            expected=f"gaps of at most {cfg.imu.max_gap_s:g} s (imu.max_gap_s)",
            found=f"{too_long.t_before:.6f} -> {too_long.t_after:.6f} GPS s",
        )
    return bridged


def gnss_gaps(gnss: GnssSolution, usable: np.ndarray, factor: float = 3.0) -> np.ndarray:
    """(K, 2) GPS seconds around each gap between usable GNSS epochs longer than ``factor`` nominal intervals.

    Missing epochs and epochs of a quality worse than ``gnss.min_quality`` both open a gap: the
    adjustment bridges it on the IMU alone (its sigma grows with the gap).
    """
    t = gnss.time_gps[usable]
    if t.size < 3:
        return np.empty((0, 2))
    dt = np.diff(t)
    idx = np.flatnonzero(dt > factor * float(np.median(dt)))
    return np.column_stack([t[idx], t[idx + 1]]) if idx.size else np.empty((0, 2))


def check_imu_plausible(root: Path, cfg: ProjectConfig, gnss: GnssSolution, imu: ImuData) -> None:
    """Units, axes and signs of the IMU record against the GNSS trajectory (:mod:`georefine.trajectory.imu_check`).

    The same rule for ``georefine check`` and every workflow, run before any work (about a second).

    Raises
    ------
    InputError
        Naming the IMU file, the fields, what a forward-right-down record in SI units would show
        and what this one shows.
    """
    keep = gnss.quality <= cfg.gnss.min_quality
    if keep.sum() < 2:
        return  # check_navigation_spans reports it
    i = int(np.flatnonzero(keep)[0])
    lat, lon, h = (np.atleast_1d(a)[i] for a in gnss.geodetic())
    frame = LocalFrame(float(lat), float(lon), float(h))
    t0 = float(np.floor(imu.time_gps[0]))
    g_time, g_p, _ = gnss_in_w(frame, t0, gnss, cfg.gnss.min_quality)
    finding = check_imu_frame(imu.time_gps - t0, imu.gyro, imu.acc, g_time, g_p,
                              float(normal_gravity(frame.lat0_rad, frame.h0_m)))
    if finding is not None:
        raise InputError(finding.message, path=root / cfg.imu.file, field=finding.field, expected=finding.expected,
                         found=finding.found)


def inspect_project(
    project_dir: str | Path,
    *,
    chunk_size: int = 2_000_000,
    progress: Callable[[str, float, float], None] | None = None,
) -> ProjectSummary:
    """Validate a project folder: configuration, every sensor file, and their consistency.

    Raises
    ------
    InputError
        On the first problem, naming the file, line or record, field, expected and found.
    """
    root = Path(project_dir)
    if not root.is_dir():
        raise InputError("project folder not found", path=root)
    cfg = load_project(root)
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


def output_folder(out: str | Path, project_root: Path) -> Path:
    """``out`` as a Path, refusing the project folder or anything inside it (inputs stay untouched),
    and a path that exists but is not a folder, or lies below a file."""
    out = Path(out)
    if out.resolve() == project_root.resolve() or project_root.resolve() in out.resolve().parents:
        raise InputError("refusing to write into the project folder", path=out, expected="an output folder outside the inputs")
    return check_output_folder(out)
