"""hybridoc: optimal control of hybrid systems.

The core package holds the problem model (:class:`HybridOCP`), the event-exact judge
(:func:`evaluate`, :func:`gradient`), the shared :class:`Solution` type, plotting and the
CLI. Scenes and the library of classic problems live in :mod:`hybridoc.problems`, the HMP
reference in :mod:`hybridoc.reference`, the solvers (and :func:`solve`, which runs any of
them) in :mod:`hybridoc.solvers`.

The public names are imported on first use (PEP 562): ``import hybridoc`` loads neither
numpy nor CasADi, so that the ``hybridoc`` command starts quickly; ``from hybridoc import
evaluate`` imports what ``evaluate`` needs.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

from hybridoc import providers as _providers

# The install maps the repository's top-level reference/, solvers/ and problems/ into
# hybridoc.*. Python started in a source checkout's root finds this bare folder first, where
# they are missing: searching the checkout's root as part of this package finds them there.
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if not os.path.isdir(os.path.join(os.path.dirname(__file__), "problems")) and all(
    os.path.isfile(os.path.join(_ROOT, name, "__init__.py"))
    for name in ("reference", "solvers", "problems")
):
    __path__.append(_ROOT)

if TYPE_CHECKING:  # pragma: no cover - what type checkers and editors see
    from hybridoc.callable_eval import evaluate_callable
    from hybridoc.errors import (
        ControlsError,
        ConvergenceError,
        EvaluationError,
        HybridocError,
        SceneError,
        SimultaneousEventError,
    )
    from hybridoc.evaluation import Evaluation, Gradient
    from hybridoc.evaluator import evaluate, gradient
    from hybridoc.events import Event
    from hybridoc.guards import Guard
    from hybridoc.methods import solve
    from hybridoc.modes import Mode
    from hybridoc.ocp import HybridOCP
    from hybridoc.problem import as_ocp
    from hybridoc.problems import Disc, DiscOCP, Scene, Wall, builtin_names, load_scene
    from hybridoc.reference import solve_reference
    from hybridoc.solution import Solution, Status
    from hybridoc.workflows.training import closed_loop_cost
    from hybridoc.workflows.validation import crossval

__version__: str

__all__ = [
    "ControlsError",
    "ConvergenceError",
    "Disc",
    "DiscOCP",
    "Evaluation",
    "EvaluationError",
    "Event",
    "Gradient",
    "Guard",
    "HybridOCP",
    "HybridocError",
    "Mode",
    "Scene",
    "SceneError",
    "SimultaneousEventError",
    "Solution",
    "Status",
    "Wall",
    "as_ocp",
    "builtin_names",
    "closed_loop_cost",
    "crossval",
    "evaluate",
    "evaluate_callable",
    "gradient",
    "load_scene",
    "solve",
    "solve_reference",
]

# Where each public name is defined (the TYPE_CHECKING block above says the same).
_EXPORTS: dict[str, str] = {
    "ControlsError": "hybridoc.errors",
    "ConvergenceError": "hybridoc.errors",
    "Disc": "hybridoc.problems",
    "Evaluation": "hybridoc.evaluation",
    "EvaluationError": "hybridoc.errors",
    "Event": "hybridoc.events",
    "Gradient": "hybridoc.evaluation",
    "Guard": "hybridoc.guards",
    "HybridOCP": "hybridoc.ocp",
    "HybridocError": "hybridoc.errors",
    "Mode": "hybridoc.modes",
    "Scene": "hybridoc.problems",
    "SceneError": "hybridoc.errors",
    "SimultaneousEventError": "hybridoc.errors",
    "Solution": "hybridoc.solution",
    "Status": "hybridoc.solution",
    "Wall": "hybridoc.problems",
    "as_ocp": "hybridoc.problem",
    "builtin_names": "hybridoc.problems",
    "closed_loop_cost": "hybridoc.workflows.training",  # torch
    "crossval": "hybridoc.workflows.validation",
    "evaluate": "hybridoc.evaluator",
    "evaluate_callable": "hybridoc.callable_eval",
    "gradient": "hybridoc.evaluator",
    "load_scene": "hybridoc.problems",
    "solve": "hybridoc.methods",
    "solve_reference": "hybridoc.reference",
    "DiscOCP": "hybridoc.problems",
}

# Submodules that ``import hybridoc`` used to load as a side effect: ``hybridoc.problems.X``
# after a bare ``import hybridoc`` keeps working.
_SUBMODULES = frozenset(
    {
        "callable_eval",
        "errors",
        "evaluation",
        "evaluator",
        "events",
        "kernels",
        "ocp",
        "problem",
        "problems",
        "rootfind",
        "solution",
    }
)


def _judging() -> Any:
    from hybridoc import judging

    return judging


def _hmp_control_law() -> Any:
    from hybridoc.reference.result import hmp_control

    return hmp_control


# What the model-layer Solution delegates to higher layers (hybridoc/providers.py): loaders,
# run on first use, so that this import stays free of numpy.
_providers.register("judging", _judging)
_providers.register("control-law:hmp", _hmp_control_law)


def _version() -> str:
    # one source of the version: pyproject.toml, through the installed metadata (importing
    # importlib.metadata costs tens of milliseconds: only when the version is asked for)
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hybridoc")
    except PackageNotFoundError:  # pragma: no cover - imported from a bare source tree
        return "0+unknown"


def __getattr__(name: str) -> Any:
    """Import a public name, ``__version__`` or a submodule on first access (PEP 562)."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
    elif name == "__version__":
        value = _version()
    elif name in _SUBMODULES:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module 'hybridoc' has no attribute {name!r}")
    globals()[name] = value  # later accesses are plain attribute lookups
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__) | {"__version__"})
