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

The pieces of a run, a module each
    :mod:`~hybridoc.solvers.gd.options` declares the options, once (:class:`GDOptions`:
    defaults and checks), and fills in their defaults that depend on the problem
    (:func:`checked_options`). :mod:`~hybridoc.solvers.gd.solve` holds the entry points
    (:func:`solve_gd`, a thin wrapper of :func:`run_gd`), which dispatch to the hops
    (:mod:`~hybridoc.solvers.gd.hops`), the multi-start (:mod:`~hybridoc.solvers.gd.starts`)
    or the augmented Lagrangian (:mod:`~hybridoc.solvers.gd.terminal`) around the
    continuation (:func:`~hybridoc.solvers.gd.descent.continuation`: the smoothing stages,
    then the real problem), which runs single descents (:mod:`~hybridoc.solvers.gd.descent`:
    the optimiser loop in :class:`~hybridoc.solvers.gd.descent.Run`, with the numpy
    optimisers of :mod:`hybridoc.solvers.optimizers`: torch is imported only by the torch
    simulator, ``path="torch"``); :mod:`~hybridoc.solvers.gd.kinks` takes a converged
    descent past the kinks of the loss. The loss is :mod:`~hybridoc.solvers.gd.loss`'s, the
    time limit :mod:`~hybridoc.solvers.gd.limits`', and :mod:`~hybridoc.solvers.gd.method`
    registers the method. One :class:`~hybridoc.progress.Progress` serves the whole run: a
    stage per smoothing weight, hop round and multi-start phase, a count per iteration.
"""

from hybridoc.scales import optimizer_units as units
from hybridoc.solvers.gd.descent import convergence_test
from hybridoc.solvers.gd.hops import HOP_BATCH, HOP_ITERS, HOP_PATIENCE, HOP_SCALES
from hybridoc.solvers.gd.kinks import (
    KINK_BAND,
    KINK_GTOL,
    KINK_ITERS,
    KINK_MAX_SIZE,
    pinned_events,
)
from hybridoc.solvers.gd.loss import exploration_loss, make_loss
from hybridoc.solvers.gd.method import DISCRETE_TOLERANCE, GD_HOPS, GD_STARTS, METHOD
from hybridoc.solvers.gd.options import (
    DEFAULT_SMOOTHING,
    INTEGRATORS,
    MEMORY_FRACTION,
    MULTISTART_ITERS,
    MULTISTART_REFINE,
    MULTISTART_SMOOTHING,
    MULTISTART_STEPS,
    OPTIMIZERS,
    PATH_WEIGHT,
    PATHS,
    STALL_RTOL,
    GDOptions,
    available_memory,
    checked_options,
    default_integrator,
    default_settings,
    memory_limit,
    parse_smoothing,
    stall_window,
)
from hybridoc.solvers.gd.solve import run_gd, solve_gd
from hybridoc.solvers.gd.terminal import RHO_GROWTH, RHO_MAX, RHO_PROGRESS, TERMINAL_MARGIN

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
    "KINK_MAX_SIZE",
    "MEMORY_FRACTION",
    "METHOD",
    "MULTISTART_ITERS",
    "MULTISTART_REFINE",
    "MULTISTART_SMOOTHING",
    "MULTISTART_STEPS",
    "OPTIMIZERS",
    "PATHS",
    "PATH_WEIGHT",
    "RHO_GROWTH",
    "RHO_MAX",
    "RHO_PROGRESS",
    "STALL_RTOL",
    "TERMINAL_MARGIN",
    "GDOptions",
    "available_memory",
    "checked_options",
    "convergence_test",
    "default_integrator",
    "default_settings",
    "exploration_loss",
    "make_loss",
    "memory_limit",
    "parse_smoothing",
    "pinned_events",
    "run_gd",
    "solve_gd",
    "stall_window",
    "units",
]
