"""Damaged photo inputs through ``georefine check`` and ``georefine coadjust`` (the photo part of the
table in test_bad_inputs.py, in a file of its own so that it runs beside it).

Every case must give, from both commands: exit code 2, one line on stderr naming the file and
the field, no traceback, and no output folder.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from bad_input_helpers import assert_refused, edit_line, lines, remove, set_field, truncate, write
from cli_helpers import run_georefine as _georefine
from georefine.sim.scenarios import simulate_project

# Photo inputs: a small block (600 x 400 px photos), consumed by the co-adjustment.
SMALL_BLOCK = ["scene.length_m=260", "scanner.pulse_rate_hz=5000", "scanner.line_rate_hz=100",
               "photos.camera.width_px=600", "photos.camera.height_px=400", "photos.camera.focal_px=800",
               "photos.control_points=3", "photos.check_points=3"]
PHOTO = "photos/IMG_01001.jpg"


@pytest.fixture(scope="module")
def block(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bad_block") / "block"
    simulate_project("block", out, seed=11, overrides=SMALL_BLOCK)
    return out


def _coadjust(p: Path, out: Path) -> list[str]:
    return ["coadjust", str(p), "--points", str(p / "truth"), "--out", str(out), "--case", "1"]


def _resize_photo(p: Path) -> None:
    import cv2

    image = cv2.imread(str(p / PHOTO))
    cv2.imwrite(str(p / PHOTO), cv2.resize(image, (300, 200)))


def _single_ray_check_point(p: Path) -> None:
    """Keep one measurement of the first check point."""
    gcp = lines(p / "photos/gcp.csv")
    check = next(line.split(",")[0] for line in gcp[1:] if line.endswith(",check"))
    rows = lines(p / "photos/image_points.csv")
    ours = [r for r in rows[1:] if r.split(",")[1] == check]
    write(p / "photos/image_points.csv", [rows[0], *(r for r in rows[1:] if r.split(",")[1] != check), ours[0]])


PHOTO_CASES = [
    ("photo cut to 40 %", truncate(PHOTO, 0.4), ("IMG_01001.jpg", "incomplete", "cut short")),
    ("photo missing", remove(PHOTO), ("eop.csv", "IMG_01001.jpg", "not found")),
    ("photo not an image", lambda p: (p / PHOTO).write_text("not a picture"), ("IMG_01001.jpg", "decode")),
    ("photo of another size", _resize_photo, ("IMG_01001.jpg", "600 x 400", "300 x 200")),
    ("eop text x", edit_line("photos/eop.csv", 2, lambda s: set_field(s, 1, "east", ",")), ("eop.csv", "'x'")),
    ("eop unknown camera", edit_line("photos/eop.csv", 2, lambda s: set_field(s, 13, "tele", ",")),
     ("eop.csv", "camera", "tele")),
    ("camera focal 0", lambda p: (p / "photos/cameras.yaml").write_text(
        (p / "photos/cameras.yaml").read_text().replace("fx_px: 800.0", "fx_px: 0.0")), ("cameras.yaml", "fx_px")),
    ("check point in one photo", _single_ray_check_point, ("gcp.csv", "check point", "two images")),
    ("measurement outside the photo", edit_line("photos/image_points.csv", 0, lambda s: set_field(s, 2, "900", ",")),
     ("image_points.csv", "col", "600")),
]


@pytest.mark.parametrize("name, edit, words", PHOTO_CASES, ids=[c[0] for c in PHOTO_CASES])
def test_a_damaged_photo_input_is_one_line_and_exit_2_from_check_and_coadjust(block, tmp_path, name, edit, words):
    p = tmp_path / "p"
    shutil.copytree(block, p)
    edit(p)
    assert_refused(name, [["check", str(p)], _coadjust(p, tmp_path / "o")], words, tmp_path / "o")


def test_check_reports_the_photo_block(block):
    run = _georefine("check", str(block))
    assert run.returncode == 0, run.stderr
    assert "photos: 30 images (1 camera), 3 control and 3 check points" in run.stdout
