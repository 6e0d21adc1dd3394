"""Damaged photo inputs through ``georefine check`` and ``georefine coadjust`` (the photo part of the
table in test_bad_inputs.py, in a file of its own so that it runs beside it).

Every case must give, from both commands: exit code 2, one line on stderr naming the file and
the field, no traceback, and no output folder.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from cli_helpers import run_georefine as _georefine
from georefine.sim.scenarios import simulate_project


def _lines(p: Path) -> list[str]:
    return p.read_text().splitlines()


def _write(p: Path, lines: list[str]) -> None:
    p.write_text("\n".join(lines) + "\n")


def _truncate(rel: str, fraction: float):
    def edit(p: Path) -> None:
        data = (p / rel).read_bytes()
        (p / rel).write_bytes(data[: int(len(data) * fraction)])
    return edit


def _remove(rel: str):
    return lambda p: (p / rel).unlink()


def _edit_line(rel: str, k: int, fn):
    """Replace the ``k``-th data line (after the CSV header) of ``rel``."""
    def edit(p: Path) -> None:
        lines = _lines(p / rel)
        lines[k + 1] = fn(lines[k + 1])
        _write(p / rel, lines)
    return edit


def _set_field(line: str, i: int, value: str) -> str:
    f = line.split(",")
    f[i] = value
    return ",".join(f)


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
    gcp = _lines(p / "photos/gcp.csv")
    check = next(line.split(",")[0] for line in gcp[1:] if line.endswith(",check"))
    rows = _lines(p / "photos/image_points.csv")
    ours = [r for r in rows[1:] if r.split(",")[1] == check]
    _write(p / "photos/image_points.csv", [rows[0], *(r for r in rows[1:] if r.split(",")[1] != check), ours[0]])


PHOTO_CASES = [
    ("photo cut to 40 %", _truncate(PHOTO, 0.4), ("IMG_01001.jpg", "incomplete", "cut short")),
    ("photo missing", _remove(PHOTO), ("eop.csv", "IMG_01001.jpg", "not found")),
    ("photo not an image", lambda p: (p / PHOTO).write_text("not a picture"), ("IMG_01001.jpg", "decode")),
    ("photo of another size", _resize_photo, ("IMG_01001.jpg", "600 x 400", "300 x 200")),
    ("eop text x", _edit_line("photos/eop.csv", 2, lambda s: _set_field(s, 1, "east")), ("eop.csv", "'x'")),
    ("eop unknown camera", _edit_line("photos/eop.csv", 2, lambda s: _set_field(s, 13, "tele")),
     ("eop.csv", "camera", "tele")),
    ("camera focal 0", lambda p: (p / "photos/cameras.yaml").write_text(
        (p / "photos/cameras.yaml").read_text().replace("fx_px: 800.0", "fx_px: 0.0")), ("cameras.yaml", "fx_px")),
    ("check point in one photo", _single_ray_check_point, ("gcp.csv", "check point", "two images")),
    ("measurement outside the photo", _edit_line("photos/image_points.csv", 0, lambda s: _set_field(s, 2, "900")),
     ("image_points.csv", "col", "600")),
]


@pytest.mark.parametrize("name, edit, words", PHOTO_CASES, ids=[c[0] for c in PHOTO_CASES])
def test_a_damaged_photo_input_is_one_line_and_exit_2_from_check_and_coadjust(block, tmp_path, name, edit, words):
    p = tmp_path / "p"
    shutil.copytree(block, p)
    edit(p)
    for cmd in (["check", str(p)], _coadjust(p, tmp_path / "o")):
        run = _georefine(*cmd)
        err = run.stderr.strip()
        assert run.returncode == 2, (name, cmd[0], run.returncode, run.stderr[-2000:])
        assert "Traceback" not in run.stderr and err.count("\n") == 0 and err.startswith("error: "), (name, err)
        for w in words:
            assert w in err, (name, cmd[0], w, err)
    assert not (tmp_path / "o").exists(), name


def test_check_reports_the_photo_block(block):
    run = _georefine("check", str(block))
    assert run.returncode == 0, run.stderr
    assert "photos: 30 images (1 camera), 3 control and 3 check points" in run.stdout
