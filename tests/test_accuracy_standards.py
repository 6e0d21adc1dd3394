"""ASPRS Positional Accuracy Standards (Edition 2, 2023) and NSSDA figures (adjustment/accuracy_standards.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from georefine.adjustment.accuracy_standards import PositionalAccuracy, positional_accuracy, surface_vertical_errors
from georefine.evaluation.reference_planes import PlaneObservation, ReferencePlane


def _errors_with_rms(rng, n, rms):
    """``(n, 3)`` errors whose RMS per axis is exactly ``rms``."""
    e = rng.normal(size=(n, 3))
    return e / np.sqrt(np.mean(e**2, axis=0)) * np.asarray(rms)


def test_edition_2_includes_the_check_points_survey_and_nssda_gives_95_percent():
    rng = np.random.default_rng(1)
    e = _errors_with_rms(rng, 30, (0.03, 0.03, 0.05))
    a = positional_accuracy(e, np.full((30, 3), 0.01))
    assert a.rmse_h1_m == pytest.approx(math.sqrt(2) * 0.03)
    assert a.rmse_h2_m == pytest.approx(math.sqrt(2) * 0.01)
    assert a.rmse_h_m == pytest.approx(math.sqrt(0.03**2 * 2 + 0.01**2 * 2))
    assert a.rmse_v1_m == pytest.approx(0.05) and a.rmse_v_m == pytest.approx(math.hypot(0.05, 0.01))
    assert a.rmse_3d_m == pytest.approx(math.hypot(a.rmse_h_m, a.rmse_v_m))
    assert a.mean_v_m == pytest.approx(float(np.mean(e[:, 2])))
    assert a.nssda_horizontal_95_m == pytest.approx(1.7308 * a.rmse_h1_m) and "1.7308" in a.nssda_rule
    assert a.nssda_vertical_95_m == pytest.approx(1.96 * 0.05)
    assert a.enough_checkpoints and not positional_accuracy(e[:29]).enough_checkpoints
    assert PositionalAccuracy.from_dict(a.to_dict()) == a


def test_unequal_horizontal_errors_take_the_circular_approximation():
    e = _errors_with_rms(np.random.default_rng(2), 40, (0.01, 0.05, 0.02))
    a = positional_accuracy(e)
    assert a.rmse_h2_m == 0.0 and a.rmse_h_m == pytest.approx(math.hypot(0.01, 0.05))
    assert a.nssda_horizontal_95_m == pytest.approx(2.4477 * 0.5 * (0.01 + 0.05)) and "circular" in a.nssda_rule


def test_vertical_only_and_no_check_points():
    a = positional_accuracy(np.array([0.01, -0.02, 0.03]))
    assert a.rmse_h_m is None and a.nssda_horizontal_95_m is None and a.n_checkpoints == 3
    assert a.rmse_v_m == pytest.approx(math.sqrt((0.01**2 + 0.02**2 + 0.03**2) / 3))
    assert PositionalAccuracy.from_dict(a.to_dict()) == a
    empty = positional_accuracy(np.zeros((0, 3)))
    assert empty.n_checkpoints == 0 and empty.rmse_v_m is None


def _plane(sid, slope, rms=0.004, n_points=16):
    normal = np.array([-slope, 0.0, 1.0]) / math.hypot(slope, 1.0)
    u = np.cross([0.0, 1.0, 0.0], normal)
    u /= np.linalg.norm(u)
    return ReferencePlane(sid, np.zeros(3), normal, u, np.cross(normal, u), np.zeros((3, 2)), rms, n_points)


def test_level_reference_surfaces_are_vertical_check_points_and_steep_ones_are_not():
    planes = [_plane("flat", 0.0), _plane("gentle", 0.08), _plane("roof", 0.5), _plane("facade", 1e6)]
    obs = [PlaneObservation(p.surface_id, s, 0, 100, d, 0.01) for p in planes for s, d in ((1, 0.010), (2, 0.020))]
    errors, survey, ids = surface_vertical_errors(obs, planes)
    assert ids == ["flat", "gentle"]
    np.testing.assert_allclose(errors, [0.015, 0.015 * math.hypot(0.08, 1.0)])  # along the normal -> vertical
    np.testing.assert_allclose(survey, [0.001, 0.001])  # the fit residual over sqrt(16)
