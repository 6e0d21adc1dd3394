"""Point density and strip overlap (evaluation/coverage.py) and the facts the report's figures carry (evaluation/figures.py)."""

from __future__ import annotations

import numpy as np
import pytest

from browser_helpers import png_facts
from georefine.evaluation.cell_moments import cell_keys, cell_moments
from georefine.evaluation.coverage import CellCounts, CoverageMap, coverage_map, write_coverage_png
from georefine.evaluation.figures import AXES_KEY, MIN_FONT_KEY, save_png
from georefine.evaluation.strip_differences import LAYER_CODE, StripDifferenceStream


def _strips(seed: int = 5):
    """Two strips over flat ground, 50 m by 20 m each, overlapping by half: 20 and 10 points/m²."""
    rng = np.random.default_rng(seed)
    a = np.column_stack([rng.uniform(0, 50, 20_000), rng.uniform(0, 20, 20_000), rng.normal(0, 0.01, 20_000)])
    b = np.column_stack([rng.uniform(25, 75, 10_000), rng.uniform(0, 20, 10_000), rng.normal(0, 0.01, 10_000)])
    return a, b


def _truth(a, b):
    cells = {}
    for k, x in enumerate((a, b)):
        ij = np.floor(x[:, :2]).astype(np.int64)
        for key, n in zip(*np.unique(cell_keys(ij), return_counts=True)):
            c = cells.setdefault(int(key), [0, set()])
            c[0] += int(n)
            c[1].add(k)
    return cells


@pytest.mark.parametrize("chunks", [1, 7])
def test_the_stream_counts_every_point_and_strip_of_each_cell_whatever_the_chunks(chunks):
    a, b = _strips()
    stream = StripDifferenceStream(1.0)
    for part_a, part_b in zip(np.array_split(a, chunks), np.array_split(b, chunks)):
        stream.add([cell_moments(part_a, 1.0, 0), cell_moments(part_b, 1.0, LAYER_CODE + 1)], len(part_a) + len(part_b))
    m = stream.coverage()
    truth = _truth(a, b)
    assert m.points.sum() == 30_000 and np.count_nonzero(m.points) == len(truth)
    rows, cols = m.points.shape
    for key, (n, strips) in list(truth.items())[::37]:
        i, j = key >> 32, (key & 0xFFFFFFFF) - (1 << 31)
        r, c = int(round(m.y1 - j - 1)), int(round(i - m.x0))
        assert m.points[r, c] == n and m.strips[r, c] == len(strips)
    s = m.summary()
    assert s["area_km2"] == pytest.approx(75 * 20 / 1e6)
    assert s["overlap_share"] == pytest.approx(1 / 3) and s["max_strips"] == 2
    assert s["density_median_per_m2"] == pytest.approx(20.0, abs=2.0)  # the half seen from strip 1 only
    # The 95th percentile of all cells is the 85th of the third with both strips (Poisson, 30 points/m²).
    assert s["density_p95_per_m2"] == pytest.approx(30.0 + 1.036 * np.sqrt(30.0), abs=2.0)


def test_merged_counts_add_the_rows_of_a_cell():
    m = CellCounts.merge([CellCounts(np.array([5, 1]), np.array([2, 3])), None,
                          CellCounts(np.array([1, 9]), np.array([4, 1]))])
    assert m.keys.tolist() == [1, 5, 9] and m.n.tolist() == [7, 2, 1]
    assert len(CellCounts.merge([])) == 0


def test_coarse_cells_keep_the_points_and_the_density_of_the_covered_part():
    points = np.zeros((4, 6), np.int64)
    points[:, :3] = 10  # 10 points/m² on the western half; the eastern half empty
    strips = (points > 0).astype(np.uint8)
    m = CoverageMap(points, strips, 100.0, 200.0, 1.0)
    c = m.coarse(4)  # two columns of 4 m cells, the first half covered
    assert c.points.sum() == points.sum() and c.cell_size_m == 4.0 and c.points.shape == (1, 2)
    assert c.density()[0, 0] == pytest.approx(10.0)  # 120 points on the 12 m² with points, not on 16 m²
    assert np.isnan(c.density()[0, 1]) and c.strips.tolist() == [[1, 0]]
    assert (c.x0, c.y1) == (100.0, 200.0)


def test_an_empty_coverage_has_no_figures():
    m = coverage_map(CellCounts.empty(), {}, 1.0)
    s = m.summary()
    assert s["area_km2"] == 0.0 and np.isnan(s["density_median_per_m2"]) and s["max_strips"] == 0


@pytest.mark.parametrize("what", ["density", "overlap"])
def test_the_coverage_maps_are_drawn_at_equal_aspect_with_readable_text(tmp_path, what):
    a, b = _strips()
    stream = StripDifferenceStream(1.0)
    stream.add([cell_moments(a, 1.0, 0), cell_moments(b, 1.0, LAYER_CODE)], 30_000)
    path = write_coverage_png(tmp_path / f"{what}.png", stream.coverage(), what, epsg=25832,
                              sites=[("S1", 30.0, 10.0)])
    facts = png_facts(path.read_bytes())
    equal, total = map(int, facts[AXES_KEY].split("/"))
    assert total >= 1 and equal == total and float(facts[MIN_FONT_KEY]) >= 16.0  # 8 pt at 150 dpi
    with pytest.raises(ValueError, match="expected one of"):
        write_coverage_png(tmp_path / "x.png", stream.coverage(), "height")


def test_save_png_records_the_smallest_text_and_the_axes_at_equal_aspect(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (map_ax, plot_ax) = plt.subplots(1, 2)
    fig.colorbar(map_ax.imshow(np.eye(3)), ax=map_ax)  # imshow: equal aspect; the colour bar is not counted
    plot_ax.plot([0, 1], [0, 2])
    plot_ax.set_title("small", fontsize=6)
    plot_ax.text(0.5, 0.5, "  ", fontsize=2)  # blank text is not text a reader has to read
    path = save_png(fig, tmp_path / "f.png", dpi=120)
    plt.close(fig)
    facts = png_facts(path.read_bytes())
    assert facts[AXES_KEY] == "1/2" and float(facts[MIN_FONT_KEY]) == pytest.approx(6 * 120 / 72, abs=0.05)
    assert not list(tmp_path.glob("*.part"))
    with pytest.raises(ValueError, match="not a PNG"):
        png_facts(b"GIF89a")
