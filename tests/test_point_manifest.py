"""The manifest of the point files Georefine wrote into a folder, and the evaluations that read it."""

from __future__ import annotations

import json
import logging

import pytest

from georefine.errors import InputError
from georefine.io.las import point_files
from georefine.io.point_manifest import MANIFEST, manifest_files, record_point_files


def test_a_folder_with_a_manifest_gives_its_files_and_names_the_others(tmp_path, caplog):
    a, b = tmp_path / "strip_1.laz", tmp_path / "strip_2.laz"
    for f in (a, b):
        f.write_bytes(b"x" * 10)
    record_point_files([a], [5])
    record_point_files([b], [7])  # a second writer merges
    entries = json.loads((tmp_path / MANIFEST).read_text())["files"]
    assert [(e["file"], e["points"]) for e in entries] == [("strip_1.laz", 5), ("strip_2.laz", 7)]
    (tmp_path / "old_strip.laz").write_bytes(b"stale")
    with caplog.at_level(logging.WARNING, logger="georefine.io.point_manifest"):
        assert point_files([tmp_path]) == [a, b]
    assert "left out 1 LAS/LAZ file(s)" in caplog.text and "old_strip.laz" in caplog.text
    assert point_files([tmp_path / "old_strip.laz"]) == [tmp_path / "old_strip.laz"]  # named: used
    b.unlink()
    with pytest.raises(InputError, match="strip_2.laz: a point file the manifest lists is missing"):
        manifest_files(tmp_path)


def test_a_folder_without_a_manifest_is_read_whole(tmp_path):
    for name in ("b.laz", "a.las", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert manifest_files(tmp_path) is None
    assert point_files([tmp_path]) == [tmp_path / "a.las", tmp_path / "b.laz"]
