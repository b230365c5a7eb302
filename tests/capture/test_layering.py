"""The layering of the source tree as a contract, checked on the imports parsed with ``ast`` (module-level and
function-local ones alike):

* ``materials`` imports nothing from ``renderer`` or ``capture``, ``renderer`` nothing from ``capture``;
* no module of the project imports an underscore-prefixed name from another of its modules (a helper used across
  modules is a public, documented name of the module that owns it). Tests are exempt: they exercise private
  helpers of the module they test;
* the rooms of ``capture`` (docs/architecture.md): the pipeline (the modules at the top of ``capture/``) and its
  solver stages (``capture/fit/``) import nothing from ``capture/synth/`` (scenes with a known truth) or
  ``capture/bench/`` (benchmarks and stress tests), except the ``synth`` and ``demo`` commands of ``capture.cli``;
  ``capture/synth/`` uses from the rest of ``capture`` only the dataset format and the photo model, and nothing in
  ``capture`` imports ``capture/bench/``;
* no import cycles among the modules of the three packages (a package's ``__init__`` imports its modules, so a
  module importing its own package, e.g. a stage of ``capture/fit/`` importing ``capture.fit``, closes a cycle
  through it).
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
    assert {"materials", "renderer", "capture", "capture.fit", "capture.fit.fast", "capture.synth",
            "capture.synth.scenes", "capture.bench", "capture.bench.reconstruction"} <= set(MODULES)


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


#: The rooms of ``capture`` (docs/architecture.md) that the pipeline must not depend on, and who may import them.
SYNTH, BENCH = "capture.synth", "capture.bench"
#: Modules outside capture/synth/ and capture/bench/ that may import capture/synth/: the ``synth`` and ``demo``
#: commands write synthetic datasets.
SYNTH_USERS = {"capture.cli"}
#: What capture/synth/ may import from the rest of capture: the dataset format and the photo model.
SYNTH_NEEDS = {"capture.dataset", "capture.photo"}


def _capture_imports():
    """``(importing module, imported capture module)`` for every import between two modules of ``capture``."""
    return [(name, module) for name, path in MODULES.items() if _in(name, "capture")
            for module, _ in _imports(name, path) if _in(module, "capture") and module != "capture"]


def test_the_pipeline_imports_neither_scenes_nor_benchmarks():
    edges = _capture_imports()
    on_synth = sorted({(a, b) for a, b in edges if _in(b, SYNTH) and not _in(a, SYNTH) and not _in(a, BENCH)
                       and a not in SYNTH_USERS})
    assert on_synth == [], f"capture modules importing capture/synth/ (only {sorted(SYNTH_USERS)} may): {on_synth}"
    on_bench = sorted({(a, b) for a, b in edges if _in(b, BENCH) and not _in(a, BENCH)})
    assert on_bench == [], f"capture modules importing capture/bench/ (scripts and tests may, nothing else): {on_bench}"
    # the allowance is still needed (the commands do write synthetic datasets)
    assert {a for a, b in edges if _in(b, SYNTH) and not _in(a, SYNTH) and not _in(a, BENCH)} == SYNTH_USERS


def test_scenes_use_only_the_dataset_format_and_the_photo_model():
    edges = _capture_imports()
    found = {b for a, b in edges if _in(a, SYNTH) and not _in(b, SYNTH)}
    extra = sorted(found - SYNTH_NEEDS)
    assert extra == [], f"capture/synth/ imports {extra}; from the rest of capture it may use {sorted(SYNTH_NEEDS)}"


def _graph() -> dict[str, set[str]]:
    """Module → the modules of the three packages it imports (an imported name resolves to its module, a package's
    own name to the package)."""
    mods = {n for n in MODULES if not _in(n, "scripts")}
    by_length = sorted(mods, key=len, reverse=True)
    graph = {}
    for name in mods:
        deps = set()
        for module, _ in _imports(name, MODULES[name]):
            target = next((m for m in by_length if _in(module, m)), None)
            if target is not None and target != name:
                deps.add(target)
        graph[name] = deps
    return graph


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` as ``[a, b, …, a]``, or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (cycle := visit(m)):
                return cycle
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (cycle := visit(n)):
            return cycle
    return None


def test_no_import_cycles():
    graph = _graph()
    # the graph sees packages importing their modules and modules importing across rooms
    assert graph["capture.fit"] >= {"capture.fit.fast", "capture.fit.adam"}
    assert {"capture.synth", "capture.bench.timing"} <= graph["capture.bench.reconstruction"]
    cycle = _find_cycle(graph)
    assert cycle is None, f"import cycle: {' → '.join(cycle)}"


def test_the_checks_catch_what_they_look_for(tmp_path):
    # the parser resolves relative imports and sees function-local ones
    src = tmp_path / "capture" / "fit" / "x.py"
    src.parent.mkdir(parents=True)
    src.write_text("from .noise import _hidden\n\ndef f():\n    from ..metrics import thing\n    import renderer\n")
    got = _imports("capture.fit.x", src)
    assert ("capture.fit.noise", "_hidden") in got and ("capture.metrics", "thing") in got and ("renderer", None) in got
    # the cycle search finds a cycle through a package's __init__ and none in a tree
    assert _find_cycle({"p": {"p.a"}, "p.a": {"p.b"}, "p.b": {"p"}}) == ["p", "p.a", "p.b", "p"]
    assert _find_cycle({"p": {"p.a", "p.b"}, "p.a": {"p.b"}, "p.b": set()}) is None
