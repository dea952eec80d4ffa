"""gd's options: :class:`GDOptions`, each option declared once with its default and its
checks, and the defaults that depend on the problem (:func:`checked_options`: the learning
rate and iterations from the problem's hints, the integrator, the smoothing weights, and the
sizes' memory estimates)."""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc import resources, tolerances
from hybridoc.errors import OptionError
from hybridoc.methods import (
    nonnegative_int,
    option,
    positive_float,
    positive_int,
)
from hybridoc.ocp import HybridOCP
from hybridoc.problems import scene_of
from hybridoc.scales import optimizer_units as units

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.solvers.contacts import ContactModel


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


def check_choice(name: str, value: Any, choices: Sequence[str]) -> None:
    """Raise :class:`~hybridoc.errors.OptionError` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise OptionError(f"unknown {name} {value!r}; choose one of {', '.join(choices)}")


def _check_options(o: GDOptions) -> None:
    """Every check of gd's options that does not depend on the problem, in one place (run
    by :class:`GDOptions` on construction): an :class:`~hybridoc.errors.OptionError` of one
    line for an unknown name or a value out of range. The contact model's name and TOI
    setting are checked where they are resolved (:func:`checked_options`), the sizes'
    memory against the problem (:func:`_check_memory`)."""
    check_choice("optimizer", o.optimizer, OPTIMIZERS)
    if o.integrator is not None:
        check_choice("integrator", o.integrator, INTEGRATORS)
    check_choice("path", o.path, PATHS)
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


def disc_simulation(ocp: HybridOCP) -> bool:
    """Whether the disc simulator simulates ``ocp`` (a disc scene; the generic
    time-of-impact simulation otherwise)."""
    return scene_of(ocp) is not None


def default_integrator(ocp: HybridOCP, contact: ContactModel) -> str:
    """``"exact"`` where it exists (impulse models with both TOI corrections, generic
    problems), else the paper's ``"symplectic-euler"``."""
    if not disc_simulation(ocp):
        return "exact"
    exact = contact.impulse_based and getattr(contact, "toi", None) == "both"
    return "exact" if exact else "symplectic-euler"


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


#: multi-start: the coarse grid of the batched phase, its iterations, and how many distinct
#: results are refined at full resolution
MULTISTART_STEPS = 60


MULTISTART_ITERS = 60


MULTISTART_REFINE = 2


MULTISTART_SMOOTHING = (3e-6,)
