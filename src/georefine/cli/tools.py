"""The command groups that read results: ``georefine export ...`` and ``georefine evaluate ...``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from georefine.cli.common import force_option, output_ok, scheduler_option, stdout, user_errors

__all__ = ["evaluate_app", "export_app"]

export_app = typer.Typer(
    rich_markup_mode=None,  # plain help: units in brackets stay, on/off flags show as flags
    help="Write results in the formats of other tools (trajectories for evo and trajectopy, ...).",
    no_args_is_help=True,
)


@export_app.command("trajectory")
def export_trajectory_cmd(
    source: Path = typer.Argument(..., help="Trajectory SBET, or a trajectory CSV (.csv) of Georefine."),
    fmt: str = typer.Option(..., "--format", "-f", help="tum (evo: timestamp tx ty tz qx qy qz qw, GPS seconds) or "
                            "trajectopy (.traj: #epsg, #fields, seconds of the GPS week)."),
    out: Path = typer.Option(..., "--out", "-o", help="File to write (its folder must exist)."),
    epsg: Optional[int] = typer.Option(
        None, "--epsg", help="CRS of the positions: projected (grid east-north-up axes) or geocentric, e.g. 4978. "
        "Default: the output CRS the SBET's companion file or the CSV states."),
    gps_week: Optional[int] = typer.Option(
        None, "--gps-week", help="GPS week of an SBET in seconds of week that has no companion file."),
) -> None:
    """Write a trajectory as TUM (evo) or trajectopy's format: one pose per IMU record or CSV row.

    Positions of the IMU in the CRS; the quaternion is the body attitude (x forward, y right, z down) in
    the CRS's axes (grid east-north-up, meridian convergence included), so that evo_ape and trajectopy's
    ATE without alignment give Georefine's own figures.
    """
    with user_errors():
        from georefine import api

        result = api.export_trajectory(source, out, fmt, epsg=epsg, gps_week=gps_week)
    stdout.print(result.summary())


# ---------------------------------------------------------------------------
# georefine evaluate ...
# ---------------------------------------------------------------------------

evaluate_app = typer.Typer(
    rich_markup_mode=None,  # plain help: units in brackets stay, on/off flags show as flags
    help="Evaluate results against a reference (trajectory differences, ...).",
    no_args_is_help=True,
)


@evaluate_app.command("trajectory")
def evaluate_trajectory(
    estimate: Path = typer.Argument(..., help="Estimated trajectory (SBET)."),
    reference: Path = typer.Option(..., "--reference", "-r", help="Reference trajectory (SBET)."),
    out: Optional[Path] = typer.Option(
        None, "--out", "-o",
        help="Folder for trajectory_comparison.json and the difference plots (created if needed).",
    ),
    gps_week: Optional[int] = typer.Option(
        None, "--gps-week",
        help="GPS week of SBETs that store seconds of week. Without it such a file takes the week of its companion "
        "file (NAME.json, beside Georefine's SBETs) or is assumed to be in the same week as the other file (both "
        "seconds of week: compared as seconds of week).",
    ),
    span: Optional[tuple[float, float]] = typer.Option(
        None, "--span", metavar="START END",
        help="Only compare inside this time window: seconds of week (< 604800) or GPS seconds.",
    ),
    force: bool = force_option(),
) -> None:
    """Roll/pitch/yaw and position differences of ESTIMATE minus a reference (paper 000, Fig. 9).

    The common times are the samples of the sparser trajectory; the other is interpolated (position linear, attitude geodesic).
    Differences are estimate minus reference; angle differences are wrapped to (-180, 180] deg.
    """
    with user_errors():
        output_ok(out, force)
        from georefine import api

        evaluation = api.evaluate_trajectory(estimate, reference, out, gps_week=gps_week, span=span)
    comparison, files = evaluation.comparison, evaluation.files
    from rich.table import Table

    table = Table(title=f"{estimate.name} - {reference.name}: {len(comparison)} epochs, "
                  f"{comparison.time[-1]:.1f} s ({comparison.time_base} time base)")
    for column in ("quantity", "unit", "RMSE", "mean", "std", "max |d|"):
        table.add_column(column, justify="left" if column in ("quantity", "unit") else "right")
    for name, unit, *values in comparison.table():
        fmt = "{:.2f}" if unit == "mdeg" else "{:.4f}"
        table.add_row(name, unit, *(fmt.format(v) for v in values))
    stdout.print(table)
    for note in comparison.notes:
        stdout.print(f"note: {note}")
    for path in files:
        stdout.print(f"wrote {path}")


@evaluate_app.command("reference-planes")
def evaluate_reference_planes_cmd(
    points: list[Path] = typer.Argument(..., help="Georeferenced LAS/LAZ strips or folders of them (output CRS)."),
    reference: Path = typer.Option(..., "--reference", "-r", help="Reference surfaces CSV (surface_id,point_id,x,y,z)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Folder for reference_planes.json and .csv."),
    inset: float = typer.Option(0.25, "--inset", help="Margin inside each surveyed outline (m)."),
    max_distance: float = typer.Option(0.3, "--max-distance", help="Points farther from the plane are ignored (m)."),
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Distances of the points to surveyed reference planes per strip x channel (paper 000, Table 1).

    Mean and RMSE over all observations (one observation = mean signed distance of one strip x
    channel on one surface) and AVG-SD, the mean over surfaces of the standard deviation of that
    surface's observations.
    """
    with user_errors():
        output_ok(out, force)
        from georefine import api

        figures = api.evaluate_reference_planes(points, reference, out, inset_m=inset, max_distance_m=max_distance,
                                                scheduler=scheduler)
    from rich.table import Table

    table = Table(title=f"reference planes: {figures.n_observations} observations")
    for column in ("surface", "observations", "mean (mm)", "SD (mm)", "RMSE (mm)"):
        table.add_column(column, justify="left" if column == "surface" else "right")
    for s in figures.surfaces:
        table.add_row(s.surface_id, str(s.observations), f"{s.mean_m * 1e3:.1f}", f"{s.sd_m * 1e3:.1f}",
                      f"{s.rmse_m * 1e3:.1f}")
    stdout.print(table)
    stdout.print(f"Mean {figures.mean_m * 1e3:.1f} mm, RMSE {figures.rmse_m * 1e3:.1f} mm, "
                 f"AVG-SD {figures.avg_sd_m * 1e3:.1f} mm")
    if out is not None:
        stdout.print(f"wrote {out / 'reference_planes.json'} and {out / 'reference_planes.csv'}")


@evaluate_app.command("run")
def evaluate_run_cmd(
    project: Path = typer.Argument(..., help="The simulated project folder (its truth/ is the reference)."),
    run_dir: Path = typer.Argument(..., help="The output folder of `georefine run` on it."),
    single: Optional[Path] = typer.Option(None, "--single", help="A single-pass run of the same project, beside it."),
    scheduler: str = scheduler_option(),
) -> None:
    """A run evaluated against its truth as paper 000 reports it, into RUN/evaluation: trajectory
    differences per strip, reference planes, strip differences, and every pair of strips' differences
    on planar surfaces, for the G/I, the G/I/L and the run's strip-adjustment baseline."""
    with user_errors():
        from georefine import api

        ev = api.evaluate_run(project, run_dir, single, scheduler=scheduler)
    stdout.print("roll / pitch / yaw RMSE (mdeg) against the truth, per strip:")
    for label, t in ev.trajectory.items():
        per = "; ".join(f"{sid}: {f.roll_rmse_mdeg:.2f} / {f.pitch_rmse_mdeg:.2f} / {f.yaw_rmse_mdeg:.2f}"
                        for sid, f in t.strips.items())
        stdout.print(f"  {label}: {per}")
    for label, v in ev.strip_pairs.items():
        measured = v.pairs.measured()
        if measured:
            stdout.print(f"strip pairs, {label}: median {min(p.median_mm for p in measured):.1f}-"
                         f"{max(p.median_mm for p in measured):.1f} mm over {len(measured)} overlapping pairs")
    stdout.print(f"wrote {Path(run_dir) / 'evaluation' / 'summary.json'} and the plots beside it")


@evaluate_app.command("strip-differences")
def evaluate_strip_differences_cmd(
    points: list[Path] = typer.Argument(..., help="Georeferenced LAS/LAZ strips or folders of them (output CRS)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Folder for the map (PNG, GeoTIFF) and JSON."),
    cell: float = typer.Option(1.0, "--cell", help="Raster cell size (m)."),
    max_roughness: float = typer.Option(0.03, "--max-roughness", min=0.0,
                                        help="Planar cells only: RMS plane residual (m)."),
    max_slope: float = typer.Option(60.0, "--max-slope", min=0.0, max=90.0,
                                    help="Planar cells only: steepest plane (degrees)."),
    max_normal_angle: float = typer.Option(5.0, "--max-normal-angle", min=0.0,
                                           help="Largest angle between the planes' normals in a cell (degrees)."),
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Strip differences on a raster (paper 000, Fig. 7): per cell max - min of the plane heights
    of the layers strip x channel that are planar there, along their normal; cells that are not
    a planar surface in every view (wires, vegetation, edges) are gated."""
    with user_errors():
        output_ok(out, force)
        from georefine import api

        m = api.evaluate_strip_differences(points, out, cell_size_m=cell, max_roughness_m=max_roughness,
                                           max_slope_deg=max_slope, max_normal_angle_deg=max_normal_angle,
                                           scheduler=scheduler)
    s, g = m.summary(), m.gating()
    stdout.print(f"strip differences on {s['cells']:,} planar cells of {cell:g} m: median {s['median_m'] * 1e3:.1f} mm, "
                 f"P95 {s['p95_m'] * 1e3:.1f} mm")
    stdout.print(f"gated {g['candidates'] - g['kept']:,} of {g['candidates']:,} cells: " + ", ".join(
        f"{k} {g[k]:,}" for k in ("rough", "steep", "edge", "normals")))
    if out is not None:
        import json

        cov = json.loads((out / "strip_differences.json").read_text(encoding="utf-8")).get("coverage")
        if cov:
            stdout.print(f"point density: median {cov['density_median_per_m2']:.1f} points/m² on {cell:g} m cells, "
                         f"5 % of the area below {cov['density_p5_per_m2']:.1f}; "
                         f"{100 * cov['overlap_share']:.0f} % of {cov['area_km2']:.2f} km² seen from two strips or more")
        import csv

        with open(out / "strip_pairs.csv", newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        medians = [float(r["median_mm"]) for r in rows if r["median_mm"]]
        if medians:
            stdout.print(f"strip pairs: {len(medians)} of {len(rows)} overlap on planar cells, median difference "
                         f"{min(medians):.1f}-{max(medians):.1f} mm")
        elif rows:
            stdout.print(f"strip pairs: none of {len(rows)} has enough common planar cells")
        else:
            stdout.print("strip pairs: none, the points hold one strip (one point source id)")
        stdout.print(f"wrote {out / 'strip_differences.png'}, .tif and .json, coverage_density.png, "
                     "coverage_overlap.png, strip_pairs.csv and strip_pairs.png")
