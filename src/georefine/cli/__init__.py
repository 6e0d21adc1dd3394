"""The ``georefine`` command line. The only package that prints and sets exit codes.

Each subcommand parses its options and calls one function of the public API,
:mod:`georefine.api`, and nothing else of the library (the commands that read results,
``export`` and ``evaluate``, are in :mod:`georefine.cli.tools`; what they share in
:mod:`georefine.cli.common`). Heavy imports are deferred into
the commands so that ``georefine --help`` stays fast. Any :class:`~georefine.errors.GeorefineError`
(bad input, bad configuration) becomes one line on standard error and exit code 2.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Optional

import typer

from georefine import __version__
from georefine.cli.common import force_option, output_ok, progress, scheduler_option, stdout, user_errors
from georefine.cli.tools import evaluate_app, export_app
from georefine.steps import steps_text

app = typer.Typer(
    rich_markup_mode=None,  # plain help: units in brackets stay, on/off flags show as flags
    name="georefine",
    help="Rigorous georeferencing of airborne LiDAR and aerial images.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(export_app, name="export")
app.add_typer(evaluate_app, name="evaluate")


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
    level = logging.INFO if verbose else logging.WARNING
    logging.basicConfig(
        level=level,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
        force=True,  # this command's stderr, also when the application runs again in one process (the tests)
    )
    for handler in logging.getLogger().handlers:  # the output folder's log takes INFO whatever --verbose says
        handler.setLevel(level)
    # laspy logs a read error before raising it; the reader turns it into the command's one line
    logging.getLogger("laspy").setLevel(logging.CRITICAL)


@app.command()
def simulate(
    scenario: str = typer.Argument(..., help="Scenario name: corridor, corridor-tiny, corridor-paper (1.8 MHz), corridor-paper-full (30 km at 1.8 MHz), block (photos and jammed GNSS), area (8 parallel and 2 cross strips) or area-tiny."),
    out: Path = typer.Option(..., "--out", "-o", help="Project folder to create (must not exist or be empty)."),
    seed: int = typer.Option(42, "--seed", help="Random seed; the same seed gives the same files."),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Override a parameter: key.sub=value (repeatable)."),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML file with parameter overrides."),
    imu_grade: Optional[str] = typer.Option(None, "--imu-grade", help="IMU grade: navigation, tactical, mems or ideal; or the unit stim300 (mems with every error its datasheet states)."),
    gnss_grade: Optional[str] = typer.Option(None, "--gnss-grade", help="GNSS grade: ppk (default) or ideal."),
    imr: bool = typer.Option(False, "--imr", help="Also write the IMU data as a NovAtel .imr file."),
    # sync: Embree and the LAZ encoder already use both cores (BENCHMARKS.md, "Scenario simulation").
    scheduler: str = scheduler_option("sync"),
) -> None:
    """Simulate a flight and write a project folder with real file formats and the truth."""
    with user_errors():
        from georefine import api

        with progress() as report:
            result = api.simulate(
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
    with user_errors():
        from georefine import api

        with progress() as report:
            summary = api.check(project, progress=report)
    stdout.print(summary.summary())


@app.command()
def trajectory(
    project: Path = typer.Argument(..., help="Project folder with project.yaml."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    filter_only: bool = typer.Option(False, "--filter-only", help=f"Stop after {steps_text(1)}, the filter."),
    force: bool = force_option(),
) -> None:
    """Estimate the trajectory from GNSS and IMU (workflow steps 1-2).

    Writes trajectory.sbet (IMU rate, seconds of the GPS week; the week in trajectory.sbet.json, the
    posterior sigma in smrmsg_trajectory.out), trajectory.csv (output CRS, roll/pitch/heading and
    posterior sigma), adjustment.json (statistics, IMU errors, timings) and the resolved
    configuration.
    """
    with user_errors():
        output_ok(out, force, project)
        from georefine import api

        with progress(out) as report:
            result = api.estimate_trajectory(project, out, filter_only=filter_only, progress=report)
    stdout.print(result.summary())


@app.command()
def run(
    project: Path = typer.Argument(..., help="Project folder with project.yaml."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    strips: Optional[str] = typer.Option(None, "--strips", help="Comma-separated strip ids (point_source_id) to use."),
    no_lidar: bool = typer.Option(
        False, "--no-lidar", help=f"No LiDAR adjustment: only {steps_text(1, 2, 6)}: the G/I trajectory and its "
        "point clouds."),
    fresh: bool = typer.Option(False, "--fresh", help="Recompute every step instead of resuming from OUT/.cache."),
    no_points: bool = typer.Option(False, "--no-points", help=f"Skip {steps_text(6)}: no point clouds."),
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Run the whole workflow: filter, G/I adjustment, planar features, G/I/L adjustment, point clouds.

    Writes gi/ and gil/ (trajectory.sbet with trajectory.sbet.json and smrmsg_trajectory.out,
    trajectory.csv, adjustment.json), points/*.laz,
    features/ (features.csv, objects.csv), metrics.json and the resolved configuration. Each
    step's result is cached in OUT/.cache: a rerun resumes what its inputs have not changed.
    """
    with user_errors():
        output_ok(out, force, project)
        from georefine import api
        from georefine.errors import InputError

        ids = None
        if strips:
            try:
                ids = [int(x) for x in strips.split(",") if x.strip()]
            except ValueError:
                raise InputError("strip ids must be integers", field="--strips", found=repr(strips)) from None
        try:
            with progress(out) as report:
                result = api.run(project, out, strips=ids, lidar=not no_lidar, resume=not fresh,
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
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Georeference the project's strips with a trajectory (LAZ 1.4 in the output CRS)."""
    with user_errors():
        output_ok(out, force, project)
        from georefine import api

        with progress(out) as report:
            result = api.georeference(project, trajectory_file, out, gps_week=gps_week, progress=report,
                                      scheduler=scheduler)
    stdout.print(result.summary())


@app.command()
def clean(
    out: Path = typer.Argument(..., help="An output folder Georefine made (a run, a demo, ...)."),
    everything: bool = typer.Option(False, "--all", help="Remove the whole folder, results included."),
) -> None:
    """Free the disk space of an output folder: its step caches (OUT/.cache, and those of the runs
    inside a demo's folder), after which a rerun recomputes every step; with --all the folder.
    Only folders Georefine made are touched."""
    with user_errors():
        from georefine import api

        result = api.clean(out, everything=everything)
    if not result.removed:
        stdout.print(f"nothing to clean in {out}: no step cache")
        return
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
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Make a project from delivered data: georeferenced strips and their SBET (+ smrmsg, + raw IMU).

    Every point goes back into the scanner frame with the SBET, the lever arm and the boresight;
    `georefine run PROJECT --out RUN` then adjusts the SBET with the LiDAR planes.
    """
    with user_errors():
        output_ok(out, force)
        from georefine import api

        arm, bs = _vector3(lever_arm, "--lever-arm"), _vector3(boresight, "--boresight")
        with progress(out) as report:
            result = api.import_strips(strips, sbet, out, lever_arm_m=arm, boresight_deg=bs, smrmsg=smrmsg,
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
    boresight: bool = typer.Option(True, "--boresight/--no-boresight", help="corridor: also calibrate a boresight "
                                   "stated 0.05 deg off (both passes, OUT/run-boresight)."),
    method: str = typer.Option("sift", "--method", help="block: matcher, sift or xfeat."),
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
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
    with user_errors():
        output_ok(out, force)
        from georefine import api

        with progress(out) as report:
            result = api.run_demo(out, scenario=scenario, seed=seed, overrides=overrides or [],
                                  single_pass=single_pass, boresight=boresight, progress=report, scheduler=scheduler)
    from rich.table import Table

    m = result.metrics
    table = Table(title=f"Georefine demo ({scenario}, seed {seed}) against {m.evaluation.reference}, beside paper 000")
    for column in ("quantity", "paper 000 (G/I / G/I/L / single pass)", "G/I", "G/I/L", "single-pass G/I/L",
                   "against paper 000 (✗: the paper's is better)"):
        table.add_column(column, justify="left" if column == "quantity" else "right")
    for row in result.summary_table():
        table.add_row(*row)
    stdout.print(table)
    b = m.evaluation.boresight
    if b is not None:
        err, sig = b.error_mdeg, b.sigma_mdeg
        stdout.print("boresight calibration (started "
                     + ", ".join(f"{1e3 * (s - t):+.0f}" for s, t in zip(b.stated_deg, b.true_deg))
                     + " mdeg off): roll/pitch/yaw error " + " / ".join(f"{e:+.1f}" for e in err)
                     + " mdeg, sigma " + " / ".join(f"{s:.1f}" for s in sig) + " mdeg")
    stdout.print("timings: " + ", ".join(f"{k} {v:.0f} s" for k, v in m.timings_s.items()))
    stdout.print(f"report: {result.report.resolve()}")


def _block_demo(out: Path, seed: int, overrides: list[str], method: str, scheduler: str, force: bool) -> None:
    with user_errors():
        output_ok(out, force)
        if method not in ("sift", "xfeat"):  # before progress() makes the folder
            from georefine.errors import InputError

            raise InputError("unknown matching method for the demo", field="--method", expected="sift or xfeat",
                             found=method)
        from georefine import api

        with progress(out) as report:
            result = api.run_demo(out, scenario="block", seed=seed, overrides=overrides, method=method,
                                  progress=report, scheduler=scheduler)
    from rich.table import Table

    table = Table(title=f"Georefine demo (block, seed {seed}): co-adjustment, beside paper 004")
    for column in ("case", "points", "RMSE X [m]", "RMSE Y [m]", "RMSE Z [m]", "RE [px]", "Graz X / Y / Z, RE",
                   "Loosdorf X / Y / Z, RE", "against Graz (✗: the paper's is better)"):
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
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Render lidargrams at the photos' approximate orientation: OUT/NAME.png and NAME.npz (ULPI raster).

    Also writes the resolved configuration (config.resolved.yaml).
    """
    with user_errors():
        output_ok(out, force, project)
        from georefine import api

        with progress(out) as report:
            names = api.render_lidargrams(project, points, out, progress=report, scheduler=scheduler,
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
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Render lidargrams and match photos and lidargrams (verified matches, tracks, pictures).

    Writes OUT/lidargrams/, pairs.csv, matches.csv, tracks.csv, matches_<kind>.png, summary.json
    and the resolved configuration (config.resolved.yaml). Options given override
    processing.lidargrammetry of project.yaml.
    """
    with user_errors():
        output_ok(out, force, project)
        from georefine import api

        kinds = None if pairs is None else [k.strip() for k in pairs.split(",") if k.strip()]
        overrides = {**_matcher(method, features, extractor_weights, lightglue_weights),
                     **_given(pair_kinds=kinds, lidargram_scale=scale)}
        with progress(out) as report:
            summary = api.match(project, points, out, overrides=overrides, progress=report, scheduler=scheduler)
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
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """Co-match photos and lidargrams and co-adjust them (paper 004, cases 1-3).

    Writes eop_photos.csv and eop_lidargrams.csv (output CRS), points/*.laz (cases 1 and 2: the
    refined cloud, same point order as the input), matches_lidargram_photo.png, metrics.json and
    the resolved configuration (config.resolved.yaml). Options given override
    processing.lidargrammetry of project.yaml.
    """
    with user_errors():
        output_ok(out, force, project)
        from georefine import api

        sig_r = None if sigma_rotation is None else [v.strip() for v in sigma_rotation.split(",")]
        overrides = {**_matcher(method, features, extractor_weights, lightglue_weights),
                     **_given(use_depth=False if no_depth else None, lidargram_sigma_position_m=sigma_position,
                              lidargram_sigma_rotation_deg=sig_r)}
        with progress(out) as report:
            m = api.coadjust(project, points, out, case, overrides=overrides, progress=report, scheduler=scheduler)
    stdout.print(f"case {case}: {m.description}")
    for label, st in (("control points", m.control_points), ("check points", m.check_points)):
        if st is not None:
            x, y, z = st.rmse_xyz_m
            stdout.print(f"  {label} ({st.n}): RMSE X {x:.3f} Y {y:.3f} Z {z:.3f} m, RE {st.reprojection_px:.2f} px")
    pl = m.photo_lidargram_matches
    stdout.print(f"  {m.photos} photos, {m.lidargrams} lidargrams, {pl.n_pairs} photo-lidargram pairs "
                 f"(median {pl.median_verified:.0f} verified matches), {m.tracks} tie points")
    stdout.print(f"  results in {out}")


@app.command()
def hybrid(
    project: Path = typer.Argument(..., help="Project folder with GNSS, IMU, scans and a photos section."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (outside the project)."),
    case: int = typer.Option(1, "--case", help="1: photo block first, then fixed; 2: photos and trajectory together."),
    planes: bool = typer.Option(
        True, "--planes/--no-planes",
        help="Start from the G/I/L adjustment and keep its plane observations (off: from the G/I adjustment)."),
    keypoint_offset: bool = typer.Option(
        False, "--keypoint-offset",
        help="A return observes the keypoint's surface point beside it, not itself (sparse clouds)."),
    method: Optional[str] = typer.Option(None, "--method", help=_METHOD_HELP),
    features: Optional[str] = typer.Option(None, "--lightglue-features", help="LightGlue's features: disk or aliked."),
    extractor_weights: Optional[Path] = typer.Option(None, "--extractor-weights", help="DISK/ALIKED weights (.pth)."),
    lightglue_weights: Optional[Path] = typer.Option(None, "--lightglue-weights", help="LightGlue weights (.pth)."),
    fresh: bool = typer.Option(False, "--fresh", help="Recompute every step instead of resuming from OUT/.cache."),
    scheduler: str = scheduler_option(),
    force: bool = force_option(),
) -> None:
    """One adjustment of GNSS, IMU, LiDAR and photos: lidargram ties on the continuous-time trajectory.

    Lidargram keypoints observe the trajectory through the LiDAR returns they show; the photos
    observe the same tie points. Writes gi/ (and with planes gil/, features/), preliminary/points
    (the cloud the lidargrams are rendered from), hybrid/ (the adjusted trajectory and
    adjustment.json), points/*.laz (every point re-georeferenced, same order as the scans),
    eop_photos.csv, metrics.json and the resolved configuration. Options given override
    processing.lidargrammetry of project.yaml.
    """
    with user_errors():
        output_ok(out, force, project)
        from georefine import api

        overrides = {**_matcher(method, features, extractor_weights, lightglue_weights),
                     **_given(return_keypoint_offset=True if keypoint_offset else None)}
        with progress(out) as report:
            m = api.adjust_hybrid(project, out, case=case, planes=planes, overrides=overrides, resume=not fresh,
                                  progress=report, scheduler=scheduler)
    stdout.print(m.summary())
    stdout.print(f"  results in {out}")
