"""hybridoc: optimal control of hybrid systems.

The core package holds the problem model (:class:`HybridOCP`), the event-exact judge
(:func:`evaluate`, :func:`gradient`), the shared :class:`Solution` type, plotting and the
CLI. Scenes and the library of classic problems live in :mod:`hybridoc.problems`, the HMP
reference in :mod:`hybridoc.reference`, the solvers (and :func:`solve`, which runs any of
them) in :mod:`hybridoc.solvers`.
"""

from __future__ import annotations

from typing import Any

from hybridoc import _layout  # noqa: F401  (running from a source checkout)
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
from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problem import as_ocp
from hybridoc.problems import Disc, Scene, Wall, builtin_names, load_scene
from hybridoc.solution import Solution, Status

try:  # one source of the version: pyproject.toml, through the installed metadata
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as _version

    __version__ = _version("hybridoc")
except PackageNotFoundError:  # pragma: no cover - imported from a bare source tree
    __version__ = "0+unknown"

__all__ = [
    "ControlsError",
    "ConvergenceError",
    "Disc",
    "Evaluation",
    "EvaluationError",
    "Event",
    "Gradient",
    "Guard",
    "HybridOCP",
    "HybridocError",
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
]


def __getattr__(name: str) -> Any:
    # the solvers import torch lazily; ``hybridoc.solve`` is theirs, re-exported on demand
    if name in ("solve", "crossval"):
        from hybridoc.solvers import registry

        return getattr(registry, name) if name == "solve" else registry.crossval
    if name == "closed_loop_cost":  # torch: imported on demand, like the solvers
        from hybridoc.solvers.policy_training import closed_loop_cost

        return closed_loop_cost
    raise AttributeError(f"module 'hybridoc' has no attribute {name!r}")
