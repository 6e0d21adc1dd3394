"""Gravity-related heights from a geoid grid (``crs.geoid_grid``, ``crs.vertical_epsg``).

The grids are written here, with undulations known exactly (constant, sloped, random at the
nodes), as NOAA GTX files (40-byte big-endian header, rows south to north) and, where GDAL's
``gdal_translate`` is installed, as GeoTIFF; PROJ's ``vgridshift`` reads both. Checked: the sign
(``H = h - N``), the interpolation and the grid's orientation, the compound CRS in the LAZ
header (read back by laspy/pyproj and accepted by the ``projinfo`` command), the configuration
errors, points outside the grid, and ``georefine georeference`` end to end with the evaluation
reading its clouds back to ellipsoidal heights.
"""

from __future__ import annotations

import math
import shutil
import struct
import subprocess
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml

from georefine.config import CrsConfig, validate_model
from georefine.errors import ConfigError, InputError
from georefine.geometry.frames import GeoidHeights, LocalFrame, OutputCRS
from georefine.io.las import PointCloud, time_index
from georefine.io.las_writer import LasWriter
from georefine.lidar.georeference import PoseInterpolator
from georefine.lidar.tiles import georeference_strip, plan_strip
from georefine.trajectory.sampled import Trajectory

T0 = 1.4e9


def write_gtx(path: Path, lat0: float, lon0: float, step: float, N: np.ndarray) -> Path:
    """A GTX grid: ``N[i, j]`` (m) at latitude ``lat0 + i step``, longitude ``lon0 + j step`` (deg)."""
    rows, cols = N.shape
    with open(path, "wb") as fh:
        fh.write(struct.pack(">4d2i", lat0, lon0, step, step, rows, cols))
        fh.write(np.asarray(N, dtype=">f4").tobytes())
    return path


def nodes(lat0: float, lon0: float, step: float, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    return lat0 + step * np.arange(shape[0]), lon0 + step * np.arange(shape[1])


def sloped(lat_deg, lon_deg):
    """A plane in latitude and longitude: bilinear interpolation reproduces it exactly."""
    return 47.0 + 0.8 * (np.asarray(lat_deg) - 48.0) - 0.5 * (np.asarray(lon_deg) - 11.0)


GRID = (47.5, 10.5, 0.05, (21, 21))  # lat0, lon0, step (deg), shape: 47.5..48.5 N, 10.5..11.5 E


@pytest.fixture
def sloped_gtx(tmp_path) -> Path:
    lat, lon = nodes(*GRID)
    return write_gtx(tmp_path / "sloped.gtx", GRID[0], GRID[1], GRID[2], sloped(lat[:, None], lon[None, :]))


def _grids(tmp_path: Path, N: np.ndarray) -> list[Path]:
    """The grid as GTX and, with gdal_translate, as GeoTIFF."""
    gtx = write_gtx(tmp_path / "n.gtx", GRID[0], GRID[1], GRID[2], N)
    out = [gtx]
    if shutil.which("gdal_translate"):
        tif = tmp_path / "n.tif"
        subprocess.run(["gdal_translate", "-q", "-of", "GTiff", str(gtx), str(tif)], check=True)
        out.append(tif)
    return out


def test_constant_undulation_is_subtracted(tmp_path):
    """PROJ's vgridshift with the multiplier -1: H = h - N (N = 47.3 m everywhere)."""
    rng = np.random.default_rng(1)
    for grid in _grids(tmp_path, np.full(GRID[3], 47.3)):
        g = GeoidHeights(str(grid), 7837)
        lat, lon = np.radians(rng.uniform(47.6, 48.4, 50)), np.radians(rng.uniform(10.6, 11.4, 50))
        h = rng.uniform(300.0, 900.0, 50)
        np.testing.assert_allclose(g.orthometric(lat, lon, h), h - 47.3, atol=1e-5)  # float32 grid values
        np.testing.assert_allclose(g.ellipsoidal(lat, lon, h - 47.3), h, atol=1e-5)


def test_sloped_and_random_undulations_interpolate_with_the_grid_north_up(tmp_path):
    """A plane in (lat, lon) comes out exact between the nodes; random values at the nodes come
    out at their nodes (rows south to north, columns west to east), so the grid is not flipped."""
    rng = np.random.default_rng(2)
    lat_n, lon_n = nodes(*GRID)
    lat, lon = rng.uniform(47.55, 48.45, 200), rng.uniform(10.55, 11.45, 200)
    h = rng.uniform(300.0, 900.0, 200)
    for grid in _grids(tmp_path, sloped(lat_n[:, None], lon_n[None, :])):
        H = GeoidHeights(str(grid), 7837).orthometric(np.radians(lat), np.radians(lon), h)
        np.testing.assert_allclose(H, h - sloped(lat, lon), atol=1e-4)
    N = rng.uniform(30.0, 60.0, GRID[3])
    for grid in _grids(tmp_path, N):
        i, j = rng.integers(1, GRID[3][0] - 1, 40), rng.integers(1, GRID[3][1] - 1, 40)
        H = GeoidHeights(str(grid), 7837).orthometric(np.radians(lat_n[i]), np.radians(lon_n[j]), np.full(40, 500.0))
        np.testing.assert_allclose(H, 500.0 - N[i, j], atol=1e-4)


def test_points_outside_the_grid_are_an_error_naming_the_grid(sloped_gtx):
    g = GeoidHeights(str(sloped_gtx), 7837)
    lat, lon = np.radians([48.0, 49.2, 48.1]), np.radians([11.0, 11.0, 11.0])
    with pytest.raises(InputError, match=r"sloped.gtx, field 'crs.geoid_grid': the geoid grid gives no undulation "
                                         r"for 1 of 3 points of strip_9.laz.*latitude 49.200000 deg"):
        g.orthometric(lat, lon, np.full(3, 500.0), what="points of strip_9.laz")


def test_configuration_both_or_neither_vertical_crs_and_existing_grid(tmp_path, sloped_gtx):
    # Ellipsoidal is the default.
    assert CrsConfig().geoid(tmp_path) is None
    assert CrsConfig.model_fields["geoid_grid"].default is None
    assert "ellipsoidal unless" in CrsConfig.model_fields["output_epsg"].description
    ok = validate_model(CrsConfig, {"geoid_grid": "sloped.gtx", "vertical_epsg": 7837})
    g = ok.geoid(tmp_path)  # relative to the project folder, made absolute
    assert Path(g.grid) == sloped_gtx.absolute() and g.vertical_epsg == 7837
    with pytest.raises(ConfigError, match=r"field 'vertical_epsg'.*is a Projected CRS, not a vertical CRS"):
        validate_model(CrsConfig, {"geoid_grid": "sloped.gtx", "vertical_epsg": 25832})
    with pytest.raises(ConfigError, match=r"field 'vertical_epsg'.*is a Compound CRS, not a vertical CRS"):
        validate_model(CrsConfig, {"geoid_grid": "sloped.gtx", "vertical_epsg": 5555})
    with pytest.raises(ConfigError, match=r"geoid_grid is given without vertical_epsg"):
        validate_model(CrsConfig, {"geoid_grid": "sloped.gtx"})
    with pytest.raises(ConfigError, match=r"vertical_epsg is given without geoid_grid"):
        validate_model(CrsConfig, {"vertical_epsg": 7837})
    with pytest.raises(ConfigError, match=r"field 'geoid_grid'.*GeoTIFF or GTX"):
        validate_model(CrsConfig, {"geoid_grid": "geoid.csv", "vertical_epsg": 7837})
    missing = validate_model(CrsConfig, {"geoid_grid": "geoid/none.gtx", "vertical_epsg": 7837})
    with pytest.raises(ConfigError, match=r"none.gtx, field 'crs.geoid_grid': no such geoid grid file"):
        missing.geoid(tmp_path)
    (tmp_path / "bad.gtx").write_bytes(b"not a grid")
    bad = validate_model(CrsConfig, {"geoid_grid": "bad.gtx", "vertical_epsg": 7837})
    with pytest.raises(ConfigError, match=r"bad.gtx, field 'crs.geoid_grid': PROJ cannot use it as a vertical grid"):
        bad.geoid(tmp_path)


def _strip(path: Path, rng) -> Path:
    """A 12 s sweep of 24,000 scanner-frame points (the trajectory is the identity at ``w``'s origin)."""
    n = 24_000
    t = np.sort(rng.uniform(0.0, 12.0, n))
    xyz = np.column_stack([rng.uniform(-400, 400, n), rng.uniform(-400, 400, n), rng.uniform(-30, 30, n)])
    ones = np.ones(n, np.uint8)
    with LasWriter(path, scale=1e-4) as w:
        w.write(PointCloud(t + T0, xyz, np.full(n, 100), np.zeros(n, np.uint8), np.full(n, 3), ones, ones))
    return path


def _poses() -> PoseInterpolator:
    time = np.arange(-1.0, 13.0, 0.01)
    return PoseInterpolator(Trajectory(time, np.zeros((time.size, 3)), np.broadcast_to(np.eye(3), (time.size, 3, 3)).copy(), T0))


def test_final_laz_has_orthometric_heights_and_a_compound_crs(tmp_path, sloped_gtx):
    rng = np.random.default_rng(3)
    strip = _strip(tmp_path / "strip_3.laz", rng)
    frame, crs = LocalFrame(math.radians(48.0), math.radians(11.0), 500.0), OutputCRS(25832)
    plan = plan_strip(strip, 3, T0, 10_000, 0.0, index=time_index(strip))
    assert len(plan.tiles) >= 2  # converted per tile (and per sub-chunk within a tile)
    geoid = GeoidHeights(str(sloped_gtx), 7837)
    ell = georeference_strip(plan, tmp_path / "ell.laz", _poses(), T0, np.zeros(3), np.eye(3), frame, crs)
    ort = georeference_strip(plan, tmp_path / "ort.laz", _poses(), T0, np.zeros(3), np.eye(3), frame, crs,
                             heights=geoid)
    assert ell.points_written == ort.points_written == 24_000
    a, b = laspy.read(ell.output), laspy.read(ort.output)
    np.testing.assert_allclose(b.x, a.x, atol=1e-9)
    np.testing.assert_allclose(b.y, a.y, atol=1e-9)
    lat, lon, _ = crs.to_geodetic(np.column_stack([a.x, a.y, a.z]))
    N = sloped(np.degrees(lat), np.degrees(lon))
    assert 46.5 < N.min() < N.max() < 47.5
    np.testing.assert_allclose(b.z, a.z - N, atol=1.5e-3)  # 1 mm LAS steps, float32 grid
    # The header: a compound CRS, the projected CRS + DHHN2016 height, no ellipsoidal-height note.
    ch = b.header.parse_crs()
    assert ch.is_compound and [c.to_epsg() for c in ch.sub_crs_list] == [25832, 7837]
    assert a.header.parse_crs().to_2d().to_epsg() == 25832 and not a.header.parse_crs().is_compound
    assert not [v for v in b.header.vlrs if v.record_id == 3 and v.user_id == "LASF_Spec"]
    assert [v for v in a.header.vlrs if v.record_id == 3 and v.user_id == "LASF_Spec"]
    with laspy.open(ort.output) as f:
        wkt = f.header.vlrs.get("WktCoordinateSystemVlr")[0].string
    assert wkt.startswith("COMPD_CS[") and 'AUTHORITY["EPSG","7837"]' in wkt
    if shutil.which("projinfo"):  # PROJ's own command accepts it and identifies both EPSG parts
        run = subprocess.run(["projinfo", "--identify", "-q", "-o", "WKT1_GDAL", wkt], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        ident = subprocess.run(["projinfo", "--identify", wkt], capture_output=True, text=True)
        assert ident.returncode == 0 and "EPSG:25832+7837: 100 %" in ident.stdout, ident.stdout + ident.stderr


def test_points_outside_the_grid_stop_the_georeferencing_and_leave_no_file(tmp_path):
    rng = np.random.default_rng(4)
    strip = _strip(tmp_path / "strip_3.laz", rng)
    # A grid that ends 200 m north of w's origin (48.0018 deg): the northern points are outside it.
    lat, lon = nodes(47.5, 10.5, 0.0018, (279, 556))
    small = write_gtx(tmp_path / "small.gtx", 47.5, 10.5, 0.0018, sloped(lat[:, None], lon[None, :]))
    frame, crs = LocalFrame(math.radians(48.0), math.radians(11.0), 500.0), OutputCRS(25832)
    plan = plan_strip(strip, 3, T0, 10_000, 0.0, index=time_index(strip))
    with pytest.raises(InputError, match=r"small.gtx, field 'crs.geoid_grid': the geoid grid gives no undulation "
                                         r"for .* points of strip_3.laz"):
        georeference_strip(plan, tmp_path / "out.laz", _poses(), T0, np.zeros(3), np.eye(3), frame, crs,
                           heights=GeoidHeights(str(small), 7837))
    assert not (tmp_path / "out.laz").exists() and not list(tmp_path.glob(".*.part"))


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    from georefine.sim.scenarios import simulate_project

    out = tmp_path_factory.mktemp("geoid") / "p"
    simulate_project("corridor-tiny", out, seed=4, overrides=["scanner.pulse_rate_hz=5000"])
    return out


def _with_geoid(project: Path, dest: Path, grid_rel: str | None, vertical_epsg: int | None = 7837) -> Path:
    shutil.copytree(project, dest, ignore=shutil.ignore_patterns("truth"))
    cfg = yaml.safe_load((dest / "project.yaml").read_text())
    cfg["crs"] = {**cfg.get("crs", {}), "geoid_grid": grid_rel, "vertical_epsg": vertical_epsg}
    (dest / "project.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return dest


def test_georeference_workflow_writes_orthometric_strips_that_evaluate_as_ellipsoidal(project, tmp_path):
    """``georefine georeference`` (run_georeference) with a geoid grid in the project: the strips hold
    H = h - N in the compound CRS; the evaluation's reader gives back the ellipsoidal points."""
    from georefine.config import load_project
    from georefine.evaluation.clouds import scan_clouds
    from georefine.io.las import vertical_epsg_of
    from georefine.workflows import run_georeference

    cfg = load_project(project)
    assert cfg.crs.output_epsg == 25832 and cfg.crs.geoid_grid is None
    # corridor-tiny lies near (46.70 N, 11.65 E): a sloped grid around it (N = 47 + 0.8 dlat - 0.5 dlon).
    lat0, lon0 = 46.70, 11.65
    lat_n, lon_n = nodes(lat0 - 0.2, lon0 - 0.2, 0.02, (21, 21))
    N = 47.0 + 0.8 * (lat_n[:, None] - lat0) - 0.5 * (lon_n[None, :] - lon0)
    geo = _with_geoid(project, tmp_path / "geo", "geoid/grid.gtx")
    (geo / "geoid").mkdir()
    write_gtx(geo / "geoid" / "grid.gtx", lat0 - 0.2, lon0 - 0.2, 0.02, N)
    sbet = project / "truth" / "trajectory.sbet"
    ell = run_georeference(project, sbet, tmp_path / "ell")
    ort = run_georeference(geo, sbet, tmp_path / "ort")
    crs = OutputCRS(25832)
    for e, o in zip(ell.strips, ort.strips):
        a, b = laspy.read(e.output), laspy.read(o.output)
        assert vertical_epsg_of(o.output) == 7837 and vertical_epsg_of(e.output) is None
        lat, lon, _ = crs.to_geodetic(np.column_stack([a.x, a.y, a.z]))
        expected = 47.0 + 0.8 * (np.degrees(lat) - lat0) - 0.5 * (np.degrees(lon) - lon0)
        np.testing.assert_allclose(b.z, a.z - expected, atol=1.5e-3)
    # The evaluation reads the orthometric strips back to ellipsoidal heights with the project's grid.
    files = [o.output for o in ort.strips]
    box = np.array([[[-1e9, -1e9, -1e9], [1e9, 1e9, 1e9]]])
    geoid = load_project(geo).crs.geoid(geo)
    back = scan_clouds(files, boxes=box, heights=(crs, geoid)).near_xyz
    ref = scan_clouds([e.output for e in ell.strips], boxes=box).near_xyz
    assert back.shape == ref.shape and np.abs(back - ref).max() < 1.5e-3
    raw = scan_clouds(files, boxes=box).near_xyz  # without the grid: taken as they are
    assert np.abs(np.median(ref[:, 2] - raw[:, 2]) - 47.0) < 0.2


def test_a_project_whose_grid_is_missing_or_does_not_cover_it_is_refused(project, tmp_path):
    from georefine.config import load_project
    from georefine.workflows import run_georeference

    gone = _with_geoid(project, tmp_path / "gone", "geoid/missing.gtx")
    with pytest.raises(ConfigError, match=r"missing.gtx, field 'crs.geoid_grid': no such geoid grid file"):
        load_project(gone)
    far = _with_geoid(project, tmp_path / "far", "far.tif" if shutil.which("gdal_translate") else "far.gtx")
    lat, lon = nodes(*GRID)  # around 48 N 11 E, not the project's 46.7 N
    gtx = write_gtx(tmp_path / "far.gtx", GRID[0], GRID[1], GRID[2], sloped(lat[:, None], lon[None, :]))
    if shutil.which("gdal_translate"):
        subprocess.run(["gdal_translate", "-q", "-of", "GTiff", str(gtx), str(far / "far.tif")], check=True)
    else:
        shutil.copy(gtx, far / "far.gtx")
    with pytest.raises(InputError, match=r"far\.(tif|gtx), field 'crs.geoid_grid': the geoid grid gives no undulation"):
        run_georeference(far, project / "truth" / "trajectory.sbet", tmp_path / "pts")
    assert not list((tmp_path / "pts").glob("*.laz")) if (tmp_path / "pts").exists() else True
