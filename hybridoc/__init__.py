"""hybridoc: optimal control of hybrid systems.

The core package holds the problem model (:class:`HybridOCP`), the event-exact evaluator
(:func:`evaluate`, :func:`gradient`), the shared :class:`Solution` type, plotting and the
CLI. Scenes live in :mod:`hybridoc.problems`, the HMP reference in
:mod:`hybridoc.reference`, the solvers in :mod:`hybridoc.solvers`.
"""

from hybridoc.callable_eval import evaluate_callable
from hybridoc.errors import (
    ControlsError,
    ConvergenceError,
    EvaluationError,
    HybridocError,
    SceneError,
)
from hybridoc.evaluator import Evaluation, Event, Gradient, evaluate, gradient
from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problems import Disc, Scene, Wall, builtin_names, load_scene
from hybridoc.solution import Solution

__version__ = "0.1.0"

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
    "Solution",
    "Wall",
    "builtin_names",
    "evaluate",
    "evaluate_callable",
    "gradient",
    "load_scene",
]
