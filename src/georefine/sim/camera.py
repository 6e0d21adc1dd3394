"""Simulated aerial photo block: frame camera, block layout, rendered photos, control points.

The ``block`` scenario (paper 004) flies a frame camera in parallel strips over the scene
(:class:`PhotoBlockConfig`): nadir photos with the image's long side across the track, the
forward overlap and side overlap given, and a ground sample distance that sets the flying
height (``H = f GSD``). The true exterior orientation has the small attitude and position
scatter of a real photo flight; the approximate one written to ``eop.csv`` adds GNSS/IMU-like
errors (the photos' direct georeferencing).

Photos are rendered by ray casting the scene (:meth:`Scene.intersect`, Embree) through every
pixel centre with the camera's distortion (:meth:`Camera.rays`), so the images carry the same
distortion the camera model undoes. The grey value is the scene's albedo -- the texture the
LiDAR intensity follows -- lit by a sun (Lambert, plus sky light), then blurred (optics,
Gaussian) and given sensor noise, and written as 8-bit greyscale JPEG (the paper converts its
photos to black and white). Shadows are not cast.

Control and check points are points on open ground (terrain or road, nothing above them)
inside the block, each visible (ray-cast, unoccluded) in at least two photos; their image
measurements are the true projections plus measurement noise, their coordinates the truth plus
survey noise. They are not painted into the scene (no targets): the measurements are the
operator's, simulated.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field

from georefine.config import StrictModel
from georefine.errors import InputError
from georefine.geometry.camera import FLIP, Camera, project_points
from georefine.geometry.rotation import exp_so3, rot_z
from georefine.io.files import atomic_output

__all__ = ["CameraConfig", "PhotoBlockConfig", "PhotoBlock", "plan_block", "pixel_rays", "render_photo", "control_points",
           "write_photo_block"]


class CameraConfig(StrictModel):
    """The simulated frame camera (pixels); distortion as OpenCV's model."""

    width_px: int = Field(3000, ge=64)
    height_px: int = Field(2000, ge=64)
    focal_px: float = Field(4000.0, gt=0)
    principal_offset_px: tuple[float, float] = Field((6.3, -4.1), description="principal point minus image centre")
    k1: float = -0.045
    k2: float = 0.012
    k3: float = 0.0
    p1: float = 1.5e-4
    p2: float = -8.0e-5

    def camera(self, name: str = "camera") -> Camera:
        return Camera(self.width_px, self.height_px, self.focal_px, self.focal_px,
                      self.width_px / 2 + self.principal_offset_px[0], self.height_px / 2 + self.principal_offset_px[1],
                      self.k1, self.k2, self.k3, self.p1, self.p2, name)


class PhotoBlockConfig(StrictModel):
    """Layout, rendering and control of the simulated photo block."""

    camera: CameraConfig = Field(default_factory=CameraConfig)
    gsd_m: float = Field(0.08, gt=0.01, le=0.5, description="ground sample distance at mean terrain height")
    strips: int = Field(2, ge=1, le=20)
    forward_overlap: float = Field(0.6, ge=0.2, lt=0.95)
    side_overlap: float = Field(0.4, ge=0.0, lt=0.9)
    start_y_m: float = Field(40.0, description="first photo centre along +y (scene coordinates)")
    end_y_m: float | None = Field(None, description="last photo centre at most here (default: scene length - 40 m)")
    attitude_scatter_deg: float = Field(0.8, ge=0, description="true roll/pitch/kappa scatter about the plan")
    position_scatter_m: float = Field(2.0, ge=0, description="true position scatter about the plan")
    approx_position_sigma_m: float = Field(0.10, ge=0, description="error of eop.csv positions (per axis)")
    approx_attitude_sigma_deg: float = Field(0.02, ge=0, description="error of eop.csv angles")
    sun_azimuth_deg: float = Field(150.0, description="from north, clockwise")
    sun_elevation_deg: float = Field(45.0, gt=0, le=90)
    sky_light: float = Field(0.35, ge=0, le=1, description="share of diffuse light")
    blur_sigma_px: float = Field(0.6, ge=0, description="optics (Gaussian)")
    noise_dn: float = Field(1.5, ge=0, description="sensor noise, 8-bit digital numbers")
    jpeg_quality: int = Field(95, ge=50, le=100)
    control_points: int = Field(6, ge=0)
    check_points: int = Field(12, ge=0)
    survey_sigma_m: tuple[float, float, float] = Field((0.01, 0.01, 0.02), description="GCP coordinate noise")
    measurement_sigma_px: float = Field(0.3, ge=0, description="image measurement noise of the points")


class PhotoBlock:
    """Planned photos: names, true poses ``(R_w_c, p_w_c)``, strip of each photo."""

    def __init__(self, names: list[str], R_w_c: np.ndarray, p_w_c: np.ndarray, strip: np.ndarray) -> None:
        self.names, self.R_w_c, self.p_w_c, self.strip = names, R_w_c, p_w_c, strip

    def __len__(self) -> int:
        return len(self.names)


def plan_block(cfg: PhotoBlockConfig, scene, rng: np.random.Generator) -> PhotoBlock:
    """True exterior orientation of the block over ``scene`` (strips along +y, alternating direction)."""
    cam = cfg.camera
    length = scene.config.length_m
    end_y = cfg.end_y_m if cfg.end_y_m is not None else length - 40.0
    ground = float(np.median(scene.terrain_height(np.zeros(50), np.linspace(0, length, 50))))
    height = cam.focal_px * cfg.gsd_m
    across, along = cam.width_px * cfg.gsd_m, cam.height_px * cfg.gsd_m  # footprint (m)
    base, spacing = (1 - cfg.forward_overlap) * along, (1 - cfg.side_overlap) * across
    ys = np.arange(cfg.start_y_m, end_y + 1e-9, base)
    names, Rs, ps, strips = [], [], [], []
    for s in range(cfg.strips):
        x = (s - (cfg.strips - 1) / 2) * spacing
        north = s % 2 == 0
        heading = rot_z(np.array(0.0 if north else np.pi))  # image top along the flight
        for k, y in enumerate(ys if north else ys[::-1]):
            scatter = exp_so3(np.radians(cfg.attitude_scatter_deg) * rng.standard_normal(3))
            Rs.append(heading @ FLIP @ scatter)
            ps.append(np.array([x, y, ground + height]) + cfg.position_scatter_m * rng.standard_normal(3))
            names.append(f"IMG_{s + 1:02d}{k + 1:03d}.jpg")
            strips.append(s + 1)
    return PhotoBlock(names, np.array(Rs), np.array(ps), np.array(strips))


def pixel_rays(camera: Camera) -> np.ndarray:
    """Unit rays ``(H * W, 3)`` in ``c`` through every pixel centre, row by row (one camera, all photos)."""
    uu, vv = np.meshgrid(np.arange(camera.width_px) + 0.5, np.arange(camera.height_px) + 0.5)
    return camera.rays(np.column_stack([uu.ravel(), vv.ravel()]))


def render_photo(scene, camera: Camera, R_w_c: np.ndarray, p_w_c: np.ndarray, cfg: PhotoBlockConfig,
                 rng: np.random.Generator, rays_c: np.ndarray | None = None, rows_per_chunk: int = 256) -> np.ndarray:
    """The 8-bit greyscale photo ``(H, W)`` of the scene from pose ``(R_w_c, p_w_c)``.

    ``rays_c``: :func:`pixel_rays` of the camera, computed once for a block.
    """
    import cv2

    H, W = camera.height_px, camera.width_px
    rays_c = pixel_rays(camera) if rays_c is None else rays_c
    az, el = np.radians(cfg.sun_azimuth_deg), np.radians(cfg.sun_elevation_deg)
    sun = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])  # towards the sun, ENU
    img = np.empty((H, W))
    for r0 in range(0, H, rows_per_chunk):
        r1 = min(H, r0 + rows_per_chunk)
        d_w = rays_c[r0 * W:r1 * W] @ R_w_c.T
        rng_m, face = scene.intersect(np.broadcast_to(p_w_c, d_w.shape), d_w)
        hit = face >= 0
        grey = np.full(len(face), 0.55)  # sky / beyond the scene
        if hit.any():
            pts = p_w_c + d_w[hit] * rng_m[hit, None]
            n = scene.surface_normal(face[hit])
            n = np.where((np.sum(n * d_w[hit], axis=1) > 0)[:, None], -n, n)  # towards the camera
            light = cfg.sky_light * (0.5 + 0.5 * n[:, 2]) + (1 - cfg.sky_light) * np.clip(n @ sun, 0.0, None)
            grey[hit] = scene.albedo(pts, face[hit]) * light
        img[r0:r1] = grey.reshape(r1 - r0, W)
    dn = img * (255.0 / 0.75)
    if cfg.blur_sigma_px > 0:
        dn = cv2.GaussianBlur(dn, (0, 0), cfg.blur_sigma_px)
    dn = dn + cfg.noise_dn * rng.standard_normal(dn.shape)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


def control_points(scene, camera: Camera, block: PhotoBlock, cfg: PhotoBlockConfig, rng: np.random.Generator,
                   margin_px: float = 30.0, max_tries: int = 5000):
    """True control/check points and their true image coordinates.

    Returns ``(xyz_w (n, 3), is_control (n,), measurements)`` with measurements a list of
    ``(point index, photo index, u, v)`` (true projections, no noise).
    """
    n_wanted = cfg.control_points + cfg.check_points
    lo = block.p_w_c[:, :2].min(axis=0)
    hi = block.p_w_c[:, :2].max(axis=0)
    xyz, meas = [], []
    tries = 0
    while len(xyz) < n_wanted and tries < max_tries:
        tries += 1
        x, y = rng.uniform(lo, hi)
        z = float(scene.terrain_height(np.array([x]), np.array([y]))[0])
        # Open ground: looking straight down, the first surface is the terrain (or road) there.
        r, f = scene.intersect(np.array([[x, y, z + 100.0]]), np.array([[0.0, 0.0, -1.0]]))
        if f[0] < 0 or abs(100.0 - r[0]) > 0.02 or scene.face_material[f[0]] > 1:
            continue
        X = np.array([x, y, z + 100.0 - r[0]])
        if any(np.hypot(*(X[:2] - q[:2])) < 30.0 for q in xyz):
            continue  # spread the points
        uv, front = project_points(camera, np.broadcast_to(X, (len(block), 3)), block.R_w_c, block.p_w_c)
        seen = []
        for i in np.flatnonzero(front & camera.inside(uv, margin_px)):
            d = X - block.p_w_c[i]
            dist = np.linalg.norm(d)
            r, f = scene.intersect(block.p_w_c[i][None], d[None])
            if abs(r[0] - dist) < 0.02:  # nothing in between
                seen.append((i, uv[i]))
        if len(seen) >= 2:
            k = len(xyz)
            xyz.append(X)
            meas.extend((k, i, float(p[0]), float(p[1])) for i, p in seen)
    if len(xyz) < n_wanted:  # a scene too small or too built-up for the points asked for
        raise InputError(
            "too few places for control and check points", field="photos.control_points",
            expected=f"{n_wanted} points (photos.control_points + photos.check_points) on open ground, 30 m apart "
            "and seen in two photos: ask for fewer, or a longer scene (scene.length_m)",
            found=f"{len(xyz)} after {tries} tries",
        )
    is_control = np.zeros(len(xyz), dtype=bool)
    is_control[rng.permutation(len(xyz))[: cfg.control_points]] = True
    return np.array(xyz), is_control, meas


def write_photo_block(root, scene, cfg: PhotoBlockConfig, frame, crs, rng: np.random.Generator,
                      progress=lambda *a: None) -> dict:
    """Plan, render and write the block into the project folder ``root``; the truth into ``root/truth``.

    Writes ``photos/IMG_SSNNN.jpg``, ``photos/cameras.yaml``, ``photos/eop.csv`` (approximate
    EOP with its a-priori sigma), ``photos/gcp.csv`` (survey noise), ``photos/image_points.csv``
    (measurement noise); ``truth/photos_eop.csv`` (true EOP), ``truth/gcp.csv`` (exact points).
    """
    import cv2

    from georefine.io import photos as pio

    root = Path(root)
    (root / "photos").mkdir(exist_ok=True)
    camera = cfg.camera.camera("camera")
    block = plan_block(cfg, scene, rng)
    rays = pixel_rays(camera)
    for i, name in enumerate(block.names):
        progress("photos", i, len(block))
        img = render_photo(scene, camera, block.R_w_c[i], block.p_w_c[i], cfg, rng, rays)
        with atomic_output(root / "photos" / name, "wb") as fh:
            fh.write(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])[1].tobytes())
    progress("photos", len(block), len(block))
    pio.write_cameras(root / "photos" / "cameras.yaml", {"camera": camera})
    truth = pio.eop_from_w(block.names, block.R_w_c, block.p_w_c, frame, crs, "camera")
    pio.write_eop(root / "truth" / "photos_eop.csv", truth)
    n = len(block)
    dR = exp_so3(np.radians(cfg.approx_attitude_sigma_deg) * rng.standard_normal((n, 3)))
    approx_p = block.p_w_c + cfg.approx_position_sigma_m * rng.standard_normal((n, 3))
    sig_p = np.full((n, 3), max(cfg.approx_position_sigma_m, 1e-3))
    sig_a = np.full((n, 3), max(cfg.approx_attitude_sigma_deg, 1e-4))
    pio.write_eop(root / "photos" / "eop.csv",
                  pio.eop_from_w(block.names, block.R_w_c @ dR, approx_p, frame, crs, "camera", sig_p, sig_a))
    xyz_w, is_control, meas = control_points(scene, camera, block, cfg, rng)
    ids = tuple(f"{'GCP' if c else 'CHK'}{k + 1:02d}" for k, c in enumerate(is_control))
    roles = tuple("control" if c else "check" for c in is_control)
    xyz = crs.from_w(frame, xyz_w)
    sig = np.broadcast_to(np.asarray(cfg.survey_sigma_m), xyz.shape)
    pio.write_gcps(root / "truth" / "gcp.csv", pio.ControlPoints(ids, xyz, sig, roles))
    pio.write_gcps(root / "photos" / "gcp.csv", pio.ControlPoints(ids, xyz + sig * rng.standard_normal(xyz.shape),
                                                                  sig, roles))
    m = np.array([(u, v) for _, _, u, v in meas]) + cfg.measurement_sigma_px * rng.standard_normal((len(meas), 2))
    pio.write_image_points(root / "photos" / "image_points.csv", pio.ImagePoints(
        tuple(block.names[i] for _, i, _, _ in meas), tuple(ids[k] for k, _, _, _ in meas), m,
        np.arange(len(meas))))
    return {"photos": n, "control_points": int(is_control.sum()), "check_points": int((~is_control).sum()),
            "image_measurements": len(meas), "flying_height_m": float(cfg.camera.focal_px * cfg.gsd_m)}
