"""The package is a stack of layers (docs/ARCHITECTURE.md §1): every import points downward.

The contract is checked on the source tree with :mod:`ast`, so lazy imports inside functions
and ``TYPE_CHECKING`` blocks count as much as module-level ones:

* a module imports only modules of its own package or of a lower layer; packages of the same
  layer (``lidar`` and ``lidargrammetry``, ``workflows`` and ``sim``) do not import each other;
* no module imports another module's private names (``from x import _y``), and a private
  module (``_x.py``) is imported only from inside its own package;
* no module reaches another module's private names through an import either: ``alias._y``
  (or ``alias.sub._y``), where ``alias`` is bound by an import, is refused whether it names a
  module of Georefine (``import georefine.trajectory.strapdown as sd; sd._y``, ``from
  georefine.trajectory import strapdown; strapdown._y``), a third-party module (``laspy._y``,
  ``np._y``) or a name imported from one;
* no module reads another package's private attributes: ``obj._y`` (``obj`` anything but
  ``self`` and ``cls``) is refused unless a module of the accessing module's own top-level
  package (``georefine.adjustment`` for ``adjustment/observations/imu.py``; the top-level
  modules together) defines ``_y`` -- a function, class, assigned name or dataclass field, or
  an attribute assigned to ``self`` or ``cls``. So an ``adjustment`` factor's ``_factor`` read
  in ``evaluation``, or laspy's ``_raw_min`` read in ``io``, is reported. A short list of
  underscore names is public by convention (:data:`PUBLIC_BY_CONVENTION`: namedtuple's);
  a private name is one with a leading underscore that is not a dunder (``__y__``);
* the modules' import graph has no cycles;
* ``trajectory`` and ``adjustment`` read and write no files: they import nothing from ``io``.

The tests also show that the checker catches a violation: an upward import, or a private
name reached through an alias or an attribute, added to a copy of the real tree is reported.
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

LAYERS: list[tuple[str, ...]] = [
    ("georefine", "georefine.errors", "georefine.progress", "georefine.steps", "georefine.heap"),  # conventions, errors, progress, steps, the heap
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
    ("georefine.api",),  # the public API: one function per CLI command, re-exported lazily by the root
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


def _absolute(node: ast.ImportFrom, package: str) -> str:
    """The absolute module name a ``from ... import`` names (relative imports resolved against ``package``)."""
    if not node.level:
        return node.module or ""
    base = package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str, path: Path, tree: ast.AST, known: set[str]) -> list[tuple[str, str, int]]:
    """``(imported module, imported name or '', line)`` for every georefine import of a module."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "georefine":
                    found.append((a.name, "", node.lineno))
        elif isinstance(node, ast.ImportFrom):
            target = _absolute(node, package)
            if target.split(".")[0] != "georefine":
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                if sub in known:  # ``from georefine.io import photos``: the submodule
                    found.append((sub, "", node.lineno))
                else:
                    found.append((target, a.name, node.lineno))
    return found


PUBLIC_BY_CONVENTION = frozenset({
    # collections.namedtuple's own API: the underscore keeps these names clear of the fields
    # (the documentation calls them public: "to prevent conflicts with field names").
    "_replace", "_asdict", "_fields", "_make",
})
"""Underscore names that are public by convention, never counted as private access."""


def _is_private(name: str) -> bool:
    """A leading underscore that is not a dunder's (``_x``, ``__x``; not ``__x__``)."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _package_of(module: str, packages: set[str]) -> str:
    """The top-level subpackage of a module (``georefine.adjustment`` for
    ``georefine.adjustment.observations.imu``); ``georefine`` for the top-level modules."""
    parts = module.split(".")
    top = ".".join(parts[:2])
    return top if len(parts) > 1 and top in packages else "georefine"


def _definitions(tree: ast.AST) -> set[str]:
    """The names a module defines: functions, classes, assigned names (dataclass fields and
    imports included) and the attributes assigned to ``self`` or ``cls``."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
              and isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
            names.add(node.attr)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


def _bound_by_imports(module: str, path: Path, tree: ast.AST) -> dict[str, str]:
    """``{name: what it is}`` for every name an import binds in the module (``np``:
    ``numpy``; ``sd``: ``georefine.trajectory.strapdown``; ``Factor``: ``sksparse.cholmod.Factor``)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    bound = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                top = a.name.split(".")[0]
                bound[a.asname or top] = a.name if a.asname else top  # ``import a.b.c`` binds ``a``
        elif isinstance(node, ast.ImportFrom):
            target = _absolute(node, package)
            for a in node.names:
                bound[a.asname or a.name] = f"{target}.{a.name}"
    return bound


def _private_access(module: str, path: Path, tree: ast.AST, defined: set[str]) -> list[tuple[str, int]]:
    """``(problem, line)`` for every private name a module reaches in another module or package.

    * ``alias._x`` (or ``alias.sub._x``) where ``alias`` is bound by an import: a private name
      of another module, be it of Georefine or of a third party;
    * ``obj._x`` for any other ``obj`` but ``self`` and ``cls``, where no module of the
      accessing module's package (``defined``) defines ``_x``: a private attribute of another
      package's object (an object of a class of ``adjustment`` read in ``evaluation``,
      laspy's header read in ``io``).
    """
    bound = _bound_by_imports(module, path, tree)
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and _is_private(node.attr)) or node.attr in PUBLIC_BY_CONVENTION:
            continue
        chain, root = [], node.value
        while isinstance(root, ast.Attribute):
            chain.insert(0, root.attr)
            root = root.value
        if isinstance(root, ast.Name) and root.id in bound and root.id not in ("self", "cls"):
            of = ".".join([bound[root.id], *chain])
            found.append((f"{module} uses the private name {node.attr} of {of}", node.lineno))
        elif not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")) and node.attr not in defined:
            found.append((f"{module} uses the private attribute {node.attr} of another package "
                          f"(no module of its own package defines it)", node.lineno))
    return found


def check_layers(root: Path) -> list[str]:
    """Every violation of the contract in the tree under ``root`` (a ``src`` folder)."""
    modules = _modules(root)
    known = set(modules)
    problems: list[str] = []
    graph: dict[str, set[str]] = {m: set() for m in modules}
    packages = {m for m, p in modules.items() if p.name == "__init__.py"}
    trees = {m: ast.parse(p.read_text(encoding="utf-8")) for m, p in modules.items()}
    defined: dict[str, set[str]] = {}
    for module, tree in trees.items():
        defined.setdefault(_package_of(module, packages), set()).update(_definitions(tree))
    for module, path in modules.items():
        layer, unit = _unit(module)
        where = f"{path.relative_to(root)}"
        for what, line in _private_access(module, path, trees[module], defined[_package_of(module, packages)]):
            problems.append(f"{where}:{line}: {what}")
        for target, name, line in _imports(module, path, trees[module], known):
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
        # private names through a module alias (a Georefine module, a third-party one)
        ("trajectory/ekf.py", "def f(t):\n    return sd._windows(len(t), t, 4)\n",
         "private name _windows of georefine.trajectory.strapdown"),
        ("trajectory/spline_fit.py", "from georefine.trajectory import strapdown\nw = strapdown._lagrange_weights\n",
         "private name _lagrange_weights of georefine.trajectory.strapdown"),
        ("lidar/planes.py", "import georefine.trajectory.strapdown as s2\nw = s2._windows\n",
         "private name _windows of georefine.trajectory.strapdown"),
        ("io/las.py", "x = laspy.header._raw_min\n", "private name _raw_min of laspy.header"),
        ("geometry/rotation.py", "x = np._NoValue\n", "private name _NoValue of numpy"),
        # private attributes of another package's objects
        ("evaluation/plots.py", "def f(fac):\n    return fac._factor\n", "private attribute _factor"),
        ("io/las.py", "def f(struct):\n    return struct._raw_min()\n", "private attribute _raw_min"),
    ],
)
def test_the_checker_catches_a_violation_added_to_the_real_tree(tmp_path, module, line, expected):
    root = _copy(tmp_path)
    path = root / "georefine" / module
    path.write_text(path.read_text(encoding="utf-8") + "\n" + line + "\n", encoding="utf-8")
    problems = check_layers(root)
    assert any(expected in p and module in p for p in problems), problems


def test_the_checker_lets_public_by_convention_and_own_private_names_pass(tmp_path):
    root = _copy(tmp_path)
    before = check_layers(root)
    path = root / "georefine" / "evaluation" / "plots.py"
    path.write_text(path.read_text(encoding="utf-8") + "\n" + "\n".join([
        "def f(row, fac):",  # namedtuple's API; an attribute assigned to self in this package
        "    return row._replace(a=1), row._asdict(), type(row)._fields, type(row)._make([1]), fac._rows",
        "class C:",
        "    def __init__(self):",
        "        self._rows = 0",
        "    def g(self):",
        "        return self._rows, self.__class__, self._undefined_here",
    ]) + "\n", encoding="utf-8")
    assert check_layers(root) == before


def test_the_checker_catches_a_cycle_inside_a_package(tmp_path):
    root = _copy(tmp_path)
    path = root / "georefine" / "adjustment" / "robust.py"
    path.write_text(path.read_text(encoding="utf-8") + "\nfrom georefine.adjustment.solver import SolverOptions\n",
                    encoding="utf-8")
    assert any(p.startswith("import cycle") and "georefine.adjustment.robust" in p for p in check_layers(root))
