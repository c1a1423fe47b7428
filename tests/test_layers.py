"""The package's layers: no module imports one above its own layer, and no import cycle, lazy imports (inside
functions) and the matcher registry's "module:class" names included; every registry entry imports."""

import ast
import re
from pathlib import Path

import pytest

import facerec3d
from facerec3d.matching.base import Matcher
from facerec3d.matching.registry import METHODS, make_matcher, matcher_class

ROOT = Path(facerec3d.__file__).parent
#: Lowest first; a module may import its own layer and those below.
LAYERS = [
    {"facerec3d", "errors", "config", "scan", "workers", "facemodel", "models", "render", "jit"},
    {"io"},
    {"geometry"},
    {"preprocess"},
    {"datasets"},
    {"matching"},
    {"gallery"},
    {"evaluation", "training"},
    {"server", "client", "cli"},
]
#: (importer, imported) pairs that still run upward, each with the reason.
PENDING: dict[tuple[str, str], str] = {}


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imports(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module → the facerec3d modules it imports anywhere in its code, or names in a registry string."""
    edges = {}
    for name, path in modules.items():
        text = path.read_text(encoding="utf-8")
        found = set(re.findall(r'"(facerec3d(?:\.\w+)+):\w+"', text))
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("facerec3d"):
                found |= {node.module, *(f"{node.module}.{a.name}" for a in node.names)}
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name.startswith("facerec3d")}
        edges[name] = {m for m in found if m in modules and m != name}
    return edges


def _layer(module: str) -> int:
    top = module.split(".")[1] if "." in module else module
    found = next((i for i, layer in enumerate(LAYERS) if top in layer), None)
    assert found is not None, f"{module} is in no layer: add {top!r} to LAYERS"
    return found


def test_no_import_runs_upward():
    upward = [(a, b) for a, bs in _imports(_modules()).items() for b in bs
              if _layer(b) > _layer(a) and (a, b) not in PENDING]
    assert not upward, upward


def test_no_import_cycles():
    edges = _imports(_modules())
    cycles, state = [], {}

    def visit(m, path):
        state[m] = "open"
        for n in sorted(edges[m]):
            if state.get(n) == "open":
                cycles.append(path[path.index(n):] + [n])
            elif n not in state:
                visit(n, path + [n])
        state[m] = "done"

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles


@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_registry_entry_imports_and_builds(method):
    cls = matcher_class(method)
    assert issubclass(cls, Matcher) and cls.name == method
    matcher = make_matcher(method)
    assert make_matcher(method, matcher.options()).options() == matcher.options()
