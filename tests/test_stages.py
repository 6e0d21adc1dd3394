"""What an unattended run shows and leaves: stage lines off a terminal, the output folder's log,
and Ctrl-C (georefine.cli.stages, georefine.cli.common.progress)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys

from cli_helpers import STAGE_LINE, run_georefine
from georefine.cli.stages import LOG_NAME, StageLog, folder_snapshot, format_duration, remove_new_empty_folders


class _Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _log(interval: float = 30.0):
    lines: list[str] = []
    clock = _Clock()
    log = StageLog(lines.append, interval_s=interval, clock=clock, wall=lambda: 1.8e9 + clock.t)
    return log, lines, clock


def _texts(lines: list[str]) -> list[str]:
    assert all(STAGE_LINE.match(line) for line in lines), lines
    return [line.split("  ", 1)[1] for line in lines]


def test_a_stage_says_when_it_starts_how_far_it_is_at_most_every_interval_and_when_it_ends():
    log, lines, clock = _log()
    log.report("scan", 0, 10)
    clock.t += 10.0
    log.report("scan", 2, 10)  # within the interval: no line
    clock.t += 20.0
    log.report("scan", 3, 10)  # 30 s in, 30 %: 70 s left at this pace
    clock.t += 5.0
    log.report("scan", 4, 10)
    clock.t += 65.0
    log.report("scan", 10, 10)
    log.report("scan", 10, 10)  # reported again: said once
    assert _texts(lines) == ["scan: started", "scan: 30 % after 0:00:30, about 0:01:10 left", "scan: done in 0:01:40"]


def test_stages_may_overlap_start_again_and_end_with_the_run():
    log, lines, clock = _log()
    log.report("simulation", 0, 4)
    log.report("filter", 0, 1)
    clock.t += 3.0
    log.report("filter", 1, 1)
    log.report("adjustment", 2, 30)  # converged after 2 of at most 30 iterations: never reaches its total
    assert log.running() == ["simulation", "adjustment"]
    log.report("filter", 0, 1)  # a second outer iteration
    clock.t += 2.0
    log.close()
    assert log.running() == []
    assert _texts(lines) == ["simulation: started", "filter: started", "filter: done in 0:00:03", "adjustment: started",
                             "filter: started again", "simulation: done in 0:00:05", "filter: done in 0:00:02",
                             "adjustment: done in 0:00:02"]
    assert format_duration(3725.4) == "1:02:05"


def test_only_the_empty_folders_a_run_made_are_removed(tmp_path):
    out = tmp_path / "o"
    (out / "kept_empty").mkdir(parents=True)
    before = folder_snapshot(out)
    for rel in ("gi", "gil/sub/deeper", "features", ".cache"):
        (out / rel).mkdir(parents=True)
    (out / ".cache" / "gi-0.pkl").write_bytes(b"x")
    removed = remove_new_empty_folders(out, before)
    assert sorted(p.relative_to(out).as_posix() for p in removed) == ["features", "gi", "gil", "gil/sub",
                                                                        "gil/sub/deeper"]
    assert sorted(p.name for p in out.iterdir()) == [".cache", "kept_empty"]


def test_off_a_terminal_a_command_prints_timestamped_stage_lines_and_its_log_holds_them(gil_project, tmp_path):
    out = tmp_path / "t"
    proc = run_georefine("trajectory", str(gil_project), "--out", str(out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    stages = [line for line in proc.stderr.splitlines() if STAGE_LINE.match(line)]
    texts = [line.split("  ", 1)[1] for line in stages]
    for name in ("reading the input", "initialisation filter", "G/I adjustment"):
        assert f"{name}: started" in texts and any(t.startswith(f"{name}: done in ") for t in texts), texts
    log = (out / LOG_NAME).read_text().splitlines()
    assert "georefine" in log[0] and "trajectory" in log[0] and f"--out {out}" in log[0]  # the command
    assert all(line in log for line in stages)  # every stage line, as printed
    assert any(" INFO georefine.trajectory.ekf: " in line for line in log)  # the records too, without --verbose
    assert " INFO " not in proc.stderr  # which stay off the console


def test_ctrl_c_says_where_it_stopped_how_to_resume_and_leaves_no_empty_folders(gil_project, gil_gi_cache, tmp_path):
    """Interrupted in the G/I/L adjustment (the G/I from the shared cache, so that it gets there soon)."""
    out = tmp_path / "run"
    (out / ".cache").mkdir(parents=True)
    for f in gil_gi_cache.iterdir():
        shutil.copy(f, out / ".cache" / f.name)
    (out / ".georefine-output").write_text("Georefine writes into this folder.\n")
    exe = shutil.which("georefine")
    cmd = [exe] if exe else [sys.executable, "-m", "georefine.cli"]
    # SIGINT back to its default in the child: a test run started in the background by a shell
    # ignores it, and an ignored signal stays ignored across exec (Python then installs no handler).
    proc = subprocess.Popen([*cmd, "run", str(gil_project), "--out", str(out), "--no-points"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=dict(os.environ, COLUMNS="200"),
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = []
    for line in proc.stderr:
        seen.append(line)
        if "G/I/L adjustment: started" in line:
            proc.send_signal(signal.SIGINT)
            break
    _, rest = proc.communicate(timeout=300)
    err = "".join(seen) + rest
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert "interrupted during G/I/L adjustment after" in last and f"kept in {out / '.cache'}" in last, last
    assert "run the same command again to resume" in last
    assert last in (out / LOG_NAME).read_text().splitlines()
    empty = [root for root, dirs, files in os.walk(out) if not dirs and not files]
    assert not empty, empty
    assert list((out / ".cache").glob("gi-*.pkl"))  # what finished stays


def test_clean_frees_the_step_caches_of_georefines_folders_only(tmp_path):
    from cli_helpers import run_georefine_here
    from georefine.io.files import OUTPUT_MARK, make_output_folder

    demo = make_output_folder(tmp_path / "demo")
    run = make_output_folder(demo / "run")
    (demo / "project" / ".cache").mkdir(parents=True)  # not an output folder: its .cache is not ours
    for folder in (run / ".cache", demo / ".cache"):
        folder.mkdir()
        (folder / "gi-0.pkl").write_bytes(b"x" * 1000)
    (run / "metrics.json").write_text("{}")
    done = run_georefine_here("clean", str(demo))
    assert done.returncode == 0, done.stderr
    assert str(run / ".cache") in done.stdout and "(0.0 MB)" in done.stdout
    assert not (demo / ".cache").exists() and not (run / ".cache").exists()
    assert (run / "metrics.json").is_file() and (demo / "project" / ".cache").is_dir()
    assert "nothing to clean" in run_georefine_here("clean", str(demo)).stdout
    refused = run_georefine_here("clean", str(demo / "project"))
    assert refused.returncode == 2 and OUTPUT_MARK in refused.stderr
    assert run_georefine_here("clean", str(demo), "--all").returncode == 0 and not demo.exists()
