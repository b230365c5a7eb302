"""The layering of the source tree as a contract, checked on the imports parsed with ``ast`` (module-level and
function-local ones alike):

* ``materials`` imports nothing from ``renderer`` or ``capture``, ``renderer`` nothing from ``capture``;
* no module of the project imports an underscore-prefixed name from another of its modules (a helper used across
  modules is a public, documented name of the module that owns it). Tests are exempt: they exercise private
  helpers of the module they test;
* no import cycles inside ``capture/fit/`` (its ``__init__`` imports the stages; a stage importing the package
  itself would close a cycle through it).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("materials", "renderer", "capture")
#: Private names imported across modules that are tolerated, as (importing module, imported module, name): none.
#: An entry would make an exception explicit; the test fails on any import not listed and on a listed one that is gone.
ALLOWED_PRIVATE_IMPORTS: set[tuple[str, str, str]] = set()


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    files = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")] + list((ROOT / "scripts").glob("*.py"))
    return {_module_name(p): p for p in sorted(files)}


MODULES = _sources()


def _imports(name: str, path: Path) -> list[tuple[str, str | None]]:
    """``(module, imported name or None)`` for every import statement in the file, relative ones resolved."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            for a in node.names:
                sub = f"{module}.{a.name}"
                # `from package import submodule` imports the submodule, not a name of the package
                out.append((sub, None) if sub in MODULES else (module, a.name))
    return out


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_the_sources_are_found():
    assert {"materials", "renderer", "capture", "capture.fit", "capture.fit.fast"} <= set(MODULES)


def test_lower_layers_import_nothing_from_higher_ones():
    higher = {"materials": ("renderer", "capture"), "renderer": ("capture",)}
    bad = [(name, module) for name, path in MODULES.items() for low, ups in higher.items() if _in(name, low)
           for module, _ in _imports(name, path) if any(_in(module, up) for up in ups)]
    assert bad == [], f"imports against the layering (materials ← renderer ← capture): {bad}"


def test_no_module_imports_a_private_name_of_another():
    found = {(name, module, imported) for name, path in MODULES.items() for module, imported in _imports(name, path)
             if imported is not None and imported.startswith("_") and not imported.startswith("__")
             and module in MODULES and module != name}
    new = sorted(found - ALLOWED_PRIVATE_IMPORTS)
    assert new == [], f"private names imported across modules (make them public where they are defined): {new}"
    stale = sorted(ALLOWED_PRIVATE_IMPORTS - found)
    assert stale == [], f"allow-list entries no longer needed, remove them: {stale}"


def test_no_import_cycles_inside_capture_fit():
    fit = {n: p for n, p in MODULES.items() if _in(n, "capture.fit")}
    graph = {}
    for name, path in fit.items():
        deps = set()
        for module, _ in _imports(name, path):
            # an import of a stage from capture.fit's own namespace goes to that stage, the package otherwise
            target = next((m for m in sorted(fit, key=len, reverse=True) if _in(module, m)), None)
            if target is not None and target != name:
                deps.add(target)
        graph[name] = deps
    assert graph["capture.fit"] >= {"capture.fit.fast", "capture.fit.adam"}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                raise AssertionError(f"import cycle in capture/fit: {' → '.join(stack[stack.index(m):] + [m])}")
            if m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)


def test_the_checks_catch_what_they_look_for(tmp_path):
    # the parser resolves relative imports and sees function-local ones
    src = tmp_path / "capture" / "fit" / "x.py"
    src.parent.mkdir(parents=True)
    src.write_text("from .noise import _hidden\n\ndef f():\n    from ..metrics import thing\n    import renderer\n")
    got = _imports("capture.fit.x", src)
    assert ("capture.fit.noise", "_hidden") in got and ("capture.metrics", "thing") in got and ("renderer", None) in got
