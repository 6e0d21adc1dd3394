"""The run's typed records and the report built from them (no simulation: records made up here).

The records of a real run are checked in tests/test_workflow_gil.py (``metrics.json`` of a
run, the demo's ``metrics.json`` and ``summary.json``); here every branch of the JSON form
(NaN as ``null``, optional parts) and the page the report renders from the records.
"""

from __future__ import annotations

import html
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from georefine.errors import InputError
from georefine.evaluation.report import summary_rows, summary_verdicts, write_report
from georefine.evaluation.summary import (
    EvaluationPlots,
    ReferencePlaneFigures,
    RunEvaluation,
    SolutionFigures,
    StripDifferenceFigures,
    SurfaceFigures,
    TrajectoryFigures,
)
from georefine.io.files import write_json
from georefine.io.run_metrics import (
    AdjustmentReport,
    FilterSummary,
    FrameOrigin,
    LidarTimeOffset,
    OuterIteration,
    PassPrecision,
    PointsWritten,
    WorkflowMetrics,
    read_adjustment_report,
    write_adjustment_report,
)


def _figures(rng) -> TrajectoryFigures:
    return TrajectoryFigures(*(float(v) for v in rng.uniform(1.0, 30.0, 3)), float(rng.uniform(0.01, 0.1)))


def _records(seed: int) -> tuple[WorkflowMetrics, RunEvaluation]:
    rng = np.random.default_rng(seed)
    metrics = WorkflowMetrics(
        t0_gps=1.4e9, strips=(1, 2), strip_time_gps={1: (1.4e9 + 10.0, 1.4e9 + 40.5), 2: (1.4e9 + 60.0, 1.4e9 + 91.25)},
        outer_iterations=tuple(
            OuterIteration(i, int(rng.integers(10_000, 20_000)), int(rng.integers(500, 900)), int(rng.integers(900, 5000)),
                           int(rng.integers(100, 500)), float(rng.uniform(0, 20)), float(rng.uniform(0, 0.01)), 0,
                           {"strip1_nadir": 7, "strip2_nadir": 9}, 0.25 if i == 1 else 0.1)
            for i in (1, 2)),
        points=(PointsWritten(1, "strip_1.laz", 1234, 0), PointsWritten(2, "strip_2.laz", 5678, 3)),
        resumed=("gi",), timings_s={"read": 0.5, "gi_adjustment": 2.25, "final_georeferencing": 1.0},
        pass_precision=(PassPrecision(1, (3.5, 3.25, 16.5), (1.0, 1.25, 1.75)),
                        PassPrecision(2, (4.0, 4.25, 40.5), (1.0, 1.25, 1.75))),
    )
    sol = {label: SolutionFigures({1: _figures(rng), 2: _figures(rng)}, _figures(rng)) for label in ("G/I", "G/I/L")}
    sol["G/I/L single pass (strip 1)"] = SolutionFigures({1: _figures(rng)}, _figures(rng))
    planes = {
        label: ReferencePlaneFigures(
            float(rng.normal(0, 0.003)), float(rng.uniform(0.005, 0.02)), float(rng.uniform(0.002, 0.01)), 12,
            (SurfaceFigures("roof_a", 6, float(rng.normal(0, 0.003)), float(rng.uniform(0.001, 0.01)), 0.004),
             SurfaceFigures("road_b", 1, 0.002, math.nan, 0.002)))  # seen once: no SD
        for label in ("G/I", "G/I/L")
    }
    gated = {"candidates": 4100, "kept": 4000, "rough": 60, "steep": 20, "edge": 15, "normals": 5}
    diffs = {"G/I": StripDifferenceFigures(4000, 0.03, 0.08, 0.035, "gi/strip_differences.png",
                                           "gi/strip_differences_zoom.png", gated),
             "G/I/L": StripDifferenceFigures(0, math.nan, math.nan, math.nan, "gil/strip_differences.png")}
    evaluation = RunEvaluation("truth", sol, EvaluationPlots("attitude_differences.png", "position_differences.png"),
                               planes, diffs)
    return metrics, evaluation


def _written(tmp_path, record) -> dict:
    """``record.to_dict()`` through the library's JSON writer and back (NaN -> null)."""
    path = tmp_path / "record.json"
    write_json(path, record.to_dict())
    return json.loads(path.read_text())


@pytest.mark.parametrize("seed", [0, 1])
def test_records_read_back_to_what_was_written(tmp_path, seed):
    metrics, evaluation = _records(seed)
    d = _written(tmp_path, metrics)
    assert WorkflowMetrics.from_dict(d) == metrics and WorkflowMetrics.from_dict(d).to_dict() == d
    assert list(d) == ["t0_gps", "strips", "strip_time_gps", "outer_iterations", "points", "resumed", "timings_s",
                       "pass_precision"]
    assert d["strip_time_gps"] == {"1": [1.4e9 + 10.0, 1.4e9 + 40.5], "2": [1.4e9 + 60.0, 1.4e9 + 91.25]}
    assert d["pass_precision"][1] == {"strip": 2, "gi_sigma_mdeg": [4.0, 4.25, 40.5], "gil_sigma_mdeg": [1.0, 1.25, 1.75]}
    e = _written(tmp_path, evaluation)
    back = RunEvaluation.from_dict(e)
    assert back.to_dict() == e
    assert list(e) == ["reference", "trajectory", "plots", "reference_planes", "strip_differences"]
    assert e["trajectory"]["G/I"]["all"]["3d_rmse_m"] == evaluation.trajectory["G/I"].overall.position_3d_rmse_m
    # Undefined figures are null in the file and None when read; the optional zoom map is left out.
    assert e["reference_planes"]["G/I"]["surfaces"][1]["sd_m"] is None and back.reference_planes["G/I"].surfaces[1].sd_m is None
    assert "zoom_map" not in e["strip_differences"]["G/I/L"] and back.strip_differences["G/I/L"].median_m is None
    assert back.strip_differences["G/I"].gated == e["strip_differences"]["G/I"]["gated"]
    assert e["strip_differences"]["G/I"]["gated"]["rough"] == 60 and "gated" not in e["strip_differences"]["G/I/L"]
    assert back.single_pass == evaluation.trajectory["G/I/L single pass (strip 1)"]
    assert back.trajectory["G/I"].strips[2] == evaluation.trajectory["G/I"].strips[2]


def test_an_evaluation_without_plots_or_clouds_reads_back():
    e = RunEvaluation("full G/I/L", {}).to_dict()
    assert e == {"reference": "full G/I/L", "trajectory": {}, "reference_planes": {}, "strip_differences": {}}
    assert RunEvaluation.from_dict(e).plots is None and RunEvaluation.from_dict(e).single_pass is None


def _solve_dict() -> dict:
    """A solve's statistics as the adjustments write them (``SolveResult.to_dict``)."""
    from georefine.adjustment.statistics import GroupStatistics, SolveResult, Timings
    from georefine.adjustment.variance_components import VarianceComponent

    groups = (GroupStatistics("gnss", "huber", 600, 1800, 0.9, 700.0, 0.4, 0.81, 12, 0.95, 0.02, (0, 3, 5)),
              GroupStatistics("imu", None, 6000, 36000, 1.1, 1050.0, 0.6, 1.21, 0))  # no robust sigma0: null
    comps = (VarianceComponent(("gnss", "imu"), 37800, 30000.5, 0.0, 33000.0, 1.1, 1.1),)
    return SolveResult("function_tolerance", 6, 5, 9000.0, 1750.0, (4000.0, 1750.0), 1e-6, 7800, 6600, 37800, 30000,
                       1.17, groups, Timings(0.5, 0.2, 0.3, 1.2, 0.1), "cholmod", 3, 1, comps).to_dict()


def _adjustment_reports() -> dict[str, AdjustmentReport]:
    """One report of each writer: the trajectory command's filter and G/I, a run's G/I/L, a
    delivered trajectory's G/I/L and the hybrid adjustment."""
    frame = FrameOrigin(48.1372, 11.5756, 519.25)
    imu = {"bias_knot_times_s": [0.0, 60.0], "acc_bias_ug": [[1.0, 2.0, 3.0], [1.5, 2.5, 3.5]],
           "acc_scale_ppm": [10.0, -20.0, 5.0], "acc_scale_sigma_ppm": None}
    gnss = {"knot_times_s": [0.0, 60.0], "enu_m": [[0.01, 0.0, -0.02], [0.0, 0.01, 0.0]]}
    offset = LidarTimeOffset(0.0, 0.00125, 0.02, 0.71, 0.001, None)
    return {
        "filter": AdjustmentReport("filter", 1.4e9, {"read": 0.5, "filter": 2.0}, project="/data/p", frame=frame,
                                   filter=FilterSummary(1200, 3, 10.25)),
        "G/I": AdjustmentReport("G/I", 1.4e9, {"filter": 2.0, "adjustment_solve": 3.0}, adjustment=_solve_dict(),
                                imu_errors=imu, gnss_error=gnss, project="/data/p", frame=frame,
                                filter=FilterSummary(1200, 3, None)),
        "G/I/L": AdjustmentReport("G/I/L", 1.4e9, {"solve": 3.0}, adjustment=_solve_dict(), imu_errors=imu,
                                  boresight_deg=(0.062, -0.021, 0.03), boresight_sigma_mdeg=(2.0, 2.1, 9.0),
                                  lidar_time_offset=offset, project="/data/p", frame=frame,
                                  range_calibration={"offset_m": 0.0308, "scale_ppm": 97.4, "offset_sigma_m": 0.0011,
                                                     "scale_sigma_ppm": 11.8},
                                  channel_angles={"tilt_mdeg": [1.0, -2.0, 3.0], "scan_angle_mdeg": [0.5, 0.0, -1.0],
                                                  "tilt_sigma_mdeg": [0.4] * 3, "scan_angle_sigma_mdeg": [0.6] * 3}),
        "delivered": AdjustmentReport("G/I/L", 1.4e9, {"solve": 1.0}, adjustment=_solve_dict(),
                                      sbet_errors={"knot_times_s": [0.0, 1.0], "position_m": [[0.0] * 3] * 2},
                                      lidar_time_offset=LidarTimeOffset(0.0, 0.0, held="one strip only")),
        "hybrid": AdjustmentReport("hybrid", 1.4e9, {"solve": 3.0}, adjustment=_solve_dict(), imu_errors=imu,
                                   boresight_deg=(0.06, -0.02, 0.03), boresight_sigma_mdeg=(3.0, 3.5, 12.0),
                                   lidar_time_offset=LidarTimeOffset(0.0, 0.0011, 0.05, 0.7, 0.001)),
    }


@pytest.mark.parametrize("kind", ["filter", "G/I", "G/I/L", "delivered", "hybrid"])
def test_an_adjustment_report_reads_back_to_what_was_written(tmp_path, kind):
    report = _adjustment_reports()[kind]
    write_adjustment_report(tmp_path / "adjustment.json", report)
    back = read_adjustment_report(tmp_path / "adjustment.json")
    assert back == report
    d = json.loads((tmp_path / "adjustment.json").read_text())
    assert back.to_dict() == d and AdjustmentReport.from_dict(d) == report
    # One schema: every key in every file, null where the writer has no such section.
    assert list(d) == ["solution", "project", "frame", "t0_gps", "timings_s", "filter", "adjustment", "imu_errors",
                       "sbet_errors", "gnss_error", "boresight_deg", "boresight_sigma_mdeg", "lidar_time_offset",
                       "range_calibration", "channel_angles", "encoder_error"]
    assert (d["adjustment"] is None) == (kind == "filter")
    assert (d["lidar_time_offset"] is None) == (kind in ("filter", "G/I"))
    if d["lidar_time_offset"] is not None:
        assert list(d["lidar_time_offset"]) == ["configured_s", "estimate_s", "sigma_ms", "gnss_sigma_ms", "prior_s",
                                                "held"]
    # The solve's statistics are SolveResult's JSON form: it reads them back to the same figures.
    from georefine.adjustment.statistics import SolveResult

    if back.adjustment is not None:
        assert SolveResult.from_dict(back.adjustment).to_dict() == back.adjustment
    # A section missing from the object reads as None.
    assert AdjustmentReport.from_dict({k: v for k, v in d.items() if k not in ("filter", "frame")}) == replace(
        report, filter=None, frame=None)
    with pytest.raises(ValueError, match="solution must be one of"):
        replace(report, solution="G/I/L/P")


@pytest.mark.parametrize("change, field, expected", [
    (lambda d: d.pop("solution"), "solution", "one of filter, G/I, G/I/L, hybrid"),
    (lambda d: d.update(solution="gil"), "solution", "one of filter, G/I, G/I/L, hybrid"),
    (lambda d: d.update(t0_gps="1.4e9"), "t0_gps", "a number"),
    (lambda d: d["timings_s"].update(solve=None), "timings_s", "an object of numbers"),
    (lambda d: d["adjustment"].pop("termination"), "adjustment.termination", "a string"),
    (lambda d: d["adjustment"]["groups"][1].update(n_residuals=3.5), "adjustment.groups[1].n_residuals", "an integer"),
    (lambda d: d["adjustment"]["variance_components"][0].update(scale="1"),
     "adjustment.variance_components[0].scale", "a number or null"),
    (lambda d: d.update(imu_errors=[1, 2]), "imu_errors", "an object or null"),
    (lambda d: d.update(boresight_deg=[0.06, -0.02]), "boresight_deg", "three numbers or null"),
    (lambda d: d["lidar_time_offset"].pop("estimate_s"), "lidar_time_offset.estimate_s", "a number"),
    (lambda d: d["lidar_time_offset"].update(held=1), "lidar_time_offset.held", "a string or null"),
])
def test_a_malformed_adjustment_report_names_the_file_and_the_field(tmp_path, change, field, expected):
    d = _adjustment_reports()["G/I/L"].to_dict()
    d = json.loads(json.dumps(d))
    change(d)
    path = tmp_path / "adjustment.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError) as err:
        read_adjustment_report(path)
    assert err.value.path == path and err.value.field == field and err.value.expected == expected, str(err.value)
    assert str(path) in str(err.value) and field in str(err.value)


def test_an_adjustment_report_that_is_not_json_is_an_input_error(tmp_path):
    path = tmp_path / "adjustment.json"
    path.write_text('{"solution": "G/I",\n')
    with pytest.raises(InputError, match="not a JSON file") as err:
        read_adjustment_report(path)
    assert err.value.path == path and err.value.line == 2
    path.write_text("[1, 2]")
    with pytest.raises(InputError, match="not a JSON object"):
        read_adjustment_report(path)


def test_summary_rows_take_the_typed_figures():
    _, evaluation = _records(2)
    rows = summary_rows(evaluation)
    gi, gil = evaluation.trajectory["G/I"], evaluation.trajectory["G/I/L"]
    single = evaluation.single_pass
    assert rows[0][0] == "roll RMSE (mdeg)" and rows[2][0] == "yaw RMSE (mdeg)"
    assert rows[2][2:] == [f"{gi.overall.yaw_rmse_mdeg:.1f}", f"{gil.overall.yaw_rmse_mdeg:.1f}",
                           f"{single.overall.yaw_rmse_mdeg:.1f} (G/I {gi.strips[1].yaw_rmse_mdeg:.1f})"]
    avg_sd = next(r for r in rows if r[0] == "reference planes AVG-SD (mm)")
    assert avg_sd[2:4] == [f"{evaluation.reference_planes[k].avg_sd_m * 1e3:.1f}" for k in ("G/I", "G/I/L")]
    p95 = next(r for r in rows if r[0] == "strip differences P95 (mm)")
    assert p95[2] == "80.0"
    # Without an evaluation: the paper's column only.
    assert [r[2:] for r in summary_rows(None)] == [["–", "–", "–"]] * 3


def test_each_summary_row_has_a_verdict_that_flags_figures_the_paper_beats():
    _, evaluation = _records(2)
    rows, verdicts = summary_rows(evaluation), summary_verdicts(evaluation)
    assert len(verdicts) == len(rows)
    gi_yaw = evaluation.trajectory["G/I"].overall.yaw_rmse_mdeg
    single_yaw = evaluation.single_pass.overall.yaw_rmse_mdeg
    yaw = verdicts[2]
    assert ("G/I ✓" in yaw) == (gi_yaw <= 20.0) and ("single pass ✓" in yaw) == (single_yaw <= 2.0), yaw
    if single_yaw > 2.0:
        assert f"single pass ✗ {single_yaw:.1f} > 2" in yaw
    mean = evaluation.reference_planes["G/I/L"].mean_m * 1e3
    judged = verdicts[[r[0] for r in rows].index("reference planes Mean (mm)")]
    assert judged == ("G/I/L ✓" if abs(mean) < 4 else f"G/I/L ✗ {abs(mean):.1f} ≥ 4")
    assert verdicts[-1] == "–"  # the G/I/L strip differences have no cells here
    assert summary_verdicts(None) == ["–"] * 3


def test_the_report_renders_the_records_of_a_run_folder(tmp_path):
    metrics, evaluation = _records(3)
    run = tmp_path / "run"
    (run / "evaluation").mkdir(parents=True)
    write_json(run / "metrics.json", metrics.to_dict())
    write_json(run / "evaluation" / "summary.json", evaluation.to_dict())
    page = html.unescape(write_report(run).read_text())
    read = RunEvaluation.read(run / "evaluation" / "summary.json")
    for row, verdict in zip(summary_rows(read), summary_verdicts(read)):
        assert "".join(f"<td>{c}</td>" for c in [*row, verdict]) in page, row
    last = metrics.outer_iterations[-1]
    assert (f"<td>{last.iteration}</td><td>0.1</td><td>{last.features:,}</td><td>{last.objects:,}</td>"
            f"<td>{last.features_used:,}</td><td>{last.attitude_change_mdeg:.2f}</td>") in page
    assert "Resumed from the cache: gi." in page and "<td>gi_adjustment</td><td>2.2</td>" in page
    assert "strips [1, 2]" in page and "trajectory reference: truth" in page
    s = evaluation.trajectory["G/I/L"].strips[2]
    assert f"<td>G/I/L</td><td>strip 2</td><td>{s.roll_rmse_mdeg:.2f}</td>" in page
    g = evaluation.reference_planes["G/I"].surfaces[0]
    assert f"<td>roof_a</td><td>6</td><td>{g.mean_m * 1e3:.1f}</td><td>{g.sd_m * 1e3:.1f}</td>" in page
    assert "<td>road_b</td><td>1</td><td>2.0</td><td>–</td>" in page  # no SD of a surface seen once
    assert "G/I/L: median – mm, P95 – mm over 0 planar 1 m cells" in page
    assert "over 4,000 planar 1 m cells; 100 gated (grey): rough 60, steep 20, edge 15, normals 5" in page
    # The G/I/L's adjustment statistics with its variance components.
    from georefine.adjustment.statistics import GroupStatistics, SolveResult, Timings
    from georefine.adjustment.variance_components import VarianceComponent

    groups = [GroupStatistics(n, None, m, 3 * m, 1.0, 10.0, 0.5, 1.0, d, expected_downweighted=e)
              for n, m, d, e in (("imu", 1000, 0, 0.0), ("planes", 5000, 1300, 0.26146))]
    comps = (VarianceComponent(("planes",), 15000, 13456.7, 20.0, 9000.0, 0.669, 1.0),
             VarianceComponent(("imu", "gnss"), 3000, 1500.0, 20.0, 3300.0, 2.2, 2.2))

    def write_gil(groups) -> None:
        solve = SolveResult("function_tolerance", 4, 4, 30.0, 20.0, (25.0, 20.0), 1e-5, 2000, 6000, 16956, 14956, 0.83,
                            tuple(groups), Timings(0.1, 0.1, 0.2, 0.5), "cholmod", variance_components=comps)
        write_adjustment_report(run / "gil" / "adjustment.json",
                                AdjustmentReport("G/I/L", 1.4e9, {"solve": 0.5}, adjustment=solve.to_dict()))

    (run / "gil").mkdir()
    write_gil(groups)
    page = html.unescape(write_report(run).read_text())
    assert "<td>planes</td><td>15,000</td><td>13456.7</td><td>0.669</td><td>1.000</td>" in page
    assert "<td>1,300 (26.0 %)</td><td>26.1 %</td>" in page and "<td>0 (0.0 %)</td><td>0.0 %</td>" in page
    assert "<td>imu, gnss</td><td>3,000</td><td>1500.0</td><td>2.200</td><td>2.200</td>" in page
    assert "residual histograms" not in page  # results stored before the histograms
    from georefine.adjustment.statistics import RESIDUAL_EDGES, residual_histogram

    rng = np.random.default_rng(3)
    groups[1] = replace(groups[1], residual_histogram=residual_histogram(rng.standard_normal(15000) * 1.3),
                        robust_sigma0=1.3)
    write_gil(groups)
    page = html.unescape(write_report(run).read_text())
    assert page.count('alt="residual histograms"') == 1 and "Whitened residuals of each group" in page
    assert len(groups[1].residual_histogram) == len(RESIDUAL_EDGES) - 1
    assert not list(run.rglob("residuals_*.png"))  # drawn for the page, not left in the run folder
    # A run without an evaluation still gets its report.
    (run / "evaluation" / "summary.json").unlink()
    page = html.unescape(write_report(run).read_text())
    assert "trajectory reference: –" in page and "4. Reference planes" not in page
