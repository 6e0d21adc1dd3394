"""COLMAP's own tools on a model Georefine exported (used where ``colmap`` is installed)."""

from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

import numpy as np
import pytest

from georefine.io.colmap import read_model
from georefine.workflows.colmap_export import MODEL_ALIGNER


def _colmap(*args: str) -> str:
    proc = subprocess.run(["colmap", *args], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, (args, proc.stdout[-2000:], proc.stderr[-2000:])
    return proc.stdout + proc.stderr


def colmap_checks(folder: Path, work: Path, mean_reprojection_error_px: float) -> dict:
    """COLMAP 3.8's model_analyzer, image_undistorter and model_aligner on an exported model:
    each exits 0, the analyser's mean reprojection error is Georefine's (1 %), the aligned
    model's camera centres are the reference's (3 cm). Returns the figures."""
    out = _colmap("model_analyzer", "--path", str(folder))
    found = float(re.search(r"Mean reprojection error: ([0-9.]+)px", out).group(1))
    assert found == pytest.approx(mean_reprojection_error_px, rel=0.01), (found, mean_reprojection_error_px)
    _colmap("image_undistorter", "--image_path", str(folder / "images"), "--input_path", str(folder),
            "--output_path", str(work / "undistorted"), "--max_image_size", "400")
    rec = read_model(folder)
    undistorted = sorted(f.name for f in (work / "undistorted" / "images").iterdir())
    assert undistorted == sorted(rec.image(i).name for i in rec.reg_image_ids())
    (work / "aligned").mkdir()
    _colmap(*shlex.split(MODEL_ALIGNER.format(model=shlex.quote(str(folder)),
                                              out=shlex.quote(str(work / "aligned"))))[1:])
    aligned = read_model(work / "aligned")
    ref = {r.split()[0]: np.array(r.split()[1:], float)
           for r in (folder / "reference_images.txt").read_text().splitlines()}
    d = np.array([np.linalg.norm(aligned.image(i).projection_center() - ref[aligned.image(i).name])
                  for i in aligned.reg_image_ids()])
    assert len(d) == len(ref) and d.max() < 0.03, d
    return {"model_analyzer_px": found, "aligned_max_m": float(d.max())}
