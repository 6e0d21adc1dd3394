"""The package is a stack of layers (docs/ARCHITECTURE.md §1): every import points downward.

The contract is checked on the source tree with :mod:`ast`, so lazy imports inside functions
and ``TYPE_CHECKING`` blocks count as much as module-level ones:

* a module imports only modules of its own package or of a lower layer; packages of the same
  layer (``lidar`` and ``lidargrammetry``, ``workflows`` and ``sim``) do not import each other;
* no module imports another module's private names (``from x import _y``), and a private
  module (``_x.py``) is imported only from inside its own package;
* the modules' import graph has no cycles;
* ``trajectory`` and ``adjustment`` read and write no files: they import nothing from ``io``.

The tests also show that the checker catches a violation: an upward import added to a copy
of the real tree is reported.
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

LAYERS: list[tuple[str, ...]] = [
    ("georefine", "georefine.errors", "georefine.progress", "georefine.steps"),  # conventions, errors, progress, steps
    ("georefine.tasks",),  # where per-tile work runs (sync, threads, processes, a Dask cluster)
    ("georefine.geometry",),
    ("georefine.io",),
    ("georefine.config",),
    ("georefine.trajectory",),
    ("georefine.adjustment",),
    ("georefine.lidar", "georefine.lidargrammetry"),
    ("georefine.evaluation",),
    ("georefine.workflows", "georefine.sim"),
    ("georefine.demo",),
    ("georefine.cli",),
    ("georefine.__main__",),
]

NO_IO = ("georefine.trajectory", "georefine.adjustment")
"""Packages that import nothing from ``georefine.io`` (estimation only; the workflows read the files)."""


def _unit(module: str) -> tuple[int, str]:
    """``(layer index, unit)`` of a module: the longest layer entry it belongs to."""
    best = None
    for k, units in enumerate(LAYERS):
        for u in units:
            if (module == u or module.startswith(u + ".")) and (u != "georefine" or module == "georefine"):
                if best is None or len(u) > len(best[1]):
                    best = (k, u)
    if best is None:
        raise AssertionError(f"{module} is in no layer: add it to LAYERS and to docs/ARCHITECTURE.md §1")
    return best


def _modules(root: Path) -> dict[str, Path]:
    out = {}
    for f in sorted((root / "georefine").rglob("*.py")):
        parts = f.relative_to(root).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = f
    return out


def _imports(module: str, path: Path, known: set[str]) -> list[tuple[str, str, int]]:
    """``(imported module, imported name or '', line)`` for every georefine import of a module."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "georefine":
                    found.append((a.name, "", node.lineno))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "georefine":
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                if sub in known:  # ``from georefine.io import photos``: the submodule
                    found.append((sub, "", node.lineno))
                else:
                    found.append((target, a.name, node.lineno))
    return found


def check_layers(root: Path) -> list[str]:
    """Every violation of the contract in the tree under ``root`` (a ``src`` folder)."""
    modules = _modules(root)
    known = set(modules)
    problems: list[str] = []
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        layer, unit = _unit(module)
        where = f"{path.relative_to(root)}"
        for target, name, line in _imports(module, path, known):
            if target not in known:
                problems.append(f"{where}:{line}: imports {target}, which does not exist")
                continue
            if target != module:
                graph[module].add(target)
            t_layer, t_unit = _unit(target)
            if t_unit != unit and t_layer >= layer:
                kind = "a sibling package of its layer" if t_layer == layer else "a higher layer"
                problems.append(f"{where}:{line}: {module} imports {target} ({kind}: {t_unit})")
            if unit in NO_IO and t_unit == "georefine.io":
                problems.append(f"{where}:{line}: {module} imports {target} ({unit} reads and writes no files)")
            if name.startswith("_") and name != "__version__":
                problems.append(f"{where}:{line}: {module} imports the private name {name} of {target}")
            private = [p for p in target.split(".") if p.startswith("_") and p not in ("__init__", "__main__")]
            if private and not module.startswith(target.rpartition(".")[0] + "."):
                problems.append(f"{where}:{line}: {module} imports the private module {target} from outside its package")
    # Cycles between modules (depth-first search with colours).
    colour: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        colour[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if colour.get(t, 0) == 1:
                cycle = stack[stack.index(t):] + [t]
                problems.append("import cycle: " + " -> ".join(cycle))
            elif colour.get(t, 0) == 0:
                visit(t)
        stack.pop()
        colour[m] = 2

    for m in sorted(graph):
        if colour.get(m, 0) == 0:
            visit(m)
    return problems


def test_the_real_tree_is_a_stack():
    problems = check_layers(SRC)
    assert not problems, "layering violations:\n" + "\n".join(problems)


def test_every_module_is_in_a_layer():
    for module in _modules(SRC):
        _unit(module)


def _copy(tmp_path: Path) -> Path:
    root = tmp_path / "src"
    shutil.copytree(SRC / "georefine", root / "georefine", ignore=shutil.ignore_patterns("__pycache__"))
    return root


@pytest.mark.parametrize(
    ("module", "line", "expected"),
    [
        ("geometry/rotation.py", "from georefine.cli import app", "a higher layer"),
        ("io/las.py", "from georefine.workflows.lidar import run_workflow", "a higher layer"),
        ("workflows/cache.py", "import georefine.sim.scenarios", "a sibling package"),
        ("lidar/planes.py", "from georefine.lidargrammetry.render import render_lidargram", "a sibling package"),
        ("evaluation/plots.py", "from georefine.trajectory.spline import _evaluate", "private name"),
        ("adjustment/robust.py", "from georefine.trajectory._ekf_kernels import forward", "private module"),
        ("config/yaml_io.py", "def f():\n    from georefine.demo.corridor import run_demo\n", "a higher layer"),
        ("trajectory/ekf.py", "from georefine.io.imu import ImuData", "reads and writes no files"),
    ],
)
def test_the_checker_catches_a_violation_added_to_the_real_tree(tmp_path, module, line, expected):
    root = _copy(tmp_path)
    path = root / "georefine" / module
    path.write_text(path.read_text(encoding="utf-8") + "\n" + line + "\n", encoding="utf-8")
    problems = check_layers(root)
    assert any(expected in p and module in p for p in problems), problems


def test_the_checker_catches_a_cycle_inside_a_package(tmp_path):
    root = _copy(tmp_path)
    path = root / "georefine" / "adjustment" / "robust.py"
    path.write_text(path.read_text(encoding="utf-8") + "\nfrom georefine.adjustment.solver import SolverOptions\n",
                    encoding="utf-8")
    assert any(p.startswith("import cycle") and "georefine.adjustment.robust" in p for p in check_layers(root))
