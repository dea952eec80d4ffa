"""The import structure of the package (docs/architecture.rst, "Layers").

Read from the source with :mod:`ast`, counting imports inside functions (those hide cycles
from Python, which runs them late, but not from a reader): no import cycle between modules,
no private name imported from another module, the reference free of solvers, and every
module importing only from its own layer or the layers below it.
"""

from __future__ import annotations

import ast
import functools
import re
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# repository folder -> package name (pyproject.toml maps the three siblings into hybridoc.*)
PACKAGES = {
    "hybridoc": "hybridoc",
    "reference": "hybridoc.reference",
    "solvers": "hybridoc.solvers",
    "problems": "hybridoc.problems",
}

# Layers, lowest first: a module may import from its own layer and the layers below.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    (
        "model",
        (
            "hybridoc.errors",
            "hybridoc.ocp",
            "hybridoc.arrays",
            "hybridoc.guards",
            "hybridoc.modes",
            "hybridoc.flowmaps",
            "hybridoc.scales",
            "hybridoc.capabilities",
            "hybridoc.tolerances",
            "hybridoc.children",
            "hybridoc.resources",
            "hybridoc.kernels",
            "hybridoc.broadphase",
            "hybridoc.rootfind",
            "hybridoc.events",
            "hybridoc.evaluation",
            "hybridoc.solution",
            "hybridoc.providers",
            "hybridoc.outputs",
            "hybridoc.progress",
            "hybridoc.cores",
            "hybridoc.compiled",
            "hybridoc._pyfile",
        ),
    ),
    ("problems", ("hybridoc.problems", "hybridoc.problem")),
    (
        "judge",
        (
            "hybridoc.evaluator",
            "hybridoc.callable_eval",
            "hybridoc.io",
            "hybridoc.plotting",
            "hybridoc.judging",
        ),
    ),
    ("methods", ("hybridoc.methods",)),
    ("reference", ("hybridoc.reference",)),
    ("solvers", ("hybridoc.solvers",)),
    ("workflows", ("hybridoc.workflows",)),
    ("cli", ("hybridoc.cli", "hybridoc.__main__")),
    ("api", ("hybridoc",)),  # the package's lazy re-exports, above everything
]


def _modules() -> dict[str, Path]:
    out = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([package, *parts])] = path
    return out


MODULES = _modules()


def _exports() -> dict[str, dict[str, str]]:
    """``package -> {name: module}`` of the packages' lazy re-exports (PEP 562): the
    ``_EXPORTS`` dictionary of their ``__init__.py``, read from the source. An import of such
    a name is an import of the module that defines it."""
    out = {}
    for module, path in MODULES.items():
        if path.name != "__init__.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.AnnAssign | ast.Assign):
                targets = [node.target] if isinstance(node, ast.AnnAssign) else node.targets
                if any(getattr(t, "id", "") == "_EXPORTS" for t in targets):
                    out[module] = ast.literal_eval(node.value)
    assert "hybridoc" in out and "hybridoc.reference" in out
    return out


EXPORTS = _exports()


def _owner(name: str) -> str | None:
    """The module of ``name`` (a module, or a name inside one)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


# every test reads the same imports: each module is parsed once per test process
@functools.cache
def _imports(module: str) -> tuple[tuple[str, str, int], ...]:
    """``(imported module, imported name or "", line)`` of every hybridoc import in
    ``module``, at any depth (functions, methods, ``if TYPE_CHECKING`` blocks excepted)."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    skip: set[int] = set()
    for node in ast.walk(tree):  # type-only imports run never
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    out = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package
                for _ in range(node.level - 1):
                    anchor = anchor.rpartition(".")[0]
                base = f"{anchor}.{base}" if base else anchor
            if base.split(".")[0] != "hybridoc":
                continue
            for alias in node.names:
                full = f"{base}.{alias.name}"
                if base == "hybridoc" and alias.name.startswith("__"):
                    continue  # __version__: package metadata
                if alias.name in EXPORTS.get(base, {}):  # a lazy re-export
                    out.append((EXPORTS[base][alias.name], alias.name, node.lineno))
                elif full in MODULES:  # a submodule imported by name
                    out.append((full, "", node.lineno))
                else:
                    out.append((base, alias.name, node.lineno))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                # a bare ``import hybridoc`` reaches the lazy re-exports, which import
                # nothing until a name is used: that name's module is not known here
                if alias.name.split(".")[0] == "hybridoc" and alias.name != "hybridoc":
                    out.append((alias.name, "", node.lineno))
    return tuple(out)


def _graph() -> dict[str, set[str]]:
    edges: dict[str, set[str]] = defaultdict(set)
    for module in MODULES:
        for target, _, _ in _imports(module):
            owner = _owner(target)
            if owner is not None and owner != module:
                edges[module].add(owner)
    return edges


def _cycles(edges: dict[str, set[str]], vertices: list[str] | None = None) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(MODULES if vertices is None else vertices):
        if v not in index:
            visit(v)
    return found


def _layer(module: str) -> int:
    best, level = -1, -1
    for k, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, level = len(prefix), k
    return level


def test_the_analysis_sees_the_package():
    assert len(MODULES) > 60
    assert "hybridoc.reference.solve" in MODULES and "hybridoc.solvers.gd" in MODULES
    # an import inside a function counts: gd imports the judge inside solve_gd or at the top
    assert (
        "hybridoc.evaluator"
        in _graph()["hybridoc.solvers.gd.solve"] | _graph()["hybridoc.solvers.compiled"]
    )


def test_no_import_cycles():
    cycles = _cycles(_graph())
    assert not cycles, "import cycles (imports inside functions count):\n" + "\n".join(
        " <-> ".join(c) for c in cycles
    )


def test_no_private_names_across_modules():
    bad = []
    for module in MODULES:
        for target, name, line in _imports(module):
            if _owner(target) == module:
                continue
            if name.startswith("_") and not name.startswith("__"):
                bad.append(f"{MODULES[module].relative_to(ROOT)}:{line} imports {target}.{name}")
            # a private module (cli/_util.py) serves its own package only
            parts = target.split(".")
            for k, part in enumerate(parts):
                if part.startswith("_") and not part.startswith("__"):
                    package = ".".join(parts[:k])
                    if module != package and not module.startswith(package + "."):
                        bad.append(f"{MODULES[module].relative_to(ROOT)}:{line} imports {target}")
    assert not bad, "\n".join(bad)


def test_the_reference_imports_no_solver():
    bad = [
        f"{MODULES[m].relative_to(ROOT)}:{line} imports {target}"
        for m in MODULES
        if m.startswith("hybridoc.reference")
        for target, _, line in _imports(m)
        if target.startswith("hybridoc.solvers")
    ]
    assert not bad, "\n".join(bad)


def test_every_module_has_a_layer():
    missing = [m for m in MODULES if _layer(m) < 0]
    assert not missing, f"modules without a layer in LAYERS: {missing}"


def test_layers_import_only_downwards():
    names = [name for name, _ in LAYERS]
    bad = []
    for module in MODULES:
        for target, _, line in _imports(module):
            owner = _owner(target)
            if owner is None or owner == module:
                continue
            if _layer(owner) > _layer(module):
                bad.append(
                    f"{MODULES[module].relative_to(ROOT)}:{line}: {module} "
                    f"({names[_layer(module)]}) imports {owner} ({names[_layer(owner)]})"
                )
    assert not bad, "imports from a higher layer:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    "edges, cycle",
    [
        ({"a": {"b"}, "b": {"a"}}, True),
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, True),
        ({"a": {"b"}, "b": {"c"}, "c": set()}, False),
    ],
)
def test_cycle_finder(edges, cycle):
    """The finder itself sees cycles (a check that cannot fail is none)."""
    assert bool(_cycles(edges, list(edges))) is cycle


# The disc classes, which code above problems/ must not import (it asks
# HybridOCP.capabilities instead), and the modules built on the scene itself.
DISC_TYPES = frozenset({"DiscOCP", "Scene"})
DISC_SIMULATOR = (
    "hybridoc.solvers.simulator",
    "hybridoc.solvers.toi_sim",
    "hybridoc.solvers.casadi_step",
    "hybridoc.solvers.discrete_transcription",
    "hybridoc.solvers.compiled",
    "hybridoc.solvers.contacts",
)
_TYPE_TEST = re.compile(r"isinstance\([^)]*\b(DiscOCP|Scene)\b")


def _disc_type_uses(module: str) -> list[str]:
    """Where ``module`` imports a disc class or tests for one (source lines)."""
    path = MODULES[module]
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    out = [
        f"{where}:{line} imports {name}" for _, name, line in _imports(module) if name in DISC_TYPES
    ]
    for i, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if _TYPE_TEST.search(text.split("#")[0]):
            out.append(f"{where}:{i}: {text.strip()}")
    return out


def _above_problems(module: str) -> bool:
    problems = [name for name, _ in LAYERS].index("problems")
    api = [name for name, _ in LAYERS].index("api")
    return problems < _layer(module) < api and not module.startswith(DISC_SIMULATOR)


def test_upper_layers_ask_capabilities_not_disc_types():
    """Above problems/, a disc scene is known by what it offers (HybridOCP.capabilities),
    not by its type (docs/architecture.rst, "Capabilities")."""
    bad = [use for m in MODULES if _above_problems(m) for use in _disc_type_uses(m)]
    assert not bad, "disc types above problems/:\n" + "\n".join(bad)


def test_the_disc_type_check_sees_a_type_test(tmp_path, monkeypatch):
    """The check above finds an import and an isinstance test (one that cannot fail is none)."""
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from hybridoc.problems.disc_ocp import DiscOCP\n"
        "def f(ocp):\n    return isinstance(ocp, DiscOCP)\n"
    )
    monkeypatch.setitem(MODULES, "hybridoc.workflows._probe", probe)
    try:
        uses = _disc_type_uses("hybridoc.workflows._probe")
    finally:
        _imports.cache_clear()
    assert _above_problems("hybridoc.workflows._probe")
    assert len(uses) == 2, uses


def test_the_tolerance_table_in_the_docs_is_the_code_s():
    """docs/architecture.rst lists every row of hybridoc.tolerances.TOLERANCES with its value."""
    from hybridoc.tolerances import TOLERANCES

    text = (ROOT / "docs" / "architecture.rst").read_text(encoding="utf-8")
    rows = dict(
        re.findall(r"   \* - ``(\w+)``\n     - ([0-9.e+-]+)\n     - (?:relative|absolute)", text)
    )
    assert set(rows) == set(TOLERANCES)
    assert all(float(rows[name]) == t.value for name, t in TOLERANCES.items())
