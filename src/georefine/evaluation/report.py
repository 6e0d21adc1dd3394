"""One self-contained HTML report per run (docs/ARCHITECTURE.md §5): it opens from the file system.

The page shows, from the files a run and its evaluation wrote (``metrics.json``,
``gi/`` and ``gil/adjustment.json``, ``evaluation/summary.json`` and its plots,
``config.resolved.yaml``):

1. a summary beside paper 000's figures (roll/pitch/yaw RMSE, reference planes, strip differences);
2. the workflow steps with their timings and the outer iterations;
3. trajectory differences against the reference, per strip, with the Fig. 9 style plots;
4. the reference-plane table (Table 1) per surface, G/I beside G/I/L;
5. the strip-difference maps (Fig. 7) of G/I and G/I/L side by side, and the differences of every
   pair of strips before and after (the G/I and G/I/L clouds): a table and their matrices;
6. the adjustment statistics per observation group and the estimated IMU errors;
7. the configuration used.

Images are embedded as base64 PNG, so the single file is the whole report.
"""

from __future__ import annotations

import datetime as _dt
import html
import math
import tempfile
from pathlib import Path

from georefine import __version__
from georefine.evaluation.calibration import MISALIGNMENT_ELEMENTS
from georefine.evaluation.page import CSS, image, table
from georefine.evaluation.plots import plot_residual_histograms
from georefine.evaluation.summary import ANGLES, RunEvaluation, SurfaceFigures
from georefine.io.files import atomic_output
from georefine.io.run_metrics import WorkflowMetrics, read_adjustment_report

__all__ = ["PAPER_000", "write_report", "summary_rows", "summary_verdicts"]

#: Paper 000's figures (Fig. 9 and §4 text; Table 1). Trajectory: differences to its full
#: G/I/L solution; the single-pass roll is "at the same level" as G/I.
PAPER_000 = {
    "G/I": {"roll_rmse_mdeg": 8.0, "pitch_rmse_mdeg": 4.0, "yaw_rmse_mdeg": 20.0},
    "G/I/L single pass": {"roll_rmse_mdeg": 8.0, "pitch_rmse_mdeg": 2.0, "yaw_rmse_mdeg": 2.0},
    "reference_planes": {"G/I": {"avg_sd_m": 0.0101}, "G/I/L": {"avg_sd_m": 0.0033}},
}


def _f(x, scale=1.0, digits=1) -> str:
    return "–" if x is None else f"{x * scale:.{digits}f}"


def summary_rows(summary: RunEvaluation | None) -> list[list[str]]:
    """Rows ``[quantity, paper 000, G/I, G/I/L, single-pass G/I/L]`` of the headline table."""
    traj = summary.trajectory if summary is not None else {}
    gi, gil = traj.get("G/I"), traj.get("G/I/L")
    single = summary.single_pass if summary is not None else None
    rows = []
    for a in ANGLES:
        key = f"{a}_rmse_mdeg"
        paper = f"{PAPER_000['G/I'][key]:.0f} / – / {PAPER_000['G/I/L single pass'][key]:.0f}"
        cell = "–"
        if single:  # beside G/I during the same strip(s)
            same = [gi.strips[s].rmse_mdeg(a) for s in single.strips if gi is not None and s in gi.strips]
            cell = _f(single.overall.rmse_mdeg(a)) + (f" (G/I {_f(max(same))})" if same else "")
        rows.append([f"{a} RMSE (mdeg)", paper, _f(gi.overall.rmse_mdeg(a) if gi else None),
                     _f(gil.overall.rmse_mdeg(a) if gil else None), cell])
    rp = summary.reference_planes if summary is not None else {}
    if rp:
        for k, name in (("mean_m", "Mean"), ("rmse_m", "RMSE"), ("avg_sd_m", "AVG-SD")):
            paper = {"avg_sd_m": "10.1 / 3.3 / –", "mean_m": "< 4 / < 4 / –", "rmse_m": "< 22 / < 22 / –"}[k]
            rows.append([f"reference planes {name} (mm)", paper, _f(_attr(rp.get("G/I"), k), 1e3),
                         _f(_attr(rp.get("G/I/L"), k), 1e3), "–"])
    sd = summary.strip_differences if summary is not None else {}
    if sd:
        for k, name in (("median_m", "median"), ("p95_m", "P95")):
            rows.append([f"strip differences {name} (mm)", "≤ 50 on planar surfaces (Fig. 7)",
                         _f(_attr(sd.get("G/I"), k), 1e3), _f(_attr(sd.get("G/I/L"), k), 1e3), "–"])
    return rows


def _judge(value: float | None, bound: float, what: str, strict: bool = False) -> str | None:
    """``what``'s ``value`` against the paper's ``bound`` (same unit); None without a (finite) value."""
    if value is None or not math.isfinite(value):
        return None
    if (value < bound) if strict else (value <= bound):
        return f"{what} ✓"
    return f"{what} ✗ {value:.1f} {'≥' if strict else '>'} {bound:g}"


def summary_verdicts(summary: RunEvaluation | None) -> list[str]:
    """One verdict per row of :func:`summary_rows`, against paper 000's figure or the goal of the row.

    Trajectory rows: G/I against the paper's G/I and the single pass against the paper's single
    pass (the paper's figures are differences to its own G/I/L solution, Georefine's to the truth:
    a comparison of magnitudes, not a test). Reference planes: the G/I/L's Mean below 4 mm in
    magnitude, RMSE below 22 mm, AVG-SD at most 3.3 mm (Table 1). Strip differences: at most 50 mm
    on planar surfaces (Fig. 7). "✗" flags a figure the paper beats, with both figures.
    """
    out: list[str] = []
    traj = summary.trajectory if summary is not None else {}
    gi = traj.get("G/I")
    single = summary.single_pass if summary is not None else None
    for a in ANGLES:
        key = f"{a}_rmse_mdeg"
        parts = [_judge(gi.overall.rmse_mdeg(a) if gi else None, PAPER_000["G/I"][key], "G/I"),
                 _judge(single.overall.rmse_mdeg(a) if single else None, PAPER_000["G/I/L single pass"][key],
                        "single pass")]
        out.append("; ".join(p for p in parts if p) or "–")
    rp = summary.reference_planes if summary is not None else {}
    if rp:
        gil = rp.get("G/I/L")
        for k, bound, strict in (("mean_m", 4.0, True), ("rmse_m", 22.0, True), ("avg_sd_m", 3.3, False)):
            value = _attr(gil, k)
            if value is not None and k == "mean_m":
                value = abs(value)
            out.append(_judge(None if value is None else value * 1e3, bound, "G/I/L", strict) or "–")
    sd = summary.strip_differences if summary is not None else {}
    if sd:
        for k in ("median_m", "p95_m"):
            value = _attr(sd.get("G/I/L"), k)
            out.append(_judge(None if value is None else value * 1e3, 50.0, "G/I/L") or "–")
    return out


def _calibration_section(summary: RunEvaluation, ev: Path) -> str:
    """The adjustments' IMU errors and boresight against the simulated truth."""
    parts = ["<h3>Estimated IMU errors and boresight against the simulated truth</h3>",
             '<p class="note">Scale factors: estimated / true ± sigma (ppm). Biases: the RMS over the bias knots '
             "of estimated minus true against the RMS of their sigma (about 1 : 1 when the sigmas are honest; "
             "the plot shows the whole series with ±2σ bands).</p>"]
    rows = []
    for label, f in summary.imu_errors.items():
        for name, est, true, sig in (("accelerometer scale (ppm)", f.acc_scale_ppm, f.acc_scale_true_ppm,
                                      f.acc_scale_sigma_ppm),
                                     ("gyro scale (ppm)", f.gyro_scale_ppm, f.gyro_scale_true_ppm, f.gyro_scale_sigma_ppm)):
            rows.append([label, name, *(f"{e:.0f} / {t:.0f} ± {s:.0f}" for e, t, s in zip(est, true, sig))])
        for name, err, sig, digits in (("accelerometer bias (µg)", f.acc_bias_rms_error_ug, f.acc_bias_rms_sigma_ug, 0),
                                       ("gyro bias (deg/h)", f.gyro_bias_rms_error_deg_per_h,
                                        f.gyro_bias_rms_sigma_deg_per_h, 2)):
            rows.append([label, f"{name}: RMS error : RMS sigma",
                         *(f"{e:.{digits}f} : {s:.{digits}f}" for e, s in zip(err, sig))])
    if rows:
        parts.append(table(["solution", "quantity", "x", "y", "z"], rows))
    rows = [[label, f"{triad} misalignment (mrad)", *(f"{e:.3f} / {t:.3f} ± {s:.3f}" for e, t, s in zip(
                getattr(f, f"{key}_misalignment_mrad"), getattr(f, f"{key}_misalignment_true_mrad"),
                getattr(f, f"{key}_misalignment_sigma_mrad")))]
            for label, f in summary.imu_errors.items()
            for key, triad in (("acc", "accelerometer"), ("gyro", "gyro")) if getattr(f, f"{key}_misalignment_mrad")]
    if rows:
        parts.append('<p class="note">Misalignment: estimated / true ± sigma per element (row axis, column axis) '
                     "of the triad's sensitivity matrix.</p>")
        parts.append(table(["solution", "quantity", *MISALIGNMENT_ELEMENTS], rows))
    if summary.imu_errors_plot:
        parts.append(image(ev / summary.imu_errors_plot, "IMU biases against the truth"))
    b = summary.boresight
    if b is not None:
        parts.append(table(["boresight", "roll", "pitch", "yaw"], [
            ["estimated (deg)", *(f"{v:.4f}" for v in b.estimated_deg)],
            ["true (deg)", *(f"{v:.4f}" for v in b.true_deg)],
            ["project.yaml, the start (deg)", *(f"{v:.4f}" for v in b.stated_deg)],
            ["error (mdeg)", *(f"{v:.1f}" for v in b.error_mdeg)],
            ["sigma (mdeg)", *(_f(v) for v in b.sigma_mdeg)],
        ]))
    return "".join(parts)


def _strip_pairs_section(summary: RunEvaluation, ev: Path) -> str:
    """The differences of every pair of strips per cloud (before: G/I, after: G/I/L): one row per
    pair with figures in any cloud, and the clouds' matrices of the medians."""
    clouds = summary.strip_pairs
    parts = ["<h3>Strip pairs</h3>",
             '<p class="note">Per pair of strips, over the 1 m cells where both fit a plane and the cell passes '
             "the strip-difference gate: the median and P95 of |difference| along the normal, and the signed "
             "median (the second strip above the first positive).</p>"]
    keys = sorted({(p.strip_a, p.strip_b) for v in clouds.values() for p in v.pairs.measured()})
    header = ["strips"]
    for label in clouds:
        header += [f"{label} cells", f"{label} median (mm)", f"{label} P95 (mm)", f"{label} signed median (mm)"]
    rows = []
    for a, b in keys:
        row: list = [f"{a} – {b}"]
        for v in clouds.values():
            p = next((q for q in v.pairs.pairs if (q.strip_a, q.strip_b) == (a, b)), None)
            row += ["–", "–", "–", "–"] if p is None else [
                f"{p.cells:,}", _f(p.median_mm), _f(p.p95_mm), _f(p.signed_median_mm)]
        rows.append(row)
    if rows:
        parts.append(table(header, rows))
    for label, v in clouds.items():
        others = len(v.pairs.unmeasured())
        if others:
            parts.append(f'<p class="note">{html.escape(label)}: {others} further pair(s) of strips do not overlap '
                         f"or share fewer than {v.pairs.min_cells} planar cells.</p>")
    figs = [f"<figure>{image(ev / v.matrix, f'strip pairs {label}')}<figcaption>{html.escape(label)}: median "
            "|difference| per pair of strips (mm)</figcaption></figure>" for label, v in clouds.items()]
    parts.append('<div class="maps">' + "".join(figs) + "</div>")
    return "".join(parts)


def _downweighted(g: dict) -> str:
    n, total = g["n_downweighted"], g["n_observations"]
    return f"{n:,} ({100 * n / total:.1f} %)" if total else f"{n:,}"


def _chance(g: dict) -> str:
    share = g.get("expected_downweighted")
    return "–" if share is None or not math.isfinite(share) else f"{100 * share:.1f} %"


def _attr(obj, name: str):
    """``obj.name``, or ``None`` when there is no ``obj`` (a cloud that was not evaluated)."""
    return None if obj is None else getattr(obj, name)


def write_report(run_dir: Path, path: Path | None = None, *, title: str = "Georefine report") -> Path:
    """Write ``run_dir/report.html`` (or ``path``) from the run's files; returns the path.

    ``metrics.json``, ``evaluation/summary.json`` and ``gi/``, ``gil/adjustment.json`` are read into
    their types (:class:`~georefine.io.run_metrics.WorkflowMetrics`,
    :class:`~georefine.evaluation.summary.RunEvaluation`,
    :class:`~georefine.io.run_metrics.AdjustmentReport`); a run without an evaluation gets a
    report without its figures.
    """
    run_dir = Path(run_dir)
    path = Path(path) if path is not None else run_dir / "report.html"
    ev = run_dir / "evaluation"
    metrics = WorkflowMetrics.read(run_dir / "metrics.json")
    summary = RunEvaluation.read(ev / "summary.json") if (ev / "summary.json").is_file() else None
    adj = {k: read_adjustment_report(run_dir / k / "adjustment.json")
           for k in ("gi", "gil") if (run_dir / k / "adjustment.json").is_file()}
    reference = summary.reference if summary is not None else "–"
    parts = [f"<h1>{html.escape(title)}</h1>",
             f'<p class="note">Georefine {html.escape(__version__)}, {_dt.datetime.now().isoformat(timespec="seconds")}; '
             f"run folder {html.escape(str(run_dir.resolve()))}; strips {list(metrics.strips)}; "
             f"trajectory reference: {html.escape(reference)}.</p>"]

    if summary is not None and summary.overview_plot:
        parts.append(f"<figure>{image(ev / summary.overview_plot, 'flight overview')}<figcaption>The flight: "
                     "the trajectory in grey, the strips in colour with their direction, the reference surfaces "
                     "as triangles.</figcaption></figure>")
    cov = next((summary.coverage[k] for k in ("G/I/L", "G/I") if summary is not None and k in summary.coverage), None)
    if cov is not None:
        parts.append(table(["covered area (km²)", "density, median (points/m²)", "density, 5 % of the area below",
                            "area seen from two strips or more", "most strips on a cell"],
                           [[f"{cov.area_km2:.2f}", _f(cov.density_median_per_m2), _f(cov.density_p5_per_m2),
                             "–" if cov.overlap_share is None else f"{100 * cov.overlap_share:.0f} %",
                             cov.max_strips]]))
        parts.append(f"<figure>{image(ev / cov.density_map, 'point density map')}<figcaption>Points per m² "
                     "(1 m cells, all strips and channels; cells above the scale in magenta).</figcaption></figure>")
        parts.append(f"<figure>{image(ev / cov.overlap_map, 'strip overlap map')}<figcaption>Strips with points "
                     "in each cell: a place seen from one strip only (orange) has no strip difference to check "
                     "it.</figcaption></figure>")
    parts.append("<h2>1. Summary beside paper 000</h2>")
    parts.append(table(["quantity", "paper 000 (G/I / G/I/L / single pass)", "G/I", "G/I/L", "single-pass G/I/L",
                        "against paper 000 (✗: the paper's is better)"],
                       [[*row, verdict] for row, verdict in zip(summary_rows(summary), summary_verdicts(summary))]))
    parts.append('<p class="note">Paper 000 compares with its full G/I/L solution (no truth); Georefine compares '
                 "with the reference named above. Reference planes: Mean and RMSE over all strip x channel "
                 "observations, AVG-SD the mean per-surface standard deviation (Table 1).</p>")

    parts.append("<h2>2. Workflow</h2>")
    parts.append(table(["step", "seconds"], [[k, f"{v:.1f}"] for k, v in metrics.timings_s.items()]))
    if metrics.outer_iterations:
        parts.append(table(
            ["outer iteration", "knots (s)", "features", "objects", "features used", "RMS change (mdeg)",
             "RMS change (mm)"],
            [[it.iteration, "" if it.knot_interval_s is None else f"{it.knot_interval_s:.3g}", f"{it.features:,}",
              f"{it.objects:,}", f"{it.features_used:,}", f"{it.attitude_change_mdeg:.2f}",
              f"{it.position_change_m * 1e3:.1f}"]
             for it in metrics.outer_iterations]))
    if metrics.resumed:
        parts.append(f'<p class="note">Resumed from the cache: {html.escape(", ".join(metrics.resumed))}.</p>')

    parts.append("<h2>3. Trajectory differences</h2>")
    rows = []
    for label, t in (summary.trajectory if summary is not None else {}).items():
        for sid, s in [*((f"strip {k}", v) for k, v in t.strips.items()), ("all", t.overall)]:
            rows.append([label, sid, *(_f(s.rmse_mdeg(a), digits=2) for a in ANGLES), _f(s.position_3d_rmse_m, 1e3)])
    parts.append(table(["solution", "during", "roll (mdeg)", "pitch (mdeg)", "yaw (mdeg)", "3-D position (mm)"], rows))
    parts.append(image(ev / "attitude_differences.png", "attitude differences"))
    parts.append(image(ev / "position_differences.png", "position differences"))

    rp = summary.reference_planes if summary is not None else {}
    if rp:
        parts.append("<h2>4. Reference planes (Table 1)</h2>")
        surf: dict[str, dict[str, SurfaceFigures]] = {}
        for label in ("G/I", "G/I/L"):
            for s in (rp[label].surfaces if label in rp else ()):
                surf.setdefault(s.surface_id, {})[label] = s
        rows = []
        for sid, v in surf.items():
            g, gl = v.get("G/I"), v.get("G/I/L")
            rows.append([sid, (gl or g).observations, _f(_attr(g, "mean_m"), 1e3), _f(_attr(g, "sd_m"), 1e3),
                         _f(_attr(gl, "mean_m"), 1e3), _f(_attr(gl, "sd_m"), 1e3)])
        parts.append(table(
            ["surface", "observations", "G/I mean (mm)", "G/I SD (mm)", "G/I/L mean (mm)", "G/I/L SD (mm)"], rows))
        parts.append(table(["", "Mean (mm)", "RMSE (mm)", "AVG-SD (mm)", "observations"],
                            [[label, _f(v.mean_m, 1e3), _f(v.rmse_m, 1e3), _f(v.avg_sd_m, 1e3), v.n_observations]
                             for label, v in rp.items()]))
        asprs = [(label, v.asprs_vertical) for label, v in rp.items() if v.asprs_vertical is not None]
        if asprs:
            parts.append("<h3>Vertical accuracy to the standards (level reference surfaces)</h3>")
            parts.append('<p class="note">Each reference surface no steeper than 10 % is one vertical check point: '
                         "the mean over the views that see it of the points' distance along its normal, made vertical. "
                         "ASPRS Positional Accuracy Standards, Edition 2 (2023): RMSE_V (the non-vegetated vertical "
                         "accuracy, NVA) with the surfaces' survey accuracy included; the data meet the X-cm vertical "
                         "accuracy class for any X at or above it, given at least 30 check points. NSSDA: vertical "
                         "accuracy at 95 % confidence (1.96 RMSE_z).</p>")
            parts.append(table(["", "check surfaces", "RMSE_V = NVA (mm)", "mean (mm)", "survey (mm)",
                                "NSSDA 95 % (mm)"],
                               [[label, f"{a.n_checkpoints}{'' if a.enough_checkpoints else ' (fewer than 30)'}",
                                 _f(a.rmse_v_m, 1e3), _f(a.mean_v_m, 1e3), _f(a.rmse_v2_m, 1e3, 2),
                                 _f(a.nssda_vertical_95_m, 1e3)] for label, a in asprs]))

    sd = summary.strip_differences if summary is not None else {}
    if sd:
        parts.append("<h2>5. Strip differences (Fig. 7)</h2>")
        figs = []
        for label, v in sd.items():
            if v.zoom_map:
                figs.append(f"<figure>{image(ev / v.zoom_map, label)}<figcaption>{html.escape(label)}: detail "
                            "around the first reference site</figcaption></figure>")
        if figs:
            parts.append('<div class="maps">' + "".join(figs) + "</div>")
        figs = []
        for label, v in sd.items():
            cap = (f"{label}: median {_f(v.median_m, 1e3)} mm, P95 {_f(v.p95_m, 1e3)} mm "
                   f"over {v.cells:,} planar 1 m cells")
            if v.gated:
                cap += (f"; {v.gated['candidates'] - v.gated['kept']:,} gated (grey): " + ", ".join(
                    f"{k} {v.gated.get(k, 0):,}" for k in ("rough", "steep", "edge", "normals")))
            figs.append(f"<figure>{image(ev / v.map, label)}<figcaption>{html.escape(cap)}</figcaption></figure>")
        parts.append("".join(figs))  # the whole corridor at the page's width, one map under the other
    if summary is not None and summary.strip_pairs:
        parts.append(_strip_pairs_section(summary, ev))

    parts.append("<h2>6. Adjustment statistics and IMU errors</h2>")
    for key, a in adj.items():
        s = a.adjustment
        if s is None:  # the filter alone
            continue
        parts.append(f"<h3>{'G/I' if key == 'gi' else 'G/I/L'}: {html.escape(str(s.get('termination')))} after "
                     f"{s.get('iterations')} iterations, σ0² = {_f(s.get('variance_factor'), digits=3)}, "
                     f"{s.get('n_unknowns'):,} unknowns, redundancy {s.get('redundancy'):,}</h3>")
        parts.append(table(
            ["group", "observations", "rows", "RMS", "σ0² (approx.)", "cost share", "down-weighted",
             "by chance if the model fits"],
            [[g["name"], f"{g['n_observations']:,}", f"{g['n_residuals']:,}", _f(g["rms"], digits=3),
              _f(g["variance_factor"], digits=3), f"{100 * g['cost_share']:.1f} %", _downweighted(g),
              _chance(g)] for g in s.get("groups", [])]))
        parts.append('<p class="note">Down-weighted: observations whose robust weight fell below 0.5 (the Cauchy loss '
                     "of the planes: a whitened residual norm beyond c; the Huber loss of GNSS: beyond 2 delta). "
                     "A fitting model with honest sigmas puts a share of correct observations there by chance "
                     "(chi-square of their rows beyond that threshold; with c = 2 on a plane correspondence's three "
                     "rows, 26 %): a count near it is noise, one well above it wrong matches or optimistic "
                     "sigmas.</p>")
        with tempfile.TemporaryDirectory() as tmp:
            hist = plot_residual_histograms(s.get("groups", []), Path(tmp) / f"residuals_{key}.png")
            if hist is not None:
                parts.append(f"<figure>{image(hist, 'residual histograms')}<figcaption>Whitened residuals of "
                             "each group against N(0, 1) (log scale): wider than the curve, the sigmas are "
                             "optimistic; the outer bins hold every residual beyond ±5 σ.</figcaption></figure>")
        if s.get("variance_components"):
            parts.append("<p>The posterior sigmas weight each variance component by its own factor (floored at 1; "
                         "docs/ARCHITECTURE.md §4.4):</p>")
            parts.append(table(
                ["groups", "rows", "redundancy", "σ0²", "posterior scale"],
                [[", ".join(c["groups"]), f"{c['n_residuals']:,}", _f(c["redundancy"], digits=1),
                  _f(c["factor"], digits=3), _f(c["scale"], digits=3)] for c in s["variance_components"]]))
        e = a.imu_errors or {}
        if e:
            rows = []
            for name, unit in (("acc_scale_ppm", "ppm"), ("gyro_scale_ppm", "ppm")):
                v, sg = e.get(name), e.get(name.replace("_ppm", "_sigma_ppm"))
                if v is not None:
                    rows.append([name.replace("_ppm", ""), unit] + [
                        f"{v[i]:.0f} ± {sg[i]:.0f}" if sg else f"{v[i]:.0f}" for i in range(3)])
            for name, unit in (("acc_bias_ug", "µg"), ("gyro_bias_deg_per_h", "deg/h")):
                v = e.get(name)
                if v:
                    first, last = v[0], v[-1]
                    rows.append([name.rsplit("_", 1)[0] + " (first knot → last)", unit] + [
                        f"{first[i]:.2f} → {last[i]:.2f}" for i in range(3)])
            parts.append(table(["IMU error", "unit", "x", "y", "z"], rows))
            rows = [[name.replace("_mrad", ""), "mrad"] + [
                f"{v:.3f} ± {g:.3f}" if sg else f"{v:.3f}" for v, g in zip(e[name], sg or e[name])]
                for name in ("acc_misalignment_mrad", "gyro_misalignment_mrad") if e.get(name)
                for sg in [e.get(name.replace("_mrad", "_sigma_mrad"))]]
            if rows:
                parts.append(table(["IMU misalignment", "unit", *MISALIGNMENT_ELEMENTS], rows))
        if a.boresight_deg is not None:
            b, sg = a.boresight_deg, a.boresight_sigma_mdeg or (float("nan"),) * 3
            parts.append("<p>Boresight roll/pitch/yaw: " + ", ".join(
                f"{b[i]:.4f}° ± {sg[i]:.1f} mdeg" for i in range(3)) + "</p>")

    if summary is not None and (summary.imu_errors or summary.boresight is not None):
        parts.append(_calibration_section(summary, ev))

    cfg = run_dir / "config.resolved.yaml"
    if cfg.is_file():
        parts.append("<h2>7. Configuration</h2><pre>" + html.escape(cfg.read_text()) + "</pre>")

    doc = (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
           f"<style>{CSS}</style></head><body>{''.join(parts)}</body></html>\n")
    with atomic_output(path, "w") as fh:
        fh.write(doc)
    return path
