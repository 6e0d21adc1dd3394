"""The point-cloud evaluation in bounded memory: chunked cell sums equal the in-memory fit.

The strip differences used to fit every cell's plane with all of a layer's points in memory
(mean height, then the plane about it, then the residuals). They now merge per-cell moment
sums chunk by chunk and close the cells the scanner has left; the reference planes keep only
the points near each surface. These tests hold the old in-memory formula and compare.
"""

from __future__ import annotations

import logging

import laspy
import numpy as np
import pytest

from georefine.evaluation.cell_moments import CellMoments, cell_moments
from georefine.evaluation.clouds import (
    NEAR_PLANE_M,
    evaluate_reference_planes,
    evaluate_strip_differences,
    plane_boxes,
    scan_clouds,
)
from georefine.evaluation.reference_planes import (
    observe_reference_planes,
    reference_planes,
)
from georefine.evaluation.strip_differences import Reopened, StripDifferenceStream
from georefine.io.reference import ReferenceSurfaces, write_reference_surfaces
from georefine.tasks import TaskRunner

# -- the in-memory formula the evaluation used before it streamed ------------------------------


def _old_cell_planes(xyz, cell_size_m=1.0, min_points=6):
    """Two passes over all points of one layer: cell mean height, plane about it, residuals."""
    ij = np.floor(xyz[:, :2] / cell_size_m).astype(np.int64)
    cells, inv, counts = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    centre = (cells + 0.5) * cell_size_m
    dx, dy, z = xyz[:, 0] - centre[inv, 0], xyz[:, 1] - centre[inv, 1], xyz[:, 2]

    def s(w):
        return np.bincount(inv, w, cells.shape[0])

    z_ref = s(z) / counts
    dz = z - z_ref[inv]
    n = counts.astype(float)
    A = np.empty((cells.shape[0], 3, 3))
    A[:, 0, 0] = n
    A[:, 0, 1] = A[:, 1, 0] = s(dx)
    A[:, 0, 2] = A[:, 2, 0] = s(dy)
    A[:, 1, 1] = s(dx * dx)
    A[:, 1, 2] = A[:, 2, 1] = s(dx * dy)
    A[:, 2, 2] = s(dy * dy)
    b = np.stack([s(dz), s(dx * dz), s(dy * dz)], axis=1)
    ok = (counts >= min_points) & (np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(n, 1.0) ** 3 * cell_size_m**4)
    coef = np.full((cells.shape[0], 3), np.nan)
    coef[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    res = dz - (coef[inv, 0] + coef[inv, 1] * dx + coef[inv, 2] * dy)
    rough = np.sqrt(s(res * res) / n)
    keep = ok & np.isfinite(rough)
    return cells[keep], (z_ref + coef[:, 0])[keep], rough[keep], counts[keep]


def _old_map(layers, cell_size_m=1.0, min_points=6, max_roughness_m=0.03):
    """``(spread, layers per cell, x0, y1)`` of the layers' planes, as the old raster was made."""
    keys, heights = [], []
    for xyz in layers:
        cells, h, rough, _ = _old_cell_planes(xyz, cell_size_m, min_points)
        keys.append(cells[rough <= max_roughness_m])
        heights.append(h[rough <= max_roughness_m])
    cells, inv, counts = np.unique(np.concatenate(keys), axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    allh = np.concatenate(heights)
    hi, lo = np.full(len(cells), -np.inf), np.full(len(cells), np.inf)
    np.maximum.at(hi, inv, allh)
    np.minimum.at(lo, inv, allh)
    (i0, j0), (i1, j1) = cells.min(axis=0), cells.max(axis=0)
    spread = np.full((j1 - j0 + 1, i1 - i0 + 1), np.nan)
    nlay = np.zeros(spread.shape, dtype=int)
    r, c = j1 - cells[:, 1], cells[:, 0] - i0
    nlay[r, c] = counts
    spread[r[counts >= 2], c[counts >= 2]] = (hi - lo)[counts >= 2]
    return spread, nlay, float(i0 * cell_size_m), float((j1 + 1) * cell_size_m)


def _assert_same_map(m, old, gated=None):
    """``m`` before gating is the old map; gated, it is ``gated`` (the same layers' sums in one part)."""
    spread, nlay, x0, y1 = old
    assert (m.x0, m.y1) == (x0, y1) and m.ungated_m.shape == spread.shape
    np.testing.assert_array_equal(m.layers_m, nlay)
    np.testing.assert_array_equal(np.isnan(m.ungated_m), np.isnan(spread))
    np.testing.assert_allclose(m.ungated_m, spread, rtol=0, atol=1e-9, equal_nan=True)
    assert np.count_nonzero(np.isfinite(spread)) > 500
    if gated is not None:
        np.testing.assert_array_equal(m.gate, gated.gate)
        np.testing.assert_allclose(m.spread_m, gated.spread_m, rtol=0, atol=1e-9, equal_nan=True)
        g = m.gating()
        assert g["kept"] > 500 and g["rough"] > 0 and g["edge"] > 0  # the vegetation and the strips' borders


def _gated_map(layers):
    """The gated map of ``{code: points}`` with every layer's sums added at once, nothing closed."""
    stream = StripDifferenceStream(1.0)
    stream.add([cell_moments(xyz, 1.0, code) for code, xyz in layers.items()], sum(map(len, layers.values())))
    return stream.result()


# -- a scene scanned line by line ---------------------------------------------------------------

X0, Y0 = 600_000.0, 5_200_000.0


def _surface(x, y):
    """Tilted ground, a gable roof of slope 1, a flat roof (local coordinates)."""
    z = 100.0 + 0.02 * x - 0.01 * y
    gable = (x >= 20) & (x < 35) & (y >= 10) & (y < 30)
    z = np.where(gable, 106.0 + np.minimum(x - 20.0, 35.0 - x), z)
    flat = (x >= 45) & (x < 55) & (y >= 5) & (y < 25)
    return np.where(flat, 109.0, z)


def _strip(rng, strip, reverse=False, lines=128, per_line=200):
    """Points of one strip in time order: scan lines along y, three channels looking at
    y - 8, y, y + 8 m, one point of each channel in turn; vegetation over x 60-66 m."""
    k = np.arange(lines)[::-1] if reverse else np.arange(lines)
    y_line = np.repeat(0.25 * k, per_line)
    x = np.tile(np.linspace(0.0, 66.0, per_line), lines) + rng.uniform(-0.1, 0.1, lines * per_line)
    xyz, ch = [], []
    for c, ahead in enumerate((0.0, 8.0, -8.0)):
        y = y_line + ahead + rng.normal(0.0, 0.02, x.size)
        z = _surface(x, y) + 0.003 * strip - 0.002 * c
        if (strip, c) != (1, 0):  # strip 1, channel 0 sees perfect planes
            z = z + rng.normal(0.0, 0.002, x.size)
        veg = (x > 60) & (rng.random(x.size) < 0.5)
        z = np.where(veg, z + rng.uniform(0.0, 4.0, x.size), z)
        xyz.append(np.column_stack([x + X0, y + Y0, z]))
        ch.append(np.full(x.size, c))
    order = np.argsort(np.tile(np.arange(x.size), 3), kind="stable")  # interleave the channels
    return np.vstack(xyz)[order], np.concatenate(ch)[order]


def _write(path, xyz, strip, channel):
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.point_source_id = np.full(len(xyz), strip, dtype=np.uint16)
    las.scanner_channel = np.asarray(channel, dtype=np.uint8)
    las.write(path)
    return path


@pytest.fixture(scope="module")
def strips(tmp_path_factory):
    """Two strips flown in opposite directions, written as LAZ; the points as read back per layer."""
    rng = np.random.default_rng(21)
    folder = tmp_path_factory.mktemp("strips")
    files = []
    for s in (1, 2):
        xyz, channel = _strip(rng, s, reverse=s == 2)
        files.append(_write(folder / f"strip_{s}.laz", xyz, s, channel))
    layers = {}
    for f in files:
        las = laspy.read(f)
        xyz = np.column_stack([las.x, las.y, las.z])
        sid, ch = np.asarray(las.point_source_id), np.asarray(las.scanner_channel)
        for s, c in sorted(set(zip(sid.tolist(), ch.tolist()))):
            layers[(s, c)] = xyz[(sid == s) & (ch == c)]
    return files, layers


@pytest.fixture(scope="module")
def processes():
    with TaskRunner("processes", workers=2) as runner:
        yield runner


# -- tests ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("parts", "shuffle"), [(1, False), (4, True), (25, True), (60, False)])
def test_merged_chunk_sums_give_the_in_memory_planes(parts, shuffle):
    rng = np.random.default_rng(parts)
    xyz, ch = _strip(np.random.default_rng(3), 1)
    perfect = xyz[ch == 0]  # strip 1, channel 0: noise-free
    noisy = xyz[ch == 1] + [100.0, 0.0, 0.0]  # beside it
    xyz = np.vstack([perfect, noisy])
    if shuffle:
        xyz = xyz[rng.permutation(len(xyz))]
    cuts = np.sort(rng.choice(np.arange(1, len(xyz)), parts - 1, replace=False))
    chunks = [cell_moments(p, 1.0, 7) for p in np.split(xyz, cuts)]
    planes = CellMoments.merge([chunks[k] for k in rng.permutation(parts)]).planes(6)
    cells, height, rough, n = _old_cell_planes(xyz)
    np.testing.assert_array_equal(planes.cell_ij, cells)
    np.testing.assert_array_equal(planes.n_points, n)
    np.testing.assert_allclose(planes.height_m, height, rtol=0, atol=1e-9)
    np.testing.assert_allclose(planes.roughness_m, rough, rtol=0, atol=1e-9)
    assert np.all(planes.layer == 7)
    assert np.count_nonzero(rough < 1e-9) > 1000 and np.count_nonzero(planes.roughness_m < 1e-9) > 1000  # perfect


def test_the_stream_closes_the_cells_the_scanner_has_left(strips):
    _, layers = strips
    old = _old_map(list(layers.values()))
    stream = StripDifferenceStream(1.0, close_after=3000)
    total = peak = 0
    for k, xyz in enumerate(layers.values()):
        for part in np.array_split(xyz, 23):  # in time order
            m = cell_moments(part, 1.0, k)
            stream.add([m], len(part))
            total += len(m)
            peak = max(peak, stream.open_rows())
        stream.close_layer(k)
    _assert_same_map(stream.result(), old, _gated_map(dict(enumerate(layers.values()))))
    assert peak < total / 4  # only the cells near the scanner are open

    stream = StripDifferenceStream(1.0, close_after=3000)
    parts = np.array_split(layers[(1, 0)], 23)
    for part in parts[:10]:
        stream.add([cell_moments(part, 1.0, 0)], len(part))
    with pytest.raises(Reopened):  # the scanner's first cells again, long after they were closed
        stream.add([cell_moments(parts[0], 1.0, 0)], len(parts[0]))


@pytest.mark.parametrize(("scheduler", "chunk_points", "close_after"),
                         [("sync", 10**9, None), ("sync", 7_001, 20_000), ("processes", 20_000, 40_000)])
def test_the_map_of_files_does_not_depend_on_chunks_closing_or_scheduler(strips, processes, tmp_path, caplog, scheduler,
                                                                         chunk_points, close_after):
    import json

    files, layers = strips
    runner = processes if scheduler == "processes" else TaskRunner("sync")
    with caplog.at_level(logging.WARNING, logger="georefine.evaluation.clouds"):
        scan = scan_clouds(files, cell_size_m=1.0, runner=runner, chunk_points=chunk_points, close_after=close_after)
    assert "again" not in caplog.text  # the cells were closed behind the scanner, never reopened
    out = tmp_path if scheduler == "processes" else None  # the files once (the PNG takes time)
    m = evaluate_strip_differences(files, out, scan=scan)
    _assert_same_map(m, _old_map(list(layers.values())), _gated_map({s * 256 + c: x for (s, c), x in layers.items()}))
    assert scan.layers == tuple((s, c, len(x)) for (s, c), x in layers.items())
    if out is not None:
        written = json.loads((tmp_path / "strip_differences.json").read_text())
        assert written["layers"] == [{"strip": s, "channel": c, "points": len(x)} for (s, c), x in layers.items()]
        assert written["cells"] == m.summary()["cells"] and (tmp_path / "strip_differences.png").is_file()
        assert written["gated"] == m.gating() and written["ungated"]["cells"] == m.gating()["candidates"]


def test_a_strip_split_over_two_files_is_read_again_with_every_cell_open(strips, tmp_path, caplog):
    files, layers = strips
    las = laspy.read(files[0])
    xyz, ch = np.column_stack([las.x, las.y, las.z]), np.asarray(las.scanner_channel)
    half = len(xyz) // 2
    parts = [_write(tmp_path / "strip_1a.laz", xyz[:half], 1, ch[:half]), files[1],
             _write(tmp_path / "strip_1b.laz", xyz[half:], 1, ch[half:])]
    with caplog.at_level(logging.WARNING, logger="georefine.evaluation.clouds"):
        m = evaluate_strip_differences(parts, chunk_points=50_000)
    assert "reading the point clouds again" in caplog.text
    _assert_same_map(m, _old_map(list(layers.values())), _gated_map({s * 256 + c: x for (s, c), x in layers.items()}))


def test_per_surface_boxes_keep_the_points_near_every_surface_and_drop_the_rest(tmp_path):
    rng = np.random.default_rng(8)
    centres = [(100.0, 10.0, 50.0), (520.0, 12.0, 58.4), (930.0, 8.0, 66.6)]  # along a 1 km corridor
    rows = []
    for k, (cx, cy, cz) in enumerate(centres):
        for p, (dx, dy) in enumerate([(-2, -2), (2, -2), (2, 2), (-2, 2)]):
            rows.append((f"S{k}", f"P{p}", X0 + cx + dx, Y0 + cy + dy, cz + 0.02 * dx))
    sid, pid, x, y, z = zip(*rows)
    write_reference_surfaces(tmp_path / "surfaces.csv",
                             ReferenceSurfaces(np.array(sid), np.array(pid), np.column_stack([x, y, z])))
    planes = reference_planes(ReferenceSurfaces(np.array(sid), np.array(pid), np.column_stack([x, y, z])))
    # Points all along the corridor, denser on the surfaces; the ground slopes as they do.
    n = 150_000
    xy = np.column_stack([rng.uniform(0.0, 1000.0, n), rng.uniform(0.0, 20.0, n)])
    on = np.vstack([np.array(c[:2]) + rng.uniform(-3.0, 3.0, (3000, 2)) for c in centres])
    xy = np.vstack([xy, on])
    z = 50.0 + 0.02 * (xy[:, 0] - 100.0) + rng.normal(0.0, 0.003, len(xy))
    xyz = np.column_stack([xy[:, 0] + X0, xy[:, 1] + Y0, z])
    channel = rng.integers(0, 3, len(xyz))
    f = _write(tmp_path / "strip_3.laz", xyz, 3, channel)
    las = laspy.read(f)
    xyz = np.column_stack([las.x, las.y, las.z])  # as stored (0.1 mm)

    boxes = plane_boxes(planes)
    assert np.allclose(boxes[:, 1] - boxes[:, 0], 2 * NEAR_PLANE_M)
    scan = scan_clouds([f], boxes=boxes, chunk_points=40_000)
    near = np.zeros(len(xyz), dtype=bool)
    for pl in planes:
        near |= np.all(np.abs(xyz - pl.centre) <= NEAR_PLANE_M, axis=1)
    one_box = np.all((xyz >= boxes[:, 0].min(axis=0)) & (xyz <= boxes[:, 1].max(axis=0)), axis=1)
    assert len(scan.near_xyz) == np.count_nonzero(near) < 0.15 * len(xyz)
    assert np.count_nonzero(one_box) > 0.8 * len(xyz)  # one box over all surfaces: nearly the whole corridor
    np.testing.assert_array_equal(np.sort(scan.near_xyz, axis=0), np.sort(xyz[near], axis=0))
    assert set(np.unique(scan.near_strip)) == {3}

    obs, summary = evaluate_reference_planes([f], tmp_path / "surfaces.csv", chunk_points=40_000)
    expected = observe_reference_planes(xyz, 3, np.asarray(las.scanner_channel), planes)
    assert len(obs) == 9 and summary.n_observations == 9
    assert sorted((o.surface_id, o.channel, o.n_points) for o in obs) == sorted(
        (o.surface_id, o.channel, o.n_points) for o in expected)
    for o in obs:
        e = next(e for e in expected if (e.surface_id, e.channel) == (o.surface_id, o.channel))
        assert o.mean_m == pytest.approx(e.mean_m, abs=1e-12) and o.sd_points_m == pytest.approx(e.sd_points_m, abs=1e-12)


def test_cloud_error_map_is_the_mean_error_per_cell(tmp_path):
    from georefine.evaluation.coadjust import CloudErrors, _error_grid, plot_cloud_errors

    rng = np.random.default_rng(5)
    xy = rng.uniform(0.0, 10.0, (20_000, 2))
    n = xy[:, 0] * 0.01 + rng.normal(0.0, 0.001, len(xy))  # error grows eastwards
    grid = _error_grid(xy, n, np.zeros(2), 1.0, (10, 10))
    cell = (xy // 1.0).astype(int)
    inside = (cell[:, 0] == 3) & (cell[:, 1] == 7)
    assert grid[7, 3] == pytest.approx(n[inside].mean())  # row = north, column = east
    assert np.all(np.diff(np.nanmean(grid, axis=0)) > 0)
    empty = _error_grid(xy[xy[:, 0] < 5], n[xy[:, 0] < 5], np.zeros(2), 1.0, (10, 10))
    assert np.all(np.isnan(empty[:, 5:])) and not np.any(np.isnan(empty[:, :5]))
    errors = CloudErrors(xy, np.column_stack([n, n, n]), np.column_stack([n, n, n]) / 2)
    path = plot_cloud_errors(errors, tmp_path / "map.png", title="t")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
