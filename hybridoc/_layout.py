"""Make ``import hybridoc`` work from a source checkout's root.

The installed package maps ``reference/``, ``solvers/`` and ``problems/`` (top-level folders
of the repository) into ``hybridoc.reference``, ``hybridoc.solvers`` and
``hybridoc.problems``. Python started in the repository root finds the bare ``hybridoc/``
folder first, where those subpackages are missing; this finder supplies them from the
sibling folders. In an installed package it finds nothing to do.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_HERE = Path(__file__).resolve().parent
_ROOT = _HERE.parent
_MAPPED = ("reference", "solvers", "problems")


class _SiblingFinder:
    """Finds ``hybridoc.<name>`` in ``<root>/<name>`` for the mapped names.

    A meta path finder needs only ``find_spec``; not subclassing
    ``importlib.abc.MetaPathFinder`` keeps importlib.resources, tempfile and shutil out of
    ``import hybridoc`` (about 20 ms of the command's start-up).
    """

    def find_spec(self, fullname, path=None, target=None):  # type: ignore[no-untyped-def]
        parts = fullname.split(".")
        if len(parts) < 2 or parts[0] != "hybridoc" or parts[1] not in _MAPPED:
            return None
        location = _ROOT.joinpath(*parts[1:])
        if location.is_dir():
            init = location / "__init__.py"
            if not init.is_file():
                return None
            return importlib.util.spec_from_file_location(
                fullname, init, submodule_search_locations=[str(location)]
            )
        module = location.with_suffix(".py")
        if module.is_file():
            return importlib.util.spec_from_file_location(fullname, module)
        return None


def _install() -> None:
    if (_HERE / "problems").exists():
        return  # installed layout: the subpackages are real folders here
    if not all((_ROOT / name / "__init__.py").is_file() for name in _MAPPED):
        return
    if not any(isinstance(f, _SiblingFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _SiblingFinder())


_install()
