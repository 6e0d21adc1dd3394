"""The layer numbers the package docstrings state agree with the stack (docs/ARCHITECTURE.md §1).

A package's docstring (``src/georefine/<package>/__init__.py``, or the module itself for the
top-level modules of :data:`test_layers.LAYERS`) that says "layer N" (or "part of layer N", for a
subpackage) must give the index of its package in ``LAYERS``, which test_layers.py enforces and
ARCHITECTURE.md §1 lists.
"""

from __future__ import annotations

import ast
import re

from test_layers import LAYERS, SRC

_LAYER_N = re.compile(r"\blayer (\d+)\b", re.IGNORECASE)


def _layer_of(module: str) -> int:
    """Index in LAYERS of the entry that owns ``module`` (the longest matching prefix)."""
    best, index = "", None
    for i, layer in enumerate(LAYERS):
        for name in layer:
            if (module == name or module.startswith(name + ".")) and len(name) > len(best):
                best, index = name, i
    assert index is not None, f"{module} is in no layer of LAYERS"
    return index


def _package_docstrings() -> dict[str, str]:
    """Module name -> docstring, for every package ``__init__.py`` and the top-level modules LAYERS names."""
    root = SRC / "georefine"
    files = sorted(root.rglob("__init__.py"))
    files += [root / f"{name.split('.')[-1]}.py" for layer in LAYERS for name in layer
              if name.count(".") == 1 and (root / f"{name.split('.')[-1]}.py").is_file()]
    out = {}
    for path in files:
        rel = path.relative_to(SRC).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        out[".".join(parts)] = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    return out


def test_every_layer_number_in_a_package_docstring_is_its_index_in_layers():
    docstrings = _package_docstrings()
    stated = {m: [int(n) for n in _LAYER_N.findall(d)] for m, d in docstrings.items()}
    assert sum(map(len, stated.values())) >= 5, "the docstrings no longer state layers: the test checks nothing"
    wrong = {m: (numbers, _layer_of(m)) for m, numbers in stated.items()
             if any(n != _layer_of(m) for n in numbers)}
    assert not wrong, "docstring layer numbers (stated, LAYERS index): " + ", ".join(
        f"{m} {numbers} != {index}" for m, (numbers, index) in sorted(wrong.items()))


def test_the_check_sees_a_wrong_number():
    assert _layer_of("georefine.workflows") == _layer_of("georefine.sim")
    assert _layer_of("georefine.adjustment.observations") == _layer_of("georefine.adjustment")
    assert _LAYER_N.findall("Metrics (layer 7, docs/ARCHITECTURE.md §1)") == ["7"]
    assert _layer_of("georefine.evaluation") != 7  # what evaluation's docstring said before §1's numbers
