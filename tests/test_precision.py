"""The attitude sigma per pass of G/I and G/I/L, and the angles the planes add little to."""

from __future__ import annotations

import numpy as np
import pytest

from georefine.io.run_metrics import PassPrecision
from georefine.workflows.precision import LITTLE_GAIN, pass_precision, precision_lines


class _Result:
    """The two fields of a GnssImuResult that pass_precision reads."""

    def __init__(self, t, sigma_mdeg):
        self.sigma_time = np.asarray(t, float)
        self.sigma_rph_rad = np.radians(np.asarray(sigma_mdeg, float) / 1e3)


def test_sigma_per_pass_is_the_rms_over_the_strip():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 300.0, 5.0)
    gi_sig = rng.uniform(2.0, 20.0, (t.size, 3))
    gil_sig = gi_sig * [0.9, 0.3, 0.1]
    passes = pass_precision(_Result(t, gi_sig), _Result(t, gil_sig), {1: (50.0, 120.0), 2: (180.0, 250.0)})
    assert [p.strip for p in passes] == [1, 2]
    ts = np.linspace(50.0, 120.0, 71)  # every second, the sigma interpolated between their knots
    expect = np.sqrt(np.mean(np.column_stack([np.interp(ts, t, gi_sig[:, i]) for i in range(3)]) ** 2, axis=0))
    np.testing.assert_allclose(passes[0].gi_sigma_mdeg, expect, rtol=1e-12)
    np.testing.assert_allclose(np.divide(passes[1].gil_sigma_mdeg, passes[1].gi_sigma_mdeg), [0.9, 0.3, 0.1], rtol=0.2)


def test_the_summary_names_the_angles_the_planes_add_little_to():
    passes = (PassPrecision(1, (6.4, 7.0, 16.0), (4.6, 1.2, 1.7)), PassPrecision(2, (4.0, 4.0, 40.0), (1.0, 3.9, 1.8)))
    lines = precision_lines(passes)
    assert lines[0].startswith("  attitude sigma per pass, G/I -> G/I/L (mdeg): strip 1 roll 6.40 -> 4.60")
    assert "strip 2 roll 4.00 -> 1.00, pitch 4.00 -> 3.90, yaw 40.00 -> 1.80" in lines[0]
    # 4.6 / 6.4 = 0.72 and 3.9 / 4.0 = 0.98 are above the threshold; the rest is well below.
    assert LITTLE_GAIN == pytest.approx(0.7)
    assert "strip 1 roll (0.72x), strip 2 pitch (0.97x)" in lines[1] and "rests on the GNSS/IMU" in lines[1]
    assert len(precision_lines(passes[:1] + (PassPrecision(2, (4.0, 4.0, 40.0), (1.0, 1.0, 1.8)),))) == 2
    assert len(precision_lines((PassPrecision(1, (4.0, 4.0, 40.0), (1.0, 1.0, 1.8)),))) == 1
    assert precision_lines(()) == []


def test_a_pass_without_posterior_reads_back_as_nan(tmp_path):
    import json

    from georefine.io.files import write_json

    record = PassPrecision(1, (float("nan"),) * 3, (1.0, 1.25, 1.75))
    write_json(tmp_path / "p.json", record.to_dict())
    d = json.loads((tmp_path / "p.json").read_text())
    assert d["gi_sigma_mdeg"] == [None, None, None]
    back = PassPrecision.from_dict(d)
    assert np.all(np.isnan(back.gi_sigma_mdeg)) and back.gil_sigma_mdeg == (1.0, 1.25, 1.75)
    # no posterior: no sigma to compare, and nothing named as resting on the GNSS/IMU
    assert len(precision_lines((record,))) == 1
