"""Agisoft Metashape reference files: camera EOPs and markers (GCPs, check points) as CSV.

Paper 004 carries photos, lidargrams, approximate EOPs and control points into Metashape for
the co-adjustment; these files are what its *Import Reference* reads (and *Export Reference*
writes) in the layout below, comma-separated, with ``#`` comment lines ahead of the data:

Cameras::

    # Cameras (n), <CRS>, rotation angles omega, phi, kappa (degrees)
    #Label,X/Easting,Y/Northing,Z/Altitude,Omega,Phi,Kappa,X_accuracy,Y_accuracy,Z_accuracy,Omega_accuracy,Phi_accuracy,Kappa_accuracy,Enabled
    IMG_01001.jpg,654321.1234,5123456.1234,1023.4567,0.01234567,-0.02345678,90.12345678,0.1000,...,1

Markers::

    # Markers (m), <CRS>
    #Label,X/Easting,Y/Northing,Z/Altitude,X_accuracy,Y_accuracy,Z_accuracy,Enabled
    GCP01,654300.0000,5123400.0000,601.2300,0.0100,0.0100,0.0200,1

``Enabled`` is Metashape's reference check box: control points are enabled (``1``), check points
disabled (``0``), which is how Metashape tells them apart. The accuracy columns are optional
when reading. In Metashape, choose the same CRS and the rotation angles omega, phi, kappa in
the *Reference Settings*; the angles are Georefine's photogrammetric omega-phi-kappa
(:mod:`georefine.geometry.camera`, the convention of ``eop.csv``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from georefine.errors import InputError
from georefine.io.files import PathLike, atomic_output, read_text_lines
from georefine.io.photos import ControlPoints, ExteriorOrientation

__all__ = ["CAMERA_COLUMNS", "MARKER_COLUMNS", "write_cameras", "write_markers", "read_cameras", "read_markers"]

CAMERA_COLUMNS = ("Label", "X/Easting", "Y/Northing", "Z/Altitude", "Omega", "Phi", "Kappa", "X_accuracy",
                  "Y_accuracy", "Z_accuracy", "Omega_accuracy", "Phi_accuracy", "Kappa_accuracy", "Enabled")
MARKER_COLUMNS = ("Label", "X/Easting", "Y/Northing", "Z/Altitude", "X_accuracy", "Y_accuracy", "Z_accuracy",
                  "Enabled")


def write_cameras(path: PathLike, eop: ExteriorOrientation, *, crs_name: str = "", protect=()) -> None:
    """Cameras' EOPs (output CRS, omega-phi-kappa in degrees) with their a-priori accuracy if known."""
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(f"# Cameras ({len(eop)}){', ' + crs_name if crs_name else ''}, "
                 "rotation angles omega, phi, kappa (degrees)\n")
        fh.write("#" + ",".join(CAMERA_COLUMNS) + "\n")
        for i, name in enumerate(eop.images):
            acc = ["", "", "", "", "", ""] if eop.sigma_xyz is None else \
                [*(f"{v:.4f}" for v in eop.sigma_xyz[i]), *(f"{v:.6f}" for v in eop.sigma_opk_deg[i])]
            fh.write(",".join([name, *(f"{v:.4f}" for v in eop.xyz[i]), *(f"{v:.8f}" for v in eop.opk_deg[i]),
                               *acc, "1"]) + "\n")


def write_markers(path: PathLike, gcps: ControlPoints, *, crs_name: str = "", protect=()) -> None:
    """Control points enabled, check points disabled (Metashape's check points)."""
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(f"# Markers ({len(gcps)}){', ' + crs_name if crs_name else ''}\n")
        fh.write("#" + ",".join(MARKER_COLUMNS) + "\n")
        for i, pid in enumerate(gcps.ids):
            fh.write(",".join([pid, *(f"{v:.4f}" for v in gcps.xyz[i]), *(f"{v:.4f}" for v in gcps.sigma[i]),
                               "1" if gcps.role[i] == "control" else "0"]) + "\n")


def _read(path: Path, columns: tuple[str, ...], required: int) -> tuple[list[str], np.ndarray, list[int], list[str]]:
    """Labels, numbers (NaN where empty), line numbers and Enabled flags of a reference file."""
    lines = read_text_lines(path)
    header, data = None, []
    for n, s in enumerate(lines, start=1):
        t = s.strip()
        if not t:
            continue
        if t.startswith("#"):
            fields = [f.strip() for f in t.lstrip("#").split(",")]
            if fields and fields[0] == "Label":
                header = (n, fields)
            continue
        data.append((n, [f.strip() for f in t.split(",")]))
    if header is None:
        raise InputError("no column line", path=path, expected="#" + ",".join(columns))
    n_head, fields = header
    if tuple(fields[:required]) != columns[:required] or any(f not in columns for f in fields):
        raise InputError("wrong columns", path=path, line=n_head, expected="#" + ",".join(columns),
                         found="#" + ",".join(fields))
    if not data:
        raise InputError("no data lines", path=path, expected="a line per camera or marker", found="none")
    labels, values, numbers, enabled = [], np.full((len(data), len(columns) - 2), np.nan), [], []
    where = {c: k for k, c in enumerate(fields)}
    for i, (n, row) in enumerate(data):
        if len(row) != len(fields):
            raise InputError("wrong number of fields", path=path, line=n, expected=f"{len(fields)} fields",
                             found=str(len(row)))
        labels.append(row[0])
        for j, c in enumerate(columns[1:-1]):
            if c not in where or row[where[c]] == "":
                if j < required - 1:
                    raise InputError("missing value", path=path, line=n, field=c, expected="a number")
                continue
            try:
                values[i, j] = float(row[where[c]])
            except ValueError:
                raise InputError("bad number", path=path, line=n, field=c, expected="a number",
                                 found=repr(row[where[c]])) from None
        flag = row[where["Enabled"]] if "Enabled" in where else "1"
        if flag not in ("0", "1"):
            raise InputError("bad flag", path=path, line=n, field="Enabled", expected="0 or 1", found=repr(flag))
        enabled.append(flag)
        numbers.append(n)
    return labels, values, numbers, enabled


def read_cameras(path: PathLike, camera: str = "camera") -> ExteriorOrientation:
    """Cameras' EOPs of a Metashape reference file (accuracies if all are given)."""
    path = Path(path)
    labels, v, _, _ = _read(path, CAMERA_COLUMNS, 7)
    acc = v[:, 6:12]
    has = bool(np.all(np.isfinite(acc)))
    return ExteriorOrientation(tuple(labels), v[:, :3], v[:, 3:6], (camera,) * len(labels),
                               acc[:, :3] if has else None, acc[:, 3:] if has else None)


def read_markers(path: PathLike, default_sigma_m: tuple[float, float, float] = (0.01, 0.01, 0.02)) -> ControlPoints:
    """Markers of a Metashape reference file: enabled ones are control points, disabled ones check points."""
    path = Path(path)
    labels, v, numbers, enabled = _read(path, MARKER_COLUMNS, 4)
    sigma = np.where(np.isfinite(v[:, 3:6]), v[:, 3:6], np.asarray(default_sigma_m, dtype=float))
    for s, n in zip(sigma, numbers):
        if np.any(s <= 0):
            raise InputError("accuracy must be positive", path=path, line=n, field="X_accuracy", found=str(s.tolist()))
    return ControlPoints(tuple(labels), v[:, :3], sigma, tuple("control" if e == "1" else "check" for e in enabled))
