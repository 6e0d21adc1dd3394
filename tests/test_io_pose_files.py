"""Tests of georefine.io.pose_files: TUM and trajectopy poses, and the frame of their quaternions."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.geometry import earth
from georefine.geometry.frames import OutputCRS
from georefine.geometry.rotation import matrix_from_quat, quat_from_matrix
from georefine.io.pose_files import (
    PoseTable,
    geodetic_from_poses,
    poses_from_geodetic,
    read_trajectopy,
    read_tum,
    write_trajectopy,
    write_tum,
)

T0 = 1_399_708_800.0  # GPS week 2314


def _poses(seed: int, n: int = 200, epsg: int | None = 25832) -> PoseTable:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    xyz = np.array([691_000.0, 5_334_000.0, 700.0]) + rng.uniform(-500, 500, (n, 3))
    return PoseTable(T0 + 3000.0 + np.cumsum(rng.uniform(0.004, 0.006, n)), xyz, q, epsg, f"run {seed}")


def _flight(seed: int, n: int = 50):
    """Geodetic positions near 47 N 11 E (2 deg east of UTM 32's central meridian) and NED angles."""
    rng = np.random.default_rng(seed)
    lat = np.radians(47.0 + rng.uniform(-0.05, 0.05, n))
    lon = np.radians(11.0 + rng.uniform(-0.05, 0.05, n))
    h = 700.0 + rng.uniform(-50, 50, n)
    rph = np.column_stack([rng.normal(scale=0.1, size=n), rng.normal(scale=0.1, size=n),
                           rng.uniform(0, 2 * np.pi, n)])
    return T0 + np.arange(n) * 0.005, lat, lon, h, rph


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("fmt", ["tum", "trajectopy"])
def test_round_trip(tmp_path, seed, fmt):
    poses = _poses(seed)
    write, read = (write_tum, read_tum) if fmt == "tum" else (write_trajectopy, read_trajectopy)
    back = read(write(tmp_path / f"p.{fmt}", poses))
    np.testing.assert_allclose(back.time_gps, poses.time_gps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.xyz, poses.xyz, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.quat_xyzw, poses.quat_xyzw, rtol=0, atol=1e-12)
    assert back.epsg == 25832
    if fmt == "trajectopy":
        assert back.name == poses.name


def test_file_layouts(tmp_path):
    poses = _poses(2, n=3)
    tum = write_tum(tmp_path / "p.tum", poses).read_text().splitlines()
    rows = [s for s in tum if not s.startswith("#")]
    assert [len(s.split(" ")) for s in rows] == [8, 8, 8] and "# crs: EPSG:25832" in tum
    assert float(rows[0].split(" ")[0]) == poses.time_gps[0]  # absolute GPS seconds
    traj = write_trajectopy(tmp_path / "p.traj", poses).read_text().splitlines()
    for line in ("#epsg 25832", "#nframe enu", "#time_format gps_sow", "#gps_week 2314",
                 "#fields t,px,py,pz,qx,qy,qz,qw"):
        assert line in traj
    rows = [s for s in traj if not s.startswith("#")]
    assert float(rows[0].split(",")[0]) == pytest.approx(poses.time_gps[0] - 2314 * 604800.0, abs=1e-9)


@pytest.mark.parametrize("epsg", [25832, 4978])
def test_geodetic_round_trip(epsg):
    t, lat, lon, h, rph = _flight(3)
    poses = poses_from_geodetic(t, lat, lon, h, rph, epsg)
    lat2, lon2, h2, rph2 = geodetic_from_poses(poses)
    np.testing.assert_allclose(lat2, lat, atol=1e-12)
    np.testing.assert_allclose(lon2, lon, atol=1e-12)
    np.testing.assert_allclose(h2, h, atol=1e-6)
    d = np.angle(np.exp(1j * (rph2 - rph)))
    assert np.abs(d).max() < 1e-9


def test_grid_attitude_follows_the_projected_axes():
    """The body's forward axis in grid coordinates points where a step along the true heading goes
    in the CRS: the meridian convergence (1.5 deg here) has its sign right, and up is up."""
    crs = OutputCRS(25832)
    t, lat, lon, h, rph = _flight(4)
    rph[:, :2] = 0.0  # level
    poses = poses_from_geodetic(t, lat, lon, h, rph, 25832)
    R = matrix_from_quat(poses.quat_xyzw)
    forward = R[:, :, 0]
    azimuth_body = np.arctan2(forward[:, 0], forward[:, 1])
    step_m = 0.5  # along the true heading, with WGS84's radii of curvature (meridian M, prime vertical N)
    a_m, e2 = 6378137.0, 6.69437999014e-3
    w = 1.0 - e2 * np.sin(lat) ** 2
    M, N = a_m * (1.0 - e2) / w**1.5 + h, a_m / np.sqrt(w) + h
    a = crs.from_geodetic(lat, lon, h)
    b = crs.from_geodetic(lat + step_m * np.cos(rph[:, 2]) / M, lon + step_m * np.sin(rph[:, 2]) / (N * np.cos(lat)), h)
    azimuth_grid = np.arctan2(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1])
    diff = np.angle(np.exp(1j * (azimuth_body - azimuth_grid)))
    assert np.abs(diff).max() < 1e-6
    convergence = np.angle(np.exp(1j * (azimuth_body - rph[:, 2])))
    assert np.all(np.abs(convergence) > np.radians(1.0))  # a frame without it would fail the first check
    np.testing.assert_allclose(R[:, :, 2], np.tile([0.0, 0.0, -1.0], (len(t), 1)), atol=1e-12)  # body down
    np.testing.assert_allclose(poses.xyz, a, atol=1e-9)


def test_geocentric_attitude():
    t, lat, lon, h, rph = _flight(5)
    poses = poses_from_geodetic(t, lat, lon, h, rph, 4978)
    np.testing.assert_allclose(poses.xyz, earth.geodetic_to_ecef(lat, lon, h), atol=1e-6)
    R = matrix_from_quat(poses.quat_xyzw)
    R_e_n = earth.R_e_n(lat, lon)
    # the body's z axis in ECEF with roll and pitch taken out is the local down
    from georefine.geometry.rotation import R_n_b_from_rph

    np.testing.assert_allclose(R @ np.swapaxes(R_n_b_from_rph(*rph.T), 1, 2), R_e_n, atol=1e-12)


def test_geographic_crs_is_refused():
    t, lat, lon, h, rph = _flight(6, n=2)
    with pytest.raises(InputError, match=r"projected or geocentric.*EPSG:4326"):
        poses_from_geodetic(t, lat, lon, h, rph, 4326)


def test_tum_bad_lines(tmp_path):
    path = write_tum(tmp_path / "b.tum", _poses(7, n=5))
    lines = path.read_text().splitlines()
    first = next(i for i, s in enumerate(lines) if not s.startswith("#"))
    bad = lines.copy()
    bad[first + 1] = " ".join(bad[first + 1].split(" ")[:7])
    path.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError, match=rf"b\.tum, line {first + 2}: wrong number of fields.*8 fields"):
        read_tum(path)
    bad = lines.copy()
    bad[first + 2] = bad[first + 1]
    path.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError, match=rf"line {first + 3}, field 'timestamp': time repeats"):
        read_tum(path)
    bad = lines.copy()
    v = bad[first + 3].split(" ")
    v[7] = repr(2.0 * float(v[7]) + 0.5)
    bad[first + 3] = " ".join(v)
    path.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError, match=rf"line {first + 4}.*not a unit quaternion"):
        read_tum(path)
    path.write_text("# nothing\n")
    with pytest.raises(InputError, match="no poses"):
        read_tum(path)


def test_trajectopy_bad_headers(tmp_path):
    path = write_trajectopy(tmp_path / "b.traj", _poses(8, n=4))
    text = path.read_text()
    path.write_text(text.replace("#fields t,px,py,pz,qx,qy,qz,qw", "#fields t,px,py,pz,ex,ey,ez"))
    with pytest.raises(InputError, match=r"missing trajectopy fields.*t,px,py,pz,ex,ey,ez"):
        read_trajectopy(path)
    path.write_text(text.replace("#gps_week 2314\n", ""))
    with pytest.raises(InputError, match=r"field '#gps_week': seconds of week without a GPS week"):
        read_trajectopy(path)
    path.write_text(text.replace("#nframe enu", "#nframe ned"))
    with pytest.raises(InputError, match=r"field '#nframe'.*expected enu, found ned"):
        read_trajectopy(path)


def test_pose_table_rejects_bad_quaternions():
    p = _poses(9, n=3)
    with pytest.raises(ValueError, match="unit quaternions"):
        PoseTable(p.time_gps, p.xyz, 2.0 * p.quat_xyzw, 25832)
    assert np.allclose(quat_from_matrix(matrix_from_quat(p.quat_xyzw)), p.quat_xyzw)
