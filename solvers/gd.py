"""Optimal control by gradient descent through a differentiable simulation.

:func:`solve_gd` minimises the discrete objective ``phi(s_N) + sum_n c_n`` over the
``N x nu`` piecewise-constant controls and measures the result with the event-exact judge:
the returned :class:`~hybridoc.solution.Solution` carries the *true* continuous cost of the
controls. The method's options are the fields of :class:`GDOptions`; :data:`METHOD` registers
it as ``method="gd"`` (:mod:`hybridoc.methods`), with its crossval tolerance, defaults and
discrete-gap check.

Which simulation
    Disc scenes use the disc simulator with a contact model of
    :mod:`hybridoc.solvers.contacts` (the paper's Eq. 8 objective): the compiled CasADi path
    (:class:`~hybridoc.solvers.compiled.CompiledLoss`) where the model's CasADi step serves
    the scene (every model, within limits such as the number of contacts of ``lcp`` and
    ``convex``), else the torch :class:`~hybridoc.solvers.simulator.Simulator`. Every other
    problem uses the generic time-of-impact simulation (:mod:`hybridoc.solvers.toi_sim`),
    compiled the same way. The contact model is a name or a
    :class:`~hybridoc.solvers.contacts.ContactModel` (``LCP(toi="both")``,
    ``contact_model("compliant", stiffness=2e4)``), turned into a model object once, on entry.

Integrator
    ``"exact"`` (the default): the exact flow of the piecewise-constant control with
    Newton-refined times of impact, whose loss is the continuous cost. ``"symplectic-euler"``:
    the paper's scheme (``hybridoc ablation`` uses it to reproduce Table 1).

Control bounds and path constraints
    Bounds are honoured by projection (``gd``, ``adam``) or by SciPy's L-BFGS-B (``lbfgs``);
    path constraints by a quadratic penalty in the objective, and the judge reports any
    remaining violation (status ``infeasible``).

Terminal constraints and a free final time
    An augmented Lagrangian (Powell-Hestenes-Rockafellar) around SciPy's L-BFGS-B, on the
    generic time-of-impact simulation (:class:`~hybridoc.solvers.compiled.TerminalLoss`,
    whose step length ``T / N`` is an input, so that one graph serves every ``T`` and
    gives ``dJ/dT`` by the same adjoint). The inner problem is the loss plus
    ``nu . h_eq + rho/2 |h_eq|^2 + 1/(2 rho) sum(max(0, mu - rho h_in)^2 - mu^2)`` over the
    controls and, when the final time is free, ``T`` in ``horizon_bounds``; the smoothing
    stages run in the first outer iteration. After each inner solve ``nu += rho h_eq``,
    ``mu = max(0, mu - rho h_in)``, and ``rho`` grows tenfold when the violation has not
    fallen to a quarter. The loop stops when the violation (with the inequalities'
    complementarity) is below a tenth of ``terminal_tol`` or after ``terminal_iters``
    outer iterations; the judge, run at the final time found, reports the remaining
    violation in ``info["terminal_violation"]``, and a violation above ``terminal_tol`` is
    status ``infeasible``. The multi-start, the hops, the torch path and the disc contact
    models are refused there.

The pieces of a run
    :func:`checked_options` validates the options and fills in their defaults; hops
    (:func:`_hop`) and the multi-start (:func:`_multistart`) wrap the continuation
    (:func:`_continuation`: the smoothing stages, then the real problem), which runs single
    descents (:func:`_descend`, the optimiser loop in :class:`_Run`, with the numpy
    optimisers of :mod:`hybridoc.solvers.optimizers`: torch is imported only by the torch
    simulator, ``path="torch"``). One
    :class:`~hybridoc.progress.Progress` serves the whole run: a stage per smoothing weight,
    hop round and multi-start phase, a count per iteration.
"""

from __future__ import annotations

import contextvars
import dataclasses
import inspect
import math
import numbers
import signal
import time
import weakref
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc import resources, tolerances
from hybridoc.errors import OptionError
from hybridoc.evaluator import evaluate
from hybridoc.methods import (
    Method,
    nonnegative_int,
    option,
    positive_float,
    positive_int,
    settings_lines,
)
from hybridoc.ocp import HybridOCP, Structure
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.problems import scene_of
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.scales import optimizer_units as units
from hybridoc.solution import Solution, Status
from hybridoc.solvers.threads import flag_interrupts

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.evaluation import Evaluation
    from hybridoc.solvers.contacts import ContactModel

__all__ = [
    "DEFAULT_SMOOTHING",
    "DISCRETE_TOLERANCE",
    "GD_HOPS",
    "GD_STARTS",
    "HOP_BATCH",
    "HOP_ITERS",
    "HOP_PATIENCE",
    "HOP_SCALES",
    "INTEGRATORS",
    "KINK_BAND",
    "KINK_GTOL",
    "KINK_ITERS",
    "METHOD",
    "MEMORY_FRACTION",
    "OPTIMIZERS",
    "PATHS",
    "GDOptions",
    "available_memory",
    "checked_options",
    "default_integrator",
    "default_settings",
    "exploration_loss",
    "make_loss",
    "memory_limit",
    "parse_smoothing",
    "pinned_events",
    "run_gd",
    "solve_gd",
    "units",
]

INTEGRATORS = ("exact", "symplectic-euler")

OPTIMIZERS = ("gd", "adam", "lbfgs")

PATHS = ("auto", "compiled", "torch")
"""Where the loss is computed (``path`` of :func:`solve_gd`)."""

PATH_WEIGHT = 1e5
"""Default weight of the quadratic penalty on path-constraint violations (``path_weight``)."""

DEFAULT_SMOOTHING = (1e-4, 1e-5, 1e-6)
"""Default continuation weights of ``lbfgs`` (see ``smoothing`` in :func:`solve_gd`)."""

STALL_RTOL = tolerances.value("stall")
"""Convergence test at the iteration limit (:func:`solve_gd`): the loss changed by at most
this, relative, over the last :func:`stall_window` iterations."""

GD_STARTS = {"disc": 32, "generic": 16}
"""Cross-validation runs gradient descent as a multi-start (``starts``), since a local method
from one guess can land in another basin (multiple-collision's two-event extremal); disc
scenes have aimed starts, hence more of them."""

GD_HOPS = 8
"""Hops (batched restarts, :func:`solve_gd`) of gradient descent in cross-validation on the
paper's symplectic Euler objective, whose kinks (a contact moving to another step) stall a
plain descent and are not taken past by :func:`_past_kinks` (exact integrator only)."""

DISCRETE_TOLERANCE = 1e-6
"""Relative gap of gd's discrete loss to the optimum of its own discrete objective within
which the two agree in cross-validation
(:func:`~hybridoc.solvers.discrete_transcription.discrete_gap`)."""


def stall_window(iters: int) -> int:
    """The iterations over which the loss must have stalled at the limit: a tenth of them,
    at least 10 (a run of fewer iterations cannot show that it has converged)."""
    return max(10, iters // 10)


def _positive(x: Any) -> bool:
    """``x`` is a real number, finite and > 0 (not a string, not a bool)."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _whole(x: Any, least: int) -> bool:
    """``x`` is an integer (not a bool) ``>= least``."""
    return isinstance(x, numbers.Integral) and not isinstance(x, bool) and x >= least


class _NonFinite(Exception):
    """The loss or its gradient became NaN or infinite."""


# ---------------------------------------------------------------------- the options
def parse_smoothing(text: str) -> tuple[float, ...]:
    """Command-line parser of ``smoothing``: comma-separated weights, or ``none`` (or an
    empty text) for no continuation (``ValueError`` with a one-line reason)."""
    if text.strip().lower() in ("none", ""):
        return ()
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(f"expected comma-separated numbers or 'none', got {text!r}") from None


def _contact_names() -> list[str]:
    """The registered contact models (read when the CLI's flags are built)."""
    from hybridoc.solvers.contacts import model_names

    return model_names()


def _toi_modes() -> tuple[str, ...]:
    """The time-of-impact settings of the impulse models."""
    from hybridoc.solvers.contacts import TOI_MODES

    return TOI_MODES


@dataclass(frozen=True)
class GDOptions:
    """The options of gradient descent (``method="gd"``); each is a keyword of
    :func:`solve_gd`, whose docstring says more, and (but the Python-only ones) a flag of
    ``hybridoc solve``."""

    contact: str | ContactModel = option(
        "direct",
        "disc contact model (default direct)",
        choices=_contact_names,
    )
    toi: str | None = option(
        None,
        "time-of-impact correction (default both)",
        choices=_toi_modes,
    )
    integrator: str | None = option(
        None,
        "exact (default) or the paper's symplectic-euler",
        choices=INTEGRATORS,
    )
    optimizer: str = option("lbfgs", "default lbfgs", choices=OPTIMIZERS)
    smoothing: tuple[float, ...] | None = option(
        None,
        "continuation weights of the control-smoothness penalty, or 'none' "
        "(default: 1e-4,1e-5,1e-6 for lbfgs, none otherwise)",
        parse=parse_smoothing,
        metavar="MU,MU",
    )
    iters: int | None = option(
        None, "iterations (per continuation stage with lbfgs)", parse=nonnegative_int
    )
    lr: float | None = option(None, "learning rate", parse=positive_float)
    starts: int = option(
        1,
        "batched multi-start: K initial controls at once (the guess, its perturbations, "
        "random smooth and aimed controls); the best is returned, all K in the JSON "
        "(default 1)",
        parse=positive_int,
        metavar="K",
    )
    seed: int | None = option(
        0, "seed of the multi-start's random starts (default 0)", parse=nonnegative_int
    )
    hops: int = option(
        0,
        "up to K rounds of batched restarts around the result, to leave a shallow local "
        "minimum or a kink where the descent stalled (any loss with a batched compiled "
        "rollout; default 0)",
        parse=nonnegative_int,
        metavar="K",
    )
    callback: Callable[[int, float, np.ndarray], Any] | None = option(
        None,
        "called as callback(iteration, loss, controls) after every iteration; a true return "
        "value stops the optimisation",
        cli=False,
    )
    path: str = option(
        "auto",
        "auto (compiled where the model's CasADi step serves the scene, else torch), "
        "compiled or torch",
        choices=PATHS,
        cli=False,
    )
    max_step: float | None = option(
        None,
        "lbfgs only: the largest change of any control value in one iteration (default: no limit)",
        cli=False,
    )
    path_weight: float = option(
        PATH_WEIGHT, "weight of the quadratic penalty on path-constraint violations", cli=False
    )
    terminal_tol: float = option(
        tolerances.TERMINAL,
        "terminal constraints: the largest violation the judge may find at s(T) for a "
        "success (default 1e-8)",
        parse=positive_float,
    )
    terminal_rho: float = option(
        10.0,
        "terminal constraints: the augmented Lagrangian's initial penalty (default 10)",
        parse=positive_float,
    )
    terminal_iters: int = option(
        30,
        "terminal constraints: the augmented Lagrangian's outer iterations, at most (default 30)",
        parse=positive_int,
    )
    time_limit: float | None = option(
        None,
        "stop after this much wall time and return the best iterate so far as not-converged "
        "(judged; exit 2 in the CLI; default: no limit)",
        parse=positive_float,
        metavar="SECONDS",
    )

    def __post_init__(self) -> None:
        _check_options(self)


def _check_choice(name: str, value: Any, choices: Sequence[str]) -> None:
    """Raise :class:`~hybridoc.errors.OptionError` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise OptionError(f"unknown {name} {value!r}; choose one of {', '.join(choices)}")


def _check_options(o: GDOptions) -> None:
    """Every check of gd's options that does not depend on the problem, in one place (run
    by :class:`GDOptions` on construction): an :class:`~hybridoc.errors.OptionError` of one
    line for an unknown name or a value out of range. The contact model's name and TOI
    setting are checked where they are resolved (:func:`checked_options`), the sizes'
    memory against the problem (:func:`_check_memory`)."""
    _check_choice("optimizer", o.optimizer, OPTIMIZERS)
    if o.integrator is not None:
        _check_choice("integrator", o.integrator, INTEGRATORS)
    _check_choice("path", o.path, PATHS)
    # checked strictly: int(1.5) or float("1e-3") would hide a mistake in the caller
    if o.iters is not None and not _whole(o.iters, 0):
        raise OptionError(f"iters must be an integer >= 0, got {o.iters!r}")
    if o.lr is not None and not _positive(o.lr):
        raise OptionError(f"lr must be a positive finite number, got {o.lr!r}")
    if o.max_step is not None and not _positive(o.max_step):
        raise OptionError(f"max_step must be a positive finite number or None, got {o.max_step!r}")
    if not _whole(o.starts, 1):
        raise OptionError(f"starts must be an integer >= 1, got {o.starts!r}")
    if not _whole(o.hops, 0):
        raise OptionError(f"hops must be an integer >= 0, got {o.hops!r}")
    if not (_positive(o.terminal_tol) and _positive(o.terminal_rho)):
        raise OptionError(
            "terminal_tol and terminal_rho must be positive finite numbers, got "
            f"{o.terminal_tol!r} and {o.terminal_rho!r}"
        )
    if not _whole(o.terminal_iters, 1):
        raise OptionError(f"terminal_iters must be an integer >= 1, got {o.terminal_iters!r}")
    if o.time_limit is not None and not _positive(o.time_limit):
        raise OptionError(f"time_limit must be a positive number of seconds, got {o.time_limit!r}")
    _checked_smoothing(o.smoothing)


def _options_signature(run: Callable[..., Any], options: type) -> inspect.Signature:
    """``run``'s signature with its ``**options`` spelled out as the keyword-only fields of
    the dataclass ``options``, with their defaults: what :func:`inspect.signature`, the
    documentation and :meth:`~hybridoc.methods.Method.check_signature` see of a thin
    wrapper ``run(problem, *, initial=None, progress=None, **options)``, while the defaults
    are written once, in the dataclass."""
    sig = inspect.signature(run)
    params = [p for p in sig.parameters.values() if p.kind is not p.VAR_KEYWORD]
    params += [
        inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default,
                          annotation=f.type)
        for f in dataclasses.fields(options)
    ]  # fmt: skip
    return sig.replace(parameters=params)


def default_settings(problem: HybridOCP, optimizer: str) -> tuple[float, int]:
    """Default ``(learning rate, iterations)`` of an optimiser on a problem.

    Plain ``gd`` takes the problem's own settings where its author tuned them, the hints
    ``lr`` and ``iters`` of :meth:`~hybridoc.capabilities.Capabilities.hints_for` ``("gd")``
    (a scene file's ``[hints.gd]`` table: the paper's scenes carry the paper's settings),
    and otherwise a learning rate of ``0.1 / dt`` (the gradient with respect to one control
    value scales with ``dt``; in the scaled units of :func:`units`, ``dt / tc``) and 1000
    iterations. The hints are plain gradient descent's: the other optimisers keep their
    own defaults. ``adam`` uses 0.05 for
    1000 iterations; ``lbfgs`` a step of 0.1 (the trial step of its line search, taken when
    it lowers the loss:
    :data:`~hybridoc.solvers.optimizers.GD_LINE_SEARCH_EVALS`) for at most 300 iterations:
    with 1.0 it leaps from the multiple-collision guess to ``u = 0``, where nothing collides.
    """
    if optimizer == "gd":
        hints = problem.capabilities.hints_for("gd")
        lr = hints["lr"] if "lr" in hints else 0.1 / (problem.dt / units(problem)[2])
        return lr, hints.get("iters", 1000)
    if optimizer == "adam":
        return 0.05, 1000
    if optimizer == "lbfgs":
        return 0.1, 300
    raise OptionError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")


def _disc(ocp: HybridOCP) -> bool:
    """Whether the disc simulator simulates ``ocp`` (a disc scene; the generic
    time-of-impact simulation otherwise)."""
    return scene_of(ocp) is not None


# ---------------------------------------------------------------------- the loss
_LOSSES: weakref.WeakKeyDictionary[Structure, dict[tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def _model_key(model: ContactModel) -> tuple[Any, ...]:
    """What identifies a contact model in the loss cache: its class and settings."""
    return (type(model), tuple(sorted((k, repr(v)) for k, v in model.settings().items())))


def _is_direct_both(model: ContactModel) -> bool:
    return model.name == "direct" and getattr(model, "toi", None) == "both"


def make_loss(
    ocp: HybridOCP,
    contact: str | ContactModel,
    integrator: str,
    path: str = "auto",
    path_weight: float = PATH_WEIGHT,
) -> tuple[Any, str]:
    """The differentiable objective of a problem: ``(loss object, "compiled" | "torch")``.

    Parameters
    ----------
    ocp
        The problem.
    contact
        The contact model (disc scenes): a :class:`~hybridoc.solvers.contacts.ContactModel`,
        or a name for :func:`~hybridoc.solvers.contacts.contact_model` with its defaults.
        Generic problems take only ``direct`` with TOI ``both`` (their time-of-impact
        simulation).
    integrator
        ``"exact"`` or ``"symplectic-euler"`` (disc scenes).
    path
        ``"auto"``, ``"compiled"`` or ``"torch"`` (:data:`PATHS`).
    path_weight
        Weight of the path-constraint penalty.

    Returns
    -------
    tuple
        The loss object and the path taken. A compiled loss has numpy
        ``value_and_grad(controls, x0=None)`` (what gd calls: no torch) and a torch
        ``loss``; the torch simulator only ``loss(controls, x0=None)`` (torch,
        differentiable). Compiled losses are kept per problem structure and settings: building
        one takes milliseconds, but continuation stages and repeated solves reuse it.
    """
    from hybridoc.solvers.contacts import contact_model

    model = contact_model(contact)
    _check_choice("path", path, PATHS)
    scene = scene_of(ocp)
    is_disc = scene is not None
    _check_choice("integrator", integrator, INTEGRATORS)
    if is_disc:
        # every registered model has a CasADi step, within limits (e.g. the scene's number of
        # contacts for the coupled impulse models): auto falls back to torch outside them
        reason = model.casadi_unsupported(scene, integrator)
        if path == "compiled" and reason is not None:
            raise OptionError(f"no compiled path: {reason}")
        use_compiled = path == "compiled" or (path == "auto" and reason is None)
    else:
        if not _is_direct_both(model):
            raise OptionError(
                f"contact models and TOI settings apply to disc scenes; {ocp.name!r} is "
                "simulated by the generic time-of-impact method (contact='direct', toi='both')"
            )
        if integrator != "exact":
            raise OptionError(
                f"integrator {integrator!r} applies to disc scenes; the generic time-of-impact "
                "simulation integrates the flow exactly"
            )
        if path == "torch":
            raise OptionError("the torch simulator simulates disc scenes only; use path='compiled'")
        use_compiled = True
    if not use_compiled:
        from hybridoc.solvers.simulator import Simulator
        from hybridoc.solvers.threads import torch_threads

        torch_threads()  # one torch thread unless HYBRIDOC_THREADS says otherwise

        return Simulator(ocp, contact=model, integrator=integrator), "torch"
    from hybridoc.solvers.compiled import CompiledLoss, per_structure

    key = (
        ocp.steps, ocp.horizon, _model_key(model), integrator, path_weight,
        tuple(ocp.x0.tolist()),
    )  # fmt: skip
    loss = per_structure(
        _LOSSES,
        ocp,
        key,
        lambda: CompiledLoss(
            ocp, model, integrator=integrator if is_disc else None, path_weight=path_weight
        ),
    )
    return loss, "compiled"


def default_integrator(ocp: HybridOCP, contact: ContactModel) -> str:
    """``"exact"`` where it exists (impulse models with both TOI corrections, generic
    problems), else the paper's ``"symplectic-euler"``."""
    if not _disc(ocp):
        return "exact"
    exact = contact.impulse_based and getattr(contact, "toi", None) == "both"
    return "exact" if exact else "symplectic-euler"


def _initial(ocp: HybridOCP, initial: Any) -> np.ndarray:
    """The starting controls: the problem's guess, an ``(N, nu)`` array or a Solution's."""
    if initial is None:
        return np.array(ocp.u_guess, dtype=float)
    controls = getattr(initial, "controls", initial)
    return ocp.check_controls(controls, what="initial controls")


# ---------------------------------------------------------------------- the entry point
def checked_options(ocp: HybridOCP, options: GDOptions) -> GDOptions:
    """The options of a run, checked, with their defaults filled in.

    Parameters
    ----------
    ocp
        The problem (the defaults of ``lr``, ``iters`` and ``integrator`` depend on it).
    options
        The options as given.

    Returns
    -------
    GDOptions
        ``contact`` a :class:`~hybridoc.solvers.contacts.ContactModel` that carries the TOI
        setting (``toi`` is ``None``); ``integrator``, ``iters`` and ``lr`` set; ``smoothing``
        a tuple of floats, or ``None`` (the default of the optimiser); integers as ``int``.

    Raises
    ------
    hybridoc.errors.OptionError
        For an unknown name or a value out of range (one line), also of the problem's own
        defaults (its hints).
    """
    from hybridoc.solvers.contacts import contact_model

    o = options
    lr0, it0 = default_settings(ocp, o.optimizer)
    # the problem's defaults (its hints) pass the options' checks (GDOptions.__post_init__)
    o = dataclasses.replace(o, lr=lr0 if o.lr is None else o.lr,
                            iters=it0 if o.iters is None else o.iters)  # fmt: skip
    lr, iters = o.lr, o.iters
    model = contact_model(o.contact, **({} if o.toi is None else {"toi": o.toi}))
    integrator = default_integrator(ocp, model) if o.integrator is None else o.integrator
    smoothing = o.smoothing
    if smoothing is None:
        smoothing = DEFAULT_SMOOTHING if o.optimizer == "lbfgs" else ()
    _check_memory(ocp, o.starts, iters, o.hops, smoothing, o.terminal_iters)
    return dataclasses.replace(
        o, contact=model, toi=None, integrator=integrator, iters=int(iters), lr=float(lr),
        smoothing=_checked_smoothing(o.smoothing), starts=int(o.starts), hops=int(o.hops),
    )  # fmt: skip


def _checked_smoothing(smoothing: Any) -> tuple[float, ...] | None:
    if smoothing is None:
        return None
    weights = tuple(smoothing) if isinstance(smoothing, Iterable | np.ndarray) else None
    if (
        isinstance(smoothing, str)
        or weights is None
        or not all(isinstance(m, numbers.Real) and math.isfinite(m) and m >= 0 for m in weights)
    ):
        raise OptionError(f"smoothing weights must be finite numbers >= 0, got {smoothing!r}")
    return tuple(float(m) for m in weights)


def solve_gd(
    problem: ProblemLike,
    *,
    initial: Any = None,
    progress: ProgressLike = None,
    **options: Any,
) -> Solution:
    """Minimise the discrete objective by gradient descent through the simulation.

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`): a built-in name, a Scene, a
        HybridOCP, a ``.toml`` path or ``file.py:function``.
    initial
        Starting controls: ``None`` (the problem's guess), an ``(N, nu)`` array or a
        Solution.
    progress
        ``True`` for a progress meter on stderr, or a :class:`~hybridoc.progress.Progress`
        (``False``/``None``, the default: quiet). One meter serves the whole run: a stage
        per smoothing weight, hop round and multi-start phase, a count per iteration.
    contact, toi
        Disc scenes: the contact model, a name of
        :data:`hybridoc.solvers.contacts.CONTACT_MODELS` or a
        :class:`~hybridoc.solvers.contacts.ContactModel` with its own options
        (``LCP(toi="both")``, ``contact_model("compliant", stiffness=2e4)``), and the
        time-of-impact correction of an impulse model given by name (default ``"both"``).
    integrator
        ``"exact"`` or ``"symplectic-euler"`` (disc scenes only; the paper's). Default: exact
        for impulse models with both TOI corrections and for generic problems, symplectic
        Euler otherwise (the other settings have no exact form).
    optimizer
        ``"gd"`` (plain gradient descent, as in the paper), ``"adam"`` or ``"lbfgs"``
        (default: :class:`~hybridoc.solvers.optimizers.LBFGS`, a numpy port of
        ``torch.optim.LBFGS`` with its strong-Wolfe line search, as gd has always run it:
        one trial step of ``lr`` per iteration, taken when it lowers the loss,
        :data:`~hybridoc.solvers.optimizers.GD_LINE_SEARCH_EVALS`; SciPy's L-BFGS-B when
        the problem has control bounds). All run on numpy arrays: on the compiled path a
        solve imports no torch.
    smoothing
        Continuation weights ``mu_1 > mu_2 > ...``: before the real problem, solve it with the
        penalty ``mu sum_n |u_{n+1} - u_n|^2 / dt`` (about ``mu int |du/dt|^2 dt``) added, for
        each ``mu`` in turn, each stage starting from the previous result (``iters`` iterations
        per stage). The loss of piecewise-constant controls has a kink wherever an event
        crosses a grid time at which the control jumps, and gradient methods stall there; the
        penalty weakens those kinks so that the events first move to the right times.
        Default: :data:`DEFAULT_SMOOTHING` for ``lbfgs``, none for ``gd`` and ``adam``.
    iters, lr
        Iterations and learning rate; defaults from :func:`default_settings`.
    starts
        Multi-start: ``starts`` initial controls (the guess, perturbations of it, random smooth
        controls, controls aimed at each body and wall; :mod:`hybridoc.solvers.multistart`)
        descend together, one batched rollout per iteration, on a coarse grid; the best
        distinct results are refined by the single-start method at full resolution and the
        best of them returned. ``info["starts"]`` lists every start's result (its loss on
        the coarse grid; the judge's cost and events of each distinct optimum).
    seed
        Seed of the random starts (and of the hops' perturbations).
    hops
        Batched restarts after the descent, for losses with kinks and shallow local minima
        (any loss kinks where an event crosses a grid time, the symplectic Euler loss
        wherever a contact moves to another step, and gradient descent stalls at a kink that
        is not a minimum, or in a shallow local minimum beside a lower one; on the exact
        integrator a converged descent is taken past its kinks anyway, see Returns): in
        each round, :data:`HOP_BATCH` perturbations of the best control, at sizes spread
        geometrically from 1e-3 to 1 of its largest value, descend together by the batched
        L-BFGS of :mod:`hybridoc.solvers.multistart`; the lowest replaces the best when it is
        lower. Stops after ``hops`` rounds or :data:`HOP_PATIENCE` rounds without
        improvement. ``info["hops"]`` lists the rounds. Compiled path only.
    callback
        Called as ``callback(iteration, loss, controls)`` after every iteration; a true
        return value stops the optimisation.
    path
        ``"auto"`` (the compiled CasADi path where the model's CasADi step serves the scene,
        else torch), ``"compiled"`` or ``"torch"`` (disc scenes).
    max_step
        ``lbfgs`` only: the largest change of any control value in one iteration (longer
        steps are shortened and the curvature history is reset); default: no limit.
    path_weight
        Weight of the quadratic penalty on path-constraint violations (problems with
        ``path`` constraints).
    terminal_tol, terminal_rho, terminal_iters
        Problems with terminal constraints or a free final time (module notes):
        the largest terminal violation the judge may find for a success, the augmented
        Lagrangian's initial penalty and its number of outer iterations at most.
    time_limit
        Seconds of wall time after which the run stops where it is (checked at every
        evaluation of the loss) and returns its best iterate so far, judged, as
        ``not-converged`` (``info["stopped"] = "time-limit"``); default: no limit. A
        ``KeyboardInterrupt`` (Ctrl-C, SIGINT) does the same (``"interrupted"``); a second
        one during the judging of that iterate propagates.

    Returns
    -------
    hybridoc.solution.Solution
        Method ``"gd"``; the controls of the last iterate (of the best iterate if the loss
        became non-finite); ``cost`` is the judge's continuous cost of those controls.
        ``info`` holds the final discrete ``loss``, ``iterations``, ``message`` and
        ``converged``; ``status`` is ``success`` (the optimiser met its convergence test:
        L-BFGS could make no further progress, or the loss stalled, to :data:`STALL_RTOL`
        over :func:`stall_window` iterations, at the iteration limit), ``not-converged``
        (the iteration limit without meeting it, ``iters=0``, a stop by the callback, a
        non-finite or rising loss, a stall at a kink, ``time_limit`` or an interrupt) or
        ``infeasible``. Kinks: with the exact integrator and unbounded controls, a converged
        descent with an event within :data:`KINK_BAND` of a step of a grid time is taken on
        by a nonsmooth BFGS (:func:`_past_kinks`), and ``success`` needs its certificate
        (:data:`KINK_GTOL`); otherwise the status is ``not-converged``, "stalled at a kink:
        event k pinned at grid time t_j", and ``info["kinks"]`` holds the events near grid
        times, the certificate and the iterations. ``info["stages"]`` (the smoothing stages)
        and ``info["final_stage"]`` give each stage's iterations, loss evaluations and
        optimisation time; ``iterations``, ``loss_evaluations``, ``ms_per_iteration`` and
        ``timings["optimization_time_s"]`` are over all of them.
        ``settings`` holds the contact model's own
        (:meth:`~hybridoc.solvers.contacts.ContactModel.settings`) and the run's.

    Raises
    ------
    hybridoc.errors.OptionError
        For options out of range or that do not apply to the problem (one line).
    hybridoc.resources.ResourceError
        For sizes (``starts``, ``iters``, ``hops``) whose memory estimate exceeds
        :func:`memory_limit` (a :class:`~hybridoc.errors.SceneError`).
    TypeError
        For a keyword that is no option.
    """
    unknown = sorted(set(options) - _OPTION_NAMES)
    if unknown:
        raise TypeError(f"solve_gd() got an unexpected keyword argument {unknown[0]!r}")
    return run_gd(problem, GDOptions(**options), initial=initial, progress=progress)


solve_gd.__signature__ = _options_signature(solve_gd, GDOptions)  # type: ignore[attr-defined]
_OPTION_NAMES = frozenset(f.name for f in dataclasses.fields(GDOptions))


def run_gd(
    problem: ProblemLike,
    options: GDOptions | None = None,
    *,
    initial: Any = None,
    progress: ProgressLike = None,
) -> Solution:
    """:func:`solve_gd` with its options as one :class:`GDOptions` (``None``: the defaults).

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`).
    options
        The options, checked on construction; their problem-dependent defaults are filled
        in here (:func:`checked_options`).
    initial, progress
        As in :func:`solve_gd`.

    Returns
    -------
    hybridoc.solution.Solution
        As :func:`solve_gd`.
    """
    ocp = as_ocp(problem)
    opts = checked_options(ocp, GDOptions() if options is None else options)
    watch = _Watch(opts.time_limit)
    token = _WATCH.set(watch)
    # an interrupt CasADi swallows inside a loss call is still seen at the next check
    previous = flag_interrupts(watch)
    try:
        with progress_scope(progress, "gd") as meter:
            try:
                return _dispatch(ocp, opts, initial, meter)
            except (_OutOfTime, KeyboardInterrupt) as exc:
                why = "time-limit" if isinstance(exc, _OutOfTime) else "interrupted"
                return _stopped_solution(ocp, opts, initial, watch, why)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        _WATCH.reset(token)


# ---------------------------------------------------------------------- limits
class _OutOfTime(Exception):
    """The run passed its ``time_limit``."""


class _Watch:
    """The time limit of one :func:`solve_gd` run and its best iterate so far, which a stop
    at the limit or by an interrupt returns."""

    def __init__(self, time_limit: float | None) -> None:
        self.t0 = time.perf_counter()
        self.time_limit = time_limit
        self.deadline = None if time_limit is None else self.t0 + time_limit
        self.loss = math.inf
        self.u: np.ndarray | None = None
        self.horizon: float | None = None
        self.evaluations = 0
        self.iterations = 0  # of the optimisers that report them (not the batched ones)
        self.history: list[float] = []
        self.interrupted = False  # set by SIGINT (solvers.threads.flag_interrupts)

    def check(self) -> None:
        """Raise :class:`_OutOfTime` past the deadline, ``KeyboardInterrupt`` after a SIGINT
        (also one that CasADi swallowed)."""
        if self.interrupted:
            raise KeyboardInterrupt
        if self.deadline is not None and time.perf_counter() > self.deadline:
            raise _OutOfTime

    def offer(self, loss: float, u: np.ndarray, horizon: float | None = None, *,
              latest: bool = False) -> None:  # fmt: skip
        """An iterate of the problem's grid and its loss (without smoothing penalties):
        kept when it is the lowest so far, or always (``latest``: the augmented
        Lagrangian's, whose lower values may be infeasible)."""
        self.evaluations += 1
        if math.isfinite(loss) and (latest or loss < self.loss):
            self.loss, self.u, self.horizon = float(loss), np.array(u, dtype=float), horizon
            self.history.append(float(loss))


_WATCH: contextvars.ContextVar[_Watch | None] = contextvars.ContextVar("gd_watch", default=None)


def _watch() -> _Watch | None:
    return _WATCH.get()


def _stopped_solution(
    ocp: HybridOCP, opts: GDOptions, initial: Any, watch: _Watch, why: str
) -> Solution:
    """The best iterate of a run stopped at its time limit or by an interrupt, judged, as
    ``not-converged``."""
    elapsed = time.perf_counter() - watch.t0
    if why == "time-limit":
        head = f"stopped at the time limit of {watch.time_limit:g} s"
    else:
        head = f"interrupted after {elapsed:.3g} s"
    if watch.u is None:
        u, horizon = _initial(ocp, initial), None
        if ocp.has_bounds:
            u = np.clip(u, ocp.u_min, ocp.u_max)
        text = f"{head}, before the first iterate: the controls are the initial guess"
    else:
        u, horizon = watch.u, watch.horizon
        hint = "raise the time limit" if why == "time-limit" else "let it run"
        text = (
            f"{head}: returning the best iterate so far (discrete loss {watch.loss:.10g}, "
            f"after {watch.iterations} iteration(s)); {hint} to converge"
        )
    judged = ocp.replace(horizon=horizon) if horizon is not None and ocp.free_horizon else ocp
    ev = evaluate(judged, u)
    info: dict[str, Any] = {
        "loss": watch.loss if watch.u is not None else float("nan"),
        "iterations": watch.iterations,
        "loss_evaluations": watch.evaluations,
        "nan_stop": False,
        "diverged": False,
        "converged": False,
        "message": text,
        "stopped": why,
    }
    if horizon is not None and ocp.free_horizon:
        info["horizon"] = float(horizon)
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings={**_settings(ocp, opts, opts.path), "time_limit": opts.time_limit},
        timings={"solve_time_s": elapsed, "optimization_time_s": elapsed},
        info=info,
        arrays={"loss_history": np.array(watch.history, dtype=float)},
    )
    return sol.set_status(Status.NOT_CONVERGED, text)


# the memory estimates' limit lives in hybridoc.resources (shared by every command); kept
# here under their old names
available_memory = resources.available_memory
memory_limit = resources.memory_limit
MEMORY_FRACTION = resources.MEMORY_FRACTION


#: bytes per stored float in a Python list (a pointer and a float object)
_LIST_FLOAT = 32


def _size_estimates(
    ocp: HybridOCP, starts: int, iters: int, hops: int, smoothing: Any, terminal_iters: int
) -> list[tuple[str, int, int, str]]:
    """``(argument, value, bytes, per-unit text)`` of each size argument of a run: what its
    value allocates at least (``smoothing``: the continuation's weights, resolved).

    - ``starts``: each start of the multi-start holds its starting controls on the
      problem's grid (twice: the pool and its stack), on the coarse grid of at most
      :data:`MULTISTART_STEPS` steps its iterate, the batched L-BFGS's 20 curvature pairs,
      trial points and gradients (48 arrays in all) and the rollout's states and adjoints
      (6 per state and step), in float64, and its row of the report (1 KiB);
    - ``iters``: the loss history, a float per iteration and stage;
    - ``hops``: a record per round and the batch of :data:`HOP_BATCH` perturbations;
    - ``terminal_iters``: a record per outer iteration.
    """
    coarse = min(ocp.steps, MULTISTART_STEPS)
    per_start = 16 * ocp.steps * ocp.nu + 8 * coarse * (48 * ocp.nu + 6 * ocp.nx) + 1024
    stages = 1 + len(tuple(smoothing or ()))
    return [
        ("starts", starts, starts * per_start, f"{_fmt_bytes(per_start)} per start"),
        ("iters", iters, iters * stages * _LIST_FLOAT,
         f"{_LIST_FLOAT} B per iteration of each of {stages} stage(s)"),
        ("hops", hops, hops * 512, "512 B per round"),
        ("terminal_iters", terminal_iters, terminal_iters * 512, "512 B per outer iteration"),
    ]  # fmt: skip


_fmt_bytes = resources.fmt_bytes


def _check_memory(
    ocp: HybridOCP, starts: Any, iters: Any, hops: Any, smoothing: Any, terminal_iters: Any
) -> None:
    """Refuse sizes whose memory estimate (:func:`_size_estimates`) passes
    :func:`memory_limit` (a :class:`~hybridoc.resources.ResourceError`, a
    :class:`~hybridoc.errors.SceneError`, naming the argument, the estimate and the limit;
    :func:`hybridoc.resources.check`): ``HYBRIDOC_MEMORY_LIMIT`` sets the limit,
    ``--allow-large`` or ``HYBRIDOC_ALLOW_LARGE=1`` lifts it."""
    if not all(_whole(v, 0) for v in (starts, iters, hops, terminal_iters)):
        return  # the range checks report those
    for name, value, need, unit in _size_estimates(
        ocp, starts, iters, hops, _checked_smoothing(smoothing), terminal_iters
    ):
        resources.check(f"{name}={value}", need, unit, f"use a smaller {name.replace('_', '-')}")


def _dispatch(ocp: HybridOCP, opts: GDOptions, initial: Any, progress: Progress) -> Solution:
    """Hops around a multi-start or a continuation, as ``opts`` (checked) says; the
    augmented Lagrangian for terminal constraints or a free final time."""
    if ocp.has_terminal_constraints or ocp.free_horizon:
        return _solve_terminal(ocp, opts, initial, progress)
    if opts.hops:
        t_hop = time.perf_counter()
        loss_obj, used_path = make_loss(
            ocp, opts.contact, opts.integrator, opts.path, opts.path_weight
        )
        if not hasattr(loss_obj, "value_and_grad_batch"):
            raise OptionError(
                f"hops run batched rollouts on the compiled path; the {used_path} path of "
                f"contact {opts.contact.label!r} has none"
            )
        base = _dispatch(ocp, dataclasses.replace(opts, hops=0), initial, progress)
        return _hop(ocp, base, loss_obj, opts, t_hop, progress)
    if opts.starts > 1:
        return _multistart(ocp, opts, progress)
    return _continuation(ocp, opts, initial, progress)


def _settings(ocp: HybridOCP, opts: GDOptions, used_path: str) -> dict[str, Any]:
    """The JSON-ready settings of a Solution: the contact model's and the run's."""
    return {
        **opts.contact.settings(),
        "integrator": opts.integrator,
        "optimizer": opts.optimizer,
        "iters": opts.iters,
        "lr": opts.lr,
        "path": used_path,
        "simulation": "disc" if _disc(ocp) else "generic",
    }


def _continuation(ocp: HybridOCP, opts: GDOptions, initial: Any, progress: Progress) -> Solution:
    """One start: the smoothing stages (``opts.smoothing``), then the problem itself."""
    t_start = time.perf_counter()
    loss_obj, used_path = make_loss(ocp, opts.contact, opts.integrator, opts.path, opts.path_weight)
    u0 = _initial(ocp, initial)
    if ocp.has_bounds:
        u0 = np.clip(u0, ocp.u_min, ocp.u_max)
    smoothing = opts.smoothing
    if smoothing is None:
        smoothing = DEFAULT_SMOOTHING if opts.optimizer == "lbfgs" else ()
    settings = _settings(ocp, opts, used_path)
    if not smoothing:
        progress.stage(f"descent ({opts.optimizer})")
        return _descend(ocp, opts, loss_obj, u0, settings, progress, t_start=t_start)
    histories, its, stages = [], 0, []
    n = len(smoothing) + 1
    for i, mu in enumerate(smoothing):
        progress.stage(f"stage {i + 1} of {n}, smoothing mu {mu:g}")
        stage = _descend(ocp, opts, loss_obj, u0, dict(settings), progress, penalty=mu)
        u0 = stage.controls
        histories.append(stage.arrays["loss_history"])
        its += stage.info["iterations"]
        stages.append({"mu": mu, "loss": stage.info["loss"], "cost": stage.cost,
                       **_stage_counts(stage)})  # fmt: skip
        # a stage need not converge (the next one starts from it), but NaN or a rising
        # loss ends the continuation
        if stage.info["nan_stop"] or stage.info["diverged"]:
            break
    progress.stage(f"stage {n} of {n}, descent ({opts.optimizer}) after smoothing")
    sol = _descend(ocp, opts, loss_obj, u0, settings, progress)
    sol.settings["smoothing"] = list(smoothing)
    last = _stage_counts(sol)
    # every count over all stages (issue #34: the evaluations and time were the last one's)
    sol.info["final_stage"] = last
    sol.info["iterations"] += its
    sol.info["loss_evaluations"] = last["loss_evaluations"] + sum(
        st["loss_evaluations"] for st in stages)  # fmt: skip
    sol.timings["optimization_time_s"] = last["optimization_time_s"] + sum(
        st["optimization_time_s"] for st in stages)  # fmt: skip
    sol.info["ms_per_iteration"] = 1e3 * sol.timings["optimization_time_s"] / max(
        sol.info["iterations"], 1)  # fmt: skip
    sol.info["stages"] = stages
    sol.arrays["loss_history"] = np.concatenate(histories + [sol.arrays["loss_history"]])
    # where each stage starts in loss_history: the curve jumps there as the loss changes
    starts = np.cumsum([0] + [len(h) for h in histories]).tolist()
    names = [f"mu {st['mu']:g}" for st in stages] + ["no smoothing"]
    sol.info["history_stages"] = [[int(k), name] for k, name in zip(starts, names, strict=True)]
    sol.timings["solve_time_s"] = time.perf_counter() - t_start
    return sol


def _stage_counts(sol: Solution) -> dict[str, Any]:
    """The iterations, loss evaluations and optimisation time of one descent."""
    return {
        "iterations": int(sol.info["iterations"]),
        "loss_evaluations": int(sol.info["loss_evaluations"]),
        "optimization_time_s": float(sol.timings["optimization_time_s"]),
    }


def _descend(
    ocp: HybridOCP,
    opts: GDOptions,
    loss_obj: Any,
    u0: np.ndarray,
    settings: dict[str, Any],
    progress: Progress,
    *,
    penalty: float = 0.0,
    t_start: float | None = None,
) -> Solution:
    """One descent from ``u0`` (with the smoothing ``penalty``), judged: its Solution."""
    t_start = time.perf_counter() if t_start is None else t_start
    run = _Run(ocp, loss_obj, opts, penalty, progress)
    final_u, final_loss, k, message, nan_stop, history = run.optimise(u0)
    ev = evaluate(ocp, final_u)
    diverged = bool(history) and history[-1] > history[0] * (1 + 1e-9) + 1e-300
    converged, why = _converged(message, history, k, opts.iters)
    kink: dict[str, Any] | None = None
    if converged and not (nan_stop or diverged) and penalty == 0.0 and _kinks_apply(ocp, opts):
        final_u, final_loss, ev, kink = _past_kinks(ocp, run, final_u, final_loss, ev, progress)
        if kink is not None:
            k += kink["iterations"]
            history.append(final_loss)
            if kink["stalled"]:
                converged, why = False, kink["message"]
    if converged and kink is None and penalty == 0.0 and np.array_equal(final_u, u0):
        converged, why = _unmoved(run, final_u)
    t_opt = time.perf_counter() - run.t_loop
    status, status_message = _status(ev, message, history, nan_stop, diverged, converged, why)
    info = {
        "loss": float(final_loss),
        "iterations": int(k),
        "loss_evaluations": int(run.n_evals),
        "nan_stop": nan_stop,
        "diverged": diverged,
        "converged": converged and not (nan_stop or diverged),
        "message": message,
        "ms_per_iteration": 1e3 * t_opt / max(k, 1),
        "restarts": run.restarts,
    }
    if kink is not None:
        info["kinks"] = kink
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings=settings,
        timings={"solve_time_s": time.perf_counter() - t_start, "optimization_time_s": t_opt},
        info=info,
        arrays={"loss_history": np.array(history, dtype=float)},
    )
    return sol.set_status(status, status_message)


def _unmoved(run: _Run, u: np.ndarray) -> tuple[bool, str]:
    """A descent that claims convergence without having moved from its start ``u``: whether
    ``u`` is stationary after all (the certificate of :data:`KINK_GTOL` on the scaled
    objective), and if not, the status message. Without this check a step that is too
    short for the controls' size (another unit, a tiny ``lr``) leaves the start unchanged
    and "L-BFGS made no further progress" reads as success."""
    run.scale = 1.0 / (run.jc * run.dts)
    x = run.scaled(u)
    f, g = run.fun(x)
    stat = float(np.linalg.norm(g)) * (1.0 + float(np.abs(x).max())) / (1.0 + abs(f))
    if stat <= KINK_GTOL:
        return True, ""
    return False, (
        f"the descent took no step from its start, where the gradient does not vanish "
        f"(stationarity {stat:.2e} > {KINK_GTOL:g} in the problem's scaled units): "
        "no convergence shown; try another --lr"
    )


# ---------------------------------------------------------------------- kinks
KINK_BAND = 0.1
"""An event within this fraction of a step of a grid time (not 0 or ``T``) sits at or
near a kink of the loss (:func:`_past_kinks`)."""
KINK_ITERS = 1000
"""The most iterations of the nonsmooth BFGS that takes a descent past a kink."""
KINK_GTOL = 1e-6
"""A point at a kink is stationary when the smallest convex combination of the gradients
around it (:attr:`~hybridoc.solvers.optimizers.NonsmoothResult.stationarity`, of the loss
per step ``J / dt``) times ``1 + max |u|`` is at most this times ``1 + |J / dt|``: no
direction lowers the loss by more than about this, relative, per unit change of the
controls."""
KINK_MAX_SIZE = 2000
"""The nonsmooth BFGS keeps a dense ``n x n`` inverse Hessian (``n = N nu``): above this
size gd reports a kink without going past it."""


def _kinks_apply(ocp: HybridOCP, opts: GDOptions) -> bool:
    """Whether gd looks for kinks after a converged descent: the exact integrator (the
    judge's event times are the simulation's), unbounded controls, no callback (the
    nonsmooth iterations do not report to it)."""
    return opts.integrator == "exact" and not ocp.has_bounds and opts.callback is None


def pinned_events(ocp: HybridOCP, ev: Evaluation, band: float = KINK_BAND) -> list[dict[str, Any]]:
    """The events of an evaluation within ``band`` of a step of an inner grid time
    ``t_k = k T / N``, ``0 < k < N``, where the piecewise-constant control jumps and the loss
    has a kink: ``{"event", "name", "time", "grid_index", "grid_time", "offset"}`` each
    (``event`` counts from 1, ``offset`` is ``(time - t_k) / dt``)."""
    dt = ocp.dt
    out = []
    for i, e in enumerate(ev.events):
        k = round(e.time / dt)
        offset = e.time / dt - k
        if 0 < k < ocp.steps and abs(offset) <= band:
            out.append({
                "event": i + 1, "name": e.name or str(e.guard), "time": e.time,
                "grid_index": int(k), "grid_time": k * dt, "offset": float(offset),
            })  # fmt: skip
    return out


def _past_kinks(
    ocp: HybridOCP,
    run: _Run,
    u: np.ndarray,
    loss: float,
    ev: Evaluation,
    progress: Progress,
) -> tuple[np.ndarray, float, Evaluation, dict[str, Any] | None]:
    """Take a converged descent past the kinks of its loss.

    L-BFGS stalls where an event time crosses a grid time (the loss is continuous there but
    its gradient jumps), short of the kink or on it. When an event is within
    :data:`KINK_BAND` of a step of a grid time, the nonsmooth BFGS
    (:func:`~hybridoc.solvers.optimizers.nonsmooth_bfgs`) continues from the result: it
    converges onto the kink where the optimum of the grid sits on one, and moves on where
    it does not. Its certificate, the smallest convex combination of the gradients at its
    last iterates, decides: stationary (:data:`KINK_GTOL`), or stalled at a kink.

    Returns the controls, their loss and evaluation, and ``None`` (no event near a grid
    time) or the record ``info["kinks"]``: the events near grid times before and after,
    the iterations, evaluations, the certificate, ``stalled`` and the status message.
    """
    from hybridoc.solvers.optimizers import nonsmooth_bfgs

    near = pinned_events(ocp, ev)
    if not near:
        return u, loss, ev, None
    record: dict[str, Any] = {"before": near, "loss_before": float(loss), "iterations": 0}
    scale = 1.0 / (run.jc * run.dts)  # the objective L-BFGS sees, (J / jc) / dt~
    run.scale = scale
    x = run.scaled(u)  # scaled controls: the certificate is the same in any units
    f_here, g_here = run.fun(x)
    here = float(np.linalg.norm(g_here)) * (1.0 + float(np.abs(x).max())) / (1.0 + abs(f_here))
    if here <= KINK_GTOL:  # stationary where it stands: the loss is smooth there
        record.update(after=near, loss=float(loss), stationarity=here, stalled=False, message="")
        return u, loss, ev, record
    if u.size > KINK_MAX_SIZE:
        relative = here
        record["message_bfgs"] = f"not run: {u.size} controls, above {KINK_MAX_SIZE}"
    else:
        progress.stage(f"past the kinks: event {near[0]['event']} near grid time "
                       f"t_{near[0]['grid_index']}")  # fmt: skip
        res = nonsmooth_bfgs(run.fun, x, max_iter=KINK_ITERS, gtol=KINK_GTOL,
                             start=(f_here, g_here))  # fmt: skip
        record.update(iterations=res.iterations, evaluations=res.evaluations,
                      message_bfgs=res.message, bundle=res.bundle)  # fmt: skip
        relative = res.stationarity
        if res.f < f_here:
            u, loss = run.physical(res.x), res.f / scale
            ev = evaluate(ocp, u)
    after = pinned_events(ocp, ev)
    stalled = not relative <= KINK_GTOL
    record.update(after=after, loss=float(loss), stationarity=float(relative), stalled=stalled)
    record["message"] = ""
    if stalled:
        pin = (after or near)[0]
        record["message"] = (
            f"stalled at a kink: event {pin['event']} ({pin['name']!r}, t = {pin['time']:.10g}) "
            f"pinned at grid time t_{pin['grid_index']} = {pin['grid_time']:.10g} (off by "
            f"{pin['offset']:+.2e} of a step), where the loss is not smooth; the gradients "
            f"around it do not cancel (stationarity {relative:.2e} > {KINK_GTOL:g})"
        )
    return u, loss, ev, record


def _infeasible(ev: Evaluation) -> str:
    return ev.infeasibility() or "the judge finds the controls infeasible"


def _status(
    ev: Evaluation,
    message: str,
    history: Sequence[float],
    nan_stop: bool,
    diverged: bool,
    converged: bool,
    why: str,
) -> tuple[Status, str]:
    """The status of one descent and its message: a non-finite stop, a rising loss, no
    convergence (``why``), controls the judge finds infeasible, or success."""
    if nan_stop:
        return Status.NOT_CONVERGED, message
    if diverged:
        return Status.NOT_CONVERGED, (
            f"the loss rose from {history[0]:.6g} to {history[-1]:.6g}: the optimisation "
            "diverged; try a smaller learning rate"
        )
    if not converged:
        if not ev.feasible:  # the stronger finding: what it returns is not admissible at all
            return Status.INFEASIBLE, f"{_infeasible(ev)}; and {why}" if why else _infeasible(ev)
        return Status.NOT_CONVERGED, why
    if not ev.feasible:
        return Status.INFEASIBLE, _infeasible(ev)
    return Status.SUCCESS, ""


def _converged(message: str, history: Sequence[float], k: int, iters: int) -> tuple[bool, str]:
    """Whether one optimisation met its convergence test, and if not, the status message.

    The test: the optimiser stopped because it could make no further progress (L-BFGS: a
    fresh start moves nowhere; L-BFGS-B: SciPy's own test), or, at the iteration limit, the
    loss spread by at most :data:`STALL_RTOL` (relative, ``max - min`` over the last
    :func:`stall_window` iterations; a loss tending to 0 is measured against 1e-12 of the
    initial one). Plain ``gd`` and ``adam`` have only the second.
    """
    if message.startswith("converged"):
        return True, ""
    if message == "stopped by the callback":
        return False, f"stopped by the callback after {k} iteration(s), before converging"
    if iters == 0:
        return False, "iters = 0: no descent was run; the controls are the initial guess"
    w = stall_window(iters)
    if len(history) > w:
        window = np.asarray(history[-w - 1 :], dtype=float)
        # the spread over the window, not two end points (a 2-cycle would pass), relative
        # to the loss, with a floor for a loss that falls towards 0
        scale = max(abs(float(window.min())), 1e-12 * abs(float(history[0])), 1e-300)
        change = float(window.max() - window.min()) / scale
        if change <= STALL_RTOL:
            return True, ""
        tail = f"the loss still changed by {change:.2e} (relative) over the last {w} iterations"
        if float(window[1:].min()) >= float(np.min(history[:-w])):
            # no better than before the window: it oscillates, more iterations will not help
            return False, (
                f"stopped at the iteration limit ({iters}) before converging: {tail} without "
                "improving on its best loss (it oscillates: a smaller --lr, or the default "
                "optimizer lbfgs, may settle)"
            )
    else:
        tail = (
            f"{k} iteration(s) are too few to tell (the test: a relative change of the loss of "
            f"at most {STALL_RTOL:g} over the last {w} iterations)"
        )
    return False, (
        f"stopped at the iteration limit ({iters}) before converging: {tail}; raise the "
        "iterations (--iters)"
    )


# ---------------------------------------------------------------------- hops
HOP_BATCH = 32
"""Hops (:func:`solve_gd`): perturbations of the best control per round."""
HOP_ITERS = 150
"""Hops: iterations of the batched L-BFGS of each round."""
HOP_PATIENCE = 2
"""Hops: rounds without improvement before stopping."""
HOP_SCALES = (1e-3, 1.0)
"""Hops: smallest and largest perturbation size, relative to ``max |u|`` (geometric spread)."""


def _hop(
    ocp: HybridOCP,
    base: Solution,
    loss_obj: Any,
    opts: GDOptions,
    t0: float,
    progress: Progress,
) -> Solution:
    """:func:`solve_gd` with ``hops`` (see there): batched restarts around the best control."""
    from hybridoc.solvers.multistart import batched_lbfgs, smooth_noise

    if base.info.get("nan_stop") or base.info.get("diverged"):
        return base
    # scaled controls u / cs and loss (J / jc) / dt~ (units): the same hops in any units
    cs, jc, tc = units(ocp)
    per = jc * (ocp.horizon / ocp.steps / tc)
    lower = upper = None
    if ocp.has_bounds:
        lower, upper = ocp.u_min / cs, ocp.u_max / cs

    watch = _watch()

    def vg(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if watch is not None:
            watch.check()
        U = X * cs
        J, gU, _ = loss_obj.value_and_grad_batch(U)
        if watch is not None and len(J):
            b = int(np.argmin(np.where(np.isfinite(J), J, np.inf)))
            watch.offer(float(J[b]), U[b])
        return J / per, gU * cs / per  # the batched L-BFGS's scaling, as in the multi-start

    x = np.array(base.controls, dtype=float) / cs
    f = float(loss_obj.value_and_grad(x * cs)[0]) / jc
    rng = np.random.default_rng(opts.seed)
    rounds: list[dict[str, Any]] = []
    stale = 0
    for r in range(opts.hops):
        progress.stage(f"hops: round {r + 1} of at most {opts.hops}")
        progress.detail(f"loss {f:.6g}")
        size = max(float(np.abs(x).max()), 1e-3)
        scales = size * np.geomspace(*HOP_SCALES, HOP_BATCH)
        P = np.stack([x + sc * smooth_noise(rng, *x.shape, modes=8) for sc in scales])
        if lower is not None:
            P = np.clip(P, lower, upper)
        X, F, _ = batched_lbfgs(vg, P, iters=HOP_ITERS, lower=lower, upper=upper)
        F = np.where(np.isfinite(F), F * (per / jc), np.inf)
        k = int(np.argmin(F))
        improved = bool(F[k] < f - 1e-13 * max(abs(f), 1.0))
        rounds.append({"loss": float(F[k]), "improved": improved, "size": float(scales[k] / size)})
        if improved:
            x, f, stale = X[k], float(F[k]), 0
        else:
            stale += 1
            if stale >= HOP_PATIENCE:
                break
    x, f = x * cs, f * jc  # back in the problem's units
    for r in rounds:
        r["loss"] *= jc
    kink = None
    improved = any(r["improved"] for r in rounds)
    if improved and _kinks_apply(ocp, opts):
        # the batched L-BFGS stalls at kinks as the single descent does
        run = _Run(ocp, loss_obj, opts, 0.0, progress)
        x, f, _, kink = _past_kinks(ocp, run, x, f, evaluate(ocp, x), progress)
    return _hopped_solution(ocp, base, x, f, rounds, stale, opts.hops, t0, kink)


def _hopped_solution(
    ocp: HybridOCP,
    base: Solution,
    x: np.ndarray,
    f: float,
    rounds: list[dict[str, Any]],
    stale: int,
    hops: int,
    t0: float,
    kink: dict[str, Any] | None = None,
) -> Solution:
    """The Solution of the hops: the best control ``x`` (loss ``f``), judged; ``kink`` the
    record of :func:`_past_kinks` on it."""
    ev = evaluate(ocp, x)
    # converged: the descent met its own test, or the hops moved it and then found nothing
    # lower in HOP_PATIENCE rounds (a descent stopped at its iteration limit that no hop
    # improves has shown nothing)
    improved = any(r["improved"] for r in rounds)
    converged = bool(base.info.get("converged")) or (improved and stale >= HOP_PATIENCE)
    info = dict(
        base.info, loss=f, hops=rounds, loss_before_hops=base.info.get("loss"),
        converged=converged,
    )  # fmt: skip
    if kink is not None:
        info["kinks"] = kink
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings=dict(base.settings, hops=hops),
        timings=dict(base.timings, hop_time_s=time.perf_counter() - t0 - base.timings.get(
            "solve_time_s", 0.0), solve_time_s=time.perf_counter() - t0),
        info=info,
        arrays=dict(base.arrays),
    )  # fmt: skip
    status, message = Status.SUCCESS, ""
    if kink is not None and kink["stalled"]:
        sol.info["converged"] = False
        status, message = Status.NOT_CONVERGED, f"after the hops, {kink['message']}"
    elif not converged:
        status, message = Status.NOT_CONVERGED, (
            f"{base.message}; and the hops did not settle either" if base.message else
            "the hops did not settle"
        )  # fmt: skip
    elif not ev.feasible:
        status, message = Status.INFEASIBLE, _infeasible(ev)
    return sol.set_status(status, message)


# ---------------------------------------------------------------------- multi-start
#: multi-start: the coarse grid of the batched phase, its iterations, and how many distinct
#: results are refined at full resolution
MULTISTART_STEPS = 60
MULTISTART_ITERS = 60
MULTISTART_REFINE = 2
MULTISTART_SMOOTHING = (3e-6,)


def _multistart(ocp: HybridOCP, opts: GDOptions, progress: Progress) -> Solution:
    """:func:`solve_gd` with ``starts > 1`` (see its ``starts``)."""
    from hybridoc.solvers.multistart import distinct_basins, explore

    t0 = time.perf_counter()
    if _disc(ocp) and opts.contact.name != "direct":
        raise OptionError(
            "the batched multi-start explores with the compiled exact simulation of contact "
            "'direct'; other contact models start from its result with --initial"
        )
    coarse = min(ocp.steps, MULTISTART_STEPS)
    rows: list[dict[str, Any]] = []
    progress.stage(f"multi-start: {opts.starts} starts on {coarse} steps")
    watch = _watch()
    found = explore(
        ocp, opts.starts, seed=opts.seed, steps=coarse, iters=MULTISTART_ITERS, report=rows,
        loss_for=exploration_loss, deadline=None if watch is None else watch.deadline,
    )  # fmt: skip
    if watch is not None:
        for r in found:  # judged on the problem's grid: the exact loss is the judged cost
            watch.offer(float(r["cost"]), r["controls"])
        watch.check()
    t_explore = time.perf_counter() - t0
    single = dataclasses.replace(opts, starts=1)
    # the batched phase has found the basin: one light smoothing stage for the kinks
    smoothing = opts.smoothing
    if smoothing is None:
        smoothing = MULTISTART_SMOOTHING if opts.optimizer == "lbfgs" else ()
    refined: list[Solution] = []
    for r in distinct_basins(found):
        key = tuple(r["sequence"])
        progress.stage(f"multi-start: refining the basin {' '.join(key) or '(no events)'}")
        refine = dataclasses.replace(single, smoothing=smoothing)
        refined.append(_continuation(ocp, refine, r["controls"], progress))
        if len(refined) >= MULTISTART_REFINE:
            break
    if not refined:
        return _continuation(ocp, single, None, progress)
    best = min(refined, key=lambda s: s.cost)
    best.settings["starts"] = opts.starts
    best.settings["seed"] = opts.seed
    best.info["starts"] = rows  # every start: coarse loss, judged cost and events
    best.info["explore_steps"] = coarse
    best.info["refined"] = [{"cost": s.cost, "sequence": s.sequence} for s in refined]
    best.timings["explore_time_s"] = t_explore
    best.timings["solve_time_s"] = time.perf_counter() - t0
    return best


def exploration_loss(coarse: HybridOCP) -> Any:
    """The loss the multi-start explores with: the compiled exact simulation, contact
    ``direct`` with TOI ``both`` (kept in the cache of :func:`make_loss`)."""
    from hybridoc.solvers.contacts import contact_model

    return make_loss(coarse, contact_model("direct", toi="both"), "exact")[0]


# ---------------------------------------------------------------------- one optimisation
_Result = tuple[np.ndarray, float, int, str, bool, list[float]]
"""What :meth:`_Run.optimise` returns: controls, loss, iterations, message, NaN stop and the
loss history."""


class _Run:
    """One optimisation of :func:`solve_gd` (no continuation), on numpy buffers.

    The objective (the loss with the smoothing and path penalties) and its gradient come
    from the compiled loss's ``value_and_grad`` as numpy arrays (the torch simulator's
    through its autograd: :func:`_torch_value_and_grad`); the optimisers are those of
    :mod:`hybridoc.solvers.optimizers` (``torch.optim``'s, ported), or SciPy's L-BFGS-B
    with bounds.
    """

    def __init__(
        self,
        ocp: HybridOCP,
        loss_obj: Any,
        opts: GDOptions,
        penalty: float,
        progress: Progress,
    ) -> None:
        self.ocp = ocp
        self.loss_obj = loss_obj
        self.optimizer = opts.optimizer
        self.lr = opts.lr
        self.iters = opts.iters
        self.max_step = math.inf if opts.max_step is None else opts.max_step
        self.penalty = penalty
        self.callback = opts.callback
        self.progress = progress
        self.n_evals = 0
        self.restarts = 0
        self.t_loop = time.perf_counter()
        self.shape = (ocp.steps, ocp.nu)
        # the optimisers see scaled controls u / cs and the loss per unit of cost and scaled
        # step, (J / jc) / (dt / tc): the same numbers in any units (module notes)
        self.cs, self.jc, self.tc = units(ocp)
        self.dts = ocp.dt / self.tc
        self.scale = 1.0
        self.best: dict[str, Any] = {"loss": math.inf, "u": None}
        self.last: tuple[np.ndarray, float] | None = None
        self.watch = _watch()
        if hasattr(loss_obj, "value_and_grad"):
            self.loss_grad: Callable[[np.ndarray], tuple[float, np.ndarray]] = lambda u: (
                loss_obj.value_and_grad(u)[:2]
            )
        else:
            self.loss_grad = _torch_value_and_grad(loss_obj)

    def value_and_grad(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        """The objective (with the smoothing and path penalties) of controls ``u`` and its
        gradient; keeps the best and the last evaluation."""
        self.n_evals += 1
        if self.watch is not None:
            self.watch.check()
        if not np.isfinite(u).all():
            raise _NonFinite("the controls became NaN or infinite")
        value, grad = self.loss_grad(u)
        value = float(value)
        if self.watch is not None:
            self.watch.offer(value, u)
        if self.penalty:
            # mu sum |du~|^2 / dt~ in units of cost: the same weight in any units
            diff = (u[1:] - u[:-1]) / self.cs
            value = value + self.penalty * self.jc * float((diff * diff).sum()) / self.dts
            grad = np.array(grad, dtype=float)
            w = 2.0 * self.penalty * self.jc / self.dts
            grad[1:] += w * diff / self.cs
            grad[:-1] -= w * diff / self.cs
        if not math.isfinite(value):
            raise _NonFinite(f"the loss became {value}")
        if value < self.best["loss"]:
            self.best["loss"], self.best["u"] = value, u.copy()
        self.last = (u.copy(), value)
        if not np.isfinite(grad).all():
            raise _NonFinite("the gradient became NaN or infinite")
        return value, grad

    def fun(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """The scaled objective (times :attr:`scale`) of flat scaled controls ``u / cs``, for
        the optimisers."""
        value, grad = self.value_and_grad(self.physical(x))
        return value * self.scale, np.ravel(grad * self.cs) * self.scale

    def physical(self, x: np.ndarray) -> np.ndarray:
        """Controls ``(N, nu)`` of flat scaled controls."""
        return x.reshape(self.shape) * self.cs

    def scaled(self, u: np.ndarray) -> np.ndarray:
        """Flat scaled controls of controls ``(N, nu)``."""
        return np.ravel(u / self.cs)

    def loss_here(self, u: np.ndarray) -> float:
        """The loss at ``u`` (the last evaluation when it was there: no second rollout)."""
        if self.last is not None and np.array_equal(self.last[0], u):
            return self.last[1]
        return self.value_and_grad(u)[0]

    def report(self, k: int, loss: float, controls: Callable[[], np.ndarray]) -> bool:
        """Iteration ``k`` is done: count it, call the callback; whether the callback stops."""
        # the iteration limit is no total (a stage stops at convergence): no bar to it
        self.progress.count(k, None, f"iterations, loss {loss:.6g}")
        if self.watch is not None:
            self.watch.iterations += 1
        return self.callback is not None and bool(self.callback(k, loss, controls()))

    def optimise(self, u0: np.ndarray) -> _Result:
        """Run the optimiser; returns controls, loss, iterations, message, NaN stop, history."""
        self.t_loop = time.perf_counter()
        if self.optimizer == "lbfgs" and self.ocp.has_bounds:
            return self.lbfgsb(u0)
        u0 = np.array(u0, dtype=float)
        self.best = {"loss": math.inf, "u": u0.copy()}
        history: list[float] = []
        state = {"u": u0}
        k = 0
        try:
            if self.optimizer == "lbfgs":
                message, k = self.lbfgs(u0, history, state)
            else:
                message, k = self.first_order(u0, history, state)
            u = state["u"]
            if self.optimizer != "lbfgs" or not history:
                history.append(self.loss_here(u))
            return u.copy(), history[-1], k, message, False, history
        except _NonFinite as exc:
            best, k = self.best, state.get("k", k)
            message = (
                f"stopped early at iteration {k}: {exc}; returning the best iterate "
                f"(discrete loss {best['loss']:.6g}); try a smaller learning rate"
            )
            return best["u"], best["loss"], k, message, True, history or [best["loss"]]

    def first_order(
        self, u: np.ndarray, history: list[float], state: dict[str, Any]
    ) -> tuple[str, int]:
        """Plain gradient descent or Adam, projected on the control bounds."""
        from hybridoc.solvers.optimizers import SGD, Adam

        opt = SGD(self.lr) if self.optimizer == "gd" else Adam(self.lr)
        ocp = self.ocp
        for k in range(self.iters):
            state["k"] = k
            value, grad = self.value_and_grad(u)
            history.append(value)
            # a step in scaled controls along the gradient of the scaled loss
            u = opt.step(u / self.cs, grad * self.cs / self.jc) * self.cs
            if ocp.has_bounds:
                u = np.clip(u, ocp.u_min, ocp.u_max)
            state["u"] = u
            if self.report(k + 1, history[-1], lambda u=u: u.copy()):
                return "stopped by the callback", k + 1
        state["k"] = self.iters
        return "finished the requested iterations", self.iters

    def lbfgs(self, u0: np.ndarray, history: list[float], state: dict[str, Any]) -> tuple[str, int]:
        """L-BFGS with the max-step cut-back and restarts at kinks
        (:func:`~hybridoc.solvers.optimizers.lbfgs_iterations`)."""
        from hybridoc.solvers.optimizers import GD_LINE_SEARCH_EVALS, lbfgs_iterations

        # L-BFGS has absolute thresholds (curvature pairs with y.s <= 1e-10 are dropped) while
        # the gradient with respect to one control value scales with dt: it sees loss / dt
        self.scale = 1.0 / (self.jc * self.dts)
        state["k"] = 0
        if self.iters == 0:
            return "finished the requested iterations", 0
        x0 = self.scaled(u0)
        start = self.fun(x0)
        history.append(self.loss_here(u0))
        steps = lbfgs_iterations(
            self.fun, x0, lr=self.lr, max_step=self.max_step / float(self.cs.max()),
            max_ls=GD_LINE_SEARCH_EVALS, start=start,
        )  # fmt: skip
        for k, it in zip(range(self.iters), steps, strict=False):
            state["k"] = k
            u = self.physical(it.x)
            state["u"] = u
            if it.event in ("restart", "converged", "cut-rejected"):
                history.append(history[-1])
            else:
                history.append(self.loss_here(u))
            if it.event in ("cut", "cut-rejected", "restart"):
                self.restarts += 1
            if it.event == "converged":
                return "converged: L-BFGS made no further progress", k + 1
            if self.report(k + 1, history[-1], lambda u=u: u.copy()):
                return "stopped by the callback", k + 1
        state["k"] = self.iters
        return "finished the requested iterations", self.iters

    def lbfgsb(self, u0: np.ndarray) -> _Result:
        """SciPy's L-BFGS-B on the same objective (problems with control bounds)."""
        from scipy.optimize import minimize

        ocp = self.ocp
        shape = u0.shape
        history: list[float] = []
        k = 0
        # scaled: controls u / cs, loss (J / jc) / dt~ (identity scales: J / dt as before)
        per = self.jc * self.dts

        def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
            u = self.physical(x)
            if self.last is not None and np.array_equal(self.last[0], u):
                value = self.last[1]  # the callback's point: SciPy has just evaluated it
                return value / per, self.last_grad
            value, grad = self.value_and_grad(u)
            self.last_grad = np.ravel(grad * self.cs) / per
            return value / per, self.last_grad

        def cb(x: np.ndarray) -> None:
            nonlocal k
            k += 1
            history.append(fun(x)[0] * per)
            if self.report(k, history[-1], lambda: self.physical(x)):
                raise StopIteration

        lo, hi = ocp.u_min / self.cs, ocp.u_max / self.cs
        bounds = list(zip(np.tile(lo, shape[0]), np.tile(hi, shape[0]), strict=True))
        self.last_grad = np.zeros(u0.size)
        history.append(fun(self.scaled(u0))[0] * per)
        try:
            res = minimize(
                fun, self.scaled(u0), jac=True, method="L-BFGS-B", bounds=bounds,
                callback=cb, options={"maxiter": self.iters, "ftol": 1e-15, "gtol": 1e-12},
            )  # fmt: skip
        except _NonFinite as exc:
            return u0, history[-1], k, f"stopped early: {exc}", True, history
        x = res.x
        if res.status == 99:  # the callback raised StopIteration
            msg = "stopped by the callback"
        elif res.status == 1:  # SciPy's iteration limit
            msg = f"finished the requested iterations (L-BFGS-B: {res.message})"
        else:  # SciPy's convergence tests, or a line search that cannot progress
            msg = f"converged: L-BFGS-B: {res.message}"
        final = fun(x)[0] * per
        history.append(final)
        return self.physical(x), final, k, msg, False, history


def _torch_value_and_grad(loss_obj: Any) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
    """``u -> (loss, gradient)`` of a torch loss (the torch simulator) on numpy arrays."""
    import torch

    def value_and_grad(u: np.ndarray) -> tuple[float, np.ndarray]:
        ut = torch.tensor(u, dtype=torch.float64, requires_grad=True)
        value = loss_obj.loss(ut)
        val = float(value.detach())
        if not math.isfinite(val):
            return val, np.zeros_like(u)
        value.backward()
        return val, ut.grad.numpy().copy()

    return value_and_grad


# ---------------------------------------------------------------------- terminal constraints
RHO_GROWTH = 10.0
"""Terminal constraints: the factor of the penalty when an outer iteration has not cut the
violation to :data:`RHO_PROGRESS` of the previous one."""
RHO_PROGRESS = 0.25
"""Terminal constraints: see :data:`RHO_GROWTH`."""
RHO_MAX = 1e9
"""Terminal constraints: the largest penalty (beyond it the inner problem is too stiff for
L-BFGS to gain anything)."""
TERMINAL_MARGIN = 0.1
"""The outer loop stops at this fraction of ``terminal_tol`` (on the simulation's final
state), so that the judge's own final state, equal up to rounding and the event-time Newton
iterations, is within the tolerance."""

_TERMINAL_LOSSES: weakref.WeakKeyDictionary[Structure, dict[tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def _terminal_loss(ocp: HybridOCP, path_weight: float) -> Any:
    """The :class:`~hybridoc.solvers.compiled.TerminalLoss` of a problem, kept per structure
    (the final time is an input of it, not part of the key)."""
    from hybridoc.solvers.compiled import TerminalLoss, per_structure

    key = (ocp.steps, path_weight, tuple(ocp.x0.tolist()))
    return per_structure(
        _TERMINAL_LOSSES, ocp, key, lambda: TerminalLoss(ocp, path_weight=path_weight)
    )


def _terminal_refusal(ocp: HybridOCP, opts: GDOptions) -> str | None:
    """Why gd cannot run ``opts`` on a problem with terminal constraints or a free final
    time (``None``: it can)."""
    what = "terminal constraints" if ocp.has_terminal_constraints else "a free final time"
    if ocp.has_terminal_constraints and ocp.free_horizon:
        what = "terminal constraints and a free final time"
    if opts.optimizer != "lbfgs":
        return (
            f"{what} are solved by an augmented Lagrangian around L-BFGS-B; optimizer "
            f"{opts.optimizer!r} is not supported there (use lbfgs)"
        )
    if opts.starts > 1 or opts.hops:
        return (
            f"the multi-start and the hops explore the unconstrained, fixed-time loss; with "
            f"{what} use starts=1 and hops=0 (and --initial for another start)"
        )
    if opts.path == "torch" or not _is_direct_both(opts.contact) or opts.integrator != "exact":
        return (
            f"{what} use the compiled generic time-of-impact simulation (contact 'direct', "
            "TOI 'both', integrator 'exact', path 'auto' or 'compiled')"
        )
    if opts.max_step is not None:
        return f"max_step applies to gd's own L-BFGS; {what} use SciPy's L-BFGS-B"
    return None


class _Augmented:
    """The inner problem of the augmented Lagrangian: ``x = (u, z)`` with
    ``T = T0 + z sqrt(dt0)`` when the final time is free (the scale makes the curvature in
    ``z`` of the ``1 / dt0``-scaled objective comparable with that in a control value),
    objective ``(J + A + smoothing) / dt0``."""

    def __init__(self, ocp: HybridOCP, loss: Any, opts: GDOptions, progress: Progress) -> None:
        self.ocp, self.loss, self.opts, self.progress = ocp, loss, opts, progress
        self.shape = (ocp.steps, ocp.nu)
        self.T0 = float(ocp.horizon)
        self.dt0 = self.T0 / ocp.steps
        self.sz = math.sqrt(self.dt0)
        self.free = ocp.free_horizon
        self.nu = np.zeros(loss.n_eq)
        self.mu = np.zeros(loss.n_in)
        self.rho = float(opts.terminal_rho)
        self.penalty = 0.0
        self.n_evals = 0
        self.iterations = 0
        self.history: list[float] = []
        self.marks: list[list[Any]] = []  # [start in history, name] of each stage
        self.watch = _watch()

    def pack(self, u: np.ndarray, T: float) -> np.ndarray:
        z = [(T - self.T0) / self.sz] if self.free else []
        return np.concatenate([np.ravel(u), z])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        n = self.shape[0] * self.shape[1]
        T = self.T0 + self.sz * float(x[n]) if self.free else self.T0
        return x[:n].reshape(self.shape), T

    def bounds(self) -> list[tuple[float, float]]:
        ocp = self.ocp
        out = list(zip(np.tile(ocp.u_min, ocp.steps), np.tile(ocp.u_max, ocp.steps), strict=True))
        if self.free:
            lo, hi = ocp.horizon_bounds  # type: ignore[misc]
            out.append(((lo - self.T0) / self.sz, (hi - self.T0) / self.sz))
        return [(None if math.isinf(a) else a, None if math.isinf(b) else b) for a, b in out]

    def fun(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        self.n_evals += 1
        if self.watch is not None:
            self.watch.check()
        if not np.isfinite(x).all():
            raise _NonFinite("the controls or the final time became NaN or infinite")
        u, T = self.unpack(x)
        J, A, _, gU, gT = self.loss.evaluate(u, T, self.nu, self.mu, self.rho)
        if self.watch is not None:  # the latest: a lower J may violate the constraints
            self.watch.offer(float(J), u, T, latest=True)
        value = J + A
        if self.penalty:
            diff = u[1:] - u[:-1]
            value += self.penalty * float((diff * diff).sum()) / self.dt0
            w = 2.0 * self.penalty / self.dt0
            gU = gU.copy()
            gU[1:] += w * diff
            gU[:-1] -= w * diff
        grad = np.concatenate([np.ravel(gU), [gT * self.sz] if self.free else []])
        if not (math.isfinite(value) and np.isfinite(grad).all()):
            raise _NonFinite(f"the loss or its gradient became non-finite ({value})")
        return value / self.dt0, grad / self.dt0

    def minimise(self, x0: np.ndarray) -> tuple[np.ndarray, str, bool]:
        """One inner L-BFGS-B solve from ``x0``: the result, SciPy's message, and whether
        it met its convergence test (not the iteration limit or a callback's stop)."""
        from scipy.optimize import minimize

        opts = self.opts
        k0 = self.iterations

        def cb(x: np.ndarray) -> None:
            self.iterations += 1
            if self.watch is not None:
                self.watch.iterations += 1
            u, _ = self.unpack(x)
            value = self.fun(x)[0] * self.dt0
            self.history.append(value)
            self.progress.count(self.iterations - k0, None, f"iterations, loss {value:.6g}")
            if opts.callback is not None and opts.callback(self.iterations, value, u.copy()):
                raise StopIteration

        res = minimize(
            self.fun, x0, jac=True, method="L-BFGS-B", bounds=self.bounds(), callback=cb,
            options={"maxiter": opts.iters, "maxfun": 20 * max(opts.iters, 1),
                     "ftol": 1e-15, "gtol": 1e-12},
        )  # fmt: skip
        if res.status == 99:
            return res.x, "stopped by the callback", False
        if res.status == 1 or opts.iters == 0:
            return res.x, f"finished the requested iterations (L-BFGS-B: {res.message})", False
        return res.x, f"converged: L-BFGS-B: {res.message}", True


def _solve_terminal(ocp: HybridOCP, opts: GDOptions, initial: Any, progress: Progress) -> Solution:
    """gd on a problem with terminal constraints or a free final time (module notes):
    the augmented Lagrangian's outer loop around L-BFGS-B, judged at the final time found."""
    reason = _terminal_refusal(ocp, opts)
    if reason is not None:
        raise OptionError(f"gd cannot solve {ocp.name!r} so: {reason}")
    t_start = time.perf_counter()
    loss = _terminal_loss(ocp, opts.path_weight)
    prob = _Augmented(ocp, loss, opts, progress)
    u0 = _initial(ocp, initial)
    if ocp.has_bounds:
        u0 = np.clip(u0, ocp.u_min, ocp.u_max)
    x = prob.pack(u0, prob.T0)
    smoothing = DEFAULT_SMOOTHING if opts.smoothing is None else opts.smoothing
    tol = opts.terminal_tol
    outer: list[dict[str, Any]] = []
    message, converged, nan_stop = "", False, False
    try:
        # the smoothing stages (module notes on kinks) run on the first outer iteration only
        for i, mu_s in enumerate(smoothing):
            prob.marks.append([len(prob.history), f"mu {mu_s:g}"])
            progress.stage(
                f"smoothing stage {i + 1} of {len(smoothing)}, mu {mu_s:g} "
                f"(terminal penalty {prob.rho:g})"
            )
            prob.penalty = mu_s
            x, _, _ = prob.minimise(x)
        prob.penalty = 0.0
        previous = math.inf
        for k in range(opts.terminal_iters):
            if k == 0:  # one mark: a line per outer iteration would crowd the figure
                prob.marks.append([len(prob.history), "augmented Lagrangian"])
            progress.stage(
                f"augmented Lagrangian: outer iteration {k + 1} of at most "
                f"{opts.terminal_iters}, rho {prob.rho:g}"
            )
            x, message, converged = prob.minimise(x)
            u, T = prob.unpack(x)
            J, _, s_end, _, _ = loss.evaluate(u, T)
            he, hi = loss.constraints(s_end)
            # primal feasibility, and complementarity of the inequalities' multipliers
            viol = max(
                float(np.max(np.abs(he), initial=0.0)),
                float(np.max(np.abs(np.minimum(hi, prob.mu / prob.rho)), initial=0.0)),
            )
            outer.append({"rho": prob.rho, "violation": viol, "loss": J, "horizon": T})
            progress.detail(f"violation {viol:.3g}")
            if message == "stopped by the callback" or viol <= TERMINAL_MARGIN * tol:
                break
            prob.nu = prob.nu + prob.rho * he
            prob.mu = np.maximum(0.0, prob.mu - prob.rho * hi)
            if viol > RHO_PROGRESS * previous:
                prob.rho = min(prob.rho * RHO_GROWTH, RHO_MAX)
            previous = viol
    except _NonFinite as exc:
        message, converged, nan_stop = f"stopped early: {exc}", False, True
    u, T = prob.unpack(x)
    J = float(loss.evaluate(u, T)[0])
    return _terminal_solution(ocp, opts, prob, u, T, J, outer, message, converged, nan_stop,
                              t_start)  # fmt: skip


def _terminal_solution(
    ocp: HybridOCP,
    opts: GDOptions,
    prob: _Augmented,
    u: np.ndarray,
    T: float,
    J: float,
    outer: list[dict[str, Any]],
    message: str,
    converged: bool,
    nan_stop: bool,
    t_start: float,
) -> Solution:
    """The judged Solution of :func:`_solve_terminal`: the judge runs at the final time
    found, and its terminal violation decides between success and infeasible."""
    judged = ocp.replace(horizon=T) if ocp.free_horizon else ocp
    ev = evaluate(judged, u)
    violation = getattr(ev, "terminal_violation", None)
    if violation is None:  # a judge that does not report it yet: measure its final state
        violation = ocp.terminal_violation(ev.final_state)
    violation = float(violation)
    info: dict[str, Any] = {
        "loss": J,
        "iterations": prob.iterations,
        "loss_evaluations": prob.n_evals,
        "nan_stop": nan_stop,
        "diverged": False,
        "converged": converged,
        "message": message,
        "outer": outer,
        "terminal_violation": violation,
        "terminal_multipliers": {"eq": prob.nu.tolist(), "ineq": prob.mu.tolist()},
        "history_stages": prob.marks if prob.history else [],
    }
    if ocp.free_horizon:
        info["horizon"] = float(T)
    settings = {
        **_settings(ocp, opts, "compiled"),
        "simulation": "generic",
        "optimizer": "lbfgs-b",
        "augmented_lagrangian": True,
        "terminal_tol": opts.terminal_tol,
        "terminal_rho": opts.terminal_rho,
        "terminal_iters": opts.terminal_iters,
        "smoothing": list(DEFAULT_SMOOTHING if opts.smoothing is None else opts.smoothing),
    }
    elapsed = time.perf_counter() - t_start
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings=settings,
        timings={"solve_time_s": elapsed, "optimization_time_s": elapsed},
        info=info,
        arrays={"loss_history": np.array(prob.history or [J], dtype=float)},
    )
    status, text = Status.SUCCESS, ""
    if not converged:
        status = Status.NOT_CONVERGED
        text = message or "the inner L-BFGS-B did not converge"
    if violation > opts.terminal_tol:
        status = Status.INFEASIBLE
        text = (
            f"the judge finds the terminal constraints violated by {violation:.3g}, above "
            f"terminal_tol {opts.terminal_tol:.3g}, after {len(outer)} outer iteration(s) "
            f"(penalty {prob.rho:g}); {text or 'raise terminal_iters'}"
        )
    elif status is Status.SUCCESS and max(ev.bound_violation, ev.path_violation) > (
        tolerances.FEASIBILITY
    ):
        status, text = Status.INFEASIBLE, _infeasible(ev)
    return sol.set_status(status, text)


# ---------------------------------------------------------------------- the Method
def _supports(ocp: HybridOCP) -> str | None:
    """``None`` when gd can solve ``ocp``: its functions must be SX (the compiled step)."""
    for fn in (ocp.f, ocp.L, ocp.phi, ocp.terminal_eq, ocp.terminal_ineq):
        if fn is not None and not fn.is_a("SXFunction"):
            return f"the differentiable simulation needs SX functions; {fn.name()!r} is MX"
    return None


def _fmt(x: Any, digits: int) -> str:
    if x is None or math.isnan(float(x)):
        return "-"
    return f"{float(x):.{digits}g}"


def _summary_lines(sol: Solution) -> list[tuple[str, str]]:
    """What ``hybridoc solve`` prints about a gd solution: loss, iterations, settings."""
    lines = []
    if "loss" in sol.info:
        lines.append(("loss", f"{_fmt(sol.info['loss'], 12)} (the simulation's discrete loss)"))
    if "iterations" in sol.info:
        lines.append(("iterations", str(sol.info["iterations"])))
    if "horizon" in sol.info:
        lines.append(("final time", f"{_fmt(sol.info['horizon'], 12)} (free)"))
    if "terminal_violation" in sol.info:
        outer = len(sol.info.get("outer", []))
        lines.append((
            "constraints",
            f"terminal violation {_fmt(sol.info['terminal_violation'], 3)} (judged) after {outer} "
            "augmented-Lagrangian iteration(s)",
        ))  # fmt: skip
    return lines + settings_lines(sol)


def _crossval_defaults(ocp: HybridOCP, options: dict[str, Any]) -> dict[str, Any]:
    """Crossval's gd: a multi-start (:data:`GD_STARTS`), and :data:`GD_HOPS` hops on the
    symplectic Euler objective, whose kinks stall a descent, unless the caller sets them."""
    out = dict(options)
    if ocp.has_terminal_constraints or ocp.free_horizon:
        return out  # one augmented-Lagrangian run: the multi-start explores another loss
    aimed = ocp.capabilities.geometry is not None  # aimed starts (multistart.diverse_controls)
    out.setdefault("starts", GD_STARTS["disc" if aimed else "generic"])
    if out.get("integrator") == "symplectic-euler":
        out.setdefault("hops", GD_HOPS)
    return out


def _crossval_check(ocp: HybridOCP, sol: Solution) -> tuple[dict[str, Any], list[str]]:
    """On the symplectic Euler objective: gd's discrete loss against the optimum of that
    objective (:func:`~hybridoc.solvers.discrete_transcription.discrete_gap`), within
    :data:`DISCRETE_TOLERANCE`."""
    if sol.settings.get("integrator") != "symplectic-euler":
        return {}, []
    from hybridoc.solvers.discrete_transcription import discrete_gap

    entry = discrete_gap(ocp, sol)
    dgap = entry.get("discrete_gap_relative")
    reasons = []
    if dgap is not None and dgap > DISCRETE_TOLERANCE:
        reasons.append(
            f"gd's discrete loss is {dgap:+.3e} above the optimum of its own discrete "
            f"objective (the N-step transcription from its control), beyond "
            f"{DISCRETE_TOLERANCE:.0e}"
        )
    return entry, reasons


METHOD = Method(
    "gd",
    "gradient descent through the differentiable time-of-impact simulation",
    run=solve_gd,
    options=GDOptions,
    tolerance=tolerances.CROSSVAL,
    supports=_supports,
    summary_lines=_summary_lines,
    crossval_defaults=_crossval_defaults,
    crossval_check=_crossval_check,
    features=frozenset({"terminal", "free_horizon"}),
)
"""Gradient descent as a registered method (``method="gd"``, :data:`hybridoc.methods.BUILTIN`);
it honours terminal constraints and a free final time (the augmented Lagrangian)."""
