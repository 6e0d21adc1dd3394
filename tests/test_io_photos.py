"""Photo inputs: cameras.yaml, eop.csv, gcp.csv, image_points.csv; checks and frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.geometry.camera import Camera, R_w_c_from_opk
from georefine.geometry.frames import LocalFrame, OutputCRS
from georefine.io import photos

CAMERAS = """cameras:
  rgb:
    width_px: 6000
    height_px: 4000
    fx_px: 7000.0
    cx_px: 3000.5
    cy_px: 2000.5
    k1: -0.05
"""
EOP = """image,x,y,z,omega_deg,phi_deg,kappa_deg
a.jpg,500100.0,5300000.0,900.0,0.5,-0.3,1.0
b.jpg,500400.0,5300000.0,901.0,-0.2,0.1,0.5
"""
GCP = """id,x,y,z,sx,sy,sz,role
g1,500200.0,5299950.0,300.0,0.01,0.01,0.02,control
c1,500300.0,5300050.0,305.0,0.01,0.01,0.02,check
"""
POINTS = """image,id,col,row
a.jpg,g1,3100.2,2500.7
b.jpg,g1,900.4,2510.1
b.jpg,c1,2000.0,1000.0
a.jpg,c1,3900.0,1100.0
"""


def _block(tmp_path: Path, cameras=CAMERAS, eop=EOP, gcp=GCP, points=POINTS, images=("a.jpg", "b.jpg")):
    for name, text in (("cameras.yaml", cameras), ("eop.csv", eop), ("gcp.csv", gcp), ("image_points.csv", points)):
        (tmp_path / name).write_text(text)
    (tmp_path / "img").mkdir(exist_ok=True)
    for name in images:
        (tmp_path / "img" / name).write_bytes(b"")
    cams = photos.read_cameras(tmp_path / "cameras.yaml")
    block = photos.PhotoBlock(cams, photos.read_eop(tmp_path / "eop.csv", cams), photos.read_gcps(tmp_path / "gcp.csv"),
                              photos.read_image_points(tmp_path / "image_points.csv"), tmp_path / "img")
    photos.check_photo_block(block, eop_path=tmp_path / "eop.csv", gcp_path=tmp_path / "gcp.csv",
                             image_points_path=tmp_path / "image_points.csv")
    return block


def test_reading_and_writing_round_trip(tmp_path):
    block = _block(tmp_path)
    cam = block.cameras["rgb"]
    assert (cam.fy_px, cam.k1, cam.k2) == (7000.0, -0.05, 0.0)
    assert block.eop.cameras == ("rgb", "rgb") and block.eop.sigma_xyz is None
    assert block.gcps.is_control.tolist() == [True, False]
    out = tmp_path / "out"
    out.mkdir()
    photos.write_cameras(out / "cameras.yaml", block.cameras)
    photos.write_eop(out / "eop.csv", block.eop)
    photos.write_gcps(out / "gcp.csv", block.gcps)
    photos.write_image_points(out / "image_points.csv", block.image_points)
    assert photos.read_cameras(out / "cameras.yaml") == block.cameras
    eop = photos.read_eop(out / "eop.csv", block.cameras)
    np.testing.assert_allclose(eop.xyz, block.eop.xyz)
    np.testing.assert_allclose(eop.opk_deg, block.eop.opk_deg)
    np.testing.assert_allclose(photos.read_image_points(out / "image_points.csv").uv, block.image_points.uv)
    assert photos.read_gcps(out / "gcp.csv").ids == block.gcps.ids


def test_eop_naming_a_missing_image(tmp_path):
    with pytest.raises(InputError, match=r"eop.csv, line 3, field 'image': image file not found.*'b.jpg'"):
        _block(tmp_path, images=("a.jpg",))


def test_camera_with_zero_focal_length(tmp_path):
    with pytest.raises(InputError, match=r"cameras.yaml, field 'cameras.rgb.fx_px'.*positive focal length"):
        _block(tmp_path, cameras=CAMERAS.replace("fx_px: 7000.0", "fx_px: 0"))


def test_image_point_outside_the_image(tmp_path):
    with pytest.raises(InputError, match=r"image_points.csv, line 4, field 'col': measurement outside the image"):
        _block(tmp_path, points=POINTS.replace("2000.0,1000.0", "6000.5,1000.0"))


def test_control_point_measured_in_no_image(tmp_path):
    gcp = GCP + "g9,500250.0,5300000.0,301.0,0.01,0.01,0.02,control\n"
    with pytest.raises(InputError, match=r"gcp.csv, line 4, field 'id': control point measured in no image.*'g9'"):
        _block(tmp_path, gcp=gcp)


def test_a_check_point_needs_two_images_and_a_control_point_seen_once_is_a_warning(tmp_path):
    once = POINTS.replace("a.jpg,c1,3900.0,1100.0\n", "")
    with pytest.raises(InputError, match=r"gcp.csv, line 3, field 'id': check point measured in one image only "
                                         r"\(expected measurements in two images or more.*'c1'"):
        _block(tmp_path, points=once)
    (tmp_path / "b").mkdir()
    _block(tmp_path / "b", points=POINTS.replace("b.jpg,g1,900.4,2510.1\n", ""))
    cams = photos.read_cameras(tmp_path / "b" / "cameras.yaml")
    block = photos.PhotoBlock(cams, photos.read_eop(tmp_path / "b" / "eop.csv", cams),
                              photos.read_gcps(tmp_path / "b" / "gcp.csv"),
                              photos.read_image_points(tmp_path / "b" / "image_points.csv"), tmp_path / "b" / "img")
    warnings = photos.check_photo_block(block, gcp_path=tmp_path / "b" / "gcp.csv")
    assert warnings == ["gcp.csv: control point 'g1' is measured in one image only (a.jpg): no second ray checks it"]


def test_a_photo_cut_short_or_of_another_size_is_refused(tmp_path):
    import cv2

    image = (np.arange(120 * 80) % 251).astype(np.uint8).reshape(80, 120)
    cv2.imwrite(str(tmp_path / "ok.jpg"), image)
    cv2.imwrite(str(tmp_path / "ok.png"), image)
    assert photos.read_photo(tmp_path / "ok.jpg").shape == (80, 120)
    assert photos.read_photo(tmp_path / "ok.png").shape == (80, 120)
    for name in ("ok.jpg", "ok.png"):
        data = (tmp_path / name).read_bytes()
        (tmp_path / f"cut-{name}").write_bytes(data[: len(data) * 2 // 3])
        with pytest.raises(InputError, match=rf"cut-{name}: image file is incomplete"):
            photos.read_photo(tmp_path / f"cut-{name}")
    (tmp_path / "text.jpg").write_text("no picture")
    with pytest.raises(InputError, match="text.jpg: image does not decode"):
        photos.read_photo(tmp_path / "text.jpg")
    with pytest.raises(InputError, match="image does not open"):
        photos.read_photo(tmp_path / "none.jpg")
    fits = Camera(name="c", width_px=120, height_px=80, fx_px=100.0, fy_px=100.0, cx_px=60.0, cy_px=40.0)
    assert photos.read_photo(tmp_path / "ok.jpg", fits).shape == (80, 120)
    other = Camera(name="c", width_px=80, height_px=120, fx_px=100.0, fy_px=100.0, cx_px=40.0, cy_px=60.0)
    with pytest.raises(InputError, match=r"ok.jpg: image size is not its camera's \(expected 80 x 120 px \(camera 'c'\), "
                                         r"found 120 x 80 px\)"):
        photos.read_photo(tmp_path / "ok.jpg", other)


@pytest.mark.parametrize("points, message", [
    (POINTS + "x.jpg,g1,10,10\n", r"line 6, field 'image': image not in the exterior orientation"),
    (POINTS + "a.jpg,zz,10,10\n", r"line 6, field 'id': point not in the control points"),
    (POINTS + "a.jpg,g1,10,10\n", r"line 6, field 'id': point 'g1' measured twice in image 'a.jpg' \(first on line 2\)"),
])
def test_inconsistent_measurements(tmp_path, points, message):
    with pytest.raises(InputError, match=message):
        _block(tmp_path, points=points)


@pytest.mark.parametrize("eop, message", [
    (EOP.replace("0.5,-0.3", "abc,-0.3"), r"line 2, field 'omega_deg': bad number"),
    (EOP + "a.jpg,1,2,3,0,0,0\n", r"line 4, field 'image': 'a.jpg' appears twice"),
    (EOP.replace("image,x", "img,x"), r"line 1: wrong header"),
    (EOP.replace("kappa_deg", "kappa_deg,sx"), r"line 1: incomplete group of columns.*all of sx,sy,sz"),
])
def test_bad_eop_files(tmp_path, eop, message):
    (tmp_path / "eop.csv").write_text(eop)
    with pytest.raises(InputError, match=message):
        photos.read_eop(tmp_path / "eop.csv")


def test_poses_in_w_round_trip_and_meridian_convergence():
    frame = LocalFrame.from_degrees(47.07, 15.44, 400.0)  # Graz, UTM 33N (central meridian 15 deg)
    crs = OutputCRS(32633)
    rng = np.random.default_rng(21)
    n = 20
    p_w = np.column_stack([rng.uniform(-3000, 3000, n), rng.uniform(-3000, 3000, n), rng.uniform(700, 1200, n)])
    R_w = R_w_c_from_opk(*rng.uniform([-0.05, -0.05, -np.pi], [0.05, 0.05, np.pi], (n, 3)).T)
    eop = photos.eop_from_w([f"i{k}" for k in range(n)], R_w, p_w, frame, crs, "rgb")
    R_back, p_back = photos.poses_in_w(eop, frame, crs)
    np.testing.assert_allclose(p_back, p_w, atol=1e-6)
    np.testing.assert_allclose(R_back, R_w, atol=1e-12)
    # A camera at the origin of w looking straight down with its image top to true north: true north
    # lies west of grid north east of the central meridian, by the convergence (lon - lon0) sin(lat)
    # to first order (0.322 deg here, pyproj's meridian_convergence), and the image top's grid
    # azimuth is -kappa.
    eop0 = photos.eop_from_w(["o"], np.diag([1.0, -1.0, -1.0])[None], np.zeros((1, 3)), frame, crs, "rgb")
    expected = np.degrees(np.radians(15.44 - 15.0) * np.sin(np.radians(47.07)))
    assert eop0.opk_deg[0, 2] == pytest.approx(expected, abs=1e-4)
    assert abs(eop0.opk_deg[0, 0]) < 1e-9 and abs(eop0.opk_deg[0, 1]) < 1e-9


def test_camera_defaults_from_the_single_camera(tmp_path):
    cams = {"a": Camera(10, 10, 5.0, 5.0, 5.0, 5.0, name="a"), "b": Camera(10, 10, 5.0, 5.0, 5.0, 5.0, name="b")}
    (tmp_path / "eop.csv").write_text(EOP)
    with pytest.raises(InputError, match="field 'camera': no camera column"):
        photos.read_eop(tmp_path / "eop.csv", cams)
    assert photos.read_eop(tmp_path / "eop.csv", {"a": cams["a"]}).cameras == ("a", "a")
