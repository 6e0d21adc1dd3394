"""`georefine demo`: the whole story of paper 000 from one command.

1. Simulate the scenario (default ``corridor``) into ``OUT/project`` -- kept and reused when a
   previous demo simulated the same scenario, seed and overrides there. Steps 1-2 (filter, G/I
   adjustment) run in a second process as soon as the GNSS and IMU files are written.
2. ``georefine run`` on both passes into ``OUT/run`` (steps 1-6), and the G/I/L cloud's
   reference planes and strip differences.
3. Meanwhile, in the second process, the single-pass case: ``georefine run --strips FIRST
   --no-points`` into ``OUT/run-single-pass`` (its trajectory is what the paper compares), then
   the G/I cloud (``OUT/run/gi/points``) and its evaluation. Both runs share one step cache
   (``OUT/.cache``), so the GNSS/IMU adjustment is computed once.
   Then the boresight calibration: a project that states the scanner's boresight
   :data:`BORESIGHT_ERROR_DEG` off the truth and estimates it
   (``processing.lidar.estimate_boresight``), on the same files (``OUT/boresight-project``, whose
   ``project.yaml`` names them in ``OUT/project``), run on both passes into ``OUT/run-boresight``.
4. Evaluation (:mod:`georefine.workflows.evaluate`): trajectory differences against the truth, and
   the summary of reference planes and strip-difference maps of G/I and G/I/L; the estimated
   IMU errors and the calibrated boresight against the truth.
5. ``OUT/report.html`` (:mod:`georefine.evaluation.report`) and ``OUT/metrics.json``: the
   summary beside the paper's figures, the runs' metrics and the timings of the demo's stages.
"""

from __future__ import annotations

import logging
import shutil
import time as _time
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from georefine.demo.lanes import Lanes, QueuedProgress, demo_stamp, reusable_project, simulation_scheduler
from georefine.evaluation.report import summary_rows, summary_verdicts, write_report
from georefine.evaluation.summary import CloudEvaluation, RunEvaluation
from georefine.io.files import atomic_output, make_output_folder, write_json
from georefine.io.run_metrics import WorkflowMetrics
from georefine.progress import Progress, no_progress
from georefine.sim.scenarios import resolve_scenario, simulate_project
from georefine.tasks import DEFAULT_SCHEDULER
from georefine.workflows.evaluate import evaluate_cloud, evaluate_run
from georefine.workflows.lidar import precompute_gnss_imu, run_workflow

log = logging.getLogger(__name__)

__all__ = ["BORESIGHT_ERROR_DEG", "DemoMetrics", "DemoResult", "boresight_project", "run_demo"]

BORESIGHT_ERROR_DEG = (0.05, 0.0, 0.0)
"""What the calibration project's boresight (roll, pitch, yaw) is off the truth: a 0.05 deg roll
error, 0.9 m across a 1,000 m swath edge at 600 m above ground, which the two passes recover."""


def boresight_project(project: Path, folder: Path, error_deg=BORESIGHT_ERROR_DEG) -> Path:
    """``folder/project.yaml``: ``project``'s configuration with the boresight ``error_deg`` off and
    estimated, its files named relative to ``folder`` (nothing is copied). The time offset is
    held at the project's: the calibration is about the boresight. One outer iteration: on the
    corridor (seed 42) it recovers the boresight as two do (roll/pitch/yaw error 2.4/0.3/1.3 mdeg
    against 2.3/0.3/1.0, sigma 2.3/2.5/14.9) in 60 s instead of 128 s."""
    cfg = yaml.safe_load((project / "project.yaml").read_text(encoding="utf-8"))
    rel = Path("..") / project.name

    def moved(name: str) -> str:
        return (rel / name).as_posix()

    cfg["gnss"]["files"] = [moved(f) for f in cfg["gnss"]["files"]]
    if cfg["gnss"].get("smrmsg"):
        cfg["gnss"]["smrmsg"] = moved(cfg["gnss"]["smrmsg"])
    cfg["imu"]["file"] = moved(cfg["imu"]["file"])
    cfg["scanner"]["files"] = [moved(f) for f in cfg["scanner"]["files"]]
    if cfg.get("reference") and cfg["reference"].get("surfaces"):
        cfg["reference"]["surfaces"] = moved(cfg["reference"]["surfaces"])
    cfg["scanner"]["boresight_deg"] = [b + e for b, e in zip(cfg["scanner"]["boresight_deg"], error_deg)]
    lidar = cfg.setdefault("processing", {}).setdefault("lidar", {})
    lidar["estimate_boresight"] = True
    lidar["outer_iterations"] = 1
    lidar.setdefault("time_offset", {})["search"] = False
    folder.mkdir(parents=True, exist_ok=True)
    text = yaml.safe_dump(cfg, sort_keys=False)
    path = folder / "project.yaml"
    if not path.is_file() or path.read_text(encoding="utf-8") != text:  # unchanged: its runs' cache keys hold
        with atomic_output(path, "wb") as fh:
            fh.write(text.encode("utf-8"))
    return folder


def _boresight_lane(project: Path, out: Path, cache: Path, progress: QueuedProgress,
                    scheduler: str = DEFAULT_SCHEDULER) -> dict[str, float]:
    """The boresight calibration run (both passes, no point clouds) in the second process."""
    t = _time.perf_counter()
    calibration = boresight_project(project, out / "boresight-project")
    run_workflow(calibration, out / "run-boresight", points=False, cache_dir=cache,
                 progress=replace(progress, prefix="boresight calibration: "), scheduler=scheduler)
    return {"run_boresight": _time.perf_counter() - t}


@dataclass(frozen=True)
class DemoMetrics:
    """What ``OUT/metrics.json`` of the corridor demo holds.

    Attributes
    ----------
    scenario, seed, overrides
        What was simulated.
    evaluation
        The evaluation of the run (``OUT/run/evaluation/summary.json``).
    run
        The full run's metrics (``OUT/run/metrics.json``).
    timings_s
        Wall time (s) of the demo's stages, in the order they ended; ``total`` last.
    """

    scenario: str
    seed: int
    overrides: tuple[str, ...]
    evaluation: RunEvaluation
    run: WorkflowMetrics
    timings_s: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of ``OUT/metrics.json``."""
        return {"scenario": self.scenario, "seed": self.seed, "overrides": list(self.overrides),
                "evaluation": self.evaluation.to_dict(), "run": self.run.to_dict(), "timings_s": dict(self.timings_s)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DemoMetrics:
        return cls(str(d["scenario"]), int(d["seed"]), tuple(str(o) for o in d["overrides"]),
                   RunEvaluation.from_dict(d["evaluation"]), WorkflowMetrics.from_dict(d["run"]),
                   {str(k): float(v) for k, v in d["timings_s"].items()})


@dataclass(frozen=True)
class DemoResult:
    out: Path
    report: Path
    metrics: DemoMetrics

    def summary_table(self) -> list[list[str]]:
        """Rows ``[quantity, paper 000, G/I, G/I/L, single-pass G/I/L, against paper 000]``."""
        ev = self.metrics.evaluation
        return [[*row, verdict] for row, verdict in zip(summary_rows(ev), summary_verdicts(ev))]


def _second_lane(project: Path, out: Path, cache: Path, first_strip: int,
                 progress: QueuedProgress, scheduler: str = DEFAULT_SCHEDULER) -> tuple[dict[str, float], CloudEvaluation]:
    """The demo's second process: the single-pass run, then the G/I point cloud and its evaluation.

    Both need only the G/I adjustment (in the shared step cache), not the full run; the G/I
    trajectory file of the single-pass run is that of the full run (the same cache entry).
    """
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    run_workflow(project, out / "run-single-pass", strips=[first_strip], points=False, cache_dir=cache,
                 progress=replace(progress, prefix="single pass: "), scheduler=scheduler)
    timings["run_single_pass"] = _time.perf_counter() - t
    gi_sbet = out / "run-single-pass" / "gi" / "trajectory.sbet"
    t = _time.perf_counter()
    strips = [int(p["strip_id"]) for p in yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"]]
    gi = evaluate_cloud(project, out / "run", "G/I", trajectory=gi_sbet, strips=strips, progress=progress,
                        scheduler=scheduler)
    timings["evaluate_gi_cloud"] = _time.perf_counter() - t
    return timings, gi


def run_demo(
    out: str | Path,
    *,
    scenario: str = "corridor",
    seed: int = 42,
    overrides: list[str] | None = None,
    single_pass: bool = True,
    boresight: bool = True,
    progress: Progress = no_progress,
    scheduler: str = DEFAULT_SCHEDULER,
) -> DemoResult:
    """Simulate, run (both passes and one), evaluate and report into ``out``.

    Two lanes, one per core: this process simulates, runs both passes and evaluates the G/I/L
    cloud; a second process runs steps 1-2 as soon as the simulator has written GNSS and IMU,
    then the single-pass case and the G/I cloud (without the single pass, this process
    evaluates the G/I cloud). Results go through files and the step cache (``OUT/.cache``)
    only, so each lane's results are those of the same commands run alone. ``scheduler``
    names where each lane's per-tile work runs (:mod:`georefine.tasks`; an address puts both
    lanes' tasks on one cluster).
    """
    out = Path(out)
    overrides = list(overrides or [])
    resolve_scenario(scenario, seed_overrides=overrides)  # a bad scenario or override leaves no folder behind
    make_output_folder(out)
    project = out / "project"
    cache = out / ".cache"
    timings: dict[str, float] = {}
    start = _time.perf_counter()
    with Lanes(progress) as lanes:
        t = _time.perf_counter()
        navigation: list[Future] = []
        if not reusable_project(project, scenario, seed, overrides):
            if project.exists():
                shutil.rmtree(project)
            simulate_project(scenario, project, seed=seed, overrides=overrides, progress=lanes,
                             scheduler=simulation_scheduler(scheduler),
                             on_navigation=lambda root: navigation.append(lanes.submit(precompute_gnss_imu, root, cache)))
            write_json(project / "truth" / "demo.json", demo_stamp(scenario, seed, overrides))
        timings["simulate"] = _time.perf_counter() - t
        # Steps 1-2 in the cache before the lanes start, so that neither computes them (a no-op
        # when the project was reused and the cache holds them).
        t = _time.perf_counter()
        try:
            lanes.result(navigation[0] if navigation else lanes.submit(precompute_gnss_imu, project, cache))
        except Exception as exc:  # noqa: BLE001 - the runs repeat the steps and report their errors
            log.warning("GNSS/IMU steps in the second process failed (%s); the runs repeat them", exc)
        timings["wait_for_gnss_imu"] = _time.perf_counter() - t

        second = third = None
        if single_pass:
            first = int(yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"][0]["strip_id"])
            second = lanes.submit(_second_lane, project, out, cache, first, lanes.queued(), scheduler)
        if boresight:  # after the second lane's work, in the same process
            third = lanes.submit(_boresight_lane, project, out, cache, lanes.queued(), scheduler)
        t = _time.perf_counter()
        full = run_workflow(project, out / "run", cache_dir=cache, progress=lanes, scheduler=scheduler)
        timings["run_both_passes"] = _time.perf_counter() - t
        t = _time.perf_counter()
        clouds = {"G/I/L": evaluate_cloud(project, out / "run", "G/I/L", progress=lanes, scheduler=scheduler)}
        timings["evaluate_gil_cloud"] = _time.perf_counter() - t
        if second is not None:
            t = _time.perf_counter()
            lane_timings, clouds["G/I"] = lanes.result(second)
            timings["wait_for_second_lane"] = _time.perf_counter() - t
            timings.update(lane_timings)
        if third is not None:
            t = _time.perf_counter()
            lane_timings = lanes.result(third)
            timings["wait_for_boresight_calibration"] = _time.perf_counter() - t
            timings.update(lane_timings)

    t = _time.perf_counter()
    single_dir = out / "run-single-pass" if single_pass else None
    evaluation = evaluate_run(project, out / "run", single_dir, clouds=clouds, progress=lanes, scheduler=scheduler,
                              boresight_run=out / "run-boresight" if boresight else None)
    timings["evaluate"] = _time.perf_counter() - t
    t = _time.perf_counter()
    report = write_report(out / "run", out / "report.html", title=f"Georefine demo: {scenario}, seed {seed}")
    timings["report"] = _time.perf_counter() - t
    timings["total"] = _time.perf_counter() - start
    metrics = DemoMetrics(scenario, seed, tuple(overrides), evaluation, full.metrics, timings)
    write_json(out / "metrics.json", metrics.to_dict())
    return DemoResult(out, report, metrics)
