"""The public Python API (``georefine.api``, re-exported by the package; README, "Using Georefine from Python").

* the package re-exports exactly the API's names, loaded on first use: ``import georefine``
  imports none of the library's heavy layers, and ``help(georefine)`` lists the API;
* the command line calls the library through the API alone, every command one API function;
* every API function names the command that calls it and returns a frozen result;
* the README's Python example runs as written (slow: a simulation and a run), and the project
  it made, opened, reads ``project.yaml`` once and derives its navigation once.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import os
import pydoc
import re
import subprocess
import sys
from pathlib import Path

import pytest

import georefine
from georefine import api

ROOT = Path(__file__).resolve().parents[1]
CLI = ROOT / "src" / "georefine" / "cli"


def _readme_python_example() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Using Georefine from Python", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


@pytest.mark.slow
def test_the_readme_python_example_runs_as_written(tmp_path, monkeypatch):  # first: the file's long test (minutes)
    code = _readme_python_example()
    assert "gr.run(" in code and "evaluate_trajectory" in code
    env = dict(os.environ, GEOREFINE_SCHEDULER="threads")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, env=env,
                         timeout=1800)
    assert out.returncode == 0, out.stderr[-3000:]
    m = re.search(r"G/I/L attitude RMSE: roll ([\d.]+), pitch ([\d.]+), yaw ([\d.]+) mdeg; position ([\d.]+) cm",
                  out.stdout)
    assert m, out.stdout
    roll, pitch, yaw, position_cm = map(float, m.groups())
    # The whole flight of the README's smallest example (tests/test_readme_tiny.py: the same
    # project and seed; measured there 3.3 / 2.3 / 10.1 mdeg and 44 mm for the CLI's run).
    assert roll < 6 and pitch < 5 and yaw < 20 and position_cm < 10, m.group(0)
    assert (tmp_path / "tiny-py-run" / "points" / "strip_1.laz").is_file()
    assert str(Path("tiny-py-run") / "points" / "strip_1.laz") in out.stdout
    # The project it made, opened once: its navigation read once, project.yaml never again.
    _check_the_opened_project_reads_its_configuration_once(tmp_path / "tiny-py", monkeypatch)


def test_the_package_re_exports_exactly_the_api():
    # The root names the API without importing it (import georefine stays light): the same list twice.
    assert list(georefine.API) == api.__all__ and len(set(api.__all__)) == len(api.__all__)
    public = {n for n, v in vars(api).items() if not n.startswith("_") and getattr(v, "__module__", None) == api.__name__}
    assert public <= set(api.__all__), public - set(api.__all__)  # every function and result defined there
    for name in api.__all__:
        assert getattr(georefine, name) is getattr(api, name), name
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        georefine.nothing_here  # noqa: B018


def test_import_georefine_stays_light():
    code = ("import sys, georefine; heavy = [m for m in ('georefine.api', 'georefine.workflows', 'numba', 'dask', "
            "'scipy', 'cv2') if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_help_lists_the_api():
    text = pydoc.render_doc(georefine, renderer=pydoc.plaintext)
    for name in ("open_project", "simulate", "run", "estimate_trajectory", "georeference", "coadjust",
                 "adjust_hybrid", "evaluate_run", "WorkflowResult", "Project"):
        assert re.search(rf"\b{name}\b", text), name


def _library_imports(path: Path) -> set[str]:
    """Every georefine module a CLI file imports (``from georefine import api`` gives ``georefine.api``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "georefine":
            if node.module == "georefine":
                found |= {f"georefine.{a.name}" if a.name == "api" else "georefine" for a in node.names}
            else:
                found.add(node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "georefine"}
    return found


def test_the_commands_call_the_library_through_the_api_alone():
    # The commands' own modules; cli/common.py and cli/stages.py are the command line's plumbing
    # (consoles, output-folder marks, the log file) and use io.files for it.
    allowed = {"georefine", "georefine.api", "georefine.errors", "georefine.steps", "georefine.cli.common",
               "georefine.cli.tools", "georefine.cli.stages"}
    for path in (CLI / "__init__.py", CLI / "tools.py"):
        assert _library_imports(path) <= allowed, (path.name, _library_imports(path) - allowed)


def _commands() -> dict[str, str]:
    """The source of every command function of the CLI, by command name."""
    from georefine.cli import app
    from georefine.cli.tools import evaluate_app, export_app

    out = {}
    for prefix, typer_app in (("", app), ("evaluate ", evaluate_app), ("export ", export_app)):
        for command in typer_app.registered_commands:
            name = command.name or command.callback.__name__.replace("_", "-")
            out[prefix + name] = inspect.getsource(command.callback)
    return out


def test_every_command_calls_one_api_function():
    functions = {n for n in api.__all__ if inspect.isfunction(getattr(api, n))}
    called_somewhere = set()
    for name, source in _commands().items():
        if name == "demo":  # the block scenario goes through _block_demo, which calls api.run_demo too
            source += inspect.getsource(sys.modules["georefine.cli"]._block_demo)
        calls = set(re.findall(r"\bapi\.(\w+)\(", source))
        assert len(calls) == 1 and calls <= functions, (name, calls)
        called_somewhere |= calls
    # Every API function is a command's, but the opened project.
    assert functions - called_somewhere == {"open_project"}


def test_every_api_function_names_its_command_and_returns_a_frozen_result():
    commands = set(_commands())
    for name in api.__all__:
        value = getattr(api, name)
        if not inspect.isfunction(value) or name == "open_project":
            continue
        doc = inspect.getdoc(value) or ""
        named = set(re.findall(r"``georefine ([a-z-]+(?: [a-z-]+)?)``", doc))
        assert named and named <= commands | {c.split()[0] for c in commands}, (name, named)
        returned = inspect.signature(value).return_annotation
        for type_name in re.findall(r"[A-Z]\w+", str(returned)):
            cls = getattr(api, type_name, None)
            if cls is not None and dataclasses.is_dataclass(cls):
                assert cls.__dataclass_params__.frozen, (name, type_name)


def _check_the_opened_project_reads_its_configuration_once(project_dir, monkeypatch):
    from georefine.workflows import opened

    project = api.open_project(project_dir)
    calls = []
    real = opened.load_navigation

    def counting(p):
        calls.append(p)
        return real(p)

    monkeypatch.setattr(opened, "load_navigation", counting)

    def no_reload(*args, **kwargs):  # a step that reads project.yaml again fails here
        raise AssertionError("project.yaml read again")

    monkeypatch.setattr(opened, "load_project", no_reload)
    assert project.navigation is project.navigation and len(calls) == 1
    assert project.frame is project.navigation.frame
    assert [f.strip_files for f in project.flights] == [tuple(project.config.scanner.files)]
    assert opened.as_project(project) is project
    with pytest.raises(api.InputError, match="project folder not found"):
        api.open_project(project_dir / "no such folder")
