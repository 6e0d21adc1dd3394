"""The strip-difference map shows planar surfaces only, and its GeoTIFF is read by GDAL as written.

A synthetic scene scanned by two strips of two channels each: tilted ground, a pitched roof,
a power line over the ground seen in two ways (with the ground in one plane, or as its own
plane), a tree, an object that moved between the strips, and strip 2's swath ending mid-cell.
Strip 2 lies 2 cm higher than strip 1 everywhere. Before gating, the wires show differences of
metres (as on the simulated corridor); gated, every kept cell shows the 2 cm along the
surface's normal, and each bad cell is gated for its own reason.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import laspy
import numpy as np
import pyproj
import pytest

from georefine.evaluation.clouds import evaluate_strip_differences
from georefine.evaluation.strip_differences import BAND_DESCRIPTION, GATES

X0, Y0 = 500_000.0, 5_100_000.0  # EPSG:25832, cells of 1 m from (X0, Y0)
SIZE = 40
OFFSET = 0.02  # strip 2 above strip 1
WIRE_X = (20.2, 20.8)  # two conductors in cells i = 20, 15 m above the ground
ROUGH_WIRE_Y, STEEP_WIRE_Y = (5, 12), (24, 31)  # cells j of the two stretches of the power line
ROOF = (12, 18, 20, 32)  # cells i0, i1, j0, j1: slope 0.7 across x, 3 m above the ground at its low side
TREE, CROWN_M = (6.5, 31.0), 2.5  # centre and radius of the crown
MOVED = (22, 26, 14, 18)  # cells tilted by 0.3 in strip 2 only
EDGE_X = 29.6  # strip 2 covers x < 29.6


def _ground(x, y):
    return 100.0 + 0.05 * x + 0.02 * y


def _inside(x, y, box):
    return (x >= box[0]) & (x < box[1]) & (y >= box[2]) & (y < box[3])


def _surface(x, y, strip):
    z = np.where(_inside(x, y, ROOF), 103.0 + 0.7 * (x - ROOF[0]) + 0.02 * y, _ground(x, y))
    if strip == 2:
        z = np.where(_inside(x, y, MOVED), z + 0.3 * (x - MOVED[0]), z)
    return z + (OFFSET if strip == 2 else 0.0)


def _wire_points(stretch, xs, dz):
    """Four points a metre on each of the lines ``xs`` along ``stretch``, ``dz`` above the ground."""
    y = (np.arange(*stretch)[:, None] + [0.2, 0.4, 0.6, 0.8]).ravel()
    return [np.column_stack([np.full(y.size, x), y, _ground(x, y) + d]) for x, d in zip(xs, dz)]


def _layer(rng, strip, channel):
    """One strip x channel: 30 points per m2 with 2 mm noise, and what it sees of the objects."""
    n = 30 * SIZE * SIZE
    x, y = rng.uniform(0.0, SIZE, n), rng.uniform(0.0, SIZE, n)
    z = _surface(x, y, strip) + rng.normal(0.0, 0.002, n)
    d = np.hypot(x - TREE[0], y - TREE[1])  # the crown returns 60 % of the pulses, 3 % at its thin rim
    crown = rng.random(n) < np.where(d < CROWN_M - 0.8, 0.6, np.where(d < CROWN_M, 0.03, 0.0))
    z = np.where(crown, z + rng.uniform(0.5, 8.0, n), z)
    keep = x < EDGE_X if strip == 2 else np.ones(n, dtype=bool)
    wire = (x >= 20.0) & (x < 21.0)
    extra = []
    # First stretch of the power line: (1, 0) sees only the ground, (2, 1) only the wires (two
    # lines at one height: a plane 15 m up), the others both: rough.
    if (strip, channel) == (2, 1):
        keep &= ~(wire & (y >= ROUGH_WIRE_Y[0]) & (y < ROUGH_WIRE_Y[1]))
    if (strip, channel) != (1, 0):
        extra += _wire_points(ROUGH_WIRE_Y, WIRE_X, (15.0, 15.0))
    # Second stretch: (2, 0) sees one line of ground and one wire (a smooth plane at 88 degrees),
    # the others only the ground.
    if (strip, channel) == (2, 0):
        keep &= ~(wire & (y >= STEEP_WIRE_Y[0]) & (y < STEEP_WIRE_Y[1]))
        extra += _wire_points(STEEP_WIRE_Y, WIRE_X, (OFFSET, 15.0))
    return np.vstack([np.column_stack([x, y, z])[keep], *extra]) + [X0, Y0, 0.0]


def _write(path, xyz, strip, channel):
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(pyproj.CRS.from_epsg(25832))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.point_source_id = np.full(len(xyz), strip, dtype=np.uint16)
    las.scanner_channel = np.asarray(channel, dtype=np.uint8)
    las.write(path)
    return path


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """The scene written as two LAZ strips and evaluated: the map and the output folder."""
    rng = np.random.default_rng(15)
    folder = tmp_path_factory.mktemp("gating")
    files = []
    for s in (1, 2):
        parts = [(_layer(rng, s, c), c) for c in (0, 1)]
        xyz = np.vstack([p for p, _ in parts])
        channel = np.concatenate([np.full(len(p), c) for p, c in parts])
        files.append(_write(folder / f"strip_{s}.laz", xyz, s, channel))
    out = folder / "ev"
    return evaluate_strip_differences(files, out), out


def _cells(m, i0, i1, j0, j1):
    """Map rows and columns of the cells with ``i0 <= i < i1``, ``j0 <= j < j1`` (scene cells)."""
    c0 = int(round((X0 - m.x0) / m.cell_size_m))
    r0 = int(round((m.y1 - Y0) / m.cell_size_m)) - 1
    return slice(r0 - j1 + 1, r0 - j0 + 1), slice(c0 + i0, c0 + i1)


def test_wires_trees_edges_and_moved_objects_are_gated_planar_cells_kept(evaluated):
    m, out = evaluated
    code = {g: k for k, g in enumerate(GATES)}
    # The wires: metres apart before gating, gated after, each stretch for its own reason.
    for (y0, y1), reason in ((ROUGH_WIRE_Y, "rough"), (STEEP_WIRE_Y, "steep")):
        cells = _cells(m, 20, 21, y0, y1)
        assert np.all(m.ungated_m[cells] > 5.0)
        assert np.all(m.gate[cells] == code[reason]) and np.all(np.isnan(m.spread_m[cells]))
    # The tree: no cell kept under the crown; at its border, where some layers have no return
    # from the crown and others have, gated as rough.
    ci, cj = int(TREE[0]), int(TREE[1])
    box = _cells(m, ci - 3, ci + 4, cj - 3, cj + 4)
    centre_i, centre_j = np.meshgrid(np.arange(ci - 3, ci + 4) + 0.5, np.arange(cj + 3, cj - 4, -1) + 0.5)
    under = np.hypot(centre_i - TREE[0], centre_j - TREE[1]) < CROWN_M - 0.5
    assert np.count_nonzero(under) >= 9 and not np.any(m.gate[box][under] == code["kept"])
    assert np.count_nonzero(m.gate[box] == code["rough"]) >= 3
    # The object that moved: planar in both strips but tilted apart.
    moved = _cells(m, MOVED[0] + 1, MOVED[1] - 1, MOVED[2] + 1, MOVED[3] - 1)
    assert np.all(m.gate[moved] == code["normals"]) and np.all(m.ungated_m[moved] > 0.3 * 1.0)
    # Strip 2's swath ends in cell 29: its neighbours at 30 have no points of strip 2.
    assert np.all(m.gate[_cells(m, 29, 30, 1, SIZE - 1)] == code["edge"])
    assert np.all(m.gate[_cells(m, 0, SIZE, 0, 1)] == code["edge"])  # the scene's own border
    # Kept cells: 2 cm along the normal where both strips are, 0 where only strip 1 is.
    ground = _cells(m, 1, 10, 1, 20)
    n_ground = 1.0 / np.sqrt(1.0 + 0.05**2 + 0.02**2)
    assert np.all(m.gate[ground] == code["kept"])
    np.testing.assert_allclose(m.spread_m[ground], OFFSET * n_ground, atol=0.002)
    roof = _cells(m, ROOF[0] + 1, ROOF[1] - 1, ROOF[2] + 1, ROOF[3] - 1)
    n_roof = 1.0 / np.sqrt(1.0 + 0.7**2 + 0.02**2)
    assert np.all(m.gate[roof] == code["kept"])
    assert np.median(m.spread_m[roof]) == pytest.approx(OFFSET * n_roof, abs=0.0005)  # 16.4 mm, not 20
    np.testing.assert_allclose(m.spread_m[roof], OFFSET * n_roof, atol=0.002)
    only_1 = _cells(m, 31, SIZE - 1, 1, SIZE - 1)
    assert np.all(m.gate[only_1] == code["kept"]) and np.all(m.spread_m[only_1] < 0.002)
    s = m.summary()
    assert s["cells_above_1m"] == 0 and s["max_m"] < 0.025 and m.ungated_summary()["cells_above_1m"] >= 14

    written = json.loads((out / "strip_differences.json").read_text())
    g = written["gated"]
    assert g == m.gating() and g["candidates"] == g["kept"] + g["rough"] + g["steep"] + g["edge"] + g["normals"]
    assert min(g["rough"], g["steep"], g["edge"], g["normals"]) > 0
    assert written["ungated"]["max_m"] > 10.0 and written["max_m"] < 0.025
    assert (written["max_slope_deg"], written["max_normal_angle_deg"]) == (60.0, 5.0)


def _run(*args):
    return subprocess.run(args, capture_output=True, text=True, check=True).stdout


@pytest.mark.skipif(shutil.which("gdalinfo") is None or shutil.which("gdalsrsinfo") is None,
                    reason="GDAL command-line tools not installed")
def test_gdal_reads_the_evaluations_geotiff_in_the_strips_crs(evaluated):
    m, out = evaluated
    tif = out / "strip_differences.tif"
    info = json.loads(_run("gdalinfo", "-json", str(tif)))
    band = info["bands"][0]
    assert (band["description"], band.get("unit"), band["noDataValue"]) == (BAND_DESCRIPTION, "metre", "NaN")
    assert info["geoTransform"] == [m.x0, 1.0, 0.0, m.y1, 0.0, -1.0]
    assert _run("gdalsrsinfo", "-e", str(tif)).split()[0] == "EPSG:25832"  # from the strips' WKT
