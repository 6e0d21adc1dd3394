"""Delivered data as a project: georeferenced strips and an SBET back to scanner-frame strips (docs/ARCHITECTURE.md §4.9).

What a LiDAR vendor's software delivers is one LAS/LAZ file per strip in a projected CRS with
GPS time, and the trajectory it georeferenced them with (an SBET and its ``smrmsg``).
:func:`import_strips` turns that into a Georefine project that ``georefine run`` adjusts:

* every point goes back into the scanner frame by inverse direct georeferencing with the SBET,
  the lever arm ``p_b_s`` and the boresight ``R_b_s`` it was georeferenced with::

      x_s = R_b_s^T (R_w_b(t)^T (x_w - p_w_b(t)) - p_b_s)

  (``x_w`` the point in ``w``, from the file's CRS through PROJ; the pose interpolated in the
  SBET at the point's time as georeferencing interpolates it, so georeferencing the imported
  strip with the same SBET gives the delivered points back to the file's resolution);
* ``scans/<strip>.laz``: LAS 1.4 point format 6, ``gps_time`` adjusted standard GPS time,
  ``scanner_channel`` (0 when the file's format has none), ``point_source_id`` = strip id,
  intensity and return numbers kept;
* ``nav/``: the SBET and ``smrmsg`` copied; ``project.yaml`` with ``crs.output_epsg`` (the
  strips' CRS), the ``trajectory`` section and the ``scanner`` section; ``import.json``
  records where every file came from.

Everything is checked before anything is written: every strip opens, has a CRS that PROJ
identifies as one EPSG code (the same for all), GPS time (adjusted standard time, or GPS week
time with ``--gps-week``), points, and lies inside the SBET. The per-point work runs in record
ranges as tasks (:mod:`georefine.tasks`), written in order as they arrive: memory holds a few
ranges whatever the files' sizes. ``project.yaml`` is written last.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georefine.config import (
    ChannelConfig,
    ImuFileConfig,
    boresight_matrix,
    default_channels,
    read_yaml,
    validate_model,
    write_yaml,
)
from georefine.errors import InputError
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.files import SECONDS_PER_WEEK, make_output_folder, write_json
from georefine.io.las import PointCloud
from georefine.io.las_encode import EncodedPoints, LasLayout, encode_points
from georefine.io.las_writer import LasWriter
from georefine.io.trajectory import read_sbet, read_smrmsg, smrmsg_path
from georefine.lidar.georeference import PoseInterpolator
from georefine.progress import Progress, no_progress
from georefine.tasks import DEFAULT_SCHEDULER, TaskRunner, runner_for
from georefine.trajectory.sampled import trajectory_from_sbet

log = logging.getLogger(__name__)

__all__ = ["DeliveredStrip", "ImportResult", "import_strips", "inspect_delivered_strip"]

RANGE_POINTS = 500_000
"""Records per task of the inverse georeferencing."""
GPS_TIME_OFFSET_S = 1.0e9
"""Adjusted standard GPS time is GPS seconds minus this (LAS 1.4)."""


@dataclass(frozen=True)
class DeliveredStrip:
    """Header facts of a delivered strip, checked (:func:`inspect_delivered_strip`)."""

    path: Path
    point_count: int
    epsg: int
    has_channel: bool
    week_seconds: float | None
    """GPS seconds of the week's start when the file stores GPS week time; None for adjusted standard time."""
    time_gps: tuple[float, float]
    source_ids: tuple[int, ...]
    channels: tuple[int, ...]


def _open(path: Path):
    import laspy

    if not path.is_file():
        raise InputError("file not found", path=path)
    try:
        return laspy.open(path)
    except Exception as exc:  # noqa: BLE001 - laspy/lazrs raise many types for corrupt files
        raise InputError(f"cannot open as LAS/LAZ: {exc}", path=path, expected="a LAS or LAZ file") from exc


def _strip_epsg(path: Path, header) -> int:
    try:
        crs = header.parse_crs()
    except Exception as exc:  # noqa: BLE001 - a malformed WKT or GeoTIFF key set
        raise InputError(f"unreadable CRS: {exc}", path=path, field="CRS (WKT or GeoTIFF VLR)") from exc
    if crs is None:
        raise InputError("the strip states no CRS", path=path, field="CRS (WKT or GeoTIFF VLR)",
                         expected="the projected CRS the points are in", found="none")
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    if len(horizontal.axis_info) == 3:  # a projected CRS promoted to 3-D (ellipsoidal heights)
        horizontal = horizontal.to_2d()
    epsg = horizontal.to_epsg(min_confidence=70)
    if epsg is None or not horizontal.is_projected:
        raise InputError("the strip's CRS is not a projected CRS with an EPSG code", path=path,
                         field="CRS", expected="a projected CRS PROJ identifies (e.g. EPSG:25832)",
                         found=horizontal.name)
    return int(epsg)


def inspect_delivered_strip(path: str | Path, gps_week: int | None = None, chunk: int = 2_000_000) -> DeliveredStrip:
    """Validate one delivered strip and read its time span (one pass over ``gps_time``).

    Raises
    ------
    InputError
        The file does not open, states no CRS or one PROJ cannot identify, its point format has
        no GPS time, it stores GPS week time and ``gps_week`` is None, or it has no points.
    """
    from laspy.header import GpsTimeType

    path = Path(path)
    with _open(path) as reader:
        h = reader.header
        names = set(h.point_format.dimension_names)
        if "gps_time" not in names:
            raise InputError("the strip has no GPS time", path=path, field="point_format",
                             expected="a point format with gps_time (1, 3, 4, 5, 6-10)", found=str(h.point_format.id))
        epsg = _strip_epsg(path, h)
        week = None
        if h.global_encoding.gps_time_type != GpsTimeType.STANDARD:
            if gps_week is None:
                raise InputError("the strip stores GPS week time: the week is needed", path=path,
                                 field="global_encoding", expected="--gps-week", found="GPS week time (bit 0 clear)")
            week = gps_week * SECONDS_PER_WEEK
        n = int(h.point_count)
        if n == 0:
            raise InputError("strip has no points", path=path)
        t_min, t_max, ids, channels = np.inf, -np.inf, set(), set()
        for rec in reader.chunk_iterator(chunk):
            t = np.asarray(rec.gps_time, dtype=float)
            t_min, t_max = min(t_min, float(t.min())), max(t_max, float(t.max()))
            ids.update(np.unique(np.asarray(rec.point_source_id)).tolist())
            channels.update(np.unique(np.asarray(rec.scanner_channel)).tolist() if "scanner_channel" in names else [0])
    base = week if week is not None else GPS_TIME_OFFSET_S
    return DeliveredStrip(path, n, epsg, "scanner_channel" in names, week, (t_min + base, t_max + base),
                          tuple(sorted(int(i) for i in ids)), tuple(sorted(int(c) for c in channels)))


def _inverse_range(path: Path, start: int, stop: int, base_s: float, has_channel: bool, strip_id: int,
                   poses: PoseInterpolator, t0_gps: float, p_b_s: np.ndarray, R_b_s: np.ndarray,
                   frame: LocalFrame, crs: OutputCRS, layout: LasLayout) -> EncodedPoints:
    """Records ``start:stop`` of a delivered strip in the scanner frame, encoded for the output file."""
    with _open(path) as reader:
        reader.seek(start)
        rec = reader.read_points(stop - start)
    t_gps = np.asarray(rec.gps_time, dtype=np.float64) + base_s
    xyz = np.column_stack([np.asarray(rec.x), np.asarray(rec.y), np.asarray(rec.z)])
    x_w = crs.to_w(frame, xyz)
    p, R = poses(t_gps - t0_gps)
    x_b = np.einsum("nji,nj->ni", R, x_w - p) - p_b_s
    x_s = x_b @ R_b_s  # R_b_s^T x_b, row-wise
    n = t_gps.size
    cloud = PointCloud(
        time_gps=t_gps, xyz=x_s, intensity=np.asarray(rec.intensity),
        scanner_channel=np.asarray(rec.scanner_channel) if has_channel else np.zeros(n, np.uint8),
        point_source_id=np.full(n, strip_id, dtype=np.uint16), return_number=np.asarray(rec.return_number),
        number_of_returns=np.asarray(rec.number_of_returns),
    )
    return encode_points(cloud, layout)


@dataclass(frozen=True)
class ImportResult:
    """What :func:`import_strips` wrote."""

    project: Path
    strips: tuple[DeliveredStrip, ...]
    strip_ids: tuple[int, ...]
    epsg: int
    gps_week: int

    def summary(self) -> str:
        lines = [f"Project written to {self.project} (EPSG:{self.epsg}, GPS week {self.gps_week})"]
        for s, k in zip(self.strips, self.strip_ids):
            lines.append(f"  strip {k}: {s.path.name}, {s.point_count:,} points, GPS s {s.time_gps[0]:.1f}-{s.time_gps[1]:.1f}")
        lines.append(f"Adjust it with: georefine run {self.project} --out RUN")
        return "\n".join(lines)


def _channels(present: set[int]) -> list[ChannelConfig]:
    """The default views (nadir, forward, backward) when the ids are among 0-2; else ``channel N``, tilt 0."""
    if present <= {0, 1, 2}:
        return default_channels()
    return [ChannelConfig(id=c, name=f"channel {c}", tilt_deg=0.0) for c in sorted(present)]


def _strip_ids(strips: list[DeliveredStrip]) -> list[int]:
    """The files' own ``point_source_id`` when each file has one, non-zero and unique; else 1, 2, ..."""
    own = [s.source_ids[0] if len(s.source_ids) == 1 else 0 for s in strips]
    if all(own) and len(set(own)) == len(own):
        return own
    return list(range(1, len(strips) + 1))


def import_strips(
    strips: list[str | Path],
    sbet: str | Path,
    out: str | Path,
    *,
    lever_arm_m: tuple[float, float, float],
    boresight_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
    smrmsg: str | Path | None = None,
    gps_week: int | None = None,
    channels: list[ChannelConfig] | None = None,
    imu: str | Path | None = None,
    name: str | None = None,
    progress: Progress = no_progress,
    scheduler: str | TaskRunner = DEFAULT_SCHEDULER,
) -> ImportResult:
    """Write a Georefine project from delivered strips and their SBET (module docstring).

    ``gps_week``: the week of the SBET (and of strips in GPS week time); by default that of the
    first strip's first point (adjusted standard time). ``smrmsg``: by default the accuracy file
    beside the SBET named the POSPac way (``sbet_X.out`` -> ``smrmsg_X.out``), if there is one.
    ``channels``: the scanner views (default nadir/forward/backward for ids 0-2, ``channel N``
    otherwise). ``imu``: a YAML file holding the ``imu`` section of ``project.yaml`` for the raw
    IMU the SBET was computed from (its ``file`` relative to the YAML file; copied into
    ``imu/``): the project then observes the trajectory with the SBET's positions
    (``gnss.format: sbet``) and the raw IMU instead of adjusting the SBET itself
    (docs/ARCHITECTURE.md §4.9).

    Raises
    ------
    InputError
        A bad strip (:func:`inspect_delivered_strip`), strips in different CRSs, no week for the
        SBET, an SBET that does not cover a strip (which strip, both spans), a bad SBET or smrmsg.
    """
    paths = [Path(p) for p in strips]
    if not paths:
        raise InputError("no strips given", field="STRIPS")
    out = Path(out)
    infos = []
    for k, p in enumerate(paths):
        progress("inspect strips", k, len(paths))
        infos.append(inspect_delivered_strip(p, gps_week))
    progress("inspect strips", len(paths), len(paths))
    epsgs = sorted({s.epsg for s in infos})
    if len(epsgs) > 1:
        bad = next(s for s in infos if s.epsg != infos[0].epsg)
        raise InputError("strips in different CRSs", path=bad.path, field="CRS",
                         expected=f"EPSG:{infos[0].epsg} (as {infos[0].path.name})", found=f"EPSG:{bad.epsg}")
    epsg = epsgs[0]
    if gps_week is None:
        gps_week = int(infos[0].time_gps[0] // SECONDS_PER_WEEK)
    sbet_path = Path(sbet)
    nav = read_sbet(sbet_path, gps_week=gps_week)
    if np.any(nav.wander_rad != 0.0):
        raise InputError("wander angle is not 0: only north-aligned SBETs are read", path=sbet_path, field="wander")
    span = (float(nav.time_gps[0]), float(nav.time_gps[-1]))
    for s in infos:
        if s.time_gps[0] < span[0] or s.time_gps[1] > span[1]:
            raise InputError("the SBET does not cover the strip", path=s.path, field="gps_time",
                             expected=f"GPS s {span[0]:.3f} to {span[1]:.3f} (the SBET {sbet_path.name}, week {gps_week})",
                             found=f"{s.time_gps[0]:.3f} to {s.time_gps[1]:.3f}")
    if smrmsg is None and smrmsg_path(sbet_path).is_file():  # POSPac's naming: sbet_X.out, smrmsg_X.out
        smrmsg = smrmsg_path(sbet_path)
        log.info("%s: its accuracy file %s is used", sbet_path.name, Path(smrmsg).name)
    if smrmsg is not None:
        read_smrmsg(Path(smrmsg), gps_week=gps_week)  # refused now, not at the first run
    imu_cfg = None
    if imu is not None:
        imu_path = Path(imu)
        imu_cfg = validate_model(ImuFileConfig, read_yaml(imu_path), imu_path)
        source = imu_path.parent / imu_cfg.file
        if not source.is_file():
            raise InputError("IMU file not found", path=source, field="file", expected=f"a file named in {imu_path.name}")
    ids = _strip_ids(infos)
    if channels is None:
        channels = _channels({c for s in infos for c in s.channels})
    missing = sorted({c for s in infos for c in s.channels} - {c.id for c in channels})
    if missing:
        raise InputError("points of scanner channels not given", field="channels",
                         expected="ids " + ", ".join(str(c.id) for c in channels), found=f"channel {missing[0]}")

    frame = LocalFrame(float(nav.lat_rad[0]), float(nav.lon_rad[0]), float(nav.h_m[0]))
    t0 = float(np.floor(nav.time_gps[0]))
    traj = trajectory_from_sbet(nav, frame, t0)
    crs = OutputCRS(epsg)
    p_b_s = np.asarray(lever_arm_m, dtype=float)
    R_b_s = boresight_matrix(boresight_deg)
    make_output_folder(out)
    (out / "scans").mkdir(exist_ok=True)
    (out / "nav").mkdir(exist_ok=True)
    protect = tuple({p.parent for p in paths} | {sbet_path.parent})
    scan_files = []
    with runner_for(scheduler) as runner:
        poses = runner.share(PoseInterpolator(traj))
        for s, k in zip(infos, ids):
            dest = out / "scans" / f"{s.path.stem}.laz"
            base = s.week_seconds if s.week_seconds is not None else GPS_TIME_OFFSET_S
            with LasWriter(dest, scale=0.0001, offset=(0.0, 0.0, 0.0), protect=protect) as writer:
                layout = writer.layout_for()
                tasks = [(s.path, a, min(a + RANGE_POINTS, s.point_count), base, s.has_channel, k, poses, t0, p_b_s,
                          R_b_s, frame, crs, layout) for a in range(0, s.point_count, RANGE_POINTS)]
                for points in runner.map(_inverse_range, tasks, label=f"import {s.path.name}", progress=progress):
                    writer.write_encoded(points)
            scan_files.append(f"scans/{dest.name}")
    nav_name = f"nav/{sbet_path.name}"
    shutil.copyfile(sbet_path, out / nav_name)
    smrmsg_name = None
    if smrmsg is not None:
        smrmsg_name = f"nav/{Path(smrmsg).name}"
        shutil.copyfile(smrmsg, out / smrmsg_name)
    write_json(out / "import.json", {
        "strips": [{"source": str(s.path.resolve()), "file": f, "strip_id": k, "points": s.point_count,
                    "time_gps": list(s.time_gps)} for s, f, k in zip(infos, scan_files, ids)],
        "sbet": str(sbet_path.resolve()), "smrmsg": None if smrmsg is None else str(Path(smrmsg).resolve()),
        "epsg": epsg, "gps_week": gps_week, "lever_arm_m": list(map(float, lever_arm_m)),
        "boresight_deg": list(map(float, boresight_deg)), "imu": None if imu is None else str(Path(imu).resolve()),
    })
    navigation: dict = {}
    if imu_cfg is not None:  # the SBET's positions and the raw IMU (gnss.format: sbet)
        (out / "imu").mkdir(exist_ok=True)
        imu_name = f"imu/{Path(imu_cfg.file).name}"
        shutil.copyfile(Path(imu).parent / imu_cfg.file, out / imu_name)
        gnss = {"files": [nav_name], "format": "sbet", "gps_week": int(gps_week), "lever_arm_m": [0.0, 0.0, 0.0]}
        if smrmsg_name:
            gnss["smrmsg"] = smrmsg_name
        navigation = {"gnss": gnss, "imu": dict(imu_cfg.model_dump(mode="json"), file=imu_name)}
    else:
        trajectory = {"sbet": nav_name, "gps_week": int(gps_week)}
        if smrmsg_name:
            trajectory["smrmsg"] = smrmsg_name
        navigation = {"trajectory": trajectory}
    write_yaml(out / "project.yaml", {
        "name": name or out.name,
        "crs": {"output_epsg": epsg},
        **navigation,
        "scanner": {
            "files": scan_files, "lever_arm_m": list(map(float, lever_arm_m)),
            "boresight_deg": list(map(float, boresight_deg)),
            "channels": [c.model_dump() for c in channels],
        },
    })
    return ImportResult(out, tuple(infos), tuple(ids), epsg, int(gps_week))
