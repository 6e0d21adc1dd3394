"""The strip-pair differences (evaluation/strip_pairs.py) on strips of known offsets.

A small block: three parallel strips with sidelap (1, 2, 3), a cross strip (4) and a patch (5)
that touches strip 1 at a corner, over tilted ground with a 30 degree mono-pitch roof, a thin
wall, a tree patch and a wire that only the cross strip sees. Strip 3 lies 30 mm higher than
the others; strip 2 has two channels, the second 4 mm higher than the first, so its centre is
2 mm up. Every pair's signed median must be the difference of the strips' offsets, the pairs
that do not overlap or share too few cells must have no figures, and no cell that the trees,
the wall or the wire make non-planar may count.
"""

from __future__ import annotations

import csv
import json
import logging
import math

import laspy
import numpy as np
import pytest

from georefine.errors import InputError
from georefine.evaluation.cell_moments import cell_keys, cell_moments
from georefine.evaluation.clouds import record_ranges, scan_clouds
from georefine.evaluation.figures import MIN_FONT_KEY
from georefine.evaluation.strip_differences import GATES, LAYER_CODE
from georefine.evaluation.strip_pairs import (
    CSV_HEADER,
    MIN_PAIR_CELLS,
    StripPair,
    StripPairDifferences,
    StripPairStream,
    scan_clouds_with_pairs,
    strip_pair_differences,
    write_pairs_csv,
    write_pairs_png,
)
from georefine.evaluation.summary import (
    CloudEvaluation,
    RunEvaluation,
    StripDifferenceFigures,
    StripPairFigures,
)
from georefine.io.files import write_json
from georefine.tasks import TaskRunner

X0, Y0 = 600_000.0, 5_200_000.0
NOISE_M = 0.005
SPACING_M = 0.25
ROOF = (42.5, 57.5, 10.5, 29.5)  # x0, x1, y0, y1: a mono-pitch roof rising 30 degrees to the east
ROOF_SLOPE = math.tan(math.radians(30.0))
WALL = (85.45, 85.55, 20.0, 40.0)  # 10 cm thick, 3.5 m high
TREES = (44.0, 56.0, 55.0, 70.0)
WIRE_X, WIRE = 50.3, (30.0, 50.0)  # along y, 12 m up, seen by the cross strip only
# strip: (x range, y range, direction of the scan lines' advance)
STRIPS = {1: ((0.0, 60.0), (0.0, 80.0), "y"), 2: ((40.0, 100.0), (0.0, 80.0), "y"),
          3: ((80.0, 140.0), (0.0, 80.0), "y"), 4: ((0.0, 140.0), (30.0, 50.0), "x"),
          5: ((-10.0, 6.0), (70.0, 86.0), "y")}
OFFSET_M = {3: 0.030}  # strip 3 higher
CHANNEL_OFFSET_M = 0.004  # strip 2's second channel higher than its first


def _inside(x, y, box):
    return (x >= box[0]) & (x < box[1]) & (y >= box[2]) & (y < box[3])


def _surface(x, y):
    z = 100.0 + 0.02 * x - 0.01 * y
    z = np.where(_inside(x, y, ROOF), 108.0 + ROOF_SLOPE * (x - ROOF[0]), z)
    return np.where(_inside(x, y, WALL), 103.5, z)


def _expected_offset_m(strip: int, channels: int) -> float:
    """A strip's height above the truth: its offset plus the centre of its channels'."""
    extra = 0.5 * CHANNEL_OFFSET_M if strip == 2 and channels == 2 else 0.0
    return OFFSET_M.get(strip, 0.0) + extra


def _strip(rng, strip: int, channels: int):
    """``{(strip, channel): points}`` of one strip, each channel in time order (scan line by line)."""
    (xa, xb), (ya, yb), along = STRIPS[strip]
    out = {}
    for c in range(channels):
        u = np.arange(xa, xb, SPACING_M) if along == "y" else np.arange(ya, yb, SPACING_M)  # across the lines
        t = np.arange(ya, yb, SPACING_M) if along == "y" else np.arange(xa, xb, SPACING_M)  # line positions
        across = np.tile(u, t.size) + rng.uniform(0.0, SPACING_M, u.size * t.size)
        line = np.repeat(t, u.size) + rng.uniform(0.0, SPACING_M, u.size * t.size)
        x, y = (across, line) if along == "y" else (line, across)
        x, y = np.clip(x, xa, xb - 1e-6), np.clip(y, ya, yb - 1e-6)
        z = _surface(x, y) + rng.normal(0.0, NOISE_M, x.size)
        trees = _inside(x, y, TREES) & (rng.random(x.size) < 0.5)
        z = np.where(trees, z + rng.uniform(3.0, 10.0, x.size), z)
        xyz = [np.column_stack([x, y, z])]
        if strip == 2 and c == 0:  # the wall's face, seen from the west
            wy = np.arange(WALL[2], WALL[3], SPACING_M / 2)
            wz = rng.uniform(100.0, 103.5, wy.size)
            xyz.append(np.column_stack([np.full(wy.size, WALL[0] + 0.01), wy, wz]))
        if strip == 4:  # two returns on the wire per scan line that crosses it
            wy = np.repeat(np.arange(WIRE[0], WIRE[1], SPACING_M), 2)
            xyz.append(np.column_stack([np.full(wy.size, WIRE_X), wy, np.full(wy.size, 112.0)]))
        xyz = np.vstack(xyz)
        xyz = xyz[np.argsort(xyz[:, 1] if along == "y" else xyz[:, 0], kind="stable")]  # time order
        xyz[:, 2] += OFFSET_M.get(strip, 0.0) + (CHANNEL_OFFSET_M if (strip == 2 and c == 1) else 0.0)
        out[(strip, c)] = xyz + [X0, Y0, 0.0]
    return out


def _block(seed: int, channels: int = 2):
    rng = np.random.default_rng(seed)
    layers = {}
    for s in STRIPS:
        layers.update(_strip(rng, s, channels if s == 2 else 1))
    return layers


def _cells_in(cells, box):
    """Which cells (``(K, 2)`` indices) touch ``box`` (local coordinates)."""
    x, y = cells[:, 0] - math.floor(X0), cells[:, 1] - math.floor(Y0)
    return (x + 1 > box[0]) & (x < box[1]) & (y + 1 > box[2]) & (y < box[3])


@pytest.fixture(scope="module")
def block():
    return _block(7)


@pytest.fixture(scope="module")
def pairs(block):
    return strip_pair_differences(block)


# -- the figures -----------------------------------------------------------------------------------


def test_every_pair_has_the_difference_of_its_strips_offsets(pairs):
    assert pairs.strips == (1, 2, 3, 4, 5) and len(pairs.pairs) == 10
    assert [(p.strip_a, p.strip_b) for p in pairs.pairs] == [(a, b) for a in range(1, 6) for b in range(a + 1, 6)]
    measured = {(p.strip_a, p.strip_b) for p in pairs.measured()}
    assert measured == {(1, 2), (1, 4), (2, 3), (2, 4), (3, 4)}
    for p in pairs.measured():
        expected_mm = 1e3 * (_expected_offset_m(p.strip_b, 2) - _expected_offset_m(p.strip_a, 2))
        assert p.cells >= 200, p
        assert abs(p.signed_median_mm - expected_mm) < 0.6, p  # 2 mm apart is told from 0 and from 4
        if abs(expected_mm) > 10.0:  # the noise is small beside it: |d| is the offset
            assert abs(p.median_mm - abs(expected_mm)) < 0.6 and abs(p.rms_mm - abs(expected_mm)) < 1.0, p
            assert abs(expected_mm) < p.p95_mm < abs(expected_mm) + 4.0, p
        else:  # plane fits of 16 points with 5 mm noise: about 1.8 mm per cell
            assert p.median_mm < 3.5 and p.p95_mm < 8.0, p
    assert pairs.pair(3, 2).signed_median_mm == pairs.pair(2, 3).signed_median_mm > 25.0  # b above a
    assert pairs.pair(3, 4).signed_median_mm < -25.0


def test_pairs_that_do_not_overlap_or_share_few_cells_have_no_figures(pairs):
    for a, b in ((1, 3), (2, 5), (3, 5), (4, 5)):
        p = pairs.pair(a, b)
        assert p == StripPair(a, b, 0) and not p.measured
    corner = pairs.pair(1, 5)  # 6 m x 10 m of common cover, less its border cells
    assert 0 < corner.cells < MIN_PAIR_CELLS and corner.median_mm is None and corner.signed_median_mm is None
    assert strip_pair_differences({k: v for k, v in _block(7).items()}, min_cells=corner.cells).pair(1, 5).measured
    assert {(p.strip_a, p.strip_b) for p in pairs.unmeasured()} == {(1, 3), (1, 5), (2, 5), (3, 5), (4, 5)}


def test_on_a_roof_the_difference_is_along_its_normal():
    rng = np.random.default_rng(11)
    x = rng.uniform(0.0, 30.0, 30 * 30 * 16)
    y = rng.uniform(0.0, 30.0, x.size)
    layers = {}
    for s, dz in ((1, 0.0), (2, 0.030)):
        z = 100.0 + ROOF_SLOPE * x + dz + rng.normal(0.0, NOISE_M, x.size)
        layers[(s, 0)] = np.column_stack([x + X0, y + Y0, z])
    p = strip_pair_differences(layers).pair(1, 2)
    # 30 mm vertically between parallel planes 30 degrees steep are 26 mm apart.
    assert p.cells > 600 and abs(p.signed_median_mm - 30.0 * math.cos(math.radians(30.0))) < 0.5


def test_trees_wall_and_wire_do_not_count_and_the_pairs_agree_with_the_raster():
    layers = _block(3, channels=1)  # one channel per strip: the raster's max - min is the largest pair's
    stream = StripPairStream()
    stream.add([cell_moments(x, 1.0, s * LAYER_CODE + c) for (s, c), x in layers.items()],
               sum(map(len, layers.values())))
    cells = stream.pair_cells()
    m = stream.result()
    i0, j1 = round(m.x0 / m.cell_size_m), round(m.y1 / m.cell_size_m) - 1
    gate = m.gate[j1 - cells.cell_ij[:, 1], cells.cell_ij[:, 0] - i0]
    local = cells.cell_ij - [math.floor(X0), math.floor(Y0)]
    # The wire: under it strips 1 and 2 see planar ground, the cross strip wire and ground. The
    # raster gates those cells as rough; the pairs count none of them, (1, 2) included.
    rows, cols = m.gate.shape
    grid = np.column_stack([np.tile(np.arange(cols) + i0, rows), np.repeat(j1 - np.arange(rows), cols)])
    wire_box = (math.floor(WIRE_X), math.floor(WIRE_X) + 1, *WIRE)
    assert np.count_nonzero(_cells_in(grid, wire_box) & (m.gate.ravel() == GATES.index("rough"))) >= 15
    assert not np.any(_cells_in(cells.cell_ij, wire_box))
    # Trees, the wall and the roof's eaves put points on two objects in every view: no pair there.
    assert not np.any((local[:, 0] == math.floor(WALL[0])) & (local[:, 1] >= WALL[2]) & (local[:, 1] < WALL[3]))
    assert not np.any((local[:, 0] >= TREES[0]) & (local[:, 0] < TREES[1]) & (local[:, 1] >= TREES[2])
                      & (local[:, 1] < TREES[3]))
    eaves = ((np.isin(local[:, 0], [42, 57]) & (local[:, 1] >= 10) & (local[:, 1] <= 29))
             | (np.isin(local[:, 1], [10, 29]) & (local[:, 0] >= 42) & (local[:, 0] <= 57)))
    assert not np.any(eaves)
    assert not np.any(np.isin(gate, [GATES.index(g) for g in ("rough", "steep")]))
    # The roof itself counts (planar at 30 degrees).
    roof = (local[:, 0] > 42) & (local[:, 0] < 57) & (local[:, 1] > 10) & (local[:, 1] < 29)
    assert np.count_nonzero(roof & (cells.strip_a == 1) & (cells.strip_b == 2)) > 150
    # Where the raster keeps a cell, every pair planar there is kept, and the largest is its value.
    kept = gate == GATES.index("kept")
    key = cell_keys(cells.cell_ij[kept])
    d = np.abs(cells.difference_m[kept])
    order = np.lexsort((d, key))
    last = np.append(key[order][1:] != key[order][:-1], True)
    ij = cells.cell_ij[kept][order][last]
    # Up to the normal: the pair's mean, not the cell's, within 5 degrees (cos 5 deg = 0.9962).
    np.testing.assert_allclose(d[order][last], m.spread_m[j1 - ij[:, 1], ij[:, 0] - i0], rtol=4e-3, atol=1e-9)
    assert np.count_nonzero(np.isfinite(m.spread_m)) == ij.shape[0] > 3000


# -- streaming and files ------------------------------------------------------------------------------


def _assert_same_pairs(got: StripPairDifferences, want: StripPairDifferences, atol: float = 1e-6):
    assert got.strips == want.strips and got.min_cells == want.min_cells
    for g, w in zip(got.pairs, want.pairs):
        assert (g.strip_a, g.strip_b, g.cells) == (w.strip_a, w.strip_b, w.cells)
        for f in ("median_mm", "p95_mm", "rms_mm", "signed_median_mm"):
            a, b = getattr(g, f), getattr(w, f)
            assert (a is None) == (b is None) and (a is None or abs(a - b) < atol), (g, w, f)


def test_closing_the_cells_behind_the_scanner_changes_nothing(block, pairs):
    stream = StripPairStream(close_after=20_000)
    peak = 0
    for (s, c), xyz in block.items():
        for part in np.array_split(xyz, max(1, len(xyz) // 5_000)):
            stream.add([cell_moments(part, 1.0, s * LAYER_CODE + c)], len(part))
            peak = max(peak, stream.open_rows())
        stream.close_layer(s * LAYER_CODE + c)
    _assert_same_pairs(stream.pairs(), pairs, atol=1e-9)
    assert peak < 0.25 * sum(len(cell_moments(x)) for x in block.values())  # bounded: the cells near the scanner


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


class _Counting(TaskRunner):
    """A runner in this process that counts the record ranges it reads."""

    def __init__(self) -> None:
        super().__init__("sync")
        self.tasks = 0

    def map(self, fn, args, **kwargs):
        for value in super().map(fn, args, **kwargs):
            self.tasks += 1
            yield value


@pytest.fixture(scope="module")
def files(block, tmp_path_factory):
    folder = tmp_path_factory.mktemp("pairs")
    out = []
    for s in STRIPS:
        parts = [(k, x) for k, x in block.items() if k[0] == s]
        xyz = np.vstack([x for _, x in parts])
        channel = np.concatenate([np.full(len(x), c) for (_, c), x in parts])
        order = np.argsort(np.concatenate([np.arange(len(x)) / len(x) for _, x in parts]), kind="stable")
        out.append(_write(folder / f"strip_{s}.laz", xyz[order], s, channel[order]))  # channels interleaved
    read = {}
    for f in out:
        las = laspy.read(f)
        xyz = np.column_stack([las.x, las.y, las.z])
        sid, ch = np.asarray(las.point_source_id), np.asarray(las.scanner_channel)
        for s, c in sorted(set(zip(sid.tolist(), ch.tolist()))):
            read[(s, c)] = xyz[(sid == s) & (ch == c)]
    return out, read


def test_the_files_are_read_once_for_the_raster_and_the_pairs(files, caplog):
    paths, read = files
    runner = _Counting()
    with caplog.at_level(logging.WARNING, logger="georefine.evaluation.clouds"):
        scan, got = scan_clouds_with_pairs(paths, runner=runner, chunk_points=30_000, close_after=60_000)
    assert "again" not in caplog.text
    assert runner.tasks == len(record_ranges(paths, 30_000)) > len(paths)  # every record range once
    _assert_same_pairs(got, strip_pair_differences(read), atol=1e-6)
    alone = scan_clouds(paths, cell_size_m=1.0, chunk_points=30_000, close_after=60_000)
    np.testing.assert_array_equal(scan.strip_differences.gate, alone.strip_differences.gate)
    np.testing.assert_array_equal(scan.strip_differences.spread_m, alone.strip_differences.spread_m)
    assert scan.layers == alone.layers


def test_a_strip_split_over_two_files_is_read_again_for_the_pairs_too(files, tmp_path, caplog):
    paths, read = files
    las = laspy.read(paths[0])
    xyz, ch = np.column_stack([las.x, las.y, las.z]), np.asarray(las.scanner_channel)
    half = len(xyz) // 2
    split = [_write(tmp_path / "strip_1a.laz", xyz[:half], 1, ch[:half]), *paths[1:],
             _write(tmp_path / "strip_1b.laz", xyz[half:], 1, ch[half:])]
    with caplog.at_level(logging.WARNING, logger="georefine.evaluation.clouds"):
        _, got = scan_clouds_with_pairs(split, chunk_points=40_000)
    assert "reading the point clouds again" in caplog.text
    _assert_same_pairs(got, strip_pair_differences(read), atol=1e-6)


def test_no_points_is_an_error_not_a_matrix_of_nan(tmp_path):
    with pytest.raises(InputError, match="no points to compare"):
        StripPairStream().pairs()
    with pytest.raises(InputError, match="no points to compare"):
        strip_pair_differences({})
    with pytest.raises(InputError, match="no points to compare"):
        strip_pair_differences({(1, 0): np.zeros((0, 3))})
    one = strip_pair_differences({(1, 0): _block(7)[(1, 0)]})  # one strip: no pair, and no NaN either
    assert one.strips == (1,) and one.pairs == ()


# -- the records and files -------------------------------------------------------------------------


def test_the_record_reads_back_from_json(pairs, tmp_path):
    write_json(tmp_path / "pairs.json", pairs.to_dict())
    d = json.loads((tmp_path / "pairs.json").read_text())
    back = StripPairDifferences.from_dict(d)
    assert back == pairs and back.to_dict() == d
    assert d["pairs"][1] == {"strip_a": 1, "strip_b": 3, "cells": 0, "median_mm": None, "p95_mm": None,
                             "rms_mm": None, "signed_median_mm": None}
    assert list(d) == ["cell_size_m", "min_cells", "strips", "pairs"] and d["min_cells"] == MIN_PAIR_CELLS


def test_the_run_evaluation_holds_the_pairs_and_old_summaries_still_read(pairs, tmp_path):
    figures = StripPairFigures(pairs, "gil/strip_pairs.csv", "gil/strip_pairs.png")
    sd = StripDifferenceFigures(10, 0.001, 0.002, 0.001, "gil/strip_differences.png")
    evaluation = RunEvaluation("truth", strip_differences={"G/I/L": sd}, strip_pairs={"G/I/L": figures})
    write_json(tmp_path / "summary.json", evaluation.to_dict())
    back = RunEvaluation.read(tmp_path / "summary.json")
    assert back == evaluation and back.strip_pairs["G/I/L"].pairs.pair(2, 3).median_mm == pairs.pair(2, 3).median_mm
    assert back.to_dict() == json.loads((tmp_path / "summary.json").read_text())
    old = evaluation.to_dict()
    del old["strip_pairs"]
    assert RunEvaluation.from_dict(old).strip_pairs == {}
    assert "strip_pairs" not in RunEvaluation("truth").to_dict()
    cloud = CloudEvaluation(sd, strip_pairs=figures)
    assert CloudEvaluation.from_dict(cloud.to_dict()) == cloud
    assert CloudEvaluation.from_dict(CloudEvaluation(sd).to_dict()).strip_pairs is None


def test_the_csv_has_a_row_per_pair_and_empty_figures_without_overlap(pairs, tmp_path):
    path = write_pairs_csv(tmp_path / "strip_pairs.csv", pairs)
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == CSV_HEADER == ("strip_a", "strip_b", "cells", "median_mm", "p95_mm", "rms_mm",
                                            "signed_median_mm")
    assert len(rows) == 1 + len(pairs.pairs) == 11
    for row, p in zip(rows[1:], pairs.pairs):
        assert row[:3] == [str(p.strip_a), str(p.strip_b), str(p.cells)]
        if p.measured:
            assert [float(v) for v in row[3:]] == pytest.approx(
                [p.median_mm, p.p95_mm, p.rms_mm, p.signed_median_mm], abs=0.005)
        else:
            assert row[3:] == ["", "", "", ""]
    row = next(r for r in rows[1:] if r[:2] == ["2", "3"])
    assert abs(float(row[6]) - 28.0) < 0.6


def test_the_matrix_is_written_with_readable_numbers(pairs, tmp_path):
    from PIL import Image

    path = write_pairs_png(tmp_path / "strip_pairs.png", pairs, title="test")
    with Image.open(path) as im:
        min_px = float(im.text[MIN_FONT_KEY])
        width, height = im.size
    assert min_px >= 9.0 * 110 / 72 - 0.05  # 9 pt at the saved 110 dpi
    assert width > 400 and height > 400
    assert not list(tmp_path.glob(".*.part"))  # written under a temporary name, renamed


def test_the_evaluation_of_a_run_cloud_writes_the_pairs(files, tmp_path):
    from georefine.workflows.evaluate import evaluate_cloud

    paths, read = files
    project, run = tmp_path / "project", tmp_path / "run"
    project.mkdir()
    (run / "points").mkdir(parents=True)
    for f in paths:
        (run / "points" / f.name).write_bytes(f.read_bytes())
    result = evaluate_cloud(project, run, "G/I/L", scheduler="sync", chunk_points=30_000)
    assert result.strip_pairs is not None
    assert (result.strip_pairs.csv, result.strip_pairs.matrix) == ("gil/strip_pairs.csv", "gil/strip_pairs.png")
    _assert_same_pairs(result.strip_pairs.pairs, strip_pair_differences(read), atol=1e-6)
    with open(run / "evaluation" / result.strip_pairs.csv, newline="", encoding="utf-8") as fh:
        assert len(list(csv.reader(fh))) == 11
    assert (run / "evaluation" / result.strip_pairs.matrix).is_file()
    assert CloudEvaluation.from_dict(json.loads(json.dumps(result.to_dict()))).strip_pairs == result.strip_pairs


def test_the_report_shows_the_pairs_before_and_after(pairs, tmp_path):
    import html
    from dataclasses import replace

    from georefine.evaluation.report import write_report
    from georefine.io.run_metrics import WorkflowMetrics

    run = tmp_path / "run"
    (run / "evaluation" / "gi").mkdir(parents=True)
    (run / "evaluation" / "gil").mkdir()
    after = StripPairDifferences(pairs.strips, tuple(
        replace(p, median_mm=p.median_mm / 10, p95_mm=p.p95_mm / 10, signed_median_mm=p.signed_median_mm / 10)
        if p.measured else p for p in pairs.pairs), pairs.min_cells)
    clouds = {}
    for label, sub, figures in (("G/I", "gi", pairs), ("G/I/L", "gil", after)):
        write_pairs_png(run / "evaluation" / sub / "strip_pairs.png", figures, title=label)
        clouds[label] = StripPairFigures(figures, f"{sub}/strip_pairs.csv", f"{sub}/strip_pairs.png")
    sd = StripDifferenceFigures(10, 0.001, 0.002, 0.001, "gil/strip_differences.png")
    write_json(run / "metrics.json", WorkflowMetrics(1.4e9, (1, 2, 3, 4, 5), {s: (1.4e9, 1.4e9 + 9) for s in STRIPS})
               .to_dict())
    write_json(run / "evaluation" / "summary.json",
               RunEvaluation("truth", strip_differences={"G/I/L": sd}, strip_pairs=clouds).to_dict())
    page = html.unescape(write_report(run).read_text())
    p, q = pairs.pair(2, 3), after.pair(2, 3)
    assert (f"<td>2 – 3</td><td>{p.cells:,}</td><td>{p.median_mm:.1f}</td><td>{p.p95_mm:.1f}</td>"
            f"<td>{p.signed_median_mm:.1f}</td><td>{q.cells:,}</td><td>{q.median_mm:.1f}</td>") in page
    assert "<td>1 – 3</td>" not in page and "<td>1 – 5</td>" not in page  # no figures: not in the table
    assert "G/I/L: 5 further pair(s) of strips do not overlap or share fewer than 50 planar cells." in page
    assert page.count('alt="strip pairs G/I') == 2
