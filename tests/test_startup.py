"""Start-up: ``import hybridoc`` and the ``hybridoc`` command's parser import nothing heavy.

``hybridoc --help`` must not wait for numpy, CasADi, torch, SciPy or matplotlib (issue #18);
the public names are imported on first use, and every command's help still lists what the
registries hold. These are behaviour tests (what gets imported); the time itself is measured
by ``benchmarks/bench_startup.py``.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import hybridoc
from hybridoc.cli import build_parser

HEAVY = ("numpy", "casadi", "torch", "scipy", "matplotlib")


def _fresh(tmp_path: Path, code: str) -> dict:
    """Run ``code`` in a new interpreter; it prints one JSON object, returned here."""
    # cwd = tmp_path so that the repository's bare hybridoc/ does not shadow the install
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


_LOADED = (
    "import json, sys; "
    f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))))"
)


def test_import_hybridoc_imports_nothing_heavy(tmp_path: Path) -> None:
    assert _fresh(tmp_path, "import hybridoc; " + _LOADED) == []


def test_building_the_parser_imports_nothing_heavy(tmp_path: Path) -> None:
    code = "import hybridoc.cli; hybridoc.cli.build_parser().format_help(); " + _LOADED
    assert _fresh(tmp_path, code) == []


def test_every_public_name_is_importable() -> None:
    """Each name of ``__all__``, resolved by the package's lazy ``__getattr__`` (its
    first-touch path, called directly: in this process a name may have been touched
    already), is the object of the module that defines it; ``from hybridoc import *`` and
    ``dir`` see all of them. In this process rather than a fresh interpreter, which paid
    torch, CasADi and SciPy again (5-16 s under load); the two tests above keep the fresh
    interpreter, where what is imported is the behaviour."""
    import importlib

    lazy = hybridoc.__getattr__  # type: ignore[attr-defined]
    bad = [
        n
        for n in hybridoc.__all__
        if lazy(n) is not getattr(importlib.import_module(hybridoc._EXPORTS[n]), n)
    ]
    ns: dict[str, object] = {}
    exec("from hybridoc import *", ns)
    missing = sorted(set(hybridoc.__all__) - set(ns) | set(hybridoc.__all__) - set(dir(hybridoc)))
    assert bad == [] and missing == []
    assert lazy("__version__") == hybridoc.__version__


def test_lazy_names_are_declared_once() -> None:
    """``__all__``, the lazy table and the TYPE_CHECKING imports name the same objects."""
    tree = ast.parse(Path(hybridoc.__file__).read_text(encoding="utf-8"))
    typed: dict[str, str] = {}
    for node in tree.body:
        if isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom) and imp.module is not None
                typed.update({alias.name: imp.module for alias in imp.names})
    assert typed == hybridoc._EXPORTS
    assert sorted(hybridoc.__all__) == sorted(hybridoc._EXPORTS)


def test_unknown_attribute_is_an_attribute_error() -> None:
    try:
        hybridoc.no_such_name  # noqa: B018
    except AttributeError as exc:
        assert "no_such_name" in str(exc)
    else:  # pragma: no cover
        raise AssertionError("hybridoc.no_such_name did not raise")


def test_deferred_help_lists_the_registries() -> None:
    """The commands that read registries add their arguments on first use: their help still
    lists every method and contact model."""
    from hybridoc.methods import METHODS
    from hybridoc.solvers.contacts import model_names

    subs = build_parser()._subparsers._group_actions[0].choices  # type: ignore[union-attr]
    solve_help = " ".join(subs["solve"].format_help().split())
    assert "--method {" + ",".join(METHODS) + "}" in solve_help
    assert "--contact {" + ",".join(model_names()) + "}" in solve_help
    contacts = ", ".join(model_names())
    for command in ("gradcheck", "compare-contacts"):
        assert f"(models: {contacts})" in " ".join(subs[command].format_help().split())
    assert "--search K" in subs["reference"].format_help()
