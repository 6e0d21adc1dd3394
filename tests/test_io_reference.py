"""Tests of georefine.io.reference (reference-surface CSV)."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.io.reference import (
    ReferenceSurfaces,
    read_reference_surfaces,
    write_reference_surfaces,
)

HEADER = "surface_id,point_id,x,y,z\n"


def _surfaces(seed: int, n_surfaces: int = 6) -> ReferenceSurfaces:
    rng = np.random.default_rng(seed)
    sid, pid, xyz = [], [], []
    for s in range(n_surfaces):
        centre = np.array([691_000.0, 5_334_000.0, 600.0]) + rng.uniform(-1000, 1000, 3)
        corners = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], float)
        for k, c in enumerate(corners):
            sid.append(f"roof_{s}")
            pid.append(f"P{k + 1}")
            xyz.append(centre + c + rng.normal(scale=0.005, size=3))
    return ReferenceSurfaces(np.array(sid), np.array(pid), np.array(xyz))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_round_trip(tmp_path, seed):
    surfaces = _surfaces(seed)
    back = read_reference_surfaces(write_reference_surfaces(tmp_path / "ref.csv", surfaces))
    np.testing.assert_array_equal(back.surface_id, surfaces.surface_id)
    np.testing.assert_array_equal(back.point_id, surfaces.point_id)
    np.testing.assert_allclose(back.xyz, surfaces.xyz, atol=5e-5 + 1e-9)
    assert back.surface_ids() == [f"roof_{s}" for s in range(6)]
    assert back.points_of("roof_2").shape == (4, 3)


def test_comments_and_blank_lines_keep_line_numbers(tmp_path):
    path = tmp_path / "ref.csv"
    path.write_text("# surveyed 2024-05-17\n" + HEADER + "a,1,0,0,0\n\na,2,1,0,0\n# note\na,3,x,1,0\n")
    with pytest.raises(InputError) as info:
        read_reference_surfaces(path)
    assert info.value.line == 7 and info.value.field == "x" and "'x'" in str(info.value)


def test_surface_with_two_points_names_surface_and_lines(tmp_path):
    path = tmp_path / "ref.csv"
    path.write_text(HEADER + "a,1,0,0,0\na,2,1,0,0\na,3,0,1,0\nb,1,5,5,0\nb,2,6,5,0\n")
    with pytest.raises(InputError) as info:
        read_reference_surfaces(path)
    msg = str(info.value)
    assert "ref.csv" in msg and "surface 'b'" in msg and "lines 5, 6" in msg and "found 2 points" in msg


def test_collinear_surface(tmp_path):
    path = tmp_path / "ref.csv"
    path.write_text(HEADER + "line,1,0,0,0\nline,2,1,1,1\nline,3,2,2,2\nline,4,3,3,3\n")
    with pytest.raises(InputError, match=r"points of surface 'line' are collinear \(lines 2, 3, 4, 5\)"):
        read_reference_surfaces(path)


def test_duplicate_point(tmp_path):
    path = tmp_path / "ref.csv"
    path.write_text(HEADER + "a,1,0,0,0\na,2,1,0,0\na,3,0,1,0\na,2,1,1,0\n")
    with pytest.raises(InputError, match=r"line 5, field 'point_id': duplicate point '2' of surface 'a'.*line 3"):
        read_reference_surfaces(path)


def test_wrong_header_and_field_count(tmp_path):
    path = tmp_path / "ref.csv"
    path.write_text("id,x,y,z\n")
    with pytest.raises(InputError, match=r"line 1: unexpected header"):
        read_reference_surfaces(path)
    path.write_text(HEADER + "a,1,0,0\n")
    with pytest.raises(InputError, match=r"line 2: wrong number of fields"):
        read_reference_surfaces(path)


def test_writer_checks_surfaces(tmp_path):
    bad = ReferenceSurfaces(np.array(["a", "a"]), np.array(["1", "2"]), np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]])
    with pytest.raises(InputError, match="too few points"):
        write_reference_surfaces(tmp_path / "x.csv", bad)
    assert not (tmp_path / "x.csv").exists()
