"""Photo inputs (docs/ARCHITECTURE.md §3): cameras, exterior orientation, control points, image measurements.

Files (all optional parts of a project; names are configurable)
    ``cameras.yaml``::

        cameras:
          rgb:                       # camera name
            width_px: 6000
            height_px: 4000
            fx_px: 7000.0
            fy_px: 7000.0            # default fx_px
            cx_px: 3000.2            # principal point, top-left pixel centre at (0.5, 0.5)
            cy_px: 1999.6
            k1: 0.0                  # Brown distortion, OpenCV's model (all default 0)
            k2: 0.0
            k3: 0.0
            p1: 0.0
            p2: 0.0

    ``eop.csv``: ``image,x,y,z,omega_deg,phi_deg,kappa_deg`` and optionally the six a-priori
    standard deviations ``sx,sy,sz,s_omega_deg,s_phi_deg,s_kappa_deg`` (m, deg) and ``camera``
    (required when ``cameras.yaml`` has more than one camera). ``x,y,z``: projection centre in
    the output CRS (easting, northing, ellipsoidal height). The angles are the photogrammetric
    omega-phi-kappa of :mod:`georefine.geometry.camera` relative to the CRS's *grid* axes
    at the projection centre (grid east, grid north, up), as Metashape and PATB write them in a
    projected CRS: they differ from angles against true north by the meridian convergence,
    which :func:`poses_in_w` and :func:`eop_from_w` account for exactly.

    ``gcp.csv``: ``id,x,y,z,sx,sy,sz,role`` (output CRS, m; role ``control`` or ``check``).

    ``image_points.csv``: ``image,id,col,row`` (pixels, top-left pixel centre at (0.5, 0.5)).

Every reader names the file, line and field of what is wrong; :func:`check_photo_block` checks
the files against each other (a missing image file, a measurement outside its image, a check
point measured in fewer than two images, unknown names), and :func:`read_photo` each image
(it decodes, it is complete, its size is its camera's).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from georefine.errors import InputError
from georefine.geometry import earth
from georefine.geometry.camera import Camera, R_w_c_from_opk, opk_from_R_w_c
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io.files import PathLike, atomic_output, read_text_lines

_log = logging.getLogger(__name__)

__all__ = [
    "ExteriorOrientation", "ControlPoints", "ImagePoints", "PhotoBlock",
    "read_cameras", "write_cameras", "read_eop", "write_eop", "read_gcps", "write_gcps", "read_photo",
    "read_image_points", "write_image_points", "check_photo_block", "poses_in_w", "eop_from_w",
    "EOP_COLUMNS", "EOP_SIGMA_COLUMNS", "GCP_COLUMNS", "IMAGE_POINT_COLUMNS",
]

EOP_COLUMNS = ("image", "x", "y", "z", "omega_deg", "phi_deg", "kappa_deg")
EOP_SIGMA_COLUMNS = ("sx", "sy", "sz", "s_omega_deg", "s_phi_deg", "s_kappa_deg")
GCP_COLUMNS = ("id", "x", "y", "z", "sx", "sy", "sz", "role")
IMAGE_POINT_COLUMNS = ("image", "id", "col", "row")
_CAMERA_KEYS = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2")
ROLES = ("control", "check")


# ---------------------------------------------------------------------------- data
@dataclass(frozen=True)
class ExteriorOrientation:
    """Approximate or adjusted exterior orientation of images, as in ``eop.csv`` (output CRS)."""

    images: tuple[str, ...]
    xyz: np.ndarray  # (n, 3) m
    opk_deg: np.ndarray  # (n, 3)
    cameras: tuple[str, ...]  # camera name per image
    sigma_xyz: np.ndarray | None = None  # (n, 3) m
    sigma_opk_deg: np.ndarray | None = None  # (n, 3)

    def __len__(self) -> int:
        return len(self.images)

    def index(self) -> dict[str, int]:
        return {name: i for i, name in enumerate(self.images)}


@dataclass(frozen=True)
class ControlPoints:
    """Ground control and check points (output CRS)."""

    ids: tuple[str, ...]
    xyz: np.ndarray  # (n, 3) m
    sigma: np.ndarray  # (n, 3) m
    role: tuple[str, ...]  # "control" or "check"

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def is_control(self) -> np.ndarray:
        return np.array([r == "control" for r in self.role], dtype=bool)


@dataclass(frozen=True)
class ImagePoints:
    """Image measurements of control/check points."""

    images: tuple[str, ...]
    ids: tuple[str, ...]
    uv: np.ndarray  # (m, 2) px
    lines: np.ndarray  # (m,) line numbers in the file (for messages)

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class PhotoBlock:
    """Everything of a photo block that the files say (see :func:`check_photo_block`)."""

    cameras: dict[str, Camera]
    eop: ExteriorOrientation
    gcps: ControlPoints | None = None
    image_points: ImagePoints | None = None
    image_folder: Path | None = None


# ---------------------------------------------------------------------------- tables
def _read_table(path: Path, required: tuple[str, ...], optional: tuple[str, ...] = (),
                together: tuple[str, ...] = ()) -> tuple[dict, np.ndarray]:
    """Columns (lists of stripped strings) of a comma-separated table with a header; line numbers.

    ``together``: optional columns that come all or none.
    """
    lines = read_text_lines(path)
    numbered = [(i + 1, s) for i, s in enumerate(lines) if s.strip() and not s.lstrip().startswith("#")]
    if not numbered:
        raise InputError("empty file", path=path, expected="a header line: " + ",".join(required))
    head_line, head = numbered[0]
    header = [h.strip().lower() for h in head.split(",")]
    missing = [c for c in required if c not in header]
    unknown = [c for c in header if c not in required + optional]
    if missing or unknown or len(set(header)) != len(header):
        raise InputError("wrong header", path=path, line=head_line,
                         expected=",".join(required) + (f" [+ {','.join(optional)}]" if optional else ""),
                         found=head.strip())
    present = [c for c in together if c in header]
    if present and len(present) != len(together):
        raise InputError("incomplete group of columns", path=path, line=head_line,
                         expected="all of " + ",".join(together) + " or none", found=",".join(present))
    cols: dict[str, list[str]] = {c: [] for c in header}
    numbers = []
    for n, s in numbered[1:]:
        fields = [f.strip() for f in s.split(",")]
        if len(fields) != len(header):
            raise InputError("wrong number of fields", path=path, line=n, expected=f"{len(header)} fields",
                             found=f"{len(fields)}")
        for c, f in zip(header, fields):
            cols[c].append(f)
        numbers.append(n)
    if not numbers:
        raise InputError("no data lines", path=path, expected="at least one line after the header", found="none")
    return cols, np.asarray(numbers)


def _floats(path: Path, cols: dict, names: tuple[str, ...], numbers: np.ndarray, *, positive: bool = False) -> np.ndarray:
    out = np.empty((len(numbers), len(names)))
    for j, name in enumerate(names):
        for i, text in enumerate(cols[name]):
            try:
                v = float(text)
            except ValueError:
                v = np.nan
            if not np.isfinite(v) or (positive and v <= 0):
                raise InputError("bad number", path=path, line=int(numbers[i]), field=name,
                                 expected="a positive number" if positive else "a finite number", found=repr(text))
            out[i, j] = v
    return out


def _names(path: Path, cols: dict, name: str, numbers: np.ndarray, *, unique: bool) -> tuple[str, ...]:
    seen: dict[str, int] = {}
    for text, n in zip(cols[name], numbers.tolist()):
        if not text:
            raise InputError("empty name", path=path, line=n, field=name, expected="a non-empty text", found="''")
        if unique and text in seen:
            raise InputError(f"{text!r} appears twice (first on line {seen[text]})", path=path, line=n, field=name)
        seen.setdefault(text, n)
    return tuple(cols[name])


# ---------------------------------------------------------------------------- cameras
def read_cameras(path: PathLike) -> dict[str, Camera]:
    """Cameras of a ``cameras.yaml`` (format in the module docstring)."""
    path = Path(path)
    try:
        doc = yaml.safe_load("\n".join(read_text_lines(path)))
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML: {exc}", path=path) from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), dict) or not doc["cameras"]:
        raise InputError("no cameras", path=path, field="cameras", expected="a mapping of camera names to parameters")
    cameras = {}
    for name, p in doc["cameras"].items():
        where = f"cameras.{name}"
        if not isinstance(p, dict):
            raise InputError("not a mapping", path=path, field=where, expected="width_px, height_px, fx_px, ...")
        unknown = sorted(set(p) - set(_CAMERA_KEYS))
        if unknown:
            raise InputError("unknown keys", path=path, field=where, expected=", ".join(_CAMERA_KEYS), found=str(unknown))
        for key in ("width_px", "height_px", "fx_px", "cx_px", "cy_px"):
            if key not in p:
                raise InputError("missing key", path=path, field=f"{where}.{key}", expected="a number")
        values = {k: p[k] for k in _CAMERA_KEYS if k in p}
        values.setdefault("fy_px", values["fx_px"])
        for k, v in values.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise InputError("not a number", path=path, field=f"{where}.{k}", expected="a number", found=repr(v))
        try:
            cameras[str(name)] = Camera(name=str(name), **values)
        except ValueError as exc:  # the camera names the bad parameter first
            key = str(exc).split()[0]
            raise InputError(str(exc), path=path, field=f"{where}.{key}") from None
    return cameras


def write_cameras(path: PathLike, cameras: dict[str, Camera], protect=()) -> None:
    doc = {"cameras": {name: {k: (int(getattr(c, k)) if k.endswith(("width_px", "height_px")) else float(getattr(c, k)))
                              for k in _CAMERA_KEYS} for name, c in cameras.items()}}
    with atomic_output(path, "w", protect=protect) as fh:
        yaml.safe_dump(doc, fh, sort_keys=False)


# ---------------------------------------------------------------------------- EOP
def read_eop(path: PathLike, cameras: dict[str, Camera] | None = None) -> ExteriorOrientation:
    """Exterior orientation of ``eop.csv``; ``cameras`` checks (and defaults) the camera column."""
    path = Path(path)
    cols, numbers = _read_table(path, EOP_COLUMNS, EOP_SIGMA_COLUMNS + ("camera",), together=EOP_SIGMA_COLUMNS)
    images = _names(path, cols, "image", numbers, unique=True)
    values = _floats(path, cols, EOP_COLUMNS[1:], numbers)
    sigma = _floats(path, cols, EOP_SIGMA_COLUMNS, numbers, positive=True) if "sx" in cols else None
    if "camera" in cols:
        cams = _names(path, cols, "camera", numbers, unique=False)
    elif cameras is not None and len(cameras) > 1:
        raise InputError("no camera column", path=path, field="camera",
                         expected=f"a camera per image: there are {len(cameras)} cameras")
    else:
        cams = (next(iter(cameras)) if cameras else "camera",) * len(images)
    if cameras is not None:
        for name, n in zip(cams, numbers.tolist()):
            if name not in cameras:
                raise InputError("unknown camera", path=path, line=n, field="camera",
                                 expected="one of " + ", ".join(cameras), found=repr(name))
    return ExteriorOrientation(images, values[:, :3], values[:, 3:], cams,
                               None if sigma is None else sigma[:, :3], None if sigma is None else sigma[:, 3:])


def write_eop(path: PathLike, eop: ExteriorOrientation, protect=()) -> None:
    header = list(EOP_COLUMNS)
    if eop.sigma_xyz is not None:
        header += EOP_SIGMA_COLUMNS
    header.append("camera")
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(",".join(header) + "\n")
        for i, name in enumerate(eop.images):
            row = [name, *(f"{v:.4f}" for v in eop.xyz[i]), *(f"{v:.8f}" for v in eop.opk_deg[i])]
            if eop.sigma_xyz is not None:
                row += [*(f"{v:.4f}" for v in eop.sigma_xyz[i]), *(f"{v:.6f}" for v in eop.sigma_opk_deg[i])]
            fh.write(",".join([*row, eop.cameras[i]]) + "\n")


# ---------------------------------------------------------------------------- GCP and image points
def read_gcps(path: PathLike) -> ControlPoints:
    """Control and check points of ``gcp.csv``."""
    path = Path(path)
    cols, numbers = _read_table(path, GCP_COLUMNS)
    ids = _names(path, cols, "id", numbers, unique=True)
    xyz = _floats(path, cols, ("x", "y", "z"), numbers)
    sigma = _floats(path, cols, ("sx", "sy", "sz"), numbers, positive=True)
    roles = tuple(r.lower() for r in cols["role"])
    for r, n in zip(roles, numbers.tolist()):
        if r not in ROLES:
            raise InputError("unknown role", path=path, line=n, field="role", expected=" or ".join(ROLES), found=repr(r))
    return ControlPoints(ids, xyz, sigma, roles)


def write_gcps(path: PathLike, gcps: ControlPoints, protect=()) -> None:
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(",".join(GCP_COLUMNS) + "\n")
        for i, pid in enumerate(gcps.ids):
            fh.write(",".join([pid, *(f"{v:.4f}" for v in gcps.xyz[i]), *(f"{v:.4f}" for v in gcps.sigma[i]),
                               gcps.role[i]]) + "\n")


def read_image_points(path: PathLike) -> ImagePoints:
    """Measurements of ``image_points.csv`` (a point at most once per image)."""
    path = Path(path)
    cols, numbers = _read_table(path, IMAGE_POINT_COLUMNS)
    images = _names(path, cols, "image", numbers, unique=False)
    ids = _names(path, cols, "id", numbers, unique=False)
    uv = _floats(path, cols, ("col", "row"), numbers)
    seen: dict[tuple[str, str], int] = {}
    for key, n in zip(zip(images, ids), numbers.tolist()):
        if key in seen:
            raise InputError(f"point {key[1]!r} measured twice in image {key[0]!r} (first on line {seen[key]})",
                             path=path, line=n, field="id")
        seen[key] = n
    return ImagePoints(images, ids, uv, numbers)


def write_image_points(path: PathLike, points: ImagePoints, protect=()) -> None:
    with atomic_output(path, "w", protect=protect) as fh:
        fh.write(",".join(IMAGE_POINT_COLUMNS) + "\n")
        for img, pid, (u, v) in zip(points.images, points.ids, points.uv):
            fh.write(f"{img},{pid},{u:.3f},{v:.3f}\n")


# ---------------------------------------------------------------------------- consistency
_JPEG_SOI, _JPEG_EOI = b"\xff\xd8\xff", b"\xff\xd9"
_PNG_SIGNATURE, _PNG_IEND = b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"
_TAIL_BYTES = 4096  # a JPEG's end-of-image marker must lie this close to the end (padding, trailers)


def read_photo(path: PathLike, camera: Camera | None = None, *, grey: bool = True) -> np.ndarray:
    """An image file decoded (8-bit grey or as stored), refused if it is incomplete or not its camera's size.

    A JPEG cut short still decodes -- OpenCV fills the missing rows with grey and says so only on
    stderr -- so a JPEG must end with its end-of-image marker and a PNG with its ``IEND`` chunk;
    any other format must decode. ``camera``: the image must be ``width_px x height_px``.

    Raises
    ------
    InputError
        The file is missing, incomplete, does not decode, or has another size than its camera.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"image does not open: {exc.strerror or exc}", path=path) from None
    if data.startswith(_JPEG_SOI) and _JPEG_EOI not in data[-_TAIL_BYTES:]:
        raise InputError("image file is incomplete", path=path, expected="a JPEG that ends with its end-of-image "
                         "marker (FF D9)", found=f"{len(data):,} bytes without it: the file was cut short")
    if data.startswith(_PNG_SIGNATURE) and _PNG_IEND not in data[-16:]:
        raise InputError("image file is incomplete", path=path, expected="a PNG that ends with its IEND chunk",
                         found=f"{len(data):,} bytes without it: the file was cut short")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError("image does not decode", path=path, expected="an image file OpenCV reads (JPEG, PNG, TIFF)")
    if camera is not None and image.shape[:2] != (camera.height_px, camera.width_px):
        raise InputError("image size is not its camera's", path=path, expected=f"{camera.width_px} x "
                         f"{camera.height_px} px (camera {camera.name!r})", found=f"{image.shape[1]} x {image.shape[0]} px")
    return image


def check_photo_block(
    block: PhotoBlock,
    *,
    eop_path: PathLike = "eop.csv",
    gcp_path: PathLike = "gcp.csv",
    image_points_path: PathLike = "image_points.csv",
) -> list[str]:
    """Check the files of a block against each other; the warnings.

    A control point measured in a single image is a warning (it still ties that image to the
    ground, but no second ray checks the measurement).

    Raises
    ------
    InputError
        An image of ``eop.csv`` without its file in ``block.image_folder``; a measurement of an
        image or point that the other files do not have, or outside its image; a control
        point measured in no image; a check point measured in fewer than two (it cannot be
        intersected).
    """
    eop = block.eop
    if block.image_folder is not None:
        folder = Path(block.image_folder)
        for i, name in enumerate(eop.images):
            if not (folder / name).is_file():
                raise InputError("image file not found", path=eop_path, line=i + 2, field="image",
                                 expected=f"a file {name!r} in {folder}", found="no such file")
    if block.image_points is None:
        if block.gcps is not None and len(block.gcps):
            raise InputError("control points but no image measurements", path=gcp_path, field="id",
                             expected="image_points.csv with the points' image coordinates")
        return []
    ip = block.image_points
    index = eop.index()
    gcp_ids = set(block.gcps.ids) if block.gcps is not None else set()
    for img, pid, (u, v), n in zip(ip.images, ip.ids, ip.uv, ip.lines.tolist()):
        if img not in index:
            raise InputError("image not in the exterior orientation", path=image_points_path, line=n, field="image",
                             expected=f"an image of {Path(eop_path).name}", found=repr(img))
        if pid not in gcp_ids:
            raise InputError("point not in the control points", path=image_points_path, line=n, field="id",
                             expected=f"an id of {Path(gcp_path).name}", found=repr(pid))
        cam = block.cameras.get(eop.cameras[index[img]])
        if cam is not None:
            for name, value, size in (("col", u, cam.width_px), ("row", v, cam.height_px)):
                if not 0.0 <= value <= size:
                    raise InputError("measurement outside the image", path=image_points_path, line=n, field=name,
                                     expected=f"0 <= {name} <= {size} (image {img!r}, camera {cam.name!r})",
                                     found=f"{value:g}")
    rays: dict[str, set[str]] = {}
    for img, pid in zip(ip.images, ip.ids):
        rays.setdefault(pid, set()).add(img)
    warnings = []
    if block.gcps is not None:
        for i, (pid, role) in enumerate(zip(block.gcps.ids, block.gcps.role)):
            n = len(rays.get(pid, ()))
            if n == 0 or (role == "check" and n < 2):
                need = "one image or more" if role == "control" else "two images or more (a check point is intersected)"
                raise InputError(
                    f"{role} point measured in {'no image' if n == 0 else 'one image only'}", path=gcp_path,
                    line=i + 2, field="id", expected=f"measurements in {need} in {Path(image_points_path).name}",
                    found=repr(pid))
            if n == 1:
                warnings.append(f"{Path(gcp_path).name}: control point {pid!r} is measured in one image only "
                                f"({next(iter(rays[pid]))}): no second ray checks it")
    return warnings


# ---------------------------------------------------------------------------- frames
def _grid_from_enu(crs: OutputCRS, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Rotations ``(n, 3, 3)`` from local east-north-up to the CRS's grid east-north-up (meridian convergence)."""
    return crs.R_grid_enu(lat, lon, h)


def poses_in_w(eop: ExteriorOrientation, frame: LocalFrame, crs: OutputCRS) -> tuple[np.ndarray, np.ndarray]:
    """``(R_w_c (n,3,3), p_w_c (n,3))`` of an exterior orientation given in the output CRS."""
    lat, lon, h = crs.to_geodetic(eop.xyz)
    p_w_c = frame.from_geodetic(lat, lon, h)
    R_grid_c = R_w_c_from_opk(*np.radians(eop.opk_deg).T)
    R_e_enu = earth.R_e_enu(lat, lon)
    R_enu_w = np.swapaxes(R_e_enu, 1, 2) @ frame.R_e_w
    R_grid_enu = _grid_from_enu(crs, lat, lon, h)
    R_w_c = np.swapaxes(R_enu_w, 1, 2) @ np.swapaxes(R_grid_enu, 1, 2) @ R_grid_c
    return R_w_c, p_w_c


def eop_from_w(images, R_w_c: np.ndarray, p_w_c: np.ndarray, frame: LocalFrame, crs: OutputCRS, cameras,
               sigma_xyz: np.ndarray | None = None, sigma_opk_deg: np.ndarray | None = None) -> ExteriorOrientation:
    """The exterior orientation in the output CRS of poses in ``w`` (inverse of :func:`poses_in_w`)."""
    p_w_c = np.asarray(p_w_c, dtype=float).reshape(-1, 3)
    lat, lon, h = frame.to_geodetic(p_w_c)
    xyz = crs.from_geodetic(lat, lon, h)
    R_enu_w = np.swapaxes(earth.R_e_enu(lat, lon), 1, 2) @ frame.R_e_w
    R_grid_c = _grid_from_enu(crs, lat, lon, h) @ R_enu_w @ np.asarray(R_w_c, dtype=float).reshape(-1, 3, 3)
    opk = np.degrees(opk_from_R_w_c(R_grid_c))
    cams = tuple(cameras) if not isinstance(cameras, str) else (cameras,) * len(xyz)
    return ExteriorOrientation(tuple(images), xyz, opk, cams, sigma_xyz, sigma_opk_deg)
