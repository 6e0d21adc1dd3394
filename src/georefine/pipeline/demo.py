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
4. Evaluation (:mod:`georefine.evaluation.run`): trajectory differences against the truth, and
   the summary of reference planes and strip-difference maps of G/I and G/I/L.
5. ``OUT/report.html`` (:mod:`georefine.evaluation.report`) and ``OUT/metrics.json``: the
   summary beside the paper's figures, the runs' metrics and the timings of the demo's stages.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import queue
import shutil
import time as _time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from pathlib import Path

import yaml

from georefine.evaluation.report import summary_rows, write_report
from georefine.evaluation.run import evaluate_cloud, evaluate_run
from georefine.pipeline.lidar import precompute_gnss_imu, run_workflow
from georefine.pipeline.navigation import Progress, _no_progress
from georefine.products import write_json
from georefine.sim.scenarios import simulate_project

log = logging.getLogger(__name__)

__all__ = ["DemoResult", "run_demo"]


@dataclass(frozen=True)
class DemoResult:
    out: Path
    report: Path
    metrics: dict

    def summary_table(self) -> list[list[str]]:
        """Rows ``[quantity, paper 000, G/I, G/I/L, single-pass G/I/L]``."""
        return summary_rows(self.metrics["evaluation"])


def _reusable(project: Path, scenario: str, seed: int, overrides: list[str]) -> bool:
    stamp = project / "truth" / "demo.json"
    if not stamp.is_file() or not (project / "project.yaml").is_file():
        return False
    return json.loads(stamp.read_text()) == {"scenario": scenario, "seed": seed, "overrides": overrides}


class _Relay:
    """The demo's progress callback: reports its own steps and those the second process queued."""

    def __init__(self, progress: Progress, events) -> None:
        self.progress, self.events = progress, events

    def __call__(self, name: str, done: float, total: float) -> None:
        self.progress(name, done, total)
        self.drain()

    def drain(self) -> None:
        while True:
            try:
                name, done, total = self.events.get_nowait()
            except queue.Empty:
                return
            self.progress(name, done, total)

    def result(self, future: Future):
        """``future.result()``, showing the second process's progress meanwhile."""
        while True:
            try:
                value = future.result(timeout=0.25)
            except FutureTimeout:
                self.drain()
                continue
            self.drain()
            return value


_events = None  # the second process's progress queue (set by _init_worker)


def _init_worker(events) -> None:
    global _events
    _events = events


def _queued(prefix: str) -> Progress:
    def report(name: str, done: float, total: float) -> None:
        if _events is not None:
            _events.put((f"{prefix}{name}", done, total))

    return report


def _second_lane(project: Path, out: Path, cache: Path, first_strip: int) -> tuple[dict, dict]:
    """The demo's second process: the single-pass run, then the G/I point cloud and its evaluation.

    Both need only the G/I adjustment (in the shared step cache), not the full run; the G/I
    trajectory file of the single-pass run is that of the full run (the same cache entry).
    """
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    run_workflow(project, out / "run-single-pass", strips=[first_strip], points=False, cache_dir=cache,
                 progress=_queued("single pass: "))
    timings["run_single_pass"] = _time.perf_counter() - t
    gi_sbet = out / "run-single-pass" / "gi" / "trajectory.sbet"
    t = _time.perf_counter()
    strips = [int(p["strip_id"]) for p in yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"]]
    gi = evaluate_cloud(project, out / "run", "G/I", trajectory=gi_sbet, strips=strips, progress=_queued(""))
    timings["evaluate_gi_cloud"] = _time.perf_counter() - t
    return timings, gi


def run_demo(
    out: str | Path,
    *,
    scenario: str = "corridor",
    seed: int = 42,
    overrides: list[str] | None = None,
    single_pass: bool = True,
    progress: Progress = _no_progress,
) -> DemoResult:
    """Simulate, run (both passes and one), evaluate and report into ``out``.

    Two lanes, one per core: this process simulates, runs both passes and evaluates the G/I/L
    cloud; a second process runs steps 1-2 as soon as the simulator has written GNSS and IMU,
    then the single-pass case and the G/I cloud (without the single pass, this process
    evaluates the G/I cloud). Results go through files and the step cache (``OUT/.cache``)
    only, so each lane's results are those of the same commands run alone.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    overrides = list(overrides or [])
    project = out / "project"
    cache = out / ".cache"
    timings: dict[str, float] = {}
    start = _time.perf_counter()
    ctx = multiprocessing.get_context("spawn")
    events = ctx.Queue()
    relay = _Relay(progress, events)
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_init_worker, initargs=(events,)) as pool:
        t = _time.perf_counter()
        navigation: list[Future] = []
        if not _reusable(project, scenario, seed, overrides):
            if project.exists():
                shutil.rmtree(project)
            simulate_project(scenario, project, seed=seed, overrides=overrides, progress=relay,
                             on_navigation=lambda root: navigation.append(pool.submit(precompute_gnss_imu, root, cache)))
            write_json(project / "truth" / "demo.json", {"scenario": scenario, "seed": seed, "overrides": overrides})
        timings["simulate"] = _time.perf_counter() - t
        # Steps 1-2 in the cache before the lanes start, so that neither computes them (a no-op
        # when the project was reused and the cache holds them).
        t = _time.perf_counter()
        try:
            relay.result(navigation[0] if navigation else pool.submit(precompute_gnss_imu, project, cache))
        except Exception as exc:  # noqa: BLE001 - the runs repeat the steps and report their errors
            log.warning("GNSS/IMU steps in the second process failed (%s); the runs repeat them", exc)
        timings["wait_for_gnss_imu"] = _time.perf_counter() - t

        second = None
        if single_pass:
            first = int(yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"][0]["strip_id"])
            second = pool.submit(_second_lane, project, out, cache, first)
        t = _time.perf_counter()
        full = run_workflow(project, out / "run", cache_dir=cache, progress=relay)
        timings["run_both_passes"] = _time.perf_counter() - t
        t = _time.perf_counter()
        clouds = {"G/I/L": evaluate_cloud(project, out / "run", "G/I/L", progress=relay)}
        timings["evaluate_gil_cloud"] = _time.perf_counter() - t
        if second is not None:
            t = _time.perf_counter()
            lane_timings, clouds["G/I"] = relay.result(second)
            timings["wait_for_second_lane"] = _time.perf_counter() - t
            timings.update(lane_timings)

    t = _time.perf_counter()
    single_dir = out / "run-single-pass" if single_pass else None
    evaluation = evaluate_run(project, out / "run", single_dir, clouds=clouds, progress=relay)
    timings["evaluate"] = _time.perf_counter() - t
    metrics = {"scenario": scenario, "seed": seed, "overrides": overrides, "evaluation": evaluation,
               "run": full.metrics, "timings_s": timings}
    t = _time.perf_counter()
    report = write_report(out / "run", out / "report.html", title=f"Georefine demo: {scenario}, seed {seed}")
    timings["report"] = _time.perf_counter() - t
    timings["total"] = _time.perf_counter() - start
    write_json(out / "metrics.json", metrics)
    return DemoResult(out, report, metrics)
