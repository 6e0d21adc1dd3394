"""`georefine demo`: the whole story of paper 000 from one command.

1. Simulate the scenario (default ``corridor``) into ``OUT/project`` -- kept and reused when a
   previous demo simulated the same scenario, seed and overrides there.
2. ``georefine run`` on both passes into ``OUT/run`` (steps 1-6).
3. The single-pass case: ``georefine run --strips FIRST --no-points`` into ``OUT/run-single-pass``
   (its trajectory is what the paper compares); both runs share one step cache (``OUT/.cache``),
   so the GNSS/IMU adjustment is computed once.
4. Evaluation (:mod:`georefine.evaluation.run`): trajectory differences against the truth,
   reference planes and strip-difference maps of G/I and G/I/L.
5. ``OUT/report.html`` (:mod:`georefine.evaluation.report`) and ``OUT/metrics.json``: the
   summary beside the paper's figures, the runs' metrics and the timings of the demo's stages.
"""

from __future__ import annotations

import json
import shutil
import time as _time
from dataclasses import dataclass
from pathlib import Path

import yaml

from georefine.evaluation.report import summary_rows, write_report
from georefine.evaluation.run import evaluate_run
from georefine.pipeline.lidar import run_workflow
from georefine.pipeline.navigation import Progress, _no_progress
from georefine.products import write_json
from georefine.sim.scenarios import simulate_project

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


def run_demo(
    out: str | Path,
    *,
    scenario: str = "corridor",
    seed: int = 42,
    overrides: list[str] | None = None,
    single_pass: bool = True,
    progress: Progress = _no_progress,
) -> DemoResult:
    """Simulate, run (both passes and one), evaluate and report into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    overrides = list(overrides or [])
    project = out / "project"
    timings: dict[str, float] = {}

    t = _time.perf_counter()
    if not _reusable(project, scenario, seed, overrides):
        if project.exists():
            shutil.rmtree(project)
        simulate_project(scenario, project, seed=seed, overrides=overrides, progress=progress)
        write_json(project / "truth" / "demo.json", {"scenario": scenario, "seed": seed, "overrides": overrides})
    timings["simulate"] = _time.perf_counter() - t

    cache = out / ".cache"
    t = _time.perf_counter()
    full = run_workflow(project, out / "run", cache_dir=cache, progress=progress)
    timings["run_both_passes"] = _time.perf_counter() - t
    single_dir = None
    if single_pass:
        first = yaml.safe_load((project / "truth" / "scenario.yaml").read_text())["passes"][0]["strip_id"]
        t = _time.perf_counter()
        run_workflow(project, out / "run-single-pass", strips=[int(first)], points=False, cache_dir=cache,
                     progress=progress)
        timings["run_single_pass"] = _time.perf_counter() - t
        single_dir = out / "run-single-pass"

    t = _time.perf_counter()
    evaluation = evaluate_run(project, out / "run", single_dir, progress=progress)
    timings["evaluate"] = _time.perf_counter() - t
    metrics = {"scenario": scenario, "seed": seed, "overrides": overrides, "evaluation": evaluation,
               "run": full.metrics, "timings_s": timings}
    t = _time.perf_counter()
    report = write_report(out / "run", out / "report.html", title=f"Georefine demo: {scenario}, seed {seed}")
    timings["report"] = _time.perf_counter() - t
    write_json(out / "metrics.json", metrics)
    return DemoResult(out, report, metrics)
