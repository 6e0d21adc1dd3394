"""Frame camera: pinhole with Brown distortion, and photogrammetric omega-phi-kappa (docs/ARCHITECTURE.md §4.8).

**Camera frame** ``c`` (docs/ARCHITECTURE.md §2): x right, y down, z along the optical axis. A camera pose is
``(R_w_c, p_w_c)``: ``x_c = R_w_c^T (X_w - p_w_c)``; ``p_w_c`` is the projection centre.

**Pixel coordinates** ``(u, v)``: column to the right, row down, in pixels, with COLMAP's
origin: ``(0, 0)`` is the top-left *corner* of the image, so the centre of the top-left pixel is
``(0.5, 0.5)`` -- the convention of ``image_points.csv`` (docs/ARCHITECTURE.md §3) and of the principal point
in ``cameras.yaml``. OpenCV puts that pixel centre at ``(0, 0)``: :meth:`Camera.opencv` gives
the matrix and coefficients for cv2 with the half pixel taken off.

**Model** (OpenCV's ``k1 k2 p1 p2 k3``, COLMAP's ``OPENCV``/``FULL_OPENCV``): with
``x = X/Z, y = Y/Z``, ``r2 = x^2 + y^2`` and ``radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3``,

``x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)``, ``y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y``,
``u = fx x_d + cx``, ``v = fy y_d + cy``.

:meth:`Camera.undistort` inverts the distortion by Gauss-Newton on the 2x2 Jacobian.

**Omega-phi-kappa** (PATB, Metashape's and MicMac's ``OriExport`` "omega phi kappa"): the
photogrammetric camera frame has x right, y up (towards the top of the image) and z backwards,
away from the scene; ``M = Rx(omega) Ry(phi) Rz(kappa)`` maps it to the object frame (east,
north, up), with active rotations ``Rx(a) = [[1,0,0],[0,c,-s],[0,s,c]]`` etc. So

``R_w_c = Rx(omega) Ry(phi) Rz(kappa) diag(1, -1, -1)``

(a nadir photo with the image top to the north has omega = phi = kappa = 0). The object frame
here is a Cartesian east-north-up frame (``w``); for angles in a projected CRS see
:mod:`georefine.io.photos`, which accounts for the meridian convergence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from georefine.geometry.rotation import rot_x, rot_y, rot_z, skew

__all__ = ["Camera", "PoseJacobians", "project_points", "R_w_c_from_opk", "opk_from_R_w_c", "FLIP"]

FLIP = np.diag([1.0, -1.0, -1.0])
"""Photogrammetric camera axes (x right, y up, z back) <-> computer-vision axes (x right, y down, z forward)."""


@dataclass(frozen=True)
class Camera:
    """Interior orientation of a frame camera (pixels; distortion coefficients dimensionless).

    Raises
    ------
    ValueError
        A non-positive or non-finite size or focal length, or a non-finite coefficient
        (:mod:`georefine.io.photos` names the file and field).
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    name: str = "camera"

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and int(v) == v > 0):
                raise ValueError(f"{name} must be a positive whole number of pixels, got {v}")
        for name in ("fx_px", "fy_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive focal length in pixels, got {v}")
        for name in ("cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)}")

    # ------------------------------------------------------------------ distortion
    @property
    def coefficients(self) -> np.ndarray:
        """``[k1, k2, p1, p2, k3]`` (OpenCV's order)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.coefficients != 0.0))

    def distort(self, xn: np.ndarray, jacobian: bool = False):
        """Distorted normalised coordinates ``(N, 2)`` of ideal ones; optionally ``d x_d / d x_n`` ``(N, 2, 2)``."""
        xn = np.asarray(xn, dtype=float)
        x, y = xn[..., 0], xn[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xy = x * y
        xd = np.stack([x * radial + 2.0 * self.p1 * xy + self.p2 * (r2 + 2.0 * x * x),
                       y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * xy], axis=-1)
        if not jacobian:
            return xd
        dradial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2)  # d radial / d r2
        J = np.empty(xn.shape[:-1] + (2, 2))
        J[..., 0, 0] = radial + 2.0 * x * x * dradial + 2.0 * self.p1 * y + 6.0 * self.p2 * x
        J[..., 0, 1] = 2.0 * x * y * dradial + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        J[..., 1, 0] = 2.0 * x * y * dradial + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        J[..., 1, 1] = radial + 2.0 * y * y * dradial + 6.0 * self.p1 * y + 2.0 * self.p2 * x
        return xd, J

    def undistort(self, xd: np.ndarray, iterations: int = 20, tol: float = 1e-14, chunk: int = 16384) -> np.ndarray:
        """Ideal normalised coordinates of distorted ones (Gauss-Newton, start at ``xd``).

        Solved ``chunk`` points at a time: the iteration's temporaries then stay in the CPU cache
        (every pixel of a 6 Mpx camera: 1.4 s in chunks of 16,384, 7.4 s at once).
        """
        xd = np.asarray(xd, dtype=float)
        if not self.has_distortion:
            return xd.copy()
        flat = xd.reshape(-1, 2)
        if len(flat) > chunk:
            return np.concatenate([self._undistort(flat[i:i + chunk], iterations, tol)
                                   for i in range(0, len(flat), chunk)]).reshape(xd.shape)
        return self._undistort(xd, iterations, tol)

    def _undistort(self, xd: np.ndarray, iterations: int, tol: float) -> np.ndarray:
        xn = xd.copy()
        for _ in range(iterations):
            f, J = self.distort(xn, jacobian=True)
            r = f - xd
            det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
            step = np.stack([(J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1]) / det,
                             (J[..., 0, 0] * r[..., 1] - J[..., 1, 0] * r[..., 0]) / det], axis=-1)
            xn = xn - step
            if np.all(np.abs(step) < tol):
                break
        return xn

    # ------------------------------------------------------------------ projection
    def project(self, x_c: np.ndarray, jacobian: bool = False):
        """Pixel coordinates ``(N, 2)`` of camera-frame points ``(N, 3)`` (z > 0 is in front).

        With ``jacobian``: also ``d(u, v) / d x_c`` ``(N, 2, 3)``.
        """
        x_c = np.asarray(x_c, dtype=float)
        z = x_c[..., 2]
        inv_z = 1.0 / z
        xn = x_c[..., :2] * inv_z[..., None]
        f = np.array([self.fx_px, self.fy_px])
        c = np.array([self.cx_px, self.cy_px])
        if not jacobian:
            return self.distort(xn) * f + c
        xd, Jd = self.distort(xn, jacobian=True)
        uv = xd * f + c
        Jn = np.zeros(x_c.shape[:-1] + (2, 3))  # d xn / d x_c
        Jn[..., 0, 0] = inv_z
        Jn[..., 1, 1] = inv_z
        Jn[..., 0, 2] = -xn[..., 0] * inv_z
        Jn[..., 1, 2] = -xn[..., 1] * inv_z
        J = f[:, None] * (Jd @ Jn)
        return uv, J

    def normalised(self, uv: np.ndarray) -> np.ndarray:
        """Ideal normalised image coordinates ``(x, y)`` (``x_c / z``) of pixel coordinates."""
        uv = np.asarray(uv, dtype=float)
        xd = (uv - np.array([self.cx_px, self.cy_px])) / np.array([self.fx_px, self.fy_px])
        return self.undistort(xd)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit viewing directions ``(N, 3)`` in ``c`` of pixel coordinates."""
        xn = self.normalised(uv)
        d = np.concatenate([xn, np.ones(xn.shape[:-1] + (1,))], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def inside(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Whether pixel coordinates lie inside the image (by at least ``margin_px``)."""
        uv = np.asarray(uv, dtype=float)
        return ((uv[..., 0] >= margin_px) & (uv[..., 0] <= self.width_px - margin_px)
                & (uv[..., 1] >= margin_px) & (uv[..., 1] <= self.height_px - margin_px))

    # ------------------------------------------------------------------ interchange
    @property
    def K(self) -> np.ndarray:
        """Calibration matrix in this module's pixel convention (top-left pixel centre at 0.5)."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """``(K, dist)`` for cv2 (top-left pixel centre at 0, so ``c - 0.5``), dist ``[k1, k2, p1, p2, k3]``."""
        K = self.K.copy()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        return K, self.coefficients

    def scaled(self, factor: float, name: str | None = None) -> Camera:
        """The same optics imaged on a sensor ``factor`` times as many pixels wide (e.g. a coarser lidargram)."""
        w, h = int(round(self.width_px * factor)), int(round(self.height_px * factor))
        return Camera(w, h, self.fx_px * factor, self.fy_px * factor, self.cx_px * factor, self.cy_px * factor,
                      self.k1, self.k2, self.k3, self.p1, self.p2, name or self.name)


@dataclass(frozen=True)
class PoseJacobians:
    """Derivatives of pixel coordinates ``(N, 2, 3)`` of :func:`project_points`.

    ``rotation``: with respect to the right perturbation ``R_w_c <- R_w_c Exp(delta)``;
    ``position``: with respect to ``p_w_c``; ``point``: with respect to ``X_w``.
    """

    rotation: np.ndarray
    position: np.ndarray
    point: np.ndarray


def project_points(camera: Camera, X_w: np.ndarray, R_w_c: np.ndarray, p_w_c: np.ndarray, jacobians: bool = False):
    """Pixel coordinates of world points under camera poses, and which lie in front of the camera.

    Parameters
    ----------
    camera
    X_w : (N, 3)
    R_w_c : (3, 3) or (N, 3, 3)
        One pose for all points or one per point.
    p_w_c : (3,) or (N, 3)
    jacobians
        Also return :class:`PoseJacobians`.

    Returns
    -------
    uv : (N, 2)
    in_front : (N,) bool
        ``z_c > 0``.
    jac : PoseJacobians, only with ``jacobians``
    """
    X_w = np.asarray(X_w, dtype=float)
    R_w_c = np.asarray(R_w_c, dtype=float)
    d = X_w - np.asarray(p_w_c, dtype=float)
    x_c = np.einsum("...ji,...j->...i", R_w_c, d) if R_w_c.ndim == 3 else d @ R_w_c
    in_front = x_c[..., 2] > 0.0
    if not jacobians:
        return camera.project(x_c), in_front
    uv, J = camera.project(x_c, jacobian=True)
    R_c_w = np.swapaxes(R_w_c, -1, -2)
    J_point = J @ R_c_w
    return uv, in_front, PoseJacobians(rotation=J @ skew(x_c), position=-J_point, point=J_point)


# ---------------------------------------------------------------------------- omega-phi-kappa
def R_w_c_from_opk(omega: np.ndarray, phi: np.ndarray, kappa: np.ndarray) -> np.ndarray:
    """``R_w_c = Rx(omega) Ry(phi) Rz(kappa) diag(1, -1, -1)`` (rad; see the module docstring)."""
    return rot_x(np.asarray(omega, float)) @ rot_y(np.asarray(phi, float)) @ rot_z(np.asarray(kappa, float)) @ FLIP


def opk_from_R_w_c(R_w_c: np.ndarray) -> np.ndarray:
    """``(omega, phi, kappa)`` (rad, ``(..., 3)``) of camera rotations; phi in [-pi/2, pi/2].

    From ``M = R_w_c diag(1, -1, -1)``: ``phi = asin(M13)``, ``omega = atan2(-M23, M33)``,
    ``kappa = atan2(-M12, M11)``.
    """
    M = np.asarray(R_w_c, dtype=float) @ FLIP
    phi = np.arcsin(np.clip(M[..., 0, 2], -1.0, 1.0))
    omega = np.arctan2(-M[..., 1, 2], M[..., 2, 2])
    kappa = np.arctan2(-M[..., 0, 1], M[..., 0, 0])
    return np.stack([omega, phi, kappa], axis=-1)
