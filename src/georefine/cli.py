"""The ``georefine`` command line. The only module that prints and sets exit codes.

Each subcommand wires files around one library function. Heavy imports are deferred into
the commands so that ``georefine --help`` stays fast. Any :class:`~georefine.errors.GeorefineError`
(bad input, bad configuration) becomes one line on standard error and exit code 2.
"""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

import typer
from rich.console import Console

from georefine import __version__
from georefine.errors import GeorefineError

app = typer.Typer(
    name="georefine",
    help="Rigorous georeferencing of airborne LiDAR and aerial images.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
stdout = Console(soft_wrap=True)


def _version_callback(value: bool) -> None:
    if value:
        stdout.print(f"georefine {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True, help="Show the version and exit."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details to standard error."),
) -> None:
    """Georefine: tightly-coupled GNSS/IMU/LiDAR trajectory estimation and lidargrammetry."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    # laspy logs a read error before raising it; the reader turns it into the command's one line
    logging.getLogger("laspy").setLevel(logging.CRITICAL)


_SCHEDULER_HELP = ("Where the per-tile work runs: sync, threads, processes (a local Dask cluster, one worker "
                   "process per core) or the address of a running dask scheduler, e.g. tcp://127.0.0.1:8786. "
                   "Results do not depend on it.")


def _scheduler_option(default: str = "threads"):
    """``--scheduler``; ``default`` is the scheduler measured fastest on 2 cores for the command."""
    return typer.Option(default, "--scheduler", envvar="GEOREFINE_SCHEDULER",
                        help=f"{_SCHEDULER_HELP} Default {default}: the fastest here on 2 cores.")


def _force_option():
    return typer.Option(False, "--force", help="Write into an output folder that holds files Georefine did not write "
                        "(its files of the same names are replaced).")


def _output_ok(out: Optional[Path], force: bool) -> None:
    """Refuse an output folder that holds files Georefine did not write, unless --force (io.files.refuse_foreign_output)."""
    if out is not None:
        from georefine.io.files import refuse_foreign_output

        refuse_foreign_output(out, force)


@contextmanager
def _user_errors() -> Iterator[None]:
    """Turn library errors into one message and exit code 2."""
    try:
        yield
    except GeorefineError as exc:
        console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(2) from None


@contextmanager
def _progress() -> Iterator:
    """A rich progress bar; yields ``report(task, done, total)`` for the library to call."""
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("{task.description:<28}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=not console.is_terminal,
    ) as progress:
        tasks: dict[str, int] = {}

        def report(name: str, done: float, total: float) -> None:
            if name not in tasks:
                tasks[name] = progress.add_task(name, total=total)
            progress.update(tasks[name], completed=done, total=total)

        yield report


@app.command()
def simulate(
    scenario: str = typer.Argument(..., help="Scenario name: corridor, corridor-tiny, corridor-paper (1.8 MHz) or block."),
    out: Path = typer.Option(..., "--out", "-o", help="Project folder to create (must not exist or be empty)."),
    seed: int = typer.Option(42, "--seed", help="Random seed; the same seed gives the same files."),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Override a parameter: key.sub=value (repeatable)."),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML file with parameter overrides."),
    imu_grade: Optional[str] = typer.Option(None, "--imu-grade", help="IMU grade: navigation, tactical, mems or ideal."),
    gnss_grade: Optional[str] = typer.Option(None, "--gnss-grade", help="GNSS grade: ppk (default) or ideal."),
    imr: bool = typer.Option(False, "--imr", help="Also write the IMU data as a NovAtel .imr file."),
    # sync: Embree and the LAZ encoder already use both cores (BENCHMARKS.md, "Scenario simulation").
    scheduler: str = _scheduler_option("sync"),
) -> None:
    """Simulate a flight and write a project folder with real file formats and the truth."""
    with _user_errors():
        from georefine.sim.scenarios import simulate_project

        with _progress() as report:
            result = simulate_project(
                scenario,
                out,
                seed=seed,
                overrides=list(set_ or []),
                config_file=config,
                imu_grade=imu_grade,
                gnss_grade=gnss_grade,
                write_imr=imr,
                progress=report,
                scheduler=scheduler,
            )
    stdout.print(result.summary())


@app.command()
def check(
    project: Path = typer.Argument(..., help="Project folder with project.yaml."),
) -> None:
    """Validate a project: project.yaml and every sensor file it names, and their time spans."""
    with _user_errors():
        from georefine.workflows.project import inspect_project

        with _progress() as report:
            summary = inspect_project(project, progress=report)
    stdout.print(summary.summary())


@app.command()
def trajectory(
    project: Path = typer.Argument(..., help="Project folder with project.yaml."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    filter_only: bool = typer.Option(False, "--filter-only", help="Stop after the initialisation filter (step 1)."),
    force: bool = _force_option(),
) -> None:
    """Estimate the trajectory from GNSS and IMU (workflow steps 1-2).

    Writes trajectory.sbet (IMU rate, seconds of the GPS week; the week in trajectory.sbet.json, the
    posterior sigma in smrmsg_trajectory.out), trajectory.csv (output CRS, roll/pitch/heading and
    posterior sigma), adjustment.json (statistics, IMU errors, timings) and the resolved
    configuration.
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.workflows import run_trajectory

        with _progress() as report:
            result = run_trajectory(project, out, filter_only=filter_only, progress=report)
    stdout.print(result.summary())


@app.command()
def run(
    project: Path = typer.Argument(..., help="Project folder with project.yaml."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    strips: Optional[str] = typer.Option(None, "--strips", help="Comma-separated strip ids (point_source_id) to use."),
    no_lidar: bool = typer.Option(
        False, "--no-lidar", help="No LiDAR adjustment: steps 1, 2 and 6 (the G/I trajectory and its point clouds)."),
    fresh: bool = typer.Option(False, "--fresh", help="Recompute every step instead of resuming from OUT/.cache."),
    no_points: bool = typer.Option(False, "--no-points", help="Skip the final point clouds (step 6)."),
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Run the whole workflow: filter, G/I adjustment, planar features, G/I/L adjustment, point clouds.

    Writes gi/ and gil/ (trajectory.sbet with trajectory.sbet.json and smrmsg_trajectory.out,
    trajectory.csv, adjustment.json), points/*.laz,
    features/ (features.csv, objects.csv), metrics.json and the resolved configuration. Each
    step's result is cached in OUT/.cache: a rerun resumes what its inputs have not changed.
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.errors import InputError
        from georefine.workflows.lidar import run_workflow

        ids = None
        if strips:
            try:
                ids = [int(x) for x in strips.split(",") if x.strip()]
            except ValueError:
                raise InputError("strip ids must be integers", field="--strips", found=repr(strips)) from None
        try:
            with _progress() as report:
                result = run_workflow(project, out, strips=ids, lidar=not no_lidar, resume=not fresh,
                                      points=not no_points, progress=report, scheduler=scheduler)
        except InputError as exc:
            if exc.field != "strips":
                raise
            # The library names its parameter; the user gave it as --strips.
            raise InputError(exc.message, field="--strips", expected=exc.expected, found=exc.found) from None
    stdout.print(result.summary())


@app.command()
def georeference(
    project: Path = typer.Argument(..., help="Project folder with project.yaml."),
    trajectory_file: Path = typer.Option(..., "--trajectory", help="Trajectory SBET (IMU, WGS84)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder for the LAZ strips."),
    gps_week: Optional[int] = typer.Option(None, "--gps-week", help="GPS week of an SBET in seconds of week without "
                                           "a companion file (default: the week of the strips' GPS time)."),
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Georeference the project's strips with a trajectory (LAZ 1.4 in the output CRS)."""
    with _user_errors():
        _output_ok(out, force)
        from georefine.workflows import run_georeference

        with _progress() as report:
            result = run_georeference(project, trajectory_file, out, gps_week=gps_week, progress=report,
                                      scheduler=scheduler)
    stdout.print(result.summary())


def _vector3(text: str, option: str) -> tuple[float, float, float]:
    """``"x,y,z"`` as three floats (an InputError naming ``option`` otherwise)."""
    from georefine.errors import InputError

    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        v = ()
    if len(v) != 3:
        raise InputError("three comma-separated numbers expected", field=option, expected="x,y,z", found=repr(text))
    return v  # type: ignore[return-value]


@app.command("import-strips")
def import_strips_cmd(
    strips: list[Path] = typer.Argument(..., help="Georeferenced LAS/LAZ strips (projected CRS, GPS time)."),
    sbet: Path = typer.Option(..., "--sbet", help="The trajectory they were georeferenced with (SBET)."),
    out: Path = typer.Option(..., "--out", "-o", help="Project folder to write."),
    lever_arm: str = typer.Option(..., "--lever-arm", help="Scanner origin in the IMU body frame, x,y,z (m, FRD)."),
    boresight: str = typer.Option("0,0,0", "--boresight", help="Boresight roll,pitch,yaw (deg) of R_b_s."),
    smrmsg: Optional[Path] = typer.Option(
        None, "--smrmsg", help="The SBET's smrmsg accuracy file (default: smrmsg_X.out beside sbet_X.out, if there)."),
    gps_week: Optional[int] = typer.Option(
        None, "--gps-week", help="GPS week of the SBET (default: the first strip's, from its adjusted GPS time)."),
    imu: Optional[Path] = typer.Option(
        None, "--imu", help="YAML with the imu section of project.yaml for the raw IMU (its file relative to the "
        "YAML): the SBET's positions and the raw IMU then observe the trajectory."),
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Make a project from delivered data: georeferenced strips and their SBET (+ smrmsg, + raw IMU).

    Every point goes back into the scanner frame with the SBET, the lever arm and the boresight;
    `georefine run PROJECT --out RUN` then adjusts the SBET with the LiDAR planes.
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.workflows.import_strips import import_strips

        arm, bs = _vector3(lever_arm, "--lever-arm"), _vector3(boresight, "--boresight")
        with _progress() as report:
            result = import_strips(strips, sbet, out, lever_arm_m=arm, boresight_deg=bs, smrmsg=smrmsg,
                                   gps_week=gps_week, imu=imu, progress=report, scheduler=scheduler)
    stdout.print(result.summary())


@app.command()
def demo(
    out: Optional[Path] = typer.Option(None, "--out", "-o",
                                       help="Output folder (default georefine-demo, or georefine-demo-block)."),
    scenario: str = typer.Option("corridor", "--scenario",
                                 help="corridor (paper 000: trajectory) or block (paper 004: lidargrammetry)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Simulation seed (default 42 corridor, 3 block)."),
    overrides: Optional[list[str]] = typer.Option(None, "--set", help="Scenario override key.sub=value (repeatable)."),
    single_pass: bool = typer.Option(True, "--single-pass/--no-single-pass", help="Also run the single-pass case."),
    method: str = typer.Option("sift", "--method", help="block: matcher, sift or xfeat."),
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Simulate a scenario, run the whole method on it, evaluate it as the paper does and write
    OUT/report.html and OUT/metrics.json.

    corridor: the whole workflow of paper 000 (both passes and a single pass). block: the
    jammed G/I cloud and the three co-adjustment cases of paper 004.
    """
    if scenario == "block":
        _block_demo(out or Path("georefine-demo-block"), 3 if seed is None else seed, overrides or [], method,
                    scheduler, force)
        return
    out = out or Path("georefine-demo")
    seed = 42 if seed is None else seed
    with _user_errors():
        _output_ok(out, force)
        from georefine.demo.corridor import run_demo

        with _progress() as report:
            result = run_demo(out, scenario=scenario, seed=seed, overrides=overrides or [], single_pass=single_pass,
                              progress=report, scheduler=scheduler)
    from rich.table import Table

    m = result.metrics
    table = Table(title=f"Georefine demo ({scenario}, seed {seed}) against {m.evaluation.reference}, beside paper 000")
    for column in ("quantity", "paper 000 (G/I / G/I/L / single pass)", "G/I", "G/I/L", "single-pass G/I/L"):
        table.add_column(column, justify="left" if column == "quantity" else "right")
    for row in result.summary_table():
        table.add_row(*row)
    stdout.print(table)
    stdout.print("timings: " + ", ".join(f"{k} {v:.0f} s" for k, v in m.timings_s.items()))
    stdout.print(f"report: {result.report.resolve()}")


def _block_demo(out: Path, seed: int, overrides: list[str], method: str, scheduler: str, force: bool) -> None:
    with _user_errors():
        _output_ok(out, force)
        if method not in ("sift", "xfeat"):
            from georefine.errors import InputError

            raise InputError("unknown matching method for the demo", field="--method", expected="sift or xfeat",
                             found=method)
        from georefine.demo.block import run_block_demo

        with _progress() as report:
            result = run_block_demo(out, seed=seed, overrides=overrides, method=method, progress=report,
                                    scheduler=scheduler)
    from rich.table import Table

    table = Table(title=f"Georefine demo (block, seed {seed}): co-adjustment, beside paper 004")
    for column in ("case", "points", "RMSE X [m]", "RMSE Y [m]", "RMSE Z [m]", "RE [px]", "Graz X / Y / Z, RE",
                   "Loosdorf X / Y / Z, RE"):
        table.add_column(column, justify="left" if column in ("case", "points") else "right")
    for row in result.summary_table():
        table.add_row(*row)
    stdout.print(table)
    for case, d in sorted(result.metrics.refined_cloud.items()):
        stdout.print(f"case {case}: refined cloud RMS {d.rms_before_m:.3f} -> {d.rms_after_m:.3f} m "
                     f"({d.ratio:.2f}x the jammed cloud's error) over {d.points:,} points inside the block")
    stdout.print("timings: " + ", ".join(f"{k} {v:.0f} s" for k, v in result.metrics.timings_s.items()))
    stdout.print(f"report: {result.report.resolve()}")


_FROM_CONFIG = "Default: processing.lidargrammetry in project.yaml, else"


def _given(**options) -> dict:
    """The options given on the command line (not None) as ``processing.lidargrammetry`` overrides."""
    return {k: v for k, v in options.items() if v is not None}


@app.command()
def lidargrams(
    project: Path = typer.Argument(..., help="Project folder with a photos section in project.yaml."),
    points: list[Path] = typer.Option(..., "--points", "-p", help="Georeferenced LAZ strips or their folder (output CRS)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    scale: Optional[float] = typer.Option(
        None, "--scale", help=f"Lidargram resolution relative to the photos. {_FROM_CONFIG} 0.5."),
    merged: bool = typer.Option(False, "--merged", help="One lidargram per photo of all strips together."),
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Render lidargrams at the photos' approximate orientation: OUT/NAME.png and NAME.npz (ULPI raster).

    Also writes the resolved configuration (config.resolved.yaml).
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.workflows.lidargrammetry import run_lidargrams

        with _progress() as report:
            names = run_lidargrams(project, points, out, progress=report, scheduler=scheduler,
                                   overrides=_given(lidargram_scale=scale, per_strip=False if merged else None))
    stdout.print(f"{len(names)} lidargrams written to {out}")


_METHOD_HELP = ("Matcher: sift, xfeat (the deep extra), or lightglue (the deep extra and local weight files). "
                f"{_FROM_CONFIG} sift.")


def _matcher(method: Optional[str], features: Optional[str], extractor_weights: Optional[Path],
             lightglue_weights: Optional[Path]) -> dict:
    """The matcher options given, as overrides; weight files made absolute (project.yaml's are relative
    to the project folder, the command line's to the working directory)."""
    return _given(matcher=method, lightglue_features=features,
                  extractor_weights=None if extractor_weights is None else str(extractor_weights.resolve()),
                  lightglue_weights=None if lightglue_weights is None else str(lightglue_weights.resolve()))


@app.command()
def match(
    project: Path = typer.Argument(..., help="Project folder with a photos section in project.yaml."),
    points: list[Path] = typer.Option(..., "--points", "-p", help="Georeferenced LAZ strips or their folder (output CRS)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    method: Optional[str] = typer.Option(None, "--method", help=_METHOD_HELP),
    pairs: Optional[str] = typer.Option(
        None, "--pairs", help="Pair kinds, comma-separated: photo-photo, photo-lidargram, lidargram-lidargram. "
        f"{_FROM_CONFIG} photo-photo,photo-lidargram."),
    scale: Optional[float] = typer.Option(
        None, "--scale", help=f"Lidargram resolution relative to the photos. {_FROM_CONFIG} 0.5."),
    features: Optional[str] = typer.Option(None, "--lightglue-features", help="LightGlue's features: disk or aliked."),
    extractor_weights: Optional[Path] = typer.Option(None, "--extractor-weights", help="DISK/ALIKED weights (.pth)."),
    lightglue_weights: Optional[Path] = typer.Option(None, "--lightglue-weights", help="LightGlue weights (.pth)."),
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Render lidargrams and match photos and lidargrams (verified matches, tracks, pictures).

    Writes OUT/lidargrams/, pairs.csv, matches.csv, tracks.csv, matches_<kind>.png, summary.json
    and the resolved configuration (config.resolved.yaml). Options given override
    processing.lidargrammetry of project.yaml.
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.workflows.lidargrammetry import run_match

        kinds = None if pairs is None else [k.strip() for k in pairs.split(",") if k.strip()]
        overrides = {**_matcher(method, features, extractor_weights, lightglue_weights),
                     **_given(pair_kinds=kinds, lidargram_scale=scale)}
        with _progress() as report:
            summary = run_match(project, points, out, overrides=overrides, progress=report, scheduler=scheduler)
    stdout.print(f"{summary.photos} photos, {summary.lidargrams} lidargrams, {summary.tracks} tracks")
    for k in summary.pair_kinds:
        stdout.print(f"  {k.kind}: {k.pairs} pairs ({k.pairs_with_matches} with matches), "
                     f"median {k.median_verified:.0f} verified matches")
    stdout.print(f"  results in {out}")


@app.command()
def coadjust(
    project: Path = typer.Argument(..., help="Project folder with a photos section in project.yaml."),
    points: list[Path] = typer.Option(..., "--points", "-p", help="Georeferenced LAZ strips or their folder (output CRS)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    case: int = typer.Option(..., "--case", help="1: refine LiDAR, 2: photos and LiDAR, 3: refine photos (paper 004)."),
    method: Optional[str] = typer.Option(None, "--method", help=_METHOD_HELP),
    features: Optional[str] = typer.Option(None, "--lightglue-features", help="LightGlue's features: disk or aliked."),
    extractor_weights: Optional[Path] = typer.Option(None, "--extractor-weights", help="DISK/ALIKED weights (.pth)."),
    lightglue_weights: Optional[Path] = typer.Option(None, "--lightglue-weights", help="LightGlue weights (.pth)."),
    no_depth: bool = typer.Option(False, "--no-depth", help="Image-only lidargram observations (the paper's formulation)."),
    sigma_position: Optional[float] = typer.Option(
        None, "--lidargram-sigma-position", help=f"A-priori sigma of lidargram positions [m]. {_FROM_CONFIG} 1.0."),
    sigma_rotation: Optional[str] = typer.Option(
        None, "--lidargram-sigma-rotation",
        help=f"A-priori sigma of lidargram rotations about the camera x,y,z axes [deg], one or three "
        f"comma-separated. {_FROM_CONFIG} 0.01,0.01,0.1."),
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Co-match photos and lidargrams and co-adjust them (paper 004, cases 1-3).

    Writes eop_photos.csv and eop_lidargrams.csv (output CRS), points/*.laz (cases 1 and 2: the
    refined cloud, same point order as the input), matches_lidargram_photo.png, metrics.json and
    the resolved configuration (config.resolved.yaml). Options given override
    processing.lidargrammetry of project.yaml.
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.workflows.lidargrammetry import run_coadjust

        sig_r = None if sigma_rotation is None else [v.strip() for v in sigma_rotation.split(",")]
        overrides = {**_matcher(method, features, extractor_weights, lightglue_weights),
                     **_given(use_depth=False if no_depth else None, lidargram_sigma_position_m=sigma_position,
                              lidargram_sigma_rotation_deg=sig_r)}
        with _progress() as report:
            m = run_coadjust(project, points, out, case, overrides=overrides, progress=report, scheduler=scheduler)
    stdout.print(f"case {case}: {m.description}")
    for label, st in (("control points", m.control_points), ("check points", m.check_points)):
        if st is not None:
            x, y, z = st.rmse_xyz_m
            stdout.print(f"  {label} ({st.n}): RMSE X {x:.3f} Y {y:.3f} Z {z:.3f} m, RE {st.reprojection_px:.2f} px")
    pl = m.photo_lidargram_matches
    stdout.print(f"  {m.photos} photos, {m.lidargrams} lidargrams, {pl.n_pairs} photo-lidargram pairs "
                 f"(median {pl.median_verified:.0f} verified matches), {m.tracks} tie points")
    stdout.print(f"  results in {out}")


# ---------------------------------------------------------------------------
# georefine export ...
# ---------------------------------------------------------------------------

export_app = typer.Typer(
    help="Write results in the formats of other tools (trajectories for evo and trajectopy, ...).",
    no_args_is_help=True,
)
app.add_typer(export_app, name="export")


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
    with _user_errors():
        from georefine.workflows.products import export_trajectory

        result = export_trajectory(source, out, fmt, epsg=epsg, gps_week=gps_week)
    stdout.print(result.summary())


# ---------------------------------------------------------------------------
# georefine evaluate ...
# ---------------------------------------------------------------------------

evaluate_app = typer.Typer(
    help="Evaluate results against a reference (trajectory differences, ...).",
    no_args_is_help=True,
)
app.add_typer(evaluate_app, name="evaluate")


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
    force: bool = _force_option(),
) -> None:
    """Roll/pitch/yaw and position differences of ESTIMATE minus a reference (paper 000, Fig. 9).

    The common times are the samples of the sparser trajectory; the other is interpolated (position linear, attitude geodesic).
    Differences are estimate minus reference; angle differences are wrapped to (-180, 180] deg.
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.evaluation.trajectory_files import (
            compare_sbet_files,
            write_trajectory_evaluation,
        )

        comparison = compare_sbet_files(estimate, reference, gps_week=gps_week, time_window=span)
        files = (
            write_trajectory_evaluation(out, comparison, protect=(estimate, reference)).all()
            if out is not None else ()
        )
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
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Distances of the points to surveyed reference planes per strip x channel (paper 000, Table 1).

    Mean and RMSE over all observations (one observation = mean signed distance of one strip x
    channel on one surface) and AVG-SD, the mean over surfaces of the standard deviation of that
    surface's observations.
    """
    with _user_errors():
        _output_ok(out, force)
        from georefine.evaluation.clouds import evaluate_reference_planes, point_files
        from georefine.evaluation.summary import ReferencePlaneFigures
        from georefine.tasks import TaskRunner

        files = point_files(points)
        with TaskRunner(scheduler) as runner:
            _, summary = evaluate_reference_planes(files, reference, out, inset_m=inset, max_distance_m=max_distance,
                                                   runner=runner)
        figures = ReferencePlaneFigures.from_summary(summary)
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
    scheduler: str = _scheduler_option(),
    force: bool = _force_option(),
) -> None:
    """Strip differences on a raster (paper 000, Fig. 7): per cell max - min of the plane heights
    of the layers strip x channel that are planar there, along their normal; cells that are not
    a planar surface in every view (wires, vegetation, edges) are gated."""
    with _user_errors():
        _output_ok(out, force)
        from georefine.evaluation.clouds import evaluate_strip_differences, point_files
        from georefine.tasks import TaskRunner

        files = point_files(points)
        with TaskRunner(scheduler) as runner:
            m = evaluate_strip_differences(files, out, cell_size_m=cell, max_roughness_m=max_roughness,
                                           max_slope_deg=max_slope, max_normal_angle_deg=max_normal_angle, runner=runner)
    s, g = m.summary(), m.gating()
    stdout.print(f"strip differences on {s['cells']:,} planar cells of {cell:g} m: median {s['median_m'] * 1e3:.1f} mm, "
                 f"P95 {s['p95_m'] * 1e3:.1f} mm")
    stdout.print(f"gated {g['candidates'] - g['kept']:,} of {g['candidates']:,} cells: " + ", ".join(
        f"{k} {g[k]:,}" for k in ("rough", "steep", "edge", "normals")))
    if out is not None:
        stdout.print(f"wrote {out / 'strip_differences.png'}, .tif and .json")


if __name__ == "__main__":  # pragma: no cover
    app()
